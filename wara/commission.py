"""``wara commission``: the controls engineer's dossier of one tunnel project.

It assembles what the other commands check, each as an *item* with a verdict
(docs/commissioning.md; decision 0027 says what "fit to commission" means):

- ``cross-checks``: the rules between keys (:mod:`config.crosscheck`, as ``wara config
  validate`` runs them);
- ``capacity``: the walk, attitude and placement planners' verdicts at the worst case
  (:func:`worst_cases`: the project's heaviest load, the part, on the steepest grades of
  its alignment), against what the supply gives (:mod:`ipc_app.planner.capacity`);
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

Items are independent: each is judged whatever another found (an item that raises is
*not fit*, its error its reason); but a project that breaks a cross-check cannot be
loaded by the service, so the items that run it are not run and are not fit.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from config import crosscheck, units
from config.schema import WORKPIECE_BODY, ProjectConfig
from wara.examples import EXAMPLES
from wara.progress import Progress, hms

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


def worst_cases(cfg: ProjectConfig) -> list[tuple[str, ProjectConfig]]:
    """The cases the capacity item plans: the project as written, then the invert on
    each of the steepest grades of its alignment (the most rising and the most falling
    segment, :func:`config.crosscheck.pitch_range_deg`) where they differ from it. The
    load is the project's heaviest, the machine with its part (the planners' statics
    carry the bodies of the YAML). A new kind of worst case (the tightest curve, when an
    alignment can have one) is a case more here."""
    cases = [(f"as written, base.pitch_deg {cfg.base.pitch_deg:g}", cfg)]
    rng = crosscheck.pitch_range_deg(cfg)
    if rng is not None:
        for pitch in sorted(set(rng)):
            if abs(pitch - cfg.base.pitch_deg) > 1e-6:
                grade = -100.0 * math.tan(math.radians(pitch))
                label = f"steepest grade {grade:+.3f} % (tunnel.alignment), pitch {pitch:.4f}"
                cases.append((label, with_pitch(cfg, pitch)))
    return cases


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

    for case, c in worst_cases(cfg):
        checks: list[tuple[str, bool, float, float, str]] = []
        if c.walking is not None and c.frames is not None:
            for direction in ("forward", "back"):
                w = plan_walk(c, 1, direction=direction)
                why = w.refusal.message if w.refusal is not None else ""
                peak = _walk_pressure(c, w)
                limit = pressure_limit_pa(c, "holds")
                checks.append((f"walk 1 step {direction}, loaded", w.feasible, peak, limit, why))
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
    item.figures["cases"] = [case for case, _ in worst_cases(cfg)]
    item.notes.append(
        "a curved alignment's tightest curve is not a case yet: no planner takes a curve"
    )


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
    if cfg.walking is not None and cfg.frames is not None:
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


# ------------------------------------------------------------------ the child runs


def wara_argv(*args: str) -> list[str]:
    return [sys.executable, "-m", "wara", *args]


def run_child(
    argv: list[str], name: str, logs: Path, bar: Progress, label: str
) -> tuple[int, str, str]:
    """Run a ``wara`` child process, its stdout and stderr to ``logs/NAME.out`` and
    ``.log``, the progress line showing ``label``, the time so far and the child's last
    line on stderr; ``(exit code, stdout, stderr)``."""
    logs.mkdir(parents=True, exist_ok=True)
    out_path, err_path = logs / f"{name}.out", logs / f"{name}.log"
    t0 = time.monotonic()
    with out_path.open("w") as out, err_path.open("w") as err:
        proc = subprocess.Popen(argv, stdout=out, stderr=err, stdin=subprocess.DEVNULL)
        try:
            while proc.poll() is None:
                time.sleep(0.5)
                last = _last_line(err_path)
                bar.note = f"{label} {hms(time.monotonic() - t0)}" + (f": {last}" if last else "")
                bar.tick()
        finally:
            if proc.poll() is None:  # interrupted: the child and its own children go
                proc.terminate()
                try:
                    proc.wait(timeout=20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait()
    return proc.returncode, out_path.read_text(), err_path.read_text()


def _last_line(path: Path) -> str:
    try:
        with path.open("rb") as f:
            f.seek(max(0, path.stat().st_size - 400))
            lines = f.read().decode("utf-8", "replace").replace("\r", "\n").splitlines()
    except OSError:
        return ""
    lines = [ln.strip() for ln in lines if ln.strip() and not ln.lstrip().startswith("{")]
    return lines[-1][:90] if lines else ""


def _child_json(code: int, out: str, err: str, item: Item, what: str) -> dict[str, Any] | None:
    """The child's JSON, or ``None`` with the item not fit naming why (its last line)."""
    try:
        data = json.loads(out)
        if isinstance(data, dict):
            return data
    except ValueError:
        pass
    tail = [ln for ln in err.splitlines() if ln.strip()]
    item.refuse(f"{what} did not report (exit {code}): {tail[-1] if tail else 'no output'}")
    return None


