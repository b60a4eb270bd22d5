"""The control channel's protocol: every command as one row of :data:`TABLE` (its name,
arguments and their limits, the reply, the handler that does it), JSON lines.

The client writes one JSON object per line (``{"cmd": NAME, ...arguments}``), the server
answers each with one JSON object on one line. :func:`parse` checks a line against its
row (the values against :data:`ipc_app.service.requests.LIMITS`) and gives a
:class:`Request` or the error reply; :func:`call` runs the row's handler of
:class:`CtlHandlers` (injected by the service) and always gives one reply. The transport
(the socket, its threads and limits) is :mod:`ipc_app.service.ctl`.

A refused or failed request answers ``{"ok": false, "error": "one line", "code": C}``
(:class:`~ipc_app.service.requests.Code`). :func:`markdown_table` renders the table of
docs/service.md (a test keeps the two equal).
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import structlog

from ipc_app.service import requests as rq
from ipc_app.service.motion import Motion
from ipc_app.service.motions.homing import HomingMotion
from ipc_app.service.requests import LIMITS, MAX_SURVEY_POINTS, MAX_WALK_STEPS, brief

log = structlog.get_logger("wara.service.ctl")

Reply = dict[str, Any]


@dataclass(frozen=True)
class CtlHandlers:
    """What the service does for each command; each returns a JSON-ready dict.

    Return ``{"ok": False, "error": ..., "code": "refused" | "infeasible", ...}`` to
    refuse; a dict without ``ok`` counts as accepted.
    """

    adjust: Callable[[float, float], Reply]
    #: ``status()``, or ``status(after, wait_s)``: once the state count is past ``after``
    status: Callable[..., Reply]
    stop: Callable[[], Reply]
    reset: Callable[[], Reply]
    #: the PackML commands beyond these four (None: refused as not supported)
    clear: Callable[[], Reply] | None = None
    hold: Callable[[], Reply] | None = None
    unhold: Callable[[], Reply] | None = None
    unit_mode: Callable[[str], Reply] | None = None
    jog: Callable[[str, float], Reply] | None = None
    #: an entry of another front end's audit trail (user, action, result)
    audit: Callable[[str, str, str], Reply] | None = None
    #: N steps; the direction (forward, back: checked by the service); unloaded
    walk: Callable[[int, str, bool], Reply] | None = None
    #: place ring N's part; the previous part's deviation (y mm, z mm, roll, pitch, yaw deg)
    place: Callable[[int, tuple[float, ...]], Reply] | None = None
    #: ring N's cycle: the previous part's deviation (5 numbers, as ``place``) or its
    #: as-built pose (6: x, y, z mm, roll, pitch, yaw deg), walk steps (None: the
    #: project's), walk back unloaded
    cycle: Callable[[int, tuple[float, ...], int | None, bool], Reply] | None = None
    #: the operator confirms the part is fixed (their name)
    confirm_fixed: Callable[[str], Reply] | None = None
    #: the cycle's survey: points (name, face y, face z, x, y, z; m) or a pose (6 numbers)
    survey: Callable[[tuple[Any, ...] | None, tuple[float, ...] | None], Reply] | None = None
    #: where the machine stands, surveyed: M's centre's chainage (m), its heading error
    #: (deg) and offset (mm) against the axis, both positive to the left
    locate: Callable[[float, float, float], Reply] | None = None
    #: a motion of :data:`TABLE` started by its class and arguments (``home``)
    motion: Callable[[type[Motion], tuple[Any, ...]], Reply] | None = None


@dataclass(frozen=True)
class Request:
    """One parsed, checked request: the command and its arguments."""

    cmd: str
    args: tuple[Any, ...] = ()


@dataclass(frozen=True)
class Arg:
    """One argument of a command, for the docs: its key, what it is, the entry of
    :data:`~ipc_app.service.requests.LIMITS` that bound it, and whether it may be left
    out (then ``default``)."""

    key: str
    what: str
    limits: tuple[str, ...] = ()
    default: str | None = None

    def doc(self) -> str:
        text = f"`{self.key}`: {self.what}"
        if self.limits:
            text += ", " + " and ".join(LIMITS[k].text() for k in self.limits)
        return text + (f" (default {self.default})" if self.default is not None else "")


Parse = Callable[[Mapping[str, Any]], tuple[Any, ...]]


@dataclass(frozen=True)
class Command:
    """A row of :data:`TABLE`: ``parse`` takes the request object's arguments (raises
    ValueError naming the wrong one), ``handler`` is the :class:`CtlHandlers` field that
    does it, with ``motion`` the motion it starts; ``inline``: answered by the I/O thread
    itself (quick; never queued behind the others)."""

    name: str
    args: tuple[Arg, ...]
    reply: str
    what: str
    parse: Parse = lambda _req: ()
    handler: str = ""
    motion: type[Motion] | None = None
    inline: bool = False


# --------------------------------------------------------------------------- arguments


def _name(req: Mapping[str, Any], key: str) -> str:
    return rq.name(req.get(key), key)


def _adjust(req: Mapping[str, Any]) -> tuple[Any, ...]:
    roll = rq.number(req.get("roll_deg"), "roll_deg")
    pitch = rq.number(req.get("pitch_deg"), "pitch_deg")
    rq.attitude(roll, pitch)
    return roll, pitch


def _status(req: Mapping[str, Any]) -> tuple[Any, ...]:
    """A status that waits: ``after`` (the ``state_seq`` the client has seen) and
    ``wait_ms``, both given; ``(after, wait_s)``; neither: at once."""
    if "after" not in req and "wait_ms" not in req:
        return ()
    after = req.get("after")
    if isinstance(after, bool) or not isinstance(after, int) or after < 0:
        raise ValueError(f"'after' must be a count (an integer >= 0), got {brief(after)}")
    wait_ms = rq.number(req.get("wait_ms"), "wait_ms", "ms")
    lim = LIMITS["status_wait_ms"]
    if not lim.holds(wait_ms):
        raise ValueError(f"'wait_ms' must be within {lim.lo:g}..{lim.hi:g}, got {wait_ms:g}")
    return after, wait_ms / 1000.0


def _jog(req: Mapping[str, Any]) -> tuple[Any, ...]:
    return _name(req, "cylinder"), rq.number(req.get("distance_mm"), "distance_mm", "mm")


def _audit(req: Mapping[str, Any]) -> tuple[Any, ...]:
    result = rq.text(req.get("result"), "result")
    return _name(req, "user"), _name(req, "action"), result


def _walk(req: Mapping[str, Any]) -> tuple[Any, ...]:
    steps = rq.integer(req.get("steps"), "steps", "walk_steps")
    unloaded = rq.flag(req.get("unloaded", False), "unloaded")
    # the directions themselves are the walk planner's (the service checks)
    direction = rq.name(req.get("direction", "forward"), "direction")
    return steps, direction, unloaded


def _place(req: Mapping[str, Any]) -> tuple[Any, ...]:
    ring = rq.integer(req.get("ring"), "ring", "ring")
    dev = req.get("previous_deviation", [0.0] * 5)
    if not isinstance(dev, list) or len(dev) != 5:
        raise ValueError(
            "'previous_deviation' must be five numbers [y_mm, z_mm, roll_deg, pitch_deg, "
            f"yaw_deg], got {brief(dev)}"
        )
    try:
        vals = tuple(rq.number(v, "v", "mm" if k < 2 else "degrees") for k, v in enumerate(dev))
    except ValueError as exc:
        raise ValueError(f"previous_deviation: {exc}") from None
    rq.check_sheet_deviation(vals, "previous_deviation")
    return ring, vals


def _cycle(req: Mapping[str, Any]) -> tuple[Any, ...]:
    ring = rq.integer(req.get("ring"), "ring", "cycle_ring")
    dev, pose = req.get("previous_deviation"), req.get("previous_pose")
    if dev is not None and pose is not None:
        raise ValueError("give 'previous_deviation' or 'previous_pose', not both")
    if pose is not None:  # a pose's plausibility needs the project: the service checks it
        prev = rq.numbers(pose, 6, "'previous_pose'")
    else:
        prev = rq.numbers(dev if dev is not None else [0.0] * 5, 5, "'previous_deviation'")
        rq.check_sheet_deviation(prev, "'previous_deviation'")
    steps = req.get("walk_steps")
    if steps is not None:
        steps = rq.integer(steps, "walk_steps", "cycle_walk_steps")
    unloaded = rq.flag(req.get("walk_back_unloaded", True), "walk_back_unloaded")
    return ring, prev, steps, unloaded


def _survey(req: Mapping[str, Any]) -> tuple[Any, ...]:
    points, pose = req.get("points"), req.get("pose")
    if (points is None) == (pose is None):
        raise ValueError("survey: give 'points' or 'pose'")
    if pose is not None:
        return None, rq.numbers(pose, 6, "'pose'")
    if not isinstance(points, list) or not 1 <= len(points) <= MAX_SURVEY_POINTS:
        raise ValueError(f"'points' must be a list of 1..{MAX_SURVEY_POINTS} points")
    out = []
    for k, p in enumerate(points, start=1):
        if not isinstance(p, list) or len(p) != 6:
            raise ValueError(f"point {k}: [name, face_y_m, face_z_m, x_m, y_m, z_m]")
        out.append((rq.name(p[0], "name"), *rq.numbers(p[1:], 5, f"point {k}")))
    return tuple(out), None


def _locate(req: Mapping[str, Any]) -> tuple[Any, ...]:
    return (
        rq.bounded(req.get("chainage_m"), "chainage_m", "chainage_m"),
        rq.bounded(req.get("heading_error_deg"), "heading_error_deg", "heading_error_deg"),
        rq.bounded(req.get("lateral_mm"), "lateral_mm", "lateral_mm"),
    )


_MODE = "`mode`"
_DEVIATION = "the previous part's deviation [y_mm, z_mm, roll_deg, pitch_deg, yaw_deg]"

#: Every command of the control channel.
TABLE: dict[str, Command] = {
    c.name: c
    for c in (
        Command(
            "adjust",
            (Arg("roll_deg", "target workpiece roll, deg", ("attitude_deg",)),
             Arg("pitch_deg", "target workpiece pitch, deg", ("attitude_deg",))),
            "the planner's verdict (waits up to 15 s): `mode`, `duration_s`, or "
            "`code: infeasible` with `reasons`",
            "plan and run an adjustment", _adjust, "adjust",
        ),
        Command(
            "status",
            (Arg("after", "the `state_seq` seen; with `wait_ms`", default="none: at once"),
             Arg("wait_ms", "the longest wait for the next change of mode", ("status_wait_ms",),
                 default="none")),
            "mode, faults, positions, sync error, twist, motion, loop statistics, `ctl` "
            "(the channel's health), `state_seq` (its count of mode changes)",
            "the service's status", _status, "status", inline=True,
        ),
        Command("stop", (), f"{_MODE} (always accepted; a stop never clears a fault)",
                "controlled stop: valves closed, load held", handler="stop", inline=True),
        Command("reset", (), f"{_MODE} once the cause is gone, else `code: refused`",
                "ABORTED (clear first) or STOPPED -> IDLE", handler="reset"),
        Command("clear", (), _MODE, "ABORTED -> STOPPED once the cause is gone",
                handler="clear"),
        Command("hold", (), _MODE, "EXECUTE -> HELD: the motion stops where it is",
                handler="hold"),
        Command("unhold", (), _MODE, "HELD -> EXECUTE once the motion's resume check passes",
                handler="unhold"),
        Command(
            "unit_mode", (Arg("unit_mode", "PRODUCTION, MAINTENANCE or MANUAL"),), _MODE,
            "the PackML unit mode (in STOPPED, IDLE or ABORTED)",
            lambda req: (_name(req, "unit_mode"),), "unit_mode",
        ),
        Command(
            "jog",
            (Arg("cylinder", "an attitude cylinder's id", ("name_chars",)),
             Arg("distance_mm", "rod travel, mm (+ out)")),
            _MODE, "MANUAL: one cylinder at the jog speed",
            _jog, "jog",
        ),
        Command(
            "audit",
            (Arg("user", "who", ("name_chars",)), Arg("action", "what", ("name_chars",)),
             Arg("result", "the outcome", ("audit_chars",))),
            "nothing: the entry is in the log and the run record",
            "an entry of another front end's audit trail (the OPC UA server's calls)",
            _audit, "audit",
        ),
        Command(
            "walk",
            (Arg("steps", "steps", ("walk_steps",)),
             Arg("direction", "forward or back", default="forward"),
             Arg("unloaded", "the statics without the workpiece", default="false")),
            f"{_MODE}, `duration_s` of the plan; `code: infeasible` with the `refusal`",
            "walk N steps (planned first)", _walk, "walk",
        ),
        Command(
            "place",
            (Arg("ring", "the ring being built", ("ring",)),
             Arg("previous_deviation", _DEVIATION, ("deviation_mm", "deviation_deg"),
                 default="zeros")),
            f"{_MODE}, `ring`; `code: infeasible` with the binding limit",
            "place ring N's part at its planned target pose", _place, "place",
        ),
        Command(
            "cycle",
            (Arg("ring", "the ring being built", ("cycle_ring",)),
             Arg("previous_deviation", _DEVIATION, ("deviation_mm", "deviation_deg"),
                 default="zeros"),
             Arg("previous_pose", "or its as-built pose [x, y, z mm, roll, pitch, yaw deg]"),
             Arg("walk_steps", "steps to the ring and back", ("cycle_walk_steps",),
                 default="`cycle.walk_steps`"),
             Arg("walk_back_unloaded", "walk back without the part", default="true")),
            "`ring`, `phase`: the ring cycle runs in the service's cycle thread",
            "ring N's cycle: walk, place, fixing, release, survey, record, walk back",
            _cycle, "cycle",
        ),
        Command(
            "confirm_fixed", (Arg("user", "who confirms (audited)", ("name_chars",)),),
            "`ring`, `phase` (release: the platform lowers off the part next)",
            "the cycle's part is fixed (refused outside its `fixing`)",
            lambda req: (_name(req, "user"),), "confirm_fixed",
        ),
        Command(
            "survey",
            (Arg("points", "[[name, face_y_m, face_z_m, x_m, y_m, z_m], ...]", ("survey_points",)),
             Arg("pose", "or the as-built pose [6] (the acceptance store's)")),
            "`ring`, `rms_residual_mm`; a refused fit answered with its reason, the cycle "
            "still waiting",
            "the cycle's survey", _survey, "survey",
        ),
        Command(
            "locate",
            (Arg("chainage_m", "M's centre's chainage", ("chainage_m",)),
             Arg("heading_error_deg", "the machine's heading less the axis's (+ left)",
                 ("heading_error_deg",)),
             Arg("lateral_mm", "M's centre's offset from the axis (+ left)", ("lateral_mm",))),
            "`on_axis` (what it set), `replaced` (the estimate before), `change`; refused "
            "while a walk has not ended (its end sets it) or without a walking section",
            "where the machine stands, surveyed: the next walk steers from it",
            _locate, "locate",
        ),
        Command(
            "home", (), f"{_MODE}, `duration_s`",
            "homing: each attitude layer to mid-stroke, level, then held",
            handler="motion", motion=HomingMotion,
        ),
    )
}  # fmt: skip

#: The command names.
COMMANDS: tuple[str, ...] = tuple(TABLE)
#: Commands answered by the I/O thread itself: quick, and never queued behind others.
INLINE_COMMANDS = frozenset(c.name for c in TABLE.values() if c.inline)


def _error(code: str, message: str) -> Reply:
    return {"ok": False, "error": message, "code": code}


def parse(line: bytes) -> Request | Reply:
    """One request line -> a :class:`Request`, or the error reply for a bad one."""
    try:
        req = json.loads(line)
    except RecursionError:
        return _error("bad_request", "request is nested too deeply")
    except ValueError as exc:  # JSONDecodeError, UnicodeDecodeError, 4300-digit integers
        return _error("bad_request", f"request is not JSON: {str(exc)[:200]}")
    if not isinstance(req, dict):
        return _error("bad_request", "request must be a JSON object with a 'cmd' key")
    cmd = req.get("cmd")
    if not isinstance(cmd, str) or cmd not in TABLE:
        return _error("bad_request", f"unknown command {brief(cmd)}; expected one of {COMMANDS}")
    try:
        return Request(cmd, TABLE[cmd].parse(req))
    except ValueError as exc:
        return _error("bad_request", str(exc))


def call(handlers: CtlHandlers, req: Request) -> Reply:
    """Run a parsed request's handler; whatever it does, one reply comes back."""
    row = TABLE[req.cmd]
    try:
        fn = getattr(handlers, row.handler)
        if fn is None:
            return _error("bad_request", f"{req.cmd} is not supported by this service")
        reply = fn(row.motion, req.args) if row.motion is not None else fn(*req.args)
    except ValueError as exc:
        return _error("bad_request", str(exc))
    except Exception as exc:
        log.exception("ctl_handler_failed", cmd=req.cmd)
        return _error("internal", f"{req.cmd} failed in the service: {type(exc).__name__}: {exc}")
    if not isinstance(reply, Mapping):
        log.error("ctl_handler_bad_reply", cmd=req.cmd, reply_type=type(reply).__name__)
        return _error("internal", f"{req.cmd} failed in the service: no reply")
    out: Reply = {"ok": True, **reply}
    if out["ok"] is not True and not isinstance(out.get("error"), str):  # one line, always
        out["error"] = f"{req.cmd} refused ({out.get('code', 'no reason given')})"
    return out


def dispatch(handlers: CtlHandlers, line: bytes) -> Reply:
    """One request line -> one reply (the protocol, without the socket)."""
    req = parse(line)
    return call(handlers, req) if isinstance(req, Request) else req


def markdown_table() -> str:
    """The command table of docs/service.md, rendered from :data:`TABLE`."""
    rows = ['| command | arguments | reply (besides `"ok": true`) | what |', "|---|---|---|---|"]
    for c in TABLE.values():
        args = "; ".join(a.doc() for a in c.args) or "-"
        rows.append(f"| `{c.name}` | {args} | {c.reply} | {c.what} |")
    return "\n".join(rows) + "\n"


__all__ = [
    "COMMANDS",
    "INLINE_COMMANDS",
    "MAX_WALK_STEPS",
    "TABLE",
    "Arg",
    "Command",
    "CtlHandlers",
    "Request",
    "call",
    "dispatch",
    "markdown_table",
    "parse",
]
