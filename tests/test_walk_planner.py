"""The walk planner: phases, expected leg shares, the stability margin along the plan,
and refusals that name the constraint, the phase and the instant; ``wara walk plan``."""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from config import ProjectConfig, default_project_path
from ipc_app.model import rod_forces
from ipc_app.model.kinematics import Vec
from ipc_app.model.support import (
    WalkingMachine,
    stability_margin,
    standing_load,
    support_forces,
)
from ipc_app.planner.walk import ORDER, PHASES, Move, WalkStart, plan_walk
from wara.cli import main


def _walking(project: ProjectConfig, **changes: Any) -> ProjectConfig:
    assert project.walking is not None
    return project.model_copy(update={"walking": project.walking.model_copy(update=changes)})


def test_three_steps_lay_out_every_phase_in_order(project: ProjectConfig) -> None:
    plan = plan_walk(project, 3)
    assert plan.feasible and plan.refusal is None
    keys = [p.key for p in plan.phases]
    assert keys == list(PHASES) * 3
    assert [p.step for p in plan.phases] == [k for k in (1, 2, 3) for _ in PHASES]
    # phases follow each other without gaps
    for a, b in zip(plan.phases, plan.phases[1:], strict=False):
        assert b.t_start_s == pytest.approx(a.t_start_s + a.duration_s)
    d = plan.to_dict()
    assert d["distance_m"] == pytest.approx(6.0)
    assert max(d["step_duration_s"]) < 120.0  # the goal: a step within 2 min
    # x_S: rear -> front in phase 1, front -> rear in phase 6
    p1 = plan.phases[0]
    p6 = plan.phases[5]
    assert (p1.x_s_m[0], p1.x_s_m[-1]) == pytest.approx((-1.0, 1.0))
    assert (p6.x_s_m[0], p6.x_s_m[-1]) == pytest.approx((1.0, -1.0))


def test_travel_move_respects_speed_and_acceleration(project: ProjectConfig) -> None:
    walk = project.walking
    assert walk is not None
    move = Move(2.0, walk.travel_speed_m_s, walk.travel_accel_m_s2)
    t = np.linspace(0.0, move.duration_s, 20001)
    x = move.position(t)
    v = np.gradient(x, t)
    a = np.gradient(v, t)
    assert x[-1] == pytest.approx(2.0)
    assert v.max() == pytest.approx(walk.travel_speed_m_s, rel=1e-3)
    assert np.abs(a[5:-5]).max() <= walk.travel_accel_m_s2 * 1.01
    # 2 m at 50 mm/s with 50 mm/s^2: 40 s cruising plus 1 s for the ramps
    assert move.duration_s == pytest.approx(41.0)


def test_the_travel_acceleration_key_sets_the_travel_phases(project: ProjectConfig) -> None:
    """``walking.travel_accel_mm_s2`` sets the travel pair's ramps (the legs' moves keep
    the planner's): 2 m at 50 mm/s take 41 s with 50 mm/s^2, 42.5 s with 20."""
    assert project.walking is not None and project.walking.travel_accel_mm_s2 == 50
    slow = project.model_copy(
        update={"walking": project.walking.model_copy(update={"travel_accel_mm_s2": 20.0})}
    )
    for cfg, travel_s in ((project, 41.0), (slow, 42.5)):
        by_key = {p.key: p for p in plan_walk(cfg, 1).phases}
        assert by_key["1"].duration_s == pytest.approx(travel_s)
        assert by_key["6"].duration_s == pytest.approx(travel_s)
        assert by_key["5"].duration_s == pytest.approx(3.5)  # a lift: the legs' trapezoid


