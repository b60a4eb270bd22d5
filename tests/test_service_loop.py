"""FixedRateLoop on an injected clock (exact arithmetic), plus one short real-clock run."""

from __future__ import annotations

import gc
import os
import sys
import threading
from collections.abc import Callable
from pathlib import Path

import pytest
from structlog.testing import capture_logs

from config.schema import Realtime
from ipc_app.service.loop import (
    ChangeGate,
    FixedRateLoop,
    LinuxOsApi,
    RealtimeReport,
    SlackGate,
    apply_realtime,
)


class FakeTime:
    """A clock that only moves when the loop sleeps or a step 'computes'."""

    def __init__(self) -> None:
        self.t = 100.0
        self.sleeps: list[float] = []

    def clock(self) -> float:
        return self.t

    def sleep(self, dt: float) -> None:
        self.sleeps.append(dt)
        self.t += dt


def make(
    ft: FakeTime,
    compute: Callable[[int], float],
    n_cycles: int,
    period: float = 1.0,
    **kw: object,
) -> tuple[FixedRateLoop, list[tuple[int, float]]]:
    calls: list[tuple[int, float]] = []
    holder: list[FixedRateLoop] = []

    def step(k: int, t: float) -> None:
        calls.append((k, t))
        ft.t += compute(k)
        if len(calls) >= n_cycles:
            holder[0].stop()

    kw.setdefault("freeze_heap", False)  # the real service freezes; the test process not
    loop = FixedRateLoop(step, period, clock=ft.clock, sleep=ft.sleep, **kw)  # type: ignore[arg-type]
    holder.append(loop)
    return loop, calls


def test_absolute_deadlines_do_not_drift() -> None:
    ft = FakeTime()
    loop, calls = make(ft, lambda k: 0.25, 50)
    loop.run()
    assert [k for k, _ in calls] == list(range(50))
    # every wake-up exactly on t0 + k * period: next += period, not now + period
    assert all(t == 100.0 + k for k, t in calls)
    s = loop.stats()
    assert s["cycles"] == 50 and s["overruns"] == 0 and s["skipped_periods"] == 0
    assert s["compute_p50_ms"] == pytest.approx(250.0)
    assert s["compute_p99_fraction"] == pytest.approx(0.25)
    assert s["jitter_max_ms"] == 0.0 and s["period_dev_max_ms"] == 0.0


def test_overrun_skips_whole_periods_and_is_counted() -> None:
    ft = FakeTime()
    # cycle 10 takes 3.5 periods: deadlines 11, 12, 13 are gone; the next step is 14
    loop, calls = make(ft, lambda k: 3.5 if k == 10 else 0.25, 15)
    loop.run()
    ks = [k for k, _ in calls]
    assert ks[:11] == list(range(11))
    assert ks[11] == 14
    t14 = dict(calls)[14]
    assert t14 == 100.0 + 14  # back on the grid, not late
    s = loop.stats()
    assert s["overruns"] == 1 and s["skipped_periods"] == 3
    assert s["worst_overrun_cycle_ms"] == pytest.approx(3500.0)
    assert s["cycles"] == 15


def test_ending_on_the_deadline_is_on_time_and_just_after_skips_one() -> None:
    on_time, calls = make(FakeTime(), lambda k: 1.0 if k == 2 else 0.0, 5)
    on_time.run()
    assert [k for k, _ in calls] == [0, 1, 2, 3, 4]
    assert on_time.stats()["skipped_periods"] == 0
    late, calls = make(FakeTime(), lambda k: 1.25 if k == 2 else 0.0, 5)
    late.run()
    assert [k for k, _ in calls] == [0, 1, 2, 4, 5]
    assert late.stats()["skipped_periods"] == 1


