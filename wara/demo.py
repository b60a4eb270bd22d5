"""The end-to-end demo in one process: ``wara demo``.

The main job (:func:`run_ring_demo`): a few ring cycles one after another
(:func:`wara.cycle.run_cycle`: walk, place, fixing hold, release, survey, record, walk
back), each ring's target planned from the survey of the ring before, the part before the
first ring deliberately off the design axis so that the rings steer back; then the
acceptance report of the rings' records. With ``--attitude`` (:func:`run_demo`):
Examples 1-3 of the reference machine one after another from a level start. Both on the
:class:`~wara.harness.Harness` (the HIL simulator and the IPC service on one in-process
bus), in real time (the default) or in lockstep. The two-process form of the attitude
examples is :mod:`wara.demo_two_process`.
"""

from __future__ import annotations

import contextlib
import math
import sys
from collections.abc import Callable
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

from config import load_project
from ipc_app.model.placement import Pose, sheet_deviation
from ipc_app.service.modes import Mode
from wara.examples import EXAMPLES, ExampleResult
from wara.goals import ATTITUDE_GOALS, SYNC_TOL_MM, limits
from wara.harness import Harness, Trace, ride_through

__all__ = ["ride_through", "run_demo", "run_ring_demo"]


def run_demo(
    config_path: str | None = None,
    *,
    mode: str = "realtime",
    examples: tuple[tuple[float, float], ...] = EXAMPLES,
    plot_dir: Path | None = None,
    progress: Callable[[str], None] | None = None,
    opcua: bool = False,
) -> dict[str, Any]:
    """Run the examples; returns the JSON-ready summary (``passed`` tells the verdict)."""
    cfg = load_project(config_path)
    say = progress or (lambda _s: None)
    demo = Harness(cfg, config_path, mode=mode, progress=say)
    results: list[ExampleResult] = []
    error: str | None = None
    stack = contextlib.ExitStack()
    try:
        if opcua:  # the OPC UA server for the demo's duration, up before the simulator
            from wara.demo_opcua import serve_opcua

            stack.enter_context(serve_opcua(demo.core, config_path, say, demo.slack_gate))
        demo.start()
        say("starting: waiting for the PLC")
        if not demo.wait_for(Mode.IDLE, 20.0):
            error = f"service did not come up: {demo.fault_note()}"
            say(error)
        for roll, pitch in examples if error is None else ():
            results.append(demo.run_example(roll, pitch))
            say(
                f"example ({roll:+.1f}, {pitch:+.1f}) deg: "
                f"{'passed' if results[-1].passed else 'FAILED ' + results[-1].note}"
            )
            if demo.faulted():  # the rest would be refused: report now
                say(f"stopping: {demo.fault_note()}")
                break
        figures = demo.run_figures()
    finally:
        stack.close()
        demo.close()
    summary: dict[str, Any] = {
        "mode": mode,
        "error": error,
        "examples": [asdict(r) for r in results],
        **figures,
        "tolerances": limits(ATTITUDE_GOALS),
        "passed": error is None
        and len(results) == len(examples)
        and all(r.passed for r in results),
    }
    if plot_dir is not None:
        summary["plots"] = [str(p) for p in plot_trace(demo.trace, plot_dir)]
    return summary


#: The ring demo's rings: ring 1 (the part before) lies :data:`RING_DEMO_DEVIATION` off its
#: design, rings 2-5 are built: two at the steering-back bound (6 -> 4 -> 2 mm), then
#: within 1 mm of the design axis (docs/placement.md, "The demo's rings").
RING_DEMO_RINGS = 4
#: The first ring's misalignment: the previous part 6 mm left and 6 mm low
#: (y, z mm; roll, pitch, yaw deg).
RING_DEMO_DEVIATION: tuple[float, float, float, float, float] = (6.0, -6.0, 0.0, 0.0, 0.0)
#: The subdirectory of the demo's output directory that gets the acceptance report.
REPORT_SUBDIR = "report"
#: The demo's acceptance store in its output directory (replaced on each run).
DB_NAME = "acceptance.sqlite"


