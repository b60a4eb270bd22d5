"""Recovery from a bus-off does not depend on how the bus was made: a bus passed in (the
demo, the tests) comes back after the back-off as a bus the link opened itself does."""

from __future__ import annotations

import uuid
from collections.abc import Callable

import can
import numpy as np
import pytest

from config import ProjectConfig
from plc_bridge import IpcLink, LinkState, PlcLink, PlcStatus
from plc_bridge.bus import CAN_ERR_BUSOFF
from plc_bridge.supervision import BusState
from tests.plc_fakes import Clock

DT = 0.005


def _pair(project: ProjectConfig, passed_in: bool) -> tuple[IpcLink, PlcLink, can.BusABC, Clock]:
    """Both sides on a private virtual channel (as the demo wires them), and a third
    node on it that can put an error frame on the wire."""
    channel = f"busoff-{uuid.uuid4().hex}"
    clock = Clock()

    def opener() -> Callable[[], can.BusABC]:
        return lambda: can.Bus(interface="virtual", channel=channel, receive_own_messages=False)

    if passed_in:
        ipc = IpcLink(project, opener()(), clock=clock)
        plc = PlcLink(project, opener()(), clock=clock)
    else:
        ipc = IpcLink(project, bus_factory=opener(), clock=clock)
        plc = PlcLink(project, bus_factory=opener(), clock=clock)
    return ipc, plc, opener()(), clock


def _run(ipc: IpcLink, plc: PlcLink, clock: Clock, seconds: float) -> None:
    plc.set_status(PlcStatus(pump_running=True))
    plc.set_positions_m(np.full(19, 0.4))
    for _ in range(round(seconds / DT)):
        plc.poll()
        ipc.poll()
        ipc.send_valve_commands(np.zeros(19))
        clock.advance(DT)


@pytest.mark.parametrize("passed_in", [True, False], ids=["bus passed in", "bus factory"])
def test_one_stray_bus_off_frame_is_recovered(project: ProjectConfig, passed_in: bool) -> None:
    ipc, plc, other, clock = _pair(project, passed_in)
    try:
        _run(ipc, plc, clock, 0.5)
        assert ipc.state() is LinkState.OK and plc.state() is LinkState.OK
        other.send(can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8)))
        _run(ipc, plc, clock, 0.05)
        # both saw it: nothing is sent, the peer goes silent
        assert ipc.bus_health.state is BusState.BUS_OFF
        assert plc.bus_health.state is BusState.BUS_OFF
        assert ipc.state() is LinkState.LOST
        _run(ipc, plc, clock, 1.5)  # back-off 0.1 s, then the FAULT_HOLD of the link
        assert ipc.bus_health.state is BusState.ACTIVE
        assert plc.bus_health.state is BusState.ACTIVE
        assert ipc.state() is LinkState.OK and plc.state() is LinkState.OK
        assert ipc.bus_health.counters["bus_off_events"] == 1
        assert ipc.bus_health.counters["reopened"] == 1
        assert ipc.status() is not None
    finally:
        ipc.close()
        plc.close()
        other.shutdown()


def test_a_bus_still_off_goes_off_again_with_a_longer_back_off(project: ProjectConfig) -> None:
    """A passed-in bus used again while its controller is still off reports bus-off again;
    the back-off grows each time, so the retries stay bounded."""
    ipc, plc, other, clock = _pair(project, passed_in=True)
    off = can.Message(arbitration_id=CAN_ERR_BUSOFF, is_error_frame=True, data=bytes(8))
    retries: list[float] = []
    try:
        for _ in range(400):  # 2 s: bus-off reported again after every retry
            before = ipc.bus_health.counters["reopened"]
            ipc.poll()
            if ipc.bus_health.counters["reopened"] != before:
                retries.append(clock.t)
            if ipc.bus_health.state is BusState.ACTIVE:
                other.send(off)
            clock.advance(DT)
        assert ipc.state() is LinkState.LOST
        gaps = np.diff(retries)
        assert len(retries) >= 3 and bool(np.all(np.diff(gaps) > 0))
    finally:
        ipc.close()
        plc.close()
        other.shutdown()
