"""What both sides of the link share (:class:`LinkSide`): bus, codecs, E2E supervision,
the transmit schedule, bus recovery, the link state.

A side is built from its :class:`SideRole` (which node it is, the peer's heartbeat, its
loop-rate inputs, what it schedules): the base has all it needs before the subclass adds
its own fields, so no overridden method runs on a half-built object.
"""

from __future__ import annotations

import contextlib
import copy
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from typing import Any, TypeVar

import can
import numpy as np

from config import ConfigError, units
from config.schema import N_CYLINDERS, ProjectConfig
from plc_bridge.bus import open_bus, parse_error_frame
from plc_bridge.busload import active_cylinders, is_active
from plc_bridge.catalog import Catalog, MessageSpec, load_catalog
from plc_bridge.codec import FrameCodec
from plc_bridge.e2e import COUNTER_MODULO
from plc_bridge.link.words import Reading
from plc_bridge.supervision import (
    RX_FAULTS,
    RX_OUTCOMES,
    BusHealth,
    BusState,
    LinkState,
    RxRecord,
    all_fresh,
)

log = logging.getLogger("plc_bridge")

W = TypeVar("W")

#: A DEGRADED link stays so for this long after the last rejected/lost frame or bus error.
FAULT_HOLD_S = 1.0


class TxFrame(can.Message):
    """A frame this side sends: a :class:`can.Message` that is quick to make and to
    deep-copy.

    ``TxFrame(arbitration_id, data)`` is a classic frame (11-bit id, no remote, error
    or FD flags, ``is_rx`` True and ``timestamp`` 0 as python-can's defaults), its
    fields set directly: python-can's constructor, general over every flag, takes
    about three times as long, and every frame of both nodes is made here (the
    simulated PLC's too). Any other keyword goes to python-can's constructor.

    python-can's ``virtual`` bus (the in-process demo, tests) deep-copies every frame
    sent, once per receiver; ``Message.__deepcopy__`` copies the payload with
    ``copy.deepcopy`` (the pickle protocol, about 60 % of the copy). This one copies the
    same fields and the payload directly: an equal, independent message. Other
    interfaces serialise the frame and never copy it.
    """

    __slots__ = ()

    def __init__(
        self, arbitration_id: int = 0, data: bytes | bytearray = b"", **kwargs: Any
    ) -> None:
        if kwargs:
            super().__init__(arbitration_id=arbitration_id, data=data, **kwargs)
            return
        self.timestamp = 0.0
        self.arbitration_id = arbitration_id
        self.is_extended_id = False
        self.is_remote_frame = False
        self.is_error_frame = False
        self.channel = None
        self.is_fd = False
        self.is_rx = True
        self.bitrate_switch = False
        self.error_state_indicator = False
        self.data = bytearray(data)
        self.dlc = len(data)

    def __deepcopy__(self, memo: dict[int, Any] | None) -> can.Message:
        return can.Message(
            timestamp=self.timestamp,
            arbitration_id=self.arbitration_id,
            is_extended_id=self.is_extended_id,
            is_remote_frame=self.is_remote_frame,
            is_error_frame=self.is_error_frame,
            channel=copy.deepcopy(self.channel, memo),
            dlc=self.dlc,
            data=bytearray(self.data),
            is_fd=self.is_fd,
            is_rx=self.is_rx,
            bitrate_switch=self.bitrate_switch,
            error_state_indicator=self.error_state_indicator,
        )


#: the name this class had (tests)
_TxMessage = TxFrame


class SlotGroup:
    """Received messages' latest values by ``can_index`` (``width`` values a slot, DBC
    units) and their receive times, kept as the frames arrive and go stale: the IPC's
    positions and pressures, the PLC's valve commands. Plain lists, made into arrays
    in one conversion per read (:meth:`LinkSide._array`).

    What they hold: a message's values where its record has values (NaN where not),
    its receive time where it has one (-inf where never). A record has values only
    while fresh as of the link's last timeout check, so at that check's time these
    lists are the reading; at any other time the reading is worked out from the records.
    """

    __slots__ = ("last", "rows", "vals", "width")

    def __init__(self, rows: list[tuple[RxRecord, int, int, int, int]], width: int) -> None:
        self.rows = rows
        self.width = width
        self.vals = [math.nan] * (N_CYLINDERS * width)
        self.last = [-math.inf] * N_CYLINDERS
        for rec, lo, hi, vlo, vhi in rows:
            rec.groups += ((self, lo, hi, vlo, vhi),)

    def refill(self) -> None:
        """Take every row again from its record (after its state was set from outside)."""
        for rec, lo, hi, vlo, vhi in self.rows:
            v = rec.values
            self.vals[vlo:vhi] = [math.nan] * (vhi - vlo) if v is None else v[: vhi - vlo]
            last = rec.last_rx
            self.last[lo:hi] = [-math.inf if last is None else last] * (hi - lo)


