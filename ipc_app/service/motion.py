"""The interface of the service's motions, after ros2_control's controllers.

A :class:`Motion` is one thing the machine does on an operator's request: an attitude
adjustment, a jog, a walk, the placement move, the part's release, homing (the modules
of :mod:`ipc_app.service.motions`, each an adapter over a sequencer of
:mod:`ipc_app.control`). The service's step knows none of them by name: the
:class:`~ipc_app.service.manager.MotionManager` holds the one active motion and calls
this interface.

Its life:

- ``prepare`` (a class method, in the requesting thread, never the loop's): the request
  checked and planned against the last measured state, the sequencer built; a
  :class:`~ipc_app.service.requests.Reply` refusal, or the motion;
- :meth:`Motion.start` (the loop, the cycle the mode machine accepted it): it engages at
  the measured rods; returns its :data:`Effects` (record events, the group it claims);
- :meth:`Motion.update` once per cycle while the valves may be driven: a
  :class:`Command` (the valve commands, the references, whether it completed, the
  interlock causes its own checks found, the events of the cycle, a new claim);
- :meth:`Motion.stop_point` when it is held or suspended, :meth:`Motion.resume_check`
  and :meth:`Motion.resume` when it goes on;
- :meth:`Motion.end` when another motion takes over or the service stops (IDLE).

:meth:`Motion.claim` says which cylinders it drives at the loop rate (the CAN fast
group: the link sends their valve frames every cycle and the PLC their positions), which
it watches (read and stroke-end checked) and the PLC mode; ``None`` is the attitude
layers in ATTITUDE_ADJUST, the service's own group.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np

from config.schema import ProjectConfig
from ipc_app.service.interlocks import Cause, Limits, Metrics, resume_cause
from ipc_app.service.requests import Reply
from plc_bridge.link import Mode as PlcMode

if TYPE_CHECKING:
    from ipc_app.control.attitude import AttitudeController
    from ipc_app.planner.steering import OnAxis
    from ipc_app.service.machine_io import MachineInputs
    from ipc_app.service.modes import Mode
    from ipc_app.service.record import RunRecorder


@dataclass(frozen=True)
class Event:
    """One run-record event (``kind`` and its fields), recorded at the cycle's time."""

    kind: str
    fields: Mapping[str, Any] = field(default_factory=dict)


def event(kind: str, **fields: Any) -> Event:
    return Event(kind, fields)


@dataclass(frozen=True)
class Claim:
    """What a motion drives: ``group`` at the loop rate on the link, ``watched`` read and
    checked at the stroke ends, the PLC's ``plc_mode``; ``event``: the run record's event
    of taking it (a phase entered; the manager adds ``active``, the group, and
    ``bus_load_percent``, the bus load it gives)."""

    group: tuple[int, ...]
    watched: tuple[int, ...]
    plc_mode: PlcMode
    event: Event | None = None


#: What :meth:`Motion.start` and :meth:`Motion.end` do beyond their own state, in order:
#: an :class:`Event` is recorded; a :class:`Claim` is taken (``None``: the attitude
#: layers are taken back).
Effects = tuple[Event | Claim | None, ...]


@dataclass(frozen=True)
class Command:
    """One cycle of a motion: ``valves`` (19 spool commands in [-1, 1]) and
    ``references`` (19 rod references, m; None: not referenced), recorded in this order
    after the cycle's drive: ``events``, then ``causes`` (interlocks its own checks
    tripped: latched), then ``done`` (the motion reached its end: COMPLETE, then
    :meth:`Motion.completed`), then ``claim`` (a phase that drives another group)."""

    valves: np.ndarray
    references: np.ndarray | None
    done: bool = False
    causes: Sequence[Cause] = ()
    events: Sequence[Event] = ()
    claim: Claim | None = None


class Wait:
    """:meth:`Motion.resume_check`'s answer while it cannot judge yet."""

    def __repr__(self) -> str:
        return "WAIT"


#: The resume check cannot judge yet (a slow group's frame still to come): ask again.
WAIT = Wait()


@dataclass
class MotionStats:
    """Figures of the present / last motion, for the operator and the demo."""

    target_deg: tuple[float, float] = (0.0, 0.0)
    started_s: float = 0.0
    duration_s: float = 0.0
    max_twist_m: float = 0.0
    max_sync_error_m: float = 0.0
    hold_sync_error_m: float = 0.0
    hold_samples: int = 0
    plan: dict[str, Any] | None = None


class Planner(Protocol):
    """What the service needs of the planner worker (non-blocking from the loop)."""

    def submit(
        self,
        request_id: int,
        roll_deg: float,
        pitch_deg: float,
        start_upper_m: Any = ...,
        start_lower_m: Any = ...,
    ) -> bool: ...

    def poll(self) -> Any: ...

    def call(self, fn: str, *args: Any, **kwargs: Any) -> Any:
        """``fn(cfg, *args, **kwargs)`` in the planner process, blocking the caller (the
        walk's and the placement's planning; never from the loop)."""


class Preparation(Protocol):
    """A request the loop helps prepare: polled once per cycle before the motion's
    update (an adjustment: its target submitted to the planner, the answer taken)."""

    def poll(self, inp: MachineInputs) -> None: ...


