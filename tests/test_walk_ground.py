"""The lowering frame's expected ground follows the body (ipc_app/control/walk/ground.py,
docs/walking.md): the invert measured by the standing feet at a frame's lift and at its
lowering; the body's tilt and the standing feet's compression move where a foot meets it."""

from __future__ import annotations

import numpy as np
import pytest

from config import load_project
from ipc_app.control.walk import MAIN, SUB, WalkSequencer
from ipc_app.control.walk.ground import LiftMark, invert_plane, surface_z_m
from ipc_app.control.walk.phases import PhaseRun
from ipc_app.planner.walk import plan_walk

K = 2e8
STANDING_XY = np.array([[1.9, 0.95], [1.9, -0.95], [-1.9, 0.95], [-1.9, -0.95]])
LOWERING_XY = np.array([[2.8, 1.2], [2.8, -1.2], [-2.8, 1.2], [-2.8, -1.2]])


def test_a_body_pitched_nose_up_meets_the_invert_later_at_the_front() -> None:
    rods0 = np.full(4, 0.01)
    forces = np.full(4, 1.7e5)
    mark = LiftMark(invert_plane(STANDING_XY, surface_z_m(rods0, forces, K)), np.zeros(4))
    theta = 1e-3  # the body's front up: the standing rods extend by theta x to keep
    rods = rods0 + theta * STANDING_XY[:, 0]  # their feet on the invert
    touch = mark.touch_rods_now(STANDING_XY, surface_z_m(rods, forces, K), LOWERING_XY)
    assert touch == pytest.approx(theta * LOWERING_XY[:, 0], abs=1e-12)


def test_standing_feet_pressed_deeper_bring_the_invert_up_under_the_body() -> None:
    rods = np.full(4, 0.01)
    forces0 = np.full(4, 1.7e5)
    mark = LiftMark(invert_plane(STANDING_XY, surface_z_m(rods, forces0, K)), np.zeros(4))
    # the load moved forward: the front feet press 87.5 kN more into the invert, the
    # rear ones as much less; with the rods held the body sinks at the front
    forces = forces0 + np.array([8.75e4, 8.75e4, -8.75e4, -8.75e4])
    touch = mark.touch_rods_now(STANDING_XY, surface_z_m(rods, forces, K), LOWERING_XY)
    sink_front = 8.75e4 / K  # at x = 1.9; the plane goes on to x = 2.8
    assert touch[0] == pytest.approx(-sink_front * 2.8 / 1.9, rel=1e-9)
    assert touch[2] == pytest.approx(sink_front * 2.8 / 1.9, rel=1e-9)


def sequencer_at(
    phase: str, standing: tuple[int, ...]
) -> tuple[WalkSequencer, list[str], np.ndarray, np.ndarray]:
    """The shipped project's 1-step sequencer started, then at the start of ``phase``,
    ``standing``'s legs at 8 MPa on their caps, every rod at mid-stroke: the sequencer,
    the plan's phase keys, the rods' positions and the pressures."""
    cfg = load_project(None)
    seq = WalkSequencer(cfg, 0.005, plan_walk(cfg, 1))
    keys = [ph.key for ph in seq.plan.phases]
    x = seq.half.copy()
    p = np.zeros((seq.n, 2))
    p[[seq.legs[j] for j in standing], 0] = 8e6
    seq.start(0.0, x, p)
    seq._begin(keys.index(phase), 1.0, x, p)
    return seq, keys, x, p


