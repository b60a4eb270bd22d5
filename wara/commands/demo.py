"""``wara demo``: the end-to-end demo (HIL simulator + IPC service).

The default: ring cycles (:func:`wara.demo.run_ring_demo`), ``--rings`` of them from a
first ring 6 mm off the design axis, each walking the 2 m step to its ring and back, in
simulated time (``--realtime``: on the wall clock, some 4 min a ring), the acceptance
report into ``--out``; exit 0 only
if every ring met its goals on the simulator's truth (``wara cycle``'s), 3 when a ring's
target is unreachable. ``--attitude``: Examples 1-3 of the attitude adjustment, in real time
(``--lockstep``: simulated time); exit 0
only if every example met its tolerances (attitude error <= 0.01 deg, twist <= 0.5 mm
during motion, sync error at standstill <= 0.07 mm). ``--two-process``: the simulator and
the service as two processes over UDP multicast in a private network namespace
(:mod:`wara.demo_two_process`; ``--transport``: ``wara_udp`` by default, or python-can's
``udp_multicast``); exit 2 when the namespace cannot be made here. With ``--rings N``
(or ``--out``) it runs the ring cycles on the wall clock (:mod:`wara.two_process_cycle`:
every ring's goals, and the loop's compute p99 under 20 % of the period; its figures per
phase and each overrun explained); without, the attitude examples
(:mod:`wara.two_process_examples`), which also need no overrun after start-up in a 60 s
run.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from config.numbers import decimal, integer
from wara.cli import EXIT_FAILED, EXIT_INFEASIBLE, EXIT_OK, EXIT_USAGE, UsageError
from wara.extras import require, require_realtime_simulator

#: Most rings one demo runs.
MAX_RINGS = 20
#: Where the ring demo writes its acceptance store and report by default.
DEFAULT_OUT = "wara-demo"
#: Options of the attitude examples only (attribute, option).
_ATTITUDE_ONLY = (("examples", "--examples"), ("plot", "--plot"), ("opcua", "--opcua"))


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "demo",
        help="end-to-end demo: simulator + service, ring cycles (--attitude: Examples 1-3)",
    )
    p.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--rings",
        type=integer,
        default=None,
        metavar="N",
        help="ring cycles to run (default 4: rings 2-5, ring 1 6 mm off the design axis)",
    )
    p.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help=f"the rings' acceptance store and report (default ./{DEFAULT_OUT}; "
        "DIR/acceptance.sqlite is replaced, the report is DIR/report/report.html)",
    )
    p.add_argument(
        "--attitude",
        action="store_true",
        help="the attitude adjustment's Examples 1-3 instead of the ring cycles",
    )
    p.add_argument("--plot", default=None, metavar="DIR", help="--attitude: write plots into DIR")
    form = p.add_mutually_exclusive_group()
    form.add_argument(
        "--lockstep",
        action="store_true",
        help="simulated time in one thread (fast, no loop jitter figures; the ring "
        "cycles' default)",
    )
    form.add_argument(
        "--realtime",
        action="store_true",
        help="on the wall clock, the loop and the simulator as two threads (the attitude "
        "examples' default; the ring cycles about 17 min)",
    )
    form.add_argument(
        "--two-process",
        action="store_true",
        help="simulator and service as two processes over UDP multicast in a private "
        "network namespace, on the wall clock (needs unshare and ip): with --rings N the "
        "ring cycles (some 5 min a ring), else the attitude examples (at least 60 s)",
    )
    p.add_argument(
        "--transport",
        choices=("wara_udp", "udp_multicast"),
        default=None,
        help="--two-process: the cross-process CAN interface (default wara_udp; "
        "udp_multicast is python-can's)",
    )
    p.add_argument(
        "--no-pin",
        action="store_true",
        help="--two-process: leave CPU placement to the scheduler (default: the service's "
        "loop thread and the simulator each on CPUs of their own, as on the IPC)",
    )
    p.add_argument(
        "--settle-s",
        type=decimal,
        default=None,
        metavar="S",
        help="--two-process: seconds each target is held before its figures are read "
        "(default 4; the standstill sync error is taken after the first 1 s)",
    )
    p.add_argument(
        "--examples",
        type=integer,
        default=None,
        metavar="N",
        help="--attitude: run only the first N examples (a shorter run)",
    )
    p.add_argument(
        "--opcua",
        action="store_true",
        help="--attitude: serve the OPC UA server for the demo's duration (prints the "
        "endpoint URL, "
        "a demo operator user and its password file; needs the opcua extra)",
    )
    # Hidden: for tests and the re-execution inside the namespace.
    p.add_argument("--min-run-s", type=decimal, default=None, help=argparse.SUPPRESS)
    p.add_argument("--inside-netns", default=None, metavar="DIR", help=argparse.SUPPRESS)
    p.add_argument(
        "--keep-dir",
        default=None,
        metavar="DIR",
        help="--two-process: keep the run's files in DIR (the project copy, both processes' "
        "logs, the service's run record)",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    rings_asked = args.rings is not None or args.out is not None
    # --two-process: the attitude examples, or the ring cycles with --rings / --out
    attitude = args.attitude or (args.two_process and not rings_asked)
    if not attitude:
        for opt, name in _ATTITUDE_ONLY:
            if getattr(args, opt) not in (None, False):
                raise UsageError(f"{name} goes with --attitude (the attitude examples)")
        for opt in ("settle_s", "min_run_s"):
            if getattr(args, opt) is not None:
                raise UsageError(
                    f"--{opt.replace('_', '-')} goes with the attitude examples "
                    "(--two-process without --rings)"
                )
    elif rings_asked:
        raise UsageError(
            f"--{'rings' if args.rings is not None else 'out'} goes with the ring cycles, "
            "not with --attitude"
        )
    if not args.two_process:
        if args.no_pin:
            raise UsageError("--no-pin goes with --two-process")
        for opt in ("settle_s", "min_run_s", "inside_netns", "keep_dir", "transport"):
            if getattr(args, opt) is not None:
                raise UsageError(f"--{opt.replace('_', '-')} goes with --two-process")
    # the ring cycles walk 2 m to each ring and back (some 4 min of machine time a ring):
    # simulated time unless asked; the attitude examples (a minute) on the wall clock
    if not attitude:
        args.lockstep = not (args.realtime or args.two_process)
    if not args.lockstep:
        require_realtime_simulator()
    if not attitude:
        return _run_rings_two_process(args) if args.two_process else _run_rings(args)
    if args.opcua:
        if args.two_process or args.lockstep:
            raise UsageError("--opcua goes with the real-time one-process demo")
        require("asyncua", "--opcua")
    if args.two_process:
        return _run_two_process(args)
    if args.plot:
        require("matplotlib", "--plot")
    from ipc_app.service.logs import configure_logging
    from wara.demo import EXAMPLES, failure_reason, render_table, stderr_progress

    n = _examples(args.examples, len(EXAMPLES))

    # The service's log goes to stderr as JSON lines (warnings and faults only; the
    # progress lines tell the rest), never into the table or the JSON on stdout.
    logs = configure_logging("WARNING")
    try:
        summary = _run_demo(
            args.config,
            mode="lockstep" if args.lockstep else "realtime",
            examples=EXAMPLES[:n],
            plot_dir=Path(args.plot) if args.plot else None,
            progress=stderr_progress,
            opcua=args.opcua,
        )
    finally:
        logs.stop()
    if not summary["passed"]:
        stderr_progress(f"FAILED: {failure_reason(summary)}")
    print(json.dumps(summary, indent=2) if args.json else render_table(summary))
    return EXIT_OK if summary["passed"] else EXIT_FAILED


def _run_rings(args: argparse.Namespace) -> int:
    """The ring cycles, then the acceptance report of their records."""
    rings = _ring_count(args)
    from ipc_app.service.logs import configure_logging
    from wara.demo import ring_failure_reason, run_ring_demo, stderr_progress

    logs = configure_logging("WARNING")
    try:
        out = run_ring_demo(
            args.config,
            out_dir=Path(args.out or DEFAULT_OUT),
            mode="lockstep" if args.lockstep else "realtime",
            rings=rings,
            progress=stderr_progress,
        )
    finally:
        logs.stop()
    from wara.demo import render_ring_table

    print(json.dumps(out, indent=2) if args.json else render_ring_table(out))
    if out["refused"] is not None:
        stderr_progress(f"refused: {out['refused']}")
        return EXIT_INFEASIBLE
    if not out["passed"]:
        stderr_progress(f"FAILED: {ring_failure_reason(out)}")
        return EXIT_FAILED
    return EXIT_OK


def _ring_count(args: argparse.Namespace) -> int:
    """``--rings`` (default :data:`wara.demo.RING_DEMO_RINGS`), checked; the project must
    be able to place."""
    from config import load_project
    from wara.demo import RING_DEMO_RINGS

    rings = RING_DEMO_RINGS if args.rings is None else args.rings
    if not 1 <= rings <= MAX_RINGS:
        raise UsageError(f"--rings must be within 1..{MAX_RINGS}, got {rings}")
    cfg = load_project(args.config)
    if cfg.placement is None or cfg.cycle is None:
        raise UsageError("the project has no placement and cycle sections: it cannot place")
    require("matplotlib", "wara demo (its acceptance report)")
    return rings


def _run_rings_two_process(args: argparse.Namespace) -> int:
    """The ring cycles with the simulator and the service as two processes
    (:mod:`wara.two_process_cycle`): the namespace from outside, the run inside it."""
    from wara import demo_two_process as d2
    from wara import two_process_cycle as tpc
    from wara.demo import stderr_progress

    rings = _ring_count(args)
    out_dir = Path(args.out or DEFAULT_OUT)
    got = _in_two_processes(
        args,
        lambda: tpc.run_two_process_cycle(
            args.config,
            rings=rings,
            out_dir=out_dir,
            json_out=args.json,
            keep_dir=Path(args.keep_dir) if args.keep_dir else None,
            transport=args.transport or d2.DEFAULT_TRANSPORT,
            pin=not args.no_pin,
        ),
        lambda: tpc.run_inside(
            Path(args.inside_netns), args.config, rings=rings, out_dir=out_dir,
            progress=stderr_progress,
        ),
    )  # fmt: skip
    if isinstance(got, int):
        return got
    print(json.dumps(got, indent=2) if args.json else tpc.render_table(got))
    if got["refused"] is not None:
        stderr_progress(f"refused: {got['refused']}")
        return EXIT_INFEASIBLE
    if not got["passed"]:
        stderr_progress("FAILED: " + "; ".join(got["missed"]))
        return EXIT_FAILED
    return EXIT_OK


def _in_two_processes(
    args: argparse.Namespace,
    outside: Callable[[], int],
    inside: Callable[[], dict[str, Any]],
) -> dict[str, Any] | int:
    """``--two-process``: outside the namespace ``outside()`` (the command again inside
    it; its exit code, 2 when the namespace cannot be made), inside it ``inside()``'s
    result; a run whose processes or control socket failed: one line on stderr (and the
    verdict with ``--json``), exit 1."""
    import sys

    from ipc_app.service.ctl import CtlError
    from wara import demo_two_process as d2

    if args.inside_netns is None:
        try:
            return outside()
        except d2.NetnsUnavailable as exc:
            print(
                f"wara demo: --two-process needs a private network namespace: {exc}",
                file=sys.stderr,
            )
            return EXIT_USAGE
    try:
        return inside()
    except (d2.TwoProcessError, CtlError) as exc:
        print(f"wara demo: two-process run failed: {exc}", file=sys.stderr)
        if args.json:  # the verdict stays machine-readable
            faults = exc.faults if isinstance(exc, d2.TwoProcessError) else []
            print(json.dumps({"mode": "two-process", "passed": False, "error": str(exc),
                              "faults": faults}))  # fmt: skip
        return EXIT_FAILED


def _run_demo(*args: Any, **kwargs: Any) -> dict[str, Any]:
    """:func:`wara.demo.run_demo`; an OPC UA server that does not start is one line."""
    from wara.demo import run_demo

    if not kwargs.get("opcua"):
        return run_demo(*args, **kwargs)
    from ipc_app.opcua.process import OpcUaStartError

    try:
        return run_demo(*args, **kwargs)
    except OpcUaStartError as exc:
        raise UsageError(str(exc)) from None


def _examples(n: int | None, available: int) -> int:
    if n is None:
        return available
    if not 1 <= n <= available:
        raise UsageError(f"--examples must be 1..{available}")
    return n


def _run_two_process(args: argparse.Namespace) -> int:

    from ipc_app.service.core import ServiceCore
    from wara import demo_two_process as d2
    from wara import two_process_examples as ex
    from wara.demo import EXAMPLES, stderr_progress

    if args.plot:
        raise UsageError("--plot is not available with --two-process (see the run record)")
    settle = ex.DEFAULT_SETTLE_S if args.settle_s is None else args.settle_s
    if not settle > ServiceCore.HOLD_SETTLE_S:
        raise UsageError(
            f"--settle-s must be above {ServiceCore.HOLD_SETTLE_S:g} s (the hold settles "
            "first, then the standstill sync error is measured)"
        )
    n = _examples(args.examples, len(EXAMPLES))
    min_run = ex.MIN_RUN_S if args.min_run_s is None else args.min_run_s
    summary = _in_two_processes(
        args,
        lambda: ex.run_two_process(
            args.config,
            json_out=args.json,
            settle_s=settle,
            examples=n,
            min_run_s=min_run,
            keep_dir=Path(args.keep_dir) if args.keep_dir else None,
            transport=args.transport or d2.DEFAULT_TRANSPORT,
            pin=not args.no_pin,
        ),
        lambda: ex.run_inside_netns(
            Path(args.inside_netns),
            args.config,
            settle_s=settle,
            examples=EXAMPLES[:n],
            min_run_s=min_run,
            progress=stderr_progress,
        ),
    )
    if isinstance(summary, int):
        return summary
    print(json.dumps(summary, indent=2) if args.json else ex.render_table(summary))
    return EXIT_OK if summary["passed"] else EXIT_FAILED
