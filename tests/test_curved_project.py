"""The curved and graded example project (``config/projects/curved_grade_heavy_part.yaml``):
the shipped machine on a 400 m curve to the left and a 3 % rising grade with 40 t parts
tapered 47.5 mm (docs/curves.md). It validates, the walk plan carries the part, ring 2's
target is within Table 4, and the part placed in lockstep on the simulator is judged
against Table 4 with the gap at both ends of the joint; end to end in lockstep against
its own goals: the attitude examples on its pitched invert, a step along the curve, and
a ring cycle (a step there, ring 2 placed, a step back unloaded)."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest

from config import crosscheck, default_project_path, load_project
from ipc_app.model.placement import Pose, axis_pose, ring_chainage_m
from ipc_app.planner.placement import plan_from_deviation
from tests.cli_helpers import run_main
from tests.walk_checks import assert_steps_within_the_walk_goals
from wara.cycle import run_cycle
from wara.demo import run_demo
from wara.place import run_place
from wara.walk import run_walk

CURVED = default_project_path().with_name("curved_grade_heavy_part.yaml")


def test_the_project_is_on_a_400_m_curve_and_a_3_percent_grade_with_tapered_parts() -> None:
    cfg = load_project(CURVED)
    al = cfg.tunnel.alignment
    assert al is not None and al.horizontal is not None
    assert cfg.workpiece_mass_kg == 40000 and cfg.workpiece.taper_mm == 47.5
    assert crosscheck.problems(cfg) == []
    c2 = ring_chainage_m(cfg, 2)
    at = axis_pose(al, c2)
    assert at.yaw == pytest.approx(math.radians(al.horizontal.heading_deg) + 0.125 + c2 / 400.0)
    assert -math.tan(at.pitch) == pytest.approx(0.03)
    code, out, err = run_main(["config", "validate", str(CURVED)])
    assert code == 0 and "OK" in out, err


def test_the_walk_plan_carries_the_heavier_part() -> None:
    code, out, err = run_main(["walk", "plan", "--config", str(CURVED), "--steps", "1"])
    assert code == 0, err
    assert "least stability margin" in out


def test_ring_2s_target_on_the_curve_is_within_table_4() -> None:
    code, out, err = run_main(["place", "plan", "--config", str(CURVED), "--ring", "2", "--json"])
    assert code == 0, err
    plan = json.loads(out)
    assert plan["feasible"] and not plan["reasons"]
    t4 = plan["table4"]
    assert all(item["passed"] is not False for item in t4.values()), t4
    assert 0.0 <= t4["min_gap_mm"]["value"] <= t4["max_gap_mm"]["value"] <= 10.0


def test_rectangular_parts_on_its_curve_are_refused_naming_the_taper() -> None:
    cfg = load_project(CURVED)
    square = cfg.model_copy(update={"workpiece": cfg.workpiece.model_copy(update={"taper_mm": 0})})
    assert crosscheck.problems(square)[0].startswith(
        "tunnel.alignment.horizontal.elements[2].radius_m: 400 m opens the joint 47.5 mm"
    )
    plan = plan_from_deviation(square, 2, Pose())
    assert not plan.feasible
    assert plan.reasons[0].startswith(
        "the joint opens 47.5 mm on a 400 m curve to the left with rectangular parts "
        "(workpiece.taper_mm); a taper of 47.5 mm closes it: "
    )


@pytest.fixture(scope="module")
def placed() -> dict[str, Any]:
    return run_place(str(CURVED), 2, Pose(), mode="lockstep")


def test_a_part_placed_on_the_curve_in_lockstep_meets_table_4_at_both_ends(
    placed: dict[str, Any],
) -> None:
    assert placed["passed"], placed["missed"]
    truth = placed["table4_truth"]
    assert all(item["passed"] is not False for item in truth.values()), truth
    # the gap at both ends of the joint: the largest within the limit, the smallest >= 0
    assert 0.0 <= placed["min_gap_mm"] <= placed["max_gap_mm"] <= 10.0
    assert placed["goals"]["min_gap_mm"]["met"] and placed["goals"]["max_gap_mm"]["met"]
    assert placed["final_mode"] == "COMPLETE"


@pytest.fixture(scope="module")
def walked_on_the_curve() -> tuple[dict[str, Any], list[Any]]:
    """One step forward on the 400 m curve in lockstep, the service's estimate of where
    the machine stands and the simulator's truth kept after each cycle."""
    seen: list[Any] = []

    def keep(h: Any) -> None:
        seen[:] = [h.core.on_axis, h.sim.truth().walk]

    out = run_walk(str(CURVED), 1, mode="lockstep", on_cycle=keep)
    return out, seen


