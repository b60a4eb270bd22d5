"""``wara cycle``: ring cycles on the HIL simulator and the IPC service (docs/placement.md).

    wara cycle --rings 4 --lockstep --previous-deviation 6,-6,0,0,0 --json

Exit codes: 0 every ring met its goals; 1 a goal missed, a phase failed or the service
stopped (the phase it was in is named); 2 bad arguments or configuration; 3 a ring's
target unreachable (the binding limit), refused before that ring moved.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from acceptance.store import StoreError, check_store, default_db_path
from config import load_project
from config.numbers import integer
from ipc_app.model.placement import Pose
from wara.cli import EXIT_FAILED, EXIT_INFEASIBLE, EXIT_OK, UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "cycle",
        help="ring cycles: walk, place, fix, release, survey, record, walk back",
        description="Ring cycles on the HIL simulator and the IPC service (docs/placement.md).",
    )
    p.add_argument("--config", default=None, metavar="PATH", help="project YAML")
    p.add_argument("--rings", type=integer, default=1, help="number of rings (1..50)")
    p.add_argument("--first-ring", type=integer, default=2, help="the first ring built (2..99999)")
    p.add_argument(
        "--previous-deviation",
        default=None,
        metavar="Y_MM,Z_MM,ROLL_DEG,PITCH_DEG,YAW_DEG",
        help="the part before the first ring: its deviation from its design (default none)",
    )
    p.add_argument("--db", default=None, metavar="PATH", help="acceptance store (records)")
    p.add_argument("--seed", type=integer, default=0, help="the simulated survey's noise")
    p.add_argument("--lockstep", action="store_true", help="simulated time in one thread")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if not 1 <= args.rings <= 50:
        raise UsageError(f"--rings must be within 1..50, got {args.rings}")
    if not 2 <= args.first_ring <= 99_999 - args.rings:
        raise UsageError(
            f"--first-ring must be within 2..{99_999 - args.rings}, got {args.first_ring}"
        )
    cfg = load_project(args.config)
    if cfg.placement is None or cfg.cycle is None:
        raise UsageError("the project has no placement and cycle sections: it cannot place")
    from wara.commands.place import parse_deviation
    from wara.extras import require_realtime_simulator

    dev = Pose() if args.previous_deviation is None else parse_deviation(args.previous_deviation)
    db_path = Path(args.db) if args.db else default_db_path()
    try:  # before anything moves: a store that cannot take the records refuses now
        check_store(db_path, create=True)
    except StoreError as exc:
        raise UsageError(str(exc)) from None
    if not args.lockstep:
        require_realtime_simulator()
    from ipc_app.service.logs import configure_logging
    from wara.cycle import run_cycle

    def say(msg: str) -> None:
        print(f"wara cycle: {msg}", file=sys.stderr)

    logs = configure_logging("WARNING")
    try:
        out = run_cycle(
            args.config,
            args.rings,
            first_ring=args.first_ring,
            previous_deviation=dev,
            db_path=db_path,
            mode="lockstep" if args.lockstep else "realtime",
            seed=args.seed,
            progress=say,
        )
    finally:
        logs.stop()
    from wara.cycle import render

    print(json.dumps(out, indent=2) if args.json else render(out))
    if out["refused"] is not None:
        print(f"wara cycle: refused: {out['refused']}", file=sys.stderr)
        return EXIT_INFEASIBLE
    if not out["passed"]:
        print(f"wara cycle: FAILED: {'; '.join(out['missed'])}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK
