"""The slide axes' move to a planned target, closed over the CAN wire with the HIL
simulator in lockstep: the part reaches the target's yaw, lateral position and gap on the
simulator's truth (hil_sim.placement). The loop is wara.placement_run's, which runs the
controllers directly, not inside the service core (it has no placement mode yet)."""

from __future__ import annotations

import numpy as np
import pytest

from config import ProjectConfig, units
from hil_sim.placement import pose_from_home, slide_state
from ipc_app.model.placement import Pose
from tests.cli_helpers import run_main
from tests.hil_helpers import make_bench
from wara.placement_run import run_placement_lockstep


def test_truth_chain_of_the_slide_stage(project: ProjectConfig) -> None:
    b = make_bench(project)
    try:
        rig = b.sim.rig
        idx = {c.id: c.can_index for c in project.cylinders}
        half = {c.id: c.stroke_m / 2 for c in project.cylinders}
        rig.set_rod_position(idx["central_axis"], half["central_axis"] + 0.004)
        rig.set_rod_position(idx["lateral_1"], half["lateral_1"] - 0.003)
        rig.set_rod_position(idx["lateral_2"], half["lateral_2"] - 0.003)
        e = 1.5 * np.sin(units.deg(0.02))
        rig.set_rod_position(idx["rotation_1"], half["rotation_1"] + e)
        rig.set_rod_position(idx["rotation_2"], half["rotation_2"] - e)
        x, y, yaw = slide_state(project, rig.rod_positions_m)
        assert (x, y) == pytest.approx((0.004, -0.003)) and units.to_deg(yaw) == pytest.approx(0.02)
        _r, t = pose_from_home(project, rig)
        lower_q = rig.q
        assert np.max(np.abs(lower_q)) < 1e-4  # the platforms at rest near mid-stroke
        assert t == pytest.approx([0.004, -0.003, 0.0], abs=2e-4)
    finally:
        b.close()


@pytest.mark.slow
def test_a_placement_move_reaches_the_planned_target_on_the_truth(
    project: ProjectConfig,
) -> None:
    """The previous part 6 mm left, 6 mm low and turned by 0.03 deg: the target steers
    back by 2 mm; attitude, height, yaw, lateral and gap reach it on the simulator's
    truth within the simulation goals."""
    dev = Pose(y=units.mm(6.0), z=units.mm(-6.0), yaw=units.deg(0.03))
    r = run_placement_lockstep(project, 5, dev)
    assert r["passed"], r.get("goals")
    e = r["error_from_target"]
    assert max(abs(e[k]) for k in ("x_mm", "y_mm", "z_mm")) <= 1.0
    assert max(abs(e[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg")) <= 0.01
    assert abs(r["gap_error_mm"]) <= 1.0
    assert abs(r["plan"]["heave_mm"]) > 3.0  # the height did move (6 mm low -> 4 mm)
    assert r["max_sync_error_mm"] < project.safety.max_sync_error_mm
    assert all(v["passed"] is not False for v in r["table4_truth"].values())


def test_place_run_refuses_an_unreachable_target() -> None:
    code, out, _ = run_main(["place", "run", "--lockstep", "--previous-deviation", "9,0,0,0,0"])
    assert code == 3 and "centreline_deviation_x_mm" in out
