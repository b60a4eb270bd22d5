"""The part's release (placement.md section 4; docs/placement.md, "The release").

Once the operator has confirmed the part bolted to its ring, the upper layer's four
cylinders lower together, position-controlled with synchronization as every attitude
move (the :class:`~ipc_app.control.attitude.AttitudeController`'s sync groups, the lower
layer held), their references moving down at ``cycle.release_speed_mm_s`` from where the
placed pose's hold stood (:meth:`AttitudeController.move_layer`: no reset, bumpless),
until the part's load is off the platform:

1. ``lowering``: until every upper cylinder's load pressure (its rod force
   ``p_A A_A - p_B A_B`` over its cap area: model.md section 5's cap pressure) has stayed
   within ``cycle.platform_pressure_tolerance_mpa`` of its empty-platform value for
   :data:`RELEASED_FOR_S`. The empty-platform value (:func:`platform_pressures_pa`): the
   statics of the platform without the workpiece at the layers' measured attitudes
   (:meth:`~ipc_app.model.statics.MachineStatics.upper_cylinder_forces`), less each
   rod's friction while it lowers at the release speed (its plant's Coulomb friction and
   viscous damping: the pressures carry the platform less what the friction holds);
2. ``clearance``: a further ``cycle.release_clearance_mm`` at the same speed, then
   :data:`SETTLE_S` of holding; then ``done`` (the caller stops: valves closed).

Not released when the rods have lowered ``cycle.release_max_travel_mm`` (the bolts not
holding, or the part not fixed: its weight is still on the platform):
:attr:`ReleaseSequencer.out_of_travel`, the service's ``release`` interlock (a latched
stop, the part still on the platform, held).

Work per cycle is bounded: one path sample, eight controller updates, four pressures.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from config import units
from config.derived import viscous_damping_n_s_m
from config.schema import ProjectConfig
from ipc_app.control.attitude import AttitudeController
from ipc_app.model.kinematics import fit_layer
from ipc_app.model.statics import MachineStatics

FloatArray = NDArray[np.float64]

#: The phases, in order.
PHASES: tuple[str, ...] = ("lowering", "clearance")
#: Every load pressure within the tolerance this long before the part counts as off (s).
RELEASED_FOR_S = 0.1
#: After the clearance's lowering, the hold settles this long before the release is done.
SETTLE_S = 0.5


def upper_index(cfg: ProjectConfig) -> list[int]:
    """can_index of the upper layer's cylinders 1..4."""
    return [cfg.cylinder(c).can_index for c in cfg.layers.upper.cylinders]


def upper_cap_areas_m2(cfg: ProjectConfig) -> FloatArray:
    """The upper cylinders' cap areas (4,), m^2, in the layer's order."""
    return np.array([cfg.cylinder(c).cap_area_m2 for c in cfg.layers.upper.cylinders])


def load_pressures_pa(cfg: ProjectConfig, p: FloatArray) -> FloatArray:
    """The upper cylinders' load pressures (4,), Pa: ``(p_A A_A - p_B A_B) / A_A`` from
    the chamber pressures ``p`` (19, 2)."""
    out = np.zeros(4)
    for k, cid in enumerate(cfg.layers.upper.cylinders):
        c = cfg.cylinder(cid)
        i = c.can_index
        out[k] = (p[i, 0] * c.cap_area_m2 - p[i, 1] * c.rod_area_m2) / c.cap_area_m2
    return out


