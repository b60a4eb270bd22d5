"""The PLC (device) side of the link, :class:`PlcLink`: what ``hil_sim`` plays."""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import can
import numpy as np

from config import units
from config.schema import N_CYLINDERS, ProjectConfig
from plc_bridge.catalog import MessageSpec
from plc_bridge.link.side import LinkSide, SideRole, indices_of, mask_of
from plc_bridge.link.words import (
    ControlWord,
    FloatArray,
    HmiTarget,
    Mode,
    PlcStatus,
    Reading,
    TargetAck,
)
from plc_bridge.supervision import SURELY_MARGIN_S, RxRecord

log = logging.getLogger("plc_bridge")


class PlcLink(LinkSide):
    """The PLC (device) side, for ``hil_sim``: sends status and sensors at their cycle
    times (fast for the active group the IPC announces), supervises the IPC commands.

    Critical messages (LOST when stale): ``IPC_Control`` and the valve frames of the
    active group. A PLC acts on two things: :meth:`command_timeout` (commands stale:
    spools to centre at once, drives again when fresh frames come back) and
    :meth:`ipc_timeout` (the loss has lasted longer than ``safety.command_timeout_ms``:
    latch IPC_TIMEOUT).
    """

    ROLE = SideRole(
        node="PLC",
        heartbeat="IPC_Control",
        heartbeat_timeout_key="command_timeout_ms",
        loop_rx_prefix="IPC_ValveCmd_",
    )

    def __init__(self, cfg: ProjectConfig, bus: can.BusABC | None = None, **kwargs: Any):
        super().__init__(cfg, bus, role=self.ROLE, **kwargs)
        self._status = PlcStatus()
        # the latest readings as given (SI), and in DBC units once a frame needs them
        self._pos_m: FloatArray = np.full(N_CYLINDERS, math.nan)
        self._press_pa: FloatArray = np.full((N_CYLINDERS, 2), math.nan)
        self._pos_mm: list[float] | None = None
        #: (19, 2) flat by rows: cap, rod of can_index 0, then of 1, ...
        self._press_mpa: list[float] | None = None
        self._deferred_pos: Callable[[], None] | None = None
        self._deferred_press: Callable[[], None] | None = None
        self._limits = (0, 0)
        self._hmi: HmiTarget | None = None
        self._ctl_rec = self._rx_by_name["IPC_Control"]
        self._valve = self._loop_rows
        #: what the PLC's command timeouts watch: the control word and the valve frames
        self._command_recs = (self._ctl_rec, *(rec for rec, _ in self._valve))
        self._ipc_timeout_s = units.ms(cfg.safety.command_timeout_ms)
        # before these times the answers of command_timeout / ipc_timeout are certainly
        # False (the PLC asks every scan; a frame accepted only moves them on)
        self._commands_fresh_until = -math.inf
        self._ipc_seen_until = -math.inf
        #: per sent message (frame id): what builds its values, chosen once here, not
        #: by its name per frame (the positions alone are some 800 frames a second)
        self._builders: dict[int, Callable[[float], list[float]]] = {
            spec.frame_id: self._builder(spec) for spec in self.tx_specs
        }

    def _on_accepted(self, rec: RxRecord, now: float) -> None:
        if rec.name == "IPC_Control" and rec.values is not None:
            i = rec.codec.signal_names.index("FastCylinderMask")
            act = indices_of(int(rec.values[i]))
            if act != self._active:
                log.info("PLC: active group now %s", sorted(act))
                self._apply_active(act, now)
                self._commands_fresh_until = -math.inf  # the timeouts changed

    # ----------------------------------------------------------------- inputs

    def control(self, now: float | None = None) -> ControlWord | None:
        """The IPC control word, or None when stale (command timeout)."""
        return self._word(self._ctl_rec, _control_word, now)

    def valve_commands(self, now: float | None = None) -> Reading:
        """Spool commands in [-1, 1] by ``can_index``; NaN where stale (centre the spool)."""
        return self._array(self._loop_slices, 1.0, self._clock() if now is None else now)

    def command_timeout(self, now: float | None = None) -> bool:
        """True when the control word or any valve frame is stale: hold spools at centre."""
        if now is None:
            now = self._clock()
        if now < self._commands_fresh_until:
            return False
        until = math.inf
        for r in self._command_recs:
            if not r.fresh(now):
                return True
            until = min(until, r.fresh_until_s())
        self._commands_fresh_until = until
        return False

    def ipc_timeout(self, now: float | None = None) -> bool:
        """True when the control word or a valve frame has not been received for longer
        than ``safety.command_timeout_ms``: the loss is no longer short (latch a fault)."""
        if now is None:
            now = self._clock()
        if now < self._ipc_seen_until:
            return False
        limit = self._ipc_timeout_s
        oldest = math.inf
        for r in self._command_recs:
            if r.age_s(now) > limit:
                return True
            last = r.last_rx
            if last is not None and last < oldest:
                oldest = last
        self._ipc_seen_until = oldest + limit - SURELY_MARGIN_S
        return False

    # ----------------------------------------------------------------- outputs

    def set_status(self, status: PlcStatus) -> None:
        self._status = status

    def set_positions_m(self, x: Sequence[float] | FloatArray) -> None:
        """Rod positions [m] by ``can_index``; NaN is sent as SENSOR_FAULT."""
        arr = np.array(x, dtype=float)
        if arr.shape != (N_CYLINDERS,):
            raise ValueError(f"positions: expected {N_CYLINDERS} values, got shape {arr.shape}")
        self._pos_m, self._pos_mm = arr, None

    def set_pressures_pa(self, p: Sequence[Sequence[float]] | FloatArray) -> None:
        """Pressures [Pa], shape (19, 2): cap, rod side; NaN is sent as SENSOR_FAULT."""
        arr = np.array(p, dtype=float)
        if arr.shape != (N_CYLINDERS, 2):
            raise ValueError(f"pressures: expected shape ({N_CYLINDERS}, 2), got {arr.shape}")
        self._press_pa, self._press_mpa = arr, None

    def defer_readings(
        self,
        positions: Callable[[], None] | None,
        pressures: Callable[[], None] | None = None,
    ) -> None:
        """Readings on demand: ``positions`` is called once, before the next frame that
        carries positions is built in :meth:`poll`, and sets them
        (:meth:`set_positions_m`); ``pressures`` likewise for the pressures
        (:meth:`set_pressures_pa`); ``None``: no longer. For a simulated PLC whose
        transducers sample every scan while most scans send none of those frames."""
        self._deferred_pos = positions
        self._deferred_press = pressures

    def set_limit_switches(self, retracted: Iterable[bool], extended: Iterable[bool]) -> None:
        self._limits = (
            mask_of(i for i, b in enumerate(retracted) if b),
            mask_of(i for i, b in enumerate(extended) if b),
        )

    def set_hmi_target(self, target: HmiTarget | None) -> None:
        self._hmi = target

    def _values_for(self, spec: MessageSpec, now: float) -> list[float] | None:
        return self._builders[spec.frame_id](now)

    @staticmethod
    def tx_kind(spec: MessageSpec) -> str:
        """What a message the PLC sends carries: ``positions``, ``pressures``, ``status``,
        ``limits`` or ``hmi`` (:meth:`_builder`; the simulator's compiled scan too)."""
        name = spec.name
        if name.startswith("PLC_RodPos_"):
            return "positions"
        if name.startswith("PLC_Pressure_"):
            return "pressures"
        kinds = {"PLC_Status": "status", "PLC_Limits": "limits", "PLC_HmiTarget": "hmi"}
        if name not in kinds:
            raise ValueError(f"{name}: the PLC sends no such message")
        return kinds[name]

    def _builder(self, spec: MessageSpec) -> Callable[[float], list[float]]:
        """The function that gives ``spec``'s values (DBC units, in its signals' order)."""
        kind = self.tx_kind(spec)
        if kind in ("positions", "pressures"):
            lo, hi = spec.slots[0], spec.slots[-1] + 1
            if list(spec.slots) != list(range(lo, hi)):
                raise ValueError(f"{spec.name}: slots {spec.slots} are not consecutive")
            if kind == "positions":
                return lambda _now: self._positions_mm()[lo:hi]
            return lambda _now: self._pressures_mpa()[2 * lo : 2 * hi]
        names = self._codec_by_name[spec.name].signal_names
        if kind == "status":
            return lambda now: self._status_values(names, now)
        if kind == "limits":
            return lambda _now: [
                {"LimitRetractedMask": self._limits[0], "LimitExtendedMask": self._limits[1]}[n]
                for n in names
            ]
        return lambda _now: self._hmi_values(names)

    def _positions_mm(self) -> list[float]:
        """The latest positions in DBC units (mm, by ``can_index``), the deferred ones
        taken first."""
        source = self._deferred_pos
        if source is not None:
            self._deferred_pos = None
            source()
        pos = self._pos_mm
        if pos is None:
            pos = self._pos_mm = (self._pos_m / units.MM).tolist()
        return pos

    def _pressures_mpa(self) -> list[float]:
        """The latest pressures in DBC units (MPa; cap, rod by ``can_index``, flat)."""
        source = self._deferred_press
        if source is not None:
            self._deferred_press = None
            source()
        press = self._press_mpa
        if press is None:
            press = self._press_mpa = (self._press_pa / units.MPA).ravel().tolist()
        return press

    def _status_values(self, names: tuple[str, ...], now: float) -> list[float]:
        s = self._status
        d: dict[str, float] = {
            "ModeActual": int(s.mode),
            "EStop": int(s.estop),
            "PumpRunning": int(s.pump_running),
            "DrivesEnabled": int(s.drives_enabled),
            "CommandTimeout": int(s.command_timeout or self.command_timeout(now)),
            "FaultCode": int(s.fault),
            "SupplyPressure": units.to_mpa(s.supply_pressure_pa),
            "WalkAvailable": int(s.walk_available),
        }
        return [d[n] for n in names]

    def _hmi_values(self, names: tuple[str, ...]) -> list[float]:
        t = self._hmi
        d: dict[str, float] = {
            "TargetRoll": 0.0 if t is None else units.to_deg(t.roll_rad),
            "TargetPitch": 0.0 if t is None else units.to_deg(t.pitch_rad),
            "TargetRequest": 0 if t is None else int(t.request),
            "TargetSeq": 0 if t is None else t.seq & 0xFF,
            "WalkSteps": 0 if t is None else t.walk_steps & 0x3,
        }
        return [d[n] for n in names]


def _control_word(d: dict[str, float]) -> ControlWord:
    return ControlWord(
        mode=Mode(int(d["ModeRequest"])),
        enable=bool(d["EnableRequest"]),
        stop=bool(d["StopRequest"]),
        fault_reset=bool(d["FaultReset"]),
        ack_seq=int(d["TargetAckSeq"]),
        ack_status=TargetAck(int(d["TargetAckStatus"])),
        state=int(d["PackMLState"]),
        unit_mode=int(d["UnitMode"]),
    )
