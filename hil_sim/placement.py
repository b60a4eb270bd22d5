"""The simulator's truth of the workpiece's full pose (placement.md section 2).

The part rides on a slide stage on the upper platform: the central-axis cylinder moves
it along the platform's x, the lateral pair along its y (their mean), the rotation pair
turns it about the platform's z at lever arm ``placement.rotation_lever_arm_m``
(``yaw = asin((e_1 - e_2) / 2r)``). Its reference point (the centre of its bottom face)
is the upper platform's origin when the slide rods are at mid-stroke.

:func:`pose_from_home` is that chain on the rig's state, relative to where the part is
with every cylinder at mid-stroke (the home pose): lower platform
``(z_L, R_L)`` about its origin, the upper base ``origin_in_lower_m`` above it, the upper
platform ``(z_U, R_U)``, the slide ``(x, y, yaw)``. As :mod:`hil_sim.rig` says of the
layer kinematics, this is the plant's own, on purpose not the controller's
``ipc_app.model.placement``: it is what the controller is checked against.

Once the part is bolted to its ring (:func:`bolt_part`) its pose is frozen: from then
on :func:`pose_from_home` is that pose, wherever the platform goes.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from config.schema import ProjectConfig
from hil_sim.rig import Rig, rotation

FloatArray = NDArray[np.float64]


def _rz(yaw: float) -> FloatArray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def slide_state(cfg: ProjectConfig, rod_positions_m: FloatArray) -> tuple[float, float, float]:
    """``(x, y, yaw)`` of the slide stage from the rods (from retracted, by can_index)."""
    if cfg.placement is None:
        raise ValueError("the project has no placement section: no slide stage")
    ext: dict[str, list[float]] = {"rotation": [], "lateral": [], "central_axis": []}
    for c in cfg.cylinders_by_can_index:
        if c.role in ext:
            ext[c.role].append(float(rod_positions_m[c.can_index]) - c.stroke_m / 2)
    r = cfg.placement.rotation_lever_arm_m
    e1, e2 = ext["rotation"]
    yaw = math.asin(max(-1.0, min(1.0, (e1 - e2) / (2.0 * r))))
    return ext["central_axis"][0], sum(ext["lateral"]) / 2.0, yaw


def pose_from_home(cfg: ProjectConfig, rig: Rig) -> tuple[FloatArray, FloatArray]:
    """``(R, t)``: the part's frame relative to its home pose (all rods at mid-stroke);
    while the part is bolted, the pose it was bolted in."""
    if rig.part_state == "bolted" and rig.bolted_pose is not None:
        r, t = rig.bolted_pose
        return r.copy(), t.copy()
    q = rig.q
    x, y, yaw = slide_state(cfg, rig.rod_positions_m)
    r_l = rotation(float(q[1]), float(q[2]))
    r_u = rotation(float(q[4]), float(q[5]))
    origin_u = np.array(cfg.layers.upper.origin_in_lower_m, dtype=float)
    ez = np.array([0.0, 0.0, 1.0])
    on_upper = float(q[3]) * ez + r_u @ np.array([x, y, 0.0])
    t = float(q[0]) * ez + r_l @ (origin_u + on_upper) - origin_u
    return r_l @ r_u @ _rz(yaw), t


def bolt_part(cfg: ProjectConfig, rig: Rig) -> tuple[FloatArray, FloatArray]:
    """The part bolted to its ring where it is now: its pose frozen (the returned ``(R,
    t)`` from home) and its pads under it on the upper platform, carried there by the
    slide stage (:meth:`Rig.bolt_part`)."""
    pose = pose_from_home(cfg, rig)
    x, y, yaw = slide_state(cfg, rig.rod_positions_m)
    rig.bolt_part(rig.pad_points_m(x, y, yaw), pose)
    return pose
