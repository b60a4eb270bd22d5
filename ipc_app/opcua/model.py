"""The OPC UA information model as data: every variable, where it sits, its unit, and
how its value is read from the service's status (``wara ctl status``).

No asyncua here: :mod:`ipc_app.opcua.server` builds the address space from
:func:`variables` and writes :func:`values` of each status it takes. Values are SI
(metres, radians, pascals, seconds); the status's millimetres, degrees and milliseconds
are converted through :mod:`config.units`. docs/opcua.md has the table.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from config import units
from config.schema import ProjectConfig
from ipc_app.service.interlocks import Interlock
from ipc_app.service.modes import PACKML_STATES, UNIT_MODES, UnitMode

#: The namespaces of the model (the companion specifications' URIs, and ours).
NS_DI = "http://opcfoundation.org/UA/DI/"
NS_MACHINERY = "http://opcfoundation.org/UA/Machinery/"
NS_PACKML = "http://opcfoundation.org/UA/PackML/"
NS_WARA = "urn:wara:ipc"
#: the companion specifications' namespaces (their NodeSets are loaded)
COMPANIONS = (NS_DI, NS_MACHINERY, NS_PACKML)

#: The objects under the machine that are instances of a companion type: path ->
#: (namespace of the browse name, namespace of the type, the type's numeric id in it).
TYPED: dict[tuple[str, ...], tuple[str, str, int]] = {
    ("Identification",): (NS_DI, NS_MACHINERY, 1012),  # MachineIdentificationType
    ("MachineryBuildingBlocks", "MachineryItemState"): (
        NS_MACHINERY,
        NS_MACHINERY,
        1002,  # MachineryItemState_StateMachineType
    ),
    ("MachineryBuildingBlocks", "MachineryOperationMode"): (
        NS_MACHINERY,
        NS_MACHINERY,
        1008,  # MachineryOperationModeStateMachineType
    ),
    # OPC 30050: its Status (PackMLStatusObjectType), its BaseStateMachine with the
    # MachineState and ExecuteState sub-machines, Admin, and the type's methods
    ("PackML",): (NS_PACKML, NS_PACKML, 6),  # PackMLBaseObjectType
}
#: The other objects under these roots: folders with a browse name in this namespace.
COMPANION_ROOTS = {"MachineryBuildingBlocks": NS_MACHINERY, "PackML": NS_PACKML}

Status = Mapping[str, Any]


@dataclass(frozen=True)
class Unit:
    """A UNECE unit (OPC 10000-8 EUInformation: the UnitId is the common code packed)."""

    code: str
    symbol: str
    name: str

    @property
    def unit_id(self) -> int:
        uid = 0
        for ch in self.code:
            uid = (uid << 8) | ord(ch)
        return uid


METRE = Unit("MTR", "m", "metre")
RADIAN = Unit("C81", "rad", "radian")
PASCAL = Unit("PAL", "Pa", "pascal")
SECOND = Unit("SEC", "s", "second")
ONE = Unit("C62", "1", "one")


@dataclass(frozen=True)
class Var:
    """One variable: its path of browse names (``ns`` of each), type, unit, getter."""

    path: tuple[str, ...]
    #: "Double", "Boolean", "String", "LocalizedText", "Int32", "UInt32", or "NodeId" (a
    #: state machine's ``CurrentState/Id``: :class:`StateRef` or None)
    kind: str
    read: Callable[[Status], Any]
    unit: Unit | None = None
    ns: str = NS_WARA


@dataclass(frozen=True)
class StateRef:
    """A state object of a companion type (a ``CurrentState/Id`` value): its namespace
    and numeric id, from the NodeSet."""

    ns: str
    id: int


#: OPC 40001-1's states (MachineryItemState_StateMachineType,
#: MachineryOperationModeStateMachineType): name -> numeric id in the Machinery NodeSet.
MACHINERY_STATE_IDS = {
    "OutOfService": 5004,
    "NotAvailable": 5005,
    "Executing": 5006,
    "NotExecuting": 5007,
    "None": 5024,
    "Maintenance": 5025,
    "Processing": 5026,
    "Setup": 5027,
}
#: OPC 30050's state machines by the service's mode: PackMLBaseStateMachineType
#: (Aborted, or Cleared with MachineState inside), PackMLMachineStateMachineType
#: (Stopped, or Running with ExecuteState inside) and PackMLExecuteStateMachineType;
#: (name, numeric id in the PackML NodeSet), None where that machine is not active.
PACKML_BASE: dict[str, tuple[str, int]] = {"ABORTED": ("Aborted", 62)}
PACKML_BASE_ELSE = ("Cleared", 71)
PACKML_MACHINE: dict[str, tuple[str, int] | None] = {"ABORTED": None, "STOPPED": ("Stopped", 53)}
PACKML_MACHINE_ELSE = ("Running", 75)
PACKML_EXECUTE: dict[str, tuple[str, int]] = {
    "IDLE": ("Idle", 28),
    "STARTING": ("Starting", 29),
    "SUSPENDED": ("Suspended", 31),
    "HELD": ("Held", 34),
    "EXECUTE": ("Execute", 36),
    "COMPLETE": ("Complete", 38),
}


def packml_states(mode_name: str) -> tuple[tuple[str, int] | None, ...]:
    """The (base, machine, execute) states of OPC 30050 for one of the service's modes."""
    base = PACKML_BASE.get(mode_name, PACKML_BASE_ELSE)
    machine = PACKML_MACHINE.get(mode_name, PACKML_MACHINE_ELSE)
    execute = PACKML_EXECUTE.get(mode_name) if machine == PACKML_MACHINE_ELSE else None
    return base, machine, execute


