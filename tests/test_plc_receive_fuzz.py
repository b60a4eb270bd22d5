"""Hypothesis fuzzing of the receive path: random ids, lengths, payloads, counters,
CRCs and timing. The link never raises, never hands out a value that no CRC-valid
frame carried (nor a stale one), and counts every frame in exactly one outcome."""

from __future__ import annotations

import math

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from config import load_project
from plc_bridge import FrameCodec, IpcLink, PlcLink, load_catalog
from plc_bridge.supervision import RX_OUTCOMES
from tests.plc_fakes import Clock, QueueBus

CFG = load_project()
CAT = load_catalog()
CODECS = {m.frame_id: FrameCodec(m) for m in CAT.messages}
KNOWN = sorted(CODECS)


@st.composite
def _frame(draw: st.DrawFn) -> tuple[can.Message, float]:
    kind = draw(st.sampled_from(["valid", "valid", "valid", "bitflip", "random", "error", "odd"]))
    dt = draw(st.sampled_from([0.0, 0.001, 0.005, 0.02, 0.2]))
    fid = draw(st.sampled_from(KNOWN) if kind != "random" else st.integers(0, 0x7FF))
    if kind == "error":
        return can.Message(
            arbitration_id=draw(st.integers(0, 0x3FF)),
            is_error_frame=True,
            data=draw(st.binary(min_size=8, max_size=8)),
        ), dt
    codec = CODECS.get(fid)
    if kind in ("valid", "bitflip") and codec is not None:
        raws = [draw(st.integers(s.raw_min - 2, s.raw_max + 2)) for s in codec.spec.signals]
        data = bytearray(codec.encode_raw(draw(st.integers(0, 15)), raws))
        if kind == "bitflip":
            bit = draw(st.integers(0, 8 * len(data) - 1))
            data[bit // 8] ^= 1 << (bit % 8)
    else:
        data = bytearray(draw(st.binary(max_size=8)))
    msg = can.Message(arbitration_id=fid, data=bytes(data), is_extended_id=False)
    if kind == "odd":
        msg.is_extended_id = draw(st.booleans())
        msg.is_remote_frame = not msg.is_extended_id
    return msg, dt


def _deterministic_outcome(side: str, msg: can.Message) -> str | None:
    """The outcome fixed by the frame alone (None: depends on the counter state)."""
    if msg.is_error_frame:
        return "error_frame"
    if msg.is_extended_id or msg.is_remote_frame:
        return "not_classic"
    codec = CODECS.get(msg.arbitration_id)
    if codec is None:
        return "unknown_id"
    if codec.spec.sender == side:
        return "own_echo"
    if len(msg.data) != codec.dlc:
        return "length_error"
    if not codec.check_crc(bytes(msg.data)):
        return "crc_error"
    return None


@pytest.mark.slow
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(_frame(), min_size=1, max_size=60), st.sampled_from(["IPC", "PLC"]))
def test_receive_path_never_raises_never_lies_counts_everything(
    frames: list[tuple[can.Message, float]], side: str
) -> None:
    clock = Clock()
    bus = QueueBus()
    link = IpcLink(CFG, bus, clock=clock) if side == "IPC" else PlcLink(CFG, bus, clock=clock)
    carried: dict[int, set[tuple[float, ...]]] = {fid: set() for fid in KNOWN}
    expected: dict[str, int] = dict.fromkeys(RX_OUTCOMES, 0)
    undetermined = 0
    for msg, dt in frames:
        clock.advance(dt)
        outcome = _deterministic_outcome(side, msg)
        if outcome is None:
            undetermined += 1
            values = CODECS[msg.arbitration_id].decode(bytes(msg.data))
            carried[msg.arbitration_id].add(values)
        else:
            expected[outcome] += 1
        bus.inject(msg)
        link.poll()
        # Every value handed out was carried by a CRC-valid frame and is fresh.
        for rec in link._rx.values():
            latest = rec.latest(clock.t)
            if latest is not None:
                assert any(
                    all((a == b) or (a != a and b != b) for a, b in zip(latest, v, strict=True))
                    for v in carried[rec.codec.frame_id]
                )
                assert clock.t - (rec.last_rx or -math.inf) <= max(
                    rec.timeout_s, rec.grace_timeout_s
                )
        if side == "IPC":
            assert isinstance(link, IpcLink)
            x = link.positions_m()
            assert np.all(np.isnan(x.value) == ~x.valid)
            assert np.all((x.value[x.valid] >= 0) & (x.value[x.valid] <= 4.194302))
            link.status(), link.hmi_target(), link.limit_switches(), link.pressures_pa()
        else:
            assert isinstance(link, PlcLink)
            u = link.valve_commands()
            assert np.all(np.abs(u.value[u.valid]) <= 1.0)
            link.control()
    got = link.rx_outcomes
    assert sum(got.values()) == len(frames)
    for k in ("error_frame", "not_classic", "unknown_id", "own_echo", "length_error", "crc_error"):
        assert got[k] == expected[k], k
    rest = (
        "accepted",
        "initial",
        "counter_repeated",
        "counter_wrong_sequence",
        "counter_invalid",
        "value_error",
    )
    assert sum(got[k] for k in rest) == undetermined
