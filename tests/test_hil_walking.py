"""The walking rig: foot contact on the invert, friction and slip, ground offsets,
leaking load-holding valves, and the scenario events that drive them."""

from __future__ import annotations

import math
import uuid
from pathlib import Path

import can
import numpy as np
import pytest

from config import ConfigError, ProjectConfig, load_project, units
from config.hil_scenario import HilScenario
from config.schema import CANNOT_WALK
from hil_sim.rig import Rig
from hil_sim.simulator import HilSimulator
from hil_sim.walking import WalkingRig

CURVED = Path(__file__).parents[1] / "config" / "projects" / "curved_grade_heavy_part.yaml"
SCAN = 4  # RK4 steps of 0.25 ms per PLC scan


def settled(project: ProjectConfig, seconds: float = 0.5) -> WalkingRig:
    rig = WalkingRig(project)
    rig.advance(round(seconds / rig.step_s))
    return rig


def weight_n(rig: WalkingRig) -> float:
    """Everything the feet carry, along the base's z (the invert's normal)."""
    return rig.mass_kg * -rig.g_base[2]


def test_start_state_is_main_frame_standing_sub_frame_lifted(project: ProjectConfig) -> None:
    assert project.walking is not None
    rig = settled(project)
    forces = rig.foot_forces_n
    heights = rig.foot_heights_m
    # the four main feet carry the weight; the lifted sub feet none, at clearance
    assert forces[:4].sum() == pytest.approx(weight_n(rig), rel=1e-4)
    assert np.all(forces[:4] > 100e3)
    assert np.all(forces[4:] == 0.0)
    invert = rig.invert_height_m
    assert heights[4:] == pytest.approx(np.full(4, invert + project.walking.clearance_m), abs=5e-4)
    # pressed into the invert by load / stiffness (about 0.9 mm), the invert raised by as
    # much: the body where the rigid rig's is, the part at its home pose
    pen = invert - heights[:4]
    assert pen == pytest.approx(forces[:4] / project.walking.contact.stiffness_n_m, rel=1e-3)
    assert invert == pytest.approx(pen.mean(), rel=1e-4)
    assert 0.5e-3 < invert < 1.5e-3
    assert rig.q[0] == pytest.approx(0.0, abs=1e-6)  # the body at the rigid rig's height
    x_m, x_s = rig.world_x_m
    assert x_m == pytest.approx(0.0, abs=1e-4)
    assert rig.x_s_m == pytest.approx(-project.walking.step_length_m / 2, abs=1e-3)
    assert x_s == pytest.approx(x_m + rig.x_s_m)


def test_contact_is_unilateral_a_hole_under_a_foot_unloads_it(project: ProjectConfig) -> None:
    rig = WalkingRig(project)
    a, b = project.layers.lower.a_m, project.layers.lower.b_m
    # a hole 0.5 m deep under main_leg_3 at (-a, -b): the foot hangs above it; the COG
    # is inside the triangle of legs 1, 2, 4, so the body rests on those three
    rig.set_ground([(-a - 0.3, -a + 0.3, -b - 0.3, -b + 0.3, -0.5)])
    # the body settles onto the other three legs (their oil compressed)
    rig.advance(round(2.5 / rig.step_s))
    forces = rig.foot_forces_n
    assert forces[2] == 0.0
    assert rig.foot_heights_m[2] > -0.5  # in the air, not at the hole's bottom
    # the other three carry the whole weight (statically determinate now)
    assert forces[[0, 1, 3]].sum() == pytest.approx(weight_n(rig), rel=2e-3)


def test_a_raised_invert_under_one_foot_loads_it(project: ProjectConfig) -> None:
    flat = settled(project)
    rig = WalkingRig(project)
    a, b = project.layers.lower.a_m, project.layers.lower.b_m
    rig.set_ground([(a - 0.3, a + 0.3, b - 0.3, b + 0.3, units.mm(1.0))])
    rig.advance(round(0.5 / rig.step_s))
    assert rig.foot_forces_n[0] > flat.foot_forces_n[0] + 5e3
    assert rig.foot_forces_n[:4].sum() == pytest.approx(weight_n(rig), rel=1e-3)
    # the foot sits on the step: about 1 mm higher than on the flat
    assert rig.foot_heights_m[0] - flat.foot_heights_m[0] == pytest.approx(1e-3, abs=3e-4)


