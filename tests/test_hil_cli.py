"""``wara hil`` and ``wara bench hil``, the scenario schema and the shipped example."""

from __future__ import annotations

import json
import uuid
from pathlib import Path

import can
import pytest

from config import ConfigError, ProjectConfig
from config.hil_scenario import EVENT_KINDS, HilScenario, load_hil_scenario
from hil_sim.simulator import HilSimulator
from wara.cli import main
from wara.commands.hil import parse_fault, scenario_with_faults

EXAMPLE = Path(__file__).resolve().parents[1] / "config" / "scenarios" / "hil_faults_example.yaml"
#: the walking rig's example: the events that need ``plant.contact``
WALK_EXAMPLE = EXAMPLE.with_name("hil_walk_example.yaml")
CONTACT_KINDS = {"ground", "foot_slip"}


def test_example_scenario_has_every_kind_and_builds(project: ProjectConfig) -> None:
    sc = load_hil_scenario(EXAMPLE)
    walk = load_hil_scenario(WALK_EXAMPLE)
    assert {e.kind for e in sc.events} == set(EVENT_KINDS) - CONTACT_KINDS
    assert {e.kind for e in walk.events} >= CONTACT_KINDS and walk.plant.contact
    for scenario in (sc, walk):
        bus = can.Bus(interface="virtual", channel=uuid.uuid4().hex)
        sim = HilSimulator(project, bus, scenario)
        sim.step(0.01)
        sim.close()


def test_scenario_errors_name_file_and_key(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text(
        "events:\n  - {kind: drop, rate: 1.5}\n  - {kind: estop, start_s: 2, end_s: 1}\n"
    )
    with pytest.raises(ConfigError) as err:
        load_hil_scenario(bad)
    text = str(err.value)
    assert f"{bad}: events[0].drop.rate" in text and "events[1].estop" in text
    bad.write_text("plant: {step_ms: 0.3, plc_cycle_ms: 1.0}\nspeed: 3\n")
    with pytest.raises(ConfigError, match="speed: unknown key"):
        load_hil_scenario(bad)


def test_fault_option_parses_like_the_yaml() -> None:
    ev = parse_fault("drop:rate=0.2,messages=[PLC_RodPos_*, PLC_Status],start_s=5")
    assert ev == {
        "kind": "drop",
        "rate": 0.2,
        "messages": ["PLC_RodPos_*", "PLC_Status"],
        "start_s": 5,
    }
    sc = scenario_with_faults(HilScenario(), ["plc_silent:start_s=1,end_s=2", "bus_off"])
    assert [e.kind for e in sc.events] == ["plc_silent", "bus_off"]


def test_wara_hil_lockstep_runs(capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["hil", "--lockstep", "--duration", "0.2", "--status-interval", "0.1",
                 "--fault", "estop:start_s=0.1"])  # fmt: skip
    assert code == 0
    err = capsys.readouterr().err
    assert "mode=IDLE" in err and "faults: estop" in err and "simulated 0.200 s" in err


def test_wara_hil_bad_fault_is_a_usage_error(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["hil", "--lockstep", "--duration", "0.1", "--fault", "drop:rate"]) == 2
    assert (
        main(["hil", "--lockstep", "--duration", "0.1", "--fault", "sensor:cylinder=x,mode=stuck"])
        == 2
    )
    assert "unknown cylinder 'x'" in capsys.readouterr().err


@pytest.mark.slow
def test_wara_bench_hil_json(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "hil", "--json", "--quick"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["cylinders"] == 19 and out["step_ms"] == 0.25
    assert out["realtime_factor"] > 0 and out["plant_realtime_factor"] > out["realtime_factor"]


def test_wara_hil_cpus_are_checked(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["hil", "--lockstep", "--duration", "0.1", "--cpus", "x"]) == 2
    assert "expected CPU numbers" in capsys.readouterr().err
    assert main(["hil", "--lockstep", "--duration", "0.1", "--cpus", "4095"]) == 2
    assert "this process may use" in capsys.readouterr().err


@pytest.mark.slow
def test_wara_hil_runs_on_the_cpus_given() -> None:
    """In a child process (pinning the test runner would outlive the test)."""
    import os
    import subprocess
    import sys
    from pathlib import Path

    cpu = min(os.sched_getaffinity(0))
    code = (
        "import os, sys; from wara.cli import main; "
        f"rc = main(['hil', '--lockstep', '--duration', '0.05', '--quiet', '--cpus', '{cpu}']); "
        "print(sorted(os.sched_getaffinity(0))); sys.exit(rc)"
    )
    repo = Path(__file__).resolve().parents[1]
    proc = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
        cwd=repo, env={**os.environ, "PYTHONPATH": str(repo)}, check=False,
    )  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == f"[{cpu}]"
