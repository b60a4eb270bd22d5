"""Cross-checks between keys of a project: the rules no single key's range can state.

The schema (:mod:`config.schema`) checks each key against its own range; a rule here
relates two or more keys (the pressure limit against the rating, the step against the
ring width, the bus load of the loop rate against the budget). :data:`RULES` is the one
table of them: a rule's name, the keys it relates, what is consistent (the docs table of
docs/config.md is checked against it) and its check, a function of the validated
project returning ``None`` or the one-line reason, which names both keys with their
values and what would be consistent. The loader runs every rule after the schema
validates (:func:`config.loader.load_project`, ``wara config validate``).

Two rules need what only another package computes: the bus load from the DBC
(``plc_bridge.busload``) and the statics of the machine (``ipc_app.model.support``).
``config`` imports nothing of ours (tests/test_architecture.py), so their checks are
*provided*: the rule names the module that holds its check, and that module registers
it with :func:`provide` when imported. The ``wara`` command installs an importer
(:func:`set_importer`), so every command that loads a project runs every rule; a program
that uses ``config`` alone (site QA's ``acceptance``) runs the rules whose module it has
imported, the others not.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Collection, Sequence
from dataclasses import dataclass
from typing import TypeVar

from config import alignment, derived, units
from config.schema import WORKPIECE_BODY, HorizontalElement, ProjectConfig, VerticalElement

#: A rule's check: ``None`` if the project keeps the rule, else the one-line reason.
Check = Callable[[ProjectConfig], str | None]
_E = TypeVar("_E", HorizontalElement, VerticalElement)

#: ``workpiece.mass_kg``, when given beside the workpiece body, must equal it within this.
MASS_TOLERANCE_KG = 1.0
#: ``walking.step_length_mm`` times a whole number must be the ring width within this.
STEP_TOLERANCE_MM = 1.0
#: ``base.pitch_deg`` must be the alignment's gradient as an angle within this (the
#: shipped 0.17 deg is the 0.3 % gradient's 0.1719 deg rounded to two places).
PITCH_TOLERANCE_DEG = 0.01
#: ``robot.mass_kg`` must be the machine's bodies' sum within this share (a weighed
#: figure against its split into lumps).
ROBOT_MASS_TOLERANCE = 0.01
#: A cylinder's action point may lie this far outside the robot's envelope (its feet and
#: the envelope's rounding).
ENVELOPE_TOLERANCE_M = 0.001
#: The steepest grade the machine is built for (curves.md section 5); the statics on it
#: are the static-pressure rule's (``base.pitch_deg`` is the grade's).
STEEPEST_GRADE_PERCENT = 5.0


@dataclass(frozen=True)
class Rule:
    """One cross-check: ``keys`` the keys it relates (the first is the one the reason
    starts with), ``consistent`` what keeps it (the docs' wording), ``check`` its
    function, or ``provider`` the module that provides it (:func:`provide`)."""

    name: str
    keys: tuple[str, ...]
    consistent: str
    check: Check | None = None
    provider: str = ""


def _g(v: float) -> str:
    """A value as the YAML would write it (``24``, ``0.17``, ``2000``)."""
    return f"{v:g}"


def _within_rating(key: str, value: float, why: str, cfg: ProjectConfig) -> str | None:
    rated = cfg.hydraulics.rated_pressure_mpa
    if value <= rated:
        return None
    return (
        f"{key}: {_g(value)} MPa is above the cylinders' rating "
        f"(hydraulics.rated_pressure_mpa {_g(rated)} MPa){why}; expected at most {_g(rated)}"
    )


def _max_pressure(cfg: ProjectConfig) -> str | None:
    why = ": the interlock would let the pressure pass the rating"
    return _within_rating("safety.max_pressure_mpa", cfg.safety.max_pressure_mpa, why, cfg)


def _supply_pressure(cfg: ProjectConfig) -> str | None:
    supply = cfg.hydraulics.supply_pressure_mpa
    return _within_rating("hydraulics.supply_pressure_mpa", supply, "", cfg)


def _stroke_end_margin(cfg: ProjectConfig) -> str | None:
    margin = cfg.safety.stroke_end_margin_mm
    short = min(cfg.cylinders, key=lambda c: (c.stroke_mm, c.can_index))
    if margin < short.stroke_mm / 2:
        return None
    i = cfg.cylinders.index(short)
    return (
        f"safety.stroke_end_margin_mm: {_g(margin)} mm is not below half the stroke of "
        f"cylinder {short.id} (cylinders[{i}].stroke_mm {_g(short.stroke_mm)} mm): the "
        f"margins at both ends would close the stroke; expected below {_g(short.stroke_mm / 2)}"
    )


def _step_length(cfg: ProjectConfig) -> str | None:
    if cfg.walking is None:
        return None
    step, ring_m = cfg.walking.step_length_mm, cfg.tunnel.ring_width_m
    ring_mm = ring_m * 1000.0
    n = max(1, round(ring_mm / step))
    if abs(n * step - ring_mm) <= STEP_TOLERANCE_MM:
        return None
    return (
        f"walking.step_length_mm: {_g(step)} mm does not divide the ring "
        f"(tunnel.ring_width_m {_g(ring_m)} m = {ring_mm / step:.3g} steps): the walk "
        f"reaches the next ring in whole steps; expected {_g(ring_mm)} (one step a ring) "
        f"or a whole fraction of it"
    )


def _workpiece_mass(cfg: ProjectConfig) -> str | None:
    key, piece = cfg.workpiece.mass_kg, cfg.workpiece_body
    if key is None or piece is None or abs(key - piece.mass_kg) <= MASS_TOLERANCE_KG:
        return None
    body = piece.mass_kg
    i = next(i for i, b in enumerate(cfg.layers.upper.bodies) if b.name == WORKPIECE_BODY)
    return (
        f"workpiece.mass_kg: {_g(key)} kg is not the mass of the workpiece body "
        f"(layers.upper.bodies[{i}].mass_kg {_g(body)} kg, which the statics and the "
        f"simulator use); expected {_g(body)}, or the key left out (it defaults to the "
        f"body's)"
    )


def _rods_in_bodies(cfg: ProjectConfig) -> str | None:
    for owner, (key, role) in derived.ROD_OWNERS.items():
        bodies = derived.owner_bodies(cfg, owner)
        rods = derived.owned_rods_kg(cfg, owner)
        own = sum(b.mass_kg for b in bodies if b.name != WORKPIECE_BODY)
        if rods == 0.0 or rods < own:
            continue
        n = round(rods / cfg.hydraulics.rod_mass_kg)
        return (
            f"hydraulics.rod_mass_kg: {_g(cfg.hydraulics.rod_mass_kg)} kg, {n} {role} rods "
            f"({_g(rods)} kg), is not within the bodies that weigh them in ({key}"
            f"{' but the workpiece' if owner == 'upper' else ''}: {_g(own)} kg); expected "
            f"below {_g(own / n)} kg a rod, or those bodies heavier"
        )
    return None


def machine_bodies_kg(cfg: ProjectConfig) -> float | None:
    """The machine's own mass as its bodies give it (walking.md: robot 35 t = 15 upper
    structure + 6 fine-tuning platform + 6 main frame + 8 sub frame): the lower layer's
    bodies, the upper layer's but the workpiece, both frames' (``None`` without frames,
    which hold two of the lumps)."""
    if cfg.frames is None:
        return None
    bodies = (
        cfg.layers.lower.bodies
        + tuple(b for b in cfg.layers.upper.bodies if b.name != WORKPIECE_BODY)
        + cfg.frames.main.bodies
        + cfg.frames.sub.bodies
    )
    return sum(b.mass_kg for b in bodies)


def _robot_mass(cfg: ProjectConfig) -> str | None:
    total = machine_bodies_kg(cfg)
    robot = cfg.robot.mass_kg
    if total is None or abs(robot - total) <= ROBOT_MASS_TOLERANCE * total:
        return None
    return (
        f"robot.mass_kg: {_g(robot)} kg is not the machine's bodies' sum (layers.lower.bodies, "
        f"layers.upper.bodies but the workpiece, frames.main.bodies, frames.sub.bodies: "
        f"{_g(total)} kg); expected {_g(total)} within {_g(100 * ROBOT_MASS_TOLERANCE)} %"
    )


def gradient_pitch_deg(gradient_percent: float) -> float:
    """The base pitch of an invert on a gradient: model.md's +pitch turns x down, so a
    rising axis (gradient > 0) is a negative pitch."""
    return -math.degrees(math.atan(gradient_percent / 100.0))


def pitch_range_deg(cfg: ProjectConfig) -> tuple[float, float] | None:
    """The base pitches of the design axis's gradients, ``(least, most)`` deg (one
    gradient: both the same; ``None`` without an alignment); of an axis by chainage, the
    grades the rings lie on: the grade at ring 1's chainage (on a vertical curve, where
    the rings meet it) and the grade elements after it."""
    al = cfg.tunnel.alignment
    if al is None:
        return None
    if al.gradient_percent is not None:
        p = gradient_pitch_deg(al.gradient_percent)
        return p, p
    if al.vertical is not None:  # the grades the rings lie on (the approach's are not)
        v = al.vertical
        on = [e for _, e in _ring_elements(v.elements, al.first_ring_chainage_m)]
        grades = [100.0 * alignment.level(v, al.first_ring_chainage_m).grade]
        grades += [e.gradient_percent for e in on if e.gradient_percent is not None]
        return min(map(gradient_pitch_deg, grades)), max(map(gradient_pitch_deg, grades))
    pitches = []
    for a, b in zip(al.points, al.points[1:], strict=False):
        run = math.hypot(b.x_m - a.x_m, b.y_m - a.y_m)
        if run > 0:
            pitches.append(-math.degrees(math.atan2(b.z_m - a.z_m, run)))
    return (min(pitches), max(pitches)) if pitches else None


def _ring_elements(elements: Sequence[_E], first_ring_m: float) -> list[tuple[int, _E]]:
    """The elements (with their index) the rings lie on: those ending after ring 1's
    chainage (the last goes on)."""
    out = []
    for i, e in enumerate(elements):
        end = elements[i + 1].start_chainage_m if i + 1 < len(elements) else math.inf
        if end > first_ring_m:
            out.append((i, e))
    return out


def _arcs(cfg: ProjectConfig) -> list[tuple[str, str, float | None]]:
    """(key, what it is, signed radius or None for a straight) of each horizontal element
    the rings lie on; a straight axis (``gradient_percent``) as one straight; a table's:
    none (its polyline has no radius)."""
    al = cfg.tunnel.alignment
    if al is None or al.points:
        return []
    if al.horizontal is None:
        return [("tunnel.alignment.gradient_percent", "a straight axis", None)]
    out: list[tuple[str, str, float | None]] = []
    for i, e in _ring_elements(al.horizontal.elements, al.first_ring_chainage_m):
        key = f"tunnel.alignment.horizontal.elements[{i}]"
        if e.radius_m:
            out.append((f"{key}.radius_m", f"{_g(e.radius_m)} m", e.radius_m))
        elif e.kind == "straight":  # a clothoid lies between its neighbours: theirs bound it
            out.append((key, "a straight", None))
    return out


def tightest_curve(cfg: ProjectConfig) -> tuple[str, float, float] | None:
    """The tightest arc the rings lie on: ``(its radius's key, signed radius m, a
    chainage on it)``, the chainage one step in from where the rings meet it (the middle
    of an arc shorter than two steps), so a step either way stays on it; ``None`` without
    an arc (a straight axis, a table, no ``walking``)."""
    al, w = cfg.tunnel.alignment, cfg.walking
    if al is None or al.horizontal is None or w is None:
        return None
    elements = al.horizontal.elements
    best: tuple[str, float, float] | None = None
    for i, e in _ring_elements(elements, al.first_ring_chainage_m):
        if not e.radius_m or (best is not None and abs(e.radius_m) >= abs(best[1])):
            continue
        start = max(e.start_chainage_m, al.first_ring_chainage_m)
        end = elements[i + 1].start_chainage_m if i + 1 < len(elements) else math.inf
        at = start + w.step_length_m if end - start >= 2.0 * w.step_length_m else (start + end) / 2
        best = (f"tunnel.alignment.horizontal.elements[{i}].radius_m", e.radius_m, at)
    return best


def _radius_and_taper(cfg: ProjectConfig) -> str | None:
    part, gap = cfg.workpiece, cfg.acceptance.max_gap_mm
    w_l = 1000.0 * part.width_m * part.length_m  # mm m: the opening is w L / R
    t = part.taper_mm
    for key, what, radius in _arcs(cfg):
        curve = 0.0 if radius is None else w_l / radius
        opening = abs(curve - t)
        if opening <= gap + 1e-9:
            continue
        fix = f"a workpiece.taper_mm of {_g(round(curve - gap, 1))}..{_g(round(curve + gap, 1))}"
        if radius is not None and t * radius > 0:
            fix += f", or a radius of at least {w_l / (abs(t) + gap):.0f} m"
        return (
            f"{key}: {what} opens the joint {opening:.1f} mm with workpiece.taper_mm {_g(t)} "
            f"(w L / R less the taper: workpiece.width_m {_g(part.width_m)} x length_m "
            f"{_g(part.length_m)}), beyond acceptance.max_gap_mm {_g(gap)}; expected {fix}"
        )
    return None


def tightest_radius_m(cfg: ProjectConfig) -> float:
    """The tightest radius the walk steers (curves.md section 3): a step turns the frames
    by ``step / R`` plus the steering back, S's yaw in M at most ``max_yaw``."""
    assert cfg.walking is not None
    w = cfg.walking
    room = w.max_yaw_rad - w.max_heading_correction_per_step_rad
    return math.inf if room <= 0.0 else w.step_length_m / math.sin(room)