#: bus states in which nothing is sent (:meth:`BusHealth.can_send`)
_CANNOT_SEND = frozenset({BusState.BUS_OFF, BusState.DOWN})


def mask_of(indices: Iterable[int]) -> int:
    m = 0
    for i in indices:
        m |= 1 << i
    return m


def indices_of(mask: int) -> frozenset[int]:
    return frozenset(i for i in range(N_CYLINDERS) if mask >> i & 1)


@dataclass(frozen=True)
class SideRole:
    """What a side is, given to :class:`LinkSide` when it is built (no hook asks later)."""

    #: The DBC node this side is (``IPC`` or ``PLC``): it sends that node's messages.
    node: str
    #: The received message that is the peer's heartbeat, and its timeout's ``safety`` key.
    heartbeat: str
    heartbeat_timeout_key: str
    #: Prefix of the received loop-rate messages (the IPC's positions, the PLC's valve
    #: commands): the link is LOST when one that carries an active cylinder is stale.
    loop_rx_prefix: str
    #: Sent messages that :meth:`LinkSide.poll` sends on their cycle; ``None``: all of them.
    scheduled_tx: tuple[str, ...] | None = None


class LinkSide:
    """What both sides share: bus, codecs, E2E supervision, schedule, recovery.

    A subclass passes its :class:`SideRole` and sets its own fields after
    ``super().__init__``: this constructor calls no method a subclass overrides. The
    subclass supplies :meth:`_values_for` (the values of a scheduled frame) and may
    supply :meth:`_on_accepted`; both run only from :meth:`poll`.
    """

    def __init__(
        self,
        cfg: ProjectConfig,
        bus: can.BusABC | None = None,
        *,
        role: SideRole,
        bus_factory: Callable[[], can.BusABC] | None = None,
        catalog: Catalog | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        self.role = role
        self.catalog = catalog if catalog is not None else load_catalog()
        self._clock = clock
        self._loop_period_s = cfg.control.period_s
        codecs = {m.frame_id: FrameCodec(m) for m in self.catalog.messages}
        self._codec_by_name = {c.name: c for c in codecs.values()}
        self.tx_specs = self.catalog.sent_by(self.role.node)
        self.rx_specs = tuple(m for m in self.catalog.messages if m.sender != self.role.node)
        self._tx_ids = frozenset(m.frame_id for m in self.tx_specs)
        self._scheduled_tx = (
            self.tx_specs
            if role.scheduled_tx is None
            else tuple(self.catalog.by_name(n) for n in role.scheduled_tx)
        )
        self.rx_ids = tuple(m.frame_id for m in self.rx_specs)
        max_delta = cfg.can.max_delta_counter
        self._rx: dict[int, RxRecord] = {
            m.frame_id: RxRecord(codecs[m.frame_id], 1.0, max_delta) for m in self.rx_specs
        }
        self._rx_by_name = {r.name: r for r in self._rx.values()}
        #: The received loop-rate messages with the ``can_index`` slots each carries.
        self._loop_rows: list[tuple[RxRecord, list[int]]] = [
            (self._rx_by_name[m.name], list(m.slots))
            for m in self.catalog.with_prefix(role.loop_rx_prefix)
        ]
        self._groups: list[SlotGroup] = []
        self._hooked = type(self)._on_accepted is not LinkSide._on_accepted
        self._loop_slices = self._slot_group(self._loop_rows, 1)
        #: the time of the last timeout check (NaN: none since the timeouts changed or
        #: a record that was not fresh took a frame): the records' freshness then is
        #: what their values and ``was_fresh`` say (:class:`SlotGroup`, :meth:`state`)
        self._fresh_at = math.nan
        #: at that check: (the critical records fresh, every record fresh)
        self._fresh_counts = (False, False)
        #: Per received word (:meth:`_word`): the values it was built from, and the word.
        self._words: dict[str, tuple[tuple[float, ...], Any]] = {}
        self._tx_counter: dict[int, int] = {m.frame_id: 0 for m in self.tx_specs}
        self._period: dict[int, float] = {}
        self._next_due: dict[int, float] = {}
        #: No scheduled frame is due before this (-inf: look): :meth:`_send_due` skips
        #: the scan of its messages until then. Whatever changes ``_next_due`` or
        #: ``_period`` outside that scan sets it back to -inf.
        self._wake = -math.inf
        #: Per scheduled message (in :attr:`_scheduled_tx` order), the time from which
        #: :meth:`_send_due` sends it (``_next_due`` less a quarter period): worked out
        #: again whenever ``_wake`` is set back to -inf, kept up to date by the scan.
        self._due_at: list[float] = [-math.inf] * len(self._scheduled_tx)
        #: No received message can go stale before this, nor turn fresh without a frame
        #: accepted (which sets it back to -inf when its record was not fresh, as a
        #: change of the timeouts does; a frame accepted on a fresh record only moves
        #: that record's own edge later, so the time stays a bound):
        #: :meth:`_check_timeouts` skips its records until then.
        self._stale_check_at = -math.inf
        self.rx_outcomes: Counter[str] = Counter()
        self.tx_counts: Counter[str] = Counter()
        self._last_fault = -math.inf
        self._fault_logged_at: dict[str, float] = {}
        self.bus_health = BusHealth(self.role.node)
        if bus is None:
            factory = bus_factory or (lambda: open_bus(cfg.can, self.rx_ids))
            bus = factory()
            bus_factory = factory
        self.bus = bus
        self._bus_factory = bus_factory
        self._active: frozenset[int] = frozenset()
        self._apply_active(frozenset(active_cylinders(cfg)), self._clock())
        # Stagger the first transmission of the slow periodic frames (one per ms) so that
        # they do not leave as one burst into a short socketcan transmit queue.
        t0 = self._clock()
        for k, fid in enumerate(sorted(self._period)):
            self._next_due[fid] = t0 + (0.0 if self._period[fid] < 0.02 else units.MS * k)
        self._wake = -math.inf

    @classmethod
    def from_config(cls, cfg: ProjectConfig, **kwargs: Any) -> Any:
        """Open the bus ``cfg.can`` names (with receive filters) and build the side on it."""
        return cls(cfg, None, **kwargs)

    # ----------------------------------------------------------------- schedule

    def _timeout_for(self, spec: MessageSpec, active: frozenset[int]) -> float:
        cycle = spec.cycle_in_force_s(is_active(spec, active), self._loop_period_s)
        if spec.name == self.role.heartbeat:
            ms = getattr(self.cfg.safety, self.role.heartbeat_timeout_key)
            if units.ms(ms) < 1.5 * cycle:
                raise ConfigError(
                    f"safety.{self.role.heartbeat_timeout_key}: {ms} ms is shorter than 1.5 cycles "
                    f"of {spec.name} ({units.to_ms(cycle):.0f} ms); "
                    f"use at least {units.to_ms(1.5 * cycle):.0f}"
                )
            return units.ms(ms)
        return self.cfg.can.stale_cycles * cycle

    def _apply_active(self, active: frozenset[int], now: float) -> None:
        """Make ``active`` the fast group: receive timeouts, the cycle of every sent
        message (scheduled or sent by the owner's loop), the critical records."""
        self._active = active
        for spec in self.rx_specs:
            self._rx[spec.frame_id].set_timeout(self._timeout_for(spec, active), now)
        self._stale_check_at = -math.inf
        self._fresh_at = math.nan
        for spec in self.tx_specs:
            self._period[spec.frame_id] = spec.cycle_in_force_s(
                is_active(spec, active), self._loop_period_s
            )
        self._wake = -math.inf
        self._set_active_group(active)

    def _set_active_group(self, active: frozenset[int]) -> None:
        """``active`` as the group, and the records the link is LOST without: the peer's
        heartbeat and the loop-rate rows that carry an active cylinder (the timeouts and
        periods are :meth:`_apply_active`'s)."""
        self._active = active
        self._critical_recs: tuple[RxRecord, ...] = (
            self._rx_by_name[self.role.heartbeat],
            *(rec for rec, slots in self._loop_rows if any(i in active for i in slots)),
        )

    @property
    def active_cylinders(self) -> tuple[int, ...]:
        """``can_index`` of the active group (their frames run at the fast cycle)."""
        return tuple(sorted(self._active))

    def _values_for(self, spec: MessageSpec, now: float) -> list[float] | None:
        raise NotImplementedError

    @staticmethod
    def _compile_rows(
        rows: list[tuple[RxRecord, list[int]]], width: int
    ) -> list[tuple[RxRecord, int, int, int, int]]:
        """Per message (record, first slot, end slot, first value, end value), for
        :meth:`_array`: each message carries consecutive ``can_index`` slots (checked)."""
        out = []
        for rec, slots in rows:
            lo, hi = slots[0], slots[-1] + 1
            if list(slots) != list(range(lo, hi)):
                raise ValueError(f"{rec.name}: slots {slots} are not consecutive")
            out.append((rec, lo, hi, lo * width, hi * width))
        return out

    def _slot_group(self, rows: list[tuple[RxRecord, list[int]]], width: int) -> SlotGroup:
        group = SlotGroup(self._compile_rows(rows, width), width)
        self._groups.append(group)
        return group

    def _records_set(self) -> None:
        """The records' state was set from outside (the simulator's compiled scans hand
        theirs back): the groups taken again, every shortcut worked out anew."""
        for group in self._groups:
            group.refill()
        self._wake = -math.inf
        self._stale_check_at = -math.inf
        self._fresh_at = math.nan

    def _array(self, group: SlotGroup, si_per_unit: float, now: float) -> Reading:
        """The latest values of ``group`` by ``can_index`` in SI; NaN where not usable.

        At the time of the last timeout check (the loop polls, then reads) the group's
        lists are the answer: one numpy conversion each. At any other time each row's
        record says: values while fresh at ``now`` (:meth:`RxRecord.latest`, written
        out), its age where it was ever received. The same figures either way
        (``tests/test_plc_link.py``).
        """
        width = group.width
        if now == self._fresh_at:
            val = np.array(group.vals)
            age = now - np.array(group.last)  # never received: inf
        else:
            vals = [math.nan] * (N_CYLINDERS * width)
            ages = [math.inf] * N_CYLINDERS
            for rec, lo, hi, vlo, vhi in group.rows:
                last = rec.last_rx
                if last is None:
                    continue
                a = now - last
                ages[lo:hi] = [a] * (hi - lo)
                v = rec.values
                if v is not None and a <= (
                    rec.grace_timeout_s if now < rec.grace_until else rec.timeout_s
                ):
                    vals[vlo:vhi] = v[: vhi - vlo]
            val = np.array(vals)
            age = np.array(ages)
        if si_per_unit != 1.0:  # (times 1.0 changes no value: the valve commands)
            val *= si_per_unit  # DBC unit -> SI, factor from config.units
        if width > 1:
            val = val.reshape(N_CYLINDERS, width)
        return Reading(value=val, valid=val == val, age_s=age)  # == : not NaN

    def _word(
        self, rec: RxRecord, build: Callable[[dict[str, float]], W], now: float | None
    ) -> W | None:
        """The word ``build`` makes of ``rec``'s latest values, None when stale; the same
        (frozen) object while the values stay the same (the IPC's status, HMI target and
        limit switches every cycle, the PLC's control word every scan with frames)."""
        v = rec.latest(self._clock() if now is None else now)
        if v is None:
            return None
        last = self._words.get(rec.name)
        if last is not None and last[0] == v:
            return last[1]
        word = build(dict(zip(rec.codec.signal_names, v, strict=True)))
        self._words[rec.name] = (v, word)
        return word

    # ----------------------------------------------------------------- transmit

    def _send(self, codec: FrameCodec, values: Sequence[float], now: float) -> bool:
        """Send one frame without blocking; failures are counted, never raised."""
        fid = codec.frame_id
        counters = self._tx_counter
        counter = counters[fid]
        counters[fid] = (counter + 1) % COUNTER_MODULO
        health = self.bus_health
        if health.state in _CANNOT_SEND:  # (BusHealth.can_send)
            self.tx_counts["tx_suppressed"] += 1
            return False
        msg = TxFrame(fid, codec.encode(counter, values))
        try:
            self.bus.send(msg, timeout=0.0)
        except can.CanError as exc:
            health.on_send_error(getattr(exc, "error_code", None), str(exc), now)
            return False
        except OSError as exc:
            health.on_send_error(exc.errno, str(exc), now)
            return False
        self.tx_counts["tx_frames"] += 1
        if health.tx_error_active:  # a failure before: it works again (logged once)
            health.on_send_ok()
        return True

    def _send_due(self, now: float) -> None:
        if now < self._wake:
            return  # every frame's own test below would skip it
        due_at = self._due_at
        if self._wake == -math.inf:  # _next_due or _period changed: their times anew
            due_at[:] = [
                self._next_due[spec.frame_id] - 0.25 * self._period[spec.frame_id]
                for spec in self._scheduled_tx
            ]
        wake = math.inf
        for k, at in enumerate(due_at):
            if now < at:
                if at < wake:
                    wake = at
                continue
            spec = self._scheduled_tx[k]
            fid = spec.frame_id
            period = self._period[fid]
            values = self._values_for(spec, now)
            if values is not None:
                self._send(self._codec_by_name[spec.name], values, now)
            nd = self._next_due[fid] + period
            if nd <= now:
                if nd + period <= now:
                    self.tx_counts["tx_overruns"] += 1
                nd = now + period
            self._next_due[fid] = nd
            at = due_at[k] = nd - 0.25 * period
            if at < wake:
                wake = at
        self._wake = wake

    # ----------------------------------------------------------------- receive

    def poll(self, now: float | None = None, max_frames: int = 1000) -> int:
        """Drain received frames without blocking, supervise, send due periodic frames.

        Call once per loop cycle. Returns the number of frames read. Never raises on
        bus trouble: it is counted, logged once per event and reflected in :meth:`state`.
        """
        if now is None:
            now = self._clock()
        n = 0
        if self.bus_health.state is not BusState.DOWN:
            bus = self.bus
            while n < max_frames:
                try:
                    msg = bus.recv(0.0)
                except (can.CanError, OSError, ValueError) as exc:
                    self.bus_health.on_recv_error(str(exc) or type(exc).__name__, now)
                    break
                if msg is None:
                    break
                n += 1
                self.on_message(msg, now)
        self._check_timeouts(now)
        self._recover(now)
        self._send_due(now)
        return n

    def on_message(self, msg: can.Message, now: float) -> str:
        """Classify and take in one received frame; returns its outcome (always counted)."""
        if msg.is_error_frame:
            outcome = "error_frame"
            self.bus_health.on_error_frame(parse_error_frame(msg), now)
        elif msg.is_remote_frame or msg.is_extended_id or msg.is_fd:
            outcome = "not_classic"
        else:
            rec = self._rx.get(msg.arbitration_id)
            if rec is None:
                outcome = "own_echo" if msg.arbitration_id in self._tx_ids else "unknown_id"
            else:
                lost_before = rec.lost_frames
                outcome = rec.on_frame(msg.data, now)
                if outcome == "accepted":
                    for g, lo, hi, vlo, vhi in rec.groups:
                        g.vals[vlo:vhi] = rec.values[: vhi - vlo]  # type: ignore[index]
                        g.last[lo:hi] = [now] * (hi - lo)
                    if now < self._fresh_at:  # older than the check: fresh then?
                        self._fresh_at = math.nan
                    if not rec.was_fresh:  # it may turn fresh: walk the records again
                        self._stale_check_at = -math.inf
                        self._fresh_at = math.nan  # (its was_fresh is not fresh(now))
                    health = self.bus_health
                    health.backoff_s = health.backoff_initial_s  # (BusHealth.on_frame_ok)
                    if rec.lost_frames != lost_before:
                        self._last_fault = now
                    if self._hooked:
                        self._on_accepted(rec, now)
                elif outcome in RX_FAULTS:
                    self._last_fault = now
                    last = self._fault_logged_at.get(rec.name, -math.inf)
                    if now - last > FAULT_HOLD_S:
                        log.warning(
                            "%s: %s (0x%03X) rejected: %s (repeats are counted, not logged)",
                            self.role.node,
                            rec.name,
                            rec.codec.frame_id,
                            outcome,
                        )
                    self._fault_logged_at[rec.name] = now
        self.rx_outcomes[outcome] += 1
        return outcome

    def _on_accepted(self, rec: RxRecord, now: float) -> None:
        """Hook: a frame passed all checks (the PLC side reads the active mask here;
        called only where a subclass has its own)."""

    def _check_timeouts(self, now: float) -> None:
        if now < self._stale_check_at:
            self._fresh_at = now
            return  # every record's own check below would change nothing
        check_at = math.inf
        every = True  # every record fresh
        for rec in self._rx.values():
            was = rec.was_fresh
            if rec.check_timeout(now):
                for g, _lo, _hi, vlo, vhi in rec.groups:
                    g.vals[vlo:vhi] = [math.nan] * (vhi - vlo)
                self._last_fault = now
                log.warning(
                    "%s: %s (0x%03X) stale: no valid frame for %.0f ms (timeout %.0f ms)",
                    self.role.node,
                    rec.name,
                    rec.codec.frame_id,
                    units.to_ms(rec.age_s(now)),
                    units.to_ms(rec.timeout_s),
                )
            elif rec.was_fresh and not was and rec.counters["timeouts"]:
                log.info("%s: %s receiving again", self.role.node, rec.name)
            if rec.was_fresh:
                until = rec.fresh_until_s()
                if until < check_at:
                    check_at = until
            else:
                every = False
        self._stale_check_at = check_at
        self._fresh_at = now
        self._fresh_counts = (every or all(r.was_fresh for r in self._critical_recs), every)

    def _recover(self, now: float) -> None:
        health = self.bus_health
        if health.state not in _CANNOT_SEND or not health.due_for_reopen(now):
            return
        if self._bus_factory is None:
            # A bus passed in cannot be made anew here: after the same back-off it is
            # used again as it is (a bus-off controller restarts by itself; if it is
            # still off or down, the next error frame or send failure says so).
            self.bus_health.reopened(True, now, "back-off over, the bus passed in used again")
            return
        with contextlib.suppress(Exception):  # a broken bus may fail to close; reopen anyway
            self.bus.shutdown()
        try:
            self.bus = self._bus_factory()
        except Exception as exc:  # any open failure means: retry later
            self.bus_health.reopened(False, now, str(exc))
            return
        self.bus_health.reopened(True, now)

    # ----------------------------------------------------------------- state

    def state(self, now: float | None = None) -> LinkState:
        """OK / DEGRADED / LOST (see :class:`LinkState`)."""
        if now is None:
            now = self._clock()
        if not self.bus_health.can_send():
            return LinkState.LOST
        if now == self._fresh_at:  # as of the timeout check at this time
            critical_fresh, all_fresh_now = self._fresh_counts
        else:
            critical_fresh = all_fresh(self._critical_recs, now)
            all_fresh_now = critical_fresh and all_fresh(self._rx.values(), now)
        if not critical_fresh:
            return LinkState.LOST
        if (
            self.bus_health.state is not BusState.ACTIVE
            or now - self._last_fault <= FAULT_HOLD_S
            or now - self.bus_health.last_fault_time <= FAULT_HOLD_S
            or not all_fresh_now
        ):
            return LinkState.DEGRADED
        return LinkState.OK

    def rx_counters(self) -> dict[str, int]:
        """Frames received so far (``received``) and how many ended in each outcome
        (``accepted``, ``crc_error``, ``counter_invalid``, ``unknown_id``, ...:
        :data:`~plc_bridge.supervision.RX_OUTCOMES`), zeros included. Safe from another
        thread than the one polling: one copy of the counter (a C-level dict merge under
        the GIL), then the sum."""
        counts = dict(self.rx_outcomes)
        out = {"received": sum(counts.values())}
        out.update({k: counts.get(k, 0) for k in RX_OUTCOMES})
        return out

    def health(self, now: float | None = None) -> dict[str, Any]:
        """Counters and per-message supervision, JSON-ready."""
        if now is None:
            now = self._clock()
        msgs = {}
        for r in self._rx.values():
            age = r.age_s(now)
            msgs[r.name] = {
                "fresh": r.fresh(now),
                "age_ms": None if math.isinf(age) else round(units.to_ms(age), 3),
                "timeout_ms": round(units.to_ms(r.timeout_s), 3),
                "lost_frames": r.lost_frames,
                **dict(r.counters),
            }
        return {
            "node": self.role.node,
            "state": self.state(now).value,
            "bus_state": self.bus_health.state.value,
            "active_cylinders": list(self.active_cylinders),
            "rx": dict(self.rx_outcomes),
            "tx": dict(self.tx_counts),
            "bus": dict(self.bus_health.counters),
            "lost_frames": sum(r.lost_frames for r in self._rx.values()),
            "messages": msgs,
        }

    def close(self) -> None:
        """Shut the bus down (only a bus this side opened itself or was handed)."""
        with contextlib.suppress(Exception):  # closing a failed bus must not raise
            self.bus.shutdown()

    def __enter__(self) -> Any:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
