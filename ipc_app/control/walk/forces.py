"""The walk's force estimates (docs/walking.md, "Expected shares" and "One instant for
the checks"): what each leg puts on the body, from pressures sampled at different
instants, less its rod's friction; and the body's equilibrium the expected shares and
the releasing legs' rates come from.

- :class:`RodFriction`: each leg's rod friction from its measured motion.
- :class:`LegForceSamples`: the legs' forces taken at one instant.
- :class:`HoldingFrameSpeed`: the body's speed at the feet, from the holding frame's rods.
- :func:`equilibrium_matrix`, :func:`min_norm_forces` and :class:`HeldLegShares`: the
  body's equilibrium (heave, roll, pitch) on the eight legs, the minimum-norm forces of
  some legs that give a load, a held leg's share of what the others leave.

Constant work per cycle: eight legs, on plain floats where numpy's overhead would
dominate (the results are those numpy would give, element by element).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from ipc_app.model.support import WalkingMachine

FloatArray = NDArray[np.float64]


class RodFriction:
    """Each leg's rod friction (8,), N, opposing its measured motion (extending
    positive): its plant's Coulomb friction (full above :attr:`COULOMB_SPEED_M_S`) and
    viscous damping (``config.derived.viscous_damping_n_s_m``) at the rod's speed over
    :attr:`MOTION_WINDOW_S`. The pressures carry it on top of what the leg puts on the
    body."""

    #: a lowering rod's speed is taken over this window (the pressures' 50 ms cycle), s
    MOTION_WINDOW_S = 0.05
    #: a rod's Coulomb friction is taken full above this speed, linear below, m/s: near
    #: standstill its sign is not known (the speed over :attr:`MOTION_WINDOW_S` of 1 um
    #: positions, a rod stopping or reversing within the window; the rig's friction is
    #: smooth over some 0.3-0.5 mm/s, docs/hil.md); with 0.1 mm/s the estimate of a
    #: standing leg's force swung by the whole 2 kN as its measured speed crossed zero
    COULOMB_SPEED_M_S = 5e-4

    def __init__(self, coulomb_n: FloatArray, viscous_n_s_m: FloatArray, period_s: float) -> None:
        #: each leg's Coulomb friction, N, and viscous damping, N s/m
        self.coulomb_n = coulomb_n
        self.viscous_n_s_m = viscous_n_s_m
        self._friction = list(zip(coulomb_n.tolist(), viscous_n_s_m.tolist(), strict=True))
        rows = max(2, round(self.MOTION_WINDOW_S / period_s) + 1)
        #: the legs' last rod positions over :attr:`MOTION_WINDOW_S` (a ring), m, the
        #: machine time of each row, s, and the row the next cycle writes
        self.positions_m = np.zeros((rows, 8))
        self.times_s = [0.0] * rows
        self.next_row = 0
        #: the Coulomb friction each leg's force may carry that :meth:`friction_n` could
        #: not tell from its motion, N (8, of the last call): the whole of it at rest,
        #: none at :attr:`COULOMB_SPEED_M_S` or faster (a seal at rest holds any force
        #: within it; docs/walking.md, the expected shares)
        self.unknown_n: tuple[float, ...] = tuple(coulomb_n.tolist())

    def restart(self, now_s: float, leg_positions_m: FloatArray) -> None:
        """Every row at the legs' positions now: at rest."""
        self.positions_m[:] = leg_positions_m
        self.times_s = [now_s] * len(self.times_s)

    def record(self, now_s: float, leg_positions_m: FloatArray) -> None:
        """This cycle's rod positions of the eight legs."""
        row = self.next_row % self.positions_m.shape[0]
        self.positions_m[row] = leg_positions_m
        self.times_s[row] = now_s
        self.next_row += 1

    def friction_n(self) -> FloatArray:
        """Each leg's rod friction now (8,), N.

        The speed is over the samples' own times: across a stop (a suspension, a hold)
        the window's oldest sample is from before it, and taken as one window old it
        read a standing leg's creep as several times as fast (10-20 kN of viscous
        friction after a 140 ms suspension, an overload)."""
        n = self.positions_m.shape[0]
        k_new, k_old = (self.next_row - 1) % n, self.next_row % n
        newest = self.positions_m[k_new].tolist()
        oldest = self.positions_m[k_old].tolist()
        span_s = self.times_s[k_new] - self.times_s[k_old]
        c_speed = self.COULOMB_SPEED_M_S
        out = [0.0] * 8
        if not span_s > 0.0:
            self.unknown_n = tuple(self.coulomb_n.tolist())
            return np.array(out)
        unknown = [0.0] * 8
        for j, (coulomb, viscous) in enumerate(self._friction):
            v = (newest[j] - oldest[j]) / span_s
            c = v / c_speed
            c = -1.0 if c < -1.0 else (1.0 if c > 1.0 else c)
            out[j] = coulomb * c + viscous * v
            unknown[j] = coulomb * (1.0 - abs(c))
        self.unknown_n = tuple(unknown)
        return np.array(out)


