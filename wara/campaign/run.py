"""One campaign run: the lockstep harness (simulator + service core) with run ``i``'s
drawn parameters, doing what the spec's ``run`` says: attitude targets one after
another (judged as the demo's examples), a walk (judged per step as ``wara walk``
judges it) or ring cycles (judged per ring on the simulator's truth as ``wara cycle``
judges them).

:func:`run_one` is the whole task a campaign worker runs, and what ``wara campaign
replay`` runs again with plots: the row it returns depends only on the spec, the
project and the run index.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from config.schema import ProjectConfig
from ipc_app.model.placement import Pose
from ipc_app.service.modes import Mode
from ipc_app.service.worker import PlannerWorker
from wara.campaign.kinds import judge_fault, judge_nominal, ride_through_ms
from wara.campaign.spec import (
    FIGURES_OF,
    HIGHER_IS_BETTER,
    AttitudeTargets,
    Campaign,
    Draw,
    RingCycleRun,
    WalkRun,
    figure_margin,
    set_path,
)
from wara.examples import ExampleResult
from wara.goals import Goal, judge, ring_figures, step_figures
from wara.harness import Harness

#: Columns of a row that are not the same from one execution of a run to the next.
VOLATILE_COLUMNS = ("wall_s", "worker")

#: How long (simulated) the service may take to come up before the first target.
STARTUP_S = 20.0


@dataclass
class RunOutcome:
    """What a run did: its figures (the worst over its targets, steps or rings; NaN
    where it did not get that far), whether it finished (every target held, every step
    walked, every ring built), why not, and the service's state at the end."""

    figures: dict[str, float]
    done: bool
    problem: str = ""
    fault_reasons: list[str] = field(default_factory=list)
    #: the latched causes in order (:class:`~ipc_app.service.interlocks.Interlock` values)
    fault_interlocks: list[str] = field(default_factory=list)
    final_mode: str = ""
    sim_time_s: float = 0.0


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
    """Run ``index`` of the campaign; one result row (see :func:`row_of`). ``plot_dir``:
    the run's plots (attitude targets: ``demo.png``; a walk: ``walk.png``)."""
    t0 = time.perf_counter()
    draw = c.draw(index)
    cfg = service_project(c, overrides)
    own = planner is None
    if planner is None:
        from wara.campaign.engine import PLANNER_TIMEOUT_S

        planner = PlannerWorker(c.project_file, timeout_s=PLANNER_TIMEOUT_S)
        planner.start()
    try:
        run = c.spec.run
        if isinstance(run, WalkRun):
            outcome = _walk(c, run, cfg, draw, planner, plot_dir)
        elif isinstance(run, RingCycleRun):
            outcome = _ring_cycle(c, run, cfg, draw, planner)
        else:
            outcome = _attitude(c, run, cfg, draw, planner, plot_dir)
    finally:
        if own:
            planner.close()
    return row_of(c, draw, outcome, wall_s=time.perf_counter() - t0, worker=worker)


def _attitude(
    c: Campaign,
    run: AttitudeTargets,
    cfg: ProjectConfig,
    draw: Draw,
    planner: PlannerWorker,
    plot_dir: Path | None,
) -> RunOutcome:
    """The targets one after another, each judged as a demo example."""
    names = FIGURES_OF[run.kind]
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
                and all(math.isfinite(getattr(r, f)) for f in names)
            )
            if h.faulted() or not held[-1]:
                break
        sim_t = h.sim.t_s
        fault_reasons = list(h.core.modes.fault_reasons)
        interlocks = [str(i) for i in h.core.modes.fault_interlocks]
        final_mode = str(h.core.modes.mode)
        if plot_dir is not None:
            from wara.demo import plot_trace

            plot_trace(h.trace, plot_dir)
    finally:
        h.close()
    n = len(draw.targets)
    complete = len(results) == n
    figures = {f: max(getattr(r, f) for r in results) if complete else math.nan for f in names}
    figures["duration_s"] = sum(r.duration_s for r in results) if complete else math.nan
    return RunOutcome(
        figures,
        done=not problem and len(held) == n and all(held),
        problem=problem or next((r.note for r in results if r.note), ""),
        fault_reasons=fault_reasons,
        fault_interlocks=interlocks,
        final_mode=final_mode,
        sim_time_s=sim_t,
    )


