"""The service's attitude controller against the real cylinder model (standalone rods
carrying their static share of the load): it follows a planned trajectory with the two
linked groups synchronized, and leaves every other valve closed."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import pytest

from config import ProjectConfig
from hil_sim.hydraulics import CylinderBank, CylinderParams
from ipc_app.control.attitude import AttitudeController
from ipc_app.planner import Plan, plan


class _Rig(NamedTuple):
    """The controller and the standalone rods of both layers, at rest at mid-stroke in
    equilibrium with the plan's loads; ``x``: the 19 measurements the controller reads."""

    ac: AttitudeController
    idx: list[int]
    bank: CylinderBank
    loads: np.ndarray
    x0: np.ndarray
    x: np.ndarray
    steps: int


def _at_rest(project: ProjectConfig, p: Plan) -> _Rig:
    period = project.control.period_s
    ac = AttitudeController(project, period)
    idx = ac.layers["lower"] + ac.layers["upper"]
    cyls = [project.cylinders_by_can_index[i] for i in idx]
    bank = CylinderBank(CylinderParams.from_config(cyls, project.hydraulics), step_s=0.5e-3)
    loads = np.concatenate([np.array(p.lower.force_n), np.array(p.upper.force_n)])
    x0 = np.array([c.stroke_m / 2 for c in cyls])
    bank.hold_at(x0, loads)  # start at rest in equilibrium with the load
    x = np.zeros(len(project.cylinders))
    x[:] = ac.half_stroke
    x[idx] = bank.x_m
    return _Rig(ac, idx, bank, loads, x0, x, round(period / bank.step_s))


def _follow_example_1(project: ProjectConfig) -> tuple[float, float, float]:
    """(worst sync error after 1 s, worst tracking error, final error) in m."""
    p = plan(project, 2.0, 1.0)
    assert p.feasible and p.trajectory is not None
    period = project.control.period_s
    ac, idx, bank, loads, _x0, x, steps = _at_rest(project, p)
    ac.engage(x, 0.0, p.trajectory)
    t = 0.0
    worst_sync = worst_tracking = 0.0
    duration = p.trajectory.duration_s
    while t < duration + 3.0:
        x[idx] = bank.x_m
        u = ac.update(t, x)
        others = np.setdiff1d(np.arange(len(project.cylinders)), idx)
        assert np.all(u[others] == 0.0)
        assert np.all(np.abs(u) <= 1.0)
        bank.advance_steps(u[idx], loads, steps)
        t += period
        if t > 1.0:
            worst_sync = max(worst_sync, *(m.sync_error_m for m in ac.metrics.values()))
        worst_tracking = max(worst_tracking, *(m.tracking_error_m for m in ac.metrics.values()))
    ref = ac.final_references()
    return worst_sync, worst_tracking, float(np.max(np.abs(bank.x_m - ref[idx])))


@pytest.mark.slow
def test_follows_example_1_synchronized(project: ProjectConfig) -> None:
    assert project.control.ladrc.reference_feedforward  # the shipped tuning
    worst_sync, worst_tracking, final = _follow_example_1(project)
    assert final < 0.5e-3  # at the plan within 0.5 mm
    assert worst_sync < 0.2e-3  # synchronized within 0.2 mm during the whole motion
    # what the feed-forward's nominal b0 misses under load, over wc: the lower group's
    # derived wc 5.5 rad/s (ipc_app.control.tuning) lags 0.53 mm, 6 rad/s lagged 0.49
    assert worst_tracking < 0.6e-3


@pytest.mark.slow
def test_feedforward_cuts_the_tracking_lag(project: ProjectConfig) -> None:
    """Without the trajectory's speeds fed forward the rods lag by speed / wc."""
    plain = project.model_copy(
        update={
            "control": project.control.model_copy(
                update={
                    "ladrc": project.control.ladrc.model_copy(
                        update={"reference_feedforward": False}
                    )
                }
            )
        }
    )
    _, lag_plain, _ = _follow_example_1(plain)
    _, lag_ff, _ = _follow_example_1(project)
    assert lag_plain > 1e-3  # millimetres behind the plan at the top speed
    # the rest is the load: the true valve gain under load is below the nominal b0
    assert lag_ff < 0.4 * lag_plain


def test_layer_metrics_match_the_numpy_definitions(project: ProjectConfig) -> None:
    """update() computes the metrics on plain floats; they equal the array formulas exactly."""
    from ipc_app.model.kinematics import twist

    p = plan(project, -3.0, 2.0)
    assert p.trajectory is not None
    ac = AttitudeController(project, project.control.period_s)
    rng = np.random.default_rng(7)
    x = ac.half_stroke + rng.normal(0.0, 1e-3, ac.n)
    ac.engage(x, 0.0, p.trajectory)
    for k in range(50):
        t = 0.05 * k
        x = ac.half_stroke + rng.normal(0.0, 2e-3, ac.n)
        ac.update(t, x)
        ref = ac.references(t)
        assert ac.last_references is not None
        assert np.array_equal(ac.last_references, ref)
        for name, idx in ac.layers.items():
            m = ac.metrics[name]
            group = ac.groups[name]
            assert m.sync_error_m == float(np.max(np.abs(group.last_sync_error)))
            assert m.twist_m == float(abs(twist(x[idx] - ac.half_stroke[idx])))
            assert m.tracking_error_m == float(np.max(np.abs(ref[idx] - x[idx])))


