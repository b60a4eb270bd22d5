"""A placement move in lockstep: the HIL simulator and the IPC's controllers on one
virtual bus, simulated time (``wara place run --lockstep``; docs/placement.md).

The phases of placement.md section 2, each checked before it starts:

1. attitude and height: the attitude planner's trajectory to the target's roll and
   pitch, planned from the measured start less the height, with the lower layer's
   references shifted by the height (the attitude layers at the loop rate, the slide
   axes' valves closed);
2. slide: yaw, lateral and gap together (the slide axes at the loop rate; the attitude
   layers hold their end point on their slower frames: both groups at the loop rate
   would load the bus to 65 %, over ``can.max_bus_load_percent``).

The loop runs the controllers' :class:`~ipc_app.control.placement.PlacementSequencer`
directly (read -> update -> write every period), without the service core around it
(``wara ctl place`` runs the same sequencer in the service).
"""

from __future__ import annotations

import itertools
import time
from typing import Any

import can
import numpy as np

from config import ProjectConfig, units
from hil_sim.placement import pose_from_home
from hil_sim.simulator import HilSimulator
from ipc_app.control.attitude import AttitudeController
from ipc_app.control.placement import PlacementSequencer
from ipc_app.control.slide import SLIDE_ROLES
from ipc_app.model.placement import Pose, compose, deviation, joint_figures
from ipc_app.planner.placement import home_pose, judge, plan_from_deviation
from ipc_app.planner.plan import plan as plan_attitude
from plc_bridge import IpcLink, Mode

_channels = itertools.count()

#: Goals in simulation (the issue's): position and centreline within 1 mm, gap within
#: 1 mm of the target, angles within 0.01 deg.
GOAL_MM = 1.0
GOAL_DEG = 0.01


def run_placement_lockstep(
    cfg: ProjectConfig, ring: int, previous_deviation: Pose
) -> dict[str, Any]:
    """Plan ring ``ring``'s target from the previous part's deviation, move there on the
    simulator and judge the simulator's truth."""
    wall0 = time.perf_counter()
    plan = plan_from_deviation(cfg, ring, previous_deviation)
    out: dict[str, Any] = {"ring": ring, "plan": plan.to_dict()}
    if not plan.feasible:
        return {**out, "passed": False, "reasons": plan.reasons}
    ext = {
        a.group: tuple(units.mm(e) for e in a.extensions_mm)
        for a in plan.actuators
        if a.group in SLIDE_ROLES
    }
    ext_heave = units.mm(plan.heave_mm)
    channel = f"wara-place-{next(_channels)}"
    sim = HilSimulator(cfg, can.Bus(interface="virtual", channel=channel))
    link = IpcLink(cfg, can.Bus(interface="virtual", channel=channel), clock=sim.clock)
    period = cfg.control.period_s
    att = AttitudeController(cfg, period)
    attitude_set = att.layers["lower"] + att.layers["upper"]
    phase_s: dict[str, float] = {}
    worst = {"sync_error_mm": 0.0}

    def cycle(t_end: float, step: Any) -> None:
        while sim.t_s < t_end - 1e-9:
            link.poll()
            x = link.positions_m().value  # read
            u = step(sim.t_s, x)  # update
            link.send_valve_commands(np.nan_to_num(u))  # write
            sim.step(period)

    try:
        link.set_active_cylinders(attitude_set)
        link.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
        link.poll()
        att.engage(link.positions_m().value, sim.t_s, None)
        cycle(sim.t_s + 0.3, att.update)  # the link up, every frame fresh
        x = link.positions_m().value
        lo, up = att.layers["lower"], att.layers["upper"]
        half = att.half_stroke
        heave = ext_heave
        roll_deg, pitch_deg = plan.attitude_world_deg
        att_plan = plan_attitude(
            cfg,
            roll_deg,
            pitch_deg,
            start_lower_m=tuple((x[lo] - half[lo] - heave).tolist()),
            start_upper_m=tuple((x[up] - half[up]).tolist()),
        )
        if not att_plan.feasible or att_plan.trajectory is None:
            return {**out, "passed": False, "reasons": list(att_plan.reasons)}
        placer = PlacementSequencer(cfg, period, att, att_plan.trajectory, heave, ext)
        placer.start(sim.t_s, x)
        phase = 0
        while not placer.done:
            cycle(sim.t_s + period, placer.update)
            if placer.phase != phase:  # the slide axes at the loop rate
                phase = placer.phase
                link.set_active_cylinders(placer.active_group())
            if sim.t_s > 600.0:
                return {**out, "passed": False, "reasons": ["the move did not end in 600 s"]}
        phase_s = dict(placer.phase_times_s)
        worst["sync_error_mm"] = units.to_mm(placer.max_sync_error_m)
        r, t = pose_from_home(cfg, sim.rig)
    finally:
        link.close()
        sim.close()
    got = compose(home_pose(cfg, ring), Pose.from_matrix(r, t))
    err = deviation(got, plan.target)
    figures = joint_figures(cfg, plan.previous, got, plan.design)
    errors = err.to_dict()  # mm and deg
    gap_error_mm = units.to_mm(figures.max_gap_m - plan.figures.max_gap_m)
    goals = {
        "position_within_1_mm": max(abs(errors[k]) for k in ("x_mm", "y_mm", "z_mm")) <= GOAL_MM,
        "gap_within_1_mm_of_target": abs(gap_error_mm) <= GOAL_MM,
        "angles_within_0_01_deg": max(abs(errors[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
        <= GOAL_DEG,
    }
    table4 = judge(cfg, figures)
    table4_ok = all(v["passed"] is not False for v in table4.values())
    return {
        **out,
        "passed": all(goals.values()) and table4_ok,
        "goals": goals,
        "achieved": got.to_dict(),
        "error_from_target": errors,
        "gap_error_mm": gap_error_mm,
        "table4_truth": table4,
        "phase_times_s": phase_s,
        "max_sync_error_mm": worst["sync_error_mm"],
        "wall_time_s": time.perf_counter() - wall0,
    }