def test_expected_shares_hold_the_weight_in_every_sample(project: ProjectConfig) -> None:
    plan = plan_walk(project, 1)
    machine = WalkingMachine(project)
    weight = machine.mass_kg * -float(machine.g_base.z)
    for ph in plan.phases:
        assert ph.leg_forces_n.sum(axis=1) == pytest.approx(np.full(len(ph.t_s), weight))
    by_key = {p.key: p for p in plan.phases}
    # M standing: S's legs carry nothing; S standing: M's legs nothing
    assert np.all(by_key["1"].leg_forces_n[:, 4:] == 0.0)
    assert np.all(by_key["6"].leg_forces_n[:, :4] == 0.0)
    # preload: S's legs at preload_percent of their eight-leg share
    assert project.walking is not None
    eight = support_forces(machine.legs_xy(1.0), machine.mass_kg, machine.cog(1.0), machine.g_base)
    pre = by_key["3"].leg_forces_n[-1]
    assert pre[4:] == pytest.approx(eight[4:] * project.walking.preload_percent / 100)
    # transfer ends with M's legs at unloaded_percent of their standing share (the largest)
    standing = by_key["2"].leg_forces_n[-1]
    end = by_key["4"].leg_forces_n[-1]
    ratio = end[:4] / standing[:4]
    assert ratio.max() == pytest.approx(project.walking.unloaded_percent / 100)


def test_four_leg_shares_are_the_model_statics(project: ProjectConfig) -> None:
    """support_forces on M's rectangle is model.md section 5 (rod_forces, level)."""
    machine = WalkingMachine(project)
    lo = project.layers.lower
    cog = machine.cog(-1.0)
    ours = support_forces(machine.legs_xy(-1.0)[:4], machine.mass_kg, cog, machine.g_base)
    theirs = rod_forces(
        0.0, 0.0, lo.a_m, lo.b_m, machine.mass_kg,
        Vec(np.asarray(cog[0]), np.asarray(cog[1]), np.asarray(cog[2])), machine.g_base,
    )  # fmt: skip
    assert ours == pytest.approx(np.asarray(theirs), rel=1e-12)


def test_the_statics_are_trimmed_to_the_load_the_standing_legs_measure(
    project: ProjectConfig,
) -> None:
    """The machine carries 900 kg more on M than its YAML says, 0.6 m aside (the part as
    cast and set down): the standing load read from M's legs gives the true weight and
    COG back, and the trimmed machine's shares are the true ones wherever S stands,
    also with S standing alone after the step, where the model's are 2.5 % off."""
    model = WalkingMachine(project)
    g = model.g_base
    (mm, cm), (ms, cs) = model.main, model.sub
    x0, x1 = -1.0, 1.0
    extra, at = 900.0, np.array([0.3, 0.6, model.cog(x0)[2]])

    def true_cog(x_s: float) -> np.ndarray:
        c = np.array(cm) * mm + extra * at + (np.array(cs) + np.array([x_s, 0.0, 0.0])) * ms
        return c / (mm + extra + ms)

    true_mass = model.mass_kg + extra
    measured = support_forces(model.legs_xy(x0)[:4], true_mass, true_cog(x0), g)
    load = standing_load(model.main_legs_xy, measured, x0)
    assert load.weight_n == pytest.approx(true_mass * -float(g.z))
    trimmed = WalkingMachine(project, standing=load)
    assert trimmed.mass_kg == pytest.approx(true_mass)
    for x_s in (x0, 0.0, x1):
        assert trimmed.cog(x_s) == pytest.approx(true_cog(x_s), abs=1e-6)
    assert support_forces(
        trimmed.legs_xy(x0)[:4], trimmed.mass_kg, trimmed.cog(x0), g
    ) == pytest.approx(measured, rel=1e-9)
    # S standing alone at the front end (phase 5): trimmed = truth, the model is off
    truth = support_forces(model.legs_xy(x1)[4:], true_mass, true_cog(x1), g)
    s_trim = support_forces(trimmed.legs_xy(x1)[4:], trimmed.mass_kg, trimmed.cog(x1), g)
    s_model = support_forces(model.legs_xy(x1)[4:], model.mass_kg, model.cog(x1), g)
    assert s_trim == pytest.approx(truth, rel=1e-5)
    assert np.abs(s_model / truth - 1).max() > 0.02
    with pytest.raises(ValueError, match="carry no load"):
        standing_load(model.main_legs_xy, np.zeros(4), x0)


