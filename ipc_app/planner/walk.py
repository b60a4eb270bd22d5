"""The walk planner: N steps of walking.md section 2, planned and checked before the
first phase starts (docs/walking.md).

From a measured state (``x_S``, the legs' extensions, the upper platform's attitude) it
lays out every phase of every step: what moves, its trajectory (a speed- and
acceleration-limited trapezoid), the expected leg forces (:mod:`ipc_app.model.support`)
and the stability margin, sampled along the whole plan. A plan that breaks a constraint
anywhere is refused with a :class:`Violation`: the constraint, the step, the phase, the
instant, the value and its limit.

Choices where walking.md is silent:
- The body stays level on the base during a walk; the invert under the feet is the base
  plane (the ground offsets of the simulator are what the touch-down handles).
- Moves (travel, lifting, lowering) are trapezoids: the travel pair at
  ``walking.travel_speed_mm_s`` and ``walking.travel_accel_mm_s2``, the legs at
  ``planner.trajectory.max_rod_speed_mm_s`` and ``max_rod_accel_mm_s2``.
- Preload and transfer ramp the leg forces at ``walking.force_ramp_kn_s`` (the largest
  change of any leg sets the duration), a transfer's rate blended in and out
  (:mod:`ipc_app.planner.force_ramp`: one blend longer; the samples are the line's).
  During a transfer the forces move on the straight line from the preloaded to the new
  standing distribution (every point of it is an equilibrium); the transfer ends when
  every releasing leg is at ``unloaded_percent`` of its standing share, the rest is shed
  as it lifts.
- Rails and guides take no travel force: the travel force is what moves the free frame
  (its mass times the acceleration, plus gravity along the base x).
- On a curved axis each step turns by the travel pair's differential
  (:mod:`ipc_app.planner.steering`): a travel phase's ``start_m``/``end_m`` are then each
  rod's (as ``x_S`` plus or minus ``b_T sin psi``), its samples' ``x_s_m`` their mean, and
  the statics and margin take S's legs turned by ``psi`` about S's centre. A step whose
  turn exceeds ``walking.max_yaw_deg``, or whose rods leave the travel's reserve, is
  refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from config import units
from config.derived import travel_reach_m
from config.schema import ProjectConfig
from ipc_app.model.kinematics import Array, fit_layer
from ipc_app.model.support import (
    StandingLoad,
    WalkingMachine,
    cog_projection,
    stability_margin,
    support_forces,
)
from ipc_app.planner.capacity import Duty, pressure_limit_pa, pressure_reason
from ipc_app.planner.force_ramp import TRANSFER_KEYS, ForceRamp, blend_s
from ipc_app.planner.steering import OnAxis, StepTurn, on_axis_at_start, step_turns

_SAMPLES = 41  # samples per phase (the margin and forces are checked at each)

PHASES: dict[str, str] = {
    "1": "advance S",
    "2": "lower S",
    "3": "preload S",
    "4": "transfer to S",
    "5": "lift M",
    "6": "advance M",
    "7a": "lower M",
    "7b": "preload M",
    "7c": "transfer to M",
    "8": "lift S",
}
#: The phases that ramp leg forces: their ``start_m``/``end_m`` are the standing legs'
#: forces (N), not positions.
RAMP_PHASES: frozenset[str] = frozenset({"3", "4", "7b", "7c"})
#: The travel phases' names in a backward step (the other phases keep theirs).
BACK_PHASES: dict[str, str] = {"1": "move S back", "6": "move M back"}
#: The phases of one step in their order: forward (walking.md section 2) and backward
#: (its mirror: the forward step run in reverse, each phase's frames and checks as in
#: the forward phase of the same key, the travel pair moving the other way).
ORDER: dict[str, tuple[str, ...]] = {
    "forward": ("1", "2", "3", "4", "5", "6", "7a", "7b", "7c", "8"),
    "back": ("2", "3", "4", "5", "6", "7a", "7b", "7c", "8", "1"),
}
#: A walk's directions.
DIRECTIONS: tuple[str, ...] = tuple(ORDER)


def phase_name(key: str, direction: str = "forward") -> str:
    """The name of phase ``key`` in a step of ``direction``."""
    return BACK_PHASES.get(key, PHASES[key]) if direction == "back" else PHASES[key]


@dataclass(frozen=True)
class Move:
    """A trapezoidal move of ``distance_m`` within ``v_max``, ``a_max``."""

    distance_m: float
    v_max: float
    a_max: float

    @property
    def duration_s(self) -> float:
        d = abs(self.distance_m)
        if d == 0.0:
            return 0.0
        if d <= self.v_max**2 / self.a_max:  # triangle
            return 2.0 * math.sqrt(d / self.a_max)
        return d / self.v_max + self.v_max / self.a_max

    def _profile(self) -> tuple[float, float, float, float]:
        """``(d, T, v, t_a)``: the distance's size, the duration, the cruise speed and the
        acceleration time."""
        d, T = abs(self.distance_m), self.duration_s
        v = min(self.v_max, math.sqrt(d * self.a_max))
        return d, T, v, v / self.a_max

    def position(self, t: Array) -> Array:
        """Distance covered at ``t`` (signed like ``distance_m``)."""
        d, T, v, ta = self._profile()
        if T == 0.0:
            return np.zeros_like(t)
        t = np.clip(t, 0.0, T)
        s = np.where(
            t < ta,
            0.5 * self.a_max * t**2,
            np.where(
                t <= T - ta,
                0.5 * self.a_max * ta**2 + v * (t - ta),
                d - 0.5 * self.a_max * (T - t) ** 2,
            ),
        )
        return np.asarray(math.copysign(1.0, self.distance_m) * s, dtype=np.float64)

    def position_at(self, t: float) -> float:
        """:meth:`position` at one instant, in scalar arithmetic (the same operations)."""
        d, T, v, ta = self._profile()
        if T == 0.0:
            return 0.0
        t = min(max(t, 0.0), T)
        if t < ta:
            s = 0.5 * self.a_max * (t * t)
        elif t <= T - ta:
            s = 0.5 * self.a_max * ta**2 + v * (t - ta)
        else:
            s = d - 0.5 * self.a_max * ((T - t) * (T - t))
        return math.copysign(1.0, self.distance_m) * s


@dataclass(frozen=True)
class Violation:
    """Why a plan is refused: the first constraint broken along it."""

    constraint: str  #: stability_margin, leg_force_min, pressure, slip, travel_stroke, leg_stroke
    step: int  #: 1-based
    phase: str  #: a key of :data:`PHASES`
    t_s: float  #: from the start of the walk
    value: float  #: SI (m, N, Pa)
    limit: float
    unit: str
    detail: str
    direction: str = "forward"

    @property
    def message(self) -> str:
        return (
            f"{self.constraint}: step {self.step} phase {self.phase} "
            f"({phase_name(self.phase, self.direction)}) "
            f"at t = {self.t_s:.2f} s: {self.detail}"
        )

    def to_dict(self) -> dict[str, Any]:
        return {
            "constraint": self.constraint,
            "step": self.step,
            "phase": self.phase,
            "phase_name": phase_name(self.phase, self.direction),
            "t_s": round(self.t_s, 3),
            "value": self.value,
            "limit": self.limit,
            "unit": self.unit,
            "message": self.message,
        }


@dataclass(frozen=True)
class Phase:
    step: int
    key: str
    t_start_s: float
    duration_s: float
    standing: tuple[str, ...]  #: legs that carry load (ids)
    moving: tuple[str, ...]  #: cylinders in position control
    #: at the start: their positions (x_S for travel; extension), or in a force ramp
    #: (:data:`RAMP_PHASES`) the legs' forces (N)
    start_m: tuple[float, ...]
    end_m: tuple[float, ...]
    t_s: Array  #: sample instants (from the walk's start)
    x_s_m: Array  #: S's position along the rails at the samples
    leg_forces_n: Array  #: (samples, 8) expected leg forces, main 1..4 then sub 1..4
    margin_m: Array  #: stability margin at the samples
    travel_force_n: Array  #: force the travel pair must give at the samples
    friction_capacity_n: Array  #: foot friction of the standing legs at the samples
    direction: str = "forward"  #: of the step it is part of
    #: S's yaw in M at the phase's start and end, rad (:mod:`ipc_app.planner.steering`)
    yaw_rad: tuple[float, float] = (0.0, 0.0)

    @property
    def name(self) -> str:
        return phase_name(self.key, self.direction)

    @property
    def end_x_s_m(self) -> float:
        """A travel's end ``x_S``: its rods' mean."""
        return sum(self.end_m) / len(self.end_m)

    def summary(self, leg_ids: tuple[str, ...]) -> dict[str, Any]:
        """The phase for the plan's JSON: a move's start and end positions in mm
        (``start_mm``, ``end_mm``), a force ramp's forces in kN (``start_kn``, ``end_kn``)."""
        if self.key in RAMP_PHASES:
            ends = {
                "start_kn": [round(v / units.KN, 3) for v in self.start_m],
                "end_kn": [round(v / units.KN, 3) for v in self.end_m],
            }
        else:
            ends = {
                "start_mm": [round(units.to_mm(v), 3) for v in self.start_m],
                "end_mm": [round(units.to_mm(v), 3) for v in self.end_m],
            }
        return {
            "step": self.step,
            "phase": self.key,
            "name": self.name,
            "t_start_s": round(self.t_start_s, 3),
            "duration_s": round(self.duration_s, 3),
            "standing": list(self.standing),
            "moving": list(self.moving),
            **ends,
            "min_stability_margin_m": round(float(self.margin_m.min()), 4),
            "leg_forces_end_kn": {
                cid: round(float(f) / units.KN, 2)
                for cid, f in zip(leg_ids, self.leg_forces_n[-1], strict=True)
            },
            "max_travel_force_kn": round(float(np.abs(self.travel_force_n).max()) / units.KN, 3),
        }


