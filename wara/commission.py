"""``wara commission``: the controls engineer's dossier of one tunnel project.

It assembles what the other commands check, each as an *item* with a verdict
(docs/commissioning.md; decision 0027 says what "fit to commission" means):

- ``cross-checks``: the rules between keys (:mod:`config.crosscheck`, as ``wara config
  validate`` runs them);
- ``capacity``: the walk, attitude and placement planners' verdicts at the worst case
  (:func:`worst_cases`: the project's heaviest load, the part, on the steepest grades of
  its alignment and on its tightest curve), against what the supply gives
  (:mod:`ipc_app.planner.capacity`);
- ``delay-margin``: each loop's bandwidths and modelled delay margin
  (:mod:`ipc_app.control.tuning`, as ``wara sim delay-margin`` reports them);
- ``budgets``: the step's time budget and the ring cycle's (:mod:`wara.goals`): the walks
  there and back must leave time in ``cycle.max_cycle_time_min``;
- ``walk``, ``cycle``: a lockstep walk and ring cycles against the project's own goals
  (``wara walk``, ``wara cycle`` as child processes);
- ``delay-hold``: the attitude hold with the required delay on the wire (``wara sim
  delay-margin`` in a child process; not in ``--quick``);
- ``campaign``: a nominal campaign on Dask (``wara campaign run`` in a child process, its
  report read here).

The offline items are here, the ones that run the service in :mod:`wara.commission_runs`.
Items are independent: each is judged whatever another found (an item that raises is
*not fit*, its error its reason); but a project that breaks a cross-check cannot be
loaded by the service, so the items that run it are not run and are not fit.
"""

from __future__ import annotations

import math
import os
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

from config import crosscheck, units
from config.schema import ProjectConfig
from wara.examples import EXAMPLES
from wara.progress import Progress

FIT = "fit"
NOT_FIT = "not fit"
SKIPPED = "skipped"
NOT_APPLICABLE = "not applicable"

#: The items in the dossier's order.
ITEMS: tuple[str, ...] = (
    "cross-checks",
    "capacity",
    "delay-margin",
    "budgets",
    "walk",
    "cycle",
    "delay-hold",
    "campaign",
)
#: Items whose run is the service's (it loads only a project that keeps the cross-checks).
SERVICE_ITEMS = frozenset({"walk", "cycle", "delay-hold", "campaign"})


@dataclass
class Item:
    """One item of the dossier: its verdict (:data:`FIT` ...), one line per reason it is
    not fit (or was skipped), notes, a table (``rows``: one dict per row, its keys the
    columns), figures for the JSON and plots (name, PNG bytes)."""

    name: str
    title: str
    status: str = FIT
    reasons: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)
    rows: list[dict[str, Any]] = field(default_factory=list)
    figures: dict[str, Any] = field(default_factory=dict)
    images: list[tuple[str, bytes]] = field(default_factory=list)
    wall_s: float = 0.0

    def refuse(self, reason: str) -> None:
        """Not fit, for ``reason`` (one line)."""
        self.status = NOT_FIT
        self.reasons.append(" ".join(reason.split()))

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "title": self.title,
            "status": self.status,
            "fit": self.status != NOT_FIT,
            "reasons": self.reasons,
            "notes": self.notes,
            "rows": self.rows,
            "figures": self.figures,
            "wall_s": round(self.wall_s, 2),
        }


@dataclass(frozen=True)
class Settings:
    """What to run: ``steps`` of the walk, ``rings`` of the cycle, ``runs`` of the
    campaign (0: skipped) on ``workers`` local processes or at ``scheduler``;
    ``delay_hold``: the lockstep hold with the required delay."""

    steps: int = 3
    rings: int = 4
    runs: int = 20
    workers: int | None = None
    scheduler: str | None = None
    delay_hold: bool = True
    progress: bool = True


# ------------------------------------------------------------------ the worst case


def with_pitch(cfg: ProjectConfig, pitch_deg: float) -> ProjectConfig:
    """The project with its invert at ``pitch_deg`` (``base.pitch_deg``)."""
    return cfg.model_copy(update={"base": cfg.base.model_copy(update={"pitch_deg": pitch_deg})})


@dataclass(frozen=True)
class WorstCase:
    """One case the capacity item plans: its label, the project as planned there and,
    on a curve, where the walk starts against the axis each way
    (:func:`steered_start`)."""

    label: str
    cfg: ProjectConfig
    #: ``(signed radius m, chainage m)`` of the tightest curve the walk plans on
    curve: tuple[float, float] | None = None


