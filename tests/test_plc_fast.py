"""The simulator's compiled PLC scans (``hil_sim.plc_fast``) are its Python scans.

Each case runs the simulator on a lockstep bus against an ``IpcLink`` driven from the
test, twice: with the compiled scans (where they may run, handing over to the Python
scan around every event) and with the Python scan only. Every frame on the wire (its
scan time, sender, id and data), every log line of the link, and the state at the end
(the PLC's supervision counters and health, its status word, the commands it applies,
the HMI acknowledgement, the wire's fault counts, the plant's state) must be the same.
The cases reach what the compiled scans do themselves (frames lost, corrupted, delayed,
held, repeated, out of sequence, of unknown ids; command timeouts, the IPC's latched
fault and its reset; the active group changing; limit switches; E-stop, ignored
commands, stuck spools, HMI targets, load-holding valves) and what they hand back (a
stalled, a silent PLC, sensor faults, bus-off, a part being loaded, someone reading the
PLC's link mid-run).
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from typing import Any

import can
import numpy as np
import pytest

from config import ProjectConfig
from config.hil_scenario import HilScenario
from hil_sim._jit import HAVE_NUMBA
from hil_sim.plc_fast import FastPlc
from hil_sim.simulator import HilSimulator
from plc_bridge import IpcLink, Mode
from plc_bridge.lockstep_bus import LockstepBus, lockstep_pair

pytestmark = pytest.mark.skipif(not HAVE_NUMBA, reason="the compiled scans need numba")

DT = 0.005
U_UPPER = np.zeros(19)
U_UPPER[8:12] = 0.3

Step = Callable[[int, HilSimulator, IpcLink, LockstepBus], None]


def _run(
    cfg: ProjectConfig,
    scenario: dict[str, Any],
    seconds: float,
    compiled: bool,
    monkeypatch: pytest.MonkeyPatch,
    caplog: pytest.LogCaptureFixture,
    each: Step | None = None,
    u: np.ndarray = U_UPPER,
) -> dict[str, Any]:
    with monkeypatch.context() as mp:
        if not compiled:
            mp.setattr(FastPlc, "available", staticmethod(lambda sim: False))
        plc_bus, ipc_bus = lockstep_pair("fast-vs-python")
        frames: list[tuple[float, str, int, bytes, bool]] = []
        sim = HilSimulator(cfg, plc_bus, HilScenario.model_validate(scenario))
        assert (sim._fast is not None) is compiled
        for side, bus in (("plc", plc_bus), ("ipc", ipc_bus)):
            _record_sends(bus, side, frames, sim)
        ipc = IpcLink(cfg, ipc_bus, clock=sim.clock)
        ipc.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="plc_bridge"):
            for k in range(round(seconds / DT)):
                if each is not None:
                    each(k, sim, ipc, ipc_bus)
                ipc.poll()
                ipc.send_valve_commands(u)
                sim.step(DT)
            logs = [r.getMessage() for r in caplog.records if r.getMessage().startswith("PLC")]
        tr = sim.truth()
        plc = sim.plc
        out = {
            "frames": frames,
            "logs": logs,
            "health": plc.health(sim.t_s),
            "rx_counters": plc.rx_counters(),
            "tx": dict(plc.tx_counts),
            "status": sim.status,
            "applied": tr.applied_command.tolist(),
            "hmi_ack": sim.hmi_ack,
            "wire": dict(sim.wire.counts),
            "y": sim.rig.y.tobytes(),
            "rig_t": sim.rig.t_s,
            "t": sim.t_s,
            "latched": sim._latched,
            "ipc_health": ipc.health(),
        }
        ipc.close()
        sim.close()
        return out


def _record_sends(
    bus: LockstepBus, side: str, frames: list[tuple[Any, ...]], sim: HilSimulator
) -> None:
    """Every frame ``bus`` sends, one by one or in a batch, into ``frames`` with the
    simulator's time and the sender."""
    send, send_all = bus.send, bus.send_all

    def record(msg: can.Message) -> None:
        frames.append((sim.t_s, side, msg.arbitration_id, bytes(msg.data), msg.is_error_frame))

    def one(msg: can.Message, timeout: float | None = None) -> None:
        record(msg)
        send(msg, timeout)

    def batch(msgs: list[can.Message]) -> None:
        for msg in msgs:
            record(msg)
        send_all(msgs)

    bus.send = one  # type: ignore[method-assign]
    bus.send_all = batch  # type: ignore[method-assign]


