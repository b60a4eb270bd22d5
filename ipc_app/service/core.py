"""The service's control step: read -> interlocks -> modes -> ride-through -> the active
motion -> write.

:class:`ServiceCore` owns no thread and no clock: :meth:`ServiceCore.step` is called once
per period with the time, by :class:`~ipc_app.service.loop.FixedRateLoop` in the service
or in lockstep with the HIL simulator in tests and the demo. Its work per cycle is
bounded: drain the CAN receive queue, a fixed set of checks, the active motion's one
update, two CAN sends. Planning runs in the worker process and motions are built in the
requesting thread; the control channel's threads only call the (thread-safe) mode
machine, queue requests for the loop and read the last snapshot.

Interlocks are data (:mod:`ipc_app.service.interlocks`: which one, its config key, when
it applies); a tripped check is a :class:`~ipc_app.service.interlocks.Cause` and the
reaction a controlled stop: valves closed, load held, ABORTED latched until ``reset``.
E-stop from the PLC takes the machine to ABORTED (valves closed) until released and
reset. The modes are PackML states (:mod:`ipc_app.service.modes`, docs/modes.md).

The step knows no motion by name: the :class:`~ipc_app.service.manager.MotionManager`
holds the active one (:mod:`ipc_app.service.motion`, :mod:`ipc_app.service.motions`)
and rides it through a short loss of the link. The request methods below are the
service's façade for the control channel, the ring cycle and the harness; each checks
its values (:mod:`ipc_app.service.requests`), prepares the motion here, in the caller's
thread, and hands it to the loop.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np
import structlog

from config.schema import CANNOT_WALK, ProjectConfig
from ipc_app.control.attitude import AttitudeController
from ipc_app.model.placement import Pose
from ipc_app.planner.placement import PlacementPlan
from ipc_app.planner.steering import OnAxis, on_axis_at_start
from ipc_app.planner.survey import SurveyPoint
from ipc_app.planner.walk import WalkStart
from ipc_app.service.cycle import RingCycle, RingRecords
from ipc_app.service.interlocks import Cause, Interlock, Latched, link_losses, motion_causes
from ipc_app.service.interlocks import present_causes as present_causes_of
from ipc_app.service.machine_io import Handshake, MachineInputs, MachineOutputs, write
from ipc_app.service.manager import MotionManager
from ipc_app.service.modes import UNIT_MODES, Mode, ModeMachine, Transition, UnitMode
from ipc_app.service.motion import Motion, Planner, Preparation, Ticket
from ipc_app.service.motions.attitude import AdjustPlanning, JogMotion
from ipc_app.service.motions.homing import HomingMotion
from ipc_app.service.motions.place import PlaceMotion, plan_from_sheet
from ipc_app.service.motions.release import ReleaseMotion
from ipc_app.service.motions.walk import WalkMotion, walk_start
from ipc_app.service.record import RunRecorder
from ipc_app.service.requests import HmiRequests, Reply
from ipc_app.service.status import MODE_CODES, StatusBoard, record_columns
from plc_bridge.link import ControlWord, IpcLink
from plc_bridge.link import Mode as PlcMode

log = structlog.get_logger("wara.service")

#: Modes at the start of a cycle in which its motion checks may run.
_LIMIT_MODES = frozenset({Mode.EXECUTE, Mode.COMPLETE, Mode.SUSPENDED})


class ServiceCore:
    """One IPC service: modes, interlocks, requests and the active motion."""

    HOLD_SETTLE_S = MotionManager.HOLD_SETTLE_S
    RESUME_FRESH_CYCLES = MotionManager.RESUME_FRESH_CYCLES
    #: how often the service's cycle thread looks at the ring cycle, s
    CYCLE_TICK_S = 0.05

    def __init__(
        self,
        cfg: ProjectConfig,
        link: IpcLink,
        planner: Planner,
        *,
        record: RunRecorder | None = None,
    ) -> None:
        self.cfg = cfg
        self.link = link
        self.planner = planner
        self.record = record
        self.on_axis: OnAxis | None = None
        self.period_s = cfg.control.period_s
        self.boot_timeout_s = cfg.safety.boot_timeout_s
        self.attitude = AttitudeController(cfg, self.period_s)
        self.active = self.attitude.layers["lower"] + self.attitude.layers["upper"]
        self.handshake = Handshake(link.control)
        self._inputs: MachineInputs | None = None
        self._present: list[Cause] = []  # interlock conditions present this cycle
        self.modes = ModeMachine(
            active_causes=lambda: list(self._present),
            on_transition=self._on_transition,
            on_fault=self._on_fault,
        )
        self.motions = MotionManager(cfg, link, self.modes, self.handshake, self.active, record)
        self.adjusting = AdjustPlanning(
            self, planner, self.modes, self.handshake, self.motions, record
        )
        #: requests prepared with the loop's help (the planner's answer polled each cycle)
        self.preparations: tuple[Preparation, ...] = (self.adjusting,)
        self.board = StatusBoard(cfg, self.attitude, record)
        self.state_changes = self.board.state_changes
        self._calls: deque[tuple[Ticket, Callable[[MachineInputs], Reply]]] = deque()
        self._pulse_for = "reset"
        self._reset_cv = threading.Condition()
        self._reset_outcome: Reply | None = None
        self._boot_since: float | None = None
        self._now = 0.0
        self.hmi = HmiRequests(
            adjust=lambda r, p, seq: self.request_adjust(r, p, hmi_seq=seq),
            walk=lambda n, seq: self.request_walk(n, hmi_seq=seq),
            stop=self.modes.stop,
            ack=self.handshake.ack,
            refused=self.motions.hmi_refused,
        )
        self.loop_stats: dict[str, Any] = {}
        self.cycles = 0
        #: the ring cycle asked of the service (``request_cycle``), the last one
        self.ring_cycle: RingCycle | None = None

    record_columns = staticmethod(record_columns)

    # The manager's state, as the callers read it (the façade).
    motion = property(lambda self: self.motions.stats, doc="MotionStats of the last motion")
    reader = property(lambda self: self.motions.reader)
    limits = property(
        lambda self: self.motions.limits,
        lambda self, lim: setattr(self.motions, "limits", lim),
        doc="the interlock limits of the group driven now",
    )
    max_suspend_s = property(lambda self: self.motions.max_suspend_s)
    bus_load = property(lambda self: self.motions.bus_load)
    suspends = property(lambda self: self.motions.suspends)
    resumes = property(lambda self: self.motions.resumes)

    def _sequencer(self, name: str) -> Any:
        m = self.motions.active
        return m.sequencer if m is not None and m.name == name else None

    def _status_of(self, name: str) -> dict[str, Any] | None:
        m = self.motions.active
        return m.status() if m is not None and m.name == name else None

    def walk_status(self) -> dict[str, Any] | None:
        """The walk's step and phase for ``wara ctl status`` (None: no walk)."""
        return self._status_of("walk")

    def place_status(self) -> dict[str, Any] | None:
        """The placement's ring, phase and figures (None: none)."""
        return self._status_of("place")

    def release_status(self) -> dict[str, Any] | None:
        """The release's phase and figures (None: none)."""
        return self._status_of("release")

    walker = property(lambda self: self._sequencer("walk"), doc="the walk's WalkSequencer")
    placer = property(lambda self: self._sequencer("place"), doc="the PlacementSequencer")
    releaser = property(lambda self: self._sequencer("release"), doc="the ReleaseSequencer")

    def _on_transition(self, tr: Transition) -> None:
        if tr.event == "reset":
            self.handshake.cleared()
        if self.record is not None:
            self.record.event(
                self._now, "mode", event=tr.event, from_mode=str(tr.from_mode),
                to_mode=str(tr.to_mode), reason=tr.reason,
            )  # fmt: skip

    def _on_fault(self, latched: Latched) -> None:
        if self.record is not None:  # each newly latched cause once, from the data
            self.record.event(self._now, "fault", **latched.to_dict())

    def event(self, kind: str, **fields: Any) -> None:
        """A run-record event at the last cycle's time (the ring cycle's)."""
        if self.record is not None:
            self.record.event(self._now, kind, **fields)

    # ------------------------------------------------------------------ requests

    def request_reset(self, wait_s: float = 0.0) -> dict[str, Any]:
        """Reset: from ABORTED clear first (the PLC is asked to clear its own latched
        fault, ``fault_reset`` in the control word, :class:`Handshake`; then the modes
        once no cause is present), then STOPPED -> IDLE. With ``wait_s`` > 0 wait for
        the outcome."""
        return self._after_pulse("reset", wait_s).to_dict()

    def request_clear(self, wait_s: float = 0.0) -> dict[str, Any]:
        """Clear: ABORTED -> STOPPED (the PLC's fault cleared as for a reset)."""
        return self._after_pulse("clear", wait_s).to_dict()

    def _after_pulse(self, event: str, wait_s: float) -> Reply:
        act = self.modes.reset if event == "reset" else self.modes.clear
        if self.modes.mode != Mode.ABORTED:
            return Reply.outcome(act())  # a plain reset, or refused with its message
        with self._reset_cv:
            self._reset_outcome = None
            self._pulse_for = event
            self.handshake.request_reset()
            if wait_s <= 0:
                note = "resetting" if event == "reset" else "clearing"
                return Reply.accepted(mode=str(self.modes.mode), note=note)
            self._reset_cv.wait_for(lambda: self._reset_outcome is not None, timeout=wait_s)
            out = self._reset_outcome
        return out if out is not None else Reply.outcome(act())

    def _startup_cause(self, booting_s: float, losses: list[str]) -> Cause:
        detail = "not complete: " + "; ".join(losses)
        return Cause(Interlock.STARTUP, value=booting_s, limit=self.boot_timeout_s, detail=detail)

    def _reset_step(self, now: float, present: list[Cause]) -> None:
        """Drive a requested reset or clear (loop thread)."""
        if not self.handshake.resetting:
            return
        plc_fault = any(c.interlock is Interlock.PLC_FAULT for c in present)
        if self.handshake.reset_step(now, plc_fault):
            act = self.modes.reset if self._pulse_for == "reset" else self.modes.clear
            out = Reply.outcome(act())
            with self._reset_cv:
                self._reset_outcome = out
                self._reset_cv.notify_all()

    def request_unit_mode(self, unit: str) -> dict[str, Any]:
        """PRODUCTION, MAINTENANCE or MANUAL; only in STOPPED, IDLE or ABORTED."""
        try:
            um = UnitMode(unit.upper())
        except ValueError:
            names = ", ".join(str(u) for u in UnitMode)
            return Reply.bad_request(f"unit mode {unit!r}: one of {names}").to_dict()
        return Reply.outcome(self.modes.set_unit_mode(um)).to_dict()

    def request_hold(self, wait_s: float = 0.0) -> dict[str, Any]:
        """EXECUTE -> HELD (done by the loop: the pose where the motion stops)."""
        return self._in_loop(self.motions.hold, wait_s)

    def request_unhold(self, wait_s: float = 0.0) -> dict[str, Any]:
        """HELD -> EXECUTE once the motion's resume check passes (loop)."""
        return self._in_loop(self.motions.unhold, wait_s)

    def request_adjust(
        self, roll_deg: float, pitch_deg: float, wait_s: float = 0.0, hmi_seq: int = 0
    ) -> dict[str, Any]:
        """Ask for an adjustment; with ``wait_s`` > 0 wait for the planner's verdict.
        ``hmi_seq``: the HMI's TargetSeq (0 for a local request: nothing is acknowledged
        to the PLC)."""
        return self.adjusting.request(roll_deg, pitch_deg, wait_s, hmi_seq).to_dict()

    def request_motion(
        self, kind: type[Motion], args: tuple[Any, ...] = (), *, hmi_seq: int | None = None
    ) -> Ticket:
        """``kind``'s motion prepared here (the caller's thread: checked and planned, its
        sequencer built), then handed to the loop, which starts it or refuses it. The
        ticket answers when the loop has taken it (at once when refused here)."""
        got = kind.prepare(self, *args)
        if isinstance(got, Reply):
            if hmi_seq:
                why = got.error or ""
                self._queue(lambda inp: self.motions.hmi_refused(inp.t, hmi_seq, why))
            return Ticket(reply=got)
        return self._queue(lambda inp: self.motions.begin(got, inp, hmi_seq), got)

    def start_motion(
        self, kind: type[Motion], args: tuple[Any, ...] = (), wait_s: float = 0.0
    ) -> dict[str, Any]:
        """:meth:`request_motion`'s reply (``wait_s`` > 0: once the loop has taken it)."""
        return self._reply(self.request_motion(kind, args), wait_s)

    def request_jog(self, cylinder: str, distance_mm: float, wait_s: float = 0.0) -> dict[str, Any]:
        """Jog one attitude cylinder by ``distance_mm`` at ``control.manual_jog_speed_mm_s``
        (unit mode MANUAL, from IDLE or COMPLETE; the other cylinders hold)."""
        return self.start_motion(JogMotion, (cylinder, distance_mm), wait_s)

    def request_home(self, wait_s: float = 0.0) -> dict[str, Any]:
        """Homing: each attitude layer to its reference stroke, level, then held."""
        return self.start_motion(HomingMotion, (), wait_s)

    def request_walk(
        self,
        steps: int,
        wait_s: float = 0.0,
        hmi_seq: int = 0,
        direction: str = "forward",
        unloaded: bool = False,
    ) -> dict[str, Any]:
        """Walk ``steps`` steps ``direction`` (``forward``, ``back``), ``unloaded``: the
        statics without the workpiece; refused before anything moves if a constraint
        breaks. ``hmi_seq``: the HMI's TargetSeq of a WALK request (answered ACCEPTED,
        REJECTED, COMPLETED); 0 for a local request."""
        args = (steps, direction, unloaded)
        return self._reply(self.request_motion(WalkMotion, args, hmi_seq=hmi_seq), wait_s)

    def walk_start(self) -> WalkStart | str:
        """The measured state a walk would start from now, or why there is none yet."""
        return walk_start(self)

    def request_place(
        self, ring: int, previous_deviation: Pose, wait_s: float = 0.0
    ) -> dict[str, Any]:
        """Place ring ``ring``'s part: its target planned from the previous part's
        deviation from its design, then :meth:`request_place_plan`."""
        plan = plan_from_sheet(self, ring, previous_deviation)
        if isinstance(plan, Reply):
            return plan.to_dict()
        return self.request_place_plan(plan, wait_s)

    def request_place_plan(self, plan: PlacementPlan, wait_s: float = 0.0) -> dict[str, Any]:
        """Move the part to ``plan``'s target (:class:`PlaceMotion`)."""
        return self.start_motion(PlaceMotion, (plan,), wait_s)

    def request_release(self, ring: int, wait_s: float = 0.0) -> dict[str, Any]:
        """Lower the upper platform off ring ``ring``'s fixed part (:class:`ReleaseMotion`)."""
        return self.start_motion(ReleaseMotion, (ring,), wait_s)

    def _queue(self, fn: Callable[[MachineInputs], Reply], motion: Motion | None = None) -> Ticket:
        ticket = Ticket(motion)
        self._calls.append((ticket, fn))  # bounded by the control channel's worker pool
        return ticket

    def _in_loop(self, fn: Callable[[MachineInputs], Reply], wait_s: float) -> dict[str, Any]:
        return self._reply(self._queue(fn), wait_s)

    def _reply(self, ticket: Ticket, wait_s: float) -> dict[str, Any]:
        reply = ticket.wait(wait_s)
        if reply is None:
            return {"ok": True, "mode": str(self.modes.mode), "note": "pending"}
        return reply.to_dict()

    @property
    def requests_pending(self) -> int:
        """Requests waiting for the loop to take them."""
        return len(self._calls)

    @property
    def preparing(self) -> bool:
        """An HMI request is being planned on a thread of its own (:class:`HmiRequests`)."""
        return self.hmi.preparing

    def audit(self, user: str, action: str, result: str) -> dict[str, Any]:
        """One entry of a front end's audit trail (the OPC UA server's method calls):
        logged and put into the run record as an ``audit`` event."""
        log.info("audit", user=user, action=action, result=result)
        if self.record is not None:
            self.record.event(self._now, "audit", user=user, action=action, result=result)
        return {}

    def locate(self, where: OnAxis) -> dict[str, Any]:
        """Where the machine stands against the axis, surveyed (``wara ctl locate``; curves.md
        section 3): :attr:`on_axis` is set to ``where``, the next walk is planned and
        steered from it. Refused without a walking section, and while a walk has not
        ended (executing, held, suspended or stopped part-way: its end sets
        :attr:`on_axis` from the turns it measured). The reply: what it set, the
        estimate it replaced (the start's when none) and the change."""
        cfg = self.cfg
        if not cfg.walks:
            why = f"locate refused: {CANNOT_WALK}"
            return Reply.refused(why).to_dict()
        m = self.motions.active
        if isinstance(m, WalkMotion) and m.on_axis_pending:
            why = (
                f"locate refused: the walk ({m.describe()}) has not ended (the service is "
                f"{self.modes.mode}); its end sets where the machine stands from the turns "
                "it measured: locate once it has ended"
            )
            return Reply.refused(why).to_dict()
        before = self.on_axis or on_axis_at_start(cfg)
        self.on_axis = where
        now, was = where.to_dict(), before.to_dict()
        change = {k: round(now[k] - was[k], 5) for k in now}
        log.info("locate", on_axis=now, replaced=was, change=change)
        self.event("locate", on_axis=now, replaced=was, change=change)
        return Reply.accepted(on_axis=now, replaced=was, change=change).to_dict()

    def stop(self, reason: str) -> dict[str, Any]:
        """A controlled stop (``wara ctl stop``); a running ring cycle ends with it."""
        out = Reply.outcome(self.modes.stop(reason)).to_dict()
        cyc = self.ring_cycle
        if cyc is not None and cyc.active:
            cyc.stop(reason)
        return out

    # ------------------------------------------------------------------ the ring cycle

    @property
    def now_s(self) -> float:
        """Machine time of the last cycle, s."""
        return self._now

    @property
    def inputs(self) -> MachineInputs | None:
        """The last cycle's readings (one reference, replaced whole each cycle)."""
        return self._inputs

    def request_cycle(
        self,
        ring: int,
        previous: Pose,
        records: RingRecords,
        *,
        walk_steps: int | None = None,
        walk_back_unloaded: bool = True,
        drive: bool = True,
        say: Callable[[str], None] | None = None,
    ) -> dict[str, Any]:
        """Run ring ``ring``'s cycle (:class:`~ipc_app.service.cycle.RingCycle`):
        ``previous`` the part before as built (its own ring's T), ``records`` where the
        ring's acceptance record goes, ``walk_steps`` default ``cycle.walk_steps``.
        ``drive``: a thread of the service ticks it (``wara ctl cycle``); False: the
        caller does (the HIL driver between its simulated periods)."""
        rc = self.ring_cycle
        if rc is not None and rc.active:
            why = f"cycle refused: ring {rc.ring}'s cycle is in {rc.phase}"
            return Reply.refused(why).to_dict()
        cyc = RingCycle.request(self, ring, previous, records, walk_steps, walk_back_unloaded, say)
        if isinstance(cyc, Reply):
            return cyc.to_dict()
        self.ring_cycle = cyc
        cyc.start()
        if drive:
            threading.Thread(
                target=cyc.drive, args=(self.CYCLE_TICK_S,), name="wara-cycle", daemon=True
            ).start()
        return Reply.accepted(ring=ring, phase=cyc.phase).to_dict()

    def confirm_fixed(self, user: str) -> dict[str, Any]:
        """The operator confirms the part is fixed (``wara ctl confirm-fixed``)."""
        cyc = self.ring_cycle
        if cyc is None:
            return Reply.refused("confirm-fixed refused: no cycle").to_dict()
        return cyc.confirm_fixed(user).to_dict()

    def submit_survey(
        self, points: list[SurveyPoint] | None = None, pose: Pose | None = None
    ) -> dict[str, Any]:
        """The ring's as-built pose for the cycle's ``survey`` (``wara ctl survey``)."""
        cyc = self.ring_cycle
        if cyc is None:
            return Reply.refused("survey refused: no cycle").to_dict()
        return cyc.submit_survey(points, pose).to_dict()

    # ------------------------------------------------------------------ status

    def snapshot(self) -> dict[str, Any]:
        """The last cycle's status (safe to call from any thread); with ``on_axis`` (m, deg,
        mm) for a machine that walks."""
        rc = self.ring_cycle
        cycle = rc.status() if rc is not None else None
        snap = self.board.snapshot(self.link, self._inputs, self.motions.active, cycle)
        if self.cfg.walks:
            # where the machine stands against the axis (what `wara ctl locate` replaces)
            snap["on_axis"] = (self.on_axis or on_axis_at_start(self.cfg)).to_dict()
        return snap

    def achieved_attitude_deg(self, x: np.ndarray) -> tuple[float, float]:
        """Workpiece (roll, pitch) from measured rod positions (sensor view)."""
        return self.board.achieved_attitude_deg(x)

    # ------------------------------------------------------------------ the step

    def step(self, cycle: int, now: float) -> None:
        """One cycle: read the machine, update the modes and the motion, write."""
        self._now = now
        self.cycles += 1
        # the limit switches only where the stroke-end check may run this cycle (the
        # valve modes, and SUSPENDED, which may resume before the checks)
        inp = self.motions.reader.read(now, self.modes.mode in _LIMIT_MODES)
        self._inputs = inp
        u, ref = self.update(inp)
        write(self.link, MachineOutputs(self.control_words(), u, now))
        ride = (self.motions.suspends, self.motions.resumes)
        self.board.publish(
            self.modes, now, inp.positions.value, u, inp.link_state, ref, self.motions.stats,
            self.loop_stats, ride,
        )  # fmt: skip

    def control_words(self) -> tuple[ControlWord, ...]:
        """The cycle's control words after :meth:`update`: the handshake's edits, then
        the PLC mode and enable, the PackML state and unit mode."""
        enabled = self.modes.valves_enabled
        return self.handshake.finish(
            self.motions.plc_mode() if enabled else PlcMode.IDLE,
            enabled,
            MODE_CODES[self.modes.mode],
            UNIT_MODES[self.modes.unit_mode],
        )

    def update(self, inp: MachineInputs) -> tuple[np.ndarray, np.ndarray | None]:
        """The cycle's decisions from its inputs: interlocks, modes, ride-through, the
        requests, the active motion. Returns the spool commands and this cycle's
        references (None when the valves are closed); the control-word edits go to
        :attr:`handshake`."""
        now = inp.t
        self.handshake.begin()
        if inp.status is not None:  # e-stop first: it needs nothing else to be valid
            self.modes.estop(inp.status.estop)
        present = present_causes_of(inp, self.motions.limits)
        losses = link_losses(inp)
        late = False  # start-up not complete in time
        if not self.modes.booted:
            if self._boot_since is None:
                self._boot_since = now
            late = now - self._boot_since > self.boot_timeout_s
            if late and losses:  # present (a reset refused) until the link is fresh
                present.append(self._startup_cause(now - self._boot_since, losses))
        self._present = present
        if not self.modes.booted:
            if not present and not losses:  # every input fresh, the PLC hearing us
                self.modes.boot_complete()
            elif late:
                for cause in present:  # not complete within the start-up time
                    self.modes.fault(cause)
        else:
            for cause in present:  # latched by (interlock, where): repeats only counted
                self.modes.fault(cause)
        self._reset_step(now, present)
        self.motions.ride_through(now, losses, inp)
        if self.modes.valves_enabled and inp.positions_valid:
            for cause in motion_causes(inp, self.motions.metrics(), self.motions.limits):
                self.modes.fault(cause)
        if inp.hmi is not None:
            self.hmi.take(inp.hmi, now)
        while self._calls:  # the operator's requests, in order
            ticket, fn = self._calls.popleft()
            ticket.answer(fn(inp))
        for prep in self.preparations:
            prep.poll(inp)
        return self.motions.drive(inp)
