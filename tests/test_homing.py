"""Homing (``wara ctl home``): each attitude layer to its reference stroke, level, at
rest; the service's path within the trajectory's limits; refused where the modes say
so; end to end on the HIL simulator in lockstep, after an adjustment cut short by a
fault (docs/service.md, "Motions")."""

from __future__ import annotations

import math
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from config import ProjectConfig, load_project, units
from ipc_app.service.app import service_handlers
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import CtlServer
from ipc_app.service.ctl_protocol import Request, parse
from ipc_app.service.interlocks import Cause, Interlock
from ipc_app.service.modes import Mode
from ipc_app.service.motions.homing import HomingMotion
from ipc_app.service.record import RunRecorder, read_run
from tests.machine_inputs import machine_inputs
from tests.test_service_core import _bare_core, _update
from wara.cli import main
from wara.harness import Harness


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    """A directory for a socket (AF_UNIX paths are limited to 107 bytes)."""
    with tempfile.TemporaryDirectory(prefix="wara-home-") as d:
        yield Path(d)


def _attitude(cfg: ProjectConfig) -> list[int]:
    ids = (*cfg.layers.lower.cylinders, *cfg.layers.upper.cylinders)
    return [cfg.cylinder(c).can_index for c in ids]


def _off_home(cfg: ProjectConfig) -> np.ndarray:
    """Rods 30 mm (lower) and -80..+60 mm (upper, tilted) from mid-stroke."""
    x = np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])
    idx = _attitude(cfg)
    x[idx] += np.array([30, 30, 30, 30, -80, -10, 60, -10]) * 1e-3
    return x


def test_the_path_reaches_mid_stroke_within_the_trajectory_limits(project: ProjectConfig) -> None:
    core, _ = _bare_core(project)
    motion = HomingMotion.prepare(core)
    assert isinstance(motion, HomingMotion)
    x = _off_home(project)
    path = motion.path_from(machine_inputs(project, x=x))
    idx = _attitude(project)
    half = np.array([c.stroke_m / 2 for c in project.cylinders_by_can_index])
    lo, up = path.positions(0.0)
    assert lo + up == pytest.approx((x[idx] - half[idx]).tolist())  # from where it stands
    end_lo, end_up = path.positions(path.duration_s)
    assert max(map(abs, end_lo + end_up)) < 1e-12  # mid-stroke
    traj = project.planner.trajectory
    cap = np.array([c.cap_area_m2 for c in project.cylinders_by_can_index])[idx]
    ts = np.linspace(0.0, path.duration_s, 2001)
    speeds = np.array([[*v_lo, *v_up] for _lo, _up, v_lo, v_up in map(path.sample, ts)])
    assert np.abs(speeds).max() <= traj.max_rod_speed_m_s * (1 + 1e-9)
    flow = (cap * np.maximum(speeds, 0.0)).sum(axis=1)  # the extending rods' cap sides
    assert flow.max() <= project.hydraulics.pump_flow_m3_s * (1 + 1e-9)
    accel = np.gradient(speeds, ts, axis=0)
    assert np.abs(accel).max() <= traj.max_rod_accel_m_s2 * 1.01
    # the limit is met, not merely respected: the longest rod goes at the top speed
    assert np.abs(speeds).max() == pytest.approx(traj.max_rod_speed_m_s, rel=1e-2)
    # every rod on one time scaling: the layers' twist shrinks with it
    d = np.array([[*d_lo, *d_up] for d_lo, d_up in map(path.positions, ts)])
    twist = d[:, 4] - d[:, 5] + d[:, 6] - d[:, 7]
    assert np.all(np.diff(np.abs(twist)) <= 1e-12)


