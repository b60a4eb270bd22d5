"""The step sequencer of the walk (walking.md sections 2 and 4, docs/walking.md,
"The step sequencer").

:class:`WalkSequencer` runs the phases of a :class:`~ipc_app.planner.walk.WalkPlan` one
after another on the service's read -> update -> write step: :meth:`WalkSequencer.update`
takes one cycle's rod positions and chamber pressures and returns the spool commands of
all 19 cylinders and the cycle's :class:`~ipc_app.control.walk.figures.WalkFigures`,
which the walk interlocks (:mod:`ipc_app.service.walk_interlocks`) judge. Its loops,
statics and force estimates are :class:`~ipc_app.control.walk.loops.WalkLoops`'.

Each phase runs by its kind (:data:`~ipc_app.control.walk.phases.PHASES`): one method
starts each kind (``_start_*``) and one runs a cycle of it (``_run_*``), setting what
the loops are to do (a :class:`~ipc_app.control.walk.phases.PhaseCycle`); the rest of
the cycle is the same for every kind: the moving group's synchronization and its band
(the reference clock stops while the group is out of ``walking.leg_sync_band_mm`` /
``travel_sync_band_mm`` and goes on once it is back: hold and continue), the commands,
the checks' figures.

- **Travel**: the pair to the phase's end ``x_S`` on a trapezoid. Its references are
  per cylinder, each from its own stroke at the phase's start, and the band judges the
  tracking errors about them: a planned differential of the pair (a curve's steering,
  curves.md section 3) is a term of those references.
- **Lower** and **lift**: the frame's four legs in position control, together; a
  lowering leg stops at its touch-down and holds its touch force in force control.
- **Preload** and **transfer**: the receiving legs' force references ramped at
  ``walking.force_ramp_kn_s``; the releasing frame's legs stay in position control,
  each reference following its foot's unloading as the plan releases it
  (``+ (F_plan - F_0) / k_contact``, ``F_plan`` the force at the release rate the body's
  equilibrium gives with the receiving legs' ramp: the foot rises by what its contact
  decompresses), so the body keeps its height at those legs.

Work per cycle is bounded: one reference sample per moving group, at most 14 controller
updates and one stability margin (a hull of at most eight points).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import ClassVar

import numpy as np
from numpy.typing import NDArray

from config import units
from config.derived import hydraulic_stiffness_n_m
from config.schema import ProjectConfig
from ipc_app.control.sync import sync_errors
from ipc_app.control.tuning import touchdown_speed_m_s
from ipc_app.control.walk.figures import StepFigures, WalkFigures
from ipc_app.control.walk.forces import equilibrium_matrix, min_norm_forces
from ipc_app.control.walk.ground import LiftMark, invert_plane, surface_z_m
from ipc_app.control.walk.loops import WalkLoops, twist_part
from ipc_app.control.walk.phases import (
    PHASES,
    PhaseCycle,
    PhaseKind,
    PhaseRun,
    walk_active_group,
)
from ipc_app.model.support import cap_side_forces_n
from ipc_app.planner.force_ramp import TRANSFER_KEYS, ForceRamp, blend_s
from ipc_app.planner.walk import Move, Phase, WalkPlan

FloatArray = NDArray[np.float64]
#: a kind's start (the sequencer, the phase, rod positions, pressures, S's position)
StartKind = Callable[["WalkSequencer", PhaseRun, FloatArray, FloatArray, float], None]
#: a kind's cycle
RunKind = Callable[["WalkSequencer", PhaseRun, PhaseCycle], None]


class WalkSequencer(WalkLoops):
    """Runs a walk plan on the machine; see the module docstring."""

    #: a position move ends when every moving rod is this close to its end reference
    END_TOLERANCE_M = 1e-4
    #: time constant of the low-pass that follows a lowering rod's free cap pressure, s
    FREE_ROD_S = 0.25
    #: preload ends with every preloaded leg within this fraction of its target
    PRELOAD_TOLERANCE = 0.10
    #: in the slow part of a lowering, the free rod's pressure follows while within this
    #: fraction of the touch rise above its baseline
    FREE_BAND = 0.1
    #: in the fast part of a lowering, a leg's force on the body above its free rod's
    #: (friction and the oil's drag while it moves, low-passed) by this fraction of its
    #: touch force (``walking.touch_mpa`` over its cap area) is a foot pressing the
    #: invert: it enters the body's equilibrium (:meth:`contact_n`); above the touch
    #: force itself it is an obstacle (the touch-down interlock)
    PRESSING = 0.25

    def __init__(self, cfg: ProjectConfig, period_s: float, plan: WalkPlan) -> None:
        super().__init__(cfg, period_s, plan)
        ctl = cfg.control
        self.coupling_lambda = ctl.sync.coupling_lambda
        self.sync_scheme = ctl.sync.scheme
        self.leg_sync_band_m = units.mm(self.walk.leg_sync_band_mm)
        self.travel_sync_band_m = units.mm(self.walk.travel_sync_band_mm)
        self.touch_rise_pa = units.mpa(self.walk.touch_mpa)
        #: a leg's cap-side force above this is a foot touching (walking.touch_mpa), N
        self.touch_force_n = [float(v) for v in self.touch_rise_pa * self.cap_area_m2[self.legs]]
        self.touchdown_travel_m = units.mm(self.walk.touchdown_travel_mm)
        self.touchdown_speed_m_s = touchdown_speed_m_s(cfg)
        self.ramp_blend_s = blend_s(cfg)
        traj = cfg.planner.trajectory
        self.leg_speed_m_s = traj.max_rod_speed_m_s
        self.leg_accel_m_s2 = traj.max_rod_accel_m_s2
        #: a lowering's fast part (:meth:`_fast_lowering`), made once: the loop's thread
        #: reads it every cycle of a lowering
        self._fast_lower = Move(
            self.walk.clearance_m - self.touchdown_travel_m, self.leg_speed_m_s,
            self.leg_accel_m_s2,
        )  # fmt: skip
        #: every walk cylinder's position reference while it holds, m
        self.hold_ref = np.zeros(self.n)
        self.done = False
        self.steps: list[StepFigures] = []
        self.figures = WalkFigures()
        self.last_refs = np.zeros(self.n)
        #: (machine time, step, phase) of each phase start, for the run record
        self.phase_log: list[tuple[float, int, str]] = []
        self.leg_force_n = np.zeros(8)
        #: force references of the legs in force control this cycle (NaN: not), N
        self.force_ref_n = np.full(8, math.nan)
        #: each frame's last lift (its legs' indices -> where they left the invert)
        self.lift_marks: dict[tuple[int, ...], LiftMark] = {}

    def active_group(self) -> list[int]:
        """The present phase's active group (:func:`walk_active_group`)."""
        return walk_active_group(self.cfg, self._key_now())

    def phase_name(self) -> str:
        return self.run.phase.name if self.run is not None else ""

    # ----------------------------------------------------------------- the phases

    def start(self, now: float, x: FloatArray, p: FloatArray) -> None:
        """Engage at the measured state: every walk cylinder holds, the first phase starts."""
        self.set_upper(x)
        self.hold_ref = np.array(x, dtype=float)
        self.rod_friction.restart(now, x[self.legs])
        for i, c in self.pos.items():
            c.reset(float(x[i]))
        self.pair_live = False  # the travel pair's loops too, at the rods
        self._begin(0, now, x, p)

    def _begin(self, k: int, now: float, x: FloatArray, p: FloatArray) -> None:
        """Start the plan's phase ``k`` at the measured state."""
        ph = self.plan.phases[k]
        f = self.forces_n(p)
        for i in self.legs + self.travel:
            self.hold_ref[i] = float(x[i])
        self._share_cache.clear()
        run = PhaseRun(k, ph, now, start_position_m=np.array(x, dtype=float), start_force_n=f)
        x_s = self.x_s(x)
        if k == 0 or ph.step != self.plan.phases[k - 1].step:
            self.steps.append(StepFigures(ph.step, started_s=now))
        self.phase_log.append((now, ph.step, ph.key))
        if run.kind.sheds_standing_load:  # the overload's floor for its standing legs
            run.standing_share_n = self.share(x_s, run.role.standing)
        self._START[run.kind](self, run, x, p, x_s)
        self.run = run
        self.figures.margin_ahead_m = self._margin_ahead(ph, x_s)

    def _start_travel(self, run: PhaseRun, x: FloatArray, p: FloatArray, x_s: float) -> None:
        run.duration_s = Move(run.phase.end_x_s_m - x_s, *self._travel_limits()).duration_s
        self._legs_to_position_control(x)

    def _start_lower(self, run: PhaseRun, x: FloatArray, p: FloatArray, x_s: float) -> None:
        fast = self._fast_lowering()
        run.duration_s = fast.duration_s + 2 * self.touchdown_travel_m / self.touchdown_speed_m_s
        run.touched = [False] * 4
        run.free_cap_pa = [float(p[self.legs[j], 0]) for j in run.role.frame]
        run.touch_force_n = [0.0] * 4
        run.free_force_n = [math.nan] * 4
        run.pressing = [False] * 4
        mark = self.lift_marks.get(tuple(run.role.frame))
        if mark is not None:  # the expected ground follows the body since the lift
            touch = mark.touch_rods_now(*self._invert_now(run, x, p, x_s))
            start = np.array([x[self.legs[j]] for j in run.role.frame])
            shift = touch - (start + self.walk.clearance_m)
            run.ground_shift_m = np.clip(shift, -self.touchdown_travel_m, self.touchdown_travel_m)
        self._legs_to_position_control(x)

    def _start_lift(self, run: PhaseRun, x: FloatArray, p: FloatArray, x_s: float) -> None:
        run.duration_s = self._lift().duration_s
        xy, surface, _ = self._invert_now(run, x, p, x_s)
        lifting = list(run.role.frame)
        self.lift_marks[tuple(lifting)] = LiftMark(
            invert_plane(xy, surface),
            x[[self.legs[j] for j in lifting]] - self.forces_n(p)[lifting] / self.k_contact,
        )
        self._legs_to_position_control(x)

    def _invert_now(
        self, run: PhaseRun, x: FloatArray, p: FloatArray, x_s: float
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The standing feet's body coordinates and the invert's surface under them
        (:mod:`~ipc_app.control.walk.ground`), and the moving frame's feet's coordinates."""
        xy = self.machine.legs_xy(x_s)
        standing = list(run.role.standing)
        rods = x[[self.legs[j] for j in standing]]
        surface = surface_z_m(rods, self.forces_n(p)[standing], self.k_contact)
        return xy[standing], surface, xy[list(run.role.frame)]

    def _start_force_ramp(self, run: PhaseRun, x: FloatArray, p: FloatArray, x_s: float) -> None:
        """A preload or a transfer: the receiving legs' ramp to their target in force
        control, the releasing legs' rates (:meth:`_set_release_rate`)."""
        f = run.start_force_n
        receiving, releasing = run.role.frame, run.role.standing
        if run.kind is PhaseKind.PRELOAD:
            run.target_force_n = run.phase.leg_forces_n[-1].copy()
        else:
            run.target_force_n = self.share(x_s, receiving)
            for j in releasing:
                cyl = self.cfg.cylinders_by_can_index[self.legs[j]]
                run.k_oil_n_m[j] = hydraulic_stiffness_n_m(
                    cyl, self.cfg.plant_of(cyl), self.cfg.hydraulics, float(x[self.legs[j]])
                )
        self._set_ramp(run, f)
        if run.kind is PhaseKind.TRANSFER:
            run.plan_start_n = run.phase.leg_forces_n[0].copy()
        self._set_release_rate(run, x_s, f)
        for j in receiving:
            i = self.legs[j]
            if i not in self.force_mode:
                self.force_mode.add(i)
                self.force[i].reset(float(f[j]), self.pos[i].command)
        for j in releasing:
            i = self.legs[j]
            if i in self.force_mode:  # bumpless back to position control
                self._to_position_control(i, x)

    _START: ClassVar[dict[PhaseKind, StartKind]] = {
        PhaseKind.TRAVEL: _start_travel,
        PhaseKind.LOWER: _start_lower,
        PhaseKind.PRELOAD: _start_force_ramp,
        PhaseKind.TRANSFER: _start_force_ramp,
        PhaseKind.LIFT: _start_lift,
    }

    def _to_position_control(self, i: int, x: FloatArray) -> None:
        """Leg ``i`` from force control back to position control, bumpless, holding
        where it is."""
        self.force_mode.discard(i)
        self.pos[i].reset(float(x[i]), self.force[i].command)
        self.hold_ref[i] = float(x[i])

    def _legs_to_position_control(self, x: FloatArray) -> None:
        for i in list(self.force_mode):
            self._to_position_control(i, x)

    def _travel_limits(self) -> tuple[float, float]:
        """The travel pair's speed, m/s, and acceleration, m/s^2."""
        return self.walk.travel_speed_m_s, self.walk.travel_accel_m_s2

    def _fast_lowering(self) -> Move:
        """A lowering's fast part: at leg speed to ``touchdown_travel`` above the
        expected ground."""
        return self._fast_lower

    def _lift(self) -> Move:
        return Move(-self.walk.clearance_m, self.leg_speed_m_s, self.leg_accel_m_s2)

    def _set_ramp(self, run: PhaseRun, f: FloatArray) -> None:
        """A force ramp from the receiving legs' forces ``f`` to their target: its line's
        time at full rate (the largest change of any leg), a transfer's blended in and out."""
        delta = max(abs(float(run.target_force_n[j] - f[j])) for j in run.role.frame)
        blend = self.ramp_blend_s if run.phase.key in TRANSFER_KEYS else 0.0
        run.ramp = ForceRamp.of(delta / self.walk.force_ramp_n_s, blend)
        run.duration_s = run.ramp.duration_s

    def _margin_ahead(self, ph: Phase, x_s: float) -> float:
        """The least margin along the phase's commanded motion, from the measured start,
        with the legs that stand during it (after it, for a lift)."""
        standing = self._frame(ph.standing, self.leg_ids)
        if PHASES[ph.key].kind is PhaseKind.TRAVEL:
            xs = np.linspace(x_s, ph.end_x_s_m, 21)
            return min(self.margin(float(v), standing) for v in xs)
        return self.margin(x_s, standing)

    def _next(self, now: float, x: FloatArray, p: FloatArray) -> None:
        run = self.run
        assert run is not None
        step = self.steps[-1]
        if run.kind is PhaseKind.TRANSFER:
            step.transfer_time_s += now - run.started_s
        if run.kind is PhaseKind.TRAVEL and step.turn_rad is None:
            # the step's first travel turned the lifted frame: S's yaw in M (forward S
            # turned, back M turned the other way)
            turned = self.yaw_s_in_m(x) - self.yaw_s_in_m(run.start_position_m)
            step.turn_rad = -turned if self.plan.direction == "back" else turned
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
        self.pair_live = False  # the travel pair's loops too, at the rods
        self.slow_integral.clear()  # the travel pair's slow hold too, at no command
        self._twist_started = False  # the twist loop too, at the forces now
        self.body_speed.restart()  # the body's speed at the feet too, at rest
        for j, i in enumerate(self.legs):
            if i in self.force_mode:
                self.force[i].reset(float(f[j]))
        run = self.run
        if run is not None and run.kind.ramps_force:
            # the receiving legs' ramp restarts from their forces now (while stopped they
            # held what they had, the ramp's reference stood where the clock stopped;
            # a loop reset at the one and driven to the other takes the step at once)
            if run.kind is PhaseKind.TRANSFER:  # the plan's line goes on from where it stood
                line_n = run.target_force_n - run.plan_start_n
                run.plan_start_n = run.plan_start_n + run.progress * line_n
            for j in run.role.frame:
                run.start_force_n[j] = f[j]
            run.clock_s = 0.0
            self._set_ramp(run, f)
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
        self.rod_friction.record(now, x[self.legs])
        f_aligned = self.aligned_forces_n(now, f, p_age_s)
        run = self.run
        if run is None or self.done:
            self._hold(u, refs, rates, x, active)
            self.last_refs = refs
            return u
        fig = self.figures
        fig.step, fig.phase = run.phase.step, run.phase.key
        fig.leg_sync_m = fig.travel_sync_m = 0.0
        fig.no_touchdown, fig.overdue_s, fig.share_off = "", 0.0, ("", 1.0)
        fig.obstacle = ("", 0.0)
        # the checks' forces: at one instant, less each rod's friction (what the legs
        # put on the body, the statics' terms)
        body_force_n = f_aligned - self.friction_n()
        cyc = PhaseCycle(now, x, p, f, body_force_n, refs, rates, self._plan_forces_now(run))
        self._RUN[run.kind](self, run, cyc)
        twist_frame = self._twist_position(
            cyc.position_ref_m, x, self._twist_frame(run.phase), active
        )
        self._synchronize(run, cyc)
        self._drive(run, u, cyc, active, twist_frame)
        self._check_figures(run, cyc, f_aligned)
        self.steps[-1].take(fig)
        self.last_refs = cyc.position_ref_m
        if cyc.finished:
            self._next(now, x, p)
        return u

    def _plan_forces_now(self, run: PhaseRun) -> FloatArray:
        """The plan's leg forces (8,) at the reference clock, N: its samples
        interpolated."""
        samples = run.phase.leg_forces_n
        at = run.progress * (len(samples) - 1)
        below = int(at)
        above = min(below + 1, len(samples) - 1)
        return samples[below] * (1 - (at - below)) + samples[above] * (at - below)

    def _run_travel(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The travel pair to the phase's end (a trapezoid of ``x_S``), each rod from its
        stroke at the phase's start to its own end (they differ while S is turned in M,
        curves.md section 3) in proportion: the pair's sync errors are the rods'
        deviations from their planned difference."""
        dt = self.period_s
        move = run.travel_move
        if move is None:  # from the phase's start to its end: the same every cycle
            x_s_start = float(np.mean(run.start_position_m[self.travel])) - self.centred_stroke_m
            move = Move(run.phase.end_x_s_m - x_s_start, *self._travel_limits())
            run.travel_move = move
            run.travel_share = [
                (end + self.centred_stroke_m - float(run.start_position_m[i])) / move.distance_m
                if move.distance_m != 0.0
                else 1.0
                for i, end in zip(self.travel, run.phase.end_m, strict=True)
            ]
        travelled_m = move.position_at(run.clock_s)
        rate_m_s = (move.position_at(run.clock_s + dt) - travelled_m) / dt
        refs = cyc.position_ref_m
        for i, share in zip(self.travel, run.travel_share, strict=True):
            refs[i] = run.start_position_m[i] + share * travelled_m
            cyc.rate_ref_m_s[i] = share * rate_m_s if self.feedforward else 0.0
        cyc.moving = list(self.travel)
        cyc.sync_band_m = self.travel_sync_band_m
        cyc.finished = run.clock_s >= run.duration_s and all(
            abs(cyc.position_m[i] - refs[i]) <= self.END_TOLERANCE_M for i in self.travel
        )

    def _run_lower(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The frame's legs down together until each foot touches down; a touched leg
        stops and holds its touch force."""
        lowered_m, rate_m_s = self._lowering(run.clock_s)
        frame = run.role.frame
        # each leg's expected ground shift taken in over the fast part, with its rate
        fast_m = self._fast_lowering().distance_m
        in_fast = lowered_m < fast_m
        share = min(1.0, lowered_m / fast_m) if fast_m > 0 else 1.0
        for k, j in enumerate(frame):
            i = self.legs[j]
            if run.touched[k]:  # touched: it holds its touch force
                cyc.force_ref[i] = self._touch_hold(run, k, j)
                continue
            shift = float(run.ground_shift_m[k])
            rate = rate_m_s * (1.0 + shift / fast_m) if in_fast and fast_m > 0 else rate_m_s
            self._move_leg(run, cyc, i, lowered_m + share * shift, rate)
        cyc.sync_band_m = self.leg_sync_band_m
        # touch-down is looked for from touchdown_travel above the expected ground
        window_from_m = self.walk.clearance_m - self.touchdown_travel_m
        run.in_touchdown_window = lowered_m >= window_from_m - 1e-9
        for k, j in enumerate(frame):
            if not run.touched[k]:
                self._follow_free_rod(run, cyc, k, j)
                self._look_for_touchdown(run, cyc, k, j)
        cyc.finished = all(run.touched)
        if not cyc.finished and run.clock_s >= run.duration_s:
            self.figures.no_touchdown = self.leg_ids[frame[run.touched.index(False)]]

    def _touch_hold(self, run: PhaseRun, k: int, j: int) -> tuple[float, float]:
        """The force reference (N, N/s) of the ``k``-th leg of a lowering frame (leg
        ``j``), touched down: from its force at the touch-down down to the touch force
        (``walking.touch_mpa`` over its cap) at ``walking.force_ramp_kn_s``, then held.
        The touch-down is seen up to some frames of its pressure late, while the foot
        presses on; what it pressed on in that time is let off, not held through the
        other legs' touch-downs (seen: 41.5 kN held and pushed further, 111 % of a
        corner leg's share of the unloaded machine, with a 25 kN touch force)."""
        rate_n_s = self.walk.force_ramp_n_s
        floor_n = self.touch_force_n[j]
        held_n = run.touch_force_n[k]
        if held_n <= floor_n:
            return held_n, 0.0
        held_n = max(floor_n, held_n - rate_n_s * self.period_s)
        run.touch_force_n[k] = held_n
        return held_n, (-rate_n_s if held_n > floor_n else 0.0)

    def _follow_free_rod(self, run: PhaseRun, cyc: PhaseCycle, k: int, j: int) -> None:
        """The ``k``-th leg of a lowering frame (leg ``j``), not touched down: in the fast
        part, whether its foot presses the invert (``run.pressing``), judged against its
        free rod's force, which follows it while it does not. A moving rod's force on the
        body is its seals' friction and the oil's drag, some kilonewtons, more than the
        friction the loops assume on a stiffer seal; judged against zero, a free rod was
        taken as a foot pressing (1 of the walk campaign's first 12 drawn machines): the
        standing legs' expected shares fell by its force and the overload check tripped
        on one at 113 %."""
        f_n = float(cyc.body_force_n[j])
        free_n = run.free_force_n[k]
        if math.isnan(free_n):
            free_n = run.free_force_n[k] = f_n
        above_n = f_n - free_n
        run.pressing[k] = (
            not run.in_touchdown_window and above_n > self.PRESSING * self.touch_force_n[j]
        )
        if not run.pressing[k]:
            run.free_force_n[k] = free_n + above_n * self.period_s / self.FREE_ROD_S

    def _look_for_touchdown(self, run: PhaseRun, cyc: PhaseCycle, k: int, j: int) -> None:
        """The ``k``-th leg of a lowering frame (leg ``j``), not touched down yet."""
        i = self.legs[j]
        cap_pa = float(cyc.pressure_pa[i, 0])
        rise_pa = cap_pa - run.free_cap_pa[k]
        in_window = run.in_touchdown_window
        # a foot on the invert above the window (an obstacle, or the ground higher than
        # expected by more than the window), judged on its force on the body, not the
        # cap pressure's rise (a free rod lowering fast needs some 1.6 MPa more cap
        # pressure than at rest, the touch rise is 1 MPa): it stops as at a touch-down,
        # and the touch-down interlock stops the walk
        obstacle = not in_window and float(cyc.body_force_n[j]) > self.touch_force_n[j]
        if obstacle:
            lowered_m = float(cyc.position_m[i] - run.start_position_m[i])
            above_m = self.walk.clearance_m + float(run.ground_shift_m[k]) - lowered_m
            self.figures.obstacle = (self.leg_ids[j], above_m)
        if obstacle or (in_window and rise_pa > self.touch_rise_pa):
            run.touched[k] = True
            run.touch_force_n[k] = float(cyc.leg_force_n[j])
            # then it stops: force control from here, at rest (its valve closed; a stiff
            # foot held in position would keep what the position loop's overshoot
            # pressed into it, and started from the lowering's command it would go on
            # pressing the invert for the loop's time constant: seen, twice the touch
            # force)
            self.force_mode.add(i)
            self.force[i].reset(float(cyc.leg_force_n[j]), 0.0)
            cyc.force_ref[i] = (run.touch_force_n[k], 0.0)
            if i in cyc.moving:
                cyc.moving.remove(i)
        elif rise_pa <= 0.5 * self.touch_rise_pa:
            # the free rod's pressure, low-passed while it moves; a sample more than half
            # the touch rise above it is the foot pressing the invert, not the free
            # motion: the value holds. In the slow part it holds sooner: a foot pressing
            # by a tenth of the touch rise is not free any more (followed up to half of
            # it, the baseline rose with a fast press and the touch-down came late)
            gain = self.period_s / self.FREE_ROD_S
            if not in_window or rise_pa <= self.FREE_BAND * self.touch_rise_pa:
                run.free_cap_pa[k] += (cap_pa - run.free_cap_pa[k]) * gain

    def _run_lift(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The frame's legs up together by the clearance."""
        dt = self.period_s
        move = self._lift()
        lifted_m = move.position_at(run.clock_s)
        rate_m_s = (move.position_at(run.clock_s + dt) - lifted_m) / dt
        frame = run.role.frame
        for j in frame:
            self._move_leg(run, cyc, self.legs[j], lifted_m, rate_m_s)
        cyc.sync_band_m = self.leg_sync_band_m
        refs = cyc.position_ref_m
        cyc.finished = run.clock_s >= run.duration_s and all(
            abs(cyc.position_m[self.legs[j]] - refs[self.legs[j]]) <= self.END_TOLERANCE_M
            for j in frame
        )

    def _move_leg(
        self, run: PhaseRun, cyc: PhaseCycle, i: int, moved_m: float, rate_m_s: float
    ) -> None:
        """Leg ``i`` ``moved_m`` from its start at ``rate_m_s``, in the moving group."""
        cyc.position_ref_m[i] = run.start_position_m[i] + moved_m
        cyc.rate_ref_m_s[i] = rate_m_s if self.feedforward else 0.0
        cyc.moving.append(i)

    def _run_preload(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The touched legs' ramp to their preload; the standing frame holds the body."""
        self._ramp_receiving(run, cyc)
        self._hold_body(run, cyc)
        target = run.target_force_n
        f = cyc.leg_force_n
        cyc.finished = run.progress >= 1.0 and all(
            abs(f[j] - target[j]) <= self.PRELOAD_TOLERANCE * abs(target[j]) for j in run.role.frame
        )
        self._overdue(run, cyc)

    def _run_transfer(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The receiving legs' ramp to their standing share, the releasing legs holding
        the body as they unload; done with every releasing leg unloaded and every
        receiving one within its share's tolerance."""
        self._ramp_receiving(run, cyc)
        # the plan's force now: its line from the preload to the standing share at the
        # ramp's progress (the plan's samples end short of the share, at the releasing
        # legs' unloaded_percent, and the ramp goes on to it)
        line_start_n, progress = run.plan_start_n, run.progress
        for j in run.role.frame:
            target_n = float(run.target_force_n[j])
            cyc.plan_force_n[j] = line_start_n[j] + progress * (target_n - line_start_n[j])
        self._hold_body(run, cyc)
        receiving, releasing = run.role.frame, run.role.standing
        target = run.target_force_n
        f = cyc.leg_force_n
        unloaded = self.walk.unloaded_percent / 100.0
        standing_share_n = run.standing_share_n
        released = all(f[j] < unloaded * standing_share_n[j] for j in releasing)
        worst = max(receiving, key=lambda j: abs(f[j] / target[j] - 1.0))
        share_ratio = float(f[worst] / target[worst])
        self.figures.share_off = (self.leg_ids[worst], share_ratio)
        tolerance = self.walk.share_tolerance_percent / 100.0
        cyc.finished = progress >= 1.0 and released and abs(share_ratio - 1.0) <= tolerance
        self._overdue(run, cyc)

    def _ramp_receiving(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The receiving legs' force references on their ramp, with its rate."""
        progress = run.progress
        for j in run.role.frame:
            f0, f1 = float(run.start_force_n[j]), float(run.target_force_n[j])
            line_s = self._linear_s(run)
            rate_n_s = (f1 - f0) / line_s * run.rate_share if line_s > 0 else 0.0
            cyc.force_ref[self.legs[j]] = (f0 + progress * (f1 - f0), rate_n_s)

    def _hold_body(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The body held at the releasing legs: each reference follows its foot's
        unloading as the plan releases it (its rate from the body's equilibrium,
        :meth:`_set_release_rate`; not the measured forces: following those closes a loop
        through the receiving legs' force loops that rang in the pitch pattern, some
        1.2 s a period), not in the twist mode."""
        releasing = list(run.role.standing)
        released_n = run.release_rate_n_s[releasing] * self._linear_s(run) * run.progress
        unloaded_n = run.release_from_n[releasing] + released_n - run.start_force_n[releasing]
        follow_m = unloaded_n / self.k_contact
        follow_m -= twist_part(follow_m)
        # the releasing loops told their oil columns' decompression: in 7c (in phase 4
        # it changed the state M's touch-downs meet in 7a: at 5 mm/s 7b's trip went from
        # 110.26 to 110.75 %)
        told = run.progress < 1.0 and run.role.decompression_feedforward
        told_rate_n_s = run.release_rate_n_s[releasing] * (run.rate_share if told else 0.0)
        follow_m_s = told_rate_n_s / self.k_contact
        follow_m_s -= twist_part(follow_m_s)
        for k, (j, follow) in enumerate(zip(releasing, follow_m, strict=True)):
            i = self.legs[j]
            cyc.position_ref_m[i] = run.start_position_m[i] + float(follow)
            if self.feedforward:
                cyc.rate_ref_m_s[i] = float(follow_m_s[k])
            # the rod moves by its oil column's decompression as the leg unloads
            cyc.known_speed_m_s[i] = -float(told_rate_n_s[k]) / float(run.k_oil_n_m[j])
        cyc.sync_band_m = self.leg_sync_band_m

    def _overdue(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        overdue_s = cyc.now_s - run.started_s - self.walk.transfer_timeout_s
        self.figures.overdue_s = max(0.0, overdue_s)

    _RUN: ClassVar[dict[PhaseKind, RunKind]] = {
        PhaseKind.TRAVEL: _run_travel,
        PhaseKind.LOWER: _run_lower,
        PhaseKind.PRELOAD: _run_preload,
        PhaseKind.TRANSFER: _run_transfer,
        PhaseKind.LIFT: _run_lift,
    }

    def _synchronize(self, run: PhaseRun, cyc: PhaseCycle) -> None:
        """The moving group's dual-error coupling, and its band: the reference clock
        stops while the group is beyond it (the group holds where it is, no
        feed-forward) and goes on once it is back (hold and continue)."""
        sync_m = 0.0
        moving, refs, x = cyc.moving, cyc.position_ref_m, cyc.position_m
        if len(moving) >= 2:
            errors_m = sync_errors([refs[i] - x[i] for i in moving], self.sync_scheme)
            sync_m = max(abs(e) for e in errors_m)
            for e, i in zip(errors_m, moving, strict=True):
                refs[i] += self.coupling_lambda * e
        fig = self.figures
        travel = run.kind is PhaseKind.TRAVEL
        if travel:
            fig.travel_sync_m = sync_m
        elif moving:
            fig.leg_sync_m = sync_m
        if bool(moving) and sync_m > cyc.sync_band_m:
            if run.out_of_band_since_s is None:
                run.out_of_band_since_s = cyc.now_s
            fig.out_of_band = "travel" if travel else "legs"
            fig.out_of_band_s = cyc.now_s - run.out_of_band_since_s
            for i in moving:
                cyc.rate_ref_m_s[i] = 0.0
        else:
            run.out_of_band_since_s = None
            fig.out_of_band, fig.out_of_band_s = "", 0.0
            run.clock_s += self.period_s

    def _drive(
        self,
        run: PhaseRun,
        u: FloatArray,
        cyc: PhaseCycle,
        active: set[int],
        twist_frame: tuple[int, ...],
    ) -> None:
        """The commands ``u``: the force-controlled legs' (told the body's motion on
        the holding frame, :meth:`body_motion_n_s`), the position-controlled active
        ones', the slow holds', then the standing frame's twist mode."""
        x, refs, f = cyc.position_m, cyc.position_ref_m, cyc.leg_force_n
        self.force_ref_n[:] = math.nan
        told = self.body_motion_n_s(run.role.standing, x, cyc.force_ref)
        for i, (ref_n, rate_n_s) in cyc.force_ref.items():
            j = self.legs.index(i)
            self.force_ref_n[j] = ref_n
            rate = rate_n_s if self.feedforward else 0.0
            u[i] = self.force[i].update(ref_n, float(f[j]), rate, told[i])
            refs[i] = float(x[i])
        self._hold(
            u, refs, cyc.rate_ref_m_s, x, active, skip=set(cyc.force_ref),
            known=cyc.known_speed_m_s,
        )  # fmt: skip
        self._twist_control(u, cyc.body_force_n, cyc.plan_force_n, twist_frame)

    def _check_figures(self, run: PhaseRun, cyc: PhaseCycle, f_aligned: FloatArray) -> None:
        """This cycle's figures of the walk interlocks, from the measurement."""
        fig, ph = self.figures, run.phase
        x_s = self.x_s(cyc.position_m)
        leg_force_n = cyc.leg_force_n.tolist()
        touch = self.touch_force_n
        touching = tuple(j for j in range(8) if leg_force_n[j] > touch[j])
        fig.margin_m = self.margin(x_s, touching) if len(touching) >= 3 else -math.inf
        fig.travel_force_n = float(
            np.sum(
                cap_side_forces_n(
                    cyc.pressure_pa[self.travel], self._travel_cap_m2, self._travel_rod_m2
                )
            )
        )
        capacity = 0.0  # summed in order, as sum() of the standing legs' forces
        for j in self._frame(ph.standing, self.leg_ids):
            capacity += max(0.0, leg_force_n[j])
        fig.friction_capacity_n = self.walk.foot_friction_coefficient * capacity
        fig.expected_n = tuple(self._expected_n(run, cyc, x_s).tolist())
        # judged: a leg in force control its cap-side force (what its loop sets against
        # its reference), any other its force on the body (against its statics' share)
        judged = cyc.body_force_n.tolist()
        if self.force_mode:
            aligned = f_aligned.tolist()
            for j, i in enumerate(self.legs):
                if i in self.force_mode:
                    judged[j] = aligned[j]
        fig.leg_force_n = tuple(judged)
        fig.friction_unknown_n = self.rod_friction.unknown_n
        fig.phase_t_s = run.clock_s

    def _expected_n(self, run: PhaseRun, cyc: PhaseCycle, x_s: float) -> FloatArray:
        """Expected shares (the overload check's), N: a force-controlled leg the plan's
        force now, a leg held in position its minimum-norm share of what the others'
        forces on the body leave of the load; never below the eight-leg share, nor a
        standing leg in a lowering, preload or transfer below what it carries standing
        alone (``run.standing_share_n``)."""
        x_s_now = x_s if run.kind is PhaseKind.TRAVEL else float(run.phase.x_s_m[0])
        share8 = self._share8(x_s_now)
        held = list(run.role.standing)
        expected = np.maximum(
            self.held_shares.expected_n(
                self.machine, x_s_now, share8, self.contact_n(cyc.body_force_n),
                cyc.plan_force_n, held,
            ),
            share8,
        )  # fmt: skip
        if run.kind.sheds_standing_load:
            # a leg is overloaded only above what it carried standing alone; a lag behind
            # the plan's release is the preload and transfer checks' to judge, the feet
            # landing in a lowering move the minimum-norm shares ahead of the legs'
            # pressures within a cycle (decision 0037)
            expected = np.maximum(expected, run.standing_share_n)
        return expected

    # ----------------------------------------------------------------- shared pieces

    @staticmethod
    def _linear_s(run: PhaseRun) -> float:
        """A force ramp's line at full rate, s."""
        return run.ramp.linear_s if run.ramp is not None else run.duration_s

    def _set_release_rate(self, run: PhaseRun, x_s: float, f: FloatArray) -> None:
        """A preload's or transfer's releasing legs' force rates (``run.release_rate_n_s``,
        N/s) while the receiving legs' references ramp from ``f`` to
        ``run.target_force_n``: the body's equilibrium (heave, roll, pitch) with the load
        constant, minimum norm over the releasing legs (no twist); and their forces where
        the rates start (``run.release_from_n``: ``f``), from which their references
        follow."""
        receiving, releasing = list(run.role.frame), list(run.role.standing)
        run.release_rate_n_s = np.zeros(8)
        run.release_from_n = np.array(f, dtype=float)
        if self._linear_s(run) <= 0:
            return
        ramp_n_s = (run.target_force_n - f) / self._linear_s(run)
        a = equilibrium_matrix(self.machine, x_s)
        run.release_rate_n_s[releasing] = -min_norm_forces(
            a, releasing, a[:, receiving] @ ramp_n_s[receiving]
        )

    def contact_n(self, f: FloatArray) -> FloatArray:
        """Each leg's force on the body (8,), N, from ``f``, the legs' cap-side forces less
        their rods' friction (:meth:`friction_n`); the body's equilibrium is in these (a
        leg's rod and foot are not in the load: a standing leg's is its foot's load less
        its rod's weight):

        - a leg in force control, standing or touched down: ``f``;
        - a leg of a frame hanging while the travel pair moves: its rod's weight
          (``hydraulics.rod_mass_kg``) pulling down;
        - a lowering leg not touched down: in the fast part of its lowering (in the air)
          its rod's weight, unless its foot presses the invert (``run.pressing``: ``f``
          above its free rod's by :attr:`PRESSING` of its touch force; that load is not on
          the standing legs); in the slow part ``f`` (a foot that presses the invert
          before its touch-down is declared carries that load), at least its rod's
          weight;
        - any other leg (a lifting frame): ``f``, at least its rod's weight."""
        w_rod = self.machine.rod_weight_n
        out = np.maximum(f, -w_rod)
        run = self.run
        if run is None:
            return out
        if run.kind is PhaseKind.TRAVEL:
            for j in run.role.frame:  # hanging
                out[j] = -w_rod
        elif run.kind is PhaseKind.LOWER:
            for k, j in enumerate(run.role.frame):
                if not run.in_touchdown_window and not run.touched[k]:
                    out[j] = float(f[j]) if run.pressing[k] else -w_rod
                else:
                    out[j] = max(-w_rod, float(f[j]))
        return out

    def _lowering(self, clock_s: float) -> tuple[float, float]:
        """Distance lowered, m, and its rate, m/s, at ``clock_s``: the leg speed to
        ``touchdown_travel`` above the expected ground, then the touch-down speed to as
        far below it."""
        fast = self._fast_lowering()
        if clock_s < fast.duration_s:
            s = fast.position_at(clock_s)
            s1 = fast.position_at(clock_s + self.period_s)
            return s, (s1 - s) / self.period_s
        slow_s = clock_s - fast.duration_s
        return fast.distance_m + self.touchdown_speed_m_s * slow_s, self.touchdown_speed_m_s
