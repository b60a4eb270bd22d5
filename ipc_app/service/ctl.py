"""The local control channel: a Unix-domain socket, JSON lines, owner-only.

Protocol: the client writes one JSON object per line, the server answers each with one
JSON object on one line; a connection may carry several requests (answered in order).
A last request without its newline is answered when the client half-closes
(``shutdown(SHUT_WR)``).

=========  ===========================================  =====================================
command    request                                      reply (besides ``"ok": true``)
=========  ===========================================  =====================================
adjust     ``{"cmd": "adjust", "roll_deg": R,           what the service's handler returns,
           "pitch_deg": P}``                            e.g. ``mode``, ``request_id``
status     ``{"cmd": "status"}``; with ``"after": N,       the service's status (``mode``, ...,
           "wait_ms": W``: once ``state_seq`` is no     ``state_seq``: its count of mode
           longer N, at most W ms (0..1000) later       changes)
stop       ``{"cmd": "stop"}``                          ``mode``
reset      ``{"cmd": "reset"}``                         ``mode``
clear      ``{"cmd": "clear"}``                         ``mode``
hold       ``{"cmd": "hold"}``                          ``mode``
unhold     ``{"cmd": "unhold"}``                        ``mode``
unit_mode  ``{"cmd": "unit_mode", "unit_mode": U}``     ``mode`` (U: PRODUCTION, MAINTENANCE,
                                                        MANUAL)
jog        ``{"cmd": "jog", "cylinder": ID,             ``mode``
           "distance_mm": D}``
audit      ``{"cmd": "audit", "user": U, "action": A,  nothing: the entry is in the log and
           "result": R}``                               the run record (the OPC UA server's
                                                        method calls: who, what, result)
=========  ===========================================  =====================================

A refused or failed request answers ``{"ok": false, "error": "one line", "code": C}`` with
``C`` one of ``bad_request`` (not JSON, nested too deeply, unknown command, missing or
non-finite number, line longer than :data:`MAX_LINE_BYTES`), ``refused`` (the mode
machine said no, e.g. adjust while ABORTED), ``busy`` (every worker busy with an ``adjust``
or ``reset``; or no slot for a new client), ``infeasible`` (the planner's ``reasons`` list
is included) or ``internal`` (a handler raised; logged).

The server (:class:`CtlServer`) is one I/O thread on a selector plus a small fixed pool
of worker threads; no thread is started per client. ``status`` and ``stop`` are answered
by the I/O thread itself (they are quick), so they get through however many requests are
waiting; ``adjust`` and ``reset`` may block (``adjust`` waits for the planner's verdict so
the operator sees the reasons of an infeasible target) and run in the pool
(``max_workers``; when all are busy the request is answered ``busy`` at once). At most
``max_clients`` connections are kept: a new one takes the slot of the connection idle the
longest (without a request being worked on), so idle or slow clients never lock anyone
out. A connection is closed after ``idle_timeout_s`` without a complete request, or when
its line exceeds :data:`MAX_LINE_BYTES`. Each connection buffers at most one line and one
reply: a client that does not read its replies is not read from either.

Nothing a client sends or does ends the I/O thread: an error on one connection closes
that connection. Should the thread end nonetheless (a bug), or stall, or the socket file
be removed, :attr:`CtlServer.healthy` turns False and :meth:`CtlServer.health` says why;
the service treats that as a fault and calls :meth:`CtlServer.restart`.

The handlers (:class:`CtlHandlers`) are injected by the service and run in this module's
threads, never in the loop thread; they talk to the loop only through thread-safe objects
(the mode machine, a queue).

The socket: ``path`` given by the service, else :func:`default_socket_path`
(``$WARA_CTL_SOCKET``; ``$RUNTIME_DIRECTORY/ctl.sock`` under systemd with
``RuntimeDirectory=wara``; ``/run/wara/ctl.sock`` when that directory exists; else
``$XDG_RUNTIME_DIR/wara/ctl.sock`` or ``<tmp>/wara-<uid>/ctl.sock``). It is bound under
``umask 0o177`` and chmod-ed 0600, so only the service's user (and root) can connect;
a directory the server creates is 0700. A stale socket file (nobody listening) is
replaced; a live one is an error (two services would fight over the valves).

Client: :func:`request` (``wara ctl`` uses it) raises :class:`CtlUnavailable` when no
service listens; a full listen queue or a ``busy`` answer is retried for a bounded time.

Over 500 lines because the protocol table above, the selector thread, the worker pool
and the eviction rules are one piece: every limit a rude client meets is here.
"""

from __future__ import annotations

import contextlib
import errno
import json
import math
import os
import queue
import selectors
import socket
import stat
import tempfile
import threading
import time
from collections import Counter
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from config.numbers import check_name, check_text

log = structlog.get_logger("wara.service.ctl")

