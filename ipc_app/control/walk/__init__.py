"""The walk's control (walking.md sections 2, 4 and 5; docs/walking.md, "The step
sequencer"): :class:`WalkSequencer` runs a :class:`~ipc_app.planner.walk.WalkPlan` on
the service's read -> update -> write step.

- :mod:`.phases`: the phases by kind (:class:`PhaseKind`, the table :data:`PHASES`),
  the frames, the active group, a phase as it runs.
- :mod:`.sequencer`: :class:`WalkSequencer`, one method per kind of phase.
- :mod:`.loops`: its loops (position, force, the twist mode, the hold), the machine's
  statics.
- :mod:`.forces`: the legs' force estimates and the body's equilibrium.
- :mod:`.figures`: what the walk interlocks judge each cycle, each step's extremes.
"""

from ipc_app.control.walk.figures import StepFigures, WalkFigures
from ipc_app.control.walk.phases import (
    LIFT,
    LOWER,
    MAIN,
    PHASES,
    PRELOAD,
    SUB,
    TRANSFER,
    TRAVEL,
    PhaseKind,
    PhaseRole,
    walk_active_group,
)
from ipc_app.control.walk.sequencer import WalkSequencer

__all__ = [
    "LIFT",
    "LOWER",
    "MAIN",
    "PHASES",
    "PRELOAD",
    "SUB",
    "TRANSFER",
    "TRAVEL",
    "PhaseKind",
    "PhaseRole",
    "StepFigures",
    "WalkFigures",
    "WalkSequencer",
    "walk_active_group",
]