@pytest.mark.slow
def test_a_step_on_the_curve_turns_the_machine_with_the_axis(
    walked_on_the_curve: tuple[dict[str, Any], list[Any]],
) -> None:
    """curves.md section 3: S turns in M by the axis's 0.286 deg as it advances, M follows
    as the rods come back to equal strokes; on the truth the machine ends on the axis,
    its heading the axis's, S square in M again."""
    out, (on_axis, truth) = walked_on_the_curve
    assert out["passed"], out["missed"]
    (step,) = out["steps"]
    axis_turn = math.degrees(2.0 / 400.0)
    assert step["turn_deg"] == pytest.approx(axis_turn, abs=0.005)  # measured on the rods
    assert abs(out["heading_error_deg"]) < 0.01
    assert abs(out["lateral_offset_mm"]) < 1.0
    assert out["goals"]["heading_error_deg"]["met"]
    assert math.degrees(float(truth.heading_rad[1])) == pytest.approx(axis_turn, abs=0.01)
    assert abs(math.degrees(truth.yaw_s_in_m_rad)) < 0.01
    assert float(truth.plan_xy_m[0, 1]) == pytest.approx(2.0**2 / (2 * 400.0), abs=1e-3)
    # the service's estimate: one step along the axis, its heading error the measured
    # turn less the axis's
    assert on_axis is not None
    assert on_axis.chainage_m == pytest.approx(1.9991, abs=1e-3)
    assert math.degrees(on_axis.heading_error_rad) == pytest.approx(
        step["turn_deg"] - math.degrees(2.0 / 400.0) * 0.99955, abs=1e-3
    )


@pytest.mark.slow
def test_a_step_in_its_sag_curve_sets_each_foot_on_the_invert_there(tmp_path: Path) -> None:
    """curves.md section 3: the invert under each frame follows the axis's grade at its
    chainage. Ring 1 moved back into the project's 3 km sag curve (0.3 % to 3 %, the base
    pitched to the grade there, -0.934 deg): a step passes its goals, and after it M's
    feet stand on the curve, the front pair (x = 4.8 m) 3.7 mm higher than the rear
    (-0.8 m) against the start's chord."""
    text = CURVED.read_text()
    sag = text.replace("first_ring_chainage_m: 0.0", "first_ring_chainage_m: -60.0")
    sag = sag.replace("  pitch_deg: -1.72", "  pitch_deg: -0.934")
    assert sag.count("-60.0") == 1 and "-0.934" in sag
    path = tmp_path / "sag.yaml"
    path.write_text(sag)
    cfg = load_project(path)
    heights: list[Any] = []

    def keep(h: Any) -> None:
        heights[:] = [h.sim.rig.foot_heights_m, h.sim.rig.foot_forces_n]

    out = run_walk(str(path), 1, mode="lockstep", on_cycle=keep)
    assert out["passed"], out["missed"]
    feet, forces = heights
    g0 = 0.003 + 40.0 / 3000.0
    cos_a = 1.0 / math.hypot(1.0, g0)
    a = cfg.layers.lower.a_m
    x_front, x_rear = 2.0 + a, 2.0 - a
    want = ((x_front * cos_a) ** 2 - (x_rear * cos_a) ** 2) / (2.0 * 3000.0) * cos_a
    # each foot pressed into the invert by its load over the contact's stiffness
    assert cfg.walking is not None
    invert = feet[:4] + forces[:4] / cfg.walking.contact.stiffness_n_m
    front, rear = invert[[0, 3]].mean(), invert[[1, 2]].mean()  # legs at +a: 1, 4
    assert front - rear == pytest.approx(want, abs=1e-4)


@pytest.mark.slow(seconds=30)
def test_the_attitude_examples_pass_on_its_pitched_invert() -> None:
    """The attitude examples on the invert of the 3 % grade (base pitch -1.72 deg) with
    the 40 t part, each within the project's tolerances."""
    out = run_demo(str(CURVED), mode="lockstep")
    assert out["passed"], out.get("error") or out["fault_reasons"]
    assert out["final_mode"] == "COMPLETE" and len(out["examples"]) == 3
    for ex in out["examples"]:
        assert ex["passed"], ex
        for figure, limit in out["tolerances"].items():
            assert ex[figure] <= limit, (figure, ex)


@pytest.mark.slow(seconds=60)
def test_a_ring_cycle_on_the_curve_places_ring_2_within_table_4(tmp_path: Path) -> None:
    """A ring cycle on the 400 m curve: a step there turning with the axis, ring 2's
    tapered part placed (Table 4 on the simulator's truth, the gap at both ends of the
    joint), a step back unloaded; each step within the project's walk goals."""
    cfg = load_project(CURVED)
    out = run_cycle(str(CURVED), 1, db_path=tmp_path / "a.sqlite", cfg=cfg)
    assert out["error"] is None, out["error"]
    assert out["fault_reasons"] == [], out["fault_reasons"]
    (ring,) = out["rings"]
    assert ring["passed"], ring
    steps = [*ring["walks"]["walk"], *ring["walks"]["walk_back"]]
    assert len(steps) == 2
    assert_steps_within_the_walk_goals(cfg, steps)
    acc = cfg.acceptance
    table4 = {k: getattr(acc, k) for k in type(acc).model_fields if getattr(acc, k) is not None}
    for key, limit in table4.items():  # Table 4 on the simulator's truth
        assert abs(ring[key]) <= limit, (key, ring[key])
    assert 0.0 <= ring["min_gap_mm"] <= ring["max_gap_mm"] <= acc.max_gap_mm
