"""IPC side against PLC side, and the supervision rules, under a simulated clock.

``TestBackToBackVirtual`` runs both sides on python-can's ``virtual`` bus;
``TestBackToBackSocketcan`` re-runs the same class on ``vcan0`` through the kernel (marked
``kernel``: in the VM of ``python3 tests/kernel/run_in_vm.py`` where this kernel has no CAN).
The supervision tests feed hand-made frames through a queue-backed fake bus.
"""

from __future__ import annotations

import errno
import logging
import math
import os
import uuid
from collections.abc import Iterator
from typing import Any

import can
import numpy as np
import pytest

from config import ProjectConfig
from plc_bridge import (
    BusLoadError,
    BusState,
    ControlWord,
    FrameCodec,
    HmiTarget,
    IpcLink,
    LinkState,
    Mode,
    PlcLink,
    PlcStatus,
    TargetAck,
    TargetRequest,
    load_catalog,
)
from plc_bridge.bus import CAN_ERR_BUSOFF, CAN_ERR_CRTL, CAN_ERR_RESTARTED
from plc_bridge.lockstep_bus import lockstep_pair
from tests.kernel import vcan_skip_reason
from tests.plc_fakes import Clock, QueueBus, frame

DT = 0.005
CAT = load_catalog()
X = np.linspace(0.0105, 0.7805, 19)  # m
P = np.stack([np.linspace(1e6, 19e6, 19), np.linspace(0.5e6, 2e6, 19)], axis=1)  # Pa
U = np.linspace(-1.0, 1.0, 19)


