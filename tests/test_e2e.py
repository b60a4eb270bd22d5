"""End to end on the harness's in-process bus: the HIL simulator (rig + PLC) and the IPC
service core in lockstep, with the real planner worker process and a real run record.

Each interlock and each simulator fault leads to the specified safe state within a
stated number of control cycles (5 ms each), the valves are commanded closed from then
on, and the run record holds every cycle and the transition.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from config import ProjectConfig, default_project_path, load_project
from config.hil_scenario import HilScenario
from config.loader import validate_data
from ipc_app.service.interlocks import Interlock
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder, read_run
from ipc_app.service.worker import PlannerWorker
from plc_bridge.link import Fault
from tests.service_helpers import CRASH_ROLL_DEG
from wara.examples import ATTITUDE_TOL_DEG, SYNC_TOL_MM, TWIST_TOL_MM
from wara.harness import Harness

pytestmark = pytest.mark.slow

FAULT_AT_S = 3.0  # simulated time of the fault: Example 1 (2, 1) deg is moving then


@pytest.fixture(scope="module")
def planner() -> Iterator[PlannerWorker]:
    w = PlannerWorker(None, timeout_s=30.0)
    w.start()
    yield w
    w.close()


def _scenario(*events: dict[str, Any]) -> HilScenario:
    return validate_data(HilScenario, {"events": list(events)}, "test scenario")


def _project(tmp_path: Path, **safety: Any) -> ProjectConfig:
    if not safety:
        return load_project()
    data = yaml.safe_load(default_project_path().read_text())
    data["safety"].update(safety)
    # The schema only: a pressure limit below the static load (7 MPa) is what provokes
    # the interlock here, and the loader's cross-check refuses it (config.crosscheck).
    return validate_data(ProjectConfig, data, "project.yaml")


class Run:
    """One lockstep run: boot, adjust to Example 1, then watch."""

    def __init__(
        self, cfg: ProjectConfig, planner: PlannerWorker, tmp_path: Path, scenario: HilScenario
    ) -> None:
        from ipc_app.service.core import ServiceCore

        self.record = RunRecorder(tmp_path / "run", ServiceCore.record_columns(cfg))
        self.record.start()
        self.demo = Harness(
            cfg, mode="lockstep", scenario=scenario, record=self.record, planner=planner
        )
        self.cycles = 0
        self.sent_after_fault: list[np.ndarray] = []

    def step(self) -> None:
        d = self.demo
        d.advance(d.period)
        self.cycles += 1

    def until(self, pred: Any, max_s: float) -> int | None:
        n = round(max_s / self.demo.period)
        for k in range(n):
            if pred():
                return k
            self.step()
        return None

    def start_motion(self) -> None:
        d = self.demo
        assert self.until(lambda: d.core.modes.mode == Mode.IDLE, 5.0) is not None
        assert d.core.request_adjust(2.0, 1.0)["ok"]
        assert self.until(lambda: d.core.modes.mode == Mode.EXECUTE, 30.0) is not None
        assert d.sim.t_s < FAULT_AT_S, "motion must start before the fault"
        assert self.until(lambda: d.sim.t_s >= FAULT_AT_S, FAULT_AT_S) is not None

    def close(self) -> dict[str, Any]:
        self.demo.close()
        return self.record.stop()


def _safe_state(
    run: Run, expected: Mode, interlocks: frozenset[Interlock], max_cycles: int
) -> None:
    core = run.demo.core
    k = run.until(lambda: core.modes.mode == expected, max_cycles * core.period_s + 1e-9)
    assert k is not None, (core.modes.mode, core.modes.fault_reasons)
    assert k <= max_cycles
    if interlocks:  # the first latched cause is one of the specified reactions
        assert core.modes.fault_interlocks[0] in interlocks, core.modes.fault_reasons
    # From then on the IPC commands every valve closed, and the PLC applies nothing.
    for _ in range(20):
        run.step()
        assert not core.modes.valves_enabled
    assert np.all(run.demo.sim.truth().applied_command == 0.0)


_SENSOR_TIMEOUT_CYCLES = 22  # safety.sensor_timeout_ms (100) / 5 ms + 2
_LOST = frozenset({Interlock.SENSOR_TIMEOUT})
_ALL_LOST = frozenset({Interlock.SENSOR_TIMEOUT, Interlock.PLC_HEARTBEAT})
_SYNC_OR_TRACKING = frozenset({Interlock.SYNC_ERROR, Interlock.TRACKING_ERROR})

CASES = [
    # (fault event, safe mode, the first interlock is one of, max cycles after the fault).
    # A lost input suspends the motion first and faults once the loss is longer than
    # its timeout.
    ({"kind": "plc_silent", "start_s": FAULT_AT_S}, Mode.ABORTED, _ALL_LOST, 22),
    ({"kind": "bus_off", "start_s": FAULT_AT_S}, Mode.ABORTED, _ALL_LOST, 22),
    (
        {"kind": "drop", "start_s": FAULT_AT_S, "rate": 1.0, "messages": ["PLC_RodPos_*"]},
        Mode.ABORTED,
        _LOST,
        _SENSOR_TIMEOUT_CYCLES,
    ),
    (
        {"kind": "bad_crc", "start_s": FAULT_AT_S, "messages": ["PLC_RodPos_*"]},
        Mode.ABORTED,
        _LOST,
        _SENSOR_TIMEOUT_CYCLES,
    ),
    (
        {"kind": "frozen_counter", "start_s": FAULT_AT_S, "messages": ["PLC_RodPos_*"]},
        Mode.ABORTED,
        _LOST,
        _SENSOR_TIMEOUT_CYCLES,
    ),
    (
        # (the wire keeps the order: the frames behind the delayed ones wait too)
        {"kind": "delay", "start_s": FAULT_AT_S, "delay_ms": 200, "messages": ["PLC_RodPos_*"]},
        Mode.ABORTED,
        _ALL_LOST,
        _SENSOR_TIMEOUT_CYCLES,
    ),
    (
        {"kind": "sensor", "start_s": FAULT_AT_S, "cylinder": "upper_2", "mode": "fail"},
        Mode.ABORTED,
        frozenset({Interlock.SENSOR}),
        5,
    ),
    (
        {
            "kind": "sensor",
            "start_s": FAULT_AT_S,
            "cylinder": "upper_3",
            "mode": "jump",
            "offset": 5.0,
        },
        Mode.ABORTED,
        frozenset({Interlock.SYNC_ERROR}),
        5,
    ),
    (
        {"kind": "sensor", "start_s": FAULT_AT_S, "cylinder": "upper_2", "mode": "stuck"},
        Mode.ABORTED,
        _SYNC_OR_TRACKING,
        100,
    ),
    (
        {"kind": "stuck_valve", "start_s": FAULT_AT_S, "cylinder": "upper_2", "opening": 0.0},
        Mode.ABORTED,
        _SYNC_OR_TRACKING,
        100,
    ),
    (
        {"kind": "ignore_commands", "start_s": FAULT_AT_S},
        Mode.ABORTED,
        _SYNC_OR_TRACKING,
        100,
    ),
    ({"kind": "estop", "start_s": FAULT_AT_S}, Mode.ABORTED, frozenset(), 8),
    # Stalls longer than the timeouts: no longer a short loss.
    (
        {"kind": "plc_stall", "start_s": FAULT_AT_S, "end_s": FAULT_AT_S + 0.3},
        Mode.ABORTED,
        _ALL_LOST,
        _SENSOR_TIMEOUT_CYCLES,
    ),
    (
        {
            "kind": "wire_stall",
            "start_s": FAULT_AT_S,
            "end_s": FAULT_AT_S + 0.3,
            "direction": "plc_to_ipc",
        },
        Mode.ABORTED,
        _ALL_LOST,
        _SENSOR_TIMEOUT_CYCLES,
    ),
    # commands held: the PLC centres the spools at once and latches IPC_TIMEOUT after
    # safety.command_timeout_ms (100 ms = 20 cycles) plus its status cycle (20 ms)
    (
        {
            "kind": "wire_stall",
            "start_s": FAULT_AT_S,
            "end_s": FAULT_AT_S + 0.3,
            "direction": "ipc_to_plc",
        },
        Mode.ABORTED,
        frozenset({Interlock.PLC_FAULT}),
        26,
    ),
]


@pytest.mark.parametrize(
    ("event", "mode", "interlocks", "max_cycles"),
    CASES,
    ids=[f"{c[0]['kind']}-{c[0].get('mode', '')}" for c in CASES],
)
def test_fault_leads_to_safe_state(
    planner: PlannerWorker,
    tmp_path: Path,
    event: dict[str, Any],
    mode: Mode,
    interlocks: frozenset[Interlock],
    max_cycles: int,
) -> None:
    run = Run(load_project(), planner, tmp_path, _scenario(event))
    try:
        run.start_motion()
        _safe_state(run, mode, interlocks, max_cycles)
    finally:
        summary = run.close()
    _record_is_complete(tmp_path / "run", run.cycles, summary, mode)
    if interlocks:  # each latched cause is an event of its own, from the data
        faults = [e for e in read_run(tmp_path / "run").events if e["kind"] == "fault"]
        assert faults and faults[0]["interlock"] in {str(i) for i in interlocks}
        assert len({(e["interlock"], e["where"]) for e in faults}) == len(faults)


#: Cycles from the end of a stall to the motion going on: the first frame after a
#: timeout only re-synchronizes its alive counter, then RESUME_FRESH_CYCLES fresh cycles.
RESUME_WITHIN_CYCLES = 8

RIDE_CASES = [
    # (stall, from start_s to end_s; suspends expected: min, max)
    ({"kind": "plc_stall", "start_s": FAULT_AT_S, "end_s": FAULT_AT_S + 0.01}, (0, 1)),
    ({"kind": "plc_stall", "start_s": FAULT_AT_S, "end_s": FAULT_AT_S + 0.05}, (1, 1)),
    ({"kind": "wire_stall", "start_s": FAULT_AT_S, "end_s": FAULT_AT_S + 0.01}, (0, 1)),
    ({"kind": "wire_stall", "start_s": FAULT_AT_S, "end_s": FAULT_AT_S + 0.05}, (1, 1)),
    (
        {
            "kind": "wire_stall",
            "start_s": FAULT_AT_S,
            "end_s": FAULT_AT_S + 0.05,
            "direction": "ipc_to_plc",
        },
        (1, 1),
    ),
]


@pytest.mark.parametrize(
    ("event", "suspends"),
    RIDE_CASES,
    ids=[
        f"{c[0]['kind']}-{c[0].get('direction', 'both')}-"
        f"{round((c[0]['end_s'] - c[0]['start_s']) * 1000)}ms"
        for c in RIDE_CASES
    ],
)
def test_short_stall_is_ridden_through(
    planner: PlannerWorker, tmp_path: Path, event: dict[str, Any], suspends: tuple[int, int]
) -> None:
    """A stall during Example 1's motion: the motion is suspended (valves closed, the
    trajectory clock stopped) and resumes by itself within RESUME_WITHIN_CYCLES of the
    stall's end; the example still meets its goals. Each suspend and resume is in the
    run record and the status."""
    run = Run(load_project(), planner, tmp_path, _scenario(event))
    try:
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 5.0) is not None
        res = d.run_example(2.0, 1.0)
        core = d.core
        assert res.passed, (res, core.modes.fault_reasons)
        ride = core.snapshot()["ride_through"]
        assert suspends[0] <= ride["suspends"] <= suspends[1], ride
        assert ride["resumes"] == ride["suspends"]
    finally:
        run.close()
    events = read_run(tmp_path / "run").events
    sus = [e for e in events if e["kind"] == "suspended"]
    res_ = [e for e in events if e["kind"] == "resumed"]
    assert len(sus) == len(res_) == ride["suspends"]
    for s_ev, r_ev in zip(sus, res_, strict=True):
        assert s_ev["reason"] and event["start_s"] <= s_ev["t_s"] < event["end_s"] + 0.02
        assert r_ev["suspended_s"] == pytest.approx(r_ev["t_s"] - s_ev["t_s"])
        after_end = (r_ev["t_s"] - event["end_s"]) / core.period_s
        assert after_end <= RESUME_WITHIN_CYCLES, after_end
    # in motion as long as planned (the stand-still is shifted out), the shift no more
    # than the suspension
    plan = d.core.motion.plan or {}
    assert res.duration_s == pytest.approx(plan["trajectory_duration_s"], abs=2 * core.period_s)
    for r_ev in res_:
        assert 0.0 <= r_ev["shift_s"] <= r_ev["suspended_s"] + core.period_s


def _record_is_complete(path: Path, cycles: int, summary: dict[str, Any], mode: Mode) -> None:
    data = read_run(path)
    assert summary.get("rows_dropped", 0) == 0
    assert len(data.t_s) >= cycles  # every stepped cycle, plus the boot cycles
    assert np.all(np.diff(data.t_s) > 0)
    kinds = [(e.get("kind"), e.get("to_mode")) for e in data.events]
    assert ("mode", str(mode)) in kinds, kinds
    assert json.dumps(data.events)  # JSON-ready


@pytest.mark.parametrize(
    ("safety", "interlock"),
    [
        ({"max_pressure_mpa": 7.0}, Interlock.PRESSURE),
        ({"max_twist_mm": 0.5, "max_sync_error_mm": 50.0}, Interlock.TWIST),
    ],
)
def test_limit_interlocks(
    planner: PlannerWorker, tmp_path: Path, safety: dict[str, float], interlock: Interlock
) -> None:
    cfg = _project(tmp_path, **safety)
    # The twist case: one position sensor jumps 4 mm, i.e. 1 mm of measured twist.
    events = (
        [
            {
                "kind": "sensor",
                "start_s": FAULT_AT_S,
                "cylinder": "upper_3",
                "mode": "jump",
                "offset": 4.0,
            }
        ]
        if interlock is Interlock.TWIST
        else []
    )
    run = Run(cfg, planner, tmp_path, _scenario(*events))
    try:
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 5.0) is not None
        assert d.core.request_adjust(2.0, 1.0)["ok"]
        k = run.until(lambda: d.core.modes.mode == Mode.ABORTED, 12.0)
        assert k is not None, d.core.modes.snapshot()
        assert interlock in d.core.modes.fault_interlocks
    finally:
        run.close()


def test_planner_crash_is_a_fault(tmp_path: Path) -> None:
    crash = PlannerWorker(None, timeout_s=10.0, plan_fn="tests.service_helpers:misbehaving_plan")
    crash.start()
    run = Run(load_project(), crash, tmp_path, _scenario())
    try:
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 5.0) is not None
        assert d.core.request_adjust(CRASH_ROLL_DEG, 1.0)["ok"]  # the planner process dies
        assert run.until(lambda: d.core.modes.mode == Mode.ABORTED, 60.0) is not None
        assert d.core.modes.fault_interlocks == (Interlock.PLANNER,)
    finally:
        run.close()
        crash.close()


def test_infeasible_target_is_refused_with_reasons(planner: PlannerWorker, tmp_path: Path) -> None:
    run = Run(load_project(), planner, tmp_path, _scenario())
    try:
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 5.0) is not None
        assert d.core.request_adjust(30.0, 2.0)["ok"]
        assert run.until(lambda: d.core.modes.mode != Mode.STARTING, 30.0) is not None
        assert d.core.modes.mode == Mode.IDLE
        assert "stroke" in d.core.modes.snapshot()["message"]
    finally:
        run.close()


@pytest.mark.parametrize(
    "event",
    [
        {
            "kind": "leakage",
            "start_s": 1.0,
            "cylinder": "upper_4",
            "internal_leakage_m3_s_pa": 5.0e-11,
        },
        {
            "kind": "load_step",
            "start_s": FAULT_AT_S,
            "layer": "upper",
            "mass_kg": 2000,
            "cog_m": [0.5, 0.3, 1.0],
        },
        # Non-critical frames: the link is DEGRADED, the motion goes on. (Random drops of
        # the 200 Hz position frames make a reading stale after two in a row: a fault.)
        {"kind": "drop", "start_s": 1.0, "rate": 0.2, "messages": ["PLC_Pressure_*"]},
    ],
    ids=["raised-leakage", "load-step", "drop-20-percent-pressures"],
)
def test_disturbances_are_ridden_through(
    planner: PlannerWorker, tmp_path: Path, event: dict[str, Any]
) -> None:
    run = Run(load_project(), planner, tmp_path, _scenario(event))
    try:
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 5.0) is not None
        res = d.run_example(2.0, 1.0)
        assert res.passed, res
    finally:
        run.close()


def test_examples_reach_their_targets(planner: PlannerWorker, tmp_path: Path) -> None:
    run = Run(load_project(), planner, tmp_path, _scenario())
    try:
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 5.0) is not None
        for roll, pitch in ((2.0, 1.0), (-3.0, 2.0), (5.0, -1.0)):
            res = d.run_example(roll, pitch)
            assert res.passed, res
            assert res.attitude_error_deg <= ATTITUDE_TOL_DEG
            assert res.max_twist_mm <= TWIST_TOL_MM
            assert res.sync_error_mm <= SYNC_TOL_MM
    finally:
        run.close()


def test_hmi_target_from_the_plc_is_planned_executed_and_acknowledged(
    planner: PlannerWorker, tmp_path: Path
) -> None:
    event = {"kind": "hmi_target", "at_s": 1.0, "roll_deg": -3.0, "pitch_deg": 2.0}
    run = Run(load_project(), planner, tmp_path, _scenario(event))
    try:
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.EXECUTE, 30.0) is not None
        assert d.core.modes.target_deg == pytest.approx((-3.0, 2.0))
        assert run.until(lambda: d.core.modes.mode == Mode.COMPLETE, 60.0) is not None
        run.until(lambda: d.sim.hmi_ack is not None and d.sim.hmi_ack[1].name == "COMPLETED", 1.0)
        assert d.sim.hmi_ack is not None and d.sim.hmi_ack[1].name == "COMPLETED"
        roll = np.degrees(d.sim.truth().workpiece_roll_rad)
        assert roll == pytest.approx(-3.0, abs=ATTITUDE_TOL_DEG)
    finally:
        run.close()


def test_hmi_acks_carry_the_seq_of_their_own_request(
    planner: PlannerWorker, tmp_path: Path
) -> None:
    """An HMI target refused while ADJUSTING is answered REJECTED with its own TargetSeq
    and leaves the running one's (its COMPLETED carries its own); a later local request
    is not acknowledged to the PLC with the old HMI sequence number."""
    events = [
        {"kind": "hmi_target", "at_s": 0.5, "roll_deg": 2.0, "pitch_deg": 1.0},
        {"kind": "hmi_target", "at_s": 2.0, "roll_deg": -3.0, "pitch_deg": 2.0},
    ]
    run = Run(load_project(), planner, tmp_path, _scenario(*events))
    acks: list[tuple[int, str]] = []

    def watch() -> bool:
        c = run.demo.link.control
        if c.ack_seq and (not acks or acks[-1] != (c.ack_seq, c.ack_status.name)):
            acks.append((c.ack_seq, c.ack_status.name))
        return False

    try:
        d = run.demo
        assert run.until(lambda: watch() or d.core.modes.mode == Mode.EXECUTE, 30.0) is not None
        assert run.until(lambda: watch() or d.core.modes.mode == Mode.COMPLETE, 30.0) is not None
        assert d.sim.hmi_issued == [1, 2]  # one TargetSeq per event, once
        assert acks == [(1, "ACCEPTED"), (2, "REJECTED"), (1, "COMPLETED")], acks
        assert d.core.modes.target_deg == pytest.approx((2.0, 1.0))
        # a local request, planned and run: the PLC's ack stays the HMI's last answer
        assert d.core.request_adjust(2.5, 1.0)["ok"]
        assert run.until(lambda: watch() or d.core.modes.mode == Mode.EXECUTE, 30.0) is not None
        assert run.until(lambda: watch() or d.core.modes.mode == Mode.COMPLETE, 30.0) is not None
        assert acks == [(1, "ACCEPTED"), (2, "REJECTED"), (1, "COMPLETED")], acks
    finally:
        run.close()


def test_reset_clears_the_plcs_own_fault(planner: PlannerWorker, tmp_path: Path) -> None:
    """Commands lost on the way to the PLC while moving: the PLC latches IPC_TIMEOUT and
    closes the valves; the service faults on it. ``reset`` pulses fault_reset to the PLC
    and returns to IDLE once the PLC has cleared it."""
    event = {
        "kind": "drop",
        "start_s": FAULT_AT_S,
        "end_s": FAULT_AT_S + 0.5,
        "rate": 1.0,
        "direction": "ipc_to_plc",
        "messages": ["IPC_*"],
    }
    run = Run(load_project(), planner, tmp_path, _scenario(event))
    try:
        run.start_motion()
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.ABORTED, 2.0) is not None
        timeout = (Interlock.PLC_FAULT, Fault.IPC_TIMEOUT.name)
        run.until(lambda: timeout in [(f.interlock, f.where) for f in d.core.modes.faults], 1.0)
        assert timeout in [(f.interlock, f.where) for f in d.core.modes.faults]
        run.until(lambda: d.sim.t_s > FAULT_AT_S + 1.0, 2.0)  # the wire is healthy again
        # Without fault_reset the PLC keeps its fault, so a plain reset is refused.
        assert not d.core.modes.reset().accepted
        assert d.core.request_reset()["ok"]
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 2.0) is not None
        assert d.sim.truth().status.fault == 0
    finally:
        run.close()


def test_estop_released_then_reset_returns_to_idle(planner: PlannerWorker, tmp_path: Path) -> None:
    event = {"kind": "estop", "start_s": FAULT_AT_S, "end_s": FAULT_AT_S + 0.5}
    run = Run(load_project(), planner, tmp_path, _scenario(event))
    try:
        run.start_motion()
        d = run.demo
        assert run.until(lambda: d.core.modes.mode == Mode.ABORTED, 0.1) is not None
        # Still pressed: the reset is refused.
        refused = d.core.request_reset()
        run.until(lambda: False, 0.1)
        assert d.core.modes.mode == Mode.ABORTED, refused
        run.until(lambda: d.sim.t_s > FAULT_AT_S + 1.0, 2.0)  # released
        assert d.core.request_reset()["ok"]
        assert run.until(lambda: d.core.modes.mode == Mode.IDLE, 2.0) is not None
        assert not d.core.modes.valves_enabled
    finally:
        run.close()
