"""The walking rig: the machine body on eight legs with foot contact (walking.md sections
1-3, docs/walking.md).

Model (what :class:`hil_sim.rig.Rig` has, and how this differs)
------------------------------------------------------------------
- The body is M and S joined by the rails: one rigid body in heave, roll and pitch
  (``q[0:3]``, relative to the base plane at world x = 0) plus ``x_S``, S's position along
  the rails. The upper platform on it is the rig's (``q[3:6]``). Its bodies: the YAML's
  layer bodies, ``frames.main.bodies`` (lower platform frame) and ``frames.sub.bodies``
  (S's frame, placed at ``x_S``).
- Each of the eight legs is a cylinder whose barrel is fixed to the body at
  ``(s_i a_M, t_i b_M)`` (main) or ``(x_S + s_i a_S, t_i b_S)`` (sub) and whose rod end is
  a foot: a point mass (``rod_mass_kg``) with its own height ``h`` (base frame). The rod
  position is ``stroke/2 + d_i(q) - h`` (``d_i``: the body point's height, model.md
  section 3); at ``h = 0`` and a level body at mid-stroke the foot just touches the base
  plane.
- Foot contact is unilateral: with the foot ``pen = ground(x, y) - h`` below the invert,
  ``N = max(0, k pen - c h')`` (``walking.contact``: stiffness ``k``; ``c = 2 zeta
  sqrt(k m_foot)``, the damping ratio of the foot's own mode, ``m_foot`` the foot's inertia
  :attr:`WalkingRig.foot_inertia_kg`); in the air ``N = 0``. The
  invert is the base plane raised by :attr:`WalkingRig.invert_height_m`, plus the
  scenario's ground offsets (a step at a ring joint, a hole), evaluated at the foot's
  world position. ``invert_height_m`` is M's feet's compression in the start state (the
  machine standing on M with its part, about 0.9 mm): the body starts where the attitude
  rig's does (``q = 0`` in heave, the rods at mid-stroke: the part at its home pose), so a
  placement after a walk sets the part where it does without one.
- Along x each frame is a body of its own: world positions ``X_M`` and ``X_S = X_M +
  x_S``, the simulator's truth. The two travel cylinders join them (rod position ``e_0 +
  x_S``, ``e_0`` mid-stroke; their force pushes S forward and M back) and gravity along
  the base's x acts on both. A frame's feet hold it by friction: an elasto-plastic
  (bristle) model per frame, a shear spring ``k_t`` with damping to an anchor, the force
  capped at ``mu * sum N`` of its feet; above the cap the anchor is dragged along (the
  feet slip) and the slip is counted in :attr:`WalkingRig.slip_m`.
- Hydraulics, valves, load-holding valves and end stops are the rig's, integrated with
  the same RK4 in one numba kernel; the mass matrix is evaluated once per PLC scan.
"""

from __future__ import annotations

import math

import numpy as np

from config.derived import without_rods
from config.schema import ProjectConfig
from hil_sim._jit import jit
from hil_sim.rig import (
    _Q,
    _QD,
    _SIGNS,
    _V,
    _X,
    N_STATE,
    FloatArray,
    IntArray,
    N,
    Rig,
    _add_pad_forces,
    _mass_and_gravity,
    cylinder_forces,
    extension_and_jacobian,
    inverse,
    plate_inertia,
)

#: offsets of the walking state after the rig's: foot heights, foot speeds, X_M, V_M, X_S, V_S
_H = N_STATE
_HD = _H + 8
_XW = _HD + 8
N_WALK_STATE = _XW + 4
#: ground offset slots: rows (x_from, x_to, y_from, y_to, dz) in the base frame, m
N_GROUND = 8


@jit
def ground_height(xw, yw, ground):
    """Invert height above the base plane at ``(xw, yw)``: the sum of the offsets there."""
    z = 0.0
    for k in range(ground.shape[0]):
        if ground[k, 0] <= xw < ground[k, 1] and ground[k, 2] <= yw < ground[k, 3]:
            z += ground[k, 4]
    return z


