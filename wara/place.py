"""A placement on the HIL simulator through the service: ``wara place run``
(docs/placement.md).

The HIL simulator and the IPC service on one in-process bus (:class:`~wara.harness.Harness`).
Ring ``ring``'s target is planned in the planner process from the previous part's
deviation (as ``wara ctl place`` plans it) and asked of the service
(:meth:`~ipc_app.service.core.ServiceCore.request_place_plan`): the service plans the
attitude trajectory from its measured state and its loop runs the placement's phases
(attitude and height, then the slide axes) with its modes and interlocks, as on the
machine. The placed part is judged on the simulator's truth against the placement's
goals (:func:`wara.goals.placement_goals`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from config import load_project, units
from config.hil_scenario import HilScenario
from config.schema import ProjectConfig
from ipc_app.model.placement import Pose, deviation, joint_figures
from ipc_app.planner.placement import PlacementPlan
from ipc_app.planner.placement import judge as judge_table4
from ipc_app.service.cycle import MOTION_LIMIT_S, RECORD_KEYS
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from ipc_app.service.worker import PLAN_PLACE_FN, PlannerCallError
from wara.goals import judge, placement_figures, placement_goals
from wara.harness import Harness

#: The service's modes while a motion it took runs (held and ridden-through included).
MOVING = frozenset({Mode.STARTING, Mode.EXECUTE, Mode.HELD, Mode.SUSPENDED})


def placed_figures(
    cfg: ProjectConfig, plan: PlacementPlan, previous: Pose, as_built: Pose
) -> dict[str, Any]:
    """What a placed part is judged on: Table 4 of ``as_built`` against ``previous`` (the
    acceptance keys, signed), its error from ``plan``'s target (``x_mm`` ... ``yaw_deg``),
    the gap's error from the planned gap, and ``table4_truth`` (each item with its
    limit and verdict, as the planner judges a plan). All poses in the ring's T."""
    return placed_against(cfg, plan.design, plan.target, plan.figures.max_gap_m, previous, as_built)


def placed_against(
    cfg: ProjectConfig,
    design: Pose,
    target: Pose,
    planned_gap_m: float,
    previous: Pose,
    as_built: Pose,
) -> dict[str, Any]:
    """:func:`placed_figures` from a plan's poses and planned gap (a plan read back from
    its acceptance record)."""
    fig = joint_figures(cfg, previous, as_built, design)
    table4 = fig.to_dict()
    return {
        **{k: table4[k] for k in RECORD_KEYS},
        "min_gap_mm": table4["min_gap_mm"],
        "error_from_target": deviation(as_built, target).to_dict(),
        "gap_error_mm": units.to_mm(fig.max_gap_m - planned_gap_m),
        "table4_truth": judge_table4(cfg, fig),
    }


def run_place(
    config_path: str | None,
    ring: int,
    previous_deviation: Pose,
    *,
    cfg: ProjectConfig | None = None,
    mode: str = "lockstep",
    record: RunRecorder | None = None,
    scenario: HilScenario | None = None,
    progress: Callable[[str], None] | None = None,
    on_cycle: Callable[[Harness], None] | None = None,
) -> dict[str, Any]:
    """Plan ring ``ring``'s target from the previous part's deviation from its design,
    place the part there through the service and judge the simulator's truth. The
    JSON-ready result: ``passed``, ``refused`` (the target or its attitude trajectory
    unreachable: nothing moved), ``error``, ``plan``, ``goals``, ``missed``, the truth's
    figures (:func:`placed_figures`, ``achieved``), the service's (``phase_times_s``,
    ``max_sync_error_mm``), ``final_mode``, ``fault_reasons``.

    ``cfg``: the project as loaded from ``config_path`` (tests: a changed one);
    ``on_cycle``: called after each period of the move with the harness (tests)."""
    wall0 = time.perf_counter()
    if cfg is None:
        cfg = load_project(config_path)
    if cfg.placement is None:
        raise ValueError("the project has no placement section: it cannot place")
    say = progress or (lambda _s: None)
    out: dict[str, Any] = {"ring": ring, "passed": False, "refused": None, "error": None}
    h = Harness(cfg, config_path, mode=mode, record=record, scenario=scenario, trace=False)
    try:
        h.start()
        if not h.wait_for(Mode.IDLE, 20.0):
            out["error"] = f"service did not come up: {h.fault_note()}"
            return _finish(out, h, wall0)
        try:  # in the planner process, as the service plans a ``wara ctl place``
            plan: PlacementPlan = h.worker.call(PLAN_PLACE_FN, ring, previous_deviation)
        except PlannerCallError as exc:
            out["error"] = f"place refused: {exc}"
            return _finish(out, h, wall0)
        out["plan"] = plan.to_dict()
        res = h.core.request_place_plan(plan, wait_s=5.0 if mode == "realtime" else 0.0)
        if not res.get("ok"):
            out["error"] = res.get("error")
            if res.get("code") == "infeasible":
                out["refused"] = res.get("error")
                out["reasons"] = res.get("reasons") or [res.get("error")]
            return _finish(out, h, wall0)
        say(f"ring {ring}: placing")
        status = _follow(h, on_cycle)
        as_built = h.part_pose(ring)
    finally:
        h.close()
    if status is None:
        out["error"] = f"the service did not take the placement: {h.fault_note()}"
        return _finish(out, h, wall0)
    out["phase_times_s"] = status["phase_times_s"]
    out["max_sync_error_mm"] = status["max_sync_error_mm"]
    figures = placed_figures(cfg, plan, plan.previous, as_built)
    out["achieved"] = as_built.to_dict()
    out.update(figures)
    problem = "" if h.core.modes.mode == Mode.COMPLETE else h.fault_note()
    if status["elapsed_s"] > motion_limit_s(cfg):
        problem = f"the placement did not end within {motion_limit_s(cfg):.0f} s"
        problem += " (cycle.max_motion_min)"
    verdict = judge(placement_goals(cfg), placement_figures(figures), problem=problem)
    out.update(verdict.to_dict())
    out["error"] = problem or None
    return _finish(out, h, wall0)


def motion_limit_s(cfg: ProjectConfig) -> float:
    """The bound on a motion's machine time: the project's ``cycle.max_motion_min``, or
    its default where the project has no ``cycle`` section."""
    return cfg.cycle.max_motion_s if cfg.cycle is not None else MOTION_LIMIT_S


def _follow(h: Harness, on_cycle: Callable[[Harness], None] | None) -> dict[str, Any] | None:
    """Advance while the placement runs (at most ``cycle.max_motion_min`` of machine time);
    its last status (``elapsed_s`` added), None when the service did not take it."""
    dt = h.period if h.mode == "lockstep" else 0.05
    h.advance(dt)  # the loop takes the request
    status = h.core.place_status()
    elapsed = 0.0
    while status is not None and h.core.modes.mode in MOVING and elapsed <= motion_limit_s(h.cfg):
        h.advance(dt)
        elapsed += dt
        if on_cycle is not None:
            on_cycle(h)
        status = h.core.place_status() or status
    return None if status is None else {**status, "elapsed_s": elapsed}


def _finish(out: dict[str, Any], h: Harness, wall0: float) -> dict[str, Any]:
    out["final_mode"] = str(h.core.modes.mode)
    out["fault_reasons"] = list(h.core.modes.fault_reasons)
    out["wall_time_s"] = time.perf_counter() - wall0
    return out