def worst_cases(cfg: ProjectConfig) -> list[WorstCase]:
    """The cases the capacity item plans: the project as written, then the invert on
    each of the steepest grades of its alignment (the most rising and the most falling
    segment, :func:`config.crosscheck.pitch_range_deg`) where they differ from it by more
    than the cross-check's tolerance (the pitch as written is within it of its grade), then
    the tightest curve the rings lie on (:func:`config.crosscheck.tightest_curve`) on
    its own grade, the walk steering back its most (:func:`steered_start`). The load is
    the project's heaviest, the machine with its part (the planners' statics carry the
    bodies of the YAML)."""
    cases = [WorstCase(f"as written, base.pitch_deg {cfg.base.pitch_deg:g}", cfg)]
    rng = crosscheck.pitch_range_deg(cfg)
    if rng is not None:
        for pitch in sorted(set(rng)):
            if abs(pitch - cfg.base.pitch_deg) > crosscheck.PITCH_TOLERANCE_DEG:
                grade = -100.0 * math.tan(math.radians(pitch))
                label = f"steepest grade {grade:+.3f} % (tunnel.alignment), pitch {pitch:.4f}"
                cases.append(WorstCase(label, with_pitch(cfg, pitch)))
    curve = crosscheck.tightest_curve(cfg)
    al = cfg.tunnel.alignment
    if curve is not None and al is not None and al.vertical is not None:
        from config.alignment import level

        key, radius, chainage = curve
        grade = level(al.vertical, chainage).grade
        pitch = crosscheck.gradient_pitch_deg(100.0 * grade)
        label = (
            f"tightest curve {radius:g} m ({key}) at chainage {chainage:.1f} m, grade "
            f"{100.0 * grade:+.3f} %, steering back its most"
        )
        cases.append(WorstCase(label, with_pitch(cfg, pitch), (radius, chainage)))
    return cases


def steered_start(case: WorstCase, direction: str) -> Any:
    """The walk's start in ``case`` (``None``: the planner's own, on the axis at ring 1's
    rear joint face); on its curve, the machine on the axis with the heading error that
    makes the step's correction (``walking.max_heading_correction_per_step_deg``) add to
    the axis's turn: the step turns its most, ``step / R`` plus the correction."""
    if case.curve is None:
        return None
    from ipc_app.planner.steering import OnAxis
    from ipc_app.planner.walk import start_state

    assert case.cfg.walking is not None
    radius, chainage = case.curve
    sign = 1.0 if direction == "forward" else -1.0
    error = -sign * math.copysign(case.cfg.walking.max_heading_correction_per_step_rad, radius)
    start = start_state(case.cfg)
    return replace(start, on_axis=OnAxis(chainage, heading_error_rad=error))


# ------------------------------------------------------------------ offline items


def cross_checks(cfg: ProjectConfig, item: Item, path: str) -> None:
    """Every rule of :data:`config.crosscheck.RULES` (the provided ones imported), as
    :func:`config.crosscheck.problems` runs them: a row each, a reason per rule broken."""
    for rule in crosscheck.RULES:
        check = crosscheck.check_of(rule)
        reason = check(cfg) if check is not None else None
        item.rows.append(
            {
                "rule": rule.name,
                "keys": ", ".join(rule.keys),
                "kept": reason is None if check is not None else None,
                "reason": reason or ("" if check is not None else "no check available"),
            }
        )
        if reason is not None:
            item.refuse(reason)
    from config.loader import defaulted_sections, read_yaml

    defaulted = defaulted_sections(ProjectConfig, read_yaml(Path(path)))
    if defaulted:
        item.notes.append(
            f"section(s) not in the file, every key at its default: {', '.join(defaulted)}"
        )


def _walk_pressure(cfg: ProjectConfig, walk: Any) -> float:
    """The walk plan's largest leg pressure (cap side, Pa)."""
    import numpy as np

    areas = np.array([cfg.cylinder(cid).cap_area_m2 for cid in walk.leg_ids])
    return max(float((ph.leg_forces_n / areas).max()) for ph in walk.phases)


