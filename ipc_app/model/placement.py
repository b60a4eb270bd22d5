"""Six-DOF placement geometry (placement.md sections 1-3): the one implementation that the
target planner, the survey fit and the placement move use.

Frames (docs/placement.md):

- Project frame P: the survey's coordinates (x, y horizontal, z up), in which
  ``tunnel.alignment`` gives the design axis.
- Tunnel frame T of a ring: origin on the design centreline at the ring's rear joint
  face, x along the design axis (chainage increasing), y to the left (horizontal), z
  completing a right-handed frame (up, tilted with the gradient).
- Part frame: origin at the centre of the part's bottom face, x along its width (the
  tunnel's axis, the ring width), y along its length (across the tunnel), z up.

A pose ``(x, y, z, roll, pitch, yaw)`` is the part frame in T: position of the
reference point and ``R = Rz(yaw) @ Ry(pitch) @ Rx(roll)`` (the attitude of
:func:`~ipc_app.model.kinematics.attitude_matrix`, turned by the yaw about T's z).

Six-DOF actuators (placement.md section 2), extensions from mid-stroke:

- height: the lower layer's four legs together (``d_i = z + ...`` of model.md section 3);
- yaw: the rotation pair at lever arm ``r`` about the upper platform's z axis, pushing
  in opposition: ``e_1 = r sin(yaw)``, ``e_2 = -r sin(yaw)``, so
  ``yaw = asin((e_1 - e_2) / (2 r))`` (small angles: ``(e_1 - e_2) / (2 r)``);
- lateral: the lateral pair together, ``e_1 = e_2 = y``;
- gap: the central-axis cylinder, ``e = x``.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from config import units
from config.alignment import chainage_after, level, plan_point, table_segment
from config.schema import Alignment, ProjectConfig
from ipc_app.model.kinematics import Array, attitude_matrix, rot_z

#: Names of a pose's six coordinates, in order.
POSE_KEYS: tuple[str, ...] = ("x", "y", "z", "roll", "pitch", "yaw")
#: :meth:`Pose.to_dict`'s keys in that order (mm and deg): a pose as six numbers on the
#: control channel
POSE_DICT_KEYS: tuple[str, ...] = tuple(
    f"{k}_mm" if k in ("x", "y", "z") else f"{k}_deg" for k in POSE_KEYS
)


class Pose(NamedTuple):
    """A rigid pose in SI (m, rad): position and ``Rz(yaw) Ry(pitch) Rx(roll)``."""

    x: float = 0.0
    y: float = 0.0
    z: float = 0.0
    roll: float = 0.0
    pitch: float = 0.0
    yaw: float = 0.0

    @property
    def position(self) -> Array:
        return np.array([self.x, self.y, self.z])

    @property
    def matrix(self) -> Array:
        return rot_z(self.yaw) @ attitude_matrix(self.roll, self.pitch)

    def deviated(self, dev: Pose) -> Pose:
        """This (design) pose with a survey sheet's deviation added: positions and angles
        term by term, in this pose's frame (not composed)."""
        return Pose(*(a + b for a, b in zip(self, dev, strict=True)))

    def apply(self, points: Array) -> Array:
        """Points (n, 3) of the part frame, in the pose's frame."""
        return np.asarray(points, dtype=float) @ self.matrix.T + self.position

    def to_dict(self) -> dict[str, float]:
        """mm and deg, as the CLI prints and the acceptance store keeps it."""
        return {
            "x_mm": units.to_mm(self.x),
            "y_mm": units.to_mm(self.y),
            "z_mm": units.to_mm(self.z),
            "roll_deg": units.to_deg(self.roll),
            "pitch_deg": units.to_deg(self.pitch),
            "yaw_deg": units.to_deg(self.yaw),
        }

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Pose:
        """The inverse of :meth:`to_dict`; KeyError/ValueError name a bad item."""
        vals = []
        for key in POSE_DICT_KEYS:
            v = float(d[key])
            if not math.isfinite(v):
                raise ValueError(f"{key}: got {v!r}: expected a finite number")
            vals.append(units.mm(v) if key.endswith("_mm") else units.deg(v))
        return cls(*vals)

    @classmethod
    def from_matrix(cls, r: Array, t: Array) -> Pose:
        pitch = -math.asin(max(-1.0, min(1.0, float(r[2, 0]))))
        roll = math.atan2(float(r[2, 1]), float(r[2, 2]))
        yaw = math.atan2(float(r[1, 0]), float(r[0, 0]))
        return cls(float(t[0]), float(t[1]), float(t[2]), roll, pitch, yaw)


