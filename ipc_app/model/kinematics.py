"""Frames and single-layer kinematics (model.md sections 1 and 3): the one implementation
that planner, trajectory, controller and service use.

The functions are vectorized: angles may be floats or numpy arrays of any (common)
shape; per-cylinder results gain a trailing axis of length 4 (cylinders 1-4). The
control loop samples one point per cycle, where numpy's per-call overhead is most of the
cost: :func:`extensions_at` and :func:`layer_twist` give the same formulas on plain
floats. Each formula is written once (``_layer_extensions``, ``_plane_attitude``,
:func:`layer_twist`) and evaluated on arrays or on floats.

Attitude of a platform relative to the frame below: ``R(roll, pitch) = Ry(pitch) @ Rx(roll)``.
Cylinder i acts at platform point ``p_i = (s_i a, t_i b, 0)`` with
``(s_i, t_i)`` = 1:(+,+), 2:(-,+), 3:(-,-), 4:(+,-).
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

Array = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

#: Signs of the action points, cylinders 1-4 (model.md section 2).
S = np.array([1.0, -1.0, -1.0, 1.0])
T = np.array([1.0, 1.0, -1.0, -1.0])


def rot_x(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


def rot_y(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def rot_z(angle: float) -> Array:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def attitude_matrix(roll: float, pitch: float) -> Array:
    """``R(roll, pitch) = Ry(pitch) @ Rx(roll)`` for scalar angles."""
    return rot_y(pitch) @ rot_x(roll)


class Vec(NamedTuple):
    """A 3-vector whose components may be arrays (for vectorized geometry)."""

    x: Array
    y: Array
    z: Array


def rotate(roll: ArrayLike, pitch: ArrayLike, v: Vec) -> Vec:
    """``R(roll, pitch) @ v``, componentwise and broadcast."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    y1 = cr * v.y - sr * v.z
    z1 = sr * v.y + cr * v.z
    return Vec(cp * v.x + sp * z1, y1, -sp * v.x + cp * z1)


def rotate_t(roll: ArrayLike, pitch: ArrayLike, v: Vec) -> Vec:
    """``R(roll, pitch).T @ v``, componentwise and broadcast."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    x1 = cp * v.x - sp * v.z
    z1 = sp * v.x + cp * v.z
    return Vec(x1, cr * v.y + sr * z1, -sr * v.y + cr * z1)


def normal(roll: ArrayLike, pitch: ArrayLike) -> Vec:
    """``R(roll, pitch) @ e_z``: the platform's normal in the frame below."""
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    return Vec(sp * cr, -sr, cp * cr)


def _layer_extensions(
    sin: Callable[[Any], Any],
    cos: Callable[[Any], Any],
    roll: Any,
    pitch: Any,
    a: float,
    b: float,
    heave: Any = 0.0,
    twist: Any = None,
) -> list[Any]:
    """The layer's extensions, cylinders 1-4, with ``sin``/``cos`` of numpy or of math.

    ``d_i = z - x_i sin(pitch) + y_i sin(roll) cos(pitch) + twist P_i`` with
    ``x_i = s_i a``, ``y_i = t_i b``, ``P = (1, -1, 1, -1)`` (``twist`` None: no term).
    """
    asp = a * sin(pitch)
    bsc = b * sin(roll) * cos(pitch)
    d1 = heave - asp + bsc
    d2 = heave + asp + bsc
    d3 = heave + asp - bsc
    d4 = heave - asp - bsc
    if twist is None:
        return [d1, d2, d3, d4]
    return [d1 + twist, d2 - twist, d3 + twist, d4 - twist]


def extensions(
    roll: ArrayLike,
    pitch: ArrayLike,
    a: float,
    b: float,
    heave: ArrayLike = 0.0,
    twist: ArrayLike | None = None,
) -> Array:
    """Extensions from mid-stroke of cylinders 1-4 (shape ``(..., 4)``).

    ``d_i = z - x_i sin(pitch) + y_i sin(roll) cos(pitch)`` with ``x_i = s_i a``, ``y_i = t_i b``;
    with ``twist`` given, ``+ twist (1, -1, 1, -1)`` (a layer that is not a plane).
    """
    r, p, z = np.broadcast_arrays(
        np.asarray(roll, dtype=float), np.asarray(pitch, dtype=float), np.asarray(heave, float)
    )
    tw = None if twist is None else np.asarray(twist, dtype=float)
    return np.stack(_layer_extensions(np.sin, np.cos, r, p, a, b, z, tw), axis=-1)


