"""The service core's step: the interlock checks and the mode decisions from one cycle's
:class:`MachineInputs` built by hand (no bus, no link), the handshake's control words,
and at the end two runs on real parts (a python-can virtual bus, the PLC side of the
protocol driving the real cylinder model, the real planner worker) for the wiring."""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator
from dataclasses import replace
from typing import Any

import can
import numpy as np
import pytest
from pydantic import ValidationError

from config import ProjectConfig
from hil_sim.hydraulics import CylinderBank, CylinderParams
from ipc_app.control.attitude import LayerMetrics
from ipc_app.model import MachineStatics
from ipc_app.service.core import ServiceCore
from ipc_app.service.interlocks import (
    Interlock,
    Limits,
    link_losses,
    motion_causes,
    present_causes,
    resume_cause,
)
from ipc_app.service.machine_io import Handshake
from ipc_app.service.modes import Mode
from ipc_app.service.motions.attitude import AdjustMotion, JogMotion
from ipc_app.service.worker import PlannerWorker, PlanResult
from plc_bridge.link import (
    ControlWord,
    Fault,
    HmiTarget,
    IpcLink,
    LimitSwitches,
    PlcLink,
    PlcStatus,
    TargetAck,
    TargetRequest,
)
from plc_bridge.link import Mode as PlcMode
from tests.machine_inputs import HEALTHY, machine_inputs, reading

# --------------------------------------------------------------------------- the checks


@pytest.fixture()
def lim(project: ProjectConfig) -> Limits:
    return Limits.from_config(project, _active(project))


def _active(cfg: ProjectConfig) -> tuple[int, ...]:
    layers = (cfg.layers.lower.cylinders, cfg.layers.upper.cylinders)
    return tuple(cfg.cylinder(c).can_index for ids in layers for c in ids)


def _mid(cfg: ProjectConfig) -> np.ndarray:
    return np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])


_CALM = {"lower": LayerMetrics(0.0, 0.0, 0.0), "upper": LayerMetrics(0.0, 0.0, 0.0)}


def test_a_healthy_machine_trips_nothing(project: ProjectConfig, lim: Limits) -> None:
    inp = machine_inputs(project)
    assert present_causes(inp, lim) == []
    assert link_losses(inp) == []
    assert motion_causes(inp, _CALM, lim) == []
    assert resume_cause(inp, inp.positions.value.tolist(), lim) is None


def test_pressure_names_the_cylinder_and_skips_invalid_readings(
    project: ProjectConfig, lim: Limits
) -> None:
    p = np.full((len(project.cylinders), 2), 10e6)
    i, j = lim.active[5], lim.active[0]
    p[i, 1] = lim.max_pressure_pa + 1e6
    p[j, 0] = np.nan  # an invalid reading is never the peak
    (cause,) = present_causes(machine_inputs(project, p=p), lim)
    assert cause.key == (Interlock.PRESSURE, lim.ids[i])
    assert cause.value == pytest.approx(project.safety.max_pressure_mpa + 1.0)
    assert cause.limit == project.safety.max_pressure_mpa
    p[:] = np.nan  # nothing valid: nothing over the limit
    assert present_causes(machine_inputs(project, p=p), lim) == []


def test_a_lost_plc_status_is_the_heartbeat(project: ProjectConfig, lim: Limits) -> None:
    never = machine_inputs(project, status=None, status_age_s=np.inf)
    (cause,) = present_causes(never, lim)
    assert cause.interlock is Interlock.PLC_HEARTBEAT and cause.detail == "PLC status lost"
    late = machine_inputs(project, status=None, status_age_s=0.15)
    (cause,) = present_causes(late, lim)
    assert cause.value == pytest.approx(150.0)
    assert cause.limit == project.safety.plc_heartbeat_timeout_ms
    (cause,) = present_causes(machine_inputs(project, bus_ok=False), lim)
    assert cause.interlock is Interlock.PLC_HEARTBEAT and cause.detail == "bus off or down"
    assert link_losses(never) == ["PLC status stale"]


