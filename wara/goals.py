"""The goals of each kind of run, and the one judge of a run's figures.

The kinds: the attitude examples (``wara demo --attitude``; :mod:`wara.examples`), the
walk (``wara walk``, judged per step), the placement (``wara place run``) and the ring
cycle (``wara cycle``, judged per ring). The campaigns (:mod:`wara.campaign`) judge their
runs against the same goals unless their spec sets limits of its own.

A :class:`Goal` limits one figure of a run (its unit in its name) and says where its
limit comes from. Where the project has a key for it, the limit is read from the project
the run is judged for (``walking.*``, ``acceptance.*``, ``cycle.max_cycle_time_min``): a
project that changes ``walking.overload_percent`` is judged against its own value. The
goals no project key holds are the accuracy asked of the controllers in simulation,
whatever the project (:data:`ATTITUDE_TOL_DEG` ... below). A judge is a pure function
from a run's figures to a :class:`Verdict`: each goal with its value, its limit and
whether it was met, and the missed ones named in :attr:`Verdict.note`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from config import units
from config.schema import ProjectConfig
from ipc_app.service.cycle import RECORD_KEYS

# ------------------------------------------------------------ the simulation's own goals

#: The workpiece's attitude: at rest within this of the target (the reference machine's
#: examples) and placed within this of the placement target (each angle).
ATTITUDE_TOL_DEG = 0.01
#: A layer's largest twist during an attitude adjustment.
TWIST_TOL_MM = 0.5
#: The sync error at standstill after an adjustment (the paper's dual-cylinder accuracy).
SYNC_TOL_MM = 0.07
#: A placed part's position from its target (each of x, y, z), and its gap from the
#: planned gap.
POSITION_TOL_MM = 1.0
#: Each step's distance from the step length, and a walk's from its steps'.
DISTANCE_TOL_MM = 5.0

#: Where a goal of the simulation's own comes from (no project key holds it).
SIMULATION = "simulation goal"

#: Figures whose limit is a lower bound (met at or above it); every other is an upper one.
HIGHER_IS_BETTER = frozenset({"min_stability_margin_m", "min_gap_mm"})


@dataclass(frozen=True)
class Goal:
    """``figure`` at most ``limit`` (at least, for :data:`HIGHER_IS_BETTER`); ``source``:
    the project key the limit is read from (or what it is derived from), else
    :data:`SIMULATION`."""

    figure: str
    limit: float
    source: str = SIMULATION

    @property
    def at_least(self) -> bool:
        return self.figure in HIGHER_IS_BETTER

    def met(self, value: float) -> bool:
        """Within the limit; on it counts as within, a NaN value is not."""
        return bool(value >= self.limit if self.at_least else value <= self.limit)


@dataclass(frozen=True)
class Judged:
    """One goal and the run's value of its figure."""

    goal: Goal
    value: float

    @property
    def met(self) -> bool:
        return self.goal.met(self.value)

    @property
    def note(self) -> str:
        """``figure value > limit`` (``<`` for a lower bound)."""
        g = self.goal
        return f"{g.figure} {self.value:.4g} {'<' if g.at_least else '>'} {g.limit:g}"

    def to_dict(self) -> dict[str, Any]:
        g = self.goal
        return {"value": self.value, "limit": g.limit, "met": self.met, "source": g.source}


@dataclass(frozen=True)
class Verdict:
    """A run's (or one of its parts') goals judged. ``problem``: why the run has no
    figures to judge, or did not end as it should (refused, a latched fault, a stop),
    empty when it did. ``parts``: the verdicts of its parts by name (a walk's steps)."""

    judged: tuple[Judged, ...]
    problem: str = ""
    parts: tuple[tuple[str, Verdict], ...] = ()

    @property
    def missed(self) -> tuple[Judged, ...]:
        return tuple(j for j in self.judged if not j.met)

    @property
    def passed(self) -> bool:
        return not self.problem and not self.missed and all(v.passed for _, v in self.parts)

    @property
    def notes(self) -> list[str]:
        """The problem (in place of the goals: figures of a run that did not end as it
        should are no verdict on it), else each missed goal; then each part's notes
        behind its name."""
        out = [self.problem] if self.problem else [j.note for j in self.missed]
        out += [f"{name}: {n}" for name, v in self.parts for n in v.notes]
        return out

    @property
    def note(self) -> str:
        """Why it did not pass (empty when it did)."""
        return "; ".join(self.notes)

    def to_dict(self) -> dict[str, Any]:
        """``passed``, ``goals`` (figure -> value, limit, met, source) and ``missed``."""
        return {
            "passed": self.passed,
            "goals": {j.goal.figure: j.to_dict() for j in self.judged},
            "missed": self.notes,
        }