def capacity(cfg: ProjectConfig, item: Item) -> None:
    """The planners at each :func:`worst_cases` case: a walk step each way loaded (the
    legs hold up to the supply), the attitude examples and the placement of ring 2 (the
    cylinders move their load: the supply less the load-sensing margin)."""
    from ipc_app.model.placement import Pose
    from ipc_app.planner import plan
    from ipc_app.planner.capacity import pressure_limit_pa
    from ipc_app.planner.placement import plan_from_deviation
    from ipc_app.planner.walk import plan_walk

    for wc in worst_cases(cfg):
        case, c = wc.label, wc.cfg
        checks: list[tuple[str, bool, float, float, str]] = []
        if c.walks:
            for direction in ("forward", "back"):
                w = plan_walk(c, 1, steered_start(wc, direction), direction=direction)
                why = w.refusal.message if w.refusal is not None else ""
                peak = _walk_pressure(c, w)
                limit = pressure_limit_pa(c, "holds")
                what = f"walk 1 step {direction}, loaded"
                if wc.curve is not None and w.turns:
                    what += f", turning {units.to_deg(w.turns[0].turn_rad):+.3f} deg"
                checks.append((what, w.feasible, peak, limit, why))
        for roll, pitch in EXAMPLES:
            p = plan(c, roll, pitch, with_trajectory=False)
            limit = pressure_limit_pa(c, "moves")
            checks.append(
                (
                    f"attitude roll {roll:g} pitch {pitch:g} deg",
                    p.feasible,
                    p.peak_pressure_pa,
                    limit,
                    "; ".join(p.reasons),
                )
            )
        if c.placement is not None:
            pl = plan_from_deviation(c, 2, Pose())
            peaks = [a.pressure_mpa for a in pl.actuators if a.pressure_mpa is not None]
            limits = [a.pressure_limit_mpa for a in pl.actuators if a.pressure_limit_mpa]
            checks.append(
                (
                    "placement of ring 2 on its design",
                    pl.feasible,
                    units.mpa(max(peaks)) if peaks else math.nan,
                    units.mpa(min(limits)) if limits else math.nan,
                    "; ".join(pl.reasons),
                )
            )
        for what, ok, peak, limit, why in checks:
            item.rows.append(
                {
                    "case": case,
                    "plan": what,
                    "feasible": ok,
                    "peak_mpa": round(units.to_mpa(peak), 2),
                    "limit_mpa": round(units.to_mpa(limit), 2),
                    "reason": why,
                }
            )
            if not ok:
                item.refuse(f"{case}: {what}: {why}")
    item.figures["cases"] = [wc.label for wc in worst_cases(cfg)]


def delay_margin(cfg: ProjectConfig, item: Item) -> None:
    """Each loop's tuning and modelled margin (``wara sim delay-margin``'s table), and
    the project's check (:func:`ipc_app.control.tuning.delay_margin_problem`)."""
    from ipc_app.control.tuning import delay_margin_problem, derive
    from wara.studies.delay_margin import loop_margins

    required = cfg.control.delay_margin_ms
    item.rows = loop_margins(cfg, required)
    item.figures["required_ms"] = required
    t = derive(cfg)
    if t.touchdown_speed_m_s is not None:
        item.notes.append(
            f"the walk's touch-down speed {units.to_mm(t.touchdown_speed_m_s):.2f} mm/s "
            f"({t.touchdown_source})"
        )
    problem = delay_margin_problem(cfg)
    if problem is not None:
        item.refuse(problem)


def budgets(cfg: ProjectConfig, item: Item) -> None:
    """The step's budget (:func:`wara.goals.step_time_limit_s`) and the cycle's: the
    walks there and back (``cycle.walk_steps`` steps each way, each within the step's
    budget) and the release's longest lowering within ``cycle.max_cycle_time_min``."""
    from ipc_app.planner.walk import plan_walk
    from wara.goals import step_time_limit_s

    step_s = 0.0
    if cfg.walks:
        step_s = step_time_limit_s(cfg)
        planned = plan_walk(cfg, 1).duration_s
        item.rows += [
            {"budget": "a step", "seconds": round(step_s, 1),
             "source": "the planned step and two touch-down windows (walking.*)"},
            {"budget": "of which the planned step", "seconds": round(planned, 1),
             "source": "the walk planner (walking.*, trajectory)"},
        ]  # fmt: skip
    if cfg.cycle is None:
        item.notes.append("the project has no cycle section: no ring cycle budget")
        return
    cyc = cfg.cycle
    budget_s = 60.0 * cyc.max_cycle_time_min
    walks_s = 2 * cyc.walk_steps * step_s
    release_s = (cyc.release_max_travel_mm + cyc.release_clearance_mm) / cyc.release_speed_mm_s
    left_s = budget_s - walks_s - release_s
    item.rows += [
        {"budget": "the ring cycle's machine time (the fixing hold excluded)",
         "seconds": round(budget_s, 1), "source": "cycle.max_cycle_time_min"},
        {"budget": f"its walks: {cyc.walk_steps} step(s) there and back",
         "seconds": round(walks_s, 1), "source": "cycle.walk_steps x the step's budget"},
        {"budget": "its release, the longest lowering", "seconds": round(release_s, 1),
         "source": "cycle.release_max_travel_mm + release_clearance_mm at release_speed_mm_s"},
        {"budget": "left for the placement, the survey and the record",
         "seconds": round(left_s, 1), "source": "the cycle's budget less the above"},
    ]  # fmt: skip
    item.figures.update(
        {"step_s": step_s, "cycle_s": budget_s, "walks_s": walks_s, "left_s": left_s}
    )
    if left_s <= 0:
        item.refuse(
            f"cycle.max_cycle_time_min: {cyc.max_cycle_time_min:g} min leaves no time to place "
            f"the part: the walks there and back ({cyc.walk_steps} step(s) of "
            f"{step_s:.1f} s each way) and the release take {walks_s + release_s:.0f} s"
        )


