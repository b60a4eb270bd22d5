"""Schema of HIL scenarios (``wara hil --scenario FILE``, docs/hil.md).

A HIL scenario says how the stand-in rig is simulated (integration step, PLC scan,
sensors) and what happens when: operator events (E-stop, an HMI target request) and
injected faults (on the CAN wire, in the sensors, in the hydraulics). It names
cylinders by their ``id`` and CAN messages by DBC name patterns (``PLC_RodPos_*``);
both are checked against the project when the simulator is built.

Same rules as the project schema: unknown keys are errors, engineering units in the
key names, SI through properties, errors that name the file and the key.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, model_validator

from config import units
from config.loader import load_model
from config.schema import NonNegative, Positive, ProjectConfig, Strict, Vec3

Fraction = Annotated[float, Field(ge=0, le=1)]


class PlantSettings(Strict):
    """Numerical and rig choices the project YAML does not carry."""

    #: RK4 step of the hydraulics and the platforms (0.1 .. 0.5 ms, model.md section 9)
    step_ms: Annotated[float, Field(ge=0.1, le=0.5)] = 0.25
    #: PLC scan: commands read, faults applied, sensors written once per scan
    plc_cycle_ms: Annotated[float, Field(ge=0.1, le=10)] = 1.0
    #: the simulator's rod mass when it is to differ from the machine's (a model error of
    #: the truth, e.g. in a campaign); None: the project's ``hydraulics.rod_mass_kg``
    rod_mass_kg: Positive | None = None

    def rod_mass_for(self, cfg: ProjectConfig) -> float:
        """The rod mass the rig simulates: this override, else the project's."""
        return cfg.hydraulics.rod_mass_kg if self.rod_mass_kg is None else self.rod_mass_kg

    #: pilot-operated check valves on the attitude cylinders: while the PLC has the
    #: drives off, the cylinder ports are blocked (no valve flow, no leakage to tank)
    load_holding_valves: bool = True
    #: a limit switch closes this close to either end of the stroke
    limit_switch_mm: Positive = 2.0
    #: the walking rig: the body on its eight legs with foot contact on the invert, both
    #: frames in world x (hil_sim/walking.py; needs the project's frames and walking)
    contact: bool = False

    @property
    def step_s(self) -> float:
        return units.ms(self.step_ms)

    @property
    def plc_cycle_s(self) -> float:
        return units.ms(self.plc_cycle_ms)

    @property
    def limit_switch_m(self) -> float:
        return units.mm(self.limit_switch_mm)

    @model_validator(mode="after")
    def _whole_steps(self) -> PlantSettings:
        ratio = self.plc_cycle_ms / self.step_ms
        if abs(ratio - round(ratio)) > 1e-9:
            raise ValueError(
                f"plc_cycle_ms ({self.plc_cycle_ms}) must be a whole number of "
                f"step_ms ({self.step_ms})"
            )
        return self


class PositionSensors(Strict):
    resolution_um: NonNegative = 1.0
    noise_um: NonNegative = 1.0
    sample_ms: Positive = 1.0


class PressureSensors(Strict):
    resolution_kpa: NonNegative = 5.0
    noise_kpa: NonNegative = 10.0
    sample_ms: Positive = 1.0


class SensorSettings(Strict):
    position: PositionSensors = PositionSensors()
    pressure: PressureSensors = PressureSensors()


# --------------------------------------------------------------------------- events


class _Timed(Strict):
    #: simulated time the event starts
    start_s: NonNegative = 0.0
    #: simulated time it ends (null: until the end of the run)
    end_s: NonNegative | None = None

    @model_validator(mode="after")
    def _order(self) -> _Timed:
        if self.end_s is not None and self.end_s <= self.start_s:
            raise ValueError(f"end_s ({self.end_s}) must be after start_s ({self.start_s})")
        return self

    def active(self, t_s: float) -> bool:
        return t_s >= self.start_s - 1e-12 and (self.end_s is None or t_s < self.end_s - 1e-12)


class EStop(_Timed):
    """The E-stop circuit opens at ``start_s`` and is released at ``end_s``."""

    kind: Literal["estop"]


