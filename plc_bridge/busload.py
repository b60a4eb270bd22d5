"""Bus load from the DBC and the configured rates, with worst-case bit stuffing.

A classic CAN data frame with an 11-bit id and ``n`` data bytes is
``8n + 47`` bits (SOF, id, control, data, CRC, delimiters, ACK, EOF and the
3-bit intermission), of which the ``34 + 8n`` bits from SOF to the CRC are subject
to stuffing; in the worst case one stuff bit follows every four of them after the
first (Davis, Burns, Bril, Lukkien 2007):

    bits(n) = 8n + 47 + floor((34 + 8n - 1) / 4)          # 135 bits for n = 8

Rates: each message runs at ``GenMsgCycleTime`` from the DBC, except those carrying
a cylinder of the active group, which run at their fast cycle: the control loop
period (``control.loop_rate_hz``) for ``WaraLoopRate`` messages (valve commands, rod
positions), ``GenMsgCycleTimeFast`` for the others (pressures).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import asdict, dataclass
from typing import Any

from config import crosscheck, units
from config.schema import ProjectConfig
from plc_bridge.catalog import Catalog, MessageSpec, load_catalog


def frame_bits(dlc: int, extended: bool = False) -> int:
    """Worst-case length in bits of a classic CAN data frame, intermission included."""
    if not 0 <= dlc <= 8:
        raise ValueError(f"classic CAN frames carry 0..8 data bytes, not {dlc}")
    g = 54 if extended else 34
    return 8 * dlc + g + 13 + (g + 8 * dlc - 1) // 4


@dataclass(frozen=True)
class MessageLoad:
    name: str
    frame_id: str
    sender: str
    dlc: int
    bits_per_frame: int
    active: bool
    cycle_ms: float
    frames_per_s: float
    bits_per_s: float
    load_percent: float


@dataclass(frozen=True)
class BusLoad:
    """Result of :func:`bus_load`; ``as_dict()`` is what ``wara can busload --json`` prints."""

    bitrate: int
    loop_rate_hz: float
    active_cylinders: tuple[int, ...]
    frames_per_s: float
    bits_per_s: float
    load_percent: float
    max_load_percent: float
    messages: tuple[MessageLoad, ...]

    @property
    def ok(self) -> bool:
        return self.load_percent <= self.max_load_percent

    def as_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["active_cylinders"] = list(self.active_cylinders)
        d["ok"] = self.ok
        d["messages"] = [asdict(m) for m in self.messages]
        return d


def is_active(spec: MessageSpec, active: frozenset[int]) -> bool:
    """A message runs fast when it carries at least one cylinder of the active group."""
    return spec.can_be_fast and any(i in active for i in spec.slots)


def active_cylinders(cfg: ProjectConfig) -> tuple[int, ...]:
    """``can_index`` of the cylinders in ``can.active_groups`` (the default active group)."""
    groups = set(cfg.can.active_groups)
    return tuple(sorted(c.can_index for c in cfg.cylinders if c.group in groups))


def bus_load(
    cfg: ProjectConfig,
    active: Iterable[int] | None = None,
    catalog: Catalog | None = None,
) -> BusLoad:
    """Bus load of the whole protocol for ``active`` (default: the config's active group)."""
    cat = catalog if catalog is not None else load_catalog()
    act = frozenset(active_cylinders(cfg) if active is None else active)
    period = cfg.control.period_s
    bitrate = cfg.can.bitrate
    rows = []
    for m in cat.messages:
        on = is_active(m, act)
        cycle = m.cycle_in_force_s(on, period)
        bits = frame_bits(m.dlc)
        fps = 1.0 / cycle
        rows.append(
            MessageLoad(
                name=m.name,
                frame_id=f"0x{m.frame_id:03X}",
                sender=m.sender,
                dlc=m.dlc,
                bits_per_frame=bits,
                active=on,
                cycle_ms=round(units.to_ms(cycle), 6),
                frames_per_s=round(fps, 6),
                bits_per_s=round(fps * bits, 3),
                load_percent=round(100.0 * fps * bits / bitrate, 4),
            )
        )
    fps_total = sum(1.0 / m.cycle_in_force_s(is_active(m, act), period) for m in cat.messages)
    bps_total = sum(r.frames_per_s * r.bits_per_frame for r in rows)
    return BusLoad(
        bitrate=bitrate,
        loop_rate_hz=cfg.control.loop_rate_hz,
        active_cylinders=tuple(sorted(act)),
        frames_per_s=round(fps_total, 3),
        bits_per_s=round(bps_total, 3),
        load_percent=round(100.0 * bps_total / bitrate, 3),
        max_load_percent=cfg.can.max_bus_load_percent,
        messages=tuple(rows),
    )


@crosscheck.provide("bus-load-within-budget", __name__)
def check_bus_load(cfg: ProjectConfig) -> str | None:
    """The cross-check of the configured bus load (config.crosscheck): the DBC's messages
    with ``can.active_groups`` at the loop rate within ``can.max_bus_load_percent``."""
    load = bus_load(cfg)
    if load.ok:
        return None
    return (
        f"can.max_bus_load_percent: {load.max_load_percent:g} % is exceeded: the "
        f"messages load the bus to {load.load_percent:.1f} % (control.loop_rate_hz "
        f"{cfg.control.loop_rate_hz:g} Hz, can.bitrate {cfg.can.bitrate} bit/s, "
        f"can.active_groups {list(cfg.can.active_groups)}; `wara can busload`); expected "
        f"at most {load.max_load_percent:g} %: a lower loop rate, or at this one a bitrate "
        f"of at least {math.ceil(load.bits_per_s * 100.0 / load.max_load_percent)} bit/s"
    )
