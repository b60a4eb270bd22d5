"""``wara can busload|dump|record`` and ``wara bench can``."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import numpy as np
import pytest
import yaml

from config import ProjectConfig
from plc_bridge import DBC_PATH, PlcLink, PlcStatus, load_catalog, open_bus
from wara.cli import main


def _write_config(tmp_path: Path, project: ProjectConfig, **can_changes: object) -> Path:
    data = project.model_dump(mode="json")
    data["can"].update(can_changes)
    p = tmp_path / "project.yaml"
    p.write_text(yaml.safe_dump(data, sort_keys=False))
    return p


def test_busload_json_default_within_budget(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["can", "busload", "--json"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["bitrate"] == 500_000 and d["ok"] and d["load_percent"] <= 50
    assert {"bitrate", "frames_per_s", "bits_per_s", "load_percent"} <= d.keys()
    assert len(d["messages"]) == 29
    m = d["messages"][0]
    assert {"name", "frame_id", "frames_per_s", "bits_per_s", "load_percent"} <= m.keys()
    assert sum(x["bits_per_s"] for x in d["messages"]) == pytest.approx(d["bits_per_s"])


def test_busload_over_budget_exits_1(
    tmp_path: Path, project: ProjectConfig, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _write_config(tmp_path, project, bitrate=250_000)
    assert main(["can", "busload", "--config", str(cfg)]) == 1
    assert "OVER BUDGET" in capsys.readouterr().out
    with pytest.raises(SystemExit) as exc:  # argparse: the --active type refuses it
        main(["can", "busload", "--active", "x,y"])
    assert exc.value.code == 2
    assert "argument --active: value 1 of 'x,y'" in capsys.readouterr().err


@pytest.fixture
def plc_sending(tmp_path: Path, project: ProjectConfig) -> Iterator[Path]:
    """A project YAML on a private virtual channel, and a PLC side sending on it."""
    # Trailing digits on purpose: log formats derive a (16-bit) channel number from them.
    channel = f"cli-{uuid.uuid4().hex}-7654321"
    cfg_path = _write_config(tmp_path, project, channel=channel)
    stop = threading.Event()
    cfg = project.model_copy(update={"can": project.can.model_copy(update={"channel": channel})})

    def run() -> None:
        plc = PlcLink.from_config(cfg)
        plc.set_positions_m(np.linspace(0.01, 0.19, 19))
        plc.set_status(PlcStatus(pump_running=True, supply_pressure_pa=16e6))
        while not stop.is_set():
            plc.poll()
            time.sleep(0.002)
        plc.close()

    t = threading.Thread(target=run, daemon=True)
    t.start()
    time.sleep(0.05)
    yield cfg_path
    stop.set()
    t.join(5)


def test_dump_decodes_with_names_units_and_e2e(
    plc_sending: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert (
        main(["can", "dump", "--config", str(plc_sending), "--count", "40", "--duration", "5"]) == 0
    )
    out = capsys.readouterr().out
    assert "PLC_RodPos_0" in out and "RodPos_00=10.0 mm" in out
    assert "[crc ok ctr" in out and "crc BAD" not in out
    assert main(["can", "dump", "--config", str(plc_sending), "--count", "3", "--json"]) == 0
    lines = [json.loads(x) for x in capsys.readouterr().out.splitlines()]
    assert len(lines) == 3 and all(x["e2e"]["crc_ok"] for x in lines)


@pytest.mark.parametrize("suffix", [".log", ".asc", ".blf"])
def test_record_writes_a_log_that_python_can_and_cantools_read(
    plc_sending: Path, tmp_path: Path, suffix: str
) -> None:
    out = tmp_path / f"run{suffix}"
    assert main(["can", "record", str(out), "--config", str(plc_sending), "--count", "50"]) == 0
    frames = [m for m in can.LogReader(str(out)) if not m.is_error_frame]
    assert len(frames) == 50
    db = load_catalog().database
    names = {db.get_message_by_frame_id(m.arbitration_id).name for m in frames}
    assert "PLC_Status" in names or any(n.startswith("PLC_RodPos") for n in names)
    if suffix == ".log":  # candump -l format: `cantools decode` reads it
        cmd = [sys.executable, "-m", "cantools"]
        dec = subprocess.run(
            [*cmd, "decode", "--single-line", str(DBC_PATH)],
            input=out.read_text(),
            capture_output=True,
            text=True,
            check=True,
        )
        assert "PLC_RodPos_0(" in dec.stdout or "PLC_Status(" in dec.stdout


def test_record_refuses_unknown_format(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["can", "record", str(tmp_path / "x.txt"), "--count", "1"]) == 2
    assert "unknown log format" in capsys.readouterr().err


def test_dump_reports_a_bus_that_cannot_open(
    tmp_path: Path, project: ProjectConfig, capsys: pytest.CaptureFixture[str]
) -> None:
    cfg = _write_config(tmp_path, project, interface="udp_multicast", channel="wara")
    assert main(["can", "dump", "--config", str(cfg), "--count", "1"]) == 2
    assert "not a multicast group" in capsys.readouterr().err


def test_open_bus_socketcan_error_names_the_fix(project: ProjectConfig) -> None:
    from plc_bridge import BusOpenError
    from plc_bridge.bus import socketcan_available

    if socketcan_available("vcan9") is None:
        pytest.skip("vcan9 exists here")
    link = project.can.model_copy(update={"interface": "socketcan", "channel": "vcan9"})
    with pytest.raises(BusOpenError, match="vcan9"):
        open_bus(link)


def test_bench_can_quick(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "can", "--json", "--quick"]) == 0
    d = json.loads(capsys.readouterr().out)
    assert d["ok"] and d["codec_percent_of_period"] < d["goal_percent"]
    assert d["frames_per_cycle"]["ipc_tx"] == pytest.approx(3.0)
    # Ratios within one run, not absolute times (shared, noisy machine).
    assert d["speedup_vs_cantools"] > 1.0


def test_remote_without_its_plugin_is_a_clean_error(project: ProjectConfig) -> None:
    from plc_bridge import BusOpenError

    link = project.can.model_copy(update={"interface": "remote", "channel": "localhost:54701"})
    try:
        bus = open_bus(link)
    except BusOpenError as exc:
        assert "python-can-remote" in str(exc)
    else:  # the plug-in is installed here: it opened (or will fail to connect later)
        bus.shutdown()