def sheet_deviation(
    y_mm: float, z_mm: float, roll_deg: float, pitch_deg: float, yaw_deg: float
) -> Pose:
    """A part's deviation from its design as a survey sheet states it (y, z in mm;
    roll, pitch, yaw in deg; none along the axis) as a :class:`Pose` in SI units."""
    return Pose(
        0.0, units.mm(y_mm), units.mm(z_mm), units.deg(roll_deg), units.deg(pitch_deg),
        units.deg(yaw_deg),
    )  # fmt: skip


def compose(outer: Pose, inner: Pose) -> Pose:
    """``outer ∘ inner``: a pose given in ``outer``'s frame, expressed in the frame below."""
    r = outer.matrix @ inner.matrix
    return Pose.from_matrix(r, outer.matrix @ inner.position + outer.position)


def inverse(p: Pose) -> Pose:
    r = p.matrix.T
    return Pose.from_matrix(r, -r @ p.position)


# --------------------------------------------------------------------------- the design axis


def axis_pose(alignment: Alignment, chainage_m: float) -> Pose:
    """The tunnel frame at ``chainage_m`` as a pose in the project frame.

    A straight axis runs through the project origin along +x, rising by
    ``gradient_percent``; a table is linear between its rows (its tangent is the row
    segment's; beyond the ends the end segments go on); an axis by chainage has the
    point, heading (the pose's yaw) and grade (its pitch: ``-atan(grade)``) of its
    horizontal and vertical elements (:mod:`config.alignment`).
    """
    if alignment.horizontal is not None and alignment.vertical is not None:
        p = plan_point(alignment.horizontal, chainage_m)
        lv = level(alignment.vertical, chainage_m)
        t = np.array([math.cos(p.heading), math.sin(p.heading), lv.grade])
        t /= float(np.linalg.norm(t))
        origin = np.array([p.x, p.y, lv.z])
    elif alignment.gradient_percent is not None:
        g = alignment.gradient_percent / 100.0
        t = np.array([1.0, 0.0, g]) / math.hypot(1.0, g)
        origin = chainage_m * t
    else:
        pts = alignment.points
        k, f = table_segment(pts, chainage_m)
        a, b = pts[int(k)], pts[int(k) + 1]
        pa = np.array([a.x_m, a.y_m, a.z_m])
        pb = np.array([b.x_m, b.y_m, b.z_m])
        origin = pa + float(f) * (pb - pa)
        t = (pb - pa) / float(np.linalg.norm(pb - pa))
    y = np.cross([0.0, 0.0, 1.0], t)
    y /= float(np.linalg.norm(y))
    z = np.cross(t, y)
    return Pose.from_matrix(np.column_stack([t, y, z]), origin)


def chainage_along(alignment: Alignment, chainage_m: float, along_m: float) -> float:
    """The chainage ``along_m`` further along the axis than ``chainage_m``: for an axis by
    chainage (measured in plan) the axis's length with its grades
    (:func:`~config.alignment.chainage_after`), else ``chainage_m + along_m`` (the
    straight axis's chainage runs along it; a table's is as its rows say)."""
    if alignment.vertical is not None:
        return chainage_after(alignment.vertical, chainage_m, along_m)
    return chainage_m + along_m


def ring_chainage_m(cfg: ProjectConfig, ring: int) -> float:
    """Chainage of ring ``ring``'s rear joint face: ``ring - 1`` ring widths along the
    axis from ring 1's."""
    alignment = _alignment(cfg)
    return chainage_along(
        alignment, alignment.first_ring_chainage_m, (ring - 1) * cfg.tunnel.ring_width_m
    )