def _travel_against(project: ProjectConfig, mu_sub: float) -> tuple[WalkingRig, float]:
    """Both frames standing (the invert raised under S's feet to meet them), the travel
    pair driven out: the largest travel force, and the rig."""
    assert project.frames is not None and project.walking is not None
    rig = WalkingRig(project)
    a_s, b_s = project.frames.sub.a_m, project.frames.sub.b_m
    x_s = rig.world_x_m[1]
    up = project.walking.clearance_m + 0.5e-3
    rig.set_ground(
        [(x_s + sx * a_s - 0.2, x_s + sx * a_s + 0.2, sy * b_s - 0.2, sy * b_s + 0.2, up)
         for sx, sy in ((1, 1), (-1, 1), (-1, -1), (1, -1))]
    )  # fmt: skip
    rig.advance(round(0.3 / rig.step_s))
    assert np.all(rig.foot_forces_n > 1e3)  # all eight feet touch
    rig.set_friction(1, mu_sub)
    rig.ports_open[:] = 1.0
    rig.command[rig._travel_idx] = 0.3
    peak = 0.0
    for _ in range(300):
        rig.advance(SCAN)
        peak = max(peak, float(rig.rod_forces_n[rig._travel_idx].sum()))
    return rig, peak


def test_standing_frame_slips_when_the_travel_force_exceeds_friction(
    project: ProjectConfig,
) -> None:
    """S's feet lightly loaded (about 127 kN: the invert raised 0.5 mm into its parked
    legs): the travel pair at full supply pushes harder than friction can hold, so S
    slides, and the travel force it took is mu N."""
    for mu in (0.8, 0.4):
        rig, peak = _travel_against(project, mu)
        n_sub = rig.foot_forces_n[4:].sum()
        assert rig.slip_m[1] > 1e-3
        assert rig.slip_m[0] == 0.0  # M, far more loaded, holds
        assert peak == pytest.approx(mu * n_sub, rel=0.3)


def test_gravity_along_the_gradient_slips_a_frame_only_on_a_slippery_invert(
    project: ProjectConfig,
) -> None:
    assert project.base.pitch_deg > 0  # the invert falls towards +x
    for mu, slips in ((0.4, False), (0.0005, True)):
        rig = WalkingRig(project)
        rig.set_friction(0, mu)
        rig.advance(round(0.5 / rig.step_s))
        assert bool(rig.slip_m[0] > 1e-4) is slips
        assert bool(rig.world_x_m[0] > 1e-4) is slips


def test_a_leaking_holding_valve_lets_its_leg_sink(project: ProjectConfig) -> None:
    tight = settled(project, 1.0)
    rig = WalkingRig(project)
    rig.valve_leak[0] = 1e-10  # main_leg_1, valves closed (drives off)
    rig.advance(round(1.0 / rig.step_s))
    assert rig.pressures_pa[0, 0] < tight.pressures_pa[0, 0] - 0.5e6
    assert rig.rod_positions_m[0] < tight.rod_positions_m[0] - 1e-5
    assert rig.foot_forces_n[0] < tight.foot_forces_n[0] - 5e3


def test_attitude_rig_is_unchanged_without_contact(project: ProjectConfig) -> None:
    """The attitude demo's rig stays the rigid-legs one unless the scenario asks."""
    assert HilScenario().plant.contact is False
    rig = Rig(project)
    assert not isinstance(rig, WalkingRig)


def _sim(project: ProjectConfig, events: list[dict[str, object]], contact: bool) -> HilSimulator:
    scenario = HilScenario.model_validate({"plant": {"contact": contact}, "events": events})
    bus = can.Bus(interface="virtual", channel=f"walk-{uuid.uuid4().hex}")
    return HilSimulator(project, bus, scenario)


