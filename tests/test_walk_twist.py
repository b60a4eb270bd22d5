"""The walk's twist-mode controller (ipc_app/control/walk.py, docs/walking.md): a frame
standing in position control has its references moved in the twist mode only, by a PI
law whose gains ``walking.twist_bandwidth_rad_s`` sets."""

from __future__ import annotations

import numpy as np
import pytest

from config import load_project
from config.schema import ProjectConfig
from ipc_app.control.walk import MAIN, SUB, WalkSequencer
from ipc_app.planner.walk import plan_walk

PERIOD_S = 0.005
TWIST = np.array([1.0, -1.0, 1.0, -1.0])


def sequencer(bandwidth_rad_s: float | None = None) -> WalkSequencer:
    cfg = load_project(None)
    if bandwidth_rad_s is not None:
        assert cfg.walking is not None
        walking = cfg.walking.model_copy(update={"twist_bandwidth_rad_s": bandwidth_rad_s})
        cfg = ProjectConfig.model_validate({**cfg.model_dump(), "walking": walking.model_dump()})
    return WalkSequencer(cfg, PERIOD_S, plan_walk(cfg, 1))


def offsets_after(seq: WalkSequencer, twist_n: float, cycles: int) -> np.ndarray:
    """The sub frame's reference offsets (4,) after ``cycles`` with its legs' forces
    carrying ``twist_n`` of twist over a twist-free plan."""
    plan_f = np.full(8, 150e3)
    f = plan_f.copy()
    f[list(SUB)] += twist_n * TWIST
    refs = np.zeros(seq.n)
    for _ in range(cycles):
        refs = np.zeros(seq.n)
        seq._twist_control(refs, f, plan_f, SUB)
    return np.array([refs[seq.legs[j]] for j in SUB])


def test_a_twist_moves_the_references_against_it_in_the_twist_mode_only() -> None:
    seq = sequencer()
    cfg = seq.cfg
    assert cfg.walking is not None
    n, twist_n = 200, 5e3  # 1 s, 5 kN
    off = offsets_after(seq, twist_n, n)
    k = cfg.walking.contact.stiffness_n_m
    ki = cfg.walking.twist_bandwidth_rad_s / k
    kp = ki / cfg.control.ladrc.wc_rad_s
    amplitude = ki * twist_n * n * PERIOD_S + kp * twist_n
    # legs 1 and 3 (the ones carrying too much) retract, 2 and 4 extend, by the same
    assert off == pytest.approx(-amplitude * TWIST, rel=1e-9)
    # nothing in the body's three patterns: the height and the attitude are untouched
    pts = seq.machine.legs_xy(0.0)[list(SUB)]
    assert abs(off.sum()) < 1e-12
    assert abs(off @ pts[:, 0]) < 1e-12 and abs(off @ pts[:, 1]) < 1e-12


def test_the_bandwidth_key_governs_the_twist_loop() -> None:
    slow = offsets_after(sequencer(2.0), 5e3, 200)
    fast = offsets_after(sequencer(4.0), 5e3, 200)
    assert fast == pytest.approx(2.0 * slow, rel=1e-9)  # both gains scale with the key


def test_no_twist_no_motion_and_a_frame_in_force_control_is_left_alone() -> None:
    seq = sequencer()
    assert np.all(offsets_after(seq, 0.0, 50) == 0.0)
    seq = sequencer()
    seq.force_mode.add(seq.legs[SUB[0]])
    assert np.all(offsets_after(seq, 5e3, 50) == 0.0)


def test_the_controlled_frame_by_phase() -> None:
    seq = sequencer()
    by_key = {ph.key: seq._twist_frame(ph) for ph in seq.plan.phases}
    assert by_key["1"] == MAIN and by_key["2"] == MAIN and by_key["3"] == MAIN
    assert by_key["6"] == SUB and by_key["7a"] == SUB and by_key["7b"] == SUB
    for key in ("4", "5", "7c", "8"):
        assert by_key[key] == ()


def test_a_force_ramp_restarts_from_the_forces_at_the_resume() -> None:
    """After a stop in a transfer the receiving legs' ramp goes on from what they carry
    now, not from where its reference stood (the loops restart at the measurement)."""
    seq = sequencer()
    k = next(i for i, ph in enumerate(seq.plan.phases) if ph.key == "7c")
    x = seq.half.copy()
    p = np.zeros((seq.n, 2))
    p[seq.legs, 0] = 5e6
    seq.start(0.0, x, p)
    seq._begin(k, 1.0, x, p)
    run = seq.run
    assert run is not None and run.phase.key == "7c"
    run.tau = 0.5 * run.duration_s  # halfway along the ramp when it stopped
    p[seq.legs[MAIN[0]], 0] = 6e6  # main_leg_1 took some load while stopped
    seq.resume(x, p)
    f = seq.forces_n(p)
    assert run.tau == 0.0
    assert np.allclose(run.start_f[list(MAIN)], f[list(MAIN)])
    delta = max(abs(run.target_f[j] - f[j]) for j in MAIN)
    assert run.duration_s == pytest.approx(delta / seq.walk.force_ramp_n_s)
