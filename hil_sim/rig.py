"""The whole hydraulic rig: 19 valve-controlled cylinders, two of their groups under
rigid platforms (docs/hil.md, model.md sections 1-3, 5, 9).

Model
-----
- The eleven single-axis cylinders (sub-frame legs, travel, rotation, central axis,
  lateral) are standalone: rod plus lumped load mass (``moving_mass_kg``) under a
  load force, exactly :func:`hil_sim.hydraulics.cylinder_derivative`.
- The four legs of the standing frame carry the lower platform, the four upper
  attitude cylinders the upper platform. Each platform has three degrees of freedom
  relative to the frame below it, ``(heave z, roll, pitch)``; the generalized
  coordinates are ``q = (z_L, roll_L, pitch_L, z_U, roll_U, pitch_U)``. Rod
  extensions from mid-stroke follow from the exact layer kinematics
  ``d_i = z - x_i sin(pitch) + y_i sin(roll) cos(pitch)``; rod speeds are ``J_d q'``.
- Rods push along their base's z axis; lateral forces are taken by guides at the
  platform centre (paper assumption 2), which do no work on ``q``.
- Bodies sit at the COGs of the YAML (model.md section 5): the part (the upper
  layer's body ``workpiece``) a point mass, every other body a plate over its layer's
  support rectangle (:func:`plate_inertia`); each rod is a point mass (``rod_mass_kg``)
  at its action point, moving with its base along the rod axis. Lagrange:
  ``M(q) q'' = J_d^T F_rod + Q_g(q) + Q_pads`` with ``M = sum m J^T J + sum W^T I W``
  and ``Q_g = sum m J^T g_b`` (``g_b``: gravity in the tunnel base frame; ``Q_pads``: a
  bolted part's pads, :func:`pad_forces`). ``M`` and ``Q_g`` are evaluated once per PLC
  scan; the velocity-product (Coriolis) terms are left out: the platforms turn at a few
  mrad/s.
- The rods' smoothed Coulomb friction near standstill is a damper RK4 integrates only
  up to a rate: :meth:`Rig.bound_friction` keeps it there (docs/hil.md).
- Rod forces come from the chamber pressures (``p_A A_A - p_B A_B``), friction and
  the end stops, so cylinders that move out of step fight through the oil and the
  twist shows up as pressure.
- Load-holding valves (option): while the PLC has the drives off, a cylinder's ports
  are blocked and the cylinder is tight: no valve flow and neither of the paper's
  leakages (read as the running servo's, its valve's null leakage in them: docs/hil.md).
  A leaking holding valve (a fault) leaks both chambers to tank.
- Start: parked (:func:`parked_pressures`): the pressures its servo held it at, at rest,
  when the drives closed the holding valves (the loaded chamber at its load pressure,
  below the supply); a falling chamber pressure stops at zero (cavitation).

Everything is integrated together with fixed-step RK4 in one numba kernel.

The layer kinematics here (:func:`rotation`, :func:`extension_and_jacobian`) are the
simulator's truth, on purpose not the controller's ``ipc_app.model.kinematics``: the
plant is what the controller's model is checked against (the demo reports the attitude
the simulator reached, not the one the controller believes), ``hil_sim`` never imports
``ipc_app``, and these run inside the numba kernel together with their Jacobian, which
the controller has no use for. Both follow model.md sections 1-3.

Over 500 lines because the rigid platforms' kinematics, their Jacobian and the compiled
step of all 19 cylinders form one kernel that must see them together.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import Any

import numpy as np
from numpy.typing import NDArray

from config import units
from config.derived import without_rods
from config.schema import N_CYLINDERS, WORKPIECE_BODY, ProjectConfig
from hil_sim._jit import jit
from hil_sim.hydraulics import (
    CylinderParams,
    chamber_pressure_derivatives,
    end_stop_force_n,
    friction_force_n,
    orifice_flows,
    rod_force_n,
    valve_derivative,
)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

N = N_CYLINDERS
#: offsets in the flat state vector
_SPOOL, _RATE, _PA, _PB, _X, _V = (k * N for k in range(6))
_Q = 6 * N
_QD = _Q + 6
N_STATE = _QD + 6

#: (sign x, sign y) of action points 1..4 (model.md section 2)
_SIGNS = ((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))


# --------------------------------------------------------------------------- kinematics


@jit
def rotation(roll, pitch):
    """``R(roll, pitch) = Ry(pitch) @ Rx(roll)`` (model.md section 1)."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    r = np.empty((3, 3))
    r[0, 0], r[0, 1], r[0, 2] = cp, sp * sr, sp * cr
    r[1, 0], r[1, 1], r[1, 2] = 0.0, cr, -sr
    r[2, 0], r[2, 1], r[2, 2] = -sp, cp * sr, cp * cr
    return r


@jit
def _rotation_partials(roll, pitch):
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    dr = np.zeros((3, 3))
    dr[0, 1], dr[0, 2] = sp * cr, -sp * sr
    dr[1, 1], dr[1, 2] = -sr, -cr
    dr[2, 1], dr[2, 2] = cp * cr, -cp * sr
    dp = np.zeros((3, 3))
    dp[0, 0], dp[0, 1], dp[0, 2] = -sp, cp * sr, cp * cr
    dp[2, 0], dp[2, 1], dp[2, 2] = -cp, -sp * sr, -sp * cr
    return dr, dp


@jit
def extension_and_jacobian(z, roll, pitch, px, py):
    """Extension from mid-stroke of the rod at ``(px, py)`` and its row ``dd/d(z, roll, pitch)``."""
    cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
    return _extension_row(z, cr, sr, cp, sp, px, py)


@jit
def _extension_row(z, cr, sr, cp, sp, px, py):
    """:func:`extension_and_jacobian` from the layer's ``cos``/``sin`` of roll and pitch,
    taken once for the four rods of a layer (the kernel's inner loop)."""
    d = z - px * sp + py * sr * cp
    return d, 1.0, py * cr * cp, -px * cp - py * sr * sp


