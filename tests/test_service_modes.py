"""The operator-visible mode machine: legal paths, refusals, latching, restart."""

from __future__ import annotations

import itertools
import json
import random
from pathlib import Path
from typing import Any

import pytest
from structlog.testing import capture_logs

from ipc_app.service.interlocks import Cause, FaultLatch, Interlock
from ipc_app.service.modes import (
    PACKML_STATES,
    RULES,
    UNIT_MODE_CHANGE,
    UNIT_MODES,
    Mode,
    ModeMachine,
    UnitMode,
    markdown_table,
    mermaid,
)


def fresh(causes: list[Cause] | None = None) -> ModeMachine:
    active = causes if causes is not None else []
    ticks = itertools.count()
    m = ModeMachine(active_causes=lambda: list(active), clock=lambda: float(next(ticks)))
    assert m.boot_complete().accepted
    return m


def test_restart_starts_in_boot_then_idle_with_valves_closed() -> None:
    m = ModeMachine()
    assert m.mode is Mode.STOPPED and not m.valves_enabled
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
        (Mode.STARTING, False),
        (Mode.EXECUTE, True),
        (Mode.COMPLETE, True),
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
    assert m.request_adjust(2.0, 0.0).mode is Mode.STARTING
    assert m.target_deg == (2.0, 0.0)


@pytest.mark.parametrize("mode_path", ["idle", "planning", "adjusting", "holding"])
def test_fault_latches_from_every_mode_and_closes_valves(mode_path: str) -> None:
    m = fresh()
    steps = {"idle": 0, "planning": 1, "adjusting": 2, "holding": 3}[mode_path]
    events = [lambda: m.request_adjust(1.0, 0.0), m.plan_ready, m.motion_done][:steps]
    for e in events:
        e()
    out = m.fault(Cause(Interlock.TWIST, "upper", 0.8, 0.5))
    assert out.accepted and m.mode is Mode.ABORTED and not m.valves_enabled
    assert m.fault_interlocks == (Interlock.TWIST,)
    # latched: stop does not clear it, adjust is refused with the reason and the cure
    assert m.stop().mode is Mode.ABORTED
    refused = m.request_adjust(0.0, 0.0)
    assert not refused.accepted
    assert "ABORTED" in refused.message and Cause(Interlock.TWIST, "upper", 0.8, 0.5).text() in (
        refused.message
    )
    assert "reset" in refused.message


def test_reset_only_when_cause_gone() -> None:
    hb = Cause(Interlock.PLC_HEARTBEAT, detail="PLC status lost")
    causes = [hb]
    m = fresh(causes)
    m.fault(hb)
    out = m.reset()
    assert not out.accepted and m.mode is Mode.ABORTED
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
    assert m.fault(Cause(Interlock.SENSOR_TIMEOUT, "upper_1", 60.0, 50.0)).mode is Mode.ABORTED
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
    assert m.estop(True).mode is Mode.ABORTED and not m.valves_enabled
    assert m.fault(Cause(Interlock.PLANNER, detail="late")).mode is Mode.ABORTED  # noted
    out = m.reset()
    assert not out.accepted and "e-stop still pressed" in out.message
    m.estop(False)
    assert m.mode is Mode.ABORTED  # release alone does not re-arm
    assert m.reset().mode is Mode.IDLE


def test_transitions_and_refusals_are_logged_with_reason() -> None:
    with capture_logs() as logs:
        m = fresh()
        cause = Cause(Interlock.SENSOR, "upper_2")
        m.fault(cause)
        m.request_adjust(1.0, 1.0)
    modes = [e for e in logs if e["event"] == "mode"]
    assert modes[-1]["mode"] == "ABORTED" and modes[-1]["reason"] == cause.text()
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
    assert seen == [("boot_complete", "IDLE"), ("request_adjust", "STARTING"), ("fault", "ABORTED")]


# --------------------------------------------------------------------------- PackML table

#: How each event is asked for.
_EVENTS: dict[str, Any] = {
    "boot_complete": lambda m: m.boot_complete(),
    "request_adjust": lambda m: m.request_adjust(1.0, 0.0),
    "plan_ready": lambda m: m.plan_ready(),
    "plan_failed": lambda m: m.plan_failed(["infeasible"]),
    "jog": lambda m: m.jog("main_leg_1 +1 mm"),
    "walk": lambda m: m.walk("3 step(s) of 2.000 m"),
    "place": lambda m: m.place("ring 5"),
    "release": lambda m: m.release("ring 5"),
    "home": lambda m: m.start_motion("home", "each attitude layer to mid-stroke, level"),
    "motion_done": lambda m: m.motion_done(),
    "hold": lambda m: m.hold(),
    "unhold": lambda m: m.unhold(),
    "suspend": lambda m: m.suspend("stale"),
    "resume": lambda m: m.resume("fresh"),
    "stop": lambda m: m.stop(),
    "fault": lambda m: m.fault(Cause(Interlock.PLANNER, detail="test")),
    "estop": lambda m: m.estop(True),
    "clear": lambda m: m.clear(),
    "reset": lambda m: m.reset(),
}

#: A path of events from a booted IDLE (PRODUCTION) to each state.
_PATHS: dict[Mode, tuple[str, ...]] = {
    Mode.STOPPED: ("fault", "clear"),
    Mode.IDLE: (),
    Mode.STARTING: ("request_adjust",),
    Mode.EXECUTE: ("request_adjust", "plan_ready"),
    Mode.COMPLETE: ("request_adjust", "plan_ready", "motion_done"),
    Mode.HELD: ("request_adjust", "plan_ready", "hold"),
    Mode.SUSPENDED: ("request_adjust", "plan_ready", "suspend"),
    Mode.ABORTED: ("fault",),
}


