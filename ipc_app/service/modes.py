"""The operator-visible state machine of the IPC service, in the PackML frame.

The service's modes are states of the PackML state model (ISA-TR88.00.02); the
transitions are data (:data:`RULES`: the event, the states it is allowed in, the state
it leads to, the PackML acting state it passes through, the unit modes it is allowed
in, the ``wara ctl`` command that asks for it). docs/modes.md shows the table and the
diagram rendered from :data:`RULES` (a test keeps them equal).

The service rests in eight states: STOPPED (start-up, or cleared after an abort), IDLE,
STARTING (the planner works), EXECUTE (the motion), COMPLETE (the target reached and
held), HELD (an operator hold), SUSPENDED (a short loss of the link), ABORTED (a latched
fault or the e-stop). The other PackML states (Resetting, Completing, Holding,
Unholding, Suspending, Unsuspending, Stopping, Aborting, Clearing) are acting states the
service passes through within the cycle of the event (the ``via`` of its rule).

Valves may be driven only in EXECUTE and COMPLETE (:attr:`ModeMachine.valves_enabled`);
every other state is a controlled stop: valves closed, the load held by the closed
valves. A latched fault is ABORTED until ``clear`` (every cause gone, e-stop released:
STOPPED) and ``reset`` (IDLE); ``reset`` from ABORTED does both. Nothing is persisted: a
new :class:`ModeMachine` (a restart of the service) is always in STOPPED and
:meth:`~ModeMachine.boot_complete` takes it to IDLE once, with the valves closed.

Unit modes (:class:`UnitMode`): PRODUCTION (adjustments, from the IPC and the HMI),
MAINTENANCE (no motion: for work on the machine, the load held by closed valves),
MANUAL (jog of one cylinder at ``control.manual_jog_speed_mm_s``, interlocks on). The
unit mode changes only in STOPPED, IDLE or ABORTED.

Each event method returns an :class:`Outcome`; a refused request has
``accepted=False`` and a message saying why and what would make it possible. Nothing
raises, so the loop thread can call the events it owns without a try block. Every
transition and every refusal is logged with structlog (``event="mode"``).

Planner failures: an *infeasible target* is the operator's problem, ``plan_failed``
returns to IDLE with the planner's reasons; a *planner crash or timeout* is an interlock,
the service calls ``fault(Cause(Interlock.PLANNER, ...))``.

Faults are :class:`~ipc_app.service.interlocks.Cause` objects, latched by interlock and
place in a :class:`~ipc_app.service.interlocks.FaultLatch` (first and worst value, count):
a lasting condition is one entry, and only a new entry is logged.

The machine is thread-safe (one short re-entrant lock): the control channel thread calls the
operator requests while the loop thread calls the rest.

Over 500 lines because the rules, the machine that follows them and their rendering
for the docs are one unit: a rule changed here changes the docs' table and diagram.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

import structlog

from ipc_app.service.interlocks import Cause, FaultLatch, Interlock, Latched

log = structlog.get_logger("wara.service.modes")


class Mode(StrEnum):
    """The PackML states the service rests in."""

    STOPPED = "STOPPED"
    IDLE = "IDLE"
    STARTING = "STARTING"
    EXECUTE = "EXECUTE"
    COMPLETE = "COMPLETE"
    HELD = "HELD"
    SUSPENDED = "SUSPENDED"
    ABORTED = "ABORTED"


class UnitMode(StrEnum):
    """The PackML unit modes of the machine."""

    PRODUCTION = "PRODUCTION"
    MAINTENANCE = "MAINTENANCE"
    MANUAL = "MANUAL"


#: The PackML state numbers (ISA-TR88.00.02 ``StateCurrent``) of all seventeen states:
#: the ``mode_code`` of the run record and the DBC's ``PackMLState`` value table.
PACKML_STATES: dict[str, int] = {
    "CLEARING": 1,
    "STOPPED": 2,
    "STARTING": 3,
    "IDLE": 4,
    "SUSPENDED": 5,
    "EXECUTE": 6,
    "STOPPING": 7,
    "ABORTING": 8,
    "ABORTED": 9,
    "HOLDING": 10,
    "HELD": 11,
    "UNHOLDING": 12,
    "SUSPENDING": 13,
    "UNSUSPENDING": 14,
    "RESETTING": 15,
    "COMPLETING": 16,
    "COMPLETE": 17,
}
#: The PackML unit mode numbers (``UnitModeCurrent``): the DBC's ``UnitMode`` value table.
UNIT_MODES: dict[UnitMode, int] = {
    UnitMode.PRODUCTION: 1,
    UnitMode.MAINTENANCE: 2,
    UnitMode.MANUAL: 3,
}

#: Modes in which the control loop may drive the valves.
VALVE_MODES = frozenset({Mode.EXECUTE, Mode.COMPLETE})
#: Modes in which an axis is moving, being planned or stopped mid-way; ``stop`` brings
#: them to IDLE.
ACTIVE_MODES = frozenset({Mode.STARTING, Mode.EXECUTE, Mode.COMPLETE, Mode.HELD, Mode.SUSPENDED})
#: Modes a short loss of the link suspends (and :meth:`ModeMachine.resume` returns to).
SUSPENDABLE_MODES = frozenset({Mode.EXECUTE, Mode.COMPLETE})
#: Modes in which the unit mode may change.
UNIT_MODE_CHANGE = frozenset({Mode.STOPPED, Mode.IDLE, Mode.ABORTED})

_ALL_UNITS = frozenset(UnitMode)
_MOVING_UNITS = frozenset({UnitMode.PRODUCTION, UnitMode.MANUAL})


@dataclass(frozen=True)
class Rule:
    """One transition: ``event`` is allowed in ``sources`` (and in ``units``) and leads
    to ``target`` (None: back to the state suspended or held from) through the PackML
    acting state ``via``; ``command`` is the ``wara ctl`` command that asks for it (None:
    the service's own event)."""

    event: str
    sources: frozenset[Mode]
    target: Mode | None
    via: str | None
    units: frozenset[UnitMode]
    command: str | None
    what: str


def _rule(
    event: str,
    sources: set[Mode] | frozenset[Mode],
    target: Mode | None,
    via: str | None,
    what: str,
    *,
    units: frozenset[UnitMode] = _ALL_UNITS,
    command: str | None = None,
) -> Rule:
    return Rule(event, frozenset(sources), target, via, units, command, what)


_ANY_BUT_ABORTED = frozenset(Mode) - {Mode.ABORTED}

#: Every transition of the service, by event.
RULES: dict[str, Rule] = {
    r.event: r
    for r in (
        _rule("boot_complete", {Mode.STOPPED}, Mode.IDLE, "RESETTING",
              "start-up complete: every input fresh (once per process)"),
        _rule("request_adjust", {Mode.IDLE, Mode.COMPLETE}, Mode.STARTING, None,
              "an adjustment to a target attitude (PackML Start): the planner works",
              units=frozenset({UnitMode.PRODUCTION}), command="adjust"),
        _rule("plan_ready", {Mode.STARTING}, Mode.EXECUTE, None,
              "a feasible plan: the valves open"),
        _rule("plan_failed", {Mode.STARTING}, Mode.IDLE, None,
              "the target is infeasible (the planner's reasons)"),
        _rule("walk", {Mode.IDLE, Mode.COMPLETE}, Mode.EXECUTE, "STARTING",
              "N steps of the walk, planned and checked before anything moves",
              units=frozenset({UnitMode.PRODUCTION}), command="walk"),
        _rule("place", {Mode.IDLE, Mode.COMPLETE}, Mode.EXECUTE, "STARTING",
              "the part to its planned target pose (attitude and height, then yaw, "
              "lateral and gap), checked before anything moves",
              units=frozenset({UnitMode.PRODUCTION}), command="place"),
        _rule("release", {Mode.IDLE, Mode.COMPLETE}, Mode.EXECUTE, "STARTING",
              "the ring cycle's release: the upper platform lowers off the fixed part "
              "until its pressures are the empty platform's, then clear of it",
              units=frozenset({UnitMode.PRODUCTION})),
        _rule("home", {Mode.IDLE, Mode.COMPLETE}, Mode.EXECUTE, "STARTING",
              "each attitude layer to its reference stroke (mid-stroke), level, then held",
              units=_MOVING_UNITS, command="home"),
        _rule("jog", {Mode.IDLE, Mode.COMPLETE}, Mode.EXECUTE, "STARTING",
              "one cylinder at the jog speed, the others held (interlocks on)",
              units=frozenset({UnitMode.MANUAL}), command="jog"),
        _rule("motion_done", {Mode.EXECUTE}, Mode.COMPLETE, "COMPLETING",
              "the trajectory ended: the pose is held"),
        _rule("hold", {Mode.EXECUTE}, Mode.HELD, "HOLDING",
              "operator hold: valves closed, the trajectory clock stopped",
              units=_MOVING_UNITS, command="hold"),
        _rule("unhold", {Mode.HELD}, Mode.EXECUTE, "UNHOLDING",
              "the motion goes on once the rods are where it stopped",
              units=_MOVING_UNITS, command="unhold"),
        _rule("suspend", SUSPENDABLE_MODES, Mode.SUSPENDED, "SUSPENDING",
              "a short loss of the link: valves closed, the trajectory clock stopped"),
        _rule("resume", {Mode.SUSPENDED}, None, "UNSUSPENDING",
              "frames fresh again and the rods where they stopped"),
        _rule("stop", ACTIVE_MODES, Mode.IDLE, "STOPPING",
              "controlled stop: valves closed, load held", command="stop"),
        _rule("fault", _ANY_BUT_ABORTED, Mode.ABORTED, "ABORTING",
              "an interlock tripped: latched"),
        _rule("estop", _ANY_BUT_ABORTED, Mode.ABORTED, "ABORTING",
              "e-stop pressed: latched even after release"),
        _rule("clear", {Mode.ABORTED}, Mode.STOPPED, "CLEARING",
              "every cause gone and the e-stop released; the PLC's fault cleared",
              command="clear"),
        _rule("reset", {Mode.STOPPED}, Mode.IDLE, "RESETTING",
              "after start-up; from ABORTED, `reset` clears first", command="reset"),
    )
}  # fmt: skip


@dataclass(frozen=True)
class Transition:
    """One logged change of mode."""

    t: float
    event: str
    from_mode: Mode
    to_mode: Mode
    reason: str


@dataclass(frozen=True)
class Outcome:
    """What an event did: ``accepted`` and the mode after it, or why it was refused."""

    accepted: bool
    mode: Mode
    message: str
    transition: Transition | None = None

    def to_dict(self) -> dict[str, Any]:
        return {"accepted": self.accepted, "mode": str(self.mode), "message": self.message}


@dataclass
class _State:
    mode: Mode = Mode.STOPPED
    unit: UnitMode = UnitMode.PRODUCTION
    since: float = 0.0
    faults: FaultLatch = field(default_factory=FaultLatch)
    estop_active: bool = False
    booted: bool = False
    target_deg: tuple[float, float] | None = None
    resume_to: Mode | None = None
    last_message: str = "booting"


class ModeMachine:
    """The operator-visible modes; see the module docstring and :data:`RULES`.

    ``active_causes`` is asked by :meth:`clear` for the interlock conditions that are
    still present (:class:`Cause` objects); a clear succeeds only when it returns
    nothing and the e-stop is released. ``clock`` is for the transition times.
    ``on_transition`` is called with each :class:`Transition` (e.g. to write it to the
    run record or to systemd's STATUS=), ``on_fault`` with each newly latched cause; both
    run in the caller's thread under the machine's re-entrant lock, so they must be
    quick and must not block.
    """

    def __init__(
        self,
        *,
        active_causes: Callable[[], Sequence[Cause]] = lambda: (),
        clock: Callable[[], float] = time.monotonic,
        on_transition: Callable[[Transition], None] | None = None,
        on_fault: Callable[[Latched], None] | None = None,
        history: int = 100,
    ) -> None:
        self._active_causes = active_causes
        self._clock = clock
        self._on_transition = on_transition
        self._on_fault = on_fault
        self._lock = threading.RLock()
        self._s = _State(since=clock())
        self._history: deque[Transition] = deque(maxlen=history)
        log.info("mode", mode=str(Mode.STOPPED), event_name="start", reason="service start")

    # ------------------------------------------------------------------ queries
    @property
    def mode(self) -> Mode:
        return self._s.mode

    @property
    def booted(self) -> bool:
        """The start-up is complete (:meth:`boot_complete` accepted)."""
        return self._s.booted

    @property
    def unit_mode(self) -> UnitMode:
        return self._s.unit

    @property
    def valves_enabled(self) -> bool:
        """True only in EXECUTE and COMPLETE; in every other mode the valves stay closed."""
        return self._s.mode in VALVE_MODES

    @property
    def fault_reasons(self) -> tuple[str, ...]:
        """The latched causes as text (for people; code uses :attr:`faults`)."""
        with self._lock:
            return tuple(e.text() for e in self._s.faults.entries())

    @property
    def faults(self) -> tuple[Latched, ...]:
        """The latched causes, in the order they were first latched."""
        with self._lock:
            return self._s.faults.entries()

    @property
    def fault_interlocks(self) -> tuple[Interlock, ...]:
        with self._lock:
            return self._s.faults.interlocks()

    @property
    def target_deg(self) -> tuple[float, float] | None:
        """(roll, pitch) of the adjustment being planned or run, deg."""
        return self._s.target_deg

    @property
    def history(self) -> tuple[Transition, ...]:
        return tuple(self._history)

    def snapshot(self) -> dict[str, Any]:
        """A JSON-ready picture for ``wara ctl status``."""
        with self._lock:
            s = self._s
            return {
                "mode": str(s.mode),
                "unit_mode": str(s.unit),
                "since_s": s.since,
                "valves_enabled": s.mode in VALVE_MODES,
                "fault_reasons": [e.text() for e in s.faults.entries()],
                "faults": [e.to_dict() for e in s.faults.entries()],
                "faults_dropped": s.faults.dropped,
                "estop_active": s.estop_active,
                "target_deg": list(s.target_deg) if s.target_deg else None,
                "message": s.last_message,
            }

    # ------------------------------------------------------------------ events
    def boot_complete(self) -> Outcome:
        """STOPPED -> IDLE once the service is wired (valves closed); once per process."""
        with self._lock:
            if self._s.booted:
                return self._refuse("boot_complete", "boot_complete refused: already booted")
            out = self._go_locked("boot_complete", "start-up complete")
            if out.accepted:
                self._s.booted = True
            return out

    def request_adjust(self, roll_deg: float, pitch_deg: float) -> Outcome:
        """IDLE or COMPLETE -> STARTING for target (roll, pitch), in PRODUCTION. A refused
        request changes nothing."""
        with self._lock:
            out = self._go_locked(
                "request_adjust",
                f"adjust to roll {roll_deg:+.4f} deg, pitch {pitch_deg:+.4f} deg",
            )
            if out.accepted:
                self._s.target_deg = (roll_deg, pitch_deg)
            return out

    def plan_ready(self) -> Outcome:
        """STARTING -> EXECUTE: a feasible plan arrived; the valves may open."""
        return self._go("plan_ready", "feasible plan")

    def plan_failed(self, reasons: Sequence[str]) -> Outcome:
        """STARTING -> IDLE: the target is infeasible; ``reasons`` are the planner's."""
        why = "target refused: " + ("; ".join(reasons) if reasons else "no reason given")
        return self._go_clearing_target("plan_failed", why)

    def _go_clearing_target(self, event: str, reason: str) -> Outcome:
        """Rule ``event``; once accepted the status shows no attitude target (a motion
        that is not one, or a refused one)."""
        with self._lock:
            out = self._go_locked(event, reason)
            if out.accepted:
                self._s.target_deg = None
            return out

    def start_motion(self, event: str, what: str) -> Outcome:
        """IDLE or COMPLETE -> EXECUTE for the motion of rule ``event`` (``jog``,
        ``walk``, ``place``, ``release``, ``home``; ``what``: what it does), in the unit
        modes of its rule."""
        return self._go_clearing_target(event, f"{event} {what}")

    def jog(self, what: str) -> Outcome:
        """:meth:`start_motion` of a jog (``what``: which cylinder, how far), in MANUAL."""
        return self.start_motion("jog", what)

    def walk(self, what: str) -> Outcome:
        """:meth:`start_motion` of a walk (``what``: the steps)."""
        return self.start_motion("walk", what)

    def place(self, what: str) -> Outcome:
        """:meth:`start_motion` of a placement move (``what``: the ring and its target)."""
        return self.start_motion("place", what)

    def release(self, what: str) -> Outcome:
        """:meth:`start_motion` of the part's release (``what``: the ring)."""
        return self.start_motion("release", what)

    def motion_done(self) -> Outcome:
        """EXECUTE -> COMPLETE: the trajectory ended and the target is reached."""
        return self._go("motion_done", "target reached")

    def hold(self, reason: str = "operator hold") -> Outcome:
        """EXECUTE -> HELD: valves closed, the motion stopped where it is."""
        return self._go("hold", reason)

    def unhold(self, reason: str = "operator unhold") -> Outcome:
        """HELD -> EXECUTE (the core checks the rods first)."""
        return self._go("unhold", reason)

    def suspend(self, reason: str) -> Outcome:
        """EXECUTE/COMPLETE -> SUSPENDED: the link dropped out; valves closed, held."""
        with self._lock:
            was = self._s.mode
            out = self._go_locked("suspend", reason)
            if out.accepted:
                self._s.resume_to = was
            return out

    def resume(self, reason: str) -> Outcome:
        """SUSPENDED -> the mode it was suspended from."""
        with self._lock:
            to = self._s.resume_to or Mode.COMPLETE
            out = self._go_locked("resume", reason, to=to)
            if out.accepted:
                self._s.resume_to = None
            return out

    def stop(self, reason: str = "operator stop") -> Outcome:
        """Controlled stop: STARTING/EXECUTE/COMPLETE/HELD/SUSPENDED -> IDLE, valves closed.

        Always accepted: in STOPPED, IDLE or ABORTED the valves are already closed and the
        mode does not change (a stop never clears a fault).
        """
        with self._lock:
            if self._s.mode in ACTIVE_MODES:
                out = self._go_locked("stop", reason)
                self._s.target_deg = None
                return out
            msg = f"stop: already stopped in {self._s.mode}"
            return Outcome(True, self._s.mode, msg)

    def fault(self, cause: Cause) -> Outcome:
        """Any mode -> ABORTED, latched by (interlock, where). In ABORTED a new cause is
        added and logged once; a known one only updates its worst value and count
        (nothing logged)."""
        with self._lock:
            s = self._s
            new = s.faults.add(cause, self._clock())
            if new and self._on_fault is not None:
                self._on_fault(s.faults.entries()[-1])
            if s.mode == Mode.ABORTED:
                if new:
                    log.warning(
                        "fault",
                        mode=str(s.mode),
                        interlock=str(cause.interlock),
                        where=cause.where,
                        reason=cause.text(),
                        latched=True,
                    )
                return Outcome(True, s.mode, f"{s.mode} kept; fault noted: {cause.text()}")
            return self._transition("fault", Mode.ABORTED, cause.text())

    def estop(self, active: bool) -> Outcome:
        """E-stop input. Pressed: any mode -> ABORTED. Released: stays ABORTED until reset."""
        with self._lock:
            s = self._s
            if active == s.estop_active and (not active or s.mode == Mode.ABORTED):
                return Outcome(True, s.mode, f"e-stop {'still' if active else 'not'} active")
            s.estop_active = active
            if active:
                if s.mode == Mode.ABORTED:
                    s.last_message = "e-stop pressed"
                    return Outcome(True, s.mode, s.last_message)
                return self._transition("estop", Mode.ABORTED, "e-stop pressed")
            log.info("estop_released", mode=str(s.mode))
            s.last_message = "e-stop released; reset to continue"
            return Outcome(True, s.mode, s.last_message)

    def clear(self) -> Outcome:
        """ABORTED -> STOPPED, only if the e-stop is released and no cause is active."""
        with self._lock:
            s = self._s
            if s.mode != Mode.ABORTED:
                return self._refuse("clear", f"nothing to clear: mode is {s.mode}")
            blocking = [c.text() for c in self._active_causes()]
            if s.estop_active:
                blocking.insert(0, "e-stop still pressed")
            if blocking:
                return self._refuse(
                    "clear", "clear refused, cause still present: " + "; ".join(blocking)
                )
            cleared = "; ".join(e.text() for e in s.faults.entries()) or "e-stop"
            out = self._transition("clear", Mode.STOPPED, f"cleared: {cleared}")
            s.faults.clear()
            s.target_deg = None
            s.resume_to = None
            return out

    def reset(self) -> Outcome:
        """STOPPED -> IDLE (after start-up); from ABORTED :meth:`clear` first (both
        refused while a cause is present)."""
        with self._lock:
            s = self._s
            if s.mode == Mode.ABORTED:
                out = self.clear()
                if not out.accepted:
                    return Outcome(False, s.mode, out.message.replace("clear", "reset", 1))
                if not s.booted:  # aborted during start-up: it completes by itself
                    s.last_message = "cleared; IDLE once every input is fresh (start-up)"
                    return Outcome(True, s.mode, s.last_message)
            if s.mode != Mode.STOPPED or not s.booted:
                why = "start-up not complete" if s.mode == Mode.STOPPED else f"mode is {s.mode}"
                return self._refuse("reset", f"nothing to reset: {why}")
            return self._go_locked("reset", "reset")

    def set_unit_mode(self, unit: UnitMode) -> Outcome:
        """Change the unit mode; only in STOPPED, IDLE or ABORTED."""
        with self._lock:
            s = self._s
            if s.mode not in UNIT_MODE_CHANGE:
                names = "/".join(sorted(str(m) for m in UNIT_MODE_CHANGE))
                return self._refuse("unit_mode", f"unit mode refused in {s.mode}: only in {names}")
            was, s.unit = s.unit, unit
            s.last_message = f"unit mode {unit}"
            log.info("unit_mode", mode=str(s.mode), unit_mode=str(unit), was=str(was))
            return Outcome(True, s.mode, s.last_message)

    # ------------------------------------------------------------------ internals
    def allowed(self, event: str) -> bool:
        """Whether ``event`` is allowed now (mode and unit mode)."""
        r = RULES[event]
        return self._s.mode in r.sources and self._s.unit in r.units

    def _go(self, event: str, reason: str) -> Outcome:
        with self._lock:
            return self._go_locked(event, reason)

    def _go_locked(self, event: str, reason: str, to: Mode | None = None) -> Outcome:
        r = RULES[event]
        s = self._s
        if s.mode not in r.sources:
            names = "/".join(sorted(str(m) for m in r.sources))
            hint = ""
            if s.mode == Mode.ABORTED:
                why = "; ".join(e.text() for e in s.faults.entries()) or "e-stop"
                hint = f" (latched: {why}; `wara ctl reset` once the cause is gone)"
            return self._refuse(
                event, f"{event} refused in {s.mode}: only allowed in {names}{hint}"
            )
        if s.unit not in r.units:
            names = "/".join(sorted(str(u) for u in r.units))
            return self._refuse(
                event,
                f"{event} refused in unit mode {s.unit}: only in {names} (`wara ctl unit-mode`)",
            )
        target = to or r.target or s.mode
        return self._transition(event, target, reason)

    def _transition(self, event: str, to: Mode, reason: str) -> Outcome:
        s = self._s
        now = self._clock()
        tr = Transition(now, event, s.mode, to, reason)
        self._history.append(tr)
        s.mode, s.since, s.last_message = to, now, reason
        log.info("mode", from_mode=str(tr.from_mode), mode=str(to), event_name=event, reason=reason)
        if self._on_transition is not None:
            self._on_transition(tr)
        return Outcome(True, to, reason, tr)

    def _refuse(self, event: str, message: str) -> Outcome:
        log.warning("refused", mode=str(self._s.mode), event_name=event, reason=message)
        return Outcome(False, self._s.mode, message)


# --------------------------------------------------------------------------- docs


def markdown_table() -> str:
    """The transition table of docs/modes.md, rendered from :data:`RULES`."""
    rows = [
        "| event | `wara ctl` | from | to | through | unit modes | what |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in RULES.values():
        src = ", ".join(str(m) for m in Mode if m in r.sources)
        to = str(r.target) if r.target is not None else "the state it came from"
        units = ", ".join(str(u) for u in UnitMode if u in r.units)
        cmd = f"`{r.command}`" if r.command else "-"
        rows.append(f"| `{r.event}` | {cmd} | {src} | {to} | {r.via or '-'} | {units} | {r.what} |")
    return "\n".join(rows) + "\n"


def mermaid() -> str:
    """The state diagram of docs/modes.md (mermaid), rendered from :data:`RULES`: one
    arrow per pair of states, labelled with its events (and their acting state)."""
    edges: dict[tuple[Mode, Mode], list[str]] = {}
    for r in RULES.values():
        label = r.event + (f" ({r.via})" if r.via else "")
        targets = sorted(SUSPENDABLE_MODES) if r.target is None else [r.target]
        for m in Mode:
            for to in targets:
                if m in r.sources and m != to:
                    edges.setdefault((m, to), []).append(label)
    lines = ["```mermaid", "stateDiagram-v2", "    [*] --> STOPPED"]
    lines += [f"    {a} --> {b}: {' / '.join(ls)}" for (a, b), ls in edges.items()]
    lines.append("```")
    return "\n".join(lines) + "\n"
