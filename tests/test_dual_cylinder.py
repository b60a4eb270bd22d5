"""The paper's dual-cylinder study end to end: scenario, closed loop, CLI, goals, bench."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from config import ConfigError
from config.scenario import load_scenario, scenario_path
from wara.cli import main
from wara.studies.dual_cylinder import (
    evaluate,
    last_move_end_s,
    quintic_waypoints,
    run_study,
    settling_time_s,
)


def test_shipped_scenario_carries_paper_table_3() -> None:
    sc = load_scenario()
    hc1, hc2 = (c.cylinder for c in sc.cylinders)
    assert (hc1.bore_mm, hc2.bore_mm) == (160, 164)
    assert (hc1.stroke_mm, hc2.stroke_mm) == (800, 800)
    assert hc1.plant is not None and hc2.plant is not None
    assert (hc1.plant.internal_leakage_m3_s_pa, hc2.plant.internal_leakage_m3_s_pa) == (
        7.2e-12,
        7.5e-12,
    )
    assert (hc1.plant.area_gradient_mm, hc2.plant.area_gradient_mm) == (26, 24)
    assert (hc1.plant.damping_ratio, hc2.plant.damping_ratio) == (0.65, 0.67)
    h = sc.hydraulics
    assert (h.oil_density_kg_m3, h.bulk_modulus_mpa, h.supply_pressure_mpa) == (850, 700, 16)
    assert sc.noise is not None and sc.noise.start_s == 80
    assert sc.control.rate_hz == 1000
    assert sc.cylinders[0].load_force_kn != sc.cylinders[1].load_force_kn
    peak = max(p for _, p in sc.reference.waypoints)
    assert 380 <= peak <= 420


def test_scenario_errors_name_the_key(tmp_path: Path) -> None:
    text = scenario_path("dual_cylinder").read_text()
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("plant_step_ms: 0.5", "plant_step_ms: 0.5\nplant_stepp: 1"))
    with pytest.raises(ConfigError, match=r"bad.yaml: plant_stepp: unknown key"):
        load_scenario(bad)
    bad.write_text(text.replace("plant_step_ms: 0.5", "plant_step_ms: 0.3"))
    with pytest.raises(ConfigError, match="whole number of plant steps"):
        load_scenario(bad)
    bad.write_text(text.replace("[40, 400]", "[40, 900]"))
    with pytest.raises(ConfigError, match="outside the stroke"):
        load_scenario(bad)


def test_reference_blends_between_waypoints() -> None:
    wps = ((0.0, 10.0), (5.0, 10.0), (15.0, 110.0))
    t = np.array([0.0, 5.0, 10.0, 15.0, 20.0])
    np.testing.assert_allclose(quintic_waypoints(wps, t), [10, 10, 60, 110, 110])
    # rest at the waypoints: zero slope
    eps = 1e-6
    slope = np.diff(quintic_waypoints(wps, np.array([15.0 - eps, 15.0]))) / eps
    assert abs(slope[0]) < 1e-6


@pytest.fixture(scope="module")
def short_runs() -> dict:
    sc = load_scenario()
    return {k: run_study(sc, k, duration_s=25.0) for k in ("ladrc", "pid")}


@pytest.mark.slow
def test_closed_loop_tracks_and_is_reproducible(short_runs: dict) -> None:
    sc = load_scenario()
    run = short_runs["ladrc"]
    again = run_study(sc, "ladrc", duration_s=25.0)
    np.testing.assert_array_equal(run.position_m, again.position_m)
    assert run.position_m.shape == (25_000, 2)
    # it moves with the reference (20 mm at 8.7 s ... ) and stays within a few mm
    assert np.max(np.abs(run.reference_m - run.position_m)) < 3e-3
    assert run.position_m[-1, 0] > 0.1
    assert np.max(np.abs(run.command)) <= 1.0


@pytest.mark.slow
def test_report_fields_and_windows(short_runs: dict) -> None:
    sc = load_scenario()
    report, _ = evaluate(short_runs, sc)
    lad = report["controllers"]["ladrc"]
    for key in (
        "sync_error_max_mm",
        "sync_error_rms_mm",
        "tracking_error_rms_mm",
        "settling_time_s",
        "realtime_factor",
    ):
        assert key in lad
    assert report["windows_s"] == {"after_transient": [10.0, 25.0]}  # noise starts at 80 s
    assert lad["sync_error_max_mm"] >= lad["sync_error_rms_mm"] > 0
    assert "pid_to_ladrc_sync_error_max_ratio" in report


@pytest.mark.slow
def test_settling_time_is_measured_after_the_last_move(short_runs: dict) -> None:
    sc = load_scenario()
    assert last_move_end_s(sc) == 100.0
    assert settling_time_s(short_runs["ladrc"], sc) is None  # the run ends before 100 s


def test_cli_usage_errors(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim", "dual-cylinder", "--duration-s", "5", "--quiet"]) == 2
    assert "initial transient" in capsys.readouterr().err
    assert main(["sim", "dual-cylinder", "--plot", "/nonexistent/dir/x.png", "--quiet"]) == 2


@pytest.mark.slow
def test_cli_short_study_json_and_plot(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    png = tmp_path / "study.png"
    code = main(["sim", "dual-cylinder", "--duration-s", "15", "--json", "--plot", str(png)])
    out, err = capsys.readouterr()
    report = json.loads(out)
    assert set(report["controllers"]) == {"ladrc", "pid"}
    assert code == (0 if report["goals_met"] else 1)
    assert "100%" in err  # progress indicator
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert png.stat().st_size > 50_000


@pytest.mark.slow
def test_paper_goals_on_the_full_study(capsys: pytest.CaptureFixture[str]) -> None:
    """The issue's goals, measured the way the CLI measures them (the full 120 s)."""
    code = main(["sim", "dual-cylinder", "--json", "--quiet"])
    report = json.loads(capsys.readouterr().out)
    lad = report["controllers"]["ladrc"]
    pid = report["controllers"]["pid"]
    assert lad["sync_error_max_mm"] <= 0.07  # the paper's accuracy, noise included
    assert lad["sync_error_max_mm_after_noise"] <= 0.07
    assert pid["sync_error_max_mm"] > 1.5 * lad["sync_error_max_mm"]
    assert report["pid_to_ladrc_sync_error_max_ratio"] == pytest.approx(
        pid["sync_error_max_mm"] / lad["sync_error_max_mm"]
    )
    assert report["goals_met"] is True
    assert code == 0


@pytest.mark.slow
def test_bench_sim_reports_the_realtime_factor(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "sim", "--json", "--quick"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["bench"] == "sim"
    assert result["study_duration_s"] == 20.0
    assert result["realtime_factor"] == pytest.approx(40.0 / result["wall_s"])
    assert result["goal_min_realtime_factor"] == 20.0
    assert set(result["realtime_factor_per_controller"]) == {"ladrc", "pid"}
