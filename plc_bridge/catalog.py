"""The message catalogue, read from ``wara_plc.dbc`` (the single source of truth).

Nothing about ids, layouts, scaling, units, value tables or cycle times is written in
Python: this module reads them from the DBC with cantools and checks the house rules
the codec relies on (E2E header in bytes 0-1, Intel byte order, unique data ids,
integer signals). The result is a small immutable :class:`Catalog` of
:class:`MessageSpec` objects that the codec compiles and the links schedule.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from functools import cached_property, lru_cache
from pathlib import Path
from typing import Any

import cantools

from config import units
from plc_bridge.errors import CatalogError

#: The DBC shipped with the package.
DBC_PATH = Path(__file__).with_name("wara_plc.dbc")

#: Raw value named like this in a value table marks a failed sensor (SNA).
SENSOR_FAULT = "SENSOR_FAULT"

_SLOT = re.compile(r"_(\d{2})$")


@dataclass(frozen=True)
class SignalSpec:
    """One payload signal: its bits, scaling and limits as the DBC gives them."""

    name: str
    start: int
    length: int
    is_signed: bool
    scale: float
    offset: float
    minimum: float
    maximum: float
    unit: str
    choices: dict[int, str] = field(default_factory=dict, compare=False)
    comment: str = ""

    @property
    def raw_min(self) -> int:
        """Smallest valid raw value (the DBC minimum)."""
        return round((self.minimum - self.offset) / self.scale)

    @property
    def raw_max(self) -> int:
        """Largest valid raw value (the DBC maximum)."""
        return round((self.maximum - self.offset) / self.scale)

    @property
    def sna_raw(self) -> int | None:
        """Raw value outside [raw_min, raw_max] that the value table names SENSOR_FAULT.

        (A SENSOR_FAULT entry inside the range, like fault code 7, is an ordinary value.)
        """
        for raw, name in self.choices.items():
            if name == SENSOR_FAULT and not self.raw_min <= raw <= self.raw_max:
                return raw
        return None

    @property
    def slot(self) -> int | None:
        """The cylinder ``can_index`` a per-cylinder signal (``RodPos_07``) belongs to."""
        m = _SLOT.search(self.name)
        return int(m.group(1)) if m else None


@dataclass(frozen=True)
class MessageSpec:
    """One message: id, length, sender, E2E data id, cycle times and payload signals."""

    name: str
    frame_id: int
    dlc: int
    sender: str
    data_id: int
    cycle_s: float
    fast_cycle_s: float | None
    loop_rate: bool
    signals: tuple[SignalSpec, ...]
    comment: str = ""

    @cached_property
    def slots(self) -> tuple[int, ...]:
        """Cylinder ``can_index`` values this message carries (sorted, unique)."""
        return tuple(sorted({s.slot for s in self.signals if s.slot is not None}))

    @property
    def can_be_fast(self) -> bool:
        return self.fast_cycle_s is not None or self.loop_rate

    def cycle_in_force_s(self, active: bool, loop_period_s: float) -> float:
        """The cycle time while its cylinders are (not) in the active group."""
        if not active:
            return self.cycle_s
        if self.loop_rate:
            return loop_period_s
        return self.fast_cycle_s if self.fast_cycle_s is not None else self.cycle_s

    def signal(self, name: str) -> SignalSpec:
        for s in self.signals:
            if s.name == name:
                return s
        raise KeyError(f"message {self.name} (0x{self.frame_id:03X}) has no signal {name!r}")


@dataclass(frozen=True)
class Catalog:
    """All messages of the protocol, by name and by CAN id."""

    path: Path
    messages: tuple[MessageSpec, ...]
    database: Any = field(compare=False, repr=False)  # the cantools Database

    def __post_init__(self) -> None:
        object.__setattr__(self, "_by_name", {m.name: m for m in self.messages})
        object.__setattr__(self, "_by_id", {m.frame_id: m for m in self.messages})

    def by_name(self, name: str) -> MessageSpec:
        try:
            return self._by_name[name]  # type: ignore[attr-defined]
        except KeyError:
            raise KeyError(f"{self.path.name}: no message {name!r}") from None

    def by_id(self, frame_id: int) -> MessageSpec | None:
        return self._by_id.get(frame_id)  # type: ignore[attr-defined]

    def sent_by(self, node: str) -> tuple[MessageSpec, ...]:
        return tuple(m for m in self.messages if m.sender == node)

    def with_prefix(self, prefix: str) -> tuple[MessageSpec, ...]:
        """Messages whose name starts with ``prefix`` (``PLC_RodPos_``), by id."""
        return tuple(
            sorted(
                (m for m in self.messages if m.name.startswith(prefix)), key=lambda m: m.frame_id
            )
        )


def _attr(msg: Any, name: str) -> Any:
    attrs = msg.dbc.attributes if msg.dbc is not None else {}
    a = attrs.get(name)
    return None if a is None else a.value


def _is_yes(value: Any) -> bool:
    return value in (1, "1", "Yes")


def _spec_of(msg: Any, path: Path) -> MessageSpec:
    where = f"{path.name}: message {msg.name} (0x{msg.frame_id:03X})"
    if msg.is_extended_frame or msg.is_fd or msg.length > 8:
        raise CatalogError(f"{where}: must be a classic CAN frame with an 11-bit id")
    if len(msg.senders) != 1:
        raise CatalogError(f"{where}: needs exactly one sender node, has {msg.senders}")
    crc = msg.signals[0] if msg.signals else None
    ctr = msg.signals[1] if len(msg.signals) > 1 else None
    if not (crc and crc.name.endswith("_CRC") and crc.start == 0 and crc.length == 8):
        raise CatalogError(f"{where}: first signal must be the CRC at bit 0, 8 bits")
    if not (ctr and ctr.name.endswith("_Counter") and ctr.start == 8 and ctr.length == 4):
        raise CatalogError(f"{where}: second signal must be the alive counter at bit 8, 4 bits")
    data_id = _attr(msg, "E2EDataID")
    if not data_id:
        raise CatalogError(f"{where}: missing attribute E2EDataID")
    cycle_ms = _attr(msg, "GenMsgCycleTime")
    if not cycle_ms:
        raise CatalogError(f"{where}: missing attribute GenMsgCycleTime")
    fast_ms = _attr(msg, "GenMsgCycleTimeFast") or None
    signals = []
    for s in msg.signals[2:]:
        if s.byte_order != "little_endian" or s.is_float:
            raise CatalogError(f"{where}: signal {s.name} must be an Intel integer signal")
        if s.start < 12 or s.start + s.length > 8 * msg.length:
            raise CatalogError(f"{where}: signal {s.name} overlaps the E2E header or the DLC")
        if s.minimum is None or s.maximum is None:
            raise CatalogError(f"{where}: signal {s.name} needs a [min|max] range")
        signals.append(
            SignalSpec(
                name=s.name,
                start=s.start,
                length=s.length,
                is_signed=s.is_signed,
                scale=float(s.scale),
                offset=float(s.offset),
                minimum=float(s.minimum),
                maximum=float(s.maximum),
                unit=s.unit or "",
                choices={int(k): str(v) for k, v in (s.choices or {}).items()},
                comment=s.comment or "",
            )
        )
    return MessageSpec(
        name=msg.name,
        frame_id=msg.frame_id,
        dlc=msg.length,
        sender=msg.senders[0],
        data_id=int(data_id),
        cycle_s=units.ms(float(cycle_ms)),
        fast_cycle_s=None if fast_ms is None else units.ms(float(fast_ms)),
        loop_rate=_is_yes(_attr(msg, "WaraLoopRate")),
        signals=tuple(signals),
        comment=msg.comment or "",
    )


def load_catalog(path: str | Path | None = None) -> Catalog:
    """Read and check a DBC; ``None`` is the shipped ``wara_plc.dbc`` (cached)."""
    if path is None:
        return _shipped_catalog()
    return _load(Path(path))


@lru_cache(maxsize=1)
def _shipped_catalog() -> Catalog:
    return _load(DBC_PATH)


def _load(path: Path) -> Catalog:
    try:
        db = cantools.database.load_file(str(path), database_format="dbc", strict=True)
    except FileNotFoundError:
        raise CatalogError(f"{path}: file not found") from None
    except Exception as exc:  # cantools raises several parser error types
        raise CatalogError(f"{path}: not a valid DBC: {exc}") from None
    messages: list[Any] = list(getattr(db, "messages", []))
    specs = tuple(_spec_of(m, path) for m in sorted(messages, key=lambda m: m.frame_id))
    seen: dict[int, str] = {}
    for m in specs:
        if m.data_id in seen:
            raise CatalogError(
                f"{path.name}: E2EDataID 0x{m.data_id:04X} of {m.name} is also used by "
                f"{seen[m.data_id]}; every message needs its own data id"
            )
        seen[m.data_id] = m.name
    return Catalog(path=path, messages=specs, database=db)