@jit
def _matvec3(a, x, out):
    """``out = a @ x`` for a (3, 3) matrix (written out: no BLAS call, cheap to compile)."""
    for r in range(3):
        out[r] = a[r, 0] * x[0] + a[r, 1] * x[1] + a[r, 2] * x[2]


@jit
def _body_point_jacobian(q, c, layer, origin_u, r_l, dr_l, dp_l, r_u, dr_u, dp_u, jac, w, t, col):
    """Writes ``jac`` (3, 6): ``d(position)/dq`` in the lower layer's base frame of the point
    ``c`` fixed to the lower (``layer`` 0) or the upper platform (platform frame), given
    the two layers' rotations and their partials at ``q``; ``w``, ``t``, ``col``: scratch."""
    jac[:, :] = 0.0
    if layer == 0:
        jac[2, 0] = 1.0
        _matvec3(dr_l, c, col)
        jac[:, 1] = col
        _matvec3(dp_l, c, col)
        jac[:, 2] = col
        return
    _matvec3(r_u, c, w)
    for a in range(3):
        w[a] += origin_u[a]
    w[2] += q[3]
    jac[2, 0] = 1.0
    _matvec3(dr_l, w, col)
    jac[:, 1] = col
    _matvec3(dp_l, w, col)
    jac[:, 2] = col
    jac[:, 3] = r_l[:, 2]
    _matvec3(dr_u, c, t)
    _matvec3(r_l, t, col)
    jac[:, 4] = col
    _matvec3(dp_u, c, t)
    _matvec3(r_l, t, col)
    jac[:, 5] = col


@jit
def point_jacobian(q, c, layer, origin_u):
    """``d(position)/dq`` (3, 6) of the point ``c`` fixed to the lower (``layer`` 0) or
    upper platform (its frame), in the lower layer's base frame, at ``q``."""
    r_l = rotation(q[1], q[2])
    dr_l, dp_l = _rotation_partials(q[1], q[2])
    r_u = rotation(q[4], q[5])
    dr_u, dp_u = _rotation_partials(q[4], q[5])
    jac = np.zeros((3, 6))
    w = np.zeros(3)
    t = np.zeros(3)
    col = np.zeros(3)
    _body_point_jacobian(q, c, layer, origin_u, r_l, dr_l, dp_l, r_u, dr_u, dp_u, jac, w, t, col)
    return jac


@jit
def _mass_and_gravity(q, body_m, body_c, body_i, body_layer, rod_xy, rod_m, origin_u, g_b):
    """Mass matrix ``M`` (6, 6) and generalized gravity ``Q_g`` (6,) at ``q``.

    Each body is its mass at its COG plus, where ``body_i`` is not zero, its principal
    moments of inertia about the COG (platform axes): ``M += W^T diag(I) W`` with ``W``
    the body's angular velocity per ``q'`` in its own frame.
    """
    m_mat = np.zeros((6, 6))
    q_g = np.zeros(6)
    r_l = rotation(q[1], q[2])
    dr_l, dp_l = _rotation_partials(q[1], q[2])
    r_u = rotation(q[4], q[5])
    dr_u, dp_u = _rotation_partials(q[4], q[5])
    r_lu = r_l @ r_u
    jac = np.zeros((3, 6))
    omega = np.zeros((3, 6))
    wb = np.zeros((3, 6))
    w = np.zeros(3)
    t = np.zeros(3)
    col = np.zeros(3)
    n_bodies = body_m.shape[0]
    # angular velocity per q' of each platform in the lower base frame: R = Ry(p) Rx(r)
    # turns at p' e_y + r' Ry(p) e_x; the upper platform adds R_L times its own
    cl, sl = math.cos(q[2]), math.sin(q[2])
    cu, su = math.cos(q[5]), math.sin(q[5])
    omega[0, 1], omega[2, 1] = cl, -sl
    omega[1, 2] = 1.0
    for a in range(3):
        omega[a, 4] = r_l[a, 0] * cu - r_l[a, 2] * su
        omega[a, 5] = r_l[a, 1]
    for k in range(n_bodies + 8):
        jac[:, :] = 0.0
        if k < n_bodies:
            m = body_m[k]
            layer = body_layer[k]
            _body_point_jacobian(
                q, body_c[k], layer, origin_u, r_l, dr_l, dp_l, r_u, dr_u, dp_u, jac, w, t, col
            )
            inertia = body_i[k]
            if m > 0.0 and (inertia[0] > 0.0 or inertia[1] > 0.0 or inertia[2] > 0.0):
                rb = r_l if layer == 0 else r_lu
                last = 3 if layer == 0 else 6
                for a in range(3):  # W = R^T omega (the lower platform: its own columns)
                    for b in range(6):
                        acc = 0.0
                        if b < last:
                            for e in range(3):
                                acc += rb[e, a] * omega[e, b]
                        wb[a, b] = acc
                for a in range(6):
                    for b in range(6):
                        m_mat[a, b] += (
                            inertia[0] * wb[0, a] * wb[0, b]
                            + inertia[1] * wb[1, a] * wb[1, b]
                            + inertia[2] * wb[2, a] * wb[2, b]
                        )
        else:
            j = k - n_bodies
            m = rod_m[j]
            layer = j // 4
            qo = 3 * layer
            d, j0, j1, j2 = extension_and_jacobian(
                q[qo], q[qo + 1], q[qo + 2], rod_xy[j, 0], rod_xy[j, 1]
            )
            if layer == 0:
                jac[2, 0], jac[2, 1], jac[2, 2] = j0, j1, j2
            else:
                w[0] = origin_u[0] + rod_xy[j, 0]
                w[1] = origin_u[1] + rod_xy[j, 1]
                w[2] = origin_u[2] + d
                jac[2, 0] = 1.0
                _matvec3(dr_l, w, col)
                jac[:, 1] = col
                _matvec3(dp_l, w, col)
                jac[:, 2] = col
                for a in range(3):
                    jac[a, 3] = r_l[a, 2] * j0
                    jac[a, 4] = r_l[a, 2] * j1
                    jac[a, 5] = r_l[a, 2] * j2
        if m == 0.0:
            continue
        for a in range(6):
            q_g[a] += m * (jac[0, a] * g_b[0] + jac[1, a] * g_b[1] + jac[2, a] * g_b[2])
            for b in range(6):
                m_mat[a, b] += m * (
                    jac[0, a] * jac[0, b] + jac[1, a] * jac[1, b] + jac[2, a] * jac[2, b]
                )
    return m_mat, q_g