@pytest.mark.parametrize(
    ("code", "where"),
    [(Fault.NONE, None), (Fault.ESTOP, None), (Fault.IPC_TIMEOUT, "IPC_TIMEOUT"), (77, "77")],
)
def test_plc_fault_codes(project: ProjectConfig, lim: Limits, code: int, where: str) -> None:
    inp = machine_inputs(project, status=replace(HEALTHY, fault=code))
    got = [c.key for c in present_causes(inp, lim)]
    assert got == ([] if where is None else [(Interlock.PLC_FAULT, where)])


def test_sensor_fault_and_sensor_timeout(project: ProjectConfig, lim: Limits) -> None:
    x = _mid(project)
    a, b = lim.active[2], lim.active[4]
    x[a] = x[b] = np.nan
    pos = reading(x)
    pos.age_s[a] = 0.0
    pos.age_s[b] = lim.sensor_timeout_s * 0.9
    inp = machine_inputs(project, positions=pos, failed_sensors=frozenset({a}))
    assert not inp.positions_valid
    assert [c.key for c in present_causes(inp, lim)] == [(Interlock.SENSOR, lim.ids[a])]
    pos.age_s[b] = lim.sensor_timeout_s + 0.01
    got = present_causes(replace(inp, positions=pos), lim)
    assert [c.key for c in got] == [
        (Interlock.SENSOR, lim.ids[a]),
        (Interlock.SENSOR_TIMEOUT, lim.ids[b]),
    ]
    assert link_losses(inp) == ["rod positions of the active group stale"]
    # only the first timed-out cylinder is named; one never received says so
    pos2 = reading(np.full(len(project.cylinders), np.nan))
    (cause,) = present_causes(machine_inputs(project, positions=pos2), lim)
    assert cause.key == (Interlock.SENSOR_TIMEOUT, lim.ids[lim.active[0]])
    assert cause.detail == "never received" and cause.value is None


def test_link_losses_of_a_stale_status_and_stale_commands(project: ProjectConfig) -> None:
    assert link_losses(machine_inputs(project, status_stale=True)) == ["PLC status stale"]
    inp = machine_inputs(project, status=replace(HEALTHY, command_timeout=True))
    assert link_losses(inp) == ["the PLC reports the IPC's commands stale"]


@pytest.mark.parametrize(
    ("figure", "limit", "interlock"),
    [
        ("twist_m", "max_twist_m", Interlock.TWIST),
        ("sync_error_m", "max_sync_m", Interlock.SYNC_ERROR),
        ("tracking_error_m", "max_tracking_m", Interlock.TRACKING_ERROR),
    ],
)
def test_motion_figures_over_their_limits(
    project: ProjectConfig, lim: Limits, figure: str, limit: str, interlock: Interlock
) -> None:
    at = getattr(lim, limit)
    for value, tripped in ((at * 0.99, False), (at * 1.01, True)):
        upper = replace(_CALM["upper"], **{figure: value})
        got = motion_causes(machine_inputs(project), {**_CALM, "upper": upper}, lim)
        assert [c.key for c in got] == ([(interlock, "upper")] if tripped else [])


def test_stroke_end_names_the_first_cylinder_and_the_limit_switch(
    project: ProjectConfig, lim: Limits
) -> None:
    x = _mid(project)
    j, k = lim.active[6], lim.active[7]
    x[j] = lim.stroke_m[j] - lim.end_margin_m / 2
    x[k] = 0.0
    (cause,) = motion_causes(machine_inputs(project, x=x), _CALM, lim)
    assert cause.key == (Interlock.STROKE_END, lim.ids[j])
    assert cause.value == pytest.approx(project.safety.stroke_end_margin_mm / 2)
    at = [False] * len(lim.active)
    at[1] = True
    (cause,) = motion_causes(machine_inputs(project, at_limit=at), _CALM, lim)
    assert cause.key == (Interlock.STROKE_END, lim.ids[lim.active[1]])
    assert cause.detail == "(limit switch)"


def test_resume_check(project: ProjectConfig, lim: Limits) -> None:
    inp = machine_inputs(project)
    ref = inp.positions.value.tolist()
    i = lim.active[3]
    ref[i] += lim.max_sync_m * 1.5
    cause = resume_cause(inp, ref, lim)
    assert cause is not None and cause.key == (Interlock.RESUME_CHECK, lim.ids[i])
    p = np.full((len(project.cylinders), 2), 10e6)
    p[lim.active[0], 1] = np.nan
    cause = resume_cause(machine_inputs(project, p=p), None, lim)
    assert cause is not None and cause.key == (Interlock.RESUME_CHECK, "pressures")