class BackToBack:
    """The IPC and the PLC side on one bus; subclasses choose the bus."""

    def buses(self, cfg: ProjectConfig) -> tuple[can.BusABC, can.BusABC]:
        raise NotImplementedError

    @pytest.fixture
    def pair(self, project: ProjectConfig) -> Iterator[tuple[IpcLink, PlcLink, Clock]]:
        clock = Clock()
        a, b = self.buses(project)
        ipc = IpcLink(project, a, clock=clock)
        plc = PlcLink(project, b, clock=clock)
        plc.set_positions_m(X)
        plc.set_pressures_pa(P)
        plc.set_status(
            PlcStatus(mode=Mode.ATTITUDE_ADJUST, pump_running=True, supply_pressure_pa=16e6)
        )
        yield ipc, plc, clock
        ipc.close()
        plc.close()

    def settle(self) -> None:
        """Give the transport time to deliver (nothing to wait for on virtual)."""

    def run(
        self,
        ipc: IpcLink | None,
        plc: PlcLink | None,
        clock: Clock,
        seconds: float,
        u: np.ndarray = U,
    ) -> None:
        for _ in range(round(seconds / DT)):
            if plc is not None:
                plc.poll()
            self.settle()
            if ipc is not None:
                ipc.poll()
                ipc.send_valve_commands(u)
            self.settle()
            clock.advance(DT)

    def test_values_cross_with_their_resolution(self, pair: Any) -> None:
        ipc, plc, clock = pair
        ipc.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
        plc.set_hmi_target(HmiTarget(math.radians(-3.0), math.radians(2.0), seq=7))
        plc.set_limit_switches([i == 4 for i in range(19)], [i == 18 for i in range(19)])
        self.run(ipc, plc, clock, 0.3)
        assert ipc.state() is LinkState.OK and plc.state() is LinkState.OK
        x = ipc.positions_m()
        assert x.all_valid() and np.max(np.abs(x.value - X)) <= 0.5e-6  # 1 um steps
        assert np.all(x.age_s < 0.06)
        p = ipc.pressures_pa()
        assert p.value.shape == (19, 2) and np.max(np.abs(p.value - P)) <= 2.5e3  # 0.005 MPa
        st = ipc.status()
        assert st is not None and st.mode is Mode.ATTITUDE_ADJUST and st.pump_running
        assert st.supply_pressure_pa == pytest.approx(16e6) and not st.command_timeout
        t = ipc.hmi_target()
        assert t is not None and t.seq == 7 and t.request is TargetRequest.NEW_TARGET
        assert math.degrees(t.roll_rad) == pytest.approx(-3.0, abs=5e-5)
        assert math.degrees(t.pitch_rad) == pytest.approx(2.0, abs=5e-5)
        lim = ipc.limit_switches()
        assert lim is not None and lim.retracted.tolist() == [i == 4 for i in range(19)]
        assert lim.extended[18] and lim.extended.sum() == 1
        u = plc.valve_commands()
        assert u.all_valid() and np.max(np.abs(u.value - U)) <= 0.5 / 2047 + 1e-12
        c = plc.control()
        assert c == ControlWord(mode=Mode.ATTITUDE_ADJUST, enable=True)
        assert not plc.command_timeout()
        assert ipc.health()["rx"].keys() <= {"accepted", "initial"}

    def test_hmi_request_is_reported_once_and_acknowledged(self, pair: Any) -> None:
        ipc, plc, clock = pair
        plc.set_hmi_target(HmiTarget(0.01, -0.02, seq=3))
        self.run(ipc, plc, clock, 0.3)
        req = ipc.new_hmi_request()
        assert req is not None and req.seq == 3
        assert ipc.new_hmi_request() is None
        ipc.set_control(ack_seq=req.seq, ack_status=TargetAck.ACCEPTED)
        self.run(ipc, plc, clock, 0.05)
        c = plc.control()
        assert c is not None and (c.ack_seq, c.ack_status) == (3, TargetAck.ACCEPTED)

    def test_plc_silent_means_lost_and_no_values(self, pair: Any) -> None:
        ipc, plc, clock = pair
        self.run(ipc, plc, clock, 0.2)
        assert ipc.state() is LinkState.OK
        self.run(ipc, None, clock, 0.12)  # longer than plc_heartbeat_timeout_ms = 100
        assert ipc.state() is LinkState.LOST and ipc.status() is None
        self.run(ipc, None, clock, 0.2)  # the HMI target too (3 x 100 ms)
        assert ipc.status() is None and ipc.hmi_target() is None
        x = ipc.positions_m()
        assert not x.valid.any() and np.isnan(x.value).all()
        assert ipc.health()["messages"]["PLC_Status"]["timeouts"] == 1
        self.run(ipc, plc, clock, 0.3)  # the PLC comes back: counters re-synchronise
        assert ipc.state() is LinkState.DEGRADED and ipc.positions_m().all_valid()
        self.run(ipc, plc, clock, 1.0)  # OK again one fault-free second later
        assert ipc.state() is LinkState.OK

    def test_ipc_silent_means_command_timeout_on_the_plc(self, pair: Any) -> None:
        ipc, plc, clock = pair
        self.run(ipc, plc, clock, 0.2)
        assert not plc.command_timeout()
        self.run(None, plc, clock, 0.02)  # valve frames stop: 3 x 5 ms
        assert plc.command_timeout()
        u = plc.valve_commands()
        assert np.isnan(u.value[[0, 1, 2, 3, 8, 9, 10, 11]]).all()
        assert plc.state() is LinkState.LOST
        # The PLC tells the IPC, once the IPC listens again.
        plc.poll()
        self.settle()
        ipc.poll()
        st = ipc.status()
        assert st is not None and st.command_timeout

    def test_sensor_fault_is_nan_not_a_number(self, pair: Any) -> None:
        ipc, plc, clock = pair
        x = X.copy()
        x[2] = math.nan
        plc.set_positions_m(x)
        self.run(ipc, plc, clock, 0.2)
        r = ipc.positions_m()
        assert not r.valid[2] and math.isnan(r.value[2]) and r.valid[3]
        assert r.all_valid([0, 1, 3]) and not r.all_valid([0, 1, 2, 3])

    def test_active_group_switch_moves_the_fast_frames(self, pair: Any) -> None:
        ipc, plc, clock = pair
        self.run(ipc, plc, clock, 0.1)
        rx = ipc._rx_by_name["PLC_RodPos_2"]  # cylinders 4, 5: sub frame legs
        before = rx.counters["accepted"]
        self.run(ipc, plc, clock, 0.1)
        assert rx.counters["accepted"] - before <= 3  # 20 Hz
        load = ipc.set_active_cylinders([4, 5, 6, 7, 8, 9, 10, 11])
        assert load.ok
        self.run(ipc, plc, clock, 0.05)
        assert plc.active_cylinders == (4, 5, 6, 7, 8, 9, 10, 11)
        before = rx.counters["accepted"]
        self.run(ipc, plc, clock, 0.1)
        assert rx.counters["accepted"] - before >= 18  # 200 Hz
        assert ipc.state() is LinkState.OK and plc.state() is LinkState.OK
        with pytest.raises(BusLoadError, match="would load the bus"):
            ipc.set_active_cylinders(range(19))
        assert ipc.active_cylinders == (4, 5, 6, 7, 8, 9, 10, 11)


class TestBackToBackVirtual(BackToBack):
    def buses(self, cfg: ProjectConfig) -> tuple[can.BusABC, can.BusABC]:
        ch = f"test-{uuid.uuid4().hex}"
        return can.Bus(interface="virtual", channel=ch), can.Bus(interface="virtual", channel=ch)