def test_overrun_log_is_throttled() -> None:
    ft = FakeTime()
    # every 4th cycle overruns by 1 period; 5 overruns within 20 s, throttle 100 s
    loop, _ = make(ft, lambda k: 1.5 if k % 4 == 0 else 0.1, 15, overrun_log_every_s=100.0)
    with capture_logs() as logs:
        loop.run()
    lines = [e for e in logs if e["event"] == "loop_overrun"]
    assert loop.stats()["overruns"] >= 4
    assert len(lines) == 1
    assert lines[0]["log_level"] == "warning" and lines[0]["skipped_periods"] == 1


def test_ring_is_bounded_and_stats_exported_periodically() -> None:
    ft = FakeTime()
    exported: list[dict[str, object]] = []
    loop, _ = make(
        ft,
        lambda k: 0.5 if k < 100 else 0.1,
        200,
        ring_size=32,
        stats_every_s=50.0,
        on_stats=exported.append,
    )
    loop.run()
    s = loop.stats()
    assert s["window_cycles"] == 32 and s["cycles"] == 200
    # the window only holds the last 32 cycles: all at 0.1 s
    assert s["compute_max_ms"] == pytest.approx(100.0)
    assert len(exported) == 3  # at t0+50, +100, +150 (s)
    assert all(e["period_ms"] == 1000.0 for e in exported)


def test_step_exception_stops_loop_and_is_kept() -> None:
    ft = FakeTime()

    def step(k: int, t: float) -> None:
        if k == 3:
            raise RuntimeError("bus gone")

    loop = FixedRateLoop(step, 1.0, clock=ft.clock, sleep=ft.sleep, freeze_heap=False)
    with capture_logs() as logs:
        loop.run()
    assert isinstance(loop.error, RuntimeError)
    assert loop.stats()["cycles"] == 3
    assert any(e["event"] == "loop_step_failed" for e in logs)


def test_bad_period_refused() -> None:
    with pytest.raises(ValueError, match="period_s"):
        FixedRateLoop(lambda k, t: None, 0.0)


def test_slack_gc_mode_collects_in_loop_thread_and_restores() -> None:
    ft = FakeTime()
    keep: list[object] = []
    old = gc.get_threshold()
    gc.set_threshold(50, 5, 5)
    try:

        def alloc(k: int) -> float:
            # cycles of garbage so that the young generation fills up
            for _ in range(60):
                a: list[object] = []
                a.append(a)
            keep.append(gc.isenabled())
            return 0.1

        loop, _ = make(ft, alloc, 20, gc_mode="slack")
        assert gc.isenabled()
        loop.run()
    finally:
        gc.set_threshold(*old)
    assert keep and not any(keep)  # collector off while the loop ran
    assert gc.isenabled()  # and back on after
    assert loop.stats()["gc_collections"] > 0


def test_real_thread_stops_promptly_on_request() -> None:
    cycles = threading.Event()
    count = [0]

    def step(k: int, t: float) -> None:
        count[0] += 1
        if count[0] >= 5:
            cycles.set()

    loop = FixedRateLoop(step, 0.002, name="test-loop")  # freezes the heap, as in service
    try:
        loop.start()
        assert cycles.wait(30.0)
    finally:
        frozen = gc.get_freeze_count()
        gc.unfreeze()
    assert frozen > 0
    assert loop.stop(timeout_s=10.0)  # True: the thread has ended
    assert not loop.running and loop.error is None
    assert loop.stats()["cycles"] >= 5


class FakeOs:
    def __init__(self, refuse: set[str], unlimited: bool = True) -> None:
        self.refuse = refuse
        self.unlimited = unlimited
        self.calls: list[tuple[str, object]] = []

    def _do(self, name: str, arg: object) -> None:
        self.calls.append((name, arg))
        if name in self.refuse:
            raise PermissionError(1, "Operation not permitted")

    def sched_setscheduler(self, priority: int) -> None:
        self._do("sched", priority)

    def sched_setaffinity(self, cpus: tuple[int, ...]) -> None:
        self._do("affinity", cpus)

    def mlockall(self, flags: int) -> None:
        self._do("mlock", flags)

    def memlock_unlimited(self) -> bool:
        return self.unlimited

    def hold_cpu_latency(self, latency_us: int) -> Callable[[], None]:
        self._do("latency", latency_us)
        return lambda: self.calls.append(("latency released", latency_us))


