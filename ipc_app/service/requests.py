"""Every operator request's limits in one table, its checks, and the typed reply.

A request reaches the service from ``wara ctl`` (the control socket,
:mod:`ipc_app.service.ctl_protocol`), from the OPC UA server (which speaks that socket)
and from the HMI over CAN (``PLC_HmiTarget``, read by the loop). Whatever the front end,
a value is checked against the one entry of :data:`LIMITS` that bounds it (its range,
its unit, why it is bounded there), with the checks below; a refusal names the key, the
bound and what was given.

What follows from the project (a stroke, a ring's design pose, a walk's statics) is not
here: the motions check that against the measured state before anything moves.

Each request is answered with a :class:`Reply`: accepted with its fields, or refused
with a :class:`Code` and a one-line error. :meth:`Reply.to_dict` is the JSON the control
socket sends and what the service's request methods return.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, Any

from config import units
from config.numbers import check_name, check_text
from plc_bridge.link import HmiTarget, PlcStatus, TargetAck, TargetRequest

if TYPE_CHECKING:
    from ipc_app.service.modes import Outcome


class Code(StrEnum):
    """Why a request was not done (the ``code`` of a refusal)."""

    #: the request itself is malformed: a missing or non-finite number, out of its limit
    BAD_REQUEST = "bad_request"
    #: the mode machine or the measured state says no (``wara ctl`` exits 1)
    REFUSED = "refused"
    #: the planner found the target infeasible (``wara ctl`` exits 3)
    INFEASIBLE = "infeasible"
    #: the planner process timed out, died or is stopped
    PLANNER = "planner"
    #: every worker of the control socket is busy
    BUSY = "busy"
    #: a handler raised (logged)
    INTERNAL = "internal"


@dataclass(frozen=True)
class Reply:
    """The answer to one request: ``ok``, and for a refusal its :class:`Code` and
    one-line ``error``; ``fields`` the rest (``mode``, ``duration_s``, the planner's
    ``reasons`` ...)."""

    ok: bool
    code: Code | None = None
    error: str | None = None
    fields: Mapping[str, Any] = field(default_factory=dict)

    @classmethod
    def accepted(cls, **fields: Any) -> Reply:
        return cls(True, fields=fields)

    @classmethod
    def refused(cls, error: str, code: Code = Code.REFUSED, **fields: Any) -> Reply:
        return cls(False, code, error, fields)

    @classmethod
    def bad_request(cls, error: str) -> Reply:
        return cls(False, Code.BAD_REQUEST, error)

    @classmethod
    def outcome(cls, out: Outcome) -> Reply:
        """The mode machine's verdict (``accepted``, ``mode``, ``message``); refused, its
        message is the error."""
        if out.accepted:
            return cls(True, fields=out.to_dict())
        return cls(False, Code.REFUSED, out.message, out.to_dict())

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"ok": self.ok}
        if self.code is not None:
            out["code"] = str(self.code)
        if self.error is not None:
            out["error"] = self.error
        return out | dict(self.fields)


# --------------------------------------------------------------------------- limits


@dataclass(frozen=True)
class Limit:
    """One request value's range ``lo..hi`` and why it is bounded there."""

    lo: float
    hi: float
    unit: str
    why: str
    #: the bounds themselves are outside (``lo < v < hi``)
    exclusive: bool = False

    def holds(self, v: float) -> bool:
        return self.lo < v < self.hi if self.exclusive else self.lo <= v <= self.hi

    def text(self) -> str:
        unit = f" {self.unit}" if self.unit else ""
        if self.exclusive:
            return f"over {self.lo:g} and under {self.hi:g}{unit}"
        return f"{self.lo:g}..{self.hi:g}{unit}"

    def outside(self, v: float, name: str) -> str | None:
        """Why ``v`` (given as ``name``) is outside the range, with the reason for it;
        None: it is within."""
        return (
            None
            if self.holds(v)
            else f"{name} must be within {self.text()} ({self.why}), got {v:g}"
        )


