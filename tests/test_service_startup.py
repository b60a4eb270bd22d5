"""Start-up of `wara serve` and `wara hil`: a failure to start is one line on stderr, exit 2,
no traceback, and no run record left behind (the bus and the socket are opened before the
recorder); BOOT ends within its time, in IDLE or in a fault that says why (lockstep); the
planner processes start under the normal scheduler; `wara ctl status` as text."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import structlog
import yaml

from config import load_project
from config.loader import default_project_path
from wara.cli import main


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    """`wara serve` configures logging for the process; put it back for the next tests."""
    root = logging.getLogger()
    level, handlers = root.level, list(root.handlers)
    yield
    root.setLevel(level)
    root.handlers[:] = handlers
    structlog.reset_defaults()


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    with tempfile.TemporaryDirectory(prefix="wara-start-") as d:  # AF_UNIX: short paths
        yield Path(d)


def _project(tmp: Path, **can: Any) -> str:
    data = yaml.safe_load(default_project_path().read_text())
    data["can"].update(can)
    path = tmp / "project.yaml"
    path.write_text(yaml.safe_dump(data))
    return str(path)


BAD_BUSES = {
    "socketcan on a missing channel": {"interface": "socketcan", "channel": "nosuchcan7"},
    "wara_udp on a channel that is not multicast": {
        "interface": "wara_udp",
        "channel": "10.1.2.3",
    },
    "udp_multicast on a host name": {"interface": "udp_multicast", "channel": "localhost"},
}


def _one_line(err: str, prefix: str) -> str:
    assert err.count("\n") == 1 and err.startswith(prefix), err
    assert "Traceback" not in err
    return err


@pytest.mark.parametrize("can", BAD_BUSES.values(), ids=BAD_BUSES.keys())
def test_serve_with_a_bus_that_cannot_open(
    short_tmp: Path, can: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    records = short_tmp / "runs"
    code = main(
        [
            "serve",
            "--config",
            _project(short_tmp, **can),
            "--record-dir",
            str(records),
            "--socket",
            str(short_tmp / "ctl.sock"),
            "--duration-s",
            "1",
        ]
    )
    err = _one_line(capsys.readouterr().err, "wara serve: error: ")
    assert code == 2 and can["channel"] in err
    assert not records.exists()
    assert not (short_tmp / "ctl.sock").exists()


def test_serve_with_a_socket_path_that_is_a_regular_file(
    short_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    records, sock = short_tmp / "runs", short_tmp / "ctl.sock"
    sock.write_text("not a socket\n")
    code = main(["serve", "--record-dir", str(records), "--socket", str(sock), "--duration-s", "1"])
    err = _one_line(capsys.readouterr().err, "wara serve: error: ")
    assert code == 2 and "exists and is not a socket" in err
    assert not records.exists()
    assert sock.read_text() == "not a socket\n"  # left alone


def test_serve_with_a_record_dir_that_cannot_be_written(
    short_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = short_tmp / "file"
    blocker.write_text("")
    code = main(
        [
            "serve",
            "--record-dir",
            str(blocker / "runs"),
            "--socket",
            str(short_tmp / "ctl.sock"),
            "--duration-s",
            "1",
        ]
    )
    err = _one_line(capsys.readouterr().err, "wara serve: error: cannot write the run record")
    assert code == 2 and "--record-dir" in err
    assert not (short_tmp / "ctl.sock").exists()


@pytest.mark.parametrize("can", BAD_BUSES.values(), ids=BAD_BUSES.keys())
def test_hil_with_a_bus_that_cannot_open(
    short_tmp: Path, can: dict[str, str], capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["hil", "--config", _project(short_tmp, **can), "--duration", "1", "--quiet"])
    err = _one_line(capsys.readouterr().err, "wara hil: error: ")
    assert code == 2 and can["channel"] in err


class _NoPlanner:
    """BOOT needs no planner: nothing is submitted before IDLE."""

    timeout_s = 1.0
    busy = calling = False

    def submit(self, *args: Any, **kwargs: Any) -> bool:
        raise AssertionError("nothing is planned in these tests")

    def poll(self) -> None:
        return None


def _lockstep(*events: dict[str, Any]) -> Any:
    from config import load_project
    from config.hil_scenario import HilScenario
    from wara.harness import Harness

    scenario = HilScenario.model_validate({"events": list(events)})
    return Harness(load_project(), mode="lockstep", scenario=scenario, planner=_NoPlanner())  # type: ignore[arg-type]


@pytest.mark.slow  # subprocesses or a run of many seconds: not in the fast lane
def test_boot_ends_in_a_fault_when_the_plc_never_hears_the_commands() -> None:
    """The IPC's frames held on the wire: the PLC reports the commands stale, every input
    of the IPC is fresh. start-up (STOPPED) ends in ABORTED `start-up` with that reason once
    `safety.boot_timeout_s` is over, and a reset is refused while it lasts; once the
    PLC hears the commands the reset is taken (IDLE)."""
    from ipc_app.service.interlocks import Interlock
    from ipc_app.service.modes import Mode

    timeout = load_project().safety.boot_timeout_s
    demo = _lockstep(
        {"kind": "wire_stall", "start_s": 0.0, "end_s": timeout + 1.0, "direction": "ipc_to_plc"}
    )
    core = demo.core
    try:
        demo.advance(timeout - 0.05)
        assert core.modes.mode == Mode.STOPPED
        cycles = 0
        while core.modes.mode == Mode.STOPPED and cycles < 100:
            demo.advance(demo.period)
            cycles += 1
        assert core.modes.mode == Mode.ABORTED and cycles <= 12, (cycles, core.modes.mode)
        first = core.modes.faults[0]
        assert first.interlock is Interlock.STARTUP and first.limit == timeout
        assert first.first is not None and timeout < first.first <= timeout + 0.06
        assert "the PLC reports the IPC's commands stale" in first.detail
        assert core.modes.fault_interlocks == (Interlock.STARTUP,)
        core.request_reset()
        demo.advance(0.6)  # longer than the reset pulse, still within the stall
        assert core.modes.mode == Mode.ABORTED  # refused: the PLC still does not hear them
        demo.advance(0.6)  # the wire delivers; the PLC hears fresh commands
        core.request_reset()
        demo.advance(1.0)
        assert core.modes.mode == Mode.IDLE, core.modes.fault_reasons
    finally:
        demo.close()


def test_boot_completes_when_the_link_comes_fresh_within_the_timeout() -> None:
    from ipc_app.service.modes import Mode

    timeout = load_project().safety.boot_timeout_s
    demo = _lockstep(
        {"kind": "wire_stall", "start_s": 0.0, "end_s": timeout - 1.0, "direction": "ipc_to_plc"}
    )
    try:
        assert demo.wait_for(Mode.IDLE, timeout + 1.0)
        assert not demo.core.modes.faults
    finally:
        demo.close()


def test_wara_ctl_status_text_shows_the_ride_through(
    short_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """The status text carries the suspends and resumes ridden through (the service's
    counters, as in the JSON status)."""
    from ipc_app.service.app import service_handlers
    from ipc_app.service.ctl import CtlServer, request
    from ipc_app.service.modes import Mode

    demo = _lockstep()
    core = demo.core
    ctl = CtlServer(service_handlers(lambda: core, lambda: ctl), short_tmp / "ctl.sock")
    try:
        assert demo.wait_for(Mode.IDLE, 2.0)
        core.motions.suspends, core.motions.resumes = 3, 2  # as the manager counts them
        demo.advance(demo.period)  # published with the next cycle
        ctl.bind()
        ctl.start()
        assert main(["ctl", "--socket", str(short_tmp / "ctl.sock"), "status"]) == 0
        text = capsys.readouterr().out.splitlines()
        assert "ride_through.suspends: 3" in text and "ride_through.resumes: 2" in text
        assert request("status", socket_path=short_tmp / "ctl.sock")["ride_through"] == {
            "suspends": 3,
            "resumes": 2,
        }
    finally:
        ctl.stop()
        demo.close()


_PLANNER_POLICY = """
import os, sys, threading, time
try:
    os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
