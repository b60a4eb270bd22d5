"""Walking on a curve, planned (curves.md section 3; docs/curves.md "Walking on a curve"):
each step turns the machine by the axis's turn plus a bounded correction, made by the
travel pair's differential; a turn beyond ``walking.max_yaw_deg`` or rods beyond the
travel's reserve are refused naming the key."""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import pytest

from config import ProjectConfig, load_project
from ipc_app.model.support import WalkingMachine, cog_projection, stability_margin
from ipc_app.planner.steering import OnAxis, on_axis_at_start, step_turns, walked
from ipc_app.planner.walk import WalkPlan, plan_walk
from wara.cli import main

PROJECTS = Path(__file__).resolve().parents[1] / "config" / "projects"


@pytest.fixture(scope="module")
def curved() -> ProjectConfig:
    """A 400 m arc to the left with a 3 % grade; ring 1 on the arc."""
    return load_project(PROJECTS / "curved_grade_heavy_part.yaml")


def _walking(cfg: ProjectConfig, **changes: Any) -> ProjectConfig:
    assert cfg.walking is not None
    return cfg.model_copy(update={"walking": cfg.walking.model_copy(update=changes)})


def _travels(plan: WalkPlan) -> list[tuple[str, tuple[float, ...], tuple[float, ...]]]:
    return [(p.key, p.start_m, p.end_m) for p in plan.phases if p.key in ("1", "6")]


@pytest.mark.parametrize("name", ["shanghai_airport_link", "metro_light_part"])
def test_a_straight_axis_plans_no_turn(name: str) -> None:
    cfg = load_project(PROJECTS / f"{name}.yaml")
    plan = plan_walk(cfg, 2)
    assert plan.feasible
    assert [t.turn_rad for t in plan.turns] == [0.0, 0.0]
    for _, start, end in _travels(plan):
        assert start[0] == start[1] and end[0] == end[1]
    assert all(p.yaw_rad == (0.0, 0.0) for p in plan.phases)


@pytest.mark.parametrize("direction", ["forward", "back"])
def test_each_step_turns_by_the_axis_through_the_travel_pairs_differential(
    curved: ProjectConfig, direction: str
) -> None:
    assert curved.walking is not None
    b_t, step = curved.walking.travel_half_span_m, curved.walking.step_length_m
    plan = plan_walk(curved, 2, direction=direction)
    assert plan.feasible, plan.refusal
    for turn in plan.turns:
        if direction == "forward":  # on the 400 m arc to the left: step / R (in plan)
            assert turn.axis_turn_rad == pytest.approx(step / 400.0, rel=2e-3)
        else:  # back from chainage 0 into the clothoid before the arc: less each step
            assert -step / 400.0 < turn.axis_turn_rad < -0.9 * step / 400.0
        assert turn.correction_rad == 0.0
    sign = -1.0 if direction == "back" else 1.0
    for k, turn in enumerate(plan.turns):
        first, second = _travels(plan)[2 * k : 2 * k + 2]
        assert first[0] == ("6" if direction == "back" else "1")
        # the first travel ends with the rods apart by 2 b_T sin(psi), the second equal
        psi = sign * turn.turn_rad
        assert first[2][0] - first[2][1] == pytest.approx(2 * b_t * math.sin(psi), abs=1e-12)
        assert first[1][0] == first[1][1] and second[2][0] == second[2][1]
        assert second[1] == first[2]
        # forward: S turns left in M (the right rod further out); back: M turns the axis's
        # way relative to the standing S, so S's yaw in M is the other way
        assert math.copysign(1.0, first[2][0] - first[2][1]) == (1.0 if psi > 0 else -1.0)


def test_the_plan_turns_s_legs_in_its_statics(curved: ProjectConfig) -> None:
    """Phase 5 stands on S turned in M: its margin is taken with S's legs turned about
    S's centre (curves.md section 3), not where they would be unturned."""
    plan = plan_walk(curved, 1)
    ph = next(p for p in plan.phases if p.key == "5")
    yaw = plan.turns[0].turn_rad
    assert ph.yaw_rad == (pytest.approx(yaw), pytest.approx(yaw))
    machine = WalkingMachine(curved)
    point = cog_projection(machine.cog(float(ph.x_s_m[0])), machine.g_base)
    turned = stability_margin(machine.legs_xy(float(ph.x_s_m[0]), yaw)[4:], point)
    unturned = stability_margin(machine.legs_xy(float(ph.x_s_m[0]))[4:], point)
    assert float(ph.margin_m[0]) == pytest.approx(turned, abs=1e-12)
    assert abs(turned - unturned) > 1e-4


