"""The walk's loops and what they measure: :class:`WalkLoops`, the base of
:class:`~ipc_app.control.walk.sequencer.WalkSequencer`, which drives them phase by phase.

- **Position control with synchronization** for the legs that lift or lower and for the
  travel pair: one LADRC per walk cylinder (``control.ladrc``, the attitude loops'
  tuning and feed-forward), coupled in its moving group by the dual-error feedback of
  :class:`~ipc_app.control.sync.SyncGroup` (the sequencer's, with the group's band).
- **Force (pressure) control** for the legs in touch-down, preload and transfer: the
  same LADRC on the cap-side force ``p_A A_A - p_B A_B``; ``b0`` is the position ``b0``
  times the leg's stiffness against the invert (oil column in series with the
  contact), bandwidths ``walking.force_wc_rad_s`` and ``force_wo_rad_s`` or, left out,
  derived from the plant (:mod:`ipc_app.control.tuning`, as the position loops' are).
- **The twist mode** of a frame standing in position control: a force loop on its legs'
  twist sets that mode's share of their valve commands (:meth:`WalkLoops._twist_control`).
- **The hold** of every other walk cylinder (:meth:`WalkLoops._hold`): in the active
  group with its LADRC; outside it (frames at the slow cycle) with a slow proportional
  hold (:attr:`WalkLoops.SLOW_HOLD_RAD_S`), the travel pair with a proportional-integral
  one (:attr:`WalkLoops.TRAVEL_HOLD_RAD_S`).
- **The machine's statics and the legs' forces** as the checks see them: shares and
  margins from the measured upper platform (the workpiece's COG), the legs' forces at
  one instant less their rods' friction (:mod:`ipc_app.control.walk.forces`).
"""

from __future__ import annotations

import math
from collections.abc import Collection

import numpy as np
from numpy.typing import NDArray

from config.derived import viscous_damping_n_s_m
from config.schema import ProjectConfig
from ipc_app.control.ladrc import LADRC
from ipc_app.control.plant_gain import cylinder_b0
from ipc_app.control.tuning import (
    force_bandwidths,
    leg_stiffness_n_m,
    position_bandwidths,
    turn_bandwidths,
)
from ipc_app.control.walk.forces import (
    HeldLegShares,
    HoldingFrameSpeed,
    LegForceSamples,
    RodFriction,
)
from ipc_app.control.walk.phases import MAIN, PHASES, SUB, PhaseKind, PhaseRun
from ipc_app.model.kinematics import fit_layer
from ipc_app.model.support import (
    Edge,
    WalkingMachine,
    cap_side_forces_n,
    cog_projection,
    edges_margin,
    hull_edges,
    support_forces,
)
from ipc_app.planner.walk import Phase, WalkPlan

FloatArray = NDArray[np.float64]

#: the twist mode of four legs at (s_i a, t_i b): legs 1 and 3 against 2 and 4
#: the twist mode's sign of each of a frame's four legs: legs 1 and 3 against 2 and 4
TWIST_SIGNS = (1.0, -1.0, 1.0, -1.0)
TWIST = np.array(TWIST_SIGNS)


def _twist(v: list[float]) -> float:
    """``TWIST @ v`` on four plain floats."""
    return v[0] - v[1] + v[2] - v[3]


def twist_part(values: FloatArray) -> FloatArray:
    """The twist mode's part of four legs' ``values`` (:data:`TWIST`)."""
    return TWIST * (_twist(np.asarray(values, dtype=float).tolist()) / 4)


