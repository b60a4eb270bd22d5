"""The step sequencer of the walk (walking.md sections 2 and 4, docs/walking.md).

It runs the phases of a :class:`~ipc_app.planner.walk.WalkPlan` one after another on
the service's read -> update -> write step: :meth:`WalkSequencer.update` takes one
cycle's rod positions and chamber pressures and returns the spool commands of all 19
cylinders and the cycle's :class:`WalkFigures`, which the walk interlocks
(:mod:`ipc_app.service.walk_interlocks`) judge.

Control (the choices are in docs/walking.md, "The step sequencer"):

- **Position control with synchronization** for the legs that lift or lower and for the
  travel pair: one LADRC per rod (``control.ladrc``, the attitude loops' tuning and
  feed-forward), coupled in their group by the dual-error feedback of
  :class:`~ipc_app.control.sync.SyncGroup`. The phase's reference clock stops while the
  group is out of its sync band (``walking.leg_sync_band_mm`` /
  ``travel_sync_band_mm``) and goes on once it is back inside (hold and continue).
- **Force (pressure) control** for the legs in preload and transfer: the same LADRC on
  the cap-side force ``p_A A_A - p_B A_B``, its reference ramped at
  ``walking.force_ramp_kn_s``; ``b0`` is the position ``b0`` times the leg's stiffness
  against the invert (oil column in series with the contact), bandwidths
  ``walking.force_wc_rad_s`` and ``force_wo_rad_s``.
- **The attitude held during transfer**: the releasing frame's legs stay in position
  control; each reference follows its foot's unloading as the plan releases it
  (``+ (F_plan - F_0) / k_contact``, ``F_plan`` the force at the release rate the body's
  equilibrium gives with the receiving legs' ramp: the foot rises by what its contact
  decompresses), so the body keeps its height at those legs while the receiving legs'
  forces ramp up.
- Every other walk cylinder holds its position: in the active group (the phase's moving
  and standing legs, the travel pair while it moves) with its group's LADRC; outside it
  (frames at the slow cycle) with a slow proportional hold (:attr:`WalkSequencer.SLOW_HOLD_RAD_S`).

Work per cycle is bounded: one reference sample per moving group, at most 14 controller
updates and one stability margin (a hull of at most eight points).

Over 500 lines because the phases' position, force and transfer control share one
sequencer's state (the groups, the touch-down baselines, the force references), which
the interlocks read each cycle; the plan and its statics are in
:mod:`ipc_app.planner.walk`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from config import units
from config.derived import hydraulic_stiffness_n_m, viscous_damping_n_s_m
from config.schema import ProjectConfig
from ipc_app.control.ladrc import LADRC
from ipc_app.control.plant_gain import cylinder_b0
from ipc_app.control.sync import sync_errors
from ipc_app.model.kinematics import fit_layer
from ipc_app.model.support import (
    WalkingMachine,
    cap_side_forces_n,
    cog_projection,
    stability_margin,
    support_forces,
)
from ipc_app.planner.walk import Move, Phase, WalkPlan

FloatArray = NDArray[np.float64]

#: phases by what they do
TRAVEL = frozenset({"1", "6"})
LOWER = frozenset({"2", "7a"})
PRELOAD = frozenset({"3", "7b"})
TRANSFER = frozenset({"4", "7c"})
LIFT = frozenset({"5", "8"})
MAIN = (0, 1, 2, 3)
SUB = (4, 5, 6, 7)


def transfer_frames(key: str) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """A preload's or transfer's (receiving, releasing) frames: S takes the load in 3
    and 4, M in 7b and 7c."""
    return (SUB, MAIN) if key in ("3", "4") else (MAIN, SUB)


def walk_active_group(cfg: ProjectConfig, key: str) -> list[int]:
    """``can_index`` of the cylinders whose frames run at the loop rate in phase ``key``
    (the active group changes with the phase): while the travel pair moves, it and the
    standing frame's legs; in every other phase the eight legs. The rest (the hanging
    frame while the pair moves, the upper platform) run at their slow cycle and are held
    by :attr:`WalkSequencer.SLOW_HOLD_RAD_S`."""
    main = [cfg.cylinder(c).can_index for c in cfg.layers.lower.cylinders]
    sub = sorted((c for c in cfg.cylinders if c.role == "sub_leg"), key=lambda c: c.position or 0)
    sub_idx = [c.can_index for c in sub]
    travel = [c.can_index for c in cfg.cylinders_by_can_index if c.role == "travel"]
    if key in TRAVEL:
        return travel + (main if key == "1" else sub_idx)
    return main + sub_idx


@dataclass
class WalkFigures:
    """One cycle of the walk, what the walk interlocks judge (SI units)."""

    step: int = 0
    phase: str = ""
    #: the phase's reference clock (stops while a group is out of its band)
    phase_t_s: float = 0.0
    leg_force_n: tuple[float, ...] = ()
    #: expected force of each leg now (the plan's, at least its eight-leg share)
    expected_n: tuple[float, ...] = ()
    #: largest |sync error| of the moving leg group / the travel pair (0: not moving)
    leg_sync_m: float = 0.0
    travel_sync_m: float = 0.0
    #: the group out of its band now, and for how long
    out_of_band: str = ""
    out_of_band_s: float = 0.0
    margin_m: float = math.inf
    #: least margin along the present phase's commanded motion (checked at its start)
    margin_ahead_m: float = math.inf
    travel_force_n: float = 0.0
    friction_capacity_n: float = math.inf
    #: a leg whose lowering ended without a touch-down (its id), else ""
    no_touchdown: str = ""
    #: a lowering leg whose foot met the invert above the touch-down window (in the fast
    #: part of its lowering: more than ``touchdown_travel_mm`` above the expected ground):
    #: its id and its height above the expected ground then, m; else ("", 0.0)
    obstacle: tuple[str, float] = ("", 0.0)
    #: preload/transfer still not done after this long (0 while in time)
    overdue_s: float = 0.0
    #: the worst receiving leg's share at a transfer's end (id, ratio), else ("", 1.0)
    share_off: tuple[str, float] = ("", 1.0)


@dataclass
class StepFigures:
    """The service's figures of one step (for ``wara walk`` and the run record)."""

    index: int
    started_s: float = 0.0
    duration_s: float = 0.0
    max_leg_sync_error_m: float = 0.0
    max_travel_sync_error_m: float = 0.0
    min_stability_margin_m: float = math.inf
    max_leg_force_ratio: float = 0.0
    transfer_time_s: float = 0.0

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "duration_s": round(self.duration_s, 3),
            "max_leg_sync_error_mm": round(units.to_mm(self.max_leg_sync_error_m), 4),
            "max_travel_sync_error_mm": round(units.to_mm(self.max_travel_sync_error_m), 4),
            "min_stability_margin_m": round(self.min_stability_margin_m, 4),
            "max_leg_force_ratio": round(self.max_leg_force_ratio, 4),
            "transfer_time_s": round(self.transfer_time_s, 3),
        }


