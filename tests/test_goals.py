"""The judges of the runs (wara.goals): each reads its limits from the project it judges
for, so a project that changes a limit is judged against its own value, and a missed
goal is named with its value and limit."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from config import ProjectConfig
from config.loader import default_project_path
from ipc_app.service.cycle import RECORD_KEYS
from wara.examples import ExampleResult, judge_example
from wara.goals import (
    ATTITUDE_GOALS,
    Goal,
    judge,
    limits,
    placement_goals,
    ring_figures,
    ring_goals,
    step_figures,
    step_time_limit_s,
    walk_step_goals,
)


def _with(project: ProjectConfig, section: str, **keys: Any) -> ProjectConfig:
    part = getattr(project, section)
    return project.model_copy(update={section: part.model_copy(update=keys)})


#: A step as ``wara walk`` rows it: the service's figures and the truth's distance.
STEP = {
    "direction": "forward",
    "index": 1,
    "distance_m": 2.0012,
    "duration_s": 114.2,
    "max_leg_sync_error_mm": 0.05,
    "max_travel_sync_error_mm": 0.0035,
    "max_transfer_attitude_change_deg": 0.0059,
    "max_leg_force_ratio": 1.07,
    "min_stability_margin_m": 0.875,
    "transfer_time_s": 4.8,
}


def test_a_step_is_judged_against_the_projects_walking_keys(project: ProjectConfig) -> None:
    figures = step_figures(STEP, 2.0)
    assert figures["distance_error_mm"] == pytest.approx(1.2)
    assert judge(walk_step_goals(project), figures).passed
    for key, value, note in [
        ("overload_percent", 105.0, "max_leg_force_ratio 1.07 > 1.05"),
        ("leg_sync_band_mm", 0.04, "max_leg_sync_error_mm 0.05 > 0.04"),
        ("travel_sync_band_mm", 0.003, "max_travel_sync_error_mm 0.0035 > 0.003"),
        ("min_stability_margin_m", 0.9, "min_stability_margin_m 0.875 < 0.9"),
    ]:
        changed = _with(project, "walking", **{key: value})
        verdict = judge(walk_step_goals(changed), figures)
        assert not verdict.passed and verdict.note == note, key
        (missed,) = verdict.missed
        assert missed.goal.source == f"walking.{key}"
        assert verdict.to_dict()["goals"][missed.goal.figure]["met"] is False


def test_the_step_time_follows_the_planned_step_and_its_touch_downs(
    project: ProjectConfig,
) -> None:
    """The shipped 2 m step is planned in 119.6 s (its transfers' ramps blended in and out,
    ipc_app.planner.force_ramp); each of its two lowerings may take the
    whole touch-down window (2 x 10 mm at the derived 2.4 mm/s). Half the touch-down
    speed doubles the windows; a shorter step plans shorter."""
    walking = project.walking
    assert walking is not None
    limit = step_time_limit_s(project)
    window_s = 20.0 / 2.4
    assert limit == pytest.approx(119.6 + 2 * window_s, abs=0.1)
    slow = _with(project, "walking", touchdown_speed_mm_s=1.2)
    assert step_time_limit_s(slow) == pytest.approx(limit + 2 * window_s, abs=1e-6)
    short = _with(project, "walking", step_length_mm=200.0)
    assert step_time_limit_s(short) < limit - 60.0
    assert judge(walk_step_goals(short), step_figures(STEP, 0.2)).note.startswith(
        "distance_error_mm 1801 > 5; max_step_duration_s 114.2 > "
    )


def test_a_step_back_is_judged_on_its_distance_back(project: ProjectConfig) -> None:
    back = {**STEP, "direction": "back", "distance_m": -1.999}
    assert step_figures(back, 2.0)["distance_error_mm"] == pytest.approx(1.0)
    wrong_way = {**STEP, "direction": "back"}
    verdict = judge(walk_step_goals(project), step_figures(wrong_way, 2.0))
    assert verdict.note == "distance_error_mm 4001 > 5"


def _placed(**table4: float) -> dict[str, Any]:
    values = dict.fromkeys(RECORD_KEYS, 0.5) | table4
    return {
        **values,
        "error_from_target": {
            "x_mm": 0.01,
            "y_mm": -0.3,
            "z_mm": 0.02,
            "roll_deg": 0.0,
            "pitch_deg": -0.004,
            "yaw_deg": 0.001,
        },
        "gap_error_mm": -0.2,
        "cycle_time_s": 300.0,
        "min_gap_mm": 0.4,
    }


def test_a_placed_part_is_judged_against_the_projects_acceptance(project: ProjectConfig) -> None:
    """Table 4 from the project's ``acceptance`` (absolute values; the angle rows only
    when the project gives them a limit), the position, angles and gap from the target."""
    placed = _placed(vertical_misalignment_mm=-7.5)
    names = [g.figure for g in placement_goals(project)]
    assert names == [
        "vertical_misalignment_mm", "horizontal_misalignment_mm", "max_gap_mm",
        "centreline_deviation_x_mm", "centreline_deviation_y_mm", "min_gap_mm",
        "position_error_mm", "angle_error_deg", "gap_error_mm",
    ]  # fmt: skip
    assert judge(ring_goals(project), ring_figures(placed)).passed
    # the gap at both ends of the joint: the largest within its limit, the smallest >= 0
    overlap = judge(ring_goals(project), ring_figures({**placed, "min_gap_mm": -0.3}))
    assert overlap.note == "min_gap_mm -0.3 < 0"
    tight = _with(project, "acceptance", vertical_misalignment_mm=7.0, pitch_angle_deg=0.003)
    verdict = judge(ring_goals(tight), ring_figures(placed))
    assert verdict.note == "vertical_misalignment_mm 7.5 > 7; pitch_angle_deg 0.5 > 0.003"
    assert {j.goal.source for j in verdict.missed} == {
        "acceptance.vertical_misalignment_mm",
        "acceptance.pitch_angle_deg",
    }


def test_a_ring_cycle_is_judged_against_the_projects_cycle_time(project: ProjectConfig) -> None:
    placed = _placed()
    assert limits(ring_goals(project))["cycle_time_s"] == 900.0
    quick = _with(project, "cycle", max_cycle_time_min=4.0)
    verdict = judge(ring_goals(quick), ring_figures(placed))
    assert verdict.note == "cycle_time_s 300 > 240"
    assert verdict.missed[0].goal.source == "cycle.max_cycle_time_min"


def test_an_attitude_example_names_the_goal_it_missed() -> None:
    """The examples' goals have no project key: the same for every project."""
    res = ExampleResult(2.0, 1.0)
    res.set_achieved(2.012, 1.0)
    res.max_twist_mm, res.sync_error_mm = 0.01, 0.01
    assert judge_example(res).note == "attitude_error_deg 0.012 > 0.01"
    assert limits(ATTITUDE_GOALS) == {
        "attitude_error_deg": 0.01,
        "max_twist_mm": 0.5,
        "sync_error_mm": 0.07,
    }


