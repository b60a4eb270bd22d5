"""The end-to-end walk: ``wara walk --steps N`` (docs/walking.md).

The HIL simulator with the walking rig (``plant.contact: true``) and the IPC service on
one in-process bus (:class:`~wara.harness.Harness`), the walk asked for as ``wara ctl
walk`` asks for it, and each step judged against the goals from the service's figures
and the simulator's truth (distance, the workpiece's attitude during each transfer, the
feet's forces at the end).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from config import load_project, units
from config.hil_scenario import HilScenario, PlantSettings
from config.schema import ProjectConfig
from ipc_app.control.walk import TRANSFER
from ipc_app.model.placement import axis_pose
from ipc_app.planner.steering import OnAxis, on_axis_at_start, step_turns
from ipc_app.planner.walk import DIRECTIONS, ORDER
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from ipc_app.service.worker import PlannerWorker
from wara.goals import Goal, Verdict, judge, step_figures, walk_goals, walk_step_goals
from wara.harness import Harness


@dataclass
class _StepTruth:
    #: M's centre in plan at the step's start and end (the walk's base frame), m
    xy_start: tuple[float, float]
    xy_end: tuple[float, float] | None = None
    attitude_change_deg: float = 0.0

    def distance_m(self) -> float:
        """Along M's chord, signed by x: on a 300 m curve a step's chord is 2 m less
        4 um of arc."""
        return _chord_m(self.xy_start, self.xy_end or self.xy_start)


def _chord_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    dx, dy = b[0] - a[0], b[1] - a[1]
    return math.copysign(math.hypot(dx, dy), dx)


def _m_xy(h: Harness) -> tuple[float, float]:
    """M's centre in plan, the simulator's truth."""
    walk = h.sim.truth().walk
    assert walk is not None
    return float(walk.plan_xy_m[0, 0]), float(walk.plan_xy_m[0, 1])


def against_axis(
    cfg: ProjectConfig, chainage_m: float, xy: tuple[float, float], heading_rad: float
) -> tuple[float, float]:
    """The machine (M's centre ``xy`` and its heading, in the walk's base frame: x along
    the axis at the start chainage, on it) against the design axis at ``chainage_m``: its
    heading error (rad) and its offset (m), both positive to the left."""
    alignment = cfg.tunnel.alignment
    start = on_axis_at_start(cfg).chainage_m
    if alignment is None:
        return heading_rad, xy[1]
    p0, p1 = axis_pose(alignment, start), axis_pose(alignment, chainage_m)
    c, s = math.cos(p0.yaw), math.sin(p0.yaw)
    dx, dy = p1.x - p0.x, p1.y - p0.y
    # the axis's point and heading at chainage_m in the base frame (plan; the base
    # frame's x runs along the grade, which shortens the plan's by cos(grade): below
    # 1e-3 of a step on a 5 % grade, and along both)
    ax, ay = c * dx + s * dy, -s * dx + c * dy
    yaw = p1.yaw - p0.yaw
    lateral = -math.sin(yaw) * (xy[0] - ax) + math.cos(yaw) * (xy[1] - ay)
    return heading_rad - yaw, lateral


@dataclass
class WalkTrace:
    """Per sample: time, phase index, leg forces (kN, truth), leg and travel rods (mm),
    the service's stability margin, and in a transfer the part's roll and pitch change
    from the transfer's start (mdeg, truth: the judged figure; NaN outside one)."""

    t: list[float] = field(default_factory=list)
    phase: list[int] = field(default_factory=list)
    forces_kn: list[list[float]] = field(default_factory=list)
    x_mm: list[list[float]] = field(default_factory=list)
    margin_m: list[float] = field(default_factory=list)
    transfer_attitude_mdeg: list[tuple[float, float]] = field(default_factory=list)


def walk_scenario(base: HilScenario | None = None) -> HilScenario:
    """``base`` (or the defaults) with the walking rig on."""
    sc = base or HilScenario()
    plant = sc.plant.model_copy(update={"contact": True}) if base else PlantSettings(contact=True)
    return sc.model_copy(update={"plant": plant})