def _same(
    cfg: ProjectConfig, mp: Any, caplog: Any, scenario: dict[str, Any], seconds: float, **kw: Any
) -> dict[str, Any]:
    fast = _run(cfg, scenario, seconds, True, mp, caplog, **kw)
    slow = _run(cfg, scenario, seconds, False, mp, caplog, **kw)
    assert len(fast["frames"]) == len(slow["frames"])
    for i, (a, b) in enumerate(zip(fast["frames"], slow["frames"], strict=True)):
        assert a == b, f"frame {i}: compiled {a} against python {b}"
    for key in slow:
        assert fast[key] == slow[key], key
    return slow


def _set(**changes: Any) -> Callable[[IpcLink], None]:
    return lambda ipc: ipc.set_control(**changes)


def _at(plan: dict[float, Callable[[IpcLink], None]]) -> Step:
    """Act on the IPC link at these times (s)."""
    steps = {round(t / DT): f for t, f in plan.items()}

    def each(k: int, sim: HilSimulator, ipc: IpcLink, bus: LockstepBus) -> None:
        if k in steps:
            steps[k](ipc)

    return each


CASES: dict[str, tuple[dict[str, Any], float, dict[str, Any]]] = {
    "nominal": ({}, 1.0, {}),
    "wire faults": (
        {
            "events": [
                {"kind": "drop", "rate": 0.3, "direction": "both", "start_s": 0.1, "end_s": 0.4},
                {"kind": "bad_crc", "rate": 0.2, "direction": "both", "start_s": 0.3, "end_s": 0.6},
                {"kind": "delay", "delay_ms": 3, "start_s": 0.5, "end_s": 0.9},
                {
                    "kind": "frozen_counter",
                    "messages": ["PLC_Status"],
                    "start_s": 0.7,
                    "end_s": 0.8,
                },
                {"kind": "wire_stall", "start_s": 1.0, "end_s": 1.04, "direction": "ipc_to_plc"},
                {"kind": "wire_stall", "start_s": 1.2, "end_s": 1.23, "direction": "plc_to_ipc"},
            ]
        },
        1.5,
        {},
    ),
    "ipc timeout, latched, reset": (
        {
            "events": [
                {"kind": "wire_stall", "start_s": 0.2, "end_s": 0.4, "direction": "ipc_to_plc"}
            ]
        },
        0.8,
        {"each": _at({0.6: _set(fault_reset=True), 0.7: _set(fault_reset=False)})},
    ),
    "modes and active groups": (
        {},
        1.2,
        {
            "each": _at(
                {
                    0.2: _set(mode=Mode.MANUAL),
                    0.3: lambda ipc: ipc.set_active_cylinders([0, 1, 2, 3, 12, 13]),
                    0.6: lambda ipc: ipc.set_active_cylinders(range(8, 12)),
                    0.8: _set(enable=False),
                    0.9: _set(enable=True, stop=True),
                    1.0: _set(stop=False, ack_seq=3, ack_status=1),
                }
            )
        },
    ),
    "plc events": (
        {
            "plant": {"load_holding_valves": True},
            "events": [
                {"kind": "estop", "start_s": 0.1, "end_s": 0.2},
                {"kind": "ignore_commands", "start_s": 0.3, "end_s": 0.4},
                {"kind": "stuck_valve", "cylinder": "upper_1", "start_s": 0.45, "end_s": 0.6},
                {"kind": "stuck_valve", "cylinder": "upper_2", "opening": 0.2, "start_s": 0.5},
                {"kind": "hmi_target", "at_s": 0.55, "roll_deg": 1.0, "pitch_deg": -0.5},
                {"kind": "load_step", "layer": "upper", "mass_kg": 2000, "start_s": 0.6},
                {
                    "kind": "leakage",
                    "cylinder": "upper_3",
                    "internal_leakage_m3_s_pa": 1e-12,
                    "start_s": 0.65,
                },
                {
                    "kind": "holding_valve_leak",
                    "cylinder": "upper_4",
                    "leakage_m3_s_pa": 1e-13,
                    "start_s": 0.7,
                },
            ],
        },
        1.0,
        {"each": _at({0.25: _set(fault_reset=True), 0.3: _set(fault_reset=False)})},
    ),
    "handed back to python": (
        {
            "events": [
                {"kind": "plc_stall", "start_s": 0.1, "end_s": 0.13},
                {"kind": "plc_silent", "start_s": 0.2, "end_s": 0.25},
                {"kind": "bus_off", "start_s": 0.55, "end_s": 0.6},
            ]
        },
        0.9,
        {"each": lambda k, sim, ipc, bus: _load_part(k, sim)},
    ),
    # a sensor-fault event in the scenario: its readings are taken every scan, as Python
    "sensor faults": (
        {
            "events": [
                {"kind": "sensor", "cylinder": "upper_1", "mode": "fail", "start_s": 0.1},
                {"kind": "sensor", "cylinder": "upper_2", "mode": "stuck", "start_s": 0.2},
            ]
        },
        0.3,
        {},
    ),
}