@dataclass
class WalkPlan:
    steps: int
    step_length_m: float
    leg_ids: tuple[str, ...]
    min_margin_limit_m: float
    phases: list[Phase] = field(default_factory=list)
    violations: list[Violation] = field(default_factory=list)
    #: "forward" (x increasing, walking.md section 2) or "back" (its mirror)
    direction: str = "forward"
    #: planned without the workpiece (:class:`~ipc_app.model.support.WalkingMachine`)
    unloaded: bool = False
    #: the load measured on M's legs at the start, which the statics are trimmed to
    standing: StandingLoad | None = None
    #: each step's turn along the axis (:mod:`ipc_app.planner.steering`)
    turns: list[StepTurn] = field(default_factory=list)

    @property
    def distance_m(self) -> float:
        """Signed: the machine's travel in world x (negative walking back)."""
        sign = -1.0 if self.direction == "back" else 1.0
        return sign * self.steps * self.step_length_m

    @property
    def feasible(self) -> bool:
        return not self.violations

    @property
    def refusal(self) -> Violation | None:
        """The binding constraint: the first violation along the plan."""
        return min(self.violations, key=lambda v: v.t_s) if self.violations else None

    @property
    def duration_s(self) -> float:
        last = self.phases[-1]
        return last.t_start_s + last.duration_s

    @property
    def min_margin(self) -> tuple[float, Phase]:
        ph = min(self.phases, key=lambda p: float(p.margin_m.min()))
        return float(ph.margin_m.min()), ph

    def to_dict(self) -> dict[str, Any]:
        margin, where = self.min_margin
        step_time = [
            sum(p.duration_s for p in self.phases if p.step == k) for k in range(1, self.steps + 1)
        ]
        ref = self.refusal
        return {
            "feasible": self.feasible,
            "steps": self.steps,
            "direction": self.direction,
            "unloaded": self.unloaded,
            "distance_m": round(self.distance_m, 6),
            "duration_s": round(self.duration_s, 3),
            "step_duration_s": [round(t, 3) for t in step_time],
            "min_stability_margin_m": round(margin, 4),
            "min_stability_margin_at": {"step": where.step, "phase": where.key},
            "min_stability_margin_limit_m": self.min_margin_limit_m,
            "standing_load": None
            if self.standing is None
            else {
                "weight_kn": round(self.standing.weight_n / units.KN, 2),
                "cog_projection_m": [round(v, 4) for v in self.standing.cog_projection_m],
                "x_s_m": round(self.standing.x_s_m, 4),
            },
            "steering": [t.to_dict() for t in self.turns],
            "refusal": ref.to_dict() if ref is not None else None,
            "violations": [v.to_dict() for v in self.violations[:10]],
            "phases": [p.summary(self.leg_ids) for p in self.phases],
        }