class WalkLoops:
    """The walk cylinders' loops, the machine's statics and the legs' force estimates
    of one walk plan; see the module docstring."""

    #: slow hold of a walk cylinder outside the active group: command = gain * error / b0
    SLOW_HOLD_RAD_S = 1.0
    #: the travel pair's slow hold, proportional-integral (:meth:`_hold`): command =
    #: (gain * error + integral gain * its integral) / b0. Its frames' slow cycle (rod
    #: positions every 50 ms, valve commands every 20 ms) costs it 0.3 rad of phase at
    #: 4 rad/s; at 1 rad/s the hanging M crept 0.7 mm with the integral (docs/curves.md)
    TRAVEL_HOLD_RAD_S = 4.0
    #: its integral gain, 1/s^2: a double pole at half its gain (critically damped on the
    #: rod's integrator)
    TRAVEL_HOLD_INTEGRAL_RAD2_S2 = TRAVEL_HOLD_RAD_S**2 / 4

    def __init__(self, cfg: ProjectConfig, period_s: float, plan: WalkPlan) -> None:
        _, self.walk = cfg.walking_sections()
        self.cfg = cfg
        self.period_s = period_s
        self.plan = plan
        #: the present phase (None: before the first)
        self.run: PhaseRun | None = None
        self.n = len(cfg.cylinders)
        self.leg_ids = plan.leg_ids
        self.legs = [cfg.cylinder(c).can_index for c in self.leg_ids]
        travel = [c for c in cfg.cylinders_by_can_index if c.role == "travel"]
        self.travel = [c.can_index for c in travel]
        self.upper = [cfg.cylinder(c).can_index for c in cfg.layers.upper.cylinders]
        self.walk_cylinders = self.legs + self.travel + self.upper
        by_index = cfg.cylinders_by_can_index
        self.half = np.array([c.stroke_m / 2 for c in by_index])
        #: the travel pair's extension with S centred under M (``e_0``), m
        self.centred_stroke_m = travel[0].stroke_m / 2
        self.b_t_m = self.walk.travel_half_span_m
        self.cap_area_m2 = np.array([c.cap_area_m2 for c in by_index])
        self.rod_area_m2 = np.array([c.rod_area_m2 for c in by_index])
        self._leg_cap_m2 = self.cap_area_m2[self.legs]
        self._leg_rod_m2 = self.rod_area_m2[self.legs]
        self._travel_cap_m2 = self.cap_area_m2[self.travel]
        self._travel_rod_m2 = self.rod_area_m2[self.travel]
        ctl = cfg.control
        self.feedforward = ctl.ladrc.reference_feedforward
        self.b0 = np.zeros(self.n)
        self.pos: dict[int, LADRC] = {}
        for i in self.walk_cylinders:
            cyl = by_index[i]
            self.b0[i] = cylinder_b0(cyl, cfg.hydraulics, order=ctl.ladrc.order)
            wc, wo = position_bandwidths(cfg, cyl)
            self.pos[i] = LADRC.from_config(ctl.ladrc, float(self.b0[i]), period_s, wc=wc, wo=wo)
        # the travel pair in the loop-rate group: its common mode (the pair moving the
        # frame) and its turn (the rods against each other turning the lifted frame about
        # the pivot, a far heavier mode: ipc_app.control.tuning.turn_plant), each its own
        # loop on the rods' mean and half difference
        travel_cyl = by_index[self.travel[0]]
        b0_t = float(self.b0[self.travel[0]])
        wc, wo = position_bandwidths(cfg, travel_cyl)
        self.pair_common = LADRC.from_config(ctl.ladrc, b0_t, period_s, wc=wc, wo=wo)
        #: the turn loop by the frame it turns (M lifted in phase 6, S in phase 1)
        self.pair_turn: dict[tuple[int, ...], LADRC] = {}
        for frame, legs in (("main", MAIN), ("sub", SUB)):
            wc, wo = turn_bandwidths(cfg, travel_cyl, frame)
            self.pair_turn[legs] = LADRC.from_config(ctl.ladrc, b0_t, period_s, wc=wc, wo=wo)
        #: the pair's two loops run (else they start again at the rods, bumpless)
        self.pair_live = False
        self.k_contact = self.walk.contact.stiffness_n_m
        #: each leg's rod friction (its plant's): Coulomb, N, and viscous, N s/m
        plants = [(by_index[i], cfg.plant_of(by_index[i])) for i in self.legs]
        self.coulomb_n = np.array([pl.coulomb_friction_n for _c, pl in plants])
        self.viscous_n_s_m = np.array(
            [viscous_damping_n_s_m(c, pl, cfg.hydraulics) for c, pl in plants]
        )
        self.rod_friction = RodFriction(self.coulomb_n, self.viscous_n_s_m, period_s)
        self.force_samples = LegForceSamples(self.legs)
        self.force: dict[int, LADRC] = {}
        #: each leg's stiffness against the invert, N/m (its force loop's ``b0`` and its
        #: known disturbance, :meth:`body_motion_n_s`)
        self.leg_k_n_m: dict[int, float] = {}
        for i in self.legs:
            cyl = by_index[i]
            self.leg_k_n_m[i] = leg_stiffness_n_m(cfg, cyl)
            b0 = cylinder_b0(cyl, cfg.hydraulics, order=1) * self.leg_k_n_m[i]
            wc, wo = force_bandwidths(cfg, cyl)
            self.force[i] = LADRC(1, b0, wc, wo, period_s, rate_limit=ctl.ladrc.rate_limit_per_s)
        #: the body's speed at the feet from the holding frame's rods
        self.body_speed = HoldingFrameSpeed(period_s)
        #: the legs (``can_index``) in force control
        self.force_mode: set[int] = set()
        #: the twist-mode controller of a standing frame: a force loop on its legs'
        #: twist, the mode's share of their valve commands (:meth:`_twist_control`)
        b0_f = float(np.mean([self.force[self.legs[j]].b0 for j in SUB]))
        self.twist = LADRC(
            1, b0_f, self.walk.twist_bandwidth_rad_s, self.walk.twist_observer_rad_s, period_s,
            rate_limit=ctl.ladrc.rate_limit_per_s,
        )  # fmt: skip
        self._twist_frame_now: tuple[int, ...] = ()
        self._twist_started = False
        self.machine = WalkingMachine(cfg, unloaded=plan.unloaded, standing=plan.standing)
        #: the eight-leg shares by S's position, per mm (emptied at each phase's start)
        self._share_cache: dict[int, tuple[float, FloatArray]] = {}
        self.held_shares = HeldLegShares()
        #: the hull's edges per (S's x at which they are taken, the standing legs)
        self._margin_edges: dict[tuple[float, tuple[int, ...]], list[Edge]] = {}
        #: the integral term of each travel cylinder held outside the active group (its
        #: command's share, from zero as it leaves the group; :meth:`_hold`)
        self.slow_integral: dict[int, float] = {}

    def _key_now(self) -> str:
        """The present phase's key (before the first: the plan's first phase's)."""
        return self.run.phase.key if self.run is not None else self.plan.phases[0].key

    # ----------------------------------------------------------------- the machine

    def forces_n(self, p: FloatArray) -> FloatArray:
        """Cap-side force of each leg (8,), N: ``p_A A_A - p_B A_B``."""
        idx = self.legs
        return cap_side_forces_n(p[idx], self._leg_cap_m2, self._leg_rod_m2)

    def x_s(self, x: FloatArray) -> float:
        """S's position along the rails, measured: the travel pair's mean less ``e_0``
        (summed in order and divided, as ``np.mean`` of so few values does)."""
        total = 0.0
        for i in self.travel:
            total += float(x[i])
        return total / len(self.travel) - self.centred_stroke_m

    def yaw_s_in_m(self, x: FloatArray) -> float:
        """S's yaw in M from the travel rods, rad (curves.md section 3): ``asin((e_1 -
        e_2) / (2 b_T))``, ``e_1`` the rod with the lower can_index (on the right)."""
        d = (float(x[self.travel[0]]) - float(x[self.travel[1]])) / (2.0 * self.b_t_m)
        return math.asin(min(1.0, max(-1.0, d)))

    def set_upper(self, x: FloatArray) -> None:
        """The upper platform's attitude fixes the workpiece's COG: from its rods."""
        up = self.cfg.layers.upper
        fit = fit_layer(x[self.upper] - self.half[self.upper], up.a_m, up.b_m)
        self.machine = WalkingMachine(
            self.cfg, float(fit.roll), float(fit.pitch), self.plan.unloaded, self.plan.standing
        )
        self.held_shares.clear()
        self._margin_edges.clear()

    def share(self, x_s: float, legs: tuple[int, ...]) -> FloatArray:
        """Expected forces (8,) with ``legs`` standing (minimum norm), N."""
        out = np.zeros(8)
        pts = self.machine.legs_xy(x_s)[list(legs)]
        out[list(legs)] = support_forces(
            pts, self.machine.mass_kg, self.machine.cog(x_s), self.machine.g_base
        )
        return out

    def _share8(self, x_s: float) -> FloatArray:
        """The eight-leg share (8,) with S at ``x_s``, N (kept per mm within a phase)."""
        key = round(x_s * 1e3)
        hit = self._share_cache.get(key)
        if hit is None:
            hit = (x_s, self.share(x_s, MAIN + SUB))
            self._share_cache[key] = hit
        return hit[1]

    def margin(self, x_s: float, legs: tuple[int, ...]) -> float:
        """The static stability margin with ``legs`` standing, S at ``x_s``, m. The
        hull's edges are kept per set of legs: M's do not move with ``x_s`` and S's move
        with it (the COG's projection is taken into S's frame instead), only a mix of
        both frames is kept per ``x_s`` (S stands still in every phase but a travel)."""
        x_ref, all_sub = self.machine.frame_reference(legs, x_s)
        key = (x_ref, legs)
        edges = self._margin_edges.get(key)
        if edges is None:
            edges = hull_edges(self.machine.legs_xy(x_ref)[list(legs)])
            if len(self._margin_edges) > 64:  # mixed frames per x_s: bounded
                self._margin_edges.clear()
            self._margin_edges[key] = edges
        px, py = cog_projection(self.machine.cog_xyz(x_s), self.machine.g_base).tolist()
        return edges_margin(edges, px - (x_s if all_sub else 0.0), py)

    @staticmethod
    def _frame(ids: tuple[str, ...], leg_ids: tuple[str, ...]) -> tuple[int, ...]:
        return tuple(leg_ids.index(c) for c in ids if c in leg_ids)

    def friction_n(self) -> FloatArray:
        """Each leg's rod friction now (8,), N (:class:`~.forces.RodFriction`)."""
        return self.rod_friction.friction_n()

    def aligned_forces_n(self, now: float, f: FloatArray, age_s: FloatArray | None) -> FloatArray:
        """The legs' cap-side forces (8,) at one instant, N, for the checks
        (:class:`~.forces.LegForceSamples`)."""
        return self.force_samples.aligned_n(now, f, age_s)

    def body_motion_n_s(
        self, holding: tuple[int, ...], x: FloatArray, force_legs: Collection[int]
    ) -> dict[int, float]:
        """Each force-controlled leg's (``can_index`` in ``force_legs``) known
        disturbance this period, N/s: ``-k_leg w``, ``w`` the body's speed at its foot
        from the ``holding`` frame's rods (:class:`~.forces.HoldingFrameSpeed`); none
        while no frame of four holds or no leg is in force control."""
        speed = self.body_speed
        if not force_legs or len(holding) != 4:
            speed.restart()
            return {}
        rods = [float(x[self.legs[j]]) for j in holding]
        if speed.frame != holding:
            speed.start(holding, self.machine.legs_xy(self.x_s(x)), rods)
        else:
            speed.update(rods)
        k = self.leg_k_n_m
        return {i: -k[i] * speed.at(self.legs.index(i)) for i in force_legs}

    # ----------------------------------------------------------------- the hold

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
        active group, the slow hold outside it. ``known``: a rod speed the loop is told of
        (its oil column's decompression, m/s).

        The travel pair's slow hold is proportional-integral: a frame hanging on it
        outside the active group (a lowering or a lift) loads it along a grade, a loaded
        cylinder leaks across its piston and out (its chambers' pressures), and a rod at
        rest needs its valve open by what passes that leakage; a proportional hold opens
        it only by a position error (the leak's speed over the gain: the hanging M crept
        2.8 mm in phase 7a with the 40 t part on a 3 % rise, docs/curves.md). The
        integral starts at zero as the pair leaves the active group (at a phase's start,
        its rods at rest: the proportional part's zero there too), and stops growing
        while the command is saturated. Started at the LADRCs' last command instead
        (each one's, the pair's mean, or its observers' holding command) it took the
        HFDU project's unloaded walk back to 110.0-113.9 % at M's touch-down against the
        110 % overload trip (from zero: 107.6 %; the proportional hold's 107.7 %). The
        other walk cylinders keep the proportional hold (their creep reaches no walk
        goal)."""
        dt = self.period_s
        refs_l, x_l, rates_l = refs.tolist(), x.tolist(), rates.tolist()
        pos, b0, travel = self.pos, self.b0.tolist(), self.travel
        pair = all(i in active and not (skip and i in skip) for i in travel)
        if pair:
            self._drive_pair(u, refs_l, x_l, rates_l, known)
        else:
            self.pair_live = False
        for i in self.walk_cylinders:
            if (skip and i in skip) or (pair and i in travel):
                continue
            if i in active:
                self.slow_integral.pop(i, None)
                d = known.get(i, 0.0) if known else 0.0
                u[i] = pos[i].update(refs_l[i], x_l[i], rates_l[i], d)
                continue
            e = refs_l[i] - x_l[i]
            if i not in travel:
                ui = max(-1.0, min(1.0, self.SLOW_HOLD_RAD_S * e / b0[i]))
                u[i] = ui
                pos[i].reset(x_l[i], ui)
                continue
            integral = self.slow_integral.get(i, 0.0)
            u0 = self.TRAVEL_HOLD_RAD_S * e / b0[i] + integral
            ui = max(-1.0, min(1.0, u0))
            u[i] = ui
            if u0 == ui:
                integral += self.TRAVEL_HOLD_INTEGRAL_RAD2_S2 * e * dt / b0[i]
            self.slow_integral[i] = integral
            pos[i].reset(x_l[i], ui)

    def _drive_pair(
        self,
        u: FloatArray,
        refs: list[float],
        x: list[float],
        rates: list[float],
        known: dict[int, float] | None,
    ) -> None:
        """The travel pair in the active group: its common loop on the rods' mean, its
        turn loop on their half difference (the rod with the lower can_index first);
        each rod's command their sum or difference. Started bumpless at the rods and
        their last commands."""
        i, j = self.travel
        lifted = PHASES[self._key_now()].frame
        common, turn = self.pair_common, self.pair_turn[lifted]
        if not self.pair_live:
            ui, uj = self.pos[i].command, self.pos[j].command
            common.reset(0.5 * (x[i] + x[j]), 0.5 * (ui + uj))
            turn.reset(0.5 * (x[i] - x[j]), 0.5 * (ui - uj))
            self.pair_live = True
        di = known.get(i, 0.0) if known else 0.0
        dj = known.get(j, 0.0) if known else 0.0
        uc = common.update(
            0.5 * (refs[i] + refs[j]), 0.5 * (x[i] + x[j]), 0.5 * (rates[i] + rates[j]),
            0.5 * (di + dj),
        )  # fmt: skip
        ud = turn.update(
            0.5 * (refs[i] - refs[j]), 0.5 * (x[i] - x[j]), 0.5 * (rates[i] - rates[j]),
            0.5 * (di - dj),
        )  # fmt: skip
        for k, cmd in ((i, uc + ud), (j, uc - ud)):
            uk = max(-1.0, min(1.0, cmd))
            u[k] = uk
            self.pos[k].reset(x[k], uk)

    # ----------------------------------------------------------------- the twist mode

    def _twist_frame(self, ph: Phase) -> tuple[int, ...]:
        """The frame whose twist mode is controlled in phase ``ph``: the one that stands
        in position control while the travel pair moves (alone on the invert) or while
        the other frame lowers and preloads; none in a lift or a transfer."""
        role = PHASES[ph.key]
        return role.standing if role.kind.holds_twist else ()

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
        t = _twist([float(x[i] - refs[i]) for i in idx]) / 4
        for i, sign in zip(idx, TWIST_SIGNS, strict=True):
            refs[i] += sign * t
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
        (``plan_f``; minimum norm: none), with the force loops' ``b0`` (the legs'
        stiffness in series with the contact), crossover ``walking.twist_bandwidth_rad_s``
        and observer bandwidth ``walking.twist_observer_rad_s`` while the travel pair
        moves and ``walking.twist_observer_touchdown_rad_s`` while the other frame lowers
        and preloads (switched with the state kept). Each position loop's observer is
        told the command applied (:meth:`LADRC.apply`). The state carries over from one
        phase to the next while the same frame stays controlled."""
        if len(frame) != 4:
            return
        self.twist.set_observer(
            self.walk.twist_observer_rad_s
            if PHASES[self._key_now()].kind is PhaseKind.TRAVEL
            else self.walk.twist_observer_touchdown_rad_s
        )
        idx = [self.legs[j] for j in frame]
        f_l, plan_l, u_l = f.tolist(), plan_f.tolist(), u.tolist()
        twist_now_n = _twist([f_l[j] for j in frame]) / 4
        twist_ref_n = _twist([plan_l[j] for j in frame]) / 4
        u_pos = [u_l[i] for i in idx]
        u_twist_pos = _twist(u_pos) / 4
        if not self._twist_started:
            self.twist.reset(twist_now_n, u_twist_pos)
            self._twist_started = True
        du = self.twist.update(twist_ref_n, twist_now_n) - u_twist_pos
        for k, (i, sign) in enumerate(zip(idx, TWIST_SIGNS, strict=True)):
            u[i] = self.pos[i].apply(u_pos[k] + sign * du)
