"""Planning in a worker process, behind two non-blocking calls for the loop thread.

The planner's solve takes milliseconds, but the trajectory, the first imports and the
garbage it leaves make its time unbounded: it must never run in the control loop, nor in
the loop's process where it would hold the GIL. :class:`PlannerWorker` keeps one planner
process alive (``forkserver`` context: the fork server preloads the planner once, so a
restart after a crash takes milliseconds instead of a fresh interpreter's second).

The loop thread calls only:

- :meth:`PlannerWorker.submit` - stores the request and wakes the supervisor through a
  pipe (one ``os.write``); ``False`` while another request is pending;
- :meth:`PlannerWorker.poll` - takes a finished :class:`PlanResult` off an in-process
  queue, or ``None``.

The service's other threads (the control channel's, the ring cycle's; never the loop)
call :meth:`PlannerWorker.call`: the walk's and the placement's planning
(``"module:function"`` with picklable arguments, run as ``fn(cfg, *args, **kwargs)`` in
the same process), blocking the caller until the value comes back; one such call at a
time, beside the loop's request.

A supervisor thread of this process does everything that may block: starting the process,
sending the request, unpickling the result, the per-request timeout (the process is killed
and restarted), and crash detection (the process sentinel; restarted with a back-off).
Every failure becomes a :class:`PlanResult` with ``error`` set (``ok`` is False) - for the
service, a planner failure is an interlock (``ModeMachine.fault``), an infeasible target
(``ok`` and not ``feasible``) is a refused request (``ModeMachine.plan_failed``).

The result carries the planner's :class:`~ipc_app.planner.trajectory.Trajectory` (a
frozen dataclass of floats, two ``LayerPath`` and the check samples; it pickles as is):
the loop follows it with ``result.reference(t)`` which returns the eight cylinder
positions and velocities at ``t`` seconds since the motion started (about 0.2 ms).

Example::

    worker = PlannerWorker(config_path)      # validates the config here (ConfigError)
    worker.start()
    worker.submit(7, roll_deg=-3, pitch_deg=2, start_upper_m=du, start_lower_m=dl)
    ...                                      # every cycle:
    result = worker.poll()
    if result is not None and result.request_id == 7:
        if not result.ok: modes.fault(Cause(Interlock.PLANNER, detail=result.error))
        elif not result.feasible: modes.plan_failed(result.reasons)
        else: modes.plan_ready()
"""

from __future__ import annotations

import contextlib
import importlib
import itertools
import multiprocessing as mp
import multiprocessing.connection as mpc
import os
import queue
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TypeVar

import numpy as np
import structlog

from config import default_project_path, load_project
from config.loader import load_model
from config.schema import ProjectConfig
from ipc_app.planner.plan import Plan
from ipc_app.planner.trajectory import Trajectory

log = structlog.get_logger("wara.service.worker")

Four = tuple[float, float, float, float]
T = TypeVar("T")
StartMethod = Literal["forkserver", "spawn"]
#: The planner function run in the worker: "module:function", called ``fn(cfg, request)``
#: and returning a :class:`~ipc_app.planner.plan.Plan` (tests point it at fakes).
DEFAULT_PLAN_FN = "ipc_app.service.worker:run_planner"
#: What the service's threads have the planner process run (:meth:`PlannerWorker.call`):
#: the walk, the placement target (from a deviation, or from the previous part's pose)
#: and the placement's attitude trajectory. Planning is never the loop's work, nor that
#: of any thread of the loop's process.
PLAN_WALK_FN = "ipc_app.planner.walk:plan_walk"
PLAN_PLACE_FN = "ipc_app.planner.placement:plan_from_deviation"
PLAN_TARGET_FN = "ipc_app.planner.placement:plan_target"
PLAN_ATTITUDE_FN = "ipc_app.planner.plan:plan"


