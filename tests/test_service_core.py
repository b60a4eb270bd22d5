"""The service core on real parts: a python-can virtual bus, the PLC side of the
protocol (PlcLink) driving the real cylinder model for all 19 cylinders, the real planner
worker process. (The full rigid-platform rig is hil_sim's; see the end-to-end tests.)"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from typing import Any

import can
import numpy as np
import pytest

from config import ProjectConfig
from hil_sim.hydraulics import CylinderBank, CylinderParams
from ipc_app.model import MachineStatics
from ipc_app.service.core import ServiceCore
from ipc_app.service.interlocks import Cause, Interlock
from ipc_app.service.modes import Mode
from ipc_app.service.worker import PlannerWorker
from plc_bridge.link import IpcLink, PlcLink, PlcStatus

_channels = itertools.count()


class MiniRig:
    """Stand-in PLC + rig: every cylinder standalone with its static share of the load."""

    def __init__(self, cfg: ProjectConfig, bus: can.BusABC, clock: list[float]) -> None:
        self.cfg = cfg
        self.clock = clock
        self.plc = PlcLink(cfg, bus, clock=lambda: clock[0])
        cyls = cfg.cylinders_by_can_index
        self.bank = CylinderBank(CylinderParams.from_config(cyls, cfg.hydraulics), step_s=0.5e-3)
        fl, fu = MachineStatics(cfg).forces(0.0, 0.0, 0.0, 0.0)
        self.load = np.full(len(cyls), 5e3)
        for i, cid in enumerate(cfg.layers.lower.cylinders):
            self.load[cfg.cylinder(cid).can_index] = fl[i]
        for i, cid in enumerate(cfg.layers.upper.cylinders):
            self.load[cfg.cylinder(cid).can_index] = fu[i]
        self.bank.hold_at(np.array([c.stroke_m / 2 for c in cyls]), self.load)
        self.silent = False

    def step(self, dt: float) -> None:
        now = self.clock[0]
        if self.silent:
            self.bank.advance(np.zeros(self.bank.n), self.load, dt)
            return
        self.plc.poll(now)
        word = self.plc.control(now)
        u = np.nan_to_num(self.plc.valve_commands(now).value)
        if word is None or not word.enable:
            u = np.zeros_like(u)
        self.bank.advance(u, self.load, dt)
        self.plc.set_positions_m(self.bank.x_m)
        self.plc.set_pressures_pa(np.stack([self.bank.p_a_pa, self.bank.p_b_pa], axis=1))
        self.plc.set_status(PlcStatus(pump_running=True, drives_enabled=True))


@pytest.fixture(scope="module")
def worker() -> Iterator[PlannerWorker]:
    w = PlannerWorker(None, timeout_s=30.0)
    w.start()
    yield w
    w.close()


def _setup(cfg: ProjectConfig, worker: PlannerWorker) -> tuple[ServiceCore, MiniRig, list[float]]:
    ch = f"core-test-{next(_channels)}"
    clock = [0.0]
    rig = MiniRig(cfg, can.Bus(interface="virtual", channel=ch), clock)
    link = IpcLink(cfg, can.Bus(interface="virtual", channel=ch), clock=lambda: clock[0])
    return ServiceCore(cfg, link, worker), rig, clock


def _run(
    core: ServiceCore, rig: MiniRig, clock: list[float], seconds: float, until: Mode | None = None
) -> int:
    dt = core.period_s
    n = round(seconds / dt)
    for k in range(n):
        rig.step(dt)
        clock[0] += dt
        core.step(k, clock[0])
        if until is not None and core.modes.mode == until:
            return k
        if core.modes.mode == Mode.PLANNING:
            time.sleep(0.002)  # the planner process works in wall-clock time
    return n


def test_adjusts_to_example_1_and_holds(project: ProjectConfig, worker: PlannerWorker) -> None:
    core, rig, clock = _setup(project, worker)
    _run(core, rig, clock, 0.5)
    assert core.modes.mode == Mode.IDLE, core.modes.snapshot()
    assert core.request_adjust(2.0, 1.0)["ok"]
    _run(core, rig, clock, 30.0, until=Mode.ADJUSTING)
    assert core.modes.mode == Mode.ADJUSTING, core.modes.snapshot()
    _run(core, rig, clock, 60.0, until=Mode.HOLDING)
    assert core.modes.mode == Mode.HOLDING
    _run(core, rig, clock, 2.0)
    x = rig.bank.x_m
    roll, pitch = core.achieved_attitude_deg(x)
    assert roll == pytest.approx(2.0, abs=0.01) and pitch == pytest.approx(1.0, abs=0.01)
    assert core.motion.max_twist_m < 0.5e-3
    assert core.motion.hold_samples > 0


def test_silent_plc_faults_within_stated_cycles(
    project: ProjectConfig, worker: PlannerWorker
) -> None:
    core, rig, clock = _setup(project, worker)
    _run(core, rig, clock, 0.5)
    assert core.modes.mode == Mode.IDLE
    rig.silent = True
    # the shorter of the positions' and the status' timeout plus two cycles
    s = project.safety
    limit = int(min(s.sensor_timeout_ms, s.plc_heartbeat_timeout_ms) / 1e3 / core.period_s) + 2
    k = _run(core, rig, clock, 1.0, until=Mode.FAULT)
    assert core.modes.mode == Mode.FAULT and k <= limit, (k, limit)
    assert core.modes.fault_interlocks[0] in (Interlock.SENSOR_TIMEOUT, Interlock.PLC_HEARTBEAT)
    _run(core, rig, clock, 0.1)
    assert {Interlock.SENSOR_TIMEOUT, Interlock.PLC_HEARTBEAT} <= set(core.modes.fault_interlocks)
    # reset is refused while the cause is present
    assert not core.modes.reset().accepted
    rig.silent = False
    _run(core, rig, clock, 0.5)
    assert core.modes.reset().accepted
    assert core.modes.mode == Mode.IDLE


def test_pressure_and_stroke_end_checks_name_the_cylinder(
    project: ProjectConfig, worker: PlannerWorker
) -> None:

    core, _, _ = _setup(project, worker)
    status = PlcStatus(pump_running=True, drives_enabled=True)
    n = len(project.cylinders)
    p = np.full((n, 2), 10e6)
    valid = np.ones((n, 2), dtype=bool)
    assert core._conditions(True, status, p, valid) == []
    i = core.active[5]
    p[i, 1] = core.max_pressure_pa + 1e6
    p[core.active[0], 0] = np.nan  # an invalid reading is never the peak
    valid[core.active[0], 0] = False
    (cause,) = core._conditions(True, status, p, valid)
    assert cause.key == (Interlock.PRESSURE, project.cylinders_by_can_index[i].id)
    assert cause.value == pytest.approx(project.safety.max_pressure_mpa + 1.0)
    assert cause.limit == project.safety.max_pressure_mpa

    faults: list[Cause] = []
    core.modes.fault = faults.append  # type: ignore[method-assign,assignment]
    x = core.stroke / 2
    core._motion_checks(x)
    assert faults == []
    j = core.active[6]
    x = x.copy()
    x[j] = core.stroke[j] - core.end_margin_m / 2
    core._motion_checks(x)
    (cause,) = faults
    assert cause.key == (Interlock.STROKE_END, project.cylinders_by_can_index[j].id)
    assert cause.value == pytest.approx(project.safety.stroke_end_margin_mm / 2)


def test_interlock_checks_match_their_former_numpy_form(
    project: ProjectConfig, worker: PlannerWorker
) -> None:
    """The pressure peak (one reduction) and the stroke-end check (plain floats, the switch
    mask once per word) give the messages of the former numpy definitions (kept here)."""
    from plc_bridge.link import LimitSwitches

    core, _, _ = _setup(project, worker)
    rng = np.random.default_rng(3)
    status = PlcStatus(pump_running=True, drives_enabled=True)
    n = len(project.cylinders)
    lim = core.max_pressure_pa

    def former_pressure(p: np.ndarray, valid: np.ndarray) -> list[tuple[Interlock, str]]:
        if valid.any():
            pv = np.where(valid, p, 0.0)
            if float(pv.max()) > lim:
                i = int(np.argmax(pv.max(axis=1)))
                return [(Interlock.PRESSURE, project.cylinders_by_can_index[i].id)]
        return []

    hits = 0
    for k in range(400):
        p = rng.uniform(-1e6, lim * (1.1 if k % 2 else 0.99), (n, 2))
        p[rng.random((n, 2)) < (0.3 if k % 3 else 1.0)] = np.nan  # some or all invalid
        valid = ~np.isnan(p)
        got = core._conditions(True, status, p, valid)
        want = former_pressure(p, valid)
        assert [c.key for c in got] == want
        hits += len(want)
    assert 50 < hits < 350  # both outcomes exercised

    idx = core.active
    faults: list[Cause] = []
    core.modes.fault = faults.append  # type: ignore[method-assign,assignment]
    switches: list[LimitSwitches | None] = [None]
    core.link.limit_switches = lambda now=None: switches[0]  # type: ignore[method-assign]

    def former_stroke(x: np.ndarray, limits: LimitSwitches | None) -> list[tuple[Any, ...]]:
        xa = x[core._active_arr]
        near = (xa < core.end_margin_m) | (xa > core._stroke_hi)
        if limits is not None:
            near |= limits.retracted[core._active_arr] | limits.extended[core._active_arr]
        if near.any():
            i = idx[int(np.argmax(near))]
            cid = project.cylinders_by_can_index[i].id
            v = float(x[i])
            return [(Interlock.STROKE_END, cid, min(v, core.stroke[i] - v) * 1e3)]
        return []

    core.attitude.metrics = {}  # only the stroke-end part
    hits = 0
    for k in range(400):
        x = core.stroke * rng.uniform(-0.002, 1.002, n)
        if k % 4 == 0:
            x = core.stroke / 2
        if k % 5 == 0:
            switches[0] = LimitSwitches(rng.random(n) < 0.05, rng.random(n) < 0.05)
        elif k % 5 == 1:
            switches[0] = None
        faults.clear()
        core._motion_checks(x)
        got = [(c.interlock, c.where, pytest.approx(c.value)) for c in faults]
        assert got == former_stroke(x, switches[0]), k
        hits += len(faults)
    assert 50 < hits < 350


def test_status_carries_the_link_receive_counters(
    project: ProjectConfig, worker: PlannerWorker
) -> None:
    core, rig, clock = _setup(project, worker)
    _run(core, rig, clock, 0.5)
    before = core.snapshot()["link_rx"]
    assert before["received"] == sum(v for k, v in before.items() if k != "received") > 0
    assert before["crc_error"] == before["unknown_id"] == 0
    # A PLC_Status with a wrong CRC and a frame of an id nobody sends, from a third node.
    ch = core.link.bus.channel_id  # type: ignore[attr-defined]  # the virtual bus
    with can.Bus(interface="virtual", channel=ch) as third:
        good = rig.plc._codec_by_name["PLC_Status"].encode(7, [1, 0, 1, 1, 0, 0, 16.0])
        third.send(can.Message(arbitration_id=0x090, data=bytes([good[0] ^ 0x5A]) + good[1:],
                               is_extended_id=False))  # fmt: skip
        third.send(can.Message(arbitration_id=0x191, data=bytes(8), is_extended_id=False))
        _run(core, rig, clock, 0.05)
    after = core.snapshot()["link_rx"]
    assert after["crc_error"] - before["crc_error"] == 1
    assert after["unknown_id"] - before["unknown_id"] == 1
    assert after["received"] == sum(v for k, v in after.items() if k != "received")
