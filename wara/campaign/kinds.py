"""The two kinds of campaign (``kind`` in the spec, docs/campaigns.md).

**nominal**: what differs within the machine's specification. Its events are only those
a healthy machine shows, each bounded by what the project itself allows
(:data:`NOMINAL_BOUNDS`, checked at load by :func:`check_nominal`); a run passes when it
meets its goals.

**fault**: the faults. A run is judged on the reaction (:func:`judge_fault`): it rides
the fault through and completes within its goals, or it ends in the safe state with a
cause the faults that happened in it may latch (:data:`FAULT_CAUSES`), except that a
link loss no longer than :func:`ride_through_ms` must be ridden through.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from config.schema import ProjectConfig
from ipc_app.service.interlocks import Interlock as I

#: The events a nominal campaign may draw; any other event kind is a fault.
NOMINAL_EVENTS = ("delay", "drop", "plc_stall", "ground")

#: The link losses the service rides through (SUSPENDED) up to :func:`ride_through_ms`.
RIDE_THROUGH = frozenset({"plc_stall", "wire_stall", "plc_silent"})

#: The frames a link loss silences whose age the always-checked interlocks judge: the
#: PLC's status (``safety.plc_heartbeat_timeout_ms``) and the rod positions
#: (``safety.sensor_timeout_ms``).
_WATCHED_FRAMES = ("PLC_Status", "PLC_RodPos_0")


def ride_through_ms(project: ProjectConfig) -> float:
    """The longest link loss the service owes a ride-through, ms: at most
    ``safety.max_suspend_ms``, and short enough that the last frame before it (up to one
    frame cycle old) plus the loss stay within the heartbeat and the sensor timeout,
    which latch in every mode (SUSPENDED too)."""
    from plc_bridge.catalog import load_catalog

    catalog, period_s = load_catalog(), project.control.period_s
    cycle_ms = 1e3 * max(
        catalog.by_name(f).cycle_in_force_s(True, period_s) for f in _WATCHED_FRAMES
    )
    s = project.safety
    return min(
        s.max_suspend_ms,
        s.plc_heartbeat_timeout_ms - cycle_ms,
        s.sensor_timeout_ms - cycle_ms,
    )


_LINK = frozenset(
    {
        I.PLC_HEARTBEAT,
        I.SENSOR_TIMEOUT,
        I.SUSPEND_TIMEOUT,
        I.RESUME_CHECK,
        I.WALK_RESUME,
        I.STARTUP,
    }
)
_MOTION = frozenset({I.TRACKING_ERROR, I.SYNC_ERROR, I.TWIST, I.SYNC_BAND, I.STROKE_END})
#: Event kind -> the causes its safe state may latch (the first latched cause is judged).
FAULT_CAUSES: dict[str, frozenset[I]] = {
    "plc_stall": _LINK,
    "wire_stall": _LINK,
    "plc_silent": _LINK,
    "bus_off": _LINK,
    "drop": _LINK,
    "delay": _LINK,
    "bad_crc": _LINK,
    "frozen_counter": _LINK,
    "ignore_commands": _MOTION,
    "stuck_valve": _MOTION,
    # a transducer stuck, jumped or noisy sends valid frames: the loops' errors see it
    "sensor": frozenset({I.SENSOR, I.SENSOR_TIMEOUT}) | _MOTION,
    "leakage": _MOTION | {I.OVERLOAD},
    "holding_valve_leak": _MOTION | {I.OVERLOAD, I.TOUCHDOWN, I.TRANSFER},
    "load_step": _MOTION | {I.OVERLOAD, I.PRESSURE},
    "ground": frozenset({I.TOUCHDOWN, I.TRANSFER, I.OVERLOAD, I.STABILITY, I.SYNC_BAND}),
    "foot_slip": frozenset({I.SLIP, I.SYNC_BAND, I.TRANSFER}),
    "estop": frozenset({I.PLC_FAULT}),
}


@dataclass(frozen=True)
class Bound:
    """A nominal event's key (in ``event`` or drawn in ``fields``; ``duration_s``: its
    drawn duration), its largest value within the specification read from the project,
    and why."""

    key: str
    largest: Callable[[ProjectConfig], float]
    why: str


#: Event kind -> the bounds of its keys in a nominal campaign. A key a bound names must
#: be given (a drop's ``max_burst``, a stall's ``duration_s``).
NOMINAL_BOUNDS: dict[str, tuple[Bound, ...]] = {
    "delay": (
        Bound(
            "delay_ms",
            lambda p: p.control.delay_margin_ms,
            "control.delay_margin_ms, the extra measurement delay every loop is designed for",
        ),
    ),
    "drop": (
        Bound(
            "rate",
            lambda p: 0.01,
            "isolated losses of a healthy bus (CAN repeats a corrupted frame; a frame is "
            "lost only to a receiver's overrun)",
        ),
        Bound(
            "max_burst",
            lambda p: p.can.max_delta_counter - 1,
            "can.max_delta_counter - 1, the lost frames in a row the E2E check accepts",
        ),
    ),
    "plc_stall": (
        Bound(
            "duration_s",
            lambda p: p.can.stale_cycles * p.control.period_s,
            "can.stale_cycles loop periods: a scan late by less leaves no frame stale",
        ),
    ),
    "ground": (),
}


def _largest(dist: Any) -> float:
    """The largest value a :class:`~wara.campaign.spec.Distribution` draws (inf when
    unbounded)."""
    top = {
        "uniform": dist.high,
        "triangular": dist.high,
        "choice": max(dist.values, default=math.inf),
    }.get(dist.dist, math.inf)
    return min(top, math.inf if dist.max is None else dist.max)


def check_nominal(events: Any, project: ProjectConfig) -> None:
    """A nominal campaign's ``events`` within the specification of ``project``
    (ValueError naming the event, its key, the largest value allowed and why)."""
    for j, ev in enumerate(events):
        kind = ev.event["kind"]
        where = f"events[{j}] ({kind})"
        if kind not in NOMINAL_BOUNDS:
            raise ValueError(
                f"{where}: a fault, not a dispersion within the specification "
                f"(a nominal campaign draws {', '.join(NOMINAL_EVENTS)}): put it in a "
                "campaign of kind: fault"
            )
        for b in NOMINAL_BOUNDS[kind]:
            if b.key == "duration_s":
                top = math.nan if ev.duration_s is None else _largest(ev.duration_s)
            elif b.key in ev.fields:
                top = _largest(ev.fields[b.key])
            else:
                top = float(ev.event.get(b.key, math.nan))
            limit = b.largest(project)
            if not top <= limit + 1e-12:
                shown = (
                    "not given"
                    if math.isnan(top)
                    else "unbounded (give its distribution a max)"
                    if math.isinf(top)
                    else f"up to {top:g}"
                )
                raise ValueError(
                    f"{where}: {b.key} {shown}; within the specification at most {limit:g} "
                    f"({b.why}); a larger one belongs in a campaign of kind: fault"
                )


@dataclass(frozen=True)
class Verdict:
    """A run's verdict: passed, its status (the row's ``status``), why."""

    passed: bool
    status: str
    note: str


def judge_nominal(done: bool, over: list[str]) -> Verdict:
    """A nominal campaign's run: completed (``done``) within its goals (``over``: the
    goals it missed)."""
    if done:
        return Verdict(not over, "over_limit" if over else "passed", "; ".join(over))
    return Verdict(False, "not_finished", "")


def judge_fault(
    happened: list[tuple[str, float]],
    done: bool,
    over: list[str],
    interlocks: list[str],
    ride_through_ms: float,
) -> Verdict:
    """A fault campaign's run: ``happened`` the (kind, duration s; NaN: to the end) of
    its events that happened, ``done`` whether the motion completed, ``over`` the goals
    it missed, ``interlocks`` the latched causes in order (:class:`Interlock` values)."""
    if done and not over and happened:
        return Verdict(True, "ridden_through", "")
    if done or not interlocks:
        return judge_nominal(done, over)
    cause = I(interlocks[0])
    allowed = frozenset().union(*(FAULT_CAUSES.get(k, frozenset()) for k, _ in happened))
    if cause not in allowed:
        kinds = ", ".join(k for k, _ in happened) or "no fault"
        return Verdict(False, "wrong_cause", f"{cause} latched after {kinds}")
    short = [
        (k, d)
        for k, d in happened
        if k in RIDE_THROUGH and math.isfinite(d) and d * 1e3 <= ride_through_ms
    ]
    if len(short) == len(happened):
        k, d = short[0]
        return Verdict(
            False,
            "not_ridden_through",
            f"a {k} of {d * 1e3:.0f} ms (within the ride-through's {ride_through_ms:g} ms) "
            f"ended in the safe state: {cause}",
        )
    return Verdict(True, "safe_state", f"{cause}")
