"""The operator-visible mode machine: legal paths, refusals, latching, restart."""

from __future__ import annotations

import itertools
import json
import random

import pytest
from structlog.testing import capture_logs

from ipc_app.service.interlocks import Cause, FaultLatch, Interlock
from ipc_app.service.modes import Mode, ModeMachine


def fresh(causes: list[Cause] | None = None) -> ModeMachine:
    active = causes if causes is not None else []
    ticks = itertools.count()
    m = ModeMachine(active_causes=lambda: list(active), clock=lambda: float(next(ticks)))
    assert m.boot_complete().accepted
    return m


def test_restart_starts_in_boot_then_idle_with_valves_closed() -> None:
    m = ModeMachine()
    assert m.mode is Mode.BOOT and not m.valves_enabled
    assert m.boot_complete().mode is Mode.IDLE
    assert not m.valves_enabled
    # a second boot_complete is refused: BOOT happens once per process
    assert not m.boot_complete().accepted


def test_nominal_cycle_and_valve_permission() -> None:
    m = fresh()
    seen = []
    for event in (
        lambda: m.request_adjust(-3.0, 2.0),
        m.plan_ready,
        m.motion_done,
        m.stop,
    ):
        out = event()
        assert out.accepted, out.message
        seen.append((m.mode, m.valves_enabled))
    assert seen == [
        (Mode.PLANNING, False),
        (Mode.ADJUSTING, True),
        (Mode.HOLDING, True),
        (Mode.IDLE, False),
    ]
    assert [t.event for t in m.history] == [
        "boot_complete",
        "request_adjust",
        "plan_ready",
        "motion_done",
        "stop",
    ]


def test_infeasible_plan_returns_to_idle_with_reasons() -> None:
    m = fresh()
    m.request_adjust(30.0, 0.0)
    out = m.plan_failed(["upper_1 beyond stroke"])
    assert out.accepted and m.mode is Mode.IDLE
    assert "upper_1 beyond stroke" in out.message
    assert m.target_deg is None


def test_new_adjustment_from_holding() -> None:
    m = fresh()
    m.request_adjust(1.0, 1.0)
    m.plan_ready()
    m.motion_done()
    assert m.request_adjust(2.0, 0.0).mode is Mode.PLANNING
    assert m.target_deg == (2.0, 0.0)


@pytest.mark.parametrize("mode_path", ["idle", "planning", "adjusting", "holding"])
def test_fault_latches_from_every_mode_and_closes_valves(mode_path: str) -> None:
    m = fresh()
    steps = {"idle": 0, "planning": 1, "adjusting": 2, "holding": 3}[mode_path]
    events = [lambda: m.request_adjust(1.0, 0.0), m.plan_ready, m.motion_done][:steps]
    for e in events:
        e()
    out = m.fault(Cause(Interlock.TWIST, "upper", 0.8, 0.5))
    assert out.accepted and m.mode is Mode.FAULT and not m.valves_enabled
    assert m.fault_interlocks == (Interlock.TWIST,)
    # latched: stop does not clear it, adjust is refused with the reason and the cure
    assert m.stop().mode is Mode.FAULT
    refused = m.request_adjust(0.0, 0.0)
    assert not refused.accepted
    assert "FAULT" in refused.message and Cause(Interlock.TWIST, "upper", 0.8, 0.5).text() in (
        refused.message
    )
    assert "reset" in refused.message


def test_reset_only_when_cause_gone() -> None:
    hb = Cause(Interlock.PLC_HEARTBEAT, detail="PLC status lost")
    causes = [hb]
    m = fresh(causes)
    m.fault(hb)
    out = m.reset()
    assert not out.accepted and m.mode is Mode.FAULT
    assert hb.text() in out.message
    causes.clear()
    out = m.reset()
    assert out.accepted and m.mode is Mode.IDLE
    assert m.fault_reasons == ()
    assert not m.reset().accepted  # nothing to reset


def test_second_fault_adds_reason() -> None:
    m = fresh()
    m.fault(Cause(Interlock.PRESSURE, "upper_2", 25.0, 24.0))
    m.fault(Cause(Interlock.STROKE_END, "upper_2", 3.0, 5.0))
    assert m.fault_interlocks == (Interlock.PRESSURE, Interlock.STROKE_END)
    assert [f.where for f in m.faults] == ["upper_2", "upper_2"]
    assert m.snapshot()["fault_reasons"] == list(m.fault_reasons)
    assert [f["interlock"] for f in m.snapshot()["faults"]] == ["pressure", "stroke end"]


