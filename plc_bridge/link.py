"""The two sides of the protocol over one bus: :class:`IpcLink` and :class:`PlcLink`.

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

from __future__ import annotations

import contextlib
import copy
import logging
import math
import time
from collections import Counter
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field, fields, replace
from enum import IntEnum
from typing import Any, ClassVar

import can
import numpy as np
import numpy.typing as npt

from config import ConfigError, units
from config.schema import N_CYLINDERS, ProjectConfig
from plc_bridge.bus import open_bus, parse_error_frame
from plc_bridge.busload import BusLoad, active_cylinders, bus_load, is_active
from plc_bridge.catalog import Catalog, MessageSpec, load_catalog
from plc_bridge.codec import FrameCodec
from plc_bridge.e2e import COUNTER_MODULO
from plc_bridge.errors import BusLoadError
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

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]

#: A DEGRADED link stays so for this long after the last rejected/lost frame or bus error.
FAULT_HOLD_S = 1.0


# --------------------------------------------------------------------------- words
# Mirrors of the DBC value tables (tests/test_plc_dbc.py checks they are equal).


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


_CONTROL_FIELDS = frozenset(f.name for f in fields(ControlWord))


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


@dataclass(frozen=True)
class HmiTarget:
    """PLC_HmiTarget: the operator's target attitude of the workpiece plane."""

    roll_rad: float
    pitch_rad: float
    request: TargetRequest = TargetRequest.NEW_TARGET
    seq: int = 0


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


# --------------------------------------------------------------------------- common


class _TxMessage(can.Message):
    """A frame this side sends: a :class:`can.Message` with a cheaper deep copy.

    python-can's ``virtual`` bus (lockstep, tests, the in-process demo) deep-copies every
    frame sent, once per receiver; ``Message.__deepcopy__`` copies the payload with
    ``copy.deepcopy`` (the pickle protocol, about 60 % of the copy). This one copies the
    same fields and the payload directly: an equal, independent message. Other
    interfaces serialise the frame and never copy it.
    """

    __slots__ = ()

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


def _mask_of(indices: Iterable[int]) -> int:
    m = 0
    for i in indices:
        m |= 1 << i
    return m


def _indices_of(mask: int) -> frozenset[int]:
    return frozenset(i for i in range(N_CYLINDERS) if mask >> i & 1)


