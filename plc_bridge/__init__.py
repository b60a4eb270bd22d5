"""The CAN protocol between the IPC and the PLC: DBC, codec, bus back-ends, supervision.

``wara_plc.dbc`` is the message catalogue; :class:`IpcLink` is the IPC (master) side
that ``ipc_app`` uses, :class:`PlcLink` the PLC (device) side that ``hil_sim`` plays.
See ``docs/can-protocol.md``.
"""

from plc_bridge.bus import open_bus
from plc_bridge.busload import BusLoad, bus_load, frame_bits
from plc_bridge.catalog import DBC_PATH, Catalog, MessageSpec, load_catalog
from plc_bridge.codec import FrameCodec
from plc_bridge.errors import BridgeError, BusLoadError, BusOpenError, CatalogError
from plc_bridge.link import (
    ControlWord,
    Fault,
    HmiTarget,
    IpcLink,
    LimitSwitches,
    Mode,
    PlcLink,
    PlcStatus,
    Reading,
    TargetAck,
    TargetRequest,
)
from plc_bridge.supervision import BusState, LinkState

__all__ = [
    "DBC_PATH",
    "BridgeError",
    "BusLoad",
    "BusLoadError",
    "BusOpenError",
    "BusState",
    "Catalog",
    "CatalogError",
    "ControlWord",
    "Fault",
    "FrameCodec",
    "HmiTarget",
    "IpcLink",
    "LimitSwitches",
    "LinkState",
    "MessageSpec",
    "Mode",
    "PlcLink",
    "PlcStatus",
    "Reading",
    "TargetAck",
    "TargetRequest",
    "bus_load",
    "frame_bits",
    "load_catalog",
    "open_bus",
]
