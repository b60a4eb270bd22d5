"""The end-to-end walk: ``wara walk --steps N`` (docs/walking.md).

The HIL simulator with the walking rig (``plant.contact: true``) and the IPC service on
one in-process bus (:class:`~wara.harness.Harness`), the walk asked for as ``wara ctl
walk`` asks for it, and each step judged against the goals from the service's figures
and the simulator's truth (distance, the workpiece's attitude during each transfer, the
feet's forces at the end).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from config import load_project, units
from config.hil_scenario import HilScenario, PlantSettings
from config.schema import ProjectConfig
from ipc_app.control.walk import LIFT, LOWER, TRANSFER, TRAVEL, WalkSequencer
from ipc_app.planner.walk import DIRECTIONS
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from ipc_app.service.worker import PlannerWorker
from wara.harness import Harness

#: the goals of a step (walking.md; the issue's)
STEP_LENGTH_TOL_M = 0.005  # each step within the walk's 5 mm too
LEG_SYNC_MM = 2.0
TRAVEL_SYNC_MM = 5.0
ATTITUDE_CHANGE_DEG = 0.01
FORCE_RATIO = 1.10
MIN_MARGIN_M = 0.25
STEP_S = 120.0


@dataclass
class _StepTruth:
    x_m_start: float
    x_m_end: float = 0.0
    attitude_change_deg: float = 0.0


@dataclass
class WalkTrace:
    """Per sample: time, phase index, leg forces (kN, truth), leg and travel rods (mm),
    the service's stability margin."""

    t: list[float] = field(default_factory=list)
    phase: list[int] = field(default_factory=list)
    forces_kn: list[list[float]] = field(default_factory=list)
    x_mm: list[list[float]] = field(default_factory=list)
    margin_m: list[float] = field(default_factory=list)


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
    there and back); the JSON-ready result (``passed``, ``refused``...). The simulated
    machine carries its part, so the walks are loaded (an unloaded walk's statics are
    the service's; the simulator without the part diverges, docs/walking.md).

    ``on_cycle``: called after each sample with the harness (tests: stop, resume).
    ``cfg``: the project as loaded from ``config_path`` (tests: a changed one).
    ``sim_cfg``, ``seed``, ``planner``: the simulated machine when it differs from the
    project, the simulator's seed, a running planner worker to share (a campaign's run;
    :class:`~wara.harness.Harness`)."""
    if cfg is None:
        cfg = load_project(config_path)
    if not directions or any(d not in DIRECTIONS for d in directions):
        raise ValueError(f"directions must be of {', '.join(DIRECTIONS)}, got {directions!r}")
    say = progress or (lambda _s: None)
    h = Harness(
        cfg, config_path, mode=mode, scenario=walk_scenario(scenario), record=record,
        sim_cfg=sim_cfg, seed=seed, planner=planner, trace=False,
    )  # fmt: skip
    trace = WalkTrace()
    truths: list[_StepTruth] = []
    walkers: list[WalkSequencer] = []
    out: dict[str, Any] = {"passed": False, "refused": None, "error": None}
    try:
        h.start()
        if not (h.wait_for(Mode.IDLE, 20.0) and h.wait_walk_ready()):
            out["error"] = f"service did not come up: {h.fault_note()}"
            return _finish(out, h, truths, trace, steps, plot_dir, walkers, directions)
        rig = h.sim.rig
        out["start_x_m"] = round(float(rig.world_x_m[0]), 6)  # type: ignore[attr-defined]
        for direction in directions:
            if walkers and h.core.modes.mode != Mode.COMPLETE:
                break
            res = h.core.request_walk(
                steps, wait_s=5.0 if mode == "realtime" else 0.0,
                direction=direction,
            )  # fmt: skip
            if not res.get("ok"):
                out["refused"] = res.get("refusal") or res.get("error")
                out["error"] = res.get("error")
                break
            seen = _follow(h, steps, mode, say, on_cycle, trace, truths)
            if seen is not None:
                walkers.append(seen)
        return _finish(out, h, truths, trace, steps, plot_dir, walkers, directions)
    finally:
        h.close()


def _follow(
    h: Harness,
    steps: int,
    mode: str,
    say: Callable[[str], None],
    on_cycle: Callable[[Harness], None] | None,
    trace: WalkTrace,
    truths: list[_StepTruth],
) -> WalkSequencer | None:
    """Advance while one walk runs; each step's truth into ``truths``; its sequencer."""
    rig = h.sim.rig
    dt = h.period if mode == "lockstep" else 0.05
    limit_s = steps * STEP_S * 1.5
    waited = 0.0
    att0: tuple[float, float] | None = None
    last_phase = -1
    seen = h.core.walker
    first = len(truths)
    while waited < limit_s:
        h.advance(dt)
        waited += dt
        core = h.core
        w = core.walker
        if on_cycle is not None:
            on_cycle(h)
        if w is not None:
            seen = w
        if w is None or w.run is None:
            if core.modes.mode != Mode.EXECUTE:
                break
            continue
        k = w.run.index
        ph = w.run.phase
        x_m = rig.world_x_m[0]  # type: ignore[attr-defined]
        if k != last_phase:
            if last_phase < 0 or ph.step != w.plan.phases[last_phase].step:
                if len(truths) > first:
                    truths[-1].x_m_end = x_m
                truths.append(_StepTruth(x_m))
                say(f"step {ph.step} {w.plan.direction}")
            last_phase = k
            att0 = rig.workpiece_attitude_rad() if ph.key in TRANSFER else None
        if att0 is not None and ph.key in TRANSFER:
            r, pch = rig.workpiece_attitude_rad()
            change = units.to_deg(max(abs(r - att0[0]), abs(pch - att0[1])))
            truths[-1].attitude_change_deg = max(truths[-1].attitude_change_deg, change)
        if (mode == "lockstep" and h._k % 10 == 0) or mode == "realtime":
            trace.t.append(h.sim.t_s)
            trace.phase.append(k)
            trace.forces_kn.append((rig.foot_forces_n / units.KN).tolist())  # type: ignore[attr-defined]
            legs = w.legs + w.travel
            trace.x_mm.append((rig.rod_positions_m[legs] * units.to_mm(1.0)).tolist())
            fm = w.figures.margin_m
            trace.margin_m.append(fm if np.isfinite(fm) else np.nan)
        if w.done or core.modes.mode not in (Mode.EXECUTE, Mode.HELD, Mode.SUSPENDED):
            break  # done, or ended otherwise (ridden through a suspension)
    if len(truths) > first and truths[-1].x_m_end == 0.0:
        truths[-1].x_m_end = rig.world_x_m[0]  # type: ignore[attr-defined]
    return seen