#: MachineryItemState (OPC 40001-1 MachineryItemState_StateMachineType) of each mode.
ITEM_STATE = {
    "STOPPED": "NotExecuting",
    "IDLE": "NotExecuting",
    "COMPLETE": "NotExecuting",
    "STARTING": "Executing",
    "EXECUTE": "Executing",
    "HELD": "NotExecuting",
    "SUSPENDED": "NotExecuting",
    "ABORTED": "OutOfService",
}
#: MachineryOperationMode (OPC 40001-1) of each unit mode.
OPERATION_MODE = {
    str(UnitMode.PRODUCTION): "Processing",
    str(UnitMode.MAINTENANCE): "Maintenance",
    str(UnitMode.MANUAL): "Setup",
}
UNIT_MODE_CODES = {str(k): v for k, v in UNIT_MODES.items()}


def _get(st: Status, *keys: str) -> Any:
    v: Any = st
    for k in keys:
        if not isinstance(v, Mapping):
            return None
        v = v.get(k)
    return v


def _num(v: Any, scale: Callable[[float], float] = float) -> float:
    """A status number in SI; NaN where the status has none (a stale sensor)."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        return math.nan
    return float(scale(float(v)))


def _mm(v: Any) -> float:
    return _num(v, units.mm)


def _deg(v: Any) -> float:
    return _num(v, units.deg)


def _ms(v: Any) -> float:
    return _num(v, units.ms)


def _pick(seq: Any, i: int) -> Any:
    return seq[i] if isinstance(seq, list | tuple) and len(seq) > i else None


def _latched(st: Status, lock: Interlock) -> list[dict[str, Any]]:
    return [f for f in _get(st, "faults") or () if f.get("interlock") == str(lock)]


def _field(conv: Callable[[Any], Any], *keys: str) -> Callable[[Status], Any]:
    return lambda s: conv(_get(s, *keys))


def _side(i: int) -> Callable[[Any], float]:
    return lambda v: _num(_pick(v, i))


def _is_latched(lock: Interlock) -> Callable[[Status], bool]:
    return lambda s: bool(_latched(s, lock))


def _cause(lock: Interlock) -> Callable[[Status], str]:
    return lambda s: "; ".join(str(f.get("text", "")) for f in _latched(s, lock))


def mode(st: Status) -> str:
    m = st.get("mode")
    return m if isinstance(m, str) else "STOPPED"


def _step_phase(s: Status) -> tuple[Any, Any]:
    """(step, phase) of the ring cycle (``cycle``: its ring and phase), else of the walk
    (``walk``: its step and phase, e.g. ``7a lower M``)."""
    if isinstance(c := s.get("cycle"), Mapping):
        return c.get("ring"), c.get("phase")
    if isinstance(w := s.get("walk"), Mapping):
        name = " ".join(str(w[k]) for k in ("phase", "phase_name") if w.get(k))
        return w.get("step"), name
    return None, None


def _machinery_state(path: tuple[str, ...], name: Callable[[Status], str]) -> list[Var]:
    """A Machinery state machine's ``CurrentState`` and its ``Id``."""
    return [
        Var((*path, "CurrentState"), "LocalizedText", name, ns=NS_MACHINERY),
        Var(
            (*path, "CurrentState", "Id"),
            "NodeId",
            lambda s: StateRef(NS_MACHINERY, MACHINERY_STATE_IDS[name(s)]),
            ns=NS_MACHINERY,
        ),
    ]