def test_home_is_a_motion_of_the_modes_and_the_protocol(project: ProjectConfig) -> None:
    """Refused in MAINTENANCE and while another motion runs; accepted from IDLE, it
    drives the eight attitude cylinders to mid-stroke and holds there (COMPLETE)."""
    assert parse(b'{"cmd": "home"}') == Request("home", ())
    core, _ = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0))
    assert core.request_unit_mode("MAINTENANCE")["accepted"]
    ticket = core.request_motion(HomingMotion)
    _update(core, machine_inputs(project, t=0.1))
    assert ticket.reply is not None and ticket.reply.code == "refused"
    assert "unit mode MAINTENANCE" in str(ticket.reply.error)
    assert core.request_unit_mode("PRODUCTION")["accepted"]
    x = _off_home(project)
    ticket = core.request_motion(HomingMotion)
    _update(core, machine_inputs(project, t=0.2, x=x))
    assert ticket.started and core.modes.mode is Mode.EXECUTE
    again = core.request_motion(HomingMotion)
    _update(core, machine_inputs(project, t=0.205, x=x))
    assert again.reply is not None and "home refused in EXECUTE" in str(again.reply.error)
    motion = ticket.motion
    assert isinstance(motion, HomingMotion) and motion.home_path is not None
    assert (motion.status() or {})["from_mm"] == pytest.approx(80.0)
    path = motion.home_path
    t_end = 0.2 + path.duration_s
    _update(core, machine_inputs(project, t=t_end + 0.005, x=x))
    assert core.modes.mode is Mode.COMPLETE and core.modes.valves_enabled
    idx = _attitude(project)
    mid = np.array([c.stroke_m / 2 for c in project.cylinders_by_can_index])
    assert core.attitude.references(t_end + 1.0)[idx] == pytest.approx(mid[idx])


@pytest.mark.slow
def test_wara_ctl_home_after_a_fault_on_the_simulator(tmp_path: Path, short_tmp: Path) -> None:
    """An adjustment cut short by a fault leaves the platform tilted; after the reset,
    ``wara ctl home`` (the CLI on the service's socket) brings each layer to mid-stroke
    on the simulator's truth: level (the workpiece at the base's attitude), at rest,
    the rods never faster than the trajectory's limit; the pose is held."""
    cfg = load_project(None)
    rec = RunRecorder(tmp_path / "run", ServiceCore.record_columns(cfg))
    rec.start()
    h = Harness(cfg, None, mode="lockstep", record=rec)
    idx = _attitude(cfg)
    half = np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])
    try:
        h.start()
        assert h.wait_for(Mode.IDLE, 20.0), h.fault_note()
        assert h.core.request_adjust(-3.0, 2.0)["ok"]
        assert h.wait_for(Mode.EXECUTE, 10.0), h.fault_note()
        h.advance(5.0)
        h.core.modes.fault(Cause(Interlock.PLANNER, detail="a fault for the test"))
        h.advance(0.5)
        off_mm = units.to_mm(float(np.abs(h.sim.rig.rod_positions_m[idx] - half[idx]).max()))
        assert off_mm > 20.0  # mid-way: the upper layer tilted
        h.core.request_reset()
        assert h.wait_for(Mode.IDLE, 5.0, stop_on_fault=False), h.fault_note()
        handlers = service_handlers(lambda: h.core, lambda: server, wait_s=0.0)
        with CtlServer(handlers, short_tmp / "home.sock") as server:
            assert main(["ctl", "--socket", str(server.path), "home"]) == 0
        fastest = 0.0
        for _ in range(4000):  # at most 20 s
            h.advance(h.period)
            fastest = max(fastest, float(np.abs(h.sim.rig.rod_velocities_m_s[idx]).max()))
            if h.core.modes.mode is not Mode.EXECUTE:
                break
        assert h.core.modes.mode is Mode.COMPLETE, h.fault_note()
        h.advance(2.0)
        rods_mm = units.to_mm(h.sim.rig.rod_positions_m[idx] - half[idx])
        speed_mm_s = units.to_mm(float(np.abs(h.sim.rig.rod_velocities_m_s[idx]).max()))
        truth = h.sim.truth()
        status: dict[str, Any] = h.core.snapshot()
    finally:
        h.close()
        rec.stop()
    assert np.abs(rods_mm).max() < 0.01  # each layer at its reference stroke
    assert speed_mm_s < 0.01  # at rest
    base = (cfg.base.roll_rad, cfg.base.pitch_rad)
    level = max(abs(truth.workpiece_roll_rad - base[0]), abs(truth.workpiece_pitch_rad - base[1]))
    assert math.degrees(level) < 0.001
    assert fastest <= cfg.planner.trajectory.max_rod_speed_m_s * 1.05
    assert status["mode"] == "COMPLETE" and status["valves_enabled"]
    assert status["motion"]["max_twist_mm"] < 0.5
    assert status["home"]["from_mm"] == pytest.approx(off_mm, abs=0.1)
    events = read_run(tmp_path / "run").events
    (home,) = [e for e in events if e["kind"] == "mode" and e["event"] == "home"]
    assert (home["from_mode"], home["to_mode"]) == ("IDLE", "EXECUTE")
    assert home["reason"] == "home each attitude layer to mid-stroke, level"
