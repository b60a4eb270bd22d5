"""Precompiled packers: the DBC compiled at start-up into shift/mask/scale tables.

cantools encodes and decodes from the same DBC in about 5-8 us per frame; the loop
sends and receives a dozen frames per 5 ms cycle, so each message is compiled once
into a :class:`FrameCodec` that does the same arithmetic on one Python integer
(Intel byte order: the payload is ``int.from_bytes(data, "little")``). The rules are
cantools' own: ``raw = round((value - offset) / scale)``, ``value = raw * scale +
offset``; ``tests/test_plc_codec.py`` checks every message bit-exact against cantools.

The compiled form is Python source made per message from its fields (as
``collections.namedtuple`` and ``dataclasses`` make theirs): each signal's shift, mask,
scale and range written into straight-line code, no loop over fields, and the CRC
looked up for all bytes at once (:data:`~plc_bridge.e2e.CRC_SHIFTED`). It runs in
the IPC's plain Python install, faster than loops over the same fields
(:meth:`FrameCodec.to_raw`, :meth:`FrameCodec.encode_raw` and
:meth:`FrameCodec.decode_reference` are those loops: the reference the compiled form is
tested against).

What cantools would reject, the codec makes safe instead of raising in the loop:
a value outside the DBC range is clipped to it (counted by the caller), and NaN is
sent as the signal's SENSOR_FAULT raw value where it has one (else as 0, the neutral
command). On receive, a raw value outside the range or equal to SENSOR_FAULT is
returned as NaN: it is never handed out as a number.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import lru_cache
from typing import Any

from plc_bridge.catalog import MessageSpec
from plc_bridge.e2e import CRC_SHIFTED, CRC_TABLE


class FrameCodec:
    """Encode/decode one message, E2E header included. Built from a :class:`MessageSpec`.

    >>> from plc_bridge.catalog import load_catalog
    >>> codec = FrameCodec(load_catalog().by_name("PLC_RodPos_0"))
    >>> data = codec.encode(3, [123.456, 0.001])
    >>> codec.check_crc(data), codec.counter_of(data), codec.decode(data)
    (True, 3, (123.456, 0.001))
    """

    __slots__ = (
        "_crc0",
        "_enc",
        "_fields",
        "_n",
        "crc_of",
        "data_id",
        "decode_word",
        "dlc",
        "encode",
        "frame_id",
        "name",
        "signal_names",
        "spec",
    )

    #: :meth:`encode`: frame bytes from physical values in DBC units (mm, MPa, deg,
    #: normalized) and the alive counter; NaN as the signal's SENSOR_FAULT raw value
    #: (else the neutral one), a value beyond the range clipped to it
    encode: Callable[[int, Sequence[float]], bytes]
    #: the CRC-8 a frame of this message's length must carry in byte 0 (over the data
    #: id and its bytes 1..DLC-1)
    crc_of: Callable[[bytes | bytearray], int]
    #: the physical values of the frame whose payload is ``word``; NaN for SENSOR_FAULT
    #: and out-of-range raw values (:meth:`decode` of its bytes)
    decode_word: Callable[[int], tuple[float, ...]]

    def __init__(self, spec: MessageSpec) -> None:
        self.spec = spec
        self.name = spec.name
        self.frame_id = spec.frame_id
        self.dlc = spec.dlc
        self.data_id = spec.data_id
        self.signal_names = tuple(s.name for s in spec.signals)
        # (shift, mask, sign_bit, scale, offset, raw_min, raw_max, nan_raw, sna_raw)
        fields = []
        for s in spec.signals:
            mask = (1 << s.length) - 1
            sign_bit = (1 << (s.length - 1)) if s.is_signed else 0
            sna = s.sna_raw
            nan_raw = sna if sna is not None else min(max(0, s.raw_min), s.raw_max)
            fields.append(
                (s.start, mask, sign_bit, s.scale, s.offset, s.raw_min, s.raw_max, nan_raw, sna)
            )
        self._fields = tuple(fields)
        self._n = len(fields)
        # encode loop: (shift, mask, offset, scale, raw_min, raw_max, nan_raw)
        self._enc = tuple((f[0], f[1], f[4], f[3], f[5], f[6], f[7]) for f in fields)
        # CRC state after the two data id bytes: the same for every frame of this id
        self._crc0 = CRC_TABLE[CRC_TABLE[self.data_id & 0xFF] ^ (self.data_id >> 8)]
        self._compile()

    def _compile(self) -> None:
        """Make :attr:`crc_of`, :attr:`decode_word` and :attr:`encode` from the fields
        (the module docstring; made once per layout: links and simulators share them)."""
        self.crc_of, self.decode_word, self.encode = _compiled(
            self.name, self.signal_names, self.dlc, self._crc0, self._fields, self._enc
        )

    # ------------------------------------------------------------------ encode

    def to_raw(self, values: Sequence[float]) -> list[int]:
        """Physical values (DBC units) to raw integers: rounded, clipped, NaN -> SNA."""
        if len(values) != self._n:
            raise ValueError(
                f"{self.name}: expected {self._n} values {self.signal_names}, got {len(values)}"
            )
        raws = []
        for v, (_, _, _, scale, offset, lo, hi, nan_raw, _) in zip(
            values, self._fields, strict=True
        ):
            if v != v:  # NaN
                raws.append(nan_raw)
                continue
            r = round((v - offset) / scale)
            raws.append(lo if r < lo else hi if r > hi else r)
        return raws

    def _finish(self, word: int) -> bytes:
        """The frame of ``word`` (byte 0 still zero) with its CRC in byte 0 (the byte loop
        over :data:`~plc_bridge.e2e.CRC_TABLE`: the reference)."""
        t = CRC_TABLE
        crc = self._crc0
        for b in (word >> 8).to_bytes(self.dlc - 1, "little"):  # bytes 1..DLC-1
            crc = t[crc ^ b]
        return (word | crc).to_bytes(self.dlc, "little")

    def encode_raw(self, counter: int, raws: Sequence[int]) -> bytes:
        """Frame bytes from raw signal values (not range-checked) and the alive counter."""
        word = (counter & 0xF) << 8
        for r, (shift, mask, *_rest) in zip(raws, self._fields, strict=True):
            word |= (r & mask) << shift
        return self._finish(word)

    # ------------------------------------------------------------------ decode

    def check_crc(self, data: bytes | bytearray) -> bool:
        """True if ``data`` has this message's length and a correct CRC-8."""
        if len(data) != self.dlc:
            return False
        return self.crc_of(data) == data[0]

    @staticmethod
    def counter_of(data: bytes | bytearray) -> int:
        return data[1] & 0x0F

    def decode_raw(self, data: bytes | bytearray) -> list[int]:
        """Raw signal values (sign-extended); no CRC or range check."""
        word = int.from_bytes(data, "little")
        out = []
        for shift, mask, sign_bit, *_rest in self._fields:
            r = (word >> shift) & mask
            if sign_bit and r & sign_bit:
                r -= mask + 1
            out.append(r)
        return out

    def decode(self, data: bytes | bytearray) -> tuple[float, ...]:
        """Physical values in DBC units; NaN for SENSOR_FAULT and out-of-range raws."""
        return self.decode_word(int.from_bytes(data, "little"))

    def decode_reference(self, data: bytes | bytearray) -> tuple[float, ...]:
        """:meth:`decode` as a loop over the fields (the compiled form's reference)."""
        word = int.from_bytes(data, "little")
        out = []
        for shift, mask, sign_bit, scale, offset, lo, hi, _, _ in self._fields:
            r = (word >> shift) & mask
            if sign_bit and r & sign_bit:
                r -= mask + 1
            out.append(r * scale + offset if lo <= r <= hi else math.nan)
        return tuple(out)

    def __repr__(self) -> str:
        return f"FrameCodec({self.name}, id=0x{self.frame_id:03X}, dlc={self.dlc})"