def _load_part(k: int, sim: HilSimulator) -> None:
    """The part bolted at 0.7 s, a new one loaded from 0.75 s for 0.1 s."""
    if k == round(0.7 / DT):
        sim.bolt_part()
    elif k == round(0.75 / DT):
        sim.load_part(0.1)


@pytest.mark.parametrize("case", list(CASES))
def test_compiled_scans_are_the_python_scans(
    project: ProjectConfig, monkeypatch: pytest.MonkeyPatch, caplog: Any, case: str
) -> None:
    scenario, seconds, kw = CASES[case]
    _same(project, monkeypatch, caplog, scenario, seconds, **kw)


def test_limit_switches_and_odd_frames(
    project: ProjectConfig, monkeypatch: pytest.MonkeyPatch, caplog: Any
) -> None:
    """A rod driven into its end switch and back; frames the PLC does not take (unknown
    ids, its own ids, extended, remote) and ones it rejects (wrong length)."""
    u = np.zeros(19)

    def each(k: int, sim: HilSimulator, ipc: IpcLink, bus: LockstepBus) -> None:
        if k == 0:
            u[14] = 1.0
            rig = sim.rig
            rig.set_rod_position(14, rig.params.stroke_m[14] - 1e-3)
        if k == 60:
            u[14] = -1.0
        if k in (10, 11, 12, 13, 14):
            bus.send(
                [
                    can.Message(arbitration_id=0x7F0, data=b"\x01", is_extended_id=False),
                    can.Message(arbitration_id=0x90, data=bytes(6), is_extended_id=False),
                    can.Message(arbitration_id=0x80, data=bytes(8), is_extended_id=True),
                    can.Message(arbitration_id=0x80, is_remote_frame=True, is_extended_id=False),
                    can.Message(arbitration_id=0x80, data=bytes(3), is_extended_id=False),
                ][k - 10]
            )
        ctl = ipc._ctl_codec
        if k in (20, 30, 40):  # a good CRC, and: a repeated counter, counter 15, a bad mode
            raws = ctl.to_raw(ipc._control_values())
            counter = (ipc._tx_counter[ctl.frame_id] - 1) % 15
            if k == 30:
                counter = 15
            elif k == 40:
                raws[ctl.signal_names.index("ModeRequest")] = 7  # DBC range 0..4
                counter = ipc._tx_counter[ctl.frame_id]
                ipc._tx_counter[ctl.frame_id] = (counter + 1) % 15
            data = ctl.encode_raw(counter, raws)
            bus.send(can.Message(arbitration_id=ctl.frame_id, data=data, is_extended_id=False))

    out = _same(project, monkeypatch, caplog, {}, 0.5, each=each, u=u)
    rx = out["rx_counters"]
    assert rx["unknown_id"] == 1 and rx["own_echo"] == 1 and rx["not_classic"] == 2
    assert rx["length_error"] == 1 and rx["counter_repeated"] >= 1
    assert rx["counter_invalid"] == 1 and rx["value_error"] == 1


def test_reading_the_link_mid_run_hands_the_state_over_and_back(
    project: ProjectConfig, monkeypatch: pytest.MonkeyPatch, caplog: Any
) -> None:
    """``sim.plc`` gives the Python objects the compiled scans' state; the next step
    takes it again: every other step here, and the wire is the same as without."""

    def each(k: int, sim: HilSimulator, ipc: IpcLink, bus: LockstepBus) -> None:
        if k % 2:
            sim.plc.health(sim.t_s)

    _same(project, monkeypatch, caplog, {}, 0.6, each=each)


def test_walking_rig(project: ProjectConfig, monkeypatch: pytest.MonkeyPatch, caplog: Any) -> None:
    """The walking rig's plant is advanced by its own method after each compiled scan."""
    _same(project, monkeypatch, caplog, {"plant": {"contact": True}}, 0.6)