OFFLINE: dict[str, tuple[str, Callable[..., None]]] = {
    "capacity": ("Capacity at the worst case", capacity),
    "delay-margin": ("Delay margin and bandwidths of each loop", delay_margin),
    "budgets": ("Step and cycle time budgets", budgets),
}


# ------------------------------------------------------------------ the dossier


def commission(
    cfg: ProjectConfig, path: str, out: Path, s: Settings
) -> tuple[list[Item], dict[str, Any]]:
    """Every item of :data:`ITEMS` in turn; the items and the JSON summary."""
    out.mkdir(parents=True, exist_ok=True)
    logs = out / "logs"
    bar = Progress(
        len(ITEMS), 0, 0, enabled=s.progress, failed_word="not fit", eta=False, every_s=15.0
    )
    titles = {
        "cross-checks": "Cross-checks between keys",
        **{k: t for k, (t, _) in OFFLINE.items()},
        "walk": f"Lockstep walk, {s.steps} step(s)",
        "cycle": f"Ring cycles, {s.rings} ring(s)",
        "delay-hold": "Attitude hold with the required delay",
        "campaign": f"Campaign on Dask, {s.runs} run(s)",
    }
    items: list[Item] = []
    broken = crosscheck.problems(cfg)
    t_start = time.monotonic()
    bar.show()
    for name in ITEMS:
        item = Item(name, titles[name])
        bar.note = name
        bar.tick()
        t0 = time.monotonic()
        try:
            _run_item(name, cfg, path, s, item, out, logs, bar, broken)
        except Exception as exc:  # one item's failure is that item's verdict, no other's
            item.status = NOT_FIT
            item.reasons.append(f"the check itself failed: {type(exc).__name__}: {exc}")
            item.notes.append(traceback.format_exc(limit=3))
        item.wall_s = time.monotonic() - t0
        items.append(item)
        bar.note = f"{name}: {item.status}"
        bar.update(item.status == NOT_FIT)
    bar.finish()
    fit = all(i.status != NOT_FIT for i in items)
    summary = {
        "project": cfg.project.name,
        "section": cfg.project.section,
        "file": path,
        "fit": fit,
        "not_fit": [f"{i.name}: {r}" for i in items if i.status == NOT_FIT for r in i.reasons],
        "settings": {
            "steps": s.steps, "rings": s.rings, "runs": s.runs,
            "workers": s.workers, "scheduler": s.scheduler, "delay_hold": s.delay_hold,
        },
        "generated_at": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "wall_s": round(time.monotonic() - t_start, 1),
        "cpus": os.cpu_count(),
        "items": [i.to_dict() for i in items],
    }  # fmt: skip
    return items, summary


def _run_item(
    name: str,
    cfg: ProjectConfig,
    path: str,
    s: Settings,
    item: Item,
    out: Path,
    logs: Path,
    bar: Progress,
    broken: list[str],
) -> None:
    if name == "cross-checks":
        cross_checks(cfg, item, path)
        return
    if name in OFFLINE:
        OFFLINE[name][1](cfg, item)
        return
    skip = _skipped(name, cfg, s)
    if skip is not None:
        item.status, why = skip
        item.reasons.append(why)
        return
    if name in SERVICE_ITEMS and broken:
        item.refuse(
            "not run: the service loads no project that breaks a cross-check "
            f"({len(broken)} broken: see cross-checks)"
        )
        return
    from wara.commission_runs import campaign_item, cycle_item, delay_hold_item, walk_item

    if name == "walk":
        walk_item(path, s.steps, item, logs, bar)
    elif name == "cycle":
        cycle_item(path, cfg, s.rings, item, logs, bar)
    elif name == "delay-hold":
        delay_hold_item(path, cfg, item, logs, bar)
    elif name == "campaign":
        campaign_item(path, cfg, s, item, out, bar)


def _skipped(name: str, cfg: ProjectConfig, s: Settings) -> tuple[str, str] | None:
    """``(status, why)`` of an item not run: asked not to, or not the project's."""
    if name == "walk" and not cfg.walks:
        return NOT_APPLICABLE, "the project has no walking and frames sections: it does not walk"
    if name == "cycle" and (cfg.cycle is None or cfg.placement is None):
        return NOT_APPLICABLE, "the project has no cycle and placement sections: it does not place"
    if name == "delay-hold" and not s.delay_hold:
        return SKIPPED, "skipped (--quick): the loop model's margins are item delay-margin"
    if name == "campaign" and s.runs == 0:
        return SKIPPED, "skipped (--runs 0 or --quick)"
    return None
