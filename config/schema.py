"""Pydantic v2 models of a W-ARa tunnel project: the whole machine, not only the planner.

Every model forbids unknown keys and is frozen. Keys carry engineering units in their
names; each model offers SI properties (``stroke_m``, ``cap_area_m2``) computed with
:mod:`config.units`, so the code never converts units itself.

Every number is finite (:data:`Finite`: no NaN, no infinity) and every numeric key of a
project states the range a machine of this kind can have, so that a typo (an extra
zero, ``.inf``, a loop rate in kHz written as Hz) is refused at load time rather than
switching an interlock off or reaching the planner.
"""

from __future__ import annotations

import itertools
from collections import Counter
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from config import units

#: A finite float (NaN and +-inf refused): the base of every float in the schema.
Finite = Annotated[float, Field(allow_inf_nan=False)]
Positive = Annotated[Finite, Field(gt=0)]
NonNegative = Annotated[Finite, Field(ge=0)]

# Ranges a machine of this kind can have (generous: they catch typos, not tuning).
#: a mass on or of the machine: the workpiece is 36 t
MassKg = Annotated[Finite, Field(gt=0, le=1e6)]
#: a length in metres on the machine or the tunnel
LengthM = Annotated[Finite, Field(gt=0, le=100)]
#: an envelope dimension in millimetres
LengthMm = Annotated[Finite, Field(gt=0, le=100_000)]
#: a cylinder bore or rod diameter
DiameterMm = Annotated[Finite, Field(gt=0, le=1000)]
#: a cylinder stroke
StrokeMm = Annotated[Finite, Field(gt=0, le=10_000)]
#: a hydraulic pressure: industrial hydraulics stay below 70 MPa (700 bar)
PressureMpa = Annotated[Finite, Field(gt=0, le=70)]
#: a small pressure (tank, margin) that may be zero
PressureMarginMpa = Annotated[Finite, Field(ge=0, le=20)]
#: a coordinate in metres (centre of gravity, platform origin)
CoordM = Annotated[Finite, Field(ge=-100, le=100)]
#: a timeout in milliseconds: above 0, at most a minute
TimeoutMs = Annotated[Finite, Field(gt=0, le=60_000)]
#: a gain or bandwidth that may be zero
GainNonNegative = Annotated[Finite, Field(ge=0, le=1e6)]
#: a bandwidth in rad/s or Hz
BandwidthPositive = Annotated[Finite, Field(gt=0, le=1e5)]
Vec3 = tuple[CoordM, CoordM, CoordM]


class Strict(BaseModel):
    """Base: unknown keys are errors, values are immutable after loading, floats finite."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class Cycle(Strict):
    """The ring cycle (placement.md section 4; docs/placement.md, "The ring cycle")."""

    #: steps of the walk to the ring (and back, unloaded); 0: the machine stands at the ring
    walk_steps: Annotated[int, Field(ge=0, le=1000)] = 0
    #: in the simulated cycle (``wara cycle``, the demo) the operator's confirmation that
    #: the part is fixed comes automatically after this much machine time of the hold
    fixing_confirm_after_s: Annotated[Finite, Field(gt=0, le=3600)] = 5.0
    #: the simulated survey: points measured on the placed part's front joint face
    survey_points: Annotated[int, Field(ge=4, le=100)] = 8
    #: and the noise of each measured coordinate (1 sigma, a total station's)
    survey_noise_mm: Annotated[Finite, Field(ge=0, le=10)] = 1.0
    #: a ring cycle's machine time, the fixing hold excluded, is judged against this
    max_cycle_time_min: Annotated[Finite, Field(gt=0, le=600)] = 15.0
    #: a motion of the ring cycle (a walk, the placement, the release) not ended this
    #: long after it was asked for, holds and ride-throughs included, is stuck: the
    #: cycle ends in its phase, the machine stopped (a backstop: each motion's own
    #: interlocks end one that goes wrong much sooner)
    max_motion_min: Annotated[Finite, Field(gt=0, le=600)] = 60.0
    #: the release: the upper layer's four cylinders lower together at this speed ...
    release_speed_mm_s: Annotated[Finite, Field(gt=0, le=20)] = 1.0
    #: ... until every upper cylinder's load pressure (rod force over cap area) is within
    #: this of its empty-platform value (the statics without the workpiece, less the
    #: rods' friction while lowering); at loading, their mean (weighted by the cap areas:
    #: their summed force) of its value with the part on (the part's COG as cast moves
    #: its weight between the four, not their sum)
    platform_pressure_tolerance_mpa: Annotated[Finite, Field(gt=0, le=10)] = 0.2
    #: then a further lowering, clear of the part, before the controlled stop
    release_clearance_mm: Annotated[Finite, Field(ge=0, le=100)] = 5.0
    #: lowered this far with the pressures not fallen (the part not fixed): the
    #: ``release`` interlock stops the machine
    release_max_travel_mm: Annotated[Finite, Field(gt=0, le=100)] = 10.0

    @property
    def survey_noise_m(self) -> float:
        return units.mm(self.survey_noise_mm)

    @property
    def max_motion_s(self) -> float:
        return 60.0 * self.max_motion_min

    @property
    def release_speed_m_s(self) -> float:
        return units.mm(self.release_speed_mm_s)

    @property
    def platform_pressure_tolerance_pa(self) -> float:
        return units.mpa(self.platform_pressure_tolerance_mpa)

    @property
    def release_clearance_m(self) -> float:
        return units.mm(self.release_clearance_mm)

    @property
    def release_max_travel_m(self) -> float:
        return units.mm(self.release_max_travel_mm)


# --------------------------------------------------------------------------- project


class ProjectInfo(Strict):
    #: the project's name (shown in the reports and the OPC UA identification)
    name: str = Field(min_length=1)
    #: the tunnel section it covers
    section: str = ""
    #: free text
    description: str = ""


class AlignmentPoint(Strict):
    """One row of a design-axis table: the centreline at a chainage, project coordinates
    (x, y horizontal, z up)."""

    #: the chainage of this row (increasing from row to row)
    chainage_m: Annotated[Finite, Field(ge=-1e6, le=1e6)]
    #: the centreline's x at this chainage, project frame
    x_m: Annotated[Finite, Field(ge=-1e7, le=1e7)]
    #: its y (horizontal)
    y_m: Annotated[Finite, Field(ge=-1e7, le=1e7)]
    #: its z (up)
    z_m: Annotated[Finite, Field(ge=-1e4, le=1e4)]


#: Adjoining elements of a chainage-form alignment must meet within this (m): a
#: clothoid's or vertical curve's length against what its parameter or radius gives.
CONTIGUITY_TOLERANCE_M = 0.01


class HorizontalElement(Strict):
    """One element of the horizontal alignment, from its start chainage to the next
    element's (the last goes on). Chainage is measured along the axis in plan, as the
    designers' drawings give it."""

    #: the chainage where this element starts (increasing from element to element)
    start_chainage_m: Annotated[Finite, Field(ge=-1e6, le=1e6)]
    #: `straight`, `arc` (radius_m) or `clothoid` (clothoid_parameter_m: its curvature
    #: changes linearly from the element before's to the element after's)
    kind: Literal["straight", "arc", "clothoid"]
    #: an arc's radius, signed: positive turns left (its centre on the axis's left, +y;
    #: counter-clockwise seen from above), negative right
    radius_m: Annotated[Finite, Field(ge=-1e6, le=1e6)] | None = None
    #: a clothoid's parameter A: its length is A^2 times the change of curvature it
    #: makes (A^2 = R x length from a straight into an arc of radius R)
    clothoid_parameter_m: Annotated[Finite, Field(gt=0, le=1e5)] | None = None

    @model_validator(mode="after")
    def _its_keys(self) -> HorizontalElement:
        has_r, has_a = self.radius_m is not None, self.clothoid_parameter_m is not None
        if self.kind == "arc" and (not has_r or self.radius_m == 0 or has_a):
            raise ValueError("an arc gives radius_m (signed, not 0) and no clothoid_parameter_m")
        if self.kind == "clothoid" and (not has_a or has_r):
            raise ValueError("a clothoid gives clothoid_parameter_m and no radius_m")
        if self.kind == "straight" and (has_r or has_a):
            raise ValueError("a straight gives neither radius_m nor clothoid_parameter_m")
        return self

    @property
    def curvature_per_m(self) -> float:
        """A straight's or arc's curvature (1/m, positive turning left); a clothoid's is
        its neighbours'."""
        return 1.0 / self.radius_m if self.radius_m else 0.0