class TestBackToBackLockstep(BackToBack):
    """The same tests on the lockstep harness's deque pair."""

    def buses(self, cfg: ProjectConfig) -> tuple[can.BusABC, can.BusABC]:
        return lockstep_pair(f"test-{uuid.uuid4().hex}")


def test_lockstep_pair_delivers_to_the_peer_only_in_order() -> None:
    a, b = lockstep_pair("order")
    for i in range(3):
        a.send(can.Message(arbitration_id=0x100 + i, is_extended_id=False, data=bytes([i])))
    assert a.recv(1.0) is None  # never its own frames, never blocks
    got = [b.recv(0.0) for _ in range(4)]
    assert [m.arbitration_id for m in got[:3]] == [0x100, 0x101, 0x102]  # type: ignore[union-attr]
    assert got[3] is None and all(m.is_rx for m in got[:3])  # type: ignore[union-attr]
    b.set_filters([{"can_id": 0x101, "can_mask": 0x7FF}])
    for i in range(3):
        a.send(can.Message(arbitration_id=0x100 + i, is_extended_id=False, data=bytes([i])))
    assert b.recv(0.0).arbitration_id == 0x101  # type: ignore[union-attr]
    b.shutdown()
    a.send(can.Message(arbitration_id=0x100, is_extended_id=False))  # the peer is gone
    with pytest.raises(can.CanOperationError):
        b.recv(0.0)
    a.shutdown()
    with pytest.raises(can.CanOperationError):
        a.send(can.Message(arbitration_id=0x100, is_extended_id=False))


_NO_VCAN = vcan_skip_reason("vcan0")


@pytest.mark.kernel
@pytest.mark.skipif(_NO_VCAN is not None, reason=str(_NO_VCAN))
class TestBackToBackSocketcan(BackToBack):
    """The same tests through the kernel (vcan0), with kernel receive filters, plus what
    only a kernel bus has: the filters themselves, error frames, the interface going
    down. In the kernel VM (``python3 tests/kernel/run_in_vm.py``) where not here."""

    def buses(self, cfg: ProjectConfig) -> tuple[can.BusABC, can.BusABC]:
        from plc_bridge import open_bus

        link = self.vcan(cfg)
        a = open_bus(link, [m.frame_id for m in CAT.sent_by("PLC")])
        b = open_bus(link, [m.frame_id for m in CAT.sent_by("IPC")])
        return a, b

    @staticmethod
    def vcan(cfg: ProjectConfig) -> Any:
        return cfg.can.model_copy(update={"interface": "socketcan", "channel": "vcan0"})

    def settle(self) -> None:
        import time

        time.sleep(0.0005)

    def test_kernel_filters_keep_other_ids_and_extended_frames_out(self, pair: Any) -> None:
        ipc, plc, clock = pair
        with can.Bus(interface="socketcan", channel="vcan0") as stranger:
            for arb, ext in ((0x191, False), (0x7FF, False), (0x090, True), (0x110, True)):
                stranger.send(can.Message(arbitration_id=arb, is_extended_id=ext, data=bytes(8)))
            self.run(ipc, plc, clock, 0.3)
        # On the virtual bus these would reach the links as unknown_id / not_classic;
        # the kernel drops them before either side reads, and nobody sees its own frames.
        for side in (ipc, plc):
            rx = side.health()["rx"]
            assert rx.keys() <= {"accepted", "initial"}, rx
        assert ipc.state() is LinkState.OK and plc.state() is LinkState.OK

    def test_bus_off_error_frame_from_the_kernel_stops_sending_until_restarted(
        self, pair: Any
    ) -> None:
        ipc, plc, clock = pair
        self.run(ipc, plc, clock, 0.2)
        assert ipc.state() is LinkState.OK
        # A third socket on vcan0 puts controller error frames on the interface, as a
        # CAN driver does (linux/can/error.h); the kernel hands them only to sockets
        # with an error mask, which open_bus sets.
        with can.Bus(interface="socketcan", channel="vcan0") as ctrl:
            ctrl.send(
                can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8))
            )
            self.settle()
            ipc.poll()
            assert ipc.bus_health.state is BusState.BUS_OFF and ipc.state() is LinkState.LOST
            sent = ipc.tx_counts["tx_frames"]
            ipc.send_valve_commands(U)
            assert ipc.tx_counts["tx_frames"] == sent and ipc.tx_counts["tx_suppressed"] >= 1
            ctrl.send(
                can.Message(arbitration_id=CAN_ERR_RESTARTED, is_error_frame=True, data=bytes(8))
            )
            self.settle()
            ipc.poll()
            assert ipc.bus_health.state is BusState.ACTIVE
            passive = bytearray(8)
            passive[1] = 0x20  # CAN_ERR_CRTL_TX_PASSIVE
            ctrl.send(
                can.Message(arbitration_id=CAN_ERR_CRTL, is_error_frame=True, data=bytes(passive))
            )
            self.settle()
            ipc.poll()
            assert ipc.bus_health.state is BusState.PASSIVE
        assert ipc.health()["rx"]["error_frame"] == 3
        assert ipc.health()["bus"]["error_frames"] == 3
        # The PLC side got the same frames (both sockets have the error mask).
        plc.poll()
        assert plc.health()["rx"]["error_frame"] == 3

    @pytest.mark.skipif(os.geteuid() != 0, reason="ip link set vcan0 down needs root")
    def test_interface_down_then_up_is_reopened(self, project: ProjectConfig) -> None:
        import subprocess
        import time

        cfg = project.model_copy(update={"can": self.vcan(project)})
        clock = Clock()
        ipc = IpcLink.from_config(cfg, clock=clock)
        plc = PlcLink.from_config(cfg, clock=clock)
        plc.set_positions_m(X)
        plc.set_status(PlcStatus(pump_running=True))
        try:
            self.run(ipc, plc, clock, 0.2)
            assert ipc.state() is LinkState.OK
            subprocess.run(["ip", "link", "set", "vcan0", "down"], check=True)
            try:
                self.run(ipc, plc, clock, 0.05)
                assert ipc.bus_health.state is BusState.DOWN and ipc.state() is LinkState.LOST
            finally:
                subprocess.run(["ip", "link", "set", "vcan0", "up"], check=True)
            time.sleep(0.05)
            self.run(ipc, plc, clock, 1.5)  # the first retry (0.1 s back-off), then frames
            assert ipc.bus_health.state is BusState.ACTIVE
            assert ipc.bus_health.counters["reopen_attempts"] >= 1
            assert ipc.state() is not LinkState.LOST and ipc.positions_m().all_valid()
        finally:
            ipc.close()
            plc.close()


