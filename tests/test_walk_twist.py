"""The walk's twist-mode controller (ipc_app/control/walk/, docs/walking.md): a frame
standing in position control has its commands set modally, the twist's share by a force
loop whose crossover ``walking.twist_bandwidth_rad_s`` sets, the rest by the position
loops, which do not see the twist."""

from __future__ import annotations

import numpy as np
import pytest

from config import load_project
from config.schema import ProjectConfig
from ipc_app.control.walk import MAIN, SUB, WalkSequencer
from ipc_app.planner.walk import plan_walk

PERIOD_S = 0.005
TWIST = np.array([1.0, -1.0, 1.0, -1.0])


def sequencer(
    bandwidth_rad_s: float | None = None,
    observer_rad_s: float | None = None,
    touchdown_rad_s: float | None = None,
) -> WalkSequencer:
    cfg = load_project(None)
    assert cfg.walking is not None
    upd = {
        "twist_bandwidth_rad_s": bandwidth_rad_s,
        "twist_observer_rad_s": observer_rad_s,
        "twist_observer_touchdown_rad_s": touchdown_rad_s,
    }
    upd = {k: v for k, v in upd.items() if v is not None}
    walking = cfg.walking.model_copy(update=upd)
    cfg = ProjectConfig.model_validate({**cfg.model_dump(), "walking": walking.model_dump()})
    return WalkSequencer(cfg, PERIOD_S, plan_walk(cfg, 1))


#: the sub frame's position loops' commands: heave and pitch, no twist
U_POS = np.array([0.02, 0.01, 0.01, 0.02])


def commands_after(seq: WalkSequencer, twist_n: float, cycles: int) -> np.ndarray:
    """The sub frame's valve commands (4,) after ``cycles`` with its legs' forces
    carrying ``twist_n`` of twist over a twist-free plan, its position loops asking
    :data:`U_POS`."""
    plan_f = np.full(8, 150e3)
    f = plan_f.copy()
    f[list(SUB)] += twist_n * TWIST
    u = np.zeros(seq.n)
    for _ in range(cycles):
        u = np.zeros(seq.n)
        u[[seq.legs[j] for j in SUB]] = U_POS
        seq._twist_control(u, f, plan_f, SUB)
    return np.array([u[seq.legs[j]] for j in SUB])


def test_a_twist_drives_the_commands_against_it_in_the_twist_mode_only() -> None:
    seq = sequencer()
    cfg = seq.cfg
    assert cfg.walking is not None
    twist_n = 5e3
    u = commands_after(seq, twist_n, 1)
    # the first command of a first-order LADRC started at the measured twist: -wc T / b0,
    # b0 the force loops' (a leg's stiffness in series with the contact)
    b0 = float(np.mean([seq.force[seq.legs[j]].b0 for j in SUB]))
    u_t = -cfg.walking.twist_bandwidth_rad_s * twist_n / b0
    assert u == pytest.approx(U_POS + u_t * TWIST, rel=1e-9)
    # legs 1 and 3 (the ones carrying too much) retract against the others
    assert u_t < 0
    # the position loops' three patterns (the body's height and attitude) untouched
    pts = seq.machine.legs_xy(0.0)[list(SUB)]
    d = u - U_POS
    assert abs(d.sum()) < 1e-12
    assert abs(d @ pts[:, 1]) < 1e-12 and abs(d @ (pts[:, 0] - pts[:, 0].mean())) < 1e-12
    # the position loops' observers are told the command applied
    assert [seq.pos[seq.legs[j]].command for j in SUB] == pytest.approx(u.tolist(), rel=1e-12)


def test_the_twist_is_driven_out_and_the_command_rests() -> None:
    """Closed on a model of the mode (the twist force's rate the loop's ``b0`` times its
    command): from 5 kN to within 1 % in 1 s at 6 rad/s."""
    seq = sequencer()
    b0 = seq.twist.b0
    plan_f = np.full(8, 150e3)
    t = 5e3
    for _ in range(200):
        f = plan_f.copy()
        f[list(SUB)] += t * TWIST
        u = np.zeros(seq.n)
        seq._twist_control(u, f, plan_f, SUB)
        u_t = float(TWIST @ u[[seq.legs[j] for j in SUB]]) / 4
        t += b0 * u_t * PERIOD_S
    assert abs(t) < 50.0


def test_the_bandwidth_key_governs_the_twist_loop() -> None:
    slow = commands_after(sequencer(2.0), 5e3, 1) - U_POS
    fast = commands_after(sequencer(4.0), 5e3, 1) - U_POS
    assert fast == pytest.approx(2.0 * slow, rel=1e-9)  # the first command is -wc T / b0


def test_the_observer_key_governs_the_twist_loop() -> None:
    """``walking.twist_observer_rad_s`` is the twist loop's observer bandwidth (not the
    force loops'): a twist held against the loop is estimated, and driven against,
    the faster the higher it is."""
    slow, fast = sequencer(observer_rad_s=3.0), sequencer(observer_rad_s=12.0)
    assert (slow.twist.wo, fast.twist.wo) == (3.0, 12.0)
    assert slow.force[slow.legs[0]].wo == fast.force[fast.legs[0]].wo  # force_wo_rad_s
    u_slow = commands_after(slow, 5e3, 40) - U_POS
    u_fast = commands_after(fast, 5e3, 40) - U_POS
    assert abs(u_fast[0]) > 1.2 * abs(u_slow[0]) and u_fast[0] < 0 and u_slow[0] < 0


