"""``wara bench NAME --json``: benchmarks that print one JSON object.

Speed goals are ratios measured inside one run (this class of machine is shared and
noisy), never absolute timings in unit tests.
"""

from __future__ import annotations

import argparse
import importlib
import json
from typing import Any

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
    "harness": "wara.benches.harness:run",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run a benchmark and print JSON")
    p.add_argument("name", choices=sorted(BENCHES), help="what to measure")
    p.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    p.add_argument("--json", action="store_true", help="JSON output (the only format)")
    p.add_argument("--quick", action="store_true", help="smaller run, for smoke tests")
    p.add_argument(
        "--runs", type=int, default=None, metavar="N", help="demo: how many runs (default 5)"
    )
    p.add_argument(
        "--cpu-hog",
        action="store_true",
        help="demo: a CPU-bound process pinned to one CPU beside the runs",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    if args.name != "demo" and (args.runs is not None or args.cpu_hog):
        from wara.cli import UsageError

        raise UsageError("--runs and --cpu-hog go with `wara bench demo`")
    module_name, func_name = BENCHES[args.name].split(":")
    func = getattr(importlib.import_module(module_name), func_name)
    result: dict[str, Any] = func(args)
    print(json.dumps(result, indent=2))
    return 0
