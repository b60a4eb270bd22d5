"""Planners (exact, ldw_pso), trajectory and the ``wara plan`` contract."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from config import ProjectConfig, default_project_path, load_project
from config.schema import LdwPso
from ipc_app.model import extensions, fit_layer
from ipc_app.planner import OBJECTIVES, PlanningProblem, plan
from ipc_app.planner.exact import solve_exact
from ipc_app.planner.ldw_pso import solve_ldw_pso
from ipc_app.planner.reference import dense_search
from wara.cli import main

EXAMPLES = [(2.0, 1.0), (-3.0, 2.0), (5.0, -1.0)]
TARGETS = [*EXAMPLES, (-7.0, -3.5), (10.0, 4.0)]


def _problem(cfg: ProjectConfig, roll: float, pitch: float, obj: str) -> PlanningProblem:
    return PlanningProblem(cfg, math.radians(roll), math.radians(pitch), obj)  # type: ignore[arg-type]


@pytest.mark.parametrize("obj", OBJECTIVES)
@pytest.mark.parametrize(("roll", "pitch"), TARGETS)
def test_exact_equals_dense_search(
    project: ProjectConfig, obj: str, roll: float, pitch: float
) -> None:
    pr = _problem(project, roll, pitch, obj)
    ex = solve_exact(pr, project.planner.exact)
    ds = dense_search(pr)
    assert ex.feasible and ds.feasible
    e, d = float(ex.evaluation.objective), float(ds.evaluation.objective)
    assert abs(e - d) <= 1e-6 * abs(d), (e, d)


@pytest.mark.parametrize("obj", OBJECTIVES)
def test_exact_never_worse_than_ldw_pso(project: ProjectConfig, obj: str) -> None:
    opts = LdwPso(swarm_size=30, iterations=150)
    for roll, pitch in EXAMPLES:
        pr = _problem(project, roll, pitch, obj)
        ex = float(solve_exact(pr, project.planner.exact).evaluation.objective)
        for seed in range(3):
            ps = solve_ldw_pso(pr, opts, seed)
            if ps.feasible:
                assert ex <= float(ps.evaluation.objective) * (1 + 1e-12)


def test_ldw_pso_is_reproducible_with_a_seed(project: ProjectConfig) -> None:
    pr = _problem(project, -3.0, 2.0, "pump_energy")
    opts = LdwPso(swarm_size=20, iterations=60)
    a = solve_ldw_pso(pr, opts, 11)
    b = solve_ldw_pso(pr, opts, 11)
    c = solve_ldw_pso(pr, opts, 12)
    assert (a.d1, a.d2) == (b.d1, b.d2)
    assert (a.d1, a.d2) != (c.d1, c.d2)


def test_ldw_pso_plan_satisfies_linkage(project: ProjectConfig) -> None:
    p = plan(project, 2.0, 1.0, method="ldw_pso", seed=3)
    for lay in (p.upper, p.lower):
        d = lay.displacement_m
        assert d[2] == pytest.approx(-d[0], abs=1e-15) and d[3] == pytest.approx(-d[1], abs=1e-15)


@pytest.mark.parametrize(("roll", "pitch"), EXAMPLES)
def test_examples_are_feasible_and_exact(project: ProjectConfig, roll: float, pitch: float) -> None:
    p = plan(project, roll, pitch)
    assert p.feasible, p.reasons
    assert p.attitude_error_rad <= 1e-9
    assert math.degrees(p.achieved_roll_rad) == pytest.approx(roll, abs=1e-9)
    assert math.degrees(p.achieved_pitch_rad) == pytest.approx(pitch, abs=1e-9)
    lim_u = project.layers.upper.extension_limit_m
    lim_l = project.layers.lower.extension_limit_m
    assert max(abs(x) for x in p.upper.displacement_m) <= lim_u + 1e-12
    assert max(abs(x) for x in p.lower.displacement_m) <= lim_l + 1e-12
    assert min(p.upper.force_n + p.lower.force_n) >= project.planner.min_rod_force_n
    assert p.sum_pressure_pa / 1e6 == pytest.approx(48.5, abs=1.0)  # paper: "system load" ~50 MPa


def test_trajectory_constraints_hold_at_every_sample(project: ProjectConfig) -> None:
    p = plan(project, 5.0, -1.0, objective="sum_pressure")
    tr = p.trajectory
    assert tr is not None and tr.feasible
    lo, up = project.layers.lower, project.layers.upper
    # Start at mid-stroke, end at the plan, all eight together.
    assert np.allclose(tr.d_lower[0], 0.0) and np.allclose(tr.d_upper[0], 0.0)
    assert np.allclose(tr.d_lower[-1], p.lower.displacement_m, atol=1e-12)
    assert np.allclose(tr.d_upper[-1], p.upper.displacement_m, atol=1e-12)
    # Linkage at every sample and strokes within the planning limits.
    for d, lim in ((tr.d_lower, lo.extension_limit_m), (tr.d_upper, up.extension_limit_m)):
        assert np.allclose(d[:, 2], -d[:, 0], atol=1e-15)
        assert np.allclose(d[:, 3], -d[:, 1], atol=1e-15)
        assert np.max(np.abs(d)) <= lim + 1e-12
    # Speed limit from the samples (finite differences), and zero speed at both ends.
    d = np.concatenate([tr.d_lower, tr.d_upper], axis=1)
    v = np.diff(d, axis=0) / np.diff(tr.t)[:, None]
    vmax = project.planner.trajectory.max_rod_speed_m_s
    assert np.max(np.abs(v)) <= vmax * 1.001
    assert np.max(np.abs(v)) >= 0.5 * vmax  # the duration is not padded needlessly
    for k in (0, -1):
        _, _, vl, vu = tr.reference(float(tr.t[k]))
        assert np.max(np.abs(np.concatenate([vl, vu]))) < 1e-9
    # positions() is reference() without the velocities, bit for bit (the loop uses it).
    for t in (-1.0, 0.0, 0.37, float(tr.t[len(tr.t) // 3]), tr.duration_s, tr.duration_s + 1):
        dl, du, _, _ = tr.reference(t)
        pl, pu = tr.positions(t)
        assert np.array_equal(dl, pl) and np.array_equal(du, pu)
    # Every sample satisfies the statics constraints.
    pr = PlanningProblem(project, p.target_roll_rad, p.target_pitch_rad, "sum_pressure")
    for k in range(0, tr.t.size, 10):
        fl = fit_layer(tr.d_lower[k], lo.a_m, lo.b_m)
        fu = fit_layer(tr.d_upper[k], up.a_m, up.b_m)
        ev = pr.evaluate_attitudes(fl.roll, fl.pitch, fu.roll, fu.pitch)
        assert bool(ev.feasible)


def test_twisted_start_is_reproduced_then_removed(project: ProjectConfig) -> None:
    up = project.layers.upper
    start_u = np.array(extensions(0.01, 0.0, up.a_m, up.b_m, 0.002)) + 2e-5 * np.array(
        [1, -1, 1, -1]
    )
    p = plan(project, 2.0, 1.0, start_upper_m=start_u)
    assert p.feasible, p.reasons
    tr = p.trajectory
    assert tr is not None
    assert np.allclose(tr.d_upper[0], start_u, atol=1e-15)
    assert float(fit_layer(tr.d_upper[-1], up.a_m, up.b_m).twist) == pytest.approx(0, abs=1e-15)


def test_start_beyond_coplanarity_is_refused(project: ProjectConfig) -> None:
    start_u = 1e-3 * np.array([1, -1, 1, -1])  # 1 mm twist: point 4 is 4 mm off the plane
    p = plan(project, 2.0, 1.0, start_upper_m=start_u)
    assert not p.feasible
    assert any("coplanarity" in r and "t = 0.00 s" in r for r in p.reasons)


def test_start_affects_pump_energy(project: ProjectConfig) -> None:
    level = plan(project, -3.0, 2.0)
    up = project.layers.upper
    near = extensions(math.radians(-3.0), math.radians(1.83), up.a_m, up.b_m)
    moved = plan(project, -3.0, 2.0, start_upper_m=near)
    assert moved.objective_value < 0.2 * level.objective_value


def _run(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wara", "plan", *args], capture_output=True, text=True, check=False
    )


@pytest.mark.slow
def test_cli_json_contract() -> None:
    proc = _run("--roll-deg", "-3", "--pitch-deg", "2", "--json")
    assert proc.returncode == 0, proc.stderr
    d = json.loads(proc.stdout)
    for key in (
        "feasible",
        "method",
        "objective",
        "objective_value",
        "sum_pressure_mpa",
        "peak_pressure_mpa",
        "attitude_error_rad",
        "yaw_residual_deg",
        "trajectory_duration_s",
        "solve_time_s",
    ):
        assert key in d
    for layer in ("upper", "lower"):
        assert set(d[layer]) >= {"roll_deg", "pitch_deg", "displacement_m"}
        assert len(d[layer]["displacement_m"]) == 4
        assert len(d["pressure_mpa"][layer]) == 4
    assert d["method"] == "exact" and d["objective"] == "pump_energy"


@pytest.mark.slow
def test_cli_unreachable_target_exits_3_with_reasons() -> None:
    proc = _run("--roll-deg", "30", "--pitch-deg", "2", "--json")
    assert proc.returncode == 3
    d = json.loads(proc.stdout)
    assert d["feasible"] is False
    assert any("stroke: lower cylinder" in r and "main_leg" in r for r in d["reasons"])


def test_lift_off_is_reported(tmp_path: Path) -> None:
    data = yaml.safe_load(default_project_path().read_text())
    data["layers"]["upper"]["bodies"][0]["cog_m"] = [0.0, 1.6, 1.2]  # beyond the cylinders
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    p = plan(load_project(path), -2.0, 0.0)
    assert not p.feasible
    assert any(r.startswith("lift-off: upper cylinder") for r in p.reasons), p.reasons


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--roll-deg", "1", "--pitch-deg", "1", "--start-upper-mm", "1,2,3"], "four"),
        (["--roll-deg", "x", "--pitch-deg", "1"], "'x' is not a number"),
        (["--roll-deg", "95", "--pitch-deg", "1"], "within"),
        (["--roll-deg", "1", "--pitch-deg", "1", "--objective", "speed"], "invalid choice"),
        (["--pitch-deg", "1"], "required"),
    ],
)
def test_cli_bad_arguments_exit_2_with_one_line(args: list[str], message: str) -> None:
    proc = _run(*args)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1


def test_cli_table(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["plan", "--roll-deg", "2", "--pitch-deg", "1"]) == 0
    out = capsys.readouterr().out
    assert "FEASIBLE" in out and "upper" in out and "trajectory duration" in out


@pytest.mark.parametrize("profile", ["quintic", "trapezoidal"])
def test_the_loops_sample_is_the_planned_and_checked_trajectory(
    project: ProjectConfig, profile: str
) -> None:
    """The reference definition is what the planner checked against the constraints: the
    samples ``d_lower``/``d_upper`` at ``t``, computed on arrays. The loop's per-cycle
    ``sample`` (plain floats) gives those positions, and its velocity is their time
    derivative."""
    from dataclasses import replace

    from ipc_app.planner.trajectory import time_scaling, time_scaling_at

    for tau in np.linspace(-0.01, 1.01, 2_001).tolist():
        s_np, ds_np, _ = time_scaling(profile, np.asarray(tau))
        assert time_scaling_at(profile, tau) == pytest.approx(
            (float(s_np), float(ds_np)), abs=1e-15
        )

    twisted_start = {"start_lower_m": (0.0004, -0.0003, -0.0002, 0.0006)}
    cases = [((2.0, 1.0), {}), ((-3.0, 2.0), {}), ((5.0, -1.0), twisted_start)]
    for (roll, pitch), start in cases:
        planned = plan(project, roll, pitch, **start).trajectory  # type: ignore[arg-type]
        assert planned is not None
        assert planned.lower.twist0 != 0.0 or not start  # the twist/heave terms are exercised
        # Re-sampled with the profile under test: the checked samples of that profile.
        s_t, _, _ = time_scaling(profile, planned.t / planned.duration_s)
        _, _, want_l = planned.lower.at(s_t)
        _, _, want_u = planned.upper.at(s_t)
        tr = replace(planned, profile=profile)
        for k in range(0, tr.t.size, 7):
            t = float(tr.t[k])
            dl, du, vl, vu = tr.sample(t)
            np.testing.assert_allclose(dl, want_l[k], rtol=0, atol=1e-15)
            np.testing.assert_allclose(du, want_u[k], rtol=0, atol=1e-15)
            assert (dl, du) == tr.positions(t)
            h = 1e-4  # s: the velocity is the derivative of the positions
            before, after = tr.positions(t - h), tr.positions(t + h)
            for v, a, b in ((vl, before[0], after[0]), (vu, before[1], after[1])):
                num = (np.array(b) - np.array(a)) / (2 * h)
                np.testing.assert_allclose(v, num, rtol=0, atol=2e-6)


def test_a_plan_starts_from_rods_in_the_stroke_reserve_and_comes_back(
    project: ProjectConfig,
) -> None:
    """A plan that ends at the planning limit leaves the rods there within micrometres, or
    a hold settles a little past it: the next plan starts from there and never goes
    deeper into the reserve; it ends within the limit. A start beyond the stroke itself
    (a sensor reading no rod can give) is refused with the stroke reason."""
    first = plan(project, 0.19, 3.6)
    second = plan(
        project,
        -5.69,
        3.59,
        start_upper_m=first.upper.displacement_m,
        start_lower_m=first.lower.displacement_m,
    )
    lim = project.layers.upper.extension_limit_m
    half = project.cylinder(project.layers.upper.cylinders[0]).stroke_m / 2
    end = np.asarray(second.upper.displacement_m, dtype=float)
    at_limit = np.isclose(np.abs(end), lim, rtol=0, atol=1e-9)
    assert second.feasible and at_limit.any()
    for beyond_m in (5e-6, 1e-3, 0.5 * (half - lim)):
        start = np.where(at_limit, end + np.sign(end) * beyond_m, end)
        for roll, pitch in ((0.5, 0.5), (0.0, 0.0), (-5.69, 3.59)):
            nxt = plan(
                project,
                roll,
                pitch,
                start_upper_m=start,
                start_lower_m=second.lower.displacement_m,
            )
            assert nxt.feasible, (beyond_m, roll, pitch, nxt.reasons)
            tr = nxt.trajectory
            assert tr is not None
            depth = np.abs(tr.d_upper).max(axis=0)
            assert np.all(depth <= np.maximum(np.abs(start), lim) + 1e-12)
            assert np.all(np.abs(tr.d_upper[-1]) <= lim + 1e-12)
    start = np.where(at_limit, np.sign(end) * (half + 1e-3), end)
    refused = plan(
        project, 0.0, 0.0, start_upper_m=start, start_lower_m=second.lower.displacement_m
    )
    assert not refused.feasible
    assert any("stroke:" in r and "planning limit" in r for r in refused.reasons)
