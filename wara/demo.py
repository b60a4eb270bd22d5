"""The end-to-end demo: the HIL simulator and the IPC service on one CAN bus.

Runs Examples 1-3 of the reference machine one after another from a level start: each
target goes to the service (as ``wara ctl adjust`` would), the planner worker plans it,
the service's loop drives the simulated rig over the DBC, and the figures are read from
the service (what the operator sees) and from the simulator's truth.

Two timings:
- ``realtime`` (the default): the service's :class:`FixedRateLoop` runs in its own thread
  on the wall clock (jitter and overruns are real), the simulator in another thread,
  paced by the wall clock, on the in-process ``virtual`` bus;
- ``lockstep``: simulator and service alternate in one thread on simulated time (fast;
  for tests and studies). Simulated time stands still while the planner process works
  (bounded by the worker's own timeout), so a plan arrives in the cycle after it was
  asked for, however busy the machine is: a run does not depend on the wall clock.
"""

from __future__ import annotations

import itertools
import math
import os
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from config import load_project, units
from config.hil_scenario import HilScenario
from config.schema import ProjectConfig, Realtime
from hil_sim.simulator import HilSimulator
from ipc_app.service.core import ServiceCore
from ipc_app.service.loop import FixedRateLoop, OsApi, RealtimeReport, freeze_startup_heap
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from ipc_app.service.worker import PlannerWorker
from plc_bridge.link import IpcLink

EXAMPLES: tuple[tuple[float, float], ...] = ((2.0, 1.0), (-3.0, 2.0), (5.0, -1.0))

#: Goals of issue 6 (tolerances each example must meet).
ATTITUDE_TOL_DEG = 0.01
TWIST_TOL_MM = 0.5
SYNC_TOL_MM = 0.07

#: Standstill after the motion over which the sync error at standstill is taken.
HOLD_MEASURE_S = 3.0

#: SCHED_FIFO priority of the real-time demo's two threads (loop and simulator), when the
#: system grants it: a busy machine's other processes then wait for them, not they for
#: those (docs/service.md, "The one-process demo's timing").
DEMO_RT_PRIORITY = 10

#: The interpreter's thread switch interval while the real-time demo runs (default 5 ms).
SWITCH_INTERVAL_S = 0.0005

_channels = itertools.count()


@dataclass
class ExampleResult:
    target_roll_deg: float
    target_pitch_deg: float
    achieved_roll_deg: float = math.nan
    achieved_pitch_deg: float = math.nan
    attitude_error_deg: float = math.nan
    max_twist_mm: float = math.nan
    sync_error_mm: float = math.nan
    #: largest sync error of either group during the motion (controller view)
    max_sync_error_mm: float = math.nan
    duration_s: float = math.nan
    passed: bool = False
    note: str = ""


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

    @property
    def t(self) -> np.ndarray:
        return self._series("t")

    @property
    def roll_deg(self) -> np.ndarray:
        return self._series("roll_deg")

    @property
    def pitch_deg(self) -> np.ndarray:
        return self._series("pitch_deg")

    @property
    def x_mm(self) -> np.ndarray:
        return self._series("x_mm")

    @property
    def sync_mm(self) -> np.ndarray:
        return self._series("sync_mm")

    @property
    def p_mpa(self) -> np.ndarray:
        return self._series("p_mpa")


_DEG = units.to_deg(1.0)
_MM = units.to_mm(1.0)
_MPA = units.to_mpa(1.0)