def _in(mode: Mode, unit: UnitMode) -> ModeMachine:
    m = fresh()
    for e in _PATHS[mode]:
        assert _EVENTS[e](m).accepted, (mode, e)
    assert m.mode is mode
    if m.mode in UNIT_MODE_CHANGE:
        assert m.set_unit_mode(unit).accepted
    else:
        m._s.unit = unit  # the unit mode it was started in (changes only at rest)
    return m


def test_every_event_has_a_rule_and_a_call() -> None:
    assert set(_EVENTS) == set(RULES) and set(_PATHS) == set(Mode)


@pytest.mark.parametrize("unit", list(UnitMode))
@pytest.mark.parametrize("mode", list(Mode))
@pytest.mark.parametrize("event", list(RULES))
def test_each_event_in_each_state_and_unit_mode(event: str, mode: Mode, unit: UnitMode) -> None:
    """Allowed by its rule: the transition to the rule's target; otherwise refused with
    the mode unchanged (``stop`` where there is nothing to stop, and a fault or e-stop in
    ABORTED, are accepted without a change: noted)."""
    rule = RULES[event]
    m = _in(mode, unit)
    before = len(m.history)
    out = _EVENTS[event](m)
    allowed = mode in rule.sources and unit in rule.units
    if event == "boot_complete":
        allowed = False  # once per process: these machines are booted
    if event == "reset" and mode is Mode.ABORTED:
        allowed = True  # clears first
    if allowed:
        want = rule.target if rule.target is not None else Mode.EXECUTE  # suspended from
        assert out.accepted and m.mode is want, (out.message, m.mode)
        assert m.history[-1].event == event and len(m.history) > before
    else:
        assert m.mode is mode and len(m.history) == before, out.message
        if event in ("stop", "fault", "estop"):
            assert out.accepted  # nothing to stop / already ABORTED: noted, no change
        else:
            assert not out.accepted and out.message
            if mode in rule.sources and event != "boot_complete":  # by the unit mode
                assert f"unit mode {unit}" in out.message


def test_boot_complete_only_once_and_reset_only_after_it() -> None:
    m = ModeMachine()
    out = m.reset()
    assert not out.accepted and "start-up not complete" in out.message
    assert m.boot_complete().accepted and not m.boot_complete().accepted


def test_the_unit_mode_changes_only_at_rest() -> None:
    for mode in Mode:
        m = _in(mode, UnitMode.PRODUCTION)
        assert m.set_unit_mode(UnitMode.MANUAL).accepted is (mode in UNIT_MODE_CHANGE)
        assert m.unit_mode is (UnitMode.MANUAL if mode in UNIT_MODE_CHANGE else UnitMode.PRODUCTION)


def test_a_latched_fault_is_aborted_until_clear_and_reset() -> None:
    causes: list[Cause] = []
    m = fresh(causes)
    hb = Cause(Interlock.PLC_HEARTBEAT, detail="lost")
    m.fault(hb)
    causes.append(hb)
    assert not m.clear().accepted and m.mode is Mode.ABORTED
    causes.clear()
    assert m.clear().mode is Mode.STOPPED and not m.valves_enabled
    assert not m.request_adjust(1.0, 0.0).accepted  # STOPPED: reset first
    assert m.reset().mode is Mode.IDLE
    assert [t.event for t in m.history][-3:] == ["fault", "clear", "reset"]


DOC = Path(__file__).resolve().parents[1] / "docs" / "modes.md"


@pytest.mark.parametrize(
    ("name", "render"), [("transitions table", markdown_table), ("state diagram", mermaid)]
)
def test_docs_modes_is_the_rendering_of_the_rules(name: str, render: Any) -> None:
    text = DOC.read_text(encoding="utf-8")
    begin = f"<!-- {name}: generated by ipc_app.service.modes.{render.__name__}() -->\n"
    end = f"<!-- end of {name} -->"
    assert begin in text and end in text, name
    assert text.split(begin, 1)[1].split(end, 1)[0] == render(), (
        f"docs/modes.md's {name} differs from RULES: paste the output of "
        f"ipc_app.service.modes.{render.__name__}() between the markers"
    )


def test_packml_numbers_cover_every_state_and_the_dbc_tables() -> None:
    from plc_bridge import load_catalog

    assert {str(m) for m in Mode} <= set(PACKML_STATES)
    assert sorted(PACKML_STATES.values()) == list(range(1, 18))
    ctl = load_catalog().by_name("IPC_Control")
    assert ctl.signal("PackMLState").choices == {0: "UNDEFINED"} | {
        v: k for k, v in PACKML_STATES.items()
    }
    assert ctl.signal("UnitMode").choices == {0: "UNDEFINED"} | {
        v: str(k) for k, v in UNIT_MODES.items()
    }


def test_a_reset_after_an_abort_during_start_up_leaves_the_start_up_to_finish() -> None:
    m = ModeMachine()
    m.fault(Cause(Interlock.PLC_HEARTBEAT, detail="PLC status lost"))
    out = m.reset()
    assert out.accepted and m.mode is Mode.STOPPED and "start-up" in out.message
    assert m.boot_complete().mode is Mode.IDLE