def test_checks_agree_with_their_numpy_reference_definitions(
    project: ProjectConfig, lim: Limits
) -> None:
    """The pressure peak (one reduction) and the stroke-end check (plain floats) give the
    causes of their definitions written with numpy masks (here)."""
    rng = np.random.default_rng(3)
    n = len(project.cylinders)
    act = np.array(lim.active)
    stroke = np.array(lim.stroke_m)

    def pressure_reference(p: np.ndarray, valid: np.ndarray) -> list[tuple[Interlock, str]]:
        if valid.any():
            pv = np.where(valid, p, 0.0)
            if float(pv.max()) > lim.max_pressure_pa:
                return [(Interlock.PRESSURE, lim.ids[int(np.argmax(pv.max(axis=1)))])]
        return []

    hits = 0
    for k in range(400):
        p = rng.uniform(-1e6, lim.max_pressure_pa * (1.1 if k % 2 else 0.99), (n, 2))
        p[rng.random((n, 2)) < (0.3 if k % 3 else 1.0)] = np.nan  # some or all invalid
        got = [c.key for c in present_causes(machine_inputs(project, p=p), lim)]
        want = pressure_reference(p, ~np.isnan(p))
        assert got == want
        hits += len(want)
    assert 50 < hits < 350  # both outcomes exercised

    def stroke_reference(x: np.ndarray, limits: LimitSwitches | None) -> list[tuple[Any, ...]]:
        xa = x[act]
        near = (xa < lim.end_margin_m) | (xa > stroke[act] - lim.end_margin_m)
        if limits is not None:
            near |= limits.retracted[act] | limits.extended[act]
        if near.any():
            i = int(act[int(np.argmax(near))])
            v = float(x[i])
            return [(Interlock.STROKE_END, lim.ids[i], min(v, stroke[i] - v) * 1e3)]
        return []

    hits = 0
    switches: LimitSwitches | None = None
    for k in range(400):
        x = stroke * rng.uniform(-0.002, 1.002, n)
        if k % 4 == 0:
            x = stroke / 2
        if k % 5 == 0:
            switches = LimitSwitches(rng.random(n) < 0.05, rng.random(n) < 0.05)
        elif k % 5 == 1:
            switches = None
        at = None if switches is None else (switches.retracted | switches.extended)[act].tolist()
        causes = motion_causes(machine_inputs(project, x=x, at_limit=at), {}, lim)
        got = [(c.interlock, c.where, pytest.approx(c.value)) for c in causes]
        assert got == stroke_reference(x, switches), k
        hits += len(causes)
    assert 50 < hits < 350


# --------------------------------------------------------------------------- handshake


def test_handshake_answers_the_request_served_and_not_a_local_one() -> None:
    hs = Handshake()
    hs.begin()
    hs.serve(7)
    hs.ack(TargetAck.REJECTED, 8)  # another request refused: its own seq
    hs.ack(TargetAck.ACCEPTED)  # the one served
    words = hs.finish(PlcMode.IDLE, False)
    assert [(w.ack_seq, w.ack_status) for w in words] == [
        (8, TargetAck.REJECTED),
        (7, TargetAck.ACCEPTED),
    ]
    hs.begin()
    hs.serve(0)
    hs.ack(TargetAck.COMPLETED)  # local: nothing to answer
    assert hs.finish(PlcMode.IDLE, False) == ()  # nothing changed: nothing to send
    hs.begin()
    assert hs.finish(PlcMode.ATTITUDE_ADJUST, True) == (
        ControlWord(PlcMode.ATTITUDE_ADJUST, True, ack_seq=7, ack_status=TargetAck.ACCEPTED),
    )


