"""A transfer's control and checks (ipc_app/control/walk/, docs/walking.md): the
releasing legs' position loops are told the decompression of their oil columns, the
receiving legs are judged against the plan's line to their standing share; a lowering's
standing legs against their share standing alone."""

from __future__ import annotations

import numpy as np
import pytest

from config import load_project
from config.derived import hydraulic_stiffness_n_m
from ipc_app.control.walk import MAIN, SUB, WalkSequencer
from ipc_app.planner.walk import plan_walk

PERIOD_S = 0.005
TWIST = np.array([1.0, -1.0, 1.0, -1.0])


def in_transfer(key: str = "7c") -> tuple[WalkSequencer, np.ndarray, np.ndarray]:
    cfg = load_project(None)
    seq = WalkSequencer(cfg, PERIOD_S, plan_walk(cfg, 1))
    k = next(i for i, ph in enumerate(seq.plan.phases) if ph.key == key)
    x = seq.half.copy()
    p = np.zeros((seq.n, 2))
    p[seq.legs, 0] = 5e6
    seq.start(0.0, x, p)
    seq._begin(k, 1.0, x, p)
    return seq, x, p


@pytest.mark.parametrize("key", ["4", "7c"])
def test_the_releasing_legs_rates_keep_the_body_in_equilibrium_without_twist(key: str) -> None:
    seq, x, p = in_transfer(key)
    run = seq.run
    assert run is not None and run.phase.key == key
    receiving, releasing = (SUB, MAIN) if key == "4" else (MAIN, SUB)
    f = seq.forces_n(p)
    ramp = np.zeros(8)
    assert run.ramp is not None  # at full rate: its line's time, blended in and out
    ramp[list(receiving)] = (run.target_force_n - f)[list(receiving)] / run.ramp.linear_s
    rate = run.release_rate_n_s
    assert np.all(rate[list(receiving)] == 0.0)
    pts = seq.machine.legs_xy(seq.x_s(x))
    a = np.vstack([np.ones(8), pts[:, 1], -pts[:, 0]])
    total = ramp + rate
    assert np.abs(a @ total).max() < 1e-6 * np.abs(ramp).max() * 3  # heave, roll, pitch
    assert abs(TWIST @ rate[list(releasing)]) < 1e-6 * np.abs(rate).max()
    assert np.all(rate[list(releasing)] < 0.0)  # they unload, each one


@pytest.mark.parametrize("key", ["4", "7c"])
def test_the_releasing_loops_are_told_their_oil_columns_decompression(key: str) -> None:
    """In 7c; not in phase 4 (docs/walking.md: there it changed what 7a meets)."""
    seq, x, p = in_transfer(key)
    run = seq.run
    assert run is not None
    releasing = MAIN if key == "4" else SUB
    told: dict[int, float] = {}
    for j in releasing:
        i = seq.legs[j]
        ctrl = seq.pos[i]

        def spy(
            r: float, y: float, rate: float = 0.0, d: float = 0.0, i: int = i, real=ctrl.update
        ) -> float:
            told[i] = d
            return float(real(r, y, rate, d))

        ctrl.update = spy  # type: ignore[method-assign]
    run.clock_s = 0.5 * run.duration_s  # the ramp at its full rate
    seq.update(1.0 + PERIOD_S, x, p, set(range(seq.n)))
    cfg = seq.cfg
    if key == "4":
        assert all(told[seq.legs[j]] == 0.0 for j in releasing)
        return
    for j in releasing:
        i = seq.legs[j]
        cyl = cfg.cylinders_by_can_index[i]
        plant = cyl.plant or cfg.hydraulics.cylinder_defaults
        k_oil = hydraulic_stiffness_n_m(cyl, plant, cfg.hydraulics, float(x[i]))
        # unloading (rate < 0): the rod extends by what its oil column decompresses
        assert told[i] == pytest.approx(-run.release_rate_n_s[j] / k_oil, rel=1e-12)
        assert told[i] > 0.0


def test_a_receiving_leg_is_judged_against_the_plans_line_to_its_standing_share() -> None:
    seq, x, p = in_transfer("7c")
    run = seq.run
    assert run is not None
    p0 = run.phase.leg_forces_n[0]
    assert np.allclose(run.plan_start_n, p0)
    run.clock_s = 0.5 * run.duration_s
    seq.update(2.0, x, p, set(range(seq.n)))
    line = p0 + 0.5 * (run.target_force_n - p0)
    share8 = seq._share8(float(run.phase.x_s_m[0]))
    for j in MAIN:
        assert seq.figures.expected_n[j] == pytest.approx(max(line[j], share8[j]), rel=1e-12)
    # the plan's own samples end short of the share, where the releasing legs are at
    # unloaded_percent: the line goes on with the ramp, to the share itself
    end = run.phase.leg_forces_n[-1]
    assert np.all(end[list(MAIN)] < run.target_force_n[list(MAIN)])


