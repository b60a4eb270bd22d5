"""``wara plan``: plan one attitude adjustment of the arc part.

    wara plan --roll-deg -3 --pitch-deg 2
    wara plan --roll-deg 2 --pitch-deg 1 --objective peak_pressure --json
    wara plan --roll-deg 5 --pitch-deg -1 --method ldw_pso --seed 7

Exit 0: feasible plan; 3: unreachable target (``feasible: false`` and the binding
reasons); 2: bad arguments or configuration.
"""

from __future__ import annotations

import argparse
import json
import math
from collections.abc import Callable
from typing import Any

from config import load_project, units
from config.numbers import decimal, integer, parse_decimals
from ipc_app.planner import METHODS, OBJECTIVES, Plan, plan
from wara.cli import EXIT_INFEASIBLE, EXIT_OK, UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan",
        help="plan an attitude adjustment (allocation, pressures, trajectory)",
        description="Split a target workpiece attitude between the lower and upper layer.",
    )
    p.add_argument("--config", default=None, help="project YAML (default: shipped Shanghai)")
    p.add_argument("--roll-deg", type=decimal, required=True, help="target workpiece roll, deg")
    p.add_argument("--pitch-deg", type=decimal, required=True, help="target workpiece pitch, deg")
    p.add_argument(
        "--objective",
        choices=OBJECTIVES,
        default=None,
        help="what to minimize (default: the project's planner.objective)",
    )
    p.add_argument(
        "--method",
        choices=METHODS,
        default=None,
        help="planner (default: the project's planner.method)",
    )
    p.add_argument("--seed", type=integer, default=None, help="seed of ldw_pso")
    p.add_argument(
        "--start-upper-mm",
        default=None,
        metavar="D1,D2,D3,D4",
        help="measured upper extensions from mid-stroke, mm (default: mid-stroke)",
    )
    p.add_argument(
        "--start-lower-mm",
        default=None,
        metavar="D1,D2,D3,D4",
        help="measured lower extensions from mid-stroke, mm (default: mid-stroke)",
    )
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=run)


def report(result: Any, as_json: bool, render: Callable[[Any], str]) -> int:
    """Print a plan (``to_dict()`` as JSON, or ``render(result)``); exit 0 if it is
    feasible, else 3 (the plan and walk commands)."""
    print(json.dumps(result.to_dict(), indent=2) if as_json else render(result))
    return EXIT_OK if result.feasible else EXIT_INFEASIBLE


def parse_four_mm(text: str | None, option: str) -> tuple[float, float, float, float]:
    """``"d1,d2,d3,d4"`` in mm -> four values in m."""
    if text is None:
        return (0.0, 0.0, 0.0, 0.0)
    try:
        values = parse_decimals(text, 4)
    except ValueError as exc:
        raise UsageError(f"{option} expects four numbers in mm, e.g. 10,-5,-10,5: {exc}") from None
    return (units.mm(values[0]), units.mm(values[1]), units.mm(values[2]), units.mm(values[3]))


def run(args: argparse.Namespace) -> int:
    if not (math.isfinite(args.roll_deg) and math.isfinite(args.pitch_deg)):
        raise UsageError("--roll-deg and --pitch-deg must be finite numbers")
    if abs(args.roll_deg) >= 90 or abs(args.pitch_deg) >= 90:
        raise UsageError("--roll-deg and --pitch-deg must be within ±90 deg")
    cfg = load_project(args.config)
    result = plan(
        cfg,
        args.roll_deg,
        args.pitch_deg,
        objective=args.objective,
        method=args.method,
        seed=args.seed,
        start_upper_m=parse_four_mm(args.start_upper_mm, "--start-upper-mm"),
        start_lower_m=parse_four_mm(args.start_lower_mm, "--start-lower-mm"),
    )
    return report(result, args.json, render_table)


def render_table(p: Plan) -> str:
    d = p.to_dict()
    lines = [
        f"Target roll {d['target']['roll_deg']:+.3f} deg, pitch {d['target']['pitch_deg']:+.3f} deg"
        f"   method {p.method}, objective {p.objective}",
        "FEASIBLE" if p.feasible else "NOT FEASIBLE",
        "",
        f"{'layer':<6} {'roll deg':>9} {'pitch deg':>9}   "
        + "  ".join(f"{'cyl ' + str(i) + ' mm':>9}" for i in range(1, 5))
        + "   "
        + "  ".join(f"{'p' + str(i) + ' MPa':>7}" for i in range(1, 5)),
    ]
    for name in ("upper", "lower"):
        lay = d[name]
        ext = "  ".join(f"{units.to_mm(x):+9.2f}" for x in lay["displacement_m"])
        prs = "  ".join(f"{x:7.3f}" for x in d["pressure_mpa"][name])
        lines.append(f"{name:<6} {lay['roll_deg']:+9.4f} {lay['pitch_deg']:+9.4f}   {ext}   {prs}")
    lines += [
        "",
        f"objective value      {p.objective_value:.6g} {d['objective_unit']}",
        f"sum of pressures     {d['sum_pressure_mpa']:.3f} MPa",
        f"peak pressure        {d['peak_pressure_mpa']:.3f} MPa",
        f"attitude error       {p.attitude_error_rad:.2e} rad",
        f"yaw residual         {d['yaw_residual_deg']:+.4f} deg (rotation cylinders take it out)",
        f"trajectory duration  {p.trajectory_duration_s:.2f} s",
        f"solve time           {units.to_ms(p.solve_time_s):.2f} ms ({p.evaluations} candidates; "
        f"{p.solve_time_share_percent:.2g} % of the {p.task_time_s / 60:g} min assembly task)",
    ]
    if p.reasons:
        lines += ["", "Why not feasible:"] + [f"  - {r}" for r in p.reasons]
    return "\n".join(lines)
