"""The harness of the end-to-end runs: the HIL simulator and the IPC service on one
in-process CAN bus (python-can's ``virtual`` in real time, a
:func:`~plc_bridge.lockstep_bus.lockstep_pair` in lockstep), driven from Python.

:class:`Harness` is what ``wara demo`` (one process), the end-to-end tests, the studies
(``wara sim delay-margin``) and ``wara bench step`` run on. A target goes to the service
as ``wara ctl adjust`` would send it, the planner worker plans it, the service's step
drives the simulated rig over the DBC, and the figures are read from the service (what
the operator sees) and from the simulator's truth.

Two timings:
- ``realtime``: the service's :class:`FixedRateLoop` runs in its own thread on the wall
  clock (jitter and overruns are real), the simulator in another thread, paced by the
  wall clock;
- ``lockstep``: simulator and service alternate in one thread on simulated time (fast;
  for tests and studies). Simulated time stands still while the planner process works
  (bounded by the worker's own timeout), so a plan arrives in the cycle after it was
  asked for, however busy the machine is: a run does not depend on the wall clock.
"""

from __future__ import annotations

import itertools
import os
import sys
import threading
import time
from collections.abc import Callable
from typing import Any

import can
import numpy as np

from config import units
from config.hil_scenario import HilScenario
from config.schema import ProjectConfig, Realtime
from hil_sim.placement import pose_from_home
from hil_sim.simulator import HilSimulator
from ipc_app.model.placement import Pose, compose
from ipc_app.planner.placement import home_pose
from ipc_app.service.core import ServiceCore
from ipc_app.service.loop import (
    SWITCH_INTERVAL_S,
    FixedRateLoop,
    OsApi,
    RealtimeReport,
    SlackGate,
    freeze_startup_heap,
)
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from ipc_app.service.worker import PlannerWorker
from plc_bridge.link import IpcLink
from plc_bridge.lockstep_bus import lockstep_pair
from wara.examples import HOLD_MEASURE_S, ExampleResult, judge_example

#: SCHED_FIFO priority of the real-time harness's threads (loop, simulator and the
#: others), when the system grants it: a busy machine's other processes then wait for
#: them, not they for those (docs/service.md, "The one-process demo's timing").
RT_PRIORITY = 10


_channels = itertools.count()


_DEG = units.to_deg(1.0)
_MM = units.to_mm(1.0)
_MPA = units.to_mpa(1.0)


class _Series:
    """A :class:`Trace` attribute: the samples so far of the series of its name."""

    def __set_name__(self, owner: type, name: str) -> None:
        self.key = name

    def __get__(self, trace: Trace, owner: type | None = None) -> np.ndarray:
        return trace._series(self.key)