@jit
def inverse(a):
    """Inverse of a small nonsingular matrix (Gauss-Jordan, partial pivoting): the mass
    matrix, symmetric positive definite, so the pivots stay large."""
    n = a.shape[0]
    w = a.copy()
    inv = np.eye(n)
    for c in range(n):
        piv = c
        for r in range(c + 1, n):
            if abs(w[r, c]) > abs(w[piv, c]):
                piv = r
        if piv != c:
            for k in range(n):
                w[c, k], w[piv, k] = w[piv, k], w[c, k]
                inv[c, k], inv[piv, k] = inv[piv, k], inv[c, k]
        f = 1.0 / w[c, c]
        for k in range(n):
            w[c, k] *= f
            inv[c, k] *= f
        for r in range(n):
            if r != c and w[r, c] != 0.0:
                g = w[r, c]
                for k in range(n):
                    w[r, k] -= g * w[c, k]
                    inv[r, k] -= g * inv[c, k]
    return inv


# --------------------------------------------------------------------------- dynamics


#: the row of the rig's parameter matrix after CylinderParams' fields: the leakage across
#: the piston that stays behind closed holding valves (m^3/s/Pa; a worn seal's)
SEAL_ROW = len(fields(CylinderParams))


@jit
def cylinder_forces(y, dy, u, ports, leak, f_ext, p, x, v, f_out):
    """Valves, chambers and rod forces of all cylinders at rod positions ``x``, speeds ``v``.

    Writes the valve and pressure derivatives and, for a standalone rod, ``x' = v``,
    ``v' = F / m``; ``f_out``: the net rod forces. ``ports``: 1 open, 0 blocked by the
    load-holding valves (no valve flow and neither of the YAML's leakages: a parked
    cylinder is tight, but for a worn seal's leakage across the piston, row
    :data:`SEAL_ROW` of ``p``); ``leak``: leakage to tank past a leaking holding valve
    (m^3/s/Pa, both chambers).
    """
    for i in range(N):
        spool = y[_SPOOL + i]
        rate = y[_RATE + i]
        p_a = y[_PA + i]
        p_b = y[_PB + i]
        d_spool, d_rate = valve_derivative(spool, rate, u[i], p[9, i], p[10, i], p[11, i])
        q_a, q_b = orifice_flows(spool, p_a, p_b, p[9, i], p[8, i], p[12, i], p[13, i], p[14, i])
        dp_a, dp_b = chamber_pressure_derivatives(
            x[i], v[i], p_a, p_b, q_a * ports[i], q_b * ports[i], p[0, i], p[1, i], p[2, i],
            p[3, i], p[4, i], p[5, i], p[6, i] * ports[i] + p[SEAL_ROW, i] * (1.0 - ports[i]),
            p[7, i] * ports[i] + leak[i],
        )  # fmt: skip
        force = (
            rod_force_n(p_a, p_b, p[0, i], p[1, i])
            - friction_force_n(v[i], p[16, i], p[17, i], p[18, i])
            + end_stop_force_n(x[i], v[i], p[2, i], p[19, i], p[20, i])
            + f_ext[i]
        )
        f_out[i] = force
        dy[_SPOOL + i] = d_spool
        dy[_RATE + i] = d_rate
        dy[_PA + i] = dp_a
        dy[_PB + i] = dp_b
        dy[_X + i] = y[_V + i]
        dy[_V + i] = force / p[15, i]


@jit
def pad_forces(q, pads, pad_out):
    """The bolted part's pads on the upper platform (:class:`Pads`): ``pad_out`` (4,) the
    normal force of each pad, N, ``max(0, n0 + k g . (q - q0))``: each pad's preload at the
    bolting plus the pad's stiffness times how far its point moved towards the part since.
    ``pads`` rows: 0..3 ``g`` (the pads' points' motion along the part's normal per ``q``,
    six columns), row 4 ``q0``, row 5 ``n0`` (four) and ``k`` (column 4); ``k`` 0: none."""
    k = pads[5, 4]
    for j in range(4):
        if k == 0.0:
            pad_out[j] = 0.0
            continue
        s = 0.0
        for a in range(6):
            s += pads[j, a] * (q[a] - pads[4, a])
        f = pads[5, j] + k * s
        pad_out[j] = f if f > 0.0 else 0.0


@jit
def _add_pad_forces(q, pads, pad_out, gen):
    """The pads' generalized forces on ``q`` (the part pushes the platform down)."""
    if pads[5, 4] == 0.0:
        return
    pad_forces(q, pads, pad_out)
    for j in range(4):
        for a in range(6):
            gen[a] -= pad_out[j] * pads[j, a]