#: Every bound an operator request is checked against, by the request value it bounds.
LIMITS: dict[str, Limit] = {
    "ring": Limit(1, 99_999, "", "a ring number of the tunnel's drawing"),
    "cycle_ring": Limit(2, 99_999, "", "a ring cycle needs the part before it (ring - 1)"),
    "walk_steps": Limit(1, 1000, "", "the most steps one walk request takes"),
    "cycle_walk_steps": Limit(
        0, 1000, "", "a ring cycle's steps to its ring and back (0: it stands there)"
    ),
    "hmi_walk_steps": Limit(1, 3, "", "what PLC_HmiTarget's WalkSteps (2 bits) can carry"),
    "attitude_deg": Limit(-90, 90, "deg", "a workpiece roll or pitch", exclusive=True),
    "deviation_mm": Limit(
        -50, 50, "mm", "a survey sheet's deviation across the axis (y, z): more is a typo"
    ),
    "deviation_deg": Limit(
        -10, 10, "deg", "a survey sheet's deviation turned (roll, pitch, yaw): more is a typo"
    ),
    "chainage_m": Limit(-1e6, 1e6, "m", "a chainage of the design axis (as the alignment's)"),
    "heading_error_deg": Limit(
        -5, 5, "deg", "the machine's surveyed heading less the axis's: more is a typo"
    ),
    "lateral_mm": Limit(-500, 500, "mm", "M's centre surveyed off the axis: more is a typo"),
    "status_wait_ms": Limit(0, 1000, "ms", "how long a status may wait for a change of mode"),
    "survey_points": Limit(1, 200, "", "the points one survey request carries"),
    "audit_chars": Limit(0, 400, "characters", "an audit entry's result (one log line)"),
    "name_chars": Limit(1, 40, "characters", "a cylinder id, a user, an action (audited as is)"),
}

MAX_WALK_STEPS = int(LIMITS["walk_steps"].hi)
HMI_WALK_STEPS_MAX = int(LIMITS["hmi_walk_steps"].hi)
MAX_SURVEY_POINTS = int(LIMITS["survey_points"].hi)
MAX_STATUS_WAIT_MS = int(LIMITS["status_wait_ms"].hi)
MAX_AUDIT_CHARS = int(LIMITS["audit_chars"].hi)
MAX_ID_CHARS = int(LIMITS["name_chars"].hi)
MAX_SHEET_DEVIATION_MM = LIMITS["deviation_mm"].hi
MAX_SHEET_DEVIATION_DEG = LIMITS["deviation_deg"].hi


# --------------------------------------------------------------------------- checks


def brief(v: Any) -> str:
    """A short description of a client's value for an error message (never its whole
    repr: it may be 64 KiB or nested a thousand deep)."""
    if v is None or isinstance(v, bool | float) or (isinstance(v, str) and len(v) <= 40):
        return repr(v)
    if isinstance(v, int):
        return "an integer of more than 40 digits" if v.bit_length() > 132 else repr(v)
    return f"a {type(v).__name__}" if not isinstance(v, str) else "a long string"


def number(v: Any, key: str, unit: str = "degrees") -> float:
    """``v`` as a finite float; ValueError naming ``key`` otherwise."""
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"{key!r} must be a finite number in {unit}, got {brief(v)}")
    try:
        f = float(v)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise ValueError(f"{key!r} must be a finite number in {unit}, got {brief(v)}")
    return f


def integer(v: Any, key: str, limit: str) -> int:
    """``v`` as an int within ``LIMITS[limit]``; ValueError naming ``key`` otherwise."""
    lim = LIMITS[limit]
    if isinstance(v, bool) or not isinstance(v, int) or not lim.holds(v):
        raise ValueError(f"{key!r} must be an integer {lim.text()}, got {brief(v)}")
    return v


def bounded(v: Any, key: str, limit: str) -> float:
    """``v`` as a finite float within ``LIMITS[limit]`` (in its unit); ValueError naming
    ``key`` otherwise."""
    lim = LIMITS[limit]
    f = number(v, key, lim.unit)
    why = lim.outside(f, repr(key))
    if why:
        raise ValueError(why)
    return f


def within(v: int, limit: str, what: str) -> str | None:
    """Why ``v`` is outside ``LIMITS[limit]`` (None: it is within)."""
    lim = LIMITS[limit]
    return None if lim.holds(v) else f"{what} {lim.text()}, got {v}"


def flag(v: Any, key: str) -> bool:
    if not isinstance(v, bool):
        raise ValueError(f"{key!r} must be true or false, got {brief(v)}")
    return v


def name(v: Any, key: str) -> str:
    """A name of 1..MAX_ID_CHARS characters, no control, format or line-break character
    (:func:`config.numbers.check_name`: it goes into the audit trail as it is)."""
    return check_name(v, repr(key), MAX_ID_CHARS)


def text(v: Any, key: str) -> str:
    """An audit entry's free text (at most MAX_AUDIT_CHARS, one line)."""
    check_text(v, repr(key), MAX_AUDIT_CHARS)
    return str(v)


