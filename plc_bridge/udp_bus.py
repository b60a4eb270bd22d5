"""``wara_udp``: a lean cross-process CAN transport over UDP multicast (one host or LAN).

A python-can :class:`can.BusABC`, so :class:`~plc_bridge.link.IpcLink`,
:class:`~plc_bridge.link.PlcLink` and python-can's tools use it like any back-end. It
carries what python-can's ``udp_multicast`` carries for this project (classic CAN
frames, error frames, remote frames) with less work per frame, because that work is paid
inside the 200 Hz loop (measured in docs/service.md, "Two processes over udp_multicast"):

- one fixed 20-byte datagram per frame packed with :mod:`struct` (no msgpack, no dict)::

      offset  size  field
      0       2     magic b"WU"
      2       1     version (1)
      3       1     dlc (0..8)
      4       4     sender id (little endian, random per bus instance)
      8       4     CAN id with the SocketCAN flag bits: 0x80000000 extended,
                    0x40000000 remote, 0x20000000 error frame
      12      8     data, zero padded after ``dlc`` bytes

- a non-blocking socket read per datagram (no ``select`` per frame; ``select`` only
  when the caller asks to wait, ``recv(timeout > 0)``); the message timestamp is the
  kernel's receive time (``SO_TIMESTAMPNS``, epoch seconds, as socketcan and
  ``udp_multicast`` give), so a reader that was held up still knows when each frame
  arrived (the HIL simulator's catching-up scans rely on it); :func:`time.time` at
  the read where the kernel gives none;
- a node's own frames (the multicast socket loops them back) are recognised by the
  sender id and skipped here, never handed to the caller (``own_skipped``); datagrams
  that are not this format (another program on the group and port) are skipped and
  counted (``foreign_skipped``).

Limits (decisions): classic CAN only (an FD frame is refused on send); no delivery or
order guarantee beyond UDP's on one host; not interoperable with ``udp_multicast`` (do
not put both on the same group and port). ``send`` never blocks when ``timeout`` is 0
(the link's case): a full socket buffer raises :class:`can.CanOperationError` with
``ENOBUFS``/``EAGAIN``, which the link counts as a full transmit queue.
"""

from __future__ import annotations

import contextlib
import errno
import ipaddress
import os
import select
import socket
import struct
import time
from typing import Any

import can

from config import units

MAGIC = b"WU"
VERSION = 1
FRAME = struct.Struct("<2sBBII8s")
FRAME_SIZE = FRAME.size  # 20
EFF_FLAG = 0x80000000
RTR_FLAG = 0x40000000
ERR_FLAG = 0x20000000
_ID_MASK = 0x1FFFFFFF
_HEADER = MAGIC + bytes([VERSION])
#: linux/socket.h; Python's socket module does not name it
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
_TIMESPEC = struct.Struct("@qq")
_CMSG_SPACE = socket.CMSG_SPACE(_TIMESPEC.size)


def pack_frame(sender: int, msg: can.Message) -> bytes:
    """The datagram of one classic CAN frame (raises ValueError for FD / > 8 bytes)."""
    data = bytes(msg.data)
    if msg.is_fd or len(data) > 8:
        raise ValueError("wara_udp carries classic CAN frames only (no CAN FD, at most 8 bytes)")
    cid = msg.arbitration_id & _ID_MASK
    if msg.is_extended_id:
        cid |= EFF_FLAG
    if msg.is_remote_frame:
        cid |= RTR_FLAG
    if msg.is_error_frame:
        cid |= ERR_FLAG
    dlc = msg.dlc if msg.is_remote_frame else len(data)
    return FRAME.pack(MAGIC, VERSION, dlc, sender, cid, data)


def unpack_frame(datagram: bytes) -> tuple[int, int, int, bytes] | None:
    """(sender, CAN id with flags, dlc, data) of a datagram, or None if not this format."""
    if len(datagram) != FRAME_SIZE or datagram[:3] != _HEADER:
        return None
    _, _, dlc, sender, cid, data = FRAME.unpack(datagram)
    if dlc > 8:
        return None
    return sender, cid, dlc, data