# --------------------------------------------------------------------------- supervision


def _ipc(project: ProjectConfig) -> tuple[IpcLink, QueueBus, Clock]:
    bus = QueueBus()
    clock = Clock()
    return IpcLink(project, bus, clock=clock), bus, clock


def _status(counter: int, **over: Any) -> can.Message:
    codec = FrameCodec(CAT.by_name("PLC_Status"))
    vals = _STATUS | over
    return frame(codec.frame_id, codec.encode(counter, [vals[n] for n in codec.signal_names]))


#: A PLC status in ATTITUDE_ADJUST, pump and drives on, 16 MPa supply (by signal name).
_STATUS: dict[str, float] = {
    "ModeActual": 2, "EStop": 0, "PumpRunning": 1, "DrivesEnabled": 1, "CommandTimeout": 0,
    "WalkAvailable": 0, "FaultCode": 0, "SupplyPressure": 16.0,
}  # fmt: skip


def test_crc_error_is_rejected_counted_and_logged_once(
    project: ProjectConfig, caplog: pytest.LogCaptureFixture
) -> None:
    ipc, bus, _clock = _ipc(project)
    for c in (0, 1):
        bus.inject(_status(c))
    ipc.poll()
    assert ipc.status() is not None
    for c in (2, 3, 4):
        bad = bytearray(_status(c, SupplyPressure=20.0).data)
        bad[4] ^= 0x10
        bus.inject(frame(0x090, bytes(bad)))
    with caplog.at_level(logging.WARNING, logger="plc_bridge"):
        ipc.poll()
    st = ipc.status()
    assert st is not None and st.supply_pressure_pa == pytest.approx(16e6)  # old value kept
    assert ipc.rx_outcomes["crc_error"] == 3
    assert len([r for r in caplog.records if "crc_error" in r.getMessage()]) == 1
    assert ipc.health()["messages"]["PLC_Status"]["crc_error"] == 3


def test_counter_stuck_is_rejected_then_stale(project: ProjectConfig) -> None:
    ipc, bus, clock = _ipc(project)
    bus.inject(_status(0))
    bus.inject(_status(1))
    ipc.poll()
    for _ in range(30):  # the PLC hangs and repeats its last frame
        clock.advance(0.005)
        bus.inject(_status(1, EStop=1))
        ipc.poll()
    # Rejected while fresh; once stale, the counter re-synchronises (one "initial").
    assert ipc.rx_outcomes["counter_repeated"] == 29 and ipc.rx_outcomes["initial"] == 2
    assert ipc.status() is None  # 150 ms > 100 ms heartbeat timeout: no value at all


