"""The reference machine's Examples 1-3 and the judge of an example's result (the
attitude goals of :mod:`wara.goals`), used by both forms of the demo (one process:
:mod:`wara.demo`; two processes: :mod:`wara.demo_two_process`), the campaigns and the
harness's users (tests, studies)."""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from wara.goals import ATTITUDE_GOALS, ATTITUDE_TOL_DEG, SYNC_TOL_MM, TWIST_TOL_MM, judge

EXAMPLES: tuple[tuple[float, float], ...] = ((2.0, 1.0), (-3.0, 2.0), (5.0, -1.0))

__all__ = [
    "ATTITUDE_TOL_DEG",
    "EXAMPLES",
    "HOLD_MEASURE_S",
    "SYNC_TOL_MM",
    "TWIST_TOL_MM",
    "ExampleResult",
    "judge_example",
]

#: Standstill after the motion over which the sync error at standstill is taken.
HOLD_MEASURE_S = 3.0


@dataclass
class ExampleResult:
    target_roll_deg: float
    target_pitch_deg: float
    achieved_roll_deg: float = math.nan
    achieved_pitch_deg: float = math.nan
    attitude_error_deg: float = math.nan
    max_twist_mm: float = math.nan
    sync_error_mm: float = math.nan
    #: largest sync error of either group during the motion (controller view)
    max_sync_error_mm: float = math.nan
    duration_s: float = math.nan
    passed: bool = False
    note: str = ""

    def figures(self) -> dict[str, float]:
        """The figures the attitude goals limit."""
        return {
            "attitude_error_deg": self.attitude_error_deg,
            "max_twist_mm": self.max_twist_mm,
            "sync_error_mm": self.sync_error_mm,
        }

    def take_motion(self, motion: Mapping[str, Any]) -> None:
        """The service's figures of the motion from its status' ``motion`` block (``wara
        ctl status``): the largest twist, the sync error at standstill and while moving,
        the duration (NaN where the block has none)."""
        self.max_twist_mm = float(motion.get("max_twist_mm", math.nan))
        self.sync_error_mm = float(motion.get("hold_sync_error_mm", math.nan))
        self.max_sync_error_mm = float(motion.get("max_sync_error_mm", math.nan))
        self.duration_s = float(motion.get("duration_s", math.nan))

    def set_achieved(self, roll_deg: float, pitch_deg: float) -> None:
        """The attitude reached, and the error: the larger of roll and pitch off target."""
        self.achieved_roll_deg, self.achieved_pitch_deg = roll_deg, pitch_deg
        self.attitude_error_deg = max(
            abs(roll_deg - self.target_roll_deg), abs(pitch_deg - self.target_pitch_deg)
        )


def judge_example(res: ExampleResult, *, problem: str = "") -> ExampleResult:
    """The verdict on one example from its figures (set in ``res``) against
    :data:`~wara.goals.ATTITUDE_GOALS`.

    ``problem``: why the service is not holding the target with figures to judge (its
    mode and latched faults, missing standstill samples...), empty when it is. Passed
    when there is none and every figure is within its goal (a NaN figure is not);
    ``note`` is the problem, else the figures over their goals.
    """
    verdict = judge(ATTITUDE_GOALS, res.figures(), problem=problem)
    res.note = verdict.note
    res.passed = verdict.passed
    return res
