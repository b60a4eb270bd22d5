"""``wara bench demo``: what one run reports (exit code, verdict, reason, ride-through),
the command it runs (the README's main command through this interpreter), the CPU hog,
and the argument checks. The bench itself (N real-time demos) is run by hand; its
figures are in docs/service.md ("The one-process demo's timing"), the headline ones in
the README."""

from __future__ import annotations

import json
import os
import sys
import time

import pytest

from wara.benches import demo as bench


def _fake(summary: dict[str, object] | None, code: int, stderr: str = "") -> list[str]:
    out = "" if summary is None else json.dumps(summary)
    src = f"import sys\nsys.stdout.write({out!r})\nsys.stderr.write({stderr!r})\nsys.exit({code})\n"
    return [sys.executable, "-c", src]


def test_the_command_is_the_readme_main_command() -> None:
    cmd = bench.demo_command(None, quick=False)
    assert cmd == [sys.executable, "-m", "wara", "demo", "--json"]
    assert bench.demo_command("p.yaml", quick=True)[-4:] == [
        "--config",
        "p.yaml",
        "--rings",
        "1",
    ]


def test_the_ring_cycles_on_the_wall_clock_on_request() -> None:
    cmd = bench.demo_command(None, quick=True, realtime=True)
    assert cmd[3:] == ["demo", "--json", "--realtime", "--rings", "1"]


def test_the_attitude_examples_on_request() -> None:
    cmd = bench.demo_command(None, quick=True, attitude=True)
    assert cmd[3:] == ["demo", "--json", "--attitude", "--examples", "1"]


def test_a_passing_run() -> None:
    r = bench.one_run(
        _fake(
            {
                "passed": True,
                "loop": {"overruns": 2, "worst_overrun_cycle_ms": 7.5, "jitter_p99_ms": 0.3},
                "ride_through": {"suspends": 1, "resumes": 1},
            },
            0,
        ),
        dict(os.environ),
    )
    assert r["passed"] and r["exit_code"] == 0 and r["reason"] == ""
    assert (r["suspends"], r["resumes"], r["overruns"]) == (1, 1, 2)
    assert r["worst_cycle_ms"] == 7.5


def test_a_failed_run_says_why() -> None:
    r = bench.one_run(
        _fake(
            {
                "passed": False,
                "error": None,
                "final_mode": "ABORTED",
                "fault_reasons": ["plc fault: IPC_TIMEOUT"],
                "examples": [],
            },
            1,
        ),
        dict(os.environ),
    )
    assert not r["passed"] and r["exit_code"] == 1
    assert r["reason"] == "service ABORTED: plc fault: IPC_TIMEOUT"
    assert r["suspends"] == 0  # no ride_through key: counted as none


def test_a_run_without_json_reports_its_stderr() -> None:
    r = bench.one_run(_fake(None, 2, "wara demo: error: boom\n"), dict(os.environ))
    assert not r["passed"] and r["exit_code"] == 2
    assert "boom" in r["reason"]


def test_exit_0_without_a_passed_verdict_is_not_a_pass() -> None:
    r = bench.one_run(_fake({"passed": False, "examples": []}, 0), dict(os.environ))
    assert not r["passed"]


def test_the_cpu_hog_runs_pinned_and_is_stopped() -> None:
    with bench.cpu_hog(True) as cpu:
        assert cpu == max(os.sched_getaffinity(0))
        t0 = time.process_time()
        time.sleep(0.3)
        # the hog is another process: this one stays idle
        assert time.process_time() - t0 < 0.2
    with bench.cpu_hog(False) as cpu:
        assert cpu is None


def test_runs_and_cpu_hog_belong_to_the_demo_bench() -> None:
    from wara.cli import main

    assert main(["bench", "can", "--runs", "3"]) == 2
    assert main(["bench", "planner", "--cpu-hog"]) == 2
    assert main(["bench", "planner", "--attitude"]) == 2
    assert main(["bench", "planner", "--realtime"]) == 2
    assert main(["bench", "demo", "--attitude", "--realtime"]) == 2
    with pytest.raises(SystemExit):
        main(["bench", "demo", "--runs", "x"])