def test_realtime_nothing_asked_nothing_done() -> None:
    fake = FakeOs(set())
    assert apply_realtime(Realtime(), fake) == RealtimeReport()
    assert fake.calls == []


def test_realtime_refusals_reported_never_fatal() -> None:
    fake = FakeOs({"sched", "mlock"}, unlimited=False)
    rt = Realtime(priority=80, cpu_affinity=(1,), lock_memory=True)
    with capture_logs() as logs:
        rep = apply_realtime(rt, fake)
    assert rep.applied == ("cpu_affinity [1]",)
    assert len(rep.refused) == 2
    assert "SCHED_FIFO priority 80" in rep.refused[0] and "CAP_SYS_NICE" in rep.refused[0]
    assert "mlockall(MCL_CURRENT)" in rep.refused[1]  # finite limit: current pages only
    assert ("mlock", 1) in fake.calls
    assert sum(e["event"] == "realtime_refused" for e in logs) == 2


def test_realtime_applied_from_loop_and_reported_in_stats() -> None:
    ft = FakeTime()
    fake = FakeOs({"sched"})
    loop, _ = make(
        ft, lambda k: 0.1, 3, realtime=Realtime(priority=50, lock_memory=True), os_api=fake
    )
    loop.run()
    assert loop.realtime_report.applied == ("mlockall(MCL_CURRENT|MCL_FUTURE)",)
    assert loop.stats()["realtime_refused"][0].startswith("SCHED_FIFO priority 50")


def test_the_cpu_wakeup_latency_is_held_while_the_loop_runs_and_released_after() -> None:
    ft = FakeTime()
    fake = FakeOs(set())
    seen: list[list[tuple[str, object]]] = []
    loop, _ = make(
        ft, lambda k: seen.append(list(fake.calls)) or 0.1, 3,
        realtime=Realtime(cpu_wakeup_latency_us=0), os_api=fake,
    )  # fmt: skip
    loop.run()
    assert seen and all(c == [("latency", 0)] for c in seen)  # held during every step
    assert fake.calls == [("latency", 0), ("latency released", 0)]
    assert loop.realtime_report.applied == ("cpu_wakeup_latency 0 us (/dev/cpu_dma_latency)",)


def test_a_refused_cpu_wakeup_latency_is_reported_and_the_loop_runs() -> None:
    fake = FakeOs({"latency"})
    rep = apply_realtime(Realtime(cpu_wakeup_latency_us=10), fake)
    assert rep.applied == () and rep.releases == ()
    assert rep.refused[0].startswith("cpu_wakeup_latency 10 us (/dev/cpu_dma_latency): ")


def test_the_real_cpu_latency_request_is_a_held_file(tmp_path: Path) -> None:
    """LinuxOsApi writes the request as the kernel reads it (a 32-bit int) and holds the
    file open until released (the device replaced by a file here)."""
    import ipc_app.service.loop as loop_mod

    dev = tmp_path / "cpu_dma_latency"
    dev.write_bytes(b"")
    orig = loop_mod.CPU_LATENCY_DEVICE
    loop_mod.CPU_LATENCY_DEVICE = str(dev)
    try:
        before = len(os.listdir("/proc/self/fd"))
        release = LinuxOsApi().hold_cpu_latency(0)
        assert len(os.listdir("/proc/self/fd")) == before + 1
        release()
        assert len(os.listdir("/proc/self/fd")) == before
    finally:
        loop_mod.CPU_LATENCY_DEVICE = orig
    assert dev.read_bytes() == (0).to_bytes(4, sys.byteorder)


def test_wara_bench_loop_prints_one_json_object(capsys: pytest.CaptureFixture[str]) -> None:
    import json
    import logging

    import structlog

    from wara.cli import main

    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        assert main(["bench", "loop", "--json", "--quick"]) == 0
    finally:  # the bench configures process-wide logging, as the service would
        structlog.reset_defaults()
        root.handlers[:] = handlers
        root.setLevel(level)
    out = json.loads(capsys.readouterr().out)  # logs went to stderr
    assert out["cycles"] > 0 and out["period_ms"] == 5.0
    assert {"jitter_p99_ms", "compute_p99_ms", "overruns", "realtime"} <= set(out)