def numbers(v: Any, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(v, list) or len(v) != n:
        raise ValueError(f"{what} must be {n} numbers, got {brief(v)}")
    return tuple(number(x, "v", "mm or degrees") for x in v)


def attitude(roll_deg: float, pitch_deg: float) -> None:
    """ValueError unless both are within ``LIMITS["attitude_deg"]``."""
    lim = LIMITS["attitude_deg"]
    if not (lim.holds(roll_deg) and lim.holds(pitch_deg)):
        raise ValueError("roll_deg and pitch_deg must be within ±90 deg")


def check_sheet_deviation(vals: tuple[float, ...], what: str) -> None:
    """ValueError unless ``vals`` (y mm, z mm, roll, pitch, yaw deg) is within
    ``LIMITS["deviation_mm"]`` and ``LIMITS["deviation_deg"]``."""
    if (
        max(abs(vals[0]), abs(vals[1])) > MAX_SHEET_DEVIATION_MM
        or max(abs(v) for v in vals[2:]) > MAX_SHEET_DEVIATION_DEG
    ):
        raise ValueError(
            f"{what}: at most {MAX_SHEET_DEVIATION_MM:g} mm and {MAX_SHEET_DEVIATION_DEG:g} deg "
            "(a typo, not a survey)"
        )


def walk_refusal(steps: int, directions: tuple[str, ...], direction: str) -> Reply | None:
    """A walk request's own values (the service's check, whichever front end sent it)."""
    why = within(steps, "walk_steps", "steps")
    if why is None and direction not in directions:
        why = f"direction must be one of {', '.join(directions)}, got {direction!r}"
    return None if why is None else Reply.bad_request(why)


def plc_walk_refusal(status: PlcStatus | None) -> Reply | None:
    """A walk the PLC would not take: its status says the machine cannot walk
    (``PLC_Status.WalkAvailable`` 0: it refuses WALK and keeps the drives off), or there
    is no status to say it can. Checked before anything is planned or moved."""
    if status is None:
        return Reply.refused("walk refused: no PLC status (WalkAvailable unknown)")
    if not status.walk_available:
        return Reply.refused(
            "walk refused: the PLC reports that the machine cannot walk "
            "(PLC_Status WalkAvailable 0); nothing moved"
        )
    return None


def hmi_walk_refusal(steps: int) -> str | None:
    """The HMI's WALK request: a step count the wire carries but no walk takes."""
    lim = LIMITS["hmi_walk_steps"]
    if lim.holds(steps):
        return None
    return f"HMI walk refused: WalkSteps {steps} (a walk is {lim.text()} steps)"


def cycle_refusal(ring: int, steps: int) -> Reply | None:
    why = within(ring, "cycle_ring", "ring") or within(steps, "cycle_walk_steps", "walk_steps")
    return None if why is None else Reply.bad_request(why)


def ring_refusal(ring: int) -> Reply | None:
    why = within(ring, "ring", "ring")
    return None if why is None else Reply.bad_request(why)


class HmiRequests:
    """The HMI's requests over CAN (``PLC_HmiTarget``, read by the loop): a target is
    asked as ``wara ctl adjust`` asks it; a cancel stops; a walk is checked here and
    planned on a thread of its own (planning is not the loop's work); each answered
    with its TargetSeq."""

    def __init__(
        self,
        adjust: Callable[[float, float, int], dict[str, Any]],
        walk: Callable[[int, int], object],
        stop: Callable[[str], object],
        ack: Callable[[TargetAck, int], None],
        refused: Callable[[float, int, str], object],
    ) -> None:
        self._adjust, self._walk, self._stop, self._ack = adjust, walk, stop, ack
        self._refused = refused
        self._preparing = 0
        self._lock = threading.Lock()

    @property
    def preparing(self) -> bool:
        """A walk is being planned on its thread, not yet handed to the loop (the
        lockstep harness holds machine time meanwhile, as it does for the planner)."""
        return self._preparing > 0

    def take(self, hmi: HmiTarget, now: float) -> None:
        if hmi.request == TargetRequest.NEW_TARGET:
            deg = units.to_deg
            out = self._adjust(deg(hmi.roll_rad), deg(hmi.pitch_rad), hmi.seq)
            if not out.get("ok"):  # refused: its own seq; the running one's is kept
                self._ack(TargetAck.REJECTED, hmi.seq)
        elif hmi.request == TargetRequest.CANCEL:
            self._stop("HMI cancel")
            self._ack(TargetAck.NONE, hmi.seq)
        elif hmi.request == TargetRequest.WALK:
            why = hmi_walk_refusal(hmi.walk_steps)
            if why is not None:
                self._refused(now, hmi.seq, why)
                return
            with self._lock:
                self._preparing += 1
            threading.Thread(
                target=self._prepare_walk, args=(hmi,), name="wara-hmi-walk", daemon=True
            ).start()

    def _prepare_walk(self, hmi: HmiTarget) -> None:
        try:
            self._walk(hmi.walk_steps, hmi.seq)
        finally:
            with self._lock:
                self._preparing -= 1
