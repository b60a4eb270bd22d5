"""``wara sim dual-cylinder``: the paper's dual-cylinder synchronization study.

Examples::

    wara sim dual-cylinder                         # both controllers, 120 s, summary table
    wara sim dual-cylinder --json                  # the figures as JSON
    wara sim dual-cylinder --controller ladrc --duration-s 30
    wara sim dual-cylinder --plot study.png        # positions, sync error, commands, pressures

Exit code 0 when the scenario's goals hold (LADRC sync error within the paper's
0.07 mm after the transient; PID worse by the scenario's ratio), 1 when not.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from config.scenario import load_scenario
from wara.cli import EXIT_FAILED, EXIT_OK, UsageError
from wara.studies.dual_cylinder import CONTROLLERS, ControllerKind, StudyRun, evaluate, run_study


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("sim", help="closed-loop simulation studies (plant + controllers)")
    studies = p.add_subparsers(dest="study", metavar="STUDY")
    studies.required = True
    d = studies.add_parser(
        "dual-cylinder",
        help="the paper's dual-cylinder synchronization study (LADRC vs PID)",
        description="Two parallel cylinders of paper Table 3 track one reference under "
        "different loads, with load noise from 80 s; reports synchronization and tracking.",
    )
    d.add_argument(
        "--scenario",
        default=None,
        help="scenario YAML (default: config/scenarios/dual_cylinder.yaml)",
    )
    d.add_argument("--controller", choices=[*CONTROLLERS, "both"], default="both")
    d.add_argument(
        "--duration-s", type=float, default=None, help="simulated time (default: the scenario's)"
    )
    d.add_argument("--plot", metavar="FILE.png", default=None, help="write the study's figure")
    d.add_argument("--json", action="store_true", help="print the figures as JSON")
    d.add_argument("--quiet", action="store_true", help="no progress indicator on stderr")
    d.set_defaults(func=_dual_cylinder)


class _Progress:
    """A one-line progress indicator on stderr (redrawn on a terminal, sparse otherwise)."""

    def __init__(self, label: str, duration_s: float, enabled: bool) -> None:
        self.label = label
        self.duration_s = duration_s
        self.enabled = enabled
        self.tty = sys.stderr.isatty()
        self._last = -1

    def __call__(self, fraction: float) -> None:
        if not self.enabled:
            return
        pct = int(fraction * 100)
        step = 2 if self.tty else 25
        if pct // step == self._last and pct < 100:
            return
        self._last = pct // step
        msg = f"wara sim: {self.label} {pct:3d}% ({fraction * self.duration_s:5.1f} s simulated)"
        if self.tty:
            end = "\n" if pct >= 100 else ""
            print(f"\r{msg}", end=end, file=sys.stderr, flush=True)
        else:
            print(msg, file=sys.stderr, flush=True)


def _dual_cylinder(args: argparse.Namespace) -> int:
    scenario = load_scenario(args.scenario)
    duration = scenario.duration_s if args.duration_s is None else args.duration_s
    if not duration > scenario.transient_s:
        raise UsageError(
            f"--duration-s ({duration}) must be longer than the scenario's initial transient "
            f"({scenario.transient_s} s), which the metrics leave out"
        )
    if args.plot is not None and not Path(args.plot).parent.exists():
        raise UsageError(f"--plot {args.plot}: directory {Path(args.plot).parent} does not exist")
    kinds: list[ControllerKind] = (
        list(CONTROLLERS) if args.controller == "both" else [args.controller]
    )
    runs: dict[str, StudyRun] = {}
    for kind in kinds:
        progress = _Progress(kind, duration, enabled=not args.quiet)
        runs[kind] = run_study(scenario, kind, duration_s=duration, progress=progress)
    report, met = evaluate(runs, scenario)
    if args.plot is not None:
        from wara.studies.plots import plot_runs

        report["plot"] = str(plot_runs(runs, scenario, args.plot))
    if args.json:
        print(json.dumps(report, indent=2))
    else:
        _print_table(report)
    return EXIT_OK if met else EXIT_FAILED


def _fmt(value: Any, spec: str = ".4f") -> str:
    return "-" if value is None else format(value, spec)


def _print_table(report: dict[str, Any]) -> None:
    ctrls = report["controllers"]
    w = report["windows_s"]
    print(
        f"{report['scenario']}: {report['duration_s']:.0f} s at {report['control_rate_hz']:.0f} Hz"
    )
    print(f"sync error = {report['sync_error']}; windows (s): " + ", ".join(
        f"{k} [{v[0]:g}, {v[1]:g})" for k, v in w.items()
    ))  # fmt: skip
    rows = [
        ("sync error max, after transient [mm]", "sync_error_max_mm"),
        ("sync error rms, after transient [mm]", "sync_error_rms_mm"),
        ("sync error max, before noise [mm]", "sync_error_max_mm_before_noise"),
        ("sync error max, with noise [mm]", "sync_error_max_mm_after_noise"),
        ("sync error rms, with noise [mm]", "sync_error_rms_mm_after_noise"),
        ("tracking error rms [mm]", "tracking_error_rms_mm"),
        ("settling time after last move [s]", "settling_time_s"),
        ("realtime factor [-]", "realtime_factor"),
    ]
    names = list(ctrls)
    print(f"{'':40s}" + "".join(f"{n:>12s}" for n in names))
    for label, key in rows:
        spec = ".1f" if key == "realtime_factor" else ".4f"
        print(f"{label:40s}" + "".join(f"{_fmt(ctrls[n].get(key), spec):>12s}" for n in names))
    if "pid_to_ladrc_sync_error_max_ratio" in report:
        print(f"PID / LADRC sync error max: {report['pid_to_ladrc_sync_error_max_ratio']:.2f}x")
    for goal, ok in report["goals"].items():
        print(f"goal {goal}: {'met' if ok else 'NOT MET'}")
    if "plot" in report:
        print(f"figure: {report['plot']}")