class HoldingFrameSpeed:
    """The body's vertical speed at the feet, from the rods of the frame that holds it
    (decision 0041).

    While one frame holds the body in position control and the other's legs run in
    force control (a touched foot, a preload, a transfer), the body's motion on the
    holding legs' oil columns moves the force-controlled feet too: a foot's force changes
    by ``-k_leg w`` (``w`` the body's speed there, up positive), a disturbance the force
    loop would otherwise learn a period late through its observer, against a plant whose
    valve has a fraction of its gain under load, and the two frames ring in roll (0040).
    So each force loop is told it as a known disturbance.

    ``w``: the plane through the holding legs' rod extensions (least squares over the
    four), differenced each period and low-passed over :attr:`FILTER_S`, taken at the
    foot. The filter starts at rest when the holding frame changes and after a stop."""

    #: the low-pass of the plane's rates, s: four periods of the 5 ms loop smooth the
    #: rods' 1 um resolution (a 1 um step is 0.2 mm/s over one period)
    FILTER_S = 0.02

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        #: the holding frame (leg indices; ``()``: none, at rest from the next start)
        self.frame: tuple[int, ...] = ()
        self._fit = np.zeros((3, 4))
        self._xy: list[list[float]] = []
        self._coef: list[float] = [0.0, 0.0, 0.0]
        self._rate: list[float] = [0.0, 0.0, 0.0]

    def restart(self) -> None:
        """No frame holds (or a stop): the next :meth:`start` begins at rest."""
        self.frame = ()

    def start(self, frame: tuple[int, ...], legs_xy: FloatArray, rods_m: list[float]) -> None:
        """``frame`` (four leg indices) holds from now, the legs at ``legs_xy`` (8, 2),
        its rods at ``rods_m`` (4, m); the body at rest."""
        self.frame = frame
        self._fit = np.linalg.pinv(np.column_stack([np.ones(4), legs_xy[list(frame)]]))
        self._xy = legs_xy.tolist()
        self._coef = (self._fit @ np.array(rods_m)).tolist()
        self._rate = [0.0, 0.0, 0.0]

    def update(self, rods_m: list[float]) -> None:
        """This period's rod extensions of the holding frame (4, m)."""
        coef = (self._fit @ np.array(rods_m)).tolist()
        dt = self.period_s
        gain = dt / (self.FILTER_S + dt)
        for k in range(3):
            speed = (coef[k] - self._coef[k]) / dt
            self._rate[k] += gain * (speed - self._rate[k])
        self._coef = coef

    def at(self, leg: int) -> float:
        """The body's speed at leg ``leg``'s foot (index 0-7), m/s, up positive."""
        r, (x_m, y_m) = self._rate, self._xy[leg]
        return r[0] + r[1] * x_m + r[2] * y_m


class LegForceSamples:
    """The legs' last two pressure samples, to take their forces at one instant.

    The PLC samples each cylinder's pressures at its fast cycle (50 ms), the frames of
    different cylinders at different instants; while feet touch down or take load the
    forces change by up to some 10 kN within that cycle, and a standing leg's force from
    one instant judged against a share computed from the others' forces of another is
    off by as much (seen: 113 % of the share in the touch-down of M while S stands,
    every leg within 2 % of its share in the simulator's truth). So each leg's force is
    taken at the instant of the oldest latest sample: a leg sampled since is
    interpolated between its last two samples."""

    def __init__(self, legs: list[int]) -> None:
        #: each leg's ``can_index`` (where its sample's age is)
        self.legs = legs
        #: each leg's last two samples: cap-side force, N, and sample time, s
        self._f_last = [0.0] * 8
        self._f_prev = [0.0] * 8
        self._t_last = [-math.inf] * 8
        self._t_prev = [-math.inf] * 8

    def aligned_n(self, now_s: float, force_n: FloatArray, age_s: FloatArray | None) -> FloatArray:
        """The legs' cap-side forces (8,) at one instant, N, from this cycle's
        ``force_n`` and each cylinder's sample age (19,), s (None: all of ``now_s``)."""
        if age_s is None:
            return force_n
        ages = np.asarray(age_s, dtype=float).tolist()
        fs = force_n.tolist()
        t_last, t_prev = self._t_last, self._t_prev
        f_last, f_prev = self._f_last, self._f_prev
        for j, i in enumerate(self.legs):
            t = now_s - ages[i]
            if not math.isfinite(t):
                continue
            if t > t_last[j] + 1e-9:
                f_prev[j], t_prev[j] = f_last[j], t_last[j]
                t_last[j] = t
            f_last[j] = fs[j]
        known = [t for t in t_last if math.isfinite(t)]
        if not known:
            return force_n
        t_c = min(known)
        for j in range(8):
            t1, t0 = t_last[j], t_prev[j]
            if math.isfinite(t0) and t1 > t_c and t1 > t0:
                w = min(1.0, max(0.0, (t_c - t0) / (t1 - t0)))
                fs[j] = f_prev[j] + w * (f_last[j] - f_prev[j])
        return np.array(fs)