def run_walk(
    config_path: str | None,
    steps: int,
    *,
    mode: str = "lockstep",
    scenario: HilScenario | None = None,
    plot_dir: Path | None = None,
    record: RunRecorder | None = None,
    progress: Callable[[str], None] | None = None,
    on_cycle: Callable[[Harness], None] | None = None,
    directions: tuple[str, ...] = ("forward",),
    cfg: ProjectConfig | None = None,
    sim_cfg: ProjectConfig | None = None,
    seed: int = 0,
    planner: PlannerWorker | None = None,
) -> dict[str, Any]:
    """Walk ``steps`` steps in each of ``directions`` in turn (``("forward", "back")``:
    there and back); the JSON-ready result (``passed``, ``refused``, ``missed``...). The
    simulated machine carries its part, so the walks are loaded (an unloaded walk's
    statics are the service's; the simulator without the part diverges, docs/walking.md).
    Each step is judged against :func:`~wara.goals.walk_step_goals` of ``cfg``.

    ``on_cycle``: called after each sample with the harness (tests: stop, resume).
    ``cfg``: the project as loaded from ``config_path`` (tests: a changed one).
    ``sim_cfg``, ``seed``, ``planner``: the simulated machine when it differs from the
    project, the simulator's seed, a running planner worker to share (a campaign's run;
    :class:`~wara.harness.Harness`)."""
    if cfg is None:
        cfg = load_project(config_path)
    if not directions or any(d not in DIRECTIONS for d in directions):
        raise ValueError(f"directions must be of {', '.join(DIRECTIONS)}, got {directions!r}")
    goals = walk_step_goals(cfg)
    say = progress or (lambda _s: None)
    h = Harness(
        cfg, config_path, mode=mode, scenario=walk_scenario(scenario), record=record,
        sim_cfg=sim_cfg, seed=seed, planner=planner, trace=False,
    )  # fmt: skip
    trace = WalkTrace()
    truths: list[_StepTruth] = []
    walks: list[dict[str, Any]] = []
    out: dict[str, Any] = {"passed": False, "refused": None, "error": None}
    try:
        h.start()
        if not (h.wait_for(Mode.IDLE, 20.0) and h.wait_walk_ready()):
            out["error"] = f"service did not come up: {h.fault_note()}"
            return _finish(out, h, cfg, goals, truths, trace, steps, plot_dir, walks, directions)
        out["start_x_m"] = round(_m_xy(h)[0], 6)
        for direction in directions:
            if walks and h.core.modes.mode != Mode.COMPLETE:
                break
            res = h.core.request_walk(
                steps, wait_s=5.0 if mode == "realtime" else 0.0,
                direction=direction,
            )  # fmt: skip
            if not res.get("ok"):
                out["refused"] = res.get("refusal") or res.get("error")
                out["error"] = res.get("error")
                break
            step_s = next(g.limit for g in goals if g.figure == "max_step_duration_s")
            seen = _follow(h, cfg, steps * step_s * 1.5, mode, say, on_cycle, trace, truths)
            if seen is not None:
                walks.append(seen)
        return _finish(out, h, cfg, goals, truths, trace, steps, plot_dir, walks, directions)
    finally:
        h.close()


