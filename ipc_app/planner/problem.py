"""The allocation problem of one attitude adjustment (model.md sections 4-6).

A candidate is the pair of upper extensions ``(d1_U, d2_U)``: under the linkage
(``d3 = -d1``, ``d4 = -d2``, heave 0) they fix the upper attitude exactly
(``sin(pitch_U) = (d2 - d1) / 2a``, ``sin(roll_U) cos(pitch_U) = (d1 + d2) / 2b``), and the
upper stroke constraint is the square ``|d1|, |d2| <= stroke/2 - reserve``. The lower
attitude follows from the composition, then the statics give the eight rod forces.

:meth:`PlanningProblem.evaluate` is vectorized over candidates; both planners and the
trajectory check call it, so there is one implementation of objective and constraints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike

from config import units
from config.schema import ProjectConfig
from ipc_app.model.composition import solve_lower, target_in_base
from ipc_app.model.kinematics import (
    Array,
    BoolArray,
    coplanarity_distance,
    extensions,
    linked_attitude,
)
from ipc_app.model.statics import MachineStatics
from ipc_app.planner.capacity import pressure_limit_pa, pressure_reason

Objective = Literal["sum_pressure", "peak_pressure", "pump_energy"]
OBJECTIVES: tuple[Objective, ...] = ("sum_pressure", "peak_pressure", "pump_energy")
OBJECTIVE_UNITS = {"sum_pressure": "Pa", "peak_pressure": "Pa", "pump_energy": "J"}

#: Violation assigned where the composition has no solution (target out of reach).
UNSOLVABLE = 1e3
#: Dimensionless violation below which a candidate counts as feasible: constraints hold
#: to 1e-12 of their scale (stroke limit, mean rod force, pressure limit), far below
#: any sensor's resolution, so that vertex solutions found by Newton steps are accepted.
FEASIBILITY_TOLERANCE = 1e-12


def path_limits(start: ArrayLike, limit_m: float, half_strokes_m: ArrayLike) -> np.ndarray:
    """Per cylinder, how far from mid-stroke a trajectory from ``start`` may go (m).

    The planning limit (stroke/2 - reserve), or, for a rod that starts beyond it inside
    its stroke (a hold that settled a little past a plan that ended at the limit, or
    a move stopped in the reserve), the start itself: a move may begin in the reserve
    and come back out of it, never go deeper. The target itself is held to the limit.
    """
    d = np.abs(np.asarray(start, dtype=float).reshape(4))
    return np.where(d < np.asarray(half_strokes_m, float), np.maximum(d, limit_m), limit_m)


@dataclass(frozen=True)
class Evaluation:
    """Everything the planner knows about a batch of candidates (leading shape ``(...)``)."""

    upper_roll: Array
    upper_pitch: Array
    lower_roll: Array
    lower_pitch: Array
    d_upper: Array  # (..., 4) m from mid-stroke
    d_lower: Array  # (..., 4)
    f_upper: Array  # (..., 4) N
    f_lower: Array  # (..., 4)
    p_upper: Array  # (..., 4) Pa cap side
    p_lower: Array  # (..., 4)
    sum_pressure: Array
    peak_pressure: Array
    pump_energy: Array
    objective: Array
    violation: Array  # >= 0, dimensionless; 0 exactly where every constraint holds
    solvable: BoolArray

    @property
    def feasible(self) -> BoolArray:
        return self.violation <= FEASIBILITY_TOLERANCE


class PlanningProblem:
    """One target, one start configuration, one objective."""

    def __init__(
        self,
        cfg: ProjectConfig,
        roll: float,
        pitch: float,
        objective: Objective,
        start_upper: ArrayLike = (0.0, 0.0, 0.0, 0.0),
        start_lower: ArrayLike = (0.0, 0.0, 0.0, 0.0),
    ) -> None:
        if objective not in OBJECTIVES:
            raise ValueError(f"unknown objective {objective!r}; expected one of {OBJECTIVES}")
        self.cfg = cfg
        self.roll, self.pitch = float(roll), float(pitch)
        self.objective_name: Objective = objective
        lo, up = cfg.layers.lower, cfg.layers.upper
        self.a_upper, self.b_upper = up.a_m, up.b_m
        self.a_lower, self.b_lower = lo.a_m, lo.b_m
        self.limit_upper = up.extension_limit_m
        self.limit_lower = lo.extension_limit_m
        self.area_upper = np.array([cfg.cylinder(c).cap_area_m2 for c in up.cylinders])
        self.area_lower = np.array([cfg.cylinder(c).cap_area_m2 for c in lo.cylinders])
        self.start_upper = np.asarray(start_upper, dtype=float).reshape(4)
        self.start_lower = np.asarray(start_lower, dtype=float).reshape(4)
        half_upper = [cfg.cylinder(c).stroke_m / 2 for c in up.cylinders]
        half_lower = [cfg.cylinder(c).stroke_m / 2 for c in lo.cylinders]
        self.path_limit_upper = path_limits(self.start_upper, self.limit_upper, half_upper)
        self.path_limit_lower = path_limits(self.start_lower, self.limit_lower, half_lower)
        self.f_min = cfg.planner.min_rod_force_n
        #: what a cylinder can get: supply less the load-sensing margin (or its rating)
        self.p_limit = pressure_limit_pa(cfg)
        self.dp_margin = cfg.hydraulics.load_sensing_margin_pa
        self.coplanarity_tol = cfg.planner.coplanarity_tolerance_m
        self.statics = MachineStatics(cfg)
        self.v = target_in_base(cfg.base.roll_rad, cfg.base.pitch_rad, self.roll, self.pitch)
        # Scale of a rod force, to make lift-off violations dimensionless.
        f_level, _ = self.statics.forces(0.0, 0.0, 0.0, 0.0)
        self.force_scale = float(np.mean(f_level))

    # ------------------------------------------------------------------ geometry

    def upper_attitude(self, d1: ArrayLike, d2: ArrayLike) -> tuple[Array, Array]:
        """Upper (roll, pitch) of the linked layer with extensions d1, d2 (exact inverse)."""
        return linked_attitude(d1, d2, self.a_upper, self.b_upper)

    def evaluate(self, d1: ArrayLike, d2: ArrayLike) -> Evaluation:
        """Evaluate candidates given by the upper extensions of cylinders 1 and 2."""
        ur, upi = self.upper_attitude(d1, d2)
        low = solve_lower(ur, upi, self.v)
        return self.evaluate_attitudes(low.roll, low.pitch, ur, upi, low.solvable)

    def evaluate_attitudes(
        self,
        lower_roll: ArrayLike,
        lower_pitch: ArrayLike,
        upper_roll: ArrayLike,
        upper_pitch: ArrayLike,
        solvable: ArrayLike = True,
        d_lower: Array | None = None,
        d_upper: Array | None = None,
    ) -> Evaluation:
        """Objective and constraints for given layer attitudes (linked, heave 0).

        ``d_lower``/``d_upper`` may be given to check extensions that are not exactly the
        linked ones (trajectory samples from a twisted start).
        """
        lr, lp = np.asarray(lower_roll, float), np.asarray(lower_pitch, float)
        ur, up = np.asarray(upper_roll, float), np.asarray(upper_pitch, float)
        solv = np.broadcast_to(np.asarray(solvable, bool), np.broadcast(lr, ur).shape)
        du = extensions(ur, up, self.a_upper, self.b_upper) if d_upper is None else d_upper
        dl = extensions(lr, lp, self.a_lower, self.b_lower) if d_lower is None else d_lower
        fl, fu = self.statics.forces(lr, lp, ur, up)
        pu = fu / self.area_upper
        pl = fl / self.area_lower
        sum_p = pu.sum(-1) + pl.sum(-1)
        peak = np.maximum(pu.max(-1), pl.max(-1))
        moved = (self.area_upper * np.maximum(du - self.start_upper, 0.0)).sum(-1) + (
            self.area_lower * np.maximum(dl - self.start_lower, 0.0)
        ).sum(-1)
        energy = (peak + self.dp_margin) * moved
        objective = {"sum_pressure": sum_p, "peak_pressure": peak, "pump_energy": energy}[
            self.objective_name
        ]
        # Linked extensions computed from an attitude have zero twist exactly (d3 = -d1 to
        # the last bit), so coplanarity is checked only on extensions given from outside:
        # trajectory samples, which are held to the path limits, not the planning limit.
        path = d_lower is not None or d_upper is not None
        violation = self._violation(du, dl, fu, fl, pu, pl, path)
        violation = violation + np.where(solv, 0.0, UNSOLVABLE)
        return Evaluation(
            ur, up, lr, lp, du, dl, fu, fl, pu, pl, sum_p, peak, energy, objective, violation, solv
        )

    def _violation(
        self,
        du: Array,
        dl: Array,
        fu: Array,
        fl: Array,
        pu: Array,
        pl: Array,
        path: bool,
    ) -> Array:
        """Sum of dimensionless constraint violations (0 where all hold); ``path``: the
        extensions are trajectory samples (path limits, coplanarity checked)."""
        lim_u, lim_l = self.stroke_limits(path)
        v = np.maximum(np.abs(du) - lim_u, 0.0).sum(-1) / self.limit_upper
        v += np.maximum(np.abs(dl) - lim_l, 0.0).sum(-1) / self.limit_lower
        f = np.minimum(fu.min(-1), fl.min(-1))
        v += np.maximum(self.f_min - fu, 0.0).sum(-1) / self.force_scale * (f < self.f_min)
        v += np.maximum(self.f_min - fl, 0.0).sum(-1) / self.force_scale * (f < self.f_min)
        v += np.maximum(pu - self.p_limit, 0.0).sum(-1) / self.p_limit
        v += np.maximum(pl - self.p_limit, 0.0).sum(-1) / self.p_limit
        if path:
            for d, a, b in ((du, self.a_upper, self.b_upper), (dl, self.a_lower, self.b_lower)):
                cop = coplanarity_distance(d, a, b)
                v += np.maximum(cop - self.coplanarity_tol, 0.0) / self.coplanarity_tol
        return v

    def critical(self, ev: Evaluation, d1: ArrayLike, d2: ArrayLike) -> Array:
        """The smooth functions whose zero curves bound the pieces of the problem.

        Constraint boundaries (upper box, lower strokes, lift-off, pressure limit), and
        for the non-smooth objectives the kinks (a cylinder at its start extension) and
        the ties of the peak pressure (two cap pressures equal). Shape ``(..., m)``.
        """
        d1_, d2_ = np.asarray(d1, float), np.asarray(d2, float)
        cols = [
            np.stack([d1_ - self.limit_upper, d1_ + self.limit_upper], -1),
            np.stack([d2_ - self.limit_upper, d2_ + self.limit_upper], -1),
            ev.d_lower - self.limit_lower,
            ev.d_lower + self.limit_lower,
            ev.f_upper - self.f_min,
            ev.f_lower - self.f_min,
            ev.p_upper - self.p_limit,
            ev.p_lower - self.p_limit,
        ]
        if self.objective_name != "sum_pressure":
            p = np.concatenate([ev.p_upper, ev.p_lower], -1)
            i, j = np.triu_indices(8, 1)
            cols.append(p[..., i] - p[..., j])
        if self.objective_name == "pump_energy":
            cols.append(ev.d_upper - self.start_upper)
            cols.append(ev.d_lower - self.start_lower)
        return np.concatenate(cols, -1)

    # ------------------------------------------------------------------ reporting

    def stroke_limits(self, path: bool) -> tuple[Array, Array]:
        """(upper, lower) extension limits per cylinder (m): of a target, or of a
        trajectory sample (``path``, :func:`path_limits`)."""
        if path:
            return self.path_limit_upper, self.path_limit_lower
        return np.full(4, self.limit_upper), np.full(4, self.limit_lower)

    def reasons(
        self, ev: Evaluation, index: int | tuple[int, ...] = (), path: bool = False
    ) -> list[str]:
        """Human-readable list of the constraints violated by one candidate (``path``: a
        trajectory sample, held to the path limits)."""
        out: list[str] = []
        if not bool(np.asarray(ev.solvable)[index]):
            out.append(
                "composition: no lower attitude reaches the target normal with this upper attitude"
            )
        cfg = self.cfg
        lim_u, lim_l = self.stroke_limits(path)
        for layer, d, f, p, lim, plan_lim, a, b in (
            (
                "upper",
                ev.d_upper[index],
                ev.f_upper[index],
                ev.p_upper[index],
                lim_u,
                self.limit_upper,
                self.a_upper,
                self.b_upper,
            ),
            (
                "lower",
                ev.d_lower[index],
                ev.f_lower[index],
                ev.p_lower[index],
                lim_l,
                self.limit_lower,
                self.a_lower,
                self.b_lower,
            ),
        ):
            ids = getattr(cfg.layers, layer).cylinders
            cop = float(coplanarity_distance(d, a, b))
            if cop > self.coplanarity_tol:
                out.append(
                    f"coplanarity: {layer} action point 4 is {units.to_mm(cop):.3f} mm from the "
                    f"plane of points 1-3 (tolerance {units.to_mm(self.coplanarity_tol):.3f} mm)"
                )
            for i in range(4):
                name = f"{layer} cylinder {i + 1} ({ids[i]})"
                if abs(d[i]) > lim[i] and lim[i] > plan_lim:
                    out.append(
                        f"stroke: {name} extension {units.to_mm(d[i]):+.1f} mm deeper into the "
                        f"stroke reserve than its start ±{units.to_mm(lim[i]):.1f} mm"
                    )
                elif abs(d[i]) > lim[i]:
                    out.append(
                        f"stroke: {name} extension {units.to_mm(d[i]):+.1f} mm beyond the "
                        f"planning limit ±{units.to_mm(lim[i]):.1f} mm (stroke/2 - reserve)"
                    )
                if f[i] < self.f_min:
                    out.append(
                        f"lift-off: {name} rod force {units.to_kn(f[i]):.1f} kN below the minimum "
                        f"{units.to_kn(self.f_min):.1f} kN"
                    )
                why = pressure_reason(cfg, name, float(f[i]), float(p[i]))
                if why is not None:
                    out.append(why)
        return out