@jit
def _derivative(
    y, dy, u, ports, leak, f_ext, p, plat_idx, rod_xy, half_stroke, m_inv, q_g, pads, x_out,
    f_out, pad_out, jrows, gen,
):  # fmt: skip
    """``dy = f(y)`` for the whole rig; writes rod positions/velocities and rod forces."""
    q = y[_Q : _Q + 6]
    qd = y[_QD : _QD + 6]
    x = x_out[0]
    v = x_out[1]
    for i in range(N):
        x[i] = y[_X + i]
        v[i] = y[_V + i]
    for j in range(8):
        qo = 3 * (j // 4)
        if j % 4 == 0:  # the layer's trigonometry, once for its four rods
            roll, pitch = q[qo + 1], q[qo + 2]
            cr, sr, cp, sp = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch)
        d, j0, j1, j2 = _extension_row(q[qo], cr, sr, cp, sp, rod_xy[j, 0], rod_xy[j, 1])
        jrows[j, 0], jrows[j, 1], jrows[j, 2] = j0, j1, j2
        i = plat_idx[j]
        x[i] = half_stroke[j] + d
        v[i] = j0 * qd[qo] + j1 * qd[qo + 1] + j2 * qd[qo + 2]
    cylinder_forces(y, dy, u, ports, leak, f_ext, p, x, v, f_out)
    for a in range(6):
        gen[a] = q_g[a]
    _add_pad_forces(q, pads, pad_out, gen)
    for j in range(8):
        i = plat_idx[j]
        qo = 3 * (j // 4)
        for a in range(3):
            gen[qo + a] += jrows[j, a] * f_out[i]
        dy[_X + i] = 0.0
        dy[_V + i] = 0.0
    for a in range(6):
        dy[_Q + a] = qd[a]
    for a in range(6):
        acc = 0.0
        for b in range(6):
            acc += m_inv[a, b] * gen[b]
        dy[_QD + a] = acc


@jit
def _advance(
    y, u, ports, leak, f_ext, p, plat_idx, rod_xy, half_stroke, body_m, body_c, body_i,
    body_layer, rod_m, origin_u, g_b, pads, h, n_steps, x_out, f_out, pad_out,
):  # fmt: skip
    """``n_steps`` RK4 steps of ``h`` with commands, port states and forces held.

    ``M`` and ``Q_g`` are evaluated once per call (one PLC scan, about 1 ms): the
    platforms turn by microradians in that time.
    """
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
        u, ports, leak, f_ext, p, plat_idx, rod_xy, half_stroke, m_inv, q_g, pads, x_out, f_out,
        pad_out, np.empty((8, 3)), np.empty(6),
    )  # fmt: skip
    for _ in range(n_steps):
        _derivative(y, k1, *args)
        for a in range(n):
            tmp[a] = y[a] + hh * k1[a]
        _derivative(tmp, k2, *args)
        for a in range(n):
            tmp[a] = y[a] + hh * k2[a]
        _derivative(tmp, k3, *args)
        for a in range(n):
            tmp[a] = y[a] + h * k3[a]
        _derivative(tmp, k4, *args)
        for a in range(n):
            y[a] += h6 * (k1[a] + 2.0 * k2[a] + 2.0 * k3[a] + k4[a])
    # rod positions, speeds and forces at the final state
    _derivative(y, k1, *args)


# --------------------------------------------------------------------------- the rig


def plate_inertia(mass_kg: float, support: Any) -> tuple[float, float, float]:
    """Principal moments of inertia (about x, y, z; kg m^2) of a structure of
    ``mass_kg`` spread evenly over the support rectangle of ``support`` (``a_m``, ``b_m``:
    half-spans): a thin plate of ``2a x 2b``."""
    lx, ly = 2.0 * support.a_m, 2.0 * support.b_m
    return (mass_kg * ly**2 / 12.0, mass_kg * lx**2 / 12.0, mass_kg * (lx**2 + ly**2) / 12.0)


@dataclass(frozen=True)
class LayerTruth:
    """One platform's attitude relative to the frame below it, and its rods."""

    heave_m: float
    roll_rad: float
    pitch_rad: float
    extensions_m: FloatArray  #: (4,) from mid-stroke, cylinders 1..4
    twist_m: float  #: ``(d1 - d2 + d3 - d4) / 4`` (model.md section 3); 0 for a rigid platform
    rod_forces_n: FloatArray  #: (4,) hydraulic rod forces ``p_A A_A - p_B A_B``
    #: ``(F1 - F2 + F3 - F4) / 4``: the force the cylinders fight each other with (the
    #: component of the rod forces that the platform's weight does not fix)
    twist_force_n: float


def parked_pressures(
    force_n: float,
    area_a: float,
    area_b: float,
    supply_pa: float,
    tank_pa: float,
    internal_leakage: float,
    external_leakage: float,
) -> tuple[float, float]:
    """Chamber pressures ``(p_A, p_B)`` of a cylinder parked holding ``force_n``
    (compression positive): those its servo held it at, at rest, when the drives closed
    the load-holding valves (a parked cylinder is tight and keeps them; docs/hil.md).

    At rest under the servo the valve's two metering edges pass just what the chambers
    leak: into the loaded chamber from the supply what it loses (across the piston and
    outside), out of the other to tank what it gains, through the same opening, so
    ``sqrt(p_s - p_A) L_B = sqrt(p_B - p_T) L_A`` with ``L_A = C_i (p_A - p_B) + C_e p_A``,
    ``L_B = C_i (p_A - p_B) - C_e p_B``, and ``p_A A_A - p_B A_B = F``: the loaded
    chamber at its load pressure, below the supply; the other a little above tank. A
    hanging rod (a lifted foot) is the mirror, its rod side loaded. Where there is no
    such state (no leakage; a load the supply cannot hold) the far chamber is at tank."""
    if force_n < 0.0:  # the mirror: the rod side carries the load
        p_b, p_a = _servo_null(-force_n, area_b, area_a, supply_pa, tank_pa,
                               internal_leakage, external_leakage)  # fmt: skip
        return p_a, p_b
    return _servo_null(
        force_n, area_a, area_b, supply_pa, tank_pa, internal_leakage, external_leakage
    )


def _servo_null(
    force_n: float, a_load: float, a_far: float, p_s: float, p_t: float, c_i: float, c_e: float
) -> tuple[float, float]:
    """:func:`parked_pressures` with the loaded chamber's area ``a_load``: ``(p_load,
    p_far)``, bisecting on ``p_far`` from tank pressure up to where the loaded chamber
    would reach the supply."""

    def p_load(p_far: float) -> float:
        return (force_n + p_far * a_far) / a_load

    def balance(p_far: float) -> float:
        p = p_load(p_far)
        lost, gained = c_i * (p - p_far) + c_e * p, c_i * (p - p_far) - c_e * p_far
        return math.sqrt(max(p_s - p, 0.0)) * gained - math.sqrt(max(p_far - p_t, 0.0)) * lost

    lo, hi = p_t, (p_s * a_load - force_n) / a_far
    if not (hi > lo and balance(lo) > 0.0 and balance(hi) < 0.0):
        return p_load(p_t), p_t
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if balance(mid) > 0.0 else (lo, mid)
    return p_load(lo), lo