SOCKET_NAME = "ctl.sock"
SYSTEM_RUNTIME_DIR = Path("/run/wara")
MAX_LINE_BYTES = 64 * 1024
COMMANDS = (
    "adjust",
    "status",
    "stop",
    "reset",
    "clear",
    "hold",
    "unhold",
    "unit_mode",
    "jog",
    "audit",
    "walk",
    "place",
    "cycle",
    "confirm_fixed",
    "survey",
)
#: The longest ``result`` an ``audit`` entry may carry.
MAX_AUDIT_CHARS = 400
#: The longest cylinder id a ``jog`` request may name.
MAX_ID_CHARS = 40
#: Commands answered by the I/O thread itself: quick, and never queued behind others.
INLINE_COMMANDS = frozenset({"status", "stop"})
#: Largest reply the client reads (a status is a few KiB).
MAX_REPLY_BYTES = 16 * MAX_LINE_BYTES
#: Requests of one connection answered before the other connections get their turn.
REQUESTS_PER_TURN = 16
#: The I/O thread wakes at least this often (stop, idle time-outs, the health tick).
TICK_S = 0.2

Reply = dict[str, Any]


#: the most steps one walk request takes
MAX_WALK_STEPS = 1000


class CtlError(Exception):
    """The control channel could not be used (bad reply, socket in use, ...)."""


class CtlUnavailable(CtlError):
    """No service listens on the socket (not running, wrong path, or no permission)."""


def default_socket_path(environ: Mapping[str, str] | None = None) -> Path:
    """Where the service listens and ``wara ctl`` connects (see the module docstring)."""
    env = os.environ if environ is None else environ
    if env.get("WARA_CTL_SOCKET"):
        return Path(env["WARA_CTL_SOCKET"])
    if env.get("RUNTIME_DIRECTORY"):
        return Path(env["RUNTIME_DIRECTORY"].split(":")[0]) / SOCKET_NAME
    if SYSTEM_RUNTIME_DIR.is_dir():
        return SYSTEM_RUNTIME_DIR / SOCKET_NAME
    if env.get("XDG_RUNTIME_DIR"):
        return Path(env["XDG_RUNTIME_DIR"]) / "wara" / SOCKET_NAME
    return Path(tempfile.gettempdir()) / f"wara-{os.getuid()}" / SOCKET_NAME


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


def _error(code: str, message: str) -> Reply:
    return {"ok": False, "error": message, "code": code}


def _number(req: Mapping[str, Any], key: str, unit: str = "degrees") -> float:
    v = req.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"{key!r} must be a finite number in {unit}, got {_brief(v)}")
    try:
        f = float(v)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise ValueError(f"{key!r} must be a finite number in {unit}, got {_brief(v)}")
    return f


def _name(req: Mapping[str, Any], key: str) -> str:
    """``req[key]``: a name of 1..MAX_ID_CHARS characters, no control, format or
    line-break character (:func:`config.numbers.check_name`: it goes into the audit
    trail as it is)."""
    return check_name(req.get(key), repr(key), MAX_ID_CHARS)


def _brief(v: Any) -> str:
    """A short description of a client's value for an error message (never its whole
    repr: it may be 64 KiB or nested a thousand deep)."""
    if v is None or isinstance(v, bool | float) or (isinstance(v, str) and len(v) <= 40):
        return repr(v)
    if isinstance(v, int):
        return "an integer of more than 40 digits" if v.bit_length() > 132 else repr(v)
    return f"a {type(v).__name__}" if not isinstance(v, str) else "a long string"


