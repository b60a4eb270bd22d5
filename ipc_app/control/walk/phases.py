"""The walk's phases by kind (walking.md section 2): :class:`PhaseKind`, and
:data:`PHASES`, the table that gives each phase of the plan its kind and its frames.

The sequencer runs a phase by its kind (:class:`~ipc_app.control.walk.WalkSequencer`:
one method per kind) on the frames its row names; the walk interlocks choose the
phases they watch by kind (:data:`TRAVEL` ... :data:`LIFT`, the keys of each kind).
The backward step runs the same phases in reverse order, each with the frames of its
key (:data:`ipc_app.planner.walk.ORDER`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum

import numpy as np
from numpy.typing import NDArray

from config.schema import ProjectConfig
from ipc_app.planner.force_ramp import ForceRamp
from ipc_app.planner.walk import Move, Phase

FloatArray = NDArray[np.float64]

#: the legs of each frame in the plan's leg order (main 1..4, then sub 1..4)
MAIN = (0, 1, 2, 3)
SUB = (4, 5, 6, 7)


class PhaseKind(Enum):
    """What a phase does (walking.md section 2's table)."""

    #: the travel pair moves the frame in the air along the rails (1, 6)
    TRAVEL = "travel"
    #: a frame's legs extend until each foot touches down, then hold their touch force
    LOWER = "lower"
    #: the touched legs ramp in force control to their preload; the other frame stands
    PRELOAD = "preload"
    #: the preloaded legs ramp to their standing share, the other frame releases the load
    TRANSFER = "transfer"
    #: a frame's legs retract by the clearance
    LIFT = "lift"

    @property
    def ramps_force(self) -> bool:
        """Its frame's legs ramp in force control, the standing frame's unload (the
        body's equilibrium): preload and transfer."""
        return self in (PhaseKind.PRELOAD, PhaseKind.TRANSFER)

    @property
    def sheds_standing_load(self) -> bool:
        """The standing frame only sheds load to the other frame's feet landing, its
        preload and its transfer: its legs are overloaded only above their share
        standing alone (``PhaseRun.standing_share_n``; decision 0037): lowering,
        preload and transfer."""
        return self in (PhaseKind.LOWER, PhaseKind.PRELOAD, PhaseKind.TRANSFER)

    @property
    def holds_twist(self) -> bool:
        """The standing frame stands in position control alone on the invert, its twist
        mode controlled (``WalkSequencer._twist_control``): while the travel pair moves,
        while the other frame lowers and preloads; not in a lift or a transfer."""
        return self in (PhaseKind.TRAVEL, PhaseKind.LOWER, PhaseKind.PRELOAD)


@dataclass(frozen=True)
class PhaseRole:
    """One phase of the step: its kind and its frames (leg indices, :data:`MAIN` or
    :data:`SUB`)."""

    kind: PhaseKind
    #: the frame the phase's name names: the one the pair carries (travel), that lowers,
    #: preloads and takes the load (lower, preload, transfer), that lifts
    frame: tuple[int, ...]
    #: the other frame: it stands on the invert (travel, lower, lift) or releases the
    #: load to ``frame`` (preload, transfer)
    standing: tuple[int, ...]
    #: the releasing legs' position loops are told their oil columns' decompression
    #: (docs/walking.md: in 7c; in 4 it changed the state that M's touch-downs meet)
    decompression_feedforward: bool = False


#: every phase of the plan (:data:`ipc_app.planner.walk.PHASES`) by kind and frames
PHASES: dict[str, PhaseRole] = {
    "1": PhaseRole(PhaseKind.TRAVEL, frame=SUB, standing=MAIN),
    "2": PhaseRole(PhaseKind.LOWER, frame=SUB, standing=MAIN),
    "3": PhaseRole(PhaseKind.PRELOAD, frame=SUB, standing=MAIN),
    "4": PhaseRole(PhaseKind.TRANSFER, frame=SUB, standing=MAIN),
    "5": PhaseRole(PhaseKind.LIFT, frame=MAIN, standing=SUB),
    "6": PhaseRole(PhaseKind.TRAVEL, frame=MAIN, standing=SUB),
    "7a": PhaseRole(PhaseKind.LOWER, frame=MAIN, standing=SUB),
    "7b": PhaseRole(PhaseKind.PRELOAD, frame=MAIN, standing=SUB),
    "7c": PhaseRole(PhaseKind.TRANSFER, frame=MAIN, standing=SUB, decompression_feedforward=True),
    "8": PhaseRole(PhaseKind.LIFT, frame=SUB, standing=MAIN),
}


def keys_of(kind: PhaseKind) -> frozenset[str]:
    """The plan's phase keys of ``kind``."""
    return frozenset(key for key, role in PHASES.items() if role.kind is kind)


#: the phase keys of each kind (what the walk interlocks watch)
TRAVEL = keys_of(PhaseKind.TRAVEL)
LOWER = keys_of(PhaseKind.LOWER)
PRELOAD = keys_of(PhaseKind.PRELOAD)
TRANSFER = keys_of(PhaseKind.TRANSFER)
LIFT = keys_of(PhaseKind.LIFT)


def walk_active_group(cfg: ProjectConfig, key: str) -> list[int]:
    """``can_index`` of the cylinders whose frames run at the loop rate in phase ``key``
    (the active group changes with the phase): while the travel pair moves, it and the
    standing frame's legs; in every other phase the eight legs. The rest (the hanging
    frame while the pair moves, the upper platform) run at their slow cycle and are held
    by ``WalkSequencer.SLOW_HOLD_RAD_S``."""
    main = [cfg.cylinder(c).can_index for c in cfg.layers.lower.cylinders]
    sub = sorted((c for c in cfg.cylinders if c.role == "sub_leg"), key=lambda c: c.position or 0)
    sub_idx = [c.can_index for c in sub]
    travel = [c.can_index for c in cfg.cylinders_by_can_index if c.role == "travel"]
    role = PHASES[key]
    if role.kind is PhaseKind.TRAVEL:
        return travel + (main if role.standing == MAIN else sub_idx)
    return main + sub_idx


@dataclass
class PhaseRun:
    """The present phase as it runs."""

    #: its index in the plan's phases
    index: int
    phase: Phase
    #: machine time it started, s
    started_s: float
    #: its reference clock, s (stops while its group is out of its sync band)
    clock_s: float = 0.0
    #: every rod's position at its start (19,), m
    start_position_m: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: a travel phase's move of the pair (from ``start_position_m``), made at its first cycle
    travel_move: Move | None = None
    #: and each travel rod's share of it (1 each unless S turns in M)
    travel_share: list[float] = field(default_factory=list)
    #: the legs' cap-side forces at its start (8,), N; a force ramp's receiving legs'
    #: from where the ramp (re)started
    start_force_n: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: a preload's or transfer's receiving legs' forces at the ramp's end (8,), N
    target_force_n: FloatArray = field(default_factory=lambda: np.zeros(0))
    #: its planned duration on the reference clock, s
    duration_s: float = 0.0
    #: a preload's or transfer's ramp in time (its duration is ``duration_s``)
    ramp: ForceRamp | None = None
    #: a lowering's legs (in its frame's order): touched down
    touched: list[bool] = field(default_factory=list)
    #: ... their free rod's cap pressure (low-passed while it moves), Pa
    free_cap_pa: list[float] = field(default_factory=list)
    #: ... the force each one holds since its touch-down (from its force then down to the
    #: touch force, :meth:`WalkSequencer._touch_hold`), N
    touch_force_n: list[float] = field(default_factory=list)
    #: ... their free rod's force on the body (low-passed in the air, from the first
    #: cycle; NaN before it), N: what friction and the oil take while it moves
    free_force_n: list[float] = field(default_factory=list)
    #: ... in the fast part, a foot pressing the invert: its force on the body above its
    #: free rod's by :attr:`~WalkSequencer.PRESSING` of its touch force
    pressing: list[bool] = field(default_factory=list)
    #: the lowering is in its slow part (touch-down looked for)
    in_touchdown_window: bool = False
    #: a lowering's legs (in its frame's order): their expected ground's shift from
    #: ``clearance`` below their start, m (the body's motion since they lifted,
    #: :mod:`ipc_app.control.walk.ground`), applied over the lowering's fast part
    ground_shift_m: FloatArray = field(default_factory=lambda: np.zeros(4))
    #: machine time its group left its sync band, s (None: inside)
    out_of_band_since_s: float | None = None
    #: what the standing frame's legs carry alone (where its kind sheds_standing_load), N
    standing_share_n: FloatArray = field(default_factory=lambda: np.zeros(8))
    #: each leg's oil-column stiffness at its rod's position at the phase's start, N/m
    k_oil_n_m: FloatArray = field(default_factory=lambda: np.full(8, math.inf))
    #: a preload's or transfer's releasing legs: their force rate while the receiving
    #: legs ramp, N/s
    release_rate_n_s: FloatArray = field(default_factory=lambda: np.zeros(8))
    #: a preload's or transfer's releasing legs' forces where their rates start (the
    #: phase's start; after a resume, the forces then), N
    release_from_n: FloatArray = field(default_factory=lambda: np.zeros(8))
    #: a transfer's plan line starts here (the plan's preload; after a resume, where
    #: the line stood at the stop) and runs to ``target_force_n`` with the ramp, N
    plan_start_n: FloatArray = field(default_factory=lambda: np.zeros(8))

    @property
    def role(self) -> PhaseRole:
        return PHASES[self.phase.key]

    @property
    def kind(self) -> PhaseKind:
        return PHASES[self.phase.key].kind

    @property
    def progress(self) -> float:
        """The reference clock's share of the duration, 0 to 1; a force ramp's: how far
        along its line."""
        if self.ramp is not None:
            return self.ramp.fraction(self.clock_s)
        return 1.0 if self.duration_s <= 0 else min(1.0, self.clock_s / self.duration_s)

    @property
    def rate_share(self) -> float:
        """A force ramp's rate now as a share of its full rate, 0 to 1."""
        return 0.0 if self.ramp is None else self.ramp.rate_share(self.clock_s)


@dataclass
class PhaseCycle:
    """One cycle of a phase: the measurement, and what the phase asks of the loops
    (its ``_run_*`` method sets the references, the group and whether it is done)."""

    now_s: float
    #: rod positions (19,), m, and chamber pressures (19, 2), Pa
    position_m: FloatArray
    pressure_pa: FloatArray
    #: the legs' cap-side forces (8,), N
    leg_force_n: FloatArray
    #: the legs' forces on the body, at one instant (the checks'), N
    body_force_n: FloatArray
    #: position references (19,), m, and their rates fed forward, m/s
    position_ref_m: FloatArray
    rate_ref_m_s: FloatArray
    #: the plan's leg forces now (8,), N
    plan_force_n: FloatArray
    #: the legs in force control: ``can_index`` -> (force reference, N; its rate, N/s)
    force_ref: dict[int, tuple[float, float]] = field(default_factory=dict)
    #: a rod speed a position loop is told of (a known disturbance), m/s
    known_speed_m_s: dict[int, float] = field(default_factory=dict)
    #: the synchronized group (``can_index``) and its sync band, m
    moving: list[int] = field(default_factory=list)
    sync_band_m: float = 0.0
    finished: bool = False
