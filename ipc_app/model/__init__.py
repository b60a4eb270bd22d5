"""The reconstructed W-ARa model (../shared/design/model.md sections 1-5): the one
implementation of the kinematics, composition and statics that planner, controller and
service share."""

from ipc_app.model.composition import check_attitude, solve_lower, target_in_base
from ipc_app.model.kinematics import (
    attitude_matrix,
    coplanarity_distance,
    extensions,
    fit_layer,
    normal,
    twist,
)
from ipc_app.model.statics import MachineStatics, rod_forces

__all__ = [
    "MachineStatics",
    "attitude_matrix",
    "check_attitude",
    "coplanarity_distance",
    "extensions",
    "fit_layer",
    "normal",
    "rod_forces",
    "solve_lower",
    "target_in_base",
    "twist",
]
