"""The figures the docs and the README cite, one producer each (``wara bench figures``).

A producer is one row of :data:`PRODUCERS`: its name (the heading and anchor of its
section in docs/figures.md, and ``--only NAME``), the subsystem it belongs to, the
``wara`` commands that measure it (full form, and the short form of ``--quick``), and
a function that reads those commands' JSON and returns the figures. A new figure is a
new row and, where no producer reads its command yet, a reader here: ``templated(...)``
rows of templates on the command's JSON (``"{lockstep.realtime_factor_cpu:.1f}x"``), or a
small function where a figure is worked out from several values.

The commands run as a user types them (``sys.executable -m wara``), each in a fresh
interpreter and a temporary directory: the figures are the commands' own, not a
re-implementation of them.
"""

from __future__ import annotations

import re
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

# --------------------------------------------------------------------------- data


@dataclass(frozen=True)
class Figure:
    """One row of a section: what, the value as text, the goal where there is one."""

    name: str
    value: str
    goal: str = ""


@dataclass(frozen=True)
class Output:
    """What one command gave: its JSON (None when it printed none), exit code, wall time."""

    command: str
    data: Any
    exit_code: int
    wall_s: float
    stderr_tail: str = ""


@dataclass(frozen=True)
class Measured:
    """A producer's result: its figures, and the one line the README's table shows
    (empty: not in the README)."""

    figures: tuple[Figure, ...]
    headline: str = ""


Extract = Callable[[Sequence[Output]], Measured]


@dataclass(frozen=True)
class Producer:
    name: str
    section: str
    title: str
    commands: tuple[str, ...]
    extract: Extract
    #: the short form (``--quick``); empty: the full form is already short
    quick: tuple[str, ...] = ()
    #: on the wall clock: measured only with ``--realtime`` (or named by ``--only``)
    realtime: bool = False
    #: the README's row label; empty: not a headline figure
    headline: str = ""

    def commands_for(self, quick: bool) -> tuple[str, ...]:
        return self.quick if quick and self.quick else self.commands


# --------------------------------------------------------------------------- formatting


def get(data: Any, path: str) -> Any:
    """``data["a"]["b"][0]`` for ``"a.b.0"``; None where any step is missing."""
    cur = data
    for part in path.split("."):
        if isinstance(cur, dict):
            cur = cur.get(part)
        elif isinstance(cur, list) and part.isdigit() and int(part) < len(cur):
            cur = cur[int(part)]
        else:
            return None
        if cur is None:
            return None
    return cur


def _is_num(x: Any) -> bool:
    return isinstance(x, int | float) and not isinstance(x, bool)


def num(x: Any, spec: str = ".3g", unit: str = "") -> str:
    """``x`` formatted by ``spec``, with its unit; ``n/a`` for None or a non-number."""
    if not _is_num(x):
        return "n/a"
    return f"{x:{spec}}" + (f" {unit}" if unit else "")


_FIELD = re.compile(r"\{([A-Za-z0-9_.]+)(?::([^}]*))?\}")


def t(data: Any, template: str) -> str:
    """``template`` with each ``{path:spec}`` the value at ``path`` in ``data`` (a number
    formatted by ``spec``, anything else as text, ``n/a`` when missing)."""

    def field(m: re.Match[str]) -> str:
        value = get(data, m.group(1))
        if _is_num(value):
            return num(value, m.group(2) or "g")
        if isinstance(value, list | tuple):
            return ", ".join(map(str, value)) or "none"
        if isinstance(value, dict):
            return ", ".join(f"{k} {v}" for k, v in value.items()) or "none"
        return "n/a" if value is None else str(value)

    return _FIELD.sub(field, template)


def span(xs: Sequence[Any], spec: str = ".3g", unit: str = "") -> str:
    """``lo-hi unit`` of the numbers in ``xs`` (one value when they agree)."""
    vals = [x for x in xs if _is_num(x)]
    if not vals:
        return "n/a"
    lo, hi = num(min(vals), spec), num(max(vals), spec)
    text = lo if lo == hi else f"{lo} to {hi}" if min(vals) < 0 else f"{lo}-{hi}"
    return text + (f" {unit}" if unit else "")


def mmss(seconds: Any) -> str:
    if not _is_num(seconds):
        return "n/a"
    m, s = divmod(round(seconds), 60)
    return f"{m} min {s:02d} s" if m else f"{s} s"


def passed(ok: Any, yes: str = "met", no: str = "NOT met") -> str:
    return {True: yes, False: no}.get(ok, "n/a")


def _largest(rows: Sequence[Any], key: str, smallest: bool = False) -> Any:
    vals: list[float] = [r[key] for r in rows if isinstance(r, dict) and _is_num(r.get(key))]
    return (min if smallest else max)(vals) if vals else None


def _count(rows: Sequence[Any]) -> str:
    return f"{sum(bool(r.get('passed')) for r in rows)} of {len(rows)}"


def _percent(d: Any, fraction_path: str) -> Any:
    x = get(d, fraction_path)
    return 100 * x if _is_num(x) else None


# --------------------------------------------------------------------------- producers


