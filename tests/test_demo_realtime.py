"""``wara demo`` in real time, one process (the simulator and the service's fixed-rate
loop as threads of one interpreter, on the wall clock): the attitude examples (their
default form) shortened to Example 1, and a demo that stops at once when the service
latches a fault. The ring cycles on the wall clock (``--realtime``) are not here: with
their walks the one-process loop overruns by up to some 13 ms on this 2-core machine,
near the PLC's 15 ms limit, and one run of three ended on it (docs/demo.md, "In real time")."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from config import load_project
from config.hil_scenario import HilScenario
from config.loader import validate_data
from ipc_app.service.modes import Mode
from tests.cli_helpers import run_wara
from wara.demo import failure_reason
from wara.examples import ATTITUDE_TOL_DEG, SYNC_TOL_MM, TWIST_TOL_MM
from wara.harness import Harness

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.realtime
@pytest.mark.slow
def test_realtime_one_process_demo_example_1() -> None:
    proc = run_wara(["demo", "--attitude", "--examples", "1", "--json"], timeout_s=600)
    out = json.loads(proc.stdout)  # one JSON object on stdout, pass or fail
    assert out["mode"] == "realtime"
    assert proc.returncode == 0, (failure_reason(out), proc.stderr[-3000:])
    (ex,) = out["examples"]
    assert (ex["target_roll_deg"], ex["target_pitch_deg"]) == (2.0, 1.0)
    assert ex["attitude_error_deg"] <= ATTITUDE_TOL_DEG
    assert ex["max_twist_mm"] <= TWIST_TOL_MM
    assert ex["sync_error_mm"] <= SYNC_TOL_MM
    assert out["final_mode"] == "COMPLETE" and out["fault_reasons"] == []
    loop = out["loop"]
    assert loop["cycles"] > 1000 and loop["jitter_p99_ms"] is not None
    assert set(out["ride_through"]) == {"suspends", "resumes"}


def test_examples_option_is_checked() -> None:
    from wara.cli import main

    assert main(["demo", "--attitude", "--examples", "0"]) == 2
    assert main(["demo", "--attitude", "--examples", "4"]) == 2


@pytest.mark.slow
def test_a_latched_fault_ends_the_example_at_once_with_its_reason() -> None:
    """The PLC goes silent while Example 1 moves: the service latches the fault and the
    demo reports it in the same second of machine time, instead of waiting for the
    motion's time-out."""
    cfg = load_project()
    scenario = validate_data(
        HilScenario,
        {"events": [{"kind": "plc_silent", "start_s": 3.0, "end_s": 4.0}]},
        "test scenario",
    )
    demo = Harness(cfg, mode="lockstep", scenario=scenario)
    try:
        assert demo.wait_for(Mode.IDLE, 20.0)
        res = demo.run_example(2.0, 1.0)
        assert not res.passed
        assert demo.faulted()
        assert res.note.startswith("did not finish: service ABORTED: "), res.note
        assert "plc heartbeat" in res.note
        # stopped within a second of the fault (simulated time), not after 300 s
        assert demo.sim.t_s < 3.0 + 1.0, demo.sim.t_s
    finally:
        demo.close()


def test_failure_reason_names_the_latched_faults() -> None:
    s = {
        "error": None,
        "final_mode": "ABORTED",
        "fault_reasons": ["plc fault: IPC_TIMEOUT", "sensor: stale"],
        "examples": [],
    }
    assert failure_reason(s) == "service ABORTED: plc fault: IPC_TIMEOUT; sensor: stale"
    s = {"error": "service did not come up: x", "examples": []}
    assert failure_reason(s) == "service did not come up: x"
    s = {
        "error": None,
        "fault_reasons": [],
        "examples": [
            {"passed": True, "target_roll_deg": 2.0, "target_pitch_deg": 1.0, "note": ""},
            {"passed": False, "target_roll_deg": -3.0, "target_pitch_deg": 2.0, "note": "n"},
        ],
    }
    assert failure_reason(s) == "example (-3, +2): n"


@pytest.mark.parametrize("n", [1, 4097])
def test_trace_keeps_every_sample_in_arrays(n: int) -> None:
    cfg = load_project()
    demo = Harness(cfg, mode="lockstep")
    try:
        for _ in range(n):
            demo.trace.add(demo.sim, demo.core)
        tr = demo.trace
        assert len(tr) == n and tr.t.shape == (n,) and tr.x_mm.shape == (n, 8)
        assert tr.sync_mm.shape == (n, 2) and tr.p_mpa.shape == (n, 8)
        # the rods start at mid-stroke, in mm from the retracted end
        stroke_mm = [c.stroke_mm for c in cfg.cylinders_by_can_index]
        assert tr.x_mm[-1, 0] == pytest.approx(stroke_mm[demo.core.active[0]] / 2, abs=1.0)
    finally:
        demo.close()


