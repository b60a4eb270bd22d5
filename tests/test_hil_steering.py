"""The walking rig's yaw: S turns in M on the rails' pivot, driven by the difference of the
two travel rods (curves.md section 3; hil_sim/walking.py's module docstring)."""

from __future__ import annotations

import math
import uuid

import can
import numpy as np
import pytest

from config import ProjectConfig
from config.hil_scenario import HilScenario
from hil_sim.simulator import HilSimulator
from hil_sim.walking import WalkingRig

SCAN = 4  # RK4 steps of 0.25 ms per PLC scan
KP = 100.0  # the rods' P loop: valve opening per metre of error


def _travel(rig: WalkingRig) -> tuple[int, int]:
    t1, t2 = (int(i) for i in rig._travel_idx)
    return t1, t2


def _hold(
    rig: WalkingRig, target: np.ndarray, seconds: float, each_scan: object = None
) -> list[tuple[float, float, float]]:
    """A P loop on each travel rod towards ``target`` (m, travel_1, travel_2), valves'
    ports open; ``(theta_M, theta_S, psi)`` after each scan."""
    idx = list(_travel(rig))
    rig.ports_open[idx] = 1.0
    seen = []
    for k in range(round(seconds / (SCAN * rig.step_s))):
        if callable(each_scan):
            each_scan(k)
        rig.command[idx] = np.clip(KP * (target - rig.rod_positions_m[idx]), -1.0, 1.0)
        rig.advance(SCAN)
        th = rig.heading_rad
        seen.append((float(th[0]), float(th[1]), rig.yaw_s_in_m_rad))
    return seen


def _yaw_of_rods(rig: WalkingRig, b_t: float) -> float:
    t1, t2 = _travel(rig)
    x = rig.rod_positions_m
    return math.asin((x[t1] - x[t2]) / (2.0 * b_t))


def _turned_lifted_sub(
    project: ProjectConfig,
) -> tuple[WalkingRig, np.ndarray, list[tuple[float, float, float]]]:
    """The start state (M standing, S lifted), the travel rods driven 8 mm apart (rod 1,
    on the right, 4 mm out; rod 2 4 mm in): S turned left by about 0.29 deg."""
    rig = WalkingRig(project)
    t1, t2 = _travel(rig)
    start = rig.rod_positions_m[[t1, t2]]
    seen = _hold(rig, start + np.array([4e-3, -4e-3]), 2.0)
    return rig, start, seen


def test_lifted_sub_frame_turns_with_the_travel_rods_difference(
    project: ProjectConfig,
) -> None:
    assert project.walking is not None
    b_t = project.walking.travel_half_span_m
    rig, _start, seen = _turned_lifted_sub(project)
    t1, t2 = _travel(rig)
    diff = rig.rod_positions_m[t1] - rig.rod_positions_m[t2]
    assert diff == pytest.approx(8e-3, abs=0.3e-3)
    psi = rig.yaw_s_in_m_rad
    assert psi == pytest.approx(_yaw_of_rods(rig, b_t), abs=1e-12)
    assert psi == pytest.approx(math.asin(8e-3 / (2 * b_t)), rel=0.05)  # turned left
    # M stands: its feet hold it against the pair's reaction
    theta_m = np.array([s[0] for s in seen])
    assert np.max(np.abs(theta_m)) < 5e-5  # the feet's shear: about 20 urad at the start
    assert rig.yaw_slip_rad[0] == 0.0
    th = rig.heading_rad
    assert th[1] == pytest.approx(th[0] + psi, abs=1e-15)
    # in plan: M's centre where it was; S's on M's rails through the pivot
    plan = rig.plan_xy_m
    assert plan[0, 1] == 0.0
    assert plan[1, 1] == pytest.approx(rig.x_s_m * math.sin(th[0]), abs=1e-12)
    assert plan[:, 0] == pytest.approx(np.array(rig.world_x_m))


