"""Minimal ``sd_notify`` for a ``Type=notify`` unit, without extra dependencies.

systemd passes ``$NOTIFY_SOCKET`` (a path, or ``@name`` for the abstract namespace) and,
with ``WatchdogSec=``, ``$WATCHDOG_USEC`` (and ``$WATCHDOG_PID``). Messages are
newline-separated ``KEY=VALUE`` lines in one datagram: ``READY=1``, ``STATUS=...``,
``WATCHDOG=1``, ``STOPPING=1``. Outside systemd (no ``$NOTIFY_SOCKET``) every call is a
no-op returning False, so the service code calls it unconditionally.

Sends never block (``MSG_DONTWAIT``) and never raise: a failed send is counted in
:attr:`SystemdNotifier.send_errors` and logged once, because the control loop itself sends
``WATCHDOG=1`` (systemd should kill the service when *the loop* stalls, not when some
other thread is alive). :meth:`SystemdNotifier.watchdog_due` says when to ping: every
half of ``WATCHDOG_USEC``, as sd_watchdog_enabled(3) recommends.

Example (in the loop's step)::

    notifier = SystemdNotifier.from_env()
    notifier.ready("IDLE")                  # after start-up
    if notifier.watchdog_due(t_now):        # every cycle; sends at most every interval
        notifier.watchdog(t_now)
    notifier.stopping()                     # on shutdown
"""

from __future__ import annotations

import math
import os
import socket
from collections.abc import Mapping

import structlog

log = structlog.get_logger("wara.service.sdnotify")


def _address(path: str) -> str | bytes:
    if path.startswith("@"):
        return b"\0" + path[1:].encode()  # abstract namespace
    return path


class SystemdNotifier:
    """Talks to ``$NOTIFY_SOCKET``; a disabled notifier (``socket_path=None``) does nothing."""

    def __init__(self, socket_path: str | None, watchdog_usec: int | None = None) -> None:
        self.socket_path = socket_path or None
        self.ping_every_s: float | None = (
            watchdog_usec / 2e6 if watchdog_usec and watchdog_usec > 0 else None
        )
        self.send_errors = 0
        self._next_ping = -math.inf
        self._sock: socket.socket | None = None
        if self.socket_path is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
            self._addr = _address(self.socket_path)

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None) -> SystemdNotifier:
        """From ``$NOTIFY_SOCKET`` / ``$WATCHDOG_USEC`` / ``$WATCHDOG_PID`` (ours only)."""
        env = os.environ if environ is None else environ
        usec: int | None = None
        pid = env.get("WATCHDOG_PID")
        if env.get("WATCHDOG_USEC") and (not pid or pid == str(os.getpid())):
            try:
                usec = int(env["WATCHDOG_USEC"])
            except ValueError:
                log.warning("sdnotify_bad_watchdog_usec", value=env["WATCHDOG_USEC"])
        return cls(env.get("NOTIFY_SOCKET"), usec)

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    def notify(self, *fields: str) -> bool:
        """Send ``KEY=VALUE`` fields in one datagram; True if it was sent."""
        if self._sock is None:
            return False
        data = "\n".join(fields).encode()
        try:
            self._sock.sendto(data, socket.MSG_DONTWAIT, self._addr)
        except OSError as exc:
            self.send_errors += 1
            if self.send_errors == 1:
                log.warning("sdnotify_failed", socket=self.socket_path, error=str(exc))
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        """``READY=1`` (and ``STATUS=``): systemd considers the unit started."""
        return self.notify("READY=1", *([f"STATUS={status}"] if status else []))

    def status(self, text: str) -> bool:
        """``STATUS=``: shown by ``systemctl status wara-ipc``."""
        return self.notify(f"STATUS={text}")

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def watchdog_due(self, now: float) -> bool:
        """True when a ``WATCHDOG=1`` is due (half the watchdog interval has passed)."""
        return self.ping_every_s is not None and now >= self._next_ping

    def watchdog(self, now: float) -> bool:
        """Send ``WATCHDOG=1``; the next is due ``ping_every_s`` (half WATCHDOG_USEC) later."""
        if self.ping_every_s is not None:
            self._next_ping = now + self.ping_every_s
        return self.notify("WATCHDOG=1")

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None
