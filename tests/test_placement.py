"""Placement in six degrees of freedom: config, geometry, survey fit, target planner and
the ``wara place`` / ``wara survey`` commands (docs/placement.md)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from config import ConfigError, ProjectConfig, default_project_path, load_project, units
from config.schema import Alignment
from ipc_app.model.placement import (
    Pose,
    axis_pose,
    compose,
    design_pose,
    deviation,
    fit_pose,
    joint_figures,
    six_dof_extensions,
    to_ring_frame,
    yaw_of_pair,
)
from ipc_app.planner.placement import check_moves, home_pose, plan_from_deviation, plan_target
from ipc_app.planner.survey import SurveyError, fit_survey, format_survey, parse_survey_text
from tests.cli_helpers import run_main

FACES = [(4.0, 0.3), (-4.0, 0.3), (3.5, 2.5), (-3.5, 2.5), (0.0, 1.4)]


def _shipped() -> dict[str, Any]:
    data = yaml.safe_load(default_project_path().read_text())
    assert isinstance(data, dict)
    return data


def _write(tmp_path: Path, data: Any) -> Path:
    p = tmp_path / "project.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


# --------------------------------------------------------------------------- config


def test_shipped_project_carries_the_placement_values(project: ProjectConfig) -> None:
    pl = project.placement
    assert pl is not None and project.tunnel.alignment is not None
    assert pl.rotation_lever_arm_m == 1.5
    assert pl.target_gap_mm == 5
    assert (pl.max_correction_per_ring_mm, pl.max_correction_per_ring_deg) == (2, 0.05)
    assert project.tunnel.alignment.gradient_percent == -0.3
    # the design axis of the reference project is the base pitch of model.md (a positive
    # pitch turns x down: the axis falls along the chainage)
    assert units.to_deg(math.atan(0.003)) == pytest.approx(project.base.pitch_deg, abs=0.002)
    home = home_pose(project, 5)
    assert abs(units.to_deg(home.pitch)) < 0.002 and home.roll == 0.0
    for role in ("rotation", "lateral", "central_axis"):
        assert {c.stroke_mm for c in project.cylinders if c.role == role} == {200}


@pytest.mark.parametrize(
    ("mutate", "expected"),
    [
        (lambda d: d["placement"].update(lever_arm_m=1.5), "placement.lever_arm_m"),
        (lambda d: d["placement"].update(target_gap_mm=-1), "placement.target_gap_mm"),
        (lambda d: d["placement"]["weights"].update(speed=1), "placement.weights.speed"),
        (lambda d: d["tunnel"].pop("alignment"), "placement needs the design axis"),
        (
            lambda d: d["tunnel"]["alignment"].update(
                points=[{"chainage_m": 0, "x_m": 0, "y_m": 0, "z_m": 0}] * 2
            ),
            "either gradient_percent",
        ),
        (
            lambda d: d["tunnel"]["alignment"].update(
                gradient_percent=None,
                points=[
                    {"chainage_m": 10, "x_m": 0, "y_m": 0, "z_m": 0},
                    {"chainage_m": 5, "x_m": 5, "y_m": 0, "z_m": 0},
                ],
            ),
            "chainage_m must increase",
        ),
    ],
)
def test_placement_config_errors(tmp_path: Path, mutate: Any, expected: str) -> None:
    data = _shipped()
    mutate(data)
    with pytest.raises(ConfigError, match=expected):
        load_project(_write(tmp_path, data))


def test_a_project_without_placement_loads_and_the_commands_say_so(tmp_path: Path) -> None:
    data = _shipped()
    data.pop("placement")
    data.pop("cycle")  # the ring cycle needs the placement
    path = _write(tmp_path, data)
    assert load_project(path).placement is None
    code, _, err = run_main(["place", "plan", "--config", str(path)])
    assert code == 2 and "no placement section" in err


# --------------------------------------------------------------------------- geometry


def test_axis_frames_of_a_table_and_ring_frames_round_trip() -> None:
    table = Alignment(
        points=(
            {"chainage_m": 0, "x_m": 0, "y_m": 0, "z_m": 0},  # type: ignore[arg-type]
            {"chainage_m": 100, "x_m": 99.0, "y_m": 14.0, "z_m": 0.3},  # type: ignore[arg-type]
        )
    )
    f = axis_pose(table, 50.0)
    assert f.position == pytest.approx([49.5, 7.0, 0.15])
    assert f.yaw == pytest.approx(math.atan2(14.0, 99.0))
    cfg = load_project()
    p = Pose(0.3, 0.004, -6.2, 0.001, -0.002, 0.003)
    back = to_ring_frame(cfg, to_ring_frame(cfg, p, 4, 9), 9, 4)
    assert np.allclose(back, p, atol=1e-12)
    assert to_ring_frame(cfg, design_pose(cfg, 4), 4, 5).x == pytest.approx(-1.0)


def test_fit_pose_recovers_a_pose_and_refuses_points_on_a_line() -> None:
    rng = np.random.default_rng(3)
    truth = Pose(1.2, -0.3, 0.05, 0.01, -0.02, 0.03)
    pts = rng.uniform(-3, 3, (6, 3))
    fit = fit_pose(pts, truth.apply(pts))
    assert np.allclose(fit.pose, truth, atol=1e-12) and fit.rms_residual_m < 1e-12
    line = np.outer(np.arange(5.0), [1.0, 2.0, 0.5])
    with pytest.raises(ValueError, match="one line"):
        fit_pose(line, line)


def test_six_dof_extensions_follow_the_pair_models() -> None:
    ext = six_dof_extensions(Pose(0.01, -0.02, 0.03, 0.0, 0.0, 0.002), 1.5)
    assert ext.central_axis == 0.01 and ext.lateral == (-0.02, -0.02) and ext.heave == 0.03
    assert ext.rotation[0] == -ext.rotation[1] == pytest.approx(1.5 * math.sin(0.002))
    assert yaw_of_pair(*ext.rotation, 1.5) == pytest.approx(0.002)


def test_joint_figures_of_a_shifted_and_turned_part(project: ProjectConfig) -> None:
    d = design_pose(project, 5)
    prev = to_ring_frame(project, design_pose(project, 4), 4, 5)
    new = compose(d, Pose(0.005, 0.003, -0.002))
    f = joint_figures(project, prev, new, d).to_dict()
    assert f["horizontal_misalignment_mm"] == pytest.approx(3.0)
    assert f["vertical_misalignment_mm"] == pytest.approx(-2.0)
    assert f["max_gap_mm"] == pytest.approx(5.0) and f["min_gap_mm"] == pytest.approx(5.0)
    assert f["centreline_deviation_x_mm"] == pytest.approx(3.0)
    yawed = compose(d, Pose(0.005, 0.0, 0.0, 0.0, 0.0, units.deg(0.05)))
    g = joint_figures(project, prev, yawed, d).to_dict()
    spread = project.workpiece.length_m * math.sin(units.deg(0.05))
    assert g["max_gap_mm"] - g["min_gap_mm"] == pytest.approx(units.to_mm(spread), rel=1e-6)
    assert g["rotation_angle_deg"] == pytest.approx(0.05)


# --------------------------------------------------------------------------- the planner


def test_on_a_part_on_its_design_the_target_is_the_design(project: ProjectConfig) -> None:
    p = plan_from_deviation(project, 5, Pose())
    assert p.feasible and p.binding is None
    dev = deviation(p.target, p.design)
    assert max(abs(v) for v in dev[1:3]) < 1e-9 and max(abs(v) for v in dev[3:]) < 1e-9
    f = p.figures.to_dict()
    assert f["max_gap_mm"] == pytest.approx(5.0, abs=1e-6)
    assert abs(f["vertical_misalignment_mm"]) < 1e-6


def test_steering_back_from_6_mm_at_the_bound_per_ring(project: ProjectConfig) -> None:
    dev = Pose(y=units.mm(6.0), z=units.mm(-6.0))
    devs = [dev]
    for ring in range(2, 9):
        p = plan_from_deviation(project, ring, devs[-1])
        assert p.feasible, p.reasons
        nxt = deviation(p.target, p.design)
        for a, b in ((devs[-1].y, nxt.y), (devs[-1].z, nxt.z)):
            assert abs(units.to_mm(b - a)) <= 2.0 + 1e-6
        assert all(item["passed"] for item in p.judged.values() if item["passed"] is not None)
        devs.append(Pose(0.0, nxt.y, nxt.z, nxt.roll, nxt.pitch, nxt.yaw))
    # full correction first (6 -> 4 -> 2), then closer than 1 mm
    assert units.to_mm(devs[1].y) == pytest.approx(4.0, abs=1e-3)
    assert units.to_mm(devs[2].y) == pytest.approx(2.0, abs=1e-3)
    assert max(abs(units.to_mm(d.y)) for d in devs[4:]) <= 1.0
    assert max(abs(units.to_mm(d.z)) for d in devs[4:]) <= 1.0


def test_an_unreachable_target_names_the_binding_limit(project: ProjectConfig) -> None:
    p = plan_from_deviation(project, 3, Pose(y=units.mm(9.0)))
    assert not p.feasible and p.binding is not None
    assert p.binding.name == "centreline_deviation_x_mm"
    assert p.binding.excess == pytest.approx(2.0, abs=1e-3)
    assert "exceeded by 2.000" in p.reasons[0]


def test_moves_are_checked_against_the_strokes(project: ProjectConfig) -> None:
    d = design_pose(project, 5)
    checks, _ = check_moves(project, 5, compose(d, Pose(0.0, 0.12, 0.0)))
    lateral = next(c for c in checks if c.group == "lateral")
    assert lateral.reasons and "lateral_1 extension +120.0 mm" in lateral.reasons[0]
    checks, _ = check_moves(project, 5, compose(d, Pose(z=0.5)))
    lower = checks[0]
    assert any("main_leg_1" in r for r in lower.reasons)


# --------------------------------------------------------------------------- the survey


def _survey(project: ProjectConfig, ring: int, pose: Pose) -> str:
    return format_survey(project, ring, pose, FACES)


def test_the_survey_fit_recovers_the_as_built_pose(project: ProjectConfig) -> None:
    truth = compose(design_pose(project, 4), Pose(0.003, 0.006, -0.002, 4e-4, 2e-4, -3e-4))
    fit = fit_survey(project, 4, parse_survey_text(_survey(project, 4, truth)))
    assert fit.accepted
    assert units.to_mm(float(np.max(np.abs(fit.pose.position - truth.position)))) < 0.2
    assert units.to_deg(abs(fit.pose.yaw - truth.yaw)) < 0.005
    assert units.to_mm(fit.rms_residual_m) < 0.1  # the file's 0.1 mm rounding


def test_bad_survey_points_are_named_by_line(project: ProjectConfig) -> None:
    text = _survey(project, 4, design_pose(project, 4)).splitlines()
    text[2] = text[2].replace(text[2].split(",")[3], "8,1")  # a cell too many
    text[3] = "P3,3.5,2.5,abc,1,2"
    text.append(text[1])  # P1 again
    with pytest.raises(SurveyError) as exc:
        parse_survey_text("\n".join(text) + "\n", "f.csv")
    msg = str(exc.value)
    assert "f.csv: line 3: 7 cells, expected 6" in msg
    assert "f.csv: line 4: x_m: 'abc' is not a number" in msg
    assert "f.csv: line 7: point 'P1' again (first on line 2)" in msg
    good = _survey(project, 4, design_pose(project, 4)).splitlines()
    with pytest.raises(SurveyError, match="3 point"):
        parse_survey_text("\n".join(good[:4]) + "\n")
    with pytest.raises(SurveyError, match="line 3: a field runs over a line break"):
        parse_survey_text(good[0] + "\n" + good[1] + '\nP9,"1\n2",1,1,1,1\n')
    with pytest.raises(SurveyError, match="missing column"):
        parse_survey_text("point,face_y_m,x_m,y_m,z_m\n")


def test_a_survey_with_too_large_a_residual_is_refused(project: ProjectConfig) -> None:
    lines = _survey(project, 4, design_pose(project, 4)).splitlines()
    cells = lines[3].split(",")
    cells[5] = f"{float(cells[5]) + 0.02:.4f}"  # one point 20 mm high
    lines[3] = ",".join(cells)
    fit = fit_survey(project, 4, parse_survey_text("\n".join(lines)))
    assert not fit.accepted and "worst line" in fit.reasons[0]
    other = fit_survey(project, 7, parse_survey_text("\n".join(lines[:3] + lines[4:])))
    assert not other.accepted and "another ring" in other.reasons[0]


# --------------------------------------------------------------------------- the commands


def test_place_plan_json_and_exit_codes() -> None:
    code, out, _ = run_main(["place", "plan", "--ring", "3", "--json"])
    d = json.loads(out)
    assert code == 0 and d["feasible"] and set(d["table4"]) >= {"max_gap_mm", "tilt_angle_deg"}
    code, out, _ = run_main(["place", "plan", "--previous-deviation", "0,9,0,0,0", "--json"])
    d = json.loads(out)
    assert code == 3 and d["binding"]["limit"] == "centreline_deviation_y_mm"
    assert d["binding"]["exceeded_by"] == pytest.approx(2.0, abs=1e-3)
    code, _, err = run_main(["place", "plan", "--previous-deviation", "1,2,3"])
    assert code == 2 and "expects five numbers" in err


def test_survey_import_attaches_the_pose_that_place_plan_builds_on(
    tmp_path: Path, project: ProjectConfig
) -> None:
    truth = compose(design_pose(project, 4), Pose(0.002, units.mm(6.0), 0.0))
    f = tmp_path / "ring4.csv"
    f.write_text(_survey(project, 4, truth))
    db = tmp_path / "a.sqlite"
    code, out, _ = run_main(["survey", "import", str(f), "--ring", "4", "--db", str(db), "--json"])
    assert code == 0 and json.loads(out)["accepted"]
    code, out, _ = run_main(["place", "plan", "--from-store", "--db", str(db), "--json"])
    d = json.loads(out)
    assert code == 0 and d["ring"] == 5
    assert d["previous_deviation"]["y_mm"] == pytest.approx(6.0, abs=0.2)
    assert d["target_deviation"]["y_mm"] == pytest.approx(4.0, abs=0.2)
    code, out, _ = run_main(["place", "plan", "--ring", "5", "--survey", str(f), "--json"])
    assert code == 0 and json.loads(out)["target"] == pytest.approx(d["target"])
    bad = tmp_path / "bad.csv"
    bad.write_text(f.read_text().replace("P2,", "P1,"))
    code, _, err = run_main(["survey", "import", str(bad), "--ring", "4"])
    assert code == 2 and "line 3: point 'P1' again" in err and "Traceback" not in err
    code, out, _ = run_main(["survey", "import", str(f), "--ring", "9"])
    assert code == 1 and "REFUSED" in out


def test_place_plan_from_a_store_of_table4_records(tmp_path: Path) -> None:
    db = tmp_path / "a.sqlite"
    code, _, _ = run_main(
        ["acceptance", "add", "7", "--db", str(db), "--vertical-misalignment-mm", "1",
         "--horizontal-misalignment-mm", "1", "--max-gap-mm", "5",
         "--centreline-deviation-x-mm", "3", "--centreline-deviation-y-mm", "-1"]
    )  # fmt: skip
    assert code == 0
    code, out, _ = run_main(["place", "plan", "--from-store", "--db", str(db), "--json"])
    d = json.loads(out)
    assert code == 0 and d["ring"] == 8
    assert d["previous_deviation"]["y_mm"] == pytest.approx(3.0)
    assert d["previous_deviation"]["z_mm"] == pytest.approx(-1.0)
    code, _, err = run_main(["place", "plan", "--from-store", "--db", str(tmp_path / "no.db")])
    assert "no.db" in err
    assert code == 2


def test_plan_target_takes_the_previous_pose_in_the_new_ring_frame(project: ProjectConfig) -> None:
    prev = to_ring_frame(project, design_pose(project, 4), 4, 5)
    a = plan_target(project, prev, 5)
    b = plan_from_deviation(project, 5, Pose())
    assert np.allclose(a.target, b.target, atol=1e-9)


def test_the_slide_controller_refuses_a_move_beyond_the_strokes(project: ProjectConfig) -> None:
    from ipc_app.control.slide import SlideController

    s = SlideController(project, project.control.period_s)
    x = np.array([c.stroke_m / 2 for c in project.cylinders_by_can_index])
    with pytest.raises(ValueError, match=r"stroke: central_axis extension \+96.0 mm"):
        s.engage(x, 0.0, {"central_axis": (0.096,)})
    assert s.check({"lateral": (0.01,)}) == ["lateral: 1 extensions for 2 cylinders"]
    assert s.engage(x, 0.0, {"lateral": (0.004, 0.004)}) > 0.0