def templated(*rows: tuple[str, str, str], headline: str = "") -> Extract:
    """A producer whose figures are templates on its first command's JSON: rows of
    (what, value, goal), each a :func:`t` template."""

    def extract(outs: Sequence[Output]) -> Measured:
        d = outs[0].data
        figs = tuple(Figure(t(d, name), t(d, value), t(d, goal)) for name, value, goal in rows)
        return Measured(figs, t(d, headline))

    return extract


_T4 = (
    "vertical_misalignment_mm",
    "horizontal_misalignment_mm",
    "max_gap_mm",
    "centreline_deviation_x_mm",
    "centreline_deviation_y_mm",
)


def _off(r: Any, keys: tuple[str, ...]) -> Any:
    e = get(r, "error_from_target") or {}
    vals = [abs(e[k]) for k in keys if _is_num(e.get(k))]
    return max(vals) if vals else None


def _less_hold(rings: Sequence[Any]) -> list[Any]:
    """Each ring's machine time less the fixing hold (``cycle_time_s`` leaves it out)."""
    return [r.get("cycle_time_s") for r in rings]


def _table4(rings: Sequence[Any]) -> list[Figure]:
    """Each ring's Table 4 items on the simulator's truth, one figure a ring."""
    return [
        Figure(
            f"ring {r.get('ring')}: vertical / horizontal / gap / centreline x / y (truth)",
            " / ".join(num(r.get(k), ".3f" if k == "max_gap_mm" else "+.3f") for k in _T4) + " mm",
            "8 / 8 / 0-10 / 5 / 5 mm",
        )
        for r in rings
    ]


