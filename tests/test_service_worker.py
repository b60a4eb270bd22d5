"""PlannerWorker with real worker processes: results, refusals, timeout, crash, restart."""

from __future__ import annotations

import contextlib
import os
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from config import ConfigError, ProjectConfig, load_project
from ipc_app.planner import plan
from ipc_app.service.app import planner_worker
from ipc_app.service.worker import PlannerCallError, PlannerWorker, PlanResult
from tests.service_helpers import CRASH_ROLL_DEG, HANG_ROLL_DEG, RAISE_ROLL_DEG

WAIT_S = 60.0  # generous: a loaded 2-core machine; never a timing assertion


def wait_result(w: PlannerWorker, timeout_s: float = WAIT_S) -> PlanResult:
    polls = 0
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        r = w.poll()
        polls += 1
        if r is not None:
            return r
        time.sleep(0.01)
    raise AssertionError(f"no result after {timeout_s} s ({polls} polls)")


@pytest.fixture(scope="module")
def worker() -> Iterator[PlannerWorker]:
    w = PlannerWorker(None, timeout_s=WAIT_S, plan_fn="tests.service_helpers:misbehaving_plan")
    w.start()
    yield w
    w.close()


def test_feasible_plan_with_followable_trajectory(
    worker: PlannerWorker, project: ProjectConfig
) -> None:
    start_upper = (0.002, 0.002, 0.002, 0.002)  # a heave the path removes
    assert worker.submit(1, -3.0, 2.0, start_upper_m=start_upper)
    r = wait_result(worker)
    assert r.request_id == 1 and r.ok and r.feasible and r.reasons == ()
    assert r.plan is not None and r.plan["feasible"] is True
    direct = plan(project, -3.0, 2.0, start_upper_m=start_upper)
    assert r.duration_s == pytest.approx(direct.trajectory_duration_s)
    d_lower, d_upper, v_lower, _ = r.reference(0.0)
    np.testing.assert_allclose(d_lower, 0.0, atol=1e-12)
    np.testing.assert_allclose(d_upper, start_upper, atol=1e-12)
    np.testing.assert_allclose(v_lower, 0.0, atol=1e-9)
    _, d_upper_end, _, _ = r.reference(r.duration_s + 1.0)
    np.testing.assert_allclose(d_upper_end, direct.upper.displacement_m, atol=1e-9)


def test_infeasible_target_is_a_result_not_an_error(worker: PlannerWorker) -> None:
    assert worker.submit(2, 40.0, 0.0)
    r = wait_result(worker)
    assert r.ok and not r.feasible and r.reasons
    assert r.trajectory is None
    with pytest.raises(ValueError, match="no trajectory"):
        r.reference(0.0)


def test_one_request_at_a_time_and_poll_never_blocks(worker: PlannerWorker) -> None:
    assert worker.poll() is None
    assert worker.submit(3, 1.0, 1.0)
    assert worker.busy
    assert not worker.submit(4, 1.0, 1.0)  # refused while 3 is pending
    r = wait_result(worker)
    assert r.request_id == 3 and not worker.busy


def test_planner_exception_is_an_error_result(worker: PlannerWorker) -> None:
    restarts = worker.restarts
    assert worker.submit(5, RAISE_ROLL_DEG, 0.0)
    r = wait_result(worker)
    assert not r.ok and "ValueError: singular allocation" in (r.error or "")
    assert worker.restarts == restarts  # the process survived


@pytest.fixture
def impatient() -> Iterator[PlannerWorker]:
    """A worker with a 2 s planning timeout (the module's waits as long as WAIT_S, so a
    loaded machine's slow plan is not taken for a hang)."""
    w = PlannerWorker(None, timeout_s=2.0, plan_fn="tests.service_helpers:misbehaving_plan")
    w.start()
    yield w
    w.close()