def test_the_touchdown_observer_key_governs_the_twist_loop_while_the_other_frame_sets_down() -> (
    None
):
    """``walking.twist_observer_touchdown_rad_s`` is the observer's bandwidth in the
    phases where the other frame lowers and preloads (2, 3, 7a, 7b),
    ``twist_observer_rad_s`` in the travel phases (1, 6): switched at the phase's start
    with the estimate and the command kept."""
    seq = sequencer(observer_rad_s=3.0, touchdown_rad_s=12.0)
    assert seq.plan.phases[0].key == "1"
    commands_after(seq, 5e3, 10)
    assert seq.twist.wo == 3.0
    z, u = seq.twist.z.copy(), seq.twist.command
    x = seq.half.copy()
    p = np.zeros((seq.n, 2))
    p[seq.legs, 0] = 5e6
    seq.start(0.0, x, p)
    for key, wo in (("7a", 12.0), ("7b", 12.0), ("6", 3.0), ("2", 12.0), ("3", 12.0)):
        k = next(i for i, ph in enumerate(seq.plan.phases) if ph.key == key)
        seq._begin(k, 1.0, x, p)
        seq.twist.reset(float(z[0]), u)
        z0 = seq.twist.z.copy()
        commands_after(seq, 0.0, 1)
        assert seq.twist.wo == wo, key
        fresh = sequencer(observer_rad_s=wo, touchdown_rad_s=wo)
        fresh.twist.reset(float(z[0]), u)
        fresh._twist_started = True  # started: the loop goes on from the state set here
        assert fresh.twist.z == pytest.approx(z0)
        commands_after(fresh, 0.0, 1)
        assert seq.twist.z == pytest.approx(fresh.twist.z, rel=1e-12), key  # same gains


def test_the_position_loops_do_not_see_the_twist_and_a_frame_in_force_control_is_left_alone() -> (
    None
):
    seq = sequencer()
    assert commands_after(seq, 0.0, 50) == pytest.approx(U_POS, abs=1e-15)
    x = np.zeros(seq.n)
    x[[seq.legs[j] for j in SUB]] = [1e-5, 0.0, 0.0, 0.0]  # heave, roll, pitch and twist
    refs = np.zeros(seq.n)
    active = set(range(seq.n))
    assert seq._twist_position(refs, x, SUB, active) == SUB
    r = np.array([refs[seq.legs[j]] for j in SUB])
    assert r == pytest.approx(2.5e-6 * TWIST, abs=1e-18)  # the rods' twist, nothing else
    seq.force_mode.add(seq.legs[SUB[0]])
    refs = np.zeros(seq.n)
    assert seq._twist_position(refs, x, SUB, active) == ()
    assert np.all(refs == 0.0)


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
    run.clock_s = 0.5 * run.duration_s  # halfway along the ramp when it stopped
    p[seq.legs[MAIN[0]], 0] = 6e6  # main_leg_1 took some load while stopped
    seq.resume(x, p)
    f = seq.forces_n(p)
    assert run.clock_s == 0.0
    assert np.allclose(run.start_force_n[list(MAIN)], f[list(MAIN)])
    delta = max(abs(run.target_force_n[j] - f[j]) for j in MAIN)
    assert run.ramp is not None  # at full rate over its line, blended in and out
    assert run.ramp.linear_s == pytest.approx(delta / seq.walk.force_ramp_n_s)
    assert run.duration_s == run.ramp.linear_s + min(seq.ramp_blend_s, run.ramp.linear_s)


@pytest.mark.parametrize("speed_mm_s", [0.05, 0.25, 0.5, 2.0])
def test_a_legs_friction_estimate_is_linear_below_half_a_mm_per_s(speed_mm_s: float) -> None:
    """The rods' friction taken off the legs' forces (``WalkSequencer.friction_n``): the
    Coulomb part full from 0.5 mm/s, linear below (near standstill its sign is not
    known), plus the viscous part at the measured speed."""
    seq = sequencer()
    rods = seq.rod_friction
    n = rods.positions_m.shape[0]
    v = speed_mm_s * 1e-3
    rods.positions_m[:] = (np.arange(n) * v * PERIOD_S)[:, None]  # each leg extending at v
    rods.times_s = [k * PERIOD_S for k in range(n)]
    rods.next_row = 0  # the oldest sample next: row 0
    coulomb = seq.coulomb_n * min(1.0, speed_mm_s / 0.5)
    assert seq.friction_n() == pytest.approx(coulomb + seq.viscous_n_s_m * v, rel=1e-9)


def test_a_legs_speed_across_a_stop_is_over_the_samples_times() -> None:
    """A stop of 140 ms (a suspension: no cycle runs) inside the window: the rods crept
    0.2 mm/s all along. The speed is the creep over the samples' own times, not 4 times
    it (the window taken as one cycle per sample: 10-20 kN of viscous friction on a
    standing leg in campaign run 48, an overload)."""
    seq = sequencer()
    n = seq.rod_friction.positions_m.shape[0]
    v = 0.2e-3
    times = [k * PERIOD_S for k in range(n)]
    times[1:] = [t + 0.140 for t in times[1:]]  # the stop between the first two samples
    seq.rod_friction.times_s = times
    seq.rod_friction.positions_m[:] = (np.array(times) * v)[:, None]
    seq.rod_friction.next_row = 0
    coulomb = seq.coulomb_n * min(1.0, 0.2 / 0.5)
    assert seq.friction_n() == pytest.approx(coulomb + seq.viscous_n_s_m * v, rel=1e-9)
    seq.rod_friction.times_s = [0.0] * n  # no time between the samples (the start): at rest
    assert not np.any(seq.friction_n())