class Trace:
    """Time series for the plots (one sample per control period), in preallocated
    NumPy blocks: a sample is copied into arrays, never kept as Python lists, so a long
    run leaves no growing heap of containers for the garbage collector to walk (in the
    one-process real-time demo a full collection stops every thread; docs/service.md).

    ``t``, ``roll_deg``, ``pitch_deg`` (n,), ``x_mm`` and ``p_mpa`` (n, 8), ``sync_mm``
    (n, 2): the samples so far, as arrays.
    """

    BLOCK = 4096

    def __init__(self, active: list[int], n_groups: int = 2) -> None:
        self._active = np.asarray(active, dtype=np.intp)
        n_cyl = len(active)
        self._widths = {
            "t": 0,
            "roll_deg": 0,
            "pitch_deg": 0,
            "x_mm": n_cyl,
            "sync_mm": n_groups,
            "p_mpa": n_cyl,
        }
        self._blocks: list[dict[str, np.ndarray]] = []
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def _block(self) -> dict[str, np.ndarray]:
        i = self._n % self.BLOCK
        if i == 0 and self._n // self.BLOCK == len(self._blocks):
            self._blocks.append(
                {k: np.empty((self.BLOCK, w) if w else self.BLOCK) for k, w in self._widths.items()}
            )
        return self._blocks[self._n // self.BLOCK]

    def add(self, sim: HilSimulator, core: ServiceCore) -> None:
        rig = sim.rig
        b = self._block()
        i = self._n % self.BLOCK
        roll, pitch = rig.workpiece_attitude_rad()
        b["t"][i] = sim.t_s
        b["roll_deg"][i] = roll * _DEG
        b["pitch_deg"][i] = pitch * _DEG
        active = self._active
        b["x_mm"][i] = rig.rod_positions_m[active] * _MM
        b["p_mpa"][i] = rig.pressures_pa[active, 0] * _MPA
        for j, m in enumerate(core.attitude.metrics.values()):
            b["sync_mm"][i, j] = m.sync_error_m * _MM
        self._n += 1

    def _series(self, key: str) -> np.ndarray:
        if not self._blocks:
            w = self._widths[key]
            return np.empty((0, w) if w else 0)
        return np.concatenate([blk[key] for blk in self._blocks])[: self._n]

    t = _Series()
    roll_deg = _Series()
    pitch_deg = _Series()
    x_mm = _Series()
    sync_mm = _Series()
    p_mpa = _Series()


class Harness:
    """Simulator + service on one virtual bus; see the module docstring."""

    def __init__(
        self,
        cfg: ProjectConfig,
        config_path: str | None = None,
        *,
        mode: str = "realtime",
        seed: int = 0,
        progress: Callable[[str], None] | None = None,
        scenario: HilScenario | None = None,
        record: RunRecorder | None = None,
        planner: PlannerWorker | None = None,
        os_api: OsApi | None = None,
        sim_cfg: ProjectConfig | None = None,
        trace: bool = True,
        sim_speed: float = 1.0,
    ) -> None:
        """``planner``: a running worker to share (tests); else one is started and owned.
        ``os_api``: the real-time system calls (a fake in tests). ``sim_cfg``: the
        simulated machine when it differs from the project the service runs on (a
        campaign's dispersions); default ``cfg``. ``trace``: keep the plots' samples.
        ``sim_speed`` (lockstep only): simulated seconds per second of the service's
        clock; below 1 the simulator runs slower than the clock the service's loop,
        trajectory and observers assume, as ``wara hil --realtime`` does on an emulated
        CPU (docs/kernel-tests.md). Each control period then advances the simulator by
        ``period * sim_speed``, which must be a whole number of its PLC scans."""
        if mode not in ("realtime", "lockstep"):
            raise ValueError(f"mode must be 'realtime' or 'lockstep', got {mode!r}")
        if not 0 < sim_speed <= 1 or (mode == "realtime" and sim_speed != 1):
            raise ValueError(f"sim_speed must be in (0, 1], and 1 in real time; got {sim_speed}")
        self.cfg = cfg
        self.mode = mode
        self.progress = progress or (lambda _s: None)
        channel = f"wara-harness-{next(_channels)}"
        # one thread in lockstep: a deque pair; two threads in real time: python-can's
        # thread-safe ``virtual`` bus (the same frames either way)
        plc_bus: can.BusABC
        ipc_bus: can.BusABC
        if mode == "lockstep":
            plc_bus, ipc_bus = lockstep_pair(channel)
        else:
            plc_bus = can.Bus(interface="virtual", channel=channel)
            ipc_bus = can.Bus(interface="virtual", channel=channel)
        self.sim = HilSimulator(
            sim_cfg if sim_cfg is not None else cfg, plc_bus, scenario=scenario, seed=seed
        )
        self.sim_speed = float(sim_speed)
        self.period = cfg.control.period_s
        #: simulated time per control period (lockstep)
        self._sim_period = self.period * self.sim_speed
        scans = self._sim_period / self.sim.cycle_s
        if mode == "lockstep" and (abs(scans - round(scans)) > 1e-9 or round(scans) < 1):
            self.sim.close()
            raise ValueError(
                f"sim_speed {sim_speed:g}: {units.to_ms(self._sim_period):g} ms of simulated "
                f"time per control period is not a whole number of PLC scans of "
                f"{units.to_ms(self.sim.cycle_s):g} ms"
            )
        clock = self.service_clock if mode == "lockstep" else time.monotonic
        self.link = IpcLink(cfg, ipc_bus, clock=clock)
        self._own_worker = planner is None
        self.worker = planner if planner is not None else PlannerWorker(config_path)
        if self._own_worker:
            self.worker.start()
        self.core = ServiceCore(cfg, self.link, self.worker, record=record)
        self.trace = Trace(self.core.active)
        self._tracing = trace
        self._k = 0
        self._switch_interval: float | None = None
        self._os_api = os_api
        self.threads_realtime = RealtimeReport()
        self.loop: FixedRateLoop | None = None
        #: a control channel on this core builds its statuses in the loop's slack
        self.slack_gate = SlackGate()
        self._sim_thread: threading.Thread | None = None
        self._stop = threading.Event()

    # ------------------------------------------------------------------ running

    def start(self) -> None:
        if self.mode == "lockstep":
            return
        # The first step compiles the plant (numba; tens of seconds on a fresh machine):
        # do it before the service's wall-clock start-up window begins.
        self.progress("preparing the simulator")
        self.sim.step(self.period)
        self.sim.truth()  # its helpers compile on first use too
        # Collect and freeze the start-up heap now: done in the loop thread (the
        # service's default) it holds the GIL for up to a few hundred ms, which here
        # would also stop the simulated PLC and rightly trip the heartbeat interlock.
        freeze_startup_heap()
        # Every thread of the interpreter shares the GIL with the loop: one preempted by
        # another process while holding it stops the loop too. So all of them (main,
        # log writer, planner supervisor; the loop and simulator threads inherit it) ask
        # for SCHED_FIFO, not only the loop's; the planner process is left as it is.
        self.threads_realtime = fifo_all_threads(self._realtime().priority)
        # The loop thread must get the GIL soon after its deadline: by default a waiting
        # thread asks for it only after 5 ms (the whole period). Restored in close().
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(SWITCH_INTERVAL_S)

        self.loop = FixedRateLoop(
            self.core.step,
            self.period,
            realtime=self._realtime(),
            os_api=self._os_api,
            freeze_heap=False,
            slack_gate=self.slack_gate,
        )

        self.loop.start()
        self._sim_thread = threading.Thread(target=self._run_sim, name="hil-sim", daemon=True)
        self._sim_thread.start()

    def _realtime(self) -> Realtime:
        """The project's ``control.realtime`` with at least :data:`RT_PRIORITY`:
        the demo's threads ask for SCHED_FIFO (granted to root or with CAP_SYS_NICE /
        an RLIMIT_RTPRIO; refused and reported otherwise, and the demo runs anyway)."""
        rt = self.cfg.control.realtime
        return rt.model_copy(update={"priority": max(rt.priority, RT_PRIORITY)})

    def _run_sim(self) -> None:
        """The simulator thread: one control period of PLC scans per wake-up, paced by
        the wall clock half a period after the loop's deadlines (the two threads take the
        GIL in turn instead of fighting for it at the same instant).

        As in ``wara hil --realtime``: a late thread runs the missed scans back to back,
        each seeing only the frames that had arrived by its due time
        (:meth:`~hil_sim.wire.FaultyWire.set_arrival_horizon`: no false command timeout
        on the PLC side); more than 0.1 s behind, the schedule is reset (the plant never
        skips time). The trace is taken here, after each period of scans (a consistent
        state, no lock shared with the loop).
        """
        sim, cycle = self.sim, self.sim.cycle_s
        scans = round(self.period / cycle)
        start = time.monotonic() + self.period / 2
        to_epoch = time.time() - time.monotonic()
        k = 0  # scans done since ``start``
        while not self._stop.is_set():
            due = start + k * cycle
            delay = due - time.monotonic()
            if delay > 0:
                self._stop.wait(delay)
            elif delay < -0.1:
                start = time.monotonic() - k * cycle
            for _ in range(scans):
                sim.wire.set_arrival_horizon(start + to_epoch + k * cycle)
                sim.step(cycle)
                k += 1
            if self._tracing:
                self.trace.add(sim, self.core)
        sim.wire.set_arrival_horizon(None)

    def service_clock(self) -> float:
        """Lockstep: the service's clock (s), the simulator's over :attr:`sim_speed`."""
        return self.sim.t_s / self.sim_speed

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` of machine time pass (of the service's clock in lockstep)."""
        if self.mode == "realtime":
            time.sleep(seconds)
            if self.loop is not None and self.loop.error is not None:
                raise RuntimeError(f"service loop stopped: {self.loop.error!r}")
            return
        n = max(1, round(seconds / self.period))
        for _ in range(n):
            self.sim.step(self._sim_period)
            self._k += 1
            self.core.step(self._k, self.service_clock())
            if self._tracing:
                self.trace.add(self.sim, self.core)
            if self.core.modes.mode == Mode.STARTING or self._planning():
                self._await_planner()

    def _planning(self) -> bool:
        return self.worker.busy or self.worker.calling or self.core.preparing

    def _await_planner(self) -> None:
        """Lockstep: hold simulated time until the planner's answer is in (or its own
        timeout, on the wall clock, has turned the request into a failure): the loop's
        attitude request, or the HMI's walk, planned on a thread of its own from the
        HMI's frame until its request is back with the loop."""
        deadline = time.monotonic() + self.worker.timeout_s + 5.0
        pause = 0.0005  # growing to 20 ms: a plan takes tenths of a second to seconds,
        # and each look costs this process CPU time (some 50 us on a busy machine) that
        # the run's figures count; a run waits at most 20 ms longer for it
        while self._planning() and time.monotonic() < deadline:
            time.sleep(pause)
            pause = min(2.0 * pause, 0.02)

    def wait_for(self, mode: Mode, timeout_s: float, *, stop_on_fault: bool = True) -> bool:
        """Advance until the service is in ``mode`` (machine time in lockstep); False at
        once when it latches a fault or the e-stop (ABORTED) on the way (``stop_on_fault``)."""
        waited = 0.0
        step = 0.05
        while waited < timeout_s:
            now = self.core.modes.mode
            if now == mode:
                return True
            if stop_on_fault and now is Mode.ABORTED:
                return False
            self.advance(step)
            waited += step
        return self.core.modes.mode == mode

    def wait_walk_ready(self, timeout_s: float = 1.0) -> bool:
        """Advance until the service could plan a walk from its measured state (the
        standing legs' pressures come at their own cycle, up to 50 ms after the start-up
        is complete; :meth:`ServiceCore.walk_start`)."""
        waited = 0.0
        while isinstance(self.core.walk_start(), str):
            if waited >= timeout_s:
                return False
            self.advance(self.period)
            waited += self.period
        return True

    def run_figures(self) -> dict[str, Any]:
        """The run's figures of the loop, the scheduler, the link and the simulator, for
        a demo's summary (``loop``, ``realtime``, ``final_mode``, ``fault_reasons``,
        ``ride_through``, ``bus_load_percent``, ``simulator_realtime_factor``)."""
        stats = self.loop.stats() if self.loop is not None else {}
        return {
            "loop": {
                "jitter_p99_ms": stats.get("jitter_p99_ms"),
                "compute_p99_ms": stats.get("compute_p99_ms"),
                "overruns": stats.get("overruns"),
                "skipped_periods": stats.get("skipped_periods"),
                "worst_overrun_cycle_ms": stats.get("worst_overrun_cycle_ms"),
                "cycles": stats.get("cycles"),
                "period_ms": units.to_ms(self.period),
            },
            "realtime": {
                "loop": self.loop.realtime_report.to_dict() if self.loop is not None else None,
                "threads": self.threads_realtime.to_dict(),
            },
            "final_mode": str(self.core.modes.mode),
            "fault_reasons": list(self.core.modes.fault_reasons),
            "fault_interlocks": [str(i) for i in self.core.modes.fault_interlocks],
            "ride_through": ride_through(self.core.snapshot()),
            "bus_load_percent": self.core.bus_load.load_percent,
            "simulator_realtime_factor": self.sim.realtime_factor,
            "sim_time_s": round(self.sim.t_s, 3),
        }

    def part_pose(self, ring: int) -> Pose:
        """The part's pose on the simulator's truth, in ring ``ring``'s tunnel frame."""
        return ring_pose(self.cfg, ring, *pose_from_home(self.cfg, self.sim.rig))

    def faulted(self) -> bool:
        return self.core.modes.mode is Mode.ABORTED

    def fault_note(self) -> str:
        """Why the service stopped: its mode and the latched fault reasons."""
        reasons = "; ".join(self.core.modes.fault_reasons) or "no reason latched"
        return f"service {self.core.modes.mode}: {reasons}"

    def close(self) -> None:
        self._stop.set()
        if self.loop is not None:
            self.loop.stop()
        if self._sim_thread is not None:
            self._sim_thread.join(5.0)
        if self._switch_interval is not None:
            sys.setswitchinterval(self._switch_interval)
            self._switch_interval = None
        if self.threads_realtime.applied:  # back to the normal scheduler
            fifo_all_threads(0)
            self.threads_realtime = RealtimeReport()
        if self._own_worker:
            self.worker.close()
        self.link.close()
        self.sim.close()

    # ------------------------------------------------------------------ the examples

    def run_example(self, roll_deg: float, pitch_deg: float) -> ExampleResult:
        """One adjustment to (roll, pitch) deg as ``wara ctl adjust`` asks for it, held
        :attr:`ServiceCore.HOLD_SETTLE_S` + :data:`HOLD_MEASURE_S`, then judged
        (:func:`~wara.examples.judge_example`): the achieved attitude is the simulator's
        truth, the twist and sync errors are what the service measured (its status'
        ``motion``, as the two-process demo reads it)."""
        res = ExampleResult(roll_deg, pitch_deg)
        out = self.core.request_adjust(roll_deg, pitch_deg)
        if not out.get("ok"):
            return judge_example(res, problem=f"refused: {out.get('error')}")
        if not self.wait_for(Mode.EXECUTE, 60.0):
            return judge_example(res, problem=f"no plan: {self.fault_note()}")
        self.progress(f"adjusting to ({roll_deg:+.1f}, {pitch_deg:+.1f}) deg")
        if not self.wait_for(Mode.COMPLETE, 300.0):
            return judge_example(res, problem=f"did not finish: {self.fault_note()}")
        self.advance(self.core.HOLD_SETTLE_S + HOLD_MEASURE_S)
        truth = self.sim.truth()
        res.set_achieved(
            units.to_deg(truth.workpiece_roll_rad), units.to_deg(truth.workpiece_pitch_rad)
        )
        res.take_motion(self.core.snapshot()["motion"])  # the service's status
        holding = self.core.modes.mode == Mode.COMPLETE
        return judge_example(res, problem="" if holding else self.fault_note())


def ring_pose(cfg: ProjectConfig, ring: int, r: np.ndarray, t: np.ndarray) -> Pose:
    """The part's pose ``(r, t)`` from its home (the simulator's truth:
    :func:`hil_sim.placement.pose_from_home`, or the site socket's answer) in ring
    ``ring``'s tunnel frame."""
    return compose(home_pose(cfg, ring), Pose.from_matrix(np.asarray(r), np.asarray(t)))


def ride_through(status: dict[str, Any]) -> dict[str, int]:
    """Suspends and resumes the service rode through (its status' ``ride_through``;
    zeros where the service does not report them)."""
    rt = status.get("ride_through") or {}
    return {"suspends": int(rt.get("suspends", 0)), "resumes": int(rt.get("resumes", 0))}


def fifo_all_threads(
    priority: int, pid: int | None = None, above: Callable[[int], bool] | None = None
) -> RealtimeReport:
    """SCHED_FIFO at ``priority`` for every thread of process ``pid`` (this one by
    default; Linux: by thread id); what was applied or refused. Threads started later
    by one of them inherit the policy. ``priority`` 0: back to SCHED_OTHER. A thread for
    which ``above(tid)`` is true gets ``priority + 1`` (a control loop above the threads
    that serve it)."""
    if not hasattr(os, "sched_setscheduler"):
        return RealtimeReport()
    policy = os.SCHED_FIFO if priority > 0 else os.SCHED_OTHER
    applied: list[str] = []
    refused: list[str] = []
    try:
        tids = [int(t) for t in os.listdir(f"/proc/{'self' if pid is None else pid}/task")]
    except OSError as exc:
        return RealtimeReport((), (f"threads: {exc}",))
    keep = getattr(os, "SCHED_RESET_ON_FORK", 0)  # a thread's own choice (the planner's)
    done = 0
    for tid in tids:
        try:
            flags = os.sched_getscheduler(tid) & keep
            own = priority + 1 if priority > 0 and above is not None and above(tid) else priority
            os.sched_setscheduler(tid, policy | flags, os.sched_param(own))
            done += 1
        except ProcessLookupError:
            continue  # the thread ended since the listing: nothing to set, nothing refused
        except OSError as exc:
            refused.append(f"SCHED_FIFO {priority} for thread {tid}: {exc.strerror or exc}")
    if done:
        applied.append(f"SCHED_FIFO priority {priority} for {done} threads")
    return RealtimeReport(tuple(applied), tuple(refused[:1]))
