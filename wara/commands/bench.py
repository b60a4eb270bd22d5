"""``wara bench NAME --json``: benchmarks that print one JSON object.

Speed goals are ratios measured inside one run (this class of machine is shared and
noisy), never absolute timings in unit tests.
"""

from __future__ import annotations

import argparse
import importlib
import json
from typing import Any

from config.numbers import integer

#: benchmark name -> "module:function"; the function takes the parsed args and returns
#: a JSON-serialisable dict.
BENCHES: dict[str, str] = {
    "planner": "wara.benches.planner:run",
    "can": "wara.benches.can:run",
    "sim": "wara.benches.sim:run",
    "loop": "wara.benches.loop:run",
    "hil": "wara.benches.hil:run",
    "transport": "wara.benches.transport:run",
    "step": "wara.benches.step:run",
    "demo": "wara.benches.demo:run",
    "opcua": "wara.benches.opcua:run",
    "harness": "wara.benches.harness:run",
    "figures": "wara.benches.figures:run",
}

#: the benches that take ``--baseline DIR`` (this checkout against DIR's, in one run)
WITH_BASELINE = ("harness", "step")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark and print JSON")
    p.add_argument("name", choices=sorted(BENCHES), help="what to measure")
    p.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    p.add_argument("--json", action="store_true", help="JSON output (the only format)")
    p.add_argument("--quick", action="store_true", help="smaller run, for smoke tests")
    p.add_argument(
        "--runs",
        type=integer,
        default=None,
        metavar="N",
        help="demo: how many runs (default 5); harness, step with --baseline: rounds (default 5)",
    )
    p.add_argument(
        "--baseline",
        default=None,
        metavar="DIR",
        help="harness, step: a checkout of another revision, measured in turn with this one",
    )
    p.add_argument(
        "--cpu-hog",
        action="store_true",
        help="demo: a CPU-bound process pinned to one CPU beside the runs",
    )
    p.add_argument(
        "--attitude",
        action="store_true",
        help="demo: the demo's attitude examples (wara demo --attitude) instead of the rings",
    )
    p.add_argument(
        "--realtime",
        action="store_true",
        help="demo: the ring cycles on the wall clock (wara demo --realtime); "
        "figures: also the figures measured on the wall clock",
    )
    p.add_argument(
        "--only",
        default=None,
        metavar="NAME,...",
        help="figures: measure these figures alone (the others keep their last values)",
    )
    p.add_argument(
        "--out",
        default=None,
        metavar="PAGE",
        help="figures: the page to write (default docs/figures.md; its store beside it)",
    )
    p.add_argument(
        "--readme",
        default=None,
        metavar="PATH",
        help="figures: the README whose headline table to write (default: the one above "
        "the page's directory; '-': none)",
    )
    # Hidden: the re-execution inside the namespace (opcua).
    p.add_argument("--inside-netns", default=None, help=argparse.SUPPRESS)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from wara.cli import UsageError

    for opt in ("cpu_hog", "attitude", "realtime"):
        if (
            args.name != "demo"
            and getattr(args, opt)
            and (args.name, opt) != ("figures", "realtime")
        ):
            raise UsageError(f"--{opt.replace('_', '-')} goes with `wara bench demo`")
    for opt in ("only", "out", "readme"):
        if args.name != "figures" and getattr(args, opt) is not None:
            raise UsageError(f"--{opt} goes with `wara bench figures`")
    if args.attitude and args.realtime:
        raise UsageError(
            "--realtime goes with the ring cycles (the attitude examples run in real time)"
        )
    if args.baseline is not None and args.name not in WITH_BASELINE:
        raise UsageError(f"--baseline goes with `wara bench` {', '.join(WITH_BASELINE)}")
    if args.runs is not None and not (args.name == "demo" or args.baseline is not None):
        raise UsageError(
            "--runs goes with `wara bench demo` or `wara bench harness/step --baseline`"
        )
    if args.runs is not None and args.runs < 1:
        raise UsageError("--runs must be at least 1")
    module_name, func_name = BENCHES[args.name].split(":")
    func = getattr(importlib.import_module(module_name), func_name)
    result: dict[str, Any] | None = func(args)
    if result is not None:  # None: a run inside the namespace hands its result over a file
        print(json.dumps(result, indent=2))
    return 0
