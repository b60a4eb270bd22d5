"""Composition of the two layers (model.md section 4).

The workpiece attitude in the world is ``R_w = R_base @ R_L @ R_U``. The target fixes
only the workpiece plane's normal ``n*``; choosing the upper attitude fixes the lower.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from ipc_app.model.kinematics import Array, BoolArray, Vec, attitude_matrix, normal, rotate_t


def wrap(angle: ArrayLike) -> Array:
    """Wrap to (-pi, pi]."""
    a = np.asarray(angle, dtype=float)
    return np.pi - np.mod(np.pi - a, 2.0 * np.pi)


class LowerSolution(NamedTuple):
    roll: Array
    pitch: Array
    solvable: BoolArray  # False where no lower roll reaches the target normal


def target_in_base(base_roll: float, base_pitch: float, roll: float, pitch: float) -> Vec:
    """``v = R_base^T n*`` with ``n* = R(roll*, pitch*) e_z``."""
    n = normal(roll, pitch)
    v = rotate_t(base_roll, base_pitch, Vec(np.asarray(n.x), np.asarray(n.y), np.asarray(n.z)))
    return Vec(np.asarray(v.x), np.asarray(v.y), np.asarray(v.z))


def solve_lower(upper_roll: ArrayLike, upper_pitch: ArrayLike, v: Vec) -> LowerSolution:
    """Lower attitude ``(a_L, b_L)`` with ``R(a_L, b_L) u = v``, ``u = R(a_U, b_U) e_z``.

    The y-row gives ``u_y cos a_L - u_z sin a_L = v_y``, i.e. ``rho cos(a_L + phi) = v_y``
    with ``rho = hypot(u_y, u_z)``, ``phi = atan2(u_z, u_y)``; of its two roots the one with
    the smaller |a_L| is taken. Then ``b_L = atan2(v_x, v_z) - atan2(w_x, w_z)``,
    ``w = Rx(a_L) u``.
    """
    u = normal(upper_roll, upper_pitch)
    rho = np.hypot(u.y, u.z)
    phi = np.arctan2(u.z, u.y)
    c = v.y / rho
    solvable = np.abs(c) <= 1.0
    acos = np.arccos(np.clip(c, -1.0, 1.0))
    r1 = wrap(acos - phi)
    r2 = wrap(-acos - phi)
    roll = np.where(np.abs(r1) <= np.abs(r2), r1, r2)
    cr, sr = np.cos(roll), np.sin(roll)
    wx = u.x
    wz = u.y * sr + u.z * cr
    pitch = wrap(np.arctan2(v.x, v.z) - np.arctan2(wx, wz))
    return LowerSolution(roll, pitch, solvable)


def workpiece_matrix(
    base: tuple[float, float], lower: tuple[float, float], upper: tuple[float, float]
) -> Array:
    """``R_w = R_base @ R_L @ R_U`` for scalar (roll, pitch) pairs."""
    return attitude_matrix(*base) @ attitude_matrix(*lower) @ attitude_matrix(*upper)


class AttitudeCheck(NamedTuple):
    error_rad: float  # angle between the achieved and the target workpiece normal
    yaw_residual_rad: float  # rotation about the normal the composition leaves
    roll: float  # achieved workpiece roll, from the normal
    pitch: float  # achieved workpiece pitch, from the normal


def check_attitude(
    base: tuple[float, float],
    lower: tuple[float, float],
    upper: tuple[float, float],
    target: tuple[float, float],
) -> AttitudeCheck:
    """Compare the composed workpiece attitude with the target (scalar)."""
    rw = workpiece_matrix(base, lower, upper)
    rt = attitude_matrix(*target)
    n_w, n_t = rw[:, 2], rt[:, 2]
    cross = float(np.linalg.norm(np.cross(n_w, n_t)))
    error = float(np.arctan2(cross, float(np.dot(n_w, n_t))))
    m = rt.T @ rw
    yaw = float(np.arctan2(m[1, 0] - m[0, 1], m[0, 0] + m[1, 1]))
    # Roll and pitch of the achieved normal: n = (sin p cos r, -sin r, cos p cos r).
    roll = float(-np.arcsin(np.clip(n_w[1], -1.0, 1.0)))
    pitch = float(np.arctan2(n_w[0], n_w[2]))
    return AttitudeCheck(error, yaw, roll, pitch)
