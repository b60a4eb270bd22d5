"""Configuration: the shipped project carries the reference values; every error path
names the file, the key path, the value and what was expected."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from config import ConfigError, ProjectConfig, default_project_path, load_project
from wara.cli import main


def _shipped() -> dict[str, Any]:
    data = yaml.safe_load(default_project_path().read_text())
    assert isinstance(data, dict)
    return data


def _write(tmp_path: Path, data: Any) -> Path:
    p = tmp_path / "project.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_shipped_project_carries_reference_values(project: ProjectConfig) -> None:
    assert project.base.pitch_deg == pytest.approx(0.17)
    lo, up = project.layers.lower, project.layers.upper
    assert (lo.half_span_x_m, lo.half_span_y_m, up.half_span_x_m, up.half_span_y_m) == (
        2.8,
        1.4,
        1.6,
        1.2,
    )
    assert (lo.stroke_mm, up.stroke_mm, lo.reserve_mm, up.reserve_mm) == (800, 300, 20, 10)
    assert lo.bore_mm == up.bore_mm == 160 and lo.rod_mm == up.rod_mm == 110
    assert up.origin_in_lower_m == (0.0, 0.0, 0.9)
    masses = {b.name: (b.mass_kg, b.cog_m) for b in up.bodies}
    assert masses["workpiece"] == (36350, (0.0, 0.15, 1.2))
    assert masses["fine-tuning platform"] == (6000, (0.0, 0.0, 0.15))
    assert [(b.mass_kg, b.cog_m) for b in lo.bodies] == [(15000, (0.0, 0.0, 0.5))]
    assert project.planner.min_rod_force_n == pytest.approx(5000)
    assert project.hydraulics.rated_pressure_pa == pytest.approx(25e6)
    assert project.hydraulics.load_sensing_margin_pa == pytest.approx(1.5e6)
    assert project.hydraulics.supply_pressure_pa == pytest.approx(16e6)
    assert project.planner.coplanarity_tolerance_m == pytest.approx(0.5e-3)
    assert project.acceptance.vertical_misalignment_mm == 8
    assert project.acceptance.pitch_angle_deg is None  # lost in the paper: no fake default
    assert len(project.cylinders) == 19
    assert sorted(c.can_index for c in project.cylinders) == list(range(19))


def test_units_are_si(project: ProjectConfig) -> None:
    assert project.layers.lower.extension_limit_m == pytest.approx(0.38)
    assert project.layers.upper.extension_limit_m == pytest.approx(0.14)
    assert project.layers.upper.cap_area_m2 == pytest.approx(0.0201061929)


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["layers"]["upper"].update(strok_mm=300), "layers.upper.strok_mm: unknown key"),
        (
            lambda d: d["layers"]["lower"].update(bore_mm=-160),
            "layers.lower.bore_mm: got -160: expected input should be greater than 0",
        ),
        (
            lambda d: d["layers"]["upper"].update(reserve_mm=160),
            "layers.upper: reserve_mm (160.0) must be smaller than half the stroke (150.0 mm)",
        ),
        (
            lambda d: d["cylinders"][1].update(id="main_leg_1"),
            "duplicate cylinder id(s): main_leg_1",
        ),
        (lambda d: d["cylinders"][1].update(can_index=0), "duplicate cylinder can_index(es): [0]"),
        (
            lambda d: d["hydraulics"].pop("supply_pressure_mpa"),
            "hydraulics.supply_pressure_mpa: missing required key",
        ),
        (
            lambda d: d["planner"].update(objective="min_pressure"),
            "planner.objective: got 'min_pressure': expected input should be 'sum_pressure', "
            "'peak_pressure' or 'pump_energy'",
        ),
        (
            lambda d: d["base"].update(pitch_deg="steep"),
            "base.pitch_deg: got 'steep': expected input should be a valid number",
        ),
        (
            lambda d: d["layers"]["upper"].update(cylinders=["upper_1", "upper_2", "upper_3", "x"]),
            "layers.upper.cylinders: unknown cylinder id 'x'",
        ),
        (lambda d: d["cylinders"].pop(), "the machine has 19 cylinders"),
    ],
)
def test_config_errors_name_file_key_value_and_expectation(
    tmp_path: Path, mutate: Any, expected: str
) -> None:
    data = _shipped()
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_project(path)
    msg = str(err.value)
    assert str(path) in msg
    assert expected in msg


def test_yaml_syntax_error_names_line(tmp_path: Path) -> None:
    p = tmp_path / "bad.yaml"
    p.write_text("project:\n  name: [unclosed\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: YAML syntax error at line \d+"):
        load_project(p)


def test_missing_file(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_project(tmp_path / "nope.yaml")


@pytest.mark.slow
def test_cli_validate_ok_and_error_without_traceback(tmp_path: Path) -> None:
    assert main(["config", "validate", str(default_project_path())]) == 0
    data = _shipped()
    data["layers"]["lower"]["bore_mm"] = -1
    path = _write(tmp_path, data)
    proc = subprocess.run(
        [sys.executable, "-m", "wara", "config", "validate", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    assert "layers.lower.bore_mm: got -1" in proc.stderr


def test_cli_show_round_trips(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["config", "show"]) == 0
    out = capsys.readouterr().out
    path = tmp_path / "shown.yaml"
    path.write_text(out)
    assert load_project(path) == load_project()


def test_shipped_project_carries_the_walking_values(project: ProjectConfig) -> None:
    """walking.md section 6."""
    frames, walk = project.frames, project.walking
    assert frames is not None and walk is not None
    assert (frames.sub.a_m, frames.sub.b_m) == (1.9, 0.95)
    assert [(b.mass_kg, b.cog_m) for b in frames.main.bodies] == [(6000, (0.0, 0.0, 0.3))]
    assert [(b.mass_kg, b.cog_m) for b in frames.sub.bodies] == [(8000, (0.0, 0.0, 0.4))]
    robot = (
        sum(b.mass_kg for b in project.layers.lower.bodies)
        + sum(b.mass_kg for b in project.layers.upper.bodies if b.name != "workpiece")
        + sum(b.mass_kg for b in frames.main.bodies + frames.sub.bodies)
    )
    assert robot == project.robot.mass_kg == 35000
    assert walk.step_length_m == pytest.approx(2.0)
    assert walk.clearance_m == pytest.approx(0.05)
    assert walk.travel_reserve_m == pytest.approx(0.05)
    assert walk.travel_speed_m_s == pytest.approx(0.05)
    assert (walk.preload_percent, walk.unloaded_percent) == (20, 5)
    assert walk.min_stability_margin_m == 0.25
    assert walk.foot_friction_coefficient == 0.4
    assert (walk.contact.stiffness_n_m, walk.contact.damping_ratio) == (2e8, 0.7)
    assert project.cylinder("travel_1").stroke_mm == 2200


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (
            lambda d: d["walking"].update(step_length_mm=2150),
            "walking.step_length_mm (2150.0) must fit in the travel stroke less both "
            "reserves (2100.0 mm)",
        ),
        (lambda d: d.pop("frames"), "frames and walking go together"),
        (
            lambda d: d["walking"].update(min_stability_margin_m=-0.25),
            "walking.min_stability_margin_m: got -0.25: expected input should be greater than 0",
        ),
        (
            lambda d: d["walking"]["contact"].update(stiffness_n_m=".inf"),
            "walking.contact.stiffness_n_m: got '.inf'",
        ),
        (
            lambda d: d["walking"].update(foot_friction_coefficient=4),
            "walking.foot_friction_coefficient: got 4: expected input should be less than "
            "or equal to 2",
        ),
        (lambda d: d["frames"]["sub"].update(half_span_z_m=1), "frames.sub.half_span_z_m: unknown"),
        (lambda d: d["frames"]["sub"].pop("half_span_x_m"), "frames.sub.half_span_x_m: missing"),
    ],
)
def test_walking_config_errors(tmp_path: Path, mutate: Any, expected: str) -> None:
    data = _shipped()
    mutate(data)
    path = _write(tmp_path, data)
    with pytest.raises(ConfigError) as err:
        load_project(path)
    assert expected in str(err.value)


def test_a_project_without_walking_sections_loads(tmp_path: Path) -> None:
    data = _shipped()
    data.pop("frames")
    data.pop("walking")
    data["cycle"]["walk_steps"] = 0  # its ring cycles stand at the ring
    cfg = load_project(_write(tmp_path, data))
    assert cfg.frames is None and cfg.walking is None
