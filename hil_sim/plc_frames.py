"""The emulated PLC's frame path, compiled: encode, decode and the E2E receive checks
over tables generated from ``plc_bridge``'s codecs.

``plc_bridge`` is the one implementation of the protocol (:class:`~plc_bridge.codec.
FrameCodec` compiled from the DBC, :class:`~plc_bridge.supervision.RxRecord`'s checks);
the simulator's compiled scan (:mod:`hil_sim.plc_fast`) needs the same arithmetic in
machine code. So nothing here is written per message: :class:`FrameTables` copies each
codec's compiled fields (shift, mask, sign bit, scale, offset, raw range, the raw value
sent for NaN, the CRC state after the data id) and a record's counter-check table into
NumPy arrays, and the functions below do what ``FrameCodec.encode`` / ``decode`` /
``check_crc`` and ``RxRecord.on_frame`` do, on those arrays. ``tests/test_plc_frames.py``
checks them frame for frame against the codec and the record over every message of the
DBC, with counters, CRCs, lengths and values broken on purpose.

Without numba these run as plain Python (slowly); the simulator then keeps its Python
scan (:mod:`hil_sim.simulator`), which uses ``plc_bridge`` directly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

from hil_sim._jit import jit
from plc_bridge.codec import FrameCodec
from plc_bridge.e2e import CRC_TABLE, CounterCheck
from plc_bridge.supervision import RX_OUTCOMES, RxRecord

IntArray = NDArray[np.int64]
FloatArray = NDArray[np.float64]

#: RX_OUTCOMES by index (checked below: the compiled code uses the numbers)
ACCEPTED, INITIAL, CRC_ERROR, LENGTH_ERROR = 0, 1, 2, 3
COUNTER_REPEATED, COUNTER_WRONG_SEQUENCE, COUNTER_INVALID, VALUE_ERROR = 4, 5, 6, 7
UNKNOWN_ID, OWN_ECHO, NOT_CLASSIC, ERROR_FRAME = 8, 9, 10, 11
#: a record's counter of timeouts, after the outcomes
TIMEOUTS = len(RX_OUTCOMES)
_NAMED = {
    "accepted": ACCEPTED,
    "initial": INITIAL,
    "crc_error": CRC_ERROR,
    "length_error": LENGTH_ERROR,
    "counter_repeated": COUNTER_REPEATED,
    "counter_wrong_sequence": COUNTER_WRONG_SEQUENCE,
    "counter_invalid": COUNTER_INVALID,
    "value_error": VALUE_ERROR,
    "unknown_id": UNKNOWN_ID,
    "own_echo": OWN_ECHO,
    "not_classic": NOT_CLASSIC,
    "error_frame": ERROR_FRAME,
}
if {RX_OUTCOMES[i]: i for i in range(len(RX_OUTCOMES))} != _NAMED:  # pragma: no cover
    raise ImportError("hil_sim.plc_frames: plc_bridge's RX_OUTCOMES changed; renumber them here")

#: CounterCheck results by number (the counter table's first column)
CHECK_OK, CHECK_INITIAL, CHECK_REPEATED, CHECK_WRONG, CHECK_INVALID = 0, 1, 2, 3, 4
_CHECKS = {
    CounterCheck.OK: CHECK_OK,
    CounterCheck.INITIAL: CHECK_INITIAL,
    CounterCheck.REPEATED: CHECK_REPEATED,
    CounterCheck.WRONG_SEQUENCE: CHECK_WRONG,
    CounterCheck.INVALID: CHECK_INVALID,
}

#: columns of :attr:`FrameTables.fields_i` (per message, per field)
F_SHIFT, F_MASK, F_SIGN, F_LO, F_HI, F_NAN_RAW, F_NAN_OK = 0, 1, 2, 3, 4, 5, 6
#: columns of :attr:`FrameTables.fields_f`
F_SCALE, F_OFFSET = 0, 1
#: columns of :attr:`FrameTables.msg`
M_ID, M_DLC, M_CRC0, M_NF, M_NAN_CHECKED = 0, 1, 2, 3, 4

#: what :func:`encode_frame` returns for a value that Python's ``round`` refuses (inf)
ENCODE_OVERFLOW = -1

CRC = np.array(CRC_TABLE, dtype=np.int64)


class FrameTables:
    """The compiled fields of a list of codecs, as arrays (row ``m``: ``codecs[m]``)."""

    def __init__(self, codecs: Sequence[FrameCodec]) -> None:
        self.codecs = tuple(codecs)
        n = len(self.codecs)
        width = max((len(c.signal_names) for c in self.codecs), default=0)
        self.msg: IntArray = np.zeros((n, 5), dtype=np.int64)
        self.fields_i: IntArray = np.zeros((n, max(width, 1), 7), dtype=np.int64)
        self.fields_f: FloatArray = np.zeros((n, max(width, 1), 2))
        for m, codec in enumerate(self.codecs):
            # the codec's own compiled layout: one source for both
            fields = codec._fields  # (shift, mask, sign_bit, scale, offset, lo, hi, nan_raw, sna)
            self.msg[m] = (codec.frame_id, codec.dlc, codec._crc0, len(fields), 0)
            nan_ok = [s.sna_raw is not None for s in codec.spec.signals]
            self.msg[m, M_NAN_CHECKED] = int(not all(nan_ok))
            for f, (shift, mask, sign, scale, offset, lo, hi, nan_raw, _) in enumerate(fields):
                self.fields_i[m, f] = (shift, mask, sign, lo, hi, nan_raw, int(nan_ok[f]))
                self.fields_f[m, f] = (scale, offset)


def counter_table(rec: RxRecord) -> IntArray:
    """``rec``'s counter checks as an array: row ``(last or 15) * 16 + counter`` is
    ``(CounterCheck number, frames lost)``."""
    return np.array([(_CHECKS[c], lost) for c, lost in rec._counter_checks], dtype=np.int64)


@jit
def encode_frame(
    msg: IntArray,
    fields_i: IntArray,
    fields_f: FloatArray,
    m: int,
    counter: int,
    values: FloatArray,
    out: NDArray[np.uint8],
) -> int:
    """``FrameCodec.encode(counter, values)`` of message ``m`` into ``out[:dlc]``;
    returns the DLC, or :data:`ENCODE_OVERFLOW` for an infinite value (Python's
    ``round`` raises there)."""
    word = np.uint64((counter & 0xF) << 8)
    for f in range(msg[m, M_NF]):
        v = values[f]
        if v != v:  # NaN
            r = fields_i[m, f, F_NAN_RAW]
        else:
            x = (v - fields_f[m, f, F_OFFSET]) / fields_f[m, f, F_SCALE]
            if x == math.inf or x == -math.inf:
                return ENCODE_OVERFLOW
            lo = fields_i[m, f, F_LO]
            hi = fields_i[m, f, F_HI]
            # round(x) clipped to [lo, hi]: at or beyond a bound, round(x) is too
            if x <= lo:
                r = lo
            elif x >= hi:
                r = hi
            else:
                r = round(x)
        word |= np.uint64(r & fields_i[m, f, F_MASK]) << np.uint64(fields_i[m, f, F_SHIFT])
    dlc = msg[m, M_DLC]
    crc = msg[m, M_CRC0]
    for b in range(1, dlc):
        byte = (word >> np.uint64(8 * b)) & np.uint64(0xFF)
        out[b] = byte
        crc = CRC[crc ^ np.int64(byte)]
    out[0] = crc
    return dlc


@jit
def crc_ok(msg: IntArray, m: int, data: NDArray[np.uint8], n: int) -> bool:
    """``FrameCodec.check_crc`` of ``data[:n]`` for message ``m``."""
    if n != msg[m, M_DLC]:
        return False
    crc = msg[m, M_CRC0]
    for b in range(1, n):
        crc = CRC[crc ^ np.int64(data[b])]
    return crc == data[0]


@jit
def decode_frame(
    msg: IntArray,
    fields_i: IntArray,
    fields_f: FloatArray,
    m: int,
    data: NDArray[np.uint8],
    n: int,
    values: FloatArray,
) -> None:
    """``FrameCodec.decode(data[:n])`` of message ``m`` into ``values[:fields]``."""
    word = np.uint64(0)
    for b in range(n):
        word |= np.uint64(data[b]) << np.uint64(8 * b)
    for f in range(msg[m, M_NF]):
        mask = fields_i[m, f, F_MASK]
        r = np.int64((word >> np.uint64(fields_i[m, f, F_SHIFT])) & np.uint64(mask))
        sign = fields_i[m, f, F_SIGN]
        if sign and r & sign:
            r -= mask + 1
        if fields_i[m, f, F_LO] <= r <= fields_i[m, f, F_HI]:
            values[f] = r * fields_f[m, f, F_SCALE] + fields_f[m, f, F_OFFSET]
        else:
            values[f] = math.nan


@jit
def check_frame(
    msg: IntArray,
    fields_i: IntArray,
    fields_f: FloatArray,
    counters: IntArray,
    m: int,
    data: NDArray[np.uint8],
    n: int,
    state: IntArray,
    values: FloatArray,
    scratch: FloatArray,
) -> tuple[int, int]:
    """``RxRecord.on_frame``'s checks of one frame ``data[:n]`` of message ``m``:
    ``(outcome number, frames lost)``. ``state[0]``: the last accepted counter (-1:
    none), updated as the record updates it; on ``accepted`` the values are in
    ``values`` (``scratch``: room for the decode). The caller counts the outcome and
    keeps the time and the lost frames."""
    if n != msg[m, M_DLC]:
        return LENGTH_ERROR, 0
    if not crc_ok(msg, m, data, n):
        return CRC_ERROR, 0
    counter = np.int64(data[1] & 0x0F)
    last = state[0]
    row = (15 if last < 0 else last) * 16 + counter
    result = counters[row, 0]
    lost = counters[row, 1]
    if result == CHECK_OK:
        decode_frame(msg, fields_i, fields_f, m, data, n, scratch)
        nf = msg[m, M_NF]
        bad = False
        if msg[m, M_NAN_CHECKED]:
            for f in range(nf):
                if scratch[f] != scratch[f] and not fields_i[m, f, F_NAN_OK]:
                    bad = True
                    break
        state[0] = counter
        if bad:
            return VALUE_ERROR, 0
        for f in range(nf):
            values[f] = scratch[f]
        return ACCEPTED, lost
    if result == CHECK_INITIAL:
        state[0] = counter
        return INITIAL, 0
    if result == CHECK_REPEATED:
        return COUNTER_REPEATED, 0
    if result == CHECK_WRONG:
        state[0] = counter  # re-synchronise on it
        return COUNTER_WRONG_SEQUENCE, 0
    return COUNTER_INVALID, 0