def test_counter_jump_and_lost_frames(project: ProjectConfig) -> None:
    ipc, bus, _clock = _ipc(project)
    for c in (0, 1, 3):  # 2 lost: max_delta_counter 2 accepts it and counts it
        bus.inject(_status(c))
    ipc.poll()
    assert ipc.rx_outcomes["accepted"] == 2 and ipc.health()["lost_frames"] == 1
    bus.inject(_status(9, EStop=1))  # jumped 6: rejected, re-synchronised on 9
    bus.inject(_status(10, EStop=1))
    ipc.poll()
    assert ipc.rx_outcomes["counter_wrong_sequence"] == 1
    st = ipc.status()
    assert st is not None and st.estop
    bus.inject(_status(15))
    ipc.poll()
    assert ipc.rx_outcomes["counter_invalid"] == 1


def test_value_out_of_range_rejects_the_word(project: ProjectConfig) -> None:
    ipc, bus, _clock = _ipc(project)
    codec = FrameCodec(CAT.by_name("PLC_Status"))
    raws = [int(_STATUS[n]) for n in codec.signal_names[:-1]] + [3200]  # 16 MPa raw
    bus.inject(frame(0x090, codec.encode_raw(0, raws)))
    bus.inject(frame(0x090, codec.encode_raw(1, raws)))
    bus.inject(frame(0x090, codec.encode_raw(2, [9, *raws[1:]])))  # mode 9 does not exist
    ipc.poll()
    assert ipc.rx_outcomes["value_error"] == 1
    st = ipc.status()
    assert st is not None and st.mode is Mode.ATTITUDE_ADJUST


def test_degraded_while_a_non_critical_message_is_missing(project: ProjectConfig) -> None:
    plc_bus, ipc_bus = QueueBus(), QueueBus()
    clock = Clock()
    plc = PlcLink(project, plc_bus, clock=clock)
    ipc = IpcLink(project, ipc_bus, clock=clock)
    plc.set_positions_m(X)
    for _ in range(60):
        plc.poll()
        for m in plc_bus.sent:
            if m.arbitration_id != 0x190:  # the HMI target never arrives
                ipc_bus.inject(m)
        plc_bus.sent.clear()
        ipc.poll()
        clock.advance(DT)
    assert ipc.state() is LinkState.DEGRADED
    assert ipc.hmi_target() is None and ipc.positions_m().all_valid()


def test_bus_off_from_error_frames_then_restart(
    project: ProjectConfig, caplog: pytest.LogCaptureFixture
) -> None:
    ipc, bus, _clock = _ipc(project)
    err = can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8))
    with caplog.at_level(logging.INFO, logger="plc_bridge"):
        for _ in range(5):
            bus.inject(err)
        ipc.poll()
        assert ipc.bus_health.state is BusState.BUS_OFF and ipc.state() is LinkState.LOST
        n_sent = len(bus.sent)
        ipc.send_valve_commands(np.zeros(19))
        assert len(bus.sent) == n_sent and ipc.tx_counts["tx_suppressed"] >= 1
        bus.inject(
            can.Message(arbitration_id=CAN_ERR_RESTARTED, is_error_frame=True, data=bytes(8))
        )
        ipc.poll()
    assert ipc.bus_health.state is BusState.ACTIVE
    logs = [r.getMessage() for r in caplog.records]
    assert sum("-> BUS_OFF" in m for m in logs) == 1  # once per event, not per frame
    assert sum("BUS_OFF -> ACTIVE" in m for m in logs) == 1
    assert ipc.health()["bus"]["error_frames"] == 6
    passive = bytearray(8)
    passive[1] = 0x20  # CAN_ERR_CRTL_TX_PASSIVE
    bus.inject(can.Message(arbitration_id=CAN_ERR_CRTL, is_error_frame=True, data=bytes(passive)))
    ipc.poll()
    assert ipc.bus_health.state is BusState.PASSIVE


def test_full_transmit_queue_is_counted_not_waited_on(
    project: ProjectConfig, caplog: pytest.LogCaptureFixture
) -> None:
    ipc, bus, clock = _ipc(project)
    bus.send_error = lambda: can.CanOperationError(
        "Failed to transmit: No buffer space", errno.ENOBUFS
    )
    with caplog.at_level(logging.WARNING, logger="plc_bridge"):
        for _ in range(10):
            ipc.send_valve_commands(U)  # must not raise
            clock.advance(DT)
    assert ipc.bus_health.counters["tx_queue_full"] >= 20
    assert sum("queue full" in r.getMessage() for r in caplog.records) == 1
    bus.send_error = None
    assert ipc.send_valve_commands(U) == 2


