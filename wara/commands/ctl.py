"""``wara ctl``: talk to the running service over its local control socket.

    wara ctl adjust --roll-deg -3 --pitch-deg 2
    wara ctl status [--json]
    wara ctl stop
    wara ctl reset                  # from ABORTED: clear (PLC fault reset), then reset
    wara ctl clear | hold | unhold
    wara ctl unit-mode PRODUCTION|MAINTENANCE|MANUAL
    wara ctl jog --cylinder main_leg_1 --distance-mm 2   # MANUAL only
    wara ctl place --ring 5 --previous-deviation 6,-6,0,0,0.03
    wara ctl home                   # each attitude layer to mid-stroke, level
    wara ctl locate --chainage 812.4 --heading-error 0.02 --offset -3   # surveyed
    wara ctl --socket /tmp/wara-test/ctl.sock status

The socket defaults to the service's (``$WARA_CTL_SOCKET``, ``/run/wara/ctl.sock`` on an
installed IPC, see :func:`ipc_app.service.ctl.default_socket_path`); it is owner-only,
so run as the service user (``sudo -u wara wara ctl status``).

Exit codes: 0 accepted; 1 refused by the service (e.g. adjust while ABORTED, reset while
the cause is still present, or ``busy`` after the retries); 3 infeasible target (the
planner's reasons are printed); 2 bad arguments or no service listening (one line on
stderr). A full listen queue and a ``busy`` answer are retried for up to 5 s.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

from config.numbers import decimal, integer, name
from ipc_app.service.ctl import CtlError, request
from wara.cli import EXIT_FAILED, EXIT_INFEASIBLE, EXIT_OK, UsageError, check_walk_steps


def register(sub: argparse._SubParsersAction) -> None:
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument(
        "--socket",
        default=argparse.SUPPRESS,
        metavar="PATH",
        help="control socket of the service (default: the service's)",
    )
    common.add_argument("--json", action="store_true", help="print the reply as JSON")
    p = sub.add_parser(
        "ctl",
        parents=[common],
        help="control the running service (adjust, status, stop, reset, hold, jog, ...)",
        description="Send one command to the running W-ARa service over its local socket.",
    )
    verbs = p.add_subparsers(dest="verb", metavar="VERB", parser_class=type(p))
    verbs.required = True
    adj = verbs.add_parser("adjust", parents=[common], help="plan and run an adjustment")
    adj.add_argument("--roll-deg", type=decimal, required=True, help="target workpiece roll, deg")
    adj.add_argument("--pitch-deg", type=decimal, required=True, help="target workpiece pitch, deg")
    adj.add_argument(
        "--timeout-s", type=decimal, default=60.0, help="wait this long for the answer"
    )
    verbs.add_parser("status", parents=[common], help="mode, faults, loop statistics")
    verbs.add_parser("stop", parents=[common], help="controlled stop: valves closed, load held")
    verbs.add_parser(
        "reset", parents=[common], help="ABORTED (clear first) or STOPPED -> IDLE, cause gone"
    )
    verbs.add_parser("clear", parents=[common], help="ABORTED -> STOPPED once the cause is gone")
    verbs.add_parser("hold", parents=[common], help="EXECUTE -> HELD: stop the motion where it is")
    verbs.add_parser("unhold", parents=[common], help="HELD -> EXECUTE: the motion goes on")
    um = verbs.add_parser("unit-mode", parents=[common], help="PackML unit mode")
    um.add_argument("unit_mode", choices=("PRODUCTION", "MAINTENANCE", "MANUAL"))
    jog = verbs.add_parser("jog", parents=[common], help="MANUAL: move one cylinder slowly")
    jog.add_argument(
        "--cylinder", type=name, required=True, help="attitude cylinder id, e.g. main_leg_1"
    )
    jog.add_argument("--distance-mm", type=decimal, required=True, help="rod travel, mm (+ out)")
    walk = verbs.add_parser("walk", parents=[common], help="walk N steps (planned first)")
    walk.add_argument("--steps", type=integer, required=True, help="number of steps (1..1000)")
    walk.add_argument(
        "--direction",
        default="forward",
        help="forward (x increasing, the default) or back (the gait mirrored)",
    )
    walk.add_argument(
        "--unloaded",
        action="store_true",
        help="the statics without the workpiece (walking back from a fixed ring)",
    )
    place = verbs.add_parser(
        "place", parents=[common], help="place ring N's part at its planned target pose"
    )
    place.add_argument(
        "--ring", type=integer, required=True, help="the ring being built (1..99999)"
    )
    place.add_argument(
        "--previous-deviation",
        default=None,
        metavar="Y_MM,Z_MM,ROLL_DEG,PITCH_DEG,YAW_DEG",
        help="the previous part's deviation from its design (default none)",
    )
    cyc = verbs.add_parser(
        "cycle", parents=[common], help="ring N's cycle: walk, place, fixing, ... walk back"
    )
    cyc.add_argument("--ring", type=integer, required=True, help="the ring being built (2..99999)")
    prev = cyc.add_mutually_exclusive_group()
    prev.add_argument(
        "--previous-deviation",
        default=None,
        metavar="Y_MM,Z_MM,ROLL_DEG,PITCH_DEG,YAW_DEG",
        help="the previous part's deviation from its design (default none)",
    )
    prev.add_argument(
        "--from-store",
        action="store_true",
        help="the previous part's as-built pose from the acceptance store (--db)",
    )
    cyc.add_argument("--db", default=None, metavar="PATH", help="acceptance store to read")
    cyc.add_argument(
        "--walk-steps",
        type=integer,
        default=None,
        help="steps to the ring (default cycle.walk_steps)",
    )
    cyc.add_argument(
        "--walk-back-loaded",
        action="store_true",
        help="walk back with the part's weight in the statics (default: unloaded)",
    )
    fixed = verbs.add_parser(
        "confirm-fixed", parents=[common], help="the cycle's part is fixed: release it"
    )
    fixed.add_argument("--user", type=name, required=True, help="who confirms (audited)")
    survey = verbs.add_parser(
        "survey", parents=[common], help="the cycle's survey: a total-station file or the store"
    )
    src = survey.add_mutually_exclusive_group(required=True)
    src.add_argument("file", nargs="?", default=None, help="survey CSV (as wara survey import)")
    src.add_argument(
        "--from-store",
        action="store_true",
        help="the as-built pose wara survey import --db attached to the cycle's ring",
    )
    survey.add_argument("--db", default=None, metavar="PATH", help="acceptance store to read")
    loc = verbs.add_parser(
        "locate",
        parents=[common],
        help="where the machine stands, surveyed: the next walk steers from it",
    )
    loc.add_argument(
        "--chainage", type=decimal, required=True, metavar="M", help="M's centre's chainage, m"
    )
    loc.add_argument(
        "--heading-error",
        type=decimal,
        required=True,
        metavar="DEG",
        help="the machine's heading less the axis's, deg, positive to the left",
    )
    loc.add_argument(
        "--offset",
        type=decimal,
        required=True,
        metavar="MM",
        help="M's centre's offset from the axis, mm, positive to the left",
    )
    from ipc_app.service.ctl_protocol import TABLE

    for row in TABLE.values():  # the motions without arguments (home), from the protocol
        if row.motion is not None and not row.args:
            verbs.add_parser(row.name.replace("_", "-"), parents=[common], help=row.what)
    p.set_defaults(func=run)


def _cycle_fields(args: argparse.Namespace) -> dict[str, Any]:
    """``wara ctl cycle``'s request: the previous part from the sheet or the store."""
    from wara.commands.place import parse_deviation

    if not 2 <= args.ring <= 99_999:
        raise UsageError(f"--ring must be within 2..99999, got {args.ring}")
    fields: dict[str, Any] = {"ring": args.ring, "walk_back_unloaded": not args.walk_back_loaded}
    if args.walk_steps is not None:
        if not 0 <= args.walk_steps <= 1000:
            raise UsageError(f"--walk-steps must be within 0..1000, got {args.walk_steps}")
        fields["walk_steps"] = args.walk_steps
    if args.from_store:
        fields["previous_pose"] = _store_pose(args.db, args.ring - 1)
    elif args.previous_deviation is not None:
        d = parse_deviation(args.previous_deviation).to_dict()
        fields["previous_deviation"] = [
            d[k] for k in ("y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")
        ]
    return fields


