"""The IPC (master) side of the link, :class:`IpcLink`: what ``ipc_app`` uses."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import replace
from typing import Any

import can
import numpy as np

from config import units
from config.schema import N_CYLINDERS, ProjectConfig
from plc_bridge.busload import BusLoad, bus_load
from plc_bridge.catalog import MessageSpec
from plc_bridge.codec import FrameCodec
from plc_bridge.errors import BusLoadError
from plc_bridge.link.side import LinkSide, SideRole, mask_of
from plc_bridge.link.words import (
    CONTROL_FIELDS,
    ControlWord,
    Fault,
    FloatArray,
    HmiTarget,
    LimitSwitches,
    Mode,
    PlcStatus,
    Reading,
    TargetRequest,
)


class IpcLink(LinkSide):
    """The IPC (master) side: sends control word and valve commands, supervises the PLC.

    Critical messages (LOST when stale): ``PLC_Status`` and the rod positions of the
    active group. Timeouts: ``safety.plc_heartbeat_timeout_ms`` for the status,
    ``can.stale_cycles`` cycle times for the rest.
    """

    ROLE = SideRole(
        node="IPC",
        heartbeat="PLC_Status",
        heartbeat_timeout_key="plc_heartbeat_timeout_ms",
        loop_rx_prefix="PLC_RodPos_",
        scheduled_tx=("IPC_Control",),
    )

    def __init__(self, cfg: ProjectConfig, bus: can.BusABC | None = None, **kwargs: Any):
        super().__init__(cfg, bus, role=self.ROLE, **kwargs)
        self._control = ControlWord()
        #: the valve frames: (codec, first slot, end slot), each a run of can_index slots
        self._valve: list[tuple[FrameCodec, int, int]] = []
        for m in self.catalog.with_prefix("IPC_ValveCmd_"):
            lo, hi = m.slots[0], m.slots[-1] + 1
            if list(m.slots) != list(range(lo, hi)):
                raise ValueError(f"{m.name}: slots {m.slots} are not consecutive")
            self._valve.append((self._codec_by_name[m.name], lo, hi))
        self._last_hmi_seq: int | None = None
        self._pos = self._loop_rows
        self._press = [
            (self._rx_by_name[m.name], list(m.slots))
            for m in self.catalog.with_prefix("PLC_Pressure_")
        ]
        self._press_fast = self._slot_group(self._press, 2)
        self._status_rec = self._rx_by_name["PLC_Status"]
        self._hmi_rec = self._rx_by_name["PLC_HmiTarget"]
        self._limits_rec = self._rx_by_name["PLC_Limits"]
        self._ctl_codec = self._codec_by_name["IPC_Control"]
        spec = self.catalog.by_name("PLC_Status")
        #: The status counts as stale (a short loss) after ``can.stale_cycles`` of its
        #: cycle; the heartbeat timeout (``status()`` None, LOST) may be longer.
        self.status_stale_s = min(
            cfg.can.stale_cycles * spec.cycle_in_force_s(False, self._loop_period_s),
            self._status_rec.timeout_s,
        )

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
            k in CONTROL_FIELDS and getattr(c, k) == v for k, v in changes.items()
        ):
            return  # every field already so (the loop sets mode and enable every cycle)
        if word is not None and not changes:
            new = word  # (frozen: taken as it is)
        else:
            new = replace(word if word is not None else c, **changes)
        if new != c:
            self._control = new
            now = self._clock()
            self._send(self._ctl_codec, self._control_values(), now)
            self._next_due[self._ctl_codec.frame_id] = now + self._period[self._ctl_codec.frame_id]
            self._wake = -math.inf

    def _control_values(self) -> list[float]:
        c = self._control
        vals = {
            "ModeRequest": int(c.mode),
            "EnableRequest": int(c.enable),
            "StopRequest": int(c.stop),
            "FaultReset": int(c.fault_reset),
            "TargetAckStatus": int(c.ack_status),
            "TargetAckSeq": int(c.ack_seq) & 0xFF,
            "FastCylinderMask": mask_of(self._active),
            "PackMLState": int(c.state),
            "UnitMode": int(c.unit_mode),
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
        # clipped to [-1, 1], each counted, as np.where / np.clip did. (The sum is NaN
        # with a NaN in it; min and max bound the rest.)
        vals = arr.tolist()
        total = sum(vals)
        if total != total or min(vals) < -1.0 or max(vals) > 1.0:
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
        periods, next_due = self._period, self._next_due
        for codec, lo, hi in self._valve:
            fid = codec.frame_id
            own = periods.get(fid, 0.0)
            if own > period:  # inactive: on its own cycle
                due = next_due.get(fid, -math.inf)
                if now < due - 0.25 * period:
                    continue
                next_due[fid] = max(due + own, now)
                self._wake = -math.inf
            sent += self._send(codec, vals[lo:hi], now)
        return sent

    # ----------------------------------------------------------------- readings

    def positions_m(self, now: float | None = None) -> Reading:
        """Rod positions from fully retracted [m], by ``can_index`` (NaN where not valid)."""
        return self._array(self._loop_slices, units.MM, self._clock() if now is None else now)

    def pressures_pa(self, now: float | None = None) -> Reading:
        """Chamber pressures [Pa], shape (19, 2): column 0 cap side, column 1 rod side."""
        return self._array(self._press_fast, units.MPA, self._clock() if now is None else now)

    def status(self, now: float | None = None) -> PlcStatus | None:
        """The PLC status word, or None when stale (the PLC is then considered lost)."""
        return self._word(self._status_rec, _plc_status, now)

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
        return self._word(self._hmi_rec, _hmi_target, now)

    def new_hmi_request(self, now: float | None = None) -> HmiTarget | None:
        """A fresh HMI request whose ``seq`` has not been returned before, else None."""
        t = self.hmi_target(now)
        if t is None or t.request is TargetRequest.NONE or t.seq == self._last_hmi_seq:
            return None
        self._last_hmi_seq = t.seq
        return t

    def limit_switches(self, now: float | None = None) -> LimitSwitches | None:
        """The limit switches by ``can_index``, or None when stale. The same object (its
        arrays read-only) while the frame's values stay the same: the loop asks every
        cycle."""
        return self._word(self._limits_rec, _limit_switches, now)


def _plc_status(d: dict[str, float]) -> PlcStatus:
    code = int(d["FaultCode"])
    return PlcStatus(
        mode=Mode(int(d["ModeActual"])),
        estop=bool(d["EStop"]),
        pump_running=bool(d["PumpRunning"]),
        drives_enabled=bool(d["DrivesEnabled"]),
        command_timeout=bool(d["CommandTimeout"]),
        fault=Fault(code) if code in Fault._value2member_map_ else code,
        supply_pressure_pa=units.mpa(d["SupplyPressure"]),
        walk_available=bool(d["WalkAvailable"]),
    )


def _hmi_target(d: dict[str, float]) -> HmiTarget:
    return HmiTarget(
        roll_rad=units.deg(d["TargetRoll"]),
        pitch_rad=units.deg(d["TargetPitch"]),
        request=TargetRequest(int(d["TargetRequest"])),
        seq=int(d["TargetSeq"]),
        walk_steps=int(d["WalkSteps"]),
    )


def _limit_switches(d: dict[str, float]) -> LimitSwitches:
    bits = np.arange(N_CYLINDERS)
    ls = LimitSwitches(
        retracted=(int(d["LimitRetractedMask"]) >> bits) & 1 == 1,
        extended=(int(d["LimitExtendedMask"]) >> bits) & 1 == 1,
    )
    ls.retracted.flags.writeable = False
    ls.extended.flags.writeable = False
    return ls
