"""The fixed-rate loop: one thread, absolute deadlines, counted overruns, measured jitter.

The shape is ros2_control's: the service's ``step(cycle_index, t_now)`` does
``read -> update -> write``; the loop then advances its deadline by exactly one period
(``next += period``, never ``now + period``, so the rate does not drift). When a step
ends after the next deadline, the loop *skips whole periods*: it does not run late cycles
back to back to catch up, it jumps the deadline to the next period boundary still in the
future, counts the skipped periods and logs it (throttled to one line per
``overrun_log_every_s``). ``cycle_index`` is the period number since start, so a skip
shows as a gap in the index and ``t0 + cycle_index * period`` is always the deadline the
step was scheduled for.

Statistics come from fixed-size ring buffers (``ring_size`` cycles, no growth):

- ``jitter``: wake-up time minus the deadline (how late the step started), ms;
- ``period``: actual time between consecutive wake-ups minus the nominal period, ms
  (absolute value; only pairs without a skip in between);
- ``compute``: time spent in ``step``, ms;
- ``compute_cpu``: the loop thread's own CPU time in ``step`` (user and system, the bus's
  system calls included), ms: ``compute`` less it is time the thread was not running
  (another thread holding the GIL, another process on its CPU, a page fault's wait);

each as p50/p99/max over the window, plus totals ``cycles``, ``overruns`` (events) and
``skipped_periods``. :meth:`FixedRateLoop.stats` returns the dict from any thread;
``on_stats`` receives it from the loop thread every ``stats_every_s`` (keep it cheap:
log it or put it on a queue).

Garbage collector (decision). Before its first cycle the loop calls ``gc.collect()`` then
``gc.freeze()`` (:func:`freeze_startup_heap`; ``freeze_heap=False`` to skip), which moves
every object allocated so far (modules, config, numpy, the planner's imports) to a
permanent generation the collector never scans again, so a collection only walks what
was allocated since. Start the loop after everything else is set up. Then, ``gc_mode``:

- ``"freeze"`` (default): automatic collection stays on. A young-generation pass over the
  few objects a cycle allocates costs tens of microseconds; it is safe when the loop is
  starved (memory cannot grow without bound) and it is what the measured jitter includes.
- ``"slack"``: the collector is disabled *process-wide* (CPython has no per-thread switch)
  and the loop thread collects itself, generation by generation as the allocation counts
  call for it, only when at least half a period of slack remains before the next deadline;
  if the counts reach 10x the thresholds it collects anyway, so a starved loop cannot grow
  memory without bound. Use it when the jitter p99 shows collection spikes.

Real-time settings (:func:`apply_realtime`) are applied from inside the loop thread when
the config asks (``control.realtime``): SCHED_FIFO priority and CPU affinity for that
thread only (Linux applies both per thread), ``mlockall`` for the process, and a PM QoS
request on the CPUs' wake-up latency held until the loop ends (``cpu_wakeup_latency_us``:
a step that starts on a CPU woken from a deep idle state runs on cold caches, measured
at twice its CPU time, decision 0029). Each
setting the system refuses is reported (returned and logged with the errno) and the loop
runs anyway.

Example::

    loop = FixedRateLoop(step, cfg.control.period_s, realtime=cfg.control.realtime,
                         on_stats=lambda s: log.info("loop_stats", **s))
    loop.start()
    ...
    loop.stop()
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import gc
import math
import os
import resource
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Literal, Protocol

import numpy as np
import structlog

from config import units
from config.schema import Realtime
from config.stall import StallTrace

log = structlog.get_logger("wara.service.loop")

StepFn = Callable[[int, float], None]
GcMode = Literal["freeze", "slack"]

MCL_CURRENT = 1
MCL_FUTURE = 2
#: the kernel's PM QoS interface for the CPUs' wake-up latency (pm_qos_interface)
CPU_LATENCY_DEVICE = "/dev/cpu_dma_latency"


# --------------------------------------------------------------------------- real time


class OsApi(Protocol):
    """The system calls :func:`apply_realtime` uses (a fake in tests)."""

    def sched_setscheduler(self, priority: int) -> None: ...
    def sched_setaffinity(self, cpus: tuple[int, ...]) -> None: ...
    def mlockall(self, flags: int) -> None: ...
    def memlock_unlimited(self) -> bool: ...
    def hold_cpu_latency(self, latency_us: int) -> Callable[[], None]: ...


class LinuxOsApi:
    """The real calls, on the calling thread (pid 0)."""

    def sched_setscheduler(self, priority: int) -> None:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))

    def sched_setaffinity(self, cpus: tuple[int, ...]) -> None:
        os.sched_setaffinity(0, cpus)

    def mlockall(self, flags: int) -> None:
        libc = ctypes.CDLL(ctypes.util.find_library("c"), use_errno=True)
        if libc.mlockall(ctypes.c_int(flags)) != 0:
            err = ctypes.get_errno()
            raise OSError(err, os.strerror(err))

    def memlock_unlimited(self) -> bool:
        soft, _ = resource.getrlimit(resource.RLIMIT_MEMLOCK)
        return soft == resource.RLIM_INFINITY

    def hold_cpu_latency(self, latency_us: int) -> Callable[[], None]:
        """A PM QoS request (the kernel's ``cpu_dma_latency`` interface, as cyclictest
        makes it): held while the file stays open; returns its release."""
        fd = os.open(CPU_LATENCY_DEVICE, os.O_WRONLY | os.O_CLOEXEC)
        try:
            os.write(fd, struct.pack("=i", latency_us))
        except OSError:
            os.close(fd)
            raise
        return lambda: os.close(fd)


@dataclass(frozen=True)
class RealtimeReport:
    """What :func:`apply_realtime` did: one line per setting applied or refused."""

    applied: tuple[str, ...] = ()
    refused: tuple[str, ...] = ()
    #: what undoes a setting held while the loop runs (the PM QoS request), in order
    releases: tuple[Callable[[], None], ...] = field(default=(), compare=False, repr=False)

    def release(self) -> None:
        """Undo the settings held while the loop ran (the loop's end)."""
        for undo in self.releases:
            with contextlib.suppress(OSError):
                undo()

    def to_dict(self) -> dict[str, list[str]]:
        return {"applied": list(self.applied), "refused": list(self.refused)}


def _why(exc: OSError) -> str:
    hint = {
        1: "needs CAP_SYS_NICE / LimitRTPRIO (or CAP_IPC_LOCK / LimitMEMLOCK)",
        12: "LimitMEMLOCK too small",
        22: "invalid value for this system",
    }.get(exc.errno or 0, "")
    return f"{exc.strerror or exc}" + (f" ({hint})" if hint else "")


def apply_realtime(rt: Realtime, os_api: OsApi | None = None) -> RealtimeReport:
    """Apply ``control.realtime`` to the calling thread; never raises for a refusal.

    ``priority`` 0 means "leave the scheduler alone", an empty ``cpu_affinity`` "any CPU".
    ``mlockall`` locks current and future pages when RLIMIT_MEMLOCK is unlimited, else the
    current pages only (future allocations beyond a finite limit would fail).
    """
    api = os_api or LinuxOsApi()
    applied: list[str] = []
    refused: list[str] = []
    if rt.cpu_affinity:
        try:
            api.sched_setaffinity(tuple(rt.cpu_affinity))
            applied.append(f"cpu_affinity {list(rt.cpu_affinity)}")
        except OSError as exc:
            refused.append(f"cpu_affinity {list(rt.cpu_affinity)}: {_why(exc)}")
    if rt.priority > 0:
        try:
            api.sched_setscheduler(rt.priority)
            applied.append(f"SCHED_FIFO priority {rt.priority}")
        except OSError as exc:
            refused.append(f"SCHED_FIFO priority {rt.priority}: {_why(exc)}")
    if rt.lock_memory:
        future = api.memlock_unlimited()
        flags = MCL_CURRENT | (MCL_FUTURE if future else 0)
        what = "mlockall(MCL_CURRENT|MCL_FUTURE)" if future else "mlockall(MCL_CURRENT)"
        try:
            api.mlockall(flags)
            applied.append(what)
        except OSError as exc:
            refused.append(f"{what}: {_why(exc)}")
    releases: list[Callable[[], None]] = []
    if rt.cpu_wakeup_latency_us is not None:
        what = f"cpu_wakeup_latency {rt.cpu_wakeup_latency_us} us ({CPU_LATENCY_DEVICE})"
        try:
            releases.append(api.hold_cpu_latency(rt.cpu_wakeup_latency_us))
            applied.append(what)
        except OSError as exc:
            refused.append(f"{what}: {_why(exc)}")
    report = RealtimeReport(tuple(applied), tuple(refused), tuple(releases))
    if applied:
        log.info("realtime_applied", settings=list(applied))
    for line in refused:
        log.warning("realtime_refused", setting=line)
    return report


def freeze_startup_heap() -> int:
    """Collect once and ``gc.freeze()`` everything allocated so far; returns the count."""
    gc.collect()
    gc.freeze()
    return gc.get_freeze_count()


# --------------------------------------------------------------------------- statistics


class _Ring:
    """Fixed-size float ring; ``values()`` is the filled part (a copy)."""

    def __init__(self, size: int) -> None:
        self._buf = np.zeros(size)
        self._n = 0

    def add(self, x: float) -> None:
        self._buf[self._n % self._buf.size] = x
        self._n += 1

    def values(self) -> np.ndarray:
        return self._buf[: min(self._n, self._buf.size)].copy()


def _pct(ring: _Ring, name: str) -> dict[str, float]:
    v = ring.values()
    if v.size == 0:
        return {f"{name}_p50_ms": 0.0, f"{name}_p99_ms": 0.0, f"{name}_max_ms": 0.0}
    p50, p99 = np.percentile(v, [50, 99])
    return {
        f"{name}_p50_ms": units.to_ms(float(p50)),
        f"{name}_p99_ms": units.to_ms(float(p99)),
        f"{name}_max_ms": units.to_ms(float(v.max())),
    }


@dataclass
class _Counters:
    cycles: int = 0
    overruns: int = 0
    skipped_periods: int = 0
    gc_collections: int = 0
    overruns_since_log: int = 0
    skipped_since_log: int = 0
    last_overrun_log: float = -math.inf
    worst_overrun_s: float = 0.0


# --------------------------------------------------------------------------- the loop


#: The interpreter's thread switch interval while a real-time loop runs (default 5 ms,
#: the whole period): the loop thread waiting for the GIL gets it within this. Set by
#: the service (``run_service``) and the real-time harness.
SWITCH_INTERVAL_S = 0.0005


class _Waiters:
    """Threads waiting for a condition the loop thread changes: the loop's side is a
    check of a count and a notify only while some thread waits (no lock otherwise)."""

    def __init__(self) -> None:
        self._cv = threading.Condition()
        self._waiting = 0

    def notify(self) -> None:
        if self._waiting:
            with self._cv:
                self._cv.notify_all()

    def wait_for(self, predicate: Callable[[], bool], timeout_s: float) -> bool:
        with self._cv:
            self._waiting += 1
            try:
                return self._cv.wait_for(predicate, timeout_s)
            finally:
                self._waiting -= 1


class SlackGate:
    """Lets another thread of the loop's process do its work in the loop's slack.

    The loop's compute holds the GIL; a thread that builds a status at the same moment
    takes it from the loop in ``SWITCH_INTERVAL_S`` slices and so lengthens that cycle
    (the OPC UA server asks for a status 20 times a second). A thread that calls
    :meth:`wait` while a step runs is woken by the loop right after that step has ended
    (:meth:`cycle_done`), with the rest of the period before the next deadline; between
    steps it goes on at once.

    The loop's side is bounded: three attribute writes per cycle, and a notify only while a
    thread waits. :meth:`wait` returns at once while no loop runs (:attr:`active`), and
    after ``timeout_s`` in any case, so a late or stopped loop never blocks the caller
    for long.
    """

    def __init__(self) -> None:
        self._waiters = _Waiters()
        self._cycles = 0
        #: set by the loop while it runs
        self.active = False
        #: set by the loop from the start of a step until :meth:`cycle_done`
        self.in_step = False

    def step_started(self) -> None:
        """The loop thread: a step begins."""
        self.in_step = True

    def cycle_done(self) -> None:
        """The loop thread: the step and its bookkeeping have ended (wakes the threads
        waiting, if any)."""
        self.in_step = False
        self._cycles += 1
        self._waiters.notify()

    def wait(self, timeout_s: float) -> bool:
        """Return once no step runs: at once between steps, else when the running one
        has ended. False when it did not end within ``timeout_s`` (or no loop runs)."""
        start = self._cycles
        if not self.active:
            return False
        if not self.in_step:
            return True
        return self._waiters.wait_for(lambda: self._cycles != start, timeout_s)


class ChangeGate:
    """Lets another thread wait for the next change of the service's state (its mode, so
    its PackML state) instead of asking again and again: the OPC UA server's status
    request then returns at the change, not at its next period.

    The loop's side is bounded: :meth:`changed` increments :attr:`seq` and notifies only
    while a thread waits (the loop calls it in the cycle whose step changed the mode).
    """

    def __init__(self) -> None:
        self._waiters = _Waiters()
        #: how many changes so far (a status carries it as ``state_seq``)
        self.seq = 0

    def changed(self) -> None:
        """The loop thread: the state changed in this cycle."""
        self.seq += 1
        self._waiters.notify()

    def wait(self, after: int, timeout_s: float) -> bool:
        """Return once :attr:`seq` differs from ``after`` (at once if it does already);
        False when it did not change within ``timeout_s``."""
        if self.seq != after:
            return True
        return self._waiters.wait_for(lambda: self.seq != after, timeout_s)


class FixedRateLoop:
    """Run ``step(cycle_index, t_now)`` every ``period_s`` on absolute deadlines.

    ``clock`` (monotonic seconds) and ``sleep(seconds)`` are injectable; by default the
    sleep is an :class:`threading.Event` wait so :meth:`stop` wakes the loop at once.
    A step that raises stops the loop; the exception is kept in :attr:`error` and logged
    (the service turns that into a fault and a controlled stop).
    """

    def __init__(
        self,
        step: StepFn,
        period_s: float,
        *,
        clock: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], object] | None = None,
        realtime: Realtime | None = None,
        os_api: OsApi | None = None,
        on_stats: Callable[[dict[str, Any]], None] | None = None,
        stats_every_s: float = 5.0,
        overrun_log_every_s: float = 5.0,
        ring_size: int = 4096,
        gc_mode: GcMode = "freeze",
        freeze_heap: bool = True,
        name: str = "wara-loop",
        slack_gate: SlackGate | None = None,
    ) -> None:
        if not (period_s > 0 and math.isfinite(period_s)):
            raise ValueError(f"period_s must be a positive number of seconds, got {period_s}")
        if gc_mode not in ("freeze", "slack"):
            raise ValueError(f"gc_mode must be 'freeze' or 'slack', got {gc_mode!r}")
        self._step = step
        self.period_s = float(period_s)
        self._clock = clock
        self._stop = threading.Event()
        self._sleep: Callable[[float], object] = sleep or self._stop.wait
        self._realtime = realtime
        self._os_api = os_api
        self._on_stats = on_stats
        self._stats_every_s = stats_every_s
        self._overrun_log_every_s = overrun_log_every_s
        self._gc_mode: GcMode = gc_mode
        self._freeze_heap = freeze_heap
        self._name = name
        self._slack_gate = slack_gate
        self._jitter = _Ring(ring_size)
        self._period_dev = _Ring(ring_size)
        self._compute = _Ring(ring_size)
        self._compute_cpu = _Ring(ring_size)
        self._c = _Counters()
        self._thread: threading.Thread | None = None
        self.realtime_report = RealtimeReport()
        self.error: BaseException | None = None

    # ------------------------------------------------------------------ control
    def start(self) -> None:
        """Run the loop in a new thread (the only thread the RT settings touch)."""
        if self._thread is not None:
            raise RuntimeError("loop already started")
        self._thread = threading.Thread(target=self.run, name=self._name, daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> bool:
        """Ask the loop to stop after the current step; True when it has stopped."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout_s)
            return not self._thread.is_alive()
        return True

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def run(self) -> None:
        """The loop itself, in the calling thread, until :meth:`stop` (or a step raises)."""
        if self._realtime is not None:
            self.realtime_report = apply_realtime(self._realtime, self._os_api)
        if self._freeze_heap:
            freeze_startup_heap()
        # WARA_STALL_TRACE_MS: the stacks of a cycle that stalls (config.stall)
        self._stall = StallTrace()
        gc_was_enabled = gc.isenabled()
        if self._gc_mode == "slack":
            gc.disable()
        log.info(
            "loop_start",
            period_ms=units.to_ms(self.period_s),
            gc_mode=self._gc_mode,
            gc_frozen=gc.get_freeze_count(),
        )
        gate = self._slack_gate
        if gate is not None:
            gate.active = True
        try:
            self._run()
        except BaseException as exc:  # the service decides; the loop only reports
            self.error = exc
            log.exception("loop_step_failed", error=repr(exc))
        finally:
            if gate is not None:
                gate.active = False
            self.realtime_report.release()
            self._stall.close()
            if self._gc_mode == "slack" and gc_was_enabled:
                gc.enable()
            log.info("loop_stop", **self.stats())

    def _run(self) -> None:
        clock, period, stop = self._clock, self.period_s, self._stop
        deadline = clock()
        index = 0
        prev_wake: float | None = None
        next_stats = deadline + self._stats_every_s
        c = self._c
        stall = self._stall
        gate = self._slack_gate
        while not stop.is_set():
            now = clock()
            if now < deadline:
                self._sleep(deadline - now)
                if stop.is_set():
                    break
                now = clock()
            wake = now
            self._jitter.add(max(wake - deadline, 0.0))
            if prev_wake is not None:
                self._period_dev.add(abs(wake - prev_wake - period))
            prev_wake = wake
            stall.arm()
            if gate is not None:
                gate.step_started()
            cpu = time.thread_time()
            self._step(index, wake)
            end = clock()
            self._compute_cpu.add(time.thread_time() - cpu)
            self._compute.add(end - wake)
            c.cycles += 1
            deadline += period
            index += 1
            if end > deadline:
                missed = int((end - deadline) // period) + 1
                self._overrun(end, end - (deadline - period), missed)
                deadline += missed * period
                index += missed
                prev_wake = None
            if self._gc_mode == "slack":
                self._collect_in_slack(deadline - clock())
            if end >= next_stats:
                next_stats = end + self._stats_every_s
                if self._on_stats is not None:
                    self._on_stats(self.stats())
            if gate is not None:
                gate.cycle_done()

    def _overrun(self, now: float, took_s: float, missed: int) -> None:
        c = self._c
        c.overruns += 1
        c.skipped_periods += missed
        c.overruns_since_log += 1
        c.skipped_since_log += missed
        c.worst_overrun_s = max(c.worst_overrun_s, took_s)
        if now - c.last_overrun_log >= self._overrun_log_every_s:
            log.warning(
                "loop_overrun",
                overruns=c.overruns_since_log,
                skipped_periods=c.skipped_since_log,
                last_cycle_ms=round(units.to_ms(took_s), 3),
                period_ms=units.to_ms(self.period_s),
                throttle_s=self._overrun_log_every_s,
            )
            c.last_overrun_log = now
            c.overruns_since_log = c.skipped_since_log = 0

    def _collect_in_slack(self, slack_s: float) -> None:
        counts = gc.get_count()
        thresholds = gc.get_threshold()
        gen = -1
        for g in (2, 1, 0):
            if thresholds[g] and counts[g] >= thresholds[g]:
                gen = g
                break
        if gen < 0:
            return
        forced = counts[gen] >= 10 * thresholds[gen]
        if slack_s >= self.period_s / 2 or forced:
            gc.collect(gen)
            self._c.gc_collections += 1

    # ------------------------------------------------------------------ statistics
    def stats(self) -> dict[str, Any]:
        """Counters and p50/p99/max of jitter, period deviation and compute time, ms."""
        c = self._c
        out: dict[str, Any] = {
            "period_ms": units.to_ms(self.period_s),
            "cycles": c.cycles,
            "overruns": c.overruns,
            "skipped_periods": c.skipped_periods,
            "worst_overrun_cycle_ms": units.to_ms(c.worst_overrun_s),
            "window_cycles": int(self._compute.values().size),
        }
        out.update(_pct(self._jitter, "jitter"))
        out.update(_pct(self._period_dev, "period_dev"))
        out.update(_pct(self._compute, "compute"))
        out.update(_pct(self._compute_cpu, "compute_cpu"))
        out["compute_p99_fraction"] = out["compute_p99_ms"] / out["period_ms"]
        if self._gc_mode == "slack":
            out["gc_collections"] = c.gc_collections
        if self.realtime_report.refused:
            out["realtime_refused"] = list(self.realtime_report.refused)
        return out
