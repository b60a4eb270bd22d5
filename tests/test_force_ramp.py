"""A force ramp in time (ipc_app.planner.force_ramp): the line's fraction is the integral
of the rate, from rest to rest, one blend longer than at full rate."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from config import load_project
from ipc_app.control.tuning import position_bandwidths
from ipc_app.planner.force_ramp import ForceRamp, blend_s


@given(
    linear_s=st.floats(min_value=0.01, max_value=60.0),
    blend=st.floats(min_value=0.0, max_value=5.0),
)
def test_the_fraction_is_the_integral_of_the_rate_from_rest_to_rest(
    linear_s: float, blend: float
) -> None:
    ramp = ForceRamp.of(linear_s, blend)
    assert ramp.blend_s == min(blend, linear_s)
    assert ramp.duration_s == pytest.approx(linear_s + ramp.blend_s)
    t = np.linspace(0.0, ramp.duration_s, 4001)
    rate = np.array([ramp.rate_share(v) for v in t]) / linear_s
    frac = np.array([ramp.fraction(v) for v in t])
    integral = np.concatenate([[0.0], np.cumsum((rate[1:] + rate[:-1]) / 2 * np.diff(t))])
    assert np.abs(frac - integral).max() < 2e-3
    assert frac[0] == 0.0 and frac[-1] == 1.0 and np.all(np.diff(frac) >= -1e-15)
    assert rate.max() <= 1.0 / linear_s + 1e-12
    if ramp.blend_s > 0:
        assert ramp.rate_share(0.0) == 0.0 and ramp.rate_share(ramp.duration_s) == 0.0


def test_the_blend_is_one_period_of_the_slowest_leg_loops_crossover() -> None:
    cfg = load_project(None)
    wc = [position_bandwidths(cfg, c)[0] for c in cfg.cylinders if c.role.endswith("_leg")]
    assert blend_s(cfg) == pytest.approx(2 * np.pi / min(wc))


def test_a_ramp_with_nothing_to_move_is_done_at_once() -> None:
    """Receiving legs already at their target (a resume at the ramp's end): no line to
    run, no rate, the whole way along."""
    ramp = ForceRamp.of(0.0, 1.5)
    assert ramp.duration_s == 0.0 and ramp.fraction(0.0) == 1.0 and ramp.rate_share(0.0) == 0.0