def _tightest_radius(cfg: ProjectConfig) -> str | None:
    w = cfg.walking
    if w is None:
        return None
    tightest = tightest_radius_m(cfg)
    for key, _, radius in _arcs(cfg):
        if radius is not None and abs(radius) < tightest:
            return (
                f"{key}: {_g(radius)} m is tighter than the walk steers: a "
                f"walking.step_length_mm {_g(w.step_length_mm)} step turns "
                f"{math.degrees(w.step_length_m / abs(radius)):.3f} deg, plus "
                f"walking.max_heading_correction_per_step_deg "
                f"{_g(w.max_heading_correction_per_step_deg)} beyond walking.max_yaw_deg "
                f"{_g(w.max_yaw_deg)}; expected |radius_m| >= {tightest:.0f}"
            )
    return None


def _grades(cfg: ProjectConfig) -> list[tuple[str, float]]:
    """(key, grade in percent) of the axis: its gradient, a table's segments, the grade
    elements the rings lie on."""
    al = cfg.tunnel.alignment
    if al is None:
        return []
    if al.gradient_percent is not None:
        return [("tunnel.alignment.gradient_percent", al.gradient_percent)]
    if al.vertical is not None:
        return [
            (f"tunnel.alignment.vertical.elements[{i}].gradient_percent", e.gradient_percent)
            for i, e in _ring_elements(al.vertical.elements, al.first_ring_chainage_m)
            if e.gradient_percent is not None
        ]
    out = []
    for i, (a, b) in enumerate(itertools.pairwise(al.points)):
        run = math.hypot(b.x_m - a.x_m, b.y_m - a.y_m)
        if run > 0:
            out.append((f"tunnel.alignment.points[{i + 1}]", 100.0 * (b.z_m - a.z_m) / run))
    return out


