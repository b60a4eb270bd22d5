"""Bus back-ends from the configuration, receive filters, and error-frame decoding.

One factory, :func:`open_bus`, turns ``can.interface`` / ``can.channel`` into a
python-can bus (python-can's own interchangeable back-ends):

- ``socketcan``: production (``can0``) and ``vcan0``; kernel receive filters for
  the ids this side consumes; error frames enabled (python-can's ``state`` does not
  report bus-off on socketcan, the error frames do). The bit rate is set by the OS
  (``ip link set can0 type can bitrate 500000 restart-ms 100``), not here.
- ``virtual``: in-process, the embedded default and the tests' bus; no filters: it only
  carries the two nodes' frames, and python-can filters would also swallow the error
  frames that the HIL simulator puts on it (bus-off, restarted); the link counts
  anything it does not consume as ``unknown_id``.
- ``udp_multicast``: cross-process on one host (HIL runs); ``channel`` is the multicast
  group. Its sockets echo a node's own frames back to it: the link drops frames with
  the ids it sends itself and counts them (``own_echo``), so no filter is set here.
- ``wara_udp``: cross-process on one host like ``udp_multicast`` (``channel`` the group,
  ``can.udp_port`` the port), with less work per frame inside the loop: our own back-end,
  :class:`plc_bridge.udp_bus.WaraUdpBus` (fixed 20-byte frames, no ``select`` per frame,
  own frames skipped by a sender id before they reach the link). Not interoperable with
  ``udp_multicast``.
- ``remote``: python-can-remote (optional plug-in); ``channel`` is ``host:port``.

Lockstep runs (one thread drives both nodes) use
:func:`plc_bridge.lockstep_bus.lockstep_pair` instead of a configured bus.
"""

from __future__ import annotations

import contextlib
import ipaddress
import os
import socket
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

import can

from config.schema import CanLink
from plc_bridge.errors import BusOpenError
from plc_bridge.udp_bus import WaraUdpBus

# linux/can/error.h: error class bits in the id of an error frame, and data[1] flags.
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40
CAN_ERR_CRTL_RX_OVERFLOW = 0x01
CAN_ERR_CRTL_TX_OVERFLOW = 0x02


@dataclass(frozen=True)
class ErrorFrame:
    """What one socketcan error frame says (linux/can/error.h)."""

    bus_off: bool = False
    restarted: bool = False
    error_passive: bool = False
    warning: bool = False
    back_to_active: bool = False
    bus_error: bool = False  #: protocol violation, no ACK, transceiver or TX timeout
    overflow: bool = False  #: controller RX/TX buffer overflow
    tx_errors: int | None = None
    rx_errors: int | None = None

    @property
    def kind(self) -> str:
        """The most severe thing the frame reports, one word for logs and counters."""
        for name in ("bus_off", "restarted", "error_passive", "warning", "back_to_active"):
            if getattr(self, name):
                return name
        if self.overflow:
            return "overflow"
        return "bus_error"


def parse_error_frame(msg: can.Message) -> ErrorFrame:
    """Decode the class bits and controller flags of a socketcan error frame."""
    cls = msg.arbitration_id
    data = bytes(msg.data) + bytes(8 - len(msg.data)) if len(msg.data) < 8 else bytes(msg.data)
    ctrl = data[1] if cls & CAN_ERR_CRTL else 0
    has_counts = len(msg.data) >= 8 and bool(cls & 0x200)  # CAN_ERR_CNT (Linux >= 5.17)
    return ErrorFrame(
        bus_off=bool(cls & CAN_ERR_BUSOFF),
        restarted=bool(cls & CAN_ERR_RESTARTED),
        error_passive=bool(ctrl & (CAN_ERR_CRTL_RX_PASSIVE | CAN_ERR_CRTL_TX_PASSIVE)),
        warning=bool(ctrl & (CAN_ERR_CRTL_RX_WARNING | CAN_ERR_CRTL_TX_WARNING)),
        back_to_active=bool(ctrl & CAN_ERR_CRTL_ACTIVE),
        bus_error=bool(
            cls & (CAN_ERR_PROT | CAN_ERR_ACK | CAN_ERR_TRX | CAN_ERR_TX_TIMEOUT | CAN_ERR_BUSERROR)
        ),
        overflow=bool(ctrl & (CAN_ERR_CRTL_RX_OVERFLOW | CAN_ERR_CRTL_TX_OVERFLOW)),
        tx_errors=data[6] if has_counts else None,
        rx_errors=data[7] if has_counts else None,
    )