@dataclass(frozen=True)
class Request:
    """One parsed, checked request: the command and its arguments."""

    cmd: str
    args: tuple[Any, ...] = ()


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
    if not isinstance(cmd, str) or cmd not in COMMANDS:
        return _error("bad_request", f"unknown command {_brief(cmd)}; expected one of {COMMANDS}")
    if cmd == "unit_mode":
        try:
            return Request(cmd, (_name(req, "unit_mode"),))
        except ValueError as exc:
            return _error("bad_request", str(exc))
    if cmd == "jog":
        try:
            return Request(cmd, (_name(req, "cylinder"), _number(req, "distance_mm", "mm")))
        except ValueError as exc:
            return _error("bad_request", str(exc))
    if cmd == "audit":
        try:
            result = req.get("result")
            check_text(result, "'result'", MAX_AUDIT_CHARS)
            return Request(cmd, (_name(req, "user"), _name(req, "action"), result))
        except ValueError as exc:
            return _error("bad_request", str(exc))
    if cmd == "walk":
        steps = req.get("steps")
        if (
            isinstance(steps, bool)
            or not isinstance(steps, int)
            or not 1 <= steps <= MAX_WALK_STEPS
        ):
            return _error(
                "bad_request",
                f"'steps' must be an integer 1..{MAX_WALK_STEPS}, got {_brief(steps)}",
            )
        unloaded = req.get("unloaded", False)
        if not isinstance(unloaded, bool):
            why = f"'unloaded' must be true or false, got {_brief(unloaded)}"
            return _error("bad_request", why)
        try:  # the directions themselves are the walk planner's (the service checks)
            direction = _name({"direction": req.get("direction", "forward")}, "direction")
        except ValueError as exc:
            return _error("bad_request", str(exc))
        return Request(cmd, (steps, direction, unloaded))
    if cmd == "place":
        ring = req.get("ring")
        if isinstance(ring, bool) or not isinstance(ring, int) or not 1 <= ring <= 99_999:
            return _error("bad_request", f"'ring' must be an integer 1..99999, got {_brief(ring)}")
        dev = req.get("previous_deviation", [0.0] * 5)
        if not isinstance(dev, list) or len(dev) != 5:
            return _error(
                "bad_request",
                "'previous_deviation' must be five numbers [y_mm, z_mm, roll_deg, pitch_deg, "
                f"yaw_deg], got {_brief(dev)}",
            )
        try:
            vals = tuple(
                _number({"v": v}, "v", "mm" if k < 2 else "degrees") for k, v in enumerate(dev)
            )
        except ValueError as exc:
            return _error("bad_request", f"previous_deviation: {exc}")
        try:
            check_sheet_deviation(vals, "previous_deviation")
        except ValueError as exc:
            return _error("bad_request", str(exc))
        return Request(cmd, (ring, vals))
    if cmd in ("cycle", "confirm_fixed", "survey"):
        try:
            return _cycle_request(cmd, req)
        except ValueError as exc:
            return _error("bad_request", str(exc))
    if cmd == "status" and ("after" in req or "wait_ms" in req):
        try:
            return Request(cmd, _status_wait(req))
        except ValueError as exc:
            return _error("bad_request", str(exc))
    if cmd != "adjust":
        return Request(cmd)
    try:
        roll, pitch = _number(req, "roll_deg"), _number(req, "pitch_deg")
    except ValueError as exc:
        return _error("bad_request", str(exc))
    if abs(roll) >= 90 or abs(pitch) >= 90:
        return _error("bad_request", "roll_deg and pitch_deg must be within ±90 deg")
    return Request(cmd, (roll, pitch))


#: The longest a status may wait for the next change of state (``wait_ms``).
MAX_STATUS_WAIT_MS = 1000


def _status_wait(req: Mapping[str, Any]) -> tuple[int, float]:
    """A status that waits: ``after`` (the ``state_seq`` the client has seen) and
    ``wait_ms``, both given; ``(after, wait_s)``."""
    after = req.get("after")
    if isinstance(after, bool) or not isinstance(after, int) or after < 0:
        raise ValueError(f"'after' must be a count (an integer >= 0), got {_brief(after)}")
    wait_ms = _number(req, "wait_ms", "ms")
    if not 0 <= wait_ms <= MAX_STATUS_WAIT_MS:
        raise ValueError(f"'wait_ms' must be within 0..{MAX_STATUS_WAIT_MS}, got {wait_ms:g}")
    return after, wait_ms / 1000.0


#: The most survey points one request carries (``wara ctl survey`` checks it first).
MAX_SURVEY_POINTS = 200
#: A deviation as a survey sheet gives it (``previous_deviation``): at most this far
#: across the axis (y, z) and turned (roll, pitch, yaw); more is a typo, not a survey.
MAX_SHEET_DEVIATION_MM, MAX_SHEET_DEVIATION_DEG = 50.0, 10.0


def check_sheet_deviation(vals: tuple[float, ...], what: str) -> None:
    """ValueError unless ``vals`` (y mm, z mm, roll, pitch, yaw deg) is within the bounds."""
    if (
        max(abs(vals[0]), abs(vals[1])) > MAX_SHEET_DEVIATION_MM
        or max(abs(v) for v in vals[2:]) > MAX_SHEET_DEVIATION_DEG
    ):
        raise ValueError(
            f"{what}: at most {MAX_SHEET_DEVIATION_MM:g} mm and {MAX_SHEET_DEVIATION_DEG:g} deg "
            "(a typo, not a survey)"
        )


def _numbers(v: Any, n: int, what: str) -> tuple[float, ...]:
    if not isinstance(v, list) or len(v) != n:
        raise ValueError(f"{what} must be {n} numbers, got {_brief(v)}")
    return tuple(_number({"v": x}, "v", "mm or degrees") for x in v)