@jit
def _walk_derivative(
    y, dy, u, ports, leak, f_ext, p, up_idx, up_xy, up_half, leg_idx, leg_xy, leg_sub,
    leg_half, travel_idx, e0, m_inv, q_g, foot_m, foot_inertia, g_b, k_c, c_c, ground, fric, anchor,
    k_t, c_t, mass_x, pads, x_out, f_out, n_out, pad_out,
):  # fmt: skip
    q = y[_Q : _Q + 6]
    qd = y[_QD : _QD + 6]
    x = x_out[0]
    v = x_out[1]
    for i in range(N):
        x[i] = y[_X + i]
        v[i] = y[_V + i]
    x_s = y[_XW + 2] - y[_XW]
    v_s = y[_XW + 3] - y[_XW + 1]
    jup = np.empty((4, 3))
    for j in range(4):
        d, j0, j1, j2 = extension_and_jacobian(q[3], q[4], q[5], up_xy[j, 0], up_xy[j, 1])
        jup[j, 0], jup[j, 1], jup[j, 2] = j0, j1, j2
        i = up_idx[j]
        x[i] = up_half[j] + d
        v[i] = j0 * qd[3] + j1 * qd[4] + j2 * qd[5]
    jleg = np.empty((8, 3))
    for j in range(8):
        px = leg_xy[j, 0] + x_s * leg_sub[j]
        d, j0, j1, j2 = extension_and_jacobian(q[0], q[1], q[2], px, leg_xy[j, 1])
        jleg[j, 0], jleg[j, 1], jleg[j, 2] = j0, j1, j2
        i = leg_idx[j]
        x[i] = leg_half[j] + d - y[_H + j]
        v[i] = j0 * qd[0] + j1 * qd[1] + j2 * qd[2] - y[_HD + j]
    for j in range(2):
        i = travel_idx[j]
        x[i] = e0 + x_s
        v[i] = v_s
    cylinder_forces(y, dy, u, ports, leak, f_ext, p, x, v, f_out)
    normal = np.zeros(2)
    for j in range(8):
        i = leg_idx[j]
        frame = leg_sub[j]
        xw = y[_XW + 2 * frame] + leg_xy[j, 0]
        pen = ground_height(xw, leg_xy[j, 1], ground) - y[_H + j]
        nf = 0.0
        if pen > 0.0:
            nf = k_c * pen - c_c * y[_HD + j]
            if nf < 0.0:
                nf = 0.0
        n_out[j] = nf
        normal[frame] += nf
        dy[_H + j] = y[_HD + j]
        dy[_HD + j] = (nf - f_out[i] + foot_m * g_b[2]) / foot_inertia
        dy[_X + i] = 0.0
        dy[_V + i] = 0.0
    gen = np.empty(6)
    for a in range(6):
        gen[a] = q_g[a]
    _add_pad_forces(q, pads, pad_out, gen)
    for j in range(4):
        i = up_idx[j]
        for a in range(3):
            gen[3 + a] += jup[j, a] * f_out[i]
        dy[_X + i] = 0.0
        dy[_V + i] = 0.0
    for j in range(8):
        i = leg_idx[j]
        for a in range(3):
            gen[a] += jleg[j, a] * f_out[i]
    for a in range(6):
        dy[_Q + a] = qd[a]
    for a in range(6):
        acc = 0.0
        for b in range(6):
            acc += m_inv[a, b] * gen[b]
        dy[_QD + a] = acc
    f_travel = 0.0
    for j in range(2):
        i = travel_idx[j]
        f_travel += f_out[i]
        dy[_X + i] = 0.0
        dy[_V + i] = 0.0
    for frame in range(2):
        pos = y[_XW + 2 * frame]
        vel = y[_XW + 2 * frame + 1]
        cap = fric[frame] * normal[frame]
        tf = -k_t * (pos - anchor[frame]) - c_t[frame] * vel
        if tf > cap:
            tf = cap
        elif tf < -cap:
            tf = -cap
        push = f_travel if frame == 1 else -f_travel
        dy[_XW + 2 * frame] = vel
        dy[_XW + 2 * frame + 1] = (push + tf) / mass_x[frame] + g_b[0]