def test_stability_margin_of_a_rectangle() -> None:
    pts = np.array([(2.0, 1.0), (-2.0, 1.0), (-2.0, -1.0), (2.0, -1.0)])
    assert stability_margin(pts, np.array([0.0, 0.0])) == pytest.approx(1.0)
    assert stability_margin(pts, np.array([1.5, 0.2])) == pytest.approx(0.5)
    assert stability_margin(pts, np.array([2.5, 0.0])) == pytest.approx(-0.5)


def test_margin_in_phase_6_is_measured_against_the_sub_frame(project: ProjectConfig) -> None:
    """S standing: y margin ``b_S - y_cog``, x margin ``a_S - |x_cog' - x_S|`` with the
    COG projected along gravity (base pitch), recomputed here from the bodies."""
    assert project.frames is not None
    plan = plan_walk(project, 1)
    p6 = next(p for p in plan.phases if p.key == "6")
    bodies = [(b.mass_kg, np.array(b.cog_m)) for b in project.layers.lower.bodies]
    o = np.array(project.layers.upper.origin_in_lower_m)
    bodies += [(b.mass_kg, o + np.array(b.cog_m)) for b in project.layers.upper.bodies]
    # the frames' bodies weigh their legs' rods and feet in: out of the body (a standing
    # leg's rests on the invert); the upper rods are in the upper platform's bodies
    legs = 4 * project.hydraulics.rod_mass_kg
    main = sum(b.mass_kg for b in project.frames.main.bodies)
    bodies += [
        (b.mass_kg * (1 - legs / main), np.array(b.cog_m)) for b in project.frames.main.bodies
    ]
    sub = sum(b.mass_kg for b in project.frames.sub.bodies)
    m_sub = sub - legs
    tan_p = math.tan(project.base.pitch_rad)
    for k in (0, 10, 20, 40):
        x_s = float(p6.x_s_m[k])
        parts = bodies + [
            (b.mass_kg * (1 - legs / sub), np.array(b.cog_m) + np.array([x_s, 0, 0]))
            for b in project.frames.sub.bodies
        ]
        m = sum(mi for mi, _ in parts)
        c = sum(mi * ci for mi, ci in parts) / m
        assert m_sub > 0
        x_proj = c[0] + c[2] * tan_p  # gravity leans towards +x on the rising invert
        expected = min(
            project.frames.sub.a_m - abs(x_proj - x_s), project.frames.sub.b_m - abs(c[1])
        )
        assert p6.margin_m[k] == pytest.approx(expected, abs=1e-9)


def test_margin_below_the_limit_is_refused_at_the_phase_it_happens(
    project: ProjectConfig,
) -> None:
    """With the shipped frames the least margin is 0.872 m, from phase 5 (S alone) on.
    A limit of 0.9 m refuses at the first instant of step 1's phase 5; 0.85 m passes."""
    ok = plan_walk(_walking(project, min_stability_margin_m=0.85), 2)
    assert ok.feasible
    margin, where = ok.min_margin
    assert margin == pytest.approx(0.8723, abs=1e-4)
    assert (where.step, where.key) == (1, "5")
    plan = plan_walk(_walking(project, min_stability_margin_m=0.9), 2)
    ref = plan.refusal
    assert ref is not None
    assert (ref.constraint, ref.step, ref.phase) == ("stability_margin", 1, "5")
    p5 = next(p for p in plan.phases if p.key == "5")
    assert ref.t_s == pytest.approx(p5.t_start_s)
    assert ref.value == pytest.approx(margin, abs=1e-9) and ref.limit == 0.9
    # the plan is checked everywhere: every step's S-standing phases break it too
    assert {(v.step, v.phase) for v in plan.violations if v.constraint == "stability_margin"} == {
        (s, k) for s in (1, 2) for k in ("5", "6", "7a")
    }


def test_a_sub_frame_too_short_for_the_step_is_refused(project: ProjectConfig) -> None:
    assert project.frames is not None
    short_sub = project.frames.sub.model_copy(update={"half_span_x_m": 0.9})
    cfg = project.model_copy(
        update={"frames": project.frames.model_copy(update={"sub": short_sub})}
    )
    plan = plan_walk(cfg, 3)
    assert not plan.feasible
    ref = plan.refusal
    assert ref is not None
    # S's own four-leg share goes into tension before the margin even binds
    assert (ref.constraint, ref.step, ref.phase) == ("leg_force_min", 1, "4")
    kinds = {v.constraint for v in plan.violations}
    assert "stability_margin" in kinds