def test_interface_down_is_reopened_with_back_off(project: ProjectConfig) -> None:
    clock = Clock()
    buses: list[QueueBus] = []
    failures = {"left": 2}

    def factory() -> can.BusABC:
        if buses and failures["left"] > 0:
            failures["left"] -= 1
            raise can.CanInitializationError("No such device")
        buses.append(QueueBus())
        return buses[-1]

    ipc = IpcLink(project, bus_factory=factory, clock=clock)
    buses[0].recv_error = lambda: can.CanOperationError(
        "Failed to receive: Network is down", errno.ENETDOWN
    )
    ipc.poll()
    assert ipc.bus_health.state is BusState.DOWN
    attempts = []
    for _ in range(200):  # 1 s in 5 ms steps
        clock.advance(DT)
        before = ipc.bus_health.counters["reopen_attempts"]
        ipc.poll()
        if ipc.bus_health.counters["reopen_attempts"] != before:
            attempts.append(round(clock.t - 100.0, 3))
    assert ipc.bus_health.state is BusState.ACTIVE and len(buses) == 2
    assert ipc.bus_health.counters["reopen_failures"] == 2
    gaps = np.diff(attempts)
    assert len(attempts) == 3 and gaps[1] > gaps[0]  # back-off grows


def _reference_array(rows: Any, width: int, si_per_unit: float, now: float) -> Any:
    """The reference definition of a received array (stale rows NaN, SI scaling) that
    IpcLink's receive path must match."""
    vals = [math.nan] * (19 * width)
    ages = [math.inf] * 19
    for rec, slots in rows:
        a = rec.age_s(now)
        v = rec.latest(now)
        for j, i in enumerate(slots):
            ages[i] = a
            if v is not None:
                vals[i * width : (i + 1) * width] = v[j * width : (j + 1) * width]
    val = np.array(vals) * si_per_unit
    if width > 1:
        val = val.reshape(19, width)
    return val, np.array(ages)


def _assert_readings_are_the_reference(ipc: IpcLink, now: float) -> bool:
    """The link's positions and pressures at ``now`` are the reference's, bit for bit;
    True when a row of them is not usable (NaN)."""
    stale = False
    for reading, rows, width, unit in (
        (ipc.positions_m(now), ipc._pos, 1, 1e-3),
        (ipc.pressures_pa(now), ipc._press, 2, 1e6),
    ):
        ref_val, ref_age = _reference_array(rows, width, unit, now)
        np.testing.assert_array_equal(reading.value, ref_val)
        np.testing.assert_array_equal(reading.age_s, ref_age)
        np.testing.assert_array_equal(reading.valid, ~np.isnan(ref_val))
        stale = stale or bool(np.isnan(ref_val).any())
    return stale


def test_readings_match_the_reference_definition_bit_for_bit(project: ProjectConfig) -> None:
    clock = Clock()
    bus = QueueBus()
    ipc = IpcLink(project, bus, clock=clock)
    plc_bus = QueueBus()
    plc = PlcLink(project, plc_bus, clock=clock)
    plc.set_positions_m(X)
    plc.set_pressures_pa(P)
    plc.set_status(PlcStatus(pump_running=True))
    ipc.set_active_cylinders(range(8))
    for k in range(40):
        plc.poll()
        for m in plc_bus.sent:
            if not (m.arbitration_id in (0x111, 0x142) and k > 10):  # two go stale
                bus.inject(m)
        plc_bus.sent.clear()
        ipc.poll()
        clock.advance(DT)
    ipc._pos[3][0].last_rx = None  # one never received (e.g. after a restart)
    ipc._pos[3][0].values = None
    for now in (clock.t, clock.t + 0.02, clock.t + 1.0):
        _assert_readings_are_the_reference(ipc, now)
    x = ipc.positions_m(clock.t)
    assert x.valid.any() and not x.valid.all()  # the cases above were all exercised