def _cycle_request(cmd: str, req: Mapping[str, Any]) -> Request:
    """``cycle``, ``confirm_fixed`` and ``survey`` (the ring cycle's requests)."""
    if cmd == "confirm_fixed":
        return Request(cmd, (_name(req, "user"),))
    if cmd == "survey":
        points, pose = req.get("points"), req.get("pose")
        if (points is None) == (pose is None):
            raise ValueError("survey: give 'points' or 'pose'")
        if pose is not None:
            return Request(cmd, (None, _numbers(pose, 6, "'pose'")))
        if not isinstance(points, list) or not 1 <= len(points) <= MAX_SURVEY_POINTS:
            raise ValueError(f"'points' must be a list of 1..{MAX_SURVEY_POINTS} points")
        out = []
        for k, p in enumerate(points, start=1):
            if not isinstance(p, list) or len(p) != 6:
                raise ValueError(f"point {k}: [name, face_y_m, face_z_m, x_m, y_m, z_m]")
            name = _name({"name": p[0]}, "name")
            out.append((name, *_numbers(p[1:], 5, f"point {k}")))
        return Request(cmd, (tuple(out), None))
    ring = req.get("ring")
    if isinstance(ring, bool) or not isinstance(ring, int) or not 2 <= ring <= 99_999:
        raise ValueError(f"'ring' must be an integer 2..99999, got {_brief(ring)}")
    dev, pose = req.get("previous_deviation"), req.get("previous_pose")
    if dev is not None and pose is not None:
        raise ValueError("give 'previous_deviation' or 'previous_pose', not both")
    prev = _numbers(pose, 6, "'previous_pose'") if pose is not None else (
        _numbers(dev if dev is not None else [0.0] * 5, 5, "'previous_deviation'"))  # fmt: skip
    if pose is None:  # a pose's plausibility needs the project: the service checks it
        check_sheet_deviation(prev, "'previous_deviation'")
    steps = req.get("walk_steps")
    if steps is not None and (
        isinstance(steps, bool) or not isinstance(steps, int) or not 0 <= steps <= MAX_WALK_STEPS
    ):
        raise ValueError(
            f"'walk_steps' must be an integer 0..{MAX_WALK_STEPS}, got {_brief(steps)}"
        )
    unloaded = req.get("walk_back_unloaded", True)
    if not isinstance(unloaded, bool):
        raise ValueError(f"'walk_back_unloaded' must be true or false, got {_brief(unloaded)}")
    return Request(cmd, (ring, prev, steps, unloaded))


def call(handlers: CtlHandlers, req: Request) -> Reply:
    """Run a parsed request's handler; whatever it does, one reply comes back."""
    try:
        if req.cmd == "adjust":
            reply = handlers.adjust(*req.args)
        elif req.cmd == "status":
            reply = handlers.status(*req.args)
        elif req.cmd == "stop":
            reply = handlers.stop()
        elif req.cmd == "reset":
            reply = handlers.reset()
        else:
            fn = getattr(handlers, req.cmd)
            if fn is None:
                return _error("bad_request", f"{req.cmd} is not supported by this service")
            reply = fn(*req.args)
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


