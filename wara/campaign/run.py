"""One campaign run: the lockstep harness (simulator + service core) with run ``i``'s
drawn parameters, its targets one after another, judged as the demo's examples.

:func:`run_one` is the whole task a campaign worker runs, and what ``wara campaign
replay`` runs again with plots: the row it returns depends only on the spec, the
project and the run index.
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

from config.schema import ProjectConfig
from ipc_app.service.modes import Mode
from ipc_app.service.worker import PlannerWorker
from wara.campaign.spec import FIGURES, Campaign, Draw, set_path
from wara.examples import ExampleResult
from wara.harness import Harness

#: Columns of a row that are not the same from one execution of a run to the next.
VOLATILE_COLUMNS = ("wall_s", "worker")

#: How long (simulated) the service may take to come up before the first target.
STARTUP_S = 20.0


def service_project(c: Campaign, overrides: dict[str, float] | None) -> ProjectConfig:
    """The project the service runs on: the nominal one, with ``overrides`` (tuned
    ``control.*`` values) set."""
    if not overrides:
        return c.project
    data = c.project.model_dump(mode="json")
    for path, value in overrides.items():
        set_path(data, path, value)
    return ProjectConfig.model_validate(data)


def run_one(
    c: Campaign,
    index: int,
    *,
    planner: PlannerWorker | None = None,
    overrides: dict[str, float] | None = None,
    plot_dir: Path | None = None,
    worker: str = "",
) -> dict[str, Any]:
    """Run ``index`` of the campaign; one result row (see :func:`row_of`)."""
    t0 = time.perf_counter()
    draw = c.draw(index)
    cfg = service_project(c, overrides)
    own = planner is None
    if planner is None:
        from wara.campaign.engine import PLANNER_TIMEOUT_S

        planner = PlannerWorker(c.project_file, timeout_s=PLANNER_TIMEOUT_S)
        planner.start()
    h = Harness(
        cfg,
        c.project_file,
        mode="lockstep",
        scenario=draw.scenario,
        planner=planner,
        sim_cfg=draw.sim_project,
        seed=draw.sim_seed,
        trace=plot_dir is not None,
    )
    results: list[ExampleResult] = []
    held: list[bool] = []  # each target reached, judged and held
    problem = ""
    try:
        h.start()
        if not h.wait_for(Mode.IDLE, STARTUP_S):
            problem = f"service did not come up: {h.fault_note()}"
        for roll, pitch in draw.targets if not problem else ():
            r = h.run_example(roll, pitch)
            results.append(r)
            held.append(
                h.core.modes.mode == Mode.COMPLETE
                and all(math.isfinite(getattr(r, f)) for f in FIGURES)
            )
            if h.faulted() or not held[-1]:
                break
        sim_t = h.sim.t_s
        fault_reasons = list(h.core.modes.fault_reasons)
        final_mode = str(h.core.modes.mode)
        if plot_dir is not None:
            from wara.demo import plot_trace

            plot_trace(h.trace, plot_dir)
    finally:
        h.close()
        if own:
            planner.close()
    return row_of(
        c,
        draw,
        results,
        done=not problem and len(held) == len(draw.targets) and all(held),
        problem=problem,
        fault_reasons=fault_reasons,
        final_mode=final_mode,
        sim_time_s=sim_t,
        wall_s=time.perf_counter() - t0,
        worker=worker,
    )


def row_of(
    c: Campaign,
    draw: Draw,
    results: list[ExampleResult],
    *,
    done: bool,
    problem: str,
    fault_reasons: list[str],
    final_mode: str,
    sim_time_s: float,
    wall_s: float,
    worker: str,
) -> dict[str, Any]:
    """``done``: every target reached and held. The row: ``run``, ``seed``, the drawn
    parameters (``p.<name>``), the figures (the worst over the run's targets),
    ``margin``, ``passed``, ``status`` (passed, over_limit, not_finished), ``note``,
    ``fault_reasons``, ``final_mode``, ``sim_time_s``, and the volatile ``wall_s`` and
    ``worker``."""
    req = c.spec.requirement
    n_targets = len(draw.targets)
    figures: dict[str, float] = {}
    for f in FIGURES:
        vals = [getattr(r, f) for r in results]
        figures[f] = max(vals) if vals and len(vals) == n_targets else math.nan
    figures["duration_s"] = (
        sum(r.duration_s for r in results) if len(results) == n_targets else math.nan
    )
    over = [
        f"{name} {figures[name]:.4g} > {limit:g}"
        for name, limit in req.limits.items()
        if not figures[name] <= limit
    ]
    margin = -1.0
    if done:
        margin = min(1.0 - figures[name] / limit for name, limit in req.limits.items())
    passed = done and not over
    if passed:
        status, note = "passed", ""
    elif done:
        status, note = "over_limit", "; ".join(over)
    else:
        status = "not_finished"
        note = problem or next((r.note for r in results if r.note), "") or (f"service {final_mode}")
    row: dict[str, Any] = {"run": draw.index, "seed": draw.sim_seed}
    row.update({f"p.{k}": v for k, v in draw.params.items()})
    row.update(figures)
    row.update(
        {
            "margin": margin,
            "passed": passed,
            "status": status,
            "note": note,
            "fault_reasons": "; ".join(fault_reasons),
            "final_mode": final_mode,
            "sim_time_s": sim_time_s,
            "wall_s": wall_s,
            "worker": worker,
        }
    )
    return row
