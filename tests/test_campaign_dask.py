"""Campaigns on a real Dask LocalCluster: worker processes over TCP on localhost (not
threads), the same table from one worker as from two, a worker killed mid-campaign
losing nothing and counting nothing twice, resume, and the CLI end to end."""

from __future__ import annotations

import contextlib
import copy
import os
import shutil
import signal
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import psutil
import pytest

from tests.campaign_helpers import SMALL_SPEC, same_rows, write_spec
from tests.cli_helpers import run_main
from wara.campaign.engine import dask_client, read_results, run_campaign, run_file
from wara.campaign.spec import Campaign, load_campaign

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def client2() -> Iterator[Any]:
    with dask_client(workers=2) as client:
        yield client


@pytest.fixture(scope="module")
def small(tmp_path_factory: pytest.TempPathFactory) -> Campaign:
    return load_campaign(write_spec(tmp_path_factory.mktemp("spec")))


@pytest.fixture(scope="module")
def reference_dir(client2: Any, small: Campaign, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small campaign run on two workers."""
    out = tmp_path_factory.mktemp("ref") / "camp"
    o = run_campaign(small, out, client=client2, progress=False)
    assert o.complete and o.written == 4 and not o.errors
    return out


@pytest.fixture(scope="module")
def reference(reference_dir: Path) -> list[dict[str, Any]]:
    return read_results(reference_dir)


def _first_two(tmp: Path) -> Path:
    """The small spec with two runs: a run depends on its index only, so these are the
    first two rows of the four-run campaign."""
    data = copy.deepcopy(SMALL_SPEC)
    data["requirement"] = {"runs": 2}
    return write_spec(tmp, data, "two.yaml")


def test_two_worker_processes_over_tcp(client2: Any, reference: list[dict[str, Any]]) -> None:
    info = client2.scheduler_info()
    assert client2.scheduler.address.startswith("tcp://127.0.0.1:")
    assert len(info["workers"]) == 2
    assert all(addr.startswith("tcp://127.0.0.1:") for addr in info["workers"])
    pids = set(client2.run(os.getpid).values())
    assert len(pids) == 2 and os.getpid() not in pids
    # the runs went to both processes, never to this one
    ran_in = {int(r["worker"].rsplit(":", 1)[1]) for r in reference}
    assert ran_in <= pids and os.getpid() not in ran_in
    assert [r["run"] for r in reference] == [0, 1, 2, 3]
    # a fault campaign: the runs with a PLC stall (tens of ms) rode it through
    assert all(r["passed"] for r in reference), [r["note"] for r in reference]
    assert {r["status"] for r in reference} <= {"passed", "ridden_through"}


def test_one_worker_gives_the_same_table(reference: list[dict[str, Any]], tmp_path: Path) -> None:
    two = load_campaign(_first_two(tmp_path))
    o = run_campaign(two, tmp_path / "camp", workers=1, progress=False)
    assert o.complete and o.workers == 1
    assert same_rows(read_results(tmp_path / "camp"), reference[:2]) == []


def test_resume_runs_only_what_is_missing(
    client2: Any,
    small: Campaign,
    reference_dir: Path,
    reference: list[dict[str, Any]],
    tmp_path: Path,
) -> None:
    out = tmp_path / "camp"
    shutil.copytree(reference_dir, out)
    for i in (1, 3):
        run_file(out, i).unlink()
    with pytest.raises(Exception, match="use --resume"):
        run_campaign(small, out, client=client2, progress=False)
    seen: list[int] = []
    o = run_campaign(
        small,
        out,
        client=client2,
        resume=True,
        progress=False,
        on_row=lambda r: seen.append(r["run"]),
    )
    assert sorted(seen) == [1, 3] and o.done_before == 2 and o.written == 2
    assert same_rows(read_results(out), reference) == []


def test_a_killed_worker_loses_nothing_and_counts_nothing_twice(
    small: Campaign, reference: list[dict[str, Any]], tmp_path: Path
) -> None:
    out = tmp_path / "camp"
    killed: list[int] = []
    orphans: list[psutil.Process] = []
    with dask_client(workers=2) as client:

        def kill_one_running(row: dict[str, Any]) -> None:
            if killed:
                return
            busy = [w for w, keys in client.processing().items() if keys]
            pids = client.run(os.getpid)
            victim = pids[busy[0]] if busy else next(iter(pids.values()))
            orphans.extend(psutil.Process(victim).children(recursive=True))  # its planner
            os.kill(victim, signal.SIGKILL)
            killed.append(victim)

        try:
            o = run_campaign(small, out, client=client, progress=False, on_row=kill_one_running)
        finally:
            for p in orphans:
                with contextlib.suppress(psutil.NoSuchProcess):
                    p.kill()
    assert killed
    assert o.complete and o.written == 4 and not o.errors
    rows = read_results(out)
    assert [r["run"] for r in rows] == [0, 1, 2, 3]
    assert same_rows(rows, reference) == []


def test_cli_run_on_a_scheduler_report_replay(
    client2: Any, reference: list[dict[str, Any]], tmp_path: Path
) -> None:
    spec = _first_two(tmp_path)
    out = tmp_path / "camp"
    addr = client2.scheduler.address
    code, text, err = run_main(
        ["campaign", "run", str(spec), "--out", str(out), "--scheduler", addr]
    )
    assert code == 0, err
    assert "2 runs written (0 before) of 2" in text and "2/2" in err
    assert same_rows(read_results(out), reference[:2]) == []
    code, text, _ = run_main(
        ["campaign", "run", str(spec), "--resume", str(out), "--scheduler", addr]
    )
    assert code == 0 and f"{out}: all 2 runs were already done, nothing to run" in text
    code, text, _ = run_main(["campaign", "report", str(out)])
    assert code == 1 and "2 of 2 runs, 0 failed" in text and "incomplete" not in text
    assert (out / "report.html").stat().st_size > 10_000
    code, text, _ = run_main(["campaign", "replay", str(out), "1", "--plot", str(tmp_path)])
    assert code == 0 and "same as the campaign's row: yes" in text
    assert (tmp_path / "demo.png").exists()


def test_tune_starts_from_the_shipped_tuning_and_returns_a_fragment(
    client2: Any, small: Campaign, tmp_path: Path
) -> None:
    import yaml

    from wara.campaign.tune import tune

    res = tune(small, tmp_path / "tune", client=client2, trials=2, runs=1)
    from ipc_app.control.tuning import derived_value

    first = res["trials"][0]
    keys = ("control.ladrc.wc_rad_s", "control.ladrc.wo_rad_s")
    # the project leaves them out: the search starts from what the plant derives
    assert first["values"] == {k: derived_value(small.project, k) for k in keys}
    assert first["values"]["control.ladrc.wc_rad_s"] == 5.75
    assert len(res["trials"]) == 2 and all(t["runs"] == 1 for t in res["trials"])
    fragment = yaml.safe_load(res["fragment"])
    assert set(fragment["control"]["ladrc"]) == {"wc_rad_s", "wo_rad_s"}
    best = res["trials"][res["best_trial"]]
    assert res["figure"] == pytest.approx(best["figure"])
    assert max(t["figure"] for t in res["trials"]) == pytest.approx(best["figure"])
    # each trial's runs ran with its own values: the service's project differs
    assert (tmp_path / "tune" / "trial-0001" / "results.parquet").exists()
