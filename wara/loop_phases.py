"""Where the loop's time goes in a run: its figures per phase and each overrun, from the
service's run record and its loop reports (``wara demo --two-process --rings N``).

What the service keeps, and what is read from it here:

- the run record (``samples.csv``): one row per loop cycle, ``t_s`` the cycle's wake-up
  time. The loop's deadlines lie on the grid ``t_0 + n * period`` and it skips whole
  periods after an overrun, so each row has a grid index (:func:`grid`): its wake-up
  latency is its distance above that grid point, and a step of more than one index from
  a row to the next is an overrun that skipped the periods between (exact while wake-ups
  are less than a period late; a later one reads as a skip);
- the run record's events: ``cycle_phase`` (the ring cycle's phases), ``suspended``,
  ``walk_phase``, ...;
- the loop's reports (:meth:`FixedRateLoop.stats`, every 5 s in the status): compute and
  wake-up latency p50 / p99 / max over their last ``window_cycles`` cycles. Row ``k`` of
  the record is the loop's cycle ``k + 1``, so a report made after ``cycles`` cycles
  covers rows ``cycles - window_cycles`` to ``cycles - 1``.

A phase's compute figures are those of the reports whose whole window lies within that
phase (the worst p99 and max, the median p50; the p99 of the step's own CPU time beside
them, so that what remains is the time the loop's thread waited); a phase shorter than a
window (20.5 s at 200 Hz) gets those of the windows that overlap it, marked ``mixed``. Its overruns,
skipped periods, wake-up latency and suspends are counted from the record itself.

Each overrun is explained by what the record and its window say: when (the phase, the
ring, the events within a second: a walk's phase, a suspension), how late its cycle woke,
the least its step can have taken (``skipped * period - latency``), and its window's
compute and wake-up maxima, from which :func:`_cause` tells a *late wake-up* (the loop's
thread not run in time) from a *long step*.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from config import units

#: A grid point counts as reached this close before it (the record's rounding), periods.
_ROUND = 1e-6
#: The events that tell what the step was doing near an overrun, and how near, s.
CONTEXT_EVENTS = ("cycle_phase", "walk_phase", "walk", "walk_done", "suspended", "resumed")
CONTEXT_S = 1.0


def record_times(run_dir: Path) -> np.ndarray:
    """The ``t_s`` column of a run record's ``samples.csv`` (a half-written last line
    ignored)."""
    ts: list[float] = []
    with open(run_dir / "samples.csv", encoding="utf-8") as f:
        next(f, None)
        for line in f:
            head = line.split(",", 1)[0]
            try:
                ts.append(float(head))
            except ValueError:
                break
    return np.asarray(ts)


def grid(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """Each row's deadline index on the grid ``t_s[0] + n * period``: the last grid point
    at or before it that no earlier row took."""
    out = np.empty(t_s.size, dtype=np.int64)
    if t_s.size == 0:
        return out
    rel = (t_s - t_s[0]) / period_s
    n_prev = -1
    for i, r in enumerate(rel.tolist()):
        n = max(n_prev + 1, math.floor(r + _ROUND))
        if n > r + _ROUND:  # never after its own wake-up: a rounding of the record
            n = n_prev + 1
        out[i] = n
        n_prev = n
    return out


def latency_ms(t_s: np.ndarray, period_s: float) -> np.ndarray:
    """Each cycle's wake-up latency (ms) above its deadline on the grid."""
    if t_s.size == 0:
        return np.zeros(0)
    n = grid(t_s, period_s)
    rel = (t_s - t_s[0]) / period_s
    return np.maximum(rel - n, 0.0) * units.to_ms(period_s)


@dataclass(frozen=True)
class Span:
    """A stretch of the run: ``phase`` of ring ``ring`` (0: none), ``t0 <= t < t1``."""

    phase: str
    ring: int
    t0: float
    t1: float


def spans(
    events: Sequence[Mapping[str, Any]], t_first: float, t_end: float, t_up: float
) -> list[Span]:
    """The run cut at its ring phases (``cycle_phase``, ``cycle_end`` events): ``start-up``
    to ``t_up`` (the loop's baseline report), ``idle`` to the first phase and between
    rings, each ring's phases, ``idle`` after the last."""
    out: list[Span] = []
    cur, ring, since = "idle", 0, t_up
    if t_up > t_first:
        out.append(Span("start-up", 0, t_first, t_up))
    for ev in events:
        kind = ev.get("kind")
        if kind not in ("cycle_phase", "cycle_end"):
            continue
        t = max(float(ev["t_s"]), since)
        if t > since:
            out.append(Span(cur, ring, since, t))
        since = t
        if kind == "cycle_phase":
            cur, ring = str(ev["phase"]), int(ev["ring"])
        else:
            cur, ring = "idle", 0
    if t_end > since:
        out.append(Span(cur, ring, since, t_end))
    return out


