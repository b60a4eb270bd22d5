"""``wara place plan``: the new part's target pose from the previous part's as-built pose.

    wara place plan --ring 5 --json                        # previous part at its design
    wara place plan --ring 5 --previous-deviation 6,0,0,0,0
    wara place plan --ring 5 --survey ring4-face.csv
    wara place plan --from-store --db acceptance.sqlite    # the store's last ring

Exit 0: a target keeps every Table 4 limit and the steering-back bound, and every move
fits its actuators; 3: refused (the binding limit and by how much); 2: bad arguments or
configuration. docs/placement.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from acceptance.store import AcceptanceStore, StoreError, default_db_path
from config import load_project, units
from config.numbers import integer, parse_decimals
from config.schema import ProjectConfig
from ipc_app.model.placement import Pose, compose, design_pose, sheet_deviation, to_ring_frame
from ipc_app.planner.placement import PlacementPlan, plan_from_deviation, plan_target
from ipc_app.planner.survey import SurveyError, as_built_problems, read_survey
from wara.cli import EXIT_FAILED, EXIT_INFEASIBLE, EXIT_OK, UsageError
from wara.commands.plan import report


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "place",
        help="place the arc part in six DOF: plan the target, move there on the simulator",
        description="Placing the arc part: the target pose from the survey (docs/placement.md).",
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True
    plan = verbs.add_parser(
        "plan",
        help="the new part's target pose and its expected Table 4 figures",
        description="Plan the new part's target pose from the previous part's as-built pose.",
    )
    plan.add_argument("--config", default=None, help="project YAML (default: shipped Shanghai)")
    plan.add_argument(
        "--ring",
        type=integer,
        default=None,
        help="the ring to place (default 2; with --from-store: the next)",
    )
    src = plan.add_mutually_exclusive_group()
    src.add_argument(
        "--previous-deviation",
        default=None,
        metavar="Y_MM,Z_MM,ROLL_DEG,PITCH_DEG,YAW_DEG",
        help="the previous part's deviation from its design (default: none)",
    )
    src.add_argument("--survey", default=None, metavar="FILE.csv", help="survey of its front face")
    src.add_argument("--from-store", action="store_true", help="the acceptance store's last ring")
    plan.add_argument("--db", default=None, metavar="PATH", help="acceptance database")
    plan.add_argument("--json", action="store_true", help="print one JSON object")
    plan.set_defaults(func=run_plan)
    run = verbs.add_parser(
        "run",
        help="plan and move to the target on the HIL simulator (lockstep)",
        description="Plan the target and move there on the HIL simulator in simulated time; "
        "judge the simulator's truth against the goals.",
    )
    run.add_argument("--config", default=None, help="project YAML (default: shipped Shanghai)")
    run.add_argument("--ring", type=integer, default=2, help="the ring to place (default 2)")
    run.add_argument(
        "--previous-deviation",
        default=None,
        metavar="Y_MM,Z_MM,ROLL_DEG,PITCH_DEG,YAW_DEG",
        help="the previous part's deviation from its design (default: none)",
    )
    run.add_argument(
        "--lockstep", action="store_true", required=True, help="simulated time, one thread"
    )
    run.add_argument("--json", action="store_true", help="print one JSON object")
    run.set_defaults(func=run_move)


def _placement_config(path: str | None) -> ProjectConfig:
    cfg = load_project(path)
    if cfg.placement is None:
        raise UsageError("the project has no placement section (and tunnel.alignment)")
    return cfg


def parse_deviation(text: str) -> Pose:
    try:
        v = parse_decimals(text, 5)
    except ValueError as exc:
        raise UsageError(
            f"--previous-deviation expects five numbers Y_MM,Z_MM,ROLL_DEG,PITCH_DEG,YAW_DEG: {exc}"
        ) from None
    if max(abs(v[0]), abs(v[1])) > 50 or max(abs(x) for x in v[2:]) > 10:
        raise UsageError("--previous-deviation: at most 50 mm and 10 deg (a typo, not a survey)")
    return sheet_deviation(*v)


def attached_pose(store: AcceptanceStore, ring: int) -> Pose | None:
    """The as-built pose a survey (``wara survey import --db``) or a ring cycle attached
    to ``ring`` (``final_attitude.as_built_pose`` of its latest plan), in its own tunnel
    frame; None when there is none."""
    plan = store.latest_plan(ring)
    att = plan.final_attitude if plan is not None else None
    if not att or "as_built_pose" not in att:
        return None
    try:
        return Pose.from_dict(att["as_built_pose"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UsageError(f"ring {ring}: the attached as-built pose is unusable: {exc}") from None


def as_built_from_store(cfg: ProjectConfig, store: AcceptanceStore) -> tuple[int, Pose]:
    """The store's last ring and its part's as-built pose in its own tunnel frame: the
    pose a survey or a cycle attached to it (``final_attitude.as_built_pose``), else
    the design pose moved by the record's centreline deviations and angles (an angle
    not measured counts as 0)."""
    records = {r.ring: r for r in store.current()}
    rings = set(records) | store.rings_with_plan()
    if not rings:
        raise UsageError(f"{store.path}: no ring recorded yet")
    ring = max(rings)
    pose = attached_pose(store, ring)
    if pose is not None:
        problems = as_built_problems(cfg, ring, pose)
        if problems:  # written around this software, or in another frame
            raise UsageError(f"{store.path}: ring {ring}'s as-built pose: {'; '.join(problems)}")
        return ring, pose
    if ring not in records:
        raise UsageError(f"ring {ring}: neither a survey record nor an as-built pose")
    v = records[ring].measurement.values

    def deg(key: str) -> float:
        x = v.get(key)
        return 0.0 if x is None else units.deg(x)

    dev = Pose(
        0.0,
        units.mm(v["centreline_deviation_x_mm"] or 0.0),
        units.mm(v["centreline_deviation_y_mm"] or 0.0),
        deg("tilt_angle_deg"),
        deg("pitch_angle_deg"),
        deg("rotation_angle_deg"),
    )
    d = design_pose(cfg, ring)
    return ring, compose(d, dev)


def run_plan(args: argparse.Namespace) -> int:
    cfg = _placement_config(args.config)
    if args.ring is not None and not 2 <= args.ring <= 99_999:
        raise UsageError(
            f"--ring must be within 2..99999 (a previous ring to build on), got {args.ring}"
        )
    result: PlacementPlan
    if args.from_store:
        path = args.db or default_db_path()
        try:
            with AcceptanceStore.open(path, create=False) as store:
                prev_ring, pose = as_built_from_store(cfg, store)
        except StoreError as exc:
            raise UsageError(str(exc)) from None
        ring = prev_ring + 1 if args.ring is None else args.ring
        if ring != prev_ring + 1:
            raise UsageError(
                f"--ring {ring}: the store's last ring is {prev_ring}; place {prev_ring + 1}"
            )
        result = plan_target(cfg, to_ring_frame(cfg, pose, prev_ring, ring), ring)
    elif args.survey is not None:
        ring = 2 if args.ring is None else args.ring
        try:
            fit = read_survey(cfg, ring - 1, args.survey)
        except SurveyError as exc:  # one line per problem
            raise UsageError(str(exc)) from None
        if not fit.accepted:
            raise UsageError(f"{args.survey}: survey refused: {'; '.join(fit.reasons)}")
        result = plan_target(cfg, to_ring_frame(cfg, fit.pose, ring - 1, ring), ring)
    else:
        ring = 2 if args.ring is None else args.ring
        dev = (
            Pose() if args.previous_deviation is None else parse_deviation(args.previous_deviation)
        )
        result = plan_from_deviation(cfg, ring, dev)
    return report(result, args.json, render)


def render(p: PlacementPlan) -> str:
    d: dict[str, Any] = p.to_dict()
    t, dev = d["target"], d["target_deviation"]
    lines = [
        f"ring {p.ring}: {'FEASIBLE' if p.feasible else 'REFUSED'}",
        "target pose in the ring's tunnel frame: "
        + ", ".join(f"{k} {v:+.3f}" for k, v in t.items()),
        "deviation from the design: " + ", ".join(f"{k} {v:+.3f}" for k, v in dev.items()),
        "",
        f"{'Table 4 item':<28} {'expected':>10} {'limit':>8}  verdict",
    ]
    for key, item in d["table4"].items():
        lim = "-" if item["limit"] is None else f"{item['limit']:g}"
        lim = f">={lim}" if item.get("at_least") else lim
        verdict = "not judged" if item["passed"] is None else ("ok" if item["passed"] else "OVER")
        lines.append(f"{key:<28} {item['value']:>10.3f} {lim:>8}  {verdict}")
    lines += ["", "moves from mid-stroke (mm):"]
    for a in d["actuators"]:
        ext = ", ".join(f"{e:+.3f}" for e in a["extensions_mm"])
        lines.append(f"  {a['group']:<34} {ext}  ({'ok' if a['ok'] else 'REFUSED'})")
    if p.reasons:
        lines += ["", *(f"Refused: {r}" for r in p.reasons)]
    return "\n".join(lines)


def run_move(args: argparse.Namespace) -> int:
    from wara.place import run_place  # the simulator: only here

    cfg = _placement_config(args.config)
    if not 2 <= args.ring <= 99_999:
        raise UsageError(f"--ring must be within 2..99999, got {args.ring}")
    dev = Pose() if args.previous_deviation is None else parse_deviation(args.previous_deviation)
    from ipc_app.service.logs import configure_logging

    # the service's log to stderr as JSON lines (warnings and faults), never into stdout
    logs = configure_logging("WARNING")
    try:
        result = run_place(args.config, args.ring, dev, cfg=cfg)
    finally:
        logs.stop()
    if args.json:
        print(json.dumps(result, indent=2))
    else:
        print(render_move(result))
    if result["refused"] is not None:
        return EXIT_INFEASIBLE
    if not result["passed"]:
        print(f"wara place run: FAILED: {'; '.join(result.get('missed') or [])}", file=sys.stderr)
        return EXIT_FAILED
    return EXIT_OK


def render_move(r: dict[str, Any]) -> str:
    if "goals" not in r:
        return ("REFUSED: " if r["refused"] else "FAILED: ") + "; ".join(
            r.get("reasons") or [str(r.get("error"))]
        )
    e = r["error_from_target"]
    lines = [
        f"ring {r['ring']}: {'PASSED' if r['passed'] else 'FAILED'} "
        f"(phases: {', '.join(f'{k} {v:.2f} s' for k, v in r['phase_times_s'].items())})",
        "error from the target on the simulator's truth: "
        + ", ".join(f"{k} {v:+.4f}" for k, v in e.items()),
        f"gap error {r['gap_error_mm']:+.4f} mm; largest sync error "
        f"{r['max_sync_error_mm']:.3f} mm",
        "",
        f"{'goal':<28} {'value':>10} {'limit':>8}  verdict",
    ]
    for key, g in r["goals"].items():
        lines.append(
            f"{key:<28} {g['value']:>10.4f} {g['limit']:>8g}  {'ok' if g['met'] else 'MISSED'}"
        )
    lines += ["", f"{'Table 4 item (truth)':<28} {'value':>10} {'limit':>8}"]
    for key, item in r["table4_truth"].items():
        lim = "-" if item["limit"] is None else f"{item['limit']:g}"
        lim = f">={lim}" if item.get("at_least") else lim
        lines.append(f"{key:<28} {item['value']:>10.3f} {lim:>8}")
    return "\n".join(lines)