def test_reset_pulse_until_the_plc_fault_clears_or_the_pulse_ends() -> None:
    hs = Handshake()
    # no PLC fault: the pulse goes on the wire and off again in the same cycle
    hs.request_reset()
    hs.begin()
    assert hs.reset_step(0.0, plc_fault=False)
    assert [w.fault_reset for w in hs.finish(PlcMode.IDLE, False)] == [True, False]
    assert not hs.resetting
    # a PLC fault that stays: held for RESET_PULSE_S, then the modes are asked anyway
    hs.request_reset()
    t = 0.0
    seen = []
    while True:
        hs.begin()
        done = hs.reset_step(t, plc_fault=True)
        seen.append((t, hs.word.fault_reset))
        hs.finish(PlcMode.IDLE, False)
        if done:
            break
        t += 0.1
    assert seen[0] == (0.0, True) and seen[-1][1] is False
    assert seen[-1][0] == pytest.approx(Handshake.RESET_PULSE_S)


# --------------------------------------------------------------------------- modes


class _NoLink:
    """What ServiceCore's set-up asks of the link; :meth:`ServiceCore.update` asks nothing."""

    control = ControlWord()

    def set_active_cylinders(self, active: Any) -> None:
        return None


class _Planner:
    def __init__(self) -> None:
        self.submitted: list[tuple[Any, ...]] = []
        self.result: PlanResult | None = None

    def submit(self, request_id: int, roll_deg: float, pitch_deg: float, **kw: Any) -> bool:
        self.submitted.append((request_id, roll_deg, pitch_deg))
        return True

    def poll(self) -> PlanResult | None:
        r, self.result = self.result, None
        return r


def _bare_core(cfg: ProjectConfig) -> tuple[ServiceCore, _Planner]:
    planner = _Planner()
    return ServiceCore(cfg, _NoLink(), planner), planner  # type: ignore[arg-type]


def _update(core: ServiceCore, inp: Any) -> tuple[ControlWord, ...]:
    core.update(inp)
    return core.control_words()


def _holding(core: ServiceCore, cfg: ProjectConfig, t: float) -> None:
    assert core.modes.request_adjust(1.0, 0.0).accepted and core.modes.plan_ready().accepted
    # no trajectory: done at once
    core.motions.take(AdjustMotion(core.attitude, None, (1.0, 0.0), None), machine_inputs(cfg, t=t))
    _update(core, machine_inputs(cfg, t=t))
    assert core.modes.mode is Mode.COMPLETE


def test_boot_waits_for_fresh_inputs_then_faults_after_the_timeout(
    project: ProjectConfig,
) -> None:
    core, _ = _bare_core(project)
    lost = {"status": None, "status_age_s": np.inf}
    for t in np.arange(0.0, core.boot_timeout_s, 0.5):
        _update(core, machine_inputs(project, t=float(t), **lost))
        assert core.modes.mode is Mode.STOPPED
    _update(core, machine_inputs(project, t=core.boot_timeout_s + 0.1, **lost))
    assert core.modes.mode is Mode.ABORTED
    assert set(core.modes.fault_interlocks) == {Interlock.PLC_HEARTBEAT, Interlock.STARTUP}
    core2, _ = _bare_core(project)
    _update(core2, machine_inputs(project))
    assert core2.modes.mode is Mode.IDLE and not core2.modes.valves_enabled


def test_a_fault_latches_and_resets_only_once_the_cause_is_gone(project: ProjectConfig) -> None:
    core, _ = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0))
    over = machine_inputs(project, t=0.1, status=replace(HEALTHY, fault=Fault.OVERPRESSURE))
    _update(core, over)
    assert core.modes.mode is Mode.ABORTED
    assert core.request_reset()["note"] == "resetting"
    words = _update(core, replace(over, t=0.2))  # the PLC fault stays: pulse held
    assert core.modes.mode is Mode.ABORTED and words[0].fault_reset
    words = _update(core, machine_inputs(project, t=0.3))  # cleared: pulse off, reset
    assert not words[-1].fault_reset and words[-1].state == 4  # the pulse off, IDLE
    assert core.modes.mode is Mode.IDLE
    # a reset with the cause still present is refused, the fault kept
    _update(core, over)
    core.request_reset()
    _update(core, replace(over, t=1.0))
    _update(core, replace(over, t=1.0 + Handshake.RESET_PULSE_S))
    assert core.modes.mode is Mode.ABORTED