def _steepest_grade(cfg: ProjectConfig) -> str | None:
    for key, grade in _grades(cfg):
        if abs(grade) > STEEPEST_GRADE_PERCENT + 1e-9:
            return (
                f"{key}: a grade of {grade:.3g} % is steeper than the machine is built for "
                f"(its walking and standing on the invert: curves.md); expected within "
                f"±{_g(STEEPEST_GRADE_PERCENT)} %"
            )
    return None


def _vertical_curve(cfg: ProjectConfig) -> str | None:
    al, w = cfg.tunnel.alignment, cfg.walking
    if al is None or al.vertical is None or w is None:
        return None
    # a lowering foot meets the invert a step ahead of where its frame stood, off the
    # plane of the standing feet by the curve's rise (curves.md section 3)
    reach = cfg.layers.lower.a_m + w.step_length_m
    window = units.mm(w.touchdown_travel_mm)
    for i, e in _ring_elements(al.vertical.elements, al.first_ring_chainage_m):
        if e.radius_m is None:
            continue
        rise = reach * reach / (2.0 * e.radius_m)
        if rise > window + 1e-9:
            return (
                f"tunnel.alignment.vertical.elements[{i}].radius_m: {_g(e.radius_m)} m "
                f"raises the invert {units.to_mm(rise):.1f} mm under a foot landing "
                f"{reach:.2f} m ahead (layers.lower.half_span_x_m + walking.step_length_mm), "
                f"beyond walking.touchdown_travel_mm {_g(w.touchdown_travel_mm)}; expected "
                f"radius_m >= {reach * reach / (2.0 * window):.0f}, or a longer touch-down "
                f"travel"
            )
    return None


