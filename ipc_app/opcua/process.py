"""Start and watch the OPC UA server process (``python -m ipc_app.opcua``).

``wara serve`` starts it when ``opcua.enabled`` and ``wara demo --opcua`` for the demo.
The process takes the service's status over the control socket and retries while the
service is not up yet, so it may start before the service. Should it end after start-up
it is started again (after :data:`RESTART_PAUSE_S`); its stderr (JSON log lines) goes
to ours. No asyncua here: the import stays in the child.
"""

from __future__ import annotations

import contextlib
import os
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Sequence
from pathlib import Path
from typing import IO

import structlog

from ipc_app.service.worker import under_normal_scheduler

log = structlog.get_logger("wara.opcua.process")

RESTART_PAUSE_S = 2.0
START_TIMEOUT_S = 60.0


class OpcUaStartError(Exception):
    """The server process did not come up (one line: its own last error line)."""


class OpcUaProcess:
    def __init__(
        self,
        config_path: str | Path | None,
        socket_path: str | Path,
        extra_args: Sequence[str] = (),
        *,
        stderr: IO[str] | None = None,
    ) -> None:
        self.argv = [sys.executable, "-m", "ipc_app.opcua", "--socket", str(socket_path)]
        if config_path is not None:
            self.argv += ["--config", str(config_path)]
        self.argv += list(extra_args)
        self.stderr = stderr if stderr is not None else sys.stderr
        self.url: str | None = None
        self.restarts = 0
        self.proc: subprocess.Popen[str] | None = None
        self._tail: deque[str] = deque(maxlen=5)
        self._stop = threading.Event()
        self._watch: threading.Thread | None = None

    def _spawn(self) -> subprocess.Popen[str]:
        # under the normal scheduler whatever the spawning thread's policy (a restart comes
        # from the watch thread, which may run under SCHED_FIFO): asyncua computing at the
        # loop's priority would keep a CPU from it
        proc = under_normal_scheduler(
            lambda: subprocess.Popen(
                self.argv,
                stdin=subprocess.DEVNULL,
                stdout=subprocess.PIPE,
                stderr=subprocess.PIPE,
                text=True,
                env=os.environ.copy(),
            )
        )
        threading.Thread(target=self._pump_err, args=(proc,), daemon=True).start()
        return proc

    def _pump_err(self, proc: subprocess.Popen[str]) -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            self._tail.append(line.rstrip())
            with contextlib.suppress(ValueError, OSError):
                self.stderr.write(line)

    def _wait_ready(self, proc: subprocess.Popen[str], timeout_s: float) -> str:
        assert proc.stdout is not None
        box: list[str] = []

        def read() -> None:
            assert proc.stdout is not None
            for line in proc.stdout:
                if line.startswith("READY ") and not box:
                    box.append(line.split(None, 1)[1].strip())
            # stdout drained to its end (the child's exit)

        t = threading.Thread(target=read, daemon=True)
        t.start()
        deadline = time.monotonic() + timeout_s
        while not box and time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.05)
        if box:
            return box[0]
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        time.sleep(0.1)  # the last stderr line
        why = self._tail[-1] if self._tail else f"exit {proc.returncode}"
        raise OpcUaStartError(f"the OPC UA server did not start: {why}")

    def start(self, timeout_s: float = START_TIMEOUT_S) -> str:
        """Start it and wait for it to listen; the endpoint URL."""
        self.proc = self._spawn()
        self.url = self._wait_ready(self.proc, timeout_s)
        self._watch = threading.Thread(target=self._supervise, name="wara-opcua-watch", daemon=True)
        self._watch.start()
        return self.url

    def _supervise(self) -> None:
        while not self._stop.is_set():
            proc = self.proc
            if proc is not None and proc.poll() is not None:
                log.error("opcua_server_exited", code=proc.returncode, last=list(self._tail)[-1:])
                if self._stop.wait(RESTART_PAUSE_S):
                    return
                try:
                    self.proc = self._spawn()
                    self._wait_ready(self.proc, START_TIMEOUT_S)
                    self.restarts += 1
                    log.info("opcua_server_restarted", restarts=self.restarts)
                except OpcUaStartError as exc:
                    log.error("opcua_restart_failed", error=str(exc))
            self._stop.wait(0.5)

    @property
    def running(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def stop(self, timeout_s: float = 10.0) -> int | None:
        self._stop.set()
        proc = self.proc
        if proc is None:
            return None
        if proc.poll() is None:
            proc.terminate()
            try:
                proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
        if self._watch is not None:
            self._watch.join(timeout_s)
        return proc.returncode
