"""The IPC service process: wires the CAN link, the planner worker, the control core,
the fixed-rate loop, the control channel and systemd together.

``wara serve`` runs it (the systemd unit's ExecStart). Start-up opens the CAN bus and
binds the control socket before anything else (a failure is one line,
:class:`StartupError`, and leaves no run record behind). READY is sent once the loop runs;
WATCHDOG is sent from the loop thread itself, so a stalled loop is restarted by systemd.
SIGTERM/SIGINT stop it: valves commanded closed, then everything shut down in order.

The control channel is supervised (:class:`CtlWatch`): when its server thread ends or
the socket file goes away, ABORTED is latched (the operator lost ``stop``) and the server is
restarted; ``wara ctl status`` shows it under ``ctl``. A server that stalls, or cannot be
restarted, stops the service in order (exit 1, systemd restarts it), and the loop holds
back WATCHDOG while the channel is unhealthy.
"""

from __future__ import annotations

import contextlib
import os
import signal
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import structlog

from config import ProjectConfig, load_project, units
from ipc_app.model.placement import POSE_DICT_KEYS, Pose, sheet_deviation
from ipc_app.planner.steering import OnAxis
from ipc_app.planner.survey import SurveyPoint, as_built_problems
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import CtlError, CtlHandlers, CtlServer
from ipc_app.service.cycle import RingRecords, previous_from_deviation
from ipc_app.service.interlocks import Cause, Interlock
from ipc_app.service.logs import configure_logging
from ipc_app.service.loop import SWITCH_INTERVAL_S, FixedRateLoop, SlackGate
from ipc_app.service.record import RunRecorder, new_run_dir
from ipc_app.service.sdnotify import SystemdNotifier
from ipc_app.service.worker import PlannerWorker
from plc_bridge.errors import BridgeError
from plc_bridge.link import IpcLink

log = structlog.get_logger("wara.service")

#: How long ``wara ctl adjust`` waits for the planner's verdict.
ADJUST_WAIT_S = 15.0
#: A status waits at most this many loop periods for the end of a cycle (SlackGate).
SLACK_WAIT_PERIODS = 2


class StartupError(Exception):
    """The service cannot start: the CAN bus, the control socket or the run record
    directory cannot be opened (one line: what, where, and the fix where known)."""


def service_handlers(
    core: Callable[[], ServiceCore],
    ctl: Callable[[], CtlServer],
    wait_s: float = ADJUST_WAIT_S,
    slack: SlackGate | None = None,
    records: RingRecords | None = None,
) -> CtlHandlers:
    """The control channel's commands on the service core (``core`` and ``ctl`` are asked
    for at each request: the socket is bound before the core is built). ``adjust`` and
    ``reset`` wait up to ``wait_s`` for their outcome; the status carries ``ctl``, the
    channel's own health. With ``slack`` (the loop's gate) a status is built right after
    a loop cycle's step, in the loop's slack, not during its compute. ``records``: where
    ``cycle`` writes the rings' acceptance records (None: a cycle is refused)."""

    def status(after: int | None = None, wait_s: float = 0.0) -> dict[str, Any]:
        c = core()
        waited: dict[str, float] = {}
        if after is not None:  # until the next change of state, at most wait_s
            t0 = time.monotonic()
            c.state_changes.wait(after, wait_s)
            waited["waited_ms"] = units.to_ms(time.monotonic() - t0)
        if slack is not None:
            slack.wait(SLACK_WAIT_PERIODS * c.period_s)
        return c.snapshot() | {"ctl": ctl().health(), "state_seq": c.state_changes.seq} | waited

    return CtlHandlers(
        adjust=lambda r, p: _reply(core().request_adjust(r, p, wait_s=wait_s)),
        status=status,
        stop=lambda: _reply(core().stop("operator stop (wara ctl)")),
        reset=lambda: _reply(core().request_reset(wait_s=wait_s)),
        clear=lambda: _reply(core().request_clear(wait_s=wait_s)),
        hold=lambda: _reply(core().request_hold(wait_s=wait_s)),
        unhold=lambda: _reply(core().request_unhold(wait_s=wait_s)),
        unit_mode=lambda u: _reply(core().request_unit_mode(u)),
        jog=lambda c, d: _reply(core().request_jog(c, d, wait_s=wait_s)),
        audit=lambda u, a, r: core().audit(u, a, r),
        walk=lambda n, d, u: _reply(core().request_walk(n, wait_s=wait_s, direction=d, unloaded=u)),
        place=lambda r, d: _reply(core().request_place(r, sheet_deviation(*d), wait_s=wait_s)),
        cycle=lambda r, prev, n, u: _reply(_cycle(core(), records, r, prev, n, u)),
        confirm_fixed=lambda user: _reply(core().confirm_fixed(user)),
        survey=lambda pts, pose: _reply(_survey(core(), pts, pose)),
        locate=lambda c, h, lat: _reply(core().locate(OnAxis(c, units.deg(h), units.mm(lat)))),
        motion=lambda kind, args: _reply(core().start_motion(kind, args, wait_s=wait_s)),
    )