class Rig:
    """The plant: construct from the project, :meth:`advance`, read the truth.

    Arrays are indexed by ``can_index``. Starts standing level at mid-stroke on the
    tunnel base, valves closed, pressures in static equilibrium with the load.
    """

    def __init__(
        self,
        cfg: ProjectConfig,
        step_s: float = 0.25e-3,
        rod_mass_kg: float = 150.0,
        load_holding_valves: bool = True,
    ) -> None:
        if not 0.05e-3 <= step_s <= 1e-3:
            raise ValueError(f"step_s must be within 0.05 .. 1 ms (0.1-0.5 advised), got {step_s}")
        if rod_mass_kg <= 0:
            raise ValueError(f"rod_mass_kg must be positive, got {rod_mass_kg}")
        self.cfg = cfg
        self.step_s = float(step_s)
        self.load_holding_valves = load_holding_valves
        cyls = cfg.cylinders_by_can_index
        self.cylinder_ids: tuple[str, ...] = tuple(c.id for c in cyls)
        self.params = CylinderParams.from_config(
            cyls, cfg.hydraulics, [cfg.plant_of(c) for c in cyls]
        )
        # the fields of CylinderParams, then row SEAL_ROW: the leakage across the piston
        # that stays behind closed holding valves (0: a sound seal; a worn one's)
        self._p = np.vstack([self.params.matrix(), np.zeros((1, N))])
        self._p_nominal = self._p.copy()
        lo, up = cfg.layers.lower, cfg.layers.upper
        by_id = {c.id: c for c in cyls}
        self.lower_index = np.array([by_id[c].can_index for c in lo.cylinders], dtype=np.int64)
        self.upper_index = np.array([by_id[c].can_index for c in up.cylinders], dtype=np.int64)
        self._plat_idx = np.concatenate([self.lower_index, self.upper_index])
        self.platform_mask = np.zeros(N, dtype=bool)
        self.platform_mask[self._plat_idx] = True
        self._rod_xy = np.array(
            [(sx * layer.a_m, sy * layer.b_m) for layer in (lo, up) for sx, sy in _SIGNS]
        )
        self._half_stroke = np.array([lo.stroke_m / 2] * 4 + [up.stroke_m / 2] * 4)
        # bodies: the YAML's, plus one load-step slot per layer (mass 0 until a step); the
        # structures spread over their layer's support rectangle, the part a point mass
        masses: list[float] = []
        cogs: list[tuple[float, ...]] = []
        inertias: list[tuple[float, ...]] = []
        layers: list[int] = []
        part = -1
        # the upper cylinders' rods are masses of their own (below): out of the bodies
        # that weigh them in (config.derived.without_rods)
        for k, bodies in enumerate((lo.bodies, without_rods(cfg, "upper"))):
            layer = (lo, up)[k]
            for b in bodies:
                is_part = k == 1 and b.name == WORKPIECE_BODY
                part = len(masses) if is_part else part
                masses.append(b.mass_kg)
                cogs.append(b.cog_m)
                inertias.append((0.0,) * 3 if is_part else plate_inertia(b.mass_kg, layer))
                layers.append(k)
        self._extra_slot = {"lower": len(masses), "upper": len(masses) + 1}
        masses += [0.0, 0.0]
        cogs += [(0.0, 0.0, 0.0), (0.0, 0.0, 0.0)]
        inertias += [(0.0,) * 3, (0.0,) * 3]
        layers += [0, 1]
        self._body_m = np.array(masses, dtype=np.float64)
        self._body_c = np.array(cogs, dtype=np.float64)
        self._body_i = np.array(inertias, dtype=np.float64)
        self._body_layer = np.array(layers, dtype=np.int64)
        #: the arc part: index of the upper layer's body ``workpiece`` (-1: none), its mass
        self._part_body = part
        self.part_mass_kg = float(masses[part]) if part >= 0 else 0.0
        #: ``carried`` (on the upper platform), ``loading`` (a crane setting it down:
        #: :meth:`load_part`), ``bolted`` (fixed in the ring, resting on the pads:
        #: :meth:`bolt_part`), ``none`` (a project without a body ``workpiece``)
        self.part_state = "carried" if part >= 0 else "none"
        self._loading: tuple[float, float] = (0.0, 0.0)  # (start, duration) of a load, s
        self._bound_at_kg = self.part_mass_kg  # the part's mass at the last friction bound
        #: the bolted part's pads (:func:`pad_forces`); all zero: none
        self._pads = np.zeros((6, 6))
        #: the part's pose from home ``(R, t)`` when it was bolted (None: not bolted)
        self.bolted_pose: tuple[FloatArray, FloatArray] | None = None
        #: the pads' normal forces on the upper platform at the last state, N
        self.pad_force_n = np.zeros(4)
        self.rod_mass_kg = float(rod_mass_kg)
        #: moving mass of each platform rod (lower 1..4, upper 1..4) in the platforms' mass
        self._rod_m = np.full(8, self.rod_mass_kg)
        self._origin_u = np.array(up.origin_in_lower_m, dtype=np.float64)
        r_base = rotation(cfg.base.roll_rad, cfg.base.pitch_rad)
        self.g_base = r_base.T @ np.array([0.0, 0.0, -units.G])
        self.y = np.zeros(N_STATE)
        self.t_s = 0.0
        self.command = np.zeros(N)
        self.ports_open = np.zeros(N) if load_holding_valves else np.ones(N)
        self.external_force_n = np.zeros(N)
        #: leakage to tank past a leaking load-holding valve (m^3/s/Pa) per cylinder
        self.valve_leak = np.zeros(N)
        self._xv = np.zeros((2, N))
        self._force = np.zeros(N)
        # read-only views of the state, made once (the PLC reads them every scan)
        self._x_ro = self._xv[0].view()
        self._x_ro.flags.writeable = False
        self._p_ro = self._pressure_view()
        self._settle_level()

    # ----------------------------------------------------------------- set-up

    #: RK4's step times the fastest friction mode's rate at rest is kept at or below this
    #: (the method is stable up to 2.785 on the negative real axis; the margin covers the
    #: mass matrix's change with the attitude, and with a load, between two bounds)
    FRICTION_STEP_RATE = 2.5

    def _friction_rows(self) -> tuple[FloatArray, FloatArray, IntArray]:
        """The rods whose friction acts on the platforms' inertia: ``(rows, extra,
        index)``, each rod's speed per ``q'`` (rows of ``dd/dq``), a compliance of its
        own in series (1/kg; none here) and its can_index: both platforms' eight rods."""
        return self.rod_jacobian(), np.zeros(8), self._plat_idx

    def bound_friction(self) -> None:
        """Keep the friction modes at rest inside RK4's stability at :attr:`step_s`.

        A rod's smoothed Coulomb friction (:func:`~hil_sim.hydraulics.friction_force_n`)
        is, near standstill, a damper of ``F_c / v_c`` (2e7 N s/m at the nominal ``v_c``
        of 0.1 mm/s) on the inertia its rod moves; with the viscous ``B`` the rods'
        dampers ``C`` make modes whose fastest rate is the largest eigenvalue of
        ``C^1/2 A C^1/2``, ``A = J M^-1 J^T`` (plus each rod's own compliance) over the
        rods of :meth:`_friction_rows`. Where the step times that rate exceeds
        :attr:`FRICTION_STEP_RATE`, every one of these rods' ``v_c`` is raised by one
        factor, as far as needed: an explicit step cannot integrate a faster damper (it
        rings at half the step rate, bounded only by the friction's own saturation;
        without the part's inertia on the upper platform it diverged). Called whenever
        the bodies change (a load step, the part's bolting or loading).
        """
        m, _ = self.generalized_gravity()
        rows, extra, idx = self._friction_rows()
        a = rows @ np.linalg.solve(m, rows.T) + np.diag(extra)
        viscous = self._p[16, idx]
        coulomb = self._p[17, idx] / self._p_nominal[18, idx]  # the slope at rest
        limit = self.FRICTION_STEP_RATE / self.step_s

        def rate(share: float) -> float:
            r = np.sqrt(viscous + share * coulomb)
            return float(np.linalg.eigvalsh(r[:, None] * a * r[None, :]).max())

        if rate(0.0) > limit:
            raise ValueError(
                f"the rods' viscous damping alone is beyond what RK4 at "
                f"{self.step_s * 1e3:g} ms integrates on the platforms' inertia: a shorter "
                "plant.step_ms"
            )
        share = 1.0
        if rate(1.0) > limit:
            lo, hi = 0.0, 1.0
            for _ in range(40):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if rate(mid) <= limit else (lo, mid)
            share = lo
        self._p[18, idx] = self._p_nominal[18, idx] / share

    def generalized_gravity(self, q: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
        """``(M, Q_g)`` at ``q`` (default: the present state)."""
        qq = self.y[_Q : _Q + 6].copy() if q is None else np.asarray(q, dtype=np.float64)
        return _mass_and_gravity(
            qq,
            self._body_m,
            self._body_c,
            self._body_i,
            self._body_layer,
            self._rod_xy,
            self._rod_m,
            self._origin_u,
            self.g_base,
        )

    def rod_jacobian(self, q: FloatArray | None = None) -> FloatArray:
        """``dd/dq`` (8, 6): rows lower 1..4, upper 1..4; block diagonal."""
        qq = self.y[_Q : _Q + 6] if q is None else q
        jac = np.zeros((8, 6))
        for j in range(8):
            qo = 3 * (j // 4)
            _d, *row = extension_and_jacobian(
                qq[qo], qq[qo + 1], qq[qo + 2], self._rod_xy[j, 0], self._rod_xy[j, 1]
            )
            jac[j, qo : qo + 3] = row
        return jac

    def static_rod_forces_n(self, q: FloatArray | None = None) -> FloatArray:
        """Minimum-norm rod forces (8,) that hold the platforms still at ``q``."""
        _m, q_g = self.generalized_gravity(q)
        jac = self.rod_jacobian(q)
        out = np.zeros(8)
        for layer in range(2):
            a = jac[4 * layer : 4 * layer + 4, 3 * layer : 3 * layer + 3]
            out[4 * layer : 4 * layer + 4] = a @ np.linalg.solve(
                a.T @ a, -q_g[3 * layer : 3 * layer + 3]
            )
        return out

    def _settle_level(self) -> None:
        """Level at mid-stroke, at rest, valves closed, parked: each attitude cylinder's
        pressures hold its static load (:func:`parked_pressures`)."""
        p = self.params
        self.y[:] = 0.0
        self.y[_X : _X + N] = p.stroke_m / 2
        force = np.zeros(N)
        force[self._plat_idx] = self.static_rod_forces_n(np.zeros(6))
        self.park(force)
        self._xv[0] = self.y[_X : _X + N]
        self._force[:] = force
        self.bound_friction()

    def park(self, force_n: FloatArray) -> None:
        """The start state's pressures: the cylinders of :attr:`platform_mask` parked
        holding ``force_n`` (N, by can_index; :func:`parked_pressures`), the others (no
        load: the slide axes) empty."""
        p = self.params
        self.y[_PA : _PA + N] = 0.0
        self.y[_PB : _PB + N] = 0.0
        for i in np.flatnonzero(self.platform_mask):
            self.y[_PA + i], self.y[_PB + i] = parked_pressures(
                float(force_n[i]), float(p.area_a_m2[i]), float(p.area_b_m2[i]),
                float(p.supply_pa[i]), float(p.tank_pa[i]),
                float(p.internal_leakage_m3_s_pa[i]), float(p.external_leakage_m3_s_pa[i]),
            )  # fmt: skip

    # ----------------------------------------------------------------- faults

    def set_internal_leakage(self, index: int, value: float | None) -> None:
        """Internal leakage of cylinder ``index`` (m^3/s/Pa): a worn piston seal, which
        leaks across the piston also behind closed holding valves; ``None`` restores the
        YAML's (the running servo's, none while parked)."""
        for row in (6, SEAL_ROW):
            self._p[row, index] = self._p_nominal[row, index] if value is None else value

    def set_platform_load(self, layer: str, mass_kg: float, cog_m: tuple[float, ...]) -> None:
        """The extra mass set down on a platform (frame of that platform)."""
        k = self._extra_slot[layer]
        if self._body_m[k] == mass_kg and tuple(self._body_c[k]) == tuple(cog_m):
            return
        self._body_m[k] = mass_kg
        self._body_c[k] = cog_m
        self.bound_friction()

    # ----------------------------------------------------------------- the part

    #: Stiffness of each of the four pads the part rests on, N/m (elastomer bearing pads
    #: under a precast part: the platform's share of the part's weight falls by this
    #: much per metre of lowering, about 1.8 mm from the part's weight to none)
    pad_stiffness_n_m = 5.0e7

    def pad_points_m(self, slide_x_m: float, slide_y_m: float, slide_yaw_rad: float) -> FloatArray:
        """The four pads' points (4, 3) in the upper platform's frame: under the part's
        bottom face (z 0), at ``(+-(w/2 - 0.2), +-(b_U - 0.2))`` from its reference point
        (``w`` the part's width along x, ``b_U`` the upper layer's half-span in y: inside
        both), carried with the part by the slide stage (``x``, ``y``, yaw)."""
        px = self.cfg.workpiece.width_m / 2 - 0.2
        py = self.cfg.layers.upper.b_m - 0.2
        c, s = math.cos(slide_yaw_rad), math.sin(slide_yaw_rad)
        out = np.zeros((4, 3))
        for j, (sx, sy) in enumerate(_SIGNS):
            x, y = sx * px, sy * py
            out[j] = (slide_x_m + c * x - s * y, slide_y_m + s * x + c * y, 0.0)
        return out

    def bolt_part(
        self,
        pad_points_m: FloatArray,
        pose: tuple[FloatArray, FloatArray] | None = None,
    ) -> None:
        """The part is bolted to the ring where it is (from now on the ring, not the
        platform, holds it; ``pose``: where, kept as :attr:`bolted_pose`): it leaves the
        platform's bodies and rests on it through the
        pads at ``pad_points_m`` (:meth:`pad_points_m`), each a unilateral spring of
        :attr:`pad_stiffness_n_m` against the part's frozen pose, preloaded so that the
        platform carries the part's weight as before (the minimum-norm split of its load on
        the upper platform's heave, roll and pitch). As the platform lowers, its share
        falls linearly and is zero once every pad is clear; the bolts carry the rest."""
        if self.part_state != "carried":
            raise ValueError(f"bolt_part: the part is {self.part_state}, not carried")
        q = self.y[_Q : _Q + 6].copy()
        k = self._part_body
        n = (rotation(q[1], q[2]) @ rotation(q[4], q[5]))[:, 2]  # the part's normal
        g = np.array(
            [n @ point_jacobian(q, np.asarray(c, float), 1, self._origin_u) for c in pad_points_m]
        )
        j_part = point_jacobian(q, self._body_c[k], 1, self._origin_u)
        load = self._body_m[k] * (j_part.T @ self.g_base)[3:]  # on the upper platform
        a = g[:, 3:].T  # (3, 4): each pad's push on the upper platform's heave, roll, pitch
        n0 = a.T @ np.linalg.solve(a @ a.T, -load)
        if np.any(n0 <= 0.0):
            raise ValueError(f"bolt_part: the pads do not carry the part's COG ({n0} N)")
        self._pads[:4] = g
        self._pads[4] = q
        self._pads[5, :4] = n0
        self._pads[5, 4] = self.pad_stiffness_n_m
        self._set_part_mass(0.0)
        self.part_state = "bolted"
        self.bolted_pose = pose
        self.advance(0)

    def load_part(self, duration_s: float) -> None:
        """A new part set down on the upper platform at its home position (the YAML's
        COG) by a crane: its weight ramped from none to all over ``duration_s``; a part
        bolted before stays in its ring (its pads no longer touch the platform)."""
        if self.part_state not in ("bolted", "none") or self._part_body < 0:
            raise ValueError(f"load_part: the platform carries a part ({self.part_state})")
        if not duration_s > 0:
            raise ValueError(f"load_part: duration_s must be positive, got {duration_s}")
        self._pads[:] = 0.0
        self.pad_force_n[:] = 0.0
        self.bolted_pose = None
        self._loading = (self.t_s, float(duration_s))
        self._bound_at_kg = 0.0
        self.part_state = "loading"

    @property
    def part_load_n(self) -> float:
        """How much of the part's weight the upper platform carries now, N: the part's
        weight while it is carried (the load ramp's share while loading), the pads'
        forces while it is bolted."""
        if self.part_state == "bolted":
            return float(self.pad_force_n.sum())
        if self._part_body < 0:
            return 0.0
        return float(self._body_m[self._part_body] * units.G)

    #: While a part is set down, the friction's bound (:meth:`bound_friction`) is taken
    #: again each time this share of the part's mass has been added (the bound of a
    #: lighter platform holds for a heavier one)
    LOAD_BOUND_SHARE = 0.1

    def _set_part_mass(self, mass_kg: float, bound: bool = True) -> None:
        self._body_m[self._part_body] = mass_kg
        if bound:
            self.bound_friction()
            self._bound_at_kg = mass_kg

    def _load_ramp(self) -> None:
        """A load in progress: the part's share of its weight at this scan."""
        t0, dur = self._loading
        frac = (self.t_s - t0) / dur
        frac = 1.0 if frac >= 1.0 - 1e-9 else frac  # the clock's rounding
        mass = frac * self.part_mass_kg
        step = self.LOAD_BOUND_SHARE * self.part_mass_kg
        self._set_part_mass(mass, bound=mass - self._bound_at_kg >= step or frac >= 1.0)
        if frac >= 1.0:
            self.part_state = "carried"

    def set_rod_position(self, index: int, x_m: float) -> None:
        """Put a standalone (non-platform) cylinder's rod at ``x_m``, at rest (test set-ups)."""
        if self.platform_mask[index]:
            raise ValueError(f"cylinder {index} is under a platform: move the platform")
        self.y[_X + index] = x_m
        self.y[_V + index] = 0.0
        self._xv[0, index] = x_m

    # ----------------------------------------------------------------- run

    def advance(self, n_steps: int) -> None:
        """Integrate ``n_steps`` with :attr:`command`, :attr:`ports_open` and
        :attr:`external_force_n` held."""
        if self.part_state == "loading":
            self._load_ramp()
        kernel, args = self.kernel_call(n_steps)
        kernel(*args)
        self.t_s += n_steps * self.step_s

    def kernel_call(self, n_steps: int) -> tuple[Any, tuple[Any, ...]]:
        """The compiled kernel that integrates ``n_steps`` and its arguments (this rig's
        arrays, in place): what :meth:`advance` calls after the load ramp, and the
        simulator's compiled PLC scans call in line (:mod:`hil_sim.plc_fast`; they keep
        :attr:`t_s`). The compiled scans use it for this class only: a subclass whose
        :meth:`advance` does more (the walking rig) is advanced by its own method."""
        return _advance, (
            self.y,
            self.command,
            self.ports_open,
            self.valve_leak,
            self.external_force_n,
            self._p,
            self._plat_idx,
            self._rod_xy,
            self._half_stroke,
            self._body_m,
            self._body_c,
            self._body_i,
            self._body_layer,
            self._rod_m,
            self._origin_u,
            self.g_base,
            self._pads,
            self.step_s,
            int(n_steps),
            self._xv,
            self._force,
            self.pad_force_n,
        )

    def derivative(self, y: FloatArray | None = None) -> FloatArray:
        """The state's time derivative at ``y`` (default: the present state) with the
        present commands, ports, loads and pads, the mass matrix taken at ``y`` (what
        one RK4 stage evaluates: for checks of the integration, e.g. its stability)."""
        yy = np.array(self.y if y is None else y, dtype=np.float64)
        m_mat, q_g = self.generalized_gravity(yy[_Q : _Q + 6])
        dy = np.zeros_like(yy)
        _derivative(
            yy, dy, self.command, self.ports_open, self.valve_leak, self.external_force_n,
            self._p, self._plat_idx, self._rod_xy, self._half_stroke, inverse(m_mat), q_g,
            self._pads, np.zeros((2, N)), np.zeros(N), np.zeros(4), np.zeros((8, 3)), np.zeros(6),
        )  # fmt: skip
        return dy

    # ----------------------------------------------------------------- truth

    @property
    def q(self) -> FloatArray:
        """``(z_L, roll_L, pitch_L, z_U, roll_U, pitch_U)`` (m, rad)."""
        return self.y[_Q : _Q + 6].copy()

    @property
    def x_view(self) -> FloatArray:
        """Rod positions (19,), a read-only view of the state (no copy: hot path)."""
        return self._x_ro

    @property
    def pressure_view(self) -> FloatArray:
        """``(p_A of all 19, p_B of all 19)`` flat (38,), a read-only view (hot path)."""
        if self._p_ro.base is not self.y:  # a subclass extended the state
            self._p_ro = self._pressure_view()
        return self._p_ro

    def _pressure_view(self) -> FloatArray:
        v = self.y[_PA : _PB + N].view()
        v.flags.writeable = False
        return v

    @property
    def rod_positions_m(self) -> FloatArray:
        """From fully retracted, (19,)."""
        return self._xv[0].copy()

    @property
    def rod_velocities_m_s(self) -> FloatArray:
        return self._xv[1].copy()

    @property
    def spool_m(self) -> FloatArray:
        return self.y[_SPOOL : _SPOOL + N].copy()

    @property
    def pressures_pa(self) -> FloatArray:
        """(19, 2): cap side, rod side."""
        return np.stack([self.y[_PA : _PA + N], self.y[_PB : _PB + N]], axis=1)

    @property
    def hydraulic_forces_n(self) -> FloatArray:
        """``p_A A_A - p_B A_B`` (19,), positive extending."""
        p = self.params
        return np.asarray(
            rod_force_n(self.y[_PA : _PA + N], self.y[_PB : _PB + N], p.area_a_m2, p.area_b_m2)
        )

    @property
    def rod_forces_n(self) -> FloatArray:
        """Net force each rod puts on its load (hydraulic - friction + end stop + external)."""
        return self._force.copy()

    def layer(self, name: str) -> LayerTruth:
        """``"lower"`` or ``"upper"``."""
        k = {"lower": 0, "upper": 1}[name]
        q = self.y[_Q + 3 * k : _Q + 3 * k + 3]
        idx = self.lower_index if k == 0 else self.upper_index
        d = self._xv[0][idx] - self._half_stroke[4 * k : 4 * k + 4]
        f = self.hydraulic_forces_n[idx]
        return LayerTruth(
            heave_m=float(q[0]),
            roll_rad=float(q[1]),
            pitch_rad=float(q[2]),
            extensions_m=d,
            twist_m=float((d[0] - d[1] + d[2] - d[3]) / 4.0),
            rod_forces_n=f,
            twist_force_n=float((f[0] - f[1] + f[2] - f[3]) / 4.0),
        )

    def workpiece_attitude_rad(self) -> tuple[float, float]:
        """Roll and pitch of the upper platform plane in the world (``R_base R_L R_U``)."""
        q = self.y[_Q : _Q + 6]
        r = (
            rotation(self.cfg.base.roll_rad, self.cfg.base.pitch_rad)
            @ rotation(q[1], q[2])
            @ rotation(q[4], q[5])
        )
        n = r[:, 2]
        roll = math.asin(-max(-1.0, min(1.0, n[1])))
        pitch = math.atan2(n[0], n[2])
        return roll, pitch
