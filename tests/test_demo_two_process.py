"""``wara demo --two-process`` (short form): simulator and service as two processes over
``wara_udp`` (the default transport) in a private network namespace, Example 1 only, no
60 s padding.

The command makes the namespace itself (``unshare --user --map-root-user --net``, its own
loopback with multicast routed to it); the root namespace's network is never touched.
Skipped with the reason where the namespace cannot be made.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from ipc_app.service.interlocks import Interlock
from plc_bridge.link import Fault
from tests.cli_helpers import run_wara
from wara.demo_two_process import netns_problem, silent_process_stop
from wara.examples import ATTITUDE_TOL_DEG, SYNC_TOL_MM, TWIST_TOL_MM

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def netns() -> None:
    problem = netns_problem()
    if problem is not None:
        pytest.skip(f"wara demo --two-process needs a private netns: {problem}")


def _assert_silent_process_stop(out: dict[str, object], stderr: str) -> None:
    """The run ended in the safe state on a silent process alone: its latched faults,
    as data, the service's PLC heartbeat and sensor timeouts or the PLC's
    ``IPC_TIMEOUT``, and at least one of them. A process of the two kept off its CPU for
    some 100 ms (a cause not established, docs/realtime.md "Limits"; decisions 0030,
    0033) is stopped on, as the machine should; any other ending is not accepted."""
    assert silent_process_stop(out.get("faults")), (out.get("faults"), stderr[-3000:])


def test_a_silent_process_stop_is_told_from_any_other_by_its_faults_as_data() -> None:
    """The stop the two-process runs accept (and ``wara bench opcua`` runs a cycle again
    after) is read from the latched faults as data: the PLC's ``IPC_TIMEOUT``, the
    service's PLC heartbeat or sensor timeout, and nothing else beside them."""
    ipc = {"interlock": str(Interlock.PLC_FAULT), "where": Fault.IPC_TIMEOUT.name}
    beat = {"interlock": str(Interlock.PLC_HEARTBEAT), "where": None}
    assert silent_process_stop([ipc]) and silent_process_stop([beat, ipc])
    over = {"interlock": str(Interlock.OVERLOAD), "where": "sub_leg_1"}
    estop = {"interlock": str(Interlock.PLC_FAULT), "where": Fault.ESTOP.name}
    assert not silent_process_stop([ipc, over]) and not silent_process_stop([estop])
    assert not silent_process_stop([]) and not silent_process_stop(None)


@pytest.mark.realtime
@pytest.mark.slow
def test_example_1_through_two_processes(netns: None) -> None:
    """Example 1 through two processes; as in the ring cycle's test below, the safe
    state on a silent process (here also while the service comes up) is accepted with
    its cause, exit 1."""
    argv = ["demo", "--two-process", "--json", "--examples", "1", "--min-run-s", "0"]
    # (400 s: a fresh machine compiles the simulator plant first)
    proc = run_wara([*argv, "--settle-s", "1.5"], timeout_s=400)
    assert proc.returncode in (0, 1), proc.stderr
    out = json.loads(proc.stdout)
    if "error" in out or out.get("final_mode") == "ABORTED":
        assert proc.returncode == 1 and out["passed"] is False, out
        _assert_silent_process_stop(out, proc.stderr)
        return
    assert out["mode"] == "two-process" and out["bus"].startswith("wara_udp ")
    (ex,) = out["examples"]
    assert (ex["target_roll_deg"], ex["target_pitch_deg"]) == (2.0, 1.0)
    # Reached through the other process, judged from the service's sensors after a
    # short hold, and still holding: the hold must stay stable with the transport's
    # extra, varying latency (a faster tuning rocks the lower platform into the
    # sync-error interlock here; docs/control.md, "Delay margin").
    assert out["final_mode"] == "COMPLETE", (out["final_fault_reasons"], proc.stderr[-2000:])
    assert ex["attitude_error_deg"] <= ATTITUDE_TOL_DEG, (ex, proc.stderr[-2000:])
    assert ex["max_twist_mm"] <= TWIST_TOL_MM
    assert ex["sync_error_mm"] <= SYNC_TOL_MM, ex
    assert ex["duration_s"] > 1.0
    # Both processes stopped cleanly on SIGTERM.
    assert out["exit_codes"] == {"service": 0, "simulator": 0}
    loop = out["loop"]
    assert loop["reports"] >= 1 and loop["measured_cycles"] > 0
    assert loop["compute_p99_ms"] is not None and loop["overruns"] is not None
    # Placement: with two CPUs or more the loop thread and the simulator get their own.
    pl = out["placement"]
    if len(os.sched_getaffinity(0)) >= 2:
        assert pl["service_loop_cpus"] and pl["simulator_cpus"], pl
        assert not set(pl["service_loop_cpus"]) & set(pl["simulator_cpus"])
    # The loop goal is judged (exit 1 when not met on a busy machine), never skipped.
    assert proc.returncode == (0 if out["passed"] else 1)