def test_slip_is_refused_where_the_travel_force_exceeds_friction(project: ProjectConfig) -> None:
    """Moving M (63 t) needs about 2.6 kN (acceleration and the 0.17 deg gradient); S
    (7.4 t) 0.3 kN. Friction 0.001 on 70.15 t holds 0.69 kN: S moves, M does not."""
    plan = plan_walk(_walking(project, foot_friction_coefficient=0.001), 1)
    ref = plan.refusal
    assert ref is not None
    assert (ref.constraint, ref.step, ref.phase) == ("slip", 1, "6")
    # 71.35 t of bodies less the legs' eight rods and feet of 150 kg (not in the load)
    assert ref.value > ref.limit == pytest.approx(0.001 * 70150 * 9.80665, rel=1e-4)


def test_start_outside_the_travel_is_refused(project: ProjectConfig) -> None:
    plan = plan_walk(project, 1, WalkStart(x_s_m=-1.2))
    ref = plan.refusal
    assert ref is not None and ref.constraint == "travel_stroke"
    assert ref.limit == pytest.approx(1.05)


def test_leg_stroke_is_checked(project: ProjectConfig) -> None:
    lo = project.layers.lower
    low = -lo.extension_limit_m + 0.01  # the main legs nearly retracted: S cannot lift
    plan = plan_walk(project, 1, WalkStart(x_s_m=-1.0, main_extensions_m=(low,) * 4))
    ref = plan.refusal
    assert ref is not None and ref.constraint == "leg_stroke"
    assert ref.limit == pytest.approx(lo.extension_limit_m)