def _store_pose(db: str | None, ring: int) -> list[float]:
    """The as-built pose attached to ``ring`` in the acceptance store (by ``wara survey
    import --db`` or a cycle's record), mm and deg in the ring's own T, as the six
    numbers the control channel takes (``POSE_DICT_KEYS``)."""
    from acceptance.store import AcceptanceStore, StoreError, default_db_path
    from ipc_app.model.placement import POSE_DICT_KEYS
    from wara.commands.place import attached_pose

    path = db or default_db_path()
    try:
        with AcceptanceStore.open(path, create=False) as store:
            pose = attached_pose(store, ring)
    except StoreError as exc:
        raise UsageError(str(exc)) from None
    if pose is None:
        raise UsageError(f"{path}: ring {ring} has no as-built pose (wara survey import --db)")
    d = pose.to_dict()
    return [d[k] for k in POSE_DICT_KEYS]


def _survey_fields(args: argparse.Namespace) -> dict[str, Any]:
    """``wara ctl survey``'s request: the file's points, or the store's pose for the
    ring the service's cycle is at."""
    from acceptance.store import StoreError, check_store, default_db_path
    from ipc_app.planner.survey import SurveyError, read_survey_points
    from ipc_app.service.requests import MAX_SURVEY_POINTS

    if args.from_store:
        try:  # the store first: a bad --db asks the service nothing
            check_store(args.db or default_db_path(), create=False)
        except StoreError as exc:
            raise UsageError(str(exc)) from None
        status = request("status", socket_path=getattr(args, "socket", None))
        cyc = status.get("cycle") or {}
        if cyc.get("phase") != "survey":
            raise UsageError("the service's cycle is not waiting for a survey")
        return {"pose": _store_pose(args.db, int(cyc["ring"]))}
    try:
        points = read_survey_points(args.file)
    except SurveyError as exc:  # one line per problem
        raise UsageError(str(exc)) from None
    if len(points) > MAX_SURVEY_POINTS:
        raise UsageError(
            f"{args.file}: {len(points)} points; a survey request carries at most "
            f"{MAX_SURVEY_POINTS}"
        )
    return {"points": [[p.name, *p.face, *p.measured] for p in points]}


