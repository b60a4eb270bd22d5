"""The slide axes' move to a planned target, closed over the CAN wire with the HIL
simulator in lockstep: the part reaches the target's yaw, lateral position and gap on the
simulator's truth (hil_sim.placement). ``wara place run`` (wara.place) asks the service
for the placement (its modes and interlocks in the loop) and judges the truth."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from config import ProjectConfig, load_project, units
from hil_sim.placement import pose_from_home, slide_state
from ipc_app.model.placement import Pose
from tests.cli_helpers import run_wara
from tests.hil_helpers import make_bench
from wara.place import run_place


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


@pytest.mark.parametrize(
    ("lower_deg", "upper_deg"),
    [((0.0, 0.0), (0.0, 0.0)), ((0.034, -0.01), (-0.035, 0.012)), ((-0.5, 0.3), (0.7, -0.2))],
)
def test_the_slide_extensions_take_out_the_layers_lever_arm(
    project: ProjectConfig, lower_deg: tuple[float, float], upper_deg: tuple[float, float]
) -> None:
    """With the layers at their end attitudes, the corrected slide extensions put the
    part's reference point where the plan wants it on the simulator's own chain
    (``pose_from_home``), not ``R_L o - o`` beside it."""
    from types import SimpleNamespace
    from typing import Any, cast

    from ipc_app.control.placement import lever_corrected

    def layer(deg: tuple[float, float]) -> SimpleNamespace:
        return SimpleNamespace(roll1=units.deg(deg[0]), pitch1=units.deg(deg[1]))

    traj = cast(Any, SimpleNamespace(lower=layer(lower_deg), upper=layer(upper_deg)))
    planned = {"rotation": (0.001, -0.001), "lateral": (0.002, 0.002), "central_axis": (0.005,)}
    ext = lever_corrected(project, traj, planned)
    assert ext["rotation"] == planned["rotation"]
    rods = np.array([c.stroke_m / 2 for c in project.cylinders_by_can_index])
    for c in project.cylinders:
        if c.role in ext:
            k = sorted(x.id for x in project.cylinders if x.role == c.role).index(c.id)
            rods[c.can_index] += ext[c.role][k]
    q = np.zeros(6)
    q[1], q[2] = units.deg(lower_deg[0]), units.deg(lower_deg[1])
    q[4], q[5] = units.deg(upper_deg[0]), units.deg(upper_deg[1])
    rig = SimpleNamespace(q=q, rod_positions_m=rods, part_state="carried", bolted_pose=None)
    _r, t = pose_from_home(project, cast(Any, rig))
    assert t[:2] == pytest.approx([0.005, 0.002], abs=1e-9)
    if lower_deg != (0.0, 0.0):  # uncorrected, the lower layer's 0.9 m lever shows
        assert abs(ext["lateral"][0] - 0.002) > 1e-5


@pytest.mark.slow
def test_a_placement_move_reaches_the_planned_target_on_the_truth(
    project: ProjectConfig,
) -> None:
    """The previous part 6 mm left, 6 mm low and turned by 0.03 deg: the target steers
    back by 2 mm; attitude, height, yaw, lateral and gap reach it on the simulator's
    truth within the simulation goals."""
    dev = Pose(y=units.mm(6.0), z=units.mm(-6.0), yaw=units.deg(0.03))
    r = run_place(None, 5, dev, cfg=project)
    assert r["passed"], r.get("goals")
    e = r["error_from_target"]
    # the goal is 1 mm; the slide's lever-arm correction puts it within micrometres
    assert max(abs(e[k]) for k in ("x_mm", "y_mm", "z_mm")) <= 0.02
    assert max(abs(e[k]) for k in ("roll_deg", "pitch_deg", "yaw_deg")) <= 0.01
    assert abs(r["gap_error_mm"]) <= 1.0
    assert abs(r["plan"]["heave_mm"]) > 3.0  # the height did move (6 mm low -> 4 mm)
    assert r["max_sync_error_mm"] < project.safety.max_sync_error_mm
    assert all(v["passed"] is not False for v in r["table4_truth"].values())


@pytest.mark.slow
def test_the_place_run_goes_through_the_services_modes_and_interlocks(tmp_path: Path) -> None:
    """``wara place run`` asks the service for the placement: its run record has the
    placement's events, and a position reading of upper_1 that jumps by 5 mm in the
    attitude phase trips the sync interlock (latched, the valves closed); the run fails
    naming it, with the figures of the truth where the move stopped."""
    from config.hil_scenario import HilScenario
    from ipc_app.service.core import ServiceCore
    from ipc_app.service.interlocks import Interlock
    from ipc_app.service.record import RunRecorder

    jump = {"kind": "sensor", "cylinder": "upper_1", "mode": "jump", "offset": 5.0,
            "start_s": 1.0, "end_s": 10.0}  # fmt: skip
    sc = HilScenario.model_validate({"events": [jump]})
    with RunRecorder(tmp_path / "run", ServiceCore.record_columns(load_project(None))) as rec:
        r = run_place(None, 5, Pose(y=units.mm(6.0), z=units.mm(-6.0)), scenario=sc, record=rec)
    assert not r["passed"] and r["refused"] is None and r["final_mode"] == "ABORTED"
    assert r["missed"] == [f"service ABORTED: {r['fault_reasons'][0]}"]
    assert r["fault_reasons"][0].startswith("sync error: upper")
    lines = (tmp_path / "run" / "events.jsonl").read_text(encoding="utf-8").splitlines()
    events = [json.loads(line) for line in lines if line.strip()]
    kinds = [e["kind"] for e in events]
    assert {"place", "place_phase", "fault"} <= set(kinds) and "place_done" not in kinds
    (fault,) = [e for e in events if e["kind"] == "fault"]
    assert fault["interlock"] == str(Interlock.SYNC_ERROR) and 1.0 <= fault["t_s"] <= 1.1


def test_place_run_refuses_an_unreachable_target() -> None:
    # a child process: the run sets up the service's logging (structlog) for the process
    proc = run_wara(["place", "run", "--lockstep", "--previous-deviation", "9,0,0,0,0"])
    code, out = proc.returncode, proc.stdout
    assert code == 3 and "centreline_deviation_x_mm" in out
