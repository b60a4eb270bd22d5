"""Schema of simulation scenarios (``config/scenarios/*.yaml``).

A scenario is a self-contained study: the hydraulic supply, the cylinders with their
paper parameters and loads, the reference, disturbances, sensors, the controllers'
settings and the goals the study checks. Same rules as the project schema: unknown
keys are errors, engineering units in key names, SI through properties.
"""

from __future__ import annotations

import itertools
from importlib import resources
from pathlib import Path
from typing import Annotated

from pydantic import Field, model_validator

from config import units
from config.loader import load_model
from config.schema import Cylinder, Hydraulics, Ladrc, NonNegative, Pid, Positive, Strict, Sync


class StudyCylinder(Strict):
    """One cylinder of the study: geometry and Table-3 plant, plus the load it carries."""

    cylinder: Cylinder
    #: constant force opposing extension (the weight of what the rod lifts), kN
    load_force_kn: float

    @model_validator(mode="after")
    def _has_plant(self) -> StudyCylinder:
        if self.cylinder.plant is None:
            raise ValueError(f"cylinder {self.cylinder.id!r}: a study cylinder needs its plant")
        return self

    @property
    def load_force_n(self) -> float:
        return self.load_force_kn * units.KN


class ReferenceProfile(Strict):
    """Rod position reference: waypoints ``[t_s, position_mm]`` joined by quintic blends
    (zero speed and acceleration at every waypoint); constant after the last one."""

    waypoints: tuple[tuple[float, float], ...] = Field(min_length=1)

    @model_validator(mode="after")
    def _increasing(self) -> ReferenceProfile:
        times = [t for t, _ in self.waypoints]
        if times[0] != 0:
            raise ValueError(f"the first waypoint must be at t_s = 0, got {times[0]}")
        if any(b <= a for a, b in itertools.pairwise(times)):
            raise ValueError(f"waypoint times must increase strictly, got {times}")
        return self


class ForceNoise(Strict):
    """Band-limited random load force on each cylinder (independent), from ``start_s``."""

    start_s: NonNegative
    rms_kn: NonNegative
    bandwidth_hz: Positive
    seed: int = 0

    @property
    def rms_n(self) -> float:
        return self.rms_kn * units.KN


class LoadStepSpec(Strict):
    t_s: NonNegative
    cylinder: Annotated[int, Field(ge=0)]
    delta_kn: float


class Sensors(Strict):
    position_resolution_um: NonNegative = 1.0
    position_noise_um: NonNegative = 1.0
    pressure_resolution_kpa: NonNegative = 1.0
    pressure_noise_kpa: NonNegative = 10.0
    seed: int = 0

    @property
    def position_resolution_m(self) -> float:
        return units.um(self.position_resolution_um)

    @property
    def position_noise_m(self) -> float:
        return units.um(self.position_noise_um)

    @property
    def pressure_resolution_pa(self) -> float:
        return units.kpa(self.pressure_resolution_kpa)

    @property
    def pressure_noise_pa(self) -> float:
        return units.kpa(self.pressure_noise_kpa)


class StudyControl(Strict):
    rate_hz: Annotated[float, Field(gt=0, le=10_000)] = 1000.0
    ladrc: Ladrc = Ladrc()
    pid: Pid = Pid()
    sync: Sync = Sync()

    @property
    def period_s(self) -> float:
        return 1.0 / self.rate_hz


class StudyGoals(Strict):
    #: the paper's synchronization accuracy, after the transient, noise included
    sync_error_max_mm: Positive = 0.07
    #: PID's sync_error_max_mm must exceed LADRC's by at least this factor
    min_pid_to_ladrc_ratio: Positive = 1.5
    #: simulated seconds per wall-clock second
    min_realtime_factor: Positive = 20.0


class DualCylinderScenario(Strict):
    """The paper's parallel-cylinder synchronization study (model.md section 10)."""

    name: str = Field(min_length=1)
    description: str = ""
    duration_s: Positive
    #: metrics are taken from here on (the initial transient is left out)
    transient_s: NonNegative
    plant_step_ms: Annotated[float, Field(ge=0.05, le=0.5)] = 0.5
    #: tracking-error band for the settling time after the last reference move
    settle_band_mm: Positive = 0.1
    hydraulics: Hydraulics
    cylinders: tuple[StudyCylinder, ...] = Field(min_length=2, max_length=4)
    reference: ReferenceProfile
    noise: ForceNoise | None = None
    load_steps: tuple[LoadStepSpec, ...] = ()
    sensors: Sensors = Sensors()
    control: StudyControl = StudyControl()
    goals: StudyGoals = StudyGoals()

    @model_validator(mode="after")
    def _consistent(self) -> DualCylinderScenario:
        if self.transient_s >= self.duration_s:
            raise ValueError(
                f"transient_s ({self.transient_s}) must be shorter than duration_s "
                f"({self.duration_s})"
            )
        ratio = self.control.period_s / self.plant_step_s
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"the control period ({self.control.period_s} s) must be a whole number of "
                f"plant steps ({self.plant_step_ms} ms)"
            )
        for i, c in enumerate(self.cylinders):
            lo, hi = 0.0, c.cylinder.stroke_mm
            for t, pos in self.reference.waypoints:
                if not lo <= pos <= hi:
                    raise ValueError(
                        f"reference waypoint at t_s = {t}: {pos} mm is outside the stroke of "
                        f"cylinders[{i}] ({c.cylinder.id}: 0 .. {hi} mm)"
                    )
        for step in self.load_steps:
            if step.cylinder >= len(self.cylinders):
                raise ValueError(
                    f"load step at t_s = {step.t_s}: cylinder {step.cylinder} does not exist "
                    f"(0 .. {len(self.cylinders) - 1})"
                )
        return self

    @property
    def plant_step_s(self) -> float:
        return units.ms(self.plant_step_ms)


def scenario_path(name: str) -> Path:
    """A shipped scenario by name, e.g. ``scenario_path("dual_cylinder")``."""
    return Path(str(resources.files("config") / "scenarios" / f"{name}.yaml"))


def load_scenario(path: str | Path | None = None) -> DualCylinderScenario:
    """Load a scenario YAML; ``None`` means the shipped ``dual_cylinder.yaml``."""
    return load_model(
        DualCylinderScenario, scenario_path("dual_cylinder") if path is None else path
    )