def goal_rows(parts: list[dict[str, Any]], label: str) -> list[dict[str, Any]]:
    """Each goal's worst value over ``parts`` (steps, rings: each with ``goals``)."""
    worst: dict[str, dict[str, Any]] = {}
    for p in parts:
        for figure, g in p.get("goals", {}).items():
            lim, v = g["limit"], g["value"]
            lower = figure == "min_stability_margin_m"
            w = worst.get(figure)
            if w is None or (v < w["worst"] if lower else abs(v) > abs(w["worst"])):
                worst[figure] = {
                    "figure": figure, "worst": v, "limit": lim,
                    "at": f"{label} {p.get('index', p.get('ring', ''))}", "met": None,
                    "source": g["source"],
                }  # fmt: skip
    rows = list(worst.values())
    for r in rows:
        r["met"] = all(p["goals"][r["figure"]]["met"] for p in parts if r["figure"] in p["goals"])
    return rows


def walk_item(path: str, steps: int, item: Item, logs: Path, bar: Progress) -> None:
    argv = wara_argv("walk", "--config", path, "--steps", str(steps), "--lockstep", "--json")
    code, out, err = run_child(argv, "walk", logs, bar, f"walk {steps} step(s)")
    data = _child_json(code, out, err, item, "wara walk")
    if data is None:
        return
    item.rows = goal_rows(data.get("steps", []), "step")
    item.figures = {k: data.get(k) for k in ("passed", "distance_m", "final_mode", "missed")}
    item.figures["steps"] = len(data.get("steps", []))
    if data.get("refused") is not None:
        item.refuse(f"refused before it moved: {data.get('error') or data['refused']}")
    elif not data.get("passed"):
        for m in data.get("missed") or ["the walk did not pass"]:
            item.refuse(m)


def cycle_item(path: str, rings: int, item: Item, logs: Path, bar: Progress) -> None:
    db = logs / "acceptance.sqlite"
    argv = wara_argv(
        "cycle", "--config", path, "--rings", str(rings), "--lockstep", "--json", "--db", str(db)
    )
    code, out, err = run_child(argv, "cycle", logs, bar, f"ring cycle x{rings}")
    data = _child_json(code, out, err, item, "wara cycle")
    if data is None:
        return
    item.rows = goal_rows(data.get("rings", []), "ring")
    item.figures = {k: data.get(k) for k in ("passed", "steering", "missed", "wall_time_s")}
    item.figures["cycle_time_s"] = [r.get("cycle_time_s") for r in data.get("rings", [])]
    if data.get("refused") is not None:
        item.refuse(f"refused: {data['refused']}")
    elif not data.get("passed"):
        for m in data.get("missed") or ["the cycle did not pass"]:
            item.refuse(m)


def delay_hold_item(path: str, cfg: ProjectConfig, item: Item, logs: Path, bar: Progress) -> None:
    req = cfg.control.delay_margin_ms
    argv = wara_argv("sim", "delay-margin", path, "--delays-ms", f"{req:g}", "--json", "--quiet")
    code, out, err = run_child(argv, "delay-hold", logs, bar, f"hold with {req:g} ms delay")
    data = _child_json(code, out, err, item, "wara sim delay-margin")
    if data is None:
        return
    keep = ("delay_ms", "stable", "reached_target", "attitude_error_deg", "mode", "faults")
    item.rows = [{k: r.get(k) for k in keep} for r in data.get("runs", [])]
    item.figures = {"passed": data.get("passed"), "required_ms": req}
    for r in data.get("runs", []):
        if not r.get("stable"):
            why = "; ".join(r.get("faults") or []) or (
                "target not reached" if not r.get("reached_target") else
                "sync error at the hold above the standstill goal"
            )  # fmt: skip
            item.refuse(
                f"control.delay_margin_ms: with {r['delay_ms']:g} ms of extra position delay "
                f"the attitude hold is not stable ({why})"
            )


#: The campaign's dispersions, each a factor on the project's own value (or, for the
#: simulator's sensors, their noise): within the specification of any project.
CAMPAIGN_DISPERSIONS: dict[str, dict[str, Any]] = {
    "hydraulics.bulk_modulus_mpa": {"dist": "uniform", "low": 0.6, "high": 1.0, "factor": True},
    "hydraulics.valve_max_opening_mm": {
        "dist": "normal", "mean": 1.0, "std": 0.05, "factor": True, "min": 0.8, "max": 1.2,
    },
    "hydraulics.cylinder_defaults.coulomb_friction_n": {
        "dist": "uniform", "low": 0.5, "high": 2.0, "factor": True,
    },
}  # fmt: skip
CAMPAIGN_SIMULATOR: dict[str, dict[str, Any]] = {
    "sensors.position.noise_um": {"dist": "uniform", "low": 0.5, "high": 2.0},
    "sensors.pressure.noise_kpa": {"dist": "uniform", "low": 5.0, "high": 30.0},
}


