"""The items of ``wara commission`` that run the service: the walk, the ring cycles, the
attitude hold with the required delay (``wara walk``, ``wara cycle``, ``wara sim
delay-margin`` as child processes, their JSON read back) and the campaign (``wara
campaign run`` in a child process, on Dask; its report read here). The dossier and
its other items: :mod:`wara.commission`."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import yaml

from config.schema import WORKPIECE_BODY, ProjectConfig
from wara.commission import Item, Settings
from wara.examples import EXAMPLES
from wara.progress import Progress, hms

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
    walked = data.get("steps", [])
    # the walk's own goals (its distance, its heading against the axis's at the end)
    whole = goal_rows([{"goals": data.get("goals", {})}], "")
    for r in whole:
        r["figure"], r["at"] = f"the walk's {r['figure']}", f"{len(walked)} step(s)"
    item.rows = whole + goal_rows(walked, "step")
    keys = ("passed", "distance_m", "heading_error_deg", "lateral_offset_mm", "final_mode")
    item.figures = {k: data.get(k) for k in (*keys, "missed")}
    item.figures["steps"] = len(walked)
    if data.get("refused") is not None:
        item.refuse(f"refused before it moved: {data.get('error') or data['refused']}")
    elif not data.get("passed"):
        for m in data.get("missed") or ["the walk did not pass"]:
            item.refuse(m)


def cycle_item(
    path: str, cfg: ProjectConfig, rings: int, item: Item, logs: Path, bar: Progress
) -> None:
    db = logs / "acceptance.sqlite"
    argv = wara_argv(
        "cycle", "--config", path, "--rings", str(rings), "--lockstep", "--json", "--db", str(db)
    )
    code, out, err = run_child(argv, "cycle", logs, bar, f"ring cycle x{rings}")
    data = _child_json(code, out, err, item, "wara cycle")
    if data is None:
        return
    built: list[dict[str, Any]] = data.get("rings", [])
    steps = cycle_steps(cfg, built)
    item.rows = goal_rows(built, "ring") + goal_rows(steps, "step")
    item.figures = {k: data.get(k) for k in ("passed", "steering", "missed", "wall_time_s")}
    item.figures["cycle_time_s"] = [r.get("cycle_time_s") for r in built]
    if data.get("refused") is not None:
        item.refuse(f"refused: {data['refused']}")
    elif not data.get("passed"):
        for m in data.get("missed") or ["the cycle did not pass"]:
            item.refuse(m)
    for st in steps:
        for m in st["missed"]:
            item.refuse(f"step {st['index']}: {m}")


#: A cycle's walk step's figures (the service's: ``wara cycle`` gives no truth of them)
#: and the walk goal each is judged on.
CYCLE_STEP_FIGURES = {
    "max_leg_sync_error_mm": "max_leg_sync_error_mm",
    "max_travel_sync_error_mm": "max_travel_sync_error_mm",
    "min_stability_margin_m": "min_stability_margin_m",
    "max_leg_force_ratio": "max_leg_force_ratio",
    "duration_s": "max_step_duration_s",
}


def cycle_steps(cfg: ProjectConfig, rings: list[dict[str, Any]]) -> list[dict[str, Any]]:
    """The steps of each ring's walks there and back, judged on the walk's goals
    (:func:`wara.goals.walk_step_goals`) that their figures (:data:`CYCLE_STEP_FIGURES`)
    give: ``wara cycle`` judges the rings, not their steps."""
    from wara.goals import judge, walk_step_goals

    if cfg.walking is None:
        return []
    goals = walk_step_goals(cfg)
    out = []
    for r in rings:
        for walk, steps in (r.get("walks") or {}).items():
            for st in steps:
                figs = {g: float(st[k]) for k, g in CYCLE_STEP_FIGURES.items() if k in st}
                v = judge([g for g in goals if g.figure in figs], figs)
                out.append({"index": f"{st.get('index')} of ring {r['ring']}'s {walk}",
                            **v.to_dict()})  # fmt: skip
    return out


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
        f"{v['lower_bound']:.3f} at {v['confidence']:.0%} confidence (the requirement "
        f"{v['probability']} {'shown' if v['shown'] else 'not shown'}: a smoke test, not a "
        "verification campaign: docs/commissioning.md)"
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
