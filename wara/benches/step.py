"""``wara bench step --json``: the CPU of one ``ServiceCore.step`` per mode, in lockstep.

The HIL simulator and the service alternate in one thread on the in-process ``virtual``
bus (:class:`wara.harness.Harness` in ``lockstep``), with the real planner worker process and a
run record in a temporary directory, as in the service: IDLE, then Example 1 (roll 2,
pitch 1 deg) through STARTING, EXECUTE and COMPLETE. Logs go to stderr (JSON lines), the
result to stdout. Each step is timed around
``ServiceCore.step`` only (the simulator's step is not counted): the loop thread's CPU
(``time.thread_time_ns``) and the wall time, as p50 / p99 / max in ms per mode (the mode
at the start of the step) and over all steps. Before the first timed step the start-up
heap is frozen, as the service's loop does.

``--quick``: 0.5 s of IDLE and 1 s of COMPLETE instead of 3 s and 4 s (the motion takes
its 6.1 s either way). Compare figures as ratios within one run or between runs close
in time: the machine is shared.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from config import load_project, units
from ipc_app.service.core import ServiceCore
from ipc_app.service.logs import configure_logging
from ipc_app.service.loop import freeze_startup_heap
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder

EXAMPLE = (2.0, 1.0)


def _figures(cpu_ns: list[int], wall_ns: list[int]) -> dict[str, Any]:
    cpu = np.asarray(cpu_ns, dtype=float) * (units.NS / units.MS)
    wall = np.asarray(wall_ns, dtype=float) * (units.NS / units.MS)
    if cpu.size == 0:
        return {"steps": 0}
    return {
        "steps": int(cpu.size),
        "cpu_p50_ms": round(float(np.percentile(cpu, 50)), 4),
        "cpu_p99_ms": round(float(np.percentile(cpu, 99)), 4),
        "cpu_max_ms": round(float(cpu.max()), 4),
        "wall_p50_ms": round(float(np.percentile(wall, 50)), 4),
        "wall_p99_ms": round(float(np.percentile(wall, 99)), 4),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    from wara.harness import Harness  # the simulator: only for this bench

    config_path = getattr(args, "config", None)
    quick = bool(getattr(args, "quick", False))
    idle_s, hold_s = (0.5, 1.0) if quick else (3.0, 4.0)
    cfg = load_project(config_path)
    # JSON lines on stderr, as in the service; loggers not cached (no logging per step)
    logging_handle = configure_logging("INFO", cache_loggers=False)
    samples: dict[str, tuple[list[int], list[int]]] = {str(m): ([], []) for m in Mode}
    with tempfile.TemporaryDirectory(prefix="wara-bench-step-") as tmp:
        record = RunRecorder(Path(tmp) / "run", ServiceCore.record_columns(cfg))
        record.start()
        harness = Harness(cfg, config_path, mode="lockstep", record=record)
        core = harness.core
        step = core.step
        timing = [False]
        thread_ns = time.thread_time_ns
        wall_ns = time.perf_counter_ns

        def timed(cycle: int, now: float) -> None:
            if not timing[0]:
                step(cycle, now)
                return
            mode = str(core.modes.mode)
            w0 = wall_ns()
            c0 = thread_ns()
            step(cycle, now)
            c1 = thread_ns()
            w1 = wall_ns()
            cpu, wall = samples[mode]
            cpu.append(c1 - c0)
            wall.append(w1 - w0)

        core.step = timed  # type: ignore[method-assign]
        try:
            harness.start()
            if not harness.wait_for(Mode.IDLE, 20.0):
                raise RuntimeError(f"service did not come up: {core.modes.snapshot()}")
            harness.advance(0.5)  # the first frames of every message, the first status
            freeze_startup_heap()
            timing[0] = True
            harness.advance(idle_s)
            out = core.request_adjust(*EXAMPLE)
            if not out.get("ok"):
                raise RuntimeError(f"adjust refused: {out}")
            if not harness.wait_for(Mode.EXECUTE, 60.0):
                raise RuntimeError(f"no plan: {core.modes.snapshot()}")
            if not harness.wait_for(Mode.COMPLETE, 60.0):
                raise RuntimeError(f"did not finish: {core.modes.snapshot()}")
            harness.advance(hold_s)
            final_mode = str(core.modes.mode)
        finally:
            timing[0] = False
            harness.close()
            record.stop()
            logging_handle.stop()
    modes = {m: _figures(*v) for m, v in samples.items() if v[0]}
    all_cpu = [x for v in samples.values() for x in v[0]]
    all_wall = [x for v in samples.values() for x in v[1]]
    return {
        "bench": "step",
        "example_deg": list(EXAMPLE),
        "period_ms": units.to_ms(cfg.control.period_s),
        "final_mode": final_mode,
        "modes": modes,
        "all": _figures(all_cpu, all_wall),
        "quick": quick,
    }
