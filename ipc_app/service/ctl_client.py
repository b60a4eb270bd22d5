"""The control channel's client: :func:`request` sends one command to the service's
socket (``wara ctl``, the OPC UA server) and returns its reply; :func:`default_socket_path`
is where the service listens (see :mod:`ipc_app.service.ctl`).

:func:`request` raises :class:`CtlUnavailable` when no service listens; a full listen
queue or a ``busy`` answer is retried for a bounded time.
"""

from __future__ import annotations

import json
import os
import socket
import tempfile
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

Reply = dict[str, Any]

SOCKET_NAME = "ctl.sock"
SYSTEM_RUNTIME_DIR = Path("/run/wara")
MAX_LINE_BYTES = 64 * 1024
#: Largest reply the client reads (a status is a few KiB).
MAX_REPLY_BYTES = 16 * MAX_LINE_BYTES


class CtlError(Exception):
    """The control channel could not be used (bad reply, socket in use, ...)."""


class CtlUnavailable(CtlError):
    """No service listens on the socket (not running, wrong path, or no permission)."""


def default_socket_path(environ: Mapping[str, str] | None = None) -> Path:
    """Where the service listens and ``wara ctl`` connects (in the order of
    :mod:`ipc_app.service.ctl`)."""
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


def os_reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


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
            raise CtlUnavailable(f"cannot connect to {path}: {os_reason(exc)}") from None
        try:
            sock.sendall(line)
            with sock.makefile("rb") as rfile:
                raw = rfile.readline(MAX_REPLY_BYTES)
        except TimeoutError:
            raise CtlError(f"no reply from the service within {timeout_s:g} s ({path})") from None
        except OSError as exc:
            raise CtlError(f"control socket {path} failed: {os_reason(exc)}") from None
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
