"""The walking rig: the machine body on eight legs with foot contact (walking.md sections
1-3, docs/walking.md).

Model (what :class:`hil_sim.rig.Rig` has, and how this differs)
------------------------------------------------------------------
- The body is M and S joined by the rails: one rigid body in heave, roll and pitch
  (``q[0:3]``, relative to the base plane at world x = 0) plus ``x_S``, S's position along
  the rails. The upper platform on it is the rig's (``q[3:6]``). Its bodies: the YAML's
  layer bodies, ``frames.main.bodies`` (lower platform frame) and ``frames.sub.bodies``
  (S's frame, placed at ``x_S`` and turned by psi, below).
- Each of the eight legs is a cylinder whose barrel is fixed to the body at
  ``(s_i a_M, t_i b_M)`` (main) or ``(x_S + s_i a_S, t_i b_S)`` (sub, at psi = 0; turned
  with S below) and whose rod end is
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
  x_S``, the simulator's truth. The two travel cylinders join them (rod positions ``e_0 +
  x_S`` at psi = 0, ``e_0`` mid-stroke; their force pushes S forward and M back) and
  gravity along the base's x acts on both. A frame's feet hold it by friction: an elasto-plastic
  (bristle) model per frame, a shear spring ``k_t`` with damping to an anchor, the force
  capped at ``mu * sum N`` of its feet; above the cap the anchor is dragged along (the
  feet slip) and the slip is counted in :attr:`WalkingRig.slip_m`.
- Yaw (curves.md section 3). S turns in M about z on a pivot at S's centre, by psi (S's
  yaw in M; counter-clockwise seen from above positive: turning left). The travel
  cylinder of the lower ``can_index`` (``travel_1``) acts on the right at ``y = -b_T``,
  ``travel_2`` on the left at ``y = +b_T`` (``walking.travel_half_span_mm``); their rods
  are at ``e_1 = e_0 + x_S + b_T sin psi`` and ``e_2 = e_0 + x_S - b_T sin psi``, so
  ``psi = asin((e_1 - e_2) / (2 b_T))``, with speeds ``v_S +- b_T cos psi psi'``. Each
  rod's force pushes S forward along M's x at its attachment: along the rails ``F_1 + F_2``
  as before, about the pivot ``tau = b_T cos psi (F_1 - F_2)`` on S and ``-tau`` on M
  (the ``cos psi``, 1.5e-4 from 1 at 1 deg, makes the torque the rods' power's). Nothing
  but the pair sets psi: with equal cylinders and equal commands the pair's equations are
  symmetric and psi stays 0 (to the last bit); unequal flows turn S, and what holds it
  then is the IPC's position loop on each rod. The simulated PLC does not check the two
  rods against each other (the travel sync band is the IPC's interlock).
- Each frame has a heading in the walk's base frame (x along the machine's heading at
  the start; 0 there): states ``theta_M, omega_M, theta_S, omega_S``, ``psi = theta_S -
  theta_M``, the per-frame pattern of the x model. A frame's yaw inertia is its bodies'
  (their own moments about z, :func:`hil_sim.rig.plate_inertia` over their support, and
  their masses at their COGs' distances) and its rods and feet: M carries the platforms
  and the part (the part, a point mass in the 6-DOF mass matrix, a plate over the upper
  layer's support in yaw); S's is about its centre, the pivot; M's about the pivot
  (``I_M + m_M x_S^2 - 2 x_S m_M xbar_M``: M turns about it when S stands, and when M
  stands its feet hold it). Shipped project: M 131 400 kg m^2 about its centre (194 800
  at ``x_S = -1 m``), S 13 840 kg m^2. On the travel pair the differential (yaw) mode
  weighs ``I / (2 b_T^2)`` per rod: S 4.8 t, M 46 t at ``x_S = 0`` and 68 t at
  ``x_S = +-1 m`` (b_T 1.2 m), against 4.3 t and 31.7 t in the common (along the rails)
  mode: with M lifted the pair's oil column holds M's yaw at about 12-15 rad/s, below
  the common mode's 17.8 rad/s.
- A standing frame's feet hold its yaw with the x model's bristle model turned: a
  rotational spring ``k_t r^2`` to an anchor with damping (0.7 of critical), the torque
  capped at ``mu * sum N * r``, ``r`` the feet's distance from the frame's centre
  (M 3.13 m, S 2.12 m; independent of the cap along x); above the cap the anchor is
  dragged along and the slip counted in :attr:`WalkingRig.yaw_slip_rad`. A lifted frame
  (no normal force) turns freely under the travel pair's torque; with both standing the
  differential only loads the feet. The rails stop psi at ``+-walking.max_yaw_deg``: a
  stiff spring beyond it (S's yaw on it at :attr:`WalkingRig.yaw_stop_hz`), damped,
  pushing only.
- S's legs' barrels and S's bodies' COGs turn with psi about S's centre: in M's frame a
  leg is at ``(x_S + s a_S cos psi - t b_S sin psi, s a_S sin psi + t b_S cos psi)`` (the
  leg kinematics, the bodies placed every scan). A foot's world position for the ground
  lookup is its frame's centre in plan plus ``R(theta)`` of its place in the frame.
- Plan positions: each frame's centre at (x, y) in the base frame
  (:attr:`WalkingRig.plan_xy_m`). x is the world x above, the truth for the distance,
  integrated as before (along the base's x: to first order in the headings, its
  ``x_S cos theta_M`` taken as ``x_S``). y is kept outside the RK4 stages, after each
  RK4 step, by the pivot's constraint (S's centre is at M's plus ``R(theta_M) (x_S,
  0)``): the frame with the larger normal force holds its y (its feet do not move in
  plan but by their slip, which is along x and in yaw only: no lateral friction is
  modelled), the other's follows, ``y_S - y_M = x_S sin theta_M``. Consistent to first
  order: the lifted frame's turn about the pivot is the kernel's (M's inertia about the
  pivot), its lateral motion the constraint's; the lateral forces and gravity across the
  rails (``g_b[0] sin theta``) are left out.
- Hydraulics, valves, load-holding valves and end stops are the rig's, integrated with
  the same RK4 in one numba kernel; the mass matrix is evaluated once per PLC scan.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from config.alignment import invert_rise_m
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

#: offsets of the walking state after the rig's: foot heights, foot speeds, X_M, V_M, X_S,
#: V_S, then the headings theta_M, omega_M, theta_S, omega_S
_H = N_STATE
_HD = _H + 8
_XW = _HD + 8
_YW = _XW + 4
N_WALK_STATE = _YW + 4
#: slots of the yaw parameters (:attr:`WalkingRig._yaw`, one float array): the travel
#: pair's half-span b_T; the rails' end stop (max |psi|, its stiffness, its damping); the
#: frames' yaw inertias about their centres (M, S); M's mass and first moment along x
#: about its centre (its inertia about the pivot at x_S: ``I + m x_S^2 - 2 x_S m_x``);
#: the feet's rotational bristle stiffness and damping (M, S); the feet's distance from
#: their frame's centre (M, S); the frames' centres' lateral plan positions (M, S), kept by
#: the kernel (module docstring)
_Y_BT, _Y_MAX, _Y_KSTOP, _Y_CSTOP = 0, 1, 2, 3
_Y_I, _Y_MM, _Y_MXM = 4, 6, 7
_Y_K, _Y_C, _Y_R, _Y_PY = 8, 10, 12, 14
N_YAW = 16
#: ground offset slots: rows (x_from, x_to, y_from, y_to, dz) in the base frame, m
N_GROUND = 8


#: the invert's profile along x (:func:`invert_profile`): this far either way of the start,
#: sampled this finely (linear between samples: 0.4 um off a 3 km vertical curve)
PROFILE_REACH_M = 120.0
PROFILE_STEP_M = 0.1


def invert_profile(cfg: ProjectConfig, m_leg_x_m: tuple[float, float]) -> FloatArray:
    """The invert's rise along the base's x under the frames (curves.md section 3): the
    design axis's (:func:`config.alignment.invert_rise_m`) less the line through it at
    M's rear and front legs' x (``m_leg_x_m``), so the base plane is the invert under M's
    feet where the machine starts (the body starts where the attitude rig's does). As
    :func:`ground_height` reads it: ``[x_first, dx, rise_0, rise_1, ...]``, m."""
    n = round(2.0 * PROFILE_REACH_M / PROFILE_STEP_M) + 1
    x = np.linspace(-PROFILE_REACH_M, PROFILE_REACH_M, n)
    alignment = cfg.tunnel.alignment
    rise = invert_rise_m(alignment, x)
    a, b = m_leg_x_m
    ra, rb = invert_rise_m(alignment, np.array([a, b]))
    rise = rise - (ra + (rb - ra) * (x - a) / (b - a))
    return np.concatenate([[x[0], x[1] - x[0]], rise])


@jit
def ground_height(xw, yw, ground, profile):
    """Invert height above the base plane at ``(xw, yw)``: the profile's rise at ``xw``
    (linear between its samples, held beyond its ends) plus the offsets there."""
    u = (xw - profile[0]) / profile[1]
    last = profile.shape[0] - 3
    if u <= 0.0:
        z = profile[2]
    elif u >= last:
        z = profile[2 + last]
    else:
        k = int(u)
        f = u - k
        z = profile[2 + k] + f * (profile[3 + k] - profile[2 + k])
    for k in range(ground.shape[0]):
        if ground[k, 0] <= xw < ground[k, 1] and ground[k, 2] <= yw < ground[k, 3]:
            z += ground[k, 4]
    return z


@jit
def _capped(force, cap):
    """A frame's feet's bristle force (or torque), at most ``cap`` either way."""
    if force > cap:
        return cap
    if force < -cap:
        return -cap
    return force


@jit
def _walk_derivative(
    y, dy, u, ports, leak, f_ext, p, up_idx, up_xy, up_half, leg_idx, leg_xy, leg_sub,
    leg_half, travel_idx, e0, m_inv, q_g, foot_m, foot_inertia, g_b, k_c, c_c, ground, profile,
    fric, anchor, k_t, c_t, mass_x, yaw, pads, x_out, f_out, n_out, pad_out, ch, sh, jup, jleg,
    normal, gen,
):  # fmt: skip
    """``dy = f(y)`` for the walking rig; ``ch``, ``sh`` (2), ``jup`` (4, 3), ``jleg``
    (8, 3), ``normal`` (2) and ``gen`` (6): scratch, given by the caller (an allocation
    per call cost a sixth of the kernel)."""
    q = y[_Q : _Q + 6]
    qd = y[_QD : _QD + 6]
    x = x_out[0]
    v = x_out[1]
    for i in range(N):
        x[i] = y[_X + i]
        v[i] = y[_V + i]
    x_s = y[_XW + 2] - y[_XW]
    v_s = y[_XW + 3] - y[_XW + 1]
    # headings: each frame's (its feet on the ground) and S's yaw psi in M (its legs and
    # the travel rods in M's frame)
    for frame in range(2):
        ch[frame] = math.cos(y[_YW + 2 * frame])
        sh[frame] = math.sin(y[_YW + 2 * frame])
    c_psi = ch[1] * ch[0] + sh[1] * sh[0]
    s_psi = sh[1] * ch[0] - ch[1] * sh[0]
    psi = y[_YW + 2] - y[_YW]
    psi_d = y[_YW + 3] - y[_YW + 1]
    b_t = yaw[_Y_BT]
    for j in range(4):
        d, j0, j1, j2 = extension_and_jacobian(q[3], q[4], q[5], up_xy[j, 0], up_xy[j, 1])
        jup[j, 0], jup[j, 1], jup[j, 2] = j0, j1, j2
        i = up_idx[j]
        x[i] = up_half[j] + d
        v[i] = j0 * qd[3] + j1 * qd[4] + j2 * qd[5]
    for j in range(8):
        px = leg_xy[j, 0]
        py = leg_xy[j, 1]
        if leg_sub[j] == 1:
            px, py = x_s + px * c_psi - py * s_psi, px * s_psi + py * c_psi
        d, j0, j1, j2 = extension_and_jacobian(q[0], q[1], q[2], px, py)
        jleg[j, 0], jleg[j, 1], jleg[j, 2] = j0, j1, j2
        i = leg_idx[j]
        x[i] = leg_half[j] + d - y[_H + j]
        v[i] = j0 * qd[0] + j1 * qd[1] + j2 * qd[2] - y[_HD + j]
    for j in range(2):  # travel_1 at y = -b_T, travel_2 at +b_T
        i = travel_idx[j]
        side = b_t if j == 0 else -b_t
        x[i] = e0 + x_s + side * s_psi
        v[i] = v_s + side * c_psi * psi_d
    cylinder_forces(y, dy, u, ports, leak, f_ext, p, x, v, f_out)
    normal[0] = 0.0
    normal[1] = 0.0
    for j in range(8):
        i = leg_idx[j]
        frame = leg_sub[j]
        lx = leg_xy[j, 0]
        ly = leg_xy[j, 1]
        xw = y[_XW + 2 * frame] + lx * ch[frame] - ly * sh[frame]
        yw = yaw[_Y_PY + frame] + lx * sh[frame] + ly * ch[frame]
        pen = ground_height(xw, yw, ground, profile) - y[_H + j]
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
        tf = _capped(-k_t * (pos - anchor[frame]) - c_t[frame] * vel, fric[frame] * normal[frame])
        push = f_travel if frame == 1 else -f_travel
        dy[_XW + 2 * frame] = vel
        dy[_XW + 2 * frame + 1] = (push + tf) / mass_x[frame] + g_b[0]
    # yaw: the travel pair's differential turns S about the pivot and M the other way; the
    # rails' end stop beyond +-max; each frame's feet hold it (bristle, capped mu N r)
    tau = b_t * c_psi * (f_out[travel_idx[0]] - f_out[travel_idx[1]])
    over = abs(psi) - yaw[_Y_MAX]
    if over > 0.0:
        sgn = 1.0 if psi > 0.0 else -1.0
        stop = yaw[_Y_KSTOP] * over + yaw[_Y_CSTOP] * sgn * psi_d
        if stop > 0.0:
            tau -= sgn * stop
    inertia_m = yaw[_Y_I] + x_s * (x_s * yaw[_Y_MM] - 2.0 * yaw[_Y_MXM])
    for frame in range(2):
        th = y[_YW + 2 * frame]
        om = y[_YW + 2 * frame + 1]
        tf = _capped(
            -yaw[_Y_K + frame] * (th - anchor[2 + frame]) - yaw[_Y_C + frame] * om,
            fric[frame] * normal[frame] * yaw[_Y_R + frame],
        )
        turn = tau if frame == 1 else -tau
        dy[_YW + 2 * frame] = om
        dy[_YW + 2 * frame + 1] = (turn + tf) / (inertia_m if frame == 0 else yaw[_Y_I + 1])


@jit
def _walk_advance(
    y, u, ports, leak, f_ext, p, up_idx, up_xy, up_half, leg_idx, leg_xy, leg_sub, leg_half,
    travel_idx, e0, body_m, body_c, body_i, body_layer, rod_xy, rod_m, origin_u, foot_m,
    foot_inertia, g_b, k_c, c_c, ground, profile, fric, anchor, slip, k_t, c_t, mass_x, yaw, pads,
    h, n_steps, x_out, f_out, n_out, pad_out,
):  # fmt: skip
    """``n_steps`` RK4 steps; after each, the friction anchors (along x and in yaw) follow
    a slipping frame, and the lifted frame's lateral plan position follows the standing
    one's through the pivot."""
    n = y.shape[0]
    stages = np.empty((5, n))
    k1, k2, k3, k4, tmp = stages[0], stages[1], stages[2], stages[3], stages[4]
    m_mat, q_g = _mass_and_gravity(
        y[_Q : _Q + 6], body_m, body_c, body_i, body_layer, rod_xy, rod_m, origin_u, g_b
    )
    m_inv = inverse(m_mat)
    hh = 0.5 * h
    h6 = h / 6.0
    args = (
        u, ports, leak, f_ext, p, up_idx, up_xy, up_half, leg_idx, leg_xy, leg_sub, leg_half,
        travel_idx, e0, m_inv, q_g, foot_m, foot_inertia, g_b, k_c, c_c, ground, profile, fric,
        anchor, k_t, c_t, mass_x, yaw, pads, x_out, f_out, n_out, pad_out, np.empty(2),
        np.empty(2), np.empty((4, 3)), np.empty((8, 3)), np.empty(2), np.empty(6),
    )  # fmt: skip
    normals = np.zeros(2)
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
            normals[frame] = normal
            cap = fric[frame] * normal
            pos = y[_XW + 2 * frame]
            spring = k_t * (pos - anchor[frame])
            if spring > cap or spring < -cap:
                moved = pos - math.copysign(cap / k_t, spring) - anchor[frame]
                anchor[frame] += moved
                if normal > 0.0:
                    slip[frame] += abs(moved)
            cap *= yaw[_Y_R + frame]
            k_y = yaw[_Y_K + frame]
            th = y[_YW + 2 * frame]
            spring = k_y * (th - anchor[2 + frame])
            if spring > cap or spring < -cap:
                moved = th - math.copysign(cap / k_y, spring) - anchor[2 + frame]
                anchor[2 + frame] += moved
                if normal > 0.0:
                    slip[2 + frame] += abs(moved)
        # the plan: the standing frame's centre stays where it is laterally; the other
        # one's follows through the pivot (S's centre = M's + R(theta_M) (x_S, 0))
        lateral = (y[_XW + 2] - y[_XW]) * math.sin(y[_YW])
        if normals[1] > normals[0]:
            yaw[_Y_PY] = yaw[_Y_PY + 1] - lateral
        else:
            yaw[_Y_PY + 1] = yaw[_Y_PY] + lateral


@dataclass(frozen=True)
class WalkTruth:
    """Where the walking rig's frames are (:meth:`WalkingRig.walk_truth`; the walk's base
    frame: x along the machine's heading at the start, headings 0 there)."""

    #: ``(X_M, X_S)``: the frames' world x, the truth for the distance, m
    world_x_m: tuple[float, float]
    #: S's position along the rails in M, m
    x_s_m: float
    #: ``(theta_M, theta_S)``, rad, counter-clockwise from above positive
    heading_rad: FloatArray
    #: psi = theta_S - theta_M: S's yaw in M, rad
    yaw_s_in_m_rad: float
    #: the frames' centres in plan (2, 2): rows M, S; columns x, y (lateral), m
    plan_xy_m: FloatArray
    #: how far each frame's feet have slipped along x (m) and in yaw (rad): M, S
    slip_m: FloatArray
    yaw_slip_rad: FloatArray


class WalkingRig(Rig):
    """The rig with the eight legs on the invert (module docstring).

    Starts in walking.md's start state: M standing level at mid-stroke on its feet, S
    lifted by ``walking.clearance_mm``, ``x_S`` at the rear end of the step
    (``-step/2``), ``X_M = 0``; valves closed, pressures holding the load.
    """

    #: tangential (shear) stiffness of a frame's feet on the invert, N/m (all four)
    shear_stiffness_n_m = 5.0e7
    #: the rails' end stop in yaw: the frequency of S's yaw on it, Hz (its stiffness
    #: ``I_S (2 pi f)^2``), and its damping ratio
    yaw_stop_hz = 100.0
    yaw_stop_damping_ratio = 0.5
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
        frames, walk = cfg.walking_sections()
        super().__init__(cfg, step_s, rod_mass_kg, load_holding_valves)
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
        #: the invert's rise along x (:func:`invert_profile`)
        self.profile = invert_profile(cfg, (-lo.a_m, lo.a_m))
        self.friction = np.full(2, walk.foot_friction_coefficient)
        # the friction anchors: along x (M, S), then in yaw (M, S)
        self._anchor = np.zeros(4)
        self._slip = np.zeros(4)
        #: distance each frame's feet have slipped while touching (main, sub), m
        self.slip_m = self._slip[:2]
        #: angle each frame's feet have slipped in yaw while touching (main, sub), rad
        self.yaw_slip_rad = self._slip[2:]
        self._yaw = np.zeros(N_YAW)
        self._yaw[_Y_BT] = walk.travel_half_span_m
        self._yaw[_Y_MAX] = walk.max_yaw_rad
        self._yaw[_Y_R] = math.hypot(lo.a_m, lo.b_m)
        self._yaw[_Y_R + 1] = math.hypot(frames.sub.a_m, frames.sub.b_m)
        self._set_yaw_inertia()
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

    def _set_yaw_inertia(self) -> None:
        """The frames' yaw inertias from their bodies (each body's own moment about z plus
        its mass at its COG's distance from the frame's centre; the part, a point mass in
        the rig's mass matrix, as a plate over the upper layer's support rectangle) and
        their rods and feet; M carries the platforms and the part. From them the feet's
        rotational damping and the end stop's stiffness."""
        cfg = self.cfg
        sub = self._sub_bodies
        m = self._body_m.copy()
        izz = self._body_i[:, 2].copy()
        xy = self._body_c[:, :2].copy()
        xy[self._body_layer == 1] += self._origin_u[:2]
        if self._part_body >= 0:
            izz[self._part_body] = plate_inertia(m[self._part_body], cfg.layers.upper)[2]
        m[sub] = 0.0
        izz[sub] = 0.0
        # M: its bodies, the upper rods, its own feet
        m = np.concatenate([m, self._rod_m[4:], np.full(4, self.rod_mass_kg)])
        izz = np.concatenate([izz, np.zeros(8)])
        xy = np.concatenate([xy, self._up_xy + self._origin_u[:2], self._leg_xy[:4]])
        yp = self._yaw
        yp[_Y_I] = float(izz.sum() + (m * (xy**2).sum(axis=1)).sum())
        yp[_Y_MM] = float(m.sum())
        yp[_Y_MXM] = float((m * xy[:, 0]).sum())
        # S: its bodies about its centre, its feet
        m_s = self._body_m[sub]
        xy_s = self._body_c0[sub, :2]
        feet = self._leg_xy[4:]
        yp[_Y_I + 1] = float(
            self._body_i[sub, 2].sum()
            + (m_s * (xy_s**2).sum(axis=1)).sum()
            + self.rod_mass_kg * (feet**2).sum()
        )
        for frame in range(2):
            yp[_Y_K + frame] = self.shear_stiffness_n_m * yp[_Y_R + frame] ** 2
            yp[_Y_C + frame] = 2.0 * 0.7 * math.sqrt(yp[_Y_K + frame] * yp[_Y_I + frame])
        i_s = yp[_Y_I + 1]
        yp[_Y_KSTOP] = i_s * (2.0 * math.pi * self.yaw_stop_hz) ** 2
        yp[_Y_CSTOP] = 2.0 * self.yaw_stop_damping_ratio * math.sqrt(yp[_Y_KSTOP] * i_s)

    def _leg_points(self, x_s: float, psi: float) -> FloatArray:
        """The eight legs' barrel points in M's frame (8, 2): S's rotated by ``psi`` about
        its centre at ``x_S``."""
        pts = self._leg_xy.copy()
        c, s = math.cos(psi), math.sin(psi)
        sub = self._leg_xy[4:]
        pts[4:, 0] = x_s + sub[:, 0] * c - sub[:, 1] * s
        pts[4:, 1] = sub[:, 0] * s + sub[:, 1] * c
        return pts

    def _place_sub_bodies(self, x_s: float, psi: float) -> None:
        sub = self._sub_bodies
        c0 = self._body_c0
        if psi == 0.0:
            self._body_c[sub, 0] = c0[sub, 0] + x_s
            self._body_c[sub, 1] = c0[sub, 1]
        else:
            c, s = math.cos(psi), math.sin(psi)
            self._body_c[sub, 0] = x_s + c0[sub, 0] * c - c0[sub, 1] * s
            self._body_c[sub, 1] = c0[sub, 0] * s + c0[sub, 1] * c

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
        self._anchor[:] = (along_n / self.shear_stiffness_n_m, x_s, 0.0, 0.0)
        self._yaw[_Y_PY : _Y_PY + 2] = 0.0
        self._place_sub_bodies(x_s, 0.0)
        _m, q_g = self.generalized_gravity(np.zeros(6))
        g_z = self.g_base[2]
        jac = np.zeros((8, 3))
        pts = self._leg_points(x_s, 0.0)
        for j in range(8):
            _d, *row = extension_and_jacobian(0.0, 0.0, 0.0, pts[j, 0], pts[j, 1])
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
                ground_height(self._leg_xy[j, 0], self._leg_xy[j, 1], self.ground, self.profile)
                - press[j]
                for j in range(4)
            ]
        )
        z, roll, pitch = np.linalg.lstsq(jac[:4], h, rcond=None)[0]
        y[_Q : _Q + 3] = (z, roll, pitch)
        y[_H : _H + 4] = h
        for j in range(4, 8):
            xw = x_s + self._leg_xy[j, 0]
            y[_H + j] = (
                ground_height(xw, self._leg_xy[j, 1], self.ground, self.profile) + walk.clearance_m
            )
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
        pts = self._leg_points(self.x_s_m, self.yaw_s_in_m_rad)
        for j in range(8):
            _d, *row = extension_and_jacobian(q[0], q[1], q[2], pts[j, 0], pts[j, 1])
            rows[4 + j, :3] = row
        extra = np.concatenate([np.zeros(4), np.full(8, 1.0 / self.foot_inertia_kg)])
        return rows, extra, np.concatenate([self.upper_index, self._leg_idx])

    def _set_part_mass(self, mass_kg: float, bound: bool = True) -> None:
        """The part's mass on the platform, and with it M's along the tunnel."""
        self._mass_x[0] += mass_kg - self._body_m[self._part_body]
        super()._set_part_mass(mass_kg, bound)
        self._set_yaw_inertia()

    def set_platform_load(self, layer: str, mass_kg: float, cog_m: tuple[float, ...]) -> None:
        super().set_platform_load(layer, mass_kg, cog_m)
        self._set_yaw_inertia()

    set_platform_load.__doc__ = Rig.set_platform_load.__doc__

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
        y = self.y
        self._place_sub_bodies(y[_XW + 2] - y[_XW], y[_YW + 2] - y[_YW])
        _walk_advance(
            self.y, self.command, self.ports_open, self.valve_leak, self.external_force_n,
            self._p, self.upper_index, self._up_xy, self._up_half, self._leg_idx, self._leg_xy,
            self._leg_sub, self._leg_half, self._travel_idx, self.travel_mid_m, self._body_m,
            self._body_c, self._body_i, self._body_layer, self._rod_xy, self._rod_m,
            self._origin_u, self.rod_mass_kg, self.foot_inertia_kg, self.g_base, self._k_c,
            self._c_c, self.ground, self.profile, self.friction, self._anchor, self._slip,
            self.shear_stiffness_n_m, self._c_t, self._mass_x, self._yaw, self._pads,
            self.step_s, int(n_steps), self._xv, self._force, self.foot_force_n,
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
            self.ground, self.profile, self.friction, self._anchor.copy(), self.shear_stiffness_n_m,
            self._c_t,
            self._mass_x, self._yaw.copy(), self._pads, np.zeros((2, N)), np.zeros(N),
            np.zeros(8), np.zeros(4), np.zeros(2), np.zeros(2), np.zeros((4, 3)), np.zeros((8, 3)),
            np.zeros(2), np.zeros(6),
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
    def heading_rad(self) -> FloatArray:
        """``(theta_M, theta_S)``: both frames' headings about z in the walk's base frame
        (0 at the start, counter-clockwise from above positive), rad, the truth."""
        return self.y[_YW : _YW + 4 : 2].copy()

    @property
    def yaw_s_in_m_rad(self) -> float:
        """psi: S's yaw in M on the rails' pivot, ``theta_S - theta_M`` (rad; positive:
        turned left, ``e_1 > e_2``)."""
        return float(self.y[_YW + 2] - self.y[_YW])

    @property
    def plan_xy_m(self) -> FloatArray:
        """The frames' centres in plan (2, 2): rows M, S; columns the base frame's x (the
        world x, :attr:`world_x_m`) and y (lateral), m."""
        y = self.y
        return np.array(
            [[y[_XW], self._yaw[_Y_PY]], [y[_XW + 2], self._yaw[_Y_PY + 1]]], dtype=np.float64
        )

    @property
    def yaw_inertia_kg_m2(self) -> tuple[float, float]:
        """The frames' yaw inertias: M's about the pivot at the present ``x_S`` (what it
        turns about when S stands), S's about its centre (the pivot), kg m^2."""
        yp, x_s = self._yaw, self.x_s_m
        return (
            float(yp[_Y_I] + x_s * (x_s * yp[_Y_MM] - 2.0 * yp[_Y_MXM])),
            float(yp[_Y_I + 1]),
        )

    @property
    def yaw_friction_cap_nm(self) -> FloatArray:
        """The torque each frame's feet hold in yaw now, ``mu sum(N) r`` (M, S), N m."""
        n = np.array([self.foot_force_n[:4].sum(), self.foot_force_n[4:].sum()])
        return self.friction * n * self._yaw[_Y_R : _Y_R + 2]

    def walk_truth(self) -> WalkTruth:
        """The frames' positions, headings and slip now (copies)."""
        return WalkTruth(
            world_x_m=self.world_x_m,
            x_s_m=self.x_s_m,
            heading_rad=self.heading_rad,
            yaw_s_in_m_rad=self.yaw_s_in_m_rad,
            plan_xy_m=self.plan_xy_m,
            slip_m=self.slip_m.copy(),
            yaw_slip_rad=self.yaw_slip_rad.copy(),
        )

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