def test_lifted_main_frame_turns_to_the_standing_sub_frames_heading(
    project: ProjectConfig,
) -> None:
    """S turned and then set down (the invert raised under its feet until it carries the
    machine and M's feet hang); the travel pair back to equal rods turns M about the
    pivot, and S's heading and place stay put."""
    assert project.walking is not None and project.frames is not None
    rig, start, _seen = _turned_lifted_sub(project)
    # S's feet in plan
    (xs, ys), th_s = rig.plan_xy_m[1], rig.heading_rad[1]
    a, b = project.frames.sub.a_m, project.frames.sub.b_m
    c, s = math.cos(th_s), math.sin(th_s)
    feet = [
        (xs + sx * a * c - sy * b * s, ys + sx * a * s + sy * b * c)
        for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))
    ]
    clear = project.walking.clearance_m

    def raise_invert(k: int) -> None:  # over 2 s, to 40 mm above S's lifted feet
        dz = clear - 2e-3 + min(k / 2000, 1.0) * 42e-3
        rig.set_ground([(fx - 0.3, fx + 0.3, fy - 0.3, fy + 0.3, dz) for fx, fy in feet])

    _hold(rig, start + np.array([4e-3, -4e-3]), 3.0, raise_invert)
    forces = rig.foot_forces_n
    assert np.all(forces[:4] == 0.0) and np.all(forces[4:] > 50e3)  # M lifted, S stands
    psi0 = rig.yaw_s_in_m_rad
    assert psi0 == pytest.approx(
        math.asin(8e-3 / (2 * project.walking.travel_half_span_m)), rel=0.05
    )
    th0 = rig.heading_rad
    plan0 = rig.plan_xy_m
    seen = _hold(rig, start, 3.0)
    psi = rig.yaw_s_in_m_rad
    th = rig.heading_rad
    assert abs(psi) < 3e-5  # the rods equal again (to the P loop's residual)
    assert psi == pytest.approx(_yaw_of_rods(rig, project.walking.travel_half_span_m))
    # S's heading held by its feet (their shear springs give while M is swung: about
    # 0.2 mrad, 0.4 mm at the feet); M turned by what S had turned in it
    moved = np.abs(np.array([s[1] for s in seen]) - th0[1])
    assert np.max(moved) < 5e-4
    assert moved[-1] < 1e-6
    assert th[0] - th0[0] == pytest.approx(psi0, abs=3e-5)
    assert rig.yaw_slip_rad[1] == 0.0
    # in plan: S's centre stays; M's swings about the pivot (S's centre)
    plan = rig.plan_xy_m
    assert plan[1, 1] == plan0[1, 1]
    assert plan[1, 0] == pytest.approx(plan0[1, 0], abs=1e-6)
    assert plan[0, 1] == pytest.approx(plan[1, 1] - rig.x_s_m * math.sin(th[0]), abs=1e-12)
    assert plan[0, 1] - plan0[0, 1] == pytest.approx(-rig.x_s_m * (th[0] - th0[0]), rel=1e-2)


def test_equal_commands_keep_the_sub_frame_straight(project: ProjectConfig) -> None:
    rig = WalkingRig(project)
    t1, t2 = _travel(rig)
    rig.ports_open[[t1, t2]] = 1.0
    rig.command[[t1, t2]] = 0.3
    psi = []
    for _ in range(3000):  # 3 s: S travels about 0.1 m
        rig.advance(SCAN)
        psi.append(abs(rig.yaw_s_in_m_rad))
    assert rig.x_s_m > -0.95
    assert max(psi) < 1e-4
    # each rod on a P loop of its own, on readings with 5 um of noise, along a ramp
    rig = WalkingRig(project)
    rng = np.random.default_rng(7)
    x0 = rig.rod_positions_m[t1]
    psi = []

    def ramp(k: int) -> None:
        target = x0 + min(k * 1e-3, 3.0) * 0.05
        read = rig.rod_positions_m[[t1, t2]] + rng.normal(0.0, 5e-6, 2)
        rig.command[[t1, t2]] = np.clip(50.0 * (target - read), -1.0, 1.0)

    rig.ports_open[[t1, t2]] = 1.0
    for k in range(4000):
        ramp(k)
        rig.advance(SCAN)
        psi.append(abs(rig.yaw_s_in_m_rad))
    assert rig.x_s_m > -0.9
    assert max(psi) < 1e-4
    assert np.max(np.abs(rig.heading_rad)) < 1e-4


@pytest.mark.parametrize("side", [1.0, -1.0])
def test_the_rails_end_stop_bounds_the_yaw(project: ProjectConfig, side: float) -> None:
    """The pair driven apart at full opening: S turns until the end stop holds it."""
    assert project.walking is not None
    rig = WalkingRig(project)
    t1, t2 = _travel(rig)
    rig.ports_open[[t1, t2]] = 1.0
    rig.command[[t1, t2]] = (side, -side)
    psi = []
    for _ in range(3000):
        rig.advance(SCAN)
        psi.append(rig.yaw_s_in_m_rad)
    limit = project.walking.max_yaw_rad
    assert side * psi[-1] == pytest.approx(limit, abs=1e-4)  # on the stop
    assert max(abs(p) for p in psi) < limit + 3e-4
    assert np.sign(psi[-1]) == side
    diff = rig.rod_positions_m[t1] - rig.rod_positions_m[t2]
    b_t = project.walking.travel_half_span_m
    assert abs(diff) < 2 * b_t * math.sin(limit) + 0.5e-3
    assert abs(rig.heading_rad[0]) < 1e-4  # M stands


def test_the_simulators_truth_reports_the_frames(project: ProjectConfig) -> None:
    for contact in (True, False):
        scenario = HilScenario.model_validate({"plant": {"contact": contact}})
        bus = can.Bus(interface="virtual", channel=f"steer-{uuid.uuid4().hex}")
        sim = HilSimulator(project, bus, scenario)
        try:
            sim.step(0.02)
            walk = sim.truth().walk
            if not contact:
                assert walk is None
                continue
            rig = sim.rig
            assert isinstance(rig, WalkingRig) and walk is not None
            assert walk.world_x_m == rig.world_x_m
            assert walk.x_s_m == rig.x_s_m
            assert np.array_equal(walk.heading_rad, rig.heading_rad)
            assert walk.yaw_s_in_m_rad == rig.yaw_s_in_m_rad == 0.0
            assert walk.plan_xy_m.shape == (2, 2)
            assert np.array_equal(walk.plan_xy_m[:, 0], np.array(rig.world_x_m))
            assert np.array_equal(walk.slip_m, rig.slip_m)
            assert np.array_equal(walk.yaw_slip_rad, rig.yaw_slip_rad)
        finally:
            sim.close()
