"""A transfer's force ramp in time (docs/walking.md, "The force loop").

The receiving legs' forces move along the plan's line from where they start to their
target; :class:`ForceRamp` says how far along it they are at a time. The rate is
``walking.force_ramp_kn_s`` (the largest change of any leg sets the line's duration at
that rate), reached and left in a blend: it rises linearly from zero over
:func:`blend_s` and falls to zero over the same at the end, so the ramp takes one blend
longer than at full rate throughout.

Why a blend: the releasing legs hold the body in position control while the receiving
legs' force references ramp. A rate that starts at once is a step in the force the
releasing loops must take off their legs, and their observers learn it only within
their bandwidth: the body swung in pitch, some 1.2 s a period, and the swing at the
start of 7c was most of the transfer's attitude change (docs/decisions/0026). A blend of
one period of the slowest releasing loop's crossover changes the rate no faster than
that loop follows.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from config.schema import ProjectConfig

#: the leg groups whose position loops hold the body while the other frame's legs ramp
LEG_ROLES = ("main_leg", "sub_leg")
#: the phases whose ramps are blended: the transfers (4, 7c), where the whole load moves
#: between the frames; a preload moves a fifth of a share in a second (not blended: with
#: every ramp blended the HFDU example's unloaded walk back met its 7a touch-down at
#: 110.2 % of the overload limit's share, 107.7 % with the transfers only; docs/decisions/0026)
TRANSFER_KEYS = frozenset({"4", "7c"})


def blend_s(cfg: ProjectConfig) -> float:
    """The rate's blend at each end of a force ramp, s: one period of the slowest leg
    group's position-loop crossover (``2 pi / wc``; ``control.ladrc`` or derived)."""
    from ipc_app.control.tuning import position_bandwidths

    wc = min(position_bandwidths(cfg, c)[0] for c in cfg.cylinders if c.role in LEG_ROLES)
    return 2.0 * math.pi / wc


@dataclass(frozen=True)
class ForceRamp:
    """A ramp along its line: ``linear_s`` at full rate, blended over ``blend_s`` at each
    end (no longer than ``linear_s``: a short ramp is blended over its whole length)."""

    linear_s: float
    blend_s: float

    @classmethod
    def of(cls, linear_s: float, blend: float) -> ForceRamp:
        return cls(linear_s, max(0.0, min(blend, linear_s)))

    @property
    def duration_s(self) -> float:
        return self.linear_s + self.blend_s

    def fraction(self, t_s: float) -> float:
        """How far along the line at ``t_s`` from the ramp's start, 0 to 1."""
        ln, b, end = self.linear_s, self.blend_s, self.duration_s
        if ln <= 0.0 or t_s >= end:
            return 1.0
        if t_s <= 0.0:
            return 0.0
        if b <= 0.0:
            return t_s / ln
        if t_s < b:
            return t_s * t_s / (2.0 * b * ln)
        if t_s <= end - b:
            return (t_s - b / 2.0) / ln
        return 1.0 - (end - t_s) ** 2 / (2.0 * b * ln)

    def rate_share(self, t_s: float) -> float:
        """The rate at ``t_s`` as a share of the full rate, 0 to 1."""
        ln, b, end = self.linear_s, self.blend_s, self.duration_s
        if ln <= 0.0 or t_s >= end or t_s < 0.0:
            return 0.0
        if b <= 0.0:
            return 1.0
        share = 1.0  # divided only where below 1: a tiny blend's quotient would overflow
        if t_s < b:
            share = t_s / b
        if end - t_s < b:
            share = min(share, (end - t_s) / b)
        return share