def _base_pitch(cfg: ProjectConfig) -> str | None:
    rng = pitch_range_deg(cfg)
    if rng is None:
        return None
    lo, hi = rng
    pitch = cfg.base.pitch_deg
    if lo - PITCH_TOLERANCE_DEG <= pitch <= hi + PITCH_TOLERANCE_DEG:
        return None
    al = cfg.tunnel.alignment
    assert al is not None
    if al.gradient_percent is not None:
        source = f"tunnel.alignment.gradient_percent {_g(al.gradient_percent)} %"
        want = f"{lo:.4f} within {_g(PITCH_TOLERANCE_DEG)}"
    elif al.vertical is not None:
        source = f"tunnel.alignment.vertical: grades {-hi:.4f}..{-lo:.4f} deg"
        want = f"{lo:.4f}..{hi:.4f} within {_g(PITCH_TOLERANCE_DEG)}"
    else:
        source = f"tunnel.alignment.points: gradients {-hi:.4f}..{-lo:.4f} deg"
        want = f"{lo:.4f}..{hi:.4f} within {_g(PITCH_TOLERANCE_DEG)}"
    return (
        f"base.pitch_deg: {_g(pitch)} deg is not the invert on the design axis's gradient "
        f"({source}; +pitch turns x down, a falling axis is a positive pitch); expected {want}"
    )


