"""Dual-error synchronization of cylinder groups (2 cylinders, and a linked layer of 4)."""

from __future__ import annotations

import numpy as np
import pytest

from ipc_app.control import LADRC, PID, SyncGroup, ring_neighbours, sync_errors


def test_ring_neighbours() -> None:
    assert ring_neighbours(2) == [(1,), (0,)]
    assert ring_neighbours(4) == [(1, 3), (0, 2), (1, 3), (0, 2)]  # platform edges 1-2-3-4-1
    with pytest.raises(ValueError):
        ring_neighbours(1)


def test_sync_errors_definitions() -> None:
    e = [0.3, 0.1]
    assert sync_errors(e, "mean_deviation") == pytest.approx([0.1, -0.1])
    assert sync_errors(e, "cross_coupled") == pytest.approx([0.2, -0.2])
    e4 = [1.0, 2.0, 4.0, 7.0]
    md = sync_errors(e4, "mean_deviation")
    assert sum(md) == pytest.approx(0.0)
    assert md == pytest.approx([-2.5, -1.5, 0.5, 3.5])
    cc = sync_errors(e4, "cross_coupled")
    assert cc == pytest.approx(
        [(1 - 2) + (1 - 7), (2 - 1) + (2 - 4), (4 - 2) + (4 - 7), (7 - 4) + (7 - 1)]
    )
    assert sum(cc) == pytest.approx(0.0)
    with pytest.raises(ValueError, match="scheme"):
        sync_errors(e, "nearest")  # type: ignore[arg-type]


def _run_group(
    gains: list[float],
    references: list[float],
    scheme: str,
    lam: float,
    controller: str = "pid",
    seconds: float = 6.0,
) -> float:
    """Integrating plants ``y_i' = b_i u_i + d_i`` with mismatched gains and offsets
    following ramps; returns the largest spread of the tracking errors in the last
    two thirds of the run."""
    dt = 1e-3
    n = len(gains)
    offsets = [0.002 * (i - 1.5) for i in range(n)]  # m/s, e.g. unequal leakage
    if controller == "pid":
        ctrls = [PID(20.0, 0.0, 0.0, dt) for _ in range(n)]
    else:
        ctrls = [LADRC(1, b0=0.05, wc=4.0, wo=10.0, dt=dt) for _ in range(n)]
    group = SyncGroup(ctrls, scheme, lam)  # type: ignore[arg-type]
    y = [0.0] * n
    group.reset(y)
    worst = 0.0
    steps = int(seconds / dt)
    for k in range(steps):
        refs = [r * k * dt for r in references]
        u = group.update(refs, y)
        y = [y[i] + dt * (gains[i] * u[i] + offsets[i]) for i in range(n)]
        if k > steps // 3:
            e = [refs[i] - y[i] for i in range(n)]
            worst = max(worst, max(e) - min(e))
    return worst


@pytest.mark.parametrize("scheme", ["mean_deviation", "cross_coupled"])
def test_two_cylinder_sync_error_shrinks_with_lambda(scheme: str) -> None:
    spreads = [_run_group([0.05, 0.04], [0.02, 0.02], scheme, lam) for lam in (0.0, 1.0, 4.0)]
    assert spreads[0] > spreads[1] > spreads[2]
    assert spreads[2] < 0.5 * spreads[0]


@pytest.mark.parametrize("scheme", ["mean_deviation", "cross_coupled"])
def test_linked_layer_of_four_sync_error_shrinks_with_lambda(scheme: str) -> None:
    """A layer under the linkage ``d_3 = -d_1``, ``d_4 = -d_2``: references differ, the
    synchronization compares tracking errors."""
    refs = [0.02, 0.01, -0.02, -0.01]
    gains = [0.05, 0.045, 0.055, 0.04]
    spreads = [_run_group(gains, refs, scheme, lam) for lam in (0.0, 1.0, 4.0)]
    assert spreads[0] > spreads[1] > spreads[2]
    assert spreads[2] < 0.5 * spreads[0]


def test_ladrc_group_also_synchronizes() -> None:
    loose = _run_group([0.05, 0.04], [0.02, 0.02], "mean_deviation", 0.0, "ladrc", 3.0)
    tight = _run_group([0.05, 0.04], [0.02, 0.02], "mean_deviation", 3.0, "ladrc", 3.0)
    assert tight < loose


def test_group_without_coupling_is_independent_controllers() -> None:
    dt = 1e-3
    group = SyncGroup([PID(50.0, 5.0, 0.0, dt), PID(50.0, 5.0, 0.0, dt)], coupling_lambda=0.0)
    alone = [PID(50.0, 5.0, 0.0, dt), PID(50.0, 5.0, 0.0, dt)]
    for k in range(100):
        y = [0.001 * k, 0.002 * k]
        got = group.update([0.5, 0.5], y)
        expected = [c.update(0.5, yi) for c, yi in zip(alone, y, strict=True)]
        np.testing.assert_allclose(got, expected)


def test_group_hands_the_reference_rates_to_its_controllers() -> None:
    """The rates go to each member as feed-forward; the coupling term stays feedback."""
    dt = 1e-3
    group = SyncGroup([LADRC(1, 0.05, 6.0, 12.0, dt) for _ in range(2)], coupling_lambda=1.0)
    alone = [LADRC(1, 0.05, 6.0, 12.0, dt) for _ in range(2)]
    for k in range(50):
        y = [0.001 * k, 0.0015 * k]
        refs, rates = [0.002 * k, 0.002 * k], [2.0, 2.0]
        got = group.update(refs, y, rates)
        eps = sync_errors([r - yi for r, yi in zip(refs, y, strict=True)])
        rows = zip(alone, refs, eps, y, rates, strict=True)
        expected = [c.update(r + e, yi, v) for c, r, e, yi, v in rows]
        np.testing.assert_allclose(got, expected)
    with pytest.raises(ValueError, match="2 reference rates"):
        group.update([0.0, 0.0], [0.0, 0.0], [1.0])


def test_group_checks_its_inputs() -> None:
    dt = 1e-3
    with pytest.raises(ValueError, match="at least 2"):
        SyncGroup([PID(1.0, 0.0, 0.0, dt)])
    group = SyncGroup([PID(1.0, 0.0, 0.0, dt), PID(1.0, 0.0, 0.0, dt)])
    with pytest.raises(ValueError, match="expected 2"):
        group.update([0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
