"""Supervision of received messages and of the bus itself.

Per received message (:class:`RxRecord`): CRC and length check, alive counter
(repeated = stuck sender, jump beyond ``max_delta_counter`` = wrong sequence), range
check of every signal, and a stale timeout. Every frame ends in exactly one outcome
of :data:`RX_OUTCOMES`, each counted. A record hands out values only while fresh:
stale, never-received and rejected data are not values (the links turn them into NaN
or ``None``).

Per bus (:class:`BusHealth`): error frames (error warning / passive / bus-off /
restarted), send failures (full transmit queue = ENOBUFS, interface down) and
recovery with exponential back-off. Each event is logged once when it starts, and
once when it ends, never per frame.
"""

from __future__ import annotations

import errno
import logging
import math
from collections import Counter
from collections.abc import Iterable
from enum import StrEnum
from functools import lru_cache
from typing import Any

from plc_bridge.bus import ErrorFrame
from plc_bridge.codec import FrameCodec
from plc_bridge.e2e import COUNTER_MODULO, CounterCheck, check_counter

log = logging.getLogger("plc_bridge")

#: Every received frame ends in exactly one of these (the fuzz test checks the sum).
RX_OUTCOMES: tuple[str, ...] = (
    "accepted",  # E2E and range checks passed: values updated
    "initial",  # first frame after start or timeout: counter synchronised, no value yet
    "crc_error",
    "length_error",  # DLC differs from the DBC
    "counter_repeated",  # same counter again: sender stuck or frame duplicated
    "counter_wrong_sequence",  # counter jumped by more than max_delta_counter
    "counter_invalid",  # counter value 15
    "value_error",  # a signal without a SENSOR_FAULT value is outside its DBC range
    "unknown_id",  # not a message this side consumes
    "own_echo",  # a frame this side sends, echoed back (udp_multicast)
    "not_classic",  # remote, extended-id or CAN FD frame
    "error_frame",  # bus error report (socketcan), handled by BusHealth
)

#: Outcomes that mean something is wrong with the link (they make it DEGRADED for a while).
RX_FAULTS = frozenset(
    {
        "crc_error",
        "length_error",
        "counter_repeated",
        "counter_wrong_sequence",
        "counter_invalid",
        "value_error",
    }
)


class LinkState(StrEnum):
    """What the controller may do with the link.

    - ``OK``: every supervised message fresh, no fault in the last ``hold`` seconds.
    - ``DEGRADED``: the critical messages are fresh (their values may be used), but a
      non-critical one is stale, the controller is error-passive, or a frame was
      rejected or lost recently.
    - ``LOST``: a critical message is stale or was never received, or the bus is off
      or down: stop (spools to centre on the PLC side).
    """

    OK = "OK"
    DEGRADED = "DEGRADED"
    LOST = "LOST"


#: How far short of a timeout's exact edge a "certainly not yet" time is kept
#: (:meth:`RxRecord.fresh_until_s`): far more than the rounding of ``now - last_rx``
#: on any clock, far less than a PLC scan.
SURELY_MARGIN_S = 1e-6


_OK = CounterCheck.OK


@lru_cache(maxsize=16)
def _counter_checks(max_delta: int) -> tuple[tuple[CounterCheck, int], ...]:
    return tuple(
        check_counter(last, counter, max_delta)
        for last in (*range(COUNTER_MODULO), None)
        for counter in range(16)
    )