def test_a_lasting_condition_is_one_entry_with_first_worst_and_count() -> None:
    """Latched by (interlock, where): a noisy value seen every cycle is one entry, logged
    once; the first and the worst value and the count are kept; the status stays small."""
    m = fresh()
    rng = random.Random(1)
    values = [24.5 + rng.random() for _ in range(2000)]
    with capture_logs() as logs:
        for v in values:
            m.fault(Cause(Interlock.PRESSURE, "main_leg_1", v, 24.0))
    (f,) = m.faults
    assert (f.interlock, f.where, f.count) == (Interlock.PRESSURE, "main_leg_1", 2000)
    assert f.first == values[0] and f.worst == max(values)
    assert len([e for e in logs if e["event"] in ("fault", "mode")]) == 1
    # a stroke end is worse the closer the rod gets to the end
    m.fault(Cause(Interlock.STROKE_END, "upper_1", 4.0, 5.0))
    m.fault(Cause(Interlock.STROKE_END, "upper_1", 1.0, 5.0))
    m.fault(Cause(Interlock.STROKE_END, "upper_1", 3.0, 5.0))
    assert m.faults[1].worst == 1.0 and m.faults[1].first == 4.0
    # bounded: every cylinder of every interlock
    for il in Interlock:
        for k in range(40):
            m.fault(Cause(il, f"c{k}", 1.0, 0.5))
    assert len(m.faults) == FaultLatch.MAX_ENTRIES
    assert m.snapshot()["faults_dropped"] > 0
    assert len(json.dumps(m.snapshot())) < 16_000


def test_suspend_and_resume_return_to_the_mode_suspended_from() -> None:
    for before in ("adjusting", "holding"):
        m = fresh()
        m.request_adjust(1.0, 0.0)
        m.plan_ready()
        if before == "holding":
            m.motion_done()
        was = m.mode
        assert m.suspend("rod positions stale").mode is Mode.SUSPENDED
        assert not m.valves_enabled
        assert not m.request_adjust(0.0, 0.0).accepted  # not while suspended
        assert m.resume("fresh again").mode is was
    m = fresh()
    assert not m.suspend("stale").accepted  # IDLE: nothing to suspend
    m.request_adjust(1.0, 0.0)
    m.plan_ready()
    m.suspend("stale")
    assert m.fault(Cause(Interlock.SENSOR_TIMEOUT, "upper_1", 60.0, 50.0)).mode is Mode.FAULT
    assert not m.resume("late").accepted
    m = fresh()
    m.request_adjust(1.0, 0.0)
    m.plan_ready()
    m.suspend("stale")
    assert m.stop().mode is Mode.IDLE


def test_estop_overrides_fault_and_needs_release_and_reset() -> None:
    m = fresh()
    m.request_adjust(1.0, 0.0)
    m.plan_ready()
    assert m.estop(True).mode is Mode.ESTOP and not m.valves_enabled
    assert m.fault(Cause(Interlock.PLANNER, detail="late")).mode is Mode.ESTOP  # noted
    out = m.reset()
    assert not out.accepted and "e-stop still pressed" in out.message
    m.estop(False)
    assert m.mode is Mode.ESTOP  # release alone does not re-arm
    assert m.reset().mode is Mode.IDLE


def test_transitions_and_refusals_are_logged_with_reason() -> None:
    with capture_logs() as logs:
        m = fresh()
        cause = Cause(Interlock.SENSOR, "upper_2")
        m.fault(cause)
        m.request_adjust(1.0, 1.0)
    modes = [e for e in logs if e["event"] == "mode"]
    assert modes[-1]["mode"] == "FAULT" and modes[-1]["reason"] == cause.text()
    refused = [e for e in logs if e["event"] == "refused"]
    assert refused and refused[0]["event_name"] == "request_adjust"
    assert refused[0]["log_level"] == "warning"


def test_on_transition_listener_sees_every_change() -> None:
    seen: list[tuple[str, str]] = []
    m = ModeMachine(on_transition=lambda tr: seen.append((tr.event, str(tr.to_mode))))
    m.boot_complete()
    m.request_adjust(1.0, 0.0)
    m.request_adjust(2.0, 0.0)  # refused: no transition, no call
    m.fault(Cause(Interlock.PLANNER, detail="timeout"))
    assert seen == [("boot_complete", "IDLE"), ("request_adjust", "PLANNING"), ("fault", "FAULT")]