def test_estop_needs_release_and_reset(project: ProjectConfig) -> None:
    core, _ = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0))
    _holding(core, project, 0.1)
    pressed = machine_inputs(project, t=0.2, status=replace(HEALTHY, estop=True))
    words = _update(core, pressed)
    assert core.modes.mode is Mode.ABORTED
    assert (words[-1].mode, words[-1].enable, words[-1].state) == (PlcMode.IDLE, False, 9)
    _update(core, machine_inputs(project, t=0.3))
    assert core.modes.mode is Mode.ABORTED  # released, not reset
    core.request_reset()
    _update(core, machine_inputs(project, t=0.4))
    assert core.modes.mode is Mode.IDLE


def test_motion_checks_run_only_with_the_valves_driven(project: ProjectConfig) -> None:
    x = _mid(project)
    i = project.cylinder(project.layers.upper.cylinders[0]).can_index
    x[i] = 0.001  # 1 mm from the retracted end
    core, _ = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0, x=x))
    assert core.modes.mode is Mode.IDLE  # not driven: not checked
    _holding(core, project, 0.1)
    _update(core, machine_inputs(project, t=0.2, x=x))
    assert core.modes.mode is Mode.ABORTED
    assert core.modes.fault_interlocks == (Interlock.STROKE_END,)


def test_a_short_loss_suspends_and_resumes_a_long_one_faults(project: ProjectConfig) -> None:
    core, _ = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0))
    _holding(core, project, 0.1)
    stale = {"status_stale": True}
    _update(core, machine_inputs(project, t=0.2, **stale))
    assert core.modes.mode is Mode.SUSPENDED and not core.modes.valves_enabled
    for k in range(ServiceCore.RESUME_FRESH_CYCLES):
        assert core.modes.mode is Mode.SUSPENDED
        _update(core, machine_inputs(project, t=0.25 + 0.005 * k))
    assert core.modes.mode is Mode.COMPLETE and (core.suspends, core.resumes) == (1, 1)
    # suspended again, the rods moved beyond the sync band meanwhile: resume check
    _update(core, machine_inputs(project, t=0.5, **stale))
    x = _mid(project)
    x[core.active[2]] += 2 * core.limits.max_sync_m
    for k in range(ServiceCore.RESUME_FRESH_CYCLES):
        _update(core, machine_inputs(project, t=0.55 + 0.005 * k, x=x))
    assert core.modes.fault_interlocks == (Interlock.RESUME_CHECK,)
    # and a loss longer than max_suspend_ms
    core2, _ = _bare_core(project)
    _update(core2, machine_inputs(project, t=0.0))
    _holding(core2, project, 0.1)
    _update(core2, machine_inputs(project, t=0.2, **stale))
    _update(core2, machine_inputs(project, t=0.21 + core2.max_suspend_s, **stale))
    assert core2.modes.fault_interlocks == (Interlock.SUSPEND_TIMEOUT,)


def test_hmi_requests_are_planned_answered_and_cancelled(project: ProjectConfig) -> None:
    core, planner = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0))
    req = HmiTarget(np.deg2rad(2.0), np.deg2rad(1.0), TargetRequest.NEW_TARGET, seq=5)
    _update(core, machine_inputs(project, t=0.1, hmi=req))
    assert core.modes.mode is Mode.STARTING and core.handshake.seq == 5
    assert planner.submitted == [(1, pytest.approx(2.0), pytest.approx(1.0))]
    # a second request while planning is refused with its own seq
    req2 = replace(req, seq=6)
    words = _update(core, machine_inputs(project, t=0.2, hmi=req2))
    assert [(w.ack_seq, w.ack_status) for w in words] == [(6, TargetAck.REJECTED)]
    # the planner finds the target infeasible: back to IDLE, the served seq rejected
    planner.result = PlanResult(1, False, ("stroke",), None, None, None, 0.01)
    words = _update(core, machine_inputs(project, t=0.3))
    assert core.modes.mode is Mode.IDLE
    assert (words[0].ack_seq, words[0].ack_status) == (5, TargetAck.REJECTED)
    assert words[-1].state == 4  # IDLE
    # a planner crash is an interlock
    _update(core, machine_inputs(project, t=0.4, hmi=replace(req, seq=7)))
    planner.result = PlanResult(2, False, (), "crashed", None, None, 0.01)
    _update(core, machine_inputs(project, t=0.5))
    assert core.modes.fault_interlocks == (Interlock.PLANNER,)
    # cancel from the HMI stops a hold and answers NONE
    core3, _ = _bare_core(project)
    _update(core3, machine_inputs(project, t=0.0))
    _holding(core3, project, 0.1)
    cancel = HmiTarget(0.0, 0.0, TargetRequest.CANCEL, seq=9)
    words = _update(core3, machine_inputs(project, t=0.2, hmi=cancel))
    assert core3.modes.mode is Mode.IDLE
    assert (words[0].ack_seq, words[0].ack_status) == (9, TargetAck.NONE)