#: :func:`extensions` at one attitude, on plain floats (the control loop's form):
#: ``extensions_at(roll, pitch, a, b, heave=0.0, twist=None) -> [d1, d2, d3, d4]``. A
#: partial (no Python frame of its own): the loop calls it four times a cycle.
extensions_at = functools.partial(_layer_extensions, math.sin, math.cos)


def _plane_attitude(sin_pitch: Array, sin_roll_cos_pitch: Array) -> tuple[Array, Array]:
    """(roll, pitch) from ``sin(pitch)`` and ``sin(roll) cos(pitch)``: the inverse of
    :func:`extensions` (both clipped to [-1, 1])."""
    pitch = np.arcsin(np.clip(sin_pitch, -1.0, 1.0))
    roll = np.arcsin(np.clip(sin_roll_cos_pitch / np.cos(pitch), -1.0, 1.0))
    return roll, pitch


def layer_twist(d1: Any, d2: Any, d3: Any, d4: Any) -> Any:
    """The layer's twist ``(d1 - d2 + d3 - d4) / 4`` (m), on floats or arrays."""
    return (d1 - d2 + d3 - d4) / 4.0


class LayerFit(NamedTuple):
    """Least-squares plane through four measured extensions."""

    roll: Array
    pitch: Array
    heave: Array
    twist: Array  # (d1 - d2 + d3 - d4) / 4, the residual that no plane explains


def fit_layer(d: ArrayLike, a: float, b: float) -> LayerFit:
    """Forward model: fit (roll, pitch, heave) to four extensions in least squares.

    With the symmetric action points the normal equations decouple:
    ``heave = mean(d)``, ``sin(pitch) = (-d1 + d2 + d3 - d4) / (4a)``,
    ``sin(roll) cos(pitch) = (d1 + d2 - d3 - d4) / (4b)``; the residual of each point is
    ``±twist``. On a linked plan (``d3 = -d1``, ``d4 = -d2``, heave 0) this reduces to
    :func:`linked_attitude`.
    """
    d_ = np.asarray(d, dtype=float)
    d1, d2, d3, d4 = d_[..., 0], d_[..., 1], d_[..., 2], d_[..., 3]
    heave = (d1 + d2 + d3 + d4) / 4.0
    roll, pitch = _plane_attitude((-d1 + d2 + d3 - d4) / (4.0 * a), (d1 + d2 - d3 - d4) / (4.0 * b))
    return LayerFit(roll, pitch, heave, layer_twist(d1, d2, d3, d4))


def linked_attitude(d1: ArrayLike, d2: ArrayLike, a: float, b: float) -> tuple[Array, Array]:
    """(roll, pitch) of a linked layer (``d3 = -d1``, ``d4 = -d2``, heave 0) from d1, d2:
    the exact inverse of model.md section 3, ``sin(pitch) = (d2 - d1) / 2a``,
    ``sin(roll) cos(pitch) = (d1 + d2) / 2b``."""
    d1_, d2_ = np.asarray(d1), np.asarray(d2)
    return _plane_attitude((d2_ - d1_) / (2.0 * a), (d1_ + d2_) / (2.0 * b))


def twist(d: ArrayLike) -> Array:
    """The layer's twist :func:`layer_twist` of extensions ``d`` (shape ``(..., 4)``)."""
    d_ = np.asarray(d, dtype=float)
    return np.asarray(layer_twist(d_[..., 0], d_[..., 1], d_[..., 2], d_[..., 3]))


def coplanarity_distance(d: ArrayLike, a: float, b: float) -> Array:
    """Distance of action point 4 from the plane through action points 1, 2, 3 (paper eq. 17).

    The action points are ``(x_i, y_i, d_i)`` in the layer's base frame (the rods are
    perpendicular to it). The plane through 1-3 is ``z = c0 + c1 x + c2 y`` with
    ``c1 = (d1 - d2) / 2a``, ``c2 = (d2 - d3) / 2b``; point 4 lies ``4 * twist`` below it
    along z, so the perpendicular distance is ``4 |twist| / sqrt(1 + c1^2 + c2^2)``.
    """
    d_ = np.asarray(d, dtype=float)
    c1 = (d_[..., 0] - d_[..., 1]) / (2.0 * a)
    c2 = (d_[..., 1] - d_[..., 2]) / (2.0 * b)
    return 4.0 * np.abs(twist(d_)) / np.sqrt(1.0 + c1 * c1 + c2 * c2)
