"""Each injected fault shows up on the wire exactly as specified, seen from the IPC
side (``IpcLink`` and its health counters) and a sniffer on the same bus; and the PLC
emulation: mode handshake, command timeout, E-stop, limit switches, HMI target."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from config import ProjectConfig, units
from plc_bridge import Fault, LinkState, Mode, TargetAck, TargetRequest
from plc_bridge.supervision import BusState
from tests.hil_helpers import Bench, make_bench

U_UPPER = np.zeros(19)
U_UPPER[8:12] = 0.3


@pytest.fixture
def bench_of(project: ProjectConfig) -> Iterator[Any]:
    made: list[Bench] = []

    def make(*events: dict[str, Any], **kw: Any) -> Bench:
        b = make_bench(project, events, **kw)
        made.append(b)
        b.start()
        return b

    yield make
    for b in made:
        b.close()


def plc_sent(b: Bench, name: str) -> bool:
    return name != "error_frame" and b.sim.catalog.by_name(name).sender == "PLC"


def msg_health(b: Bench, name: str) -> dict[str, Any]:
    return b.ipc.health()["messages"][name]


def test_no_fault_link_ok_and_mode_echoed(bench_of: Any) -> None:
    b = bench_of()
    b.run(0.3, U_UPPER)
    s = b.ipc.status()
    assert s is not None and s.mode is Mode.ATTITUDE_ADJUST and s.drives_enabled
    assert b.ipc.state() is LinkState.OK
    assert s.supply_pressure_pa == pytest.approx(16e6, abs=5e3)
    b.ipc.set_control(mode=Mode.MANUAL)
    b.run(0.05, U_UPPER)
    assert b.ipc.status().mode is Mode.MANUAL  # handshake: the PLC echoes the request


def test_drop_rate_exactly_as_counted(bench_of: Any) -> None:
    b = bench_of({"kind": "drop", "rate": 0.3, "messages": ["PLC_RodPos_*"]})
    b.run(1.0, U_UPPER)
    wire = b.sim.wire
    dropped = wire.total("drop")
    sent = b.sim.plc.tx_counts["tx_frames"]
    plc_seen = sum(n for k, n in b.seen.items() if plc_sent(b, k))
    assert plc_seen + dropped == sent  # every PLC frame either on the bus or dropped
    pos_seen = sum(n for k, n in b.seen.items() if k.startswith("PLC_RodPos_"))
    n = pos_seen + dropped
    assert abs(dropped / n - 0.3) < 4 * np.sqrt(0.3 * 0.7 / n)
    assert all(
        not k.startswith("PLC_RodPos") for k, _ in [k for k in wire.counts if k[0] != "drop"]
    )
    assert b.ipc.health()["lost_frames"] > 0
    assert b.seen["PLC_Status"] > 0 and wire.counts[("drop", "PLC_Status")] == 0


def test_drop_with_max_burst_loses_single_frames_the_ipc_accepts(bench_of: Any) -> None:
    """A healthy bus's isolated losses: at most ``max_burst`` frames of one message in a
    row, so the alive counter never jumps beyond ``can.max_delta_counter`` and the rod
    positions never go stale."""
    b = bench_of({"kind": "drop", "rate": 0.5, "max_burst": 1, "messages": ["PLC_RodPos_*"]})
    b.run(0.1, U_UPPER)  # the link up
    stale = 0
    for _ in range(200):
        b.run(0.005, U_UPPER)
        stale += int(not b.ipc.positions_m().valid[8:12].all())
    assert b.sim.wire.total("drop") > 100  # about half of them lost
    for k in range(10):
        h = msg_health(b, f"PLC_RodPos_{k}")
        assert h.get("counter_wrong_sequence", 0) == 0, (k, h)
    assert stale == 0


def test_bad_crc_counted_by_the_ipc_and_status_lost(bench_of: Any) -> None:
    b = bench_of(
        {"kind": "bad_crc", "rate": 1.0, "messages": ["PLC_Status"], "start_s": 0.2, "end_s": 0.5}
    )
    b.run(0.45, U_UPPER)
    assert b.ipc.status() is None and b.ipc.state() is LinkState.LOST
    b.run(0.3, U_UPPER)
    corrupted = b.sim.wire.counts[("bad_crc", "PLC_Status")]
    assert corrupted == 15  # 0.3 s of a 20 ms message
    assert msg_health(b, "PLC_Status")["crc_error"] == corrupted
    assert b.ipc.status() is not None


def test_frozen_counter_counted_as_repeated(bench_of: Any) -> None:
    b = bench_of(
        {"kind": "frozen_counter", "messages": ["PLC_RodPos_4"], "start_s": 0.2, "end_s": 0.4}
    )
    b.run(0.3, U_UPPER)
    assert not b.ipc.positions_m().valid[[8, 9]].any()  # stale: the sender looks stuck
    assert b.ipc.positions_m().valid[[10, 11]].all()
    b.run(0.2, U_UPPER)
    frozen = b.sim.wire.counts[("frozen_counter", "PLC_RodPos_4")]
    assert frozen == 40  # 0.2 s at the loop rate
    h = msg_health(b, "PLC_RodPos_4")
    # every frozen frame repeats the counter; the one after the stale timeout (15 ms)
    # only re-synchronises the receiver (docs/can-protocol.md), so it counts as initial
    assert h["counter_repeated"] == frozen - 1 and h.get("crc_error", 0) == 0
    assert b.ipc.positions_m().valid[[8, 9]].all()  # resynchronised afterwards


def test_delay_holds_frames_back_in_order(bench_of: Any) -> None:
    b = bench_of(
        {"kind": "delay", "delay_ms": 30, "messages": ["PLC_Status"], "start_s": 0.2, "end_s": 0.6}
    )
    b.run(0.2, U_UPPER)
    age_before = b.ipc.status(), msg_health(b, "PLC_Status")["age_ms"]
    assert age_before[1] <= 20.0
    b.run(0.03)  # 30 ms after the start: the first delayed frame is not there yet
    assert msg_health(b, "PLC_Status")["age_ms"] >= 25.0
    b.run(0.6, U_UPPER)
    h = msg_health(b, "PLC_Status")
    assert b.sim.wire.counts[("delay", "PLC_Status")] == 20
    assert h["lost_frames"] == 0 and h.get("counter_wrong_sequence", 0) == 0
    assert b.seen["PLC_Status"] == h["accepted"] + h["initial"]


def test_plc_silent_nothing_on_the_wire_and_valves_closed(bench_of: Any) -> None:
    b = bench_of({"kind": "plc_silent", "start_s": 0.3, "end_s": 0.6})
    b.run(0.3, U_UPPER)
    b.run(0.3, U_UPPER)
    assert not [n for t, n in b.log if 0.3 < t <= 0.6 and plc_sent(b, n)]  # not one frame
    assert b.ipc.state() is LinkState.LOST and b.ipc.status() is None
    assert not b.sim.truth().applied_command.any()
    b.run(0.1, U_UPPER)
    s = b.ipc.status()
    assert s is not None and s.fault is Fault.IPC_TIMEOUT and not s.drives_enabled  # latched
    b.ipc.set_control(fault_reset=True)
    b.run(0.05, U_UPPER)
    assert b.ipc.status().drives_enabled and b.ipc.status().fault is Fault.NONE


def test_ignore_commands_looks_healthy_but_does_not_move(bench_of: Any) -> None:
    b = bench_of({"kind": "ignore_commands"})
    b.run(0.3, U_UPPER)
    assert b.ipc.status().drives_enabled and b.ipc.state() is LinkState.OK
    assert not b.sim.truth().applied_command.any()
    assert np.abs(b.sim.truth().spool_m).max() == 0.0


def test_bus_off_reported_by_error_frames_and_recovered(bench_of: Any) -> None:
    b = bench_of({"kind": "bus_off", "start_s": 0.2, "end_s": 0.4})
    b.run(0.3, U_UPPER)
    assert b.ipc.health()["bus_state"] == BusState.BUS_OFF.value
    assert b.ipc.state() is LinkState.LOST
    assert b.seen["error_frame"] == 1
    t_off = next(t for t, n in b.log if n == "error_frame")
    assert not [n for t, n in b.log if t_off < t <= 0.4 and plc_sent(b, n)]
    b.run(0.2, U_UPPER)
    assert b.seen["error_frame"] == 2
    assert b.ipc.health()["bus_state"] == BusState.ACTIVE.value
    assert b.ipc.status() is not None


@pytest.mark.parametrize("mode", ["stuck", "jump", "noisy", "fail"])
def test_sensor_faults(bench_of: Any, mode: str) -> None:
    ev = {
        "kind": "sensor",
        "cylinder": "upper_1",
        "mode": mode,
        "start_s": 0.1,
        "offset": 2.0,
        "noise": 0.5,
    }
    b = bench_of(ev)
    u = U_UPPER
    if mode != "stuck":  # compare with the truth standing still (valves blocked)
        b.ipc.set_control(enable=False)
        u = np.zeros(19)
    b.run(0.1, u)
    readings: list[float] = []
    truths: list[float] = []

    def rec(bb: Bench) -> None:
        readings.append(bb.ipc.positions_m().value[8])
        truths.append(bb.sim.truth().rod_positions_m[8])

    b.run(0.3, u, each=rec)
    r, t = np.array(readings[5:]), np.array(truths[5:])
    if mode == "stuck":
        assert np.ptp(r) == 0.0 and np.ptp(t) > 1e-4
    elif mode == "jump":
        np.testing.assert_allclose(r - t, 2e-3, atol=3e-5)
    elif mode == "noisy":
        assert 0.2e-3 < np.std(np.diff(r - t)) / np.sqrt(2) < 1e-3
    else:
        assert np.isnan(r).all()
        assert b.ipc.status().fault is Fault.SENSOR_FAULT
        assert b.ipc.positions_m().valid[9]


def test_pressure_sensor_jump(bench_of: Any) -> None:
    b = bench_of(
        {
            "kind": "sensor",
            "cylinder": "main_leg_2",
            "quantity": "rod_pressure",
            "mode": "jump",
            "offset": 1.5,
        }
    )
    b.ipc.set_control(enable=False)  # blocked: the truth stands still
    b.run(0.3)
    p = b.ipc.pressures_pa().value[1, 1]
    assert p - b.sim.truth().pressures_pa[1, 1] == pytest.approx(1.5e6, abs=0.05e6)


def test_stuck_valve_ignores_commands(bench_of: Any) -> None:
    b = bench_of({"kind": "stuck_valve", "cylinder": "upper_3", "opening": -0.2, "start_s": 0.0})
    b.run(0.3, U_UPPER)
    tr = b.sim.truth()
    assert tr.applied_command[10] == -0.2 and tr.applied_command[9] == pytest.approx(0.3, abs=1e-3)
    assert tr.spool_m[10] == pytest.approx(-0.2 * 0.5e-3, rel=1e-3)


def test_raised_internal_leakage_equalizes_the_chambers(
    bench_of: Any, project: ProjectConfig
) -> None:
    b = bench_of(
        {
            "kind": "leakage",
            "cylinder": "upper_4",
            "internal_leakage_m3_s_pa": 5e-10,
            "start_s": 0.3,
        }
    )
    b.ipc.set_control(enable=True)
    b.run(0.3, U_UPPER)  # moving: p_A and p_B differ
    b.ipc.set_control(enable=False)  # blocked
    dp0 = b.ipc.pressures_pa().value[:, 0] - b.ipc.pressures_pa().value[:, 1]
    b.run(0.3)
    dp1 = b.ipc.pressures_pa().value[:, 0] - b.ipc.pressures_pa().value[:, 1]
    assert abs(dp1[11]) < 0.2 * abs(dp0[11])  # the leaking one equalizes fast
    assert abs(dp1[8]) > 0.5 * abs(dp0[8])


def test_load_step_raises_the_pressures_on_the_wire(bench_of: Any, project: ProjectConfig) -> None:
    """A 3 t step on the upper platform, valves closed: the oil carries it. Behind closed
    holding valves a cylinder is tight (docs/hil.md), so the rods settle by the oil's
    compression alone (a few hundredths of a mm) and stay; the wire's pressures show the
    whole step."""
    b = bench_of(
        {
            "kind": "load_step",
            "layer": "upper",
            "mass_kg": 3000,
            "cog_m": [0, 0, 1.0],
            "start_s": 0.2,
        }
    )
    cyl = project.cylinder("upper_1")
    b.ipc.set_control(enable=False)  # blocked: the oil carries the step

    def force() -> float:
        p = b.ipc.pressures_pa().value[8:12]
        return float((p[:, 0] * cyl.cap_area_m2 - p[:, 1] * cyl.rod_area_m2).sum())

    b.run(0.15)
    f0 = force()
    x0 = b.ipc.positions_m().value[8:12].copy()
    b.run(0.85)
    x1 = b.ipc.positions_m().value[8:12].copy()
    b.run(1.0)
    settle = float(np.mean(x1 - x0))
    creep = float(np.mean(b.ipc.positions_m().value[8:12] - x1))  # over the next second
    weight = 3000 * units.G * np.cos(np.radians(0.17))
    assert -0.1e-3 < settle < -0.005e-3  # the oil compressed by the step
    assert abs(creep) < 5e-6  # then it holds (within the noise): no leakage behind the valves
    assert force() - f0 == pytest.approx(weight, rel=0.05)  # within the wire's noise


def test_estop_closes_valves_and_latches(bench_of: Any) -> None:
    b = bench_of({"kind": "estop", "start_s": 0.2, "end_s": 0.4})
    b.run(0.25, U_UPPER)
    s = b.ipc.status()
    assert s.estop and s.fault is Fault.ESTOP and not s.drives_enabled and not s.pump_running
    assert not b.sim.truth().applied_command.any()
    b.run(0.2, U_UPPER)
    assert not b.ipc.status().estop and b.ipc.status().fault is Fault.ESTOP
    b.ipc.set_control(fault_reset=True)
    b.run(0.05, U_UPPER)
    assert b.ipc.status().drives_enabled


def test_command_timeout_closes_valves_and_reports(bench_of: Any) -> None:
    b = bench_of()
    b.run(0.2, U_UPPER)
    assert b.sim.truth().applied_command[8] == pytest.approx(0.3, abs=1e-3)
    b.run(0.15, ipc_alive=False)
    tr = b.sim.truth()
    assert tr.status.command_timeout and tr.status.fault is Fault.IPC_TIMEOUT
    assert not tr.applied_command.any() and not tr.status.drives_enabled
    b.run(0.05, U_UPPER)
    s = b.ipc.status()
    assert s.command_timeout is False and s.fault is Fault.IPC_TIMEOUT  # latched
    b.ipc.set_control(fault_reset=True)
    b.run(0.05, U_UPPER)
    assert b.ipc.status().fault is Fault.NONE and b.ipc.status().drives_enabled


def test_limit_switch_on_the_wire_and_no_motion_into_it(bench_of: Any) -> None:
    b = bench_of()
    rig = b.sim.rig
    rig.set_rod_position(14, rig.params.stroke_m[14] - 1e-3)  # rotation_1 at its end
    u = np.zeros(19)
    u[14] = 1.0
    b.run(0.2, u)
    ls = b.ipc.limit_switches()
    assert ls.extended[14] and not ls.extended[15] and not ls.retracted.any()
    assert b.sim.truth().applied_command[14] == 0.0
    u[14] = -1.0
    b.run(0.01, u)
    assert b.sim.truth().applied_command[14] == -1.0


def test_hmi_target_request_and_ack(bench_of: Any) -> None:
    b = bench_of({"kind": "hmi_target", "at_s": 0.1, "roll_deg": 2.0, "pitch_deg": -1.0})
    b.run(0.3)
    t = b.ipc.new_hmi_request()
    assert t is not None and t.request is TargetRequest.NEW_TARGET
    assert t.roll_rad == pytest.approx(np.radians(2.0), abs=1e-6)
    assert t.pitch_rad == pytest.approx(np.radians(-1.0), abs=1e-6)
    b.ipc.set_control(ack_seq=t.seq, ack_status=TargetAck.ACCEPTED)
    b.run(0.05)
    assert b.sim.hmi_ack == (t.seq, TargetAck.ACCEPTED)


def test_hmi_target_event_issues_one_target_seq_once(bench_of: Any) -> None:
    """One event, one new TargetSeq: not a new one every PLC scan."""
    b = bench_of(
        {"kind": "hmi_target", "at_s": 0.1, "roll_deg": 2.0, "pitch_deg": -1.0},
        {"kind": "hmi_target", "at_s": 1.0, "roll_deg": 1.0, "pitch_deg": 0.0},
    )
    seen: list[int] = []

    def each(bench: Bench) -> None:
        t = bench.ipc.new_hmi_request()
        if t is not None:
            seen.append(t.seq)

    b.run(0.9, each=each)
    assert b.sim.hmi_issued == [1] and seen == [1]
    b.run(1.1, each=each)
    assert b.sim.hmi_issued == [1, 2] and seen == [1, 2]


@pytest.mark.parametrize("ms", [10, 50])
def test_plc_stall_no_frames_spools_centred_then_drives_again(bench_of: Any, ms: int) -> None:
    """The PLC's scan stops: nothing sent or read, the outputs centred; afterwards it
    reads what queued up and drives again (a stall is not an IPC timeout)."""
    b = bench_of({"kind": "plc_stall", "start_s": 0.2, "end_s": 0.2 + ms / 1000})
    b.run(0.2, U_UPPER)
    before = b.sim.plc.tx_counts["tx_frames"]
    b.run(ms / 1000, U_UPPER)
    assert b.sim.plc.tx_counts["tx_frames"] == before  # not a frame while stalled
    assert not b.sim.truth().applied_command.any()
    b.run(0.02, U_UPPER)
    tr = b.sim.truth()
    assert tr.status.fault is Fault.NONE and tr.status.drives_enabled
    assert tr.applied_command[8] == pytest.approx(0.3, abs=1e-3)


def test_wire_stall_holds_frames_and_delivers_them_in_order(bench_of: Any) -> None:
    b = bench_of({"kind": "wire_stall", "start_s": 0.2, "end_s": 0.25, "direction": "plc_to_ipc"})
    b.run(0.2, U_UPPER)

    def from_plc() -> int:
        return sum(1 for _, name in b.log if plc_sent(b, name))

    n = from_plc()
    b.run(0.045, U_UPPER)
    assert from_plc() == n  # held
    held = b.sim.wire.total("wire_stall")
    assert held > 0
    b.run(0.015, U_UPPER)  # released at end_s, read by the IPC's next poll
    assert from_plc() - n >= held  # all delivered
    rx = b.ipc.health()["rx"]
    assert rx.get("crc_error", 0) == 0 and rx.get("counter_wrong_sequence", 0) == 0
    assert b.ipc.positions_m().all_valid(b.ipc.active_cylinders)


@pytest.mark.parametrize(("ms", "latched"), [(50, False), (150, True)])
def test_commands_held_centre_at_once_and_latch_only_after_the_timeout(
    bench_of: Any, ms: int, latched: bool
) -> None:
    """Commands held on the wire: the PLC centres the spools at once; it latches
    IPC_TIMEOUT only when the loss is longer than safety.command_timeout_ms (100 ms),
    else it drives again when the frames are back."""
    end = 0.2 + ms / 1000
    b = bench_of({"kind": "wire_stall", "start_s": 0.2, "end_s": end, "direction": "ipc_to_plc"})
    b.run(0.2, U_UPPER)
    b.run(0.02, U_UPPER)
    tr = b.sim.truth()
    assert tr.status.command_timeout and not tr.applied_command.any()
    b.run(ms / 1000, U_UPPER)
    tr = b.sim.truth()
    assert (tr.status.fault is Fault.IPC_TIMEOUT) is latched
    assert tr.status.drives_enabled is not latched


def test_unknown_cylinder_and_message_are_refused(project: ProjectConfig) -> None:
    with pytest.raises(ValueError, match="unknown cylinder 'upper_9'"):
        make_bench(project, [{"kind": "stuck_valve", "cylinder": "upper_9"}])
    with pytest.raises(ValueError, match="no DBC message matches 'PLC_Nope'"):
        make_bench(project, [{"kind": "drop", "rate": 0.1, "messages": ["PLC_Nope"]}])
