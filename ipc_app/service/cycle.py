"""The ring cycle as a request of the service (placement.md section 4; docs/placement.md).

One ring's phases, in order: ``load`` (waits until the part is on the platform at the
loading point: every upper cylinder's load pressure at its value of the statics with the
part, within ``cycle.platform_pressure_tolerance_mpa``, for :data:`LOAD_SETTLED_S`),
``walk`` (the target planned from the previous part's as-built pose first, so that an
unreachable one moves nothing; then ``walk_steps`` steps to the ring), ``place`` (to
that target), ``fixing`` (the pose held until an operator confirms the
part is fixed: :meth:`RingCycle.confirm_fixed`, audited), ``release`` (the upper
platform lowers off the fixed part until its pressures are the empty platform's, then
clear of it: :meth:`ServiceCore.request_release`; then a controlled stop, valves
closed), ``survey`` (waits for the as-built pose: survey points to fit, or a pose from
the acceptance store), ``record`` (the ring's Table 4 figures from the surveyed poses,
handed to the :class:`RingRecords` sink that writes the acceptance record),
``walk_back`` (the same steps back; unloaded unless told).

The cycle drives the service through a small port (:class:`CyclePort`: ask for a motion
and get its :class:`~ipc_app.service.motion.Ticket`, the modes, the machine time, the
last inputs, the planner, where its phases and its end are noted); the service is one.
:meth:`RingCycle.tick` advances it. It is called outside the fixed-rate loop: by the
service's cycle thread (``wara ctl cycle``), or by the HIL driver between its simulated
periods (``wara cycle``). The planning (the placement's target, the walks) runs in that
caller, never in the loop; the loop only takes the requests, as for ``wara ctl walk`` and
``place``. A stop (``wara ctl stop``), a latched fault, a refused request, a motion
that does not end in COMPLETE or not within ``cycle.max_motion_min`` ends the cycle in
the phase it was in, with the valves closed (:attr:`RingCycle.error`,
:attr:`RingCycle.stopped_in_phase`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import structlog

from config import units
from config.schema import Cycle, ProjectConfig
from ipc_app.control.release import (
    load_pressures_pa,
    platform_pressures_pa,
    upper_cap_areas_m2,
    upper_index,
)
from ipc_app.model.placement import Pose, design_pose, joint_figures, to_ring_frame
from ipc_app.planner.placement import PlacementPlan
from ipc_app.planner.survey import (
    SurveyError,
    SurveyFit,
    SurveyPoint,
    as_built_problems,
    fit_survey,
)
from ipc_app.service.machine_io import MachineInputs
from ipc_app.service.modes import Mode, ModeMachine
from ipc_app.service.motion import Motion, Planner, Ticket
from ipc_app.service.motions.place import PlaceMotion
from ipc_app.service.motions.release import ReleaseMotion
from ipc_app.service.motions.walk import WalkMotion
from ipc_app.service.requests import Code, Reply, cycle_refusal, plc_walk_refusal
from ipc_app.service.worker import PLAN_TARGET_FN, PlannerCallError

log = structlog.get_logger("wara.service")

#: The phases of one ring, in order.
PHASES: tuple[str, ...] = (
    "load", "walk", "place", "fixing", "release", "survey", "record", "walk_back",
)  # fmt: skip
#: The part counts as loaded once the pressures have matched its statics this long, s.
LOAD_SETTLED_S = 1.0
#: The Table 4 items of a ring's acceptance record (acceptance keys).
RECORD_KEYS: tuple[str, ...] = (
    "vertical_misalignment_mm",
    "horizontal_misalignment_mm",
    "max_gap_mm",
    "centreline_deviation_x_mm",
    "centreline_deviation_y_mm",
    "pitch_angle_deg",
    "tilt_angle_deg",
    "rotation_angle_deg",
)


#: ``cycle.max_motion_min``'s default, s: the bound of a ring cycle's motion for a caller
#: without the project at hand (the service takes the project's, ``cfg.cycle.max_motion_s``)
MOTION_LIMIT_S = 60.0 * Cycle.model_fields["max_motion_min"].default
#: The allowance of a HIL driver for the loop to take a motion asked for, s (the service
#: itself needs none: the motion's ticket is answered in the loop's next cycle)
START_LIMIT_S = 5.0


def previous_from_deviation(cfg: ProjectConfig, ring: int, dev: Pose) -> Pose:
    """The part before ring ``ring`` (ring - 1) as built, in its own T, from its
    deviation from its design (a survey sheet's figures, positions and angles added)."""
    return design_pose(cfg, ring - 1).deviated(dev)


class RingRecords(Protocol):
    """Where the cycle's acceptance records go (the acceptance store, kept outside the
    service's package: ``wara serve`` and ``wara cycle`` hand one in)."""

    def write(self, ring: int, values: dict[str, float | None], attached: dict[str, Any]) -> str:
        """Write ring ``ring``'s record (Table 4 ``values``) with ``attached`` (the plan,
        the cycle's figures, ``as_built_pose``); a short note of where it went."""
        ...


class CyclePort(Protocol):
    """What the ring cycle needs of the service (:class:`~ipc_app.service.core.ServiceCore`
    is one)."""

    cfg: ProjectConfig
    planner: Planner
    modes: ModeMachine

    @property
    def now_s(self) -> float: ...
    @property
    def inputs(self) -> MachineInputs | None: ...

    def request_motion(
        self, kind: type[Motion], args: tuple[Any, ...] = (), *, hmi_seq: int | None = None
    ) -> Ticket:
        """``kind``'s motion prepared and handed to the loop."""
        ...

    def audit(self, user: str, action: str, result: str) -> dict[str, Any]: ...
    def event(self, kind: str, **fields: Any) -> None:
        """A run-record event at the machine time."""
        ...


class CycleError(Exception):
    """A phase failed: the cycle ends in it (the machine holds, valves closed)."""

    def __init__(self, msg: str, refused: bool = False) -> None:
        super().__init__(msg)
        #: refused before anything moved (an infeasible target or move)
        self.refused = refused


@dataclass
class RingCycle:
    """One ring's cycle on the service ``core`` (its :class:`CyclePort`); see the module
    docstring."""

    core: CyclePort
    ring: int
    #: the previous part's as-built pose in its own ring's T (ring - 1)
    previous: Pose
    records: RingRecords
    walk_steps: int = 0
    walk_back_unloaded: bool = True
    say: Callable[[str], None] = field(default=lambda _s: None)
    phase: str = ""
    done: bool = False
    refused: bool = False
    error: str | None = None
    stopped_in_phase: str | None = None
    phase_times_s: dict[str, float] = field(default_factory=dict)
    plan: PlacementPlan | None = None
    fit: SurveyFit | None = None
    surveyed: Pose | None = None
    record_note: str = ""
    fixed_by: str = ""
    #: the recorded Table 4 figures (from the surveyed poses)
    table4: dict[str, float | None] = field(default_factory=dict)
    #: what the phase waits for now ("" while it runs by itself)
    waiting_for: str = ""
    #: the release's figures (travel, load pressures before and after, the empty ones)
    release_figures: dict[str, Any] = field(default_factory=dict)
    #: each walk's steps' figures (``walk``, ``walk_back``: StepFigures.to_dict() per step)
    walk_figures: dict[str, list[dict[str, Any]]] = field(default_factory=dict)
    _loaded_since: float | None = None
    _since: float = 0.0
    _issued_at: float | None = None
    #: the phase's motion, as the service took it
    _ticket: Ticket | None = None
    _started: bool = False
    #: the cycle thread's ticks and the operator's requests take turns
    _lock: threading.RLock = field(default_factory=threading.RLock)
    _stop_reason: str | None = None

    @classmethod
    def request(
        cls,
        core: CyclePort,
        ring: int,
        previous: Pose,
        records: RingRecords,
        walk_steps: int | None = None,
        walk_back_unloaded: bool = True,
        say: Callable[[str], None] | None = None,
    ) -> RingCycle | Reply:
        """Ring ``ring``'s cycle, checked (``walk_steps`` default ``cycle.walk_steps``)
        and noted in the run record; or why not. The caller starts it."""
        cfg = core.cfg
        if cfg.placement is None or cfg.cycle is None:
            msg = "the project has no placement and cycle sections: it cannot run a cycle"
            return Reply.bad_request(msg)
        steps = cfg.cycle.walk_steps if walk_steps is None else walk_steps
        bad = cycle_refusal(ring, steps)
        if bad is not None:
            return bad
        if core.modes.mode not in (Mode.IDLE, Mode.COMPLETE):
            why = f"cycle refused: the service is {core.modes.mode} (IDLE or COMPLETE needed)"
            return Reply.refused(why)
        if steps > 0:  # it walks: the PLC must be able to
            inp = core.inputs
            bad = plc_walk_refusal(inp.status if inp is not None else None)
            if bad is not None:
                return bad
        core.event(
            "cycle", ring=ring, previous=previous.to_dict(), walk_steps=steps,
            walk_back_unloaded=walk_back_unloaded,
        )  # fmt: skip
        return cls(
            core, ring, previous, records, walk_steps=steps,
            walk_back_unloaded=walk_back_unloaded, say=say or (lambda _s: None),
        )  # fmt: skip

    @property
    def cfg(self) -> ProjectConfig:
        return self.core.cfg

    @property
    def active(self) -> bool:
        return not self.done and self.error is None

    def status(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "ring": self.ring,
            "phase": self.phase,
            "since_s": round(self._since, 3),
            "waiting_for": self.waiting_for,
            "done": self.done,
            "error": self.error,
            "phase_times_s": {k: round(v, 3) for k, v in self.phase_times_s.items()},
        }
        if self.plan is not None:
            out["target_deviation"] = self.plan.to_dict()["target_deviation"]
        return out

    # ----------------------------------------------------------------- phases

    def _enter(self, phase: str, waiting_for: str = "", **figures: Any) -> None:
        now = self.core.now_s
        if self.phase:
            self.phase_times_s[self.phase] = now - self._since
        self.phase, self._since, self.waiting_for = phase, now, waiting_for
        self._issued_at, self._ticket, self._started = None, None, False
        log.info("cycle phase", ring=self.ring, phase=phase, waiting_for=waiting_for, **figures)
        self.core.event(
            "cycle_phase", ring=self.ring, phase=phase, waiting_for=waiting_for, **figures
        )
        self.say(f"ring {self.ring}: {phase}")

    def fail(self, msg: str, *, refused: bool = False) -> None:
        """The cycle ends in its phase with ``msg`` (the service stops the machine)."""
        self.error, self.refused = msg, refused
        self.stopped_in_phase = self.phase
        self.phase_times_s[self.phase] = self.core.now_s - self._since
        self._end(msg)

    def _end(self, error: str | None) -> None:
        """The cycle ended (``error`` None: done): the run record and the log; a failed
        cycle leaves the machine stopped (valves closed)."""
        modes = self.core.modes
        if error is not None and modes.mode in (
            Mode.STARTING, Mode.EXECUTE, Mode.COMPLETE, Mode.HELD, Mode.SUSPENDED,
        ):  # fmt: skip
            modes.stop(f"ring {self.ring}'s cycle ended in {self.phase}: {error}")
        log.info("cycle end", ring=self.ring, phase=self.phase, error=error)
        self.core.event(
            "cycle_end", ring=self.ring, phase=self.phase, error=error,
            phase_times_s=self.phase_times_s, table4=self.table4,
        )  # fmt: skip

    def drive(self, tick_s: float) -> None:
        """Tick until the cycle ends, a tick every ``tick_s`` (the service's cycle
        thread, never the loop); a tick that raises (a bug) ends the cycle."""
        while self.active:
            try:
                self.tick()
            except Exception as exc:  # a bug: the cycle ends, the machine stops
                log.exception("cycle_failed", ring=self.ring, phase=self.phase)
                self.fail(f"internal: {type(exc).__name__}: {exc}")
                return
            time.sleep(tick_s)

    def start(self) -> None:
        self._enter("load", waiting_for="a part on the platform (the upper cylinders' pressures)")

    def stop(self, reason: str) -> None:
        """An operator's stop (the machine already stopped by the caller). It never
        waits for a tick that is planning: the cycle ends at once or at its next tick."""
        self._stop_reason = reason
        if self._lock.acquire(blocking=False):
            try:
                if self.active:
                    self.fail(f"stopped: {reason}")
            finally:
                self._lock.release()

    def tick(self) -> None:
        """Advance the cycle as far as it goes now (outside the loop)."""
        with self._lock:
            self._tick_locked()

    def _tick_locked(self) -> None:
        if not self.active:
            return
        if self._stop_reason is not None:
            self.fail(f"stopped: {self._stop_reason}")
            return
        try:
            for _ in PHASES:  # on through the phases that end at once (bounded)
                before = self.phase
                self._tick()
                if self.phase == before or not self.active:
                    break
        except CycleError as exc:
            self.fail(str(exc), refused=exc.refused)

    def _tick(self) -> None:
        core, mode = self.core, self.core.modes.mode
        if mode in (Mode.ABORTED, Mode.STOPPED):
            raise CycleError(f"the service is {mode}: {'; '.join(core.modes.fault_reasons)}")
        ph = self.phase
        if ph == "load":
            if self._part_on():
                self._enter("walk", steps=self.walk_steps)
        elif ph == "walk":
            if self.plan is None:  # the target first: an unreachable one moves nothing
                self._plan_target()
            if self.walk_steps == 0 or self._motion("walk", self._walk_forward):
                self._note_walk("walk")
                self._enter("place")
        elif ph == "place":
            if self._motion("place", self._place):
                self._enter("fixing", waiting_for="operator confirmation (wara ctl confirm-fixed)")
        elif ph == "fixing":
            # a short loss of the link (SUSPENDED) is ridden through as the service rides
            # it: the pose is held either way
            if mode not in (Mode.COMPLETE, Mode.SUSPENDED):
                raise CycleError(f"the hold for fixing ended in {mode}")
        elif ph == "release":
            if self._issued_at is None and mode == Mode.SUSPENDED:
                return  # the release starts once the link is back
            if self._motion("release", self._release):
                assert self._ticket is not None and self._ticket.motion is not None
                self.release_figures = self._ticket.motion.figures()
                core.modes.stop(f"ring {self.ring} released: the platform is clear of the part")
                self._enter(
                    "survey", waiting_for="a survey (wara ctl survey FILE.csv | --from-store)"
                )
        elif ph == "survey" and self.surveyed is not None:
            self._enter("record")
            self._record()
            self._enter("walk_back", steps=self.walk_steps, unloaded=self.walk_back_unloaded)
        elif ph == "walk_back" and (
            self.walk_steps == 0 or self._motion("walk back", self._walk_back)
        ):
            self._note_walk("walk_back")
            self.phase_times_s[ph] = core.now_s - self._since
            self.phase, self.waiting_for, self.done = "done", "", True
            self._end(None)

    def _note_walk(self, phase: str) -> None:
        """The figures of the walk that just ended (none when the cycle does not walk)."""
        t = self._ticket
        if self.walk_steps and t is not None and t.motion is not None:
            self.walk_figures[phase] = t.motion.figures()["steps"]

    def _motion(self, what: str, issue: Callable[[], Ticket]) -> bool:
        """Issue the phase's motion once; True when it ended in COMPLETE."""
        core = self.core
        if self._ticket is None:
            ticket = issue()
            self._refused(what, ticket)
            self._ticket, self._issued_at = ticket, core.now_s
            return False
        mode = core.modes.mode
        if not self._started:
            if self._ticket.taken:  # by the loop: started, or refused there
                self._refused(what, self._ticket)
                self._started = True
            return False
        if mode in (Mode.EXECUTE, Mode.HELD, Mode.SUSPENDED, Mode.STARTING):
            assert self._issued_at is not None and self.cfg.cycle is not None
            limit = self.cfg.cycle.max_motion_s  # cycle.max_motion_min
            if core.now_s - self._issued_at > limit:
                raise CycleError(f"{what} did not end within {limit:.0f} s")
            return False
        if mode != Mode.COMPLETE:
            why = "; ".join(core.modes.fault_reasons) or "stopped"
            raise CycleError(f"{what} ended in {mode}: {why}")
        return True

    @staticmethod
    def _refused(what: str, ticket: Ticket) -> None:
        reply = ticket.reply
        if reply is not None and not reply.ok:
            raise CycleError(f"{what} refused: {reply.error}", reply.code == Code.INFEASIBLE)

    def _part_on(self) -> bool:
        """The part is on the platform: the upper cylinders' load (their load pressures'
        mean, weighted by their cap areas: their summed force) within
        ``cycle.platform_pressure_tolerance_mpa`` of the statics' with the part, for
        :data:`LOAD_SETTLED_S` (the pressures valid).

        Their sum, not each one's: a part's centre of gravity as cast moves its weight
        between the four cylinders, not their sum (0.18 m along the platform and 0.1 m
        across moved up to 0.87 MPa between the shipped platform's cylinders, against the
        0.2 MPa tolerance: the cycle waited for that part for ever)."""
        cfg, core = self.cfg, self.core
        assert cfg.cycle is not None
        inp = core.inputs
        now = core.now_s
        ok = False
        if inp is not None and inp.positions_valid:
            up = upper_index(cfg)
            if bool(inp.pressures.valid[up].all()):
                want = platform_pressures_pa(cfg, inp.positions.value, unloaded=False)
                got = load_pressures_pa(cfg, inp.pressures.value)
                areas = upper_cap_areas_m2(cfg)
                excess_pa = float(np.dot(got - want, areas) / np.sum(areas))
                ok = abs(excess_pa) <= cfg.cycle.platform_pressure_tolerance_pa
        if not ok:
            self._loaded_since = None
            return False
        if self._loaded_since is None:
            self._loaded_since = now
        return now - self._loaded_since >= LOAD_SETTLED_S

    def _release(self) -> Ticket:
        return self.core.request_motion(ReleaseMotion, (self.ring,))

    def _walk_forward(self) -> Ticket:
        return self.core.request_motion(WalkMotion, (self.walk_steps, "forward", False))

    def _walk_back(self) -> Ticket:
        args = (self.walk_steps, "back", self.walk_back_unloaded)
        return self.core.request_motion(WalkMotion, args)

    def _plan_target(self) -> None:
        """The ring's target from the previous part's as-built pose, before the walk to
        the ring (an unreachable target ends the cycle before anything moves)."""
        cfg = self.cfg
        previous = to_ring_frame(cfg, self.previous, self.ring - 1, self.ring)
        try:  # in the planner process, as the core's own placement planning
            plan: PlacementPlan = self.core.planner.call(PLAN_TARGET_FN, previous, self.ring)
        except PlannerCallError as exc:
            raise CycleError(f"ring {self.ring}: {exc}") from exc
        self.plan = plan
        if not plan.feasible:
            raise CycleError(f"ring {self.ring}: " + "; ".join(plan.reasons), refused=True)

    def _place(self) -> Ticket:
        assert self.plan is not None
        return self.core.request_motion(PlaceMotion, (self.plan,))

    # ----------------------------------------------------------------- requests

    def _not_in(self, phase: str) -> str:
        """Why a request of ``phase`` is refused: the cycle has ended (in which phase, and
        why), or it is in another phase."""
        if self.error is not None:
            return f"ring {self.ring}'s cycle ended in {self.phase}: {self.error}"
        if self.done:
            return f"ring {self.ring}'s cycle is done"
        return f"the cycle is in {self.phase or 'no phase'}, not {phase}"

    def confirm_fixed(self, user: str) -> Reply:
        """The operator confirms the part is fixed: the cycle goes on to ``release`` (the
        platform lowered off the part), then waits for the survey."""
        with self._lock:
            return self._confirm_fixed(user)

    def _confirm_fixed(self, user: str) -> Reply:
        if self.phase != "fixing" or not self.active:
            return Reply.refused(f"confirm-fixed refused: {self._not_in('fixing')}")
        self.fixed_by = user
        self.core.audit(user, "confirm_fixed", f"ring {self.ring} fixed")
        self._enter("release")
        return Reply.accepted(ring=self.ring, phase=self.phase)

    def submit_survey(
        self, points: list[SurveyPoint] | None = None, pose: Pose | None = None
    ) -> Reply:
        """The as-built pose: ``points`` fitted as ``wara survey import`` fits a file, or
        ``pose`` (the acceptance store's, in the ring's own T). A refused fit leaves the
        cycle waiting in ``survey`` (another survey may follow)."""
        with self._lock:
            return self._submit_survey(points, pose)

    def _submit_survey(self, points: list[SurveyPoint] | None, pose: Pose | None) -> Reply:
        if self.phase != "survey" or not self.active:
            return Reply.refused(f"survey refused: {self._not_in('survey')}")
        if (points is None) == (pose is None):
            return Reply.bad_request("give survey points or a pose")
        if points is not None:
            try:
                fit = fit_survey(self.cfg, self.ring, points)
            except SurveyError as exc:
                msg = str(exc) if str(exc).startswith("survey") else f"survey: {exc}"
                return Reply.bad_request(msg)
            if not fit.accepted:
                return Reply.refused(f"survey refused: {'; '.join(fit.reasons)}")
            self.fit, self.surveyed = fit, fit.pose
            res = units.to_mm(fit.rms_residual_m)
            out = Reply.accepted(ring=self.ring, rms_residual_mm=res)
        else:
            assert pose is not None
            problems = as_built_problems(self.cfg, self.ring, pose)
            if problems:
                return Reply.refused(f"survey refused: {'; '.join(problems)}")
            self.surveyed = pose
            out = Reply.accepted(ring=self.ring, source="store")
        self.core.event(
            "cycle_survey", ring=self.ring, pose=self.surveyed.to_dict(),
            rms_residual_mm=out.fields.get("rms_residual_mm"),
        )  # fmt: skip
        return out

    def _record(self) -> None:
        assert self.surveyed is not None and self.plan is not None
        cfg = self.cfg
        prev = to_ring_frame(cfg, self.previous, self.ring - 1, self.ring)
        fig = joint_figures(cfg, prev, self.surveyed, self.plan.design).to_dict()
        values: dict[str, float | None] = {k: fig[k] for k in RECORD_KEYS}
        attached = {
            "kind": "ring_cycle",
            "plan": self.plan.to_dict(),
            "cycle": {
                "phase_times_s": dict(self.phase_times_s),
                "fixed_by": self.fixed_by,
                "release": dict(self.release_figures),
                "survey_rms_residual_mm": (
                    units.to_mm(self.fit.rms_residual_m) if self.fit is not None else None
                ),
            },
            "as_built_pose": self.surveyed.to_dict(),
        }
        try:
            self.record_note = self.records.write(self.ring, values, attached)
        except Exception as exc:  # the store's problem: the cycle ends here, machine idle
            raise CycleError(f"the ring's record was not written: {exc}") from None
        self.table4 = values