def test_readings_right_after_the_poll_match_the_reference(project: ProjectConfig) -> None:
    """At the poll's own time the readings come from the lists kept frame by frame; they
    match the reference definition bit for bit as frames are lost, go stale, come back,
    arrive late, and the active group (the timeouts, with their grace) changes."""
    rnd = np.random.default_rng(7)
    clock = Clock()
    bus, plc_bus = QueueBus(), QueueBus()
    ipc = IpcLink(project, bus, clock=clock)
    plc = PlcLink(project, plc_bus, clock=clock)
    plc.set_status(PlcStatus(pump_running=True))
    groups = [range(8), range(8, 12), range(12, 19), range(4, 12)]
    checked = 0
    for k in range(600):
        plc.set_positions_m(X + 1e-4 * k)
        plc.set_pressures_pa(P * (1 + 1e-3 * k))
        plc.poll()
        lossy = (k // 50) % 3 == 1  # spells of heavy loss: rows go stale and come back
        late = None
        for m in plc_bus.sent:
            if k % 41 == 0 and late is None:
                late = m
            elif rnd.random() > (0.7 if lossy else 0.02):
                bus.inject(m)
        plc_bus.sent.clear()
        if k % 97 == 0:
            ipc.set_active_cylinders(groups[(k // 97) % len(groups)])
        now = clock.t
        ipc.poll(now)
        if late is not None:  # a frame taken in after the poll, with an older time
            ipc.on_message(late, now - 0.5)
        checked += _assert_readings_are_the_reference(ipc, now)
        clock.advance(DT)
    assert checked > 50  # stale rows were part of it


def test_status_and_hmi_target_follow_each_new_frame(project: ProjectConfig) -> None:
    """The words are rebuilt only for a new frame; a changed frame is never missed."""
    clock = Clock()
    bus, plc_bus = QueueBus(), QueueBus()
    ipc = IpcLink(project, bus, clock=clock)
    plc = PlcLink(project, plc_bus, clock=clock)
    seen = []
    for k in range(300):  # PLC_Status every 20 ms, PLC_HmiTarget every 100 ms
        plc.set_status(PlcStatus(pump_running=True, estop=100 <= k < 200))
        plc.set_hmi_target(HmiTarget(0.01 * (k // 100), 0.0, seq=k // 100))
        plc.poll()
        for m in plc_bus.sent:
            bus.inject(m)
        plc_bus.sent.clear()
        ipc.poll()
        clock.advance(DT)
        st, t = ipc.status(), ipc.hmi_target()
        if k < 30:  # the first of each arrived
            continue
        assert st is not None and t is not None
        assert st is ipc.status() and t is ipc.hmi_target()  # no new frame: same word
        seen.append((st.estop, t.seq))
    # Each change arrives with the next PLC_Status / PLC_HmiTarget frame.
    assert seen[0] == (False, 0) and seen[150] == (True, 1) and seen[-1] == (False, 2)
    assert 90 <= [e for e, _ in seen].count(True) <= 100
    clock.advance(1.0)
    assert ipc.status() is None and ipc.hmi_target() is None  # stale: never the cached one
    ipc.close()
    plc.close()


def test_valve_commands_match_their_reference_definition(project: ProjectConfig) -> None:
    """NaN -> 0 and clipping to [-1, 1] on plain floats: the same frames and counts as the
    np.where / np.clip reference definition (kept here)."""
    rng = np.random.default_rng(7)
    cases = [rng.uniform(-1.5, 1.5, 19) for _ in range(200)]
    for u in cases[:100]:
        u[rng.integers(0, 19, 3)] = [np.nan, np.inf, -np.inf]
    cases += [np.zeros(19), -np.zeros(19), np.full(19, np.nan), np.linspace(-1, 1, 19)]
    link, bus, clock = _ipc(project)
    ref_link, ref_bus, _ = _ipc(project)  # sent the reference form's values: already clean
    bus.sent.clear()
    ref_bus.sent.clear()
    nan_total = clipped_total = 0
    for u in cases:
        link.send_valve_commands(u, clock.t)
        arr = np.asarray(u, dtype=float)
        nan = np.isnan(arr)
        nan_total += int(nan.sum())
        arr = np.where(nan, 0.0, arr)
        over = np.abs(arr) > 1.0
        clipped_total += int(over.sum())
        ref_link.send_valve_commands(np.clip(arr, -1.0, 1.0), clock.t)
        clock.advance(DT)
    assert [(m.arbitration_id, bytes(m.data)) for m in bus.sent] == [
        (m.arbitration_id, bytes(m.data)) for m in ref_bus.sent
    ]
    assert len(bus.sent) > 2 * len(cases)
    assert link.tx_counts["nan"] == nan_total > 0
    assert link.tx_counts["clipped"] == clipped_total > 0
    assert "nan" not in ref_link.tx_counts and "clipped" not in ref_link.tx_counts


def test_unchanged_control_word_sends_nothing(project: ProjectConfig) -> None:
    link, bus, _ = _ipc(project)
    bus.sent.clear()
    link.set_control(mode=Mode.IDLE, enable=False)  # already so
    assert bus.sent == []
    link.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
    link.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
    assert len(bus.sent) == 1 and link.control.enable
    with pytest.raises(TypeError):
        link.set_control(not_a_field=1)


def test_limit_switches_are_one_read_only_word_per_value(project: ProjectConfig) -> None:
    """A word is built when a frame brings other values than the word's, and kept while
    the frames repeat them (the loop asks every cycle)."""
    clock = Clock()
    bus, plc_bus = QueueBus(), QueueBus()
    ipc = IpcLink(project, bus, clock=clock)
    plc = PlcLink(project, plc_bus, clock=clock)
    words = []
    frames = 0
    for k in range(200):
        plc.set_limit_switches([i == 3 and k >= 100 for i in range(19)], [False] * 19)
        plc.poll()
        for m in plc_bus.sent:
            frames += m.arbitration_id == CAT.by_name("PLC_Limits").frame_id
            bus.inject(m)
        plc_bus.sent.clear()
        ipc.poll()
        clock.advance(DT)
        ls = ipc.limit_switches()
        if ls is not None:
            assert ls is ipc.limit_switches()  # no new frame: the same word
            assert not ls.retracted.flags.writeable and not ls.extended.flags.writeable
            words.append(ls)
    assert frames > 10
    distinct = list({id(w): w for w in words}.values())
    assert [bool(w.retracted[3]) for w in distinct] == [False, True]  # one word per value
    assert not words[0].retracted[3] and words[-1].retracted[3]  # the change arrived
    ipc.close()
    plc.close()


def test_sent_frames_deep_copy_like_python_can_messages() -> None:
    """The virtual bus deep-copies each frame sent: the cheaper copy is an equal,
    independent can.Message."""
    import copy

    from plc_bridge.link.side import _TxMessage

    for kw in (
        {"arbitration_id": 0x200, "data": bytes(range(8)), "is_extended_id": False},
        {"arbitration_id": 0x1ABCDE, "data": b"\x01", "channel": "c0", "is_rx": False},
    ):
        msg = _TxMessage(check=False, **kw)  # type: ignore[arg-type]
        ref = copy.deepcopy(can.Message(check=False, **kw))  # type: ignore[arg-type]
        got = copy.deepcopy(msg)
        assert type(got) is can.Message
        assert all(getattr(got, a) == getattr(ref, a) for a in can.Message.__slots__ if a[0] != "_")
        assert got.data == msg.data and got.data is not msg.data
        got.data[0] ^= 0xFF
        assert got.data != msg.data  # independent


def test_counter_lookup_is_check_counter(project: ProjectConfig) -> None:
    from plc_bridge.e2e import check_counter
    from plc_bridge.supervision import RxRecord

    for max_delta in (1, 2, 5, 14):
        rec = RxRecord(FrameCodec(CAT.by_name("PLC_RodPos_0")), 0.1, max_delta)
        for last in (None, *range(15)):
            for counter in range(16):
                i = (15 if last is None else last) * 16 + counter
                assert rec._counter_checks[i] == check_counter(last, counter, max_delta)


def test_plc_timeouts_skipped_until_they_can_change_answer_as_every_record(
    project: ProjectConfig,
) -> None:
    """The PLC's per-scan questions (command_timeout, ipc_timeout, the stale edges of
    poll) skip their records until an answer can change (RxRecord.fresh_until_s): each
    answer, edge and counter is the one the records give when all are asked every scan,
    through gaps in the frames, a stale valve frame and a change of the fast group (new
    timeouts, with grace)."""
    clock = Clock()
    ipc_bus, plc_bus, ref_bus = QueueBus(), QueueBus(), QueueBus()
    ipc = IpcLink(project, ipc_bus, clock=clock)
    plc = PlcLink(project, plc_bus, clock=clock)
    ref = PlcLink(project, ref_bus, clock=clock)  # every record asked every scan
    limit = project.safety.command_timeout_ms / 1000.0
    valve_2 = CAT.by_name("IPC_ValveCmd_2").frame_id
    seen = set()
    for k in range(1600):  # 1 ms PLC scans, the IPC's cycle every 5
        now = clock.t
        if k % 5 == 0:
            if k == 700:
                ipc.set_active_cylinders(range(4))  # another fast group: other timeouts
            ipc.poll(now)
            ipc.send_valve_commands(U, now)
            for m in ipc_bus.sent:
                lost = 300 <= k < 420 or (1000 <= k < 1100 and m.arbitration_id == valve_2)
                if not lost:
                    plc_bus.inject(m)
                    ref_bus.inject(m)
            ipc_bus.sent.clear()
        ref._stale_check_at = -math.inf
        plc.poll(now)
        ref.poll(now)
        recs = ref._command_recs
        exact = (
            any(not r.fresh(now) for r in recs),
            any(r.age_s(now) > limit for r in recs),
        )
        assert (plc.command_timeout(now), plc.ipc_timeout(now)) == exact, k
        assert [(r.was_fresh, dict(r.counters), r.values) for r in plc._rx.values()] == [
            (r.was_fresh, dict(r.counters), r.values) for r in ref._rx.values()
        ], k
        seen.add(exact)
        clock.advance(0.001)
    assert seen == {(False, False), (True, False), (True, True)}
    assert sum(r.counters["timeouts"] for r in plc._rx.values()) > 2
    for link in (ipc, plc, ref):
        link.close()
