"""The walk's figures: :class:`WalkFigures`, one cycle's (what the walk interlocks
judge), and :class:`StepFigures`, one step's extremes (``wara walk``, the run record)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from config import units


@dataclass
class WalkFigures:
    """One cycle of the walk, what the walk interlocks judge (SI units)."""

    step: int = 0
    phase: str = ""
    #: the phase's reference clock (stops while a group is out of its band)
    phase_t_s: float = 0.0
    leg_force_n: tuple[float, ...] = ()
    #: expected force of each leg now (the plan's, at least its eight-leg share)
    expected_n: tuple[float, ...] = ()
    #: the seal friction each leg's force may carry that its motion does not tell, N
    #: (:attr:`~ipc_app.control.walk.forces.RodFriction.unknown_n`; empty: none)
    friction_unknown_n: tuple[float, ...] = ()
    #: largest |sync error| of the moving leg group / the travel pair (0: not moving)
    leg_sync_m: float = 0.0
    travel_sync_m: float = 0.0
    #: the group out of its band now, and for how long
    out_of_band: str = ""
    out_of_band_s: float = 0.0
    margin_m: float = math.inf
    #: least margin along the present phase's commanded motion (checked at its start)
    margin_ahead_m: float = math.inf
    travel_force_n: float = 0.0
    friction_capacity_n: float = math.inf
    #: a leg whose lowering ended without a touch-down (its id), else ""
    no_touchdown: str = ""
    #: a lowering leg whose foot met the invert above the touch-down window (in the fast
    #: part of its lowering: more than ``touchdown_travel_mm`` above the expected ground):
    #: its id and its height above the expected ground then, m; else ("", 0.0)
    obstacle: tuple[str, float] = ("", 0.0)
    #: preload/transfer still not done after this long (0 while in time)
    overdue_s: float = 0.0
    #: the worst receiving leg's share at a transfer's end (id, ratio), else ("", 1.0)
    share_off: tuple[str, float] = ("", 1.0)

    def force_ratios(self) -> list[float]:
        """Each leg's force over its expected share, the overload's figure: the force
        less the seal friction it may carry unseen (a leg is judged overloaded only
        when its load certainly is; docs/walking.md)."""
        unknown = self.friction_unknown_n or (0.0,) * len(self.leg_force_n)
        return [
            (f - u) / e for f, u, e in zip(self.leg_force_n, unknown, self.expected_n, strict=True)
        ]


@dataclass
class StepFigures:
    """The service's figures of one step (for ``wara walk`` and the run record)."""

    index: int
    started_s: float = 0.0
    duration_s: float = 0.0
    max_leg_sync_error_m: float = 0.0
    max_travel_sync_error_m: float = 0.0
    min_stability_margin_m: float = math.inf
    max_leg_force_ratio: float = 0.0
    transfer_time_s: float = 0.0
    #: the machine's heading change this step, measured: S's yaw in M from the travel
    #: rods at the end of the step's first travel (curves.md section 3), rad
    turn_rad: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "turn_deg": None if self.turn_rad is None else round(units.to_deg(self.turn_rad), 5),
            "duration_s": round(self.duration_s, 3),
            "max_leg_sync_error_mm": round(units.to_mm(self.max_leg_sync_error_m), 4),
            "max_travel_sync_error_mm": round(units.to_mm(self.max_travel_sync_error_m), 4),
            "min_stability_margin_m": round(self.min_stability_margin_m, 4),
            "max_leg_force_ratio": round(self.max_leg_force_ratio, 4),
            "transfer_time_s": round(self.transfer_time_s, 3),
        }

    def take(self, fig: WalkFigures) -> None:
        """One cycle's figures into the step's extremes."""
        self.max_leg_sync_error_m = max(self.max_leg_sync_error_m, fig.leg_sync_m)
        self.max_travel_sync_error_m = max(self.max_travel_sync_error_m, fig.travel_sync_m)
        self.min_stability_margin_m = min(self.min_stability_margin_m, fig.margin_m)
        self.max_leg_force_ratio = max(self.max_leg_force_ratio, max(fig.force_ratios()))