def test_fifo_for_every_thread_of_a_process_or_the_refusal() -> None:
    from wara.harness import fifo_all_threads

    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import threading, time\n"
            "threading.Thread(target=time.sleep, args=(60,), daemon=True).start()\n"
            "time.sleep(60)\n",
        ]
    )
    try:
        import time

        deadline = time.monotonic() + 10
        tasks = Path(f"/proc/{child.pid}/task")
        while len(list(tasks.iterdir())) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        tids = [int(t.name) for t in tasks.iterdir()]
        rep = fifo_all_threads(10, child.pid)
        if rep.applied:
            assert rep.applied == (f"SCHED_FIFO priority 10 for {len(tids)} threads",)
            assert all(os.sched_getscheduler(t) == os.SCHED_FIFO for t in tids)
            back = fifo_all_threads(0, child.pid)
            assert back.applied and not back.refused
            assert all(os.sched_getscheduler(t) == os.SCHED_OTHER for t in tids)
        else:  # not allowed here: said so, one line, and nothing changed
            assert len(rep.refused) == 1 and "SCHED_FIFO 10 for thread" in rep.refused[0]
            assert all(os.sched_getscheduler(t) == os.SCHED_OTHER for t in tids)
    finally:
        child.kill()
        child.wait()


def test_a_thread_that_ended_since_the_listing_is_not_a_refusal(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The two-process demo sets SCHED_FIFO on the service's and the simulator's threads
    every 0.5 s; a thread that ends between the listing and the call (ESRCH) was said as
    "SCHED_FIFO refused: ... No such process". It is skipped; a real refusal is still
    said."""
    import wara.harness as h

    tids = [int(t) for t in os.listdir("/proc/self/task")]
    gone = tids[0]

    def setscheduler(tid: int, policy: int, param: object) -> None:
        if tid == gone:
            raise ProcessLookupError(3, "No such process")

    monkeypatch.setattr(h.os, "sched_setscheduler", setscheduler)
    rep = h.fifo_all_threads(10)
    assert rep.refused == ()
    assert rep.applied == (f"SCHED_FIFO priority 10 for {len(tids) - 1} threads",) or (
        len(tids) == 1 and rep.applied == ()
    )

    def refuse(tid: int, policy: int, param: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(h.os, "sched_setscheduler", refuse)
    rep = h.fifo_all_threads(10)
    assert rep.applied == () and "Operation not permitted" in rep.refused[0]


def test_the_service_loop_thread_gets_the_priority_above_its_other_threads(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The two-process demo's SCHED_FIFO: the thread that pinned itself to fewer CPUs
    than its process (the service's loop, ``control.realtime.cpu_affinity``) one
    priority above the others."""
    import wara.harness as h
    from wara.demo_two_process import _pinned_alone

    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        pytest.skip("needs two CPUs to pin a thread to fewer than its process has")
    child = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import os, threading, time\n"
            f"threading.Thread(target=lambda: (os.sched_setaffinity(0, {{{cpus[0]}}}),"
            " time.sleep(60)), daemon=True).start()\n"
            "time.sleep(60)\n",
        ]
    )
    try:
        import time

        tasks = Path(f"/proc/{child.pid}/task")
        deadline = time.monotonic() + 10
        pinned = _pinned_alone(child.pid)
        while time.monotonic() < deadline:
            tids = [int(t.name) for t in tasks.iterdir()]
            if len(tids) == 2 and any(pinned(t) for t in tids):
                break
            time.sleep(0.05)
        (other,) = set(tids) - {child.pid}
        assert {t: pinned(t) for t in tids} == {child.pid: False, other: True}
        set_to: dict[int, int] = {}
        monkeypatch.setattr(h.os, "sched_getscheduler", lambda tid: 0)
        monkeypatch.setattr(
            h.os,
            "sched_setscheduler",
            lambda tid, pol, par: set_to.__setitem__(tid, par.sched_priority),
        )
        rep = h.fifo_all_threads(10, child.pid, pinned)
        assert rep.applied and set_to == {child.pid: 10, other: 11}
    finally:
        child.kill()
        child.wait()