def test_timeout_kills_and_restarts_the_worker(impatient: PlannerWorker) -> None:
    worker = impatient
    restarts, pid = worker.restarts, worker.pid
    assert worker.submit(6, HANG_ROLL_DEG, 0.0)
    r = wait_result(worker)
    assert r.request_id == 6 and not r.ok
    assert "timeout" in (r.error or "") and "restarted" in (r.error or "")
    assert worker.submit(7, 2.0, 1.0)  # the next request works on a new process
    r = wait_result(worker)
    assert r.request_id == 7 and r.ok and r.feasible
    assert worker.restarts == restarts + 1 and worker.pid != pid


@pytest.mark.parametrize("timeout_s", [0.5, 1.0])
def test_the_services_worker_times_out_after_planner_request_timeout_s(timeout_s: float) -> None:
    """``planner.request_timeout_s`` is the service's limit per request: a plan that hangs
    fails with that limit, not before it (0.5 s and 1 s: not the 10 s shipped)."""
    cfg = load_project()
    cfg = cfg.model_copy(
        update={"planner": cfg.planner.model_copy(update={"request_timeout_s": timeout_s})}
    )
    w = planner_worker(cfg, None, plan_fn="tests.service_helpers:misbehaving_plan")
    w.start()
    try:
        t0 = time.monotonic()
        assert w.submit(5, HANG_ROLL_DEG, 0.0)
        r = wait_result(w)
        elapsed = time.monotonic() - t0
    finally:
        w.close()
    assert not r.ok and f"planner timeout: no result after {timeout_s:g} s" in (r.error or "")
    assert elapsed >= timeout_s


def test_crash_is_detected_and_the_worker_restarted(worker: PlannerWorker) -> None:
    restarts = worker.restarts
    assert worker.submit(8, CRASH_ROLL_DEG, 0.0)
    r = wait_result(worker)
    assert not r.ok and "died (exit code 7)" in (r.error or "")
    assert worker.submit(9, -1.0, 0.5)
    r = wait_result(worker)
    assert r.request_id == 9 and r.ok and r.feasible
    assert worker.restarts == restarts + 1


PROBE = "tests.service_helpers:planner_call_probe"


def test_a_call_runs_in_the_planner_process_with_its_config(
    worker: PlannerWorker, project: ProjectConfig
) -> None:
    """The walk's and the placement's planning (``call``) runs in the planner process,
    not in a thread of the service's, on the config the process loaded."""
    got = worker.call(PROBE, "where", value=(1, 2.5))
    assert got == {"pid": worker.pid, "project": project.project.name, "value": (1, 2.5)}
    assert got["pid"] != os.getpid()


def test_a_call_that_raises_names_the_exception_and_the_process_lives(
    worker: PlannerWorker,
) -> None:
    restarts = worker.restarts
    with pytest.raises(PlannerCallError, match="raised ValueError: refused 3") as info:
        worker.call(PROBE, "raise", 3)
    assert info.value.raised == "ValueError"
    assert worker.restarts == restarts and worker.call(PROBE, "where")["pid"] == worker.pid


def test_a_call_and_the_loops_request_are_both_answered(worker: PlannerWorker) -> None:
    """A walk planned for the control channel while the loop's attitude request is
    pending: the one process answers both, each to its own caller."""
    assert worker.submit(11, 1.0, 0.5)
    got = worker.call(PROBE, "where", value="walk")
    assert got["value"] == "walk"
    r = wait_result(worker)
    assert r.request_id == 11 and r.ok and r.feasible