# ---------------------------------------------------------------- the slack gate


class _RecordingGate(SlackGate):
    def __init__(self, events: list[str]) -> None:
        super().__init__()
        self.events = events

    def cycle_done(self) -> None:
        self.events.append("done")
        super().cycle_done()


def test_slack_gate_opens_after_each_step_and_only_while_the_loop_runs() -> None:
    ft = FakeTime()
    events: list[str] = []
    gate = _RecordingGate(events)
    calls: list[int] = []
    holder: list[FixedRateLoop] = []

    def step(k: int, _t: float) -> None:
        assert gate.active and gate.in_step  # set before the first step; during each
        events.append(f"step {k}")
        calls.append(k)
        ft.t += 0.3
        if len(calls) >= 3:
            holder[0].stop()

    loop = FixedRateLoop(
        step, 1.0, clock=ft.clock, sleep=ft.sleep, freeze_heap=False, slack_gate=gate
    )
    holder.append(loop)
    assert not gate.active
    loop.run()
    assert events == ["step 0", "done", "step 1", "done", "step 2", "done"]
    assert not gate.active and not gate.in_step
    assert gate.wait(10.0) is False  # a stopped loop: a status no longer waits for it


def _waiter(gate: SlackGate, timeout_s: float, out: list[bool]) -> threading.Thread:
    t = threading.Thread(target=lambda: out.append(gate.wait(timeout_s)), daemon=True)
    t.start()
    return t


def _until_waiting(gate: SlackGate) -> None:
    for _ in range(2000):
        if gate._waiters._waiting:
            return
        threading.Event().wait(0.001)
    raise AssertionError("the waiter never waited")


def test_slack_gate_holds_a_waiter_until_the_step_has_ended() -> None:
    gate = SlackGate()
    gate.active = True
    assert gate.wait(30.0) is True  # between steps: at once
    gate.step_started()
    out: list[bool] = []
    t = _waiter(gate, 30.0, out)
    _until_waiting(gate)
    t.join(0.05)
    assert t.is_alive() and out == []  # no cycle ended yet: still waiting
    gate.cycle_done()
    t.join(5.0)
    assert out == [True]
    assert gate._waiters._waiting == 0


def test_slack_gate_gives_up_after_its_timeout() -> None:
    gate = SlackGate()
    gate.active = True
    gate.step_started()  # a step that does not end (a stalled loop): the caller goes on
    out: list[bool] = []
    _waiter(gate, 0.05, out).join(5.0)
    assert out == [False]


def test_service_status_is_built_in_the_loops_slack() -> None:
    """The control channel's status (what the OPC UA server asks 20 times a second)
    waits for the end of a loop step before it builds the snapshot."""
    from ipc_app.service.app import service_handlers

    built: list[str] = []

    class Core:
        period_s = 10.0  # the wait's bound is 2 periods: longer than this test
        state_changes = ChangeGate()

        def snapshot(self) -> dict[str, object]:
            built.append("snapshot")
            return {"mode": "IDLE"}

    class Ctl:
        def health(self) -> dict[str, object]:
            return {}

    gate = SlackGate()
    gate.active = True
    gate.step_started()
    handlers = service_handlers(Core, Ctl, slack=gate)  # type: ignore[arg-type]
    out: list[dict[str, object]] = []
    t = threading.Thread(target=lambda: out.append(handlers.status()), daemon=True)
    t.start()
    _until_waiting(gate)
    assert built == []  # not during the step
    gate.cycle_done()
    t.join(5.0)
    assert built == ["snapshot"] and out[0]["mode"] == "IDLE"
    handlers.status()  # between steps: built at once
    assert built == ["snapshot", "snapshot"]
