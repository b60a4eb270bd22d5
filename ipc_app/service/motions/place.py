"""The placement move (``wara ctl place``, the ring cycle's ``place``): a
:class:`~ipc_app.control.placement.PlacementSequencer` run by the service
(placement.md section 5; docs/placement.md).

Prepared in the requesting thread: the target from the previous part's deviation
(:func:`plan_from_sheet`) or as the ring cycle planned it, refused when infeasible (the
binding limit named); the attitude trajectory planned in the planner process from the
measured state, the slide moves checked, before anything moves. In the loop the
attitude phase drives the layers, then the slide phase the yaw, lateral and gap axes
(each phase claims its group); the pose is held once both have settled.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from config import units
from ipc_app.control.placement import PlacementSequencer
from ipc_app.control.slide import SLIDE_ROLES
from ipc_app.model.placement import Pose
from ipc_app.planner.placement import PlacementPlan
from ipc_app.planner.plan import Plan
from ipc_app.service.interlocks import Metrics
from ipc_app.service.machine_io import MachineInputs
from ipc_app.service.modes import Mode
from ipc_app.service.motion import Claim, Command, Effects, Event, Motion, Service, event
from ipc_app.service.requests import Code, Reply, ring_refusal
from ipc_app.service.worker import PLAN_ATTITUDE_FN, PLAN_PLACE_FN, PlannerCallError
from plc_bridge.link import Mode as PlcMode


def plan_from_sheet(svc: Service, ring: int, previous_deviation: Pose) -> PlacementPlan | Reply:
    """Ring ``ring``'s target planned from the previous part's deviation from its design
    (:func:`~ipc_app.planner.placement.plan_from_deviation`, in the planner process)."""
    if svc.cfg.placement is None:
        msg = "the project has no placement section (and tunnel.alignment): it cannot place"
        return Reply.bad_request(msg)
    bad = ring_refusal(ring)
    if bad is not None:
        return bad
    try:
        plan: PlacementPlan = svc.planner.call(PLAN_PLACE_FN, ring, previous_deviation)
    except PlannerCallError as exc:
        return Reply.refused(f"place refused: {exc}", Code.PLANNER)
    return plan


class PlaceMotion(Motion):
    """The part to :attr:`placement`'s target; see the module docstring."""

    name = "place"

    def __init__(self, svc: Service, plan: PlacementPlan, placer: PlacementSequencer) -> None:
        self.attitude = svc.attitude
        self.placement = plan
        self.plan = self.plan_dict = plan.to_dict()
        self.sequencer = self.placer = placer
        self.started_s = 0.0
        self.phase_times_s: dict[str, float] | None = None
        self._phase = -1
        self._claim: Claim | None = None

    @classmethod
    def prepare(cls, svc: Service, *args: Any) -> Motion | Reply:
        """``plan``'s move: refused (with the binding limit) when the plan is infeasible;
        the attitude trajectory planned from the measured state, every move checked."""
        (plan,) = args

        def refused(code: Code, msg: str, **more: Any) -> Reply:
            if svc.record is not None:
                svc.record.event(svc.now_s, "place_refused", ring=plan.ring, error=msg)
            return Reply.refused(msg, code, **more)

        if not plan.feasible:
            return refused(
                Code.INFEASIBLE, "place refused: " + "; ".join(plan.reasons),
                reasons=plan.reasons, plan=plan.to_dict(),
            )  # fmt: skip
        inp = svc.inputs
        if inp is None or not inp.positions_valid:
            return refused(Code.REFUSED, "place refused: no valid positions")
        x = inp.positions.value
        half = np.array([c.stroke_m / 2 for c in svc.cfg.cylinders_by_can_index])
        lo, up = svc.attitude.layers["lower"], svc.attitude.layers["upper"]
        heave = plan.heave_m
        roll_deg, pitch_deg = plan.attitude_world_deg
        try:
            att: Plan = svc.planner.call(
                PLAN_ATTITUDE_FN, roll_deg, pitch_deg,
                start_lower_m=tuple((x[lo] - half[lo] - heave).tolist()),
                start_upper_m=tuple((x[up] - half[up]).tolist()),
            )  # fmt: skip
        except PlannerCallError as exc:
            return refused(Code.PLANNER, f"place refused: {exc}")
        if not att.feasible or att.trajectory is None:
            msg = "place refused: " + "; ".join(att.reasons)
            return refused(Code.INFEASIBLE, msg, reasons=list(att.reasons))
        ext = {
            a.group: tuple(units.mm(e) for e in a.extensions_mm)
            for a in plan.actuators
            if a.group in SLIDE_ROLES
        }
        try:
            placer = PlacementSequencer(
                svc.cfg, svc.period_s, svc.attitude, att.trajectory, heave, ext
            )
        except ValueError as exc:
            return refused(Code.INFEASIBLE, f"place refused: {exc}")
        return cls(svc, plan, placer)

    def describe(self) -> str:
        tgt = self.plan_dict["target_deviation"]
        return (
            f"ring {self.placement.ring}: y {tgt['y_mm']:+.2f} mm, z {tgt['z_mm']:+.2f} mm "
            "from its design"
        )

    def accepted(self) -> dict[str, Any]:
        return {"ring": self.placement.ring}

    def metrics(self) -> Mapping[str, Metrics]:
        return self.attitude.metrics

    def claim(self) -> Claim | None:
        return self._claim

    def _phase_claim(self) -> Claim | None:
        """The present phase's group, when the phase changed since the last claim."""
        p = self.placer
        if p.phase == self._phase:
            return None
        self._phase = p.phase
        ev = event("place_phase", phase=p.phase_name, active=None, bus_load_percent=None)
        group = tuple(p.active_group())
        self._claim = Claim(group, tuple(p.watched()), PlcMode.ATTITUDE_ADJUST, ev)
        return self._claim

    def start(self, inp: MachineInputs) -> Effects:
        self.placer.start(inp.t, inp.positions.value)
        self.started_s = inp.t
        ring = self.placement.ring
        return (event("place", ring=ring, plan=self.plan_dict), self._phase_claim())

    def update(self, inp: MachineInputs, mode: Mode) -> Command:
        p = self.placer
        was_done = p.done
        u = p.update(inp.t, np.nan_to_num(inp.positions.value, nan=0.0))
        done = mode == Mode.EXECUTE and p.done and not was_done
        return Command(u, p.last_refs, done, claim=self._phase_claim())

    def completed(self, now: float) -> Event | None:
        p = self.placer
        self.phase_times_s = dict(p.phase_times_s)
        return event(
            "place_done", ring=self.placement.ring, phase_times_s=p.phase_times_s,
            max_sync_error_mm=units.to_mm(p.max_sync_error_m),
        )  # fmt: skip

    def stop_point(self, now: float, inp: MachineInputs | None) -> np.ndarray:
        ref = self.placer.last_refs
        if ref is None:
            ref = self.attitude.last_references
        return ref if ref is not None else self.attitude.references(now)

    def resume(self, inp: MachineInputs, shift_s: float, held: bool) -> None:
        x = inp.positions.value
        self.attitude.resume(x, shift_s)
        self.placer.resume(np.nan_to_num(x), shift_s)

    def end(self, now: float, mode: Mode, successor: Motion | None) -> Effects:
        """The lower layer's offset back to none, the attitude group back."""
        p = self.placer
        p.finish()
        return (None, event("place_end", phase=p.phase_name, mode=str(mode)))

    def status(self) -> dict[str, Any] | None:
        p, plan = self.placer, self.plan_dict
        return {
            "ring": self.placement.ring,
            "phase": p.phase_name,
            "done": p.done,
            "phase_times_s": {k: round(v, 3) for k, v in p.phase_times_s.items()},
            "max_sync_error_mm": round(units.to_mm(p.max_sync_error_m), 4),
            "target_deviation": plan["target_deviation"],
            "expected_table4": {k: v["value"] for k, v in plan["table4"].items() if v},
        }
