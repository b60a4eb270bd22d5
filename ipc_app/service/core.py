"""The service's control step: read -> update (interlocks, modes, control) -> write.

:class:`ServiceCore` owns no thread and no clock: :meth:`ServiceCore.step` is called once
per period with the time, by :class:`~ipc_app.service.loop.FixedRateLoop` in the service
or in lockstep with the HIL simulator in tests and the demo. Its work per cycle is
bounded: drain the CAN receive queue, a fixed set of checks, one trajectory sample, eight
controller updates, two CAN sends. Planning runs in the worker process; the control
channel's threads only call the (thread-safe) mode machine and read the last snapshot.

Interlocks are data (:mod:`ipc_app.service.interlocks`: which one, its config key, when
it applies); a tripped check is a :class:`~ipc_app.service.interlocks.Cause` and the
reaction a controlled stop: valves closed, load held, ABORTED latched until ``reset``.

A short loss of the link (the active group's rod positions or the PLC status stale, or
the PLC reporting the IPC's commands stale) suspends a motion instead (SUSPENDED: valves
closed, the trajectory clock stopped). Once fresh frames are back for
:attr:`ServiceCore.RESUME_FRESH_CYCLES` cycles and the rods are within the sync band of
where they stopped, the motion resumes by itself with the trajectory shifted in time; a
loss longer than its timeout latches the fault.

E-stop from the PLC takes the machine to ABORTED (valves closed) until released and reset.
The modes are PackML states (:mod:`ipc_app.service.modes`, docs/modes.md).

Over 500 lines because the step and the operator requests it serves (adjust, reset and
clear, hold and unhold, jog) work on the same state: the modes, the controllers, the
reference where a motion stopped; the checks themselves are in interlocks.py and the
inputs, outputs and handshake in machine_io.py.
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any, NamedTuple, Protocol

import numpy as np
import structlog

from config import units
from config.schema import ProjectConfig
from ipc_app.control.attitude import AttitudeController, ConstantSpeedPath
from ipc_app.control.placement import PlacementSequencer
from ipc_app.control.release import ReleaseSequencer, platform_pressures_pa
from ipc_app.control.slide import SLIDE_ROLES
from ipc_app.control.walk import WalkSequencer
from ipc_app.model.composition import check_attitude
from ipc_app.model.kinematics import fit_layer
from ipc_app.model.placement import Pose
from ipc_app.model.support import WalkingMachine, cap_side_forces_n, standing_load
from ipc_app.planner.placement import PlacementPlan
from ipc_app.planner.plan import Plan
from ipc_app.planner.survey import SurveyPoint
from ipc_app.planner.walk import DIRECTIONS, WalkPlan, WalkStart
from ipc_app.service.ctl import MAX_WALK_STEPS
from ipc_app.service.cycle import RingCycle, RingRecords
from ipc_app.service.interlocks import (
    Cause,
    Interlock,
    Latched,
    Limits,
    link_losses,
    motion_causes,
    present_causes,
    release_cause,
    resume_cause,
)
from ipc_app.service.loop import ChangeGate
from ipc_app.service.machine_io import (
    Handshake,
    MachineInputs,
    MachineOutputs,
    Reader,
    write,
)
from ipc_app.service.modes import (
    PACKML_STATES,
    SUSPENDABLE_MODES,
    UNIT_MODES,
    Mode,
    ModeMachine,
    Outcome,
    Transition,
    UnitMode,
)
from ipc_app.service.record import RunRecorder
from ipc_app.service.walk_interlocks import WalkLimits, walk_causes, walk_resume_cause
from ipc_app.service.worker import (
    PLAN_ATTITUDE_FN,
    PLAN_PLACE_FN,
    PLAN_WALK_FN,
    PlannerCallError,
    PlanResult,
)
from plc_bridge.link import ControlWord, HmiTarget, IpcLink, LinkState, TargetAck, TargetRequest
from plc_bridge.link import Mode as PlcMode

log = structlog.get_logger("wara.service")

#: Numeric mode in the run record (``mode_code`` column): the PackML state number.
_MODE_CODES = {m: PACKML_STATES[str(m)] for m in Mode}
#: the most steps an HMI WALK request carries (PLC_HmiTarget's WalkSteps, 2 bits)
HMI_WALK_STEPS_MAX = 3


#: Modes at the start of a cycle in which its motion checks may run.
_LIMIT_MODES = frozenset({Mode.EXECUTE, Mode.COMPLETE, Mode.SUSPENDED})


class _Call:
    """An operator request run by the loop thread (:meth:`ServiceCore._in_loop`)."""

    __slots__ = ("done", "fn", "result")

    def __init__(self, fn: Callable[[MachineInputs], dict[str, Any]]) -> None:
        self.fn = fn
        self.result: dict[str, Any] = {}
        self.done = threading.Event()


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

    def call(self, fn: str, *args: Any, **kwargs: Any) -> Any:
        """``fn(cfg, *args, **kwargs)`` in the planner process, blocking the caller (the
        walk's and the placement's planning; never from the loop)."""


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

    #: Seconds of COMPLETE before the standstill figures are taken (let the hold settle).
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
    ) -> None:
        self.cfg = cfg
        self.link = link
        self.planner = planner
        self.record = record
        self.period_s = cfg.control.period_s
        self.boot_timeout_s = cfg.safety.boot_timeout_s
        self.attitude = AttitudeController(cfg, self.period_s)
        self.active = self.attitude.layers["lower"] + self.attitude.layers["upper"]
        self.bus_load = link.set_active_cylinders(self.active)
        self._by_index = cfg.cylinders_by_can_index  # a property that sorts: once here
        self._active_ids = [(i, self._by_index[i].id) for i in self.active]
        self.stroke = np.array([c.stroke_m for c in self._by_index])
        self.limits = Limits.from_config(cfg, self.active)
        self.max_suspend_s = units.ms(cfg.safety.max_suspend_ms)
        self.reader = Reader(link, self.active)
        self.handshake = Handshake(link.control)
        self._inputs: MachineInputs | None = None
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
        self._pulse_for = "reset"
        self._calls: deque[_Call] = deque()
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
        #: the mode's changes, for a status that waits for the next one (ChangeGate)
        self.state_changes = ChangeGate()
        self._seen_mode: Mode | None = None
        self._preparing = 0  # the HMI's walks being planned off the loop (preparing)
        self._preparing_lock = threading.Lock()
        self.loop_stats: dict[str, Any] = {}
        self.cycles = 0
        # the walk: its sequencer while one runs (and holds after it), its limits
        self.walker: WalkSequencer | None = None
        self.walk_limits = WalkLimits.from_config(cfg) if cfg.walking is not None else None
        self._walk_phase = -1
        self._walk_stop: tuple[np.ndarray, np.ndarray] | None = None
        #: the rods and pressures of the walk's last driven cycle, each at its last valid
        #: value (the stop state; what a reading not valid this cycle stands at)
        self._walk_driven: tuple[np.ndarray, np.ndarray] | None = None
        #: M's legs where they stand (x, y) and their cap and rod areas, from the project
        #: alone: what :meth:`walk_start` reads the standing load with (made at its first)
        self._main_legs: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
        self._attitude_limits = self.limits
        # the placement move: its sequencer while one runs (and holds after it)
        self.placer: PlacementSequencer | None = None
        self.placement: dict[str, Any] | None = None  # the ring, plan and figures
        self._place_phase = -1
        # the part's release: its sequencer while one runs (and holds after it)
        self.releaser: ReleaseSequencer | None = None
        self.release_info: dict[str, Any] | None = None  # the ring and the figures
        #: the ring cycle's present ring and phase, as its driver reports them (status)
        self.cycle: dict[str, Any] | None = None
        #: the ring cycle asked of the service (``request_cycle``), the last one
        self.ring_cycle: RingCycle | None = None

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
        if tr.event == "reset":
            self.handshake.cleared()
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

    def request_reset(self, wait_s: float = 0.0) -> dict[str, Any]:
        """Reset: from ABORTED clear first (the PLC is asked to clear its own latched
        fault, ``fault_reset`` in the control word, :class:`Handshake`; then the modes
        once no cause is present), then STOPPED -> IDLE. With ``wait_s`` > 0 wait for
        the outcome."""
        return self._after_pulse("reset", wait_s)

    def request_clear(self, wait_s: float = 0.0) -> dict[str, Any]:
        """Clear: ABORTED -> STOPPED (the PLC's fault cleared as for a reset)."""
        return self._after_pulse("clear", wait_s)

    def _after_pulse(self, event: str, wait_s: float) -> dict[str, Any]:
        act = self.modes.reset if event == "reset" else self.modes.clear
        if self.modes.mode != Mode.ABORTED:
            return act().to_dict()  # a plain reset, or refused with its message
        with self._outcome_cv:
            self._reset_outcome = None
            self._pulse_for = event
            self.handshake.request_reset()
            if wait_s <= 0:
                note = "resetting" if event == "reset" else "clearing"
                return {"ok": True, "mode": str(self.modes.mode), "note": note}
            self._outcome_cv.wait_for(lambda: self._reset_outcome is not None, timeout=wait_s)
            out = self._reset_outcome
        return out if out is not None else act().to_dict()

    def _startup_cause(self, booting_s: float, losses: list[str]) -> Cause:
        return Cause(
            Interlock.STARTUP,
            value=booting_s,
            limit=self.boot_timeout_s,
            detail="not complete: " + "; ".join(losses),
        )

    def _reset_step(self, now: float, present: list[Cause]) -> None:
        """Drive a requested reset or clear (loop thread)."""
        if not self.handshake.resetting:
            return
        plc_fault = any(c.interlock is Interlock.PLC_FAULT for c in present)
        if self.handshake.reset_step(now, plc_fault):
            act = self.modes.reset if self._pulse_for == "reset" else self.modes.clear
            out = act().to_dict()
            with self._outcome_cv:
                self._reset_outcome = out
                self._outcome_cv.notify_all()

    def request_unit_mode(self, unit: str) -> dict[str, Any]:
        """PRODUCTION, MAINTENANCE or MANUAL; only in STOPPED, IDLE or ABORTED."""
        try:
            um = UnitMode(unit.upper())
        except ValueError:
            names = ", ".join(str(u) for u in UnitMode)
            return {
                "ok": False,
                "code": "bad_request",
                "error": f"unit mode {unit!r}: one of {names}",
            }
        return self.modes.set_unit_mode(um).to_dict()

    def request_hold(self, wait_s: float = 0.0) -> dict[str, Any]:
        """EXECUTE -> HELD (done by the loop: the pose where the motion stops)."""
        return self._in_loop(self._do_hold, wait_s)

    def request_unhold(self, wait_s: float = 0.0) -> dict[str, Any]:
        """HELD -> EXECUTE once the rods are where the motion stopped (loop)."""
        return self._in_loop(self._do_unhold, wait_s)

    def request_jog(self, cylinder: str, distance_mm: float, wait_s: float = 0.0) -> dict[str, Any]:
        """Jog one attitude cylinder by ``distance_mm`` at ``control.manual_jog_speed_mm_s``
        (unit mode MANUAL, from IDLE or COMPLETE; the other cylinders hold)."""
        return self._in_loop(lambda inp: self._do_jog(inp, cylinder, distance_mm), wait_s)

    def _in_loop(
        self, fn: Callable[[MachineInputs], dict[str, Any]], wait_s: float
    ) -> dict[str, Any]:
        call = _Call(fn)
        self._calls.append(call)  # bounded by the control channel's worker pool
        if wait_s > 0 and call.done.wait(wait_s):
            return call.result
        return {"ok": True, "mode": str(self.modes.mode), "note": "pending"}

    def _run_calls(self, inp: MachineInputs) -> None:
        while self._calls:
            call = self._calls.popleft()
            call.result = call.fn(inp)
            call.done.set()

    def _do_hold(self, inp: MachineInputs) -> dict[str, Any]:
        out = self.modes.hold()
        if out.accepted:
            self._stopped_here(inp.t)
        return out.to_dict()

    def _do_unhold(self, inp: MachineInputs) -> dict[str, Any]:
        if self.modes.mode != Mode.HELD:
            return self.modes.unhold().to_dict()  # refused, with its message
        stop_ref = self._stop_ref.tolist() if self._stop_ref is not None else None
        cause = None if inp.positions_valid else "rod positions not valid"
        if cause is None and self.walker is not None:
            c = self._walk_resume_cause(inp)
            cause = None if c is None else c.text()
            if c is not None and self.record is not None:
                self.record.event(inp.t, "walk_resume_refused", reason=c.text())
            if cause is None:
                self.walker.resume(inp.positions.value, inp.pressures.value)
                self.modes.unhold("operator unhold: the walk's resume check passed")
                return {"ok": True, "mode": str(self.modes.mode)}
        elif cause is None:
            c = resume_cause(inp, stop_ref, self.limits)
            cause = None if c is None else c.text()
        if cause is not None:
            msg = f"unhold refused: {cause}; `wara ctl stop` ends the motion"
            return {"ok": False, "code": "refused", "error": msg, "mode": str(self.modes.mode)}
        self._go_on(inp.t, inp.positions.value, self.modes.unhold, "operator unhold")
        return {"ok": True, "mode": str(self.modes.mode)}

    def _do_jog(self, inp: MachineInputs, cylinder: str, distance_mm: float) -> dict[str, Any]:
        def refused(msg: str) -> dict[str, Any]:
            return {"ok": False, "code": "refused", "error": msg, "mode": str(self.modes.mode)}

        if not self.modes.allowed("jog"):
            return self.modes.jog(cylinder).to_dict()  # refused, with its message
        where = [
            (name, k, i)
            for name, idx in self.attitude.layers.items()
            for k, i in enumerate(idx)
            if self._by_index[i].id == cylinder
        ]
        if not where:
            ids = ", ".join(self._by_index[i].id for i in self.active)
            return refused(f"jog: {cylinder!r} is not an attitude cylinder ({ids})")
        if not inp.positions_valid:
            return refused("jog refused: rod positions not valid")
        ((layer, k, i),) = where
        x = inp.positions.value
        d = units.mm(distance_mm)
        end = float(x[i]) + d
        lo, hi = self.limits.end_margin_m, self.limits.stroke_m[i] - self.limits.end_margin_m
        if not (math.isfinite(d) and d != 0.0 and lo <= end <= hi):
            return refused(
                f"jog refused: {cylinder} would end at {units.to_mm(end):.1f} mm, outside "
                f"{units.to_mm(lo):.1f}..{units.to_mm(hi):.1f} mm (stroke less the end margin)"
            )
        speed = units.mm(self.cfg.control.manual_jog_speed_mm_s)
        half = self.stroke / 2
        lo_i, up_i = self.attitude.layers["lower"], self.attitude.layers["upper"]
        path = ConstantSpeedPath(
            (x[lo_i] - half[lo_i]).tolist(), (x[up_i] - half[up_i]).tolist(), layer, (k,), d, speed
        )
        out = self.modes.jog(f"{cylinder} {distance_mm:+.2f} mm at {units.to_mm(speed):.1f} mm/s")
        if out.accepted:
            self.motion = MotionStats(started_s=inp.t)
            # a trajectory by its interface (duration_s, sample, positions)
            self.attitude.engage(x, inp.t, path)  # type: ignore[arg-type]
        return out.to_dict()

    # ------------------------------------------------------------------ the walk

    def walk_start(self) -> WalkStart | str:
        """The measured state a walk would start from now (:class:`WalkStart`: ``x_S``,
        the layers' extensions, the load M's standing legs measure), or why there is
        none yet (a refusal's text: a position or a standing leg's pressure not valid)."""
        inp = self._inputs
        if inp is None or not inp.positions_valid:
            return "walk refused: no valid positions"
        x = inp.positions.value
        cfg = self.cfg
        travel = [c.can_index for c in cfg.cylinders_by_can_index if c.role == "travel"]
        e0 = cfg.cylinders_by_can_index[travel[0]].stroke_m / 2
        x_s = float(np.mean(x[travel])) - e0
        half = self.stroke / 2
        lo, up = self.attitude.layers["lower"], self.attitude.layers["upper"]
        if not (np.all(np.isfinite(x[travel])) and np.all(np.isfinite(x[up]))):
            return "walk refused: no valid positions"
        press = inp.pressures
        if not press.all_valid(lo):
            return "walk refused: the standing legs' pressures not valid (yet)"
        if self._main_legs is None:
            legs = [cfg.cylinders_by_can_index[i] for i in lo]
            self._main_legs = (
                WalkingMachine(cfg).main_legs_xy,
                np.array([c.cap_area_m2 for c in legs]),
                np.array([c.rod_area_m2 for c in legs]),
            )
        legs_xy, cap, rod = self._main_legs
        forces = cap_side_forces_n(press.value[lo], cap, rod)
        try:  # M stands: its legs measure the machine's weight and COG
            standing = standing_load(legs_xy, forces, x_s)
        except ValueError as exc:
            return f"walk refused: {exc}"
        return WalkStart(
            x_s_m=x_s,
            main_extensions_m=tuple((x[lo] - half[lo]).tolist()),
            upper_extensions_m=tuple((x[up] - half[up]).tolist()),
            standing=standing,
        )

    def plan_walk_here(
        self, steps: int, direction: str = "forward", unloaded: bool = False
    ) -> WalkPlan | dict[str, Any]:
        """Plan ``steps`` steps from the last measured state (:meth:`walk_start`), in the
        planner process (the caller's thread waits; never the loop's); a dict when the
        service cannot walk now (why)."""
        if self.cfg.walking is None or self.cfg.frames is None:
            msg = "the project has no frames and walking sections: it cannot walk"
            return {"ok": False, "code": "bad_request", "error": msg}
        start = self.walk_start()
        if isinstance(start, str):
            return {"ok": False, "code": "refused", "error": start}
        try:
            plan: WalkPlan = self.planner.call(
                PLAN_WALK_FN, steps, start, direction=direction, unloaded=unloaded
            )
        except PlannerCallError as exc:  # ValueError: unloaded without a workpiece body
            code = "bad_request" if exc.raised == "ValueError" else "planner"
            return {"ok": False, "code": code, "error": f"walk refused: {exc}"}
        return plan

    def request_walk(
        self,
        steps: int,
        wait_s: float = 0.0,
        hmi_seq: int = 0,
        direction: str = "forward",
        unloaded: bool = False,
    ) -> dict[str, Any]:
        """Walk ``steps`` steps ``direction`` (``forward``, ``back``), ``unloaded``: the
        statics without the workpiece. Planned from the measured state and refused
        (with the phase, instant and limit) before anything moves if a constraint breaks;
        then the loop runs the step sequencer (EXECUTE) until the last phase (COMPLETE).
        ``hmi_seq``: the HMI's TargetSeq of a WALK request (answered ACCEPTED, REJECTED,
        COMPLETED); 0 for a local request."""
        if not 1 <= steps <= MAX_WALK_STEPS:
            why = f"steps 1..{MAX_WALK_STEPS}, got {steps}"
            return self._walk_refused({"ok": False, "code": "bad_request", "error": why}, hmi_seq)
        if direction not in DIRECTIONS:
            why = f"direction must be one of {', '.join(DIRECTIONS)}, got {direction!r}"
            return self._walk_refused({"ok": False, "code": "bad_request", "error": why}, hmi_seq)
        plan = self.plan_walk_here(steps, direction, unloaded)
        if isinstance(plan, dict):
            return self._walk_refused(plan, hmi_seq)
        if not plan.feasible:
            ref = plan.refusal
            assert ref is not None
            if self.record is not None:
                self.record.event(self._now, "walk_refused", refusal=ref.to_dict())
            out = {
                "ok": False,
                "code": "infeasible",
                "error": f"walk refused: {ref.message}",
                "refusal": ref.to_dict(),
            }
            return self._walk_refused(out, hmi_seq)
        return self._in_loop(lambda inp: self._do_walk(inp, plan, hmi_seq), wait_s)

    def _walk_refused(self, out: dict[str, Any], hmi_seq: int) -> dict[str, Any]:
        """A refused walk: an HMI request is answered REJECTED (in the loop)."""
        if hmi_seq:
            reason = str(out.get("error", ""))
            self._in_loop(lambda inp: self._hmi_refused(inp.t, hmi_seq, reason), 0.0)
        return out

    def _hmi_refused(self, now: float, seq: int, reason: str) -> dict[str, Any]:
        self.handshake.ack(TargetAck.REJECTED, seq)
        log.warning("hmi request refused", seq=seq, reason=reason)
        if self.record is not None:
            self.record.event(now, "hmi_refused", seq=seq, reason=reason)
        return {"ok": False, "error": reason}

    def _hmi_walk(self, hmi: HmiTarget, now: float) -> None:
        """The HMI's WALK request: a malformed step count is refused here; a valid one is
        planned off the loop (one thread per request: planning is not the loop's work)
        and answered with its TargetSeq."""
        if not 1 <= hmi.walk_steps <= HMI_WALK_STEPS_MAX:
            reason = (
                f"HMI walk refused: WalkSteps {hmi.walk_steps} "
                f"(a walk is 1..{HMI_WALK_STEPS_MAX} steps)"
            )
            self._hmi_refused(now, hmi.seq, reason)
            return
        with self._preparing_lock:
            self._preparing += 1
        threading.Thread(
            target=self._prepare_hmi_walk, args=(hmi,), name="wara-hmi-walk", daemon=True
        ).start()

    def _prepare_hmi_walk(self, hmi: HmiTarget) -> None:
        try:
            self.request_walk(hmi.walk_steps, hmi_seq=hmi.seq)
        finally:
            with self._preparing_lock:
                self._preparing -= 1

    @property
    def preparing(self) -> bool:
        """A request of the loop's (the HMI's walk) is being planned on a thread of its
        own and not yet handed back to the loop (the lockstep harness holds machine time
        meanwhile, as it does for the planner)."""
        return self._preparing > 0

    def _do_walk(self, inp: MachineInputs, plan: WalkPlan, hmi_seq: int = 0) -> dict[str, Any]:
        if not inp.positions_valid:
            err = "walk refused: no valid positions"
            if hmi_seq:
                self._hmi_refused(inp.t, hmi_seq, err)
            return {"ok": False, "code": "refused", "error": err}
        load = ", unloaded" if plan.unloaded else ""
        out = self.modes.walk(
            f"{plan.steps} step(s) {plan.direction} of {plan.step_length_m:.3f} m{load}"
        )
        if not out.accepted:
            if hmi_seq:
                self._hmi_refused(inp.t, hmi_seq, out.message)
            return {"ok": False, "code": "refused", "error": out.message, "mode": str(out.mode)}
        self._end_place(inp.t)  # a walk from a placed pose: the placement's hold ends
        self._end_release(inp.t)  # ... or from a release's
        self.handshake.serve(hmi_seq)
        self.handshake.ack(TargetAck.ACCEPTED)
        walker = WalkSequencer(self.cfg, self.period_s, plan)
        walker.start(inp.t, inp.positions.value, inp.pressures.value)
        self.walker = walker
        self._walk_phase = -1
        self._walk_driven = self._walk_stop = None
        self.motion = MotionStats(started_s=inp.t)
        self._walk_group(inp.t)
        if self.record is not None:
            self.record.event(
                inp.t, "walk", steps=plan.steps, direction=plan.direction, unloaded=plan.unloaded
            )
        return {"ok": True, "mode": str(self.modes.mode), "duration_s": plan.duration_s}

    def _walk_group(self, now: float) -> None:
        """The present phase's active group on the link (and what the reader and the
        stroke-end check watch); a phase change is an event of the run record."""
        w = self.walker
        assert w is not None and w.run is not None
        if w.run.index == self._walk_phase:
            return
        self._walk_phase = w.run.index
        group = w.active_group()
        self._use_group(group, group, now)
        ph = w.run.phase
        log.info("walk phase", step=ph.step, phase=ph.key, name=w.phase_name())
        if self.record is not None:
            self.record.event(
                now,
                "walk_phase",
                step=ph.step,
                phase=ph.key,
                name=w.phase_name(),
                active=group,
                bus_load_percent=round(self.bus_load.load_percent, 2),
                margin_ahead_m=w.figures.margin_ahead_m,
            )

    def _use_group(self, group: Sequence[int], watched: Sequence[int], now: float) -> None:
        """A motion's phase group: ``group`` at the loop rate on the link, ``watched`` read
        and checked (stroke ends) by the attitude interlocks."""
        self.bus_load = self.link.set_active_cylinders(group, now)
        self.reader = Reader(self.link, watched)
        self.limits = replace(self._attitude_limits, active=tuple(watched))

    def _attitude_group(self) -> None:
        """Back to the attitude group after a walk or a placement."""
        self.bus_load = self.link.set_active_cylinders(self.active)
        self.reader = Reader(self.link, self.active)
        self.limits = self._attitude_limits

    def _end_walk(self) -> None:
        """Back to the attitude group (an adjustment from the walk's end state, a stop)."""
        if self.walker is None:
            return
        self.walker = None
        self._walk_phase = -1
        self._walk_driven = self._walk_stop = None
        self._attitude_group()

    def _walk_resume_cause(self, inp: MachineInputs, forces: bool = True) -> Cause | None:
        """The walk's resume check against the stop state; ``forces`` False: the rods
        only (a ride-through: see :meth:`_ride_through`)."""
        w, lim = self.walker, self.walk_limits
        assert w is not None and lim is not None
        if self._walk_stop is None:
            return None
        x_stop, f_stop = self._walk_stop
        x = inp.positions.value
        share = w.figures.expected_n or tuple([1.0] * 8)
        heights = w.legs + w.upper
        return walk_resume_cause(
            x.tolist(), x_stop.tolist(), heights, w.travel, self.limits.ids,
            w.forces_n(inp.pressures.value).tolist(), f_stop.tolist(), share,
            w.leg_ids if forces else (), lim,
        )  # fmt: skip

    def walk_status(self) -> dict[str, Any] | None:
        """The walk's step and phase for ``wara ctl status`` (None: no walk)."""
        w = self.walker
        if w is None or w.run is None:
            return None
        fig = w.figures
        return {
            "steps": w.plan.steps,
            "direction": w.plan.direction,
            "unloaded": w.plan.unloaded,
            "step": fig.step,
            "phase": fig.phase,
            "phase_name": w.phase_name(),
            "done": w.done,
            "phase_time_s": round(fig.phase_t_s, 3),
            "stability_margin_m": round(fig.margin_m, 4) if math.isfinite(fig.margin_m) else None,
            "leg_forces_kn": {
                cid: round(f / units.KN, 2)
                for cid, f in zip(w.leg_ids, fig.leg_force_n, strict=False)
            },
            "out_of_band": fig.out_of_band,
            "steps_done": [s.to_dict() for s in w.steps if s.duration_s > 0],
        }

    # ------------------------------------------------------------------ the placement

    def request_place(
        self, ring: int, previous_deviation: Pose, wait_s: float = 0.0
    ) -> dict[str, Any]:
        """Place ring ``ring``'s part: its target planned from the previous part's
        deviation from its design (:func:`~ipc_app.planner.placement.plan_from_deviation`,
        in the planner process), then :meth:`request_place_plan`."""
        if self.cfg.placement is None:
            msg = "the project has no placement section (and tunnel.alignment): it cannot place"
            return {"ok": False, "code": "bad_request", "error": msg}
        if not 1 <= ring <= 99_999:
            return {"ok": False, "code": "bad_request", "error": f"ring 1..99999, got {ring}"}
        try:
            plan: PlacementPlan = self.planner.call(PLAN_PLACE_FN, ring, previous_deviation)
        except PlannerCallError as exc:
            return {"ok": False, "code": "planner", "error": f"place refused: {exc}"}
        return self.request_place_plan(plan, wait_s)

    def request_place_plan(self, plan: PlacementPlan, wait_s: float = 0.0) -> dict[str, Any]:
        """Move the part to ``plan``'s target: refused (exit 3 in ``wara ctl``, with the
        binding limit) when the plan is infeasible; the attitude trajectory planned in
        the planner process from the measured state, every move checked before anything
        moves; then the loop runs the :class:`PlacementSequencer` (EXECUTE) until both
        phases have settled (COMPLETE, holding the pose)."""

        def refused(code: str, msg: str, **more: Any) -> dict[str, Any]:
            if self.record is not None:
                self.record.event(self._now, "place_refused", ring=plan.ring, error=msg)
            return {"ok": False, "code": code, "error": msg, **more}

        if not plan.feasible:
            return refused(
                "infeasible", "place refused: " + "; ".join(plan.reasons), reasons=plan.reasons,
                plan=plan.to_dict(),
            )  # fmt: skip
        inp = self._inputs
        if inp is None or not inp.positions_valid:
            return refused("refused", "place refused: no valid positions")
        x = inp.positions.value
        half = self.stroke / 2
        lo, up = self.attitude.layers["lower"], self.attitude.layers["upper"]
        heave = plan.heave_m
        roll_deg, pitch_deg = plan.attitude_world_deg
        try:
            att: Plan = self.planner.call(
                PLAN_ATTITUDE_FN, roll_deg, pitch_deg,
                start_lower_m=tuple((x[lo] - half[lo] - heave).tolist()),
                start_upper_m=tuple((x[up] - half[up]).tolist()),
            )  # fmt: skip
        except PlannerCallError as exc:
            return refused("planner", f"place refused: {exc}")
        if not att.feasible or att.trajectory is None:
            return refused(
                "infeasible", "place refused: " + "; ".join(att.reasons), reasons=list(att.reasons)
            )
        ext = {
            a.group: tuple(units.mm(e) for e in a.extensions_mm)
            for a in plan.actuators
            if a.group in SLIDE_ROLES
        }
        try:
            placer = PlacementSequencer(
                self.cfg, self.period_s, self.attitude, att.trajectory, heave, ext
            )
        except ValueError as exc:
            return refused("infeasible", f"place refused: {exc}")
        return self._in_loop(lambda i: self._do_place(i, plan, placer), wait_s)

    def _do_place(
        self, inp: MachineInputs, plan: PlacementPlan, placer: PlacementSequencer
    ) -> dict[str, Any]:
        if not inp.positions_valid:
            return {"ok": False, "code": "refused", "error": "place refused: no valid positions"}
        tgt = plan.to_dict()["target_deviation"]
        out = self.modes.place(
            f"ring {plan.ring}: y {tgt['y_mm']:+.2f} mm, z {tgt['z_mm']:+.2f} mm from its design"
        )
        if not out.accepted:
            return {"ok": False, "code": "refused", "error": out.message, "mode": str(out.mode)}
        self._end_walk()  # a placement from a walk's end state: the walk's hold ends
        self._end_place(inp.t)
        self._end_release(inp.t)
        placer.start(inp.t, inp.positions.value)
        self.placer = placer
        self._place_phase = -1
        self.placement = {"ring": plan.ring, "plan": plan.to_dict(), "started_s": inp.t}
        self.motion = MotionStats(started_s=inp.t, plan=self.placement["plan"])
        if self.record is not None:
            self.record.event(inp.t, "place", ring=plan.ring, plan=self.placement["plan"])
        self._place_group(inp.t)
        return {"ok": True, "mode": str(self.modes.mode), "ring": plan.ring}

    def _place_update(
        self, inp: MachineInputs, placer: PlacementSequencer
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """A placement's cycle: the sequencer drives both sets of axes."""
        now = inp.t
        if not (self.modes.valves_enabled and inp.positions_valid):
            return np.zeros(len(self.cfg.cylinders)), None
        was_done = placer.done
        u = placer.update(now, np.nan_to_num(inp.positions.value, nan=0.0))
        self._last_drive_t = now
        self._motion_figures(now)
        if self.modes.mode == Mode.EXECUTE and placer.done and not was_done:
            self.modes.motion_done()
            self.motion.duration_s = now - self.motion.started_s
            if self.placement is not None:
                self.placement["phase_times_s"] = dict(placer.phase_times_s)
            if self.record is not None:
                self.record.event(
                    now,
                    "place_done",
                    ring=self.placement["ring"] if self.placement else None,
                    phase_times_s=placer.phase_times_s,
                    max_sync_error_mm=units.to_mm(placer.max_sync_error_m),
                )
        self._place_group(now)
        return u, placer.last_refs

    def _place_group(self, now: float) -> None:
        """The present phase's group on the link; a phase change is an event."""
        p = self.placer
        assert p is not None
        if p.phase == self._place_phase:
            return
        self._place_phase = p.phase
        group = p.active_group()
        self._use_group(group, p.watched(), now)
        log.info("place phase", phase=p.phase_name)
        if self.record is not None:
            self.record.event(
                now, "place_phase", phase=p.phase_name, active=group,
                bus_load_percent=round(self.bus_load.load_percent, 2),
            )  # fmt: skip

    def _end_place(self, now: float) -> None:
        """Back to the attitude group (stopped, or a new motion from the placed pose)."""
        p = self.placer
        if p is None:
            return
        p.finish()
        self.placer = None
        self._place_phase = -1
        self._attitude_group()
        if self.record is not None:
            self.record.event(now, "place_end", phase=p.phase_name, mode=str(self.modes.mode))

    # ------------------------------------------------------------------ the release

    def request_release(self, ring: int, wait_s: float = 0.0) -> dict[str, Any]:
        """Lower the upper platform off ring ``ring``'s fixed part (placement.md section
        4; :mod:`ipc_app.control.release`): the empty platform's pressures from the
        statics at the measured attitudes (here, in the caller's thread), the stroke
        checked; then the loop runs the :class:`ReleaseSequencer` (EXECUTE) until the
        load is off and the clearance lowered (COMPLETE, holding), or the ``release``
        interlock stops it."""
        if self.cfg.cycle is None:
            msg = "the project has no cycle section: it cannot release"
            return {"ok": False, "code": "bad_request", "error": msg}
        inp = self._inputs
        if inp is None or not inp.positions_valid:
            return {"ok": False, "code": "refused", "error": "release refused: no valid positions"}
        x = inp.positions.value
        try:
            empty = platform_pressures_pa(
                self.cfg, x, unloaded=True, lowering_speed_m_s=self.cfg.cycle.release_speed_m_s
            )
            at_rest = platform_pressures_pa(self.cfg, x, unloaded=True)
        except ValueError as exc:  # no workpiece body
            return {"ok": False, "code": "bad_request", "error": f"release refused: {exc}"}
        releaser = ReleaseSequencer(self.cfg, self.attitude, empty, at_rest)
        why = releaser.check(x)
        if why:
            msg = "release refused: " + "; ".join(why)
            return {"ok": False, "code": "infeasible", "error": msg}
        return self._in_loop(lambda i: self._do_release(i, ring, releaser), wait_s)

    def _do_release(
        self, inp: MachineInputs, ring: int, releaser: ReleaseSequencer
    ) -> dict[str, Any]:
        if not inp.positions_valid:
            return {"ok": False, "code": "refused", "error": "release refused: no valid positions"}
        out = self.modes.release(f"ring {ring}: the upper platform off the fixed part")
        if not out.accepted:
            return {"ok": False, "code": "refused", "error": out.message, "mode": str(out.mode)}
        self._end_walk()
        self._end_place(inp.t)  # the placed pose's hold ends: the release goes on from it
        self._end_release(inp.t)
        releaser.start(inp.t, inp.positions.value, inp.pressures.value)
        self.releaser = releaser
        self.release_info = {"ring": ring, "started_s": inp.t}
        self.motion = MotionStats(started_s=inp.t)
        if self.record is not None:
            self.record.event(
                inp.t, "release", ring=ring, **releaser.figures.to_dict(),
                speed_mm_s=units.to_mm(releaser.speed_m_s),
                tolerance_mpa=units.to_mpa(releaser.tolerance_pa),
            )  # fmt: skip
        log.info("release", ring=ring)
        return {"ok": True, "mode": str(self.modes.mode), "ring": ring}

    def _release_update(
        self, inp: MachineInputs, releaser: ReleaseSequencer
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """A release's cycle: the sequencer drives the attitude layers; its interlock."""
        now = inp.t
        if not (self.modes.valves_enabled and inp.positions_valid):
            return np.zeros(len(self.cfg.cylinders)), None
        was = (releaser.phase, releaser.done)
        up = releaser.upper
        p_valid = bool(inp.pressures.valid[up].all())
        x = np.nan_to_num(inp.positions.value, nan=0.0)
        u = releaser.update(now, x, np.nan_to_num(inp.pressures.value, nan=0.0), p_valid)
        self._last_drive_t = now
        self._motion_figures(now)
        fig = releaser.figures
        if self.modes.mode == Mode.EXECUTE:
            if releaser.out_of_travel:
                self.modes.fault(release_cause(releaser, self.limits.ids))
            elif releaser.phase != was[0] and self.record is not None:
                self.record.event(now, "release_phase", phase=releaser.phase_name, **fig.to_dict())
            if releaser.done and not was[1]:
                self.modes.motion_done()
                self.motion.duration_s = now - self.motion.started_s
                if self.record is not None:
                    self.record.event(
                        now, "release_done", phase_times_s=releaser.phase_times_s,
                        **fig.to_dict(),
                    )  # fmt: skip
                log.info("release done", **fig.to_dict())
        if not self.modes.valves_enabled:
            return np.zeros(len(self.cfg.cylinders)), None
        return u, self.attitude.last_references

    def _end_release(self, now: float) -> None:
        """The release's hold ends (stopped, or a new motion from where it left)."""
        r = self.releaser
        if r is None:
            return
        self.releaser = None
        if self.record is not None:
            self.record.event(now, "release_end", phase=r.phase_name, mode=str(self.modes.mode))

    def release_status(self) -> dict[str, Any] | None:
        """The release's phase and figures for ``wara ctl status`` (None: none)."""
        r, info = self.releaser, self.release_info
        if r is None or info is None:
            return None
        return {
            "ring": info["ring"],
            "phase": r.phase_name,
            "done": r.done,
            "phase_times_s": {k: round(v, 3) for k, v in r.phase_times_s.items()},
            **r.figures.to_dict(),
        }

    # ------------------------------------------------------------------ the ring cycle

    @property
    def now_s(self) -> float:
        """Machine time of the last cycle, s."""
        return self._now

    @property
    def inputs(self) -> MachineInputs | None:
        """The last cycle's readings (one reference, replaced whole each cycle)."""
        return self._inputs

    @property
    def requests_pending(self) -> int:
        """Requests waiting for the loop to take them."""
        return len(self._calls)

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
        if self.cfg.placement is None or self.cfg.cycle is None:
            msg = "the project has no placement and cycle sections: it cannot run a cycle"
            return {"ok": False, "code": "bad_request", "error": msg}
        if not 2 <= ring <= 99_999:
            return {"ok": False, "code": "bad_request", "error": f"ring 2..99999, got {ring}"}
        steps = self.cfg.cycle.walk_steps if walk_steps is None else walk_steps
        if not 0 <= steps <= MAX_WALK_STEPS:
            why = f"walk_steps 0..{MAX_WALK_STEPS}, got {steps}"
            return {"ok": False, "code": "bad_request", "error": why}
        if self.ring_cycle is not None and self.ring_cycle.active:
            rc = self.ring_cycle
            why = f"cycle refused: ring {rc.ring}'s cycle is in {rc.phase}"
            return {"ok": False, "code": "refused", "error": why}
        if self.modes.mode not in (Mode.IDLE, Mode.COMPLETE):
            why = f"cycle refused: the service is {self.modes.mode} (IDLE or COMPLETE needed)"
            return {"ok": False, "code": "refused", "error": why}
        cyc = RingCycle(
            self, ring, previous, records, walk_steps=steps,
            walk_back_unloaded=walk_back_unloaded, say=say or (lambda _s: None),
        )  # fmt: skip
        self.ring_cycle = cyc
        if self.record is not None:
            self.record.event(
                self._now, "cycle", ring=ring, previous=previous.to_dict(), walk_steps=steps,
                walk_back_unloaded=walk_back_unloaded,
            )  # fmt: skip
        cyc.start()
        if drive:
            threading.Thread(
                target=self._drive_cycle, args=(cyc,), name="wara-cycle", daemon=True
            ).start()
        return {"ok": True, "ring": ring, "phase": cyc.phase}

    def _drive_cycle(self, cyc: RingCycle) -> None:
        """The service's cycle thread: ticks the cycle until it ends (never the loop)."""
        while cyc.active:
            try:
                cyc.tick()
            except Exception as exc:  # a bug: the cycle ends, the machine stops
                log.exception("cycle_failed", ring=cyc.ring, phase=cyc.phase)
                cyc._fail(f"internal: {type(exc).__name__}: {exc}")
                return
            time.sleep(self.CYCLE_TICK_S)

    #: how often the service's cycle thread looks at the cycle, s
    CYCLE_TICK_S = 0.05

    def confirm_fixed(self, user: str) -> dict[str, Any]:
        """The operator confirms the part is fixed (``wara ctl confirm-fixed``)."""
        cyc = self.ring_cycle
        if cyc is None:
            return {"ok": False, "code": "refused", "error": "confirm-fixed refused: no cycle"}
        return cyc.confirm_fixed(user)

    def submit_survey(
        self, points: list[SurveyPoint] | None = None, pose: Pose | None = None
    ) -> dict[str, Any]:
        """The ring's as-built pose for the cycle's ``survey`` (``wara ctl survey``)."""
        cyc = self.ring_cycle
        if cyc is None:
            return {"ok": False, "code": "refused", "error": "survey refused: no cycle"}
        return cyc.submit_survey(points, pose)

    def stop(self, reason: str) -> dict[str, Any]:
        """A controlled stop (``wara ctl stop``); a running ring cycle ends with it."""
        out = self.modes.stop(reason).to_dict()
        cyc = self.ring_cycle
        if cyc is not None and cyc.active:
            cyc.stop(reason)
        return out

    def end_cycle(self, cyc: RingCycle, error: str | None) -> None:
        """The ring cycle ended (``error`` None: done): the run record and the log; a
        failed cycle leaves the machine stopped (valves closed)."""
        if error is not None and self.modes.mode in (
            Mode.STARTING, Mode.EXECUTE, Mode.COMPLETE, Mode.HELD, Mode.SUSPENDED,
        ):  # fmt: skip
            self.modes.stop(f"ring {cyc.ring}'s cycle ended in {cyc.phase}: {error}")
        log.info("cycle end", ring=cyc.ring, phase=cyc.phase, error=error)
        if self.record is not None:
            self.record.event(
                self._now, "cycle_end", ring=cyc.ring, phase=cyc.phase, error=error,
                phase_times_s=cyc.phase_times_s, table4=cyc.table4,
            )  # fmt: skip

    def note_cycle(self, ring: int, phase: str, **figures: Any) -> None:
        """The ring cycle's driver enters ``phase`` of ring ``ring``: in the status
        (``cycle``), the run record (a ``cycle_phase`` event with ``figures``) and the log."""
        self.cycle = {"ring": ring, "phase": phase, "since_s": self._now, **figures}
        log.info("cycle phase", ring=ring, phase=phase, **figures)
        if self.record is not None:
            self.record.event(self._now, "cycle_phase", ring=ring, phase=phase, **figures)

    def place_status(self) -> dict[str, Any] | None:
        """The placement's ring, phase and figures for ``wara ctl status`` (None: none)."""
        p, info = self.placer, self.placement
        if p is None or info is None:
            return None
        plan = info["plan"]
        return {
            "ring": info["ring"],
            "phase": p.phase_name,
            "done": p.done,
            "phase_times_s": {k: round(v, 3) for k, v in p.phase_times_s.items()},
            "max_sync_error_mm": round(units.to_mm(p.max_sync_error_m), 4),
            "target_deviation": plan["target_deviation"],
            "expected_table4": {k: v["value"] for k, v in plan["table4"].items() if v},
        }

    def request_adjust(
        self, roll_deg: float, pitch_deg: float, wait_s: float = 0.0, hmi_seq: int = 0
    ) -> dict[str, Any]:
        """Ask for an adjustment; with ``wait_s`` > 0 wait for the planner's verdict.
        ``hmi_seq``: the HMI's TargetSeq (0 for a local request: nothing is acknowledged
        to the PLC)."""
        with self._outcome_cv:
            self._outcome = None
        out = self.modes.request_adjust(roll_deg, pitch_deg)
        if out.accepted:
            self.handshake.serve(hmi_seq)
        else:
            return {"ok": False, "code": "refused", "error": out.message, "mode": str(out.mode)}
        if wait_s <= 0:
            return {"ok": True, "mode": str(Mode.STARTING)}
        with self._outcome_cv:
            self._outcome_cv.wait_for(lambda: self._outcome is not None, timeout=wait_s)
            result = self._outcome
        if result is None:
            return {"ok": True, "mode": str(self.modes.mode), "note": "still planning"}
        return result

    def audit(self, user: str, action: str, result: str) -> dict[str, Any]:
        """One entry of a front end's audit trail (the OPC UA server's method calls):
        logged and put into the run record as an ``audit`` event."""
        log.info("audit", user=user, action=action, result=result)
        if self.record is not None:
            self.record.event(self._now, "audit", user=user, action=action, result=result)
        return {}

    def snapshot(self) -> dict[str, Any]:
        """The last cycle's status (safe to call from any thread).

        Built here from what :meth:`step` published (one reference, replaced whole each
        cycle), so the loop does not pay for the status dict and the achieved attitude.
        """
        pub = self._published
        if pub is None:
            return {"mode": str(Mode.STOPPED)}
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
        inp = self._inputs  # the same or the next cycle's reading (one reference)
        if inp is not None:
            p, ok = inp.pressures.value, inp.positions.valid
            snap["pressures_pa"] = {
                cid: [float(v) if math.isfinite(v) else None for v in p[i].tolist()]
                for i, cid in self._active_ids
            }
            snap["positions_valid"] = {cid: bool(ok[i]) for i, cid in self._active_ids}
        walk = self.walk_status()
        if walk is not None:
            snap["walk"] = walk
        place = self.place_status()
        if place is not None:
            snap["place"] = place
        release = self.release_status()
        if release is not None:
            snap["release"] = release
        if self.ring_cycle is not None:
            snap["cycle"] = self.ring_cycle.status()
        elif self.cycle is not None:
            snap["cycle"] = dict(self.cycle)
        return snap

    # ------------------------------------------------------------------ the step

    def step(self, cycle: int, now: float) -> None:
        """One cycle: read the machine, update the modes and controllers, write."""
        self._now = now
        self.cycles += 1
        # the limit switches only where the stroke-end check may run this cycle (the
        # valve modes, and SUSPENDED, which may resume before the checks)
        inp = self.reader.read(now, self.modes.mode in _LIMIT_MODES)
        self._inputs = inp
        u, ref = self.update(inp)
        write(self.link, MachineOutputs(self.control_words(), u, now))
        self._publish(now, inp.positions.value, u, inp.link_state, ref)

    def control_words(self) -> tuple[ControlWord, ...]:
        """The cycle's control words after :meth:`update`: the handshake's edits, then
        the PLC mode and enable, the PackML state and unit mode."""
        enabled = self.modes.valves_enabled
        plc = PlcMode.WALK if self.walker is not None else PlcMode.ATTITUDE_ADJUST
        return self.handshake.finish(
            plc if enabled else PlcMode.IDLE,
            enabled,
            _MODE_CODES[self.modes.mode],
            UNIT_MODES[self.modes.unit_mode],
        )

    def update(self, inp: MachineInputs) -> tuple[np.ndarray, np.ndarray | None]:
        """The cycle's decisions from its inputs: interlocks, modes, planner hand-off,
        the controllers. Returns the spool commands and this cycle's references (None
        when the valves are closed); the control-word edits go to :attr:`handshake`."""
        now = inp.t
        x = inp.positions.value
        valid = inp.positions_valid
        status = inp.status
        self.handshake.begin()

        # E-stop first: it needs nothing else to be valid.
        if status is not None:
            self.modes.estop(status.estop)

        present = present_causes(inp, self.limits)
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
            # every input fresh, and the PLC hearing our commands
            if not present and not losses:
                self.modes.boot_complete()
            elif late:
                for cause in present:  # not complete within the start-up time
                    self.modes.fault(cause)
        else:
            for cause in present:  # latched by (interlock, where): repeats only counted
                self.modes.fault(cause)

        self._reset_step(now, present)
        self._ride_through(now, losses, inp)
        walker = self.walker
        if self.modes.valves_enabled and valid:
            metrics = self.attitude.metrics if walker is None else {}
            for cause in motion_causes(inp, metrics, self.limits):
                self.modes.fault(cause)

        hmi = inp.hmi
        if hmi is not None:
            if hmi.request == TargetRequest.NEW_TARGET:
                out = self.request_adjust(
                    units.to_deg(hmi.roll_rad), units.to_deg(hmi.pitch_rad), hmi_seq=hmi.seq
                )
                if not out.get("ok"):  # refused: its own seq; the running one's is kept
                    self.handshake.ack(TargetAck.REJECTED, hmi.seq)
            elif hmi.request == TargetRequest.CANCEL:
                self.modes.stop("HMI cancel")
                self.handshake.ack(TargetAck.NONE, hmi.seq)
            elif hmi.request == TargetRequest.WALK:
                self._hmi_walk(hmi, now)

        self._run_calls(inp)
        self._planning(x, valid, now)

        walker = self.walker
        if walker is not None and self.modes.mode in (Mode.IDLE, Mode.STARTING):
            self._end_walk()  # stopped, or an adjustment from the walk's end state
            walker = None
        if walker is not None:
            return self._walk_update(inp, walker)
        placer = self.placer
        if placer is not None and self.modes.mode in (Mode.IDLE, Mode.STARTING):
            self._end_place(now)  # stopped, or a new motion from the placed pose
            placer = None
        if placer is not None:
            return self._place_update(inp, placer)
        releaser = self.releaser
        if releaser is not None and self.modes.mode in (Mode.IDLE, Mode.STARTING):
            self._end_release(now)  # stopped, or a new motion from the released pose
            releaser = None
        if releaser is not None:
            return self._release_update(inp, releaser)
        if self.modes.mode == Mode.EXECUTE and self.attitude.motion_done(now):
            self.modes.motion_done()
            self.handshake.ack(TargetAck.COMPLETED)
            self.attitude.hold(self.attitude.final_references())
            self.motion.duration_s = now - self.motion.started_s
        u = np.zeros(len(self.cfg.cylinders))
        ref: np.ndarray | None = None
        if self.modes.valves_enabled and valid:
            u = self.attitude.update(now, x)
            ref = self.attitude.last_references  # this cycle's, for the run record
            self._last_drive_t = now
            self._motion_figures(now)
        return u, ref

    def _walk_update(
        self, inp: MachineInputs, walker: WalkSequencer
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """A walk's cycle: the sequencer drives, the walk interlocks judge its figures."""
        now = inp.t
        u = np.zeros(len(self.cfg.cylinders))
        if not (self.modes.valves_enabled and inp.positions_valid):
            return u, None
        # each reading that is not valid this cycle (a slow group's frame late or lost)
        # stands at its last valid value, and a cylinder outside the active group whose
        # position is not valid is not driven (its valve closed) until one comes again
        pos, press = inp.positions, inp.pressures
        last = self._walk_driven
        if last is None:
            last = (np.nan_to_num(pos.value, nan=0.0), np.nan_to_num(press.value, nan=0.0))
        x = np.where(pos.valid, pos.value, last[0])
        p = np.where(press.valid, press.value, last[1])
        was_done = walker.done
        band_was = walker.figures.out_of_band
        u = walker.update(now, x, p, set(self.limits.active), press.age_s)
        u[~pos.valid] = 0.0  # the active group's are valid here (else suspended)
        self._walk_driven = (x, p)
        band = walker.figures.out_of_band
        if band != band_was and self.record is not None:  # the sync band: hold, go on
            fig = walker.figures
            self.record.event(
                now,
                "walk_sync_hold" if band else "walk_sync_continue",
                group=band or band_was,
                step=fig.step,
                phase=fig.phase,
                sync_mm=units.to_mm(max(fig.leg_sync_m, fig.travel_sync_m)),
            )
        self._last_drive_t = now
        if self.modes.mode == Mode.EXECUTE and not was_done:
            assert self.walk_limits is not None
            for cause in walk_causes(walker.figures, walker.leg_ids, self.walk_limits):
                self.modes.fault(cause)
            if walker.done:
                self.modes.motion_done()
                self.handshake.ack(TargetAck.COMPLETED)
                self.motion.duration_s = now - self.motion.started_s
                if self.record is not None:
                    self.record.event(now, "walk_done", steps=[s.to_dict() for s in walker.steps])
            else:
                self._walk_group(now)
        if not self.modes.valves_enabled:
            return np.zeros(len(self.cfg.cylinders)), None
        return u, walker.last_refs

    # ------------------------------------------------------------------ ride-through

    def _ride_through(self, now: float, losses: list[str], inp: MachineInputs) -> None:
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
        if self.walker is not None:
            # walking.md's resume check on the rods (heights, the travel pair's coast); not
            # on the legs' forces: in a stop of at most safety.max_suspend_ms what moves
            # them is the interrupted motion settling as the valves close (up to 20 kN in
            # the walk campaign), and the overload and transfer checks judge them again
            # from the first cycle it goes on. A hold's unhold checks them too (its stop
            # may last long enough for a leg to sink or a foot to give way).
            w = self.walker
            press_needed = w.legs + list(self.limits.active)
            if not (
                inp.positions.all_valid(w.walk_cylinders) and inp.pressures.all_valid(press_needed)
            ):
                return  # a slow group's frame yet to come (the suspend timeout bounds this)
            cause = self._walk_resume_cause(inp, forces=False)
        else:
            stop_ref = self._stop_ref.tolist() if self._stop_ref is not None else None
            cause = resume_cause(inp, stop_ref, self.limits)
        if cause is not None:
            self.modes.fault(cause)
        else:
            self._resume(now, inp.positions.value)

    def _suspend(self, now: float, losses: list[str], mode: Mode) -> None:
        reason = "; ".join(losses)
        self._stopped_here(now)
        self._fresh_cycles = 0
        if not self.modes.suspend(reason).accepted:
            return
        self.suspends += 1
        log.warning("suspended", reason=reason, from_mode=str(mode), suspends=self.suspends)
        if self.record is not None:
            self.record.event(now, "suspended", reason=reason, from_mode=str(mode))

    def _stopped_here(self, now: float) -> None:
        """A motion stops (suspended or held): where the references were, and when; in a
        walk, where the rods stood and the legs' forces in its last driven cycle (the
        walk's resume check compares with them)."""
        if self.walker is not None:
            driven = self._walk_driven
            if driven is None and self._inputs is not None:  # stopped before its first
                driven = (self._inputs.positions.value, self._inputs.pressures.value)
            if driven is not None:
                self._walk_stop = (driven[0].copy(), self.walker.forces_n(driven[1]))
        ref = self.attitude.last_references if self.walker is None else self.walker.last_refs
        if self.placer is not None and self.placer.last_refs is not None:
            ref = self.placer.last_refs
        self._stop_ref = (ref if ref is not None else self.attitude.references(now)).copy()
        self._suspended_at = now

    def _go_on(
        self, now: float, x: np.ndarray, event: Callable[[str], Outcome], reason: str
    ) -> float:
        """The stopped motion goes on (resume, unhold): the trajectory shifted by the time
        stopped, the controllers reset at ``x``. Returns the shift."""
        last = self._last_drive_t if self._last_drive_t is not None else self._suspended_at
        shift = max(0.0, now - last - self.period_s)  # the next reference follows the last
        if self.walker is not None and self._inputs is not None:
            # the walk's phase clock stood still while stopped: its controllers restart
            self.walker.resume(np.nan_to_num(x), np.nan_to_num(self._inputs.pressures.value))
        self.attitude.resume(x, shift)
        if self.placer is not None:
            self.placer.resume(np.nan_to_num(x), shift)
        if self.releaser is not None:
            self.releaser.resume(shift)
        self.motion.started_s += shift
        event(reason)
        return shift

    def _resume(self, now: float, x: np.ndarray) -> None:
        suspended_s = now - self._suspended_at
        shift = self._go_on(
            now,
            x,
            self.modes.resume,
            f"frames fresh for {self.RESUME_FRESH_CYCLES} cycles, rods within the sync band "
            f"after {units.to_ms(suspended_s):.0f} ms",
        )
        self.resumes += 1
        log.warning("resumed", suspended_s=suspended_s, shift_s=shift, resumes=self.resumes)
        if self.record is not None:
            self.record.event(now, "resumed", suspended_s=suspended_s, shift_s=shift)

    def _planning(self, x: np.ndarray, valid: bool, now: float) -> None:
        mode = self.modes.mode
        if mode == Mode.STARTING and not self._submitted and valid:
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
        if self.modes.mode != Mode.STARTING:
            return  # stopped or faulted meanwhile: the plan is dropped
        self.handshake.ack(TargetAck.ACCEPTED if res.ok and res.feasible else TargetAck.REJECTED)
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
            verdict = {"ok": True, "mode": str(Mode.EXECUTE), "duration_s": res.duration_s}
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
        if self.modes.mode == Mode.EXECUTE:
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
        if self.modes.mode is not self._seen_mode:
            self._seen_mode = self.modes.mode
            self.state_changes.changed()
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