def _cycle(
    core: ServiceCore,
    records: RingRecords | None,
    ring: int,
    prev: tuple[float, ...],
    steps: int | None,
    unloaded: bool,
) -> dict[str, Any]:
    """``wara ctl cycle``: the previous part from its deviation (5 numbers) or its
    as-built pose (6), then :meth:`ServiceCore.request_cycle`, ticked by its thread."""
    if records is None:
        msg = "cycle refused: this service has no acceptance store for the ring's records"
        return {"ok": False, "code": "refused", "error": msg}
    if len(prev) == 6:
        previous = _pose(prev)
        problems = as_built_problems(core.cfg, ring - 1, previous)
        if problems:  # in ring - 1's own T: a pose of another ring, or another frame
            msg = f"cycle refused: previous_pose: {'; '.join(problems)}"
            return {"ok": False, "code": "bad_request", "error": msg}
    else:
        previous = previous_from_deviation(core.cfg, ring, sheet_deviation(*prev))
    return core.request_cycle(
        ring, previous, records, walk_steps=steps, walk_back_unloaded=unloaded
    )


def _pose(values: tuple[float, ...]) -> Pose:
    """A pose sent as six numbers (:data:`POSE_DICT_KEYS`: mm and deg)."""
    return Pose.from_dict(dict(zip(POSE_DICT_KEYS, values, strict=True)))


def _survey(
    core: ServiceCore, pts: tuple[Any, ...] | None, pose: tuple[float, ...] | None
) -> dict[str, Any]:
    """``wara ctl survey``: the points of a survey file, or the store's as-built pose."""
    if pose is not None:
        return core.submit_survey(pose=_pose(pose))
    assert pts is not None
    points = []
    for k, (name, fy, fz, x, y, z) in enumerate(pts, start=1):
        try:  # each point checked as a file's line is (name, coordinate ranges)
            points.append(SurveyPoint(k, name, (fy, fz), (x, y, z)))
        except ValueError as exc:
            return {"ok": False, "code": "bad_request", "error": f"survey: point {k}: {exc}"}
    return core.submit_survey(points=points)


def _reply(out: dict[str, Any]) -> dict[str, Any]:
    """The core's answers in the channel's terms: a mode-machine outcome that was not
    accepted is ``refused`` (with its message as the error), and a refusal carries its
    one-line ``error`` (an infeasible verdict has only the planner's reasons)."""
    if "ok" not in out and out.get("accepted") is False:
        out = {"ok": False, "code": "refused", "error": out.get("message", "refused")} | out
    if out.get("ok") is False and not isinstance(out.get("error"), str):
        reasons = out.get("reasons") or []
        why = "target infeasible" if out.get("code") == "infeasible" else "refused"
        out = out | {"error": f"{why}: {reasons[0]}" if reasons else why}
    return out


def watched_step(
    step: Callable[[int, float], None], notifier: SystemdNotifier, ctl: CtlServer
) -> Callable[[int, float], None]:
    """The loop's step: ``step``, then ``WATCHDOG=1`` when due, but only while the control
    channel is healthy (so systemd restarts a service whose channel stays dead even if
    its main thread no longer supervises it)."""

    def run(cycle: int, now: float) -> None:
        step(cycle, now)
        if notifier.watchdog_due(now) and ctl.healthy:
            notifier.watchdog(now)

    return run


