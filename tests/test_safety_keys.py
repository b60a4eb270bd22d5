"""Every key under ``safety`` governs something: for each key, the same situation with
the shipped value and with a changed value ends differently.

The cases run the real pieces (the service core on a virtual bus, the PLC side in the
HIL simulator) at the point where the key is read; the end-to-end tests show each
reaction in the whole system.
"""

from __future__ import annotations

import itertools
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from config import ProjectConfig, load_project
from config.schema import Cycle, Planner, Safety, Walking
from ipc_app.control.attitude import LayerMetrics
from ipc_app.service.app import ctl_server
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import CtlHandlers
from ipc_app.service.interlocks import SPECS, Interlock, Limits, motion_causes, present_causes
from ipc_app.service.modes import Mode
from plc_bridge import Fault
from plc_bridge.link import IpcLink, PlcLink, PlcStatus, Reading
from tests.hil_helpers import make_bench
from tests.machine_inputs import machine_inputs

_channels = itertools.count()
_STATUS = PlcStatus(pump_running=True, drives_enabled=True)


class _NoPlanner:
    def submit(self, *a: Any, **k: Any) -> bool:
        return False

    def poll(self) -> None:
        return None


def _with(cfg: ProjectConfig, **safety: float) -> ProjectConfig:
    return cfg.model_copy(update={"safety": cfg.safety.model_copy(update=safety)})


def _core(cfg: ProjectConfig) -> ServiceCore:
    bus = can.Bus(interface="virtual", channel=f"safety-{next(_channels)}")
    return ServiceCore(cfg, IpcLink(cfg, bus, clock=lambda: 0.0), _NoPlanner())


def _limits(cfg: ProjectConfig) -> Limits:
    layers = (cfg.layers.lower.cylinders, cfg.layers.upper.cylinders)
    return Limits.from_config(cfg, [cfg.cylinder(c).can_index for ids in layers for c in ids])


def _motion_faults(cfg: ProjectConfig, metrics: LayerMetrics, x: np.ndarray | None = None) -> Any:
    metrics_of = {"lower": metrics, "upper": LayerMetrics(0.0, 0.0, 0.0)}
    got = motion_causes(machine_inputs(cfg, x=x), metrics_of, _limits(cfg))
    return {c.interlock for c in got}


def twist(cfg: ProjectConfig) -> Any:
    return _motion_faults(cfg, LayerMetrics(0.0, 1.2e-3, 0.0))


def sync(cfg: ProjectConfig) -> Any:
    return _motion_faults(cfg, LayerMetrics(1.8e-3, 0.0, 0.0))


def tracking(cfg: ProjectConfig) -> Any:
    return _motion_faults(cfg, LayerMetrics(0.0, 0.0, 8e-3))


def stroke_end(cfg: ProjectConfig) -> Any:
    x = np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])
    x[_limits(cfg).active[0]] = 3e-3  # 3 mm from the retracted end
    return _motion_faults(cfg, LayerMetrics(0.0, 0.0, 0.0), x)


def pressure(cfg: ProjectConfig) -> Any:
    p = np.full((len(cfg.cylinders), 2), 20e6)
    return {c.interlock for c in present_causes(machine_inputs(cfg, p=p), _limits(cfg))}


def sensor_timeout(cfg: ProjectConfig) -> Any:
    """The active group's positions 80 ms old."""
    n = len(cfg.cylinders)
    pos = Reading(np.full(n, np.nan), np.zeros(n, bool), np.full(n, 0.08))
    inp = machine_inputs(cfg, positions=pos)
    return {c.interlock for c in present_causes(inp, _limits(cfg))}


def heartbeat(cfg: ProjectConfig) -> Any:
    """The PLC status 150 ms old: the IPC still has it, or not."""
    ch = f"safety-{next(_channels)}"
    clock = [0.0]
    ipc = IpcLink(cfg, can.Bus(interface="virtual", channel=ch), clock=lambda: clock[0])
    plc = PlcLink(cfg, can.Bus(interface="virtual", channel=ch), clock=lambda: clock[0])
    try:
        plc.set_status(_STATUS)
        for _ in range(40):
            clock[0] += 0.005
            plc.poll(clock[0])
            ipc.poll(clock[0])
        clock[0] += 0.15
        ipc.poll(clock[0])
        return ipc.status(clock[0]) is None
    finally:
        ipc.close()
        plc.close()


def command_timeout(cfg: ProjectConfig) -> Any:
    """The IPC silent for 150 ms while the PLC drives: IPC_TIMEOUT latched, or not
    (the spools are centred either way)."""
    b = make_bench(cfg)
    try:
        b.start()
        u = np.zeros(19)
        u[8:12] = 0.3
        b.run(0.2, u)
        b.run(0.15, ipc_alive=False)
        st = b.sim.truth().status
        assert st.command_timeout and not st.drives_enabled
        return Fault(st.fault)
    finally:
        b.close()


def max_suspend(cfg: ProjectConfig) -> Any:
    """Suspended, the link still dropping out after 200 ms."""
    core = _core(cfg)
    try:
        core.modes.boot_complete()
        core.modes.request_adjust(1.0, 0.0)
        core.modes.plan_ready()
        core.motions.ride_through(0.0, ["stale"], machine_inputs(cfg, t=0.0))
        assert core.modes.mode is Mode.SUSPENDED
        core.motions.ride_through(0.2, ["stale"], machine_inputs(cfg, t=0.2))
        return core.modes.mode, core.modes.fault_interlocks
    finally:
        core.link.close()