def tunnel_frame(cfg: ProjectConfig, ring: int) -> Pose:
    """Ring ``ring``'s tunnel frame T in the project frame."""
    return axis_pose(_alignment(cfg), ring_chainage_m(cfg, ring))


def to_ring_frame(cfg: ProjectConfig, pose: Pose, from_ring: int, to_ring: int) -> Pose:
    """A pose given in ring ``from_ring``'s T, in ring ``to_ring``'s T."""
    if from_ring == to_ring:
        return pose
    world = compose(tunnel_frame(cfg, from_ring), pose)
    return compose(inverse(tunnel_frame(cfg, to_ring)), world)


def design_pose(cfg: ProjectConfig, ring: int) -> Pose:
    """Where ring ``ring``'s part belongs, in its own T: its reference point
    on the invert (:attr:`~config.schema.ProjectConfig.reference_height_m`, the inner
    radius below the design centreline) at mid-width, its axes along the axis frame there."""
    _placement(cfg)
    half = cfg.workpiece.width_m / 2.0
    alignment = _alignment(cfg)
    at_mid = axis_pose(alignment, chainage_along(alignment, ring_chainage_m(cfg, ring), half))
    local = compose(at_mid, Pose(z=cfg.reference_height_m))
    return compose(inverse(tunnel_frame(cfg, ring)), local)


def _alignment(cfg: ProjectConfig) -> Alignment:
    if cfg.tunnel.alignment is None:
        raise ValueError("the project has no tunnel.alignment: the design axis is unknown")
    return cfg.tunnel.alignment


def _placement(cfg: ProjectConfig) -> Any:
    if cfg.placement is None:
        raise ValueError("the project has no placement section")
    return cfg.placement


# --------------------------------------------------------------------------- joint figures


def face_points(cfg: ProjectConfig, faces: Any, front: bool = True) -> Array:
    """Points ``(y, z)`` of a joint face (part frame, e.g. a survey's ``face_y_m,
    face_z_m``) as part-frame points (n, 3).

    A tapered part (``workpiece.taper_mm`` t) is ``w - t y / L`` wide at ``y`` (``w`` its
    width, ``L`` its length), each face taking half: the front face at
    ``x = (w - t y / L) / 2``, the rear at its negative. ``t > 0`` makes the left end
    (+y) the narrower, the inside of a left-hand curve (``radius_m > 0``); ``t < 0`` the
    right end; ``t = w L / R`` puts both faces on the curve's radii (docs/curves.md)."""
    w = cfg.workpiece
    f = np.asarray(faces, dtype=float).reshape(-1, 2)
    x = (w.width_m - w.taper_m * f[:, 0] / w.length_m) / 2.0
    return np.column_stack([x if front else -x, f[:, 0], f[:, 1]])


def face_corners(cfg: ProjectConfig, front: bool) -> Array:
    """The four corners of a joint face in the part frame (a rectangle of the part's
    length and height, at ``x = ±width/2``, tapered as :func:`face_points` says): order
    (+y, bottom), (-y, bottom), (+y, top), (-y, top)."""
    w = cfg.workpiece
    half = w.length_m / 2.0
    return face_points(
        cfg, [(half, 0.0), (-half, 0.0), (half, w.height_m), (-half, w.height_m)], front
    )


class JointFigures(NamedTuple):
    """Paper Table 4 of a new part against the previous one and the design (SI).

    At each of the four corners of the joint, the step ``d = N_k - P_k`` between the
    new part's rear-face corner and the previous part's front-face corner, in T:
    ``d_z`` is the vertical and ``d_y`` the horizontal misalignment, ``d_x`` the gap.
    Misalignment: the corner's step of largest magnitude (signed). Centreline deviation
    x (horizontal) and y (vertical): the reference point's offset from the design in
    T's y and z. Angles: the part's tilt (roll), pitch and rotation (yaw) less the
    design's.
    """

    vertical_misalignment_m: float
    horizontal_misalignment_m: float
    max_gap_m: float
    min_gap_m: float
    centreline_deviation_x_m: float
    centreline_deviation_y_m: float
    pitch_angle_rad: float
    tilt_angle_rad: float
    rotation_angle_rad: float

    def to_dict(self) -> dict[str, float]:
        """The acceptance items' keys and units (mm, deg), plus ``min_gap_mm``."""
        out: dict[str, float] = {}
        for k, v in self._asdict().items():
            if k.endswith("_m"):
                out[k[:-2] + "_mm"] = units.to_mm(v)
            else:
                out[k[:-4] + "_deg"] = units.to_deg(v)
        return out