def _manual_core(cfg: ProjectConfig) -> ServiceCore:
    core, _ = _bare_core(cfg)
    _update(core, machine_inputs(cfg, t=0.0))
    assert core.request_unit_mode("manual")["accepted"]
    return core


def test_jog_moves_one_cylinder_at_the_configured_speed_in_manual_only(
    project: ProjectConfig,
) -> None:
    core, _ = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0))
    cid = project.layers.upper.cylinders[1]
    i = project.cylinder(cid).can_index
    core.request_jog(cid, 2.0)
    _update(core, machine_inputs(project, t=0.1))
    assert core.modes.mode is Mode.IDLE  # PRODUCTION: refused
    assert core.request_unit_mode("MANUAL")["accepted"]
    for bad, dist, why in (("pump_1", 2.0, "not an attitude cylinder"), (cid, 5000.0, "outside")):
        ticket = core.request_motion(JogMotion, (bad, dist))
        _update(core, machine_inputs(project, t=0.2))
        assert ticket.reply is not None
        out = ticket.reply.to_dict()
        assert out["ok"] is False and why in out["error"]
        assert core.modes.mode is Mode.IDLE
    x0 = _mid(project)
    core.request_jog(cid, 2.0)
    _update(core, machine_inputs(project, t=1.0))
    assert core.modes.mode is Mode.EXECUTE and core.modes.valves_enabled
    speed = project.control.manual_jog_speed_mm_s * 1e-3
    ref = core.attitude.references(1.5)
    assert ref[i] - x0[i] == pytest.approx(speed * 0.5)
    others = [j for j in core.active if j != i]
    assert ref[others] == pytest.approx(x0[others])
    _update(core, machine_inputs(project, t=1.0 + 2e-3 / speed + 0.01))
    assert core.modes.mode is Mode.COMPLETE
    assert core.attitude.references(99.0)[i] - x0[i] == pytest.approx(2e-3)
    # and no unit-mode change while the pose is held
    assert not core.request_unit_mode("PRODUCTION")["accepted"]


def test_hold_stops_the_motion_and_unhold_goes_on_where_it_stopped(
    project: ProjectConfig,
) -> None:
    core = _manual_core(project)
    cid = project.layers.lower.cylinders[0]
    core.request_jog(cid, -3.0)
    _update(core, machine_inputs(project, t=1.0))
    assert core.modes.mode is Mode.EXECUTE
    _update(core, machine_inputs(project, t=1.005))
    core.request_hold()
    words = _update(core, machine_inputs(project, t=1.01))
    assert core.modes.mode is Mode.HELD and not words[-1].enable
    assert words[-1].state == 11  # PackML Held on the wire
    stop = core.motions.stop_ref
    assert stop is not None
    x = stop.copy()
    x[core.active[0]] += 2 * core.limits.max_sync_m  # moved while held: refused
    core.request_unhold()
    _update(core, machine_inputs(project, t=2.0, x=x))
    assert core.modes.mode is Mode.HELD
    core.request_unhold()
    _update(core, machine_inputs(project, t=3.0, x=stop.copy()))
    assert core.modes.mode is Mode.EXECUTE
    # the jog goes on from where it stopped: the time held is not travelled
    i = project.cylinder(cid).can_index
    assert core.attitude.references(3.005)[i] == pytest.approx(stop[i], abs=2e-5)


def test_clear_then_reset_from_a_fault(project: ProjectConfig) -> None:
    core, _ = _bare_core(project)
    _update(core, machine_inputs(project, t=0.0))
    over = machine_inputs(project, t=0.1, status=replace(HEALTHY, fault=Fault.OVERPRESSURE))
    _update(core, over)
    assert core.request_clear()["note"] == "clearing"
    words = _update(core, machine_inputs(project, t=0.2))
    assert core.modes.mode is Mode.STOPPED
    assert [w.fault_reset for w in words][:2] == [True, False] and words[-1].state == 2
    assert core.request_reset()["accepted"] and core.modes.mode is Mode.IDLE


