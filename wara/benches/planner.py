"""``wara bench planner --json``: exact vs ldw_pso vs a dense search, in one process.

Targets: a fixed 5 x 5 grid of workpiece (roll, pitch) over the workspace
(roll -8..8 deg, pitch -4..4 deg), from a level start, for each objective. Reports the
median solve time of each method and their ratio (``speedup``), and the worst relative
objective gap of ``exact`` against ``ldw_pso`` (never positive: exact is never worse) and
against the dense search (positive would mean exact is worse; the goal is <= 1e-6).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from typing import Any

import numpy as np

from config import load_project, units
from ipc_app.planner.exact import solve_exact
from ipc_app.planner.ldw_pso import solve_ldw_pso
from ipc_app.planner.problem import OBJECTIVES, PlanningProblem
from ipc_app.planner.reference import dense_search


def targets(quick: bool) -> list[tuple[float, float]]:
    if quick:
        return [(2.0, 1.0), (-3.0, 2.0), (5.0, -1.0)]
    return [(r, p) for r in np.linspace(-8, 8, 5) for p in np.linspace(-4, 4, 5)]


def run(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_project(args.config)
    pso_opts = cfg.planner.ldw_pso
    tg = targets(args.quick)
    per_objective: dict[str, Any] = {}
    all_exact: list[float] = []
    all_pso: list[float] = []
    worst_vs_pso = -np.inf
    worst_vs_dense = -np.inf
    total = len(tg) * len(OBJECTIVES)
    done = 0
    for obj in OBJECTIVES:
        t_exact: list[float] = []
        t_pso: list[float] = []
        gaps_pso: list[float] = []
        gaps_dense: list[float] = []
        infeasible = 0
        for roll, pitch in tg:
            done += 1
            print(
                f"\rbench planner: {done}/{total} {obj} ({roll:+.0f}, {pitch:+.0f}) deg ",
                end="",
                file=sys.stderr,
                flush=True,
            )
            pr = PlanningProblem(cfg, units.deg(roll), units.deg(pitch), obj)
            t0 = time.perf_counter()
            ex = solve_exact(pr, cfg.planner.exact)
            t_exact.append(time.perf_counter() - t0)
            t0 = time.perf_counter()
            ps = solve_ldw_pso(pr, pso_opts)
            t_pso.append(time.perf_counter() - t0)
            ds = dense_search(pr)
            if not ex.feasible:
                infeasible += 1
                continue
            e = float(ex.evaluation.objective)
            if ps.feasible:
                gaps_pso.append(
                    (e - float(ps.evaluation.objective)) / abs(float(ps.evaluation.objective))
                )
            if ds.feasible:
                d = float(ds.evaluation.objective)
                gaps_dense.append((e - d) / abs(d))
        all_exact += t_exact
        all_pso += t_pso
        worst_vs_pso = max(worst_vs_pso, max(gaps_pso, default=-np.inf))
        worst_vs_dense = max(worst_vs_dense, max(gaps_dense, default=-np.inf))
        per_objective[obj] = {
            "median_solve_s_exact": statistics.median(t_exact),
            "median_solve_s_ldw_pso": statistics.median(t_pso),
            "speedup": statistics.median(t_pso) / statistics.median(t_exact),
            "worst_gap_vs_ldw_pso": max(gaps_pso, default=None),
            "median_gap_vs_ldw_pso": statistics.median(gaps_pso) if gaps_pso else None,
            "worst_gap_vs_dense": max(gaps_dense, default=None),
            "infeasible_targets": infeasible,
        }
    print(file=sys.stderr)
    return {
        "targets": len(tg),
        "objectives": list(OBJECTIVES),
        "ldw_pso": {"swarm_size": pso_opts.swarm_size, "iterations": pso_opts.iterations},
        "median_solve_s_exact": statistics.median(all_exact),
        "median_solve_s_ldw_pso": statistics.median(all_pso),
        "speedup": statistics.median(all_pso) / statistics.median(all_exact),
        "worst_gap_vs_ldw_pso": float(worst_vs_pso),
        "worst_gap_vs_dense": float(worst_vs_dense),
        "per_objective": per_objective,
    }
