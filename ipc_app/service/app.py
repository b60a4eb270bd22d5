"""The IPC service process: wires the CAN link, the planner worker, the control core,
the fixed-rate loop, the control channel and systemd together.

``wara serve`` runs it (the systemd unit's ExecStart). READY is sent once the loop runs;
WATCHDOG is sent from the loop thread itself, so a stalled loop is restarted by systemd.
SIGTERM/SIGINT stop it: valves commanded closed, then everything shut down in order.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from config import load_project
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import CtlHandlers, CtlServer
from ipc_app.service.logs import configure_logging
from ipc_app.service.loop import FixedRateLoop
from ipc_app.service.record import RunRecorder, new_run_dir
from ipc_app.service.sdnotify import SystemdNotifier
from ipc_app.service.worker import PlannerWorker
from plc_bridge.link import IpcLink

log = structlog.get_logger("wara.service")

#: How long ``wara ctl adjust`` waits for the planner's verdict.
ADJUST_WAIT_S = 15.0


def run_service(
    config_path: str | Path | None,
    *,
    socket_path: str | Path | None = None,
    duration_s: float | None = None,
    stop_event: threading.Event | None = None,
    record_root: str | Path | None = None,
    log_level: str = "INFO",
) -> int:
    """Run until SIGTERM/SIGINT (or ``duration_s``, or ``stop_event``); exit code.

    Logs are JSON lines on stderr (journald keeps them); the run record goes to
    ``record_root/<UTC time>/`` (default ``$STATE_DIRECTORY/runs`` under systemd, else
    ``./wara-data/runs``).
    """
    cfg = load_project(config_path)
    logging_handle = configure_logging(log_level)
    stop = stop_event or threading.Event()
    root = Path(record_root) if record_root else default_record_root()
    recorder = RunRecorder(
        new_run_dir(root),
        ServiceCore.record_columns(cfg),
        meta={"project": cfg.project.name, "period_s": cfg.control.period_s},
    )
    recorder.start()
    link = IpcLink.from_config(cfg)
    worker = PlannerWorker(config_path)
    worker.start()
    core = ServiceCore(cfg, link, worker, record=recorder)
    notifier = SystemdNotifier.from_env()

    def step(cycle: int, now: float) -> None:
        core.step(cycle, now)
        if notifier.watchdog_due(now):
            notifier.watchdog(now)

    def on_stats(stats: dict[str, Any]) -> None:
        core.loop_stats = stats
        snap = core.snapshot()
        log.info(
            "loop_stats",
            **stats,
            mode=snap.get("mode"),
            link=snap.get("link"),
            sync_error_mm=snap.get("sync_error_mm"),
            twist_mm=snap.get("twist_mm"),
        )

    loop = FixedRateLoop(
        step, cfg.control.period_s, realtime=cfg.control.realtime, on_stats=on_stats
    )
    handlers = CtlHandlers(
        adjust=lambda r, p: core.request_adjust(r, p, wait_s=ADJUST_WAIT_S),
        status=core.snapshot,
        stop=lambda: core.modes.stop("operator stop (wara ctl)").to_dict(),
        reset=lambda: core.request_reset(wait_s=ADJUST_WAIT_S),
    )
    ctl = CtlServer(handlers, socket_path)
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    ctl.start()
    loop.start()
    notifier.ready(f"controlling at {cfg.control.loop_rate_hz:g} Hz")
    log.info(
        "service_started",
        project=cfg.project.name,
        can=cfg.can.interface,
        channel=cfg.can.channel,
        socket=str(ctl.path),
        realtime=loop.realtime_report.to_dict(),
    )
    deadline = None if duration_s is None else time.monotonic() + duration_s
    code = 0
    while not stop.wait(0.2):
        if loop.error is not None or not loop.running:
            log.error("loop_stopped", error=repr(loop.error))
            code = 1
            break
        if deadline is not None and time.monotonic() >= deadline:
            break
    notifier.stopping()
    loop.stop()
    core.modes.stop("service stopping")
    link.send_valve_commands(np.zeros(len(cfg.cylinders)))
    ctl.stop()
    worker.close()
    link.close()
    summary = recorder.stop()
    log.info(
        "service_stopped",
        code=code,
        cycles=core.cycles,
        record=str(recorder.run_dir),
        record_summary=summary,
    )
    logging_handle.stop()
    return code


def default_record_root() -> Path:
    state = os.environ.get("STATE_DIRECTORY")
    return Path(state.split(":")[0]) / "runs" if state else Path("wara-data") / "runs"
