"""``wara demo``: the end-to-end demo (HIL simulator + IPC service, Examples 1-3).

Exit 0 only if every example met its tolerances (attitude error <= 0.01 deg, twist
<= 0.5 mm during motion, sync error at standstill <= 0.07 mm).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from wara.cli import EXIT_FAILED, EXIT_OK


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="end-to-end demo: simulator + service, Examples 1-3")
    p.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", default=None, metavar="DIR", help="write plots into DIR")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="simulated time in one thread (fast, no loop jitter figures)",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from wara.demo import render_table, run_demo, stderr_progress

    summary = run_demo(
        args.config,
        mode="lockstep" if args.lockstep else "realtime",
        plot_dir=Path(args.plot) if args.plot else None,
        progress=stderr_progress,
    )
    print(json.dumps(summary, indent=2) if args.json else render_table(summary))
    return EXIT_OK if summary["passed"] else EXIT_FAILED