class _Side:
    """What both sides share: bus, codecs, E2E supervision, schedule, recovery."""

    NODE: ClassVar[str]
    #: Received message that is the peer's heartbeat, and its safety timeout key.
    HEARTBEAT: ClassVar[str]
    HEARTBEAT_TIMEOUT_KEY: ClassVar[str]

    def __init__(
        self,
        cfg: ProjectConfig,
        bus: can.BusABC | None = None,
        *,
        bus_factory: Callable[[], can.BusABC] | None = None,
        catalog: Catalog | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        self.catalog = catalog if catalog is not None else load_catalog()
        self._clock = clock
        self._loop_period_s = cfg.control.period_s
        codecs = {m.frame_id: FrameCodec(m) for m in self.catalog.messages}
        self._codec_by_name = {c.name: c for c in codecs.values()}
        self.tx_specs = self.catalog.sent_by(self.NODE)
        self.rx_specs = tuple(m for m in self.catalog.messages if m.sender != self.NODE)
        self._tx_ids = frozenset(m.frame_id for m in self.tx_specs)
        self.rx_ids = tuple(m.frame_id for m in self.rx_specs)
        max_delta = cfg.can.max_delta_counter
        self._rx: dict[int, RxRecord] = {
            m.frame_id: RxRecord(codecs[m.frame_id], 1.0, max_delta) for m in self.rx_specs
        }
        self._rx_by_name = {r.name: r for r in self._rx.values()}
        self._tx_counter: dict[int, int] = {m.frame_id: 0 for m in self.tx_specs}
        self._period: dict[int, float] = {}
        self._next_due: dict[int, float] = {}
        self.rx_outcomes: Counter[str] = Counter()
        self.tx_counts: Counter[str] = Counter()
        self._last_fault = -math.inf
        self._fault_logged_at: dict[str, float] = {}
        self.bus_health = BusHealth(self.NODE)
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
            self._next_due[fid] = t0 + (0.0 if self._period[fid] < 0.02 else 0.001 * k)

    @classmethod
    def from_config(cls, cfg: ProjectConfig, **kwargs: Any) -> Any:
        """Open the bus ``cfg.can`` names (with receive filters) and build the side on it."""
        return cls(cfg, None, **kwargs)

    # ----------------------------------------------------------------- schedule

    def _timeout_for(self, spec: MessageSpec, active: frozenset[int]) -> float:
        cycle = spec.cycle_in_force_s(is_active(spec, active), self._loop_period_s)
        if spec.name == self.HEARTBEAT:
            ms = getattr(self.cfg.safety, self.HEARTBEAT_TIMEOUT_KEY)
            if units.ms(ms) < 1.5 * cycle:
                raise ConfigError(
                    f"safety.{self.HEARTBEAT_TIMEOUT_KEY}: {ms} ms is shorter than 1.5 cycles "
                    f"of {spec.name} ({cycle * 1000:.0f} ms); use at least {1.5 * cycle * 1000:.0f}"
                )
            return units.ms(ms)
        return self.cfg.can.stale_cycles * cycle

    def _apply_active(self, active: frozenset[int], now: float) -> None:
        self._active = active
        for spec in self.rx_specs:
            self._rx[spec.frame_id].set_timeout(self._timeout_for(spec, active), now)
        for spec in self._periodic_tx():
            self._period[spec.frame_id] = spec.cycle_in_force_s(
                is_active(spec, active), self._loop_period_s
            )
        self._update_critical()

    def _periodic_tx(self) -> tuple[MessageSpec, ...]:
        """Transmitted messages that :meth:`poll` schedules by their cycle time."""
        return self.tx_specs

    @property
    def active_cylinders(self) -> tuple[int, ...]:
        """``can_index`` of the active group (their frames run at the fast cycle)."""
        return tuple(sorted(self._active))

    def _values_for(self, spec: MessageSpec, now: float) -> list[float] | None:
        raise NotImplementedError

    # ----------------------------------------------------------------- transmit

    def _send(self, codec: FrameCodec, values: Sequence[float], now: float) -> bool:
        """Send one frame without blocking; failures are counted, never raised."""
        fid = codec.frame_id
        counter = self._tx_counter[fid]
        self._tx_counter[fid] = (counter + 1) % COUNTER_MODULO
        if not self.bus_health.can_send():
            self.tx_counts["tx_suppressed"] += 1
            return False
        msg = _TxMessage(
            arbitration_id=fid,
            data=codec.encode(counter, values),
            is_extended_id=False,
            check=False,
        )
        try:
            self.bus.send(msg, timeout=0.0)
        except can.CanError as exc:
            self.bus_health.on_send_error(getattr(exc, "error_code", None), str(exc), now)
            return False
        except OSError as exc:
            self.bus_health.on_send_error(exc.errno, str(exc), now)
            return False
        self.tx_counts["tx_frames"] += 1
        self.bus_health.on_send_ok()
        return True

    def _send_due(self, now: float) -> None:
        for spec in self._periodic_tx():
            fid = spec.frame_id
            period = self._period[fid]
            if now < self._next_due[fid] - 0.25 * period:
                continue
            values = self._values_for(spec, now)
            if values is not None:
                self._send(self._codec_by_name[spec.name], values, now)
            nd = self._next_due[fid] + period
            if nd <= now:
                if nd + period <= now:
                    self.tx_counts["tx_overruns"] += 1
                nd = now + period
            self._next_due[fid] = nd

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
                    self.bus_health.on_frame_ok()
                    if rec.lost_frames != lost_before:
                        self._last_fault = now
                    self._on_accepted(rec, now)
                elif outcome in RX_FAULTS:
                    self._last_fault = now
                    last = self._fault_logged_at.get(rec.name, -math.inf)
                    if now - last > FAULT_HOLD_S:
                        log.warning(
                            "%s: %s (0x%03X) rejected: %s (repeats are counted, not logged)",
                            self.NODE,
                            rec.name,
                            rec.codec.frame_id,
                            outcome,
                        )
                    self._fault_logged_at[rec.name] = now
        self.rx_outcomes[outcome] += 1
        return outcome

    def _on_accepted(self, rec: RxRecord, now: float) -> None:
        """Hook: a frame passed all checks (the PLC side reads the active mask here)."""

    def _check_timeouts(self, now: float) -> None:
        for rec in self._rx.values():
            was = rec.was_fresh
            if rec.check_timeout(now):
                self._last_fault = now
                log.warning(
                    "%s: %s (0x%03X) stale: no valid frame for %.0f ms (timeout %.0f ms)",
                    self.NODE,
                    rec.name,
                    rec.codec.frame_id,
                    rec.age_s(now) * 1000.0,
                    rec.timeout_s * 1000.0,
                )
            elif rec.was_fresh and not was and rec.counters["timeouts"]:
                log.info("%s: %s receiving again", self.NODE, rec.name)

    def _recover(self, now: float) -> None:
        if not self.bus_health.due_for_reopen(now):
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

    def _critical_rows(self) -> Sequence[tuple[RxRecord, Sequence[int]]]:
        """This side's loop-rate inputs with the cylinder slots each carries (the IPC's
        positions, the PLC's valve commands); empty until the subclass has built them."""
        return ()

    def _update_critical(self) -> None:
        """The records the link is LOST without: the peer's heartbeat and the loop-rate
        rows that carry an active cylinder."""
        act = self._active
        self._critical_recs = (
            self._rx_by_name[self.HEARTBEAT],
            *(rec for rec, slots in self._critical_rows() if any(i in act for i in slots)),
        )

    def _critical(self) -> tuple[RxRecord, ...]:
        return self._critical_recs

    def state(self, now: float | None = None) -> LinkState:
        """OK / DEGRADED / LOST (see :class:`LinkState`)."""
        if now is None:
            now = self._clock()
        if not self.bus_health.can_send():
            return LinkState.LOST
        if not all_fresh(self._critical(), now):
            return LinkState.LOST
        if (
            self.bus_health.state is not BusState.ACTIVE
            or now - self._last_fault <= FAULT_HOLD_S
            or now - self.bus_health.last_fault_time <= FAULT_HOLD_S
            or not all_fresh(self._rx.values(), now)
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
                "age_ms": None if math.isinf(age) else round(age * 1000.0, 3),
                "timeout_ms": round(r.timeout_s * 1000.0, 3),
                "lost_frames": r.lost_frames,
                **dict(r.counters),
            }
        return {
            "node": self.NODE,
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


def _rows(catalog: Catalog, prefix: str) -> list[tuple[str, list[int]]]:
    return [(m.name, list(m.slots)) for m in catalog.with_prefix(prefix)]


# --------------------------------------------------------------------------- IPC side


class IpcLink(_Side):
    """The IPC (master) side: sends control word and valve commands, supervises the PLC.

    Critical messages (LOST when stale): ``PLC_Status`` and the rod positions of the
    active group. Timeouts: ``safety.plc_heartbeat_timeout_ms`` for the status,
    ``can.stale_cycles`` cycle times for the rest.
    """

    NODE = "IPC"
    HEARTBEAT = "PLC_Status"
    HEARTBEAT_TIMEOUT_KEY = "plc_heartbeat_timeout_ms"

    def __init__(self, cfg: ProjectConfig, bus: can.BusABC | None = None, **kwargs: Any):
        self._control = ControlWord()
        cat = kwargs.get("catalog") or load_catalog()
        self._valve = [(FrameCodec(m), list(m.slots)) for m in cat.with_prefix("IPC_ValveCmd_")]
        self._pos_rows = _rows(cat, "PLC_RodPos_")
        self._press_rows = _rows(cat, "PLC_Pressure_")
        self._last_hmi_seq: int | None = None
        # The decoded values (a new tuple per accepted frame) and the word built from
        # them: status() and hmi_target() run every cycle, a frame comes every 2-10.
        self._status_of: tuple[object, PlcStatus | None] = (None, None)
        self._hmi_of: tuple[object, HmiTarget | None] = (None, None)
        self._limits_of: tuple[object, LimitSwitches | None] = (None, None)
        super().__init__(cfg, bus, **kwargs)
        self._pos = [(self._rx_by_name[n], s) for n, s in self._pos_rows]
        self._press = [(self._rx_by_name[n], s) for n, s in self._press_rows]
        self._pos_fast = self._compile_rows(self._pos, 1)
        self._press_fast = self._compile_rows(self._press, 2)
        self._status_rec = self._rx_by_name["PLC_Status"]
        self._hmi_rec = self._rx_by_name["PLC_HmiTarget"]
        self._limits_rec = self._rx_by_name["PLC_Limits"]
        self._ctl_codec = self._codec_by_name["IPC_Control"]
        self._update_critical()
        spec = self.catalog.by_name("PLC_Status")
        #: The status counts as stale (a short loss) after ``can.stale_cycles`` of its
        #: cycle; the heartbeat timeout (``status()`` None, LOST) may be longer.
        self.status_stale_s = min(
            cfg.can.stale_cycles * spec.cycle_in_force_s(False, self._loop_period_s),
            self._status_rec.timeout_s,
        )

    def _periodic_tx(self) -> tuple[MessageSpec, ...]:
        return (self.catalog.by_name("IPC_Control"),)

    def _critical_rows(self) -> Sequence[tuple[RxRecord, Sequence[int]]]:
        return getattr(self, "_pos", ())

    # ----------------------------------------------------------------- commands

    @property
    def control(self) -> ControlWord:
        return self._control

    def set_control(self, word: ControlWord | None = None, **changes: Any) -> None:
        """Set the control word (whole, or fields by name: ``mode=``, ``enable=`` ...).

        A changed word is sent at once, then every ``GenMsgCycleTime`` by :meth:`poll`.
        """
        c = self._control
        if word is None and all(
            k in _CONTROL_FIELDS and getattr(c, k) == v for k, v in changes.items()
        ):
            return  # every field already so (the loop sets mode and enable every cycle)
        new = replace(word if word is not None else c, **changes)
        if new != self._control:
            self._control = new
            now = self._clock()
            self._send(self._ctl_codec, self._control_values(), now)
            self._next_due[self._ctl_codec.frame_id] = now + self._period[self._ctl_codec.frame_id]

    def _control_values(self) -> list[float]:
        c = self._control
        vals = {
            "ModeRequest": int(c.mode),
            "EnableRequest": int(c.enable),
            "StopRequest": int(c.stop),
            "FaultReset": int(c.fault_reset),
            "TargetAckStatus": int(c.ack_status),
            "TargetAckSeq": int(c.ack_seq) & 0xFF,
            "FastCylinderMask": _mask_of(self._active),
        }
        return [vals[n] for n in self._ctl_codec.signal_names]

    def _values_for(self, spec: MessageSpec, now: float) -> list[float] | None:
        return self._control_values()

    def set_active_cylinders(self, indices: Iterable[int], now: float | None = None) -> BusLoad:
        """Choose the cylinders whose frames run at the loop rate (e.g. switch to the sub
        frame's legs). Refused with :class:`BusLoadError` if the bus load would exceed
        ``can.max_bus_load_percent``. The PLC learns it from the next control word.
        """
        act = frozenset(int(i) for i in indices)
        bad = sorted(i for i in act if not 0 <= i < N_CYLINDERS)
        if bad:
            raise ValueError(f"can_index out of range 0..{N_CYLINDERS - 1}: {bad}")
        load = bus_load(self.cfg, act, self.catalog)
        if not load.ok:
            raise BusLoadError(
                f"active cylinders {sorted(act)} would load the bus to {load.load_percent:.1f} % "
                f"at {load.bitrate} bit/s; can.max_bus_load_percent is {load.max_load_percent}"
            )
        if now is None:
            now = self._clock()
        self._apply_active(act, now)
        self._send(self._ctl_codec, self._control_values(), now)
        return load

    def send_valve_commands(self, u: Sequence[float] | FloatArray, now: float | None = None) -> int:
        """Send the normalized spool commands of all 19 cylinders (``u[can_index]``).

        Frames with an active cylinder go every call (the loop rate); the others when
        their ``GenMsgCycleTime`` is due. Values outside [-1, 1] are clipped and NaN is
        sent as 0 (spool centred); both are counted (``tx.clipped``, ``tx.nan``).
        Never blocks. Returns the number of frames sent.
        """
        if now is None:
            now = self._clock()
        arr = np.asarray(u, dtype=float)
        if arr.shape != (N_CYLINDERS,):
            raise ValueError(
                f"valve commands: expected {N_CYLINDERS} values, got shape {arr.shape}"
            )
        # Plain floats (numpy's per-call overhead dominates on 19 values): NaN -> 0, then
        # clipped to [-1, 1], each counted, as np.where / np.clip did.
        vals = arr.tolist()
        nan = clipped = 0
        for i, v in enumerate(vals):
            if v != v:
                vals[i] = 0.0
                nan += 1
            elif v > 1.0:
                vals[i] = 1.0
                clipped += 1
            elif v < -1.0:
                vals[i] = -1.0
                clipped += 1
        if nan:
            self.tx_counts["nan"] += nan
        if clipped:
            self.tx_counts["clipped"] += clipped
        sent = 0
        period = self._loop_period_s
        for codec, slots in self._valve:
            fid = codec.frame_id
            if self._period.get(fid, 0.0) > period:  # inactive: on its own cycle
                due = self._next_due.get(fid, -math.inf)
                if now < due - 0.25 * period:
                    continue
                self._next_due[fid] = max(due + self._period[fid], now)
            sent += self._send(codec, [vals[i] for i in slots], now)
        return sent

    def _apply_active(self, active: frozenset[int], now: float) -> None:
        super()._apply_active(active, now)
        for codec, _ in getattr(self, "_valve", []):
            spec = codec.spec
            self._period[codec.frame_id] = spec.cycle_in_force_s(
                is_active(spec, active), self._loop_period_s
            )

    # ----------------------------------------------------------------- readings

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

    def _array(
        self,
        rows: list[tuple[RxRecord, int, int, int, int]],
        width: int,
        si_per_unit: float,
        now: float,
    ) -> Reading:
        """The latest values of ``rows`` by ``can_index`` in SI; NaN where not usable.

        Plain list slices per message, one numpy conversion at the end (this runs twice
        every loop cycle).
        """
        vals = [math.nan] * (N_CYLINDERS * width)
        ages = [math.inf] * N_CYLINDERS
        for rec, lo, hi, vlo, vhi in rows:
            last = rec.last_rx
            if last is None:
                continue
            age = now - last
            ages[lo:hi] = [age] * (hi - lo)
            # rec.latest(now), written out: values while fresh (RxRecord.fresh)
            v = rec.values
            if v is not None and age <= (
                rec.grace_timeout_s if now < rec.grace_until else rec.timeout_s
            ):
                vals[vlo:vhi] = v[: vhi - vlo]
        val = np.array(vals)
        val *= si_per_unit  # DBC unit -> SI, factor from config.units
        if width > 1:
            val = val.reshape(N_CYLINDERS, width)
        return Reading(value=val, valid=val == val, age_s=np.array(ages))  # == : not NaN

    def positions_m(self, now: float | None = None) -> Reading:
        """Rod positions from fully retracted [m], by ``can_index`` (NaN where not valid)."""
        return self._array(self._pos_fast, 1, units.MM, self._clock() if now is None else now)

    def pressures_pa(self, now: float | None = None) -> Reading:
        """Chamber pressures [Pa], shape (19, 2): column 0 cap side, column 1 rod side."""
        return self._array(self._press_fast, 2, units.MPA, self._clock() if now is None else now)

    def status(self, now: float | None = None) -> PlcStatus | None:
        """The PLC status word, or None when stale (the PLC is then considered lost)."""
        v = self._status_rec.latest(self._clock() if now is None else now)
        if v is None:
            return None
        if v is self._status_of[0]:  # the same frame as last call: the same (frozen) word
            return self._status_of[1]
        d = dict(zip(self._status_rec.codec.signal_names, v, strict=True))
        code = int(d["FaultCode"])
        st = PlcStatus(
            mode=Mode(int(d["ModeActual"])),
            estop=bool(d["EStop"]),
            pump_running=bool(d["PumpRunning"]),
            drives_enabled=bool(d["DrivesEnabled"]),
            command_timeout=bool(d["CommandTimeout"]),
            fault=Fault(code) if code in Fault._value2member_map_ else code,
            supply_pressure_pa=units.mpa(d["SupplyPressure"]),
        )
        self._status_of = (v, st)
        return st

    def status_age_s(self, now: float | None = None) -> float:
        """Time since the last valid PLC status frame (inf: never)."""
        return self._status_rec.age_s(self._clock() if now is None else now)

    def failed_positions(self, indices: Iterable[int], now: float | None = None) -> list[int]:
        """Of ``indices``, the cylinders whose position frame is fresh but whose sensor
        reports a fault (SENSOR_FAULT value): a failed sensor, not a lost frame."""
        if now is None:
            now = self._clock()
        want = set(indices)
        out = []
        for rec, slots in self._pos:
            if not rec.fresh(now) or rec.values is None:
                continue
            for k, i in enumerate(slots):
                if i in want and rec.values[k] != rec.values[k]:
                    out.append(i)
        return sorted(out)

    def hmi_target(self, now: float | None = None) -> HmiTarget | None:
        """The operator's current target request, or None when stale."""
        v = self._hmi_rec.latest(self._clock() if now is None else now)
        if v is None:
            return None
        if v is self._hmi_of[0]:  # the same frame as last call: the same (frozen) target
            return self._hmi_of[1]
        d = dict(zip(self._hmi_rec.codec.signal_names, v, strict=True))
        t = HmiTarget(
            roll_rad=units.deg(d["TargetRoll"]),
            pitch_rad=units.deg(d["TargetPitch"]),
            request=TargetRequest(int(d["TargetRequest"])),
            seq=int(d["TargetSeq"]),
        )
        self._hmi_of = (v, t)
        return t

    def new_hmi_request(self, now: float | None = None) -> HmiTarget | None:
        """A fresh HMI request whose ``seq`` has not been returned before, else None."""
        t = self.hmi_target(now)
        if t is None or t.request is TargetRequest.NONE or t.seq == self._last_hmi_seq:
            return None
        self._last_hmi_seq = t.seq
        return t

    def limit_switches(self, now: float | None = None) -> LimitSwitches | None:
        """The limit switches by ``can_index``, or None when stale. The same object (its
        arrays read-only) until the next frame: the loop asks every cycle."""
        v = self._limits_rec.latest(self._clock() if now is None else now)
        if v is None:
            return None
        if v is self._limits_of[0]:
            return self._limits_of[1]
        d = dict(zip(self._limits_rec.codec.signal_names, v, strict=True))
        bits = np.arange(N_CYLINDERS)
        ls = LimitSwitches(
            retracted=(int(d["LimitRetractedMask"]) >> bits) & 1 == 1,
            extended=(int(d["LimitExtendedMask"]) >> bits) & 1 == 1,
        )
        ls.retracted.flags.writeable = False
        ls.extended.flags.writeable = False
        self._limits_of = (v, ls)
        return ls


# --------------------------------------------------------------------------- PLC side


class PlcLink(_Side):
    """The PLC (device) side, for ``hil_sim``: sends status and sensors at their cycle
    times (fast for the active group the IPC announces), supervises the IPC commands.

    Critical messages (LOST when stale): ``IPC_Control`` and the valve frames of the
    active group. A PLC acts on two things: :meth:`command_timeout` (commands stale:
    spools to centre at once, drives again when fresh frames come back) and
    :meth:`ipc_timeout` (the loss has lasted longer than ``safety.command_timeout_ms``:
    latch IPC_TIMEOUT).
    """

    NODE = "PLC"
    HEARTBEAT = "IPC_Control"
    HEARTBEAT_TIMEOUT_KEY = "command_timeout_ms"

    def __init__(self, cfg: ProjectConfig, bus: can.BusABC | None = None, **kwargs: Any):
        self._status = PlcStatus()
        self._pos_mm = [math.nan] * N_CYLINDERS
        self._press_mpa = [[math.nan, math.nan] for _ in range(N_CYLINDERS)]
        self._limits = (0, 0)
        self._hmi: HmiTarget | None = None
        super().__init__(cfg, bus, **kwargs)
        self._ctl_rec = self._rx_by_name["IPC_Control"]
        self._valve = [(self._rx_by_name[n], s) for n, s in _rows(self.catalog, "IPC_ValveCmd_")]
        self._ipc_timeout_s = units.ms(cfg.safety.command_timeout_ms)
        self._update_critical()

    def _critical_rows(self) -> Sequence[tuple[RxRecord, Sequence[int]]]:
        return getattr(self, "_valve", ())

    def _on_accepted(self, rec: RxRecord, now: float) -> None:
        if rec.name == "IPC_Control" and rec.values is not None:
            i = rec.codec.signal_names.index("FastCylinderMask")
            act = _indices_of(int(rec.values[i]))
            if act != self._active:
                log.info("PLC: active group now %s", sorted(act))
                self._apply_active(act, now)

    # ----------------------------------------------------------------- inputs

    def control(self, now: float | None = None) -> ControlWord | None:
        """The IPC control word, or None when stale (command timeout)."""
        v = self._ctl_rec.latest(self._clock() if now is None else now)
        if v is None:
            return None
        d = dict(zip(self._ctl_rec.codec.signal_names, v, strict=True))
        return ControlWord(
            mode=Mode(int(d["ModeRequest"])),
            enable=bool(d["EnableRequest"]),
            stop=bool(d["StopRequest"]),
            fault_reset=bool(d["FaultReset"]),
            ack_seq=int(d["TargetAckSeq"]),
            ack_status=TargetAck(int(d["TargetAckStatus"])),
        )

    def valve_commands(self, now: float | None = None) -> Reading:
        """Spool commands in [-1, 1] by ``can_index``; NaN where stale (centre the spool)."""
        if now is None:
            now = self._clock()
        val = np.full(N_CYLINDERS, math.nan)
        age = np.full(N_CYLINDERS, math.inf)
        for rec, slots in self._valve:
            age[slots] = rec.age_s(now)
            v = rec.latest(now)
            if v is not None:
                val[slots] = v
        return Reading(value=val, valid=~np.isnan(val), age_s=age)

    def command_timeout(self, now: float | None = None) -> bool:
        """True when the control word or any valve frame is stale: hold spools at centre."""
        if now is None:
            now = self._clock()
        return not (self._ctl_rec.fresh(now) and all(r.fresh(now) for r, _ in self._valve))

    def ipc_timeout(self, now: float | None = None) -> bool:
        """True when the control word or a valve frame has not been received for longer
        than ``safety.command_timeout_ms``: the loss is no longer short (latch a fault)."""
        if now is None:
            now = self._clock()
        limit = self._ipc_timeout_s
        if self._ctl_rec.age_s(now) > limit:
            return True
        return any(r.age_s(now) > limit for r, _ in self._valve)

    # ----------------------------------------------------------------- outputs

    def set_status(self, status: PlcStatus) -> None:
        self._status = status

    def set_positions_m(self, x: Sequence[float] | FloatArray) -> None:
        """Rod positions [m] by ``can_index``; NaN is sent as SENSOR_FAULT."""
        arr = np.asarray(x, dtype=float)
        if arr.shape != (N_CYLINDERS,):
            raise ValueError(f"positions: expected {N_CYLINDERS} values, got shape {arr.shape}")
        self._pos_mm = (arr / units.MM).tolist()

    def set_pressures_pa(self, p: Sequence[Sequence[float]] | FloatArray) -> None:
        """Pressures [Pa], shape (19, 2): cap, rod side; NaN is sent as SENSOR_FAULT."""
        arr = np.asarray(p, dtype=float)
        if arr.shape != (N_CYLINDERS, 2):
            raise ValueError(f"pressures: expected shape ({N_CYLINDERS}, 2), got {arr.shape}")
        self._press_mpa = (arr / units.MPA).tolist()

    def set_limit_switches(self, retracted: Iterable[bool], extended: Iterable[bool]) -> None:
        self._limits = (
            _mask_of(i for i, b in enumerate(retracted) if b),
            _mask_of(i for i, b in enumerate(extended) if b),
        )

    def set_hmi_target(self, target: HmiTarget | None) -> None:
        self._hmi = target

    def _values_for(self, spec: MessageSpec, now: float) -> list[float] | None:
        name = spec.name
        names = self._codec_by_name[name].signal_names
        if name.startswith("PLC_RodPos_"):
            return [self._pos_mm[i] for i in spec.slots]
        if name.startswith("PLC_Pressure_"):
            return [v for i in spec.slots for v in self._press_mpa[i]]
        if name == "PLC_Status":
            s = self._status
            d: dict[str, float] = {
                "ModeActual": int(s.mode),
                "EStop": int(s.estop),
                "PumpRunning": int(s.pump_running),
                "DrivesEnabled": int(s.drives_enabled),
                "CommandTimeout": int(s.command_timeout or self.command_timeout(now)),
                "FaultCode": int(s.fault),
                "SupplyPressure": units.to_mpa(s.supply_pressure_pa),
            }
        elif name == "PLC_Limits":
            d = {"LimitRetractedMask": self._limits[0], "LimitExtendedMask": self._limits[1]}
        elif name == "PLC_HmiTarget":
            t = self._hmi
            d = {
                "TargetRoll": 0.0 if t is None else units.to_deg(t.roll_rad),
                "TargetPitch": 0.0 if t is None else units.to_deg(t.pitch_rad),
                "TargetRequest": 0 if t is None else int(t.request),
                "TargetSeq": 0 if t is None else t.seq & 0xFF,
            }
        else:  # pragma: no cover - the DBC has no other PLC message
            return None
        return [d[n] for n in names]
