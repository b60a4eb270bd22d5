"""The new part's target pose from the previous part's as-built pose (placement.md
section 3) and the six-DOF moves that reach it (section 2).

The target is a small optimization over the new part's deviation from its design pose
``v = (x, y, z, roll, pitch, yaw)`` (positions in mm, angles as mm at the part's
half-length, so that every term is in mm^2):

    J = w_m * mean_k(dy_k^2 + dz_k^2) + w_c * (dev_y^2 + dev_z^2)
        + w_g * mean_k(dx_k - gap*)^2 + w_a * (roll^2 + pitch^2 + yaw^2)

with ``d_k`` the step between the two parts' joint-face corners (the misalignment,
:func:`~ipc_app.model.placement.joint_figures`), ``dev`` the reference point's offset
from the design centreline and ``w`` the ``placement.weights``. Limits:

- Table 4 (``acceptance``): every corner's |vertical| and |horizontal| step, every
  corner's gap at most ``max_gap_mm`` (and >= 0: the parts may not overlap), |dev_y|
  and |dev_z|, the angles where their limits are set;
- the steering-back bound: each of dev_y, dev_z and the three angles differs from the
  previous part's by at most ``max_correction_per_ring_mm`` / ``_deg``.

SLSQP solves it from the previous part's deviation. When it finds no feasible point,
a second solve keeps the steering-back bound and minimizes the squared Table 4
violations: the largest left is the binding limit, reported with how much it is
exceeded, and the plan is refused. A gap limit that binds is explained first by the
design joint's opening on a curve against the parts' taper (:func:`curve_reason`,
docs/curves.md).

Over 500 lines because the target's optimization, its refusal with the binding
limit and the six-DOF moves that check it against strokes and pressures are one plan.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np
from scipy.optimize import minimize

from config import units
from config.schema import Placement, ProjectConfig
from ipc_app.model.placement import (
    JointFigures,
    Pose,
    SixDofExtensions,
    compose,
    design_pose,
    deviation,
    face_corners,
    inverse,
    joint_figures,
    six_dof_extensions,
    to_ring_frame,
    tunnel_frame,
)
from ipc_app.planner.capacity import pressure_limit_pa, pressure_reason
from ipc_app.planner.plan import plan as plan_attitude

#: Slack (mm, or mm-equivalent) within which a limit counts as kept.
_TOL_MM = 1e-6


@dataclass(frozen=True)
class Limit:
    """One inequality ``value <= limit`` of the target problem (mm or deg)."""

    name: str  # e.g. "vertical_misalignment_mm at corner 1"
    value: float
    limit: float
    hard: bool  # the steering-back bound (kept even when refusing)

    @property
    def excess(self) -> float:
        return self.value - self.limit


@dataclass(frozen=True)
class ActuatorCheck:
    """The move of one actuator group to the target, against its stroke and pressure."""

    group: str
    extensions_mm: tuple[float, ...]
    limit_mm: float
    pressure_mpa: float | None
    pressure_limit_mpa: float | None
    reasons: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {
            "group": self.group,
            "extensions_mm": list(self.extensions_mm),
            "stroke_limit_mm": self.limit_mm,
            "pressure_mpa": self.pressure_mpa,
            "pressure_limit_mpa": self.pressure_limit_mpa,
            "ok": not self.reasons,
        }


@dataclass(frozen=True)
class PlacementPlan:
    feasible: bool
    ring: int
    previous: Pose  # as built, in the new ring's T
    design: Pose
    target: Pose
    figures: JointFigures
    previous_deviation: Pose
    objective_mm2: float
    reasons: list[str]
    binding: Limit | None
    actuators: tuple[ActuatorCheck, ...] = ()
    attitude_world_deg: tuple[float, float] = (0.0, 0.0)
    solve_time_s: float = 0.0
    judged: dict[str, dict[str, Any]] = field(default_factory=dict)
    #: the lower layer's common heave from the home pose to the target (m)
    heave_m: float = 0.0

    @property
    def heave_mm(self) -> float:
        return units.to_mm(self.heave_m)

    def to_dict(self) -> dict[str, Any]:
        dev = deviation(self.target, self.design)
        return {
            "feasible": self.feasible,
            "ring": self.ring,
            "previous_as_built": self.previous.to_dict(),
            "previous_deviation": _dev_dict(self.previous_deviation),
            "design": self.design.to_dict(),
            "target": self.target.to_dict(),
            "target_deviation": _dev_dict(dev),
            "table4": self.judged,
            "min_gap_mm": units.to_mm(self.figures.min_gap_m),
            "objective_mm2": self.objective_mm2,
            "attitude_world_deg": {
                "roll_deg": self.attitude_world_deg[0],
                "pitch_deg": self.attitude_world_deg[1],
            },
            "actuators": [a.to_dict() for a in self.actuators],
            "heave_mm": self.heave_mm,
            "binding": None
            if self.binding is None
            else {
                "limit": self.binding.name,
                "value": self.binding.value,
                "allowed": self.binding.limit,
                "exceeded_by": self.binding.excess,
            },
            "reasons": self.reasons,
            "solve_time_s": self.solve_time_s,
        }


def _dev_dict(d: Pose) -> dict[str, float]:
    return {
        "y_mm": units.to_mm(d.y),
        "z_mm": units.to_mm(d.z),
        "roll_deg": units.to_deg(d.roll),
        "pitch_deg": units.to_deg(d.pitch),
        "yaw_deg": units.to_deg(d.yaw),
    }


def judge(cfg: ProjectConfig, figures: JointFigures) -> dict[str, dict[str, Any]]:
    """Each Table 4 item of ``figures`` with its limit (None: not judged) and verdict.
    The gap is judged at both ends of the joint: ``max_gap_mm`` (the largest corner's)
    within its limit and ``min_gap_mm`` (the smallest) at least 0 (``at_least``: the
    parts may not overlap)."""
    out: dict[str, dict[str, Any]] = {}
    tol = cfg.acceptance.model_dump()
    for key, value in figures.to_dict().items():
        if key == "min_gap_mm":
            out[key] = {"value": value, "limit": 0.0, "passed": value >= -_TOL_MM}
            out[key]["at_least"] = True
            continue
        limit = tol[key]
        passed = None if limit is None else abs(value) <= limit + _TOL_MM
        out[key] = {"value": value, "limit": limit, "passed": passed}
    return out


class _Problem:
    """The target problem in mm-scaled variables ``v`` (see the module docstring)."""

    def __init__(self, cfg: ProjectConfig, previous: Pose, design: Pose, prev_dev: Pose) -> None:
        assert cfg.placement is not None
        self.cfg = cfg
        self.pl: Placement = cfg.placement
        self.previous = previous
        self.design = design
        self.prev_dev = prev_dev
        self.arm_m = cfg.workpiece.length_m / 2.0  # angle -> mm at the half-length
        self.rear = face_corners(cfg, front=False)
        self.prev_front = previous.apply(face_corners(cfg, front=True))

    def pose(self, v: np.ndarray) -> Pose:
        d = self.design
        pos = d.position + units.mm(1.0) * v[:3]
        ang = units.mm(1.0) * v[3:] / self.arm_m
        return Pose(
            float(pos[0]), float(pos[1]), float(pos[2]),
            d.roll + float(ang[0]), d.pitch + float(ang[1]), d.yaw + float(ang[2]),
        )  # fmt: skip

    def steps_mm(self, v: np.ndarray) -> np.ndarray:
        return units.to_mm(1.0) * (self.pose(v).apply(self.rear) - self.prev_front)

    def start(self) -> np.ndarray:
        p = self.prev_dev
        v = np.array([0.0, p.y, p.z, p.roll * self.arm_m, p.pitch * self.arm_m, p.yaw * self.arm_m])
        v[1:] *= units.to_mm(1.0)
        gap = float(np.mean(self.steps_mm(v)[:, 0]))
        v[0] = self.pl.target_gap_mm - gap
        return v

    def objective(self, v: np.ndarray) -> float:
        w = self.pl.weights
        d = self.steps_mm(v)
        dev = self._dev_mm(v)
        return float(
            w.misalignment * np.mean(d[:, 1] ** 2 + d[:, 2] ** 2)
            + w.centreline_deviation * (dev[0] ** 2 + dev[1] ** 2)
            + w.gap * np.mean((d[:, 0] - self.pl.target_gap_mm) ** 2)
            + w.angle * float(np.sum(dev[2:] ** 2))
        )

    def _dev_mm(self, v: np.ndarray) -> np.ndarray:
        """(dev_y mm, dev_z mm, roll, pitch, yaw as mm at the half-length)."""
        d = deviation(self.pose(v), self.design)
        k = units.to_mm(self.arm_m)
        return np.array([units.to_mm(d.y), units.to_mm(d.z), d.roll * k, d.pitch * k, d.yaw * k])

    def limits(self, v: np.ndarray) -> list[Limit]:
        acc = self.cfg.acceptance
        d = self.steps_mm(v)
        dev = deviation(self.pose(v), self.design)
        out: list[Limit] = []
        for k in range(4):
            for axis, key, lim in (
                (2, "vertical_misalignment_mm", acc.vertical_misalignment_mm),
                (1, "horizontal_misalignment_mm", acc.horizontal_misalignment_mm),
            ):
                out.append(Limit(f"{key} at corner {k + 1}", abs(d[k, axis]), lim, False))
            out.append(Limit(f"max_gap_mm at corner {k + 1}", d[k, 0], acc.max_gap_mm, False))
            out.append(Limit(f"no overlap at corner {k + 1} (gap >= 0)", -d[k, 0], 0.0, False))
        for name, val, lim in (
            ("centreline_deviation_x_mm", units.to_mm(dev.y), acc.centreline_deviation_x_mm),
            ("centreline_deviation_y_mm", units.to_mm(dev.z), acc.centreline_deviation_y_mm),
        ):
            out.append(Limit(name, abs(val), lim, False))
        for name, val, lim_deg in (
            ("tilt_angle_deg", dev.roll, acc.tilt_angle_deg),
            ("pitch_angle_deg", dev.pitch, acc.pitch_angle_deg),
            ("rotation_angle_deg", dev.yaw, acc.rotation_angle_deg),
        ):
            if lim_deg is not None:
                out.append(Limit(name, abs(units.to_deg(val)), lim_deg, False))
        p = self.prev_dev
        for name, now, before in (
            ("correction per ring, y (mm)", units.to_mm(dev.y), units.to_mm(p.y)),
            ("correction per ring, z (mm)", units.to_mm(dev.z), units.to_mm(p.z)),
        ):
            out.append(Limit(name, abs(now - before), self.pl.max_correction_per_ring_mm, True))
        for name, now_r, before_r in (
            ("correction per ring, roll (deg)", dev.roll, p.roll),
            ("correction per ring, pitch (deg)", dev.pitch, p.pitch),
            ("correction per ring, yaw (deg)", dev.yaw, p.yaw),
        ):
            out.append(
                Limit(
                    name,
                    abs(units.to_deg(now_r - before_r)),
                    self.pl.max_correction_per_ring_deg,
                    True,
                )
            )
        return out


def _smooth(p: _Problem, hard: bool) -> Callable[[np.ndarray], np.ndarray]:
    """``limit - value >= 0`` of the hard or soft limits, each |.| split in two smooth
    halves (SLSQP wants differentiable constraints)."""

    def fn(v: np.ndarray) -> np.ndarray:
        d = p.steps_mm(v)
        dev = p._dev_mm(v)
        acc, pl = p.cfg.acceptance, p.pl
        k = units.to_mm(p.arm_m)
        if hard:
            prev = np.array(
                [
                    units.to_mm(p.prev_dev.y),
                    units.to_mm(p.prev_dev.z),
                    p.prev_dev.roll * k,
                    p.prev_dev.pitch * k,
                    p.prev_dev.yaw * k,
                ]
            )
            lim = np.array(
                [pl.max_correction_per_ring_mm] * 2
                + [units.deg(pl.max_correction_per_ring_deg) * k] * 3
            )
            c = dev - prev
            return np.concatenate([lim - c, lim + c])
        rows = [
            acc.vertical_misalignment_mm - d[:, 2],
            acc.vertical_misalignment_mm + d[:, 2],
            acc.horizontal_misalignment_mm - d[:, 1],
            acc.horizontal_misalignment_mm + d[:, 1],
            acc.max_gap_mm - d[:, 0],
            d[:, 0],
            np.array(
                [acc.centreline_deviation_x_mm - dev[0], acc.centreline_deviation_x_mm + dev[0]]
            ),
            np.array(
                [acc.centreline_deviation_y_mm - dev[1], acc.centreline_deviation_y_mm + dev[1]]
            ),
        ]
        for i, lim_deg in (
            (2, acc.tilt_angle_deg),
            (3, acc.pitch_angle_deg),
            (4, acc.rotation_angle_deg),
        ):
            if lim_deg is not None:
                m = units.deg(lim_deg) * k
                rows.append(np.array([m - dev[i], m + dev[i]]))
        return np.concatenate(rows)

    return fn


#: The limits of the gap (at a corner of the joint): a curve's opening binds one of them.
_GAP_LIMITS = ("max_gap_mm", "no overlap")
#: A design joint opening less than this (mm) across the part is no curve's doing.
_OPENING_MM = 0.1


class JointOpening(NamedTuple):
    """How the design joint of ring ``ring`` opens across the part: ``opening_mm`` the
    gap at the part's left end (+y) less at its right end, bottom corners (designed
    parts laid on the axis); ``radius_m`` the curve's (signed, positive turning left;
    None on a straight); ``taper_needed_mm`` the ``workpiece.taper_mm`` that closes it."""

    opening_mm: float
    radius_m: float | None
    taper_needed_mm: float


def joint_opening(cfg: ProjectConfig, ring: int) -> JointOpening:
    """The design joint's opening of ring ``ring`` against ring ``ring - 1``: with a taper
    ``t`` the gap at ``y`` is ``t y / L - y w / R`` (docs/curves.md), so the two ends differ
    by ``t - w L / R`` and ``t - opening`` closes it."""
    design = design_pose(cfg, ring)
    prev = to_ring_frame(cfg, design_pose(cfg, ring - 1), ring - 1, ring)
    d = design.apply(face_corners(cfg, front=False)) - prev.apply(face_corners(cfg, front=True))
    opening = units.to_mm(float(d[0, 0] - d[1, 0]))
    turn = deviation(design, prev).yaw
    radius = cfg.workpiece.width_m / turn if abs(turn) > 1e-12 else None
    return JointOpening(opening, radius, cfg.workpiece.taper_mm - opening)


def curve_reason(cfg: ProjectConfig, ring: int) -> str:
    """Why the design joint of ring ``ring`` opens (a curve against the parts' taper),
    as a refusal's first words, or empty when it does not open."""
    j = joint_opening(cfg, ring)
    if abs(j.opening_mm) < _OPENING_MM:
        return ""
    where = "a straight axis" if j.radius_m is None else f"a {abs(j.radius_m):.0f} m curve"
    if j.radius_m is not None:
        where += " to the left" if j.radius_m > 0 else " to the right"
    t = cfg.workpiece.taper_mm
    parts = "rectangular parts" if t == 0 else f"parts tapered {t:g} mm"
    return (
        f"the joint opens {abs(j.opening_mm):.1f} mm on {where} with {parts} "
        f"(workpiece.taper_mm); a taper of {j.taper_needed_mm:.1f} mm closes it: "
    )


def plan_target(cfg: ProjectConfig, previous: Pose, ring: int) -> PlacementPlan:
    """The target of ring ``ring``'s part from the previous part's as-built pose (given
    in ring ``ring``'s T), with its expected Table 4 figures and actuator moves."""
    if cfg.placement is None:
        raise ValueError("the project has no placement section")
    t0 = time.perf_counter()
    design = design_pose(cfg, ring)
    prev_design = to_ring_frame(cfg, design_pose(cfg, ring - 1), ring - 1, ring) if ring > 1 else (
        compose(design, Pose(x=-cfg.workpiece.width_m))
    )  # fmt: skip
    prev_dev = deviation(previous, prev_design)
    prob = _Problem(cfg, previous, design, prev_dev)
    hard_fn, soft_fn = _smooth(prob, hard=True), _smooth(prob, hard=False)
    hard = {"type": "ineq", "fun": hard_fn}
    soft = {"type": "ineq", "fun": soft_fn}
    v0 = prob.start()
    res = minimize(
        prob.objective, v0, method="SLSQP", constraints=[hard, soft],
        options={"maxiter": 200, "ftol": 1e-12},
    )  # fmt: skip
    v = np.asarray(res.x, dtype=float)
    limits = prob.limits(v)
    worst = max(limits, key=lambda lim: lim.excess)
    binding: Limit | None = None
    if worst.excess > 1e-4 or not np.all(np.isfinite(v)):
        # No pose keeps every limit: keep the steering-back bound, get as close to
        # Table 4 as it allows, and report what is left over.
        def violation(u: np.ndarray) -> float:
            return float(np.sum(np.minimum(soft_fn(u), 0.0) ** 2))

        res2 = minimize(
            violation, v0, method="SLSQP", constraints=[hard],
            options={"maxiter": 300, "ftol": 1e-14},
        )  # fmt: skip
        v = np.asarray(res2.x, dtype=float)
        limits = prob.limits(v)
        binding = max((lim for lim in limits if not lim.hard), key=lambda lim: lim.excess)
    target = prob.pose(v)
    figures = joint_figures(cfg, previous, target, design)
    reasons: list[str] = []
    if binding is not None:
        curve = curve_reason(cfg, ring) if binding.name.startswith(_GAP_LIMITS) else ""
        reasons.append(
            curve + f"{binding.name}: {binding.value:.3f}, limit {binding.limit:g}, exceeded by "
            f"{binding.excess:.3f} (the steering back is bounded to "
            f"{cfg.placement.max_correction_per_ring_mm:g} mm, "
            f"{cfg.placement.max_correction_per_ring_deg:g} deg per ring)"
        )
    actuators, world = check_moves(cfg, ring, target)
    for a in actuators:
        reasons.extend(a.reasons)
    return PlacementPlan(
        feasible=not reasons,
        ring=ring,
        previous=previous,
        design=design,
        target=target,
        figures=figures,
        previous_deviation=prev_dev,
        objective_mm2=prob.objective(v),
        reasons=reasons,
        binding=binding,
        actuators=actuators,
        attitude_world_deg=world,
        solve_time_s=time.perf_counter() - t0,
        judged=judge(cfg, figures),
        heave_m=compose(inverse(home_pose(cfg, ring)), target).z,
    )


# --------------------------------------------------------------------------- the moves


def home_pose(cfg: ProjectConfig, ring: int, stand: Pose | None = None) -> Pose:
    """Where the part is, in ring ``ring``'s T, with every cylinder at mid-stroke: the
    walk stops the robot with the part's reference point at its design position, offset
    by ``stand`` (the robot's measured standing error); its attitude is the invert's
    (``base``), which the gradient's axis frame need not match."""
    stand = Pose() if stand is None else stand
    t = tunnel_frame(cfg, ring)
    design = design_pose(cfg, ring)
    base = Pose(roll=cfg.base.roll_rad, pitch=cfg.base.pitch_rad)  # project frame, no yaw
    heading = Pose(yaw=t.yaw)
    att = compose(inverse(t), compose(heading, base))
    pos = design.position + stand.position
    return Pose(
        float(pos[0]), float(pos[1]), float(pos[2]), att.roll, att.pitch, att.yaw + stand.yaw
    )


def check_moves(
    cfg: ProjectConfig, ring: int, target: Pose, stand: Pose | None = None
) -> tuple[tuple[ActuatorCheck, ...], tuple[float, float]]:
    """The actuator moves from mid-stroke to ``target``, each checked against its
    stroke and the pressure it needs, before anything moves (placement.md section 2)."""
    assert cfg.placement is not None
    pl = cfg.placement
    home = home_pose(cfg, ring, stand)
    t = tunnel_frame(cfg, ring)
    world = compose(t, target)
    heading = Pose(yaw=t.yaw)
    in_heading = compose(inverse(heading), Pose(roll=world.roll, pitch=world.pitch, yaw=world.yaw))
    roll_deg, pitch_deg = units.to_deg(in_heading.roll), units.to_deg(in_heading.pitch)
    att = plan_attitude(cfg, roll_deg, pitch_deg, with_trajectory=False)
    delta = compose(inverse(home), target)
    yaw = in_heading.yaw - att.yaw_residual_rad - home.yaw
    ext: SixDofExtensions = six_dof_extensions(delta._replace(yaw=yaw), pl.rotation_lever_arm_m)
    checks: list[ActuatorCheck] = []
    p_limit = units.to_mpa(pressure_limit_pa(cfg))
    lower = cfg.layers.lower
    d_lower = tuple(d + ext.heave for d in att.lower.displacement_m)
    reasons = list(att.reasons) if not att.feasible else []
    for cid, d in zip(lower.cylinders, d_lower, strict=True):
        if abs(d) > lower.extension_limit_m:
            reasons.append(
                f"stroke: {cid} extension {units.to_mm(d):+.1f} mm (attitude and height) "
                f"beyond the planning limit ±{units.to_mm(lower.extension_limit_m):.1f} mm"
            )
    checks.append(
        ActuatorCheck(
            "attitude and height (lower layer)",
            tuple(units.to_mm(d) for d in d_lower),
            units.to_mm(lower.extension_limit_m),
            units.to_mpa(att.peak_pressure_pa),
            p_limit,
            tuple(reasons),
        )
    )
    upper = cfg.layers.upper
    checks.append(
        ActuatorCheck(
            "attitude (upper layer)",
            tuple(units.to_mm(d) for d in att.upper.displacement_m),
            units.to_mm(upper.extension_limit_m),
            units.to_mpa(max(att.upper.pressure_pa)),
            p_limit,
            (),  # the attitude planner's reasons stand with the lower layer's
        )
    )
    # The slide axes push the part on the upper platform against its friction.
    friction_n = pl.slide_friction_coefficient * cfg.workpiece_mass_kg * units.G
    p_max = units.to_mpa(pressure_limit_pa(cfg))
    for role, values, share in (
        ("rotation", ext.rotation, 0.5),
        ("lateral", ext.lateral, 0.5),
        ("central_axis", (ext.central_axis,), 1.0),
    ):
        cyls = [c for c in cfg.cylinders if c.role == role]
        limit = min(c.stroke_m for c in cyls) / 2 - units.mm(cfg.safety.stroke_end_margin_mm)
        why: list[str] = []
        for c, e in zip(cyls, values, strict=True):
            if abs(e) > limit:
                why.append(
                    f"stroke: {c.id} extension {units.to_mm(e):+.1f} mm beyond "
                    f"±{units.to_mm(limit):.1f} mm (stroke less the end margin)"
                )
        area = min(c.rod_area_m2 for c in cyls)
        p_need = units.to_mpa(share * friction_n / area) + cfg.hydraulics.tank_pressure_mpa
        slide = pressure_reason(cfg, role, share * friction_n, units.mpa(p_need))
        if slide is not None:
            why.append(slide)
        checks.append(
            ActuatorCheck(
                role,
                tuple(units.to_mm(e) for e in values),
                units.to_mm(limit),
                p_need,
                p_max,
                tuple(why),
            )
        )
    return tuple(checks), (roll_deg, pitch_deg)


def plan_from_deviation(cfg: ProjectConfig, ring: int, dev: Pose) -> PlacementPlan:
    """:func:`plan_target` with the previous part given by its deviation from its own
    design pose (as a survey sheet or an acceptance record states it)."""
    prev_design = (
        to_ring_frame(cfg, design_pose(cfg, ring - 1), ring - 1, ring)
        if ring > 1
        else compose(design_pose(cfg, ring), Pose(x=-cfg.workpiece.width_m))
    )
    return plan_target(cfg, prev_design.deviated(dev), ring)