def _why(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _line(obj: Reply) -> bytes:
    """One JSON line; strict JSON only (``allow_nan=False``): a reply carrying NaN or
    infinity, which no JSON reader need take, becomes an ``internal`` error reply."""
    try:
        text = json.dumps(obj, default=str, allow_nan=False)
    except (ValueError, TypeError, RecursionError) as exc:  # a handler's odd reply
        log.error("ctl_reply_not_json", error=repr(exc))
        why = "a value that is not a finite number" if "Out of range float" in str(exc) else exc
        text = json.dumps(_error("internal", f"reply could not be encoded: {why}"))
    return (text + "\n").encode()


@dataclass(eq=False)
class _Conn:
    """One client connection and its bounded buffers (I/O thread only)."""

    sock: socket.socket
    last_active: float
    inbuf: bytearray = field(default_factory=bytearray)
    outbuf: bytearray = field(default_factory=bytearray)
    in_flight: bool = False  #: a request of this connection is in the worker pool
    eof: bool = False  #: the client will send nothing more
    closing: bool = False  #: close once the output is written
    events: int = 0  #: what the selector watches


#: The server's counters (all present from the start, so that reading them from another
#: thread never sees the dict change size).
COUNTERS = (
    "accepted",
    "requests",
    "bad_request",
    "busy",
    "evicted",
    "idle_closed",
    "client_errors",
    "internal_errors",
    "accept_errors",
)


def _cmd_of(line: bytes) -> str | None:
    """The ``cmd`` of a request line (None when it is not a JSON object with one)."""
    try:
        obj = json.loads(line)
    except ValueError:
        return None
    cmd = obj.get("cmd") if isinstance(obj, dict) else None
    return cmd if isinstance(cmd, str) else None


class CtlServer:
    """Serves :class:`CtlHandlers` on a Unix socket (see the module docstring)."""

    def __init__(
        self,
        handlers: CtlHandlers,
        path: str | Path | None = None,
        *,
        idle_timeout_s: float = 60.0,
        max_clients: int = 16,
        max_workers: int = 4,
        backlog: int = 128,
        stall_s: float = 5.0,
    ) -> None:
        if max_workers < 1 or max_clients <= max_workers:
            raise ValueError("need 1 <= max_workers < max_clients (a slot must stay free)")
        self.handlers = handlers
        self.path = Path(path) if path is not None else default_socket_path()
        self.idle_timeout_s = idle_timeout_s
        self.max_clients = max_clients
        self.max_workers = max_workers
        self.backlog = backlog
        self.stall_s = stall_s
        self.counters: Counter[str] = Counter(dict.fromkeys(COUNTERS, 0))
        self.restarts = 0
        self.last_error: str | None = None
        self._sock: socket.socket | None = None
        self._inode: tuple[int, int] | None = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()
        self._tick = 0.0
        self._conns: dict[int, _Conn] = {}
        self._ready: dict[_Conn, None] = {}  # ordered set: connections with lines waiting
        self._results: queue.SimpleQueue[tuple[_Conn, Reply, bytes]] = queue.SimpleQueue()
        self._jobs: queue.SimpleQueue[tuple[_Conn, Request, bytes] | None] = queue.SimpleQueue()
        self._workers: list[threading.Thread] = []
        self._in_flight = 0
        self._accept_paused_until = 0.0
        self._sel: selectors.BaseSelector | None = None
        self._wake_r, self._wake_w = socket.socketpair()
        for s in (self._wake_r, self._wake_w):
            s.setblocking(False)

    # ------------------------------------------------------------------ lifecycle

    def bind(self) -> None:
        """Create the socket file (0600) and listen; clients queue until :meth:`start`."""
        if self._sock is not None:
            return
        try:
            self._prepare_path()
        except OSError as exc:
            raise CtlError(f"cannot create control socket {self.path}: {_why(exc)}") from None
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o177)
        try:
            sock.bind(str(self.path))
            os.chmod(self.path, 0o600)
            sock.listen(self.backlog)
            sock.setblocking(False)
            st = self.path.stat()
        except OSError as exc:
            sock.close()
            raise CtlError(f"cannot bind control socket {self.path}: {_why(exc)}") from None
        finally:
            os.umask(old)
        self._sock, self._inode = sock, (st.st_dev, st.st_ino)

    def start(self) -> None:
        """Bind (if not yet) and serve from the I/O thread."""
        self.bind()
        self._start_thread()
        log.info("ctl_listening", socket=str(self.path))

    def _start_thread(self) -> None:
        assert self._sock is not None
        self._closing.clear()
        self._tick = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="wara-ctl", daemon=True)
        self._thread.start()

    def restart(self) -> bool:
        """Serve again after the I/O thread ended or the socket file went away: the open
        connections are dropped, the socket is re-created if it is gone. True on success
        (also when nothing was wrong); False when it failed or the thread is stalled
        (a stalled thread cannot be replaced)."""
        state = self.state()
        if state in ("ok", "stopped"):
            return state == "ok"
        if state == "stalled":
            return False
        self.restarts += 1
        try:
            self._closing.set()
            self._wake()
            if self._thread is not None:
                self._thread.join(2.0)
                if self._thread.is_alive():
                    raise CtlError("the I/O thread does not end")
            self._drop_connections()
            if not self._socket_file_ok():
                if self._sock is not None:
                    self._sock.close()
                self._sock = None
                self.bind()
            self._start_thread()
        except (CtlError, OSError) as exc:
            self.last_error = f"restart failed: {exc}"
            log.error("ctl_restart_failed", error=str(exc))
            return False
        log.warning("ctl_restarted", restarts=self.restarts, socket=str(self.path))
        return True

    def stop(self) -> None:
        self._closing.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(2.0)
        for _ in self._workers:
            self._jobs.put(None)
        self._drop_connections()
        if self._sock is not None:
            self._sock.close()
            if self._socket_file_ok():  # ours still: remove it (not a successor's)
                with contextlib.suppress(FileNotFoundError):
                    self.path.unlink()
            self._sock = None
        self._wake_r.close()
        self._wake_w.close()

    def __enter__(self) -> CtlServer:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _prepare_path(self) -> None:
        parent = self.path.parent
        if not parent.exists():
            parent.mkdir(mode=0o700, parents=True)
        if self.path.exists() or self.path.is_symlink():
            if not stat.S_ISSOCK(self.path.lstat().st_mode):
                raise CtlError(f"{self.path} exists and is not a socket; refusing to replace it")
            probe = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            probe.settimeout(1.0)
            try:
                probe.connect(str(self.path))
            except OSError:
                self.path.unlink()  # stale: nobody listens
                log.info("ctl_stale_socket_removed", socket=str(self.path))
            else:
                raise CtlError(f"another service already listens on {self.path}; stop it first")
            finally:
                probe.close()

    # ------------------------------------------------------------------ health

    def _socket_file_ok(self) -> bool:
        try:
            st = self.path.lstat()
        except OSError:
            return False
        return (st.st_dev, st.st_ino) == self._inode

    def state(self) -> str:
        """``ok``; ``dead`` (the I/O thread ended), ``stalled`` (it has not come round for
        ``stall_s``), ``socket_gone`` (the socket file was removed or replaced), or
        ``stopped``."""
        if self._sock is None or self._thread is None or self._closing.is_set():
            return "stopped"
        if not self._thread.is_alive():
            return "dead"
        if not self._socket_file_ok():
            return "socket_gone"
        if time.monotonic() - self._tick > self.stall_s:
            return "stalled"
        return "ok"

    @property
    def healthy(self) -> bool:
        """True while clients can connect and are served (cheap: the loop may ask)."""
        return self.state() == "ok"

    def health(self) -> dict[str, Any]:
        """What ``wara ctl status`` shows under ``ctl`` (JSON-ready)."""
        return {
            "state": self.state(),
            "clients": len(self._conns),
            "in_flight": self._in_flight,
            "restarts": self.restarts,
            "last_error": self.last_error,
            **dict(self.counters),
        }

    # ------------------------------------------------------------------ I/O thread

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        self._sel = sel
        try:
            assert self._sock is not None
            sel.register(self._sock, selectors.EVENT_READ, None)
            sel.register(self._wake_r, selectors.EVENT_READ, self._wake_r)
            while not self._closing.is_set():
                self._tick = time.monotonic()
                try:
                    self._turn(sel)
                except Exception as exc:  # a bug, not a client: logged, counted, go on
                    self.counters["internal_errors"] += 1
                    self.last_error = f"{type(exc).__name__}: {exc}"
                    log.exception("ctl_internal_error")
                    self._drop_connections()  # their state is not to be trusted
                    time.sleep(0.05)  # no busy loop should it repeat
        except BaseException as exc:  # ends the thread: the service sees it (state "dead")
            self.last_error = f"I/O thread ended: {type(exc).__name__}: {exc}"
            log.error("ctl_thread_died", error=self.last_error, exc_info=True)
        finally:
            with contextlib.suppress(Exception):
                sel.close()

    def _turn(self, sel: selectors.BaseSelector) -> None:
        now = time.monotonic()
        listening = self._sock is not None and now >= self._accept_paused_until
        if self._sock is not None:
            self._watch(sel, self._sock, selectors.EVENT_READ if listening else 0, None)
        for key, _mask in sel.select(0.0 if self._ready else TICK_S):
            if key.data is None:
                self._accept()
            elif key.data is self._wake_r:
                with contextlib.suppress(OSError):
                    while self._wake_r.recv(4096):
                        pass
            else:
                self._on_event(key.data, _mask)
        while True:
            try:
                conn, reply, line = self._results.get_nowait()
            except queue.Empty:
                break
            self._in_flight -= 1
            conn.in_flight = False
            self._answer(conn, reply, line)
            self._ready[conn] = None
        for conn in list(self._ready):
            self._ready.pop(conn, None)
            self._guarded(conn, self._pump)
        self._expire(time.monotonic())

    def _watch(
        self, sel: selectors.BaseSelector, sock: socket.socket, events: int, data: Any
    ) -> None:
        try:
            key = sel.get_key(sock)
        except KeyError:
            if events:
                sel.register(sock, events, data)
            return
        if not events:
            sel.unregister(sock)
        elif key.events != events:
            sel.modify(sock, events, data)

    def _accept(self) -> None:
        """Take the waiting connections, as many as there are free slots (one when full:
        the other connections are read before the next, so none is evicted unread)."""
        assert self._sock is not None
        for _ in range(max(1, self.max_clients - len(self._conns))):
            try:
                sock, _ = self._sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionAbortedError:
                continue
            except OSError as exc:  # out of file descriptors or the like: pause a while
                self.counters["accept_errors"] += 1
                if exc.errno in (errno.EMFILE, errno.ENFILE) and self._evict("no descriptor"):
                    continue
                self.last_error = f"accept: {exc}"
                log.warning("ctl_accept_failed", error=str(exc))
                self._accept_paused_until = time.monotonic() + 0.1
                return
            sock.setblocking(False)
            self.counters["accepted"] += 1
            if len(self._conns) >= self.max_clients and not self._evict("slot needed"):
                self.counters["busy"] += 1
                with contextlib.suppress(OSError):
                    sock.send(_line(_error("busy", "too many control clients; try again")))
                sock.close()
                continue
            conn = _Conn(sock, time.monotonic())
            self._conns[sock.fileno()] = conn
            self._guarded(conn, self._first_read)  # the request is usually there already

    def _first_read(self, conn: _Conn) -> None:
        self._read(conn)
        self._pump(conn)

    def _evict(self, why: str) -> bool:
        """Close the connection idle the longest (none with a request being worked on)."""
        idle = [c for c in self._conns.values() if not c.in_flight]
        if not idle:
            return False
        victim = min(idle, key=lambda c: c.last_active)
        self.counters["evicted"] += 1
        log.info("ctl_client_evicted", reason=why)
        self._close(victim)
        return True

    def _expire(self, now: float) -> None:
        for conn in list(self._conns.values()):
            if not conn.in_flight and now - conn.last_active > self.idle_timeout_s:
                self.counters["idle_closed"] += 1
                self._close(conn)

    def _on_event(self, conn: _Conn, mask: int) -> None:
        def handle(c: _Conn) -> None:
            if mask & selectors.EVENT_READ:
                self._read(c)
            self._pump(c)

        self._guarded(conn, handle)

    def _guarded(self, conn: _Conn, fn: Callable[[_Conn], None]) -> None:
        """Run ``fn(conn)``; an error of that connection closes it, nothing else."""
        if conn.sock.fileno() < 0:
            return
        try:
            fn(conn)
        except OSError as exc:  # the client went away
            self.counters["client_errors"] += 1
            log.info("ctl_client_closed", reason=str(exc))
            self._close(conn)
        except Exception as exc:
            self.counters["internal_errors"] += 1
            self.last_error = f"{type(exc).__name__}: {exc}"
            log.exception("ctl_connection_error")
            self._close(conn)

    def _read(self, conn: _Conn) -> None:
        try:
            data = conn.sock.recv(MAX_LINE_BYTES)
        except (BlockingIOError, InterruptedError):
            return
        if not data:
            conn.eof = True
        conn.inbuf += data

    def _next_line(self, conn: _Conn) -> bytes | None:
        i = conn.inbuf.find(b"\n")
        if i < 0 and conn.eof and conn.inbuf:
            i = len(conn.inbuf) - 1  # the last request, without its newline
        if i < 0 or i >= MAX_LINE_BYTES:
            return None
        line = bytes(conn.inbuf[: i + 1])
        del conn.inbuf[: i + 1]
        return line

    def _pump(self, conn: _Conn) -> None:
        """Write what is pending, then answer the lines waiting, in order, a few a turn."""
        for _ in range(REQUESTS_PER_TURN):
            if conn.outbuf:
                try:
                    sent = conn.sock.send(conn.outbuf)
                except (BlockingIOError, InterruptedError):
                    sent = 0
                del conn.outbuf[:sent]
                if conn.outbuf:
                    break  # wait for the client to read
            if conn.in_flight or conn.closing:
                break
            line = self._next_line(conn)
            if line is None:
                if len(conn.inbuf) >= MAX_LINE_BYTES:
                    self.counters["bad_request"] += 1
                    conn.inbuf.clear()
                    conn.closing = True
                    conn.outbuf += _line(_error("bad_request", "request line too long"))
                    continue
                break
            if line.strip():
                self._request(conn, line)
        else:
            self._ready[conn] = None  # more waiting: after the other connections
        done = conn.closing or (conn.eof and not conn.inbuf)
        if done and not conn.outbuf and not conn.in_flight:
            self._close(conn)
            return
        self._update(conn)

    def _request(self, conn: _Conn, line: bytes) -> None:
        conn.last_active = time.monotonic()
        req = parse(line)
        if not isinstance(req, Request):
            self.counters["bad_request"] += 1
            self._answer(conn, req, line)
        elif req.cmd in INLINE_COMMANDS and not req.args:  # a waiting status: the pool
            self._answer(conn, call(self.handlers, req), line)
        elif self._in_flight >= self.max_workers:
            self.counters["busy"] += 1
            self._answer(conn, _error("busy", f"{req.cmd}: the service is busy; try again"), line)
        else:
            self._in_flight += 1
            conn.in_flight = True
            if len(self._workers) < self.max_workers and len(self._workers) < self._in_flight:
                t = threading.Thread(
                    target=self._work, name=f"wara-ctl-worker-{len(self._workers)}", daemon=True
                )
                self._workers.append(t)
                t.start()
            self._jobs.put((conn, req, line))

    def _answer(self, conn: _Conn, reply: Reply, line: bytes) -> None:
        self.counters["requests"] += 1
        # a status answered is debug: the OPC UA server asks for one every 50 ms (with
        # its ``after`` and ``wait_ms``), every other command and every refusal is info
        quiet = reply.get("ok") is True and _cmd_of(line) == "status"
        (log.debug if quiet else log.info)(
            "ctl_request",
            request=line[:200].decode(errors="replace").strip(),
            ok=reply.get("ok"),
            code=reply.get("code"),
        )
        if conn.sock.fileno() >= 0:
            conn.outbuf += _line(reply)

    def _update(self, conn: _Conn) -> None:
        """Watch for what the connection can do next (never read past one line)."""
        want = 0
        if conn.outbuf:
            want |= selectors.EVENT_WRITE
        elif not (conn.in_flight or conn.closing or conn.eof) and b"\n" not in conn.inbuf:
            want |= selectors.EVENT_READ
        if want != conn.events and self._sel is not None:
            self._watch(self._sel, conn.sock, want, conn)
            conn.events = want

    def _close(self, conn: _Conn) -> None:
        self._ready.pop(conn, None)
        fd = conn.sock.fileno()
        if fd < 0:
            return
        self._conns.pop(fd, None)
        try:
            if self._sel is not None and conn.events:
                with contextlib.suppress(KeyError, ValueError, OSError):
                    self._sel.unregister(conn.sock)
        finally:
            conn.events = 0
            conn.sock.close()

    def _drop_connections(self) -> None:
        for conn in list(self._conns.values()):
            with contextlib.suppress(Exception):
                self._close(conn)
        self._conns.clear()
        self._ready.clear()

    def _wake(self) -> None:
        with contextlib.suppress(OSError):  # full: the I/O thread wakes anyway
            self._wake_w.send(b"\0")

    # ------------------------------------------------------------------ worker pool

    def _work(self) -> None:
        while True:
            job = self._jobs.get()
            if job is None:
                return
            conn, req, line = job
            self._results.put((conn, call(self.handlers, req), line))
            self._wake()