def platform_pressures_pa(
    cfg: ProjectConfig, x_rod_m: FloatArray, unloaded: bool, lowering_speed_m_s: float = 0.0
) -> FloatArray:
    """The upper cylinders' load pressures (4,), Pa, that the statics expect at the
    layers' attitudes fitted to the rods ``x_rod_m`` (19, from retracted): the platform
    with the part (``unloaded`` False) or without it, at rest or lowering at
    ``lowering_speed_m_s`` (each rod's friction then holds part of the load: its
    plant's Coulomb friction and its viscous damping at that speed)."""
    by_index = cfg.cylinders_by_can_index
    fits = {}
    for name in ("lower", "upper"):
        layer = getattr(cfg.layers, name)
        idx = [cfg.cylinder(c).can_index for c in layer.cylinders]
        d = np.asarray([x_rod_m[i] - by_index[i].stroke_m / 2 for i in idx])
        fits[name] = fit_layer(d, layer.a_m, layer.b_m)
    lo, up = fits["lower"], fits["upper"]
    force = MachineStatics(cfg, unloaded=unloaded).upper_cylinder_forces(
        float(lo.roll), float(lo.pitch), float(up.roll), float(up.pitch)
    )
    out = np.zeros(4)
    for k, cid in enumerate(cfg.layers.upper.cylinders):
        c = cfg.cylinder(cid)
        plant = cfg.plant_of(c)
        friction = 0.0
        if lowering_speed_m_s > 0:
            viscous = viscous_damping_n_s_m(c, plant, cfg.hydraulics)
            friction = plant.coulomb_friction_n + viscous * lowering_speed_m_s
        out[k] = (float(force[k]) - friction) / c.cap_area_m2
    return out


@dataclass
class ReleaseFigures:
    """What the release has done so far (SI; pressures of cylinders 1..4)."""

    #: the upper rods' mean lowering from the start, measured, m
    travel_m: float = 0.0
    #: the lowering at which the load was off the platform (None: not yet), m
    released_at_m: float | None = None
    #: the load pressures at the start, when the load was off, and now, Pa
    start_pressure_pa: list[float] = field(default_factory=list)
    released_pressure_pa: list[float] = field(default_factory=list)
    load_pressure_pa: list[float] = field(default_factory=list)
    #: the empty platform's, lowering at the release speed (what the check compares
    #: with), and at rest (the statics alone), Pa
    empty_pressure_pa: list[float] = field(default_factory=list)
    empty_at_rest_pa: list[float] = field(default_factory=list)
    #: the largest |load pressure - empty (lowering)| now, and whose (index 0..3)
    excess_pa: float = 0.0
    worst: int = 0

    def to_dict(self) -> dict[str, object]:
        mpa = units.to_mpa
        return {
            "travel_mm": units.to_mm(self.travel_m),
            "released_at_mm": (
                None if self.released_at_m is None else units.to_mm(self.released_at_m)
            ),
            "start_pressure_mpa": [mpa(v) for v in self.start_pressure_pa],
            "released_pressure_mpa": [mpa(v) for v in self.released_pressure_pa],
            "load_pressure_mpa": [mpa(v) for v in self.load_pressure_pa],
            "empty_pressure_mpa": [mpa(v) for v in self.empty_pressure_pa],
            "empty_at_rest_mpa": [mpa(v) for v in self.empty_at_rest_pa],
            "excess_mpa": mpa(self.excess_pa),
        }