class HorizontalAlignment(Strict):
    """The design axis in plan: where it starts and its elements."""

    #: the axis's x at the first element's start chainage, project frame
    x_m: Annotated[Finite, Field(ge=-1e7, le=1e7)] = 0.0
    #: its y there
    y_m: Annotated[Finite, Field(ge=-1e7, le=1e7)] = 0.0
    #: its heading there, from the project's +x toward +y (counter-clockwise from above)
    heading_deg: Annotated[Finite, Field(ge=-360, le=360)] = 0.0
    #: the elements, each from its start chainage; before the first the axis is straight
    elements: tuple[HorizontalElement, ...] = Field(min_length=1)


class VerticalElement(Strict):
    """One element of the vertical alignment: a constant grade, or a vertical curve that
    joins the grades before and after it (its grade changes linearly with chainage)."""

    #: the chainage where this element starts (increasing from element to element)
    start_chainage_m: Annotated[Finite, Field(ge=-1e6, le=1e6)]
    #: a constant grade, rising this much per 100 m of chainage (or radius_m)
    gradient_percent: Annotated[Finite, Field(ge=-10, le=10)] | None = None
    #: a vertical curve's radius: its length is this times the change of grade between
    #: its neighbours (which set whether it is a sag or a crest)
    radius_m: Annotated[Finite, Field(gt=0, le=1e6)] | None = None

    @model_validator(mode="after")
    def _one_kind(self) -> VerticalElement:
        if (self.gradient_percent is None) == (self.radius_m is None):
            raise ValueError("give either gradient_percent (a grade) or radius_m (a curve)")
        return self


class VerticalAlignment(Strict):
    """The design axis's levels along the chainage."""

    #: the axis's z at the first element's start chainage, project frame
    z_m: Annotated[Finite, Field(ge=-1e4, le=1e4)] = 0.0
    #: the grades and vertical curves, each from its start chainage; before the first
    #: the first grade goes on
    elements: tuple[VerticalElement, ...] = Field(min_length=1)


def _contiguous_horizontal(h: HorizontalAlignment) -> None:
    el = h.elements
    for i, e in enumerate(el):
        name = f"horizontal.elements[{i}] ({e.kind} from chainage {e.start_chainage_m:g} m)"
        if i and e.start_chainage_m <= el[i - 1].start_chainage_m:
            raise ValueError(
                f"{name}: does not start after elements[{i - 1}] "
                f"({el[i - 1].start_chainage_m:g} m): the elements must follow one another"
            )
        if e.kind != "clothoid" or e.clothoid_parameter_m is None:
            continue
        if i == 0 or i == len(el) - 1:
            raise ValueError(f"{name}: a clothoid joins two elements: it cannot be first or last")
        before, after = el[i - 1], el[i + 1]
        if "clothoid" in (before.kind, after.kind):
            raise ValueError(f"{name}: a clothoid joins a straight or arc to another")
        dk = abs(after.curvature_per_m - before.curvature_per_m)
        length = after.start_chainage_m - e.start_chainage_m
        want = e.clothoid_parameter_m**2 * dk
        if dk == 0 or abs(length - want) > CONTIGUITY_TOLERANCE_M:
            raise ValueError(
                f"{name}: is {length:g} m long but A^2 x the change of curvature "
                f"({e.clothoid_parameter_m:g}^2 x {dk:.6g} 1/m) makes it {want:.3f} m: "
                f"elements[{i + 1}] should start at {e.start_chainage_m + want:.3f} m"
            )


def _contiguous_vertical(v: VerticalAlignment) -> None:
    el = v.elements
    for i, e in enumerate(el):
        kind = "grade" if e.radius_m is None else "vertical curve"
        name = f"vertical.elements[{i}] ({kind} from chainage {e.start_chainage_m:g} m)"
        if i and e.start_chainage_m <= el[i - 1].start_chainage_m:
            raise ValueError(
                f"{name}: does not start after elements[{i - 1}] "
                f"({el[i - 1].start_chainage_m:g} m): the elements must follow one another"
            )
        if e.radius_m is None:
            continue
        if i == 0 or i == len(el) - 1 or el[i - 1].radius_m or el[i + 1].radius_m:
            raise ValueError(f"{name}: a vertical curve joins a grade before it to one after it")
        g0, g1 = el[i - 1].gradient_percent or 0.0, el[i + 1].gradient_percent or 0.0
        length = el[i + 1].start_chainage_m - e.start_chainage_m
        want = e.radius_m * abs(g1 - g0) / 100.0
        if g0 == g1 or abs(length - want) > CONTIGUITY_TOLERANCE_M:
            raise ValueError(
                f"{name}: is {length:g} m long but radius_m x the change of grade "
                f"({e.radius_m:g} m x {abs(g1 - g0):g} %) makes it {want:.3f} m: "
                f"elements[{i + 1}] should start at {e.start_chainage_m + want:.3f} m"
            )


class Alignment(Strict):
    """The design axis (placement.md section 1; docs/curves.md): a straight axis with a
    gradient, a table of centreline points (linear between rows), or by chainage as the
    designers hand it over (``horizontal`` and ``vertical`` elements), in project
    coordinates. ``first_ring_chainage_m``: the chainage of ring 1's rear joint face; ring
    ``n``'s is ``n - 1`` ring widths further along the axis."""

    #: the chainage of ring 1's rear joint face; ring n's is n - 1 ring widths further
    first_ring_chainage_m: Annotated[Finite, Field(ge=-1e6, le=1e6)] = 0.0
    #: straight axis through the project origin, rising this much per 100 m of chainage
    gradient_percent: Annotated[Finite, Field(ge=-10, le=10)] | None = None
    #: the design axis as a table of centreline points, linear between rows (instead of
    #: gradient_percent)
    points: tuple[AlignmentPoint, ...] = ()
    #: the axis in plan by chainage: straights, arcs and clothoids (with ``vertical``;
    #: instead of gradient_percent or points)
    horizontal: HorizontalAlignment | None = None
    #: the axis's levels by chainage: grades joined by vertical curves (with ``horizontal``)
    vertical: VerticalAlignment | None = None

    @model_validator(mode="after")
    def _one_form(self) -> Alignment:
        if (self.horizontal is None) != (self.vertical is None):
            raise ValueError("horizontal and vertical: give both (the axis by chainage)")
        forms = (self.gradient_percent is not None) + bool(self.points) + self.by_chainage
        if forms != 1:
            raise ValueError(
                "give either gradient_percent (a straight axis), points (a table) or "
                "horizontal and vertical (the axis by chainage)"
            )
        if self.horizontal is not None and self.vertical is not None:
            _contiguous_horizontal(self.horizontal)
            _contiguous_vertical(self.vertical)
        if self.points:
            if len(self.points) < 2:
                raise ValueError("points: a table needs at least two rows")
            ch = [p.chainage_m for p in self.points]
            if any(b <= a for a, b in itertools.pairwise(ch)):
                raise ValueError("points: chainage_m must increase from row to row")
        return self

    @property
    def by_chainage(self) -> bool:
        """The axis by chainage (``horizontal`` and ``vertical``)."""
        return self.horizontal is not None


