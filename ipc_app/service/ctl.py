"""The local control channel: a Unix-domain socket, JSON lines, owner-only.

Protocol: the client writes one JSON object per line, the server answers each with one
JSON object on one line; a connection may carry several requests.

=========  ===========================================  =====================================
command    request                                      reply (besides ``"ok": true``)
=========  ===========================================  =====================================
adjust     ``{"cmd": "adjust", "roll_deg": R,           what the service's handler returns,
           "pitch_deg": P}``                            e.g. ``mode``, ``request_id``
status     ``{"cmd": "status"}``                        the service's status (``mode``, ...)
stop       ``{"cmd": "stop"}``                          ``mode``
reset      ``{"cmd": "reset"}``                         ``mode``
=========  ===========================================  =====================================

A refused or failed request answers ``{"ok": false, "error": "one line", "code": C}`` with
``C`` one of ``bad_request`` (not JSON, unknown command, missing or non-finite number),
``refused`` (the mode machine said no, e.g. adjust while FAULT), ``busy`` (too many
clients), ``infeasible`` (the
planner's ``reasons`` list is included) or ``internal`` (a handler raised; logged).

The handlers (:class:`CtlHandlers`) are injected by the service and run in this module's
threads, never in the loop thread: they may block (``adjust`` may wait for the planner to
answer so the operator sees the reasons of an infeasible target), and they talk to the
loop only through thread-safe objects (the mode machine, a queue).

The socket: ``path`` given by the service, else :func:`default_socket_path`
(``$WARA_CTL_SOCKET``; ``$RUNTIME_DIRECTORY/ctl.sock`` under systemd with
``RuntimeDirectory=wara``; ``/run/wara/ctl.sock`` when that directory exists; else
``$XDG_RUNTIME_DIR/wara/ctl.sock`` or ``<tmp>/wara-<uid>/ctl.sock``). It is bound under
``umask 0o177`` and chmod-ed 0600, so only the service's user (and root) can connect;
a directory the server creates is 0700. A stale socket file (nobody listening) is
replaced; a live one is an error (two services would fight over the valves).

Client: :func:`request` (``wara ctl`` uses it) raises :class:`CtlUnavailable` when no
service listens.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import socket
import stat
import tempfile
import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import structlog

log = structlog.get_logger("wara.service.ctl")

SOCKET_NAME = "ctl.sock"
SYSTEM_RUNTIME_DIR = Path("/run/wara")
MAX_LINE_BYTES = 64 * 1024
COMMANDS = ("adjust", "status", "stop", "reset")

Reply = dict[str, Any]


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
    status: Callable[[], Reply]
    stop: Callable[[], Reply]
    reset: Callable[[], Reply]


def _error(code: str, message: str) -> Reply:
    return {"ok": False, "error": message, "code": code}


def _number(req: Mapping[str, Any], key: str) -> float:
    v = req.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ValueError(f"{key!r} must be a finite number in degrees, got {v!r}")
    return float(v)


def dispatch(handlers: CtlHandlers, line: bytes) -> Reply:
    """One request line -> one reply (the protocol, without the socket)."""
    try:
        req = json.loads(line)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        return _error("bad_request", f"request is not JSON: {exc}")
    if not isinstance(req, dict):
        return _error("bad_request", "request must be a JSON object with a 'cmd' key")
    cmd = req.get("cmd")
    if cmd not in COMMANDS:
        return _error("bad_request", f"unknown command {cmd!r}; expected one of {COMMANDS}")
    try:
        if cmd == "adjust":
            roll, pitch = _number(req, "roll_deg"), _number(req, "pitch_deg")
            if abs(roll) >= 90 or abs(pitch) >= 90:
                return _error("bad_request", "roll_deg and pitch_deg must be within ±90 deg")
            reply = handlers.adjust(roll, pitch)
        elif cmd == "status":
            reply = handlers.status()
        elif cmd == "stop":
            reply = handlers.stop()
        else:
            reply = handlers.reset()
    except ValueError as exc:
        return _error("bad_request", str(exc))
    except Exception as exc:
        log.exception("ctl_handler_failed", cmd=cmd)
        return _error("internal", f"{cmd} failed in the service: {type(exc).__name__}: {exc}")
    out: Reply = {"ok": True}
    out.update(reply)
    return out


class CtlServer:
    """Serves :class:`CtlHandlers` on a Unix socket from its own threads."""

    def __init__(
        self,
        handlers: CtlHandlers,
        path: str | Path | None = None,
        *,
        idle_timeout_s: float = 60.0,
        max_clients: int = 8,
    ) -> None:
        self.handlers = handlers
        self.path = Path(path) if path is not None else default_socket_path()
        self._idle_timeout_s = idle_timeout_s
        self._slots = threading.BoundedSemaphore(max_clients)
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._closing = threading.Event()

    def start(self) -> None:
        """Bind (0600), listen and serve from a background thread."""
        self._prepare_path()
        sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM | socket.SOCK_CLOEXEC)
        old = os.umask(0o177)
        try:
            sock.bind(str(self.path))
        except OSError as exc:
            sock.close()
            raise CtlError(f"cannot bind control socket {self.path}: {exc.strerror}") from None
        finally:
            os.umask(old)
        os.chmod(self.path, 0o600)
        sock.listen(8)
        sock.settimeout(0.2)  # accept wakes up to notice stop()
        self._sock = sock
        self._thread = threading.Thread(target=self._accept_loop, name="wara-ctl", daemon=True)
        self._thread.start()
        log.info("ctl_listening", socket=str(self.path))

    def stop(self) -> None:
        self._closing.set()
        if self._thread is not None:
            self._thread.join(2.0)
        if self._sock is not None:
            self._sock.close()
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
            self._sock = None

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

    def _accept_loop(self) -> None:
        assert self._sock is not None
        while not self._closing.is_set():
            try:
                conn, _ = self._sock.accept()
            except TimeoutError:
                continue
            except OSError:
                if self._closing.is_set():
                    return
                raise
            if not self._slots.acquire(blocking=False):
                with conn:
                    conn.sendall(_line(_error("busy", "too many control clients; try again")))
                continue
            threading.Thread(
                target=self._serve, args=(conn,), name="wara-ctl-client", daemon=True
            ).start()

    def _serve(self, conn: socket.socket) -> None:
        try:
            conn.settimeout(self._idle_timeout_s)
            with conn, conn.makefile("rb") as rfile:
                while not self._closing.is_set():
                    line = rfile.readline(MAX_LINE_BYTES + 1)
                    if not line:
                        return
                    if len(line) > MAX_LINE_BYTES:
                        conn.sendall(_line(_error("bad_request", "request line too long")))
                        return
                    if not line.strip():
                        continue
                    reply = dispatch(self.handlers, line)
                    log.info(
                        "ctl_request",
                        request=line[:200].decode(errors="replace").strip(),
                        ok=reply.get("ok"),
                        code=reply.get("code"),
                    )
                    conn.sendall(_line(reply))
        except OSError as exc:  # client went away or idled out
            log.info("ctl_client_closed", reason=str(exc))
        finally:
            self._slots.release()


def _line(obj: Reply) -> bytes:
    return (json.dumps(obj, default=str) + "\n").encode()


def request(
    cmd: str,
    *,
    socket_path: str | Path | None = None,
    timeout_s: float = 30.0,
    **args: Any,
) -> Reply:
    """Send one command to the service and return its reply (``ok`` tells the outcome).

    Raises :class:`CtlUnavailable` when nobody listens or the socket is not ours to use,
    :class:`CtlError` for a broken reply.
    """
    path = Path(socket_path) if socket_path is not None else default_socket_path()
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
        except OSError as exc:
            raise CtlUnavailable(f"cannot connect to {path}: {exc.strerror or exc}") from None
        try:
            sock.sendall(_line({"cmd": cmd, **args}))
            with sock.makefile("rb") as rfile:
                raw = rfile.readline(MAX_LINE_BYTES * 16)
        except TimeoutError:
            raise CtlError(f"no reply from the service within {timeout_s:g} s ({path})") from None
        except OSError as exc:
            raise CtlError(f"control socket {path} failed: {exc.strerror or exc}") from None
    finally:
        sock.close()
    if not raw:
        raise CtlError(f"the service at {path} closed the connection without a reply")
    try:
        reply = json.loads(raw)
    except json.JSONDecodeError:
        raise CtlError(f"the service at {path} sent a reply that is not JSON") from None
    if not isinstance(reply, dict) or "ok" not in reply:
        raise CtlError(f"the service at {path} sent a reply without 'ok'")
    return reply
