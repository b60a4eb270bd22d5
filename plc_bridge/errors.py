"""Exceptions of the PLC bridge: one root, a few documented leaves (python-can style).

Runtime faults on the wire (CRC errors, timeouts, bus-off, a full transmit queue) are
never raised into the control loop: they are counted and reported by the link
(:meth:`plc_bridge.IpcLink.health`). Exceptions are for set-up mistakes.
"""

from __future__ import annotations


class BridgeError(Exception):
    """Root of every error raised by :mod:`plc_bridge`."""


class CatalogError(BridgeError):
    """The DBC cannot be used: missing file, parse error, a message without the E2E
    header in bytes 0-1, two messages with the same E2E data id, a signal without range.
    """


class BusOpenError(BridgeError):
    """The configured bus cannot be opened: interface missing (no ``vcan0``), the
    ``udp_multicast`` channel is not a multicast group, ``remote`` plug-in not installed.
    """


class BusLoadError(BridgeError):
    """A requested active group would push the bus load above
    ``can.max_bus_load_percent`` (e.g. asking for all 19 cylinders at 200 Hz).
    """