def test_a_heading_error_is_steered_back_within_the_bound(curved: ProjectConfig) -> None:
    assert curved.walking is not None
    bound = curved.walking.max_heading_correction_per_step_rad
    start = OnAxis(on_axis_at_start(curved).chainage_m, math.radians(0.2), 0.01)
    turns = step_turns(curved, start, 12, "forward")
    assert all(abs(t.correction_rad) <= bound + 1e-15 for t in turns)
    assert turns[0].correction_rad == pytest.approx(-bound)
    errors = [abs(t.after.heading_error_rad) for t in turns]
    assert errors[-1] < 0.2 * math.radians(0.2)
    assert abs(turns[-1].after.lateral_m) < 0.01 + 12 * 2.0 * math.radians(0.2)


def test_the_measured_turns_update_where_the_machine_stands(curved: ProjectConfig) -> None:
    start = on_axis_at_start(curved)
    turns = step_turns(curved, start, 2, "forward")
    exact = walked(curved, start, turns, [t.turn_rad for t in turns], back=False)
    assert exact.heading_error_rad == pytest.approx(0.0, abs=1e-15)
    assert exact.chainage_m == turns[-1].after.chainage_m
    over = walked(curved, start, turns, [t.turn_rad + 1e-3 for t in turns], back=False)
    assert over.heading_error_rad == pytest.approx(2e-3)
    assert over.lateral_m > 0  # turned too far left: left of the axis
    half = walked(curved, start, turns, [turns[0].turn_rad], back=False)
    assert half.chainage_m == turns[0].after.chainage_m


def test_a_turn_beyond_max_yaw_is_refused_naming_the_key(curved: ProjectConfig) -> None:
    cfg = _walking(curved, max_yaw_deg=0.2)
    plan = plan_walk(cfg, 1)
    ref = plan.refusal
    assert ref is not None and ref.constraint == "yaw"
    assert "walking.max_yaw_deg 0.2" in ref.message and "the axis +0.286 deg" in ref.message


def test_rods_beyond_the_travel_reserve_are_refused(curved: ProjectConfig) -> None:
    """1002 mm of travel each way: the straight step's 1000 fits, the turned rod's 1000
    + b_T sin(turn) does not."""
    cfg = _walking(curved, travel_reserve_mm=98.0)
    ref = plan_walk(cfg, 1).refusal
    assert ref is not None and ref.constraint == "travel_stroke" and cfg.walking is not None
    turned = 1000.0 + cfg.walking.travel_half_span_mm * math.sin(2.0 / 400.0)
    assert "walking.travel_reserve_mm" in ref.message and f"+{turned:.1f} mm" in ref.message
    straight = load_project(PROJECTS / "shanghai_airport_link.yaml")
    assert plan_walk(_walking(straight, travel_reserve_mm=98.0), 1).feasible


def test_the_plan_json_gives_each_steps_turn(curved: ProjectConfig) -> None:
    d = plan_walk(curved, 1).to_dict()
    (s,) = d["steering"]
    assert s["axis_turn_deg"] == pytest.approx(math.degrees(2.0 / 400.0), rel=2e-3)
    assert s["turn_deg"] == s["axis_turn_deg"]
    assert s["lateral_after_mm"] == 0.0
    with pytest.raises(ValueError, match="finite"):
        OnAxis(math.nan)


def test_walk_plan_shows_the_turns_and_refuses_a_bad_on_axis(
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = str(PROJECTS / "curved_grade_heavy_part.yaml")
    assert main(["walk", "plan", "--config", path, "--steps", "1", "--on-axis", "0,0.1,5"]) == 0
    out = capsys.readouterr().out
    assert "step 1 turns +0.2364 deg (the axis +0.2863, steering back -0.0500)" in out
    assert main(["walk", "plan", "--config", path, "--steps", "1", "--on-axis", "0,nan,5"]) == 2
    assert "--on-axis: expected three finite numbers" in capsys.readouterr().err