@dataclass(frozen=True)
class Overrun:
    """One overrun of the loop, found in the record; see the module docstring."""

    t_s: float
    ring: int
    phase: str
    skipped_periods: int
    latency_ms: float
    step_at_least_ms: float
    window_compute_max_ms: float | None
    window_latency_max_ms: float | None
    cause: str
    near: str

    def line(self, t0: float) -> str:
        where = f"ring {self.ring} {self.phase}" if self.ring else self.phase
        win = (
            "no report covers it"
            if self.window_compute_max_ms is None
            else f"its window's compute max {self.window_compute_max_ms:.1f} ms, wake-up "
            f"max {self.window_latency_max_ms:.1f} ms"
        )
        return (
            f"t={self.t_s - t0:8.2f} s {where}: {self.skipped_periods} period(s) skipped, "
            f"woke {self.latency_ms:.2f} ms late, step >= {self.step_at_least_ms:.1f} ms; "
            f"{win}: {self.cause}" + (f" ({self.near})" if self.near else "")
        )


def _cause(
    step_min_ms: float, around: Sequence[Mapping[str, Any]], period_ms: float
) -> tuple[str, float | None, float | None]:
    """Why a cycle overran, from the reports whose windows hold it: a *late wake-up*
    when an ordinary step (the window's compute p99) would have overrun after it, or no
    step of the window was that long and a wake-up was a period late (the next cycle's,
    read as this one's skip); a *long step* when a step of the window took at least
    ``step_min_ms``; *either* when both could. Also the windows' compute and wake-up
    maxima."""
    if not around:
        return "either (no report covers it)", None, None
    p99 = max(float(r["compute_p99_ms"]) for r in around)
    comp = max(float(r["compute_max_ms"]) for r in around)
    late = max(float(r["jitter_max_ms"]) for r in around)
    if step_min_ms <= p99:
        cause = "late wake-up"
    elif comp >= step_min_ms - 1e-6:
        cause = "either" if late >= period_ms else "long step"
    else:
        cause = "late wake-up" if late >= period_ms else "either"
    return cause, comp, late


def _near(events: Sequence[Mapping[str, Any]], t: float) -> str:
    """The events of :data:`CONTEXT_EVENTS` within :data:`CONTEXT_S` of ``t``."""
    out = []
    for ev in events:
        kind = ev.get("kind")
        dt = float(ev.get("t_s", math.inf)) - t
        if kind in CONTEXT_EVENTS and abs(dt) <= CONTEXT_S:
            what = kind
            if kind == "walk_phase":
                what = f"walk_phase {ev.get('step')}.{ev.get('phase')} {ev.get('name', '')}".strip()
            elif kind == "cycle_phase":
                what = f"cycle_phase {ev.get('phase')}"
            out.append(f"{dt:+.2f} s {what}")
    return "; ".join(out)


def _windows(
    reports: Iterable[Mapping[str, Any]], rows: int
) -> list[tuple[int, int, dict[str, Any]]]:
    """Each report's window as rows ``[a, b)`` of the record (clipped to it)."""
    out = []
    for r in reports:
        b = min(int(r["cycles"]), rows)
        a = max(b - int(r.get("window_cycles", 0)), 0)
        if b > a:
            out.append((a, b, dict(r)))
    return out