def test_a_verdict_names_what_missed_in_its_parts() -> None:
    """A walk's verdict: its own goals, its steps' by name; a problem (a latched fault, a
    refusal) stands in for its own figures, which are then no verdict."""
    goal = Goal("max_leg_force_ratio", 1.1, "walking.overload_percent")
    step2 = judge([goal], {"max_leg_force_ratio": 1.12})
    parts = [("step 1 forward", judge([goal], {})), ("step 2 forward", step2)]
    walk = judge([Goal("distance_error_mm", 5.0)], {"distance_error_mm": 0.4}, parts=parts)
    assert not walk.passed
    assert walk.notes == [
        "step 1 forward: max_leg_force_ratio nan > 1.1",
        "step 2 forward: max_leg_force_ratio 1.12 > 1.1",
    ]
    faulted = judge([goal], {"max_leg_force_ratio": math.nan}, problem="service ABORTED: x")
    assert faulted.note == "service ABORTED: x" and not faulted.passed
    assert faulted.to_dict()["missed"] == ["service ABORTED: x"]


def test_a_campaigns_default_limits_follow_its_project(tmp_path: Path) -> None:
    from tests.campaign_helpers import write_spec
    from wara.campaign.spec import load_campaign

    data = yaml.safe_load(default_project_path().read_text(encoding="utf-8"))
    data["walking"]["overload_percent"] = 120
    data["acceptance"]["max_gap_mm"] = 7
    (tmp_path / "p.yaml").write_text(yaml.safe_dump(data), encoding="utf-8")
    for kind, figure, limit in [
        ("walk", "max_leg_force_ratio", 1.2),
        ("ring_cycle", "max_gap_mm", 7),
    ]:
        spec = {"project": "p.yaml", "kind": "nominal", "run": {"kind": kind}}
        spec["requirement"] = {"runs": 2}
        c = load_campaign(write_spec(tmp_path, spec, f"{kind}.yaml"))
        assert c.limits[figure] == limit, kind
