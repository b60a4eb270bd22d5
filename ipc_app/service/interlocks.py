"""The service's interlocks as data: which one, its config key, when it applies.

Each :class:`Interlock` has one :class:`Spec` in :data:`SPECS`: the config key that
sets its limit (or ``None``), when the check runs (:class:`Applies`), the unit of its
value and the condition in words. A check that trips makes a :class:`Cause`
``(interlock, where, value)``: ``where`` is the cylinder, the group or the PLC's fault
code, ``value`` the measured figure in the spec's unit. The mode machine latches causes
by ``(interlock, where)`` in a :class:`FaultLatch`, keeping the first and the worst
value and how often it was seen, so a lasting condition is one entry however long it
lasts and however its value moves. Everything shown to the operator (``wara ctl
status``, the log, the run record) is rendered from this data; nothing matches an
interlock by its text.

:func:`markdown_table` renders the table of docs/service.md (a test keeps the two equal).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any


class Applies(StrEnum):
    """When a check runs."""

    ALWAYS = "always (after start-up)"
    DRIVEN = "valves driven (ADJUSTING, HOLDING)"
    SUSPENDED = "SUSPENDED, before the motion resumes"
    EVENT = "when the planner answers"
    STARTUP = "BOOT, and until IDLE is first reached"


class Interlock(StrEnum):
    PLC_HEARTBEAT = "plc heartbeat"
    SENSOR_TIMEOUT = "sensor timeout"
    SENSOR = "sensor"
    PRESSURE = "pressure"
    PLC_FAULT = "plc fault"
    TWIST = "twist"
    SYNC_ERROR = "sync error"
    TRACKING_ERROR = "tracking error"
    STROKE_END = "stroke end"
    SUSPEND_TIMEOUT = "suspend timeout"
    RESUME_CHECK = "resume check"
    PLANNER = "planner"
    CONTROL_CHANNEL = "control channel"
    STARTUP = "start-up"


@dataclass(frozen=True)
class Spec:
    #: config key of the limit (``safety.max_twist_mm``), or None
    key: str | None
    applies: Applies
    #: unit of :attr:`Cause.value` ("" when the cause has no value)
    unit: str
    #: the condition in words, for the docs and the status
    condition: str
    #: the worse of two values: larger (``max``) or smaller (``min``)
    worse: str = "max"


SPECS: dict[Interlock, Spec] = {
    Interlock.PLC_HEARTBEAT: Spec(
        "safety.plc_heartbeat_timeout_ms",
        Applies.ALWAYS,
        "ms",
        "no valid PLC status for longer than the timeout, or the IPC's bus is off or down",
    ),
    Interlock.SENSOR_TIMEOUT: Spec(
        "safety.sensor_timeout_ms",
        Applies.ALWAYS,
        "ms",
        "no valid rod position of an active cylinder for longer than the timeout "
        "(stale, CRC or counter errors, delayed)",
    ),
    Interlock.SENSOR: Spec(
        None,
        Applies.ALWAYS,
        "",
        "an active cylinder's position sensor reports a fault (SENSOR_FAULT value)",
    ),
    Interlock.PRESSURE: Spec(
        "safety.max_pressure_mpa",
        Applies.ALWAYS,
        "MPa",
        "a valid chamber pressure above the limit",
    ),
    Interlock.PLC_FAULT: Spec(
        None, Applies.ALWAYS, "", "the PLC reports a fault code other than e-stop"
    ),
    Interlock.TWIST: Spec(
        "safety.max_twist_mm", Applies.DRIVEN, "mm", "a layer's measured twist above the limit"
    ),
    Interlock.SYNC_ERROR: Spec(
        "safety.max_sync_error_mm",
        Applies.DRIVEN,
        "mm",
        "a group's synchronization error above the limit",
    ),
    Interlock.TRACKING_ERROR: Spec(
        "safety.max_tracking_error_mm",
        Applies.DRIVEN,
        "mm",
        "an active rod further than the limit from its reference (commands ignored, valve stuck)",
    ),
    Interlock.STROKE_END: Spec(
        "safety.stroke_end_margin_mm",
        Applies.DRIVEN,
        "mm",
        "an active rod closer than the margin to an end of its stroke, or at its limit "
        "switch (value: distance to the nearer end)",
        worse="min",
    ),
    Interlock.SUSPEND_TIMEOUT: Spec(
        "safety.max_suspend_ms",
        Applies.SUSPENDED,
        "ms",
        "SUSPENDED for longer than the limit (the link keeps dropping out)",
    ),
    Interlock.RESUME_CHECK: Spec(
        "safety.max_sync_error_mm",
        Applies.SUSPENDED,
        "mm",
        "fresh frames are back, but an active rod is further than the limit from where "
        "the motion stopped, or an active pressure is not valid",
    ),
    Interlock.PLANNER: Spec(None, Applies.EVENT, "", "the planner process crashed or timed out"),
    Interlock.CONTROL_CHANNEL: Spec(
        None,
        Applies.ALWAYS,
        "",
        "the control socket's server thread ended or stalled, or its socket file is gone "
        "(where: the server's state; the service binds it again)",
    ),
    Interlock.STARTUP: Spec(
        None,
        Applies.STARTUP,
        "s",
        "start-up not complete after `ServiceCore.BOOT_TIMEOUT_S` (5 s) because the link "
        "is not fresh: rod positions or the PLC status stale, or the PLC reporting the "
        "IPC's commands stale (detail: which); an interlock condition present then is "
        "latched as itself",
    ),
}


@dataclass(frozen=True)
class Cause:
    """One tripped check: the interlock, where (cylinder, group, fault code), the value
    (in the spec's unit) and the limit it was checked against (same unit)."""

    interlock: Interlock
    where: str = ""
    value: float | None = None
    limit: float | None = None
    detail: str = ""

    @property
    def key(self) -> tuple[Interlock, str]:
        return (self.interlock, self.where)

    def text(self) -> str:
        return _render(self.interlock, self.where, self.value, self.limit, self.detail)


def _fmt(v: float) -> str:
    return "inf" if math.isinf(v) else f"{v:.2f}"


def _render(
    il: Interlock, where: str, value: float | None, limit: float | None, detail: str
) -> str:
    unit = SPECS[il].unit
    parts = [f"{il}:"]
    if where:
        parts.append(where)
    if value is not None:
        parts.append(f"{_fmt(value)} {unit}".rstrip())
        if limit is not None:
            rel = "below" if SPECS[il].worse == "min" else "above"
            parts.append(f"({rel} the limit {_fmt(limit)} {unit})".replace(" )", ")"))
    if detail:
        parts.append(detail)
    return " ".join(parts)


@dataclass
class Latched:
    """One latched cause: first and worst value, how often seen, first and last time."""

    interlock: Interlock
    where: str
    first: float | None
    worst: float | None
    limit: float | None
    detail: str
    count: int
    first_t: float
    last_t: float

    def text(self) -> str:
        return _render(self.interlock, self.where, self.worst, self.limit, self.detail)

    def to_dict(self) -> dict[str, Any]:
        return {
            "interlock": str(self.interlock),
            "where": self.where,
            "first": self.first,
            "worst": self.worst,
            "limit": self.limit,
            "unit": SPECS[self.interlock].unit,
            "count": self.count,
            "first_t_s": self.first_t,
            "last_t_s": self.last_t,
            "text": self.text(),
        }


class FaultLatch:
    """Causes latched by ``(interlock, where)``; at most :attr:`MAX_ENTRIES` entries
    (later new keys are only counted in :attr:`dropped`), so the status stays small."""

    MAX_ENTRIES = 32

    def __init__(self) -> None:
        self._by_key: dict[tuple[Interlock, str], Latched] = {}
        self.dropped = 0

    def add(self, cause: Cause, t: float) -> bool:
        """Latch or update; True when the key is new (log it), False when updated."""
        e = self._by_key.get(cause.key)
        if e is not None:
            e.count += 1
            e.last_t = t
            v = cause.value
            if v is not None and (e.worst is None or _worse(cause.interlock, v, e.worst)):
                e.worst = v
            return False
        if len(self._by_key) >= self.MAX_ENTRIES:
            self.dropped += 1
            return False
        self._by_key[cause.key] = Latched(
            cause.interlock,
            cause.where,
            cause.value,
            cause.value,
            cause.limit,
            cause.detail,
            1,
            t,
            t,
        )
        return True

    def clear(self) -> None:
        self._by_key.clear()
        self.dropped = 0

    def entries(self) -> tuple[Latched, ...]:
        return tuple(self._by_key.values())

    def interlocks(self) -> tuple[Interlock, ...]:
        return tuple(e.interlock for e in self._by_key.values())

    def __len__(self) -> int:
        return len(self._by_key)


def _worse(il: Interlock, a: float, b: float) -> bool:
    return a < b if SPECS[il].worse == "min" else a > b


def markdown_table() -> str:
    """The interlock table of docs/service.md, rendered from :data:`SPECS`."""
    rows = [
        "| interlock | config key | applies | condition |",
        "|---|---|---|---|",
    ]
    for il, s in SPECS.items():
        key = f"`{s.key}`" if s.key else "-"
        rows.append(f"| `{il}` | {key} | {s.applies} | {s.condition} |")
    return "\n".join(rows) + "\n"
