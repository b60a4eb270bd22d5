"""The operator-visible state machine of the IPC service.

::

    BOOT --boot_complete--> IDLE --request_adjust--> PLANNING --plan_ready--> ADJUSTING
      ADJUSTING --motion_done--> HOLDING --stop / release--> IDLE
      PLANNING --plan_failed (target infeasible)--> IDLE
      HOLDING --request_adjust--> PLANNING           (next adjustment from the held pose)
      any --fault(reason)--> FAULT                   (latched; not from ESTOP)
      any --estop(True)--> ESTOP                     (latched even after estop(False))
      FAULT / ESTOP --reset()--> IDLE                (only when every cause is gone)

Valves may be driven only in ADJUSTING and HOLDING (:attr:`ModeMachine.valves_enabled`);
every other mode is a controlled stop: valves closed, the load held by the closed valves.
Nothing is persisted: a new :class:`ModeMachine` (a restart of the service) is always in
BOOT, and :meth:`~ModeMachine.boot_complete` takes it to IDLE with the valves closed.

Each event method returns an :class:`Outcome`; a refused request (``adjust`` while FAULT,
``reset`` while the heartbeat is still lost) has ``accepted=False`` and a message saying
why and what would make it possible. Nothing raises, so the loop thread can call the
events it owns (``plan_ready``, ``motion_done``, ``fault``) without a try block. Every
transition and every refusal is logged with structlog (``event="mode"``).

Planner failures: an *infeasible target* is the operator's problem, ``plan_failed``
returns to IDLE with the planner's reasons; a *planner crash or timeout* is an interlock,
the service calls ``fault("planner: ...")``.

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

log = structlog.get_logger("wara.service.modes")


class Mode(StrEnum):
    BOOT = "BOOT"
    IDLE = "IDLE"
    PLANNING = "PLANNING"
    ADJUSTING = "ADJUSTING"
    HOLDING = "HOLDING"
    FAULT = "FAULT"
    ESTOP = "ESTOP"


#: Modes in which the control loop may drive the valves.
VALVE_MODES = frozenset({Mode.ADJUSTING, Mode.HOLDING})
#: Modes in which an axis is moving or being planned; ``stop`` brings them to IDLE.
ACTIVE_MODES = frozenset({Mode.PLANNING, Mode.ADJUSTING, Mode.HOLDING})


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
    fault_reasons: list[str] = field(default_factory=list)
    estop_active: bool = False
    target_deg: tuple[float, float] | None = None
    last_message: str = "booting"


class ModeMachine:
    """The operator-visible modes; see the module docstring for the transitions.

    ``active_causes`` is asked by :meth:`reset` for the interlock conditions that are
    still present (e.g. ``["plc heartbeat lost"]``); a reset succeeds only when it
    returns nothing and the e-stop is released. ``clock`` is for the transition times.
    ``on_transition`` is called with each :class:`Transition` (e.g. to write it to the
    run record or to systemd's STATUS=); it runs in the caller's thread under the
    machine's re-entrant lock, so it must be quick and must not block.
    """

    def __init__(
        self,
        *,
        active_causes: Callable[[], Sequence[str]] = lambda: (),
        clock: Callable[[], float] = time.monotonic,
        on_transition: Callable[[Transition], None] | None = None,
        history: int = 100,
    ) -> None:
        self._active_causes = active_causes
        self._clock = clock
        self._on_transition = on_transition
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
        return tuple(self._s.fault_reasons)

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
                "fault_reasons": list(s.fault_reasons),
                "estop_active": s.estop_active,
                "target_deg": list(s.target_deg) if s.target_deg else None,
                "message": s.last_message,
            }

    # ------------------------------------------------------------------ events
    def boot_complete(self) -> Outcome:
        """BOOT -> IDLE once the service is wired (valves closed)."""
        return self._go("boot_complete", {Mode.BOOT}, Mode.IDLE, "start-up complete")

    def request_adjust(self, roll_deg: float, pitch_deg: float) -> Outcome:
        """IDLE or HOLDING -> PLANNING for target (roll, pitch)."""
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

    def fault(self, reason: str) -> Outcome:
        """Any mode -> FAULT, latched. In FAULT the reason is added; in ESTOP it is noted."""
        with self._lock:
            s = self._s
            if reason not in s.fault_reasons:
                s.fault_reasons.append(reason)
            if s.mode in (Mode.FAULT, Mode.ESTOP):
                log.warning("fault", mode=str(s.mode), reason=reason, latched=True)
                return Outcome(True, s.mode, f"{s.mode} kept; fault noted: {reason}")
            return self._transition("fault", Mode.FAULT, reason)

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
            blocking = list(self._active_causes())
            if s.estop_active:
                blocking.insert(0, "e-stop still pressed")
            if blocking:
                return self._refuse(
                    "reset", "reset refused, cause still present: " + "; ".join(blocking)
                )
            cleared = "; ".join(s.fault_reasons) or str(s.mode)
            out = self._transition("reset", Mode.IDLE, f"reset after: {cleared}")
            s.fault_reasons.clear()
            s.target_deg = None
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
                why = "; ".join(self._s.fault_reasons) or "e-stop"
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