def test_cli_walk_plan(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["walk", "plan", "--steps", "3", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["feasible"] is True and d["distance_m"] == 6.0
    assert len(d["phases"]) == 30 and d["refusal"] is None
    assert d["min_stability_margin_m"] >= d["min_stability_margin_limit_m"]
    assert main(["walk", "plan", "--steps", "1"]) == 0
    assert "FEASIBLE" in capsys.readouterr().out
    data = yaml.safe_load(default_project_path().read_text())
    data["walking"]["min_stability_margin_m"] = 0.9
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["walk", "plan", "--steps", "1", "--config", str(path)]) == 3
    out = capsys.readouterr().out
    assert "REFUSED" in out and "stability_margin: step 1 phase 5 (lift M)" in out
    assert main(["walk", "plan", "--steps", "1", "--config", str(path), "--json"]) == 3
    ref = json.loads(capsys.readouterr().out)["refusal"]
    assert (ref["constraint"], ref["phase"], ref["limit"]) == ("stability_margin", "5", 0.9)


def test_cli_walk_plan_bad_arguments(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert main(["walk", "plan", "--steps", "0"]) == 2
    assert "--steps must be within 1..1000" in capsys.readouterr().err
    assert main(["walk", "plan", "--steps", "1", "--start-main-mm", "1,2"]) == 2
    data = yaml.safe_load(default_project_path().read_text())
    data.pop("frames")
    data.pop("walking")
    data["cycle"]["walk_steps"] = 0  # its ring cycles stand at the ring
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["walk", "plan", "--steps", "1", "--config", str(path)]) == 2
    assert "has no frames and walking sections" in capsys.readouterr().err


def test_a_backward_step_is_the_forward_step_mirrored(project: ProjectConfig) -> None:
    """Back: the forward phases in reverse order from the same start state (S lifted at
    the rear end of its travel), the travel pair moving the other way, each phase
    standing the same frame; the same configurations, so the same least margin."""
    fwd, back = plan_walk(project, 2), plan_walk(project, 2, direction="back")
    assert back.feasible and back.direction == "back"
    assert [p.key for p in back.phases] == list(ORDER["back"]) * 2
    assert back.to_dict()["distance_m"] == pytest.approx(-4.0)
    by_key = {p.key: p for p in back.phases if p.step == 1}
    # M moves back relative to standing S (x_S to the front end), then S moves back
    assert (by_key["6"].x_s_m[0], by_key["6"].x_s_m[-1]) == pytest.approx((-1.0, 1.0))
    assert (by_key["1"].x_s_m[0], by_key["1"].x_s_m[-1]) == pytest.approx((1.0, -1.0))
    assert by_key["6"].name == "move M back" and by_key["1"].name == "move S back"
    assert by_key["6"].standing == fwd.phases[5].standing  # S stands while M moves
    # the step ends in the start state: M standing, S lifted, x_S at the rear end
    assert back.phases[-1].standing == fwd.phases[-1].standing
    assert back.min_margin[0] == pytest.approx(fwd.min_margin[0], abs=1e-9)
    assert back.duration_s == pytest.approx(fwd.duration_s, rel=1e-3)
    for ph in back.phases:  # every sample's forces still hold the weight
        w = WalkingMachine(project)
        total = ph.leg_forces_n.sum(axis=1)
        assert total == pytest.approx(np.full(len(total), w.mass_kg * -float(w.g_base.z)))


def test_a_backward_plan_is_checked_along_it(project: ProjectConfig) -> None:
    """The constraints of the forward plan along the backward one: a margin limit of
    0.9 m refuses at the first instant S stands alone (its phase 5), and the feet's
    friction refuses moving M back (phase 6)."""
    plan = plan_walk(_walking(project, min_stability_margin_m=0.9), 1, direction="back")
    ref = plan.refusal
    assert ref is not None
    assert (ref.constraint, ref.step, ref.phase) == ("stability_margin", 1, "5")
    assert ref.t_s == pytest.approx(next(p for p in plan.phases if p.key == "5").t_start_s)
    slip = plan_walk(_walking(project, foot_friction_coefficient=0.001), 1, direction="back")
    assert slip.refusal is not None
    assert (slip.refusal.constraint, slip.refusal.phase) == ("slip", "6")
    assert "(move M back)" in slip.refusal.message
    with pytest.raises(ValueError, match="direction must be one of forward, back"):
        plan_walk(project, 1, direction="sideways")


def test_an_unloaded_walk_plans_without_the_workpiece(project: ProjectConfig) -> None:
    """Unloaded: the upper layer's ``workpiece`` body (36.35 t) left out of the statics,
    so the legs carry the 35 t robot; a project without such a body cannot say what
    unloaded leaves and is refused."""
    loaded = plan_walk(project, 1, direction="back")
    empty = plan_walk(project, 1, direction="back", unloaded=True)
    assert empty.feasible and empty.to_dict()["unloaded"] is True
    g = -float(WalkingMachine(project).g_base.z)
    part = next(b.mass_kg for b in project.layers.upper.bodies if b.name == "workpiece")
    drop = loaded.phases[0].leg_forces_n[0].sum() - empty.phases[0].leg_forces_n[0].sum()
    assert drop == pytest.approx(part * g, rel=1e-9)
    assert empty.min_margin[0] > loaded.min_margin[0]  # the part's COG is off-centre
    bodies = tuple(b for b in project.layers.upper.bodies if b.name != "workpiece")
    up = project.layers.upper.model_copy(update={"bodies": bodies})
    cfg = project.model_copy(update={"layers": project.layers.model_copy(update={"upper": up})})
    with pytest.raises(ValueError, match="no body named 'workpiece': it cannot walk unloaded"):
        plan_walk(cfg, 1, unloaded=True)


def test_cli_walk_plan_back(capsys: pytest.CaptureFixture[str]) -> None:
    args = ["walk", "plan", "--steps", "1", "--direction", "back", "--unloaded", "--json"]
    assert main(args) == 0
    d = json.loads(capsys.readouterr().out)
    assert (d["direction"], d["unloaded"], d["distance_m"]) == ("back", True, -2.0)
    assert [p["phase"] for p in d["phases"]] == list(ORDER["back"])
    with pytest.raises(SystemExit) as exc:
        main(["walk", "plan", "--steps", "1", "--direction", "up"])
    assert exc.value.code == 2
    assert "invalid choice: 'up'" in capsys.readouterr().err
