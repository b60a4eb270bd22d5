"""Steering a walk along the design axis (curves.md section 3; docs/curves.md).

Each step turns the machine by the axis's own turn over the step plus a bounded
correction toward the axis. The turn is made by the travel pair's differential: S yaws in
M about the rails' pivot at S's centre by ``psi = asin((e_1 - e_2) / (2 b_T))``
(``walking.travel_half_span_mm``; ``e_1`` the rod with the lower ``can_index``, on the
right at ``y = -b_T``; positive counter-clockwise from above). The step's first travel
turns the lifted frame, its second returns the pair to equal strokes and so turns the
other frame by the same angle:

- forward: phase 1 (S advancing) ``psi: 0 -> +turn``, phase 6 (M advancing) ``+turn -> 0``;
- back: phase 6 (M moving back) ``psi: 0 -> -turn``, phase 1 (S moving back) ``-turn -> 0``.

Where the machine stands against the axis (:class:`OnAxis`): M's centre's chainage, the
machine's heading less the axis's there, and its lateral offset from the axis (both
positive to the left). A step's correction steers the heading error and the offset over
one step toward zero, bounded by ``walking.max_heading_correction_per_step_deg`` (the
placement's steering back is bounded per ring in the same way).

The step's prediction of the errors after it is first order in the angles (they are
below a degree): the offset grows by the distance walked times the heading error after
the turn. A straight axis with the machine on it gives every step a turn of zero: the
plan of a straight walk is the plan without steering.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from config import units
from config.alignment import start_chainage_m
from config.schema import ProjectConfig
from ipc_app.model.placement import axis_pose, chainage_along


@dataclass(frozen=True)
class OnAxis:
    """The machine against the design axis at a walk's start (module docstring)."""

    #: M's centre's chainage, m
    chainage_m: float
    #: the machine's heading less the axis's at ``chainage_m``, rad, positive to the left
    heading_error_rad: float = 0.0
    #: M's centre's offset from the axis, m, positive to the left
    lateral_m: float = 0.0

    def __post_init__(self) -> None:
        for name in ("chainage_m", "heading_error_rad", "lateral_m"):
            v = getattr(self, name)
            if not math.isfinite(v):
                raise ValueError(f"the machine's {name} must be finite, got {v}")

    def to_dict(self) -> dict[str, float]:
        """In the control channel's units (``wara ctl locate``'s): m, deg, mm."""
        return {
            "chainage_m": round(self.chainage_m, 4),
            "heading_error_deg": round(units.to_deg(self.heading_error_rad), 5),
            "lateral_mm": round(units.to_mm(self.lateral_m), 2),
        }


def on_axis_at_start(cfg: ProjectConfig) -> OnAxis:
    """The machine on the axis at ring 1's rear joint face (its commissioning place;
    chainage 0 without an alignment)."""
    return OnAxis(start_chainage_m(cfg.tunnel.alignment))


@dataclass(frozen=True)
class StepTurn:
    """One step's turn: what the axis does and what the machine does."""

    step: int
    #: the axis's heading change from the step's start chainage to its end, rad
    axis_turn_rad: float
    #: the correction toward the axis, rad (bounded)
    correction_rad: float
    #: the machine's heading change: S's yaw in M at the step's first travel's end is
    #: ``+turn_rad`` forward, ``-turn_rad`` back
    turn_rad: float
    #: where the machine stands after the step (predicted)
    after: OnAxis

    def to_dict(self) -> dict[str, Any]:
        return {
            "step": self.step,
            "axis_turn_deg": round(units.to_deg(self.axis_turn_rad), 5),
            "correction_deg": round(units.to_deg(self.correction_rad), 5),
            "turn_deg": round(units.to_deg(self.turn_rad), 5),
            "chainage_after_m": round(self.after.chainage_m, 4),
            "heading_error_after_deg": round(units.to_deg(self.after.heading_error_rad), 5),
            "lateral_after_mm": round(units.to_mm(self.after.lateral_m), 2),
        }


def _stepped(here: OnAxis, chainage_m: float, error_rad: float, along_m: float) -> OnAxis:
    """Where a step of ``along_m`` (signed) ends at ``chainage_m``, walked with the heading
    error ``error_rad``: the offset grows by the distance times its sine."""
    return OnAxis(chainage_m, error_rad, here.lateral_m + along_m * math.sin(error_rad))


def walked(
    cfg: ProjectConfig, start: OnAxis, turns: list[StepTurn], measured: list[float], back: bool
) -> OnAxis:
    """Where the machine stands after the steps of ``turns`` it made, with the turn each
    made as measured (``measured``, rad, one per finished step): the heading error
    grows by what the step turned beyond the axis, the offset by the distance walked
    times it (as :func:`step_turns` predicts), the chainage is the plan's."""
    assert cfg.walking is not None
    s, sign = cfg.walking.step_length_m, -1.0 if back else 1.0
    here = start
    for turn, made in zip(turns, measured, strict=False):
        error = here.heading_error_rad + made - turn.axis_turn_rad
        here = _stepped(here, turn.after.chainage_m, error, sign * s)
    return here


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def step_turns(cfg: ProjectConfig, start: OnAxis, steps: int, direction: str) -> list[StepTurn]:
    """The turn of each of ``steps`` steps of ``direction`` ("forward" or "back")
    from ``start`` (module docstring)."""
    assert cfg.walking is not None
    walk, alignment = cfg.walking, cfg.tunnel.alignment
    s = walk.step_length_m
    sign = -1.0 if direction == "back" else 1.0
    bound = walk.max_heading_correction_per_step_rad
    here = start

    def heading_at(chainage_m: float) -> float:  # a project without an axis: straight
        return 0.0 if alignment is None else axis_pose(alignment, chainage_m).yaw

    heading = heading_at(here.chainage_m)
    out: list[StepTurn] = []
    for k in range(1, steps + 1):
        chainage = (
            here.chainage_m + sign * s
            if alignment is None
            else chainage_along(alignment, here.chainage_m, sign * s)
        )
        heading_next = heading_at(chainage)
        axis_turn = _wrap(heading_next - heading)
        # the heading error after the step that closes the offset over the next step
        want = -sign * here.lateral_m / s
        correction = min(bound, max(-bound, want - here.heading_error_rad)) + 0.0
        after = _stepped(here, chainage, here.heading_error_rad + correction, sign * s)
        out.append(StepTurn(k, axis_turn, correction, axis_turn + correction, after))
        here, heading = after, heading_next
    return out
