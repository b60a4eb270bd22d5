"""Fault injection on the CAN wire: a python-can bus wrapper between the PLC and the bus.

:class:`FaultyWire` is a ``can.BusABC`` that the simulator hands to ``PlcLink``. It
passes frames through unchanged until faults are switched on (:meth:`set_faults`);
then, in simulated time, it

- drops frames with a given probability (seeded), either direction;
- delays frames by a fixed time (order kept; released by :meth:`release_due`);
- inverts the CRC byte of frames (the receiver counts ``crc_error``);
- freezes the alive counter at its last value, CRC recomputed so that only the
  counter is wrong (the receiver counts ``counter_repeated``);
- silences the PLC (nothing sent, nothing read);
- stalls: holds frames (either direction) until the stall's end, then delivers them in
  order, as a congested or stopped link would;
- takes the bus off: no frame either way, and error frames on the bus report
  ``bus-off`` at the start and ``restarted`` at the end (linux/can/error.h), as a
  socketcan controller does.

In real time the PLC's scans are paced by the wall clock, and a simulator process that
was held up (a busy machine) runs the missed scans back to back. So that those scans see
the bus as an on-time PLC would have, :meth:`set_arrival_horizon` hides received frames
that arrived (``msg.timestamp``, epoch seconds: the receive time on socketcan, the
kernel's on ``udp_multicast``, the send time on ``virtual``) after the wall time the
scan stands for; a later scan gets them, in order. Without it a late simulator would
read every frame of the stall in one scan and then see none while its clock catches up:
a false command timeout.

Every action is counted in :attr:`counts` (``(kind, message name) -> frames``), so a
test can compare what the IPC saw with exactly what was done to the wire.
"""

from __future__ import annotations

import collections
import fnmatch
from collections import Counter
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import Any

import can
import numpy as np

from plc_bridge.bus import CAN_ERR_BUSOFF, CAN_ERR_RESTARTED
from plc_bridge.catalog import Catalog
from plc_bridge.e2e import crc8_p01
from plc_bridge.lockstep_bus import LockstepBus

#: A frame stamped later than the arrival horizon by more than this is on another clock.
_MAX_EARLY_S = 1.0

#: Directions as the scenario names them.
PLC_TO_IPC = "plc_to_ipc"
IPC_TO_PLC = "ipc_to_plc"


@dataclass(frozen=True)
class WireFault:
    """One active fault on the wire.

    ``kind``: ``drop``, ``delay``, ``bad_crc``, ``frozen_counter``, ``plc_silent``,
    ``bus_off`` or ``wire_stall``; ``frame_ids``: the frames it applies to (empty: all);
    ``direction``: ``plc_to_ipc``, ``ipc_to_plc`` or ``both``; ``rate`` for
    drop/bad_crc; ``max_burst`` for drop (at most that many frames of one message lost
    in a row; 0: no bound); ``delay_s`` for delay; ``until_s`` (simulated time) for a
    stall.
    """

    kind: str
    frame_ids: frozenset[int] = frozenset()
    direction: str = PLC_TO_IPC
    rate: float = 1.0
    max_burst: int = 0
    delay_s: float = 0.0
    until_s: float = 0.0
    key: int = 0  #: identifies the fault (frozen counters are kept per fault)

    def applies(self, frame_id: int, direction: str) -> bool:
        if self.direction not in (direction, "both"):
            return False
        return not self.frame_ids or frame_id in self.frame_ids


def match_messages(catalog: Catalog, patterns: Iterable[str], where: str) -> frozenset[int]:
    """Frame ids of the DBC messages matching the names/fnmatch patterns (empty: all)."""
    ids: set[int] = set()
    names = [m.name for m in catalog.messages]
    for pat in patterns:
        hit = [n for n in names if fnmatch.fnmatchcase(n, pat)]
        if not hit:
            raise ValueError(
                f"{where}: no DBC message matches {pat!r}; messages are {', '.join(names)}"
            )
        ids.update(catalog.by_name(n).frame_id for n in hit)
    return frozenset(ids)


def _error_frame(cls_bits: int) -> can.Message:
    return can.Message(
        arbitration_id=cls_bits, is_error_frame=True, is_extended_id=False, data=bytes(8)
    )


