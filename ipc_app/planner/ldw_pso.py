"""The paper's planner (method ``ldw_pso``): particle swarm optimization with a linearly
decreasing inertia weight (0.9 -> 0.4, c1 = c2 = 2).

A particle is the four upper extensions (within the upper stroke). The upper attitude is
fitted from them in least squares, the lower follows from the composition; the objective
is evaluated on the linked configuration of the fitted attitude, and the linkage
violation (``|d1 + d3| + |d2 + d4|``), the coplanarity violation and every constraint
violation are added as penalties. The result is the linked configuration of the best
particle's fitted attitude, so the plan satisfies the linkage exactly.

The swarm size and iteration count of the paper were lost. The defaults (50 particles,
1000 iterations, configurable under ``planner.ldw_pso``) are the smallest of the settings
measured in docs/model-choices.md whose median gap to the exact optimum on the benchmark
targets is about 2 % for the default objective; fewer iterations leave 7-14 %. The
generator is seeded, so a run is reproducible.
"""

from __future__ import annotations

import numpy as np

from config.schema import LdwPso
from ipc_app.model.kinematics import coplanarity_distance, extensions, fit_layer
from ipc_app.planner.exact import Solution, pick
from ipc_app.planner.problem import PlanningProblem


def solve_ldw_pso(problem: PlanningProblem, opts: LdwPso, seed: int | None = None) -> Solution:
    rng = np.random.default_rng(opts.seed if seed is None else seed)
    lim = problem.limit_upper
    a, b = problem.a_upper, problem.b_upper
    n = opts.swarm_size
    vmax = 0.2 * 2 * lim

    def fitness(x: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        fit = fit_layer(x, a, b)
        # Linked upper extensions of the fitted attitude: d1, d2 fix it exactly.
        linked = extensions(fit.roll, fit.pitch, a, b)
        d1, d2 = linked[..., 0], linked[..., 1]
        ev = problem.evaluate(d1, d2)
        linkage = (np.abs(x[:, 0] + x[:, 2]) + np.abs(x[:, 1] + x[:, 3])) / lim
        cop = np.maximum(coplanarity_distance(x, a, b) - problem.coplanarity_tol, 0.0)
        penalty = ev.violation + linkage + cop / problem.coplanarity_tol
        return ev.objective, penalty, np.stack([d1, d2], axis=-1)

    x = rng.uniform(-lim, lim, size=(n, 4))
    v = rng.uniform(-vmax, vmax, size=(n, 4))
    obj, pen, _ = fitness(x)
    scale = float(np.median(np.abs(obj[np.isfinite(obj)]))) or 1.0
    weight = opts.penalty_weight

    def score(o: np.ndarray, p: np.ndarray) -> np.ndarray:
        return o / scale + weight * p

    f = score(obj, pen)
    pbest, pbest_f = x.copy(), f.copy()
    g = int(np.argmin(f))
    gbest, gbest_f = x[g].copy(), float(f[g])
    iters = opts.iterations
    for k in range(iters):
        w = opts.inertia_start - (opts.inertia_start - opts.inertia_end) * k / max(iters - 1, 1)
        r1 = rng.random((n, 4))
        r2 = rng.random((n, 4))
        v = w * v + opts.c1 * r1 * (pbest - x) + opts.c2 * r2 * (gbest - x)
        np.clip(v, -vmax, vmax, out=v)
        x = np.clip(x + v, -lim, lim)
        obj, pen, _ = fitness(x)
        f = score(obj, pen)
        better = f < pbest_f
        pbest[better] = x[better]
        pbest_f[better] = f[better]
        g = int(np.argmin(pbest_f))
        if pbest_f[g] < gbest_f:
            gbest, gbest_f = pbest[g].copy(), float(pbest_f[g])
    _, _, linked = fitness(gbest[None, :])
    d1, d2 = float(linked[0, 0]), float(linked[0, 1])
    final = problem.evaluate(np.array([d1]), np.array([d2]))
    count = n * (iters + 1) + 1
    return Solution(d1, d2, pick(final, 0), count, bool(final.feasible[0]))