class Tunnel(Strict):
    """The lining the machine works in: the parts sit on its invert (their reference
    height, :attr:`ProjectConfig.reference_height_m`) and the machine fits inside it
    (config.crosscheck); the lining's outer diameter governs nothing here (not a key)."""

    #: the lining's inside: the parts' reference height on its invert, the machine's
    #: envelope within it (config.crosscheck)
    inner_diameter_m: Annotated[Finite, Field(gt=0, le=30)]
    #: a ring's width along the axis: ring n's chainage, a survey's plausible offset along
    #: the axis (half of it)
    ring_width_m: Annotated[Finite, Field(gt=0, le=10)]
    #: the design axis; without it the machine cannot place (no ``placement``)
    alignment: Alignment | None = None

    @property
    def inner_radius_m(self) -> float:
        return self.inner_diameter_m / 2.0


class Workpiece(Strict):
    """The precast arc part.

    Its mass is the upper layer's body named :data:`WORKPIECE_BODY` (with its centre of
    gravity: what the statics and the simulator carry); ``mass_kg`` is left out then
    (:attr:`ProjectConfig.workpiece_mass_kg`). A project without that body gives it here;
    a project that gives both must give the same (config.crosscheck).
    """

    #: the arc part's length across the tunnel (Table 4's corners, the angles' lever arm)
    length_m: LengthM
    #: its height (the joint face's corners, the simulated survey's points)
    height_m: LengthM
    #: its width along the tunnel (the ring width it fills: the joint's position, the pads)
    width_m: LengthM
    #: its mass, for a project without an upper body ``workpiece``; left out, the body's
    #: (which the statics and the simulator carry; config.crosscheck: the same if both)
    mass_kg: MassKg | None = None
    #: the difference in width between the part's two ends (a tapered part closes a
    #: curve's joints: w L / R); positive: the left end (+y) narrower, for a curve to the
    #: left; negative: the right end; 0: rectangular
    taper_mm: Annotated[Finite, Field(ge=-500, le=500)] = 0.0

    @property
    def taper_m(self) -> float:
        return units.mm(self.taper_mm)


class Robot(Strict):
    """The machine as a whole (paper): its envelope, which its legs stand within and
    which must fit the tunnel, and its weight, which is its bodies' (config.crosscheck)."""

    #: the machine's envelope length: its legs stand within it (config.crosscheck)
    length_mm: LengthMm
    #: its envelope width: its legs within it, within the tunnel and the parts' hollow
    width_mm: LengthMm
    #: its envelope height: within the tunnel and below a part (it walks through them)
    height_mm: LengthMm
    #: its mass: the bodies' sum but the part's, the rods in it (config.crosscheck)
    mass_kg: MassKg


class Base(Strict):
    """Attitude of the tunnel invert under the standing frame (model.md section 1)."""

    #: roll of the tunnel invert under the standing frame
    roll_deg: Annotated[Finite, Field(ge=-15, le=15)] = 0.0
    #: pitch of the invert (positive turns x down: a falling gradient)
    pitch_deg: Annotated[Finite, Field(ge=-15, le=15)] = 0.0

    @property
    def roll_rad(self) -> float:
        return units.deg(self.roll_deg)

    @property
    def pitch_rad(self) -> float:
        return units.deg(self.pitch_deg)


#: The upper layer's body that is the arc part (``layers.upper.bodies``): what the ring
#: cycle sets in the ring and walks back without (the controller's statics unloaded, the
#: simulator's bolted part).
WORKPIECE_BODY = "workpiece"


class Body(Strict):
    """A rigid body carried by a platform: point mass at its centre of gravity.

    ``cog_m`` is in the platform frame, origin at the centre of the four action
    points at mid-stroke (model.md section 5).
    """

    #: the body's name (``workpiece`` on the upper layer: the arc part)
    name: str = Field(min_length=1)
    #: its mass, a point mass at its centre of gravity
    mass_kg: MassKg
    #: its centre of gravity in its platform's frame (origin at the action points' centre
    #: at mid-stroke)
    cog_m: Vec3


# --------------------------------------------------------------------------- cylinders

CylinderRole = Literal[
    "main_leg", "sub_leg", "upper_attitude", "travel", "rotation", "central_axis", "lateral"
]

#: How many cylinders of each role the machine has (19 in all, model.md section 2).
ROLE_COUNTS: dict[str, int] = {
    "main_leg": 4,
    "sub_leg": 4,
    "upper_attitude": 4,
    "travel": 2,
    "rotation": 2,
    "central_axis": 1,
    "lateral": 2,
}
N_CYLINDERS = sum(ROLE_COUNTS.values())


class CylinderPlant(Strict):
    """Hydraulic parameters of one valve-controlled cylinder (paper Table 3).

    ``damping_ratio`` is the paper's "viscous damping factor", read as the damping
    ratio of the hydraulic spring-mass mode (see docs/model-choices.md).
    """

    #: leakage across the piston, per Pa of pressure difference (Table 3)
    internal_leakage_m3_s_pa: Annotated[Finite, Field(ge=0, le=1e-8)] = 7.2e-12
    #: leakage to tank from each chamber, per Pa (Table 3)
    external_leakage_m3_s_pa: Annotated[Finite, Field(ge=0, le=1e-8)] = 7.2e-12
    #: the valve's area gradient w (opening width per spool travel, as a length)
    area_gradient_mm: Annotated[Finite, Field(gt=0, le=1000)] = 26.0
    #: Table 3's viscous damping factor, read as the damping ratio of the hydraulic mode
    damping_ratio: Annotated[Finite, Field(ge=0, le=10)] = 0.65
    #: oil volume of each chamber's valve block and hose
    dead_volume_l: Annotated[Finite, Field(gt=0, le=1000)] = 1.0
    #: Coulomb friction of the rod seals
    coulomb_friction_n: Annotated[Finite, Field(ge=0, le=1e6)] = 2000.0
    #: the moving mass of a standalone cylinder (rod plus its load)
    moving_mass_kg: MassKg = 9000.0

    @property
    def area_gradient_m(self) -> float:
        return units.mm(self.area_gradient_mm)

    @property
    def dead_volume_m3(self) -> float:
        return self.dead_volume_l * units.LITRE


class Cylinder(Strict):
    """One of the 19 cylinders: identity, geometry and its place on the CAN wire."""

    #: the cylinder's name (``main_leg_1``): used in messages, logs and the status
    id: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    #: what it does on the machine (the counts per role are fixed)
    role: CylinderRole
    #: its synchronization and CAN group (``main_legs``, ``upper``, ...)
    group: str = Field(pattern=r"^[a-z][a-z0-9_]*$")
    #: its position 1-4 in its layer (attitude cylinders and legs only)
    position: Annotated[int, Field(ge=1, le=4)] | None = None
    #: cap-side bore
    bore_mm: DiameterMm
    #: rod diameter (smaller than the bore)
    rod_mm: DiameterMm
    #: stroke
    stroke_mm: StrokeMm
    #: its slot in the DBC's per-cylinder signals (``ValveCmd_NN``, ``RodPos_NN``)
    can_index: Annotated[int, Field(ge=0, lt=N_CYLINDERS)]
    plant: CylinderPlant | None = None

    @model_validator(mode="after")
    def _rod_fits(self) -> Cylinder:
        if self.rod_mm >= self.bore_mm:
            raise ValueError(
                f"rod_mm ({self.rod_mm}) must be smaller than bore_mm ({self.bore_mm})"
            )
        return self

    @property
    def stroke_m(self) -> float:
        return units.mm(self.stroke_mm)

    @property
    def cap_area_m2(self) -> float:
        return units.circle_area_m2(units.mm(self.bore_mm))

    @property
    def rod_area_m2(self) -> float:
        """Annulus area on the rod side."""
        return units.annulus_area_m2(units.mm(self.bore_mm), units.mm(self.rod_mm))


# --------------------------------------------------------------------------- layers


