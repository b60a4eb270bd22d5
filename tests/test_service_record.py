"""RunRecorder: nothing lost on stop, bounded queue with counted drops, readable output."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import numpy as np
import pytest
from structlog.testing import capture_logs

from ipc_app.service.record import RunRecorder, new_run_dir, read_run

COLS = ("d_upper_1_mm", "twist_mm", "valve_cmd_1")


def test_every_row_and_event_reaches_disk_and_reads_back(tmp_path: Path) -> None:
    run_dir = new_run_dir(tmp_path)
    rec = RunRecorder(run_dir, COLS, meta={"period_s": 0.005, "config": "shanghai"})
    rec.start()
    n = 5000
    for k in range(n):
        t = k * 0.005
        assert rec.sample(t, (0.001 * k, np.sin(t), -0.5))
        if k % 1000 == 0:
            rec.event(t, "mode", mode="ADJUSTING" if k else "IDLE")
    summary = rec.stop()
    assert summary == {
        "rows_written": n,
        "rows_dropped": 0,
        "events_written": 5,
        "events_dropped": 0,
        "io_errors": 0,
    }
    run = read_run(run_dir)
    assert run.t_s.shape == (n,)
    np.testing.assert_allclose(run["d_upper_1_mm"], 0.001 * np.arange(n), rtol=1e-8)
    np.testing.assert_allclose(run["twist_mm"], np.sin(run.t_s), atol=1e-8)
    assert [e["mode"] for e in run.events] == ["IDLE"] + ["ADJUSTING"] * 4
    assert run.meta["columns"] == ["t_s", *COLS]
    assert run.meta["rows_written"] == n and run.meta["period_s"] == 0.005
    with pytest.raises(KeyError, match="no column 'pressure'"):
        run["pressure"]


def test_overflow_drops_newest_counts_logs_and_records_it(tmp_path: Path) -> None:
    rec = RunRecorder(tmp_path / "run", COLS, max_queued_rows=100, flush_every_s=3600)
    rec.start()  # the writer sleeps an hour between drains: the queue fills up
    with capture_logs() as logs:
        accepted = [rec.sample(k * 0.005, (1.0, 2.0, 3.0)) for k in range(250)]
    assert accepted.count(True) == 100 and accepted.count(False) == 150
    assert next(e for e in logs if e["event"] == "record_overflow")["rows_dropped"] == 1
    assert sum(e["event"] == "record_overflow" for e in logs) == 1  # throttled
    summary = rec.stop()  # stop wakes the writer: the 100 queued rows are not lost
    assert summary["rows_written"] == 100 and summary["rows_dropped"] == 150
    run = read_run(tmp_path / "run")
    assert run.t_s.size == 100
    overflow = [e for e in run.events if e["kind"] == "record_overflow"]
    assert overflow == [{"t_s": None, "kind": "record_overflow", "rows_dropped": 150}]
    assert run.meta["rows_dropped"] == 150


def test_concurrent_producer_and_periodic_fsync(tmp_path: Path) -> None:
    rec = RunRecorder(tmp_path / "r", COLS, flush_every_s=0.01, fsync_every_s=0.0)
    rec.start()
    done = threading.Event()

    def produce() -> None:
        for k in range(20_000):
            rec.sample(float(k), (float(k), 0.0, 0.0))
        done.set()

    th = threading.Thread(target=produce)
    th.start()
    th.join(60)
    assert done.is_set()
    rec.stop()
    run = read_run(tmp_path / "r")
    assert rec.rows_written + rec.rows_dropped == 20_000
    np.testing.assert_array_equal(run.t_s, run["d_upper_1_mm"])  # rows intact, in order
    assert np.all(np.diff(run.t_s) > 0)
    assert rec.fsyncs >= 1


def test_partial_last_line_after_a_crash_is_ignored(tmp_path: Path) -> None:
    with RunRecorder(tmp_path / "c", COLS) as rec:
        for k in range(10):
            rec.sample(k * 0.1, (1.0, 2.0, 3.0))
        rec.event(0.5, "fault", reason="twist")
    with open(tmp_path / "c" / "samples.csv", "a") as f:
        f.write("1.0,1.0,2")  # the crash hit mid-line
    with open(tmp_path / "c" / "events.jsonl", "a") as f:
        f.write('{"t_s": 1.0, "ki')
    run = read_run(tmp_path / "c")
    assert run.t_s.size == 10 and len(run.events) == 1


def test_row_of_wrong_length_is_dropped_not_written(tmp_path: Path) -> None:
    with capture_logs(), RunRecorder(tmp_path / "w", COLS) as rec:
        rec.sample(0.0, (1.0, 2.0))
        rec.sample(0.1, (1.0, 2.0, 3.0))
    assert rec.rows_written == 1 and rec.rows_dropped == 1


def test_bad_columns_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="unique"):
        RunRecorder(tmp_path, ("a", "a"))
    with pytest.raises(ValueError, match="without commas"):
        RunRecorder(tmp_path, ("a,b",))


def test_meta_is_valid_json_from_the_start(tmp_path: Path) -> None:
    rec = RunRecorder(tmp_path / "m", COLS, meta={"project": "Shanghai"})
    rec.start()
    meta = json.loads((tmp_path / "m" / "meta.json").read_text())
    assert meta["format"] == "wara-run-1" and meta["project"] == "Shanghai"
    rec.stop()