def _signed_max(v: Array) -> float:
    return float(v[int(np.argmax(np.abs(v)))])


def deviation(new: Pose, design: Pose) -> Pose:
    """The new part's pose relative to its design pose, as y/z offsets in T and angle
    differences (the centreline deviation and the angle items)."""
    rel = compose(inverse(design), new)
    off = new.position - design.position
    return Pose(float(off[0]), float(off[1]), float(off[2]), rel.roll, rel.pitch, rel.yaw)


def joint_figures(cfg: ProjectConfig, previous: Pose, new: Pose, design: Pose) -> JointFigures:
    """Table 4 of ``new`` (all three poses in the new ring's T)."""
    d = new.apply(face_corners(cfg, front=False)) - previous.apply(face_corners(cfg, front=True))
    dev = deviation(new, design)
    return JointFigures(
        vertical_misalignment_m=_signed_max(d[:, 2]),
        horizontal_misalignment_m=_signed_max(d[:, 1]),
        max_gap_m=float(d[:, 0].max()),
        min_gap_m=float(d[:, 0].min()),
        centreline_deviation_x_m=dev.y,
        centreline_deviation_y_m=dev.z,
        pitch_angle_rad=dev.pitch,
        tilt_angle_rad=dev.roll,
        rotation_angle_rad=dev.yaw,
    )


# --------------------------------------------------------------------------- actuators


class SixDofExtensions(NamedTuple):
    """Extensions from mid-stroke (m) that move the part by a pose delta on the robot:
    ``heave`` added to each of the four lower legs, the rotation pair, the lateral pair
    and the central axis."""

    heave: float
    rotation: tuple[float, float]
    lateral: tuple[float, float]
    central_axis: float


def six_dof_extensions(delta: Pose, lever_arm_m: float) -> SixDofExtensions:
    """The single-axis extensions of a pose delta (its roll and pitch go to the
    attitude planner)."""
    s = lever_arm_m * math.sin(delta.yaw)
    return SixDofExtensions(delta.z, (s, -s), (delta.y, delta.y), delta.x)


def yaw_of_pair(e1: float, e2: float, lever_arm_m: float) -> float:
    """``yaw = asin((e_1 - e_2) / (2 r))``, the inverse of :func:`six_dof_extensions`."""
    return math.asin(max(-1.0, min(1.0, (e1 - e2) / (2.0 * lever_arm_m))))


# --------------------------------------------------------------------------- survey fit


class PoseFit(NamedTuple):
    pose: Pose
    residuals_m: Array  # distance of each measured point from the fitted one
    rms_residual_m: float


def fit_pose(nominal: Array, measured: Array) -> PoseFit:
    """Least-squares rigid fit (Kabsch): the pose that maps the part-frame points
    ``nominal`` (n, 3) closest to ``measured`` (n, 3). Needs three points not on one
    line (ValueError otherwise)."""
    a = np.asarray(nominal, dtype=float)
    b = np.asarray(measured, dtype=float)
    ca, cb = a.mean(axis=0), b.mean(axis=0)
    h = (a - ca).T @ (b - cb)
    sv = np.linalg.svd(a - ca, compute_uv=False)
    if len(a) < 3 or sv[1] < 1e-3 * max(sv[0], 1e-12):
        raise ValueError("the points lie on one line: the pose cannot be fitted")
    u, _, vt = np.linalg.svd(h)
    dd = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, dd]) @ u.T
    t = cb - r @ ca
    pose = Pose.from_matrix(r, t)
    res = np.linalg.norm(pose.apply(a) - b, axis=1)
    return PoseFit(pose, res, float(np.sqrt(np.mean(res**2))))
