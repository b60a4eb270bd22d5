"""The simulator's compiled frame path (``hil_sim.plc_frames``) agrees with plc_bridge's
codec and receive checks frame for frame, over every message of the DBC: the same bytes
from the same values (NaN, out of range, halfway between two raw values), the same
values from the same bytes, and the same outcome, lost frames and counter state for the
same frame sequence, with lengths, CRCs, counters and values broken on purpose."""

from __future__ import annotations

import math
import random

import numpy as np
import pytest

from hil_sim.plc_frames import (
    ENCODE_OVERFLOW,
    TIMEOUTS,
    FrameTables,
    check_frame,
    counter_table,
    crc_ok,
    decode_frame,
    encode_frame,
)
from plc_bridge import FrameCodec, load_catalog
from plc_bridge.catalog import MessageSpec, SignalSpec
from plc_bridge.supervision import RX_OUTCOMES, RxRecord

CAT = load_catalog()
CODECS = [FrameCodec(m) for m in CAT.messages]
TABLES = FrameTables(CODECS)
WIDTH = TABLES.fields_i.shape[1]


def _value(rnd: random.Random, s: SignalSpec) -> float:
    """A value of ``s``: in range, at or beyond a bound, halfway between two raw values,
    NaN."""
    k = rnd.random()
    if k < 0.08:
        return math.nan
    if k < 0.16:
        return s.maximum + rnd.choice((0.0, 0.4, 0.5, 3.0, 1e6)) * s.scale
    if k < 0.24:
        return s.minimum - rnd.choice((0.0, 0.4, 0.5, 3.0, 1e6)) * s.scale
    if k < 0.40:
        raw = rnd.randint(s.raw_min, s.raw_max)
        return (raw + 0.5) * s.scale + s.offset
    return rnd.uniform(s.minimum, s.maximum)


def _encode(m: int, counter: int, values: list[float]) -> bytes | int:
    out = np.zeros(8, dtype=np.uint8)
    n = encode_frame(
        TABLES.msg, TABLES.fields_i, TABLES.fields_f, m, counter, np.array(values), out
    )
    return n if n < 0 else bytes(out[:n])


def _padded(data: bytes) -> np.ndarray:
    buf = np.zeros(8, dtype=np.uint8)
    buf[: min(8, len(data))] = list(data[:8])
    return buf


@pytest.mark.parametrize("m", range(len(CODECS)), ids=[c.name for c in CODECS])
def test_encode_decode_crc_agree_with_the_codec(m: int) -> None:
    codec = CODECS[m]
    spec: MessageSpec = codec.spec
    rnd = random.Random(m)
    values = np.zeros(WIDTH)
    for i in range(400):
        vals = [_value(rnd, s) for s in spec.signals]
        counter = rnd.randrange(16)
        data = codec.encode(counter, vals)
        assert _encode(m, counter, vals) == data, (vals, counter)
        # a bit flipped, a byte cut or added: the same CRC verdict and the same values
        frame = bytearray(data)
        if i % 3 == 1:
            frame[rnd.randrange(len(frame))] ^= 1 << rnd.randrange(8)
        elif i % 3 == 2:
            frame = frame[:-1] if rnd.random() < 0.5 else frame + b"\x00"
        buf = _padded(bytes(frame))
        assert crc_ok(TABLES.msg, m, buf, len(frame)) == codec.check_crc(bytes(frame))
        if len(frame) == codec.dlc:
            decode_frame(TABLES.msg, TABLES.fields_i, TABLES.fields_f, m, buf, len(frame), values)
            ref = codec.decode(bytes(frame))
            got = values[: len(ref)].tolist()
            assert [x if x == x else "nan" for x in got] == [x if x == x else "nan" for x in ref]


def test_an_infinite_value_is_refused_as_python_refuses_it() -> None:
    m = next(i for i, c in enumerate(CODECS) if c.name == "PLC_RodPos_0")
    with pytest.raises(OverflowError):
        CODECS[m].encode(0, [math.inf, 0.0])
    assert _encode(m, 0, [math.inf, 0.0]) == ENCODE_OVERFLOW


@pytest.mark.parametrize("max_delta", [1, 3])
@pytest.mark.parametrize("name", [m.name for m in CAT.messages])
def test_receive_checks_agree_with_the_record(name: str, max_delta: int) -> None:
    """A stream of frames with lost, repeated, reordered, corrupted, cut and out-of-range
    ones: the same outcome, lost frames, counter state and values as RxRecord.on_frame."""
    m = next(i for i, c in enumerate(CODECS) if c.name == name)
    codec = CODECS[m]
    rec = RxRecord(codec, 0.1, max_delta)
    counters = counter_table(rec)
    state = np.array([-1], dtype=np.int64)
    values = np.full(WIDTH, -1.0)
    scratch = np.zeros(WIDTH)
    rnd = random.Random(max_delta * 1000 + m)
    counter = 0
    seen: set[str] = set()
    total_lost = 0
    for i in range(1500):
        vals = [_value(rnd, s) for s in codec.spec.signals]
        k = rnd.random()
        counter = (counter + (rnd.randint(2, 14) if k < 0.1 else 0 if k < 0.15 else 1)) % 15
        frame = bytearray(codec.encode(counter, vals))
        k = rnd.random()
        if k < 0.05:
            frame[0] ^= 0xFF
        elif k < 0.08:
            frame = frame[:-1]
        elif k < 0.11:  # counter 15 with a good CRC (never sent)
            frame = bytearray(codec.encode(15, vals))
        elif k < 0.16:  # a raw value out of range, CRC made good
            raws = codec.to_raw(vals)
            f = rnd.randrange(len(raws))
            raws[f] = codec.spec.signals[f].raw_max + 1
            frame = bytearray(codec.encode_raw(counter, raws))
        ref = rec.on_frame(bytes(frame), float(i))
        got, lost = check_frame(
            TABLES.msg, TABLES.fields_i, TABLES.fields_f, counters, m, _padded(bytes(frame)),
            len(frame), state, values, scratch,
        )  # fmt: skip
        assert RX_OUTCOMES[got] == ref, i
        seen.add(ref)
        assert (None if state[0] < 0 else int(state[0])) == rec.last_counter
        if ref == "accepted":
            assert rec.values is not None
            assert [x if x == x else "nan" for x in values[: len(rec.values)].tolist()] == [
                x if x == x else "nan" for x in rec.values
            ]
            total_lost += lost
        else:
            assert lost == 0
    # the stream reached every outcome a record can give (length, CRC, counters, values)
    expected = {"accepted", "initial", "crc_error", "length_error", "counter_repeated"}
    expected |= {"counter_wrong_sequence", "counter_invalid"}
    if any(s.sna_raw is None and s.raw_max < (1 << s.length) - 1 for s in codec.spec.signals):
        expected.add("value_error")  # a raw value beyond the range fits in the signal
    assert expected <= seen, seen
    assert total_lost == rec.lost_frames
    assert len(RX_OUTCOMES) == TIMEOUTS
