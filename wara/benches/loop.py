"""``wara bench loop --json``: the fixed-rate loop at the project's rate on this machine.

Runs :class:`ipc_app.service.loop.FixedRateLoop` for 10 s (1 s with ``--quick``) at
``control.loop_rate_hz`` with the project's ``control.realtime`` settings; each step
evaluates a planned trajectory's reference (what the service does every cycle besides
CAN and the controllers). Prints the loop statistics: jitter (wake-up minus deadline),
period deviation and compute time p50/p99/max in ms, overruns, skipped periods, and the
real-time settings applied or refused. Logs go to stderr (JSON lines), the result to
stdout.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from config import load_project
from ipc_app.planner import plan
from ipc_app.service.logs import configure_logging
from ipc_app.service.loop import FixedRateLoop


def run(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_project(args.config)
    logging_handle = configure_logging("INFO")  # JSON lines on stderr, as in the service
    p = plan(cfg, -3.0, 2.0)
    traj = p.trajectory
    assert traj is not None
    seconds = 1.0 if args.quick else 10.0
    t0 = [0.0]

    def step(k: int, t: float) -> None:
        if k == 0:
            t0[0] = t
        traj.reference(t - t0[0])

    loop = FixedRateLoop(step, cfg.control.period_s, realtime=cfg.control.realtime)
    loop.start()
    time.sleep(seconds)
    loop.stop()
    logging_handle.stop()
    stats = loop.stats()
    stats["seconds"] = seconds
    stats["realtime"] = loop.realtime_report.to_dict()
    return stats