def boot_timeout(cfg: ProjectConfig) -> Any:
    """Start-up with no PLC status for 6 s: still waiting, or ABORTED."""
    core = _core(cfg)
    lost = {"status": None, "status_age_s": np.inf}
    try:
        for t in np.arange(0.0, 6.01, 0.5):
            core.update(machine_inputs(cfg, t=float(t), **lost))
        return core.modes.mode, core.modes.fault_interlocks
    finally:
        core.link.close()


def ctl_stall(cfg: ProjectConfig) -> str:
    """The service's control channel (as ``wara serve`` makes it) with its I/O thread
    caught in one turn for 6 s: its state (``stalled`` latches ``control channel``)."""
    entered, release = threading.Event(), threading.Event()

    def stuck_turn(_sel: object) -> None:
        entered.set()
        release.wait(10.0)

    handlers = CtlHandlers(dict, dict, dict, dict)
    with tempfile.TemporaryDirectory(prefix="wara-") as tmp:
        server = ctl_server(cfg, handlers, Path(tmp) / "c.sock")
        server._turn = stuck_turn  # type: ignore[method-assign]
        server.start()
        try:
            assert entered.wait(10.0)
            server._tick -= 6.0  # its last turn began 6 s ago
            return server.state()
        finally:
            release.set()
            server.stop()


CASES: dict[str, tuple[float, Callable[[ProjectConfig], Any]]] = {
    # key: (changed value, the situation)
    "max_twist_mm": (1.0, twist),
    "max_sync_error_mm": (1.5, sync),
    "max_tracking_error_mm": (5.0, tracking),
    "max_pressure_mpa": (18.0, pressure),
    "stroke_end_margin_mm": (2.0, stroke_end),
    "sensor_timeout_ms": (50.0, sensor_timeout),
    "plc_heartbeat_timeout_ms": (200.0, heartbeat),
    "command_timeout_ms": (200.0, command_timeout),
    "max_suspend_ms": (150.0, max_suspend),
    "boot_timeout_s": (10.0, boot_timeout),
    "ctl_stall_timeout_s": (10.0, ctl_stall),
}


def test_every_safety_key_has_a_case() -> None:
    assert set(CASES) == set(Safety.model_fields)


def test_every_interlock_key_is_a_config_key() -> None:
    keys = {s.key for s in SPECS.values() if s.key is not None}
    walking = {f"walking.{k}" for k in Walking.model_fields}  # tests/test_walk_interlocks.py
    planner = {"planner.request_timeout_s"}  # tests/test_service_worker.py: the timeout
    cycle = {"cycle.release_max_travel_mm"}  # tests/test_release.py, test_service_cycle.py
    assert keys <= {f"safety.{k}" for k in Safety.model_fields} | walking | planner | cycle
    assert all(k in Cycle.model_fields for k in (c.split(".")[1] for c in cycle))
    assert all(k in Planner.model_fields for k in (p.split(".")[1] for p in planner))


@pytest.mark.parametrize("key", sorted(CASES))
def test_changing_the_key_changes_the_behaviour(key: str) -> None:
    cfg = load_project()
    changed, situation = CASES[key]
    assert getattr(cfg.safety, key) != changed
    before = situation(cfg)
    after = situation(_with(cfg, **{key: changed}))
    assert before != after, (key, before, after)


def test_the_cases_see_the_reaction_they_stand_for() -> None:
    """Not just different: the interlock of each key trips on the side it should."""
    cfg = load_project()
    assert twist(cfg) == set() and twist(_with(cfg, max_twist_mm=1.0)) == {Interlock.TWIST}
    assert sync(_with(cfg, max_sync_error_mm=1.5)) == {Interlock.SYNC_ERROR}
    assert tracking(_with(cfg, max_tracking_error_mm=5.0)) == {Interlock.TRACKING_ERROR}
    assert pressure(_with(cfg, max_pressure_mpa=18.0)) == {Interlock.PRESSURE}
    assert stroke_end(cfg) == {Interlock.STROKE_END}
    assert stroke_end(_with(cfg, stroke_end_margin_mm=2.0)) == set()
    assert sensor_timeout(_with(cfg, sensor_timeout_ms=50.0)) == {Interlock.SENSOR_TIMEOUT}
    assert heartbeat(cfg) is True and heartbeat(_with(cfg, plc_heartbeat_timeout_ms=200.0)) is False
    assert command_timeout(cfg) is Fault.IPC_TIMEOUT
    assert command_timeout(_with(cfg, command_timeout_ms=200.0)) is Fault.NONE
    assert max_suspend(cfg) == (Mode.SUSPENDED, ())
    assert max_suspend(_with(cfg, max_suspend_ms=150.0)) == (
        Mode.ABORTED,
        (Interlock.SUSPEND_TIMEOUT,),
    )
    assert boot_timeout(cfg) == (Mode.ABORTED, (Interlock.PLC_HEARTBEAT, Interlock.STARTUP))
    assert boot_timeout(_with(cfg, boot_timeout_s=10.0)) == (Mode.STOPPED, ())
    assert ctl_stall(cfg) == "stalled" and ctl_stall(_with(cfg, ctl_stall_timeout_s=10.0)) == "ok"