@jit
def _walk_advance(
    y, u, ports, leak, f_ext, p, up_idx, up_xy, up_half, leg_idx, leg_xy, leg_sub, leg_half,
    travel_idx, e0, body_m, body_c, body_i, body_layer, rod_xy, rod_m, origin_u, foot_m,
    foot_inertia, g_b, k_c, c_c, ground, fric, anchor, slip, k_t, c_t, mass_x, pads, h, n_steps,
    x_out, f_out, n_out, pad_out,
):  # fmt: skip
    """``n_steps`` RK4 steps; after each, the friction anchors follow a slipping frame."""
    n = y.shape[0]
    k1 = np.empty(n)
    k2 = np.empty(n)
    k3 = np.empty(n)
    k4 = np.empty(n)
    tmp = np.empty(n)
    m_mat, q_g = _mass_and_gravity(
        y[_Q : _Q + 6], body_m, body_c, body_i, body_layer, rod_xy, rod_m, origin_u, g_b
    )
    m_inv = inverse(m_mat)
    hh = 0.5 * h
    h6 = h / 6.0
    args = (
        u, ports, leak, f_ext, p, up_idx, up_xy, up_half, leg_idx, leg_xy, leg_sub, leg_half,
        travel_idx, e0, m_inv, q_g, foot_m, foot_inertia, g_b, k_c, c_c, ground, fric, anchor,
        k_t, c_t, mass_x, pads, x_out, f_out, n_out, pad_out,
    )  # fmt: skip
    if n_steps == 0:
        _walk_derivative(y, k1, *args)
    for _ in range(n_steps):
        _walk_derivative(y, k1, *args)
        for a in range(n):
            tmp[a] = y[a] + hh * k1[a]
        _walk_derivative(tmp, k2, *args)
        for a in range(n):
            tmp[a] = y[a] + hh * k2[a]
        _walk_derivative(tmp, k3, *args)
        for a in range(n):
            tmp[a] = y[a] + h * k3[a]
        _walk_derivative(tmp, k4, *args)
        for a in range(n):
            y[a] += h6 * (k1[a] + 2.0 * k2[a] + 2.0 * k3[a] + k4[a])
        _walk_derivative(y, k1, *args)
        for frame in range(2):
            normal = 0.0
            for j in range(8):
                if leg_sub[j] == frame:
                    normal += n_out[j]
            cap = fric[frame] * normal
            pos = y[_XW + 2 * frame]
            spring = k_t * (pos - anchor[frame])
            if spring > cap or spring < -cap:
                moved = pos - math.copysign(cap / k_t, spring) - anchor[frame]
                anchor[frame] += moved
                if normal > 0.0:
                    slip[frame] += abs(moved)


