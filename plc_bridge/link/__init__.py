"""The two sides of the protocol over one bus: :class:`IpcLink` and :class:`PlcLink`.

Modules: :mod:`~plc_bridge.link.words` (the DBC's value tables and decoded messages),
:mod:`~plc_bridge.link.side` (what both sides share), :mod:`~plc_bridge.link.ipc` and
:mod:`~plc_bridge.link.plc` (one side each). The names below are the public ones.

Like canopen's master and device classes over one network, both are small classes
over a python-can bus, compiled from the same DBC. Neither starts a thread: the
owner's loop calls :meth:`poll` once per cycle (drain received frames without
blocking, supervise, transmit the periodic frames that are due), reads the latest
valid values, and writes its outputs. Not thread-safe: one loop owns a link.

Arrays are indexed by the cylinders' ``can_index`` (0..18; ``config`` maps ids).
Values are SI (m, Pa, rad); the DBC's engineering units (mm, MPa, deg) are converted
with :mod:`config.units` at this boundary and nowhere else.

The rule the controller relies on: a value that is stale, never received, failed
its CRC/counter/range check, or reported as a sensor fault is never handed out as a
number. Arrays carry NaN there (and ``valid`` False); words are ``None``.

IPC side::

    link = IpcLink.from_config(cfg)             # bus from cfg.can
    link.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
    while running:                              # 200 Hz
        link.poll()
        x = link.positions_m()                  # Reading: value [m], valid, age_s
        if link.state() is LinkState.LOST or not x.valid[active].all():
            u = np.zeros(19)                    # no decision on stale data
        link.send_valve_commands(u)             # 19 floats in [-1, 1]

PLC side (hil_sim)::

    plc = PlcLink.from_config(cfg)
    while running:
        plc.poll()                              # sends status/positions/... when due
        u = plc.valve_commands().value          # NaN where stale: centre that spool
        plc.set_positions_m(x); plc.set_pressures_pa(p)
        plc.set_status(PlcStatus(mode=..., pump_running=True))
"""

from plc_bridge.link.ipc import IpcLink
from plc_bridge.link.plc import PlcLink
from plc_bridge.link.side import FAULT_HOLD_S, LinkSide, SideRole
from plc_bridge.link.words import (
    ControlWord,
    Fault,
    HmiTarget,
    LimitSwitches,
    Mode,
    PlcStatus,
    Reading,
    TargetAck,
    TargetRequest,
)
from plc_bridge.supervision import LinkState

__all__ = [
    "FAULT_HOLD_S",
    "ControlWord",
    "Fault",
    "HmiTarget",
    "IpcLink",
    "LimitSwitches",
    "LinkSide",
    "LinkState",
    "Mode",
    "PlcLink",
    "PlcStatus",
    "Reading",
    "SideRole",
    "TargetAck",
    "TargetRequest",
]
