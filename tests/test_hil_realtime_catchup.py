"""A simulator process that was held up (a busy machine) runs the missed PLC scans back
to back. Each of those scans must see the bus as an on-time PLC would have: the frames
that had arrived by its due time (``FaultyWire.set_arrival_horizon``, which
``HilSimulator.run_realtime`` sets per scan). Otherwise the frames of the whole stall
arrive in its first scan and none in the next ones, and the PLC latches a false
IPC_TIMEOUT (seen in two-process demos on a loaded machine)."""

from __future__ import annotations

import uuid
from typing import Any

import can
import numpy as np

from config import ProjectConfig
from hil_sim.simulator import HilSimulator
from plc_bridge import Fault, IpcLink, Mode

T0 = 1.0e9  # epoch seconds of simulated time 0 (any base: the stamps are explicit)
U = np.zeros(19)
U[8:12] = 0.2


class StampedBus(can.BusABC):
    """The IPC's bus: every frame leaves with the arrival stamp ``stamp`` (epoch s)."""

    def __init__(self, channel: str, **kwargs: Any) -> None:
        super().__init__(channel=channel, **kwargs)
        self.inner = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
        self.stamp = 0.0

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        msg.timestamp = self.stamp
        self.inner.send(msg, timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.inner.recv(timeout), False

    def shutdown(self) -> None:
        super().shutdown()
        self.inner.shutdown()


def _stall_then_catch_up(project: ProjectConfig, horizon: bool) -> tuple[list[bool], int]:
    channel = f"catchup-{uuid.uuid4().hex}"
    sim = HilSimulator(project, can.Bus(interface="virtual", channel=channel))
    bus = StampedBus(channel)
    now = [0.0]
    ipc = IpcLink(project, bus, clock=lambda: now[0])
    try:
        ipc.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)

        def ipc_cycle(t: float) -> None:
            now[0] = t
            bus.stamp = T0 + t
            ipc.poll()
            ipc.send_valve_commands(U)

        for _ in range(60):  # 0.3 s on time: drives on, the link fresh
            ipc_cycle(sim.t_s)
            sim.step(0.005)
        assert sim.status.drives_enabled
        stalled_at = sim.t_s
        for i in range(8):  # the simulator is held up for 40 ms; the IPC goes on
            ipc_cycle(stalled_at + 0.005 * i)
        timeouts = []
        for k in range(40):  # the missed scans, back to back
            if horizon:
                sim.wire.set_arrival_horizon(T0 + stalled_at + 0.001 * k)
            sim.step(0.001)
            timeouts.append(sim.plc.command_timeout(sim.t_s))
        return timeouts, sim.status.fault
    finally:
        ipc.close()
        sim.close()


def test_catching_up_scans_see_frames_by_arrival(project: ProjectConfig) -> None:
    timeouts, fault = _stall_then_catch_up(project, horizon=True)
    assert not any(timeouts)
    assert fault == Fault.NONE


def test_without_the_horizon_the_stall_looks_like_a_silent_ipc(project: ProjectConfig) -> None:
    """The catching-up scans see the commands stale and centre the spools; a loss of
    40 ms is shorter than safety.command_timeout_ms, so nothing is latched."""
    timeouts, fault = _stall_then_catch_up(project, horizon=False)
    assert any(timeouts)
    assert fault == Fault.NONE


def test_frames_on_another_clock_are_never_held_back(project: ProjectConfig) -> None:
    """A stamp far from the horizon (another clock) passes; order is kept."""
    channel = f"catchup-{uuid.uuid4().hex}"
    sim = HilSimulator(project, can.Bus(interface="virtual", channel=channel))
    tx = can.Bus(interface="virtual", channel=channel, preserve_timestamps=True)
    try:
        wire = sim.wire
        wire.set_arrival_horizon(T0)
        for i, stamp in enumerate((T0 - 0.5, T0 + 0.002, T0 + 5.0, 0.0)):
            tx.send(can.Message(arbitration_id=0x7F0 + i, data=b"", timestamp=stamp))
        assert wire.recv(0.0).arbitration_id == 0x7F0  # arrived before the horizon
        assert wire.recv(0.0) is None  # 2 ms after it: the next scan's
        assert wire.recv(0.0) is None  # and it holds back the ones behind it
        wire.set_arrival_horizon(T0 + 0.002)
        assert [wire.recv(0.0).arbitration_id for _ in range(3)] == [0x7F1, 0x7F2, 0x7F3]
        wire.set_arrival_horizon(None)
    finally:
        tx.shutdown()
        sim.close()
