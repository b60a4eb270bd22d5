"""Synchronized cylinder trajectories from the measured configuration to a plan
(model.md section 8).

Path: the four layer angles move on one time scaling ``s(t)``,
``q(s) = q_start + s (q_plan - q_start)``; a start that is not exactly linked (heave or
twist measured at the start) has them removed along the same ``s``:
``d(s) = extensions(roll(s), pitch(s), heave_0 (1 - s)) + twist_0 (1 - s) (1, -1, 1, -1)``.
At ``s = 0`` this reproduces the measured extensions exactly (the least-squares residual
of four symmetric points is ``twist (1, -1, 1, -1)``); for a linked start the linkage
holds at every instant. All eight cylinders start and stop together.

Duration: the smallest ``T`` for which the slowest cylinder respects the rod speed limit,
the pump delivers the cap-side flow of all extending cylinders
(``sum_i A_cap,i max(v_i, 0) <= Q_pump``) and no rod exceeds the acceleration limit,
checked on a dense grid of ``s`` including the ``d''(s) s_dot^2`` term.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from config.schema import Trajectory as TrajectoryOptions
from ipc_app.model.kinematics import Array, extensions, extensions_at, fit_layer
from ipc_app.planner.problem import FEASIBILITY_TOLERANCE, PlanningProblem

_DENSE = 401  # points in s for the duration computation


#: The trapezoidal profile accelerates over this fraction of the motion, cruises at the
#: peak rate, and decelerates over the same fraction at the end.
_TRAPEZOID_RAMP = 0.25


def _profile(profile: str, tau: Any, where: Callable[[Any, Any, Any], Any]) -> tuple[Any, Any, Any]:
    """``s, ds/dtau, d2s/dtau2`` of the normalized profile at ``tau`` in [0, 1] (already
    clipped), written once: ``where`` is ``np.where`` on arrays, a conditional on floats."""
    if profile == "quintic":
        s = tau**3 * (10 - 15 * tau + 6 * tau**2)
        ds = 30 * tau**2 * (1 - tau) ** 2
        dds = 60 * tau * (1 - tau) * (1 - 2 * tau)
        return s, ds, dds
    if profile == "trapezoidal":
        f = _TRAPEZOID_RAMP
        vpk = 1.0 / (1.0 - f)
        acc = vpk / f
        ramp_up, cruise = tau < f, tau <= 1 - f
        s = where(
            ramp_up,
            0.5 * acc * tau**2,
            where(cruise, 0.5 * acc * f**2 + vpk * (tau - f), 1.0 - 0.5 * acc * (1 - tau) ** 2),
        )
        ds = where(ramp_up, acc * tau, where(cruise, vpk, acc * (1 - tau)))
        dds = where(ramp_up, acc, where(cruise, 0.0, -acc))
        return s, ds, dds
    raise ValueError(f"unknown time scaling {profile!r}; expected 'quintic' or 'trapezoidal'")


def _choose(cond: bool, yes: float, no: float) -> float:
    return yes if cond else no


def time_scaling(profile: str, tau: Array) -> tuple[Array, Array, Array]:
    """``s, ds/dtau, d2s/dtau2`` of the normalized profile on ``tau`` in [0, 1]."""
    return _profile(profile, np.clip(tau, 0.0, 1.0), np.where)


def time_scaling_at(profile: str, tau: float) -> tuple[float, float]:
    """``s, ds/dtau`` of :func:`time_scaling` at one ``tau``, on plain floats (the control
    loop samples one point per cycle, where numpy's per-call overhead is most of the cost)."""
    tau = 0.0 if tau < 0.0 else (1.0 if tau > 1.0 else tau)
    s, ds, _ = _profile(profile, tau, _choose)
    return s, ds


@dataclass(frozen=True)
class LayerPath:
    """One layer's path in s: start attitude, plan attitude, start heave and twist."""

    a: float
    b: float
    roll0: float
    pitch0: float
    roll1: float
    pitch1: float
    heave0: float
    twist0: float

    def at(self, s: Array) -> tuple[Array, Array, Array]:
        """(roll, pitch, extensions (..., 4)) at path parameter s."""
        roll = self.roll0 + s * (self.roll1 - self.roll0)
        pitch = self.pitch0 + s * (self.pitch1 - self.pitch0)
        rest = 1 - np.asarray(s)
        d = extensions(roll, pitch, self.a, self.b, self.heave0 * rest, self.twist0 * rest)
        return roll, pitch, d

    def extensions_at(self, s: float) -> list[float]:
        """The extensions of :meth:`at` at one ``s``, on plain floats
        (:func:`~ipc_app.model.kinematics.extensions_at`)."""
        roll = self.roll0 + s * (self.roll1 - self.roll0)
        pitch = self.pitch0 + s * (self.pitch1 - self.pitch0)
        rest = 1 - s
        return extensions_at(roll, pitch, self.a, self.b, self.heave0 * rest, self.twist0 * rest)


@dataclass(frozen=True)
class Trajectory:
    """A synchronized trajectory and its check at samples."""

    profile: str
    duration_s: float
    lower: LayerPath
    upper: LayerPath
    t: Array  # sample times, s
    d_lower: Array  # (N, 4) m
    d_upper: Array  # (N, 4) m
    max_rod_speed_m_s: float
    max_rod_accel_m_s2: float
    max_pump_flow_m3_s: float
    feasible: bool
    reasons: list[str] = field(default_factory=list)

    def reference(self, t: float) -> tuple[Array, Array, Array, Array]:
        """Positions and velocities of all eight cylinders at time ``t``.

        Returns ``(d_lower, d_upper, v_lower, v_upper)`` (m, m/s, each 4 values), for the
        control loop's reference generator. Before 0 and after the end the trajectory
        holds its end points. The arrays of :meth:`sample`.
        """
        dl, du, vl, vu = self.sample(t)
        return np.array(dl), np.array(du), np.array(vl), np.array(vu)

    def sample(self, t: float) -> tuple[list[float], list[float], list[float], list[float]]:
        """:meth:`reference` as plain lists (what the control loop uses every cycle).

        The velocity is the forward difference of the path over ``s`` (step ``1e-7``)
        times ``ds/dt``. Computed on plain floats (:func:`time_scaling_at`,
        :meth:`LayerPath.extensions_at`): the same formulas as the planned samples.
        """
        s, ds, rate = self._scaling(t)
        eps = 1e-7
        lower, upper = self.lower, self.upper
        dl = lower.extensions_at(s)
        du = upper.extensions_at(s)
        dl2 = lower.extensions_at(s + eps)
        du2 = upper.extensions_at(s + eps)
        sdot = ds * rate
        return (
            dl,
            du,
            [(b - a) / eps * sdot for a, b in zip(dl, dl2)],  # noqa: B905 - four each
            [(b - a) / eps * sdot for a, b in zip(du, du2)],  # noqa: B905
        )

    def positions(self, t: float) -> tuple[list[float], list[float]]:
        """``(d_lower, d_upper)`` of :meth:`sample` without the velocities (half the work;
        what the control loop needs every cycle without feed-forward)."""
        s, _, _ = self._scaling(t)
        return self.lower.extensions_at(s), self.upper.extensions_at(s)

    def _scaling(self, t: float) -> tuple[float, float, float]:
        if self.duration_s <= 0:
            tau = 1.0
            rate = 0.0
        else:
            tau = t / self.duration_s
            rate = 1.0 / self.duration_s
        s, ds = time_scaling_at(self.profile, tau)
        return s, ds, rate


def layer_path(a: float, b: float, start: Array, roll1: float, pitch1: float) -> LayerPath:
    fit = fit_layer(start, a, b)
    return LayerPath(
        a, b, float(fit.roll), float(fit.pitch), roll1, pitch1, float(fit.heave), float(fit.twist)
    )


def plan_trajectory(
    problem: PlanningProblem,
    lower_attitude: tuple[float, float],
    upper_attitude: tuple[float, float],
    opts: TrajectoryOptions,
) -> Trajectory:
    """Trajectory from the problem's start configuration to the given layer attitudes."""
    lower = layer_path(problem.a_lower, problem.b_lower, problem.start_lower, *lower_attitude)
    upper = layer_path(problem.a_upper, problem.b_upper, problem.start_upper, *upper_attitude)
    s = np.linspace(0.0, 1.0, _DENSE)
    _, _, dl = lower.at(s)
    _, _, du = upper.at(s)
    d = np.concatenate([dl, du], axis=1)
    area = np.concatenate([problem.area_lower, problem.area_upper])
    d1 = np.gradient(d, s, axis=0)  # d'(s)
    d2 = np.gradient(d1, s, axis=0)  # d''(s)
    peak_d1 = float(np.max(np.abs(d1)))
    peak_flow = float(np.max((area * np.maximum(d1, 0.0)).sum(axis=1)))
    _, ds_max_arr, dds_arr = time_scaling(opts.profile, np.linspace(0, 1, 2001))
    c_v = float(np.max(ds_max_arr))
    c_a = float(np.max(np.abs(dds_arr)))
    q_pump = problem.cfg.hydraulics.pump_flow_m3_s
    v_max, a_max = opts.max_rod_speed_m_s, opts.max_rod_accel_m_s2
    duration = max(
        c_v * peak_d1 / v_max,
        c_v * peak_flow / q_pump,
        float(np.sqrt(c_a * peak_d1 / a_max)),
    )
    speed = accel = flow = 0.0
    if duration > 0:
        # Check on a dense grid in tau (s(tau) is monotone: map d'(s), d''(s) onto it)
        # and stretch T until speed, flow and acceleration all hold.
        st, dst, ddst = time_scaling(opts.profile, np.linspace(0.0, 1.0, _DENSE))
        d1t = np.stack([np.interp(st, s, d1[:, i]) for i in range(8)], axis=1)
        d2t = np.stack([np.interp(st, s, d2[:, i]) for i in range(8)], axis=1)
        for _ in range(20):
            sdot = dst[:, None] / duration
            sddot = ddst[:, None] / duration**2
            vel = d1t * sdot
            acc = d2t * sdot**2 + d1t * sddot
            speed = float(np.max(np.abs(vel)))
            accel = float(np.max(np.abs(acc)))
            flow = float(np.max((area * np.maximum(vel, 0.0)).sum(axis=1)))
            ratio = max(speed / v_max, flow / q_pump, np.sqrt(accel / a_max))
            if ratio <= 1.0 + 1e-9:
                break
            duration *= ratio * (1 + 1e-6)
    n = max(int(np.ceil(duration / opts.sample_period_s)), 1)
    t = np.linspace(0.0, duration, n + 1)
    tau_s = t / duration if duration > 0 else np.ones_like(t)
    s_t, _, _ = time_scaling(opts.profile, tau_s)
    lr, lp, dl_t = lower.at(s_t)
    ur, up, du_t = upper.at(s_t)
    ev = problem.evaluate_attitudes(lr, lp, ur, up, True, d_lower=dl_t, d_upper=du_t)
    bad = np.nonzero(ev.violation > FEASIBILITY_TOLERANCE)[0]
    reasons: list[str] = []
    for k in bad[:3]:
        reasons.extend(
            f"trajectory at t = {t[k]:.2f} s: {r}" for r in problem.reasons(ev, int(k), path=True)
        )
    if bad.size > 3:
        reasons.append(f"trajectory: {bad.size} of {t.size} samples violate constraints")
    return Trajectory(
        opts.profile,
        duration,
        lower,
        upper,
        t,
        dl_t,
        du_t,
        speed,
        accel,
        flow,
        bad.size == 0,
        reasons,
    )