class Layer(Strict):
    """One attitude layer: four vertical cylinders under a rigid platform."""

    #: half the distance between the cylinders' action points along x (a)
    half_span_x_m: Annotated[Finite, Field(gt=0, le=20)]
    #: half the distance along y (b)
    half_span_y_m: Annotated[Finite, Field(gt=0, le=20)]
    #: the layer's cylinder bore (each listed cylinder has the same)
    bore_mm: DiameterMm
    #: their rod diameter
    rod_mm: DiameterMm
    #: their stroke
    stroke_mm: StrokeMm
    #: stroke kept in reserve at each end: the planning limit is stroke/2 less this
    reserve_mm: Annotated[Finite, Field(ge=0, le=10_000)]
    #: the four cylinder ids, at positions 1-4
    cylinders: tuple[str, str, str, str]
    #: the bodies the platform carries
    bodies: tuple[Body, ...] = ()

    @model_validator(mode="after")
    def _geometry(self) -> Layer:
        if self.rod_mm >= self.bore_mm:
            raise ValueError(
                f"rod_mm ({self.rod_mm}) must be smaller than bore_mm ({self.bore_mm})"
            )
        if self.reserve_mm >= self.stroke_mm / 2:
            raise ValueError(
                f"reserve_mm ({self.reserve_mm}) must be smaller than half the stroke "
                f"({self.stroke_mm / 2} mm)"
            )
        if len(set(self.cylinders)) != 4:
            raise ValueError(f"cylinders must name four different cylinders, got {self.cylinders}")
        return self

    @property
    def a_m(self) -> float:
        return self.half_span_x_m

    @property
    def b_m(self) -> float:
        return self.half_span_y_m

    @property
    def stroke_m(self) -> float:
        return units.mm(self.stroke_mm)

    @property
    def reserve_m(self) -> float:
        return units.mm(self.reserve_mm)

    @property
    def extension_limit_m(self) -> float:
        """Largest planned |extension| from mid-stroke: stroke/2 - reserve."""
        return self.stroke_m / 2 - self.reserve_m

    @property
    def cap_area_m2(self) -> float:
        return units.circle_area_m2(units.mm(self.bore_mm))

    @property
    def rod_area_m2(self) -> float:
        return units.annulus_area_m2(units.mm(self.bore_mm), units.mm(self.rod_mm))


class UpperLayer(Layer):
    """The fine stage; its base is the lower platform."""

    #: the upper base's origin in the lower platform's frame
    origin_in_lower_m: Vec3 = (0.0, 0.0, 0.0)


class Layers(Strict):
    lower: Layer
    upper: UpperLayer


# --------------------------------------------------------------------------- hydraulics


class Hydraulics(Strict):
    #: supply pressure (Table 3)
    supply_pressure_mpa: PressureMpa
    #: tank pressure, below the supply
    tank_pressure_mpa: PressureMarginMpa = 0.0
    #: the cylinders' rated pressure: the planner's pressure limit
    rated_pressure_mpa: PressureMpa
    #: the load-sensing pump's margin: what the slide axes may use is supply less this
    load_sensing_margin_mpa: PressureMarginMpa
    #: oil density (the orifice flows)
    oil_density_kg_m3: Annotated[Finite, Field(ge=500, le=1500)]
    #: oil bulk modulus (the chambers' stiffness)
    bulk_modulus_mpa: Annotated[Finite, Field(ge=10, le=5000)]
    #: the valve orifices' discharge coefficient
    discharge_coefficient: Annotated[Finite, Field(gt=0, le=1)] = 0.61
    #: pump flow: the trajectory's duration keeps the extending cylinders' flow within it
    pump_flow_l_min: Annotated[Finite, Field(gt=0, le=10_000)]
    #: the servo valve's spool natural frequency
    valve_natural_frequency_hz: Annotated[Finite, Field(gt=0, le=1000)] = 60.0
    #: the spool's damping ratio
    valve_damping_ratio: Annotated[Finite, Field(gt=0, le=10)] = 0.7
    #: full spool opening (command 1)
    valve_max_opening_mm: Annotated[Finite, Field(gt=0, le=20)] = 0.5
    #: weight of each leg's and upper-platform cylinder's rod and piston (a leg's with its
    #: foot): what a hanging leg pulls on the body, and what the upper rods add to the
    #: load the legs carry; the HIL rig's rod mass (machine data, one value for all)
    rod_mass_kg: Annotated[Finite, Field(gt=0, le=10_000)] = 150.0
    cylinder_defaults: CylinderPlant = CylinderPlant()

    @model_validator(mode="after")
    def _pressures(self) -> Hydraulics:
        if self.tank_pressure_mpa >= self.supply_pressure_mpa:
            raise ValueError("tank_pressure_mpa must be below supply_pressure_mpa")
        return self

    @property
    def supply_pressure_pa(self) -> float:
        return units.mpa(self.supply_pressure_mpa)

    @property
    def tank_pressure_pa(self) -> float:
        return units.mpa(self.tank_pressure_mpa)

    @property
    def rated_pressure_pa(self) -> float:
        return units.mpa(self.rated_pressure_mpa)

    @property
    def load_sensing_margin_pa(self) -> float:
        return units.mpa(self.load_sensing_margin_mpa)

    @property
    def bulk_modulus_pa(self) -> float:
        return units.mpa(self.bulk_modulus_mpa)

    @property
    def pump_flow_m3_s(self) -> float:
        return self.pump_flow_l_min * units.L_PER_MIN

    @property
    def valve_max_opening_m(self) -> float:
        return units.mm(self.valve_max_opening_mm)


# --------------------------------------------------------------------------- planner


class LdwPso(Strict):
    """The paper's planner: particle swarm, linearly decreasing inertia weight."""

    #: particles
    swarm_size: Annotated[int, Field(ge=4, le=10_000)] = 50
    #: iterations per solve
    iterations: Annotated[int, Field(ge=1, le=100_000)] = 1000
    #: inertia weight at the first iteration
    inertia_start: Annotated[Finite, Field(gt=0, le=2)] = 0.9
    #: inertia weight at the last (linear in between)
    inertia_end: Annotated[Finite, Field(gt=0, le=2)] = 0.4
    #: the cognitive coefficient
    c1: Annotated[Finite, Field(gt=0, le=10)] = 2.0
    #: the social coefficient
    c2: Annotated[Finite, Field(gt=0, le=10)] = 2.0
    #: the swarm's random seed
    seed: Annotated[int, Field(ge=0, lt=2**32)] = 0
    #: Weight of one unit of dimensionless violation against the objective divided by
    #: its median over the initial swarm.
    penalty_weight: Annotated[Finite, Field(gt=0, le=1e6)] = 1.0


class Exact(Strict):
    """The project's deterministic planner (grid, Newton on vertices, pattern search)."""

    #: points per axis of the first grid over the upper layer's extensions
    grid_points: Annotated[int, Field(ge=5, le=1001)] = 21
    #: Newton steps on the critical curves' vertices
    newton_iterations: Annotated[int, Field(ge=0, le=100)] = 8
    #: points per axis of each pattern-search grid
    zoom_points: Annotated[int, Field(ge=3, le=201)] = 7
    #: how much each pattern-search grid shrinks
    zoom_factor: Annotated[Finite, Field(gt=1, le=50)] = 3.0
    #: the search stops when its step is below this
    tolerance_m: Annotated[Finite, Field(gt=0, le=1e-3)] = 1e-10


class Trajectory(Strict):
    #: the time scaling of a move: quintic or trapezoidal in velocity
    profile: Literal["quintic", "trapezoidal"] = "quintic"
    #: largest rod speed of a planned move (the walk's legs too)
    max_rod_speed_mm_s: Annotated[Finite, Field(gt=0, le=1000)] = 20.0
    #: largest rod acceleration of a planned move
    max_rod_accel_mm_s2: Annotated[Finite, Field(gt=0, le=10_000)] = 20.0
    #: a plan's constraints are checked at samples this far apart
    sample_period_s: Annotated[Finite, Field(ge=0.001, le=10)] = 0.05

    @property
    def max_rod_speed_m_s(self) -> float:
        return units.mm(self.max_rod_speed_mm_s)

    @property
    def max_rod_accel_m_s2(self) -> float:
        return units.mm(self.max_rod_accel_mm_s2)


