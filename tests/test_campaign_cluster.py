"""Campaigns on a separate Dask scheduler with workers started as a site starts them
(``dask worker ADDR``, its own processes, not the embedded LocalCluster): a worker with
two threads gives the same table as one-thread workers, a daemon worker is refused in
one line before anything is submitted; a finished directory resumed starts no cluster;
Ctrl-C ends a run without the workers' tracebacks; the warm-up starts the planner the
runs use."""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from tests.campaign_helpers import same_rows, write_spec
from tests.cli_helpers import REPO, run_main
from wara.campaign import engine
from wara.campaign.engine import dask_client, payload_of, read_results, run_campaign
from wara.campaign.spec import Campaign, load_campaign

pytestmark = pytest.mark.slow

START_S = 120.0  # generous: a loaded 2-core machine; never a timing assertion


def _env(**extra: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), **extra}


@contextlib.contextmanager
def _processes() -> Iterator[list[subprocess.Popen[str]]]:
    procs: list[subprocess.Popen[str]] = []
    try:
        yield procs
    finally:
        for p in procs:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(p.pid, signal.SIGTERM)
        for p in procs:
            try:
                p.wait(30)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()


def _scheduler(procs: list[subprocess.Popen[str]], tmp: Path) -> str:
    """A ``dask scheduler`` process; its address."""
    file = tmp / "scheduler.json"
    procs.append(
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_scheduler",
                "--host",
                "127.0.0.1",
                "--port",
                "0",
                "--dashboard-address",
                ":0",
                "--scheduler-file",
                str(file),
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
            env=_env(),
        )
    )
    end = time.monotonic() + START_S
    while not file.exists() and time.monotonic() < end:
        time.sleep(0.2)
    import json

    for _ in range(50):
        with contextlib.suppress(ValueError):
            return str(json.loads(file.read_text())["address"])
        time.sleep(0.1)
    raise AssertionError("the scheduler did not write its address")


