"""sd_notify against a real AF_UNIX datagram socket (path and abstract namespace)."""

from __future__ import annotations

import os
import socket
from collections.abc import Iterator
from pathlib import Path

import pytest

from ipc_app.service.sdnotify import SystemdNotifier


@pytest.fixture
def receiver(tmp_path: Path) -> Iterator[tuple[socket.socket, str]]:
    path = str(tmp_path / "notify.sock")
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.settimeout(5.0)
    yield sock, path
    sock.close()


def test_not_under_systemd_is_a_noop() -> None:
    n = SystemdNotifier.from_env({})
    assert not n.enabled
    assert n.ready("IDLE") is False
    assert n.watchdog_due(1e9) is False and n.watchdog(0.0) is False


def test_ready_status_watchdog_stopping_on_a_path_socket(
    receiver: tuple[socket.socket, str],
) -> None:
    sock, path = receiver
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path})
    assert n.enabled
    assert n.ready("IDLE, loop 200 Hz")
    assert sock.recv(4096) == b"READY=1\nSTATUS=IDLE, loop 200 Hz"
    assert n.status("EXECUTE")
    assert sock.recv(4096) == b"STATUS=EXECUTE"
    assert n.watchdog(0.0)
    assert sock.recv(4096) == b"WATCHDOG=1"
    assert n.stopping()
    assert sock.recv(4096) == b"STOPPING=1"
    n.close()


def test_abstract_namespace() -> None:
    name = f"wara-test-notify-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(b"\0" + name.encode())
    sock.settimeout(5.0)
    try:
        n = SystemdNotifier.from_env({"NOTIFY_SOCKET": "@" + name})
        assert n.ready()
        assert sock.recv(4096) == b"READY=1"
    finally:
        sock.close()


def test_watchdog_pings_at_half_the_interval(receiver: tuple[socket.socket, str]) -> None:
    sock, path = receiver
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "2000000"})
    assert n.ping_every_s == 1.0
    sent = 0
    for k in range(0, 300):  # 3 s at 100 Hz on a virtual clock
        t = k * 0.01
        if n.watchdog_due(t):
            n.watchdog(t)
            sent += 1
    assert sent == 3  # t = 0, 1, 2 s
    assert [sock.recv(64) for _ in range(sent)] == [b"WATCHDOG=1"] * 3


def test_watchdog_for_another_pid_is_ignored(receiver: tuple[socket.socket, str]) -> None:
    _, path = receiver
    env = {"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "1000000", "WATCHDOG_PID": "1"}
    assert SystemdNotifier.from_env(env).ping_every_s is None
    env["WATCHDOG_PID"] = str(os.getpid())
    assert SystemdNotifier.from_env(env).ping_every_s == 0.5


def test_send_failure_is_counted_not_raised(tmp_path: Path) -> None:
    n = SystemdNotifier.from_env({"NOTIFY_SOCKET": str(tmp_path / "nobody-listens")})
    assert n.ready() is False and n.watchdog(0.0) is False
    assert n.send_errors == 2
