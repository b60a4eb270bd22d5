"""``wara sim dual-cylinder``: the paper's dual-cylinder synchronization study;
``wara sim delay-margin``: how much extra sensor delay the attitude hold tolerates.

Examples::

    wara sim dual-cylinder                         # both controllers, 120 s, summary table
    wara sim dual-cylinder --json                  # the figures as JSON
    wara sim dual-cylinder --controller ladrc --duration-s 30
    wara sim dual-cylinder --plot study.png        # positions, sync error, commands, pressures

    wara sim delay-margin                          # shipped project, 0-50 ms of delay
    wara sim delay-margin my.yaml --delays-ms 0,10,20 --json

Exit code 0 when the goals hold (dual-cylinder: LADRC sync error within the paper's
0.07 mm after the transient, PID worse by the scenario's ratio; delay-margin: the hold
stable up to ``--required-ms`` and every loop's modelled margin at least that), 1 when not.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from config.numbers import decimal
from config.scenario import load_scenario
from wara.cli import EXIT_FAILED, EXIT_OK, UsageError
from wara.extras import require
from wara.studies import CONTROLLERS, DEFAULT_DELAYS_MS, ControllerKind


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
        "--duration-s", type=decimal, default=None, help="simulated time (default: the scenario's)"
    )
    d.add_argument("--plot", metavar="FILE.png", default=None, help="write the study's figure")
    d.add_argument("--json", action="store_true", help="print the figures as JSON")
    d.add_argument("--quiet", action="store_true", help="no progress indicator on stderr")
    d.set_defaults(func=_dual_cylinder)
    m = studies.add_parser(
        "delay-margin",
        help="extra sensor delay the attitude hold tolerates (lockstep HIL, one run per delay)",
        description="Lockstep simulator and service: one target, then a hold, once per "
        "delay, with every rod-position frame held back by that delay on the wire. "
        "Reports whether the hold stays stable (docs/control.md, 'Delay margin').",
    )
    m.add_argument(
        "project", nargs="?", default=None, help="project YAML (default: shipped project)"
    )
    m.add_argument("--config", default=None, help="project YAML (the same as PROJECT)")
    m.add_argument(
        "--delays-ms",
        default=",".join(f"{d:g}" for d in DEFAULT_DELAYS_MS),
        help="comma-separated extra delays, ms (default: %(default)s)",
    )
    m.add_argument("--target", default="2,1", help="roll,pitch in deg (default: Example 1)")
    m.add_argument("--hold-s", type=decimal, default=20.0, help="hold after the motion, s")
    m.add_argument(
        "--sim-speed",
        type=decimal,
        default=1.0,
        help="simulated seconds per second of the service's clock, (0, 1]: a simulator "
        "slower than the service (an emulated CPU); the delays are the simulator's "
        "(default: %(default)g)",
    )
    m.add_argument(
        "--required-ms",
        type=decimal,
        default=None,
        help="exit 0 only if the hold is stable up to this delay and every loop's modelled "
        "margin reaches it (default: the project's control.delay_margin_ms)",
    )
    m.add_argument("--json", action="store_true", help="print the figures as JSON")
    m.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    m.set_defaults(func=_delay_margin)


def _floats(text: str, what: str, count: int | None = None) -> list[float]:
    try:
        values = [float(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise UsageError(f"{what}: {text!r} is not a comma-separated list of numbers") from None
    if not values or (count is not None and len(values) != count):
        need = f"{count} numbers" if count else "at least one number"
        raise UsageError(f"{what}: {text!r} needs {need}")
    return values


def _delay_margin(args: argparse.Namespace) -> int:
    from config import load_project
    from ipc_app.service.logs import configure_logging
    from wara.studies.delay_margin import render, run_study

    delays = _floats(args.delays_ms, "--delays-ms")
    if any(not (0 <= d <= 1000) for d in delays):
        raise UsageError(f"--delays-ms: each delay must be within 0-1000 ms, got {delays}")
    roll, pitch = _floats(args.target, "--target", 2)
    if not args.hold_s > 0:
        raise UsageError(f"--hold-s must be > 0, got {args.hold_s}")
    if not 0 < args.sim_speed <= 1:
        raise UsageError(f"--sim-speed must be in (0, 1], got {args.sim_speed}")
    if args.project is not None and args.config is not None and args.project != args.config:
        raise UsageError(f"give the project once: {args.project} or --config {args.config}")
    path = args.project if args.project is not None else args.config
    if args.required_ms is not None and not args.required_ms > 0:
        raise UsageError(f"--required-ms must be > 0, got {args.required_ms}")
    cfg = load_project(path)

    def say(text: str) -> None:
        if not args.quiet:
            print(f"wara sim delay-margin: {text}", file=sys.stderr, flush=True)

    # the service's own log: warnings and faults only (JSON lines on stderr), so the
    # progress lines stay readable
    logs = configure_logging("WARNING")
    try:
        report = run_study(
            cfg,
            path,
            delays_ms=delays,
            target=(roll, pitch),
            hold_s=args.hold_s,
            required_ms=args.required_ms,
            progress=say,
            sim_speed=args.sim_speed,
        )
    finally:
        logs.stop()
    print(json.dumps(report, indent=2) if args.json else render(report))
    return EXIT_OK if report["passed"] else EXIT_FAILED


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
    if args.plot is not None:
        require("matplotlib", "--plot")
    from wara.studies.dual_cylinder import StudyRun, evaluate, run_study

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