def _finish(
    out: dict[str, Any],
    h: Harness,
    truths: list[_StepTruth],
    trace: WalkTrace,
    steps: int,
    plot_dir: Path | None,
    walkers: list[WalkSequencer],
    directions: tuple[str, ...],
) -> dict[str, Any]:
    core = h.core
    rig = h.sim.rig
    out["final_mode"] = str(core.modes.mode)
    out["fault_reasons"] = list(core.modes.fault_reasons)
    out["directions"] = list(directions)
    rows: list[dict[str, Any]] = []
    for w in walkers:
        sign = -1.0 if w.plan.direction == "back" else 1.0
        for fig in (s.to_dict() for s in w.steps):
            k = len(rows)
            tr = truths[k] if k < len(truths) else None
            row = {"direction": w.plan.direction, **fig}
            row["distance_m"] = round(tr.x_m_end - tr.x_m_start, 6) if tr else 0.0
            row["max_transfer_attitude_change_deg"] = (
                round(tr.attitude_change_deg, 6) if tr else 0.0
            )
            complete = fig["duration_s"] > 0
            row["passed"] = bool(
                complete
                and abs(row["distance_m"] - sign * w.plan.step_length_m) <= STEP_LENGTH_TOL_M
                and row["max_leg_sync_error_mm"] <= LEG_SYNC_MM
                and row["max_travel_sync_error_mm"] <= TRAVEL_SYNC_MM
                and row["max_transfer_attitude_change_deg"] <= ATTITUDE_CHANGE_DEG
                and row["max_leg_force_ratio"] <= FORCE_RATIO
                and row["min_stability_margin_m"] >= MIN_MARGIN_M
                and row["duration_s"] <= STEP_S
            )
            rows.append(row)
    x0 = truths[0].x_m_start if truths else 0.0
    x1 = truths[-1].x_m_end if truths else 0.0
    out["distance_m"] = round(x1 - x0, 6)
    out["steps"] = rows
    ids = getattr(rig, "leg_ids", ())
    forces = getattr(rig, "foot_forces_n", np.zeros(len(ids)))
    out["leg_forces_kn"] = {
        cid: round(float(f) / units.KN, 2) for cid, f in zip(ids, forces, strict=True)
    }
    out["bus_load_percent"] = round(core.bus_load.load_percent, 2)
    out["simulator_realtime_factor"] = h.sim.realtime_factor
    out["sim_time_s"] = round(h.sim.t_s, 3)
    step_m = walkers[0].plan.step_length_m if walkers else 2.0
    want = sum(-1.0 if d == "back" else 1.0 for d in directions) * steps * step_m
    out["passed"] = bool(
        out["error"] is None
        and len(rows) == steps * len(directions)
        and all(r["passed"] for r in rows)
        and abs(out["distance_m"] - want) <= 0.005
        and out["final_mode"] == str(Mode.COMPLETE)
    )
    out["goals"] = {
        "distance_tolerance_mm": 5.0,
        "leg_sync_mm": LEG_SYNC_MM,
        "travel_sync_mm": TRAVEL_SYNC_MM,
        "transfer_attitude_change_deg": ATTITUDE_CHANGE_DEG,
        "max_leg_force_ratio": FORCE_RATIO,
        "min_stability_margin_m": MIN_MARGIN_M,
        "step_duration_s": STEP_S,
    }
    if plot_dir is not None and trace.t:
        leg_ids = walkers[-1].leg_ids if walkers else ()
        out["plots"] = [str(plot_walk(trace, leg_ids, plot_dir))]
    return out


def plot_walk(trace: WalkTrace, leg_ids: tuple[str, ...], out_dir: Path) -> Path:
    """Leg forces, leg and travel positions, the stability margin and the phase (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.asarray(trace.t)
    fig, ax = plt.subplots(4, 1, figsize=(11, 12), sharex=True)
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
    ax[2].axhline(MIN_MARGIN_M, color="r", ls="--")
    ax[2].set_ylabel("stability margin m")
    ax[3].plot(t, trace.phase, drawstyle="steps-post")
    ax[3].set_ylabel("phase (index)")
    ax[3].set_xlabel("machine time s")
    path = out_dir / "walk.png"
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path


__all__ = ["LIFT", "LOWER", "TRAVEL", "run_walk", "walk_scenario"]
