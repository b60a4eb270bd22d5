"""The walk's statics on plain floats (decision 0033) give what the matrix forms give:
the eight- and four-leg shares (``support_forces``), the stability margin against
scipy's convex hull, the held legs' shares (``HeldLegShares``, its maps kept while S
moves) against ``min_norm_forces``, and the walk loops' cached hull edges as S travels."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial import ConvexHull

from config import ProjectConfig
from ipc_app.control.walk.forces import HeldLegShares, equilibrium_matrix, min_norm_forces
from ipc_app.control.walk.loops import WalkLoops
from ipc_app.model.kinematics import Vec
from ipc_app.model.support import (
    WalkingMachine,
    cog_projection,
    stability_margin,
    support_forces,
)
from ipc_app.planner.walk import plan_walk

RNG_SEED = 20261206


def _normal_equations(pts: np.ndarray, mass: float, cog: np.ndarray, g: Vec) -> np.ndarray:
    """The reference: A^T (A A^T)^-1 r with numpy's solve."""
    gv = np.array([float(g.x), float(g.y), float(g.z)])
    rhs = -mass * np.array(
        [gv[2], cog[1] * gv[2] - cog[2] * gv[1], cog[2] * gv[0] - cog[0] * gv[2]]
    )
    a = np.vstack([np.ones(len(pts)), pts[:, 1], -pts[:, 0]])
    return np.asarray(a.T @ np.linalg.solve(a @ a.T, rhs))


def test_support_forces_are_the_normal_equations_for_any_legs_and_tilt() -> None:
    rng = np.random.default_rng(RNG_SEED)
    for _ in range(200):
        n = int(rng.integers(3, 9))
        pts = rng.uniform(-5.0, 5.0, size=(n, 2))
        cog = rng.uniform(-1.0, 1.0, size=3)
        g = Vec(*(np.asarray(v) for v in (rng.normal(0, 0.5), rng.normal(0, 0.5), -9.81)))
        mass = float(rng.uniform(1e3, 8e4))
        ours = support_forces(pts, mass, cog, g)
        ref = _normal_equations(pts, mass, cog, g)
        scale = np.abs(ref).max()
        assert np.abs(ours - ref).max() <= 1e-9 * scale


def test_legs_on_one_line_hold_no_body() -> None:
    pts = np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]])
    g = Vec(np.asarray(0.0), np.asarray(0.0), np.asarray(-9.81))
    with pytest.raises(np.linalg.LinAlgError, match="one line"):
        support_forces(pts, 1000.0, np.zeros(3), g)


def test_the_stability_margin_is_the_distance_to_scipys_hull() -> None:
    rng = np.random.default_rng(RNG_SEED + 1)
    for _ in range(200):
        pts = rng.uniform(-5.0, 5.0, size=(int(rng.integers(3, 9)), 2))
        p = rng.uniform(-6.0, 6.0, size=2)
        hull = ConvexHull(pts)
        # facets: outward normal n and offset c, n.x + c <= 0 inside
        ref = float(np.min(-(hull.equations[:, :2] @ p + hull.equations[:, 2])))
        assert stability_margin(pts, p) == pytest.approx(ref, abs=1e-12)
    assert stability_margin(np.array([[0.0, 0.0], [1.0, 0.0]]), np.zeros(2)) == -math.inf


@pytest.mark.parametrize(
    "held",
    [(4, 5, 6, 7), (4, 5, 7), (0, 1, 2, 3), (0, 2, 3), (0, 1, 4, 5), (1, 6, 7)],
    ids=["all-S", "three-S", "all-M", "three-M", "mixed", "mixed-3"],
)
def test_held_leg_shares_are_the_minimum_norm_forces_as_s_moves(
    project: ProjectConfig, held: tuple[int, ...]
) -> None:
    machine = WalkingMachine(project)
    shares = HeldLegShares()
    rng = np.random.default_rng(RNG_SEED + len(held))
    plan_n = rng.uniform(0.0, 3e5, size=8)
    # S's travel: the maps kept at one x_s serve every other
    for x_s in np.linspace(-1.0, 1.0, 41):
        eight = support_forces(
            machine.legs_xy(float(x_s)), machine.mass_kg, machine.cog(float(x_s)),
            machine.g_base,
        )  # fmt: skip
        contact = eight * rng.uniform(0.8, 1.2, size=8)
        ours = shares.expected_n(machine, float(x_s), eight, contact, plan_n, list(held))
        a = equilibrium_matrix(machine, float(x_s))
        others = [j for j in range(8) if j not in held]
        rest = a @ eight - a[:, others] @ contact[others]
        want = plan_n.copy()
        want[list(held)] = min_norm_forces(a, list(held), rest)
        assert ours == pytest.approx(want, rel=1e-9, abs=1e-6)


def test_held_leg_shares_without_held_legs_are_the_plan(project: ProjectConfig) -> None:
    machine = WalkingMachine(project)
    plan_n = np.arange(8, dtype=float)
    out = HeldLegShares().expected_n(machine, 0.3, plan_n, plan_n, plan_n, [])
    assert out is not plan_n and list(out) == list(plan_n)


def test_the_walk_loops_margin_follows_s_with_its_hull_kept(project: ProjectConfig) -> None:
    """``WalkLoops.margin`` keeps each frame's hull while S travels: the same as the
    margin taken afresh at every position, for M, S and both standing (S beyond its
    travel too, where the hull's ends, not its sides, are the nearest edges)."""
    loops = WalkLoops(project, 0.01, plan_walk(project, 1))
    machine = loops.machine
    for legs in ((0, 1, 2, 3), (4, 5, 6, 7), tuple(range(8)), (0, 1, 4, 5, 6)):
        for x_s in np.linspace(-2.5, 2.5, 21):
            x = float(x_s)
            point = cog_projection(machine.cog(x), machine.g_base)
            want = stability_margin(machine.legs_xy(x)[list(legs)], point)
            assert loops.margin(x, legs) == pytest.approx(want, abs=1e-12)