class HmiTargetEvent(Strict):
    """The operator sends a target attitude of the workpiece plane from the HMI, a cancel,
    or a walk of ``walk_steps`` steps (the frame's ``WalkSteps``: 0..3; 0 with ``walk``
    is the malformed request the service refuses)."""

    kind: Literal["hmi_target"]
    at_s: NonNegative
    roll_deg: Annotated[float, Field(ge=-45, le=45)] = 0.0
    pitch_deg: Annotated[float, Field(ge=-45, le=45)] = 0.0
    request: Literal["new_target", "cancel", "walk"] = "new_target"
    walk_steps: Annotated[int, Field(ge=0, le=3)] = 0


class PlcSilent(_Timed):
    """The PLC stops: nothing is sent, nothing is read, the valves drop to centre."""

    kind: Literal["plc_silent"]


class IgnoreCommands(_Timed):
    """The PLC looks healthy on the wire but does not apply the IPC's valve commands."""

    kind: Literal["ignore_commands"]


Direction = Literal["plc_to_ipc", "ipc_to_plc", "both"]


class _Stall(_Timed):
    @model_validator(mode="after")
    def _bounded(self) -> _Stall:
        if self.end_s is None:
            raise ValueError("a stall needs end_s (a stall without end is plc_silent)")
        return self


class PlcStall(_Stall):
    """The PLC's scan stops from ``start_s`` to ``end_s``: no scan, nothing read or sent;
    the output card's watchdog centres the spools and closes the load-holding valves.
    The plant goes on. Afterwards the PLC reads what queued up and scans again."""

    kind: Literal["plc_stall"]


class WireStall(_Stall):
    """The wire holds frames (``direction``, ``messages`` as the wire faults) from
    ``start_s`` to ``end_s`` and then delivers them, in order."""

    kind: Literal["wire_stall"]
    messages: tuple[str, ...] = ()
    direction: Direction = "both"


class _WireFault(_Timed):
    #: DBC message names or fnmatch patterns; empty: every message of the direction
    messages: tuple[str, ...] = ()
    direction: Direction = "plc_to_ipc"


class DropFrames(_WireFault):
    """Each frame is lost with probability ``rate`` (seeded); with ``max_burst``, at most
    that many frames of one message in a row (the next one gets through: the isolated
    losses of a healthy bus)."""

    kind: Literal["drop"]
    rate: Fraction
    max_burst: Annotated[int, Field(ge=1, le=1000)] | None = None


class DelayFrames(_WireFault):
    """Each frame reaches the bus ``delay_ms`` late (order kept)."""

    kind: Literal["delay"]
    delay_ms: Positive

    @property
    def delay_s(self) -> float:
        return units.ms(self.delay_ms)


class CorruptCrc(_WireFault):
    """Each frame's CRC byte is inverted with probability ``rate``."""

    kind: Literal["bad_crc"]
    rate: Fraction = 1.0


class FreezeCounter(_WireFault):
    """The alive counter stops at its last value (CRC recomputed: only the counter is wrong)."""

    kind: Literal["frozen_counter"]


class BusOff(_Timed):
    """The bus goes off: no frame either way; error frames report bus-off and the restart."""

    kind: Literal["bus_off"]


SensorQuantity = Literal["position", "cap_pressure", "rod_pressure"]


class SensorFault(_Timed):
    """One transducer: ``stuck`` at its last reading, ``noisy`` (extra white noise),
    ``jump`` (an offset), or ``fail`` (sent as SENSOR_FAULT)."""

    kind: Literal["sensor"]
    cylinder: str
    quantity: SensorQuantity = "position"
    mode: Literal["stuck", "noisy", "jump", "fail"]
    #: extra noise (rms) for ``noisy``: mm for positions, MPa for pressures
    noise: NonNegative = 0.0
    #: offset for ``jump``: mm for positions, MPa for pressures
    offset: float = 0.0


class Leakage(_Timed):
    """A worn piston seal: the cylinder's internal leakage becomes this."""

    kind: Literal["leakage"]
    cylinder: str
    internal_leakage_m3_s_pa: Positive


class StuckValve(_Timed):
    """The spool sticks: at ``opening`` (normalized, -1..1), or where it is when it sticks."""

    kind: Literal["stuck_valve"]
    cylinder: str
    opening: Annotated[float, Field(ge=-1, le=1)] | None = None


