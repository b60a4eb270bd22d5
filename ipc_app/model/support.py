"""Statics of the walking machine on its legs (walking.md section 3).

The body (M and S, level on the base during a walk) with everything it carries is one
rigid body. Its legs stand at points ``(x_i, y_i)`` of the lower platform frame (M's);
they push along the base z axis. Equilibrium is model.md section 5's three equations in
the standing legs' forces; the expected shares are their minimum-norm solution
(:func:`support_forces`, any number of legs: four of one frame, or all eight). With four
legs on a rectangle it is :func:`ipc_app.model.statics.rod_forces` at a level platform
(the tests check it).

The static stability margin is the distance from the COG's projection along gravity to
the nearest edge of the standing legs' support polygon (their convex hull), negative
outside it.

The machine's weight and the projection of its COG are measured where one frame stands
on its four legs (:class:`StandingLoad`, :func:`standing_load`: the three equilibrium
equations read backwards from the legs' forces); :class:`WalkingMachine` trims M's
lumped mass and COG to them, so that the expected shares follow the machine as it is
(the part as cast, as set down) and not only as its YAML says.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from config import crosscheck, units
from config.derived import without_rods
from config.schema import Body, ProjectConfig
from ipc_app.model.kinematics import Array, S, T, Vec, rotate
from ipc_app.model.statics import (
    MachineStatics,
    MassProperties,
    home_cap_pressures_pa,
    lump,
    unloaded_upper_bodies,
)


def cap_side_forces_n(p: Array, cap_m2: Array, rod_m2: Array) -> Array:
    """Each cylinder's push on its load from its chamber pressures ``p`` (n, 2: cap
    side, rod side; Pa) and its areas (n,): ``p_A A_A - p_B A_B``, N."""
    return np.asarray(p[:, 0] * cap_m2 - p[:, 1] * rod_m2, dtype=np.float64)


class StandingLoad(NamedTuple):
    """What the standing legs measure: the machine's weight along the base z (N) and
    its COG's projection along gravity onto the base plane (x, y m, lower platform
    frame), with S at ``x_s_m`` along the rails."""

    weight_n: float
    cog_projection_m: tuple[float, float]
    x_s_m: float


def standing_load(points_xy: Array, forces_n: Array, x_s_m: float) -> StandingLoad:
    """The weight and COG projection held by legs at ``points_xy`` (n, 2) pushing with
    ``forces_n`` (n,) along the base z (:func:`support_forces` read backwards: the
    force sum and its moments; a twist among the legs does not change them)."""
    f = np.asarray(forces_n, dtype=float)
    w = float(f.sum())
    if not (np.isfinite(w) and w > 0.0):
        raise ValueError(f"the standing legs carry no load to measure ({w:.0f} N)")
    p = f @ np.asarray(points_xy, dtype=float) / w
    return StandingLoad(w, (float(p[0]), float(p[1])), float(x_s_m))


class WalkingMachine:
    """Mass, COG and leg positions of the machine as a function of ``x_S``.

    Frames (walking.md section 1): M's legs at ``(s_i a_M, t_i b_M)``, S's legs at
    ``(x_S + s_i a_S, t_i b_S)``, in the lower platform frame. The upper platform's
    attitude relative to the lower one is given (it does not change during a walk). The
    load is the bodies (the upper platform's rods in them) less the legs' own rods and
    feet, which the frames' bodies weigh in (:func:`config.derived.without_rods`): a
    leg's force on the body is its cap-side force.

    ``unloaded``: without the workpiece, the upper layer's body named
    :data:`~config.schema.WORKPIECE_BODY` (the ring cycle walks back once the part is fixed to the
    ring and the platform has lowered off it).

    ``standing``: the load measured on M's standing legs; M's lump (everything that
    moves with M: the lower and upper layers' bodies, the part) then takes the measured
    weight less S's, and the x and y of its COG that put the total COG's projection
    where it was measured (its height stays the model's, which the legs cannot see).
    """

    def __init__(
        self,
        cfg: ProjectConfig,
        upper_roll: float = 0.0,
        upper_pitch: float = 0.0,
        unloaded: bool = False,
        standing: StandingLoad | None = None,
    ) -> None:
        frames, _ = cfg.walking_sections()
        statics = MachineStatics(cfg)
        self.g_base = statics.g_base
        mu, cu = statics.upper
        if unloaded:
            mu, cu = lump(unloaded_upper_bodies(cfg))
        ru = rotate(upper_roll, upper_pitch, Vec(*(np.asarray(c) for c in cu)))
        o = statics.origin_upper
        cog_u = (o[0] + float(ru.x), o[1] + float(ru.y), o[2] + float(ru.z))
        upper_in_lower = Body(name="upper", mass_kg=mu, cog_m=cog_u) if mu > 0 else None
        # the frames' bodies weigh their legs' rods in: out of the load
        # (config.derived.without_rods); the upper bodies' rods stay (the legs carry them)
        fixed = [b for b in cfg.layers.lower.bodies] + list(without_rods(cfg, "main"))
        if upper_in_lower is not None:
            fixed.append(upper_in_lower)
        #: the weight of one leg's rod (and foot), N along the base z: what a hanging leg
        #: pulls on the body; a standing leg's cap-side force is its foot's load less it
        self.rod_mass_kg = cfg.hydraulics.rod_mass_kg
        self.rod_weight_n = -self.rod_mass_kg * float(self.g_base.z)
        #: everything that moves with M (lower platform frame)
        self.main: MassProperties = lump(tuple(fixed))
        #: S's structure (S's frame)
        self.sub: MassProperties = lump(without_rods(cfg, "sub"))
        lo, sub = cfg.layers.lower, frames.sub
        self.main_legs_xy = np.stack([S * lo.a_m, T * lo.b_m], axis=1)
        self.sub_legs_xy = np.stack([S * sub.a_m, T * sub.b_m], axis=1)
        #: M's lump as the YAML gives it (before a measured trim)
        self.main_model = self.main
        if standing is not None:
            self.main = self._trimmed_main(standing)

    def _trimmed_main(self, standing: StandingLoad) -> MassProperties:
        g = self.g_base
        gx, gy, gz = float(g.x), float(g.y), float(g.z)
        mass = standing.weight_n / -gz
        ms, cs = self.sub
        mm = mass - ms
        if not mm > 0.0:
            raise ValueError(
                f"the standing legs measure {standing.weight_n / 1e3:.1f} kN, less than the "
                f"sub frame's own weight ({ms * -gz / 1e3:.1f} kN)"
            )
        z = self.cog(standing.x_s_m)[2]  # the model's height: the legs cannot see it
        # the total COG whose projection along gravity is the measured point
        px, py = standing.cog_projection_m
        cx, cy = px + z * gx / gz, py + z * gy / gz
        sx, sy = cs[0] + standing.x_s_m, cs[1]
        cm_z = (mass * z - ms * cs[2]) / mm
        return MassProperties(mm, ((mass * cx - ms * sx) / mm, (mass * cy - ms * sy) / mm, cm_z))

    @property
    def mass_kg(self) -> float:
        return self.main.mass_kg + self.sub.mass_kg

    def cog(self, x_s: float) -> Array:
        """The total COG (3,) in the lower platform frame with S at ``x_s``."""
        return np.array(self.cog_xyz(x_s))

    def cog_xyz(self, x_s: float) -> tuple[float, float, float]:
        """:meth:`cog` as plain floats (the walk's checks ask every cycle)."""
        mm, cm = self.main
        ms, cs = self.sub
        total = mm + ms
        return (
            (float(cm[0]) * mm + (float(cs[0]) + x_s) * ms) / total,
            (float(cm[1]) * mm + float(cs[1]) * ms) / total,
            (float(cm[2]) * mm + float(cs[2]) * ms) / total,
        )

    def frame_reference(self, legs: Sequence[int], x_s: float) -> tuple[float, bool]:
        """Where what depends on ``legs``' positions alone is taken, S at ``x_s``: at 0
        when they are one frame's (M's do not move with ``x_s``; S's move with it, so a
        caller moves its point or load into S's frame instead), at ``x_s`` for a mix of
        both frames; and whether they are all S's."""
        n_main = len(self.main_legs_xy)
        all_sub = min(legs) >= n_main
        return (0.0 if all_sub or max(legs) < n_main else x_s), all_sub

    def legs_xy(self, x_s: float, yaw: float = 0.0) -> Array:
        """(8, 2): main legs 1..4, then sub legs 1..4, at ``x_s``, S yawed by ``yaw`` (rad,
        counter-clockwise) in M about its centre (curves.md section 3)."""
        sub = self.sub_legs_xy
        if yaw != 0.0:
            c, s = math.cos(yaw), math.sin(yaw)
            sub = sub @ np.array([[c, s], [-s, c]])
        return np.concatenate([self.main_legs_xy, sub + np.array([x_s, 0.0])])


def support_forces(points_xy: Array, mass_kg: float, cog: Array, g_base: Vec) -> Array:
    """Minimum-norm leg forces (n,) holding a level body of ``mass_kg`` at ``cog`` on legs
    at ``points_xy`` (n, 2), pushing along the base z axis; compression positive.

    The body's equilibrium ``A f = r`` (rows: heave, roll ``y``, pitch ``-x``) solved as
    ``f = A^T (A A^T)^-1 r``, the 3 x 3 normal matrix's inverse written out: on plain
    floats (the walk asks for the eight-leg share as S moves). Legs on one line hold no
    body: ``numpy.linalg.LinAlgError``."""
    pts = np.asarray(points_xy, dtype=np.float64).tolist()
    g0, g1, g2 = float(g_base.x), float(g_base.y), float(g_base.z)
    c0, c1, c2 = (float(v) for v in cog)
    m = float(mass_kg)
    r0, r1, r2 = -m * g2, -m * (c1 * g2 - c2 * g1), -m * (c2 * g0 - c0 * g2)
    n = float(len(pts))
    sy = sx = syy = sxx = sxy = 0.0
    for x, y in pts:
        sy += y
        sx += x
        syy += y * y
        sxx += x * x
        sxy += x * y
    # A A^T, symmetric: [[n, sy, -sx], [sy, syy, -sxy], [-sx, -sxy, sxx]]
    a, b, c, d, e, f = n, sy, -sx, syy, -sxy, sxx
    i00, i01, i02 = d * f - e * e, c * e - b * f, b * e - c * d
    i11, i12, i22 = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * i00 + b * i01 + c * i02
    scale = abs(a * d * f) + abs(b * b * f) + abs(c * c * d) + abs(e * e * a)
    if not det > 1e-12 * scale:  # (positive definite when the legs span an area)
        raise np.linalg.LinAlgError(f"legs on one line hold no body: {pts}")
    l0 = (i00 * r0 + i01 * r1 + i02 * r2) / det
    l1 = (i01 * r0 + i11 * r1 + i12 * r2) / det
    l2 = (i02 * r0 + i12 * r1 + i22 * r2) / det
    return np.array([l0 + l1 * y - l2 * x for x, y in pts])


def cog_projection(cog: Array | tuple[float, float, float], g_base: Vec) -> Array:
    """The COG's projection along gravity onto the base plane (2,)."""
    gx, gy, gz = float(g_base.x), float(g_base.y), float(g_base.z)
    return np.array([cog[0] - cog[2] * gx / gz, cog[1] - cog[2] * gy / gz])


def _hull(points: Array) -> Array:
    """Convex hull, counter-clockwise (monotone chain)."""
    return np.array(_hull_points(points))


def _hull_points(points: Array) -> list[tuple[float, float]]:
    """:func:`_hull` as plain (x, y) floats."""
    pts = sorted({(p[0], p[1]) for p in np.asarray(points, dtype=np.float64).tolist()})
    if len(pts) < 3:
        return pts

    def cross(o: tuple[float, float], a: tuple[float, float], b: tuple[float, float]) -> float:
        return (a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0])

    lower: list[tuple[float, float]] = []
    for p in pts:
        while len(lower) >= 2 and cross(lower[-2], lower[-1], p) <= 0:
            lower.pop()
        lower.append(p)
    upper: list[tuple[float, float]] = []
    for p in reversed(pts):
        while len(upper) >= 2 and cross(upper[-2], upper[-1], p) <= 0:
            upper.pop()
        upper.append(p)
    return lower[:-1] + upper[:-1]


Edge = tuple[float, float, float, float]


def hull_edges(points_xy: Array) -> list[Edge]:
    """The convex hull's edges of ``points_xy`` (n, 2), counter-clockwise, each as its
    start (x, y) and its inward unit normal (x, y); none for fewer than three corners."""
    hull = _hull_points(points_xy)
    if len(hull) < 3:
        return []
    edges: list[Edge] = []
    for k in range(len(hull)):
        (ax, ay), (bx, by) = hull[k], hull[(k + 1) % len(hull)]
        ex, ey = bx - ax, by - ay
        length = math.hypot(ex, ey)
        edges.append((ax, ay, -ey / length, ex / length))  # a counter-clockwise edge's
    return edges


def edges_margin(edges: list[Edge], px: float, py: float) -> float:
    """Signed distance (m) from ``(px, py)`` to the nearest of ``edges``
    (:func:`hull_edges`): positive inside, negative outside; -inf without a hull."""
    margin = -math.inf if not edges else math.inf
    for ax, ay, nx, ny in edges:
        d = nx * (px - ax) + ny * (py - ay)
        if d < margin:
            margin = d
    return margin


def stability_margin(points_xy: Array, point: Array) -> float:
    """Signed distance (m) from ``point`` to the nearest edge of the convex hull of
    ``points_xy``: positive inside, negative outside (on plain floats: the walk asks
    every cycle)."""
    return edges_margin(hull_edges(points_xy), float(point[0]), float(point[1]))


def boot_cap_pressures_pa(cfg: ProjectConfig) -> dict[str, float]:
    """Each attitude cylinder's cap pressure (Pa) as the machine stands at boot, keyed by
    cylinder id: the layers' statics at the home pose
    (:func:`~ipc_app.model.statics.home_cap_pressures_pa`) and, for a project that walks,
    M's legs carrying the whole machine in walking.md's start state (S lifted at the rear
    end of its travel, its hanging legs' rods on the body), which the layers' statics
    leave out (the frames)."""
    out = home_cap_pressures_pa(cfg)
    if not cfg.walks:
        return out
    machine = WalkingMachine(cfg)
    x_s = -cfg.walking_sections()[1].step_length_m / 2
    legs = machine.legs_xy(x_s)
    rods = len(machine.sub_legs_xy) * machine.rod_mass_kg
    mass = machine.mass_kg + rods
    hanging = np.append(legs[4:].mean(axis=0), 0.0)
    cog = (machine.cog(x_s) * machine.mass_kg + hanging * rods) / mass
    forces = support_forces(legs[:4], mass, cog, machine.g_base)
    for cid, f in zip(cfg.layers.lower.cylinders, forces, strict=True):
        out[cid] = float(f) / cfg.cylinder(cid).cap_area_m2
    return out


@crosscheck.provide("static-pressure-within-limit", __name__)
def check_static_pressure(cfg: ProjectConfig) -> str | None:
    """The cross-check of the static load against the pressure limit (config.crosscheck):
    a limit at or below a cylinder's pressure as the machine stands at boot
    (:func:`boot_cap_pressures_pa`) trips the pressure interlock at boot."""
    try:
        pressures = boot_cap_pressures_pa(cfg)
    except ValueError:  # bodies lighter than their rods: rods-within-their-bodies says so
        return None
    cid = max(pressures, key=lambda k: pressures[k])
    p_mpa = units.to_mpa(pressures[cid])
    limit = cfg.safety.max_pressure_mpa
    if p_mpa < limit:
        return None
    if cid in cfg.layers.upper.cylinders:
        load = "layers.upper.bodies"
    elif cfg.frames is not None:
        load = "layers.*.bodies and frames.*.bodies, M standing, S lifted"
    else:
        load = "layers.lower.bodies and layers.upper.bodies"
    return (
        f"safety.max_pressure_mpa: {limit:g} MPa is not above the static load pressure of "
        f"cylinder {cid} ({p_mpa:.2f} MPa: {load}, at rest as the machine stands at boot; "
        f"the interlock would trip under the machine's own load); expected above {p_mpa:.2f}"
    )
