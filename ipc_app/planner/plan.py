"""Plan one attitude adjustment: allocation, pressures, trajectory.

>>> from config import load_project
>>> from ipc_app.planner import plan
>>> p = plan(load_project(), roll_deg=-3.0, pitch_deg=2.0)
>>> p.feasible, round(p.attitude_error_rad, 12)
(True, 0.0)
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike

from config import units
from config.schema import ProjectConfig
from ipc_app.model.composition import check_attitude
from ipc_app.planner.exact import Solution, solve_exact
from ipc_app.planner.ldw_pso import solve_ldw_pso
from ipc_app.planner.problem import OBJECTIVE_UNITS, Objective, PlanningProblem
from ipc_app.planner.trajectory import Trajectory, plan_trajectory

Method = Literal["exact", "ldw_pso"]
METHODS: tuple[Method, ...] = ("exact", "ldw_pso")


@dataclass(frozen=True)
class LayerPlan:
    roll_rad: float
    pitch_rad: float
    displacement_m: tuple[float, float, float, float]  # from mid-stroke, cylinders 1-4
    force_n: tuple[float, float, float, float]
    pressure_pa: tuple[float, float, float, float]
    cylinders: tuple[str, str, str, str]


@dataclass(frozen=True)
class Plan:
    """The result of one planning run (SI units; :meth:`to_dict` gives the CLI's JSON)."""

    feasible: bool
    method: Method
    objective: Objective
    objective_value: float
    target_roll_rad: float
    target_pitch_rad: float
    upper: LayerPlan
    lower: LayerPlan
    sum_pressure_pa: float
    peak_pressure_pa: float
    attitude_error_rad: float
    yaw_residual_rad: float
    achieved_roll_rad: float
    achieved_pitch_rad: float
    solve_time_s: float
    evaluations: int
    trajectory: Trajectory | None
    reasons: list[str] = field(default_factory=list)
    #: the assembly task the adjustment serves (``task.assembly_time_min``), s: the paper
    #: states a solve time as a share of it (Table 2: below 0.03 % of a 5 min task)
    task_time_s: float = math.nan

    @property
    def solve_time_share_percent(self) -> float:
        """The solve time as a share of the assembly task's time, %."""
        return 100.0 * self.solve_time_s / self.task_time_s

    @property
    def trajectory_duration_s(self) -> float:
        return self.trajectory.duration_s if self.trajectory is not None else 0.0

    def to_dict(self) -> dict[str, Any]:
        def layer(lp: LayerPlan) -> dict[str, Any]:
            return {
                "roll_deg": units.to_deg(lp.roll_rad),
                "pitch_deg": units.to_deg(lp.pitch_rad),
                "displacement_m": list(lp.displacement_m),
                "force_kn": [units.to_kn(f) for f in lp.force_n],
                "cylinders": list(lp.cylinders),
            }

        traj: dict[str, Any] | None = None
        if self.trajectory is not None:
            tr = self.trajectory
            traj = {
                "profile": tr.profile,
                "duration_s": tr.duration_s,
                "samples": int(tr.t.size),
                "max_rod_speed_mm_s": units.to_mm(tr.max_rod_speed_m_s),
                "max_rod_accel_mm_s2": units.to_mm(tr.max_rod_accel_m_s2),
                "max_pump_flow_l_min": tr.max_pump_flow_m3_s / units.L_PER_MIN,
                "feasible": tr.feasible,
            }
        return {
            "feasible": self.feasible,
            "method": self.method,
            "objective": self.objective,
            "objective_value": self.objective_value,
            "objective_unit": OBJECTIVE_UNITS[self.objective],
            "target": {
                "roll_deg": units.to_deg(self.target_roll_rad),
                "pitch_deg": units.to_deg(self.target_pitch_rad),
            },
            "achieved": {
                "roll_deg": units.to_deg(self.achieved_roll_rad),
                "pitch_deg": units.to_deg(self.achieved_pitch_rad),
            },
            "upper": layer(self.upper),
            "lower": layer(self.lower),
            "pressure_mpa": {
                "upper": [units.to_mpa(p) for p in self.upper.pressure_pa],
                "lower": [units.to_mpa(p) for p in self.lower.pressure_pa],
            },
            "sum_pressure_mpa": units.to_mpa(self.sum_pressure_pa),
            "peak_pressure_mpa": units.to_mpa(self.peak_pressure_pa),
            "attitude_error_rad": self.attitude_error_rad,
            "yaw_residual_deg": units.to_deg(self.yaw_residual_rad),
            "trajectory_duration_s": self.trajectory_duration_s,
            "trajectory": traj,
            "solve_time_s": self.solve_time_s,
            "solve_time_share_of_task_percent": self.solve_time_share_percent,
            "evaluations": self.evaluations,
            "reasons": list(self.reasons),
        }


def _layer(sol: Solution, which: str, ids: tuple[str, str, str, str]) -> LayerPlan:
    ev = sol.evaluation
    d = np.asarray(getattr(ev, f"d_{which}"), float)
    f = np.asarray(getattr(ev, f"f_{which}"), float)
    p = np.asarray(getattr(ev, f"p_{which}"), float)

    def four(a: np.ndarray) -> tuple[float, float, float, float]:
        return (float(a[0]), float(a[1]), float(a[2]), float(a[3]))

    return LayerPlan(
        float(getattr(ev, f"{which}_roll")),
        float(getattr(ev, f"{which}_pitch")),
        four(d),
        four(f),
        four(p),
        ids,
    )


def plan(
    cfg: ProjectConfig,
    roll_deg: float,
    pitch_deg: float,
    *,
    objective: Objective | None = None,
    method: Method | None = None,
    seed: int | None = None,
    start_upper_m: ArrayLike = (0.0, 0.0, 0.0, 0.0),
    start_lower_m: ArrayLike = (0.0, 0.0, 0.0, 0.0),
    with_trajectory: bool = True,
) -> Plan:
    """Plan the adjustment to workpiece attitude (roll, pitch) from a start configuration.

    ``start_*_m``: measured extensions from mid-stroke of cylinders 1-4 of each layer.
    ``objective``/``method`` default to the project's ``planner`` section; ``seed``
    overrides ``planner.ldw_pso.seed``.
    """
    if not (abs(roll_deg) < 90 and abs(pitch_deg) < 90):
        raise ValueError(f"target roll/pitch must be within ±90 deg, got ({roll_deg}, {pitch_deg})")
    obj: Objective = objective or cfg.planner.objective
    meth: Method = method or cfg.planner.method
    if meth not in METHODS:
        raise ValueError(f"unknown method {meth!r}; expected one of {METHODS}")
    roll, pitch = units.deg(roll_deg), units.deg(pitch_deg)
    problem = PlanningProblem(cfg, roll, pitch, obj, start_upper_m, start_lower_m)
    t0 = time.perf_counter()
    if meth == "exact":
        sol = solve_exact(problem, cfg.planner.exact)
    else:
        sol = solve_ldw_pso(problem, cfg.planner.ldw_pso, seed)
    solve_time = time.perf_counter() - t0
    ev = sol.evaluation
    lower = _layer(sol, "lower", cfg.layers.lower.cylinders)
    upper = _layer(sol, "upper", cfg.layers.upper.cylinders)
    check = check_attitude(
        (cfg.base.roll_rad, cfg.base.pitch_rad),
        (lower.roll_rad, lower.pitch_rad),
        (upper.roll_rad, upper.pitch_rad),
        (roll, pitch),
    )
    reasons = [] if sol.feasible else problem.reasons(ev)
    feasible = sol.feasible
    if feasible and check.error_rad > cfg.planner.attitude_tolerance_rad:
        feasible = False
        reasons.append(
            f"attitude: workpiece normal misses the target by {check.error_rad:.3e} rad "
            f"(tolerance {cfg.planner.attitude_tolerance_rad:.1e} rad)"
        )
    trajectory = None
    if with_trajectory and feasible:
        trajectory = plan_trajectory(
            problem,
            (lower.roll_rad, lower.pitch_rad),
            (upper.roll_rad, upper.pitch_rad),
            cfg.planner.trajectory,
        )
        if not trajectory.feasible:
            feasible = False
            reasons.extend(trajectory.reasons)
    return Plan(
        feasible=feasible,
        method=meth,
        objective=obj,
        objective_value=float(ev.objective),
        target_roll_rad=roll,
        target_pitch_rad=pitch,
        upper=upper,
        lower=lower,
        sum_pressure_pa=float(ev.sum_pressure),
        peak_pressure_pa=float(ev.peak_pressure),
        attitude_error_rad=check.error_rad,
        yaw_residual_rad=check.yaw_residual_rad,
        achieved_roll_rad=check.roll,
        achieved_pitch_rad=check.pitch,
        solve_time_s=solve_time,
        evaluations=sol.evaluations,
        trajectory=trajectory,
        reasons=reasons,
        task_time_s=60.0 * cfg.task.assembly_time_min,
    )