class RxRecord:
    """Supervision and latest accepted values of one received message."""

    __slots__ = (
        "_counter_checks",
        "_nan_checked",
        "codec",
        "counters",
        "grace_timeout_s",
        "grace_until",
        "groups",
        "last_counter",
        "last_rx",
        "lost_frames",
        "max_delta",
        "name",
        "nan_ok",
        "timeout_s",
        "values",
        "was_fresh",
    )

    def __init__(self, codec: FrameCodec, timeout_s: float, max_delta: int) -> None:
        self.codec = codec
        self.name = codec.name
        self.timeout_s = timeout_s
        self.grace_timeout_s = timeout_s
        self.grace_until = -math.inf
        self.max_delta = max_delta
        self.nan_ok = tuple(s.sna_raw is not None for s in codec.spec.signals)
        # False when every signal may be NaN (positions, pressures): nothing to check
        self._nan_checked = not all(self.nan_ok)
        # check_counter(last, counter, max_delta) for every (last, counter), by
        # (15 if last is None else last) * 16 + counter: one lookup per frame
        self._counter_checks = _counter_checks(max_delta)
        self.last_counter: int | None = None
        self.last_rx: float | None = None
        self.values: tuple[float, ...] | None = None
        self.was_fresh = False
        self.lost_frames = 0
        self.counters: Counter[str] = Counter()
        #: where the link keeps this message's values by can_index as they change
        #: (``(SlotGroup, first slot, end slot, first value, end value)``, its own)
        self.groups: tuple[Any, ...] = ()

    def set_timeout(self, timeout_s: float, now: float) -> None:
        """Change the stale timeout; a shorter one applies after one old timeout of grace."""
        if timeout_s < self.timeout_s and self.last_rx is not None:
            self.grace_timeout_s = self.timeout_s
            self.grace_until = now + self.timeout_s
        self.timeout_s = timeout_s

    def on_frame(self, data: bytes | bytearray, now: float) -> str:
        """Check one frame of this id; returns its outcome (and counts it)."""
        codec = self.codec
        if len(data) != codec.dlc:
            outcome = "length_error"
        elif codec.crc_of(data) != data[0]:
            outcome = "crc_error"
        else:
            counter = data[1] & 0x0F
            last = self.last_counter
            result, lost = self._counter_checks[(15 if last is None else last) * 16 + counter]
            if result is _OK:
                values = codec.decode_word(int.from_bytes(data, "little"))
                bad = False
                if self._nan_checked:
                    for v, nan_ok in zip(values, self.nan_ok, strict=True):
                        if v != v and not nan_ok:
                            bad = True
                            break
                self.last_counter = counter
                if bad:
                    outcome = "value_error"
                else:
                    self.values = values
                    self.last_rx = now
                    self.lost_frames += lost
                    outcome = "accepted"
            elif result is CounterCheck.INITIAL:
                self.last_counter = data[1] & 0x0F
                outcome = "initial"
            elif result is CounterCheck.REPEATED:
                outcome = "counter_repeated"
            elif result is CounterCheck.WRONG_SEQUENCE:
                self.last_counter = data[1] & 0x0F  # re-synchronise on it
                outcome = "counter_wrong_sequence"
            else:
                outcome = "counter_invalid"
        self.counters[outcome] += 1
        return outcome

    def fresh(self, now: float) -> bool:
        """A valid frame arrived within the timeout in force."""
        if self.last_rx is None:
            return False
        timeout = self.grace_timeout_s if now < self.grace_until else self.timeout_s
        return now - self.last_rx <= timeout

    def age_s(self, now: float) -> float:
        return math.inf if self.last_rx is None else now - self.last_rx

    def fresh_until_s(self) -> float:
        """A time before which :meth:`fresh` is certainly True with the timeouts now in
        force (:data:`SURELY_MARGIN_S` short of the exact edge, which only
        :meth:`fresh` decides); -inf when nothing was received. A later frame only moves
        it on; :meth:`set_timeout` may move it back."""
        last = self.last_rx
        if last is None:
            return -math.inf
        return last + min(self.timeout_s, self.grace_timeout_s) - SURELY_MARGIN_S

    def latest(self, now: float) -> tuple[float, ...] | None:
        """The latest accepted values in DBC units, or None when stale."""
        return self.values if self.fresh(now) else None

    def check_timeout(self, now: float) -> bool:
        """Update the fresh/stale edge; True on the fresh -> stale transition."""
        last = self.last_rx  # self.fresh(now), written out: every record, every poll
        fresh = last is not None and now - last <= (
            self.grace_timeout_s if now < self.grace_until else self.timeout_s
        )
        went_stale = self.was_fresh and not fresh
        if went_stale:
            self.counters["timeouts"] += 1
            self.last_counter = None  # the next frame re-synchronises
            self.values = None
        self.was_fresh = fresh
        return went_stale


def all_fresh(records: Iterable[RxRecord], now: float) -> bool:
    """``all(r.fresh(now) for r in records)`` without the generator (the link's state
    is asked every loop cycle, over every received message)."""
    for r in records:  # noqa: SIM110 - the generator is what this avoids
        if not r.fresh(now):
            return False
    return True


class BusState(StrEnum):
    ACTIVE = "ACTIVE"
    WARNING = "WARNING"
    PASSIVE = "PASSIVE"
    BUS_OFF = "BUS_OFF"
    DOWN = "DOWN"  #: the interface or socket failed; being reopened