def _worker(procs: list[subprocess.Popen[str]], addr: str, nthreads: int, **env: str) -> None:
    procs.append(
        subprocess.Popen(
            [
                sys.executable,
                "-m",
                "distributed.cli.dask_worker",
                addr,
                "--nthreads",
                str(nthreads),
                "--nworkers",
                "1",
                "--host",
                "127.0.0.1",
                "--dashboard-address",
                ":0",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            text=True,
            start_new_session=True,
            env=_env(**env),
        )
    )


def _wait_workers(addr: str, n: int) -> None:
    from distributed import Client

    with Client(addr, timeout=START_S) as c:
        c.wait_for_workers(n, timeout=START_S)


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Campaign:
    return load_campaign(write_spec(tmp_path_factory.mktemp("spec")))


@pytest.fixture(scope="module")
def reference(small: Campaign, tmp_path_factory: pytest.TempPathFactory) -> list[dict[str, Any]]:
    """The small campaign on the embedded cluster of two one-thread workers, its warm-up
    for the campaign's project; the planners each worker started."""
    out = tmp_path_factory.mktemp("ref") / "camp"
    with dask_client(workers=2, payload=payload_of(small)) as client:
        o = run_campaign(small, out, client=client, progress=False)
        planners = client.run(lambda: sorted(engine._PLANNERS))
    assert o.complete and o.written == 4 and not o.errors
    # the warm-up started the planner the runs used (the worker's copy of the campaign's
    # project), and no other
    assert len(planners) == 2 and all(
        len(v) == 1 and "wara-campaign-project-" in v[0] for v in planners.values()
    ), planners
    return read_results(out)


def test_a_two_thread_worker_gives_the_same_table(
    small: Campaign, reference: list[dict[str, Any]], tmp_path: Path
) -> None:
    """``dask worker ADDR --nthreads 2``: two runs in one process at once shared its
    planner and its virtual CAN channels (6 failures of 10 instead of 3, attitude
    errors of 1.6 deg, no error anywhere). Now its runs take turns, and it is said."""
    notes: list[str] = []
    with _processes() as procs:
        addr = _scheduler(procs, tmp_path)
        _worker(procs, addr, 2, DASK_DISTRIBUTED__WORKER__DAEMON="False")
        _wait_workers(addr, 1)
        with dask_client(addr, payload=payload_of(small), say=notes.append) as client:
            o = run_campaign(small, tmp_path / "camp", client=client, progress=False)
    assert o.complete and not o.errors, o.errors
    assert same_rows(read_results(tmp_path / "camp"), reference) == []
    (note,) = notes
    assert re.search(r"Dask worker tcp://127\.0\.0\.1:\d+ has 2 threads: its runs take", note)


def test_a_daemon_worker_is_refused_in_one_line_before_any_run(
    small: Campaign, tmp_path: Path
) -> None:
    """A worker started without DASK_DISTRIBUTED__WORKER__DAEMON=False: every run ended
    in a 40-line traceback. Now one line, exit 2, and nothing submitted."""
    spec = write_spec(tmp_path)
    with _processes() as procs:
        addr = _scheduler(procs, tmp_path)
        _worker(procs, addr, 1)  # the default: a daemon worker process under its nanny
        _wait_workers(addr, 1)
        code, out, err = run_main(
            ["campaign", "run", str(spec), "--out", str(tmp_path / "c"), "--scheduler", addr]
        )
    assert (code, out) == (2, "")
    (line,) = err.splitlines()
    assert "is a daemon process, which cannot start the planner process" in line, line
    assert "DASK_DISTRIBUTED__WORKER__DAEMON=False" in line
    assert not list((tmp_path / "c" / "runs").glob("run-*"))


def test_a_finished_directory_resumed_starts_no_cluster(
    small: Campaign, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    with dask_client(workers=1, payload=payload_of(small)) as client:
        run_campaign(small, tmp_path / "camp", client=client, progress=False)

    def no_cluster(*a: Any, **k: Any) -> Any:
        raise AssertionError("a cluster was started for a finished campaign")

    monkeypatch.setattr(engine, "dask_client", no_cluster)
    o = run_campaign(small, tmp_path / "camp", resume=True, progress=False)
    assert (o.complete, o.written, o.done_before) == (True, 0, 4)
    spec = write_spec(tmp_path)
    code, out, err = run_main(["campaign", "run", str(spec), "--resume", str(tmp_path / "camp")])
    assert (code, err) == (0, "")
    assert out == (
        f"{tmp_path / 'camp'}: all 4 runs were already done, nothing to run; "
        f"wara campaign report {tmp_path / 'camp'} gives the verdict\n"
    )


def test_ctrl_c_ends_a_run_without_the_workers_tracebacks(tmp_path: Path) -> None:
    """Ctrl-C (SIGINT to the process group) printed a KeyboardInterrupt traceback in
    every worker process (eight, 169 lines)."""
    spec = write_spec(tmp_path)
    err_path = tmp_path / "stderr.txt"
    with err_path.open("w") as err:
        proc = subprocess.Popen(
            [sys.executable, "-m", "wara", "campaign", "run", str(spec), "--out",
             str(tmp_path / "c"), "--workers", "2"],
            stdout=subprocess.DEVNULL, stderr=err, start_new_session=True, env=_env(),
            # as from a terminal: a test run in the background (a non-interactive shell's
            # `&`) ignores SIGINT, and Python keeps an ignored SIGINT
            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
        )  # fmt: skip
        try:
            end = time.monotonic() + START_S
            while "ETA" not in err_path.read_text() and time.monotonic() < end:
                assert proc.poll() is None, err_path.read_text()
                time.sleep(0.2)
            assert "ETA" in err_path.read_text(), err_path.read_text()
            os.killpg(proc.pid, signal.SIGINT)
            code = proc.wait(START_S)
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
    text = err_path.read_text()
    assert code == 130, text
    assert "Traceback" not in text and "KeyboardInterrupt" not in text, text
    # Python's resource tracker may report, after the command's last line, the queue
    # semaphores of the worker processes the shutdown ended, which it removes
    # (docs/campaigns.md): its lines only, nothing of ours
    ours = [ln for ln in text.rstrip().splitlines() if not _resource_tracker_line(ln)]
    assert ours[-1] == "wara: interrupted", text


def _resource_tracker_line(line: str) -> bool:
    return "resource_tracker" in line and (
        "leaked semaphore" in line or line.lstrip().startswith("warnings.warn(")
    )