@lru_cache(maxsize=256)
def _compiled(
    name: str,
    signal_names: tuple[str, ...],
    dlc: int,
    crc0: int,
    fields: tuple[tuple[Any, ...], ...],
    enc: tuple[tuple[Any, ...], ...],
) -> tuple[Any, Any, Any]:
    """The code of a message (:class:`FrameCodec`'s ``crc_of``, ``decode_word`` and
    ``encode``) made from its fields; the source only formatted numbers."""
    n_body = dlc - 1  # bytes 1..DLC-1 under the CRC
    state = crc0  # the data id's state through the body as zero bytes
    for _ in range(n_body):
        state = CRC_TABLE[state]
    terms = [str(state), *(f"S{n_body - i}[d[{i}]]" for i in range(1, n_body + 1))]
    lines = [f"def crc_of(d):\n    return {' ^ '.join(terms)}\n"]
    # decode: each signal's raw value, sign-extended, scaled where in range
    body = ["def decode_word(w):"]
    outs = []
    for k, (shift, mask, sign, scale, offset, lo, hi, _, _) in enumerate(fields):
        body.append(f"    r{k} = (w >> {shift}) & {mask}")
        if sign:
            body.append(f"    if r{k} & {sign}:\n        r{k} -= {mask + 1}")
        # (+ 0.0 changes no product of a positive scale: -0.0 needs r = 0 and scale < 0)
        plain = offset == 0.0 and scale > 0
        value = f"r{k} * {scale!r}" + ("" if plain else f" + {offset!r}")
        outs.append(f"({value} if {lo} <= r{k} <= {hi} else nan)")
    body.append(f"    return ({', '.join(outs)}{',' if len(outs) == 1 else ''})")
    lines.append("\n".join(body) + "\n")
    # encode: NaN -> its raw value, else round((v - offset) / scale) clipped
    args = ", ".join(f"v{k}" for k in range(len(fields)))
    body = [
        "def encode(counter, values):",
        f"    if len(values) != {len(fields)}:",
        "        raise ValueError(wrong_count + str(len(values)))",
    ]
    if len(fields):
        body.append(f"    {args}{',' if len(fields) == 1 else ''} = values")
    word = ["((counter & 15) << 8)"]
    for k, (shift, mask, offset, scale, lo, hi, nan_raw) in enumerate(enc):
        x = f"(v{k} - {offset!r})" if offset != 0.0 else f"v{k}"
        body += [
            f"    if v{k} != v{k}:\n        r{k} = {nan_raw}",
            f"    else:\n        r{k} = round({x} / {scale!r})",
            f"        if r{k} < {lo}:\n            r{k} = {lo}",
            f"        elif r{k} > {hi}:\n            r{k} = {hi}",
        ]
        word.append(f"((r{k} & {mask}) << {shift})")
    body.append(f"    w = {' | '.join(word)}")
    body.append(f"    crc = crc_of(w.to_bytes({dlc}, 'little'))")
    body.append(f"    return (w | crc).to_bytes({dlc}, 'little')")
    lines.append("\n".join(body) + "\n")
    scope: dict[str, Any] = {f"S{k}": t for k, t in enumerate(CRC_SHIFTED)}
    scope.update(
        nan=math.nan,
        wrong_count=f"{name}: expected {len(fields)} values {signal_names}, got ",
    )
    exec("\n".join(lines), scope)  # the source made above: numbers only
    return scope["crc_of"], scope["decode_word"], scope["encode"]