def demo(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    rings = get(d, "rings") or []
    figs = [Figure("rings passed", _count(rings), "all")]
    figs += _table4(rings)
    pos = [_off(r, ("x_mm", "y_mm", "z_mm")) for r in rings]
    ang = [_off(r, ("roll_deg", "pitch_deg", "yaw_deg")) for r in rings]
    walks = [w for r in rings for w in get(r, "walks.walk") or []]
    backs = [w for r in rings for w in get(r, "walks.walk_back") or []]
    ratios = [w.get("max_leg_force_ratio") for w in walks]
    back_ratios = [w.get("max_leg_force_ratio") for w in backs]
    corr = get(d, "steering.correction_per_ring_mm") or []
    last = " / ".join(num(x, "+.2f") for x in get(d, "steering.last_as_built_deviation_mm") or [])
    figs += [
        Figure("off target, largest position error", span(pos, ".3f", "mm"), "1 mm"),
        Figure("off target, largest angle error", span(ang, ".4f", "deg"), "0.01 deg"),
        Figure(
            "a ring less the fixing hold (machine time)",
            span(_less_hold(rings), ".1f", "s"),
            "15 min",
        ),
        Figure("largest leg force / share, walks there (loaded)", span(ratios, ".3f"), "1.10"),
        Figure(
            "largest leg force / share, walks back (unloaded)", span(back_ratios, ".3f"), "1.10"
        ),
        Figure("correction per ring", ", ".join(num(c, ".2f") for c in corr) + " mm", "2 mm"),
        Figure("last ring off the design axis, y / z", f"{last} mm"),
        Figure("wall time", mmss(get(d, "wall_time_s"))),
    ]
    headline = (
        f"{len(rings)} rings, {passed(get(d, 'passed'), 'every goal met', 'FAILED')}; the last "
        f"{last} mm off the design axis; {span(_less_hold(rings), '.0f', 's')} of machine time a "
        f"ring less the fixing hold (goal 15 min); {mmss(get(d, 'wall_time_s'))} of wall time"
    )
    return Measured(tuple(figs), headline)


def _loop_figures(d: Any) -> list[Figure]:
    return [
        Figure("loop cycles", t(d, "{loop.cycles}")),
        Figure(
            "overruns (longest)", t(d, "{loop.overruns} ({loop.worst_overrun_cycle_ms:.1f} ms)")
        ),
        Figure("jitter p99", t(d, "{loop.jitter_p99_ms:.2f} ms")),
        Figure("compute p99", t(d, "{loop.compute_p99_ms:.2f} ms"), "< 1 ms (20 %)"),
        Figure("suspends / resumes", t(d, "{ride_through.suspends} / {ride_through.resumes}")),
    ]


def demo_realtime(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    rings = get(d, "rings") or []
    figs = [
        Figure("rings passed", _count(rings), "all"),
        Figure("a ring less the fixing hold", span(_less_hold(rings), ".1f", "s"), "15 min"),
        Figure("wall time", mmss(get(d, "wall_time_s"))),
        Figure("final mode; latched faults", t(d, "{final_mode}; {fault_reasons}")),
        *_loop_figures(d),
    ]
    headline = f"{passed(get(d, 'passed'), 'every goal met', 'FAILED')}, " + t(
        d,
        "{loop.overruns} of {loop.cycles} cycles over the 5 ms period (longest "
        "{loop.worst_overrun_cycle_ms:.1f} ms)",
    )
    return Measured(tuple(figs), f"{headline}; {mmss(get(d, 'wall_time_s'))} of wall time")


def _examples(d: Any) -> tuple[list[Figure], str]:
    ex = get(d, "examples") or []
    figs = [
        Figure(
            t(
                e,
                "({target_roll_deg:+g}, {target_pitch_deg:+g}) deg: error / twist / sync at "
                "rest / sync moving",
            ),
            t(
                e,
                "{attitude_error_deg:.5f} deg / {max_twist_mm:.4f} / {sync_error_mm:.4f} / "
                "{max_sync_error_mm:.3f} mm",
            ),
            t(
                d,
                "{tolerances.attitude_error_deg} deg / {tolerances.max_twist_mm} / "
                "{tolerances.sync_error_mm} / 2 mm",
            ),
        )
        for e in ex
    ]
    worst = {k: _largest(ex, k) for k in ("attitude_error_deg", "max_twist_mm", "sync_error_mm")}
    headline = (
        f"{passed(get(d, 'passed'), 'every goal met', 'FAILED')}: attitude error <= "
        f"{num(worst['attitude_error_deg'], '.5f')} deg (goal 0.01), twist <= "
        f"{num(worst['max_twist_mm'], '.4f')} mm (0.5), sync at rest <= "
        f"{num(worst['sync_error_mm'], '.4f')} mm (0.07)"
    )
    return figs, headline


def attitude(outs: Sequence[Output]) -> Measured:
    figs, headline = _examples(outs[0].data)
    return Measured(tuple(figs), headline)


def attitude_realtime(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    ex = get(d, "examples") or []
    figs = [Figure("examples passed", _count(ex), "all")]
    figs += _loop_figures(d)
    figs.append(Figure("simulator", t(d, "{simulator_realtime_factor:.1f}x real time")))
    headline = f"{passed(get(d, 'passed'), 'passed', 'FAILED')}; " + t(
        d,
        "{loop.cycles} cycles, jitter p99 {loop.jitter_p99_ms:.2f} ms, compute p99 "
        "{loop.compute_p99_ms:.2f} ms, {loop.overruns} overruns",
    )
    return Measured(tuple(figs), headline)


def demo_repeated(outs: Sequence[Output]) -> Measured:
    figs, parts = [], []
    for o in outs:
        hog = " with a CPU hog" if "--cpu-hog" in o.command else ""
        d = o.data
        figs += [
            Figure(f"passed{hog}", t(d, "{passes} of {runs}"), "all; with the hog 19 of 20"),
            Figure(f"a run's wall time{hog}", t(d, "{wall_s.min:.1f}-{wall_s.max:.1f} s")),
            Figure(f"short losses ridden through{hog}", t(d, "{suspends_total}")),
            Figure(f"why runs failed{hog}", "; ".join(get(d, "failure_reasons") or []) or "none"),
        ]
        parts.append(t(d, "{passes} of {runs} passed") + hog)
    return Measured(tuple(figs), "; ".join(parts))


def two_process(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    ex = get(d, "examples") or []
    pct = num(_percent(d, "loop.compute_p99_fraction"), ".1f")
    figs = [
        Figure("examples passed", _count(ex), "all"),
        Figure(
            "compute p50 / p99",
            t(d, "{loop.compute_p50_ms:.2f} / {loop.compute_p99_ms:.2f} ms") + f" ({pct} %)",
            "p99 < 20 % of 5 ms",
        ),
        Figure("jitter p99 / max", t(d, "{loop.jitter_p99_ms:.2f} / {loop.jitter_max_ms:.1f} ms")),
        Figure(
            "overruns after start-up (in start-up)",
            t(d, "{loop.overruns} ({loop.overruns_startup})"),
            "0 in 60 s",
        ),
        Figure("loop goal", passed(get(d, "loop_goal.passed"))),
        Figure("placement", t(d, "{placement}")),
    ]
    headline = (
        f"examples {_count(ex)} passed; compute p99 {t(d, '{loop.compute_p99_ms:.2f}')} ms "
        f"({pct} % of the period); loop goal {passed(get(d, 'loop_goal.passed'))}"
    )
    return Measured(tuple(figs), headline)


def two_process_cycle(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    rings = get(d, "rings") or []
    pct = num(_percent(d, "loop.compute_p99_fraction"), ".1f")
    figs = [Figure("rings passed", _count(rings), "all")]
    figs += _table4(rings)
    for ph in get(d, "loop_phases.phases") or []:
        if ph.get("phase") in ("walk", "place", "walk_back"):
            figs.append(
                Figure(
                    f"{ph['phase']}: compute p50 / p99 / max (its CPU p99); overruns (skipped)",
                    t(ph, "{compute_p50_ms:.2f} / {compute_p99_ms:.2f} / {compute_max_ms:.1f} ms ")
                    + t(ph, "({compute_cpu_p99_ms:.2f} ms); {overruns} ({skipped_periods})"),
                )
            )
    causes = get(d, "loop_phases.by_cause") or {}
    figs += [
        Figure(
            "compute p99, worst report after start-up",
            t(d, "{loop.compute_p99_ms:.2f} ms") + f" ({pct} %)",
            "< 20 % of the period",
        ),
        Figure(
            "overruns after start-up, by cause",
            ", ".join(f"{k} {v}" for k, v in sorted(causes.items())) or "none",
        ),
        Figure("suspends", t(d, "{ride_through.suspends}")),
        Figure("wall time", mmss(get(d, "wall_time_s"))),
    ]
    headline = (
        f"{_count(rings)} rings passed; compute p99 {t(d, '{loop.compute_p99_ms:.2f}')} ms "
        f"({pct} % of the period); {passed(get(d, 'passed'), 'passed', 'FAILED')}"
    )
    return Measured(tuple(figs), headline)


def soak(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    faults = len(get(d, "latched_faults") or [])
    figs = [
        Figure("minutes; moves", t(d, "{minutes:.0f}; {moves}")),
        Figure("cycles after start-up", t(d, "{cycles}")),
        Figure("overruns (in start-up)", t(d, "{overruns} ({overruns_startup})")),
        Figure("jitter p99.9 / max", t(d, "{jitter_p999_ms:.2f} / {jitter_max_ms:.1f} ms")),
        Figure("suspends / resumes", t(d, "{suspends} / {resumes}")),
        Figure("latched faults", str(faults), "none"),
    ]
    headline = t(
        d,
        "{moves} moves, {cycles} cycles, {overruns} overruns, jitter p99.9 {jitter_p999_ms:.1f} "
        "ms / max {jitter_max_ms:.1f} ms, {suspends} suspends ridden through, ",
    ) + (f"{faults} latched faults" if faults else "no latched fault")
    return Measured(tuple(figs), headline)


def planner(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    ms = {k: (get(d, k) or 0) * 1000 for k in ("median_solve_s_exact", "median_solve_s_ldw_pso")}
    figs = [
        Figure("median solve, exact", num(ms["median_solve_s_exact"], ".1f", "ms")),
        Figure("median solve, ldw_pso", num(ms["median_solve_s_ldw_pso"], ".0f", "ms")),
        Figure("speedup", t(d, "{speedup:.0f}"), ">= 50"),
        Figure("worst objective gap, exact vs ldw_pso", t(d, "{worst_gap_vs_ldw_pso:.2g}"), "<= 0"),
        Figure(
            "worst objective gap, exact vs the dense search",
            t(d, "{worst_gap_vs_dense:.2g}"),
            "<= 1e-6",
        ),
        Figure("targets x objectives", f"{t(d, '{targets}')} x {len(get(d, 'objectives') or [])}"),
    ]
    headline = (
        f"median `exact` {num(ms['median_solve_s_exact'], '.1f')} ms, `ldw_pso` "
        f"{num(ms['median_solve_s_ldw_pso'], '.0f')} ms; "
        + t(
            d,
            "speedup {speedup:.0f} (goal 50); `exact` vs the dense search {worst_gap_vs_dense:.2g}",
        )
    )
    return Measured(tuple(figs), headline)


def walk_plan(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    phases = get(d, "phases") or []
    forces = [f for p in phases for f in (p.get("leg_forces_end_kn") or {}).values()]
    figs = [
        Figure("distance, duration", t(d, "{distance_m:.3f} m in {duration_s:.1f} s")),
        Figure(
            "a step (the walk's goal adds its two touch-down windows)",
            t(d, "{step_duration_s.0:.1f} s"),
        ),
        *(
            Figure(t(p, "phase {phase} ({name})"), t(p, "{duration_s:.2f} s"))
            for p in phases
            if p.get("step") == 1
        ),
        Figure(
            "least stability margin",
            t(
                d,
                "{min_stability_margin_m:.3f} m (step {min_stability_margin_at.step}, "
                "phase {min_stability_margin_at.phase})",
            ),
            t(d, "{min_stability_margin_limit_m} m"),
        ),
        Figure("largest leg force at a phase's end", num(max(forces, default=None), ".0f", "kN")),
        Figure("largest travel force", num(_largest(phases, "max_travel_force_kn"), ".2f", "kN")),
    ]
    return Measured(tuple(figs))


dual_cylinder = templated(
    ("sync error max after the transient, LADRC / PID",
     "{controllers.ladrc.sync_error_max_mm:.3f} / {controllers.pid.sync_error_max_mm:.3f} mm",
     "LADRC <= 0.07 mm"),
    ("sync error rms after the transient, LADRC / PID",
     "{controllers.ladrc.sync_error_rms_mm:.4f} / {controllers.pid.sync_error_rms_mm:.4f} mm", ""),
    ("LADRC sync error max before / with noise",
     "{controllers.ladrc.sync_error_max_mm_before_noise:.3f} / "
     "{controllers.ladrc.sync_error_max_mm_after_noise:.3f} mm", ""),
    ("tracking error rms, LADRC / PID",
     "{controllers.ladrc.tracking_error_rms_mm:.2f} / "
     "{controllers.pid.tracking_error_rms_mm:.2f} mm", ""),
    ("settling after the last move, LADRC / PID",
     "{controllers.ladrc.settling_time_s:.1f} / {controllers.pid.settling_time_s:.1f} s", ""),
    ("PID / LADRC on the max; on the rms",
     "{pid_to_ladrc_sync_error_max_ratio:.1f}; {pid_to_ladrc_sync_error_rms_ratio:.0f}", ">= 1.5"),
    ("goals met", "{goals_met}", "True"),
    headline="sync error max LADRC {controllers.ladrc.sync_error_max_mm:.3f} mm (paper 0.07), "
    "PID {controllers.pid.sync_error_max_mm:.3f} mm",
)  # fmt: skip


def delay_margin(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    runs = get(d, "runs") or []
    figs = []
    for r in runs:
        hold = [v for v in (r.get("hold_sync_error_mm") or {}).values() if _is_num(v)]
        state = "stable" if r.get("stable") else f"not stable ({r.get('mode')})"
        figs.append(
            Figure(
                t(r, "{delay_ms} ms of extra delay: sync error in the hold"),
                f"{num(max(hold, default=None), '.4f', 'mm')}, {state}",
                "0.07 mm",
            )
        )
    figs.append(Figure("delay margin", t(d, "{delay_margin_ms} ms"), t(d, ">= {required_ms} ms")))
    bad = next((r for r in runs if not r.get("stable")), None)
    headline = t(d, "the shipped tuning holds with {delay_margin_ms} ms of extra delay")
    if bad is not None:
        headline += t(bad, ", not with {delay_ms} ms")
    return Measured(tuple(figs), headline)


study_speed = templated(
    ("real-time factor", "{realtime_factor:.0f}x", ">= {goal_min_realtime_factor}x"),
    ("simulated; wall", "{study_duration_s} s per controller; {wall_s:.1f} s", ""),
    ("plant compiled (numba)", "{numba}", ""),
    headline="{realtime_factor:.0f}x real time (goal {goal_min_realtime_factor}x)",
)


def walk(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    steps = get(d, "steps") or []
    durations = [s.get("duration_s") for s in steps]
    ratios = [s.get("max_leg_force_ratio") for s in steps]
    g = "step_goals."
    figs = [
        Figure("steps passed", _count(steps), "all"),
        Figure(
            "distance (simulator truth)",
            t(d, "{distance_m:.6f} m"),
            f"{2 * len(steps):.3f} +/- 0.005 m",
        ),
        Figure(
            "a step (machine time)",
            ", ".join(num(x, ".1f") for x in durations) + " s",
            t(d, f"{{{g}max_step_duration_s.limit:.1f}} s"),
        ),
        Figure(
            "leg sync, largest",
            num(_largest(steps, "max_leg_sync_error_mm"), ".3f", "mm"),
            t(d, f"{{{g}max_leg_sync_error_mm.limit}} mm"),
        ),
        Figure(
            "travel pair sync, largest",
            num(_largest(steps, "max_travel_sync_error_mm"), ".4f", "mm"),
            t(d, f"{{{g}max_travel_sync_error_mm.limit}} mm"),
        ),
        Figure(
            "least stability margin",
            num(_largest(steps, "min_stability_margin_m", smallest=True), ".3f", "m"),
            t(d, f"{{{g}min_stability_margin_m.limit}} m"),
        ),
        Figure(
            "largest leg force / share",
            ", ".join(num(x, ".3f") for x in ratios),
            t(d, f"{{{g}max_leg_force_ratio.limit:.2f}}"),
        ),
        Figure(
            "transfer attitude change, largest",
            num(_largest(steps, "max_transfer_attitude_change_deg"), ".4f", "deg"),
            t(d, f"{{{g}max_transfer_attitude_change_deg.limit}} deg"),
        ),
        Figure("final mode", t(d, "{final_mode}")),
    ]
    headline = (
        f"{t(d, '{distance_m:.6f}')} m, {span(durations, '.1f', 's')} a step (goal "
        + t(d, "{step_goals.max_step_duration_s.limit:.1f}")
        + "), leg sync <= "
        f"{num(_largest(steps, 'max_leg_sync_error_mm'), '.3f')} mm, largest leg force "
        f"{span(ratios, '.3f')} of its share (goal "
        + t(d, "{step_goals.max_leg_force_ratio.limit:.2f}")
        + "), transfer attitude change <= "
        f"{num(_largest(steps, 'max_transfer_attitude_change_deg'), '.4f')} deg (goal "
        + t(d, "{step_goals.max_transfer_attitude_change_deg.limit}")
        + ")"
    )
    return Measured(tuple(figs), headline)


def walk_realtime(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    steps = get(d, "steps") or []
    figs = [
        Figure("steps passed", _count(steps), "all"),
        Figure("distance (simulator truth)", t(d, "{distance_m:.6f} m")),
        Figure(
            "a step (machine time)",
            span([s.get("duration_s") for s in steps], ".1f", "s"),
            t(d, "{step_goals.max_step_duration_s.limit:.1f} s"),
        ),
        Figure(
            "largest leg force / share",
            num(_largest(steps, "max_leg_force_ratio"), ".3f"),
            t(d, "{step_goals.max_leg_force_ratio.limit:.2f}"),
        ),
        Figure("final mode; latched faults", t(d, "{final_mode}; {fault_reasons}")),
    ]
    headline = (
        f"{passed(get(d, 'passed'), 'every goal met', 'FAILED')}, "
        + t(d, "{distance_m:.6f} m")
        + f", largest force ratio {num(_largest(steps, 'max_leg_force_ratio'), '.3f')}"
    )
    return Measured(tuple(figs), headline)


def place_plan(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    figs = [
        Figure(
            "target deviation y / z",
            t(d, "{target_deviation.y_mm:+.3f} / {target_deviation.z_mm:+.3f} mm"),
            "2 mm a ring",
        ),
        Figure(
            "expected vertical / horizontal misalignment; max gap",
            t(
                d,
                "{table4.vertical_misalignment_mm.value:+.3f} / "
                "{table4.horizontal_misalignment_mm.value:+.3f}; {table4.max_gap_mm.value:.3f} mm",
            ),
            "8 / 8; 0-10 mm",
        ),
        Figure("solve time", t(d, "{solve_time_s:.2f} s")),
    ]
    headline = t(
        d,
        "from 6 mm off: target {target_deviation.y_mm:+.2f} / {target_deviation.z_mm:+.2f} mm "
        "off; {solve_time_s:.2f} s a solve",
    )
    if len(outs) > 1:
        r = outs[1]
        refused = t(
            r.data, "{binding.limit} {binding.value:.3f}, exceeded by {binding.exceeded_by:.3f}"
        )
        figs.append(Figure("a previous part 9 mm off", f"exit {r.exit_code}: {refused}", "exit 3"))
        headline += f"; 9 mm off refused, exit {r.exit_code}"
    return Measured(tuple(figs), headline)


def place_run(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    pos, ang = _off(d, ("x_mm", "y_mm", "z_mm")), _off(d, ("roll_deg", "pitch_deg", "yaw_deg"))
    e, tt = "error_from_target.", "table4_truth."
    figs = [
        Figure("passed", t(d, "{passed}"), "True"),
        Figure(
            "error from the target x / y / z (truth)",
            t(d, f"{{{e}x_mm:+.4f}} / {{{e}y_mm:+.4f}} / {{{e}z_mm:+.4f}} mm"),
            "1 mm",
        ),
        Figure(
            "error roll / pitch / yaw",
            t(d, f"{{{e}roll_deg:+.5f}} / {{{e}pitch_deg:+.5f}} / {{{e}yaw_deg:+.5f}} deg"),
            "0.01 deg",
        ),
        Figure("gap error", t(d, "{gap_error_mm:.3f} mm"), "1 mm"),
        Figure(
            "Table 4 on the truth: vertical / horizontal; max gap",
            t(
                d,
                f"{{{tt}vertical_misalignment_mm.value:+.2f}} / "
                f"{{{tt}horizontal_misalignment_mm.value:+.2f}}; {{{tt}max_gap_mm.value:.2f}} mm",
            ),
            "8 / 8; 10 mm",
        ),
        Figure(
            "phase times attitude / slide",
            t(d, "{phase_times_s.attitude:.1f} / {phase_times_s.slide:.1f} s"),
        ),
        Figure("largest sync error", t(d, "{max_sync_error_mm:.3f} mm")),
        Figure("wall time", t(d, "{wall_time_s:.1f} s")),
    ]
    headline = f"within {num(pos, '.3f')} mm and {num(ang, '.4f')} deg of the target, " + t(
        d, "gap within {gap_error_mm:.3f} mm (goals 1 mm, 0.01 deg)"
    )
    return Measured(tuple(figs), headline)


def busload(outs: Sequence[Output]) -> Measured:
    d = dict(outs[0].data, kbit_s=(get(outs[0].data, "bitrate") or 0) / 1000)
    figs = [
        Figure(
            "default active group",
            t(d, "{load_percent:.2f} % of {kbit_s} kbit/s"),
            t(d, "{max_load_percent} %"),
        ),
        Figure("frames a second; bits a second", t(d, "{frames_per_s:.0f}; {bits_per_s:.0f}")),
    ]
    phases = get(outs[-1].data, "phases") or [] if len(outs) > 1 else []
    for load in sorted({p["load_percent"] for p in phases if _is_num(p.get("load_percent"))}):
        names = ", ".join(str(p.get("phase")) for p in phases if p.get("load_percent") == load)
        figs.append(
            Figure(f"walk phases {names}", num(load, ".2f", "%"), t(d, "{max_load_percent} %"))
        )
    return Measured(
        tuple(figs), t(d, "{load_percent:.2f} % of {kbit_s} kbit/s (budget {max_load_percent} %)")
    )


codec = templated(
    ("compiled codec a cycle",
     "{codec_us_per_cycle:.1f} us = {codec_percent_of_period:.2f} % of the period",
     "< {goal_percent} %"),
    ("cantools, the same work",
     "{cantools_us_per_cycle:.1f} us = {cantools_percent_of_period:.2f} %", ""),
    ("compiled vs cantools", "{speedup_vs_cantools:.1f}x", ""),
    ("the IPC side of a cycle on `virtual` (median)",
     "{link_us_per_cycle_median:.0f} us = {link_percent_of_period:.1f} %", ""),
    headline="{codec_us_per_cycle:.1f} us = {codec_percent_of_period:.2f} % of the 5 ms period "
    "(cantools {cantools_percent_of_period:.2f} %); the IPC side of a cycle "
    "{link_us_per_cycle_median:.0f} us ({link_percent_of_period:.1f} %)",
)  # fmt: skip


hil = templated(
    ("whole simulator, attitude rig, an IPC peer at 200 Hz", "{realtime_factor:.1f}x",
     ">= {goal_realtime_factor}x"),
    ("whole simulator, walking rig (contact)", "{contact_realtime_factor:.1f}x",
     ">= {goal_realtime_factor}x"),
    ("plant alone, attitude rig", "{plant_realtime_factor:.1f}x", ""),
    ("plant alone, walking rig", "{contact_plant_realtime_factor:.1f}x", ""),
    headline="{realtime_factor:.1f}x real time (goal {goal_realtime_factor}x), with the walking "
    "rig's contact {contact_realtime_factor:.1f}x; the plant alone {plant_realtime_factor:.0f}x",
)  # fmt: skip


def step(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    figs = [
        Figure(
            f"{mode}: CPU p50 / p99 ({t(d, f'{{modes.{mode}.steps}}')} steps)",
            t(d, f"{{modes.{mode}.cpu_p50_ms:.2f}} / {{modes.{mode}.cpu_p99_ms:.2f}} ms"),
        )
        for mode in get(d, "modes") or {}
    ]
    figs.append(
        Figure("all steps: CPU p50 / p99", t(d, "{all.cpu_p50_ms:.2f} / {all.cpu_p99_ms:.2f} ms"))
    )
    return Measured(tuple(figs))


def loop(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    pct = num(_percent(d, "compute_p99_fraction"), ".1f")
    figs = [
        Figure(
            "jitter p50 / p99 / max",
            t(d, "{jitter_p50_ms:.3f} / {jitter_p99_ms:.3f} / {jitter_max_ms:.2f} ms"),
        ),
        Figure("compute p99", t(d, "{compute_p99_ms:.2f} ms") + f" ({pct} % of the period)"),
        Figure("overruns", t(d, "{overruns} in {cycles} cycles")),
        Figure(
            "real-time settings applied; refused", t(d, "{realtime.applied}; {realtime.refused}")
        ),
    ]
    return Measured(tuple(figs))


def transport(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    if get(d, "error"):
        return Measured((Figure("not measured", t(d, "{error}")),))
    figs = [
        Figure(
            f"`{name}`: send / receive a frame; the IPC side of a cycle",
            t(
                d,
                f"{{transports.{name}.send_us_per_frame:.1f}} / "
                f"{{transports.{name}.recv_us_per_frame:.1f}} us; "
                f"{{transports.{name}.link_cycle_us:.0f}} us",
            ),
        )
        for name in ("udp_multicast", "wara_udp")
    ]
    figs.append(
        Figure(
            "`udp_multicast` / `wara_udp`: send, receive, cycle",
            t(
                d,
                "{speedup.send_us_per_frame:.1f}x, {speedup.recv_us_per_frame:.1f}x, "
                "{speedup.link_cycle_us:.1f}x",
            ),
        )
    )
    return Measured(tuple(figs))


opcua = templated(
    ("loop compute p99 without / with 10 clients / same CPU load",
     "{compute_p99_ms.without:.2f} / {compute_p99_ms.with:.2f} / {compute_p99_ms.same_load:.2f} ms",
     ""),
    ("with / without; with / same load (compute p99, median of the rounds)",
     "{compute_p99_ratio.median:.2f}; {same_load_ratio.median:.2f}", ""),
    ("overruns without / with / same load",
     "{overruns.without} / {overruns.with} / {overruns.same_load}", ""),
    ("CPU of the server and the clients", "{opcua_cpu_share:.2f} CPU", ""),
    ("state change to notification p50 / p99", "{latency_ms.p50:.0f} / {latency_ms.p99:.0f} ms",
     "p99 < 200 ms"),
    ("method call to notification p50 / p99",
     "{call_latency_ms.p50:.0f} / {call_latency_ms.p99:.0f} ms", "p99 < 200 ms"),
)  # fmt: skip


def harness(outs: Sequence[Output]) -> Measured:
    d = outs[0].data
    s = "lockstep.cpu_share."
    figs = [
        Figure(
            "lockstep Example 1, simulated s per CPU s",
            t(d, "{lockstep.realtime_factor_cpu:.1f}x"),
            t(d, ">= {lockstep.goal_realtime_factor}x"),
        ),
        Figure(
            "CPU: compiled PLC scans and plant / simulator's Python / plant kernel from "
            "Python / service core / rest",
            " / ".join(
                num(100 * (get(d, s + k) or 0), ".0f")
                for k in (
                    "compiled_scans",
                    "plc_scan_python",
                    "plant_kernel",
                    "service_core",
                    "rest",
                )
            )
            + " %",
        ),
    ]
    camp = get(d, "campaign") or []
    for c in camp:
        figs.append(
            Figure(
                t(c, "campaign on {workers} worker(s): runs a minute; overhead (tail + engine)"),
                t(c, "{runs_per_minute:.1f}; ")
                + " + ".join(
                    num(100 * (c.get(k) or 0), ".1f") for k in ("tail_share", "engine_gap_share")
                )
                + " %",
                "engine < 5 %",
            )
        )
    rate, goal = get(d, "lockstep.realtime_factor_cpu"), get(d, "lockstep.goal_realtime_factor")
    met = passed(rate >= goal) if _is_num(rate) and _is_num(goal) else "n/a"
    per = "; ".join(t(c, "{runs_per_minute:.1f} runs a minute on {workers}") for c in camp)
    headline = (
        f"{num(rate, '.1f')}x real time per CPU second (goal {num(goal, 'g')}x: {met}); {per}"
    )
    return Measured(tuple(figs), headline)


# --------------------------------------------------------------------------- the table

_DEMO = "The demo and the ring cycle"
_ATT = "Attitude adjustment"
_PLAN = "Planners"
_CTRL = "Control"
_WALK = "Walking"
_PLACE = "Placement"
_CAN = "CAN protocol"
_HIL = "HIL simulator"
_SVC = "IPC service"
_CAMP = "Campaigns"

#: Every figure the docs cite, one row each: name (its section's anchor in docs/figures.md),
#: subsystem, title, the commands (full form), the reader of their JSON; the short form
#: of ``--quick``, whether it runs on the wall clock (``--realtime``), the README's label.
# fmt: off
PRODUCERS: tuple[Producer, ...] = (
    Producer("demo", _DEMO, "ring cycles in simulated time (`wara demo`)",
             ("wara demo --json",), demo,
             quick=("wara demo --rings 1 --json",), headline="the demo's ring cycles"),
    Producer("demo-realtime", _DEMO, "a ring cycle on the wall clock",
             ("wara demo --realtime --rings 1 --json",), demo_realtime,
             realtime=True, headline="a ring cycle in real time"),
    Producer("place-plan", _PLACE, "the target from a part 6 mm off, and one 9 mm off",
             ("wara place plan --ring 2 --previous-deviation 6,-6,0,0,0 --json",
              "wara place plan --ring 2 --previous-deviation 9,-9,0,0,0 --json"), place_plan,
             headline="placement target"),
    Producer("place-run", _PLACE, "the placement move in lockstep",
             ("wara place run --lockstep --ring 5 --previous-deviation 6,-6,0,0,0.03 --json",),
             place_run, headline="placement move"),
    Producer("attitude", _ATT, "Examples 1-3 in lockstep",
             ("wara demo --attitude --lockstep --json",), attitude,
             headline="attitude examples 1-3"),
    Producer("attitude-realtime", _ATT, "Examples 1-3 on the wall clock, one process",
             ("wara demo --attitude --json",), attitude_realtime,
             realtime=True, headline="attitude examples in real time"),
    Producer("attitude-repeated", _ATT, "the attitude demo repeated, without and with a CPU hog",
             ("wara bench demo --attitude --runs 20 --json",
              "wara bench demo --attitude --runs 20 --cpu-hog --json"), demo_repeated,
             quick=("wara bench demo --attitude --runs 2 --json",
                    "wara bench demo --attitude --runs 2 --cpu-hog --json"),
             realtime=True, headline="the attitude demo, repeated"),
    Producer("planner", _PLAN, "attitude planner: speed and optimality",
             ("wara bench planner --json",), planner,
             quick=("wara bench planner --quick --json",), headline="planner"),
    Producer("walk-plan", _PLAN, "walk plan of three steps",
             ("wara walk plan --steps 3 --json",), walk_plan),
    Producer("dual-cylinder", _CTRL, "the paper's dual-cylinder study",
             ("wara sim dual-cylinder --json",), dual_cylinder, headline="synchronization"),
    Producer("delay-margin", _CTRL, "the attitude hold's margin for sensor delay",
             ("wara sim delay-margin --json",), delay_margin,
             quick=("wara sim delay-margin --delays-ms 0,20 --json",), headline="delay margin"),
    Producer("study-speed", _CTRL, "the dual-cylinder study's speed",
             ("wara bench sim --json",), study_speed,
             quick=("wara bench sim --quick --json",), headline="study speed"),
    Producer("walk", _WALK, "three steps in lockstep",
             ("wara walk --steps 3 --lockstep --json",), walk,
             quick=("wara walk --steps 1 --lockstep --json",), headline="walk"),
    Producer("walk-realtime", _WALK, "one step on the wall clock",
             ("wara walk --steps 1 --json",), walk_realtime, realtime=True,
             headline="walk in real time"),
    Producer("busload", _CAN, "bus load",
             ("wara can busload --json", "wara can busload --walk --json"), busload,
             headline="bus load"),
    Producer("codec", _CAN, "codec cost",
             ("wara bench can --json",), codec,
             quick=("wara bench can --quick --json",), headline="codec"),
    Producer("hil", _HIL, "simulator speed",
             ("wara bench hil --json",), hil,
             quick=("wara bench hil --quick --json",), headline="HIL speed"),
    Producer("step", _SVC, "the control step's CPU (lockstep)",
             ("wara bench step --json",), step, quick=("wara bench step --quick --json",)),
    Producer("loop", _SVC, "the fixed-rate loop alone",
             ("wara bench loop --json",), loop, quick=("wara bench loop --quick --json",)),
    Producer("transport", _SVC, "the two datagram transports",
             ("wara bench transport --json",), transport,
             quick=("wara bench transport --quick --json",)),
    Producer("two-process", _SVC, "two processes: the examples and the loop goal",
             ("wara demo --two-process --json",), two_process,
             realtime=True, headline="loop goal, two processes"),
    Producer("two-process-cycle", _SVC, "two processes: a ring cycle and the loop per phase",
             ("wara demo --two-process --rings 1 --json",), two_process_cycle,
             realtime=True, headline="a ring cycle, two processes"),
    Producer("soak", _SVC, "the two-process soak",
             ("wara soak --minutes 30 --json",), soak,
             quick=("wara soak --minutes 2 --json",), realtime=True,
             headline="soak, two processes"),
    Producer("opcua", _SVC, "the OPC UA server beside the loop",
             ("wara bench opcua --json",), opcua,
             quick=("wara bench opcua --quick --json",), realtime=True),
    Producer("harness", _CAMP, "the lockstep harness and campaign throughput",
             ("wara bench harness --json",), harness,
             quick=("wara bench harness --quick --json",), headline="lockstep harness"),
)
# fmt: on