def _walk(
    c: Campaign,
    run: WalkRun,
    cfg: ProjectConfig,
    draw: Draw,
    planner: PlannerWorker,
    plot_dir: Path | None,
) -> RunOutcome:
    """``wara walk --steps N --lockstep`` on the drawn machine; the worst step's figures."""
    from wara.walk import run_walk

    directions = (run.direction, "back" if run.direction == "forward" else "forward")
    out = run_walk(
        c.project_file,
        run.steps,
        cfg=cfg,
        scenario=draw.scenario,
        sim_cfg=draw.sim_project,
        seed=draw.sim_seed,
        planner=planner,
        plot_dir=plot_dir,
        directions=directions if run.and_back else directions[:1],
    )
    steps = out.get("steps") or []
    want = run.steps * (2 if run.and_back else 1)
    done = len(steps) == want and all(s["duration_s"] > 0 for s in steps)
    figures: dict[str, float] = dict.fromkeys(FIGURES_OF["walk"], math.nan)
    if done:
        step_m = cfg.walking.step_length_m if cfg.walking is not None else 0.0
        per_step = [step_figures(s, step_m) for s in steps]
        for name in figures:
            worst = min if name in HIGHER_IS_BETTER else max
            figures[name] = worst(f[name] for f in per_step)
    return RunOutcome(
        figures,
        done=done and out.get("final_mode") == str(Mode.COMPLETE),
        problem=str(out.get("refused") or out.get("error") or ""),
        fault_reasons=list(out.get("fault_reasons") or []),
        fault_interlocks=list(out.get("fault_interlocks") or []),
        final_mode=str(out.get("final_mode", "")),
        sim_time_s=float(out.get("sim_time_s", 0.0)),
    )


def _ring_cycle(
    c: Campaign, run: RingCycleRun, cfg: ProjectConfig, draw: Draw, planner: PlannerWorker
) -> RunOutcome:
    """``wara cycle --rings N --lockstep`` on the drawn machine, its records in a store
    of its own; the worst ring's figures on the simulator's truth."""
    from config import units
    from wara.cycle import run_cycle

    y_mm, z_mm = draw.previous_mm
    with tempfile.TemporaryDirectory(prefix="wara-campaign-ring-") as tmp:
        out = run_cycle(
            c.project_file,
            run.rings,
            previous_deviation=Pose(y=units.mm(y_mm), z=units.mm(z_mm)),
            db_path=Path(tmp) / "acceptance.sqlite",
            seed=draw.sim_seed,
            cfg=cfg,
            sim_cfg=draw.sim_project,
            planner=planner,
            scenario=draw.scenario,
        )
    rows = out.get("rings") or []
    done = len(rows) == run.rings and out.get("error") is None
    figures: dict[str, float] = dict.fromkeys(FIGURES_OF["ring_cycle"], math.nan)
    if done:
        per_ring = [ring_figures(r) for r in rows]
        for name in figures:
            figures[name] = max(f[name] for f in per_ring)
    return RunOutcome(
        figures,
        done=done,
        problem=str(out.get("error") or ""),
        fault_reasons=list(out.get("fault_reasons") or []),
        fault_interlocks=list(out.get("fault_interlocks") or []),
        final_mode=str(out.get("final_mode", "")),
        sim_time_s=float(out.get("sim_time_s", 0.0)),
    )


def _happened(c: Campaign, draw: Draw) -> list[tuple[str, float]]:
    """The (kind, duration s; NaN: to the run's end) of each event that happened in the
    run."""
    out = []
    for j, ev in enumerate(c.spec.events):
        tag = f"event{j}_{ev.event['kind']}"
        if math.isfinite(draw.params[f"{tag}_start_s"]):
            out.append((str(ev.event["kind"]), draw.params.get(f"{tag}_duration_s", math.nan)))
    return out


def row_of(
    c: Campaign, draw: Draw, outcome: RunOutcome, *, wall_s: float, worker: str
) -> dict[str, Any]:
    """The row: ``run``, ``seed``, the drawn parameters (``p.<name>``), the figures (the
    worst over the run's targets, steps or rings), ``margin`` (the smallest relative
    margin over the limits, :func:`~wara.campaign.spec.figure_margin`; -1 when the run
    did not finish), ``passed``, ``status`` (passed, over_limit, not_finished),
    ``note``, ``fault_reasons``, ``final_mode``, ``sim_time_s``, and the volatile
    ``wall_s`` and ``worker``."""
    figures = outcome.figures
    goals = (Goal(name, limit, "the campaign's limits") for name, limit in c.limits.items())
    over = [j.note for j in judge(goals, figures).missed]
    margin = -1.0
    if outcome.done:
        margin = min(figure_margin(name, figures[name], limit) for name, limit in c.limits.items())
    v = (
        judge_fault(
            _happened(c, draw),
            outcome.done,
            over,
            outcome.fault_interlocks,
            ride_through_ms(c.project),
        )
        if c.spec.kind == "fault"
        else judge_nominal(outcome.done, over)
    )
    passed, status, note = v.passed, v.status, v.note
    if status == "not_finished":
        note = outcome.problem or f"service {outcome.final_mode}"
    row: dict[str, Any] = {"run": draw.index, "seed": draw.sim_seed}
    row.update({f"p.{k}": v for k, v in draw.params.items()})
    row.update(figures)
    row.update(
        {
            "margin": margin,
            "passed": passed,
            "status": status,
            "note": note,
            "fault_reasons": "; ".join(outcome.fault_reasons),
            "final_mode": outcome.final_mode,
            "sim_time_s": outcome.sim_time_s,
            "wall_s": wall_s,
            "worker": worker,
        }
    )
    return row