def test_after_a_resume_the_line_goes_on_from_where_it_stood() -> None:
    seq, x, p = in_transfer("7c")
    run = seq.run
    assert run is not None
    p0 = run.plan_start_n.copy()
    run.clock_s = 0.5 * run.duration_s
    p[seq.legs[MAIN[0]], 0] = 6e6
    seq.resume(x, p)
    assert run.clock_s == 0.0
    assert np.allclose(run.plan_start_n, p0 + 0.5 * (run.target_force_n - p0))
    f = seq.forces_n(p)
    ramp = np.zeros(8)
    assert run.ramp is not None
    ramp[list(MAIN)] = (run.target_force_n - f)[list(MAIN)] / run.ramp.linear_s
    pts = seq.machine.legs_xy(seq.x_s(x))
    a = np.vstack([np.ones(8), pts[:, 1], -pts[:, 0]])
    assert np.abs(a @ (ramp + run.release_rate_n_s)).max() < 1e-3


@pytest.mark.parametrize("key", ["4", "7c"])
def test_the_releasing_references_follow_the_plans_release_not_the_measured_forces(
    key: str,
) -> None:
    """Each releasing reference: its start + (its force at the plan's release rate - its
    start force) / k_contact; a measured force's swing does not move it (docs/walking.md:
    following those rang in 7c). After a resume the release goes on from the forces then."""
    seq, x, p = in_transfer(key)
    run = seq.run
    assert run is not None
    releasing = MAIN if key == "4" else SUB
    run.clock_s = 0.4 * run.duration_s
    p_swing = p.copy()
    p_swing[seq.legs[releasing[0]], 0] = 4e6  # that leg's force measured 20 % lower
    for pp in (p, p_swing):
        seq.update(2.0, x, pp, set(range(seq.n)))
        refs = seq.last_refs
        tau = run.clock_s - PERIOD_S  # the clock went on after the references were set
        for j in releasing:
            i = seq.legs[j]
            assert run.ramp is not None
            released_n = run.release_rate_n_s[j] * run.ramp.linear_s * run.ramp.fraction(tau)
            follow = released_n / seq.k_contact
            assert refs[i] == pytest.approx(x[i] + follow, abs=1e-12)
        run.clock_s = 0.4 * run.duration_s
    seq.resume(x, p_swing)
    assert np.allclose(run.release_from_n, seq.forces_n(p_swing))
    seq.update(3.0, x, p_swing, set(range(seq.n)))
    rel = list(releasing)
    want = run.release_from_n[rel] - run.start_force_n[rel]
    assert run.ramp is not None
    along = run.ramp.linear_s * run.ramp.fraction(run.clock_s - PERIOD_S)
    want = (want + run.release_rate_n_s[rel] * along) / seq.k_contact
    want -= TWIST * float(TWIST @ want) / 4  # not in the twist mode
    assert np.allclose(
        seq.last_refs[[seq.legs[j] for j in rel]],
        x[[seq.legs[j] for j in rel]] + want,
        rtol=0,
        atol=1e-12,
    )


def test_a_force_ramp_starts_and_ends_at_rest_and_runs_at_full_rate_between() -> None:
    """The receiving legs' force references: their rate rises from zero over the blend
    (one period of the slowest leg loop's crossover), runs at ``walking.force_ramp_kn_s``
    (the leg with the largest change), falls to zero at the end; the releasing legs are
    told their decompression at the same share of its rate (docs/walking.md)."""
    seq, x, p = in_transfer("7c")
    run = seq.run
    assert run is not None and run.ramp is not None
    assert run.ramp.blend_s == pytest.approx(seq.ramp_blend_s)
    assert run.ramp.blend_s < run.ramp.linear_s
    full_n_s = seq.walk.force_ramp_n_s
    k_oil = run.k_oil_n_m[SUB[0]]

    def rates_at(t_s: float) -> tuple[float, float]:
        """The receiving legs' largest force-reference rate, N/s, and what the first
        releasing leg's loop is told, m/s, at ``t_s`` on the ramp's clock."""
        run.clock_s = t_s
        seen: dict[int, tuple[float, float]] = {}
        spied = [seq.legs[SUB[0]]] + [seq.legs[j] for j in MAIN]
        for i in spied:
            ctrl = seq.force[i] if i != seq.legs[SUB[0]] else seq.pos[i]

            def spy(
                r: float, y: float, rate: float = 0.0, d: float = 0.0, i: int = i, real=ctrl.update
            ) -> float:
                seen[i] = (rate, d)
                return float(real(r, y, rate, d))

            ctrl.update = spy  # type: ignore[method-assign]
        seq.update(2.0, x, p, set(range(seq.n)))
        for i in spied:
            ctrl = seq.force[i] if i != seq.legs[SUB[0]] else seq.pos[i]
            del ctrl.update  # the instance's spy: the class's method again
        largest = max(abs(seen[seq.legs[j]][0]) for j in MAIN)
        return largest, seen[seq.legs[SUB[0]]][1]

    blend = run.ramp.blend_s
    for t_s, share in [(0.0, 0.0), (blend / 2, 0.5), (blend, 1.0), (run.duration_s / 2, 1.0)]:
        largest, told = rates_at(t_s)
        assert largest == pytest.approx(share * full_n_s, rel=1e-9, abs=1e-6), t_s
        assert told == pytest.approx(-run.release_rate_n_s[SUB[0]] * share / k_oil, abs=1e-15)
    run.clock_s = run.duration_s
    assert run.progress == 1.0 and run.rate_share == 0.0


