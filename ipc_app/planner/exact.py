"""The project's deterministic planner (method ``exact``).

The allocation is two-dimensional: the upper extensions ``x = (d1_U, d2_U)`` on the
square ``|d| <= stroke/2 - reserve``. The objectives are sums and maxima of smooth
functions of ``x`` (cap pressures, extensions) under smooth constraints, so an optimum is
a vertex where two "critical curves" cross (constraint boundaries, kinks of the energy,
ties of the peak pressure: :meth:`PlanningProblem.critical`), or a point where the
objective is stationary on one curve or inside a piece.

Evaluating the model costs about the same for one candidate as for hundreds (numpy call
overhead dominates), so the planner works in a few batched calls:

1. a ``grid_points x grid_points`` grid on the whole square; the best feasible point, and
   any other in a different basin within 1 % of it, become incumbents;
2. Newton steps on the vertices: around each incumbent a 5-point stencil gives linear
   models of all critical functions; every crossing of two curves that pass near it, the
   foot of the perpendicular on each such curve, and the stationary point of a quadratic
   model of the objective become candidates; each candidate is evaluated together with
   its own stencil (one call), the best feasible one becomes the incumbent, and its
   stencil gives the next models. Near a vertex this converges quadratically;
3. a final pattern search on shrinking ``zoom_points`` grids, only while it still
   improves, covers optima that are not vertices (stationary on a curved boundary).

Every accepted point is feasible and the incumbent is kept, so the result is never
worse than the best point of the first grid. The tests compare it with a dense search
to 1e-6 relative; ``wara bench planner`` reports the gap and the speed-up over
``ldw_pso``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from config.schema import Exact
from ipc_app.planner.problem import Evaluation, PlanningProblem


@dataclass(frozen=True)
class Solution:
    d1: float
    d2: float
    evaluation: Evaluation  # of the chosen point (0-d arrays)
    evaluations: int  # candidates evaluated
    feasible: bool


def pick(ev: Evaluation, index: int) -> Evaluation:
    """One candidate of a batch evaluation."""
    return Evaluation(*(np.asarray(getattr(ev, f))[index] for f in ev.__dataclass_fields__))


def least_violation(problem: PlanningProblem, d1: np.ndarray, d2: np.ndarray) -> Solution:
    """The candidate closest to feasible (for the report of an unreachable target)."""
    ev = problem.evaluate(d1, d2)
    i = int(np.argmin(ev.violation))
    return Solution(float(d1[i]), float(d2[i]), pick(ev, i), d1.size, False)


# Stencil: centre, +x1, -x1, +x2, -x2, +x1+x2 (the last for the cross term of the quadratic).
_STENCIL = np.array([[0, 0], [1, 0], [-1, 0], [0, 1], [0, -1], [1, 1]], dtype=float)


class _Batch:
    """Points evaluated together with their stencils (one model call)."""

    def __init__(self, problem: PlanningProblem, centres: np.ndarray, delta: float) -> None:
        lim = problem.limit_upper
        self.delta = delta
        pts = centres[:, None, :] + delta * _STENCIL[None, :, :]
        pts = np.clip(pts, -lim, lim)
        self.points = pts
        ev = problem.evaluate(pts[..., 0], pts[..., 1])
        self.objective = np.where(ev.feasible, ev.objective, np.inf)
        self.centre_objective = self.objective[:, 0]
        self.raw_objective = ev.objective
        self.critical = problem.critical(ev, pts[..., 0], pts[..., 1])
        self.count = pts.shape[0] * pts.shape[1]

    def candidates(self, k: int, radius: float, lim: float) -> np.ndarray:
        """Newton candidates from the linear models around centre ``k``."""
        pts = self.points[k]
        c = self.critical[k]
        h1 = pts[1, 0] - pts[2, 0]
        h2 = pts[3, 1] - pts[4, 1]
        if h1 <= 0 or h2 <= 0:
            return np.empty((0, 2))
        c0 = c[0]
        g = np.stack([(c[1] - c[2]) / h1, (c[3] - c[4]) / h2], -1)
        gn = np.hypot(g[:, 0], g[:, 1])
        with np.errstate(divide="ignore", invalid="ignore"):
            dist = np.abs(c0) / gn
        near = np.nonzero((gn > 0) & (dist <= radius))[0]
        out = [pts[0]]
        if near.size:
            # Foot of the perpendicular on each near curve.
            gg = g[near]
            out.extend(pts[0] - (c0[near] / gn[near] ** 2)[:, None] * gg)
            i, j = np.triu_indices(near.size, 1)
            a, b = near[i], near[j]
            det = g[a, 0] * g[b, 1] - g[a, 1] * g[b, 0]
            ok = np.abs(det) > 1e-9 * gn[a] * gn[b]
            a, b, det = a[ok], b[ok], det[ok]
            dx = (-c0[a] * g[b, 1] + c0[b] * g[a, 1]) / det
            dy = (-g[a, 0] * c0[b] + g[b, 0] * c0[a]) / det
            keep = np.maximum(np.abs(dx), np.abs(dy)) <= 2 * radius
            out.extend(pts[0] + np.stack([dx[keep], dy[keep]], -1))
        # Stationary point of the quadratic model of the objective (smooth pieces).
        f = self.raw_objective[k]
        if h1 == h2 and np.all(np.isfinite(f)):
            h = h1 / 2
            fx, fy = (f[1] - f[2]) / (2 * h), (f[3] - f[4]) / (2 * h)
            fxx = (f[1] - 2 * f[0] + f[2]) / h**2
            fyy = (f[3] - 2 * f[0] + f[4]) / h**2
            fxy = (f[5] - f[1] - f[3] + f[0]) / h**2
            det2 = fxx * fyy - fxy * fxy
            if det2 > 0 and fxx > 0:
                step = -np.array([fyy * fx - fxy * fy, fxx * fy - fxy * fx]) / det2
                if np.max(np.abs(step)) <= 2 * radius:
                    out.append(pts[0] + step)
        return np.clip(np.asarray(out), -lim, lim)


def _pattern_search(
    problem: PlanningProblem, x: np.ndarray, val: float, half: float, opts: Exact
) -> tuple[np.ndarray, float, int]:
    """Polish on shrinking grids while it improves (non-vertex optima)."""
    lim = problem.limit_upper
    offsets = np.linspace(-1.0, 1.0, opts.zoom_points)
    o1, o2 = (m.ravel() for m in np.meshgrid(offsets, offsets, indexing="ij"))
    count = 0
    while half > opts.tolerance_m:
        p1 = np.clip(x[0] + half * o1, -lim, lim)
        p2 = np.clip(x[1] + half * o2, -lim, lim)
        e = problem.evaluate(p1, p2)
        count += p1.size
        v = np.where(e.feasible, e.objective, np.inf)
        j = int(np.argmin(v))
        if v[j] < val - 1e-15 * abs(val):
            x, val = np.array([p1[j], p2[j]]), float(v[j])
        else:
            break
        half /= opts.zoom_factor
    return x, val, count


def solve_exact(problem: PlanningProblem, opts: Exact) -> Solution:
    lim = problem.limit_upper
    axis = np.linspace(-lim, lim, opts.grid_points)
    g1, g2 = (m.ravel() for m in np.meshgrid(axis, axis, indexing="ij"))
    ev = problem.evaluate(g1, g2)
    count = g1.size
    if not ev.feasible.any():
        sol = least_violation(problem, g1, g2)
        return Solution(sol.d1, sol.d2, sol.evaluation, count, False)
    obj = np.where(ev.feasible, ev.objective, np.inf)
    spacing = float(axis[1] - axis[0])
    order = np.argsort(obj)
    starts = [int(order[0])]
    for i in order[1 : 4 * opts.grid_points]:
        if not obj[i] <= obj[order[0]] + 0.01 * abs(obj[order[0]]) or len(starts) == 3:
            break
        if all(max(abs(g1[i] - g1[j]), abs(g2[i] - g2[j])) > 3 * spacing for j in starts):
            starts.append(int(i))
    delta = 1e-6 * lim
    batch = _Batch(problem, np.stack([g1[starts], g2[starts]], -1), delta)
    count += batch.count
    best_x = np.array([g1[starts[0]], g2[starts[0]]])
    best_v = float(obj[starts[0]])
    radius = 1.5 * spacing
    for _ in range(opts.newton_iterations):
        cands = [batch.candidates(k, radius, lim) for k in range(batch.points.shape[0])]
        pts = np.concatenate(cands)
        if pts.size == 0:
            break
        batch = _Batch(problem, pts, delta)
        count += batch.count
        k = int(np.argmin(batch.centre_objective))
        v = float(batch.centre_objective[k])
        if v < best_v:
            step = float(np.max(np.abs(pts[k] - best_x)))
            best_x, best_v = pts[k].copy(), v
            radius = max(4 * step, 50 * delta)
            # Keep only the new incumbent's models for the next step.
            batch.points = batch.points[k : k + 1]
            batch.critical = batch.critical[k : k + 1]
            batch.raw_objective = batch.raw_objective[k : k + 1]
            if step < opts.tolerance_m:
                break
        else:
            break
    best_x, best_v, n = _pattern_search(problem, best_x, best_v, 4 * delta, opts)
    count += n
    final = problem.evaluate(best_x[None, 0], best_x[None, 1])
    return Solution(
        float(best_x[0]), float(best_x[1]), pick(final, 0), count + 1, bool(final.feasible[0])
    )
