"""The DBC is the single source of truth: it loads cleanly, tools read it, the code's
mirrors of its value tables agree, and the default bus load stays within budget."""

from __future__ import annotations

import logging
import subprocess
import sys
import warnings
from pathlib import Path

import cantools
import pytest

from config import ProjectConfig
from plc_bridge import DBC_PATH, CatalogError, bus_load, frame_bits, load_catalog
from plc_bridge.link import Fault, Mode, TargetAck, TargetRequest
from tests.plc_fakes import with_can


def test_dbc_loads_strictly_without_warnings(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.DEBUG)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        db = cantools.database.load_file(str(DBC_PATH), strict=True)
    # cantools' own records only: a thread a previous test left may log meanwhile
    loaded = [r for r in caplog.records if r.name.split(".")[0] == "cantools"]
    assert not [r for r in loaded if r.levelno >= logging.WARNING]
    assert len(db.messages) == 29
    assert {n.name for n in db.nodes} == {"IPC", "PLC"}


def test_catalog_rules() -> None:
    cat = load_catalog()
    ids = [m.frame_id for m in cat.messages]
    assert len(set(ids)) == len(ids) and max(ids) <= 0x7FF
    assert len({m.data_id for m in cat.messages}) == len(cat.messages)
    assert all(m.data_id == 0xA000 | m.frame_id for m in cat.messages)
    assert all(m.cycle_s > 0 for m in cat.messages)
    # Every cylinder has a valve command, a rod position and two pressures.
    for prefix in ("ValveCmd_", "RodPos_", "CapPress_", "RodPress_"):
        slots = sorted(s.slot for m in cat.messages for s in m.signals if s.name.startswith(prefix))
        assert slots == list(range(19)), prefix
    # Resolutions the issue asks for.
    pos = cat.by_name("PLC_RodPos_0").signal("RodPos_00")
    assert pos.scale <= 0.001 and pos.unit == "mm" and pos.maximum >= 2200
    press = cat.by_name("PLC_Pressure_0").signal("CapPress_00")
    assert press.scale <= 0.01 and press.unit == "MPa" and press.maximum >= 25
    roll = cat.by_name("PLC_HmiTarget").signal("TargetRoll")
    assert roll.scale <= 0.001 and roll.unit == "deg"


@pytest.mark.parametrize(
    ("enum", "message", "signal"),
    [
        (Mode, "IPC_Control", "ModeRequest"),
        (Mode, "PLC_Status", "ModeActual"),
        (TargetAck, "IPC_Control", "TargetAckStatus"),
        (TargetRequest, "PLC_HmiTarget", "TargetRequest"),
        (Fault, "PLC_Status", "FaultCode"),
    ],
)
def test_python_enums_mirror_the_dbc_value_tables(enum: type, message: str, signal: str) -> None:
    choices = load_catalog().by_name(message).signal(signal).choices
    assert {m.value: m.name for m in enum} == choices  # type: ignore[attr-defined]


@pytest.mark.slow
def test_cantools_dump_reads_it() -> None:
    cmd = [sys.executable, "-m", "cantools"]
    out = subprocess.run([*cmd, "dump", str(DBC_PATH)], capture_output=True, text=True, check=True)
    assert "PLC_RodPos_0" in out.stdout and "Cycle time:     5 ms" not in out.stdout
    assert "Cycle time:     20 ms" in out.stdout


def test_bad_dbc_is_refused_with_the_message_named(tmp_path: Path) -> None:
    text = DBC_PATH.read_text().replace(
        "SG_ PLC_Limits_CRC : 0|8@1+", "SG_ PLC_Limits_CRC : 0|7@1+"
    )
    p = tmp_path / "bad.dbc"
    p.write_text(text)
    with pytest.raises(CatalogError, match=r"PLC_Limits \(0x180\): first signal must be the CRC"):
        load_catalog(p)
    with pytest.raises(CatalogError, match="file not found"):
        load_catalog(tmp_path / "none.dbc")


def test_frame_bits_worst_case_stuffing() -> None:
    assert frame_bits(8) == 135  # the "about 135 bits per 8-byte frame"
    assert frame_bits(0) == 55
    assert frame_bits(8, extended=True) == 160


def test_default_configuration_within_bus_load_budget(project: ProjectConfig) -> None:
    load = bus_load(project)
    assert load.active_cylinders == (0, 1, 2, 3, 8, 9, 10, 11)
    assert load.load_percent <= 50.0 and load.ok
    # Both standing frames cost the same.
    sub = bus_load(project, active=[4, 5, 6, 7, 8, 9, 10, 11])
    assert sub.load_percent == pytest.approx(load.load_percent)
    # All 19 at the loop rate would not fit: the reason the groups exist.
    assert not bus_load(project, active=range(19)).ok
    # 250 Hz at 1 Mbit/s fits easily.
    fast = with_can(project, bitrate=1_000_000)
    assert bus_load(fast).load_percent < 25


def test_unknown_active_group_is_a_config_error(project: ProjectConfig) -> None:
    from pydantic import ValidationError

    with pytest.raises(
        ValidationError, match=r"can.active_groups: unknown cylinder group\(s\) \['legs'\]"
    ):
        with_can(project, active_groups=["legs", "upper"])