class ReleaseSequencer:
    """Runs one release: lowering until the load is off, then the clearance."""

    def __init__(
        self,
        cfg: ProjectConfig,
        attitude: AttitudeController,
        empty_pressure_pa: FloatArray,
        empty_at_rest_pa: FloatArray | None = None,
    ) -> None:
        """``empty_pressure_pa``: the empty platform's load pressures lowering at the
        release speed (:func:`platform_pressures_pa`), what the release waits for;
        ``empty_at_rest_pa``: at rest (for the figures)."""
        if cfg.cycle is None:
            raise ValueError("the project has no cycle section: it cannot release")
        c = cfg.cycle
        self.cfg = cfg
        self.attitude = attitude
        self.upper = upper_index(cfg)
        self.speed_m_s = c.release_speed_m_s
        self.tolerance_pa = c.platform_pressure_tolerance_pa
        self.clearance_m = c.release_clearance_m
        self.max_travel_m = c.release_max_travel_m
        rest = [] if empty_at_rest_pa is None else [float(v) for v in empty_at_rest_pa]
        self.figures = ReleaseFigures(
            empty_pressure_pa=[float(v) for v in empty_pressure_pa], empty_at_rest_pa=rest
        )
        self._empty = np.asarray(empty_pressure_pa, dtype=float)
        self.phase = 0
        self.done = False
        #: the rods lowered the whole ``release_max_travel_mm`` with the load on
        self.out_of_travel = False
        self.phase_started_s = 0.0
        #: machine time of each finished phase (s), by name
        self.phase_times_s: dict[str, float] = {}
        self._x0 = 0.0
        self._within_since: float | None = None
        self._ended_at: float | None = None

    @property
    def phase_name(self) -> str:
        return "done" if self.done else PHASES[self.phase]

    def check(self, x_rod_m: FloatArray) -> list[str]:
        """Why the release cannot start here (empty: it can): each upper rod needs the
        whole travel and the clearance above its retracted end, plus the stroke-end
        margin."""
        margin = units.mm(self.cfg.safety.stroke_end_margin_mm)
        need = self.max_travel_m + self.clearance_m + margin
        out = []
        for i in self.upper:
            if not float(x_rod_m[i]) >= need:
                cid = self.cfg.cylinders_by_can_index[i].id
                out.append(
                    f"stroke: {cid} at {units.to_mm(float(x_rod_m[i])):.1f} mm from its "
                    f"retracted end; the release needs {units.to_mm(need):.1f} mm (the "
                    "travel, the clearance and the stroke-end margin)"
                )
        return out

    def start(self, t_now: float, x_rod_m: FloatArray, p: FloatArray) -> None:
        """Start lowering from where the hold's references stand."""
        self._x0 = float(np.mean(np.asarray(x_rod_m)[self.upper]))
        self.figures.start_pressure_pa = load_pressures_pa(self.cfg, p).tolist()
        down = self.max_travel_m + self.clearance_m  # the rods trip at the travel
        self.attitude.move_layer(t_now, "upper", -down, self.speed_m_s)
        self.phase = 0
        self.phase_started_s = t_now

    def resume(self, shift_s: float) -> None:
        """After a hold or suspension: the phase's clock shifted by the time stopped (the
        path is shifted by its owner, :meth:`AttitudeController.resume`)."""
        self.phase_started_s += shift_s
        self._within_since = None
        if self._ended_at is not None:
            self._ended_at += shift_s

    def update(self, t_now: float, x_rod_m: FloatArray, p: FloatArray, p_valid: bool) -> FloatArray:
        """Valve commands (19 values in [-1, 1]) for this cycle; advances the phase."""
        att = self.attitude
        x = np.asarray(x_rod_m, dtype=float)
        u = att.update(t_now, x)
        fig = self.figures
        fig.travel_m = self._x0 - float(np.mean(x[self.upper]))
        lp = load_pressures_pa(self.cfg, p)
        fig.load_pressure_pa = lp.tolist()
        off = np.abs(lp - self._empty)
        fig.worst = int(np.argmax(off))
        fig.excess_pa = float(off[fig.worst])
        if self.done or self.out_of_travel:
            return u
        if self.phase == 0:
            within = p_valid and bool(np.all(off <= self.tolerance_pa))
            if not within:
                self._within_since = None
            elif self._within_since is None:
                self._within_since = t_now
            if self._within_since is not None and t_now - self._within_since >= RELEASED_FOR_S:
                fig.released_at_m = fig.travel_m
                fig.released_pressure_pa = lp.tolist()
                self.phase_times_s[PHASES[0]] = t_now - self.phase_started_s
                att.move_layer(t_now, "upper", -self.clearance_m, self.speed_m_s)
                self.phase = 1
                self.phase_started_s = t_now
            elif fig.travel_m >= self.max_travel_m or att.motion_done(t_now):
                self.out_of_travel = True
                att.hold(att.references(t_now))
        else:
            if self._ended_at is None and att.motion_done(t_now):
                self._ended_at = t_now
                att.hold(att.final_references())
            if self._ended_at is not None and t_now - self._ended_at >= SETTLE_S:
                self.phase_times_s[PHASES[1]] = t_now - self.phase_started_s
                self.done = True
        return u