def phase_figures(
    t_s: np.ndarray,
    events: Sequence[Mapping[str, Any]],
    reports: Sequence[Mapping[str, Any]],
    period_s: float,
    baseline_cycles: int,
) -> dict[str, Any]:
    """The loop's figures per phase of the run and its overruns (module docstring).

    ``t_s``: the record's wake-up times; ``reports``: the loop's reports (``cycles``,
    ``window_cycles``, ``compute_*_ms``, ``jitter_max_ms``); ``baseline_cycles``: the
    cycles of the report that ends start-up. Returns ``phases`` (one object per phase
    name, in order of first appearance), ``overruns`` (one per overrun after start-up),
    ``by_cause`` and ``start_up_overruns``."""
    period_ms = units.to_ms(period_s)
    rows = int(t_s.size)
    if rows < 2:
        return {"phases": [], "overruns": [], "by_cause": {}, "start_up_overruns": 0}
    n = grid(t_s, period_s)
    lat = latency_ms(t_s, period_s)
    skips = np.diff(n) - 1  # skips[i]: periods skipped after row i
    t_up = float(t_s[min(max(baseline_cycles, 1), rows) - 1])
    cut = spans(events, float(t_s[0]), float(t_s[-1]) + period_s, t_up)
    windows = _windows(reports, rows)
    win_t = [(float(t_s[a]), float(t_s[b - 1]), r) for a, b, r in windows]
    idx = np.searchsorted(t_s, [s.t0 for s in cut], side="left")
    ends = np.searchsorted(t_s, [s.t1 for s in cut], side="left")
    order: list[str] = []
    acc: dict[str, dict[str, Any]] = {}
    overruns: list[Overrun] = []
    start_up_overruns = 0
    for span, a, b in zip(cut, idx.tolist(), ends.tolist(), strict=True):
        if span.phase not in acc:
            order.append(span.phase)
            acc[span.phase] = {
                "spans": 0,
                "duration_s": 0.0,
                "cycles": 0,
                "overruns": 0,
                "skipped_periods": 0,
                "suspends": 0,
                "lat": [],
                "inside": [],
                "overlap": [],
            }
        f = acc[span.phase]
        f["spans"] += 1
        f["duration_s"] += span.t1 - span.t0
        f["cycles"] += b - a
        f["lat"].append(lat[a:b])
        f["suspends"] += sum(
            1
            for ev in events
            if ev.get("kind") == "suspended" and span.t0 <= float(ev["t_s"]) < span.t1
        )
        for w0, w1, r in win_t:
            if span.t0 <= w0 and w1 < span.t1:
                f["inside"].append(r)
            elif w0 < span.t1 and w1 >= span.t0:
                f["overlap"].append(r)
        for i in range(a, min(b, rows - 1)):
            s = int(skips[i])
            if s <= 0:
                continue
            f["overruns"] += 1
            f["skipped_periods"] += s
            if span.phase == "start-up":
                start_up_overruns += 1
                continue
            step_min = s * period_ms - float(lat[i])
            around = [r for a_, b_, r in windows if a_ <= i < b_]
            cause, comp, late = _cause(step_min, around, period_ms)
            overruns.append(
                Overrun(
                    t_s=float(t_s[i]),
                    ring=span.ring,
                    phase=span.phase,
                    skipped_periods=s,
                    latency_ms=round(float(lat[i]), 3),
                    step_at_least_ms=round(step_min, 3),
                    window_compute_max_ms=comp,
                    window_latency_max_ms=late,
                    cause=cause,
                    near=_near(events, float(t_s[i])),
                )
            )
    phases = []
    for name in order:
        f = acc[name]
        lats = np.concatenate(f["lat"]) if f["lat"] else np.zeros(0)
        reps, mixed = (f["inside"], False) if f["inside"] else (f["overlap"], True)

        def worst(key: str, reps: list[dict[str, Any]] = reps) -> float | None:
            vals = [float(r[key]) for r in reps if r.get(key) is not None]
            return max(vals) if vals else None

        p50s = [float(r["compute_p50_ms"]) for r in reps if r.get("compute_p50_ms") is not None]
        phases.append(
            {
                "phase": name,
                "spans": f["spans"],
                "duration_s": round(f["duration_s"], 3),
                "cycles": f["cycles"],
                "compute_p50_ms": float(np.median(p50s)) if p50s else None,
                "compute_p99_ms": worst("compute_p99_ms"),
                "compute_max_ms": worst("compute_max_ms"),
                "compute_cpu_p99_ms": worst("compute_cpu_p99_ms"),
                "compute_windows": len(reps),
                "compute_mixed": mixed and bool(reps),
                "latency_p99_ms": float(np.percentile(lats, 99)) if lats.size else None,
                "latency_max_ms": float(lats.max()) if lats.size else None,
                "overruns": f["overruns"],
                "skipped_periods": f["skipped_periods"],
                "suspends": f["suspends"],
            }
        )
    by_cause: dict[str, int] = {}
    for o in overruns:
        by_cause[o.cause] = by_cause.get(o.cause, 0) + 1
    return {
        "phases": phases,
        "overruns": [asdict(o) | {"line": o.line(float(t_s[0]))} for o in overruns],
        "by_cause": by_cause,
        "start_up_overruns": start_up_overruns,
    }


def render_phases(fig: Mapping[str, Any], period_ms: float) -> list[str]:
    """The per-phase table and the overruns, as lines of text."""

    def ms(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.2f}"

    head = (
        "| phase | s | cycles | compute p50 / p99 / max ms | p99 % of period | its CPU p99 ms "
        "| wake-up p99 / max ms | overruns (skipped) | suspends |"
    )
    lines = [head, "|---|---|---|---|---|---|---|---|---|"]
    for p in fig.get("phases", []):
        p99 = p["compute_p99_ms"]
        pct = "n/a" if p99 is None else f"{100 * p99 / period_ms:.1f}"
        mark = " (mixed)" if p["compute_mixed"] else ""
        lines.append(
            f"| {p['phase']} | {p['duration_s']:.1f} | {p['cycles']} | "
            f"{ms(p['compute_p50_ms'])} / {ms(p99)} / {ms(p['compute_max_ms'])}{mark} | {pct} | "
            f"{ms(p.get('compute_cpu_p99_ms'))} | "
            f"{ms(p['latency_p99_ms'])} / {ms(p['latency_max_ms'])} | "
            f"{p['overruns']} ({p['skipped_periods']}) | {p['suspends']} |"
        )
    over = fig.get("overruns", [])
    causes = ", ".join(f"{k} {v}" for k, v in sorted(fig.get("by_cause", {}).items()))
    lines.append(
        f"overruns after start-up: {len(over)}"
        + (f" ({causes})" if causes else "")
        + f"; in start-up {fig.get('start_up_overruns', 0)}"
    )
    lines += [f"  {o['line']}" for o in over]
    return lines