@pytest.mark.realtime
@pytest.mark.slow(seconds=300)
def test_a_ring_cycle_through_two_processes(netns: None, tmp_path: Path) -> None:
    """The README's two-process ring cycle, ``wara demo --two-process --rings 1``, as a
    commissioning engineer runs it: the simulator and the service on the wall clock with
    the shipped safety timeouts; ring 2 walked to, placed, fixed, released, surveyed and
    walked back from, within Table 4, and the loop's figures given per phase.

    One run in four to six on the 2-core development machine ends instead in the safe
    state on a silent process: the PLC's 15 ms limit on a silent IPC, or the service's
    100 ms limits on a silent PLC (its heartbeat, the sensors' frames). A process of the
    two is kept off its CPU for some 100 ms, for a cause not established
    (docs/realtime.md, "Limits"). That ending is the machine's right answer to it and is
    accepted here, exit 1 with the cause; any other ending is not."""
    argv = ["demo", "--two-process", "--rings", "1", "--json", "--out", str(tmp_path)]
    # some 4.5 min of wall clock, and the plant compiled on a fresh machine; on a timeout
    # the command and both processes it started are killed and the test fails
    proc = run_wara(argv, timeout_s=600)
    assert proc.returncode in (0, 1), proc.stderr[-3000:]
    out = json.loads(proc.stdout)
    assert out["refused"] is None, (out, proc.stderr[-3000:])
    assert out["exit_codes"] == {"service": 0, "simulator": 0}
    phases = {p["phase"]: p for p in out["loop_phases"]["phases"]}
    assert "walk" in phases and phases["walk"]["compute_p50_ms"] > 0
    # The loop goal is judged (exit 1 when it is missed on a busy machine), never skipped.
    assert proc.returncode == (0 if out["passed"] else 1)
    if out["final_mode"] == "ABORTED":  # the safe state, on a silent process only
        assert out["rings"] == [] and out["error"], out
        _assert_silent_process_stop(out, proc.stderr)
        return
    assert out["error"] is None and out["final_mode"] == "COMPLETE", (out, proc.stderr[-3000:])
    (ring,) = out["rings"]
    assert ring["ring"] == 2
    failed = {k: v for k, v in ring["table4_truth"].items() if v["passed"] is False}
    assert not failed, failed
    assert {"walk", "place", "fixing", "release", "survey", "walk_back"} <= set(phases)
    for name in ("walk", "walk_back"):  # a 2 m step at 200 Hz: some 120 s of cycles
        assert phases[name]["cycles"] > 15_000, phases[name]
        assert 0 < phases[name]["compute_p50_ms"] <= phases[name]["compute_p99_ms"]
    assert all(m.startswith("loop: ") for m in out["missed"]), out["missed"]  # only it


@pytest.mark.slow
def test_without_a_namespace_tool_exits_2_with_one_line(tmp_path: Path) -> None:
    """No unshare on PATH: exit 2 and one line saying why."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    proc = subprocess.run(
        [sys.executable, "-m", "wara", "demo", "--two-process"],
        capture_output=True,
        text=True,
        timeout=60,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO), "PATH": str(bin_dir)},
        check=False,
    )
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "private network namespace" in lines[0]
    assert "unshare not found" in lines[0]
    assert proc.stdout == ""


def test_two_process_options_are_checked() -> None:
    from wara.cli import main

    assert main(["demo", "--settle-s", "3"]) == 2  # only with --two-process
    assert main(["demo", "--two-process", "--settle-s", "0.5"]) == 2
    assert main(["demo", "--two-process", "--examples", "4"]) == 2
    assert main(["demo", "--no-pin"]) == 2  # only with --two-process


def test_placement_of_loop_and_simulator(tmp_path: Path) -> None:
    import yaml

    from config import load_project
    from wara.demo_two_process import loop_cpus, multicast_config, simulator_cpus

    cfg = load_project()
    assert loop_cpus(cfg, [0, 1]) == [0] and loop_cpus(cfg, [3]) == []
    pinned = multicast_config(None, tmp_path / "p.yaml", pin=True)
    free = sorted(os.sched_getaffinity(0))
    if len(free) >= 2:
        assert list(pinned.control.realtime.cpu_affinity) == [free[0]]
        assert simulator_cpus(pinned, free) == free[1:]
    assert pinned.control.realtime.cpu_wakeup_latency_us == 0  # steps on a warm CPU
    unpinned = multicast_config(None, tmp_path / "u.yaml", pin=False)
    assert not unpinned.control.realtime.cpu_affinity
    assert unpinned.control.realtime.cpu_wakeup_latency_us is None
    assert simulator_cpus(unpinned, free) == []
    # A project that pins its loop itself keeps its choice.
    data = yaml.safe_load((tmp_path / "u.yaml").read_text())
    data["control"]["realtime"]["cpu_affinity"] = [1]
    data["control"]["realtime"]["cpu_wakeup_latency_us"] = 50
    (tmp_path / "own.yaml").write_text(yaml.safe_dump(data))
    own = multicast_config(tmp_path / "own.yaml", tmp_path / "o.yaml", pin=True)
    assert list(own.control.realtime.cpu_affinity) == [1]
    assert own.control.realtime.cpu_wakeup_latency_us == 50
    assert simulator_cpus(own, [0, 1, 2]) == [0, 2]
