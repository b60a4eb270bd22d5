"""The service's control step: read -> interlocks -> modes -> update -> write.

:class:`ServiceCore` owns no thread and no clock: :meth:`ServiceCore.step` is called once
per period with the time, by :class:`~ipc_app.service.loop.FixedRateLoop` in the service
or in lockstep with the HIL simulator in tests and the demo. Its work per cycle is
bounded: drain the CAN receive queue, a fixed set of checks, one trajectory sample, eight
controller updates, two CAN sends. Planning runs in the worker process; the control
channel's threads only call the (thread-safe) mode machine and read the last snapshot.

Interlocks are data (:mod:`ipc_app.service.interlocks`: which one, its config key, when
it applies); a tripped check is a :class:`~ipc_app.service.interlocks.Cause` and the
reaction a controlled stop: valves closed, load held, FAULT latched until ``reset``.

A short loss of the link (the active group's rod positions or the PLC status stale, or
the PLC reporting the IPC's commands stale) suspends a motion instead (SUSPENDED: valves
closed, the trajectory clock stopped). Once fresh frames are back for
:attr:`ServiceCore.RESUME_FRESH_CYCLES` cycles and the rods are within the sync band of
where they stopped, the motion resumes by itself with the trajectory shifted in time; a
loss longer than its timeout latches the fault.

E-stop from the PLC takes the machine to ESTOP (valves closed) until released and reset.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass
from typing import Any, NamedTuple, Protocol

import numpy as np
import structlog

from config import units
from config.schema import ProjectConfig
from ipc_app.control.attitude import AttitudeController
from ipc_app.model.composition import check_attitude
from ipc_app.model.kinematics import fit_layer
from ipc_app.service.interlocks import Cause, Interlock, Latched
from ipc_app.service.modes import SUSPENDABLE_MODES, Mode, ModeMachine, Transition
from ipc_app.service.record import RunRecorder
from ipc_app.service.worker import PlanResult
from plc_bridge.link import Fault, IpcLink, LinkState, Reading, TargetAck, TargetRequest
from plc_bridge.link import Mode as PlcMode

log = structlog.get_logger("wara.service")

#: Numeric mode in the run record (``mode_code`` column).
_MODE_CODES = {m: i for i, m in enumerate(Mode)}


class Planner(Protocol):
    """What the core needs of the planner worker (non-blocking)."""

    def submit(
        self,
        request_id: int,
        roll_deg: float,
        pitch_deg: float,
        start_upper_m: Any = ...,
        start_lower_m: Any = ...,
    ) -> bool: ...

    def poll(self) -> PlanResult | None: ...


@dataclass
class MotionStats:
    """Figures of the present / last adjustment, for the operator and the demo."""

    target_deg: tuple[float, float] = (0.0, 0.0)
    started_s: float = 0.0
    duration_s: float = 0.0
    max_twist_m: float = 0.0
    max_sync_error_m: float = 0.0
    hold_sync_error_m: float = 0.0
    hold_samples: int = 0
    plan: dict[str, Any] | None = None


class _Published(NamedTuple):
    """One cycle's figures for :meth:`ServiceCore.snapshot` (built in the caller's thread)."""

    modes: dict[str, Any]
    now: float
    x: np.ndarray
    link: LinkState
    metrics: dict[str, Any]
    motion: MotionStats
    loop: dict[str, Any]
    ride: tuple[int, int]


class ServiceCore:
    """One IPC service: modes, interlocks, planner hand-off and the attitude loops."""

    #: Cycles of HOLDING before the standstill figures are taken (let the hold settle).
    HOLD_SETTLE_S = 1.0
    #: Cycles of fresh frames before a suspended motion is checked and resumed.
    RESUME_FRESH_CYCLES = 3

    def __init__(
        self,
        cfg: ProjectConfig,
        link: IpcLink,
        planner: Planner,
        *,
        record: RunRecorder | None = None,
        boot_timeout_s: float = 5.0,
    ) -> None:
        self.cfg = cfg
        self.link = link
        self.planner = planner
        self.record = record
        self.period_s = cfg.control.period_s
        self.boot_timeout_s = boot_timeout_s
        self.attitude = AttitudeController(cfg, self.period_s)
        self.active = self.attitude.layers["lower"] + self.attitude.layers["upper"]
        self.bus_load = link.set_active_cylinders(self.active)
        self._by_index = cfg.cylinders_by_can_index  # a property that sorts: once here
        self._active_ids = [(i, self._by_index[i].id) for i in self.active]
        self.stroke = np.array([c.stroke_m for c in self._by_index])
        s = cfg.safety
        self.max_twist_m = units.mm(s.max_twist_mm)
        self.max_sync_m = units.mm(s.max_sync_error_mm)
        self.max_tracking_m = units.mm(s.max_tracking_error_mm)
        self.max_pressure_pa = units.mpa(s.max_pressure_mpa)
        self.end_margin_m = units.mm(s.stroke_end_margin_mm)
        self.sensor_timeout_s = units.ms(s.sensor_timeout_ms)
        self.max_suspend_s = units.ms(s.max_suspend_ms)
        self._active_arr = np.array(self.active, dtype=np.intp)
        self._stroke_hi = self.stroke[self._active_arr] - self.end_margin_m
        self._stroke_hi_list: list[float] = self._stroke_hi.tolist()
        # the last limit-switch word and its per-active-cylinder mask (_motion_checks)
        self._limits_of: tuple[object, list[bool] | None] = (None, None)
        self._present: list[Cause] = []  # interlock conditions present this cycle
        self.modes = ModeMachine(
            active_causes=lambda: list(self._present),
            on_transition=self._on_transition,
            on_fault=self._on_fault,
        )
        self._request_id = 0
        # ride-through: suspends and resumes so far, the suspension in progress
        self.suspends = 0
        self.resumes = 0
        self._suspended_at = 0.0
        self._fresh_cycles = 0
        self._last_drive_t: float | None = None
        self._stop_ref: np.ndarray | None = None
        self._reset_requested = False
        self._reset_until: float | None = None
        self._reset_outcome: dict[str, Any] | None = None
        self._submitted = False
        self._boot_since: float | None = None
        self._now = 0.0
        self.motion = MotionStats()
        self.last_motion: MotionStats | None = None
        self._outcome_cv = threading.Condition()
        self._outcome: dict[str, Any] | None = None
        # What the last cycle published; the status dict is built from it on request,
        # in the caller's thread (see snapshot()), not every cycle in the loop.
        self._published: _Published | None = None
        self.loop_stats: dict[str, Any] = {}
        self.cycles = 0

    @staticmethod
    def record_columns(cfg: ProjectConfig) -> list[str]:
        """Columns of the per-cycle run record (after ``t_s``)."""
        ids = list(cfg.layers.lower.cylinders) + list(cfg.layers.upper.cylinders)
        return (
            ["mode_code", "valves_enabled"]
            + [f"x_{c}_mm" for c in ids]
            + [f"ref_{c}_mm" for c in ids]
            + [f"u_{c}" for c in ids]
            + ["twist_lower_mm", "twist_upper_mm", "sync_lower_mm", "sync_upper_mm"]
        )

    def _on_transition(self, tr: Transition) -> None:
        if self.record is not None:
            self.record.event(
                self._now,
                "mode",
                event=tr.event,
                from_mode=str(tr.from_mode),
                to_mode=str(tr.to_mode),
                reason=tr.reason,
            )

    def _on_fault(self, latched: Latched) -> None:
        if self.record is not None:  # each newly latched cause once, from the data
            self.record.event(self._now, "fault", **latched.to_dict())

    # ------------------------------------------------------------------ operator side

    #: How long ``fault_reset`` is held in the control word for the PLC to clear a fault.
    RESET_PULSE_S = 0.5

    def request_reset(self, wait_s: float = 0.0) -> dict[str, Any]:
        """Reset after a FAULT or E-STOP: the PLC is asked to clear its own latched fault
        (``fault_reset`` in the control word for :attr:`RESET_PULSE_S`), then the modes
        are reset once no cause is present. With ``wait_s`` > 0 wait for the outcome."""
        if self.modes.mode not in (Mode.FAULT, Mode.ESTOP):
            return self.modes.reset().to_dict()  # refused, with its message
        with self._outcome_cv:
            self._reset_outcome = None
            self._reset_requested = True
            if wait_s <= 0:
                return {"ok": True, "mode": str(self.modes.mode), "note": "resetting"}
            self._outcome_cv.wait_for(lambda: self._reset_outcome is not None, timeout=wait_s)
            out = self._reset_outcome
        return out if out is not None else self.modes.reset().to_dict()

    def _reset_step(self, now: float) -> None:
        """Drive a requested reset (loop thread)."""
        if self._reset_requested and self._reset_until is None:
            self._reset_requested = False
            self._reset_until = now + self.RESET_PULSE_S
            self.link.set_control(fault_reset=True)
        if self._reset_until is None:
            return
        plc_fault = any(c.interlock is Interlock.PLC_FAULT for c in self._present)
        if not plc_fault or now >= self._reset_until:
            self.link.set_control(fault_reset=False)
            self._reset_until = None
            out = self.modes.reset().to_dict()
            with self._outcome_cv:
                self._reset_outcome = out
                self._outcome_cv.notify_all()

    def request_adjust(
        self, roll_deg: float, pitch_deg: float, wait_s: float = 0.0, hmi_seq: int = 0
    ) -> dict[str, Any]:
        """Ask for an adjustment; with ``wait_s`` > 0 wait for the planner's verdict.
        ``hmi_seq``: the HMI's TargetSeq (0 for a local request: nothing is acknowledged
        to the PLC)."""
        with self._outcome_cv:
            self._outcome = None
        out = self.modes.request_adjust(roll_deg, pitch_deg, hmi_seq)
        if not out.accepted:
            return {"ok": False, "code": "refused", "error": out.message, "mode": str(out.mode)}
        if wait_s <= 0:
            return {"ok": True, "mode": str(Mode.PLANNING)}
        with self._outcome_cv:
            self._outcome_cv.wait_for(lambda: self._outcome is not None, timeout=wait_s)
            result = self._outcome
        if result is None:
            return {"ok": True, "mode": str(self.modes.mode), "note": "still planning"}
        return result

    def snapshot(self) -> dict[str, Any]:
        """The last cycle's status (safe to call from any thread).

        Built here from what :meth:`step` published (one reference, replaced whole each
        cycle), so the loop does not pay for the status dict and the achieved attitude.
        """
        pub = self._published
        if pub is None:
            return {"mode": str(Mode.BOOT)}
        snap = dict(pub.modes)
        x = pub.x
        snap.update(
            time_s=pub.now,
            link=str(pub.link.name),
            positions_mm={
                cid: (units.to_mm(float(x[i])) if np.isfinite(x[i]) else None)
                for i, cid in self._active_ids
            },
            sync_error_mm={k: units.to_mm(m.sync_error_m) for k, m in pub.metrics.items()},
            twist_mm={k: units.to_mm(m.twist_m) for k, m in pub.metrics.items()},
            motion=self._motion_dict(pub.motion, x),
            link_health={"state": pub.link.name},
            # read from the link's counters here, in the caller's thread, not per cycle
            link_rx=self.link.rx_counters(),
            loop=pub.loop,
            ride_through={"suspends": pub.ride[0], "resumes": pub.ride[1]},
        )
        return snap

    # ------------------------------------------------------------------ the step

    def step(self, cycle: int, now: float) -> None:
        self._now = now
        self.cycles += 1
        link = self.link
        link.poll(now)
        pos = link.positions_m(now)
        prs = link.pressures_pa(now)
        status = link.status(now)
        lstate = link.state(now)
        x = pos.value
        valid = bool(pos.valid[self._active_arr].all())  # Reading.all_valid(self.active)
        mode = self.modes.mode

        # E-stop first: it needs nothing else to be valid.
        if status is not None:
            self.modes.estop(status.estop)

        present = self._conditions(valid, status, prs.value, prs.valid, pos, now)
        self._present = present
        losses = self._losses(valid, status, now)
        if mode == Mode.BOOT:
            if self._boot_since is None:
                self._boot_since = now
            # every input fresh, and the PLC hearing our commands
            if not present and not losses:
                self.modes.boot_complete()
            elif now - self._boot_since > self.boot_timeout_s:
                for cause in present:  # no valid PLC data within the start-up time
                    self.modes.fault(cause)
        else:
            for cause in present:  # latched by (interlock, where): repeats only counted
                self.modes.fault(cause)

        self._reset_step(now)
        self._ride_through(now, losses, x, prs.valid)
        moving = self.modes.valves_enabled
        if moving and valid:
            self._motion_checks(x)

        hmi = link.new_hmi_request(now)
        if hmi is not None:
            if hmi.request == TargetRequest.NEW_TARGET:
                out = self.request_adjust(
                    units.to_deg(hmi.roll_rad), units.to_deg(hmi.pitch_rad), hmi_seq=hmi.seq
                )
                if not out.get("ok"):  # refused: its own seq; the running one's is kept
                    self._hmi_ack(TargetAck.REJECTED, hmi.seq)
            elif hmi.request == TargetRequest.CANCEL:
                self.modes.stop("HMI cancel")
                self._hmi_ack(TargetAck.NONE, hmi.seq)

        self._planning(x, valid, now)

        mode = self.modes.mode
        if mode == Mode.ADJUSTING and self.attitude.motion_done(now):
            self.modes.motion_done()
            self._hmi_ack(TargetAck.COMPLETED)
            self.attitude.hold(self.attitude.final_references())
            self.motion.duration_s = now - self.motion.started_s
        u = np.zeros(len(self.cfg.cylinders))
        ref: np.ndarray | None = None
        if self.modes.valves_enabled and valid:
            u = self.attitude.update(now, x)
            ref = self.attitude.last_references  # this cycle's, for the run record
            self._last_drive_t = now
            self._motion_figures(now)
        link.set_control(
            mode=PlcMode.ATTITUDE_ADJUST if self.modes.valves_enabled else PlcMode.IDLE,
            enable=self.modes.valves_enabled,
        )
        link.send_valve_commands(u, now)
        self._publish(now, x, u, lstate, ref)

    # ------------------------------------------------------------------ pieces

    def _conditions(
        self,
        positions_valid: bool,
        status: Any,
        p: np.ndarray,
        p_valid: np.ndarray,
        pos: Reading | None = None,
        now: float = 0.0,
    ) -> list[Cause]:
        """Interlock conditions present now (each also blocks a reset)."""
        out: list[Cause] = []
        if status is None or not self.link.bus_health.can_send():
            age = self.link.status_age_s(now)
            out.append(
                Cause(
                    Interlock.PLC_HEARTBEAT,
                    detail="PLC status lost" if status is None else "bus off or down",
                )
                if math.isinf(age)
                else Cause(
                    Interlock.PLC_HEARTBEAT,
                    value=units.to_ms(age),
                    limit=self.cfg.safety.plc_heartbeat_timeout_ms,
                    detail="since the last PLC status" if status is None else "bus off or down",
                )
            )
        if not positions_valid and pos is not None:
            out.extend(self._position_causes(pos, now))
        if status is not None and status.fault not in (Fault.NONE, Fault.ESTOP):
            name = (
                Fault(status.fault).name
                if status.fault in Fault._value2member_map_
                else str(status.fault)
            )
            out.append(Cause(Interlock.PLC_FAULT, where=name))
        # The largest valid pressure (NaN where not valid, so fmax skips them; NaN when
        # none is), against the limit (positive, so the zeros for invalid values below
        # never matter).
        if float(np.fmax.reduce(p, axis=None)) > self.max_pressure_pa:
            pv = np.where(p_valid, p, 0.0)  # rare: then find whose it is
            i = int(np.argmax(pv.max(axis=1)))
            peak = float(pv[i].max())
            out.append(
                Cause(
                    Interlock.PRESSURE,
                    where=self._by_index[i].id,
                    value=units.to_mpa(peak),
                    limit=units.to_mpa(self.max_pressure_pa),
                )
            )
        return out

    def _position_causes(self, pos: Reading, now: float) -> list[Cause]:
        """Rare path (an active position not valid): a sensor reporting a fault, or the
        first active cylinder whose position is older than ``safety.sensor_timeout_ms``."""
        out: list[Cause] = []
        failed = set(self.link.failed_positions(self.active, now))
        for i in self.active:
            if i in failed:
                out.append(Cause(Interlock.SENSOR, where=self._by_index[i].id))
        ages = pos.age_s.tolist()
        for i in self.active:
            age = ages[i]
            if i not in failed and not pos.valid[i] and age > self.sensor_timeout_s:
                out.append(
                    Cause(
                        Interlock.SENSOR_TIMEOUT,
                        where=self._by_index[i].id,
                        value=None if math.isinf(age) else units.to_ms(age),
                        limit=self.cfg.safety.sensor_timeout_ms,
                        detail="never received" if math.isinf(age) else "",
                    )
                )
                break
        return out

    def _losses(self, positions_valid: bool, status: Any, now: float) -> list[str]:
        """Why the link counts as dropped out now (empty: fresh): what suspends a motion."""
        out: list[str] = []
        if not positions_valid:
            out.append("rod positions of the active group stale")
        if status is None or self.link.status_age_s(now) > self.link.status_stale_s:
            out.append("PLC status stale")
        elif status.command_timeout:
            out.append("the PLC reports the IPC's commands stale")
        return out

    # ------------------------------------------------------------------ ride-through

    def _ride_through(
        self, now: float, losses: list[str], x: np.ndarray, p_valid: np.ndarray
    ) -> None:
        """Suspend a motion on a loss of the link; resume it once fresh and checked."""
        mode = self.modes.mode
        if mode in SUSPENDABLE_MODES:
            if losses:
                self._suspend(now, losses, mode)
            return
        if mode != Mode.SUSPENDED:
            return
        held = now - self._suspended_at
        if held > self.max_suspend_s:
            self.modes.fault(
                Cause(
                    Interlock.SUSPEND_TIMEOUT,
                    value=units.to_ms(held),
                    limit=self.cfg.safety.max_suspend_ms,
                    detail="; ".join(losses),
                )
            )
            return
        if losses:
            self._fresh_cycles = 0
            return
        self._fresh_cycles += 1
        if self._fresh_cycles < self.RESUME_FRESH_CYCLES:
            return
        cause = self._resume_check(x, p_valid)
        if cause is not None:
            self.modes.fault(cause)
        else:
            self._resume(now, x)

    def _suspend(self, now: float, losses: list[str], mode: Mode) -> None:
        reason = "; ".join(losses)
        ref = self.attitude.last_references
        self._stop_ref = (ref if ref is not None else self.attitude.references(now)).copy()
        self._suspended_at = now
        self._fresh_cycles = 0
        if not self.modes.suspend(reason).accepted:
            return
        self.suspends += 1
        log.warning("suspended", reason=reason, from_mode=str(mode), suspends=self.suspends)
        if self.record is not None:
            self.record.event(now, "suspended", reason=reason, from_mode=str(mode))

    def _resume_check(self, x: np.ndarray, p_valid: np.ndarray) -> Cause | None:
        """Every active rod within the sync band of where it stopped, its pressures valid."""
        ref = self._stop_ref
        xs = x.tolist()
        refs = ref.tolist() if ref is not None else xs
        lim = self.max_sync_m
        for i in self.active:
            dev = abs(xs[i] - refs[i])
            if not dev <= lim:  # NaN too
                return Cause(
                    Interlock.RESUME_CHECK,
                    where=self._by_index[i].id,
                    value=units.to_mm(dev),
                    limit=units.to_mm(lim),
                    detail="from where the motion stopped",
                )
        if not bool(p_valid[self._active_arr].all()):
            return Cause(Interlock.RESUME_CHECK, where="pressures", detail="not valid")
        return None

    def _resume(self, now: float, x: np.ndarray) -> None:
        last = self._last_drive_t if self._last_drive_t is not None else self._suspended_at
        shift = max(0.0, now - last - self.period_s)  # the next reference follows the last
        suspended_s = now - self._suspended_at
        self.attitude.resume(x, shift)
        self.motion.started_s += shift
        self.modes.resume(
            f"frames fresh for {self.RESUME_FRESH_CYCLES} cycles, rods within the sync band "
            f"after {units.to_ms(suspended_s):.0f} ms"
        )
        self.resumes += 1
        log.warning("resumed", suspended_s=suspended_s, shift_s=shift, resumes=self.resumes)
        if self.record is not None:
            self.record.event(now, "resumed", suspended_s=suspended_s, shift_s=shift)

    def _hmi_ack(self, status: TargetAck, seq: int | None = None) -> None:
        """Answer an HMI request in the control word (the PLC shows it to the operator):
        ``seq``, else the request being served; a local request (seq 0) is not answered."""
        seq = self.modes.hmi_seq if seq is None else seq
        if seq:
            self.link.set_control(ack_seq=seq, ack_status=status)

    def _motion_checks(self, x: np.ndarray) -> None:
        for name, m in self.attitude.metrics.items():
            if m.twist_m > self.max_twist_m:
                self.modes.fault(self._over(Interlock.TWIST, name, m.twist_m, self.max_twist_m))
            if m.tracking_error_m > self.max_tracking_m:
                self.modes.fault(
                    self._over(
                        Interlock.TRACKING_ERROR, name, m.tracking_error_m, self.max_tracking_m
                    )
                )
            if m.sync_error_m > self.max_sync_m:
                self.modes.fault(
                    self._over(Interlock.SYNC_ERROR, name, m.sync_error_m, self.max_sync_m)
                )
        # Plain floats: the first active rod within the margin of an end or at a limit
        # switch (the mask of the switches is worked out once per received word).
        limits = self.link.limit_switches(self._now)
        if limits is not self._limits_of[0]:
            at = None
            if limits is not None:
                a = self._active_arr
                at = (limits.retracted[a] | limits.extended[a]).tolist()
            self._limits_of = (limits, at)
        at_limit = self._limits_of[1]
        xs = x.tolist()
        lo = self.end_margin_m
        for k, (i, hi) in enumerate(zip(self.active, self._stroke_hi_list, strict=True)):
            v = xs[i]
            if v < lo or v > hi or (at_limit is not None and at_limit[k]):
                to_end = min(v, self.stroke[i] - v)
                self.modes.fault(
                    Cause(
                        Interlock.STROKE_END,
                        where=self._by_index[i].id,
                        value=units.to_mm(to_end),
                        limit=units.to_mm(self.end_margin_m),
                        detail="(limit switch)" if to_end >= lo else "",
                    )
                )
                break

    @staticmethod
    def _over(il: Interlock, where: str, value_m: float, limit_m: float) -> Cause:
        return Cause(il, where=where, value=units.to_mm(value_m), limit=units.to_mm(limit_m))

    def _planning(self, x: np.ndarray, valid: bool, now: float) -> None:
        mode = self.modes.mode
        if mode == Mode.PLANNING and not self._submitted and valid:
            target = self.modes.target_deg
            if target is not None:
                self._request_id += 1
                half = self.stroke / 2
                lo, up = self.attitude.layers["lower"], self.attitude.layers["upper"]
                ok = self.planner.submit(
                    self._request_id,
                    target[0],
                    target[1],
                    start_upper_m=tuple((x[up] - half[up]).tolist()),
                    start_lower_m=tuple((x[lo] - half[lo]).tolist()),
                )
                self._submitted = ok
        if not valid:
            return  # a plan is taken only with valid positions (it engages at them)
        res = self.planner.poll()
        if res is None or res.request_id != self._request_id:
            return
        self._submitted = False
        if self.modes.mode != Mode.PLANNING:
            return  # stopped or faulted meanwhile: the plan is dropped
        self._hmi_ack(TargetAck.ACCEPTED if res.ok and res.feasible else TargetAck.REJECTED)
        if not res.ok:
            self.modes.fault(Cause(Interlock.PLANNER, detail=str(res.error)))
            verdict: dict[str, Any] = {"ok": False, "code": "planner", "error": res.error}
        elif not res.feasible or res.trajectory is None:
            self.modes.plan_failed(list(res.reasons))
            verdict = {"ok": False, "code": "infeasible", "reasons": list(res.reasons)}
        else:
            self.modes.plan_ready()
            target = (res.plan or {}).get("target", {})
            self.motion = MotionStats(
                target_deg=(target.get("roll_deg", 0.0), target.get("pitch_deg", 0.0)),
                started_s=now,
                plan=res.plan,
            )
            self.attitude.engage(x, now, res.trajectory)
            verdict = {"ok": True, "mode": str(Mode.ADJUSTING), "duration_s": res.duration_s}
        log.info("plan", request_id=res.request_id, **verdict)
        if self.record is not None:
            self.record.event(now, "plan", request_id=res.request_id, plan=res.plan, **verdict)
        with self._outcome_cv:
            self._outcome = verdict
            self._outcome_cv.notify_all()

    def _motion_figures(self, now: float) -> None:
        m = self.motion
        sync = max(g.sync_error_m for g in self.attitude.metrics.values())
        tw = max(g.twist_m for g in self.attitude.metrics.values())
        if self.modes.mode == Mode.ADJUSTING:
            m.max_twist_m = max(m.max_twist_m, tw)
            m.max_sync_error_m = max(m.max_sync_error_m, sync)
        elif now - (m.started_s + m.duration_s) >= self.HOLD_SETTLE_S:
            m.hold_sync_error_m = max(m.hold_sync_error_m, sync)
            m.hold_samples += 1

    def achieved_attitude_deg(self, x: np.ndarray) -> tuple[float, float]:
        """Workpiece (roll, pitch) from measured rod positions (sensor view)."""
        lo, up = self.attitude.layers["lower"], self.attitude.layers["upper"]
        half = self.stroke / 2
        ll, ul = self.cfg.layers.lower, self.cfg.layers.upper
        fl = fit_layer(x[lo] - half[lo], ll.a_m, ll.b_m)
        fu = fit_layer(x[up] - half[up], ul.a_m, ul.b_m)
        chk = check_attitude(
            (self.cfg.base.roll_rad, self.cfg.base.pitch_rad),
            (float(fl.roll), float(fl.pitch)),
            (float(fu.roll), float(fu.pitch)),
            (0.0, 0.0),
        )
        return units.to_deg(chk.roll), units.to_deg(chk.pitch)

    def _motion_dict(self, m: MotionStats, x: np.ndarray) -> dict[str, Any]:
        out: dict[str, Any] = {
            "target_deg": list(m.target_deg),
            "duration_s": m.duration_s,
            "max_twist_mm": units.to_mm(m.max_twist_m),
            "max_sync_error_mm": units.to_mm(m.max_sync_error_m),
            "hold_sync_error_mm": units.to_mm(m.hold_sync_error_m),
            "hold_samples": m.hold_samples,
        }
        if np.all(np.isfinite(x[self.active])):
            roll, pitch = self.achieved_attitude_deg(x)
            out["achieved_deg"] = [roll, pitch]
        return out

    def _publish(
        self,
        now: float,
        x: np.ndarray,
        u: np.ndarray,
        lstate: LinkState,
        ref_now: np.ndarray | None = None,
    ) -> None:
        enabled = self.modes.valves_enabled
        # Copies of what the loop goes on mutating; x is a new array every cycle.
        self._published = _Published(
            modes=self.modes.snapshot(),
            now=now,
            x=x,
            link=lstate,
            metrics=dict(self.attitude.metrics),
            motion=MotionStats(**vars(self.motion)),  # a copy (copy.copy: 4x the time)
            loop=self.loop_stats,
            ride=(self.suspends, self.resumes),
        )
        if self.record is not None:
            # The row on plain floats (the values numpy's indexing gave, without an
            # array per column group).
            active = self.active
            xs = x.tolist()
            if not enabled:
                refs = xs
            elif ref_now is not None:
                refs = ref_now.tolist()
            else:
                refs = self.attitude.references(now).tolist()
            us = u.tolist()
            to_mm = units.to_mm
            met = self.attitude.metrics
            self.record.sample(
                now,
                [
                    float(_MODE_CODES[self.modes.mode]),
                    float(enabled),
                    *[to_mm(xs[i]) for i in active],
                    *[to_mm(refs[i]) for i in active],
                    *[us[i] for i in active],
                    to_mm(met["lower"].twist_m),
                    to_mm(met["upper"].twist_m),
                    to_mm(met["lower"].sync_error_m),
                    to_mm(met["upper"].sync_error_m),
                ],
            )
