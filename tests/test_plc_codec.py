"""The compiled codec is bit-exact against cantools for every message and signal."""

from __future__ import annotations

import math
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from plc_bridge import FrameCodec, load_catalog
from plc_bridge.catalog import MessageSpec, SignalSpec

CAT = load_catalog()
DB = CAT.database
MESSAGES = CAT.messages


def _cantools_encode(spec: MessageSpec, values: list[float], counter: int, crc: int) -> bytes:
    msg = DB.get_message_by_name(spec.name)
    named: dict[str, Any] = dict(zip([s.name for s in spec.signals], values, strict=True))
    named[msg.signals[0].name] = crc
    named[msg.signals[1].name] = counter
    return bytes(msg.encode(named, scaling=True, strict=True))


def _limits(s: SignalSpec) -> list[float]:
    """Minimum, maximum, zero (if inside) and one step above the minimum."""
    pts = [s.minimum, s.maximum, s.raw_min * s.scale + s.scale + s.offset]
    if s.minimum <= 0 <= s.maximum:
        pts.append(0.0)
    return pts


@pytest.mark.parametrize("spec", MESSAGES, ids=lambda m: m.name)
def test_every_signal_at_its_limits_round_trips_bit_exact(spec: MessageSpec) -> None:
    codec = FrameCodec(spec)
    mid = [s.raw_min * s.scale + s.offset for s in spec.signals]
    for k, sig in enumerate(spec.signals):
        for v in _limits(sig):
            values = list(mid)
            values[k] = v
            counter = (k * 3) % 15
            data = codec.encode(counter, values)
            assert len(data) == spec.dlc
            assert codec.check_crc(data) and codec.counter_of(data) == counter
            assert data == _cantools_encode(spec, values, counter, data[0]), (sig.name, v)
            decoded = codec.decode(data)
            ref = DB.decode_message(spec.frame_id, data, decode_choices=False)
            for name, got in zip(codec.signal_names, decoded, strict=True):
                assert got == pytest.approx(ref[name], abs=1e-12), name
            assert decoded[k] == pytest.approx(v, abs=sig.scale / 2 + 1e-12)


@pytest.mark.parametrize("spec", MESSAGES, ids=lambda m: m.name)
def test_out_of_range_is_clipped_and_nan_is_sensor_fault(spec: MessageSpec) -> None:
    codec = FrameCodec(spec)
    high = [s.maximum + 1000 * s.scale for s in spec.signals]
    assert codec.decode(codec.encode(0, high)) == pytest.approx([s.maximum for s in spec.signals])
    nan = codec.decode(codec.encode(0, [math.nan] * len(spec.signals)))
    for s, v in zip(spec.signals, nan, strict=True):
        assert math.isnan(v) if s.sna_raw is not None else v == max(s.minimum, min(0, s.maximum))


@st.composite
def _message_values(draw: st.DrawFn) -> tuple[MessageSpec, list[float], int]:
    spec = draw(st.sampled_from(MESSAGES))
    vals = [
        draw(st.integers(s.raw_min, s.raw_max)) * s.scale + s.offset
        if s.scale != 1
        else float(draw(st.integers(s.raw_min, s.raw_max)))
        for s in spec.signals
    ]
    return spec, vals, draw(st.integers(0, 14))


@settings(max_examples=300, deadline=None)
@given(_message_values())
def test_random_values_bit_exact_against_cantools(
    case: tuple[MessageSpec, list[float], int],
) -> None:
    spec, values, counter = case
    codec = FrameCodec(spec)
    data = codec.encode(counter, values)
    assert data == _cantools_encode(spec, values, counter, data[0])
    raw = DB.decode_message(spec.frame_id, data, decode_choices=False, scaling=False)
    assert codec.decode_raw(data) == [raw[n] for n in codec.signal_names]
    assert codec.encode_raw(counter, codec.decode_raw(data)) == data


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(MESSAGES), st.data())
def test_compiled_codec_is_its_reference_loops(spec: MessageSpec, data: st.DataObject) -> None:
    """The code made per message does what the loops over the same fields do: the same
    bytes (NaN, beyond the range, halfway between raw values), the same values (NaN
    and out-of-range raws included) and the same CRC verdict, for any frame bytes."""
    codec = FrameCodec(spec)
    values = []
    for s in spec.signals:
        values.append(
            data.draw(
                st.one_of(
                    st.floats(allow_infinity=False),
                    st.floats(s.minimum - 3 * s.scale, s.maximum + 3 * s.scale),
                    st.integers(s.raw_min - 2, s.raw_max + 2).map(
                        lambda r, s=s: (r + 0.5) * s.scale + s.offset
                    ),
                )
            )
        )
    counter = data.draw(st.integers(0, 15))

    def outcome(encode: Any) -> Any:
        try:
            return encode()
        except OverflowError:  # a value whose raw value is infinite: both refuse it
            return OverflowError

    assert outcome(lambda: codec.encode(counter, values)) == outcome(
        lambda: codec.encode_raw(counter, codec.to_raw(values))
    )
    frame = data.draw(st.binary(min_size=spec.dlc, max_size=spec.dlc))
    got, ref = codec.decode(frame), codec.decode_reference(frame)
    assert [x if x == x else "nan" for x in got] == [x if x == x else "nan" for x in ref]
    assert all(type(x) is float for x in got)
    from plc_bridge.e2e import crc8_p01

    assert codec.check_crc(frame) == (crc8_p01(spec.data_id, frame[1:]) == frame[0])