@dataclass
class _PhaseRun:
    """The present phase as it runs."""

    index: int
    phase: Phase
    t0: float  #: machine time it started
    tau: float = 0.0  #: its reference clock
    start_x: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: a travel phase's move of the pair (from ``start_x``), made at its first cycle
    travel_move: Move | None = None
    start_f: FloatArray = field(default_factory=lambda: np.zeros(0))
    target_f: FloatArray = field(default_factory=lambda: np.zeros(0))
    duration_s: float = 0.0
    touched: list[bool] = field(default_factory=list)
    baseline_pa: list[float] = field(default_factory=list)
    #: the lowering is in its slow part (touch-down looked for)
    near: bool = False
    frozen_x: list[float] = field(default_factory=list)
    touch_f: list[float] = field(default_factory=list)
    band_since: float | None = None
    standing_share_n: FloatArray = field(default_factory=lambda: np.zeros(8))
    #: each leg's oil-column stiffness at its rod's position at the phase's start, N/m
    k_oil_n_m: FloatArray = field(default_factory=lambda: np.full(8, math.inf))
    #: a preload's or transfer's releasing legs: their force rate while the receiving
    #: legs ramp, N/s
    release_rate_n_s: FloatArray = field(default_factory=lambda: np.zeros(8))
    #: a preload's or transfer's releasing legs' forces where their rates start (the
    #: phase's start; after a resume, the forces then), N
    release_from_f: FloatArray = field(default_factory=lambda: np.zeros(8))
    #: a transfer's plan line starts here (the plan's preload; after a resume, where
    #: the line stood at the stop) and runs to ``target_f`` with the ramp, N
    plan_start_f: FloatArray = field(default_factory=lambda: np.zeros(8))


