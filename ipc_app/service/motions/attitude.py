"""The attitude layers' motions: an adjustment (``wara ctl adjust``, the HMI's target),
a jog (``wara ctl jog``, MANUAL), and their base, :class:`LayersMotion`: the eight
attitude cylinders follow a path from where they stand
(:class:`~ipc_app.control.attitude.AttitudeController`), the motion ends when the path's
time is up and the end point is held.

An adjustment is planned in the planner process (:class:`AdjustPlanning`): the request
takes the mode machine to STARTING; the loop hands the target and the measured start to
the planner (non-blocking) and, when the answer comes, starts the motion (feasible),
returns to IDLE with the planner's reasons (infeasible) or latches the ``planner``
interlock (a crash or a timeout).
"""

from __future__ import annotations

import math
import threading
from collections.abc import Mapping
from typing import Any

import numpy as np
import structlog

from config import units
from ipc_app.control.attitude import AttitudeController, ConstantSpeedPath
from ipc_app.planner.trajectory import Trajectory
from ipc_app.service.interlocks import Cause, Interlock, Metrics
from ipc_app.service.machine_io import Handshake, MachineInputs
from ipc_app.service.manager import MotionManager
from ipc_app.service.modes import Mode, ModeMachine
from ipc_app.service.motion import Command, Effects, Event, Motion, Planner, Service
from ipc_app.service.record import RunRecorder
from ipc_app.service.requests import Code, Reply
from plc_bridge.link import TargetAck

log = structlog.get_logger("wara.service")


class LayersMotion(Motion):
    """The attitude layers follow a path (``duration_s``, ``sample``, ``positions``)
    engaged at the measured rods; ended by its clock, then held at its end point."""

    name = "adjust"
    answers_hmi = True

    def __init__(self, attitude: AttitudeController, path: Trajectory | None = None) -> None:
        self.attitude = attitude
        self.path = path

    def path_from(self, inp: MachineInputs) -> Any:
        """The path from the measured rods (a planned trajectory: as planned)."""
        return self.path

    def metrics(self) -> Mapping[str, Metrics]:
        return self.attitude.metrics

    def start(self, inp: MachineInputs) -> Effects:
        self.attitude.engage(inp.positions.value, inp.t, self.path_from(inp))
        return ()

    def finished(self, now: float) -> bool:
        return self.attitude.motion_done(now)

    def completed(self, now: float) -> Event | None:
        self.attitude.hold(self.attitude.final_references())
        return None

    def update(self, inp: MachineInputs, mode: Mode) -> Command:
        u = self.attitude.update(inp.t, inp.positions.value)
        return Command(u, self.attitude.last_references)  # this cycle's, for the record

    def stop_point(self, now: float, inp: MachineInputs | None) -> np.ndarray:
        ref = self.attitude.last_references
        return ref if ref is not None else self.attitude.references(now)

    def resume(self, inp: MachineInputs, shift_s: float, held: bool) -> None:
        self.attitude.resume(inp.positions.value, shift_s)


class AdjustMotion(LayersMotion):
    """An adjustment to a planned attitude (started by :class:`AdjustPlanning`)."""

    def __init__(
        self,
        attitude: AttitudeController,
        trajectory: Trajectory | None,
        target_deg: tuple[float, float],
        plan: dict[str, Any] | None,
    ) -> None:
        super().__init__(attitude, trajectory)
        self.target_deg = target_deg
        self.plan = plan


class JogMotion(LayersMotion):
    """One attitude cylinder by ``distance_mm`` at ``control.manual_jog_speed_mm_s``, the
    others held where they stand (unit mode MANUAL)."""

    name = "jog"

    def __init__(self, svc: Service, cylinder: str, distance_mm: float) -> None:
        super().__init__(svc.attitude)
        cfg = svc.cfg
        by_index = cfg.cylinders_by_can_index
        self.cylinder, self.distance_mm = cylinder, distance_mm
        self.where = [
            (name, k, i)
            for name, idx in self.attitude.layers.items()
            for k, i in enumerate(idx)
            if by_index[i].id == cylinder
        ]
        self.ids = [by_index[i].id for idx in self.attitude.layers.values() for i in idx]
        self.stroke = np.array([c.stroke_m for c in by_index])
        self.end_margin_m = units.mm(cfg.safety.stroke_end_margin_mm)
        self.speed_m_s = units.mm(cfg.control.manual_jog_speed_mm_s)

    @classmethod
    def prepare(cls, svc: Service, *args: Any) -> Motion | Reply:
        cylinder, distance_mm = args
        return cls(svc, cylinder, distance_mm)

    def describe(self) -> str:
        speed = units.to_mm(self.speed_m_s)
        return f"{self.cylinder} {self.distance_mm:+.2f} mm at {speed:.1f} mm/s"

    def refusal(self, inp: MachineInputs) -> str | None:
        if not self.where:
            return f"jog: {self.cylinder!r} is not an attitude cylinder ({', '.join(self.ids)})"
        ((_layer, _k, i),) = self.where
        d = units.mm(self.distance_mm)
        end = float(inp.positions.value[i]) + d
        lo, hi = self.end_margin_m, self.stroke[i] - self.end_margin_m
        if math.isfinite(d) and d != 0.0 and lo <= end <= hi:
            return None
        return (
            f"jog refused: {self.cylinder} would end at {units.to_mm(end):.1f} mm, outside "
            f"{units.to_mm(lo):.1f}..{units.to_mm(hi):.1f} mm (stroke less the end margin)"
        )

    def path_from(self, inp: MachineInputs) -> Any:
        ((layer, k, _i),) = self.where
        x, half = inp.positions.value, self.stroke / 2
        lo_i, up_i = self.attitude.layers["lower"], self.attitude.layers["upper"]
        return ConstantSpeedPath(
            (x[lo_i] - half[lo_i]).tolist(), (x[up_i] - half[up_i]).tolist(), layer, (k,),
            units.mm(self.distance_mm), self.speed_m_s,
        )  # fmt: skip


