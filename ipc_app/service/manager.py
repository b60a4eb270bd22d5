"""The one active motion: started, driven each cycle, held, ridden through a short loss
of the link, ended (:class:`MotionManager`; the interface: :mod:`ipc_app.service.motion`).

The manager knows no motion by name. What it does for every motion:

- **start** (:meth:`MotionManager.begin`, in the loop): refused without valid positions,
  by the motion's own check of the inputs or by the mode machine (an HMI request is then
  answered REJECTED); accepted, the motion before it ends, the new one starts and its
  effects (events, the group it claims) follow in its order;
- **drive** (:meth:`MotionManager.drive`): in IDLE or STARTING the motion ends (stopped,
  or an adjustment is being planned); with the valves driven it runs one
  :class:`~ipc_app.service.motion.Command` and the manager records it in one order:
  the events, the interlock causes (latched), COMPLETE, a new claim;
- **hold and unhold**, **suspend and resume** (:meth:`MotionManager.ride_through`): a
  motion that stops keeps where it stopped (:meth:`~ipc_app.service.motion.Motion.stop_point`);
  it goes on only once its resume check passes, its clock shifted by the time stopped.
  A loss of the link suspends it; once frames are fresh for
  :attr:`MotionManager.RESUME_FRESH_CYCLES` cycles the check runs, and a loss longer
  than ``safety.max_suspend_ms`` latches the fault;
- **claims**: the group a motion's phase drives at the loop rate goes to the link, the
  reader and the stroke-end checks; the attitude layers are the service's own group.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import replace
from typing import Any

import numpy as np
import structlog

from config import units
from config.schema import ProjectConfig
from ipc_app.service.interlocks import Cause, Interlock, Limits, Metrics, resume_cause
from ipc_app.service.machine_io import Handshake, MachineInputs, Reader
from ipc_app.service.modes import SUSPENDABLE_MODES, Mode, ModeMachine
from ipc_app.service.motion import WAIT, Claim, Effects, Event, Motion, MotionStats
from ipc_app.service.record import RunRecorder
from ipc_app.service.requests import Reply
from plc_bridge.link import IpcLink, TargetAck
from plc_bridge.link import Mode as PlcMode

log = structlog.get_logger("wara.service")


class MotionManager:
    """Holds the active motion of one service; see the module docstring."""

    #: Seconds of COMPLETE before the standstill figures are taken (let the hold settle).
    HOLD_SETTLE_S = 1.0
    #: Cycles of fresh frames before a suspended motion is checked and resumed.
    RESUME_FRESH_CYCLES = 3

    def __init__(
        self,
        cfg: ProjectConfig,
        link: IpcLink,
        modes: ModeMachine,
        handshake: Handshake,
        attitude_group: list[int],
        record: RunRecorder | None,
    ) -> None:
        self.cfg = cfg
        self.link = link
        self.modes = modes
        self.handshake = handshake
        self.record = record
        self.period_s = cfg.control.period_s
        self.max_suspend_s = units.ms(cfg.safety.max_suspend_ms)
        self.attitude_group = attitude_group
        self.bus_load = link.set_active_cylinders(attitude_group)
        self.reader = Reader(link, attitude_group)
        self.attitude_limits = Limits.from_config(cfg, attitude_group)
        self.limits = self.attitude_limits
        self.active: Motion | None = None
        self.stats = MotionStats()
        #: the references where the motion stopped (held, suspended), and when
        self.stop_ref: np.ndarray | None = None
        self.suspended_at = 0.0
        self.last_drive_t: float | None = None
        self.suspends = 0
        self.resumes = 0
        self._fresh_cycles = 0
        self._zeros = np.zeros(len(cfg.cylinders))

    # ------------------------------------------------------------------ claims

    def plc_mode(self) -> PlcMode:
        """The PLC mode of the active motion's claim (the valves enabled)."""
        claim = self.active.claim() if self.active is not None else None
        return claim.plc_mode if claim is not None else PlcMode.ATTITUDE_ADJUST

    def metrics(self) -> Mapping[str, Metrics]:
        """The active motion's layer figures (for the driven interlocks)."""
        return self.active.metrics() if self.active is not None else {}

    def take_claim(self, claim: Claim | None, now: float) -> None:
        """``claim``'s group at the loop rate on the link, its watched cylinders read and
        checked; None: back to the attitude layers."""
        if claim is None:
            self.bus_load = self.link.set_active_cylinders(self.attitude_group)
            self.reader = Reader(self.link, self.attitude_group)
            self.limits = self.attitude_limits
            return
        self.bus_load = self.link.set_active_cylinders(claim.group, now)
        self.reader = Reader(self.link, claim.watched)
        self.limits = replace(self.attitude_limits, active=tuple(claim.watched))
        ev = claim.event
        if ev is not None:
            filled = {
                "active": list(claim.group),
                "bus_load_percent": round(self.bus_load.load_percent, 2),
            }
            fields = {k: filled.get(k, v) for k, v in ev.fields.items()}
            log.info(ev.kind.replace("_", " "), **fields)
            self._record(now, Event(ev.kind, fields))

    def _apply(self, effects: Effects, now: float) -> None:
        for eff in effects:
            if isinstance(eff, Event):
                self._record(now, eff)
            else:
                self.take_claim(eff, now)

    def _record(self, now: float, ev: Event) -> None:
        if self.record is not None:
            self.record.event(now, ev.kind, **ev.fields)

    # ------------------------------------------------------------------ start, end

    def begin(self, motion: Motion, inp: MachineInputs, hmi_seq: int | None = None) -> Reply:
        """An operator's motion, in the loop: refused (an HMI request answered REJECTED),
        or the active motion from this cycle. ``hmi_seq``: the HMI's TargetSeq it serves
        (0 for a local request of a kind the HMI may ask for; None: the handshake is left
        as it is)."""
        if not inp.positions_valid:
            return self.hmi_refused(inp.t, hmi_seq, f"{motion.name} refused: no valid positions")
        why = motion.refusal(inp)
        if why is not None:
            return Reply.refused(why, mode=str(self.modes.mode))
        out = self.modes.start_motion(motion.name, motion.describe())
        if not out.accepted:
            self.hmi_refused(inp.t, hmi_seq, out.message)
            return Reply.refused(out.message, mode=str(out.mode))
        self.take(motion, inp, hmi_seq)
        return Reply.accepted(mode=str(self.modes.mode), **motion.accepted())

    def take(self, motion: Motion, inp: MachineInputs, hmi_seq: int | None = None) -> None:
        """``motion`` becomes the active one (the mode machine has accepted it)."""
        now = inp.t
        self.end(now, motion)
        if hmi_seq is not None:
            self.handshake.serve(hmi_seq)
            self.handshake.ack(TargetAck.ACCEPTED)
        effects = motion.start(inp)
        self.active = motion
        self.stats = MotionStats(target_deg=motion.target_deg, started_s=now, plan=motion.plan)
        self._apply(effects, now)

    def end(self, now: float, successor: Motion | None) -> None:
        """The active motion ends; ``successor`` takes over (None: stopped)."""
        m = self.active
        if m is None:
            return
        self.active = None
        self._apply(m.end(now, self.modes.mode, successor), now)

    def hmi_refused(self, now: float, seq: int | None, reason: str) -> Reply:
        """A refusal; an HMI request's (``seq``) answered REJECTED on the wire."""
        if seq:
            self.handshake.ack(TargetAck.REJECTED, seq)
            log.warning("hmi request refused", seq=seq, reason=reason)
            self._record(now, Event("hmi_refused", {"seq": seq, "reason": reason}))
        return Reply.refused(reason)

    # ------------------------------------------------------------------ the cycle

    def drive(self, inp: MachineInputs) -> tuple[np.ndarray, np.ndarray | None]:
        """The active motion's cycle: the spool commands and the references (None when
        the valves are closed)."""
        now = inp.t
        m = self.active
        if m is not None and self.modes.mode in (Mode.IDLE, Mode.STARTING):
            self.end(now, None)  # stopped, or an adjustment planned from where it stands
            m = None
        if m is None:
            return self._zeros.copy(), None
        if self.modes.mode == Mode.EXECUTE and m.finished(now):
            self._complete(m, now)
        if not (self.modes.valves_enabled and inp.positions_valid):
            return self._zeros.copy(), None
        cmd = m.update(inp, self.modes.mode)
        self.last_drive_t = now
        metrics = m.metrics()
        if metrics:
            self._figures(now, metrics)
        for ev in cmd.events:
            self._record(now, ev)
        for cause in cmd.causes:
            self.modes.fault(cause)
        if cmd.done:
            self._complete(m, now)
        if cmd.claim is not None:
            self.take_claim(cmd.claim, now)
        if not self.modes.valves_enabled:
            return self._zeros.copy(), None
        return cmd.valves, cmd.references

    def _complete(self, m: Motion, now: float) -> None:
        self.modes.motion_done()
        if m.answers_hmi:
            self.handshake.ack(TargetAck.COMPLETED)
        self.stats.duration_s = now - self.stats.started_s
        ev = m.completed(now)
        if ev is not None:
            self._record(now, ev)

    def _figures(self, now: float, metrics: Any) -> None:
        m = self.stats
        sync = max(g.sync_error_m for g in metrics.values())
        tw = max(g.twist_m for g in metrics.values())
        if self.modes.mode == Mode.EXECUTE:
            m.max_twist_m = max(m.max_twist_m, tw)
            m.max_sync_error_m = max(m.max_sync_error_m, sync)
        elif now - (m.started_s + m.duration_s) >= self.HOLD_SETTLE_S:
            m.hold_sync_error_m = max(m.hold_sync_error_m, sync)
            m.hold_samples += 1

    # ------------------------------------------------------------------ stop, go on

    def hold(self, inp: MachineInputs) -> Reply:
        """EXECUTE -> HELD (an operator's hold, in the loop): the motion stops here."""
        out = self.modes.hold()
        if out.accepted:
            self.stopped_here(inp.t, inp)
        return Reply.outcome(out)

    def unhold(self, inp: MachineInputs) -> Reply:
        """HELD -> EXECUTE once the motion's resume check passes (in the loop)."""
        if self.modes.mode != Mode.HELD:
            return Reply.outcome(self.modes.unhold())  # refused, with its message
        m = self.active
        cause: str | None = None if inp.positions_valid else "rod positions not valid"
        if cause is None:
            c = self._resume_check(m, inp, held=True)
            if isinstance(c, Cause):
                cause = c.text()
                if m is not None and m.resume_refused_event is not None:
                    self._record(inp.t, Event(m.resume_refused_event, {"reason": cause}))
            elif c is WAIT:
                cause = "the readings it is checked on are not in yet"
        if cause is not None:
            msg = f"unhold refused: {cause}; `wara ctl stop` ends the motion"
            return Reply.refused(msg, mode=str(self.modes.mode))
        reason = m.unhold_reason if m is not None else "operator unhold"
        self._go_on(inp, self.modes.unhold, reason, held=True)
        return Reply.accepted(mode=str(self.modes.mode))

    def _resume_check(self, m: Motion | None, inp: MachineInputs, held: bool) -> Any:
        if m is None:
            stop = self.stop_ref.tolist() if self.stop_ref is not None else None
            return resume_cause(inp, stop, self.limits)
        return m.resume_check(inp, self.stop_ref, self.limits, held)

    def stopped_here(self, now: float, inp: MachineInputs | None) -> None:
        """The motion stops (held or suspended): where its references were, and when."""
        m = self.active
        self.stop_ref = m.stop_point(now, inp).copy() if m is not None else None
        self.suspended_at = now

    def _go_on(self, inp: MachineInputs, event: Any, reason: str, held: bool) -> float:
        """The stopped motion goes on (resume, unhold): its clock shifted by the time
        stopped, its controllers bumpless at the rods. Returns the shift."""
        last = self.last_drive_t if self.last_drive_t is not None else self.suspended_at
        shift = max(0.0, inp.t - last - self.period_s)  # the next reference follows the last
        if self.active is not None:
            self.active.resume(inp, shift, held)
        self.stats.started_s += shift
        event(reason)
        return shift

    def ride_through(self, now: float, losses: list[str], inp: MachineInputs) -> None:
        """Suspend the motion on a loss of the link; resume it once fresh and checked."""
        mode = self.modes.mode
        if mode in SUSPENDABLE_MODES:
            if losses:
                self._suspend(now, losses, mode, inp)
            return
        if mode != Mode.SUSPENDED:
            return
        held = now - self.suspended_at
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
        cause = self._resume_check(self.active, inp, held=False)
        if cause is WAIT:
            return  # a slow group's frame yet to come (the suspend timeout bounds this)
        if isinstance(cause, Cause):
            self.modes.fault(cause)
        else:
            self._resume(inp)

    def _suspend(self, now: float, losses: list[str], mode: Mode, inp: MachineInputs) -> None:
        reason = "; ".join(losses)
        self.stopped_here(now, inp)
        self._fresh_cycles = 0
        if not self.modes.suspend(reason).accepted:
            return
        self.suspends += 1
        log.warning("suspended", reason=reason, from_mode=str(mode), suspends=self.suspends)
        self._record(now, Event("suspended", {"reason": reason, "from_mode": str(mode)}))

    def _resume(self, inp: MachineInputs) -> None:
        now = inp.t
        suspended_s = now - self.suspended_at
        resume: Any = self.modes.resume
        shift = self._go_on(
            inp,
            resume,
            f"frames fresh for {self.RESUME_FRESH_CYCLES} cycles, rods within the sync band "
            f"after {units.to_ms(suspended_s):.0f} ms",
            held=False,
        )
        self.resumes += 1
        log.warning("resumed", suspended_s=suspended_s, shift_s=shift, resumes=self.resumes)
        self._record(now, Event("resumed", {"suspended_s": suspended_s, "shift_s": shift}))
