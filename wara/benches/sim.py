"""``wara bench sim --json``: how much faster than real time the dual-cylinder study runs.

Runs the shipped scenario (120 s; ``--quick``: 20 s) once per controller after
compiling the plant (numba; the compile time is reported, not counted), and reports
simulated seconds per wall-clock second of each closed loop and of the whole study.
"""

from __future__ import annotations

import argparse
import time
from typing import Any

from config.scenario import load_scenario, scenario_path
from hil_sim._jit import HAVE_NUMBA
from wara.studies import CONTROLLERS
from wara.studies.dual_cylinder import StudyRun, evaluate, run_study


def run(args: argparse.Namespace) -> dict[str, Any]:
    scenario = load_scenario()
    duration = 20.0 if getattr(args, "quick", False) else scenario.duration_s
    t0 = time.perf_counter()
    run_study(scenario, "ladrc", duration_s=0.01)  # load or compile the plant kernel
    warmup = time.perf_counter() - t0
    t1 = time.perf_counter()
    runs: dict[str, StudyRun] = {
        kind: run_study(scenario, kind, duration_s=duration) for kind in CONTROLLERS
    }
    wall = time.perf_counter() - t1
    report, _met = evaluate(runs, scenario)
    simulated = duration * len(runs)
    factor = simulated / wall
    goal = scenario.goals.min_realtime_factor
    return {
        "bench": "sim",
        "scenario": str(scenario_path("dual_cylinder")),
        "study_duration_s": duration,
        "controllers": list(runs),
        "numba": HAVE_NUMBA,
        "plant_step_ms": scenario.plant_step_ms,
        "control_rate_hz": scenario.control.rate_hz,
        "warmup_s": warmup,
        "wall_s": wall,
        "realtime_factor": factor,
        "realtime_factor_per_controller": {k: r.realtime_factor for k, r in runs.items()},
        "goal_min_realtime_factor": goal,
        "goal_met": factor >= goal,
        "sync_error_max_mm": {k: v["sync_error_max_mm"] for k, v in report["controllers"].items()},
    }