# --------------------------------------------------------------------------- wiring

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
    # ready before the first request, as the service's planner is by the time an operator
    # asks: the MiniRig's cylinders creep while STARTING (no holding valves), and a plan
    # that arrives seconds late (the process still importing on a loaded machine) engages
    # from where they were, which the tracking-error interlock rightly refuses
    end = time.monotonic() + 120.0
    while not w.ready and time.monotonic() < end:
        time.sleep(0.05)
    assert w.ready, "the planner process did not start"
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
        if core.modes.mode == Mode.STARTING:
            time.sleep(0.002)  # the planner process works in wall-clock time
    return n


def test_adjusts_to_example_1_and_holds(project: ProjectConfig, worker: PlannerWorker) -> None:
    core, rig, clock = _setup(project, worker)
    _run(core, rig, clock, 0.5)
    assert core.modes.mode == Mode.IDLE, core.modes.snapshot()
    assert core.request_adjust(2.0, 1.0)["ok"]
    _run(core, rig, clock, 30.0, until=Mode.EXECUTE)
    assert core.modes.mode == Mode.EXECUTE, core.modes.snapshot()
    assert rig.plc.control(clock[0]) is not None
    _run(core, rig, clock, 60.0, until=Mode.COMPLETE)
    assert core.modes.mode == Mode.COMPLETE
    _run(core, rig, clock, 2.0)
    word = rig.plc.control(clock[0])
    assert word is not None and word.enable and word.mode is PlcMode.ATTITUDE_ADJUST
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
    k = _run(core, rig, clock, 1.0, until=Mode.ABORTED)
    assert core.modes.mode == Mode.ABORTED and k <= limit, (k, limit)
    assert core.modes.fault_interlocks[0] in (Interlock.SENSOR_TIMEOUT, Interlock.PLC_HEARTBEAT)
    _run(core, rig, clock, 0.1)
    assert {Interlock.SENSOR_TIMEOUT, Interlock.PLC_HEARTBEAT} <= set(core.modes.fault_interlocks)
    # reset is refused while the cause is present
    assert not core.modes.reset().accepted
    rig.silent = False
    _run(core, rig, clock, 0.5)
    assert core.request_reset(wait_s=0.0)["note"] == "resetting"
    _run(core, rig, clock, 0.1)
    assert core.modes.mode == Mode.IDLE


@pytest.mark.parametrize("bad", [0.0, -1.0, 25.0, float("nan")])
def test_the_jog_speed_key_is_bounded(project: ProjectConfig, bad: float) -> None:
    data = project.model_dump()
    data["control"]["manual_jog_speed_mm_s"] = bad
    with pytest.raises(ValidationError, match="manual_jog_speed_mm_s"):
        ProjectConfig.model_validate(data)


def test_the_jog_speed_key_sets_the_speed(project: ProjectConfig) -> None:
    fast = project.model_copy(
        update={"control": project.control.model_copy(update={"manual_jog_speed_mm_s": 8.0})}
    )
    core = _manual_core(fast)
    cid = fast.layers.lower.cylinders[2]
    core.request_jog(cid, 4.0)
    _update(core, machine_inputs(fast, t=1.0))
    i = fast.cylinder(cid).can_index
    assert core.attitude.references(1.25)[i] - _mid(fast)[i] == pytest.approx(2e-3)


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
        good = rig.plc._codec_by_name["PLC_Status"].encode(7, [1, 0, 1, 1, 0, 0, 0, 16.0])
        third.send(can.Message(arbitration_id=0x090, data=bytes([good[0] ^ 0x5A]) + good[1:],
                               is_extended_id=False))  # fmt: skip
        third.send(can.Message(arbitration_id=0x191, data=bytes(8), is_extended_id=False))
        _run(core, rig, clock, 0.05)
    after = core.snapshot()["link_rx"]
    assert after["crc_error"] - before["crc_error"] == 1
    assert after["unknown_id"] - before["unknown_id"] == 1
    assert after["received"] == sum(v for k, v in after.items() if k != "received")