class Planner(Strict):
    #: what the split between the layers minimizes
    objective: Literal["sum_pressure", "peak_pressure", "pump_energy"] = "pump_energy"
    #: the planner: ``exact`` (grid, Newton on vertices) or the paper's ``ldw_pso``
    method: Literal["exact", "ldw_pso"] = "exact"
    #: lift-off: every rod pushes at least this
    min_rod_force_kn: Annotated[Finite, Field(ge=0, le=10_000)]
    #: the action points' largest distance from a plane (paper eq. 17)
    coplanarity_tolerance_mm: Annotated[Finite, Field(gt=0, le=100)]
    #: a plan whose achieved attitude is further from the target is refused
    attitude_tolerance_rad: Annotated[Finite, Field(gt=0, le=1e-3)] = 1e-9
    ldw_pso: LdwPso = LdwPso()
    exact: Exact = Exact()
    trajectory: Trajectory = Trajectory()
    #: IPC: a plan request without a result for longer (a worker still starting counts)
    #: latches ``planner``; the planner process is killed and started again
    request_timeout_s: Annotated[Finite, Field(gt=0, le=3600)] = 10.0

    @property
    def min_rod_force_n(self) -> float:
        return self.min_rod_force_kn * units.KN

    @property
    def coplanarity_tolerance_m(self) -> float:
        return units.mm(self.coplanarity_tolerance_mm)


# --------------------------------------------------------------------------- control


class Ladrc(Strict):
    #: the model's order (1: the command sets a rod speed)
    order: Literal[1, 2] = 1
    #: controller bandwidth (crossover) of every position loop; left out (null): each
    #: group's derived from the plant (``ipc_app.control.tuning``, docs/control.md)
    wc_rad_s: BandwidthPositive | None = None
    #: extended state observer bandwidth; left out (null): derived as ``wc_rad_s`` is
    wo_rad_s: BandwidthPositive | None = None
    #: ``zoh``: exact, with the current observer; ``euler``: forward Euler
    discretization: Literal["euler", "zoh"] = "zoh"
    #: the command's largest change per second (full opening is 1)
    rate_limit_per_s: Annotated[Finite, Field(gt=0, le=1e6)] = 20.0
    #: feed the trajectory's rod speeds forward (docs/control.md); off: model.md's plain law
    reference_feedforward: bool = True


class Pid(Strict):
    #: proportional gain: command per m of error
    kp_per_m: GainNonNegative = 100.0
    #: integral gain: command per m s
    ki_per_m_s: GainNonNegative = 20.0
    #: derivative gain: command per m/s
    kd_s_per_m: GainNonNegative = 0.0
    #: corner frequency of the first-order filter on the derivative term
    derivative_filter_hz: BandwidthPositive = 20.0


class Sync(Strict):
    #: how a group's synchronization error is formed from its tracking errors
    scheme: Literal["mean_deviation", "cross_coupled"] = "mean_deviation"
    #: weight of the synchronization error in each cylinder's error (dual error)
    coupling_lambda: Annotated[Finite, Field(ge=0, le=100)] = 1.0


class Realtime(Strict):
    """Applied by the service when asked and allowed; reported when refused."""

    #: SCHED_FIFO priority of the loop thread; 0 leaves the scheduler alone
    priority: Annotated[int, Field(ge=0, le=99)] = 0
    #: CPUs the loop thread may run on; empty: any
    cpu_affinity: tuple[Annotated[int, Field(ge=0, le=4095)], ...] = ()
    #: lock the service's memory (``mlockall``)
    lock_memory: bool = False
    #: while the loop runs, hold a Linux PM QoS request (``/dev/cpu_dma_latency``) that
    #: no CPU take longer than this to wake: 0 keeps idle CPUs polling, so a step starts
    #: on a warm CPU (docs/realtime.md); null leaves the system's idle states alone
    cpu_wakeup_latency_us: Annotated[int, Field(ge=0, le=1_000_000)] | None = None


class Control(Strict):
    #: 50 Hz is the slowest rate at which the interlocks and the sync control still
    #: act within the safety timeouts; 2000 Hz the fastest the bus budget allows.
    loop_rate_hz: Annotated[Finite, Field(ge=50, le=2000)] = 200.0
    #: the attitude loops' controller: LADRC, or the paper's PID baseline
    controller: Literal["ladrc", "pid"] = "ladrc"
    ladrc: Ladrc = Ladrc()
    pid: Pid = Pid()
    sync: Sync = Sync()
    realtime: Realtime = Realtime()
    #: every loop must stay stable with this much extra measurement delay (socketcan, a
    #: PLC scan out of phase, two processes): derived bandwidths keep twice it in the
    #: loop model, explicit ones are refused below it (``ipc_app.control.tuning``)
    delay_margin_ms: Annotated[Finite, Field(ge=5, le=1000)] = 20.0
    #: The rod speed of a jog in the MANUAL unit mode (``wara ctl jog``): slow enough
    #: for an operator beside the machine; 20 mm/s is the top of a hand-jog range.
    manual_jog_speed_mm_s: Annotated[Finite, Field(gt=0, le=20)] = 2.0

    @property
    def period_s(self) -> float:
        return 1.0 / self.loop_rate_hz


# --------------------------------------------------------------------------- CAN link


class CanLink(Strict):
    """The IPC <-> PLC CAN link (plc_bridge; docs/can-protocol.md).

    ``channel`` is the interface name for ``socketcan`` (``can0``, ``vcan0``), any
    name for ``virtual`` (in-process), the multicast group for ``udp_multicast`` and
    ``wara_udp`` (``239.74.163.2``) and ``host:port`` for ``remote``. ``bitrate`` is the bus's
    bit rate for the load budget; on ``socketcan`` the OS sets it (deploy/).
    """

    #: the bus back-end: ``socketcan`` on the machine, ``virtual`` in-process,
    #: ``udp_multicast`` or ``wara_udp`` across processes on one host, ``remote``
    interface: Literal["socketcan", "virtual", "udp_multicast", "wara_udp", "remote"] = "virtual"
    #: the interface name (``can0``), the multicast group (``239.74.163.2``), ``host:port``
    #: for remote, any name for virtual
    channel: str = "wara"
    #: the bus's bit rate, for the load budget (on socketcan the OS sets it: deploy/)
    bitrate: Annotated[int, Field(ge=10_000, le=1_000_000)] = 500_000
    #: an active group whose worst-case load is above this is refused
    max_bus_load_percent: Annotated[Finite, Field(gt=0, le=100)] = 50.0
    #: Cylinder groups whose frames run at the loop rate at start-up (the attitude
    #: group with the main frame standing); the IPC may switch it at run time.
    active_groups: tuple[str, ...] = ("main_legs", "upper")
    #: A received message is stale after this many of its cycle times without a valid frame.
    stale_cycles: Annotated[Finite, Field(ge=1.5, le=100)] = 3.0
    #: E2E MaxDeltaCounter: accept a counter step of up to this (max_delta - 1 lost frames).
    max_delta_counter: Annotated[int, Field(ge=1, le=7)] = 2
    #: UDP port of the ``udp_multicast`` and ``wara_udp`` interfaces.
    udp_port: Annotated[int, Field(ge=1024, le=65535)] = 43113


# --------------------------------------------------------------------------- safety