class WaraUdpBus(can.BusABC):
    """CAN frames between processes over UDP multicast (see the module docstring).

    :param channel: the multicast group (IPv4 ``239.0.0.0/8`` or IPv6 ``ff00::/8``).
    :param port: the UDP port (``can.udp_port``).
    :param hop_limit: IPv4 TTL / IPv6 hop limit; 1 keeps the frames on the link.
    :param receive_own_messages: hand this bus's own frames back too (default: skipped).
    """

    def __init__(
        self,
        channel: str,
        port: int = 43113,
        hop_limit: int = 1,
        receive_own_messages: bool = False,
        **kwargs: Any,
    ) -> None:
        try:
            group = ipaddress.ip_address(channel)
        except ValueError:
            raise can.CanInitializationError(
                f"wara_udp channel {channel!r} is not an IP address"
            ) from None
        if not group.is_multicast:
            raise can.CanInitializationError(
                f"wara_udp channel {channel!r} is not a multicast group"
            )
        super().__init__(channel, can_filters=kwargs.get("can_filters"))
        self.channel_info = f"wara_udp {channel}:{port}"
        self._channel = channel
        self._can_protocol = can.CanProtocol.CAN_20
        self.sender_id = int.from_bytes(os.urandom(4), "little")
        self.receive_own_messages = receive_own_messages
        self.own_skipped = 0
        self.foreign_skipped = 0
        family = socket.AF_INET if group.version == 4 else socket.AF_INET6
        sock = socket.socket(family, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            packed = socket.inet_pton(family, channel)
            if family == socket.AF_INET:
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, hop_limit)
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
                sock.bind(("", port))
                mreq = packed + struct.pack("@I", socket.INADDR_ANY)
                sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, mreq)
            else:
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_HOPS, hop_limit)
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_MULTICAST_LOOP, 1)
                sock.bind(("", port))
                mreq = packed + struct.pack("@I", 0)
                sock.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_JOIN_GROUP, mreq)
            sock.setblocking(False)
            with contextlib.suppress(OSError):  # not Linux: stamped at the read
                sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        except OSError as exc:
            sock.close()
            raise can.CanInitializationError(
                f"cannot join multicast group {channel} port {port}: {exc}"
            ) from exc
        self._sock = sock
        self._dest = (channel, port)

    # ------------------------------------------------------------------ python-can API
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Send one frame; with ``timeout`` 0 never waits (a full buffer raises)."""
        try:
            datagram = pack_frame(self.sender_id, msg)
        except ValueError as exc:
            raise can.CanOperationError(str(exc)) from None
        try:
            self._sock.sendto(datagram, self._dest)
            return
        except BlockingIOError as exc:
            if timeout is not None and timeout <= 0:
                raise can.CanOperationError(
                    "wara_udp: socket buffer full", error_code=exc.errno
                ) from None
        except OSError as exc:
            raise can.CanOperationError(f"wara_udp send failed: {exc}", exc.errno) from exc
        # A full buffer and the caller may wait: until writable or the timeout.
        _, writable, _ = select.select([], [self._sock], [], timeout)
        if not writable:
            raise can.CanTimeoutError("wara_udp: socket buffer full", errno.EAGAIN)
        try:
            self._sock.sendto(datagram, self._dest)
        except OSError as exc:
            raise can.CanOperationError(f"wara_udp send failed: {exc}", exc.errno) from exc

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        sock = self._sock
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                datagram, anc, _, _ = sock.recvmsg(64, _CMSG_SPACE)
            except BlockingIOError:
                if deadline is None:
                    wait: float | None = None
                else:
                    wait = deadline - time.monotonic()
                    if wait <= 0:
                        return None, False
                try:
                    ready, _, _ = select.select([sock], [], [], wait)
                except OSError as exc:
                    raise can.CanOperationError(f"wara_udp wait failed: {exc}", exc.errno) from exc
                if not ready:
                    return None, False
                continue
            except OSError as exc:
                raise can.CanOperationError(f"wara_udp receive failed: {exc}", exc.errno) from exc
            frame = unpack_frame(datagram)
            if frame is None:
                self.foreign_skipped += 1
                continue
            sender, cid, dlc, data = frame
            if sender == self.sender_id and not self.receive_own_messages:
                self.own_skipped += 1
                continue
            remote = bool(cid & RTR_FLAG)
            if anc and len(anc[0][2]) >= _TIMESPEC.size:
                sec, nsec = _TIMESPEC.unpack_from(anc[0][2])
                stamp = sec + nsec * units.NS
            else:
                stamp = time.time()
            msg = can.Message(
                timestamp=stamp,
                arbitration_id=cid & _ID_MASK,
                is_extended_id=bool(cid & EFF_FLAG),
                is_remote_frame=remote,
                is_error_frame=bool(cid & ERR_FLAG),
                dlc=dlc,
                data=None if remote else data[:dlc],
                channel=self._channel,
                check=False,
            )
            return msg, False

    def fileno(self) -> int:
        return self._sock.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._sock.close()