def _envelope(cfg: ProjectConfig) -> str | None:
    rob = cfg.robot
    half_l, half_w = rob.length_mm / 2000.0, rob.width_mm / 2000.0
    # (key, its value, what it places, how far beyond it, along x)
    spans: list[tuple[str, float, str, float, bool]] = []
    for name in ("lower", "upper"):
        layer = getattr(cfg.layers, name)
        what = f"the {name} layer's cylinders"
        spans.append((f"layers.{name}.half_span_x_m", layer.a_m, what, 0.0, True))
        spans.append((f"layers.{name}.half_span_y_m", layer.b_m, what, 0.0, False))
    if cfg.walks:
        frames, walking = cfg.walking_sections()
        sub, reach = frames.sub, walking.step_length_m / 2.0
        step = _g(walking.step_length_mm)
        what = f"S's legs at either end of a step (walking.step_length_mm {step})"
        spans.append(("frames.sub.half_span_x_m", sub.a_m, what, reach, True))
        spans.append(("frames.sub.half_span_y_m", sub.b_m, "S's legs", 0.0, False))
    for key, value, what, beyond, along in spans:
        half = half_l if along else half_w
        if value + beyond <= half + ENVELOPE_TOLERANCE_M:
            continue
        dim, robot_key = ("length", "robot.length_mm") if along else ("width", "robot.width_mm")
        return (
            f"{key}: {_g(value)} m puts {what} {_g(round(value + beyond, 4))} m from the "
            f"machine's centre, outside its {dim} ({robot_key} "
            f"{_g(rob.length_mm if along else rob.width_mm)}: {_g(half)} m each way); expected "
            f"at most {_g(round(half - beyond, 4))}, or a larger {robot_key}"
        )
    return None


def _fits_the_tunnel(cfg: ProjectConfig) -> str | None:
    """The envelope standing on the invert, centred on the axis: its top corners inside
    the lining; and it passes through the placed parts' hollow (paper: the machine walks
    through them), so it is lower than a part and narrower than one is long."""
    rob, tun, part = cfg.robot, cfg.tunnel, cfg.workpiece
    w, h, r = rob.width_mm / 1000.0, rob.height_mm / 1000.0, tun.inner_radius_m
    if h >= part.height_m:
        return (
            f"robot.height_mm: {_g(rob.height_mm)} mm is not below the part's height "
            f"(workpiece.height_m {_g(part.height_m)} m): the machine walks through the placed "
            f"parts' hollow; expected below {_g(1000.0 * part.height_m)}"
        )
    if w >= part.length_m:
        return (
            f"robot.width_mm: {_g(rob.width_mm)} mm is not below the part's length across the "
            f"tunnel (workpiece.length_m {_g(part.length_m)} m): the machine walks through the "
            f"placed parts' hollow; expected below {_g(1000.0 * part.length_m)}"
        )
    corner = math.hypot(w / 2.0, h - r)
    if corner <= r:
        return None
    most = 2.0 * math.sqrt(max(r * r - (h - r) ** 2, 0.0))
    return (
        f"robot.width_mm: {_g(rob.width_mm)} mm at robot.height_mm {_g(rob.height_mm)} puts "
        f"the machine's top corners {corner:.3f} m from the axis, outside the lining "
        f"(tunnel.inner_diameter_m {_g(tun.inner_diameter_m)}); expected at most "
        f"{1000.0 * most:.0f} mm wide at that height"
    )