class CtlWatch:
    """Supervises the control channel from the service's main thread (:meth:`check`
    every 0.2 s): an unhealthy channel is a fault, latched once per outage with
    ``fault(reason)``, and a server whose thread ended or whose socket file is gone is
    restarted. :meth:`check` returns False when the channel cannot be brought back (a
    stalled thread, a failed restart): the service then stops.
    """

    def __init__(self, ctl: CtlServer, fault: Callable[[Cause], object]) -> None:
        self.ctl = ctl
        self.fault = fault
        self.outages = 0
        self._down = False

    def check(self) -> bool:
        state = self.ctl.state()
        if state in ("ok", "stopped"):
            self._down = False
            return True
        if not self._down:
            self._down = True
            self.outages += 1
            why = {
                "socket_gone": f"{self.ctl.path} removed or replaced",
                "stalled": f"no turn for over {self.ctl.stall_s:g} s",
            }.get(state, self.ctl.last_error or "no error recorded")
            log.error("ctl_unhealthy", state=state, reason=why)
            self.fault(Cause(Interlock.CONTROL_CHANNEL, where=state, detail=why))
        if state == "stalled":
            return False
        if not self.ctl.restart():
            return False
        self._down = False
        return True


def ctl_server(
    cfg: ProjectConfig, handlers: CtlHandlers, socket_path: str | Path | None
) -> CtlServer:
    """The service's control channel: stalled after ``safety.ctl_stall_timeout_s``."""
    return CtlServer(handlers, socket_path, stall_s=cfg.safety.ctl_stall_timeout_s)


def planner_worker(
    cfg: ProjectConfig, config_path: str | Path | None, **kwargs: Any
) -> PlannerWorker:
    """The service's planner process (not started): a request without a result after
    ``planner.request_timeout_s`` fails (the PLANNER interlock). ``kwargs``: the
    worker's other arguments (tests: ``plan_fn``)."""
    return PlannerWorker(config_path, timeout_s=cfg.planner.request_timeout_s, **kwargs)


def run_service(
    config_path: str | Path | None,
    *,
    socket_path: str | Path | None = None,
    duration_s: float | None = None,
    stop_event: threading.Event | None = None,
    record_root: str | Path | None = None,
    log_level: str = "INFO",
    ring_records: RingRecords | None = None,
) -> int:
    """Run until SIGTERM/SIGINT (or ``duration_s``, or ``stop_event``); exit code.

    Logs are JSON lines on stderr (journald keeps them); the run record goes to
    ``record_root/<UTC time>/`` (default ``$STATE_DIRECTORY/runs`` under systemd, else
    ``./wara-data/runs``). ``ring_records``: where a ring cycle's acceptance records
    go (``wara serve``: the acceptance store); None: ``wara ctl cycle`` is refused.
    """
    cfg = load_project(config_path)
    logging_handle = configure_logging(log_level)
    stop = stop_event or threading.Event()
    root = Path(record_root) if record_root else default_record_root()
    slack = SlackGate()
    ctl = ctl_server(
        cfg,
        service_handlers(lambda: core, lambda: ctl, slack=slack, records=ring_records),
        socket_path,
    )
    # The bus and the socket first: a start that fails there writes nothing.
    with contextlib.ExitStack() as undo:
        undo.callback(logging_handle.stop)
        try:
            link = IpcLink.from_config(cfg)
        except BridgeError as exc:
            raise StartupError(str(exc)) from None
        undo.callback(link.close)
        try:
            ctl.bind()
        except CtlError as exc:
            raise StartupError(str(exc)) from None
        undo.callback(ctl.stop)
        run_dir = new_run_dir(root)
        recorder = RunRecorder(
            run_dir,
            ServiceCore.record_columns(cfg),
            meta={"project": cfg.project.name, "period_s": cfg.control.period_s},
        )
        try:
            recorder.start()
        except OSError as exc:
            raise StartupError(
                f"cannot write the run record {run_dir}: {exc.strerror or exc} "
                "(--record-dir, or $STATE_DIRECTORY under systemd)"
            ) from None
        undo.pop_all()
    worker = planner_worker(cfg, config_path)
    worker.start()
    core = ServiceCore(cfg, link, worker, record=recorder)
    notifier = SystemdNotifier.from_env()

    step = watched_step(core.step, notifier, ctl)

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
        step,
        cfg.control.period_s,
        realtime=cfg.control.realtime,
        on_stats=on_stats,
        slack_gate=slack,
    )
    watch = CtlWatch(ctl, core.modes.fault)
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, lambda *_: stop.set())
    ctl.start()
    # The loop thread must get the GIL soon after its deadline, also while the control
    # channel's threads build a status (the OPC UA server asks 20 times a second).
    switch_interval = sys.getswitchinterval()
    sys.setswitchinterval(SWITCH_INTERVAL_S)
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
        if not watch.check():
            log.error("ctl_lost", state=ctl.state(), error=ctl.last_error)
            code = 1
            break
        if deadline is not None and time.monotonic() >= deadline:
            break
    notifier.stopping()
    loop.stop()
    sys.setswitchinterval(switch_interval)
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