def run_ring_demo(
    config_path: str | None = None,
    *,
    out_dir: Path,
    mode: str = "lockstep",
    rings: int = RING_DEMO_RINGS,
    previous_deviation: Pose | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """The ring cycles and the acceptance report; the JSON-ready summary: ``passed``,
    ``rings`` (one object per ring, :func:`wara.cycle.run_cycle`'s), ``steering``,
    ``report`` (where the HTML is), and the cycle's other figures."""
    from wara.cycle import run_cycle

    say = progress or (lambda _s: None)
    out_dir = out_dir.resolve()  # the paths printed are the ones to open
    out_dir.mkdir(parents=True, exist_ok=True)
    db = out_dir / DB_NAME
    db.unlink(missing_ok=True)  # the demo's own store: this run's rings only
    dev = previous_deviation or sheet_deviation(*RING_DEMO_DEVIATION)
    out = run_cycle(config_path, rings, previous_deviation=dev, db_path=db, mode=mode, progress=say)
    out["mode"] = mode
    out["report"] = None
    if out["rings"]:
        out["report"] = str(write_ring_report(config_path, db, out_dir / REPORT_SUBDIR))
        say(f"acceptance report: {out['report']}")
    return out


def write_ring_report(config_path: str | None, db: Path, out: Path) -> Path:
    """``wara acceptance report --db DB --out OUT`` on the demo's records; the HTML's path."""
    from acceptance.report import ReportMeta, write_report
    from acceptance.store import AcceptanceStore
    from wara.commands.acceptance import report_meta, summary_of

    cfg = load_project(config_path)
    with AcceptanceStore.open(db) as store:
        summary = summary_of(store, cfg)
    meta: ReportMeta = report_meta(cfg, config_path, db)
    return write_report(summary, out, meta).html


def render_ring_table(out: dict[str, Any]) -> str:
    """Table 4 per ring on the simulator's truth (``wara cycle``'s table), the steering
    and where the report is."""
    from wara.cycle import render

    st = out["steering"]
    last = st["last_as_built_deviation_mm"]
    lines = [
        render(out),
        f"steering back: ring 1 {st['start_deviation_mm'][0]:+.1f} / "
        f"{st['start_deviation_mm'][1]:+.1f} mm off the design axis; corrections per ring "
        + ", ".join(f"{c:.2f}" for c in st["correction_per_ring_mm"])
        + f" mm (bound {st['max_correction_per_ring_mm']:g} mm); the last ring "
        f"{last[0]:+.2f} / {last[1]:+.2f} mm off",
        f"acceptance report: {out['report'] or 'not written (no ring finished)'}",
    ]
    if not out["passed"]:
        lines.append("FAILED: " + ring_failure_reason(out))
    return "\n".join(lines)


def ring_failure_reason(out: dict[str, Any]) -> str:
    """One line: why a ring demo did not pass (the cycle's error, else each ring's
    missed goals)."""
    return "; ".join(out.get("missed") or ["not every ring ran"])


def plot_trace(trace: Trace, out_dir: Path) -> list[Path]:
    """Attitude, cylinder positions, sync errors and pressures over time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.asarray(trace.t)
    fig, ax = plt.subplots(4, 1, figsize=(11, 12), sharex=True)
    ax[0].plot(t, trace.roll_deg, label="workpiece roll")
    ax[0].plot(t, trace.pitch_deg, label="workpiece pitch")
    ax[0].set_ylabel("deg")
    ax[0].set_title("Workpiece attitude in the world (simulator truth)")
    ax[0].legend(loc="best")
    x = np.asarray(trace.x_mm)
    names = ["leg 1", "leg 2", "leg 3", "leg 4", "upper 1", "upper 2", "upper 3", "upper 4"]
    for i in range(x.shape[1] if x.ndim == 2 else 0):
        ax[1].plot(t, x[:, i], label=names[i], lw=1)
    ax[1].set_ylabel("rod position, mm")
    ax[1].set_title("Attitude cylinders (from the retracted end)")
    ax[1].legend(loc="best", ncol=4, fontsize=8)
    s = np.asarray(trace.sync_mm)
    if s.ndim == 2:
        ax[2].plot(t, s[:, 0], label="lower group")
        ax[2].plot(t, s[:, 1], label="upper group")
    ax[2].axhline(SYNC_TOL_MM, color="k", ls="--", lw=0.8, label="standstill goal")
    ax[2].set_ylabel("mm")
    ax[2].set_title("Synchronization error (largest in the group, controller view)")
    ax[2].legend(loc="best")
    p = np.asarray(trace.p_mpa)
    for i in range(p.shape[1] if p.ndim == 2 else 0):
        ax[3].plot(t, p[:, i], label=names[i], lw=1)
    ax[3].set_ylabel("cap pressure, MPa")
    ax[3].set_xlabel("time, s")
    ax[3].set_title("Cap-side pressures")
    ax[3].legend(loc="best", ncol=4, fontsize=8)
    fig.tight_layout()
    path = out_dir / "demo.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return [path]


def render_table(summary: dict[str, Any]) -> str:
    lines = example_rows(summary)
    lp = summary["loop"]
    jit = lp.get("jitter_p99_ms")
    lines += [
        "",
        f"loop: {lp['period_ms']:.1f} ms period, jitter p99 "
        f"{'n/a (lockstep)' if jit is None else f'{jit:.3f} ms'}, overruns "
        f"{lp.get('overruns', 'n/a')}; bus load {summary['bus_load_percent']:.1f} %; "
        f"simulator {summary['simulator_realtime_factor']:.1f}x real time",
        "PASSED" if summary["passed"] else "FAILED: " + failure_reason(summary),
    ]
    return "\n".join(lines)


def failure_reason(summary: dict[str, Any]) -> str:
    """One line: why a demo run did not pass (the error, else the service's latched
    faults, else the first example or ring that missed its goals)."""
    if "rings" in summary:
        return ring_failure_reason(summary)
    if summary.get("error"):
        return str(summary["error"])
    if summary.get("fault_reasons"):
        return f"service {summary.get('final_mode')}: " + "; ".join(summary["fault_reasons"])
    for r in summary.get("examples", []):
        if not r.get("passed"):
            return f"example ({r['target_roll_deg']:+g}, {r['target_pitch_deg']:+g}): {r['note']}"
    return "not every example ran"


def example_rows(summary: dict[str, Any]) -> list[str]:
    """The table's header and one row per example (shared with the two-process form)."""
    head = (
        f"{'target roll/pitch deg':>22} {'achieved roll/pitch deg':>25} {'error deg':>10} "
        f"{'max twist mm':>12} {'sync at rest mm':>15} {'sync moving mm':>14} "
        f"{'duration s':>10}  result"
    )
    lines = [head, "-" * len(head)]
    for r in summary["examples"]:
        lines.append(
            f"{r['target_roll_deg']:>+10.3f} {r['target_pitch_deg']:>+10.3f}  "
            f"{r['achieved_roll_deg']:>+12.4f} {r['achieved_pitch_deg']:>+11.4f} "
            f"{r['attitude_error_deg']:>10.5f} {r['max_twist_mm']:>12.4f} "
            f"{r['sync_error_mm']:>15.4f} {r.get('max_sync_error_mm', math.nan):>14.4f} "
            f"{r['duration_s']:>10.2f}  "
            f"{'ok' if r['passed'] else 'FAILED ' + r['note']}"
        )
    return lines


def stderr_progress(text: str) -> None:
    print(f"wara demo: {text}", file=sys.stderr, flush=True)