def test_a_resume_with_the_receiving_legs_at_their_target_ends_the_ramp_at_once() -> None:
    """Stopped at the ramp's end: the receiving legs carry their target, the ramp restarts
    with nothing to move (no rate, no division by its zero length) and is done."""
    seq, x, p = in_transfer("7c")
    run = seq.run
    assert run is not None
    for j in MAIN:
        i = seq.legs[j]
        p[i, 0] = run.target_force_n[j] / seq.cap_area_m2[i]
        p[i, 1] = 0.0
    seq.resume(x, p)
    assert run.ramp is not None and run.ramp.linear_s == pytest.approx(0.0, abs=1e-9)
    seq.update(2.0, x, p, set(range(seq.n)))
    assert run.progress == 1.0


def test_a_lowerings_standing_legs_are_judged_against_their_share_standing_alone() -> None:
    """7a (M lowering, S standing): M's feet landing leave S's legs minimum-norm shares
    below what they carried alone; each S leg is judged against the larger (decision
    0037), never less: a foot pressing outside S's support raises a share, and that one
    is kept."""
    seq, x, p = in_transfer("7a")
    run = seq.run
    assert run is not None and run.phase.key == "7a"
    alone = seq.share(seq.x_s(x), SUB)  # S where it stands at the phase's start
    x_s = float(run.phase.x_s_m[0])
    assert np.allclose(run.standing_share_n, alone)
    assert np.all(alone[list(MAIN)] == 0.0)
    run.touched = [True] * 4  # M's feet on the invert, pressing 3 MPa each
    run.touch_force_n = [1e6] * 4
    p[[seq.legs[j] for j in MAIN], 0] = 3e6
    seq.update(1.0 + PERIOD_S, x, p, set(range(seq.n)))
    share8 = seq._share8(x_s)
    contact = seq.contact_n(seq.forces_n(p) - seq.friction_n())
    min_norm = seq.held_shares.expected_n(seq.machine, x_s, share8, contact, np.zeros(8), list(SUB))
    expected = np.array(seq.figures.expected_n)
    for j in SUB:
        assert expected[j] == pytest.approx(max(min_norm[j], share8[j], alone[j]), rel=1e-9)
    # the floor is what judges here: below it the minimum-norm share of what M leaves
    assert np.any(np.maximum(min_norm, share8)[list(SUB)] < 0.95 * alone[list(SUB)])


def test_the_force_loops_are_told_the_bodys_motion_on_the_holding_frame() -> None:
    """Decision 0041: each force-controlled leg is told ``-k_leg w``, ``w`` the body's
    speed at its foot from the plane of the holding frame's rods (low-passed), from rest
    whenever the holding frame changes or the walk resumes."""
    seq, x, _p = in_transfer("7c")
    receiving = [seq.legs[j] for j in MAIN]
    xy = seq.machine.legs_xy(seq.x_s(x))
    heave_m_s, roll_rad_s = 1e-3, 2e-3  # the holding rods: up, and rolling about x
    told: dict[int, float] = {}
    for k in range(60):  # 0.3 s: 15 time constants of the filter (0.8 ** 59: 2e-6 left)
        t = k * PERIOD_S
        for j in SUB:
            x[seq.legs[j]] = seq.half[seq.legs[j]] + (heave_m_s + roll_rad_s * xy[j, 1]) * t
        told = seq.body_motion_n_s(SUB, x, receiving)
        if k == 0:
            assert told == {i: 0.0 for i in receiving}  # from rest
    for j, i in zip(MAIN, receiving, strict=True):
        w = heave_m_s + roll_rad_s * xy[j, 1]
        assert told[i] == pytest.approx(-seq.leg_k_n_m[i] * w, rel=1e-4)
    # no frame of four holding, or no leg in force control: nothing told, and from rest
    assert seq.body_motion_n_s((4, 5, 6), x, receiving) == {}
    assert seq.body_motion_n_s(SUB, x, []) == {}
    assert seq.body_motion_n_s(SUB, x, receiving) == {i: 0.0 for i in receiving}
