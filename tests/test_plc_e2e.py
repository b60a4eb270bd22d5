"""E2E profile: CRC-8 check values, table vs bitwise, counter classification."""

from __future__ import annotations

from hypothesis import given
from hypothesis import strategies as st

from plc_bridge.e2e import CounterCheck, check_counter, crc8_bitwise, crc8_p01


def test_crc_check_values_for_the_plc_programmer() -> None:
    assert crc8_bitwise(b"123456789") == 0x37  # CRC-8/GSM-A catalogue check value
    assert crc8_p01(0xA080, bytes.fromhex("0102030405")) == 0xAC


@given(st.integers(0, 0xFFFF), st.binary(max_size=7))
def test_table_crc_equals_bitwise(data_id: int, body: bytes) -> None:
    assert crc8_p01(data_id, body) == crc8_bitwise(bytes([data_id & 0xFF, data_id >> 8]) + body)


def test_counter_rules() -> None:
    assert check_counter(None, 5, 2) == (CounterCheck.INITIAL, 0)
    assert check_counter(5, 6, 2) == (CounterCheck.OK, 0)
    assert check_counter(5, 7, 2) == (CounterCheck.OK, 1)
    assert check_counter(14, 0, 2) == (CounterCheck.OK, 0)  # wraps 14 -> 0
    assert check_counter(5, 5, 2) == (CounterCheck.REPEATED, 0)
    assert check_counter(5, 8, 2) == (CounterCheck.WRONG_SEQUENCE, 0)
    assert check_counter(5, 4, 2) == (CounterCheck.WRONG_SEQUENCE, 0)
    assert check_counter(5, 15, 2) == (CounterCheck.INVALID, 0)


@given(st.integers(0, 0xFF), st.binary(min_size=1, max_size=7))
def test_shifted_tables_are_the_crc(state: int, body: bytes) -> None:
    """CRC_SHIFTED: the CRC as the state run through zero bytes XOR each byte's own
    shifted contribution (what the codec's compiled CRC sums up)."""
    from plc_bridge.e2e import CRC_SHIFTED, CRC_TABLE

    crc = state
    for b in body:
        crc = CRC_TABLE[crc ^ b]
    lin = state
    for _ in body:
        lin = CRC_TABLE[lin]
    for i, b in enumerate(body):
        lin ^= CRC_SHIFTED[len(body) - 1 - i][b]
    assert lin == crc