except OSError as exc:
    print("refused", exc.strerror)
    sys.exit(0)
from ipc_app.service.worker import PlannerWorker
w = PlannerWorker(None)
w.start()
end = time.monotonic() + 120
while not w.ready and time.monotonic() < end:
    time.sleep(0.05)
assert w.ready and w.pid is not None
children = []
for entry in os.listdir("/proc"):
    if entry.isdigit():
        try:
            stat = open(f"/proc/{entry}/stat").read()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == os.getpid():
            children.append(int(entry))
flag = os.SCHED_RESET_ON_FORK
print("planner", os.sched_getscheduler(w.pid) & ~flag)
print("children", *sorted({os.sched_getscheduler(c) & ~flag for c in children}))
print("supervisor", os.sched_getscheduler(w._thread.native_id) & ~flag)
print("main", os.sched_getscheduler(0) & ~flag)
w.close()
"""


@pytest.mark.skipif(not hasattr(os, "SCHED_RESET_ON_FORK"), reason="Linux only")
def test_planner_processes_start_under_the_normal_scheduler() -> None:
    """A service whose threads run at SCHED_FIFO (the demo and the soak put every thread
    there) starts its planner processes (the fork server, its resource tracker, the
    planner) under the normal scheduler; the supervisor thread keeps its policy."""
    proc = subprocess.run(
        [sys.executable, "-c", _PLANNER_POLICY],
        capture_output=True,
        text=True,
        timeout=300,
        cwd=Path(__file__).resolve().parents[1],
        check=False,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    if proc.stdout.startswith("refused"):
        pytest.skip(f"SCHED_FIFO not allowed here: {proc.stdout.strip()}")
    got = dict(line.split(" ", 1) for line in proc.stdout.splitlines() if " " in line)
    got = {k: v for k, v in got.items() if k in ("planner", "children", "supervisor", "main")}
    other, fifo = str(os.SCHED_OTHER), str(os.SCHED_FIFO)
    assert got == {"planner": other, "children": other, "supervisor": fifo, "main": fifo}, got