@dataclass(frozen=True)
class WalkStart:
    """The measured state a walk starts from (walking.md section 2's start state)."""

    x_s_m: float
    main_extensions_m: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    upper_extensions_m: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    #: the load M's standing legs measure (None: the YAML's bodies as they are)
    standing: StandingLoad | None = None
    #: where the machine stands against the design axis (None: on it at ring 1's rear
    #: joint face, :func:`~ipc_app.planner.steering.on_axis_at_start`)
    on_axis: OnAxis | None = None


def start_state(cfg: ProjectConfig) -> WalkStart:
    """The nominal start: ``x_S`` at the rear end of the step, legs at mid-stroke."""
    assert cfg.walking is not None
    return WalkStart(x_s_m=-cfg.walking.step_length_m / 2)


class _Planner:
    def __init__(
        self, cfg: ProjectConfig, start: WalkStart, direction: str, unloaded: bool
    ) -> None:
        _, self.walk = cfg.walking_sections()
        if direction not in ORDER:
            raise ValueError(f"direction must be one of {', '.join(ORDER)}, got {direction!r}")
        self.cfg = cfg
        self.direction = direction
        up = cfg.layers.upper
        fit = fit_layer(np.asarray(start.upper_extensions_m), up.a_m, up.b_m)
        self.machine = WalkingMachine(
            cfg, float(fit.roll), float(fit.pitch), unloaded, start.standing
        )
        self.start = start
        subs = sorted(
            (c for c in cfg.cylinders if c.role == "sub_leg"), key=lambda c: c.position or 0
        )
        self.leg_ids = tuple(cfg.layers.lower.cylinders) + tuple(c.id for c in subs)
        # the rod with the lower can_index first: on the right (steering's sign)
        self.travel_ids = tuple(c.id for c in cfg.cylinders_by_can_index if c.role == "travel")
        self.b_t = self.walk.travel_half_span_m
        #: S's yaw in M now, rad (the statics' S legs turn with it)
        self.yaw = 0.0
        legs = [cfg.cylinder(cid) for cid in self.leg_ids]
        self.cap_area = np.array([c.cap_area_m2 for c in legs])
        self.limit_pa: dict[Duty, float] = {
            d: pressure_limit_pa(cfg, d) for d in ("moves", "holds")
        }
        self.leg_limit = np.array([c.stroke_m / 2 - cfg.layers.lower.reserve_m for c in legs])
        self.x_s_limit = travel_reach_m(cfg)
        traj = cfg.planner.trajectory
        self.travel_move = (self.walk.travel_speed_m_s, self.walk.travel_accel_m_s2)
        self.leg_move = (traj.max_rod_speed_m_s, traj.max_rod_accel_m_s2)
        self.ramp_blend_s = blend_s(cfg)
        self.g = self.machine.g_base
        self.weight_n = self.machine.mass_kg * -float(self.g.z)
        self.plan = WalkPlan(
            0, self.walk.step_length_m, self.leg_ids, self.walk.min_stability_margin_m,
            direction=direction, unloaded=unloaded, standing=start.standing,
        )  # fmt: skip
        self.t = 0.0

    # ----------------------------------------------------------------- statics

    def forces(self, x_s: float, legs: list[int]) -> Array:
        """Expected forces (8,) with ``legs`` (indices) carrying the machine."""
        return self.forces_at(x_s, self.yaw, legs)

    def forces_at(self, x_s: float, yaw: float, legs: list[int]) -> Array:
        """:meth:`forces` with S yawed by ``yaw`` in M."""
        out = np.zeros(8)
        pts = self.machine.legs_xy(x_s, yaw)[legs]
        out[legs] = support_forces(pts, self.machine.mass_kg, self.machine.cog(x_s), self.g)
        return out

    def preloaded(self, x_s: float, standing: list[int], touching: list[int]) -> Array:
        """``touching`` at preload_percent of their eight-leg share, ``standing`` the rest."""
        share8 = self.forces(x_s, list(range(8)))
        out = np.zeros(8)
        out[touching] = share8[touching] * self.walk.preload_percent / 100.0
        # the standing legs carry what is left (minimum norm over them)
        four = self.forces(x_s, standing)
        pts = self.machine.legs_xy(x_s, self.yaw)
        a_t = np.vstack([np.ones(4), pts[touching, 1], -pts[touching, 0]])
        a_s = np.vstack([np.ones(4), pts[standing, 1], -pts[standing, 0]])
        residual = a_t @ out[touching]
        out[standing] = four[standing] - a_s.T @ np.linalg.solve(a_s @ a_s.T, residual)
        return out

    def margin(self, x_s: float, legs: list[int], yaw: float | None = None) -> float:
        point = cog_projection(self.machine.cog(x_s), self.g)
        pts = self.machine.legs_xy(x_s, self.yaw if yaw is None else yaw)
        return stability_margin(pts[legs], point)

    # ----------------------------------------------------------------- phases

    def add(
        self,
        step: int,
        key: str,
        duration: float,
        x_s: Array,
        forces: Array,
        support: list[int],
        moving: tuple[str, ...],
        start: tuple[float, ...],
        end: tuple[float, ...],
        moving_mass: float = 0.0,
        accel: Array | None = None,
        min_force_n: float | None = None,
        yaw: Array | None = None,
    ) -> None:
        n = len(x_s)
        t = self.t + np.linspace(0.0, duration, n)
        yaws = np.full(n, self.yaw) if yaw is None else yaw
        margin = np.array(
            [self.margin(float(x), support, float(a)) for x, a in zip(x_s, yaws, strict=True)]
        )
        normal = forces[:, support].sum(axis=1)
        a = np.zeros(n) if accel is None else accel
        travel = moving_mass * (a + float(self.g.x))
        capacity = self.walk.foot_friction_coefficient * normal
        phase = Phase(
            step, key, self.t, duration, tuple(self.leg_ids[i] for i in support), moving,
            start, end, t, x_s, forces, margin, travel, capacity, self.direction,
            (float(yaws[0]), float(yaws[-1])),
        )  # fmt: skip
        self.plan.phases.append(phase)
        self.check(phase, support, min_force_n)
        self.t += duration

    def violation(
        self,
        phase: Phase,
        k: int,
        constraint: str,
        value: float,
        limit: float,
        unit: str,
        detail: str,
    ) -> None:
        self.plan.violations.append(
            Violation(
                constraint, phase.step, phase.key, float(phase.t_s[k]), value, limit, unit,
                detail, self.direction,
            )
        )  # fmt: skip

    def check(self, phase: Phase, support: list[int], min_force_n: float | None) -> None:
        """The constraints at every sample. ``min_force_n``: the least force of a standing
        leg (default ``planner.min_rod_force_kn``; 0 while legs are being loaded or
        unloaded in force control)."""
        cfg, walk = self.cfg, self.walk
        k = int(np.argmin(phase.margin_m))
        if phase.margin_m[k] < walk.min_stability_margin_m - 1e-9:
            self.violation(
                phase, k, "stability_margin", float(phase.margin_m[k]),
                walk.min_stability_margin_m, "m",
                f"stability margin {phase.margin_m[k]:.3f} m below "
                f"{walk.min_stability_margin_m:.3f} m (x_S {phase.x_s_m[k]:+.3f} m)",
            )  # fmt: skip
        f_min = cfg.planner.min_rod_force_n if min_force_n is None else min_force_n
        standing = phase.leg_forces_n[:, support]
        kk, jj = np.unravel_index(int(np.argmin(standing)), standing.shape)
        if standing[kk, jj] < f_min - 1e-6:
            cid = self.leg_ids[support[int(jj)]]
            self.violation(
                phase, int(kk), "leg_force_min", float(standing[kk, jj]), f_min, "N",
                f"{cid} force {standing[kk, jj] / units.KN:.1f} kN below "
                f"{f_min / units.KN:.1f} kN (lifts off)",
            )  # fmt: skip
        # capacity (ipc_app.planner.capacity): a leg lifted or lowered in position control
        # moves its load (its foot); standing legs hold theirs, and legs in a force ramp
        # take theirs at the ramp's trickle of flow
        moves = [phase.key not in RAMP_PHASES and cid in phase.moving for cid in self.leg_ids]
        limit = np.array([self.limit_pa["moves" if m else "holds"] for m in moves])
        pressure = phase.leg_forces_n / self.cap_area
        kk, jj = np.unravel_index(int(np.argmax(pressure - limit)), pressure.shape)
        why = pressure_reason(
            cfg, self.leg_ids[int(jj)], float(phase.leg_forces_n[kk, jj]),
            float(pressure[kk, jj]), "moves" if moves[int(jj)] else "holds",
        )  # fmt: skip
        if why is not None:
            self.violation(
                phase, int(kk), "pressure", float(pressure[kk, jj]), float(limit[jj]), "Pa",
                why.removeprefix("pressure: "),
            )  # fmt: skip
        slip = np.abs(phase.travel_force_n) - phase.friction_capacity_n
        k = int(np.argmax(slip))
        if slip[k] > 0:
            self.violation(
                phase, k, "slip", float(abs(phase.travel_force_n[k])),
                float(phase.friction_capacity_n[k]), "N",
                f"travel force {abs(phase.travel_force_n[k]) / units.KN:.2f} kN above the "
                f"feet's friction {phase.friction_capacity_n[k] / units.KN:.2f} kN",
            )  # fmt: skip

    def rods(self, x_s: float, yaw: float) -> tuple[float, float]:
        """The travel rods (as ``x_S``) with S at ``x_s`` yawed by ``yaw``: right, left."""
        d = self.b_t * math.sin(yaw)
        return (x_s + d, x_s - d)

    def travel(
        self, step: int, key: str, x0: float, x1: float, moving_mass: float, legs: list[int],
        yaw1: float = 0.0,
    ) -> None:  # fmt: skip
        """The travel pair from ``x0`` to ``x1``, S's yaw in M from now to ``yaw1`` in
        proportion to the distance."""
        yaw0 = self.yaw
        move = Move(x1 - x0, *self.travel_move)
        tt = np.linspace(0.0, move.duration_s, _SAMPLES)
        x_s = x0 + move.position(tt)
        accel = np.gradient(np.gradient(x_s, tt), tt) if move.duration_s > 0 else np.zeros(_SAMPLES)
        # M moving relative to standing S: in the world M's acceleration is -x_S''
        accel = accel if key == "1" else -accel
        frac = (x_s - x0) / (x1 - x0) if x1 != x0 else np.ones(_SAMPLES)
        yaws = yaw0 + (yaw1 - yaw0) * frac
        forces = np.array(
            [self.forces_at(float(x), float(a), legs) for x, a in zip(x_s, yaws, strict=True)]
        )
        self.add(
            step, key, move.duration_s, x_s, forces, legs, self.travel_ids,
            self.rods(x0, yaw0), self.rods(x1, yaw1), moving_mass, accel, yaw=yaws,
        )  # fmt: skip
        self.yaw = yaw1
        self.check_turn(self.plan.phases[-1], x1, yaw1)

    def check_turn(self, phase: Phase, x_s: float, yaw: float) -> None:
        """S's yaw in M within ``walking.max_yaw_deg``, its rods within the reserve."""
        walk, last = self.walk, _SAMPLES - 1
        if abs(yaw) > walk.max_yaw_rad + 1e-12:
            turn = self.plan.turns[phase.step - 1]
            self.violation(
                phase, last, "yaw", abs(yaw), walk.max_yaw_rad, "rad",
                f"S turns {units.to_deg(abs(yaw)):.3f} deg in M (the axis "
                f"{units.to_deg(turn.axis_turn_rad):+.3f} deg, steering back "
                f"{units.to_deg(turn.correction_rad):+.3f} deg) beyond walking.max_yaw_deg "
                f"{walk.max_yaw_deg:g}",
            )  # fmt: skip
        rods = self.rods(x_s, yaw)
        far = max(rods, key=abs)
        if abs(far) > self.x_s_limit + 1e-9:
            self.violation(
                phase, last, "travel_stroke", abs(far), self.x_s_limit, "m",
                f"a travel rod at {units.to_mm(far):+.1f} mm (x_S {units.to_mm(x_s):+.1f} mm, "
                f"S turned {units.to_deg(yaw):+.3f} deg) beyond the travel's "
                f"±{units.to_mm(self.x_s_limit):.1f} mm (walking.travel_reserve_mm)",
            )  # fmt: skip

    def legs_move(
        self, step: int, key: str, x_s: float, moving: list[int], delta: float,
        start_ext: Array, support: list[int], forces: Array,
    ) -> Array:  # fmt: skip
        move = Move(delta, *self.leg_move)
        end_ext = start_ext.copy()
        end_ext[moving] += delta
        ids = tuple(self.leg_ids[i] for i in moving)
        self.add(
            step, key, move.duration_s, np.full(_SAMPLES, x_s), np.tile(forces, (_SAMPLES, 1)),
            support, ids, tuple(start_ext[moving]), tuple(end_ext[moving]),
        )  # fmt: skip
        bad = np.abs(end_ext) > self.leg_limit + 1e-9
        if bad.any():
            j = int(np.argmax(np.abs(end_ext) - self.leg_limit))
            phase = self.plan.phases[-1]
            self.violation(
                phase, _SAMPLES - 1, "leg_stroke", float(end_ext[j]), float(self.leg_limit[j]), "m",
                f"{self.leg_ids[j]} extension {units.to_mm(end_ext[j]):+.1f} mm beyond the "
                f"planning limit ±{units.to_mm(self.leg_limit[j]):.1f} mm",
            )  # fmt: skip
        return end_ext

    def ramp(
        self, step: int, key: str, x_s: float, f0: Array, f1: Array, support: list[int]
    ) -> None:
        linear_s = float(np.abs(f1 - f0).max()) / self.walk.force_ramp_n_s
        blend = self.ramp_blend_s if key in TRANSFER_KEYS else 0.0
        duration = ForceRamp.of(linear_s, blend).duration_s
        lam = np.linspace(0.0, 1.0, _SAMPLES)[:, None]
        forces = f0[None, :] * (1 - lam) + f1[None, :] * lam
        ids = tuple(self.leg_ids[i] for i in support)
        self.add(
            step, key, duration, np.full(_SAMPLES, x_s), forces, support, ids,
            tuple(f0[support]), tuple(f1[support]), min_force_n=0.0,
        )  # fmt: skip

    def transfer_end(
        self, pre: Array, final: Array, releasing: list[int], standing: Array
    ) -> Array:
        """The point on the line ``pre -> final`` where every releasing leg is at
        ``unloaded_percent`` of its standing share."""
        unloaded = self.walk.unloaded_percent / 100.0
        lam = 0.0
        for i in releasing:
            if pre[i] > unloaded * standing[i]:
                lam = max(lam, 1.0 - unloaded * standing[i] / pre[i])
        return pre + lam * (final - pre)

    def run(self, steps: int) -> WalkPlan:
        walk = self.walk
        self.plan.steps = steps
        on_axis = self.start.on_axis or on_axis_at_start(self.cfg)
        self.plan.turns = step_turns(self.cfg, on_axis, steps, self.direction)
        main, sub, every = [0, 1, 2, 3], [4, 5, 6, 7], list(range(8))
        rear, front = -walk.step_length_m / 2, walk.step_length_m / 2
        x_s = self.start.x_s_m
        if abs(x_s) > self.x_s_limit + 1e-9:
            self.plan.violations.append(
                Violation(
                    "travel_stroke", 1, ORDER[self.direction][0], 0.0, x_s, self.x_s_limit, "m",
                    f"measured x_S {units.to_mm(x_s):+.1f} mm beyond the travel's "
                    f"±{units.to_mm(self.x_s_limit):.1f} mm", self.direction,
                )
            )  # fmt: skip
            return self.plan
        ext = np.zeros(8)
        ext[:4] = self.start.main_extensions_m
        ext[4:] = ext[:4] - walk.clearance_m  # S lifted by the clearance
        m_main, m_sub = self.machine.main.mass_kg, self.machine.sub.mass_kg
        # Forward (walking.md section 2): S to the front, S takes the load, M to the
        # rear end (M moves forward), M takes the load. Back: the same phases in reverse
        # order from the same start state: S takes the load where it is, M moves back
        # (x_S to the front end), M takes the load, S moves back (x_S to the rear end).
        # Each phase of a key stands and moves the same frames in both directions.
        back = self.direction == "back"
        for step in range(1, steps + 1):
            turn = self.plan.turns[step - 1].turn_rad
            if not back:
                self.travel(step, "1", x_s, front, m_sub, main, turn)
                x_s = front
            f_m = self.forces(x_s, main)
            ext = self.legs_move(step, "2", x_s, sub, walk.clearance_m, ext, main, f_m)
            pre = self.preloaded(x_s, main, sub)
            self.ramp(step, "3", x_s, f_m, pre, every)
            f_s = self.forces(x_s, sub)
            end = self.transfer_end(pre, f_s, main, f_m)
            self.ramp(step, "4", x_s, pre, end, every)
            ext = self.legs_move(step, "5", x_s, main, -walk.clearance_m, ext, sub, f_s)
            x_to = front if back else rear
            self.travel(step, "6", x_s, x_to, m_main, sub, -turn if back else 0.0)
            x_s = x_to
            f_s = self.forces(x_s, sub)
            ext = self.legs_move(step, "7a", x_s, main, walk.clearance_m, ext, sub, f_s)
            pre = self.preloaded(x_s, sub, main)
            self.ramp(step, "7b", x_s, f_s, pre, every)
            f_m = self.forces(x_s, main)
            end = self.transfer_end(pre, f_m, sub, f_s)
            self.ramp(step, "7c", x_s, pre, end, every)
            ext = self.legs_move(step, "8", x_s, sub, -walk.clearance_m, ext, main, f_m)
            if back:
                self.travel(step, "1", x_s, rear, m_sub, main)
                x_s = rear
        return self.plan


def plan_walk(
    cfg: ProjectConfig,
    steps: int,
    start: WalkStart | None = None,
    *,
    direction: str = "forward",
    unloaded: bool = False,
) -> WalkPlan:
    """Plan ``steps`` steps from ``start`` (default: :func:`start_state`), ``direction``
    one of :data:`DIRECTIONS`; ``unloaded``: the statics without the workpiece."""
    if steps < 1:
        raise ValueError(f"steps must be at least 1, got {steps}")
    start = start if start is not None else start_state(cfg)
    planner = _Planner(cfg, start, direction, unloaded)
    return planner.run(steps)