class Safety(Strict):
    #: a layer's measured twist above this latches ``twist``
    max_twist_mm: Annotated[Finite, Field(gt=0, le=100)] = 1.5
    #: a group's synchronization error above this latches ``sync error``; also the resume
    #: check
    max_sync_error_mm: Annotated[Finite, Field(gt=0, le=100)] = 2.0
    #: Largest |reference - measurement| of an attitude cylinder while moving (catches a
    #: group that stops as a whole: commands ignored, all valves stuck).
    max_tracking_error_mm: Annotated[Finite, Field(gt=0, le=1000)] = 10.0
    #: a valid chamber pressure above this latches ``pressure``
    max_pressure_mpa: PressureMpa = 24.0
    #: an active rod closer than this to an end of its stroke latches ``stroke end``
    stroke_end_margin_mm: Annotated[Finite, Field(ge=0, le=1000)] = 5.0
    #: IPC: a rod position of the active group lost for longer latches FAULT (a shorter
    #: loss suspends the motion and resumes it)
    sensor_timeout_ms: TimeoutMs = 100.0
    #: IPC: no valid PLC status for longer latches FAULT (the link is LOST)
    plc_heartbeat_timeout_ms: TimeoutMs = 100.0
    #: PLC: stale commands centre the spools at once; lost for longer latches IPC_TIMEOUT
    command_timeout_ms: TimeoutMs = 100.0
    #: IPC: a suspended motion that has not resumed within this latches FAULT
    max_suspend_ms: TimeoutMs = 250.0
    #: IPC: start-up (STOPPED) not complete within this ends in ABORTED (``start-up``, with
    #: what is missing)
    boot_timeout_s: Annotated[Finite, Field(gt=0, le=3600)] = 5.0
    #: IPC: the control socket's server thread without a turn for longer is stalled: it
    #: latches ``control channel`` and stops the service (systemd starts it again)
    ctl_stall_timeout_s: Annotated[Finite, Field(gt=0, le=3600)] = 5.0


# --------------------------------------------------------------------------- OPC UA


class OpcUa(Strict):
    """The OPC UA server beside the service (ipc_app.opcua; docs/opcua.md).

    Off unless ``enabled``. Relative paths are taken from the working directory of the
    process that reads them: the service's (its OPC UA server inherits it; under systemd
    ``WorkingDirectory=%S/wara``, i.e. ``/var/lib/wara``), and for ``wara opcua adduser``
    and ``wara opcua cert`` the shell's; ``deploy/install.sh`` creates the server
    certificate there and ``wara opcua adduser`` the users file.
    """

    #: ``wara serve`` starts the OPC UA server beside the service
    enabled: bool = False
    #: the address the server listens on (``0.0.0.0``: every interface)
    host: str = Field(
        default="0.0.0.0", min_length=1, max_length=253, pattern=r"^[A-Za-z0-9.:\-]+$"
    )
    #: the TCP port (the endpoint ``opc.tcp://HOST:PORT/wara/``)
    port: Annotated[int, Field(ge=1024, le=65535)] = 4840
    #: the only security policy offered, always with SignAndEncrypt
    security_policy: Literal["Basic256Sha256", "Aes128_Sha256_RsaOaep", "Aes256_Sha256_RsaPss"] = (
        "Basic256Sha256"
    )
    #: users with their scrypt password hashes and roles (outside the project YAML, 0600)
    users_file: str = Field(default="opcua/users.json", min_length=1)
    #: the PKI directory: ``own/cert.der``, ``own/key.pem``, ``trusted/`` (client certificates)
    pki_dir: str = Field(default="opcua/pki", min_length=1)
    #: a session without a user name may browse, read and subscribe (never call a method)
    anonymous_read_only: bool = False
    #: how often the server takes the service's status (the variables' update period)
    update_period_ms: Annotated[Finite, Field(ge=20, le=10_000)] = 50.0
    #: at most this many client connections at once; one beyond makes the oldest without
    #: an activated session close (none such: the new one is refused)
    max_connections: Annotated[int, Field(ge=1, le=1000)] = 32
    #: a connection that has not sent Hello within this is closed
    hello_timeout_s: Annotated[Finite, Field(ge=0.5, le=60)] = 5.0
    #: a connection without an activated session this long after it opened is closed
    #: (at ``max_connections`` the oldest such connection makes way for a new one)
    session_activate_timeout_s: Annotated[Finite, Field(ge=1, le=300)] = 10.0


# --------------------------------------------------------------------------- acceptance


#: an acceptance tolerance (Table 4: 5-10 mm)
ToleranceMm = Annotated[Finite, Field(gt=0, le=100)]
#: an acceptance angle tolerance
ToleranceDeg = Annotated[Finite, Field(gt=0, le=10)]


class Acceptance(Strict):
    """Paper Table 4. The angle rows lost their values in the source: no default."""

    #: Table 4: the largest vertical step between two parts at the joint
    vertical_misalignment_mm: ToleranceMm
    #: Table 4: the largest horizontal step at the joint
    horizontal_misalignment_mm: ToleranceMm
    #: Table 4: the largest gap between the two parts
    max_gap_mm: ToleranceMm
    #: Table 4: horizontal offset of the part from the design axis
    centreline_deviation_x_mm: ToleranceMm
    #: Table 4: vertical offset from the design axis
    centreline_deviation_y_mm: ToleranceMm
    #: pitch limit (lost in the source; none: recorded, not judged)
    pitch_angle_deg: ToleranceDeg | None = None
    #: tilt (roll) limit (none: not judged)
    tilt_angle_deg: ToleranceDeg | None = None
    #: rotation (yaw) limit (none: not judged)
    rotation_angle_deg: ToleranceDeg | None = None


class Task(Strict):
    """The assembly task an adjustment serves (paper)."""

    #: the assembly task's time (paper: 5 min): a plan states its solve time as a share of
    #: it (the paper's Table 2)
    assembly_time_min: Annotated[Finite, Field(gt=0, le=10_000)] = 5.0


# --------------------------------------------------------------------------- walking


class MainFrame(Strict):
    """Main frame M (walking.md section 1): its legs are the lower layer's (``a_M, b_M``
    = the lower layer's half-spans); ``bodies`` its own structure, in the lower
    platform frame."""

    #: M's own structure, in the lower platform's frame
    bodies: tuple[Body, ...] = ()


class SubFrame(Strict):
    """Sub frame S inside M: legs ``sub_leg_1..4`` at ``(x_S + s_i a_S, t_i b_S)`` in M's
    frame; ``bodies`` its structure, in S's frame (origin at the centre of its legs)."""

    #: half the distance between S's legs along x
    half_span_x_m: Annotated[Finite, Field(gt=0, le=20)]
    #: half the distance between S's legs along y
    half_span_y_m: Annotated[Finite, Field(gt=0, le=20)]
    #: S's structure, in S's frame (origin at the centre of its legs)
    bodies: tuple[Body, ...] = ()

    @property
    def a_m(self) -> float:
        return self.half_span_x_m

    @property
    def b_m(self) -> float:
        return self.half_span_y_m


class Frames(Strict):
    main: MainFrame = MainFrame()
    sub: SubFrame


class FootContact(Strict):
    """The invert under one foot: a unilateral spring-damper (walking.md section 6)."""

    #: the invert's stiffness under one foot: the rig's contact, the sequencer's force-loop
    #: gain
    stiffness_n_m: Annotated[Finite, Field(gt=0, le=1e11)] = 2e8
    #: the contact's damping ratio on the foot's own mode
    damping_ratio: Annotated[Finite, Field(ge=0, le=10)] = 0.7