def _follow(
    h: Harness,
    cfg: ProjectConfig,
    limit_s: float,
    mode: str,
    say: Callable[[str], None],
    on_cycle: Callable[[Harness], None] | None,
    trace: WalkTrace,
    truths: list[_StepTruth],
) -> dict[str, Any] | None:
    """Advance while one walk runs, reading the service's walk status
    (:meth:`~ipc_app.service.core.ServiceCore.walk_status`: the step and phase of each
    period), at most ``limit_s`` of machine time; each step's truth into ``trace`` and
    ``truths``; the walk's last status."""
    rig = h.sim.rig
    dt = h.period if mode == "lockstep" else 0.05
    waited = 0.0
    att0: tuple[float, float] | None = None
    last: tuple[int, str] | None = None  # (step, phase) of the period before
    seen: dict[str, Any] | None = None
    first = len(truths)
    travel = [c.can_index for c in cfg.cylinders_by_can_index if c.role == "travel"]
    while waited < limit_s:
        h.advance(dt)
        waited += dt
        core = h.core
        if on_cycle is not None:
            on_cycle(h)
        st = core.walk_status()
        if st is None or not st["phase"]:
            if core.modes.mode != Mode.EXECUTE:
                break
            continue
        seen = st
        now = (st["step"], st["phase"])
        if now != last:
            xy = _m_xy(h)
            if last is None or now[0] != last[0]:
                if len(truths) > first:
                    truths[-1].xy_end = xy
                truths.append(_StepTruth(xy))
                say(f"step {st['step']} {st['direction']}")
            last = now
            att0 = rig.workpiece_attitude_rad() if st["phase"] in TRANSFER else None
        turned = (math.nan, math.nan)
        if att0 is not None:
            r, pch = rig.workpiece_attitude_rad()
            d_roll, d_pitch = units.to_deg(r - att0[0]), units.to_deg(pch - att0[1])
            turned = (d_roll * 1e3, d_pitch * 1e3)
            change = max(abs(d_roll), abs(d_pitch))
            truths[-1].attitude_change_deg = max(truths[-1].attitude_change_deg, change)
        if (mode == "lockstep" and h._k % 10 == 0) or mode == "realtime":
            legs = [cfg.cylinder(c).can_index for c in st["leg_forces_kn"]] + travel
            trace.t.append(h.sim.t_s)
            order = ORDER[st["direction"]]  # the plan's phase index
            trace.phase.append((st["step"] - 1) * len(order) + order.index(st["phase"]))
            trace.forces_kn.append((rig.foot_forces_n / units.KN).tolist())  # type: ignore[attr-defined]
            trace.x_mm.append((rig.rod_positions_m[legs] * units.to_mm(1.0)).tolist())
            fm = st["stability_margin_m"]
            trace.margin_m.append(np.nan if fm is None else fm)
            trace.transfer_attitude_mdeg.append(turned)
        if st["done"] or core.modes.mode not in (Mode.EXECUTE, Mode.HELD, Mode.SUSPENDED):
            break  # done, or ended otherwise (ridden through a suspension)
    if len(truths) > first and truths[-1].xy_end is None:
        truths[-1].xy_end = _m_xy(h)
    return seen


