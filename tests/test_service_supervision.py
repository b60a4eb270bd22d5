"""The running service (`wara serve` as systemd starts it) supervises its control channel:
the socket file removed under it is a FAULT that `status` shows, and the channel comes back."""

from __future__ import annotations

import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import pytest

from ipc_app.service.ctl import CtlError, request

pytestmark = pytest.mark.slow


def _wait_status(path: Path, timeout_s: float) -> dict[str, Any]:
    end = time.monotonic() + timeout_s
    while True:
        try:
            return request("status", socket_path=path, timeout_s=5)
        except CtlError:
            if time.monotonic() > end:
                raise
            time.sleep(0.1)


def test_a_removed_socket_is_a_fault_and_the_channel_comes_back() -> None:
    with tempfile.TemporaryDirectory(prefix="wara-sup-") as d:
        sock = Path(d) / "ctl.sock"
        proc = subprocess.Popen(
            [
                *(sys.executable, "-m", "wara", "serve", "--socket", str(sock)),
                *("--record-dir", str(Path(d) / "runs"), "--duration-s", "120"),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
        )
        try:
            st = _wait_status(sock, 60)
            assert st["ctl"]["state"] == "ok" and st["ctl"]["restarts"] == 0
            sock.unlink()
            st = _wait_status(sock, 10)  # bound again by the service's supervision
            assert st["ctl"]["restarts"] == 1 and st["ctl"]["state"] == "ok"
            for _ in range(100):  # the status is the last cycle's: wait for one more
                if any(f["interlock"] == "control channel" for f in st["faults"]):
                    break
                time.sleep(0.05)
                st = _wait_status(sock, 10)
            assert st["mode"] == "ABORTED"
            assert ("control channel", "socket_gone") in [
                (f["interlock"], f["where"]) for f in st["faults"]
            ]
            assert request("stop", socket_path=sock)["ok"]
        finally:
            proc.send_signal(signal.SIGTERM)
            _, err = proc.communicate(timeout=30)
        assert proc.returncode == 0, err[-2000:]
        assert "Traceback" not in err
        assert '"event": "ctl_unhealthy"' in err and '"event": "ctl_restarted"' in err