class Demo:
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
    ) -> None:
        """``planner``: a running worker to share (tests); else one is started and owned.
        ``os_api``: the real-time system calls (a fake in tests)."""
        if mode not in ("realtime", "lockstep"):
            raise ValueError(f"mode must be 'realtime' or 'lockstep', got {mode!r}")
        self.cfg = cfg
        self.mode = mode
        self.progress = progress or (lambda _s: None)
        channel = f"wara-demo-{next(_channels)}"
        self.sim = HilSimulator(
            cfg, can.Bus(interface="virtual", channel=channel), scenario=scenario, seed=seed
        )
        clock = self.sim.clock if mode == "lockstep" else time.monotonic
        self.link = IpcLink(cfg, can.Bus(interface="virtual", channel=channel), clock=clock)
        self._own_worker = planner is None
        self.worker = planner if planner is not None else PlannerWorker(config_path)
        if self._own_worker:
            self.worker.start()
        self.core = ServiceCore(cfg, self.link, self.worker, record=record)
        self.trace = Trace(self.core.active)
        self.period = cfg.control.period_s
        self._k = 0
        self._switch_interval: float | None = None
        self._os_api = os_api
        self.threads_realtime = RealtimeReport()
        self.loop: FixedRateLoop | None = None
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
        )

        self.loop.start()
        self._sim_thread = threading.Thread(target=self._run_sim, name="hil-sim", daemon=True)
        self._sim_thread.start()

    def _realtime(self) -> Realtime:
        """The project's ``control.realtime`` with at least :data:`DEMO_RT_PRIORITY`:
        the demo's threads ask for SCHED_FIFO (granted to root or with CAP_SYS_NICE /
        an RLIMIT_RTPRIO; refused and reported otherwise, and the demo runs anyway)."""
        rt = self.cfg.control.realtime
        return rt.model_copy(update={"priority": max(rt.priority, DEMO_RT_PRIORITY)})

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
            self.trace.add(sim, self.core)
        sim.wire.set_arrival_horizon(None)

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` of machine time pass."""
        if self.mode == "realtime":
            time.sleep(seconds)
            if self.loop is not None and self.loop.error is not None:
                raise RuntimeError(f"service loop stopped: {self.loop.error!r}")
            return
        n = max(1, round(seconds / self.period))
        for _ in range(n):
            self.sim.step(self.period)
            self._k += 1
            self.core.step(self._k, self.sim.t_s)
            self.trace.add(self.sim, self.core)
            if self.core.modes.mode == Mode.STARTING:
                self._await_planner()

    def _await_planner(self) -> None:
        """Lockstep: hold simulated time until the planner's answer is in (or its own
        timeout, on the wall clock, has turned the request into a failure)."""
        deadline = time.monotonic() + self.worker.timeout_s + 5.0
        while self.worker.busy and time.monotonic() < deadline:
            time.sleep(0.0005)

    def wait_for(self, mode: Mode, timeout_s: float, *, stop_on_fault: bool = True) -> bool:
        """Advance until the service is in ``mode`` (machine time in lockstep); False at
        once when it latches a fault or the e-stop (ABORTED) on the way (``stop_on_fault``)."""
        waited = 0.0
        step = 0.05
        while waited < timeout_s:
            now = self.core.modes.mode
            if now == mode:
                return True
            if stop_on_fault and now in (Mode.ABORTED, Mode.ABORTED):
                return False
            self.advance(step)
            waited += step
        return self.core.modes.mode == mode

    def faulted(self) -> bool:
        return self.core.modes.mode in (Mode.ABORTED, Mode.ABORTED)

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
        res = ExampleResult(roll_deg, pitch_deg)
        out = self.core.request_adjust(roll_deg, pitch_deg)
        if not out.get("ok"):
            res.note = f"refused: {out.get('error')}"
            return res
        if not self.wait_for(Mode.EXECUTE, 60.0):
            res.note = f"no plan: {self.fault_note()}"
            return res
        self.progress(f"adjusting to ({roll_deg:+.1f}, {pitch_deg:+.1f}) deg")
        if not self.wait_for(Mode.COMPLETE, 300.0):
            res.note = f"did not finish: {self.fault_note()}"
            return res
        self.advance(self.core.HOLD_SETTLE_S + HOLD_MEASURE_S)
        m = self.core.motion
        truth = self.sim.truth()
        res.achieved_roll_deg = units.to_deg(truth.workpiece_roll_rad)
        res.achieved_pitch_deg = units.to_deg(truth.workpiece_pitch_rad)
        res.attitude_error_deg = max(
            abs(res.achieved_roll_deg - roll_deg), abs(res.achieved_pitch_deg - pitch_deg)
        )
        res.max_twist_mm = units.to_mm(m.max_twist_m)
        res.sync_error_mm = units.to_mm(m.hold_sync_error_m)
        res.max_sync_error_mm = units.to_mm(m.max_sync_error_m)
        res.duration_s = m.duration_s
        if self.core.modes.mode != Mode.COMPLETE:
            res.note = self.fault_note()
        res.passed = (
            self.core.modes.mode == Mode.COMPLETE
            and res.attitude_error_deg <= ATTITUDE_TOL_DEG
            and res.max_twist_mm <= TWIST_TOL_MM
            and res.sync_error_mm <= SYNC_TOL_MM
        )
        return res


def run_demo(
    config_path: str | None = None,
    *,
    mode: str = "realtime",
    examples: tuple[tuple[float, float], ...] = EXAMPLES,
    plot_dir: Path | None = None,
    progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run the examples; returns the JSON-ready summary (``passed`` tells the verdict)."""
    cfg = load_project(config_path)
    say = progress or (lambda _s: None)
    demo = Demo(cfg, config_path, mode=mode, progress=say)
    results: list[ExampleResult] = []
    error: str | None = None
    try:
        demo.start()
        say("starting: waiting for the PLC")
        if not demo.wait_for(Mode.IDLE, 20.0):
            error = f"service did not come up: {demo.fault_note()}"
            say(error)
        for roll, pitch in examples if error is None else ():
            results.append(demo.run_example(roll, pitch))
            say(
                f"example ({roll:+.1f}, {pitch:+.1f}) deg: "
                f"{'passed' if results[-1].passed else 'FAILED ' + results[-1].note}"
            )
            if demo.faulted():  # the rest would be refused: report now
                say(f"stopping: {demo.fault_note()}")
                break
        stats = demo.loop.stats() if demo.loop is not None else {}
    finally:
        demo.close()
    summary: dict[str, Any] = {
        "mode": mode,
        "error": error,
        "examples": [asdict(r) for r in results],
        "loop": {
            "jitter_p99_ms": stats.get("jitter_p99_ms"),
            "compute_p99_ms": stats.get("compute_p99_ms"),
            "overruns": stats.get("overruns"),
            "skipped_periods": stats.get("skipped_periods"),
            "worst_overrun_cycle_ms": stats.get("worst_overrun_cycle_ms"),
            "cycles": stats.get("cycles"),
            "period_ms": demo.period * 1e3,
        },
        "realtime": {
            "loop": demo.loop.realtime_report.to_dict() if demo.loop is not None else None,
            "threads": demo.threads_realtime.to_dict(),
        },
        "final_mode": str(demo.core.modes.mode),
        "fault_reasons": list(demo.core.modes.fault_reasons),
        "ride_through": ride_through(demo.core.snapshot()),
        "bus_load_percent": demo.core.bus_load.load_percent,
        "simulator_realtime_factor": demo.sim.realtime_factor,
        "tolerances": {
            "attitude_error_deg": ATTITUDE_TOL_DEG,
            "max_twist_mm": TWIST_TOL_MM,
            "sync_error_mm": SYNC_TOL_MM,
        },
        "passed": error is None
        and len(results) == len(examples)
        and all(r.passed for r in results),
    }
    if plot_dir is not None:
        summary["plots"] = [str(p) for p in plot_trace(demo.trace, plot_dir)]
    return summary


def fifo_all_threads(priority: int, pid: int | None = None) -> RealtimeReport:
    """SCHED_FIFO at ``priority`` for every thread of process ``pid`` (this one by
    default; Linux: by thread id); what was applied or refused. Threads started later
    by one of them inherit the policy. ``priority`` 0: back to SCHED_OTHER."""
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
    for tid in tids:
        try:
            flags = os.sched_getscheduler(tid) & keep
            os.sched_setscheduler(tid, policy | flags, os.sched_param(priority))
        except OSError as exc:
            refused.append(f"SCHED_FIFO {priority} for thread {tid}: {exc.strerror or exc}")
    if len(refused) < len(tids):
        applied.append(f"SCHED_FIFO priority {priority} for {len(tids) - len(refused)} threads")
    return RealtimeReport(tuple(applied), tuple(refused[:1]))


def ride_through(status: dict[str, Any]) -> dict[str, int]:
    """Suspends and resumes the service rode through (its status' ``ride_through``;
    zeros where the service does not report them)."""
    rt = status.get("ride_through") or {}
    return {"suspends": int(rt.get("suspends", 0)), "resumes": int(rt.get("resumes", 0))}


def plot_trace(trace: Trace, out_dir: Path) -> list[Path]:
    """Attitude, cylinder positions, sync errors and pressures over time (PNG)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out_dir.mkdir(parents=True, exist_ok=True)
    t = np.asarray(trace.t)
    fig, ax = plt.subplots(4, 1, figsize=(11, 12), sharex=True)
    ax[0].plot(t, trace.roll_deg, label="workpiece roll")
    ax[0].plot(t, trace.pitch_deg, label="workpiece pitch")
    ax[0].set_ylabel("deg")
    ax[0].set_title("Workpiece attitude in the world (simulator truth)")
    ax[0].legend(loc="best")
    x = np.asarray(trace.x_mm)
    names = ["leg 1", "leg 2", "leg 3", "leg 4", "upper 1", "upper 2", "upper 3", "upper 4"]
    for i in range(x.shape[1] if x.ndim == 2 else 0):
        ax[1].plot(t, x[:, i], label=names[i], lw=1)
    ax[1].set_ylabel("rod position, mm")
    ax[1].set_title("Attitude cylinders (from the retracted end)")
    ax[1].legend(loc="best", ncol=4, fontsize=8)
    s = np.asarray(trace.sync_mm)
    if s.ndim == 2:
        ax[2].plot(t, s[:, 0], label="lower group")
        ax[2].plot(t, s[:, 1], label="upper group")
    ax[2].axhline(SYNC_TOL_MM, color="k", ls="--", lw=0.8, label="standstill goal")
    ax[2].set_ylabel("mm")
    ax[2].set_title("Synchronization error (largest in the group, controller view)")
    ax[2].legend(loc="best")
    p = np.asarray(trace.p_mpa)
    for i in range(p.shape[1] if p.ndim == 2 else 0):
        ax[3].plot(t, p[:, i], label=names[i], lw=1)
    ax[3].set_ylabel("cap pressure, MPa")
    ax[3].set_xlabel("time, s")
    ax[3].set_title("Cap-side pressures")
    ax[3].legend(loc="best", ncol=4, fontsize=8)
    fig.tight_layout()
    path = out_dir / "demo.png"
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return [path]


def render_table(summary: dict[str, Any]) -> str:
    lines = example_rows(summary)
    lp = summary["loop"]
    jit = lp.get("jitter_p99_ms")
    lines += [
        "",
        f"loop: {lp['period_ms']:.1f} ms period, jitter p99 "
        f"{'n/a (lockstep)' if jit is None else f'{jit:.3f} ms'}, overruns "
        f"{lp.get('overruns', 'n/a')}; bus load {summary['bus_load_percent']:.1f} %; "
        f"simulator {summary['simulator_realtime_factor']:.1f}x real time",
        "PASSED" if summary["passed"] else "FAILED: " + failure_reason(summary),
    ]
    return "\n".join(lines)


def failure_reason(summary: dict[str, Any]) -> str:
    """One line: why a demo run did not pass (the error, else the service's latched
    faults, else the first example that missed its goals)."""
    if summary.get("error"):
        return str(summary["error"])
    if summary.get("fault_reasons"):
        return f"service {summary.get('final_mode')}: " + "; ".join(summary["fault_reasons"])
    for r in summary.get("examples", []):
        if not r.get("passed"):
            return f"example ({r['target_roll_deg']:+g}, {r['target_pitch_deg']:+g}): {r['note']}"
    return "not every example ran"


def example_rows(summary: dict[str, Any]) -> list[str]:
    """The table's header and one row per example (shared with the two-process form)."""
    head = (
        f"{'target roll/pitch deg':>22} {'achieved roll/pitch deg':>25} {'error deg':>10} "
        f"{'max twist mm':>12} {'sync at rest mm':>15} {'sync moving mm':>14} "
        f"{'duration s':>10}  result"
    )
    lines = [head, "-" * len(head)]
    for r in summary["examples"]:
        lines.append(
            f"{r['target_roll_deg']:>+10.3f} {r['target_pitch_deg']:>+10.3f}  "
            f"{r['achieved_roll_deg']:>+12.4f} {r['achieved_pitch_deg']:>+11.4f} "
            f"{r['attitude_error_deg']:>10.5f} {r['max_twist_mm']:>12.4f} "
            f"{r['sync_error_mm']:>15.4f} {r.get('max_sync_error_mm', math.nan):>14.4f} "
            f"{r['duration_s']:>10.2f}  "
            f"{'ok' if r['passed'] else 'FAILED ' + r['note']}"
        )
    return lines


def stderr_progress(text: str) -> None:
    print(f"wara demo: {text}", file=sys.stderr, flush=True)