class FaultyWire(can.BusABC):
    """The PLC's view of the bus, with faults. Never blocks; no thread."""

    def __init__(
        self,
        inner: can.BusABC,
        catalog: Catalog,
        clock: Callable[[], float],
        seed: int = 0,
        **kwargs: Any,
    ) -> None:
        super().__init__(channel=getattr(inner, "channel_info", "wire"), **kwargs)
        self.inner = inner
        self.catalog = catalog
        self._clock = clock
        self._rng = np.random.default_rng(seed)
        self._faults: tuple[WireFault, ...] = ()
        self._delayed: collections.deque[tuple[float, can.Message]] = collections.deque()
        self._frozen: dict[tuple[int, int], int] = {}
        self._last_counter: dict[int, int] = {}
        #: frames of one message a drop fault lost in a row, by (fault key, frame id)
        self._burst: Counter[tuple[int, int]] = Counter()
        self._bus_off = False
        self._horizon: float | None = None
        self._early: can.Message | None = None  # received, arrived after the horizon
        self._held_rx: collections.deque[can.Message] = collections.deque()  # stalled
        self.counts: Counter[tuple[str, str]] = Counter()
        self._ids = frozenset(m.frame_id for m in catalog.messages)

    # ----------------------------------------------------------------- control

    @property
    def faults(self) -> tuple[WireFault, ...]:
        return self._faults

    def set_faults(self, faults: Iterable[WireFault]) -> None:
        """The faults in force from now on (the simulator calls this each PLC scan)."""
        new = tuple(faults)
        bus_off = any(f.kind == "bus_off" for f in new)
        if bus_off != self._bus_off:
            self._bus_off = bus_off
            self._delayed.clear()
            self.inner.send(_error_frame(CAN_ERR_BUSOFF if bus_off else CAN_ERR_RESTARTED))
            self.counts[("bus_off" if bus_off else "restarted", "error_frame")] += 1
        keys = {f.key for f in new if f.kind == "frozen_counter"}
        self._frozen = {k: v for k, v in self._frozen.items() if k[0] in keys}
        self._faults = new

    @property
    def silent(self) -> bool:
        return any(f.kind in ("plc_silent", "bus_off") for f in self._faults)

    def _name(self, frame_id: int) -> str:
        spec = self.catalog.by_id(frame_id)
        return spec.name if spec is not None else f"0x{frame_id:03X}"

    @property
    def receives_all(self) -> bool:
        """A receive hands over every frame there is, in order (no arrival horizon set,
        nothing held back from an earlier one): what the simulator's compiled scans,
        which drain the bus once per step, need."""
        return self._horizon is None and self._early is None

    @property
    def quiet(self) -> bool:
        """No fault in force and nothing delayed: frames pass as they are, at once."""
        return not self._faults and not self._delayed

    @property
    def has_delayed(self) -> bool:
        """Frames are delayed on their way to the bus (:meth:`release_due`)."""
        return bool(self._delayed)

    def set_arrival_horizon(self, epoch_s: float | None) -> None:
        """Receive only frames that arrived by ``epoch_s`` (None: all that are there)."""
        self._horizon = epoch_s

    # ----------------------------------------------------------------- transmit

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        fid = msg.arbitration_id
        if not self._faults and not self._delayed:  # the wire as it is most of the time
            if fid in self._ids:
                self._last_counter[fid] = msg.data[1] & 0x0F
            self.inner.send(msg, timeout=timeout)
            return
        name = self._name(fid)
        if self.silent:
            kind = "bus_off" if self._bus_off else "plc_silent"
            self.counts[(kind, name)] += 1
            return
        spec = self.catalog.by_id(fid)
        delay = 0.0
        release_at: float | None = None
        for f in self._faults:
            if not f.applies(fid, PLC_TO_IPC):
                continue
            if f.kind == "wire_stall":
                release_at = f.until_s if release_at is None else max(release_at, f.until_s)
                self.counts[("wire_stall", name)] += 1
                continue
            if f.kind == "frozen_counter" and spec is not None:
                key = (f.key, fid)
                if key not in self._frozen:
                    self._frozen[key] = self._last_counter.get(fid, msg.data[1] & 0x0F)
                data = bytearray(msg.data)
                data[1] = (data[1] & 0xF0) | self._frozen[key]
                data[0] = crc8_p01(spec.data_id, bytes(data[1:]))
                msg = _copy(msg, bytes(data))
                self.counts[("frozen_counter", name)] += 1
            elif f.kind == "bad_crc" and self._rng.random() < f.rate:
                data = bytearray(msg.data)
                data[0] ^= 0xFF
                msg = _copy(msg, bytes(data))
                self.counts[("bad_crc", name)] += 1
            elif f.kind == "drop" and self._drops(f, fid):
                self.counts[("drop", name)] += 1
                return
            elif f.kind == "delay":
                delay = max(delay, f.delay_s)
        if spec is not None and not any(
            f.kind == "frozen_counter" and f.applies(fid, PLC_TO_IPC) for f in self._faults
        ):
            self._last_counter[fid] = msg.data[1] & 0x0F
        if release_at is not None:
            self._delayed.append((max(release_at, self._clock() + delay), msg))
            return
        if delay > 0.0 or self._delayed:
            # order is kept: a frame never overtakes one delayed before it
            self._delayed.append((self._clock() + delay, msg))
            if delay > 0.0:
                self.counts[("delay", name)] += 1
            self.release_due()
            return
        self.inner.send(msg, timeout=timeout)

    def _drops(self, f: WireFault, fid: int) -> bool:
        """Whether drop fault ``f`` loses this frame of ``fid``: with probability
        ``rate``, never after ``max_burst`` frames of it lost in a row."""
        if not f.max_burst:
            return bool(self._rng.random() < f.rate)
        key = (f.key, fid)
        if self._burst[key] >= f.max_burst:
            self._burst[key] = 0
            return False
        lost = bool(self._rng.random() < f.rate)
        self._burst[key] = self._burst[key] + 1 if lost else 0
        return lost

    def send_all(self, msgs: list[can.Message]) -> None:
        """:meth:`send` of each of ``msgs`` in order; on the wire as it is most of the
        time (no fault, nothing delayed) in one go onto a bus that takes a batch
        (:meth:`~plc_bridge.lockstep_bus.LockstepBus.send_all`)."""
        inner = self.inner
        if self._faults or self._delayed or not isinstance(inner, LockstepBus):
            for msg in msgs:
                self.send(msg)
            return
        last, ids = self._last_counter, self._ids
        for msg in msgs:
            fid = msg.arbitration_id
            if fid in ids:
                last[fid] = msg.data[1] & 0x0F
        inner.send_all(msgs)

    def release_due(self, now: float | None = None) -> int:
        """Put the delayed frames whose time has come on the bus; returns how many."""
        if not self._delayed:
            return 0
        t = self._clock() if now is None else now
        n = 0
        while self._delayed and self._delayed[0][0] <= t + 1e-12:
            _, msg = self._delayed.popleft()
            self.inner.send(msg, timeout=0.0)
            n += 1
        return n

    # ----------------------------------------------------------------- receive

    def _stalled_rx(self, fid: int | None = None) -> bool:
        for f in self._faults:
            if f.kind == "wire_stall" and (
                f.direction in (IPC_TO_PLC, "both") if fid is None else f.applies(fid, IPC_TO_PLC)
            ):
                return True
        return False

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """The next frame the PLC receives, or None at once (never blocks)."""
        if self._filters is not None:
            return super().recv(0.0)
        return self._recv_internal(0.0)[0]

    def recv_all(self, limit: int) -> list[can.Message]:
        """Up to ``limit`` frames, as :meth:`recv` gives them one by one (in one go from a
        bus that hands over a batch, when nothing on the wire acts on received frames)."""
        inner = self.inner
        if (
            self._filters is None
            and not self._faults
            and not self._held_rx
            and self._early is None
            and self._horizon is None
            and isinstance(inner, LockstepBus)
        ):
            return inner.recv_all(limit)
        out: list[can.Message] = []
        while len(out) < limit and (msg := self.recv()) is not None:
            out.append(msg)
        return out

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if not self._faults and not self._held_rx and self._early is None and self._horizon is None:
            return self.inner.recv(0.0), False  # no fault, nothing held back
        while True:
            if self._held_rx and not self._stalled_rx():
                return self._held_rx.popleft(), False  # the stall is over: in order
            msg = self._early
            if msg is None:
                msg = self.inner.recv(0.0)
            else:
                self._early = None
            if msg is None:
                return None, False
            h = self._horizon
            # a timestamp far from the horizon is another clock's: never hold it back
            if h is not None and h < msg.timestamp < h + _MAX_EARLY_S:
                self._early = msg
                return None, False
            if msg.is_error_frame:
                return msg, False
            name = self._name(msg.arbitration_id)
            if self.silent:
                self.counts[("bus_off" if self._bus_off else "plc_silent", name)] += 1
                continue
            fid = msg.arbitration_id
            if self._stalled_rx(fid):
                self._held_rx.append(msg)
                self.counts[("wire_stall_rx", name)] += 1
                continue
            dropped = False
            for f in self._faults:
                if not f.applies(fid, IPC_TO_PLC):
                    continue
                if f.kind == "drop" and self._drops(f, fid):
                    self.counts[("drop_rx", name)] += 1
                    dropped = True
                    break
                if f.kind == "bad_crc" and self._rng.random() < f.rate:
                    data = bytearray(msg.data)
                    data[0] ^= 0xFF
                    msg = _copy(msg, bytes(data))
                    self.counts[("bad_crc_rx", name)] += 1
            if not dropped:
                return msg, False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()

    def total(self, kind: str) -> int:
        """Frames affected by faults of ``kind`` so far, all messages."""
        return sum(n for (k, _), n in self.counts.items() if k == kind)


def _copy(msg: can.Message, data: bytes) -> can.Message:
    return can.Message(
        arbitration_id=msg.arbitration_id,
        data=data,
        is_extended_id=msg.is_extended_id,
        timestamp=msg.timestamp,
        check=False,
    )