#: Every cross-check, in the order the loader runs them and docs/config.md lists them.
RULES: tuple[Rule, ...] = (
    Rule(
        "pressure-limit-within-rating",
        ("safety.max_pressure_mpa", "hydraulics.rated_pressure_mpa"),
        "`max_pressure_mpa` <= `rated_pressure_mpa`",
        _max_pressure,
    ),
    Rule(
        "supply-within-rating",
        ("hydraulics.supply_pressure_mpa", "hydraulics.rated_pressure_mpa"),
        "`supply_pressure_mpa` <= `rated_pressure_mpa`",
        _supply_pressure,
    ),
    Rule(
        "stroke-end-margin-within-stroke",
        ("safety.stroke_end_margin_mm", "cylinders[*].stroke_mm"),
        "`stroke_end_margin_mm` < half of every cylinder's `stroke_mm` (the shortest named)",
        _stroke_end_margin,
    ),
    Rule(
        "bus-load-within-budget",
        ("can.max_bus_load_percent", "control.loop_rate_hz", "can.bitrate", "can.active_groups"),
        "the bus load of the DBC's messages, `active_groups` at the loop rate (what "
        "`wara can busload` prints), <= `max_bus_load_percent`",
        provider="plc_bridge.busload",
    ),
    Rule(
        "static-pressure-within-limit",
        (
            "safety.max_pressure_mpa",
            "layers.*.bodies",
            "layers.*.half_span_*_m",
            "layers.*.bore_mm",
            "base",
        ),
        "every attitude cylinder's cap pressure as the machine stands at boot (the "
        "planner's statics: the layers level on the base; with `frames`, M's legs carrying "
        "the machine, S lifted) < `max_pressure_mpa`",
        provider="ipc_app.model.support",
    ),
    Rule(
        "step-divides-the-ring",
        ("walking.step_length_mm", "tunnel.ring_width_m"),
        f"1000 `ring_width_m` a whole number of `step_length_mm` (one step a ring, or "
        f"a whole fraction of one; within {_g(STEP_TOLERANCE_MM)} mm)",
        _step_length,
    ),
    Rule(
        "workpiece-mass-is-its-body",
        ("workpiece.mass_kg", "layers.upper.bodies[workpiece].mass_kg"),
        f"`workpiece.mass_kg` left out (it is the body's), or the body's within "
        f"{_g(MASS_TOLERANCE_KG)} kg",
        _workpiece_mass,
    ),
    Rule(
        "rods-within-their-bodies",
        ("hydraulics.rod_mass_kg", "layers.upper.bodies", "frames.*.bodies"),
        "the rods each set of bodies weighs in (the upper cylinders' in the upper platform's "
        "own bodies, each frame's legs' in its bodies) lighter than those bodies",
        _rods_in_bodies,
    ),
    Rule(
        "robot-mass-is-its-bodies",
        ("robot.mass_kg", "layers.*.bodies", "frames.*.bodies"),
        f"`robot.mass_kg` = the bodies' sum but the workpiece's (the rods in them), within "
        f"{_g(100 * ROBOT_MASS_TOLERANCE)} % (with `frames`)",
        _robot_mass,
    ),
    Rule(
        "base-pitch-is-the-gradient",
        ("base.pitch_deg", "tunnel.alignment"),
        f"`pitch_deg` = -atan(`gradient_percent` / 100) within {_g(PITCH_TOLERANCE_DEG)} "
        "deg (a `points` table: within its segments' range; `vertical`: the grades "
        "the rings lie on, from the grade at ring 1's chainage)",
        _base_pitch,
    ),
    Rule(
        "radius-within-the-taper",
        ("tunnel.alignment.horizontal", "workpiece.taper_mm", "acceptance.max_gap_mm"),
        "on every element the rings lie on (a straight axis: one straight; not a `points` "
        "table), the design joint's opening abs(`width_m` `length_m` / `radius_m` - "
        "`taper_mm`) (a straight's: abs(`taper_mm`)) <= `max_gap_mm`",
        _radius_and_taper,
    ),
    Rule(
        "radius-the-machine-takes",
        (
            "tunnel.alignment.horizontal",
            "walking.step_length_mm",
            "walking.max_yaw_deg",
            "walking.max_heading_correction_per_step_deg",
        ),
        "every arc the rings lie on: `step_length_mm` / abs(`radius_m`) + "
        "`max_heading_correction_per_step_deg` <= `max_yaw_deg` (S's turn in M in a step, "
        "curves.md section 3)",
        _tightest_radius,
    ),
    Rule(
        "grade-the-machine-takes",
        ("tunnel.alignment",),
        f"`gradient_percent`, a table's segments' grades, every grade element the rings lie "
        f"on: within ±{_g(STEEPEST_GRADE_PERCENT)} % (`STEEPEST_GRADE_PERCENT`, curves.md)",
        _steepest_grade,
    ),
    Rule(
        "vertical-curve-the-machine-takes",
        (
            "tunnel.alignment.vertical",
            "walking.touchdown_travel_mm",
            "layers.lower.half_span_x_m",
            "walking.step_length_mm",
        ),
        "every vertical curve the rings lie on: the invert's rise (`half_span_x_m` + "
        "`step_length_mm`)^2 / (2 `radius_m`) under a foot landing a step ahead of where it "
        "stood <= `touchdown_travel_mm` (the lowering finds the invert in that window)",
        _vertical_curve,
    ),
    Rule(
        "legs-within-the-envelope",
        ("layers.*.half_span_*_m", "frames.sub.half_span_*_m", "robot.length_mm", "robot.width_mm"),
        "every cylinder's action point (S's legs at both ends of a step) within half "
        "`length_mm` along and half `width_mm` across the machine's centre (within "
        f"{_g(1000 * ENVELOPE_TOLERANCE_M)} mm)",
        _envelope,
    ),
    Rule(
        "envelope-fits-the-tunnel",
        ("robot.width_mm", "robot.height_mm", "tunnel.inner_diameter_m", "workpiece"),
        "the envelope standing on the invert: its top corners inside the lining, lower than "
        "`workpiece.height_m` and narrower than `workpiece.length_m` (it walks through the "
        "placed parts)",
        _fits_the_tunnel,
    ),
)