def test_calls_from_two_threads_queue_one_behind_the_other(worker: PlannerWorker) -> None:
    values: list[int] = []
    threads = [
        threading.Thread(target=lambda i=i: values.append(worker.call(PROBE, "where", i)["value"]))
        for i in range(4)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join(WAIT_S)
    assert sorted(values) == [0, 1, 2, 3]


def test_a_hung_call_times_out_and_the_process_is_restarted(impatient: PlannerWorker) -> None:
    worker = impatient
    restarts, pid = worker.restarts, worker.pid
    with pytest.raises(PlannerCallError, match="planner timeout: no value after 2 s"):
        worker.call(PROBE, "hang")
    got = worker.call(PROBE, "where")  # a new process answers the next call
    assert worker.restarts == restarts + 1 and got["pid"] == worker.pid != pid


def test_a_call_whose_process_dies_fails_and_the_next_one_works(worker: PlannerWorker) -> None:
    with pytest.raises(PlannerCallError, match="died \\(exit code 7\\)"):
        worker.call(PROBE, "crash")
    assert worker.call(PROBE, "where", 5)["value"] == 5


def test_a_call_on_a_stopped_worker_is_refused() -> None:
    w = PlannerWorker(None)
    with pytest.raises(PlannerCallError, match="not running"):
        w.call(PROBE, "where")


def test_bad_config_fails_in_the_caller(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        PlannerWorker(tmp_path / "missing.yaml")


def test_bad_start_extensions_refused(worker: PlannerWorker) -> None:
    with pytest.raises(ValueError, match="four extensions"):
        worker.submit(10, 1.0, 1.0, start_upper_m=(0.0, 0.0))


@pytest.mark.slow  # subprocesses or a run of many seconds: not in the fast lane
def test_the_planner_process_ends_when_the_service_is_killed(tmp_path: Path) -> None:
    """A service killed with SIGKILL leaves no planner process behind: the idle worker
    sees it is orphaned within about PARENT_CHECK_S and ends."""
    import os
    import signal
    import subprocess
    import sys

    script = (
        "import sys, time\n"
        "from ipc_app.service.worker import PlannerWorker\n"
        "w = PlannerWorker(None)\n"
        "w.start()\n"
        "end = time.monotonic() + 120\n"
        "while not w.ready and time.monotonic() < end:\n"
        "    time.sleep(0.05)\n"
        "print('PID', w.pid, flush=True)\n"
        "time.sleep(600)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    assert parent.stdout is not None
    line = ""
    while not line.startswith("PID "):  # structlog's console lines come first
        line = parent.stdout.readline()
        assert line, "the stand-in service ended without starting its planner"
    pid = int(line.split()[1])
    os.kill(parent.pid, signal.SIGKILL)
    parent.wait(10)
    end = time.monotonic() + WAIT_S
    while time.monotonic() < end:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        with contextlib.suppress(ChildProcessError):
            os.waitpid(pid, os.WNOHANG)  # not our child; reaped by init
        time.sleep(0.1)
    os.kill(pid, signal.SIGKILL)
    raise AssertionError(f"planner process {pid} still runs {WAIT_S} s after the service died")


@pytest.mark.slow
def test_ctrl_c_of_wara_serve_ends_it_without_a_traceback(tmp_path: Path) -> None:
    """Ctrl-C in a terminal is SIGINT to the whole process group: the service and its
    planner process. The service stops in order (exit 0); the planner process printed
    a KeyboardInterrupt traceback."""
    import signal
    import subprocess
    import sys

    err_path = tmp_path / "stderr.txt"
    with err_path.open("w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "wara", "serve", "--socket", str(tmp_path / "c.sock"),
             "--db", str(tmp_path / "a.sqlite")],
            stdout=subprocess.DEVNULL, stderr=err, cwd=tmp_path, start_new_session=True,
            env={**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1])},
        )  # fmt: skip
        try:
            end = time.monotonic() + WAIT_S
            while "planner_ready" not in err_path.read_text() and time.monotonic() < end:
                assert proc.poll() is None, err_path.read_text()
                time.sleep(0.2)
            assert "planner_ready" in err_path.read_text()
            os.killpg(proc.pid, signal.SIGINT)
            assert proc.wait(WAIT_S) == 0
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
    text = err_path.read_text()
    assert "service_stopped" in text
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text
