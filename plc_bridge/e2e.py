"""End-to-end protection of every frame, modelled on AUTOSAR E2E Profile 1 (P01).

Layout of every message of ``wara_plc.dbc`` (Intel byte order):

- byte 0: CRC-8;
- byte 1, bits 0-3: alive counter 0..14 (15 is never sent, as in P01);
- the rest: payload signals.

CRC: polynomial 0x1D (CRC-8 SAE J1850), start value 0x00, no final XOR, no
reflection (P01's parameters), computed over the 16-bit data id of the message in
P01 "DATAID_BOTH" mode (low byte, then high byte) followed by bytes 1..DLC-1 of the
frame. The data id of each message is the DBC message attribute ``E2EDataID``
(``0xA000 | CAN id``), so a frame that lands under the wrong id, or a frame of the
same layout from a neighbouring id, fails the CRC.

Receiver (P01 ``MaxDeltaCounter``): with ``delta = (counter - last) mod 15``,
``delta == 0`` is a repeated frame (counter stuck), ``1 <= delta <= max_delta`` is
accepted (``delta - 1`` frames were lost), anything else is a wrong sequence: the
frame is rejected and the receiver re-synchronises on it. After start or after a
timeout the first frame only synchronises; data is delivered from the second
consecutive frame on.

Check value for the PLC programmer: ``crc8_p01(0xA080, bytes.fromhex("0102030405"))``
is ``0xAC``; over ``b"123456789"`` alone (start 0x00) the CRC is ``0x37``
(the catalogue name of these parameters is CRC-8/GSM-A). Both are checked in
``tests/test_plc_e2e.py``.
"""

from __future__ import annotations

from enum import Enum

COUNTER_MODULO = 15  #: counter values 0..14
CRC_POLY = 0x1D


def _make_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


CRC_TABLE: tuple[int, ...] = _make_table()


def _shifted_tables() -> tuple[tuple[int, ...], ...]:
    table = [CRC_TABLE]  # [k][b]: the CRC of byte b followed by k zero bytes, from 0
    for _ in range(7):
        table.append(tuple(CRC_TABLE[x] for x in table[-1]))
    return tuple(table)


#: The CRC byte by byte without a loop: ``CRC_SHIFTED[k][b]`` is what byte ``b``
#: followed by ``k`` more bytes (k = 0..7) adds to the CRC of a frame. The CRC has no
#: final XOR and no reflection, so it is linear: over bytes ``b_1..b_L`` from the state
#: ``s`` it is ``F^L(s)`` (``s`` through ``L`` zero bytes) XOR, for each byte, the CRC
#: of that byte alone followed by its successors as zeros; the lookups do not wait on
#: each other as the loop's do (:class:`~plc_bridge.codec.FrameCodec`;
#: ``tests/test_plc_e2e.py`` checks it against the bitwise definition).
CRC_SHIFTED: tuple[tuple[int, ...], ...] = _shifted_tables()


def crc8_p01(data_id: int, body: bytes | bytearray | memoryview) -> int:
    """CRC-8 over the data id (low, high byte) and ``body`` (frame bytes 1..DLC-1)."""
    t = CRC_TABLE
    crc = t[data_id & 0xFF]
    crc = t[crc ^ ((data_id >> 8) & 0xFF)]
    for b in body:
        crc = t[crc ^ b]
    return crc


def crc8_bitwise(data: bytes) -> int:
    """Reference bit-by-bit CRC-8 (poly 0x1D, start 0, no xor): for tests and PLC ports."""
    crc = 0
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return crc


class CounterCheck(Enum):
    """Result of the alive-counter check of one frame (P01 receiver states)."""

    OK = "ok"  #: next value, or next after at most max_delta - 1 lost frames
    INITIAL = "initial"  #: first frame after start or timeout: synchronises only
    REPEATED = "repeated"  #: same counter as the last frame: sender stuck or duplicate
    WRONG_SEQUENCE = "wrong_sequence"  #: jumped by more than max_delta: rejected, re-synced
    INVALID = "invalid"  #: counter value 15, which is never sent


def check_counter(last: int | None, counter: int, max_delta: int) -> tuple[CounterCheck, int]:
    """Classify ``counter`` against the ``last`` accepted one; returns (result, lost frames)."""
    if counter >= COUNTER_MODULO:
        return CounterCheck.INVALID, 0
    if last is None:
        return CounterCheck.INITIAL, 0
    delta = (counter - last) % COUNTER_MODULO
    if delta == 0:
        return CounterCheck.REPEATED, 0
    if delta <= max_delta:
        return CounterCheck.OK, delta - 1
    return CounterCheck.WRONG_SEQUENCE, 0