@dataclass(frozen=True)
class PlanRequest:
    request_id: int
    roll_deg: float
    pitch_deg: float
    start_upper_m: Four = (0.0, 0.0, 0.0, 0.0)
    start_lower_m: Four = (0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class PlanResult:
    """One answer. ``error`` None: the planner ran (``feasible`` and ``reasons`` are its)."""

    request_id: int
    feasible: bool
    reasons: tuple[str, ...]
    error: str | None
    plan: dict[str, Any] | None
    trajectory: Trajectory | None
    elapsed_s: float

    @property
    def ok(self) -> bool:
        return self.error is None

    @property
    def duration_s(self) -> float:
        return self.trajectory.duration_s if self.trajectory is not None else 0.0

    def reference(self, t_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(d_lower, d_upper, v_lower, v_upper)`` at ``t_s`` since the motion started."""
        if self.trajectory is None:
            raise ValueError(f"plan request {self.request_id} has no trajectory to follow")
        return self.trajectory.reference(t_s)

    @classmethod
    def failure(cls, request_id: int, error: str, elapsed_s: float) -> PlanResult:
        return cls(request_id, False, (error,), error, None, None, elapsed_s)


@dataclass(frozen=True)
class JobRequest:
    """A call of ``fn`` (``"module:function"``) as ``fn(cfg, *args, **kwargs)`` in the
    planner process (:meth:`PlannerWorker.call`)."""

    request_id: int
    fn: str
    args: tuple[Any, ...]
    kwargs: dict[str, Any]


@dataclass(frozen=True)
class JobResult:
    request_id: int
    value: Any
    error: str | None
    elapsed_s: float
    #: the exception's class name when the function raised (``ValueError``: a request
    #: the function refuses), else None
    raised: str | None = None


class PlannerCallError(RuntimeError):
    """:meth:`PlannerWorker.call` did not return a value: the function raised in the
    planner process (:attr:`raised`: its exception's class name), the call timed out (the
    process was restarted) or the worker stopped; the message says which."""

    def __init__(self, message: str, raised: str | None = None) -> None:
        super().__init__(message)
        self.raised = raised


def run_planner(cfg: ProjectConfig, req: PlanRequest) -> Plan:
    """The production planner call (in the worker process)."""
    from ipc_app.planner import plan

    return plan(
        cfg,
        req.roll_deg,
        req.pitch_deg,
        start_upper_m=req.start_upper_m,
        start_lower_m=req.start_lower_m,
    )


def _resolve(dotted: str) -> Callable[[ProjectConfig, PlanRequest], Plan]:
    module, _, name = dotted.partition(":")
    fn: Callable[[ProjectConfig, PlanRequest], Plan] = getattr(
        importlib.import_module(module), name
    )
    return fn


#: how often an idle planner process checks that the service is still there
PARENT_CHECK_S = 1.0


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # there, another user's
        return True
    return True


def _child_main(
    config_path: str | None, plan_fn: str, requests: Any, results: Any, owner_pid: int
) -> None:
    """The worker process: load the config once, then plan requests until ``None``.

    SIGINT is ignored: a Ctrl-C in the terminal reaches the whole process group, and the
    service, not this process, decides when it ends (``None``, or its owner gone)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        # the schema only: the service checked this file whole (the cross-checks too,
        # PlannerWorker) before starting this process, whose start they would slow by
        # their imports (the DBC's bus load, the statics; about 1 s of CPU)
        path = default_project_path() if config_path is None else config_path
        cfg = load_model(ProjectConfig, path)
        fn = _resolve(plan_fn)
    except Exception as exc:
        results.put(("fatal", f"{type(exc).__name__}: {exc}"))
        return
    results.put(("ready", os.getpid()))
    while True:
        try:
            req: PlanRequest | JobRequest | None = requests.get(timeout=PARENT_CHECK_S)
        except queue.Empty:
            if not _alive(owner_pid):  # the service was killed (its forkserver lives on
                return  # as long as this process holds its "alive" pipe)
            continue
        if req is None:
            return
        t0 = time.perf_counter()
        if isinstance(req, JobRequest):
            results.put(("job", _run_job(cfg, req, t0)))
            continue
        try:
            p = fn(cfg, req)
            result = PlanResult(
                req.request_id,
                p.feasible,
                tuple(p.reasons),
                None,
                p.to_dict(),
                p.trajectory,
                time.perf_counter() - t0,
            )
        except Exception as exc:
            msg = f"planner raised {type(exc).__name__}: {exc}"
            result = PlanResult.failure(req.request_id, msg, time.perf_counter() - t0)
        results.put(("result", result))


class PlannerWorker:
    """One planner process, supervised; see the module docstring.

    ``timeout_s`` bounds each request from :meth:`submit` to its result (including a
    worker that is still starting); on expiry the process is killed and restarted and
    the result says ``timeout``.
    """

    def __init__(
        self,
        config_path: str | Path | None = None,
        *,
        timeout_s: float = 10.0,
        start_method: StartMethod = "forkserver",
        plan_fn: str = DEFAULT_PLAN_FN,
        max_backoff_s: float = 5.0,
    ) -> None:
        load_project(config_path)  # fail here, in the caller, with a ConfigError
        self._config_path = None if config_path is None else str(config_path)
        self.timeout_s = timeout_s
        self._ctx: Any = mp.get_context(start_method)  # typeshed lacks Process on it
        if start_method == "forkserver":
            self._ctx.set_forkserver_preload(["ipc_app.planner", "ipc_app.service.worker"])
        self._plan_fn = plan_fn
        self._max_backoff_s = max_backoff_s
        self._lock = threading.Lock()
        self._pending: PlanRequest | None = None  # submitted, no result yet
        self._pending_since = 0.0
        self._sent = False  # pending request handed to the current process
        self._out: queue.SimpleQueue[PlanResult] = queue.SimpleQueue()
        # the one call in flight (call()): its request, since when, handed over, answer
        self._call_lock = threading.Lock()  # one caller at a time
        self._job: JobRequest | None = None
        self._job_since = 0.0
        self._job_sent = False
        self._job_done = threading.Event()
        self._job_result: JobResult | None = None
        self._job_ids = itertools.count(1)
        self._wake_r, self._wake_w = os.pipe()
        os.set_blocking(self._wake_w, False)
        self._closing = threading.Event()
        self._thread: threading.Thread | None = None
        self._ready = False
        self.restarts = 0
        self.pid: int | None = None

    # ------------------------------------------------------------------ loop side
    def submit(
        self,
        request_id: int,
        roll_deg: float,
        pitch_deg: float,
        start_upper_m: Sequence[float] = (0.0, 0.0, 0.0, 0.0),
        start_lower_m: Sequence[float] = (0.0, 0.0, 0.0, 0.0),
    ) -> bool:
        """Queue one request without blocking; False if a request is still pending."""
        req = PlanRequest(
            request_id,
            float(roll_deg),
            float(pitch_deg),
            _four(start_upper_m),
            _four(start_lower_m),
        )
        with self._lock:
            if self._pending is not None:
                return False
            self._pending, self._pending_since, self._sent = req, time.monotonic(), False
        self._wake()
        return True

    def poll(self) -> PlanResult | None:
        """The next finished result, or None; never blocks."""
        if self._out.empty():  # the usual case, every loop cycle: no exception raised
            return None
        try:
            return self._out.get_nowait()
        except queue.Empty:
            return None

    def call(self, fn: str, *args: Any, **kwargs: Any) -> Any:
        """``fn(cfg, *args, **kwargs)`` in the planner process, ``fn`` as
        ``"module:function"``; blocks the calling thread (never the loop's) until its
        value comes back, at most :attr:`timeout_s` once handed over (then the process is
        restarted). Callers queue one behind the other. :class:`PlannerCallError` when no
        value comes back (why: the function's exception, the timeout, a stopped worker)."""
        with self._call_lock:
            if self._thread is None or self._closing.is_set():
                raise PlannerCallError(f"{fn}: the planner worker is not running")
            job = JobRequest(next(self._job_ids), fn, args, kwargs)
            self._job_done.clear()
            with self._lock:
                self._job, self._job_since, self._job_sent = job, time.monotonic(), False
                self._job_result = None
            self._wake()
            self._job_done.wait()
            res = self._job_result
        assert res is not None
        if res.error is not None:
            raise PlannerCallError(res.error, res.raised)
        log.info("planner_call", fn=fn, elapsed_s=round(res.elapsed_s, 4))
        return res.value

    def _finish_job(self, res: JobResult) -> None:
        with self._lock:
            if self._job is None or self._job.request_id != res.request_id:
                log.warning("planner_stale_call_result", request_id=res.request_id)
                return
            self._job, self._job_result = None, res
        self._job_done.set()

    def _fail_job(self, error: str) -> None:
        job = self._job
        if job is not None:
            self._finish_job(JobResult(job.request_id, None, f"{job.fn}: {error}", 0.0))

    @property
    def busy(self) -> bool:
        return self._pending is not None

    @property
    def calling(self) -> bool:
        """A :meth:`call` is in flight (asked, its value not yet back)."""
        return self._job is not None

    @property
    def ready(self) -> bool:
        """A planner process is up, its config loaded, waiting for requests."""
        return self._ready

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        if self._thread is not None:
            raise RuntimeError("planner worker already started")
        self._thread = threading.Thread(target=self._supervise, name="wara-planner", daemon=True)
        self._thread.start()

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop the process and the supervisor; a pending request gets an error result."""
        self._closing.set()
        self._wake()
        if self._thread is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.error("planner_supervisor_stuck", timeout_s=timeout_s)
                return
        for fd in (self._wake_r, self._wake_w):
            with contextlib.suppress(OSError):
                os.close(fd)

    def __enter__(self) -> PlannerWorker:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ------------------------------------------------------------------ supervisor
    def _wake(self) -> None:
        # BlockingIOError: a wake-up is already pending; OSError: closed
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def _finish(self, result: PlanResult) -> None:
        with self._lock:
            if self._pending is None or self._pending.request_id != result.request_id:
                log.warning("planner_stale_result", request_id=result.request_id)
                return
            # in the queue before the worker stops being busy: a lockstep harness that
            # waits for ``busy`` to end then finds the result in its next cycle's poll
            # (put after, the loop could run a cycle between the two under load)
            self._out.put(result)
            self._pending = None
        log.info(
            "plan_result",
            request_id=result.request_id,
            ok=result.ok,
            feasible=result.feasible,
            error=result.error,
            elapsed_s=round(result.elapsed_s, 4),
        )

    def _fail_pending(self, error: str) -> None:
        req = self._pending
        if req is not None:
            elapsed = time.monotonic() - self._pending_since
            self._finish(PlanResult.failure(req.request_id, error, elapsed))

    def _supervise(self) -> None:
        backoff = 0.0
        while not self._closing.is_set():
            if backoff:
                self._closing.wait(backoff)
                if self._closing.is_set():
                    break
            requests, results, proc = under_normal_scheduler(self._new_process)
            self.pid = proc.pid
            with self._lock:
                self._sent = self._job_sent = False
            outcome = self._serve(proc, requests, results)
            self._ready = False
            if proc.is_alive():
                proc.kill()
            proc.join(1.0)
            requests.close()
            results.close()
            if outcome == "closing":
                break
            self.restarts += 1
            healthy = outcome in ("timeout", "died_after_ready")
            backoff = 0.0 if healthy else min(max(backoff * 2, 0.1), self._max_backoff_s)
            log.warning(
                "planner_restart", reason=outcome, exitcode=proc.exitcode, backoff_s=backoff
            )
        self._fail_pending("planner worker stopped")
        self._fail_job("planner worker stopped")

    def _new_process(self) -> tuple[Any, Any, Any]:
        """The two queues and a started planner process."""
        requests, results = self._ctx.Queue(), self._ctx.Queue()
        proc = self._ctx.Process(
            target=_child_main,
            args=(self._config_path, self._plan_fn, requests, results, os.getpid()),
            name="wara-planner-worker",
            daemon=True,
        )
        proc.start()
        return requests, results, proc

    def _serve(self, proc: Any, requests: Any, results: Any) -> str:
        """Run one process generation; returns why it ended."""
        was_ready = False
        while True:
            if self._closing.is_set():
                try:
                    requests.put(None)
                    proc.join(2.0)
                except (OSError, ValueError):
                    pass
                return "closing"
            with self._lock:
                req, since, sent = self._pending, self._pending_since, self._sent
                job, job_since, job_sent = self._job, self._job_since, self._job_sent
            now = time.monotonic()
            if req is not None and now - since > self.timeout_s:
                self._fail_pending(
                    f"planner timeout: no result after {self.timeout_s:g} s "
                    f"(request {req.request_id}); worker restarted"
                )
                self._fail_job("the planner process was restarted (another request timed out)")
                return "timeout"
            if job is not None and now - job_since > self.timeout_s:
                self._fail_job(f"planner timeout: no value after {self.timeout_s:g} s")
                self._fail_pending("the planner process was restarted (a call timed out)")
                return "timeout"
            if req is not None and not sent and was_ready:
                requests.put(req)
                with self._lock:
                    self._sent = True
            if job is not None and not job_sent and was_ready:
                requests.put(job)
                with self._lock:
                    self._job_sent = True
            due = [t + self.timeout_s for t, r in ((since, req), (job_since, job)) if r]
            wait = max(0.0, min([0.5, *(d - now for d in due)]))
            ready = mpc.wait([results._reader, proc.sentinel, self._wake_r], timeout=wait)
            if self._wake_r in ready:
                os.read(self._wake_r, 4096)
            while True:
                try:
                    kind, payload = results.get_nowait()
                except queue.Empty:
                    break
                except (EOFError, OSError):
                    break
                if kind == "ready":
                    was_ready = self._ready = True
                    log.info("planner_ready", pid=payload)
                elif kind == "fatal":
                    log.error("planner_worker_fatal", error=payload)
                    self._fail_pending(f"planner worker could not start: {payload}")
                    self._fail_job(f"planner worker could not start: {payload}")
                elif kind == "result":
                    self._finish(payload)
                elif kind == "job":
                    self._finish_job(payload)
            if proc.sentinel in ready or not proc.is_alive():
                code = proc.exitcode
                if self._pending is not None and self._sent:
                    self._fail_pending(
                        f"planner worker died (exit code {code}) while planning request "
                        f"{self._pending.request_id}; restarted"
                    )
                if self._job is not None and self._job_sent:
                    self._fail_job(f"the planner process died (exit code {code}); restarted")
                return "died_after_ready" if was_ready else "died_at_start"


def _run_job(cfg: ProjectConfig, job: JobRequest, t0: float) -> JobResult:
    """One :class:`JobRequest` in the planner process; an exception becomes ``error``."""
    try:
        module, _, name = job.fn.partition(":")
        fn = getattr(importlib.import_module(module), name)
        value = fn(cfg, *job.args, **job.kwargs)
        return JobResult(job.request_id, value, None, time.perf_counter() - t0)
    except Exception as exc:
        msg = f"{job.fn} raised {type(exc).__name__}: {exc}"
        return JobResult(job.request_id, None, msg, time.perf_counter() - t0, type(exc).__name__)


def under_normal_scheduler(fn: Callable[[], T]) -> T:
    """``fn()`` in a short-lived thread that has ``SCHED_RESET_ON_FORK``, for starting
    the planner: every process started from there (the queues' resource tracker, the
    fork server, and through the fork server every planner process) begins under the
    normal scheduler, whatever real-time policy the service's threads have. A planner
    process that inherited SCHED_FIFO would keep a CPU from the control loop for as long
    as it computes (docs/service.md, "Start-up"). The calling thread keeps its policy,
    and so do the threads it starts later (the request queue's feeder)."""
    out: list[T] = []
    failed: list[BaseException] = []

    def run() -> None:
        children_start_normal()
        try:
            out.append(fn())
        except BaseException as exc:  # re-raised in the caller
            failed.append(exc)

    t = threading.Thread(target=run, name="wara-planner-start", daemon=True)
    t.start()
    t.join()
    if failed:
        raise failed[0]
    return out[0]


def children_start_normal() -> bool:
    """Set ``SCHED_RESET_ON_FORK`` on the calling thread, keeping its own policy: the
    processes and threads it starts begin under the normal scheduler. False where the
    system has no such flag or refuses it (logged)."""
    flag = getattr(os, "SCHED_RESET_ON_FORK", 0)
    if not flag:
        return False
    try:
        policy = os.sched_getscheduler(0)
        if not policy & flag:
            os.sched_setscheduler(0, policy | flag, os.sched_getparam(0))
    except OSError as exc:
        log.warning("planner_reset_on_fork_refused", error=exc.strerror or str(exc))
        return False
    return True


def _four(values: Sequence[float]) -> Four:
    v = [float(x) for x in values]
    if len(v) != 4:
        raise ValueError(f"expected four extensions (m), got {len(v)}: {v}")
    return (v[0], v[1], v[2], v[3])
