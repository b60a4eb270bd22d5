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

:func:`present_causes`, :func:`motion_causes`, :func:`link_losses` and
:func:`resume_cause` are the checks: pure functions of one cycle's
:class:`~ipc_app.service.machine_io.MachineInputs` (and the mode, the controller's
figures) against the :class:`Limits` of the configuration, returning causes.

:func:`markdown_table` renders the table of docs/service.md (a test keeps the two equal).

Over 500 lines because each interlock's spec and the pure check that trips it are kept
together, with the table that documents them.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np

from config import units
from config.schema import ProjectConfig
from plc_bridge.link import Fault

if TYPE_CHECKING:
    from ipc_app.service.machine_io import MachineInputs


class Applies(StrEnum):
    """When a check runs."""

    ALWAYS = "always (after start-up)"
    DRIVEN = "valves driven (EXECUTE, COMPLETE)"
    SUSPENDED = "SUSPENDED, before the motion resumes"
    EVENT = "when the planner answers"
    STARTUP = "start-up (STOPPED), until IDLE is first reached"
    WALK = "walking (EXECUTE in a walk), in the phases named"
    RELEASE = "the part's release (EXECUTE in a ring cycle's release)"


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
    SYNC_BAND = "sync band"
    OVERLOAD = "overload"
    TOUCHDOWN = "touch-down"
    TRANSFER = "transfer"
    STABILITY = "stability"
    SLIP = "slip"
    WALK_RESUME = "walk resume check"
    RELEASE = "release"


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
        "the motion stopped, or an active pressure is not valid (in a walk: the walk resume "
        "check instead)",
    ),
    Interlock.PLANNER: Spec(
        "planner.request_timeout_s",
        Applies.EVENT,
        "s",
        "the planner process crashed, or gave no result within the limit",
    ),
    Interlock.CONTROL_CHANNEL: Spec(
        "safety.ctl_stall_timeout_s",
        Applies.ALWAYS,
        "s",
        "the control socket's server thread ended or stalled (no turn for longer than the "
        "limit), or its socket file is gone "
        "(where: the server's state; the service binds it again)",
    ),
    Interlock.STARTUP: Spec(
        "safety.boot_timeout_s",
        Applies.STARTUP,
        "s",
        "start-up not complete within the timeout because the link "
        "is not fresh: rod positions or the PLC status stale, or the PLC reporting the "
        "IPC's commands stale (detail: which); an interlock condition present then is "
        "latched as itself",
    ),
    Interlock.SYNC_BAND: Spec(
        "walking.sync_band_timeout_s",
        Applies.WALK,
        "s",
        "phases 1, 2, 5, 6, 7a, 8: the moving legs (`walking.leg_sync_band_mm`) or the travel "
        "pair (`walking.travel_sync_band_mm`) out of their sync band: the group holds and goes "
        "on once back inside; latched only when out for longer than the timeout",
    ),
    Interlock.OVERLOAD: Spec(
        "walking.overload_percent",
        Applies.WALK,
        "%",
        "every phase: a leg's force above the limit of its expected share (the plan's force "
        "now, at least its eight-leg share)",
    ),
    Interlock.TOUCHDOWN: Spec(
        "walking.touchdown_travel_mm",
        Applies.WALK,
        "mm",
        "phases 2, 7a: a foot not touched down (cap pressure `walking.touch_mpa` above its "
        "free-rod value) within the travel below the expected ground (a hole), or meeting "
        "the invert (its force on the body above the touch force) further above it than "
        "the travel (an obstacle; the value: its height above the expected ground)",
    ),
    Interlock.TRANSFER: Spec(
        "walking.transfer_timeout_s",
        Applies.WALK,
        "s",
        "phases 3, 4, 7b, 7c: preload or transfer not done within the timeout (at the end a "
        "receiving leg off its share by more than `walking.share_tolerance_percent`)",
    ),
    Interlock.STABILITY: Spec(
        "walking.min_stability_margin_m",
        Applies.WALK,
        "m",
        "every phase: the stability margin below the limit, from the measured state or along "
        "the phase's commanded motion (checked at its start, before anything moves)",
        worse="min",
    ),
    Interlock.SLIP: Spec(
        "walking.foot_friction_coefficient",
        Applies.WALK,
        "kN",
        "every phase: the travel force (both travel rods) above the friction capacity of the "
        "standing legs (coefficient times their measured force)",
    ),
    Interlock.WALK_RESUME: Spec(
        "walking.resume_height_tolerance_mm",
        Applies.WALK,
        "",
        "resume of a stopped walk (unhold, or the end of a suspension): a leg or upper "
        "cylinder moved more than the tolerance, a travel rod more than its coasting allowance "
        "(`walking.travel_speed_mm_s` times `safety.command_timeout_ms`, plus the tolerance), "
        "or (after a hold) a leg's force changed more than "
        "`walking.resume_force_tolerance_percent` of its share, since the stop: the unhold "
        "refused (after a suspension: stop, latched); "
        "`wara ctl stop` and a new walk re-plan from the measured state",
    ),
    Interlock.RELEASE: Spec(
        "cycle.release_max_travel_mm",
        Applies.RELEASE,
        "mm",
        "the upper platform lowered the limit with an upper cylinder's load pressure still "
        "more than `cycle.platform_pressure_tolerance_mpa` from its empty-platform value "
        "(the part's weight still on the platform: the bolts not holding, or the part not "
        "fixed); where: that cylinder, its pressure and the empty one in the detail",
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


# --------------------------------------------------------------------------- the checks


@dataclass(frozen=True)
class Limits:
    """The interlock limits of a project in SI units, and the cylinders they watch
    (``active``: can_index of the attitude cylinders, lower then upper)."""

    active: tuple[int, ...]
    #: cylinder id by can_index
    ids: tuple[str, ...]
    #: stroke by can_index [m]
    stroke_m: tuple[float, ...]
    max_twist_m: float
    max_sync_m: float
    max_tracking_m: float
    max_pressure_pa: float
    end_margin_m: float
    sensor_timeout_s: float
    #: the configured figures for the causes' ``limit`` (config units)
    sensor_timeout_ms: float
    plc_heartbeat_timeout_ms: float

    @classmethod
    def from_config(cls, cfg: ProjectConfig, active: Sequence[int]) -> Limits:
        s = cfg.safety
        cyl = cfg.cylinders_by_can_index
        return cls(
            active=tuple(active),
            ids=tuple(c.id for c in cyl),
            stroke_m=tuple(c.stroke_m for c in cyl),
            max_twist_m=units.mm(s.max_twist_mm),
            max_sync_m=units.mm(s.max_sync_error_mm),
            max_tracking_m=units.mm(s.max_tracking_error_mm),
            max_pressure_pa=units.mpa(s.max_pressure_mpa),
            end_margin_m=units.mm(s.stroke_end_margin_mm),
            sensor_timeout_s=units.ms(s.sensor_timeout_ms),
            sensor_timeout_ms=s.sensor_timeout_ms,
            plc_heartbeat_timeout_ms=s.plc_heartbeat_timeout_ms,
        )


class Metrics(Protocol):
    """A layer's figures of the last controller update (m)."""

    @property
    def sync_error_m(self) -> float: ...
    @property
    def twist_m(self) -> float: ...
    @property
    def tracking_error_m(self) -> float: ...


def present_causes(inp: MachineInputs, lim: Limits) -> list[Cause]:
    """The conditions checked in every mode (:attr:`Applies.ALWAYS`) present now: each
    latches a fault (after start-up) and blocks a reset."""
    out: list[Cause] = []
    status = inp.status
    if status is None or not inp.bus_ok:
        age = inp.status_age_s
        out.append(
            Cause(
                Interlock.PLC_HEARTBEAT,
                detail="PLC status lost" if status is None else "bus off or down",
            )
            if math.isinf(age)
            else Cause(
                Interlock.PLC_HEARTBEAT,
                value=units.to_ms(age),
                limit=lim.plc_heartbeat_timeout_ms,
                detail="since the last PLC status" if status is None else "bus off or down",
            )
        )
    if not inp.positions_valid:
        out.extend(position_causes(inp, lim))
    if status is not None and status.fault not in (Fault.NONE, Fault.ESTOP):
        name = (
            Fault(status.fault).name
            if status.fault in Fault._value2member_map_
            else str(status.fault)
        )
        out.append(Cause(Interlock.PLC_FAULT, where=name))
    # The largest valid pressure (NaN where not valid, so fmax skips them; NaN when
    # none is), against the limit (positive, so the zeros for invalid values below
    # never matter).
    p = inp.pressures.value
    if float(np.fmax.reduce(p, axis=None)) > lim.max_pressure_pa:
        pv = np.where(inp.pressures.valid, p, 0.0)  # rare: then find whose it is
        i = int(np.argmax(pv.max(axis=1)))
        peak = float(pv[i].max())
        out.append(
            Cause(
                Interlock.PRESSURE,
                where=lim.ids[i],
                value=units.to_mpa(peak),
                limit=units.to_mpa(lim.max_pressure_pa),
            )
        )
    return out


def position_causes(inp: MachineInputs, lim: Limits) -> list[Cause]:
    """Rare path (an active position not valid): a sensor reporting a fault, or the
    first active cylinder whose position is older than ``safety.sensor_timeout_ms``."""
    out: list[Cause] = []
    failed = inp.failed_sensors
    for i in lim.active:
        if i in failed:
            out.append(Cause(Interlock.SENSOR, where=lim.ids[i]))
    pos = inp.positions
    ages = pos.age_s.tolist()
    for i in lim.active:
        age = ages[i]
        if i not in failed and not pos.valid[i] and age > lim.sensor_timeout_s:
            out.append(
                Cause(
                    Interlock.SENSOR_TIMEOUT,
                    where=lim.ids[i],
                    value=None if math.isinf(age) else units.to_ms(age),
                    limit=lim.sensor_timeout_ms,
                    detail="never received" if math.isinf(age) else "",
                )
            )
            break
    return out


def link_losses(inp: MachineInputs) -> list[str]:
    """Why the link counts as dropped out now (empty: fresh): what suspends a motion."""
    out: list[str] = []
    if not inp.positions_valid:
        out.append("rod positions of the active group stale")
    status = inp.status
    if status is None or inp.status_stale:
        out.append("PLC status stale")
    elif status.command_timeout:
        out.append("the PLC reports the IPC's commands stale")
    return out


def motion_causes(inp: MachineInputs, metrics: Mapping[str, Metrics], lim: Limits) -> list[Cause]:
    """The checks of a driven motion (:attr:`Applies.DRIVEN`; the caller runs them in
    the valve modes with valid positions): each layer's twist, tracking and sync error
    (the controller's last figures), then the first active rod within the margin of an
    end of its stroke or at a limit switch."""
    out: list[Cause] = []
    for name, m in metrics.items():
        if m.twist_m > lim.max_twist_m:
            out.append(_over(Interlock.TWIST, name, m.twist_m, lim.max_twist_m))
        if m.tracking_error_m > lim.max_tracking_m:
            out.append(
                _over(Interlock.TRACKING_ERROR, name, m.tracking_error_m, lim.max_tracking_m)
            )
        if m.sync_error_m > lim.max_sync_m:
            out.append(_over(Interlock.SYNC_ERROR, name, m.sync_error_m, lim.max_sync_m))
    at_limit = inp.at_limit
    xs = inp.positions.value.tolist()
    lo = lim.end_margin_m
    stroke = lim.stroke_m
    for k, i in enumerate(lim.active):
        v = xs[i]
        if v < lo or v > stroke[i] - lo or (at_limit is not None and at_limit[k]):
            to_end = min(v, stroke[i] - v)
            out.append(
                Cause(
                    Interlock.STROKE_END,
                    where=lim.ids[i],
                    value=units.to_mm(to_end),
                    limit=units.to_mm(lo),
                    detail="(limit switch)" if to_end >= lo else "",
                )
            )
            break
    return out


def resume_cause(inp: MachineInputs, stop_ref: Sequence[float] | None, lim: Limits) -> Cause | None:
    """Before a suspended motion resumes: every active rod within the sync band of where
    it stopped (``stop_ref`` by can_index), its pressures valid; else the cause."""
    xs = inp.positions.value.tolist()
    refs = stop_ref if stop_ref is not None else xs
    band = lim.max_sync_m
    for i in lim.active:
        dev = abs(xs[i] - refs[i])
        if not dev <= band:  # NaN too
            return Cause(
                Interlock.RESUME_CHECK,
                where=lim.ids[i],
                value=units.to_mm(dev),
                limit=units.to_mm(band),
                detail="from where the motion stopped",
            )
    if not bool(inp.pressures.valid[list(lim.active)].all()):
        return Cause(Interlock.RESUME_CHECK, where="pressures", detail="not valid")
    return None


class ReleaseFigures(Protocol):
    """What the release check reads of the release (:mod:`ipc_app.control.release`)."""

    @property
    def max_travel_m(self) -> float: ...
    @property
    def upper(self) -> list[int]: ...
    @property
    def figures(self) -> Any: ...


def release_cause(release: ReleaseFigures, ids: Sequence[str]) -> Cause:
    """The ``release`` interlock's cause: lowered the whole travel with the load on (the
    worst cylinder, its load pressure against the empty platform's)."""
    fig = release.figures
    k = fig.worst
    return Cause(
        Interlock.RELEASE,
        where=ids[release.upper[k]],
        value=units.to_mm(fig.travel_m),
        limit=units.to_mm(release.max_travel_m),
        detail=(
            f"lowered with its load pressure {units.to_mpa(fig.load_pressure_pa[k]):.2f} MPa, "
            f"the empty platform's {units.to_mpa(fig.empty_pressure_pa[k]):.2f} MPa: "
            "the part's weight still on the platform"
        ),
    )


def _over(il: Interlock, where: str, value_m: float, limit_m: float) -> Cause:
    return Cause(il, where=where, value=units.to_mm(value_m), limit=units.to_mm(limit_m))