def _finish(
    out: dict[str, Any],
    h: Harness,
    cfg: ProjectConfig,
    goals: tuple[Goal, ...],
    truths: list[_StepTruth],
    trace: WalkTrace,
    steps: int,
    plot_dir: Path | None,
    walks: list[dict[str, Any]],
    directions: tuple[str, ...],
) -> dict[str, Any]:
    core = h.core
    rig = h.sim.rig
    out["final_mode"] = str(core.modes.mode)
    out["fault_reasons"] = list(core.modes.fault_reasons)
    out["fault_interlocks"] = [str(i) for i in core.modes.fault_interlocks]
    out["directions"] = list(directions)
    assert cfg.walking is not None
    step_m = cfg.walking.step_length_m
    rows: list[dict[str, Any]] = []
    parts: list[tuple[str, Verdict]] = []
    for w in walks:
        for fig in w["steps_done"]:
            k = len(rows)
            tr = truths[k] if k < len(truths) else None
            row = {"direction": w["direction"], **fig}
            row["distance_m"] = round(tr.distance_m(), 6) if tr else 0.0
            row["max_transfer_attitude_change_deg"] = (
                round(tr.attitude_change_deg, 6) if tr else 0.0
            )
            verdict = judge(goals, step_figures(row, step_m))
            row.update(verdict.to_dict())
            parts.append((f"step {k + 1} {w['direction']}", verdict))
            rows.append(row)
    xy0 = truths[0].xy_start if truths else (0.0, 0.0)
    xy1 = (truths[-1].xy_end or xy0) if truths else xy0
    out["distance_m"] = round(_chord_m(xy0, xy1), 6)
    figures = {"distance_error_mm": 0.0, "heading_error_deg": 0.0}
    walk = h.sim.truth().walk
    if walk is not None and truths:
        # where the steps walked to along the axis, as the plan lays them
        chainage = on_axis_at_start(cfg).chainage_m
        for w in walks:
            done = len(w["steps_done"])
            if done:
                turns = step_turns(cfg, OnAxis(chainage), done, w["direction"])
                chainage = turns[-1].after.chainage_m
        heading, lateral = against_axis(cfg, chainage, xy1, float(walk.heading_rad[0]))
        out["heading_error_deg"] = round(units.to_deg(heading), 5)
        out["lateral_offset_mm"] = round(units.to_mm(lateral), 3)
        figures["heading_error_deg"] = abs(units.to_deg(heading))
    out["steps"] = rows
    ids = getattr(rig, "leg_ids", ())
    forces = getattr(rig, "foot_forces_n", np.zeros(len(ids)))
    out["leg_forces_kn"] = {
        cid: round(float(f) / units.KN, 2) for cid, f in zip(ids, forces, strict=True)
    }
    out["bus_load_percent"] = round(core.bus_load.load_percent, 2)
    out["simulator_realtime_factor"] = h.sim.realtime_factor
    out["sim_time_s"] = round(h.sim.t_s, 3)
    want = sum(-1.0 if d == "back" else 1.0 for d in directions) * steps * step_m
    asked = steps * len(directions)
    problem = out["error"] or ""
    if not problem and out["final_mode"] != str(Mode.COMPLETE):
        problem = h.fault_note()
    if not problem and len(rows) < asked:
        problem = f"{len(rows)} of {asked} steps walked"
    figures["distance_error_mm"] = 1000.0 * abs(out["distance_m"] - want)
    verdict = judge(walk_goals(cfg), figures, problem=problem, parts=parts)
    out.update(verdict.to_dict())
    out["step_goals"] = {g.figure: {"limit": g.limit, "source": g.source} for g in goals}
    if plot_dir is not None and trace.t:
        leg_ids = tuple(walks[-1]["leg_forces_kn"]) if walks else ()
        out["plots"] = [str(plot_walk(trace, leg_ids, goals, plot_dir))]
    return out


def plot_walk(
    trace: WalkTrace, leg_ids: tuple[str, ...], goals: tuple[Goal, ...], out_dir: Path
) -> Path:
    """Leg forces, leg and travel positions, the stability margin, the part's roll and
    pitch change in each transfer against its limit, and the phase (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.asarray(trace.t)
    fig, ax = plt.subplots(5, 1, figsize=(11, 14), sharex=True)
    f = np.asarray(trace.forces_kn)
    for j, cid in enumerate(leg_ids):
        ax[0].plot(t, f[:, j], label=cid)
    ax[0].set_ylabel("foot force kN")
    ax[0].legend(ncol=4, fontsize=7)
    x = np.asarray(trace.x_mm)
    names = [*leg_ids, "travel_1", "travel_2"]
    for j, cid in enumerate(names[: x.shape[1]]):
        ax[1].plot(t, x[:, j], label=cid)
    ax[1].set_ylabel("rod position mm")
    ax[1].legend(ncol=5, fontsize=7)
    ax[2].plot(t, trace.margin_m)
    margin = next(g.limit for g in goals if g.figure == "min_stability_margin_m")
    ax[2].axhline(margin, color="r", ls="--")
    ax[2].set_ylabel("stability margin m")
    turned = np.asarray(trace.transfer_attitude_mdeg, dtype=float).reshape(-1, 2)
    ax[3].plot(t, turned[:, 0], label="roll")
    ax[3].plot(t, turned[:, 1], label="pitch")
    limit_mdeg = 1e3 * next(
        g.limit for g in goals if g.figure == "max_transfer_attitude_change_deg"
    )
    for sign in (1.0, -1.0):
        ax[3].axhline(sign * limit_mdeg, color="r", ls="--")
    ax[3].set_ylabel("part's turn in a transfer mdeg")
    ax[3].legend(ncol=2, fontsize=7)
    ax[4].plot(t, trace.phase, drawstyle="steps-post")
    ax[4].set_ylabel("phase (index)")
    ax[4].set_xlabel("machine time s")
    path = out_dir / "walk.png"
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


__all__ = ["run_walk", "walk_scenario"]