def equilibrium_matrix(machine: WalkingMachine, x_s: float) -> FloatArray:
    """(3, 8): what each leg's vertical force adds to the body's vertical force and to
    its moments about x and y (its position's y and -x), S at ``x_s``."""
    a = np.empty((3, 8))
    a[0] = 1.0
    # WalkingMachine.legs_xy(x_s) written out: S's legs shifted by (x_s, 0)
    a[1, :4] = machine.main_legs_xy[:, 1]
    a[1, 4:] = machine.sub_legs_xy[:, 1] + 0.0
    a[2, :4] = -machine.main_legs_xy[:, 0]
    a[2, 4:] = -(machine.sub_legs_xy[:, 0] + x_s)
    return a


def min_norm_forces(a: FloatArray, legs: list[int], rhs: FloatArray) -> FloatArray:
    """The minimum-norm forces of ``legs`` whose sum through ``a`` is ``rhs``."""
    a_r = a[:, legs]
    return a_r.T @ np.linalg.solve(a_r @ a_r.T, rhs)


class HeldLegShares:
    """Expected forces: a leg held in position carries its minimum-norm share of what
    the other legs leave of the load (the body's equilibrium with their forces on it);
    the others the plan's force.

    What depends on the legs' positions alone is kept while the held legs stay: S's
    columns of :func:`equilibrium_matrix` at ``x_s`` are its columns at 0 with ``x_s``
    times the heave row taken from the pitch row (``a(x_s) = T a(0)``), so the held legs'
    minimum-norm map at ``x_s`` is its map at 0 after ``T^-1`` when they are all S's, the
    same map when they are all M's, and kept per ``x_s`` only for a mix (constant within
    every phase but a travel, where one frame is held). On plain floats: a travel asks
    every cycle. :meth:`clear` when the machine changes."""

    def __init__(self) -> None:
        self._maps: dict[tuple[float, tuple[int, ...]], list[list[float]]] = {}
        self._xy: tuple[list[float], list[float]] | None = None

    def clear(self) -> None:
        self._maps.clear()
        self._xy = None

    def _map(
        self, machine: WalkingMachine, x_ref: float, held: tuple[int, ...]
    ) -> list[list[float]]:
        """The held legs' minimum-norm map (len(held) rows of 3), S at ``x_ref``."""
        key = (x_ref, held)
        m = self._maps.get(key)
        if m is None:
            a_r = equilibrium_matrix(machine, x_ref)[:, list(held)]
            m = np.linalg.solve(a_r @ a_r.T, a_r).T.tolist()  # the normal matrix symmetric
            if len(self._maps) > 64:  # a mix of held legs per x_s: bounded
                self._maps.clear()
            self._maps[key] = m
        return m

    def expected_n(
        self,
        machine: WalkingMachine,
        x_s: float,
        eight_leg_share_n: FloatArray,
        contact_n: FloatArray,
        plan_n: FloatArray,
        held: list[int],
    ) -> FloatArray:
        """``plan_n`` with the ``held`` legs' entries their share of the load
        (``eight_leg_share_n``'s, any equilibrium gives it) less what the other legs'
        ``contact_n`` carry, S at ``x_s`` (:func:`min_norm_forces` of the held legs, to
        rounding)."""
        if not held:
            return plan_n.copy()
        if self._xy is None:
            xy = equilibrium_matrix(machine, 0.0)
            self._xy = (xy[1].tolist(), xy[2].tolist())
        ys, xs0 = self._xy  # each leg's moment arms with S at 0: y, -x
        n_main = len(machine.main_legs_xy)
        share, contact = eight_leg_share_n.tolist(), contact_n.tolist()
        held_set = set(held)
        # the load less what the others carry, about the body's axes with S at 0
        heave = roll = pitch = shift = 0.0
        for j in range(len(share)):
            f = share[j] if j in held_set else share[j] - contact[j]
            heave += f
            roll += ys[j] * f
            pitch += xs0[j] * f
            if j >= n_main:
                shift += f
        pitch -= x_s * shift  # S's legs' pitch arms at x_s
        x_ref, all_sub = machine.frame_reference(held, x_s)
        if all_sub:
            pitch += x_s * heave  # T^-1: the map kept at 0
        out = plan_n.copy()
        for j, row in zip(held, self._map(machine, x_ref, tuple(held)), strict=True):
            out[j] = row[0] * heave + row[1] * roll + row[2] * pitch
        return out
