"""The reference machine's Examples 1-3, their goals, and the one judge of an example's
result, used by both forms of the demo (one process: :mod:`wara.demo`; two processes:
:mod:`wara.demo_two_process`) and by the harness's users (tests, studies)."""

from __future__ import annotations

import math
from dataclasses import dataclass

EXAMPLES: tuple[tuple[float, float], ...] = ((2.0, 1.0), (-3.0, 2.0), (5.0, -1.0))

#: The goals each example must meet.
ATTITUDE_TOL_DEG = 0.01
TWIST_TOL_MM = 0.5
SYNC_TOL_MM = 0.07

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

    def set_achieved(self, roll_deg: float, pitch_deg: float) -> None:
        """The attitude reached, and the error: the larger of roll and pitch off target."""
        self.achieved_roll_deg, self.achieved_pitch_deg = roll_deg, pitch_deg
        self.attitude_error_deg = max(
            abs(roll_deg - self.target_roll_deg), abs(pitch_deg - self.target_pitch_deg)
        )


def judge_example(res: ExampleResult, *, problem: str = "") -> ExampleResult:
    """The verdict on one example from its figures (set in ``res``).

    ``problem``: why the service is not holding the target with figures to judge (its
    mode and latched faults, missing standstill samples...), empty when it is. Passed
    when there is none and every figure is within its goal (a NaN figure is not);
    ``note`` is the problem, else the figures over their goals.
    """
    over = [
        f"{name} {value:.4g} > {tol:g}"
        for name, value, tol in (
            ("attitude error deg", res.attitude_error_deg, ATTITUDE_TOL_DEG),
            ("max twist mm", res.max_twist_mm, TWIST_TOL_MM),
            ("sync error mm", res.sync_error_mm, SYNC_TOL_MM),
        )
        if not value <= tol
    ]
    res.note = problem or "; ".join(over)
    res.passed = not problem and not over
    return res