def test_scenario_events_drive_the_walking_rig(project: ProjectConfig) -> None:
    a, b = project.layers.lower.a_m, project.layers.lower.b_m
    events: list[dict[str, object]] = [
        {"kind": "ground", "start_s": 0.1, "x_from_m": a - 0.3, "x_to_m": a + 0.3,
         "y_from_m": b - 0.3, "y_to_m": b + 0.3, "offset_mm": -500},
        {"kind": "foot_slip", "start_s": 0.1, "frame": "sub", "friction_coefficient": 0.05},
        {"kind": "holding_valve_leak", "start_s": 0.1, "cylinder": "main_leg_3",
         "leakage_m3_s_pa": 1e-10},
    ]  # fmt: skip
    sim = _sim(project, events, contact=True)
    try:
        rig = sim.rig
        assert isinstance(rig, WalkingRig)
        sim.step(0.05)
        assert rig.foot_forces_n[0] > 0 and rig.valve_leak[2] == 0.0
        sim.step(0.5)
        assert rig.foot_forces_n[0] == 0.0
        assert rig.friction[1] == 0.05 and rig.friction[0] == 0.4
        assert rig.valve_leak[2] == 1e-10
    finally:
        sim.close()


def test_contact_events_need_the_walking_rig(project: ProjectConfig) -> None:
    ev = {"kind": "foot_slip", "frame": "main", "friction_coefficient": 0.1}
    with pytest.raises(ValueError, match=r"events\[0\] \(foot_slip\): needs plant.contact"):
        _sim(project, [ev], contact=False)


def test_walking_rig_needs_the_frames(project: ProjectConfig) -> None:
    bare = project.model_copy(update={"frames": None, "walking": None})
    with pytest.raises(ValueError, match=f"^{CANNOT_WALK}$"):
        WalkingRig(bare)


def test_ground_event_extent_is_checked(tmp_path: Path) -> None:
    from config.hil_scenario import load_hil_scenario

    path = tmp_path / "s.yaml"
    path.write_text(
        "plant: {contact: true}\nevents:\n"
        "  - {kind: ground, x_from_m: 2, x_to_m: 1, offset_mm: 6}\n"
    )
    with pytest.raises(ConfigError, match="x_to_m and y_to_m must be above"):
        load_hil_scenario(path)


def test_the_transducers_read_the_walking_rigs_own_state(project: ProjectConfig) -> None:
    """The walking rig's state is longer than the attitude rig's: the read-only views
    the PLC samples every scan are of the state the rig integrates."""
    rig = WalkingRig(project)
    rig.advance(40)
    assert np.array_equal(rig.x_view, rig.rod_positions_m)
    assert np.array_equal(rig.pressure_view, rig.pressures_pa.T.ravel())


def test_the_feet_stand_on_the_axis_vertical_curve() -> None:
    """curves.md section 3: the invert under each frame follows the axis's grade at its
    chainage. The curved project moved back into its sag curve (3 km: 0.3 % to 3 %): M
    stands on the chord of its feet (the body level, where the rigid rig's is); S's feet,
    lifted a step behind, hang their clearance above the invert there, which the curve
    raises by x^2 / 2R less the chord's."""
    cfg = load_project(CURVED)
    assert cfg.tunnel.alignment is not None and cfg.walking is not None
    alignment = cfg.tunnel.alignment.model_copy(update={"first_ring_chainage_m": -60.0})
    sag = cfg.model_copy(update={"tunnel": cfg.tunnel.model_copy(update={"alignment": alignment})})
    flat = settled(cfg)
    rig = settled(sag)
    a = cfg.layers.lower.a_m
    assert rig.q[:3] == pytest.approx(flat.q[:3], abs=1e-6)  # heave, roll, pitch as on the grade
    assert rig.foot_forces_n[:4] == pytest.approx(flat.foot_forces_n[:4], rel=1e-3)
    cos_a = 1.0 / math.hypot(1.0, 0.003 + 40.0 / 3000.0)

    def rise(x: float) -> float:  # above the chord through M's feet
        return ((x * cos_a) ** 2 - (a * cos_a) ** 2) / (2.0 * 3000.0) * cos_a

    x_s = rig.world_x_m[1]
    assert cfg.frames is not None
    for j, (sx, _sy) in enumerate(((1, 1), (-1, 1), (-1, -1), (1, -1))):
        x = x_s + sx * cfg.frames.sub.a_m
        lifted = rig.foot_heights_m[4 + j] - flat.foot_heights_m[4 + j]
        assert lifted == pytest.approx(rise(x), abs=2e-5)