class WalkingRig(Rig):
    """The rig with the eight legs on the invert (module docstring).

    Starts in walking.md's start state: M standing level at mid-stroke on its feet, S
    lifted by ``walking.clearance_mm``, ``x_S`` at the rear end of the step
    (``-step/2``), ``X_M = 0``; valves closed, pressures holding the load.
    """

    #: tangential (shear) stiffness of a frame's feet on the invert, N/m (all four)
    shear_stiffness_n_m = 5.0e7
    #: inertia of a foot (rod, piston, foot) in its vertical motion, kg. Its weight is
    #: ``rod_mass_kg``; the inertia puts the foot's own mode near 40 Hz, inside what RK4 at
    #: 0.25 ms integrates with the leg's regularized Coulomb friction (150 kg is not).
    foot_inertia_kg = 3000.0

    def __init__(
        self,
        cfg: ProjectConfig,
        step_s: float = 0.25e-3,
        rod_mass_kg: float = 150.0,
        load_holding_valves: bool = True,
    ) -> None:
        if cfg.frames is None or cfg.walking is None:
            raise ValueError("the walking rig needs the project's frames and walking sections")
        super().__init__(cfg, step_s, rod_mass_kg, load_holding_valves)
        frames, walk = cfg.frames, cfg.walking
        self.walking = walk
        by_id = {c.id: c for c in cfg.cylinders_by_can_index}
        main = [by_id[c].can_index for c in cfg.layers.lower.cylinders]
        sub_cyls = sorted(
            (c for c in cfg.cylinders if c.role == "sub_leg"), key=lambda c: c.position or 0
        )
        self.leg_ids: tuple[str, ...] = tuple(cfg.layers.lower.cylinders) + tuple(
            c.id for c in sub_cyls
        )
        self._leg_idx = np.array(main + [c.can_index for c in sub_cyls], dtype=np.int64)
        self._leg_sub = np.array([0] * 4 + [1] * 4, dtype=np.int64)
        lo = cfg.layers.lower
        self._leg_xy = np.array(
            [(sx * lo.a_m, sy * lo.b_m) for sx, sy in _SIGNS]
            + [(sx * frames.sub.a_m, sy * frames.sub.b_m) for sx, sy in _SIGNS]
        )
        self._leg_half = np.array([by_id[cid].stroke_m / 2 for cid in self.leg_ids])
        travel = [c for c in cfg.cylinders_by_can_index if c.role == "travel"]
        self._travel_idx = np.array([c.can_index for c in travel], dtype=np.int64)
        self.travel_mid_m = travel[0].stroke_m / 2
        for k in range(8):
            self.platform_mask[self._leg_idx[k]] = True
        self.platform_mask[self._travel_idx] = True
        # bodies: the rig's (layer bodies, load-step slots) + main and sub frame structure
        self._n_rig_bodies = len(self._body_m)
        # the frames' bodies less their legs' rods and feet, which are masses of their own
        main_b, sub_b = without_rods(cfg, "main"), without_rods(cfg, "sub")
        extra_m = [b.mass_kg for b in main_b] + [b.mass_kg for b in sub_b]
        extra_c = [b.cog_m for b in main_b] + [b.cog_m for b in sub_b]
        extra_i = [plate_inertia(b.mass_kg, cfg.layers.lower) for b in main_b] + [
            plate_inertia(b.mass_kg, frames.sub) for b in sub_b
        ]
        # S's bodies: one slice (moved along the rails every scan; a slice, not an index
        # array: numpy's fancy indexing costs about three times as much per scan)
        self._sub_bodies = slice(
            self._n_rig_bodies + len(frames.main.bodies), self._n_rig_bodies + len(extra_m)
        )
        self._body_m = np.concatenate([self._body_m, np.array(extra_m, dtype=np.float64)])
        self._body_c0 = np.concatenate([self._body_c, np.array(extra_c, dtype=np.float64)])
        self._body_c = self._body_c0.copy()
        self._body_i = np.concatenate([self._body_i, np.array(extra_i, dtype=np.float64)])
        self._body_layer = np.concatenate(
            [self._body_layer, np.zeros(len(extra_m), dtype=np.int64)]
        )
        self._rod_m = np.array([0.0] * 4 + [self.rod_mass_kg] * 4)  # legs: feet of their own
        self._up_xy = self._rod_xy[4:].copy()
        self._up_half = self._half_stroke[4:].copy()
        m_sub = float(sum(b.mass_kg for b in sub_b)) + 4 * self.rod_mass_kg
        m_all = float(self._body_m.sum()) + 8 * self.rod_mass_kg + 4 * self.rod_mass_kg
        self._mass_x = np.array([m_all - m_sub, m_sub])
        k_c = walk.contact.stiffness_n_m
        self._k_c = k_c
        self._c_c = 2.0 * walk.contact.damping_ratio * math.sqrt(k_c * self.foot_inertia_kg)
        self._c_t = 2.0 * 0.7 * np.sqrt(self.shear_stiffness_n_m * self._mass_x)
        # row 0: the invert's height over the whole base plane (set by _settle_walking);
        # rows 1..N_GROUND: the scenario's offsets
        self.ground = np.zeros((N_GROUND + 1, 5))
        self.ground[0, :4] = (-math.inf, math.inf, -math.inf, math.inf)
        self.friction = np.full(2, walk.foot_friction_coefficient)
        self._anchor = np.zeros(2)
        #: distance each frame's feet have slipped while touching (main, sub), m
        self.slip_m = np.zeros(2)
        self.foot_force_n = np.zeros(8)
        #: M's world x at the part's bolting: its pads touch only while M stands there
        self._bolted_at_x_m = 0.0
        y = np.zeros(N_WALK_STATE)
        y[:N_STATE] = self.y
        self.y = y
        self._settle_walking()
        self.bound_friction()

    # ----------------------------------------------------------------- set-up

    def _settle_level(self) -> None:
        """Nothing yet: the walking rig settles in :meth:`_settle_walking`, once its legs
        are set up."""

    def _place_sub_bodies(self, x_s: float) -> None:
        self._body_c[self._sub_bodies, 0] = self._body_c0[self._sub_bodies, 0] + x_s

    def _settle_walking(self) -> None:
        walk = self.walking
        p = self.params
        y = self.y
        y[:] = 0.0
        y[_X : _X + N] = p.stroke_m / 2
        x_s = -walk.step_length_m / 2
        y[_XW + 2] = x_s
        # M's feet hold the whole machine along the base's x (S hangs on the travel pair,
        # which M's frame carries): their shear spring stretched by that load, so M
        # starts at rest at X_M = 0 (not sliding into it as the walk begins)
        along_n = -float(self._mass_x.sum()) * float(self.g_base[0])
        self._anchor[:] = (along_n / self.shear_stiffness_n_m, x_s)
        self._place_sub_bodies(x_s)
        _m, q_g = self.generalized_gravity(np.zeros(6))
        g_z = self.g_base[2]
        jac = np.zeros((8, 3))
        for j in range(8):
            px = self._leg_xy[j, 0] + x_s * self._leg_sub[j]
            _d, *row = extension_and_jacobian(0.0, 0.0, 0.0, px, self._leg_xy[j, 1])
            jac[j] = row
        f_sub = np.full(4, self.rod_mass_kg * g_z)  # a hanging foot pulls its rod down
        rhs = -(q_g[:3] + jac[4:].T @ f_sub)
        a = jac[:4]
        f_main = a @ np.linalg.solve(a.T @ a, rhs)
        upper = self.static_rod_forces_n(np.zeros(6))[4:]  # the upper block only
        forces = np.zeros(N)
        forces[self._leg_idx[:4]] = f_main
        forces[self._leg_idx[4:]] = f_sub
        forces[self.upper_index] = upper
        forces[self._travel_idx] = -self._mass_x[1] * self.g_base[0] / 2
        # main feet pressed into the invert by their load; the body plane through them,
        # the invert raised by that plane's sinking (the body at the rigid rig's height)
        press = (f_main - self.rod_mass_kg * g_z) / self._k_c
        self.ground[0, 4] = np.linalg.lstsq(jac[:4], press, rcond=None)[0][0]
        h = np.array(
            [
                ground_height(self._leg_xy[j, 0], self._leg_xy[j, 1], self.ground) - press[j]
                for j in range(4)
            ]
        )
        z, roll, pitch = np.linalg.lstsq(jac[:4], h, rcond=None)[0]
        y[_Q : _Q + 3] = (z, roll, pitch)
        y[_H : _H + 4] = h
        for j in range(4, 8):
            xw = x_s + self._leg_xy[j, 0]
            y[_H + j] = ground_height(xw, self._leg_xy[j, 1], self.ground) + walk.clearance_m
        self.park(forces)
        self.advance(0)

    # ----------------------------------------------------------------- faults

    def set_ground(self, offsets: list[tuple[float, float, float, float, float]]) -> None:
        """Ground offsets ``(x_from_m, x_to_m, y_from_m, y_to_m, dz_m)`` (world, base frame)."""
        if len(offsets) > N_GROUND:
            raise ValueError(f"at most {N_GROUND} ground offsets at a time, got {len(offsets)}")
        self.ground[1:] = 0.0
        for k, row in enumerate(offsets):
            self.ground[1 + k] = row

    def set_friction(self, frame: int, coefficient: float | None) -> None:
        """Foot friction of frame 0 (main) or 1 (sub); ``None`` restores the YAML's."""
        self.friction[frame] = (
            self.walking.foot_friction_coefficient if coefficient is None else coefficient
        )

    # ----------------------------------------------------------------- run

    #: How far M may move along the tunnel from where the part was bolted before the
    #: part's pads no longer reach the platform (the machine walked away from its ring), m
    PADS_REACH_M = 0.1

    def _friction_rows(self) -> tuple[FloatArray, FloatArray, IntArray]:
        """The upper platform's four rods, and the eight legs, each in series with its
        foot's own inertia (:attr:`foot_inertia_kg`)."""
        q = self.y[_Q : _Q + 6]
        rows = np.zeros((12, 6))
        rows[:4] = self.rod_jacobian()[4:]
        x_s = self.x_s_m
        for j in range(8):
            px = self._leg_xy[j, 0] + x_s * self._leg_sub[j]
            _d, *row = extension_and_jacobian(q[0], q[1], q[2], px, self._leg_xy[j, 1])
            rows[4 + j, :3] = row
        extra = np.concatenate([np.zeros(4), np.full(8, 1.0 / self.foot_inertia_kg)])
        return rows, extra, np.concatenate([self.upper_index, self._leg_idx])

    def _set_part_mass(self, mass_kg: float, bound: bool = True) -> None:
        """The part's mass on the platform, and with it M's along the tunnel."""
        self._mass_x[0] += mass_kg - self._body_m[self._part_body]
        super()._set_part_mass(mass_kg, bound)

    def bolt_part(
        self,
        pad_points_m: FloatArray,
        pose: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        self._bolted_at_x_m = self.world_x_m[0]
        super().bolt_part(pad_points_m, pose)

    bolt_part.__doc__ = Rig.bolt_part.__doc__

    def advance(self, n_steps: int) -> None:
        if self.part_state == "loading":
            self._load_ramp()
        elif self._pads[5, 4] != 0.0 and abs(self.world_x_m[0] - self._bolted_at_x_m) > (
            self.PADS_REACH_M
        ):
            self._pads[:] = 0.0  # walked away from the ring: the part stays behind
            self.pad_force_n[:] = 0.0
        self._place_sub_bodies(self.x_s_m)
        _walk_advance(
            self.y, self.command, self.ports_open, self.valve_leak, self.external_force_n,
            self._p, self.upper_index, self._up_xy, self._up_half, self._leg_idx, self._leg_xy,
            self._leg_sub, self._leg_half, self._travel_idx, self.travel_mid_m, self._body_m,
            self._body_c, self._body_i, self._body_layer, self._rod_xy, self._rod_m,
            self._origin_u, self.rod_mass_kg, self.foot_inertia_kg, self.g_base, self._k_c,
            self._c_c, self.ground, self.friction,
            self._anchor, self.slip_m, self.shear_stiffness_n_m, self._c_t, self._mass_x,
            self._pads, self.step_s, int(n_steps), self._xv, self._force, self.foot_force_n,
            self.pad_force_n,
        )  # fmt: skip
        self.t_s += n_steps * self.step_s

    def derivative(self, y: FloatArray | None = None) -> FloatArray:
        yy = np.array(self.y if y is None else y, dtype=np.float64)
        m_mat, q_g = self.generalized_gravity(yy[_Q : _Q + 6])
        dy = np.zeros_like(yy)
        _walk_derivative(
            yy, dy, self.command, self.ports_open, self.valve_leak, self.external_force_n,
            self._p, self.upper_index, self._up_xy, self._up_half, self._leg_idx, self._leg_xy,
            self._leg_sub, self._leg_half, self._travel_idx, self.travel_mid_m, inverse(m_mat),
            q_g, self.rod_mass_kg, self.foot_inertia_kg, self.g_base, self._k_c, self._c_c,
            self.ground, self.friction, self._anchor.copy(), self.shear_stiffness_n_m, self._c_t,
            self._mass_x, self._pads, np.zeros((2, N)), np.zeros(N), np.zeros(8), np.zeros(4),
        )  # fmt: skip
        return dy

    derivative.__doc__ = Rig.derivative.__doc__

    # ----------------------------------------------------------------- truth

    @property
    def x_s_m(self) -> float:
        """S's position along the rails relative to M (m)."""
        return float(self.y[_XW + 2] - self.y[_XW])

    @property
    def world_x_m(self) -> tuple[float, float]:
        """``(X_M, X_S)``: both frames' positions in world x (m), the simulator's truth."""
        return float(self.y[_XW]), float(self.y[_XW + 2])

    @property
    def invert_height_m(self) -> float:
        """The invert's height above the base plane, offsets aside (m): M's feet's
        compression in the start state."""
        return float(self.ground[0, 4])

    @property
    def foot_heights_m(self) -> FloatArray:
        """Feet above the base plane (8,), legs in :attr:`leg_ids` order."""
        return self.y[_H : _H + 8].copy()

    @property
    def foot_forces_n(self) -> FloatArray:
        """Normal force of the invert on each foot (8,), :attr:`leg_ids` order; 0 in the air."""
        return self.foot_force_n.copy()

    @property
    def mass_kg(self) -> float:
        """Everything the feet carry: bodies and the rods and feet."""
        return float(self._mass_x.sum())