def test_the_sequencer_shifts_a_lowering_legs_expected_ground_by_the_bodys_motion() -> None:
    """M lifts (phase 5) with S standing, the body pitches nose down on S's legs while M
    advances; at 7a M's front feet are expected that much sooner, the rear ones later,
    and each leg's lowering reference takes its shift in over the fast part."""
    seq, keys, x, p = sequencer_at("5", SUB)
    x_s = seq.x_s(x)
    xy = seq.machine.legs_xy(x_s)
    theta = -5e-4  # nose down: S's rods shorten by theta x at their feet
    x2 = x.copy()
    for j in SUB:
        x2[seq.legs[j]] += theta * xy[j, 0]
    for j in MAIN:  # lifted by the clearance
        x2[seq.legs[j]] -= seq.walk.clearance_m
    seq._begin(keys.index("7a"), 50.0, x2, p)
    run = seq.run
    assert run is not None and run.phase.key == "7a"
    xy_now = seq.machine.legs_xy(seq.x_s(x2))
    want = theta * xy_now[list(MAIN), 0]
    assert run.ground_shift_m == pytest.approx(want, abs=1e-9)
    assert abs(want).max() > 1e-3  # millimetres at the feet
    # the fast part's end: every leg touchdown_travel above its own expected ground
    # (measured there, so that the group's sync coupling sees no error)
    fast = seq._fast_lowering()
    run.clock_s = fast.duration_s
    there = x2.copy()
    for k, j in enumerate(MAIN):
        there[seq.legs[j]] += seq.walk.clearance_m + want[k] - seq.touchdown_travel_m
    seq.update(50.0 + fast.duration_s, there, p, set(range(seq.n)))
    for j in MAIN:
        i = seq.legs[j]
        assert seq.last_refs[i] == pytest.approx(there[i], abs=2e-5)


def lowering_s() -> tuple[WalkSequencer, PhaseRun, np.ndarray, np.ndarray]:
    """The shipped project's sequencer at the start of S's lowering (phase 2), M standing:
    the sequencer, its run, the rods' positions and the pressures."""
    seq, _keys, x, p = sequencer_at("2", MAIN)
    run = seq.run
    assert run is not None and run.phase.key == "2"
    return seq, run, x, p


def test_a_touched_leg_lets_off_what_it_pressed_on_down_to_its_touch_force() -> None:
    """A touch-down is seen some pressure frames late while the foot presses on; the
    touched leg's force reference falls from its force then to the touch force
    (``walking.touch_mpa`` over its cap) at ``walking.force_ramp_kn_s`` and holds it; a
    leg seen below its touch force holds what it had."""
    seq, run, x, p = lowering_s()
    first, low = SUB[0], SUB[1]
    touch = seq.touch_force_n
    extra_n = 10e3
    run.touched[0] = run.touched[1] = True
    run.touch_force_n[0] = touch[first] + extra_n
    run.touch_force_n[1] = 0.5 * touch[low]
    rate = seq.walk.force_ramp_n_s
    cycles = int(np.ceil(extra_n / (rate * seq.period_s)))
    refs = []
    for n in range(cycles + 5):
        seq.update(1.0 + n * seq.period_s, x, p, set(range(seq.n)))
        refs.append((seq.force_ref_n[first], seq.force_ref_n[low]))
    first_refs = np.array([r[0] for r in refs])
    assert first_refs[0] == pytest.approx(touch[first] + extra_n - rate * seq.period_s)
    assert np.all(np.diff(first_refs) <= 0)
    assert first_refs[cycles:] == pytest.approx(touch[first])
    assert [r[1] for r in refs] == pytest.approx([0.5 * touch[low]] * len(refs))


def test_a_lowering_rods_own_force_is_not_a_foot_pressing_the_invert() -> None:
    """In the fast part of a lowering a moving rod puts its seals' friction and the oil's
    drag on the body, kilonewtons the loops' friction does not hold: against its free
    rod's force, not zero, is a foot judged pressing the invert, and only then does its
    force come off what the standing legs are expected to carry."""
    seq, run, x, p = lowering_s()
    leg = SUB[0]
    i = seq.legs[leg]
    touch_n = seq.touch_force_n[leg]
    cap_m2 = float(seq.cap_area_m2[i])
    free_n = 1.2 * seq.PRESSING * touch_n  # a stiff seal: above the old absolute mark
    p[i, 0] = free_n / cap_m2
    t = 1.0
    for _ in range(40):
        t += seq.period_s
        seq.update(t, x, p, set(range(seq.n)))
    assert run.in_touchdown_window is False
    assert run.pressing[0] is False
    contact = seq.contact_n(seq.forces_n(p))
    assert contact[leg] == pytest.approx(-seq.machine.rod_weight_n)
    # the foot meets the invert: its force rises over the free rod's by more than the mark
    p[i, 0] = (free_n + 1.5 * seq.PRESSING * touch_n) / cap_m2
    for _ in range(3):
        t += seq.period_s
        seq.update(t, x, p, set(range(seq.n)))
    assert run.pressing[0] is True
    assert seq.contact_n(seq.forces_n(p))[leg] > free_n