class AdjustPlanning:
    """An adjustment from its request to its motion; see the module docstring."""

    def __init__(
        self,
        svc: Service,
        planner: Planner,
        modes: ModeMachine,
        handshake: Handshake,
        motions: MotionManager,
        record: RunRecorder | None,
    ) -> None:
        self.attitude = svc.attitude
        self.planner = planner
        self.modes = modes
        self.handshake = handshake
        self.motions = motions
        self.record = record
        self.half_stroke = np.array([c.stroke_m / 2 for c in svc.cfg.cylinders_by_can_index])
        self._request_id = 0
        self._submitted = False
        self._cv = threading.Condition()
        self._outcome: Reply | None = None

    def request(self, roll_deg: float, pitch_deg: float, wait_s: float, hmi_seq: int) -> Reply:
        """Ask for an adjustment (any thread); with ``wait_s`` > 0 wait for the planner's
        verdict. ``hmi_seq``: the HMI's TargetSeq (0: a local request)."""
        with self._cv:
            self._outcome = None
        out = self.modes.request_adjust(roll_deg, pitch_deg)
        if not out.accepted:
            return Reply.refused(out.message, mode=str(out.mode))
        self.handshake.serve(hmi_seq)
        if wait_s <= 0:
            return Reply.accepted(mode=str(Mode.STARTING))
        with self._cv:
            self._cv.wait_for(lambda: self._outcome is not None, timeout=wait_s)
            result = self._outcome
        if result is None:
            return Reply.accepted(mode=str(self.modes.mode), note="still planning")
        return result

    def poll(self, inp: MachineInputs) -> None:
        """The loop's side: submit the target with the measured start; take the answer
        (only with valid positions: the motion engages at them)."""
        x, valid, now = inp.positions.value, inp.positions_valid, inp.t
        if self.modes.mode == Mode.STARTING and not self._submitted and valid:
            target = self.modes.target_deg
            if target is not None:
                self._request_id += 1
                half = self.half_stroke
                lo, up = self.attitude.layers["lower"], self.attitude.layers["upper"]
                self._submitted = self.planner.submit(
                    self._request_id,
                    target[0],
                    target[1],
                    start_upper_m=tuple((x[up] - half[up]).tolist()),
                    start_lower_m=tuple((x[lo] - half[lo]).tolist()),
                )
        if not valid:
            return
        res = self.planner.poll()
        if res is None or res.request_id != self._request_id:
            return
        self._submitted = False
        if self.modes.mode != Mode.STARTING:
            return  # stopped or faulted meanwhile: the plan is dropped
        self.handshake.ack(TargetAck.ACCEPTED if res.ok and res.feasible else TargetAck.REJECTED)
        if not res.ok:
            self.modes.fault(Cause(Interlock.PLANNER, detail=str(res.error)))
            verdict = Reply(False, Code.PLANNER, res.error)
        elif not res.feasible or res.trajectory is None:
            self.modes.plan_failed(list(res.reasons))
            verdict = Reply(False, Code.INFEASIBLE, fields={"reasons": list(res.reasons)})
        else:
            self.modes.plan_ready()
            target = (res.plan or {}).get("target", {})
            target_deg = (target.get("roll_deg", 0.0), target.get("pitch_deg", 0.0))
            self.motions.take(
                AdjustMotion(self.attitude, res.trajectory, target_deg, res.plan), inp
            )
            verdict = Reply.accepted(mode=str(Mode.EXECUTE), duration_s=res.duration_s)
        fields = verdict.to_dict()
        log.info("plan", request_id=res.request_id, **fields)
        if self.record is not None:
            self.record.event(now, "plan", request_id=res.request_id, plan=res.plan, **fields)
        with self._cv:
            self._outcome = verdict
            self._cv.notify_all()
