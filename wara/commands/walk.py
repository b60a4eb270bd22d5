"""``wara walk``: the end-to-end walk, and ``wara walk plan``: its plan alone.

    wara walk --steps 3 --lockstep --json      # simulator + service, N steps, judged
    wara walk plan --steps 3
    wara walk plan --steps 1 --start-x-s-mm -1000 --json

``wara walk``: exit 0 only if every step met its goals, 1 if one did not (or the service
latched a fault), 3 if the walk was refused before anything moved. ``wara walk plan``:
exit 0 the plan keeps every constraint, 3 refused (the binding constraint: its step,
phase, instant, value and limit). Both: 2 for bad arguments or configuration.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

from config import load_project, units
from config.numbers import decimal, integer
from config.schema import CANNOT_WALK
from ipc_app.planner.steering import OnAxis
from ipc_app.planner.walk import DIRECTIONS, WalkPlan, WalkStart, plan_walk, start_state
from wara.cli import EXIT_FAILED, EXIT_INFEASIBLE, EXIT_OK, UsageError, check_walk_steps
from wara.commands.plan import parse_four_mm, report


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "walk",
        help="the step-through walk (plan N steps)",
        description="The step-through walk of walking.md.",
    )
    p.add_argument("--config", default=None, help="project YAML (default: shipped Shanghai)")
    p.add_argument("--steps", type=integer, default=None, help="walk N steps (1..1000)")
    p.add_argument(
        "--lockstep", action="store_true", help="simulated time in one thread (no jitter figures)"
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", default=None, metavar="DIR", help="write DIR/walk.png")
    _direction_options(p, unloaded=False)
    p.add_argument(
        "--and-back",
        action="store_true",
        help="then the same steps the other way (the end where the walk started)",
    )
    p.set_defaults(func=run_walk_cmd)
    verbs = p.add_subparsers(dest="verb", metavar="VERB")
    plan = verbs.add_parser(
        "plan",
        help="plan N steps: phases, trajectories, leg shares, stability margin",
        description="Plan N steps from the measured state and check every constraint.",
    )
    plan.add_argument("--config", default=None, help="project YAML (default: shipped Shanghai)")
    plan.add_argument("--steps", type=integer, required=True, help="number of steps (1..1000)")
    plan.add_argument(
        "--start-x-s-mm",
        type=decimal,
        default=None,
        help="measured x_S, S's position along the rails, mm (default: the rear end of the step)",
    )
    plan.add_argument(
        "--start-main-mm",
        default=None,
        metavar="D1,D2,D3,D4",
        help="measured main-leg extensions from mid-stroke, mm (default: mid-stroke)",
    )
    plan.add_argument(
        "--start-upper-mm",
        default=None,
        metavar="D1,D2,D3,D4",
        help="measured upper extensions from mid-stroke, mm (default: mid-stroke)",
    )
    plan.add_argument(
        "--on-axis",
        default=None,
        metavar="CHAINAGE_M,HEADING_ERROR_DEG,OFFSET_MM",
        help="where the machine stands against the design axis: M's centre's chainage, its "
        "heading less the axis's and its offset, both positive to the left (default: on the "
        "axis at ring 1's rear joint face; docs/curves.md)",
    )
    plan.add_argument("--json", action="store_true", help="print one JSON object")
    _direction_options(plan)
    plan.set_defaults(func=run_plan)


def _direction_options(p: argparse.ArgumentParser, unloaded: bool = True) -> None:
    """``--direction`` and (the plan's) ``--unloaded``."""
    p.add_argument(
        "--direction",
        choices=DIRECTIONS,
        default="forward",
        help="forward (x increasing, the default) or back (the gait mirrored)",
    )
    if not unloaded:  # the simulator carries its part (docs/walking.md)
        return
    p.add_argument(
        "--unloaded",
        action="store_true",
        help="without the workpiece (the upper layer's body 'workpiece'): walking back "
        "from a fixed ring",
    )


def run_walk_cmd(args: argparse.Namespace) -> int:
    """``wara walk --steps N``: the simulator and the service walk N steps."""
    if args.steps is None:
        raise UsageError("wara walk: give --steps N (the walk) or the verb plan")
    check_walk_steps(args.steps)
    cfg = load_project(args.config)
    if not cfg.walks:
        raise UsageError(CANNOT_WALK)
    from wara.extras import require, require_realtime_simulator

    if args.plot:
        require("matplotlib", "--plot")
    if not args.lockstep:
        require_realtime_simulator()
    from wara.walk import run_walk

    other = "back" if args.direction == "forward" else "forward"
    directions = (args.direction, other) if args.and_back else (args.direction,)

    def say(msg: str) -> None:
        print(f"wara walk: {msg}", file=sys.stderr)

    from ipc_app.service.logs import configure_logging

    # the service's log to stderr as JSON lines (warnings and faults), never into stdout
    logs = configure_logging("WARNING")
    try:
        out = run_walk(
            args.config,
            args.steps,
            mode="lockstep" if args.lockstep else "realtime",
            plot_dir=Path(args.plot) if args.plot else None,
            progress=say,
            directions=directions,
        )
    finally:
        logs.stop()
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(render_walk(out))
    if out["refused"] is not None:
        print(f"wara walk: refused: {out['error']}", file=sys.stderr)
        return EXIT_INFEASIBLE
    if not out["passed"]:
        print(f"wara walk: FAILED: {'; '.join(out['missed'])}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def render_walk(out: dict[str, object]) -> str:
    lines = [
        f"{'step':>4} {'dist m':>8} {'dur s':>7} {'leg sync mm':>11} {'travel mm':>9} "
        f"{'margin m':>8} {'force':>6} {'transfer s':>10} {'att deg':>8}  ok"
    ]
    for r in out.get("steps", []):  # type: ignore[attr-defined]
        lines.append(
            f"{r['index']:>4} {r['distance_m']:8.4f} {r['duration_s']:7.1f} "
            f"{r['max_leg_sync_error_mm']:11.3f} {r['max_travel_sync_error_mm']:9.3f} "
            f"{r['min_stability_margin_m']:8.3f} {r['max_leg_force_ratio']:6.3f} "
            f"{r['transfer_time_s']:10.2f} {r['max_transfer_attitude_change_deg']:8.5f}  "
            f"{'yes' if r['passed'] else 'NO'}"
        )
    lines.append(
        f"distance {out.get('distance_m')} m, final mode {out.get('final_mode')}, "
        f"{'PASSED' if out.get('passed') else 'FAILED'}"
    )
    return "\n".join(lines)


def run_plan(args: argparse.Namespace) -> int:
    check_walk_steps(args.steps)
    if args.start_x_s_mm is not None and not math.isfinite(args.start_x_s_mm):
        raise UsageError("--start-x-s-mm must be a finite number")
    cfg = load_project(args.config)
    if not cfg.walks:
        raise UsageError(CANNOT_WALK)
    nominal = start_state(cfg)
    start = WalkStart(
        x_s_m=nominal.x_s_m if args.start_x_s_mm is None else units.mm(args.start_x_s_mm),
        main_extensions_m=parse_four_mm(args.start_main_mm, "--start-main-mm"),
        upper_extensions_m=parse_four_mm(args.start_upper_mm, "--start-upper-mm"),
        on_axis=_on_axis(args.on_axis),
    )
    try:
        result = plan_walk(cfg, args.steps, start, direction=args.direction, unloaded=args.unloaded)
    except ValueError as exc:  # unloaded without a workpiece body
        raise UsageError(str(exc)) from None
    return report(result, args.json, render)


def _on_axis(text: str | None) -> OnAxis | None:
    if text is None:
        return None
    parts = text.split(",")
    try:
        chainage, heading, offset = (float(v) for v in parts)
        return OnAxis(chainage, units.deg(heading), units.mm(offset))
    except ValueError:
        raise UsageError(
            f"--on-axis: expected three finite numbers CHAINAGE_M,HEADING_ERROR_DEG,OFFSET_MM, "
            f"got {text!r}"
        ) from None


def render(p: WalkPlan) -> str:
    d = p.to_dict()
    lines = [
        f"{p.steps} step(s) {p.direction}{', unloaded' if p.unloaded else ''} of "
        f"{p.step_length_m:.3f} m: {d['distance_m']:+.3f} m "
        f"in {d['duration_s']:.1f} s ({max(d['step_duration_s']):.1f} s per step)",
        "FEASIBLE" if p.feasible else "REFUSED",
        "",
        f"{'step':>4} {'phase':<6} {'':<14} {'start s':>8} {'dur s':>7} {'margin m':>9} "
        f"{'travel kN':>9}   leg forces at the end, kN (main 1-4, sub 1-4)",
    ]
    for ph in d["phases"]:
        forces = " ".join(f"{f:6.1f}" for f in ph["leg_forces_end_kn"].values())
        lines.append(
            f"{ph['step']:>4} {ph['phase']:<6} {ph['name']:<14} {ph['t_start_s']:8.2f} "
            f"{ph['duration_s']:7.2f} {ph['min_stability_margin_m']:9.3f} "
            f"{ph['max_travel_force_kn']:9.2f}   {forces}"
        )
    at = d["min_stability_margin_at"]
    lines += [
        "",
        f"least stability margin  {d['min_stability_margin_m']:.3f} m "
        f"(step {at['step']}, phase {at['phase']}; limit {p.min_margin_limit_m:.3f} m)",
    ]
    if any(t.turn_rad != 0.0 for t in p.turns):
        lines.append("")
        for t in d["steering"]:
            lines.append(
                f"step {t['step']} turns {t['turn_deg']:+.4f} deg (the axis "
                f"{t['axis_turn_deg']:+.4f}, steering back {t['correction_deg']:+.4f}); after "
                f"it: chainage {t['chainage_after_m']:.3f} m, heading error "
                f"{t['heading_error_after_deg']:+.4f} deg, offset {t['lateral_after_mm']:+.1f} mm"
            )
    if p.refusal is not None:
        lines += ["", f"Refused: {p.refusal.message}"]
    return "\n".join(lines)
