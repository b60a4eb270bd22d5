"""The local control channel: a Unix-domain socket, JSON lines, owner-only.

The protocol (the commands, their arguments and limits, the replies) is
:mod:`ipc_app.service.ctl_protocol`: one JSON object per line each way; a connection may
carry several requests (answered in order). A last request without its newline is
answered when the client half-closes (``shutdown(SHUT_WR)``).

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

The handlers (:class:`~ipc_app.service.ctl_protocol.CtlHandlers`) are injected by the
service and run in this module's threads, never in the loop thread; they talk to the loop
only through thread-safe objects (the mode machine, a queue).

The socket: ``path`` given by the service, else :func:`default_socket_path`
(``$WARA_CTL_SOCKET``; ``$RUNTIME_DIRECTORY/ctl.sock`` under systemd with
``RuntimeDirectory=wara``; ``/run/wara/ctl.sock`` when that directory exists; else
``$XDG_RUNTIME_DIR/wara/ctl.sock`` or ``<tmp>/wara-<uid>/ctl.sock``). It is bound under
``umask 0o177`` and chmod-ed 0600, so only the service's user (and root) can connect;
a directory the server creates is 0700. A stale socket file (nobody listening) is
replaced; a live one is an error (two services would fight over the valves).

Client: :func:`request` (``wara ctl`` uses it) raises :class:`CtlUnavailable` when no
service listens; a full listen queue or a ``busy`` answer is retried for a bounded time.

Over 500 lines because the selector thread, the worker pool and the eviction rules are
one piece: every limit a rude client meets is here.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import queue
import selectors
import socket
import stat
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import structlog

from ipc_app.service.ctl_client import (  # the client, for the channel's users
    MAX_LINE_BYTES,
    MAX_REPLY_BYTES,
    SOCKET_NAME,
    CtlError,
    CtlUnavailable,
    default_socket_path,
    os_reason,
    request,
)
from ipc_app.service.ctl_protocol import (  # the protocol, for the channel's users
    COMMANDS,
    INLINE_COMMANDS,
    TABLE,
    CtlHandlers,
    Reply,
    Request,
    _error,
    call,
    dispatch,
    parse,
)
from ipc_app.service.requests import (  # the limits, for the channel's users
    MAX_AUDIT_CHARS,
    MAX_ID_CHARS,
    MAX_STATUS_WAIT_MS,
    MAX_SURVEY_POINTS,
    MAX_WALK_STEPS,
    check_sheet_deviation,
)

log = structlog.get_logger("wara.service.ctl")

#: Requests of one connection answered before the other connections get their turn.
REQUESTS_PER_TURN = 16
#: The I/O thread wakes at least this often (stop, idle time-outs, the health tick).
TICK_S = 0.2


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
            raise CtlError(f"cannot create control socket {self.path}: {os_reason(exc)}") from None
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
            raise CtlError(f"cannot bind control socket {self.path}: {os_reason(exc)}") from None
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


__all__ = [
    "COMMANDS",
    "INLINE_COMMANDS",
    "MAX_AUDIT_CHARS",
    "MAX_ID_CHARS",
    "MAX_LINE_BYTES",
    "MAX_REPLY_BYTES",
    "MAX_STATUS_WAIT_MS",
    "MAX_SURVEY_POINTS",
    "MAX_WALK_STEPS",
    "SOCKET_NAME",
    "TABLE",
    "CtlError",
    "CtlHandlers",
    "CtlServer",
    "CtlUnavailable",
    "Request",
    "call",
    "check_sheet_deviation",
    "default_socket_path",
    "dispatch",
    "parse",
    "request",
]