def _packml_state(path: tuple[str, ...], level: int) -> list[Var]:
    """One of PackML's three state machines (``level`` 0 base, 1 machine, 2 execute):
    ``CurrentState`` (empty where that machine is not active) and its ``Id``."""

    def state(s: Status) -> tuple[str, int] | None:
        return packml_states(mode(s))[level]

    return [
        Var((*path, "CurrentState"), "LocalizedText", lambda s: (state(s) or ("", 0))[0]),
        Var(
            (*path, "CurrentState", "Id"),
            "NodeId",
            lambda s: StateRef(NS_PACKML, st[1]) if (st := state(s)) else None,
        ),
    ]


def variables(cfg: ProjectConfig) -> list[Var]:
    """Every variable of the model for this project (the attitude cylinders by id)."""
    blocks = ("MachineryBuildingBlocks",)
    base = ("PackML", "BaseStateMachine")
    out: list[Var] = [
        # OPC 40001-1 Machinery building blocks
        *_machinery_state(
            (*blocks, "MachineryItemState"), lambda s: ITEM_STATE.get(mode(s), "NotAvailable")
        ),
        *_machinery_state(
            (*blocks, "MachineryOperationMode"),
            lambda s: OPERATION_MODE.get(str(s.get("unit_mode")), "None"),
        ),
        # OPC 30050 PackML: the state machines (the ones of PackMLBaseObjectType)
        *_packml_state(base, 0),
        *_packml_state((*base, "MachineState"), 1),
        *_packml_state((*base, "MachineState", "ExecuteState"), 2),
        Var(
            ("PackML", "Status", "UnitModeCurrent"),
            "Int32",
            lambda s: UNIT_MODE_CODES.get(str(s.get("unit_mode")), 0),
            ns=NS_PACKML,
        ),
        # beside the type's variables, in this namespace: the PackML state number
        # (ISA-TR88 / the PLC's control word), names, since when, and the step and phase
        # of a ring cycle or a walk (only when the service reports one)
        Var(("PackML", "Status", "StateCurrent"), "Int32", lambda s: PACKML_STATES.get(mode(s), 0)),
        Var(("PackML", "Status", "StateCurrentName"), "String", mode),
        Var(
            ("PackML", "Status", "UnitModeCurrentName"),
            "String",
            lambda s: str(s.get("unit_mode") or ""),
        ),
        Var(("PackML", "Status", "StateSince"), "Double", lambda s: _num(s.get("since_s")), SECOND),
        Var(
            ("PackML", "Status", "CycleStep"),
            "Int32",
            lambda s: int(v) if isinstance(v := _step_phase(s)[0], int) else -1,
        ),
        Var(("PackML", "Status", "CyclePhase"), "String", lambda s: str(_step_phase(s)[1] or "")),
        Var(("PackML", "Status", "Message"), "String", lambda s: str(s.get("message") or "")),
        # the workpiece's attitude
        Var(
            ("Attitude", "TargetRoll"),
            "Double",
            lambda s: _deg(_pick(_get(s, "target_deg"), 0)),
            RADIAN,
        ),
        Var(
            ("Attitude", "TargetPitch"),
            "Double",
            lambda s: _deg(_pick(_get(s, "target_deg"), 1)),
            RADIAN,
        ),
        Var(
            ("Attitude", "MeasuredRoll"),
            "Double",
            lambda s: _deg(_pick(_get(s, "motion", "achieved_deg"), 0)),
            RADIAN,
        ),
        Var(
            ("Attitude", "MeasuredPitch"),
            "Double",
            lambda s: _deg(_pick(_get(s, "motion", "achieved_deg"), 1)),
            RADIAN,
        ),
        Var(("Attitude", "ValvesEnabled"), "Boolean", lambda s: bool(s.get("valves_enabled"))),
        Var(("Attitude", "EStopActive"), "Boolean", lambda s: bool(s.get("estop_active"))),
        # the link to the PLC
        Var(("Link", "State"), "String", lambda s: str(s.get("link") or "")),
        Var(
            ("Link", "Suspends"), "UInt32", lambda s: int(_get(s, "ride_through", "suspends") or 0)
        ),
        Var(("Link", "Resumes"), "UInt32", lambda s: int(_get(s, "ride_through", "resumes") or 0)),
        # the fixed-rate loop's figures (the last report)
        Var(("Loop", "Period"), "Double", lambda s: _ms(_get(s, "loop", "period_ms")), SECOND),
        Var(
            ("Loop", "ComputeP99"),
            "Double",
            lambda s: _ms(_get(s, "loop", "compute_p99_ms")),
            SECOND,
        ),
        Var(
            ("Loop", "JitterP99"), "Double", lambda s: _ms(_get(s, "loop", "jitter_p99_ms")), SECOND
        ),
        Var(("Loop", "Cycles"), "UInt32", lambda s: int(_get(s, "loop", "cycles") or 0)),
        Var(("Loop", "Overruns"), "UInt32", lambda s: int(_get(s, "loop", "overruns") or 0)),
    ]
    for group in ("lower", "upper"):
        out += [
            Var(
                ("Groups", group, "SyncError"), "Double", _field(_mm, "sync_error_mm", group), METRE
            ),
            Var(("Groups", group, "Twist"), "Double", _field(_mm, "twist_mm", group), METRE),
        ]
    ids = [*cfg.layers.lower.cylinders, *cfg.layers.upper.cylinders]
    for cid in ids:
        out += [
            Var(("Cylinders", cid, "Position"), "Double", _field(_mm, "positions_mm", cid), METRE),
            Var(
                ("Cylinders", cid, "CapPressure"),
                "Double",
                _field(_side(0), "pressures_pa", cid),
                PASCAL,
            ),
            Var(
                ("Cylinders", cid, "RodPressure"),
                "Double",
                _field(_side(1), "pressures_pa", cid),
                PASCAL,
            ),
            Var(("Cylinders", cid, "Valid"), "Boolean", _field(bool, "positions_valid", cid)),
        ]
    for lock in Interlock:
        name = lock.name.title().replace("_", "")
        out += [
            Var(("Interlocks", name, "Latched"), "Boolean", _is_latched(lock)),
            Var(("Interlocks", name, "Cause"), "String", _cause(lock)),
        ]
    return out


def values(model: list[Var], status: Status) -> list[Any]:
    """The value of each of ``model``'s variables in ``status`` (same order)."""
    return [v.read(status) for v in model]