def receive_filters(frame_ids: Iterable[int]) -> list[dict[str, Any]]:
    """python-can filters accepting exactly these 11-bit ids (kernel filters on socketcan)."""
    return [{"can_id": i, "can_mask": 0x7FF, "extended": False} for i in sorted(set(frame_ids))]


def _check_multicast(channel: str, kind: str) -> None:
    try:
        addr = ipaddress.ip_address(channel)
    except ValueError:
        addr = None
    if addr is None or not addr.is_multicast:
        raise BusOpenError(
            f"can.channel: {channel!r} is not a multicast group; interface {kind} "
            f"needs one, e.g. 239.74.163.2 (IPv4) or ff15:7079:7468:6f6e:6465:6d6f:6d63:6173"
        )


#: Receive buffer asked for on datagram transports: about 2 s of this project's traffic
#: (~1800 frames/s, ~1 KiB of kernel accounting each on loopback). The Linux default
#: (rmem_default, 208 KiB) holds about 0.1 s: a process held up that long by a busy
#: machine loses frames, and the peer's supervision rightly sees a silent link.
DATAGRAM_RCVBUF_BYTES = 4 * 1024 * 1024


def enlarge_receive_buffer(bus: can.BusABC, size: int = DATAGRAM_RCVBUF_BYTES) -> int:
    """Ask for a ``size`` receive buffer on the bus's socket; returns what the kernel
    granted (capped by net.core.rmem_max), 0 where the bus has no socket."""
    try:
        fd = bus.fileno()
    except NotImplementedError:
        return 0
    if fd < 0:
        return 0
    with socket.socket(fileno=os.dup(fd)) as sock:  # the same socket; the dup is closed
        with contextlib.suppress(OSError):  # what was granted is returned either way
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, size)
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))


def open_bus(link: CanLink, rx_ids: Iterable[int] = ()) -> can.BusABC:
    """Open the configured bus, filtered to ``rx_ids`` where the back-end filters.

    Raises :class:`BusOpenError` with the interface, channel and the fix.
    """
    kind = link.interface
    filters = receive_filters(rx_ids) or None
    kwargs: dict[str, Any] = {}
    if kind == "socketcan":
        kwargs = {
            "can_filters": filters,
            "receive_own_messages": False,
            "fd": False,
            "ignore_rx_error_frames": False,
        }
    elif kind == "virtual":
        kwargs = {"receive_own_messages": False}
    elif kind == "udp_multicast":
        _check_multicast(link.channel, kind)
        kwargs = {"port": link.udp_port, "fd": False}
    elif kind == "wara_udp":
        _check_multicast(link.channel, kind)
    elif kind == "remote":
        kwargs = {"can_filters": filters}
    try:
        if kind == "wara_udp":
            bus: can.BusABC = WaraUdpBus(link.channel, port=link.udp_port)
        else:
            bus = can.Bus(interface=kind, channel=link.channel, **kwargs)
        if kind in ("udp_multicast", "wara_udp"):
            enlarge_receive_buffer(bus)
        return bus
    except (can.CanInterfaceNotImplementedError, ImportError) as exc:
        hint = " (pip install python-can-remote)" if kind == "remote" else ""
        raise BusOpenError(f"can.interface {kind!r} is not available here{hint}: {exc}") from None
    except (OSError, can.CanError) as exc:
        hint = ""
        if kind == "socketcan":
            hint = (
                f"; does {link.channel} exist and is it up? "
                f"(vcan: ip link add dev {link.channel} type vcan && ip link set {link.channel} up)"
            )
        elif kind in ("udp_multicast", "wara_udp"):
            hint = (
                f"; is port {link.udp_port} free and multicast routed on this host? "
                "(e.g. ip route add 239.0.0.0/8 dev lo)"
            )
        raise BusOpenError(
            f"cannot open can.interface {kind!r} channel {link.channel!r}: {exc}{hint}"
        ) from None


def socketcan_available(channel: str = "vcan0") -> str | None:
    """None if a socketcan bus on ``channel`` can be opened here, else the reason."""
    import socket

    if not hasattr(socket, "AF_CAN"):
        return "this Python has no AF_CAN sockets"
    try:
        s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError as exc:
        return f"the kernel has no SocketCAN support ({exc.strerror})"
    try:
        s.bind((channel,))
    except OSError as exc:
        return f"no SocketCAN interface {channel} ({exc.strerror})"
    finally:
        s.close()
    return None