class Service(Protocol):
    """What a motion's preparation reads of the service (in the requesting thread)."""

    cfg: ProjectConfig
    period_s: float
    planner: Planner
    attitude: AttitudeController
    record: RunRecorder | None
    #: where the machine stands against the design axis, as its walks measured it (None:
    #: on the axis at ring 1's rear joint face; :mod:`ipc_app.planner.steering`)
    on_axis: OnAxis | None

    @property
    def inputs(self) -> MachineInputs | None: ...
    @property
    def now_s(self) -> float: ...


class Ticket:
    """A request handed to the loop: :attr:`reply` once the loop has taken it (or at once
    when it was refused before), :attr:`motion` the motion it starts, if any. The ring
    cycle follows its motions by their tickets."""

    __slots__ = ("_done", "motion", "reply")

    def __init__(self, motion: Motion | None = None, reply: Reply | None = None) -> None:
        self.motion = motion
        self.reply = reply
        self._done = threading.Event()
        if reply is not None:
            self._done.set()

    def answer(self, reply: Reply) -> None:
        self.reply = reply
        self._done.set()

    @property
    def taken(self) -> bool:
        return self._done.is_set()

    @property
    def started(self) -> bool:
        """Taken by the loop and accepted."""
        return self._done.is_set() and self.reply is not None and self.reply.ok

    def wait(self, wait_s: float) -> Reply | None:
        """The reply, waiting up to ``wait_s`` for it (None: still pending)."""
        if self.reply is None and wait_s > 0:
            self._done.wait(wait_s)
        return self.reply


class Motion(ABC):
    """One motion of the machine; see the module docstring. Subclasses set :attr:`name`
    (the mode machine's event that starts it, :data:`~ipc_app.service.modes.RULES`, and
    its status key) and implement the abstract methods."""

    name: ClassVar[str]
    #: the HMI request it serves is answered COMPLETED when it completes
    answers_hmi: ClassVar[bool] = False
    #: the reason the mode machine is given when an operator's unhold lets it go on
    unhold_reason: ClassVar[str] = "operator unhold"
    #: the run record's event of an unhold its resume check refused (None: none)
    resume_refused_event: ClassVar[str | None] = None
    #: the attitude target and the plan, for :class:`MotionStats`
    target_deg: tuple[float, float] = (0.0, 0.0)
    plan: dict[str, Any] | None = None
    #: the :mod:`ipc_app.control` sequencer it runs (the service's ``walker``, ...)
    sequencer: Any = None

    @classmethod
    def prepare(cls, svc: Service, *args: Any) -> Motion | Reply:
        """The request checked and planned, the motion built, in the requesting thread
        (never the loop's): the motion, or the refusal."""
        raise NotImplementedError(f"{cls.__name__} is not started by a request")

    def describe(self) -> str:
        """What it does, for the mode machine's transition (``walk 1 step(s) ...``)."""
        return ""

    def accepted(self) -> dict[str, Any]:
        """What the reply to its accepted request says besides the mode."""
        return {}

    def refusal(self, inp: MachineInputs) -> str | None:
        """Why it cannot start from these inputs (the loop, before the mode machine)."""
        return None

    def claim(self) -> Claim | None:
        """What it drives now (None: the attitude layers)."""
        return None

    def metrics(self) -> Mapping[str, Metrics]:
        """The attitude layers' figures of its last update, for the driven interlocks and
        the operator's figures (empty: it does not drive them as layers)."""
        return {}

    @abstractmethod
    def start(self, inp: MachineInputs) -> Effects:
        """Engage at the measured state (the loop, once the mode machine accepted it)."""

    def finished(self, now: float) -> bool:
        """Its own clock says it has ended (asked in EXECUTE before the cycle's drive; the
        drive then holds its end point). Motions that end on what they measure say so
        in :attr:`Command.done` instead."""
        return False

    @abstractmethod
    def update(self, inp: MachineInputs, mode: Mode) -> Command:
        """One cycle with the valves driven (EXECUTE or COMPLETE, valid positions)."""

    def completed(self, now: float) -> Event | None:
        """The mode machine took it to COMPLETE: hold its end; the record's event."""
        return None

    @abstractmethod
    def stop_point(self, now: float, inp: MachineInputs | None) -> np.ndarray:
        """It stops (held, suspended): the references where it stopped (19, m)."""

    def resume_check(
        self, inp: MachineInputs, stop_ref: np.ndarray | None, limits: Limits, held: bool
    ) -> Cause | Wait | None:
        """Before it goes on (``held``: an operator's unhold, else a resume after a
        suspension): why not (a cause), None to go on, or :data:`WAIT`. By default every
        watched rod within the sync band of where it stopped, its pressures valid."""
        stop = stop_ref.tolist() if stop_ref is not None else None
        return resume_cause(inp, stop, limits)

    @abstractmethod
    def resume(self, inp: MachineInputs, shift_s: float, held: bool) -> None:
        """Go on: its clock ``shift_s`` later (the time stopped), controllers bumpless."""

    def end(self, now: float, mode: Mode, successor: Motion | None) -> Effects:
        """It ends: ``successor`` takes over (None: the service stopped, IDLE)."""
        return ()

    def status(self) -> dict[str, Any] | None:
        """Its part of ``wara ctl status`` (under :attr:`name`; None: nothing)."""
        return None

    def figures(self) -> dict[str, Any]:
        """Its figures once it has completed (the ring cycle's record)."""
        return {}
