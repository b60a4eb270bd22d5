"""The PLC and its rig agree on walking: the simulated PLC says in ``PLC_Status``
whether its rig can walk (``WalkAvailable``) and refuses WALK when it cannot (the mode
not echoed, the drives kept off); the service refuses a walk, and a ring cycle that
walks, on that word before anything is planned or moved (docs/hil.md, "PLC emulation")."""

from __future__ import annotations

import uuid

import can
import numpy as np
import pytest

from config import ProjectConfig, load_project
from hil_sim.simulator import HilSimulator
from ipc_app.model.placement import Pose
from ipc_app.service.cycle import previous_from_deviation
from ipc_app.service.modes import Mode
from plc_bridge import IpcLink
from plc_bridge import Mode as PlcMode
from wara.harness import Harness
from wara.walk import walk_scenario


def _pair(project: ProjectConfig, walking: bool) -> tuple[HilSimulator, IpcLink]:
    channel = f"walk-refusal-{uuid.uuid4().hex}"
    scenario = walk_scenario() if walking else None
    sim = HilSimulator(project, can.Bus(interface="virtual", channel=channel), scenario, seed=0)
    ipc = IpcLink(project, can.Bus(interface="virtual", channel=channel), clock=sim.clock)
    return sim, ipc


@pytest.mark.parametrize("walking", [False, True])
def test_the_plc_says_whether_its_rig_walks_and_refuses_walk_if_not(
    project: ProjectConfig, walking: bool
) -> None:
    sim, ipc = _pair(project, walking)
    try:
        ipc.set_control(mode=PlcMode.WALK, enable=True)
        for _ in range(100):  # 0.5 s: the control word and valve frames at the loop rate
            ipc.poll()
            ipc.send_valve_commands(np.zeros(len(project.cylinders)))
            sim.step(project.control.period_s)
        status = ipc.status()
        assert status is not None and status.walk_available is walking
        # the walking rig's PLC echoes WALK and drives; the attitude rig's refuses it
        assert status.mode is (PlcMode.WALK if walking else PlcMode.IDLE)
        assert status.drives_enabled is walking
        # and the same request in ATTITUDE_ADJUST is taken by both
        ipc.set_control(mode=PlcMode.ATTITUDE_ADJUST, enable=True)
        for _ in range(20):
            ipc.poll()
            ipc.send_valve_commands(np.zeros(len(project.cylinders)))
            sim.step(project.control.period_s)
        status = ipc.status()
        assert status is not None and status.mode is PlcMode.ATTITUDE_ADJUST
        assert status.drives_enabled
    finally:
        ipc.close()
        sim.close()


def test_the_service_refuses_a_walk_and_a_walking_cycle_the_plc_cannot_do() -> None:
    """The issue's run: ``wara ctl walk --steps 1`` against the attitude rig was accepted
    and ended ABORTED on a stroke end 33 s later; now it is refused at once, nothing moved."""
    cfg = load_project()
    h = Harness(cfg, None, mode="lockstep", trace=False)
    try:
        h.start()
        assert h.wait_for(Mode.IDLE, 20.0), h.fault_note()
        x0 = h.sim.rig.rod_positions_m.copy()
        out = h.core.request_walk(1)
        assert out["ok"] is False and out["code"] == "refused", out
        assert "WalkAvailable 0" in out["error"] and "cannot walk" in out["error"], out
        prev = previous_from_deviation(cfg, 2, Pose())
        cyc = h.core.request_cycle(2, prev, records=_NoRecords(), walk_steps=1, drive=False)
        assert cyc["ok"] is False and "WalkAvailable 0" in cyc["error"], cyc
        h.advance(0.5)
        assert h.core.modes.mode == Mode.IDLE and not h.core.modes.fault_reasons
        assert np.abs(h.sim.rig.rod_positions_m - x0).max() < 1e-4  # nothing moved
        # a cycle that stands at its ring (no walk) is not the PLC's concern
        still = h.core.request_cycle(2, prev, records=_NoRecords(), walk_steps=0, drive=False)
        assert still["ok"] is True, still
    finally:
        h.close()


class _NoRecords:
    def write(self, ring: int, values: dict[str, float | None], attached: dict[str, object]) -> str:
        raise AssertionError("no record is written in this test")
