"""Fake planner functions for the worker tests (imported in the worker process).

Magic roll values pick a misbehaviour; anything else runs the real planner.
"""

from __future__ import annotations

import os
import time
from typing import Any

from config.schema import ProjectConfig
from ipc_app.planner.plan import Plan
from ipc_app.service.worker import PlanRequest, run_planner

HANG_ROLL_DEG = 99.0
CRASH_ROLL_DEG = 98.0
RAISE_ROLL_DEG = 97.0


def planner_call_probe(cfg: ProjectConfig, how: str, value: Any = None) -> Any:
    """A function for :meth:`PlannerWorker.call`: where it ran and with which config
    (``"where"``), or it raises (``"raise"``), hangs (``"hang"``) or kills its process
    (``"crash"``)."""
    if how == "hang":
        time.sleep(3600)
    if how == "crash":
        os._exit(7)
    if how == "raise":
        raise ValueError(f"refused {value!r}")
    return {"pid": os.getpid(), "project": cfg.project.name, "value": value}


def misbehaving_plan(cfg: ProjectConfig, req: PlanRequest) -> Plan:
    if req.roll_deg == HANG_ROLL_DEG:
        time.sleep(3600)
    if req.roll_deg == CRASH_ROLL_DEG:
        os._exit(7)
    if req.roll_deg == RAISE_ROLL_DEG:
        raise ValueError("singular allocation")
    return run_planner(cfg, req)