#: errno values of a send that mean "transmit queue full": counted, never waited on.
QUEUE_FULL_ERRNOS = frozenset({errno.ENOBUFS, errno.EAGAIN, errno.EWOULDBLOCK})
#: errno values that mean the interface is gone: reopen with back-off.
DOWN_ERRNOS = frozenset({errno.ENETDOWN, errno.ENODEV, errno.ENXIO, errno.EBADF})


class BusHealth:
    """Bus state from error frames and send/receive failures; back-off for recovery."""

    def __init__(self, name: str, backoff_initial_s: float = 0.1, backoff_max_s: float = 5.0):
        self.name = name
        self.state = BusState.ACTIVE
        self.counters: Counter[str] = Counter()
        self.backoff_initial_s = backoff_initial_s
        self.backoff_max_s = backoff_max_s
        self.backoff_s = backoff_initial_s
        self.next_attempt = math.inf
        self.last_fault_time = -math.inf
        self.tx_error_active = False  # a send failure burst is in progress (logged once)
        self.reopen_failing = False  # reopen attempts of this outage failed (logged once)

    def _set(self, state: BusState, now: float, why: str) -> None:
        if state is self.state:
            return
        old, self.state = self.state, state
        level = logging.INFO if state is BusState.ACTIVE else logging.WARNING
        log.log(level, "%s: CAN bus %s -> %s (%s)", self.name, old.value, state.value, why)
        if state in (BusState.BUS_OFF, BusState.DOWN):
            self.next_attempt = now + self.backoff_s
        if state is not BusState.ACTIVE:
            self.last_fault_time = now

    def on_error_frame(self, err: ErrorFrame, now: float) -> None:
        self.counters["error_frames"] += 1
        self.counters[f"error_{err.kind}"] += 1
        self.last_fault_time = now
        if err.bus_off:
            self.counters["bus_off_events"] += 1
            self._set(BusState.BUS_OFF, now, "error frame: bus-off")
        elif err.restarted or err.back_to_active:
            self._set(BusState.ACTIVE, now, f"error frame: {err.kind}")
            self.backoff_s = self.backoff_initial_s
        elif self.state in (BusState.BUS_OFF, BusState.DOWN):
            pass  # stays off until restarted or reopened
        elif err.error_passive:
            self._set(BusState.PASSIVE, now, "error frame: error passive")
        elif err.warning and self.state is BusState.ACTIVE:
            self._set(BusState.WARNING, now, "error frame: error warning")

    def on_frame_ok(self) -> None:
        """A valid frame arrived: the bus works; reset the back-off."""
        self.backoff_s = self.backoff_initial_s

    def on_send_ok(self) -> None:
        if self.tx_error_active:
            self.tx_error_active = False
            log.info("%s: CAN transmit works again", self.name)

    def on_send_error(self, code: int | None, text: str, now: float) -> None:
        self.last_fault_time = now
        if code in QUEUE_FULL_ERRNOS or "buffer full" in text or "recipients" in text:
            self.counters["tx_queue_full"] += 1
            kind = "transmit queue full (dropped, not waited on)"
        else:
            self.counters["tx_errors"] += 1
            kind = f"transmit failed: {text}"
            if code in DOWN_ERRNOS:
                self._set(BusState.DOWN, now, kind)
        if not self.tx_error_active:
            self.tx_error_active = True
            log.warning("%s: CAN %s", self.name, kind)

    def on_recv_error(self, text: str, now: float) -> None:
        self.counters["rx_errors"] += 1
        self._set(BusState.DOWN, now, f"receive failed: {text}")

    def can_send(self) -> bool:
        return self.state not in (BusState.BUS_OFF, BusState.DOWN)

    def due_for_reopen(self, now: float) -> bool:
        return self.state in (BusState.BUS_OFF, BusState.DOWN) and now >= self.next_attempt

    def reopened(self, ok: bool, now: float, why: str = "") -> None:
        """Record a reopen attempt; the back-off doubles per attempt until a frame arrives."""
        self.counters["reopen_attempts"] += 1
        self.backoff_s = min(2.0 * self.backoff_s, self.backoff_max_s)
        if ok:
            self.counters["reopened"] += 1
            self._set(BusState.ACTIVE, now, why or "bus reopened")
            self.next_attempt = math.inf
            self.reopen_failing = False
        else:
            self.counters["reopen_failures"] += 1
            self.next_attempt = now + self.backoff_s
            if not self.reopen_failing:  # once per outage
                self.reopen_failing = True
                log.warning(
                    "%s: cannot reopen the CAN bus (%s); retrying with back-off up to %.1f s",
                    self.name,
                    why,
                    self.backoff_max_s,
                )