def judge(
    goals: Iterable[Goal],
    figures: Mapping[str, float],
    *,
    problem: str = "",
    parts: Sequence[tuple[str, Verdict]] = (),
) -> Verdict:
    """Each of ``goals`` against its figure in ``figures`` (a figure not there is NaN:
    not met)."""
    judged = tuple(Judged(g, float(figures.get(g.figure, math.nan))) for g in goals)
    return Verdict(judged, problem, tuple(parts))


def limits(goals: Iterable[Goal]) -> dict[str, float]:
    """figure -> limit (a demo's ``tolerances``, a campaign's default limits)."""
    return {g.figure: g.limit for g in goals}


# ------------------------------------------------------------------ the kinds of run

#: An attitude example's goals (no project key holds them: the same for every project).
ATTITUDE_GOALS: tuple[Goal, ...] = (
    Goal("attitude_error_deg", ATTITUDE_TOL_DEG),
    Goal("max_twist_mm", TWIST_TOL_MM),
    Goal("sync_error_mm", SYNC_TOL_MM),
)


def step_time_limit_s(cfg: ProjectConfig) -> float:
    """The longest a step may take: the project's step as planned from its nominal start
    (the ``walking`` and trajectory keys set its phases), each of its two lowerings given
    the whole touch-down window, ``2 x walking.touchdown_travel_mm`` at
    ``walking.touchdown_speed_mm_s`` or, left out, the derived touch-down speed
    (:func:`ipc_app.control.tuning.touchdown_speed_m_s`; the plan lowers at the legs'
    speed)."""
    from ipc_app.control.tuning import touchdown_speed_m_s
    from ipc_app.planner.walk import plan_walk, start_state

    w = cfg.walking
    if w is None:
        raise ValueError("the project has no walking section: it does not walk")
    plan = plan_walk(cfg, 1, start_state(cfg))
    window_s = 2.0 * units.mm(w.touchdown_travel_mm) / touchdown_speed_m_s(cfg)
    return plan.duration_s + 2.0 * window_s


def walk_step_goals(cfg: ProjectConfig) -> tuple[Goal, ...]:
    """A step's goals: its distance, the sync bands, the transfer's attitude change, the
    overload, the stability margin, its duration."""
    w = cfg.walking
    if w is None:
        raise ValueError("the project has no walking section: it does not walk")
    return (
        Goal("distance_error_mm", DISTANCE_TOL_MM),
        Goal("max_leg_sync_error_mm", w.leg_sync_band_mm, "walking.leg_sync_band_mm"),
        Goal("max_travel_sync_error_mm", w.travel_sync_band_mm, "walking.travel_sync_band_mm"),
        Goal(
            "max_transfer_attitude_change_deg",
            w.max_transfer_attitude_change_deg,
            "walking.max_transfer_attitude_change_deg",
        ),
        Goal("max_leg_force_ratio", w.overload_percent / 100.0, "walking.overload_percent"),
        Goal("min_stability_margin_m", w.min_stability_margin_m, "walking.min_stability_margin_m"),
        Goal(
            "max_step_duration_s",
            step_time_limit_s(cfg),
            "the planned step, its touch-downs in walking.touchdown_travel_mm at "
            "walking.touchdown_speed_mm_s",
        ),
    )


