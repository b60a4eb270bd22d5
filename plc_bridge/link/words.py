"""The words on the wire, as Python values: the DBC's value tables and the decoded messages.

:class:`Mode`, :class:`TargetAck`, :class:`TargetRequest` and :class:`Fault` mirror the
DBC value tables (``tests/test_plc_dbc.py`` checks they are equal); the dataclasses are
the decoded form of one message (SI units) that the two sides hand out and take in.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field, fields
from enum import IntEnum

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]


class Mode(IntEnum):
    IDLE = 0
    MANUAL = 1
    ATTITUDE_ADJUST = 2
    WALK = 3
    HOMING = 4


class TargetAck(IntEnum):
    NONE = 0
    ACCEPTED = 1
    REJECTED = 2
    COMPLETED = 3


class TargetRequest(IntEnum):
    NONE = 0
    NEW_TARGET = 1
    CANCEL = 2
    WALK = 3


class Fault(IntEnum):
    NONE = 0
    ESTOP = 1
    PUMP_FAULT = 2
    OIL_TEMPERATURE = 3
    OIL_LEVEL = 4
    FILTER_CLOGGED = 5
    IPC_TIMEOUT = 6
    SENSOR_FAULT = 7
    VALVE_FAULT = 8
    LIMIT_SWITCH = 9
    OVERPRESSURE = 10
    OTHER = 255


@dataclass(frozen=True)
class ControlWord:
    """IPC_Control without its E2E header and the active-group mask."""

    mode: Mode = Mode.IDLE
    enable: bool = False
    stop: bool = False
    fault_reset: bool = False
    ack_seq: int = 0
    ack_status: TargetAck = TargetAck.NONE
    #: the IPC service's PackML state and unit mode numbers (``PackMLState``,
    #: ``UnitMode``; 0: undefined), for the PLC and its HMI to show
    state: int = 0
    unit_mode: int = 0


#: The field names of :class:`ControlWord` (``IpcLink.set_control`` checks changes by name).
CONTROL_FIELDS = frozenset(f.name for f in fields(ControlWord))


@dataclass(frozen=True)
class PlcStatus:
    """PLC_Status. ``fault`` is a :class:`Fault` value (unknown codes stay ints)."""

    mode: Mode = Mode.IDLE
    estop: bool = False
    pump_running: bool = False
    drives_enabled: bool = False
    command_timeout: bool = False
    fault: int = Fault.NONE
    supply_pressure_pa: float = math.nan
    #: the machine can walk (``WalkAvailable``); False: the PLC refuses WALK
    walk_available: bool = False


@dataclass(frozen=True)
class HmiTarget:
    """PLC_HmiTarget: the operator's target attitude of the workpiece plane, or a walk of
    ``walk_steps`` steps (``request`` WALK)."""

    roll_rad: float
    pitch_rad: float
    request: TargetRequest = TargetRequest.NEW_TARGET
    seq: int = 0
    walk_steps: int = 0


@dataclass(frozen=True)
class LimitSwitches:
    retracted: BoolArray
    extended: BoolArray


@dataclass(frozen=True)
class Reading:
    """Latest values by ``can_index``: NaN and ``valid`` False where not usable."""

    value: FloatArray
    valid: BoolArray
    age_s: FloatArray = field(repr=False)

    def all_valid(self, indices: Iterable[int] | None = None) -> bool:
        if indices is None:
            return bool(self.valid.all())
        return bool(self.valid[list(indices)].all())