def _locate_fields(args: argparse.Namespace) -> dict[str, Any]:
    """``wara ctl locate``'s request, each value checked against its limit first (the
    service checks them again)."""
    from ipc_app.service.requests import LIMITS

    given = (
        ("chainage_m", "--chainage", args.chainage),
        ("heading_error_deg", "--heading-error", args.heading_error),
        ("lateral_mm", "--offset", args.offset),
    )
    for key, opt, v in given:
        why = LIMITS[key].outside(v, opt)
        if why:
            raise UsageError(why)
    return {key: v for key, _, v in given}


def run(args: argparse.Namespace) -> int:
    fields: dict[str, Any] = {}
    timeout_s = 10.0
    if args.verb == "adjust":
        if not (math.isfinite(args.roll_deg) and math.isfinite(args.pitch_deg)):
            raise UsageError("--roll-deg and --pitch-deg must be finite numbers")
        fields = {"roll_deg": args.roll_deg, "pitch_deg": args.pitch_deg}
        timeout_s = args.timeout_s
    elif args.verb == "walk":
        from ipc_app.planner.walk import DIRECTIONS

        check_walk_steps(args.steps)
        if args.direction not in DIRECTIONS:
            raise UsageError(
                f"--direction must be one of {', '.join(DIRECTIONS)}, got {args.direction!r}"
            )
        fields = {"steps": args.steps, "direction": args.direction, "unloaded": args.unloaded}
        timeout_s = 30.0
    elif args.verb == "place":
        from wara.commands.place import parse_deviation

        if not 1 <= args.ring <= 99_999:
            raise UsageError(f"--ring must be within 1..99999, got {args.ring}")
        dev = [0.0] * 5
        if args.previous_deviation is not None:
            d = parse_deviation(args.previous_deviation)
            dev = [d.to_dict()[k] for k in ("y_mm", "z_mm", "roll_deg", "pitch_deg", "yaw_deg")]
        fields = {"ring": args.ring, "previous_deviation": dev}
        timeout_s = 30.0
    elif args.verb == "cycle":
        fields, timeout_s = _cycle_fields(args), 30.0
    elif args.verb == "confirm-fixed":
        fields = {"user": args.user}
    elif args.verb == "survey":
        fields, timeout_s = _survey_fields(args), 30.0
    elif args.verb == "locate":
        fields = _locate_fields(args)
    elif args.verb == "unit-mode":
        fields = {"unit_mode": args.unit_mode}
    elif args.verb == "jog":
        if not math.isfinite(args.distance_mm):
            raise UsageError("--distance-mm must be a finite number")
        fields = {"cylinder": args.cylinder, "distance_mm": args.distance_mm}
    try:
        reply = request(
            args.verb.replace("-", "_"),
            socket_path=getattr(args, "socket", None),
            timeout_s=timeout_s,
            **fields,
        )
    except CtlError as exc:
        raise UsageError(str(exc)) from None
    if args.json:
        print(json.dumps(reply, indent=2))
    elif reply.get("ok"):
        print(render(reply))
    if reply.get("ok"):
        return EXIT_OK
    if not args.json:
        print(f"wara ctl {args.verb}: {reply.get('error', 'refused')}", file=sys.stderr)
        for reason in reply.get("reasons", []):
            print(f"  - {reason}", file=sys.stderr)
    return EXIT_INFEASIBLE if reply.get("code") == "infeasible" else EXIT_FAILED


def render(reply: dict[str, Any]) -> str:
    """``key: value`` lines, nested objects flattened with dots, ``mode`` first."""
    lines: list[str] = []

    def walk(prefix: str, obj: Any) -> None:
        if isinstance(obj, dict):
            for k, v in obj.items():
                if not prefix and k == "ok":
                    continue
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        elif isinstance(obj, float):
            lines.append(f"{prefix}: {obj:.6g}")
        elif isinstance(obj, list) and obj and all(isinstance(x, str) for x in obj):
            lines.append(f"{prefix}:")
            lines.extend(f"  - {x}" for x in obj)
        else:
            lines.append(f"{prefix}: {obj if obj is not None else '-'}")

    ordered = {k: reply[k] for k in ("mode",) if k in reply} | reply
    walk("", ordered)
    return "\n".join(lines)