_BY_NAME = {r.name: r for r in RULES}
_PROVIDED: dict[str, Check] = {}
_importer: Callable[[str], object] | None = None


def provide(name: str, module: str) -> Callable[[Check], Check]:
    """Decorator: ``module`` provides the check of rule ``name`` (a rule whose
    ``provider`` it is)."""
    rule = _BY_NAME.get(name)
    if rule is None or rule.provider != module:
        raise ValueError(f"no cross-check {name!r} provided by {module!r} in config.crosscheck")

    def register(fn: Check) -> Check:
        _PROVIDED[name] = fn
        return fn

    return register


def set_importer(importer: Callable[[str], object] | None) -> None:
    """How to import a provider module when a rule's check is not registered yet
    (``importlib.import_module``: the ``wara`` command installs it)."""
    global _importer
    _importer = importer


def check_of(rule: Rule) -> Check | None:
    """The rule's check: its own, the one its provider registered (importing the
    provider with the installed importer if need be), or ``None``."""
    if rule.check is not None:
        return rule.check
    if rule.name not in _PROVIDED and _importer is not None:
        _importer(rule.provider)
    return _PROVIDED.get(rule.name)


def problems(cfg: ProjectConfig, skip: Collection[str] = ()) -> list[str]:
    """The reason of every rule the project breaks, one line each, in table order
    (``skip``: names of rules left out)."""
    unknown = sorted(set(skip) - set(_BY_NAME))
    if unknown:
        raise ValueError(f"no cross-check(s) {unknown} in config.crosscheck")
    out = []
    for rule in RULES:
        if rule.name in skip:
            continue
        check = check_of(rule)
        reason = check(cfg) if check is not None else None
        if reason is not None:
            out.append(reason)
    return out


def docs_table() -> str:
    """The table of docs/config.md, "Cross-checks between keys" (a test keeps it equal)."""
    rows = ["| rule | keys | consistent when | check in |", "|---|---|---|---|"]
    for r in RULES:
        keys = ", ".join(f"`{k}`" for k in r.keys)
        where = f"`{r.provider}`" if r.provider else "`config.crosscheck`"
        rows.append(f"| `{r.name}` | {keys} | {r.consistent} | {where} |")
    return "\n".join(rows) + "\n"