class LoadStep(_Timed):
    """Extra load: a mass set down on a platform (``layer``, ``mass_kg``, ``cog_m`` in
    the platform frame) or a force against one cylinder (``cylinder``, ``force_kn``,
    positive opposing extension)."""

    kind: Literal["load_step"]
    layer: Literal["lower", "upper"] | None = None
    mass_kg: NonNegative = 0.0
    cog_m: Vec3 = (0.0, 0.0, 0.0)
    cylinder: str | None = None
    force_kn: float = 0.0

    @model_validator(mode="after")
    def _one_target(self) -> LoadStep:
        if (self.layer is None) == (self.cylinder is None):
            raise ValueError("a load step names either a layer (mass_kg, cog_m) or a cylinder")
        return self

    @property
    def force_n(self) -> float:
        return self.force_kn * units.KN


class GroundOffset(_Timed):
    """The invert raised (``offset_mm`` > 0) or lowered (< 0, a hole) over a rectangle of
    world x and y (base frame): a step at the previous ring's joint, a hole under a foot.
    Needs ``plant.contact``."""

    kind: Literal["ground"]
    x_from_m: Annotated[float, Field(ge=-1000, le=1000)]
    x_to_m: Annotated[float, Field(ge=-1000, le=1000)]
    y_from_m: Annotated[float, Field(ge=-100, le=100)] = -100.0
    y_to_m: Annotated[float, Field(ge=-100, le=100)] = 100.0
    offset_mm: Annotated[float, Field(ge=-10_000, le=1000)]

    @model_validator(mode="after")
    def _extent(self) -> GroundOffset:
        if self.x_to_m <= self.x_from_m or self.y_to_m <= self.y_from_m:
            raise ValueError("x_to_m and y_to_m must be above x_from_m and y_from_m")
        return self

    @property
    def row(self) -> tuple[float, float, float, float, float]:
        return (self.x_from_m, self.x_to_m, self.y_from_m, self.y_to_m, units.mm(self.offset_mm))


class FootSlip(_Timed):
    """A frame's feet on a slippery invert: its friction coefficient becomes this.
    Needs ``plant.contact``."""

    kind: Literal["foot_slip"]
    frame: Literal["main", "sub"]
    friction_coefficient: Annotated[float, Field(ge=0, le=2)]


class HoldingValveLeak(_Timed):
    """A cylinder's load-holding valve leaks: both chambers leak to tank past it, also
    while it is closed (``leakage_m3_s_pa``, on top of the cylinder's own leakage)."""

    kind: Literal["holding_valve_leak"]
    cylinder: str
    leakage_m3_s_pa: Annotated[float, Field(gt=0, le=1e-8)]


Event = Annotated[
    EStop
    | HmiTargetEvent
    | PlcSilent
    | PlcStall
    | WireStall
    | IgnoreCommands
    | DropFrames
    | DelayFrames
    | CorruptCrc
    | FreezeCounter
    | BusOff
    | SensorFault
    | Leakage
    | StuckValve
    | LoadStep
    | GroundOffset
    | FootSlip
    | HoldingValveLeak,
    Field(discriminator="kind"),
]

#: every ``kind`` an event may have, for the CLI's ``--fault`` help
EVENT_KINDS: tuple[str, ...] = (
    "estop",
    "hmi_target",
    "plc_silent",
    "plc_stall",
    "wire_stall",
    "ignore_commands",
    "drop",
    "delay",
    "bad_crc",
    "frozen_counter",
    "bus_off",
    "sensor",
    "leakage",
    "stuck_valve",
    "load_step",
    "ground",
    "foot_slip",
    "holding_valve_leak",
)


class HilScenario(Strict):
    name: str = "default"
    description: str = ""
    #: how long ``wara hil`` runs when no ``--duration`` is given (null: until stopped)
    duration_s: Positive | None = None
    seed: int = 0
    plant: PlantSettings = PlantSettings()
    sensors: SensorSettings = SensorSettings()
    events: tuple[Event, ...] = ()


def load_hil_scenario(path: str | Path | None = None) -> HilScenario:
    """Load a HIL scenario YAML; ``None`` means the defaults (no events)."""
    return HilScenario() if path is None else load_model(HilScenario, path)
