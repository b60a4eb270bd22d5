"""A slow, simple dense search: the yardstick for the ``exact`` planner.

A ``points x points`` grid over the whole upper square, then a compass-style pattern
search from its best feasible point on a 9 x 9 window that moves while it improves and
shrinks by 2.5 when it does not, down to ``tolerance_m``. Used by the tests and by
``wara bench planner`` to measure the exact planner's objective gap; never in the loop.
"""

from __future__ import annotations

import numpy as np

from ipc_app.planner.exact import Solution, pick
from ipc_app.planner.problem import PlanningProblem


def dense_search(
    problem: PlanningProblem, points: int = 401, tolerance_m: float = 1e-11
) -> Solution:
    lim = problem.limit_upper
    axis = np.linspace(-lim, lim, points)
    g1, g2 = (m.ravel() for m in np.meshgrid(axis, axis, indexing="ij"))
    ev = problem.evaluate(g1, g2)
    obj = np.where(ev.feasible, ev.objective, np.inf)
    i = int(np.argmin(obj))
    count = g1.size
    if not np.isfinite(obj[i]):
        return Solution(float(g1[i]), float(g2[i]), pick(ev, i), count, False)
    x1, x2, val = float(g1[i]), float(g2[i]), float(obj[i])
    h = float(axis[1] - axis[0])
    off = np.linspace(-1.0, 1.0, 9)
    o1, o2 = (m.ravel() for m in np.meshgrid(off, off, indexing="ij"))
    for _ in range(2000):
        if h < tolerance_m:
            break
        p1 = np.clip(x1 + h * o1, -lim, lim)
        p2 = np.clip(x2 + h * o2, -lim, lim)
        e = problem.evaluate(p1, p2)
        count += p1.size
        v = np.where(e.feasible, e.objective, np.inf)
        k = int(np.argmin(v))
        if v[k] < val:
            x1, x2, val = float(p1[k]), float(p2[k]), float(v[k])
        else:
            h /= 2.5
    final = problem.evaluate(np.array([x1]), np.array([x2]))
    return Solution(x1, x2, pick(final, 0), count + 1, bool(final.feasible[0]))
