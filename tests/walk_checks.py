"""The walk's goals on a project's steps, for the end-to-end tests of an example project
(a ring cycle's walks there and back, a ``wara walk``): each limit read from the
project's ``walking`` keys (wara.goals.walk_step_goals), not the shipped project's."""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

from config import ProjectConfig
from wara.goals import step_time_limit_s


def assert_steps_within_the_walk_goals(
    cfg: ProjectConfig, steps: Iterable[Mapping[str, Any]]
) -> None:
    """Each step's overload, leg sync, stability margin and duration within ``cfg``'s."""
    w = cfg.walking
    assert w is not None
    for step in steps:
        assert step["max_leg_force_ratio"] <= w.overload_percent / 100, step
        assert step["max_leg_sync_error_mm"] <= w.leg_sync_band_mm, step
        assert step["min_stability_margin_m"] >= w.min_stability_margin_m, step
        assert step["duration_s"] <= step_time_limit_s(cfg), step  # the step-time goal