def _hold_through_a_loss(project: ProjectConfig, warm: bool) -> tuple[float, float]:
    """Rods holding their loads against leakage; the valves closed for 25 ms (a short
    loss of the link: SUSPENDED), then the hold resumed. Returns (the layer's command
    before the loss, the largest deviation from the hold after it) in m."""
    data = project.model_dump(mode="json")
    data["hydraulics"]["cylinder_defaults"]["internal_leakage_m3_s_pa"] *= 3  # worn seals
    leaky = ProjectConfig.model_validate(data)
    period = leaky.control.period_s
    ac, idx, bank, loads, x0, x, steps = _at_rest(leaky, plan(leaky, 0.0, 0.0))
    ac.engage(x, 0.0, None)
    u = np.zeros(len(leaky.cylinders))
    for _ in range(round(6.0 / period)):  # the observers learn the leakage
        x[idx] = bank.x_m
        u = ac.update(0.0, x)
        bank.advance_steps(u[idx], loads, steps)
    held = float(np.max(np.abs(u[idx])))
    for _ in range(5):  # suspended: valves closed, no update
        bank.advance_steps(np.zeros(len(idx)), loads, steps)
    x[idx] = bank.x_m
    if warm:
        ac.resume(x, 0.0)
    else:
        for name, li in ac.layers.items():
            ac.groups[name].reset(x[li])
    worst = 0.0
    for _ in range(round(1.0 / period)):
        x[idx] = bank.x_m
        u = ac.update(0.0, x)
        bank.advance_steps(u[idx], loads, steps)
        worst = max(worst, float(np.max(np.abs(bank.x_m - x0))))
    return held, worst


@pytest.mark.slow
def test_a_hold_resumes_with_the_commands_it_held(project: ProjectConfig) -> None:
    """After a short loss the controllers go on with the command each held (its
    observer's disturbance estimate kept), not from zero: a layer holding its load
    against leakage then does not sink while the observers learn it again."""
    held, warm = _hold_through_a_loss(project, warm=True)
    _, cold = _hold_through_a_loss(project, warm=False)
    assert held > 0.01  # the hold needs the valves open
    assert warm < 0.5 * cold, (warm, cold)


def _move_through_a_loss(project: ProjectConfig, resume: str) -> float:
    """Example 1's motion with the valves closed for 25 ms half-way (SUSPENDED: the
    trajectory clock stands still), then resumed. The largest sync error from 0.1 s
    after the resume on (m)."""
    p = plan(project, 2.0, 1.0)
    assert p.feasible and p.trajectory is not None
    period = project.control.period_s
    ac, idx, bank, loads, _x0, x, steps = _at_rest(project, p)
    ac.engage(x, 0.0, p.trajectory)
    stop = round(0.5 * p.trajectory.duration_s / period)
    for k in range(stop):
        x[idx] = bank.x_m
        bank.advance_steps(ac.update(k * period, x)[idx], loads, steps)
    for _ in range(5):
        bank.advance_steps(np.zeros(len(idx)), loads, steps)
    x[idx] = bank.x_m
    shift = 5 * period
    if resume == "resume":
        ac.resume(x, shift)
    else:  # "cold": from a zero command; "whole": with the whole last command
        ac.t_start += shift
        for name, li in ac.layers.items():
            g = ac.groups[name]
            g.reset(x[li], [c.command for c in g.controllers] if resume == "whole" else None)
    worst = 0.0
    for n, k in enumerate(range(stop + 5, stop + 5 + round(2.0 / period))):
        x[idx] = bank.x_m
        bank.advance_steps(ac.update(k * period, x)[idx], loads, steps)
        if n * period >= 0.1:  # the closure's own error left behind
            worst = max(worst, *(m.sync_error_m for m in ac.metrics.values()))
    return worst


@pytest.mark.slow
def test_a_motion_resumes_without_its_speed_counted_twice(project: ProjectConfig) -> None:
    """The command a motion resumes with is the observers' holding share only: the
    trajectory's speed comes again from the feed-forward (resumed with the whole last
    command, a loaded layer runs ahead by the speed twice: in the campaign, 2 mm sync
    faults). Against a cold restart (zero command) it is 0.11 against 0.08 mm here: the
    observers' estimate mid-motion also holds the valves' gain mismatch at speed."""
    resumed = _move_through_a_loss(project, "resume")
    cold = _move_through_a_loss(project, "cold")
    whole = _move_through_a_loss(project, "whole")
    assert resumed < 0.15e-3 and cold < 0.15e-3, (resumed, cold)  # 2 mm: the interlock
    assert whole > 4 * resumed, (whole, resumed)