class Walking(Strict):
    """The step-through gait (walking.md sections 2, 3 and 6)."""

    #: one step = one ring
    step_length_mm: Annotated[Finite, Field(gt=0, le=10_000)] = 2000.0
    #: feet clear of the invert when lifted
    clearance_mm: Annotated[Finite, Field(gt=0, le=1000)] = 50.0
    #: travel cylinders: reserve kept at each end of the stroke
    travel_reserve_mm: Annotated[Finite, Field(ge=0, le=10_000)] = 50.0
    #: travel cylinders: speed limit of the pair
    travel_speed_mm_s: Annotated[Finite, Field(gt=0, le=1000)] = 50.0
    #: travel cylinders: acceleration of the pair's trapezoid (the legs keep
    #: ``planner.trajectory.max_rod_accel_mm_s2``)
    travel_accel_mm_s2: Annotated[Finite, Field(gt=0, le=10_000)] = 50.0
    #: touching legs are preloaded to this share of their expected force (phase 3)
    preload_percent: Annotated[Finite, Field(gt=0, le=100)] = 20.0
    #: a releasing leg is unloaded below this share of its standing force (phase 4)
    unloaded_percent: Annotated[Finite, Field(gt=0, le=100)] = 5.0
    #: leg force ramp during preload and transfer (force control)
    force_ramp_kn_s: Annotated[Finite, Field(gt=0, le=10_000)] = 50.0
    #: COG projection to the nearest edge of the standing legs' support, at every instant
    min_stability_margin_m: Annotated[Finite, Field(gt=0, le=20)] = 0.25
    #: travel force below this times the standing legs' total normal force (no slip)
    foot_friction_coefficient: Annotated[Finite, Field(gt=0, le=2)] = 0.4
    contact: FootContact = FootContact()
    #: sync band of a lifting or lowering leg group (walking.md section 5): the group holds
    leg_sync_band_mm: Annotated[Finite, Field(gt=0, le=100)] = 2.0
    #: sync band of the travel pair (on the rods' deviation from their planned
    #: difference while steering, curves.md section 3)
    travel_sync_band_mm: Annotated[Finite, Field(gt=0, le=100)] = 5.0
    #: b_T: the travel pair's rods act at y = -/+ this from the frames' centreline (the
    #: lower can_index on the right, -y); S's yaw in M is asin((e_1 - e_2) / (2 b_T))
    travel_half_span_mm: Annotated[Finite, Field(gt=0, le=10_000)] = 1200.0
    #: S's yaw in M about the rails' pivot at S's centre: the most a step may turn
    max_yaw_deg: Annotated[Finite, Field(gt=0, le=10)] = 1.0
    #: steering back onto the axis: a step turns the machine by the axis's own turn plus at
    #: most this toward the axis (its heading error and its offset over one step)
    max_heading_correction_per_step_deg: Annotated[Finite, Field(ge=0, le=10)] = 0.05
    #: a group out of its band for longer than this: stop, latched
    sync_band_timeout_s: Annotated[Finite, Field(gt=0, le=600)] = 5.0
    #: a leg force above this share of its expected force: stop, latched
    overload_percent: Annotated[Finite, Field(gt=100, le=1000)] = 110.0
    #: the body's roll and pitch change at most this while a transfer moves the load
    #: between the frames (walking.md section 4: the attitude held; ``wara walk``'s goal)
    max_transfer_attitude_change_deg: Annotated[Finite, Field(gt=0, le=1)] = 0.01
    #: a lowering foot has touched down when its cap pressure rose this much
    touch_mpa: Annotated[Finite, Field(gt=0, le=70)] = 1.0
    #: a foot not touched down this far below the expected ground: stop (hole, obstacle)
    touchdown_travel_mm: Annotated[Finite, Field(gt=0, le=1000)] = 10.0
    #: lowering speed from touchdown_travel_mm above the expected ground on; left out:
    #: derived from the legs' stiffness and the pressures' age (``ipc_app.control.tuning``)
    touchdown_speed_mm_s: Annotated[Finite, Field(gt=0, le=1000)] | None = None
    #: preload or transfer not done within this: stop
    transfer_timeout_s: Annotated[Finite, Field(gt=0, le=600)] = 30.0
    #: a receiving leg off its expected share by more than this at the transfer's end: stop
    share_tolerance_percent: Annotated[Finite, Field(gt=0, le=100)] = 15.0
    #: resume check after a stop: rod positions within this of the values at the stop
    resume_height_tolerance_mm: Annotated[Finite, Field(gt=0, le=100)] = 1.0
    #: resume check: leg forces within this of the values at the stop (of the leg's share)
    resume_force_tolerance_percent: Annotated[Finite, Field(gt=0, le=100)] = 10.0
    #: force loop (touch-down, preload, transfer): the LADRC's crossover on the cap-side
    #: force; left out (null): derived from the plant (``ipc_app.control.tuning``)
    force_wc_rad_s: Annotated[Finite, Field(gt=0, le=1000)] | None = None
    #: and its observer's bandwidth; left out (null): derived
    force_wo_rad_s: Annotated[Finite, Field(gt=0, le=1000)] | None = None
    #: the travel pair's turn loop (its rods' half difference, turning the lifted frame
    #: about the pivot: a far heavier mode than the pair's common one): the LADRC's
    #: crossover; left out (null): derived from the plant (``ipc_app.control.tuning``)
    turn_wc_rad_s: Annotated[Finite, Field(gt=0, le=1000)] | None = None
    #: and its observer's bandwidth; left out (null): derived
    turn_wo_rad_s: Annotated[Finite, Field(gt=0, le=1000)] | None = None
    #: the twist-mode controller of a frame standing in position control (travel,
    #: the other frame's lowering and preload): the crossover of its force loop on the
    #: legs' twist, which sets the twist mode's share of their valve commands
    twist_bandwidth_rad_s: Annotated[Finite, Field(gt=0, le=100)] = 6.0
    #: and its observer's bandwidth while the travel pair moves (phases 1, 6): the legs'
    #: twist is measured from pressures up to one pressure cycle (50 ms) old, which an
    #: observer much faster than the loop rings on
    twist_observer_rad_s: Annotated[Finite, Field(gt=0, le=1000)] = 6.0
    #: its observer's bandwidth while the other frame lowers and preloads (2, 3, 7a, 7b):
    #: the feet touching down change the standing frame's twist within a second
    twist_observer_touchdown_rad_s: Annotated[Finite, Field(gt=0, le=1000)] = 16.0

    @property
    def step_length_m(self) -> float:
        return units.mm(self.step_length_mm)

    @property
    def clearance_m(self) -> float:
        return units.mm(self.clearance_mm)

    @property
    def travel_reserve_m(self) -> float:
        return units.mm(self.travel_reserve_mm)

    @property
    def travel_speed_m_s(self) -> float:
        return units.mm(self.travel_speed_mm_s)

    @property
    def travel_accel_m_s2(self) -> float:
        return units.mm(self.travel_accel_mm_s2)

    @property
    def force_ramp_n_s(self) -> float:
        return self.force_ramp_kn_s * units.KN

    @property
    def travel_half_span_m(self) -> float:
        return units.mm(self.travel_half_span_mm)

    @property
    def max_yaw_rad(self) -> float:
        return units.deg(self.max_yaw_deg)

    @property
    def max_heading_correction_per_step_rad(self) -> float:
        return units.deg(self.max_heading_correction_per_step_deg)


# --------------------------------------------------------------------------- placement


class PlacementWeights(Strict):
    """Weights of the target planner's objective (placement.md section 3), each on a
    square in mm^2: the joint step at the face corners, the centreline deviation, the
    gap's distance from its target, and the angles from the design (as mm at the part's
    half-length). Dimensionless; only their ratios matter."""

    #: weight of the joint step at the face corners
    misalignment: Annotated[Finite, Field(ge=0, le=1e6)] = 1.0
    #: weight of the centreline deviation
    centreline_deviation: Annotated[Finite, Field(ge=0, le=1e6)] = 1.0
    #: weight of the gap's distance from its target
    gap: Annotated[Finite, Field(ge=0, le=1e6)] = 1.0
    #: weight of the angles from the design (as mm at the part's half-length)
    angle: Annotated[Finite, Field(ge=0, le=1e6)] = 1.0


