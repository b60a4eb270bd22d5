"""A two-node in-process CAN bus for lockstep runs: :func:`lockstep_pair`.

In lockstep (``wara.harness.Harness(mode="lockstep")``, the campaigns, the tests) one
thread drives both nodes in turn on simulated time, so their bus needs no thread
safety: each end is a :class:`can.BusABC` whose receive queue is a plain deque, and a
frame sent on one end is appended to the other's. python-can's ``virtual`` bus does the
same job for any number of nodes in any threads, with a lock, a ``queue.Queue`` and a
deep copy of every frame per receiver: in a lockstep run that was a large share of the
simulated PLC's 1 kHz scan. The frames, their codec and the supervision on either side
are the same on both buses.

What a receiver gets is the frame object the sender built (both nodes build a new
:class:`can.Message` for every frame and never change one they sent), stamped with the
wall-clock send time and ``is_rx``, as the ``virtual`` bus stamps its copies. Receiving
never blocks: nothing can arrive while the only thread waits. Not for two threads; the
real-time harness keeps the ``virtual`` bus.
"""

from __future__ import annotations

import collections
import time
from typing import Any

import can


class LockstepBus(can.BusABC):
    """One end of a :func:`lockstep_pair`."""

    def __init__(self, channel: str = "lockstep", **kwargs: Any) -> None:
        self._queue: collections.deque[can.Message] = collections.deque()
        self._peer: LockstepBus | None = None
        self._open = True
        self.channel_info = f"lockstep bus {channel}"
        super().__init__(channel=channel, **kwargs)

    def _check_open(self) -> None:
        if not self._open:
            raise can.CanOperationError("Cannot operate on a closed bus")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check_open()
        peer = self._peer
        if peer is not None and peer._open:
            msg.timestamp = time.time()
            msg.is_rx = True
            peer._queue.append(msg)

    def send_all(self, msgs: list[can.Message]) -> None:
        """:meth:`send` of each of ``msgs`` in order (one wall-clock stamp for them all:
        they are sent at one instant of the one thread)."""
        self._check_open()
        peer = self._peer
        if peer is not None and peer._open:
            now = time.time()
            for msg in msgs:
                msg.timestamp = now
                msg.is_rx = True
            peer._queue.extend(msgs)

    def recv_all(self, limit: int) -> list[can.Message]:
        """Up to ``limit`` frames, as :meth:`recv` would give them one by one."""
        self._check_open()
        q = self._queue
        if self._filters is not None or len(q) > limit:
            out: list[can.Message] = []
            while len(out) < limit and (msg := self.recv()) is not None:
                out.append(msg)
            return out
        out = list(q)
        q.clear()
        return out

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        self._check_open()
        q = self._queue
        return (q.popleft() if q else None), False

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame (that passes the filters, if set), or None at once when there
        is none (whatever ``timeout``)."""
        self._check_open()
        q = self._queue
        if self._filters is None:
            return q.popleft() if q else None
        while q:
            msg = q.popleft()
            if self._matches_filters(msg):
                return msg
        return None

    def has_error_frame(self) -> bool:
        """An error frame is waiting to be received (the simulator's compiled scans
        leave those to its Python scan)."""
        return any(m.is_error_frame for m in self._queue)

    def shutdown(self) -> None:
        super().shutdown()
        self._open = False
        self._queue.clear()


def lockstep_pair(channel: str = "lockstep") -> tuple[LockstepBus, LockstepBus]:
    """Two connected ends: what one sends, the other receives (never itself)."""
    a, b = LockstepBus(channel), LockstepBus(channel)
    a._peer, b._peer = b, a
    return a, b