def step_figures(row: Mapping[str, Any], step_length_m: float) -> dict[str, float]:
    """A step's figures for its goals from ``wara walk``'s row of it: the service's
    figures, the truth's distance (negative for a step ``direction`` back) and duration."""
    out = {k: float(row[k]) for k in _STEP_ROW}
    want_m = -step_length_m if row.get("direction") == "back" else step_length_m
    out["distance_error_mm"] = 1000.0 * abs(float(row["distance_m"]) - want_m)
    out["max_step_duration_s"] = float(row["duration_s"])
    return out


_STEP_ROW = (
    "max_leg_sync_error_mm",
    "max_travel_sync_error_mm",
    "max_transfer_attitude_change_deg",
    "max_leg_force_ratio",
    "min_stability_margin_m",
)


#: A walk's own goal beside its steps': the distance of the whole walk (simulator truth).
def walk_goals(cfg: ProjectConfig) -> tuple[Goal, ...]:
    """A whole walk's goals on the truth: its distance along the axis, and the machine's
    heading against the axis's at its end within what one step steers back
    (curves.md section 3)."""
    assert cfg.walking is not None
    w = cfg.walking
    return (
        Goal("distance_error_mm", DISTANCE_TOL_MM),
        Goal(
            "heading_error_deg",
            w.max_heading_correction_per_step_deg,
            "walking.max_heading_correction_per_step_deg",
        ),
    )


def placement_goals(cfg: ProjectConfig) -> tuple[Goal, ...]:
    """A placed part's goals on the simulator's truth: each Table 4 item the project's
    ``acceptance`` limits (its absolute value), the position, angles and gap from the
    target."""
    acc = cfg.acceptance
    table4 = tuple(
        Goal(k, limit, f"acceptance.{k}")
        for k in RECORD_KEYS
        if (limit := getattr(acc, k)) is not None
    )
    return (
        *table4,
        Goal("min_gap_mm", 0.0, "no overlap: the joint's smallest gap >= 0"),
        Goal("position_error_mm", POSITION_TOL_MM),
        Goal("angle_error_deg", ATTITUDE_TOL_DEG),
        Goal("gap_error_mm", POSITION_TOL_MM),
    )


def placement_figures(placed: Mapping[str, Any]) -> dict[str, float]:
    """A placed part's figures for its goals from a run's figures of it (``wara place
    run``'s result, a ``wara cycle`` ring): the Table 4 items (acceptance keys) as
    absolute values, the largest position and angle error of ``error_from_target``
    (``x_mm`` ... ``yaw_deg``), the gap's error (``gap_error_mm``) and the joint's smallest
    gap (``min_gap_mm``; a run without it: NaN, not met)."""
    out = {k: abs(float(placed[k])) for k in RECORD_KEYS}
    out["min_gap_mm"] = float(placed.get("min_gap_mm", math.nan))
    e = placed["error_from_target"]
    out["position_error_mm"] = max(abs(float(e[k])) for k in ("x_mm", "y_mm", "z_mm"))
    out["angle_error_deg"] = max(abs(float(e[k])) for k in ("roll_deg", "pitch_deg", "yaw_deg"))
    out["gap_error_mm"] = abs(float(placed["gap_error_mm"]))
    return out


def ring_goals(cfg: ProjectConfig) -> tuple[Goal, ...]:
    """A ring cycle's goals: the placed part's, and its machine time (the fixing hold
    excluded) within ``cycle.max_cycle_time_min``."""
    if cfg.cycle is None:
        raise ValueError("the project has no cycle section: it has no ring cycle")
    cycle_s = 60.0 * cfg.cycle.max_cycle_time_min
    return (*placement_goals(cfg), Goal("cycle_time_s", cycle_s, "cycle.max_cycle_time_min"))


def ring_figures(ring: Mapping[str, Any]) -> dict[str, float]:
    """A ring's figures for its goals from ``wara cycle``'s row of it: the placed part's
    (:func:`placement_figures`) and ``cycle_time_s``."""
    return {**placement_figures(ring), "cycle_time_s": float(ring["cycle_time_s"])}