class Placement(Strict):
    """Placing an arc part in six degrees of freedom (placement.md; docs/placement.md)."""

    #: r_yaw: the rotation pair acts at this lever arm about the upper platform's z axis
    rotation_lever_arm_m: Annotated[Finite, Field(gt=0, le=20)] = 1.5
    #: the gap the planner aims for between the previous part's front face and the new one's
    target_gap_mm: Annotated[Finite, Field(ge=0, le=100)] = 5.0
    #: steering back: the new part's deviation from the design differs from the
    #: previous part's by at most this per ring (each of y, z; each angle)
    max_correction_per_ring_mm: Annotated[Finite, Field(gt=0, le=100)] = 2.0
    #: the same bound for each angle
    max_correction_per_ring_deg: Annotated[Finite, Field(gt=0, le=10)] = 0.05
    weights: PlacementWeights = PlacementWeights()
    #: a survey fit whose RMS point residual is larger is refused
    survey_max_residual_mm: Annotated[Finite, Field(gt=0, le=100)] = 3.0
    #: sliding friction of the part's carriage on the upper platform: the force the
    #: lateral, rotation and central-axis cylinders need (their pressure check)
    slide_friction_coefficient: Annotated[Finite, Field(ge=0, le=1)] = 0.05

    @property
    def target_gap_m(self) -> float:
        return units.mm(self.target_gap_mm)

    @property
    def max_correction_per_ring_m(self) -> float:
        return units.mm(self.max_correction_per_ring_mm)

    @property
    def max_correction_per_ring_rad(self) -> float:
        return units.deg(self.max_correction_per_ring_deg)

    @property
    def survey_max_residual_m(self) -> float:
        return units.mm(self.survey_max_residual_mm)


# --------------------------------------------------------------------------- project


#: Why a project without the frames and walking sections is refused a walk.
CANNOT_WALK = "the project has no frames and walking sections: it cannot walk"


class ProjectConfig(Strict):
    """A complete tunnel-project parameter set (one YAML file)."""

    project: ProjectInfo
    tunnel: Tunnel
    workpiece: Workpiece
    robot: Robot
    base: Base
    layers: Layers
    cylinders: tuple[Cylinder, ...]
    hydraulics: Hydraulics
    planner: Planner
    control: Control = Control()
    can: CanLink = CanLink()
    safety: Safety = Safety()
    acceptance: Acceptance
    task: Task = Task()
    #: the two frames of the walk; without them (and ``walking``) the machine does not walk
    frames: Frames | None = None
    walking: Walking | None = None
    #: placing the part in six degrees of freedom; needs ``tunnel.alignment``
    placement: Placement | None = None
    #: the ring cycle (walk, place, fix, release, survey, record, walk back); needs placement
    cycle: Cycle | None = None

    @model_validator(mode="after")
    def _placement_needs_alignment(self) -> ProjectConfig:
        if self.placement is not None and self.tunnel.alignment is None:
            raise ValueError("placement needs the design axis: give tunnel.alignment")
        if self.cycle is not None and self.placement is None:
            raise ValueError("cycle needs the placement section (the cycle places the part)")
        if self.cycle is not None and self.cycle.walk_steps > 0 and self.walking is None:
            raise ValueError("cycle.walk_steps > 0 needs the frames and walking sections")
        return self

    opcua: OpcUa = OpcUa()

    @property
    def walks(self) -> bool:
        """Whether the project has the frames and walking sections (they go together)."""
        return self.frames is not None and self.walking is not None

    def walking_sections(self) -> tuple[Frames, Walking]:
        """The frames and walking sections; ValueError (:data:`CANNOT_WALK`) without."""
        if self.frames is None or self.walking is None:
            raise ValueError(CANNOT_WALK)
        return self.frames, self.walking

    @model_validator(mode="after")
    def _inventory(self) -> ProjectConfig:
        ids = Counter(c.id for c in self.cylinders)
        dup = sorted(k for k, n in ids.items() if n > 1)
        if dup:
            raise ValueError(f"duplicate cylinder id(s): {', '.join(dup)}")
        idx = Counter(c.can_index for c in self.cylinders)
        dup_idx = sorted(k for k, n in idx.items() if n > 1)
        if dup_idx:
            raise ValueError(f"duplicate cylinder can_index(es): {dup_idx}")
        roles = Counter(c.role for c in self.cylinders)
        if dict(roles) != ROLE_COUNTS:
            raise ValueError(
                f"the machine has {N_CYLINDERS} cylinders {ROLE_COUNTS}; got {dict(roles)}"
            )
        unknown_groups = sorted(set(self.can.active_groups) - {c.group for c in self.cylinders})
        if unknown_groups:
            raise ValueError(
                f"can.active_groups: unknown cylinder group(s) {unknown_groups}; "
                f"groups are {sorted({c.group for c in self.cylinders})}"
            )
        if (self.frames is None) != (self.walking is None):
            raise ValueError("frames and walking go together: give both sections or neither")
        if self.walking is not None:
            travel = [c for c in self.cylinders if c.role == "travel"]
            usable_mm = min(c.stroke_mm for c in travel) - 2 * self.walking.travel_reserve_mm
            if self.walking.step_length_mm > usable_mm:
                raise ValueError(
                    f"walking.step_length_mm ({self.walking.step_length_mm}) must fit in the "
                    f"travel stroke less both reserves ({usable_mm} mm)"
                )
        by_id = {c.id: c for c in self.cylinders}
        for name, layer, ok_roles in (
            ("lower", self.layers.lower, ("main_leg", "sub_leg")),
            ("upper", self.layers.upper, ("upper_attitude",)),
        ):
            for pos, cid in enumerate(layer.cylinders, start=1):
                if cid not in by_id:
                    raise ValueError(f"layers.{name}.cylinders: unknown cylinder id {cid!r}")
                cyl = by_id[cid]
                if cyl.role not in ok_roles:
                    raise ValueError(
                        f"layers.{name}.cylinders: {cid!r} has role {cyl.role!r}, "
                        f"expected one of {ok_roles}"
                    )
                if cyl.position != pos:
                    raise ValueError(
                        f"layers.{name}.cylinders: {cid!r} is listed at position {pos} "
                        f"but its position is {cyl.position}"
                    )
                if (cyl.bore_mm, cyl.rod_mm, cyl.stroke_mm) != (
                    layer.bore_mm,
                    layer.rod_mm,
                    layer.stroke_mm,
                ):
                    raise ValueError(
                        f"layers.{name}.cylinders: {cid!r} bore/rod/stroke "
                        f"{(cyl.bore_mm, cyl.rod_mm, cyl.stroke_mm)} differ from the layer's "
                        f"{(layer.bore_mm, layer.rod_mm, layer.stroke_mm)}"
                    )
        return self

    @model_validator(mode="after")
    def _workpiece_mass(self) -> ProjectConfig:
        if self.workpiece.mass_kg is None and self.workpiece_body is None:
            raise ValueError(
                f"workpiece.mass_kg: give it, or a body named {WORKPIECE_BODY!r} on the upper "
                "layer (layers.upper.bodies) whose mass it is"
            )
        return self

    @property
    def reference_height_m(self) -> float:
        """The height of a part's reference point (its bottom-face centre) above the
        design centreline: on the invert, the inner radius below the axis."""
        return -self.tunnel.inner_radius_m

    @property
    def workpiece_body(self) -> Body | None:
        """The upper layer's body named :data:`WORKPIECE_BODY`, if it has one."""
        return next((b for b in self.layers.upper.bodies if b.name == WORKPIECE_BODY), None)

    @property
    def workpiece_mass_kg(self) -> float:
        """The arc part's mass: its body's on the upper layer, else ``workpiece.mass_kg``."""
        body = self.workpiece_body
        if body is not None:
            return body.mass_kg
        assert self.workpiece.mass_kg is not None  # _workpiece_mass
        return self.workpiece.mass_kg

    def cylinder(self, cylinder_id: str) -> Cylinder:
        for c in self.cylinders:
            if c.id == cylinder_id:
                return c
        raise KeyError(f"no cylinder {cylinder_id!r} in the inventory")

    def plant_of(self, cylinder: Cylinder) -> CylinderPlant:
        """The cylinder's own plant parameters, or the hydraulics defaults."""
        return cylinder.plant if cylinder.plant is not None else self.hydraulics.cylinder_defaults

    @property
    def cylinders_by_can_index(self) -> tuple[Cylinder, ...]:
        return tuple(sorted(self.cylinders, key=lambda c: c.can_index))
