"""The operator-visible state machine of the IPC service.

::

    BOOT --boot_complete--> IDLE --request_adjust--> PLANNING --plan_ready--> ADJUSTING
      ADJUSTING --motion_done--> HOLDING --stop / release--> IDLE
      PLANNING --plan_failed (target infeasible)--> IDLE
      HOLDING --request_adjust--> PLANNING           (next adjustment from the held pose)
      ADJUSTING / HOLDING --suspend(reason)--> SUSPENDED --resume--> back where it was
      any --fault(cause)--> FAULT                    (latched; not from ESTOP)
      any --estop(True)--> ESTOP                     (latched even after estop(False))
      FAULT / ESTOP --reset()--> IDLE                (only when every cause is gone)

Valves may be driven only in ADJUSTING and HOLDING (:attr:`ModeMachine.valves_enabled`);
every other mode is a controlled stop: valves closed, the load held by the closed valves.
SUSPENDED is the short stop of a link that dropped out (PackML's Suspended): the core
resumes the motion by itself when the frames are back and its checks pass, or faults.
Nothing is persisted: a new :class:`ModeMachine` (a restart of the service) is always in
BOOT, and :meth:`~ModeMachine.boot_complete` takes it to IDLE with the valves closed.

Each event method returns an :class:`Outcome`; a refused request (``adjust`` while FAULT,
``reset`` while the heartbeat is still lost) has ``accepted=False`` and a message saying
why and what would make it possible. Nothing raises, so the loop thread can call the
events it owns (``plan_ready``, ``motion_done``, ``fault``) without a try block. Every
transition and every refusal is logged with structlog (``event="mode"``).

Planner failures: an *infeasible target* is the operator's problem, ``plan_failed``
returns to IDLE with the planner's reasons; a *planner crash or timeout* is an interlock,
the service calls ``fault(Cause(Interlock.PLANNER, ...))``.

Faults are :class:`~ipc_app.service.interlocks.Cause` objects, latched by interlock and
place in a :class:`~ipc_app.service.interlocks.FaultLatch` (first and worst value, count):
a lasting condition is one entry, and only a new entry is logged.

The machine is thread-safe (one short re-entrant lock): the control channel thread calls the
operator requests while the loop thread calls the rest.
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
    BOOT = "BOOT"
    IDLE = "IDLE"
    PLANNING = "PLANNING"
    ADJUSTING = "ADJUSTING"
    HOLDING = "HOLDING"
    SUSPENDED = "SUSPENDED"
    FAULT = "FAULT"
    ESTOP = "ESTOP"


#: Modes in which the control loop may drive the valves.
VALVE_MODES = frozenset({Mode.ADJUSTING, Mode.HOLDING})
#: Modes in which an axis is moving or being planned; ``stop`` brings them to IDLE.
ACTIVE_MODES = frozenset({Mode.PLANNING, Mode.ADJUSTING, Mode.HOLDING, Mode.SUSPENDED})
#: Modes a short loss of the link suspends (and :meth:`ModeMachine.resume` returns to).
SUSPENDABLE_MODES = frozenset({Mode.ADJUSTING, Mode.HOLDING})


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
    mode: Mode = Mode.BOOT
    since: float = 0.0
    faults: FaultLatch = field(default_factory=FaultLatch)
    estop_active: bool = False
    target_deg: tuple[float, float] | None = None
    resume_to: Mode | None = None
    last_message: str = "booting"


class ModeMachine:
    """The operator-visible modes; see the module docstring for the transitions.

    ``active_causes`` is asked by :meth:`reset` for the interlock conditions that are
    still present (:class:`Cause` objects); a reset succeeds only when it
    returns nothing and the e-stop is released. ``clock`` is for the transition times.
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
        log.info("mode", mode=str(Mode.BOOT), event_name="start", reason="service start")

    # ------------------------------------------------------------------ queries
    @property
    def mode(self) -> Mode:
        return self._s.mode

    @property
    def valves_enabled(self) -> bool:
        """True only in ADJUSTING and HOLDING; in every other mode the valves stay closed."""
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
        """BOOT -> IDLE once the service is wired (valves closed)."""
        return self._go("boot_complete", {Mode.BOOT}, Mode.IDLE, "start-up complete")

    def request_adjust(self, roll_deg: float, pitch_deg: float) -> Outcome:
        """IDLE or HOLDING -> PLANNING for target (roll, pitch). A refused request
        changes nothing."""
        with self._lock:
            out = self._go_locked(
                "request_adjust",
                {Mode.IDLE, Mode.HOLDING},
                Mode.PLANNING,
                f"adjust to roll {roll_deg:+.4f} deg, pitch {pitch_deg:+.4f} deg",
            )
            if out.accepted:
                self._s.target_deg = (roll_deg, pitch_deg)
            return out

    def plan_ready(self) -> Outcome:
        """PLANNING -> ADJUSTING: a feasible plan arrived; the valves may open."""
        return self._go("plan_ready", {Mode.PLANNING}, Mode.ADJUSTING, "feasible plan")

    def plan_failed(self, reasons: Sequence[str]) -> Outcome:
        """PLANNING -> IDLE: the target is infeasible; ``reasons`` are the planner's."""
        why = "target refused: " + ("; ".join(reasons) if reasons else "no reason given")
        with self._lock:
            out = self._go_locked("plan_failed", {Mode.PLANNING}, Mode.IDLE, why)
            if out.accepted:
                self._s.target_deg = None
            return out

    def motion_done(self) -> Outcome:
        """ADJUSTING -> HOLDING: the trajectory ended and the target is reached."""
        return self._go("motion_done", {Mode.ADJUSTING}, Mode.HOLDING, "target reached")

    def suspend(self, reason: str) -> Outcome:
        """ADJUSTING/HOLDING -> SUSPENDED: the link dropped out; valves closed, held."""
        with self._lock:
            was = self._s.mode
            out = self._go_locked("suspend", SUSPENDABLE_MODES, Mode.SUSPENDED, reason)
            if out.accepted:
                self._s.resume_to = was
            return out

    def resume(self, reason: str) -> Outcome:
        """SUSPENDED -> the mode it was suspended from."""
        with self._lock:
            to = self._s.resume_to or Mode.HOLDING
            out = self._go_locked("resume", {Mode.SUSPENDED}, to, reason)
            if out.accepted:
                self._s.resume_to = None
            return out

    def stop(self, reason: str = "operator stop") -> Outcome:
        """Controlled stop: PLANNING/ADJUSTING/HOLDING -> IDLE, valves closed.

        Always accepted: in IDLE, FAULT or ESTOP the valves are already closed and the
        mode does not change (a stop never clears a fault).
        """
        with self._lock:
            if self._s.mode in ACTIVE_MODES:
                out = self._go_locked("stop", ACTIVE_MODES, Mode.IDLE, reason)
                self._s.target_deg = None
                return out
            msg = f"stop: already stopped in {self._s.mode}"
            return Outcome(True, self._s.mode, msg)

    def fault(self, cause: Cause) -> Outcome:
        """Any mode -> FAULT, latched by (interlock, where). In FAULT or ESTOP a new
        cause is added and logged once; a known one only updates its worst value and
        count (nothing logged)."""
        with self._lock:
            s = self._s
            new = s.faults.add(cause, self._clock())
            if new and self._on_fault is not None:
                self._on_fault(s.faults.entries()[-1])
            if s.mode in (Mode.FAULT, Mode.ESTOP):
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
            return self._transition("fault", Mode.FAULT, cause.text())

    def estop(self, active: bool) -> Outcome:
        """E-stop input. Pressed: any mode -> ESTOP. Released: stays ESTOP until reset."""
        with self._lock:
            s = self._s
            if active == s.estop_active and (not active or s.mode == Mode.ESTOP):
                return Outcome(True, s.mode, f"e-stop {'still' if active else 'not'} active")
            s.estop_active = active
            if active:
                return self._transition("estop", Mode.ESTOP, "e-stop pressed")
            log.info("estop_released", mode=str(s.mode))
            s.last_message = "e-stop released; reset to continue"
            return Outcome(True, s.mode, s.last_message)

    def reset(self) -> Outcome:
        """FAULT/ESTOP -> IDLE, only if the e-stop is released and no cause is active."""
        with self._lock:
            s = self._s
            if s.mode not in (Mode.FAULT, Mode.ESTOP):
                return self._refuse("reset", f"nothing to reset: mode is {s.mode}")
            blocking = [c.text() for c in self._active_causes()]
            if s.estop_active:
                blocking.insert(0, "e-stop still pressed")
            if blocking:
                return self._refuse(
                    "reset", "reset refused, cause still present: " + "; ".join(blocking)
                )
            cleared = "; ".join(e.text() for e in s.faults.entries()) or str(s.mode)
            out = self._transition("reset", Mode.IDLE, f"reset after: {cleared}")
            s.faults.clear()
            s.target_deg = None
            s.resume_to = None
            return out

    # ------------------------------------------------------------------ internals
    def _go(
        self, event: str, allowed: set[Mode] | frozenset[Mode], to: Mode, reason: str
    ) -> Outcome:
        with self._lock:
            return self._go_locked(event, allowed, to, reason)

    def _go_locked(
        self, event: str, allowed: set[Mode] | frozenset[Mode], to: Mode, reason: str
    ) -> Outcome:
        if self._s.mode not in allowed:
            names = "/".join(sorted(str(m) for m in allowed))
            hint = ""
            if self._s.mode in (Mode.FAULT, Mode.ESTOP):
                why = "; ".join(e.text() for e in self._s.faults.entries()) or "e-stop"
                hint = f" (latched: {why}; `wara ctl reset` once the cause is gone)"
            return self._refuse(
                event, f"{event} refused in {self._s.mode}: only allowed in {names}{hint}"
            )
        return self._transition(event, to, reason)

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
