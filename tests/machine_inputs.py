"""One cycle's :class:`MachineInputs` built by hand: a healthy machine at mid-stroke
(every value valid and fresh, the PLC status without fault), with what a test changes."""

from __future__ import annotations

from typing import Any

import numpy as np

from config import ProjectConfig
from ipc_app.service.machine_io import MachineInputs
from plc_bridge.link import PlcStatus, Reading
from plc_bridge.supervision import LinkState

HEALTHY = PlcStatus(pump_running=True, drives_enabled=True)


def reading(value: np.ndarray, age_s: float = 0.005) -> Reading:
    """Values with NaN where not valid, every valid one ``age_s`` old."""
    valid = ~np.isnan(value)
    return Reading(value=value, valid=valid, age_s=np.where(valid, age_s, np.inf))


def machine_inputs(
    cfg: ProjectConfig,
    *,
    x: np.ndarray | None = None,
    p: np.ndarray | None = None,
    active: tuple[int, ...] | None = None,
    **changes: Any,
) -> MachineInputs:
    """``x`` rod positions [m] and ``p`` pressures [Pa] by can_index (NaN: not valid);
    ``changes`` any other field of :class:`MachineInputs`."""
    n = len(cfg.cylinders)
    if x is None:
        x = np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])
    if p is None:
        p = np.full((n, 2), 10e6)
    pos = changes.pop("positions", None) or reading(x)
    if active is None:
        active = tuple(cfg.cylinder(c).can_index for c in cfg.layers.lower.cylinders) + tuple(
            cfg.cylinder(c).can_index for c in cfg.layers.upper.cylinders
        )
    fields: dict[str, Any] = dict(
        t=1.0,
        positions=pos,
        pressures=reading(p),
        positions_valid=bool(pos.valid[list(active)].all()),
        failed_sensors=frozenset(),
        status=HEALTHY,
        status_age_s=0.005,
        status_stale=False,
        bus_ok=True,
        at_limit=None,
        hmi=None,
        link_state=LinkState.OK,
    )
    fields.update(changes)
    return MachineInputs(**fields)