class WalkSequencer:
    """Runs a walk plan on the machine; see the module docstring."""

    #: slow hold of a walk cylinder outside the active group: command = gain * error / b0
    SLOW_HOLD_RAD_S = 1.0
    #: a position move ends when every moving rod is this close to its end reference
    END_TOLERANCE_M = 1e-4
    #: time constant of the low-pass that follows a lowering rod's free cap pressure, s
    FREE_ROD_S = 0.25
    #: preload ends with every preloaded leg within this fraction of its target
    PRELOAD_TOLERANCE = 0.10
    #: a lowering rod's speed is taken over this window (the pressures' 50 ms cycle), s
    MOTION_WINDOW_S = 0.05
    #: in the slow part of a lowering, the free rod's pressure follows while within this
    #: fraction of the touch rise above its baseline
    FREE_BAND = 0.1
    #: in the fast part of a lowering, a leg's force on the body above this fraction of
    #: its touch force (``walking.touch_mpa`` over its cap area) is a foot pressing the
    #: invert: it enters the body's equilibrium (:meth:`contact_n`); above the touch
    #: force itself it is an obstacle (the touch-down interlock)
    PRESSING = 0.25
    #: a rod's Coulomb friction is taken full above this speed, linear below, m/s: near
    #: standstill its sign is not known (the speed over :attr:`MOTION_WINDOW_S` of 1 um
    #: positions, a rod stopping or reversing within the window; the rig's friction is
    #: smooth over some 0.3-0.5 mm/s, docs/hil.md); with 0.1 mm/s the estimate of a
    #: standing leg's force swung by the whole 2 kN as its measured speed crossed zero
    COULOMB_SPEED_M_S = 5e-4
    #: the transfers whose releasing loops are told their oil columns' decompression
    DECOMPRESSION_FEEDFORWARD = frozenset({"7c"})

    def __init__(self, cfg: ProjectConfig, period_s: float, plan: WalkPlan) -> None:
        if cfg.walking is None or cfg.frames is None:
            raise ValueError("the project has no frames and walking sections: it cannot walk")
        self.cfg = cfg
        self.walk = cfg.walking
        self.period_s = period_s
        self.plan = plan
        self.n = len(cfg.cylinders)
        self.leg_ids = plan.leg_ids
        self.legs = [cfg.cylinder(c).can_index for c in self.leg_ids]
        travel = [c for c in cfg.cylinders_by_can_index if c.role == "travel"]
        self.travel = [c.can_index for c in travel]
        self.upper = [cfg.cylinder(c).can_index for c in cfg.layers.upper.cylinders]
        self.walk_cylinders = self.legs + self.travel + self.upper
        by_index = cfg.cylinders_by_can_index
        self.half = np.array([c.stroke_m / 2 for c in by_index])
        self.e0 = travel[0].stroke_m / 2
        self.cap = np.array([c.cap_area_m2 for c in by_index])
        self.rod = np.array([c.rod_area_m2 for c in by_index])
        ctl = cfg.control
        self.b0 = np.zeros(self.n)
        self.pos: dict[int, LADRC] = {}
        for i in self.walk_cylinders:
            cyl = by_index[i]
            self.b0[i] = cylinder_b0(cyl, cfg.hydraulics, order=ctl.ladrc.order)
            self.pos[i] = LADRC.from_config(ctl.ladrc, float(self.b0[i]), period_s)
        self.k_contact = self.walk.contact.stiffness_n_m
        #: each leg's rod friction (its plant's): Coulomb, N, and viscous, N s/m
        plants = [(by_index[i], cfg.plant_of(by_index[i])) for i in self.legs]
        self.coulomb_n = np.array([pl.coulomb_friction_n for _c, pl in plants])
        self.viscous_n_s_m = np.array(
            [viscous_damping_n_s_m(c, pl, cfg.hydraulics) for c, pl in plants]
        )
        self._friction = list(
            zip(self.coulomb_n.tolist(), self.viscous_n_s_m.tolist(), strict=True)
        )
        self.force: dict[int, LADRC] = {}
        for i in self.legs:
            cyl = by_index[i]
            k_h = hydraulic_stiffness_n_m(cyl, cfg.plant_of(cyl), cfg.hydraulics)
            k = 1.0 / (1.0 / k_h + 1.0 / self.k_contact)
            b0 = cylinder_b0(cyl, cfg.hydraulics, order=1) * k
            self.force[i] = LADRC(
                1, b0, self.walk.force_wc_rad_s, self.walk.force_wo_rad_s, period_s,
                rate_limit=ctl.ladrc.rate_limit_per_s,
            )  # fmt: skip
        self.feedforward = ctl.ladrc.reference_feedforward
        self.lam = ctl.sync.coupling_lambda
        self.scheme = ctl.sync.scheme
        self.leg_band = units.mm(self.walk.leg_sync_band_mm)
        self.travel_band = units.mm(self.walk.travel_sync_band_mm)
        self.touch_pa = units.mpa(self.walk.touch_mpa)
        #: a leg's cap-side force above this is a foot touching (walking.touch_mpa), N
        self._touch_n = [float(v) for v in self.touch_pa * self.cap[self.legs]]
        self.td_travel = units.mm(self.walk.touchdown_travel_mm)
        self.td_speed = units.mm(self.walk.touchdown_speed_mm_s)
        traj = cfg.planner.trajectory
        self.leg_v, self.leg_a = traj.max_rod_speed_m_s, traj.max_rod_accel_m_s2
        self.machine = WalkingMachine(cfg, unloaded=plan.unloaded, standing=plan.standing)
        self.point_cache: dict[int, tuple[float, FloatArray]] = {}
        #: the parts of :meth:`_residual_share` that stay while S and the legs held do
        self._residual_parts: tuple[Any, ...] | None = None
        self.hold_ref = np.zeros(self.n)
        self.force_mode: set[int] = set()
        self.run: _PhaseRun | None = None
        self.done = False
        self.steps: list[StepFigures] = []
        self.figures = WalkFigures()
        self.last_refs = np.zeros(self.n)
        #: (machine time, step, phase) of each phase start, for the run record
        self.phase_log: list[tuple[float, int, str]] = []
        self.leg_force_n = np.zeros(8)
        #: force references of the legs in force control this cycle (NaN: not), N
        self.force_ref_n = np.full(8, math.nan)
        #: the twist-mode controller of a standing frame: a force loop on its legs'
        #: twist, the mode's share of their valve commands (:meth:`_twist_control`)
        b0_f = float(np.mean([self.force[self.legs[j]].b0 for j in SUB]))
        self.twist = LADRC(
            1, b0_f, self.walk.twist_bandwidth_rad_s, self.walk.twist_observer_rad_s, period_s,
            rate_limit=ctl.ladrc.rate_limit_per_s,
        )  # fmt: skip
        self._twist_frame_now: tuple[int, ...] = ()
        self._twist_started = False
        #: each leg's last two pressure samples: cap-side force, N, and sample time, s
        self._f_last = [0.0] * 8
        self._f_prev = [0.0] * 8
        self._t_last = [-math.inf] * 8
        self._t_prev = [-math.inf] * 8
        #: the legs' last rod positions over :attr:`MOTION_WINDOW_S` (a ring), m, and
        #: the machine time of each row, s
        self._x_hist = np.zeros((max(2, round(self.MOTION_WINDOW_S / period_s) + 1), 8))
        self._t_hist = [0.0] * self._x_hist.shape[0]
        self._x_k = 0

    # ----------------------------------------------------------------- helpers

    def forces_n(self, p: FloatArray) -> FloatArray:
        """Cap-side force of each leg (8,), N: ``p_A A_A - p_B A_B``."""
        idx = self.legs
        return cap_side_forces_n(p[idx], self.cap[idx], self.rod[idx])

    def x_s(self, x: FloatArray) -> float:
        """S's position along the rails, measured: the travel pair's mean less ``e_0``
        (summed in order and divided, as ``np.mean`` of so few values does)."""
        total = 0.0
        for i in self.travel:
            total += float(x[i])
        return total / len(self.travel) - self.e0

    def set_upper(self, x: FloatArray) -> None:
        """The upper platform's attitude fixes the workpiece's COG: from its rods."""
        up = self.cfg.layers.upper
        fit = fit_layer(x[self.upper] - self.half[self.upper], up.a_m, up.b_m)
        self.machine = WalkingMachine(
            self.cfg, float(fit.roll), float(fit.pitch), self.plan.unloaded, self.plan.standing
        )
        self._residual_parts = None

    def share(self, x_s: float, legs: tuple[int, ...]) -> FloatArray:
        """Expected forces (8,) with ``legs`` standing (minimum norm), N."""
        out = np.zeros(8)
        pts = self.machine.legs_xy(x_s)[list(legs)]
        out[list(legs)] = support_forces(
            pts, self.machine.mass_kg, self.machine.cog(x_s), self.machine.g_base
        )
        return out

    def margin(self, x_s: float, legs: tuple[int, ...]) -> float:
        point = cog_projection(self.machine.cog(x_s), self.machine.g_base)
        return stability_margin(self.machine.legs_xy(x_s)[list(legs)], point)

    def active_group(self) -> list[int]:
        """The present phase's active group (:func:`walk_active_group`)."""
        key = self.run.phase.key if self.run is not None else self.plan.phases[0].key
        return walk_active_group(self.cfg, key)

    @staticmethod
    def _frame(ids: tuple[str, ...], leg_ids: tuple[str, ...]) -> tuple[int, ...]:
        return tuple(leg_ids.index(c) for c in ids if c in leg_ids)

    # ----------------------------------------------------------------- phases

    def start(self, now: float, x: FloatArray, p: FloatArray) -> None:
        """Engage at the measured state: every walk cylinder holds, the first phase starts."""
        self.set_upper(x)
        self.hold_ref = np.array(x, dtype=float)
        self._x_hist[:] = x[self.legs]
        self._t_hist = [now] * len(self._t_hist)
        for i, c in self.pos.items():
            c.reset(float(x[i]))
        self._begin(0, now, x, p)

    def _begin(self, k: int, now: float, x: FloatArray, p: FloatArray) -> None:
        ph = self.plan.phases[k]
        f = self.forces_n(p)
        for i in self.legs + self.travel:
            self.hold_ref[i] = float(x[i])
        self.point_cache.clear()
        run = _PhaseRun(k, ph, now, start_x=np.array(x, dtype=float), start_f=f)
        key = ph.key
        x_s = self.x_s(x)
        if k == 0 or ph.step != self.plan.phases[k - 1].step:
            self.steps.append(StepFigures(ph.step, started_s=now))
        self.phase_log.append((now, ph.step, key))
        if key in TRAVEL:
            run.duration_s = Move(ph.end_m[0] - x_s, *self._travel_move()).duration_s
        elif key in LOWER:
            fast = Move(self.walk.clearance_m - self.td_travel, self.leg_v, self.leg_a)
            run.duration_s = fast.duration_s + 2 * self.td_travel / self.td_speed
            frame = MAIN if key == "7a" else SUB
            run.touched = [False] * 4
            run.baseline_pa = [float(p[self.legs[j], 0]) for j in frame]
            run.frozen_x = [0.0] * 4
            run.touch_f = [0.0] * 4
        elif key in LIFT:
            run.duration_s = Move(-self.walk.clearance_m, self.leg_v, self.leg_a).duration_s
        else:
            receiving, releasing = transfer_frames(key)
            # what the standing frame's legs carry alone (the overload's floor for them)
            run.standing_share_n = self.share(x_s, releasing)
            if key in PRELOAD:
                target = ph.leg_forces_n[-1].copy()
            else:
                target = self.share(x_s, receiving)
                for j in releasing:
                    cyl = self.cfg.cylinders_by_can_index[self.legs[j]]
                    run.k_oil_n_m[j] = hydraulic_stiffness_n_m(
                        cyl, self.cfg.plant_of(cyl), self.cfg.hydraulics, float(x[self.legs[j]])
                    )
            run.target_f = target
            delta = max(abs(float(target[j] - f[j])) for j in receiving)
            run.duration_s = delta / self.walk.force_ramp_n_s
            if key in TRANSFER:
                run.plan_start_f = ph.leg_forces_n[0].copy()
            self._set_release_rate(run, x_s, f)
            for j in receiving:
                i = self.legs[j]
                if i not in self.force_mode:
                    self.force_mode.add(i)
                    self.force[i].reset(float(f[j]), self.pos[i].command)
            for j in releasing:
                i = self.legs[j]
                if i in self.force_mode:  # bumpless back to position control
                    self.force_mode.discard(i)
                    self.pos[i].reset(float(x[i]), self.force[i].command)
                    self.hold_ref[i] = float(x[i])
        if key in TRAVEL or key in LOWER or key in LIFT:
            for i in list(self.force_mode):  # every leg back in position control
                self.force_mode.discard(i)
                self.pos[i].reset(float(x[i]), self.force[i].command)
                self.hold_ref[i] = float(x[i])
        self.run = run
        self.figures.margin_ahead_m = self._margin_ahead(ph, x_s)

    def _travel_move(self) -> tuple[float, float]:
        return self.walk.travel_speed_m_s, self.walk.travel_accel_m_s2

    def _margin_ahead(self, ph: Phase, x_s: float) -> float:
        """The least margin along the phase's commanded motion, from the measured start,
        with the legs that stand during it (after it, for a lift)."""
        standing = self._frame(ph.standing, self.leg_ids)
        if ph.key in TRAVEL:
            xs = np.linspace(x_s, ph.end_m[0], 21)
            return min(self.margin(float(v), standing) for v in xs)
        return self.margin(x_s, standing)

    def _next(self, now: float, x: FloatArray, p: FloatArray) -> None:
        run = self.run
        assert run is not None
        step = self.steps[-1]
        if run.phase.key in TRANSFER:
            step.transfer_time_s += now - run.t0
        k = run.index + 1
        if k < len(self.plan.phases) and self.plan.phases[k].step == run.phase.step:
            self._begin(k, now, x, p)
            return
        step.duration_s = now - step.started_s
        if k < len(self.plan.phases):
            self._begin(k, now, x, p)
        else:
            self.done = True
            self.hold_ref = np.array(x, dtype=float)

    def resume(self, x: FloatArray, p: FloatArray) -> None:
        """Go on after a stop: every controller bumpless at the measurement; the phase
        goes on from its reference clock, a preload's or transfer's force ramp from the
        receiving legs' forces now."""
        f = self.forces_n(p)
        for i, c in self.pos.items():
            c.reset(float(x[i]))
        self._twist_started = False  # the twist loop too, at the forces now
        for j, i in enumerate(self.legs):
            if i in self.force_mode:
                self.force[i].reset(float(f[j]))
        run = self.run
        if run is not None and (run.phase.key in PRELOAD or run.phase.key in TRANSFER):
            # the receiving legs' ramp restarts from their forces now (while stopped they
            # held what they had, the ramp's reference stood where the clock stopped;
            # a loop reset at the one and driven to the other takes the step at once)
            receiving, _ = transfer_frames(run.phase.key)
            if run.phase.key in TRANSFER:  # the plan's line goes on from where it stood
                lam = 1.0 if run.duration_s <= 0 else min(1.0, run.tau / run.duration_s)
                run.plan_start_f = run.plan_start_f + lam * (run.target_f - run.plan_start_f)
            for j in receiving:
                run.start_f[j] = f[j]
            delta = max(abs(float(run.target_f[j] - f[j])) for j in receiving)
            run.tau, run.duration_s = 0.0, delta / self.walk.force_ramp_n_s
            self._set_release_rate(run, self.x_s(x), f)

    # ----------------------------------------------------------------- the cycle

    def update(
        self,
        now: float,
        x: FloatArray,
        p: FloatArray,
        active: set[int],
        p_age_s: FloatArray | None = None,
    ) -> FloatArray:
        """Spool commands (19) for this cycle; :attr:`figures` is this cycle's.

        ``p_age_s``: the age of each cylinder's pressure sample (19,), s; the checks' leg
        forces are taken at one instant from it (:meth:`aligned_forces_n`). None: every
        sample is taken as of ``now``."""
        u = np.zeros(self.n)
        refs = self.hold_ref.copy()
        rates = np.zeros(self.n)
        f = self.forces_n(p)
        self.leg_force_n = f
        self._x_hist[self._x_k % self._x_hist.shape[0]] = x[self.legs]
        self._t_hist[self._x_k % self._x_hist.shape[0]] = now
        self._x_k += 1
        # the checks' forces: at one instant, less each rod's friction (what the legs
        # put on the body, the statics' terms)
        f_aligned = self.aligned_forces_n(now, f, p_age_s)
        f_check = f_aligned - self.friction_n()
        fig = self.figures
        run = self.run
        if run is None or self.done:
            self._hold(u, refs, rates, x, active)
            self.last_refs = refs
            return u
        ph = run.phase
        key = ph.key
        dt = self.period_s
        fig.step, fig.phase = ph.step, key
        fig.leg_sync_m = fig.travel_sync_m = 0.0
        fig.no_touchdown, fig.overdue_s, fig.share_off = "", 0.0, ("", 1.0)
        fig.obstacle = ("", 0.0)
        f_ref: dict[int, tuple[float, float]] = {}
        known: dict[int, float] = {}
        moving: list[int] = []
        finished = False
        progress = 1.0 if run.duration_s <= 0 else min(1.0, run.tau / run.duration_s)
        kk = progress * (len(ph.leg_forces_n) - 1)
        k0 = int(kk)
        k1 = min(k0 + 1, len(ph.leg_forces_n) - 1)
        plan_f = ph.leg_forces_n[k0] * (1 - (kk - k0)) + ph.leg_forces_n[k1] * (kk - k0)
        if key in TRAVEL:
            move = run.travel_move
            if move is None:  # from the phase's start to its end: the same every cycle
                move = run.travel_move = Move(
                    ph.end_m[0] - (float(np.mean(run.start_x[self.travel])) - self.e0),
                    *self._travel_move(),
                )
            s = move.position_at(run.tau)
            s1 = move.position_at(run.tau + dt)
            for i in self.travel:
                refs[i] = run.start_x[i] + s
                rates[i] = (s1 - s) / dt if self.feedforward else 0.0
            moving = list(self.travel)
            band = self.travel_band
            finished = run.tau >= run.duration_s and all(
                abs(x[i] - refs[i]) <= self.END_TOLERANCE_M for i in self.travel
            )
        elif key in LOWER or key in LIFT:
            frame = MAIN if key in ("5", "7a") else SUB
            sign = 1.0
            if key in LOWER:
                s, v = self._lowering(run.tau)
            else:
                move = Move(-self.walk.clearance_m, self.leg_v, self.leg_a)
                s = move.position_at(run.tau)
                s1 = move.position_at(run.tau + dt)
                v = (s1 - s) / dt
            for k, j in enumerate(frame):
                i = self.legs[j]
                if key in LOWER and run.touched[k]:  # touched: it holds its touch force
                    f_ref[i] = (run.touch_f[k], 0.0)
                    continue
                refs[i] = run.start_x[i] + sign * s
                rates[i] = v if self.feedforward else 0.0
                moving.append(i)
            band = self.leg_band
            if key in LOWER:
                # touch-down is looked for from touchdown_travel above the expected ground
                near = s >= self.walk.clearance_m - self.td_travel - 1e-9
                run.near = near
                for k, j in enumerate(frame):
                    i = self.legs[j]
                    if run.touched[k]:
                        continue
                    pa = float(p[i, 0])
                    # a foot on the invert above the window (an obstacle, or the ground
                    # higher than expected by more than the window), judged on its force
                    # on the body, not the cap pressure's rise (a free rod lowering fast
                    # needs some 1.6 MPa more cap pressure than at rest, the touch rise
                    # is 1 MPa): it stops as at a touch-down, and the touch-down
                    # interlock stops the walk
                    obstacle = not near and float(f_check[j]) > self._touch_n[j]
                    if obstacle:
                        height = self.walk.clearance_m - float(x[i] - run.start_x[i])
                        fig.obstacle = (self.leg_ids[j], height)
                    if obstacle or (near and pa - run.baseline_pa[k] > self.touch_pa):
                        run.touched[k] = True
                        run.frozen_x[k] = float(x[i])
                        run.touch_f[k] = float(f[j])
                        # then it stops: force control from here, at rest (its valve
                        # closed; a stiff foot held in position would keep what the
                        # position loop's overshoot pressed into it, and started from
                        # the lowering's command it would go on pressing the invert for
                        # the loop's time constant: seen, twice the touch force)
                        self.force_mode.add(i)
                        self.force[i].reset(float(f[j]), 0.0)
                        f_ref[i] = (run.touch_f[k], 0.0)
                        if i in moving:
                            moving.remove(i)
                    elif pa - run.baseline_pa[k] <= 0.5 * self.touch_pa:
                        # the free rod's pressure, low-passed while it moves; a sample more
                        # than half the touch rise above it is the foot pressing the
                        # invert, not the free motion: the value holds
                        # in the slow part it holds sooner: a foot pressing by a tenth of
                        # the touch rise is not free any more (followed up to half of it,
                        # the baseline rose with a fast press and the touch-down came late)
                        a = dt / self.FREE_ROD_S
                        if not near or pa - run.baseline_pa[k] <= self.FREE_BAND * self.touch_pa:
                            run.baseline_pa[k] += (pa - run.baseline_pa[k]) * a
                finished = all(run.touched)
                if not finished and run.tau >= run.duration_s:
                    j = frame[run.touched.index(False)]
                    fig.no_touchdown = self.leg_ids[j]
            else:
                finished = run.tau >= run.duration_s and all(
                    abs(x[self.legs[j]] - refs[self.legs[j]]) <= self.END_TOLERANCE_M for j in frame
                )
        else:
            receiving, releasing = transfer_frames(key)
            lam = 1.0 if run.duration_s <= 0 else min(1.0, run.tau / run.duration_s)
            for j in receiving:
                i = self.legs[j]
                f0, f1 = float(run.start_f[j]), float(run.target_f[j])
                rate = 0.0 if lam >= 1.0 else (f1 - f0) / run.duration_s
                f_ref[i] = (f0 + lam * (f1 - f0), rate)
            if key in TRANSFER:
                # the plan's force now: its line from the preload to the standing share
                # at the ramp's progress (the plan's samples end short of the share, at
                # the releasing legs' unloaded_percent, and the ramp goes on to it)
                p0 = run.plan_start_f
                for j in receiving:
                    plan_f[j] = p0[j] + lam * (float(run.target_f[j]) - p0[j])
            # the body held: follow the feet's unloading as the plan releases them (their
            # rates from the body's equilibrium, not the measured forces: following those
            # closes a loop through the receiving legs' force loops that rang in the pitch
            # pattern, some 1.2 s a period), not in the twist mode
            rel = list(releasing)
            released_n = run.release_rate_n_s[rel] * min(run.tau, run.duration_s)
            follow = (run.release_from_f[rel] + released_n - run.start_f[rel]) / self.k_contact
            tw = self._TWIST
            follow -= tw * float(tw @ follow) / 4
            # the releasing loops told their oil columns' decompression: in 7c (in phase 4
            # it changed the state M's touch-downs meet in 7a: at 5 mm/s 7b's trip went
            # from 110.26 to 110.75 %)
            on = lam < 1.0 and key in self.DECOMPRESSION_FEEDFORWARD
            f_dot = run.release_rate_n_s[list(releasing)] * (1.0 if on else 0.0)
            follow_rate = f_dot / self.k_contact
            follow_rate -= tw * float(tw @ follow_rate) / 4
            for k, (j, d) in enumerate(zip(releasing, follow, strict=True)):
                i = self.legs[j]
                refs[i] = run.start_x[i] + float(d)
                if self.feedforward:
                    rates[i] = float(follow_rate[k])
                # the rod moves by its oil column's decompression as the leg unloads
                known[i] = -float(f_dot[k]) / float(run.k_oil_n_m[j])
            band = self.leg_band
            tf = run.target_f
            if key in PRELOAD:
                finished = lam >= 1.0 and all(
                    abs(f[j] - tf[j]) <= self.PRELOAD_TOLERANCE * abs(tf[j]) for j in receiving
                )
            else:
                unloaded = self.walk.unloaded_percent / 100.0
                std = run.standing_share_n
                released = all(f[j] < unloaded * std[j] for j in releasing)
                worst = max(receiving, key=lambda j: abs(f[j] / tf[j] - 1.0))
                ratio = float(f[worst] / tf[worst])
                fig.share_off = (self.leg_ids[worst], ratio)
                tol = self.walk.share_tolerance_percent / 100.0
                finished = lam >= 1.0 and released and abs(ratio - 1.0) <= tol
            overdue = now - run.t0 - self.walk.transfer_timeout_s
            fig.overdue_s = max(0.0, overdue)
        twist_frame = self._twist_position(refs, x, self._twist_frame(ph), active)

        # synchronization of the moving group, its band: hold and continue
        sync = 0.0
        if len(moving) >= 2:
            errs = sync_errors([refs[i] - x[i] for i in moving], self.scheme)
            sync = max(abs(e) for e in errs)
            for e, i in zip(errs, moving, strict=True):
                refs[i] += self.lam * e
        if key in TRAVEL:
            fig.travel_sync_m = sync
        elif moving:
            fig.leg_sync_m = sync
        out_of_band = bool(moving) and sync > band
        if out_of_band:
            if run.band_since is None:
                run.band_since = now
            fig.out_of_band = "travel" if key in TRAVEL else "legs"
            fig.out_of_band_s = now - run.band_since
            for i in moving:  # the group holds where it is (no feed-forward)
                rates[i] = 0.0
        else:
            run.band_since = None
            fig.out_of_band, fig.out_of_band_s = "", 0.0
            run.tau += dt

        # commands: force-controlled legs, position-controlled active ones, slow holds
        self.force_ref_n[:] = math.nan
        for i, (fr, rate) in f_ref.items():
            j = self.legs.index(i)
            self.force_ref_n[j] = fr
            u[i] = self.force[i].update(fr, float(f[j]), rate if self.feedforward else 0.0)
            refs[i] = float(x[i])
        self._hold(u, refs, rates, x, active, skip=set(f_ref), known=known)
        self._twist_control(u, f_check, plan_f, twist_frame)

        # the figures of the checks
        x_s = self.x_s(x)
        fl = f.tolist()
        touch = self._touch_n
        touching = tuple(j for j in range(8) if fl[j] > touch[j])
        fig.margin_m = self.margin(x_s, touching) if len(touching) >= 3 else -math.inf
        standing = self._frame(ph.standing, self.leg_ids)
        idx_t = self.travel
        fig.travel_force_n = float(
            np.sum(cap_side_forces_n(p[idx_t], self.cap[idx_t], self.rod[idx_t]))
        )
        capacity = 0  # summed in order, as sum() of the standing legs' forces
        for j in standing:
            capacity += max(0.0, fl[j])
        fig.friction_capacity_n = self.walk.foot_friction_coefficient * float(capacity)
        x_s_now = x_s if key in TRAVEL else float(ph.x_s_m[0])
        share8 = self._share8(x_s_now)
        if key in PRELOAD or key in TRANSFER:
            held = list(transfer_frames(key)[1])
        else:
            held = list(self._frame(ph.standing, self.leg_ids))
        expected = np.maximum(self._residual_share(x_s_now, share8, f_check, plan_f, held), share8)
        if key in PRELOAD or key in TRANSFER:
            # the standing frame's legs shed load to the other frame's preload and then its
            # transfer: a leg is overloaded only above what it carried standing alone; a lag
            # behind the plan's release is the preload and transfer checks' to judge
            expected = np.maximum(expected, run.standing_share_n)
        fig.expected_n = tuple(expected.tolist())
        # judged: a leg in force control its cap-side force (what its loop sets against
        # its reference), any other its force on the body (against its statics' share)
        judged = f_check.copy()
        for j, i in enumerate(self.legs):
            if i in self.force_mode:
                judged[j] = f_aligned[j]
        fig.leg_force_n = tuple(judged.tolist())
        fig.phase_t_s = run.tau
        st = self.steps[-1]
        st.max_leg_sync_error_m = max(st.max_leg_sync_error_m, fig.leg_sync_m)
        st.max_travel_sync_error_m = max(st.max_travel_sync_error_m, fig.travel_sync_m)
        st.min_stability_margin_m = min(st.min_stability_margin_m, fig.margin_m)
        ratio = max(fv / e for fv, e in zip(fig.leg_force_n, fig.expected_n, strict=True))
        st.max_leg_force_ratio = max(st.max_leg_force_ratio, ratio)
        self.last_refs = refs
        if finished:
            self._next(now, x, p)
        return u

    #: the twist mode of four legs at (s_i a, t_i b): legs 1 and 3 against 2 and 4
    _TWIST = np.array((1.0, -1.0, 1.0, -1.0))

    def _twist_frame(self, ph: Phase) -> tuple[int, ...]:
        """The frame whose twist mode is controlled in phase ``ph``: the one that stands
        in position control while the travel pair moves (alone on the invert) or while
        the other frame lowers and preloads; none in a lift or a transfer."""
        key = ph.key
        if key in TRAVEL:
            return self._frame(ph.standing, self.leg_ids)
        if key in LOWER or key in PRELOAD:
            return SUB if key in ("7a", "7b") else MAIN
        return ()

    def _twist_position(
        self, refs: FloatArray, x: FloatArray, frame: tuple[int, ...], active: set[int]
    ) -> tuple[int, ...]:
        """The frame whose twist this cycle's :meth:`_twist_control` sets (``()``: none):
        ``frame`` when its four legs stand in position control in the active group. Its
        position references take the measured rods' twist: its position loops see no
        error in that mode (the twist loop's, in force)."""
        if frame != self._twist_frame_now:
            self._twist_frame_now = frame
            self._twist_started = False
        idx = [self.legs[j] for j in frame]
        if len(frame) != 4 or any(i in self.force_mode or i not in active for i in idx):
            self._twist_started = False
            return ()
        tw = self._TWIST
        refs[idx] += tw * float(tw @ (x[idx] - refs[idx])) / 4
        return frame

    def _twist_control(
        self, u: FloatArray, f: FloatArray, plan_f: FloatArray, frame: tuple[int, ...]
    ) -> None:
        """The twist-mode controller of a frame standing in position control.

        Four legs standing on four feet are statically indeterminate: three of their
        four force patterns (heave, roll, pitch) follow from the body's equilibrium, the
        fourth, the twist (legs 1 and 3 against 2 and 4, ``T = (F1 - F2 + F3 - F4) / 4``,
        self-equilibrated on the rectangle), only from the legs' heights, where the body
        does not move: the oil columns and the feet's contacts in series take all of it
        (30 um of twist in the rods is 6 kN in the feet), and a position loop tuned on the
        free rod has a quarter of its gain there. So the frame's commands are modal: the
        position loops (blind to the twist, :meth:`_twist_position`) set heave, roll and
        pitch, and the twist's share of the four commands is a first-order LADRC on ``T``
        of the legs' forces (``f``, the checks' forces on the body) against the plan's
        (minimum norm: none), with the force loops' ``b0`` (the legs' stiffness in series
        with the contact), crossover ``walking.twist_bandwidth_rad_s`` and observer
        bandwidth ``walking.twist_observer_rad_s`` while the travel pair moves and
        ``walking.twist_observer_touchdown_rad_s`` while the other frame lowers and
        preloads (switched with the state kept). Each position loop's
        observer is told the command applied (:meth:`LADRC.apply`). The state carries
        over from one phase to the next while the same frame stays controlled."""
        if len(frame) != 4:
            return
        key = self.run.phase.key if self.run is not None else self.plan.phases[0].key
        self.twist.set_observer(
            self.walk.twist_observer_rad_s
            if key in TRAVEL
            else self.walk.twist_observer_touchdown_rad_s
        )
        idx = [self.legs[j] for j in frame]
        tw = self._TWIST
        t_now = float(tw @ f[list(frame)]) / 4
        t_ref = float(tw @ plan_f[list(frame)]) / 4
        u_pos = u[idx]
        u_twist_pos = float(tw @ u_pos) / 4
        if not self._twist_started:
            self.twist.reset(t_now, u_twist_pos)
            self._twist_started = True
        u_t = self.twist.update(t_ref, t_now)
        u_all = u_pos + tw * (u_t - u_twist_pos)
        for k, i in enumerate(idx):
            u[i] = self.pos[i].apply(float(u_all[k]))

    def _set_release_rate(self, run: _PhaseRun, x_s: float, f: FloatArray) -> None:
        """A preload's or transfer's releasing legs' force rates (``run.release_rate_n_s``,
        N/s) while the receiving legs' references ramp from ``f`` to ``run.target_f``: the
        body's equilibrium (heave, roll, pitch) with the load constant, minimum norm over
        the releasing legs (no twist); and their forces where the rates start
        (``run.release_from_f``: ``f``), from which their references follow."""
        receiving, releasing = transfer_frames(run.phase.key)
        rec, rel = list(receiving), list(releasing)
        run.release_rate_n_s = np.zeros(8)
        run.release_from_f = np.array(f, dtype=float)
        if run.duration_s <= 0:
            return
        ramp = (run.target_f - f) / run.duration_s
        a = self._equilibrium(x_s)
        run.release_rate_n_s[rel] = -self._min_norm(a, rel, a[:, rec] @ ramp[rec])

    def _equilibrium(self, x_s: float) -> FloatArray:
        """(3, 8): what each leg's vertical force adds to the body's vertical force and
        to its moments about x and y (its position's y and -x)."""
        m = self.machine
        a = np.empty((3, 8))
        a[0] = 1.0
        # WalkingMachine.legs_xy(x_s) written out: S's legs shifted by (x_s, 0)
        a[1, :4] = m.main_legs_xy[:, 1]
        a[1, 4:] = m.sub_legs_xy[:, 1] + 0.0
        a[2, :4] = -m.main_legs_xy[:, 0]
        a[2, 4:] = -(m.sub_legs_xy[:, 0] + x_s)
        return a

    @staticmethod
    def _min_norm(a: FloatArray, legs: list[int], rhs: FloatArray) -> FloatArray:
        """The minimum-norm forces of ``legs`` whose sum through ``a`` is ``rhs``."""
        a_r = a[:, legs]
        return a_r.T @ np.linalg.solve(a_r @ a_r.T, rhs)

    def _residual_share(
        self, x_s: float, share8: FloatArray, f: FloatArray, plan_f: FloatArray, held: list[int]
    ) -> FloatArray:
        """Expected forces: a leg held in position carries its minimum-norm share of what
        the other legs leave of the load (the body's equilibrium with their contact
        forces, :meth:`contact_n`); the others the plan's force."""
        key = (x_s, tuple(held))
        c = self._residual_parts
        if c is None or c[0] != key or c[1] is not share8:
            # what depends on the legs' positions and the load alone: once while they
            # stay (every cycle of a phase but a travel), computed as each cycle did
            others = [j for j in range(8) if j not in held]
            a = self._equilibrium(x_s)
            a_r = a[:, held]
            # (key, share8, the load (any equilibrium gives it), others, a's columns
            # of the others, of the held legs, and the held legs' normal matrix)
            c = (key, share8, a @ share8, others, a[:, others], a_r, a_r @ a_r.T)
            self._residual_parts = c
        _key, _share8, rhs, others, a_o, a_r, normal = c
        contact = self.contact_n(f)
        rest = rhs - a_o @ contact[others]
        out = plan_f.copy()
        out[held] = a_r.T @ np.linalg.solve(normal, rest)  # _min_norm, its parts kept
        return out

    def contact_n(self, f: FloatArray) -> FloatArray:
        """Each leg's force on the body (8,), N, from ``f``, the legs' cap-side forces less
        their rods' friction (:meth:`friction_n`); the body's equilibrium is in these (a
        leg's rod and foot are not in the load: a standing leg's is its foot's load less
        its rod's weight):

        - a leg in force control, standing or touched down: ``f``;
        - a leg of a frame hanging while the travel pair moves: its rod's weight
          (``hydraulics.rod_mass_kg``) pulling down;
        - a lowering leg not touched down: in the fast part of its lowering (in the air)
          its rod's weight, unless ``f`` is above :attr:`PRESSING` of its touch force (a
          foot pressing the invert above the window: that load is not on the standing
          legs); in the slow part ``f`` (a foot that presses the invert before its
          touch-down is declared carries that load), at least its rod's weight;
        - any other leg (a lifting frame): ``f``, at least its rod's weight."""
        w_rod = self.machine.rod_weight_n
        out = np.maximum(f, -w_rod)
        run = self.run
        if run is None:
            return out
        key = run.phase.key
        if key in TRAVEL:
            standing = self._frame(run.phase.standing, self.leg_ids)
            for j in range(8):
                if j not in standing:
                    out[j] = -w_rod
        elif key in LOWER:
            frame = MAIN if key == "7a" else SUB
            touch = self._touch_n
            for k, j in enumerate(frame):
                if not run.near and not run.touched[k]:
                    fj = float(f[j])
                    out[j] = fj if fj > self.PRESSING * touch[j] else -w_rod
                else:
                    out[j] = max(-w_rod, float(f[j]))
        return out

    def friction_n(self) -> FloatArray:
        """Each leg's rod friction now (8,), N, opposing its measured motion (extending
        positive): its plant's Coulomb friction (full above :attr:`COULOMB_SPEED_M_S`)
        and viscous damping (``config.derived.viscous_damping_n_s_m``) at the rod's speed
        over :attr:`MOTION_WINDOW_S`. The pressures carry it on top of what the leg
        puts on the body. On plain floats, element by element as numpy would.

        The speed is over the samples' own times: across a stop (a suspension, a hold)
        the window's oldest sample is from before it, and taken as one window old it
        read a standing leg's creep as several times as fast (campaign run 48: 10-20 kN
        of viscous friction after a 140 ms suspension, an overload)."""
        n = self._x_hist.shape[0]
        k_new, k_old = (self._x_k - 1) % n, self._x_k % n
        newest = self._x_hist[k_new].tolist()
        oldest = self._x_hist[k_old].tolist()
        span = self._t_hist[k_new] - self._t_hist[k_old]
        c_speed = self.COULOMB_SPEED_M_S
        out = [0.0] * 8
        if not span > 0.0:
            return np.array(out)
        for j, (coulomb, viscous) in enumerate(self._friction):
            v = (newest[j] - oldest[j]) / span
            c = v / c_speed
            c = -1.0 if c < -1.0 else (1.0 if c > 1.0 else c)
            out[j] = coulomb * c + viscous * v
        return np.array(out)

    def aligned_forces_n(self, now: float, f: FloatArray, age_s: FloatArray | None) -> FloatArray:
        """The legs' cap-side forces (8,) at one instant, N, for the checks.

        The PLC samples each cylinder's pressures at its fast cycle (50 ms), the frames
        of different cylinders at different instants; while feet touch down or take load
        the forces change by up to some 10 kN within that cycle, and a standing leg's
        force from one instant judged against a share computed from the others' forces
        of another is off by as much (seen: 113 % of the share in the touch-down of M
        while S stands, every leg within 2 % of its share in the simulator's truth).
        So each leg's force is taken at the instant of the oldest latest sample: a leg
        sampled since is interpolated between its last two samples. Constant work: eight
        legs, two samples each, on plain floats."""
        if age_s is None:
            return f
        ages = np.asarray(age_s, dtype=float).tolist()
        fs = f.tolist()
        t_last, t_prev = self._t_last, self._t_prev
        f_last, f_prev = self._f_last, self._f_prev
        for j, i in enumerate(self.legs):
            t = now - ages[i]
            if not math.isfinite(t):
                continue
            if t > t_last[j] + 1e-9:
                f_prev[j], t_prev[j] = f_last[j], t_last[j]
                t_last[j] = t
            f_last[j] = fs[j]
        known = [t for t in t_last if math.isfinite(t)]
        if not known:
            return f
        t_c = min(known)
        for j in range(8):
            t1, t0 = t_last[j], t_prev[j]
            if math.isfinite(t0) and t1 > t_c and t1 > t0:
                w = min(1.0, max(0.0, (t_c - t0) / (t1 - t0)))
                fs[j] = f_prev[j] + w * (f_last[j] - f_prev[j])
        return np.array(fs)

    def _share8(self, x_s: float) -> FloatArray:
        key = round(x_s * 1e3)  # per mm (the cache is emptied at each phase's start)
        hit = self.point_cache.get(key)
        if hit is None:
            hit = (x_s, self.share(x_s, MAIN + SUB))
            self.point_cache[key] = hit
        return hit[1]

    def _lowering(self, tau: float) -> tuple[float, float]:
        """Distance lowered and its rate at ``tau``: the leg speed to ``touchdown_travel``
        above the expected ground, then the touch-down speed to as far below it."""
        fast = Move(self.walk.clearance_m - self.td_travel, self.leg_v, self.leg_a)
        if tau < fast.duration_s:
            s = fast.position_at(tau)
            s1 = fast.position_at(tau + self.period_s)
            return s, (s1 - s) / self.period_s
        return fast.distance_m + self.td_speed * (tau - fast.duration_s), self.td_speed

    def _hold(
        self,
        u: FloatArray,
        refs: FloatArray,
        rates: FloatArray,
        x: FloatArray,
        active: set[int],
        skip: set[int] | None = None,
        known: dict[int, float] | None = None,
    ) -> None:
        """Position control of every walk cylinder not in force control: LADRC in the
        active group, the slow proportional hold outside it. ``known``: a rod speed the
        loop is told of (its oil column's decompression, m/s; :meth:`_set_release_rate`)."""
        for i in self.walk_cylinders:
            if skip and i in skip:
                continue
            if i in active:
                d = known.get(i, 0.0) if known else 0.0
                u[i] = self.pos[i].update(float(refs[i]), float(x[i]), float(rates[i]), d)
            else:
                e = float(refs[i] - x[i])
                u[i] = max(-1.0, min(1.0, self.SLOW_HOLD_RAD_S * e / self.b0[i]))
                self.pos[i].reset(float(x[i]), u[i])

    def phase_name(self) -> str:
        return self.run.phase.name if self.run is not None else ""
