"""The walk (``wara ctl walk``, the HMI's WALK request, the ring cycle's walks): a
:class:`~ipc_app.control.walk.WalkSequencer` run by the service (walking.md; docs/walking.md).

Prepared in the requesting thread: the plan from the measured state (:func:`walk_start`:
S's position, the layers' extensions, the load M's standing legs measure), in the
planner process, refused with the phase, instant and limit before anything moves; the
sequencer built (its 27 controllers and the machine's statics). In the loop each phase
claims its active group (walking.md section 6: the legs and travel rods that move at
the loop rate, the PLC in WALK), the walk's interlocks
(:mod:`ipc_app.service.walk_interlocks`) judge its figures, and a stop keeps the rods
and the legs' forces of its last driven cycle for the walk's resume check.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import structlog

from config import units
from config.schema import CANNOT_WALK
from ipc_app.control.walk import WalkSequencer
from ipc_app.model.support import WalkingMachine, cap_side_forces_n, standing_load
from ipc_app.planner.steering import on_axis_at_start, walked
from ipc_app.planner.walk import DIRECTIONS, WalkPlan, WalkStart
from ipc_app.service.interlocks import Cause, Limits
from ipc_app.service.machine_io import MachineInputs
from ipc_app.service.modes import Mode
from ipc_app.service.motion import (
    WAIT,
    Claim,
    Command,
    Effects,
    Event,
    Motion,
    Service,
    Wait,
    event,
)
from ipc_app.service.requests import Code, Reply, plc_walk_refusal, walk_refusal
from ipc_app.service.walk_interlocks import WalkLimits, walk_causes, walk_resume_cause
from ipc_app.service.worker import PLAN_WALK_FN, PlannerCallError
from plc_bridge.link import Mode as PlcMode

log = structlog.get_logger("wara.service")


def walk_start(svc: Service) -> WalkStart | str:
    """The measured state a walk would start from now (``x_S``, the layers' extensions,
    the load M's standing legs measure), or why there is none yet (a refusal's text: a
    position or a standing leg's pressure not valid)."""
    inp = svc.inputs
    if inp is None or not inp.positions_valid:
        return "walk refused: no valid positions"
    x = inp.positions.value
    cfg = svc.cfg
    by_index = cfg.cylinders_by_can_index
    travel = [c.can_index for c in by_index if c.role == "travel"]
    e0 = by_index[travel[0]].stroke_m / 2
    x_s = float(np.mean(x[travel])) - e0
    half = np.array([c.stroke_m / 2 for c in by_index])
    lo, up = svc.attitude.layers["lower"], svc.attitude.layers["upper"]
    if not (np.all(np.isfinite(x[travel])) and np.all(np.isfinite(x[up]))):
        return "walk refused: no valid positions"
    press = inp.pressures
    if not press.all_valid(lo):
        return "walk refused: the standing legs' pressures not valid (yet)"
    legs = [by_index[i] for i in lo]
    cap = np.array([c.cap_area_m2 for c in legs])
    rod = np.array([c.rod_area_m2 for c in legs])
    forces = cap_side_forces_n(press.value[lo], cap, rod)
    try:  # M stands: its legs measure the machine's weight and COG
        standing = standing_load(WalkingMachine(cfg).main_legs_xy, forces, x_s)
    except ValueError as exc:
        return f"walk refused: {exc}"
    return WalkStart(
        x_s_m=x_s,
        main_extensions_m=tuple((x[lo] - half[lo]).tolist()),
        upper_extensions_m=tuple((x[up] - half[up]).tolist()),
        standing=standing,
        on_axis=svc.on_axis,
    )


def plan_walk_here(
    svc: Service, steps: int, direction: str = "forward", unloaded: bool = False
) -> WalkPlan | Reply:
    """Plan ``steps`` steps from the last measured state, in the planner process (the
    caller's thread waits; never the loop's); a refusal when the service cannot walk."""
    if not svc.cfg.walks:
        msg = CANNOT_WALK
        return Reply.bad_request(msg)
    start = walk_start(svc)
    if isinstance(start, str):
        return Reply.refused(start)
    try:
        plan: WalkPlan = svc.planner.call(
            PLAN_WALK_FN, steps, start, direction=direction, unloaded=unloaded
        )
    except PlannerCallError as exc:  # ValueError: unloaded without a workpiece body
        code = Code.BAD_REQUEST if exc.raised == "ValueError" else Code.PLANNER
        return Reply.refused(f"walk refused: {exc}", code)
    return plan


class WalkMotion(Motion):
    """One walk of :attr:`plan`; see the module docstring."""

    name = "walk"
    answers_hmi = True
    unhold_reason = "operator unhold: the walk's resume check passed"
    resume_refused_event = "walk_resume_refused"

    def __init__(self, svc: Service, plan: WalkPlan) -> None:
        self.cfg = svc.cfg
        self.svc = svc
        self._walked_done = False
        self.attitude = svc.attitude
        self.walk_plan = plan
        self.sequencer = self.walker = WalkSequencer(svc.cfg, svc.period_s, plan)
        self.limits = WalkLimits.from_config(svc.cfg)
        self._claim: Claim | None = None
        self._phase = -1
        #: the rods and pressures of its last driven cycle, each at its last valid value
        #: (the stop state; what a reading not valid this cycle stands at)
        self._driven: tuple[np.ndarray, np.ndarray] | None = None
        #: where the rods stood and the legs' forces when it stopped
        self._stop: tuple[np.ndarray, np.ndarray] | None = None

    @classmethod
    def prepare(cls, svc: Service, *args: Any) -> Motion | Reply:
        steps, direction, unloaded = args
        bad = walk_refusal(steps, DIRECTIONS, direction)
        if bad is None:
            bad = plc_walk_refusal(svc.inputs.status if svc.inputs is not None else None)
        if bad is not None:
            return bad
        plan = plan_walk_here(svc, steps, direction, unloaded)
        if isinstance(plan, Reply):
            return plan
        if not plan.feasible:
            ref = plan.refusal
            assert ref is not None
            if svc.record is not None:
                svc.record.event(svc.now_s, "walk_refused", refusal=ref.to_dict())
            msg = f"walk refused: {ref.message}"
            return Reply.refused(msg, Code.INFEASIBLE, refusal=ref.to_dict())
        return cls(svc, plan)

    def describe(self) -> str:
        p = self.walk_plan
        load = ", unloaded" if p.unloaded else ""
        return f"{p.steps} step(s) {p.direction} of {p.step_length_m:.3f} m{load}"

    def accepted(self) -> dict[str, Any]:
        return {"duration_s": self.walk_plan.duration_s}

    def claim(self) -> Claim | None:
        return self._claim

    def _phase_claim(self) -> Claim | None:
        """The present phase's group, when the phase changed since the last claim."""
        w = self.walker
        assert w.run is not None
        if w.run.index == self._phase:
            return None
        self._phase = w.run.index
        group = tuple(w.active_group())
        ph = w.run.phase
        ev = event(
            "walk_phase", step=ph.step, phase=ph.key, name=w.phase_name(), active=None,
            bus_load_percent=None, margin_ahead_m=w.figures.margin_ahead_m,
        )  # fmt: skip
        self._claim = Claim(group, group, PlcMode.WALK, ev)
        return self._claim

    def start(self, inp: MachineInputs) -> Effects:
        self.walker.start(inp.t, inp.positions.value, inp.pressures.value)
        p = self.walk_plan
        walk = event("walk", steps=p.steps, direction=p.direction, unloaded=p.unloaded)
        return (self._phase_claim(), walk)

    def update(self, inp: MachineInputs, mode: Mode) -> Command:
        w = self.walker
        assert self._claim is not None
        # each reading that is not valid this cycle (a slow group's frame late or lost)
        # stands at its last valid value, and a cylinder outside the active group whose
        # position is not valid is not driven (its valve closed) until one comes again
        pos, press = inp.positions, inp.pressures
        last = self._driven
        if last is None:
            last = (np.nan_to_num(pos.value, nan=0.0), np.nan_to_num(press.value, nan=0.0))
        x = np.where(pos.valid, pos.value, last[0])
        p = np.where(press.valid, press.value, last[1])
        was_done = w.done
        band_was = w.figures.out_of_band
        u = w.update(inp.t, x, p, set(self._claim.watched), press.age_s)
        u[~pos.valid] = 0.0  # the active group's are valid here (else suspended)
        self._driven = (x, p)
        events: list[Event] = []
        fig = w.figures
        if fig.out_of_band != band_was:  # the sync band: hold, go on
            events.append(
                event(
                    "walk_sync_hold" if fig.out_of_band else "walk_sync_continue",
                    group=fig.out_of_band or band_was,
                    step=fig.step,
                    phase=fig.phase,
                    sync_mm=units.to_mm(max(fig.leg_sync_m, fig.travel_sync_m)),
                )
            )
        if mode != Mode.EXECUTE or was_done:
            return Command(u, w.last_refs, events=events)
        causes = walk_causes(fig, w.leg_ids, self.limits)
        if w.done:
            return Command(u, w.last_refs, True, causes, events)
        return Command(u, w.last_refs, False, causes, events, self._phase_claim())

    def completed(self, now: float) -> Event | None:
        self._walked()
        return event("walk_done", steps=[s.to_dict() for s in self.walker.steps])

    @property
    def on_axis_pending(self) -> bool:
        """Its end has yet to set where the machine stands (:meth:`_walked`): a survey
        given meanwhile would be overwritten (``wara ctl locate`` is refused)."""
        return not self._walked_done

    def _walked(self) -> None:
        """Where the machine now stands against the axis, from the turns its finished
        steps measured (:func:`~ipc_app.planner.steering.walked`; a step stopped
        part-way is not counted): once, as the walk completes (the next walk is planned
        from it while this one still holds) or else as it ends."""
        if self._walked_done:
            return
        self._walked_done = True
        p = self.walk_plan
        done = [s for s in self.walker.steps if s.duration_s > 0]
        made = [s.turn_rad for s in done if s.turn_rad is not None]
        if made:
            start = self.svc.on_axis or on_axis_at_start(self.cfg)
            self.svc.on_axis = walked(self.cfg, start, p.turns, made, p.direction == "back")

    def stop_point(self, now: float, inp: MachineInputs | None) -> np.ndarray:
        driven = self._driven
        if driven is None and inp is not None:  # stopped before its first cycle
            driven = (inp.positions.value, inp.pressures.value)
        if driven is not None:
            self._stop = (driven[0].copy(), self.walker.forces_n(driven[1]))
        return self.walker.last_refs

    def resume_check(
        self, inp: MachineInputs, stop_ref: np.ndarray | None, limits: Limits, held: bool
    ) -> Cause | Wait | None:
        """walking.md's resume check: the rods (heights, the travel pair's coast) and,
        after an operator's hold, the legs' forces. Not the forces after a suspension:
        in a stop of at most ``safety.max_suspend_ms`` what moves them is the interrupted
        motion settling as the valves close (up to 20 kN in the walk campaign), and the
        overload and transfer checks judge them again from the first cycle it goes on;
        a hold may last long enough for a leg to sink or a foot to give way."""
        w = self.walker
        if not held:
            press_needed = w.legs + list(limits.active)
            if not (
                inp.positions.all_valid(w.walk_cylinders) and inp.pressures.all_valid(press_needed)
            ):
                return WAIT  # a slow group's frame yet to come
        if self._stop is None:
            return None
        x_stop, f_stop = self._stop
        share = w.figures.expected_n or tuple([1.0] * 8)
        return walk_resume_cause(
            inp.positions.value.tolist(), x_stop.tolist(), w.legs + w.upper, w.travel,
            limits.ids, w.forces_n(inp.pressures.value).tolist(), f_stop.tolist(), share,
            w.leg_ids if held else (), self.limits,
        )  # fmt: skip

    def resume(self, inp: MachineInputs, shift_s: float, held: bool) -> None:
        """The phase clock stood still while stopped: its controllers restart at the
        rods. After a suspension the attitude layers' controllers restart at the rods
        too, as for every motion (a release goes on from their state)."""
        x = inp.positions.value
        self.walker.resume(np.nan_to_num(x), np.nan_to_num(inp.pressures.value))
        if not held:
            self.attitude.resume(x, shift_s)

    def end(self, now: float, mode: Mode, successor: Motion | None) -> Effects:
        """Back to the attitude group, unless a walk follows (its first phase claims
        its own group). A walk stopped part-way: where it stands (:meth:`_walked`)."""
        self._walked()
        return () if isinstance(successor, WalkMotion) else (None,)

    def status(self) -> dict[str, Any] | None:
        w = self.walker
        if w.run is None:
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

    def figures(self) -> dict[str, Any]:
        return {"steps": [st.to_dict() for st in self.walker.steps]}
