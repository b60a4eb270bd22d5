"""Attitude-adjustment planning: allocation between the layers, pressures, trajectory."""

from ipc_app.planner.plan import METHODS, LayerPlan, Plan, plan
from ipc_app.planner.problem import OBJECTIVES, PlanningProblem
from ipc_app.planner.trajectory import Trajectory

__all__ = ["METHODS", "OBJECTIVES", "LayerPlan", "Plan", "PlanningProblem", "Trajectory", "plan"]