def campaign_spec(cfg: ProjectConfig, path: str, runs: int) -> dict[str, Any]:
    """A nominal campaign of ``runs`` runs of the project: an attitude target each, drawn
    in the box of the attitude examples, the part's mass within 2 % (1 sigma), the oil,
    the valves and the friction of :data:`CAMPAIGN_DISPERSIONS`; judged on the run kind's
    goals (the spec gives no limits)."""
    dispersions = dict(CAMPAIGN_DISPERSIONS)
    names = [b.name for b in cfg.layers.upper.bodies]
    if WORKPIECE_BODY in names:
        key = f"layers.upper.bodies[{names.index(WORKPIECE_BODY)}].mass_kg"
        dispersions[key] = {"dist": "normal", "mean": 1.0, "std": 0.02, "factor": True}
    rolls = [r for r, _ in EXAMPLES]
    pitches = [p for _, p in EXAMPLES]
    return {
        "name": f"commissioning of {cfg.project.name}",
        "kind": "nominal",
        "project": str(Path(path).resolve()),
        "seed": 1,
        "run": {
            "kind": "attitude_targets",
            "targets": 1,
            "roll_deg": [min(rolls), max(rolls)],
            "pitch_deg": [min(pitches), max(pitches)],
        },
        "dispersions": dispersions,
        "simulator": dict(CAMPAIGN_SIMULATOR),
        "requirement": {"runs": runs},
    }


def campaign_item(
    path: str, cfg: ProjectConfig, s: Settings, item: Item, out: Path, bar: Progress
) -> None:
    """``wara campaign run`` of :func:`campaign_spec` in a child process; its report
    (:func:`wara.campaign.report.summary`, the plots) read here. Fit: every run passed."""
    from importlib.util import find_spec

    missing = [m for m in ("distributed", "pyarrow") if find_spec(m) is None]
    if missing:
        item.refuse(f"not run: {', '.join(missing)} not installed: pip install -e '.[campaign]'")
        return
    spec_path = out / "logs" / "campaign.yaml"
    spec_path.parent.mkdir(parents=True, exist_ok=True)
    spec_path.write_text(yaml.safe_dump(campaign_spec(cfg, path, s.runs), sort_keys=False))
    where = (
        ["--scheduler", s.scheduler]
        if s.scheduler
        else (["--workers", str(s.workers)] if s.workers else [])
    )
    camp = out / "campaign"
    argv = wara_argv("campaign", "run", str(spec_path), "--out", str(camp), *where, "--json")
    code, stdout, err = run_child(argv, "campaign", out / "logs", bar, f"campaign of {s.runs}")
    data = _child_json(code, stdout, err, item, "wara campaign run")
    if data is None:
        return
    from wara.campaign.engine import campaign_of_dir, read_results
    from wara.campaign.report import plots, summary

    sm = summary(camp)
    v = sm["verdict"]
    item.figures = {"verdict": v, "figures": sm["figures"], "status_counts": sm["status_counts"]}
    item.rows = [
        {"figure": k, **{n: round(x, 6) for n, x in f.items()}} for k, f in sm["figures"].items()
    ]
    item.notes.append(
        f"{v['runs']} of {v['planned']} runs, {v['failures']} failed; pass probability >= "
        f"{v['lower_bound']:.3f} at {v['confidence']:.0%} confidence (a verification "
        f"campaign of {v['probability']} takes `wara campaign run`: docs/campaigns.md)"
    )
    rows = read_results(camp)
    if find_spec("matplotlib") is not None:
        item.images = plots(campaign_of_dir(camp), rows, sm)
    if v["runs"] < v["planned"]:
        item.refuse(f"{v['planned'] - v['runs']} of {v['planned']} runs did not complete")
    failed = [r for r in rows if not r["passed"]]
    if failed:
        item.refuse(f"{len(failed)} of {len(rows)} runs failed (at most 10 named)")
    for r in failed[:10]:
        item.refuse(f"run {r['run']}: {r['status']}: {r['note'] or r['fault_reasons']}")


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
    if name == "walk":
        walk_item(path, s.steps, item, logs, bar)
    elif name == "cycle":
        cycle_item(path, s.rings, item, logs, bar)
    elif name == "delay-hold":
        delay_hold_item(path, cfg, item, logs, bar)
    elif name == "campaign":
        campaign_item(path, cfg, s, item, out, bar)


def _skipped(name: str, cfg: ProjectConfig, s: Settings) -> tuple[str, str] | None:
    """``(status, why)`` of an item not run: asked not to, or not the project's."""
    if name == "walk" and (cfg.walking is None or cfg.frames is None):
        return NOT_APPLICABLE, "the project has no walking and frames sections: it does not walk"
    if name == "cycle" and (cfg.cycle is None or cfg.placement is None):
        return NOT_APPLICABLE, "the project has no cycle and placement sections: it does not place"
    if name == "delay-hold" and not s.delay_hold:
        return SKIPPED, "skipped (--quick): the loop model's margins are item delay-margin"
    if name == "campaign" and s.runs == 0:
        return SKIPPED, "skipped (--runs 0 or --quick)"
    return None