def request(
    cmd: str,
    *,
    socket_path: str | Path | None = None,
    timeout_s: float = 30.0,
    retry_s: float = 5.0,
    **args: Any,
) -> Reply:
    """Send one command to the service and return its reply (``ok`` tells the outcome).

    A full listen queue (``EAGAIN`` on connect) and a ``busy`` answer are retried, with a
    growing pause, for up to ``retry_s`` (at most ``timeout_s``).

    Raises :class:`CtlUnavailable` when nobody listens or the socket is not ours to use,
    :class:`CtlError` for a broken reply.
    """
    path = Path(socket_path) if socket_path is not None else default_socket_path()
    give_up = time.monotonic() + min(retry_s, timeout_s)
    pause = 0.01
    while True:
        reply = _request_once(path, cmd, timeout_s, args)
        if reply is not None and reply.get("code") != "busy":
            return reply
        if time.monotonic() + pause > give_up:
            if reply is not None:
                return reply
            raise CtlUnavailable(
                f"the W-ARa service at {path} accepts no connection (listen queue full) "
                f"after {min(retry_s, timeout_s):g} s of retries"
            )
        time.sleep(pause)
        pause = min(2 * pause, 0.2)


def _request_once(path: Path, cmd: str, timeout_s: float, args: Mapping[str, Any]) -> Reply | None:
    """One attempt; None when the listen queue is full (try again)."""
    # as given (NaN included: the server's checks answer it); replies are strict
    line = (json.dumps({"cmd": cmd, **args}, default=str) + "\n").encode()
    if len(line) > MAX_LINE_BYTES:  # the server would refuse it: say so, send nothing
        raise CtlError(
            f"the {cmd} request is {len(line)} bytes, over the control channel's "
            f"limit of {MAX_LINE_BYTES}"
        )
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    sock.settimeout(timeout_s)
    try:
        try:
            sock.connect(str(path))
        except (FileNotFoundError, ConnectionRefusedError):
            raise CtlUnavailable(
                f"no W-ARa service listening on {path} "
                "(is it running? `systemctl status wara-ipc`; or pass --socket PATH)"
            ) from None
        except PermissionError:
            raise CtlUnavailable(
                f"no permission to use {path}: it is owner-only; run as the service user "
                "(e.g. `sudo -u wara wara ctl ...`)"
            ) from None
        except BlockingIOError:
            return None  # the listen queue is full (EAGAIN)
        except OSError as exc:
            raise CtlUnavailable(f"cannot connect to {path}: {_why(exc)}") from None
        try:
            sock.sendall(line)
            with sock.makefile("rb") as rfile:
                raw = rfile.readline(MAX_REPLY_BYTES)
        except TimeoutError:
            raise CtlError(f"no reply from the service within {timeout_s:g} s ({path})") from None
        except OSError as exc:
            raise CtlError(f"control socket {path} failed: {_why(exc)}") from None
    finally:
        sock.close()
    if not raw:
        raise CtlError(f"the service at {path} closed the connection without a reply")
    try:
        reply = json.loads(raw)
    except (ValueError, RecursionError):
        raise CtlError(f"the service at {path} sent a reply that is not JSON") from None
    if not isinstance(reply, dict) or "ok" not in reply:
        raise CtlError(f"the service at {path} sent a reply without 'ok'")
    return reply
