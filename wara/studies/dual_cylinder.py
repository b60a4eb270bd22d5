"""The paper's dual-cylinder synchronization study: our plant under our controllers.

``run_study`` closes the loop at the scenario's control rate: the position
transducers read the plant, the synchronization group (LADRC or PID per cylinder,
dual-error coupled) computes the valve commands, the plant integrates one control
period with the command and the load force held. ``summarize`` turns a run into the
figures the paper reports; ``plot_runs`` draws them.

Synchronization error: the spread of the true rod positions, ``max_i x_i - min_i x_i``
(for two cylinders ``|x_1 - x_2|``), i.e. what the platform feels, not what the
noisy transducers say.
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from config import units
from config.scenario import DualCylinderScenario
from hil_sim.disturbances import LoadStep, load_profile
from hil_sim.hydraulics import CylinderBank, CylinderParams, orifice_flows
from hil_sim.sensors import PositionTransducer
from ipc_app.control import LADRC, PID, Controller, SyncGroup, cylinder_b0
from wara.studies import CONTROLLERS, ControllerKind

FloatArray = NDArray[np.float64]


def quintic_waypoints(waypoints: tuple[tuple[float, float], ...], t_s: FloatArray) -> FloatArray:
    """Reference through ``(t, value)`` waypoints with quintic blends (rest at each one)."""
    times = np.array([w[0] for w in waypoints], dtype=np.float64)
    values = np.array([w[1] for w in waypoints], dtype=np.float64)
    t = np.asarray(t_s, dtype=np.float64)
    if len(times) == 1:
        return np.full_like(t, values[0])
    seg = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    t0, t1 = times[seg], times[seg + 1]
    s = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    blend = s**3 * (10.0 - 15.0 * s + 6.0 * s * s)
    return values[seg] + (values[seg + 1] - values[seg]) * blend


def reference_m(scenario: DualCylinderScenario, t_s: FloatArray) -> FloatArray:
    """The rod position reference in metres at times ``t_s``."""
    return units.mm(1.0) * quintic_waypoints(scenario.reference.waypoints, t_s)


def last_move_end_s(scenario: DualCylinderScenario) -> float:
    """When the reference comes to rest for the last time."""
    wps = scenario.reference.waypoints
    end = 0.0
    for (_t0, p0), (t1, p1) in itertools.pairwise(wps):
        if p1 != p0:
            end = t1
    return end


def build_group(scenario: DualCylinderScenario, kind: ControllerKind) -> SyncGroup:
    """One controller per cylinder, coupled as the scenario's ``control.sync`` says."""
    ctl = scenario.control
    dt = ctl.period_s
    controllers: list[Controller] = []
    for c in scenario.cylinders:
        if kind == "ladrc":
            b0 = cylinder_b0(c.cylinder, scenario.hydraulics, order=ctl.ladrc.order)
            controllers.append(LADRC.from_config(ctl.ladrc, b0=b0, dt=dt))
        elif kind == "pid":
            controllers.append(
                PID.from_config(ctl.pid, dt=dt, rate_limit=ctl.ladrc.rate_limit_per_s)
            )
        else:
            raise ValueError(f"controller must be one of {CONTROLLERS}, got {kind!r}")
    return SyncGroup(controllers, ctl.sync.scheme, ctl.sync.coupling_lambda)


@dataclass
class StudyRun:
    """Time series of one closed-loop run, one row per control period (arrays (n, N))."""

    controller: str
    t_s: FloatArray
    reference_m: FloatArray
    position_m: FloatArray
    measured_m: FloatArray
    velocity_m_s: FloatArray
    command: FloatArray
    p_a_pa: FloatArray
    p_b_pa: FloatArray
    flow_a_m3_s: FloatArray
    load_n: FloatArray
    wall_s: float

    @property
    def duration_s(self) -> float:
        return float(self.t_s[-1] + (self.t_s[1] - self.t_s[0])) if len(self.t_s) > 1 else 0.0

    @property
    def realtime_factor(self) -> float:
        """Simulated seconds per wall-clock second of the closed loop."""
        return self.duration_s / self.wall_s if self.wall_s > 0 else float("inf")

    @property
    def sync_error_m(self) -> FloatArray:
        """Spread of the true rod positions at each sample."""
        return np.asarray(self.position_m.max(axis=1) - self.position_m.min(axis=1))


def run_study(
    scenario: DualCylinderScenario,
    controller: ControllerKind,
    duration_s: float | None = None,
    progress: Callable[[float], None] | None = None,
) -> StudyRun:
    """Simulate the scenario in closed loop; ``progress(fraction)`` is called ~100 times."""
    duration = scenario.duration_s if duration_s is None else duration_s
    dt = scenario.control.period_s
    n_ticks = round(duration / dt)
    if n_ticks < 2:
        raise ValueError(f"duration_s ({duration}) must span at least two control periods")
    cyls = scenario.cylinders
    n = len(cyls)
    params = CylinderParams.from_config([c.cylinder for c in cyls], scenario.hydraulics)
    bank = CylinderBank(params, scenario.plant_step_s)
    t = np.arange(n_ticks, dtype=np.float64) * dt
    ref = reference_m(scenario, t)
    noise = scenario.noise
    loads = load_profile(
        n_ticks,
        dt,
        [c.load_force_n for c in cyls],
        steps=[LoadStep(s.t_s, s.cylinder, s.delta_kn * units.KN) for s in scenario.load_steps],
        noise_rms_n=noise.rms_n if noise else 0.0,
        noise_bandwidth_hz=noise.bandwidth_hz if noise else 1.0,
        noise_start_s=noise.start_s if noise else 0.0,
        seed=noise.seed if noise else 0,
    )
    sensors = scenario.sensors
    position_sensor = PositionTransducer(
        n, sensors.position_resolution_m, sensors.position_noise_m, sensors.seed
    )
    group = build_group(scenario, controller)
    hold = bank.hold_at(np.full(n, ref[0]), loads[0])
    group.reset(list(position_sensor.read(bank.x_m)), list(hold))

    states = np.empty((n_ticks, 6, n))
    measured = np.empty((n_ticks, n))
    commands = np.empty((n_ticks, n))
    refs = ref.tolist()
    # feed-forward of the reference's rate (known ahead here), when the LADRC asks for it
    ff = controller == "ladrc" and scenario.control.ladrc.reference_feedforward
    rates = np.gradient(ref, dt).tolist() if ff else None
    steps_per_tick = round(dt / scenario.plant_step_s)
    report_every = max(n_ticks // 100, 1)
    state = bank.state
    read = position_sensor.read
    update = group.update
    advance = bank.advance_steps
    start = time.perf_counter()
    for k in range(n_ticks):
        y = read(state[2])
        u = update([refs[k]] * n, y, None if rates is None else [rates[k]] * n)
        states[k] = state
        measured[k] = y
        commands[k] = u
        advance(u, loads[k], steps_per_tick)
        if progress is not None and k % report_every == 0:
            progress(k / n_ticks)
    wall = time.perf_counter() - start
    if progress is not None:
        progress(1.0)
    # Valve flow into the cap side, from the recorded states (not needed by the loop).
    qa, _qb = _flows(params, states[:, 0], states[:, 4], states[:, 5])
    return StudyRun(
        controller=controller,
        t_s=t,
        reference_m=np.tile(ref[:, None], (1, n)),
        position_m=states[:, 2],
        measured_m=measured,
        velocity_m_s=states[:, 3],
        command=commands,
        p_a_pa=states[:, 4],
        p_b_pa=states[:, 5],
        flow_a_m3_s=qa,
        load_n=loads,
        wall_s=wall,
    )


def _flows(
    params: CylinderParams, spool_m: FloatArray, p_a: FloatArray, p_b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Valve flows ``(Q_A, Q_B)`` for recorded samples."""
    q_a, q_b = orifice_flows(
        spool_m,
        p_a,
        p_b,
        params.spool_max_m,
        params.orifice_coeff,
        params.supply_pa,
        params.tank_pa,
        params.regularization_pa,
    )
    return np.asarray(q_a), np.asarray(q_b)


# --------------------------------------------------------------------------- metrics


def _window_stats(err_mm: FloatArray) -> dict[str, float | None]:
    if err_mm.size == 0:
        return {"max_mm": None, "rms_mm": None}
    return {
        "max_mm": float(np.max(np.abs(err_mm))),
        "rms_mm": float(np.sqrt(np.mean(err_mm**2))),
    }


def windows(scenario: DualCylinderScenario, duration_s: float) -> dict[str, tuple[float, float]]:
    """The metric windows ``[start, end)`` in seconds."""
    after = (scenario.transient_s, duration_s)
    out = {"after_transient": after}
    if scenario.noise is not None and scenario.noise.start_s < duration_s:
        start = max(scenario.noise.start_s, scenario.transient_s)
        out["before_noise"] = (scenario.transient_s, start)
        out["after_noise"] = (start, duration_s)
    return out


def settling_time_s(run: StudyRun, scenario: DualCylinderScenario) -> float | None:
    """Time after the reference's last move until every tracking error stays within
    ``settle_band_mm`` to the end of the run; ``None`` if it never does."""
    end = last_move_end_s(scenario)
    if end >= run.duration_s:
        return None
    band = units.mm(scenario.settle_band_mm)
    err = np.abs(run.reference_m - run.position_m).max(axis=1)
    after = run.t_s >= end
    outside = np.nonzero(after & (err > band))[0]
    if outside.size == 0:
        return 0.0
    last = int(outside[-1])
    if last == len(run.t_s) - 1:
        return None
    return float(run.t_s[last + 1] - end)


def summarize(run: StudyRun, scenario: DualCylinderScenario) -> dict[str, Any]:
    """The study's figures for one run (JSON-ready)."""
    to_mm = 1.0 / units.mm(1.0)
    sync_mm = run.sync_error_m * to_mm
    track_mm = (run.reference_m - run.position_m) * to_mm
    out: dict[str, Any] = {}
    for name, (lo, hi) in windows(scenario, run.duration_s).items():
        sel = (run.t_s >= lo) & (run.t_s < hi)
        stats = _window_stats(sync_mm[sel])
        key = "" if name == "after_transient" else f"_{name}"
        out[f"sync_error_max_mm{key}"] = stats["max_mm"]
        out[f"sync_error_rms_mm{key}"] = stats["rms_mm"]
    sel = run.t_s >= scenario.transient_s
    out["tracking_error_rms_mm"] = float(np.sqrt(np.mean(track_mm[sel] ** 2)))
    out["tracking_error_max_mm"] = float(np.max(np.abs(track_mm[sel])))
    out["settling_time_s"] = settling_time_s(run, scenario)
    out["sync_error_max_mm_whole_run"] = float(np.max(sync_mm))
    out["peak_command"] = float(np.max(np.abs(run.command)))
    out["peak_pressure_mpa"] = units.to_mpa(float(max(run.p_a_pa.max(), run.p_b_pa.max())))
    out["min_pressure_mpa"] = units.to_mpa(float(min(run.p_a_pa.min(), run.p_b_pa.min())))
    out["wall_s"] = run.wall_s
    out["realtime_factor"] = run.realtime_factor
    return out


def evaluate(
    runs: dict[str, StudyRun], scenario: DualCylinderScenario
) -> tuple[dict[str, Any], bool]:
    """All runs' figures, the comparison and the goal checks; ``(report, goals_met)``."""
    duration = next(iter(runs.values())).duration_s
    goals = scenario.goals
    report: dict[str, Any] = {
        "scenario": scenario.name,
        "duration_s": duration,
        "control_rate_hz": scenario.control.rate_hz,
        "plant_step_ms": scenario.plant_step_ms,
        "sync_error": "max_i x_i - min_i x_i of the true rod positions",
        "windows_s": {k: list(v) for k, v in windows(scenario, duration).items()},
        "settling_time": (
            f"after the reference's last move ends ({last_move_end_s(scenario)} s), until "
            f"every |tracking error| stays within {scenario.settle_band_mm} mm"
        ),
        "controllers": {name: summarize(run, scenario) for name, run in runs.items()},
    }
    checks: dict[str, bool] = {}
    ctrls = report["controllers"]
    if "ladrc" in ctrls:
        checks[f"ladrc sync_error_max_mm <= {goals.sync_error_max_mm}"] = (
            ctrls["ladrc"]["sync_error_max_mm"] <= goals.sync_error_max_mm
        )
    if "ladrc" in ctrls and "pid" in ctrls:
        ratio = ctrls["pid"]["sync_error_max_mm"] / ctrls["ladrc"]["sync_error_max_mm"]
        report["pid_to_ladrc_sync_error_max_ratio"] = ratio
        report["pid_to_ladrc_sync_error_rms_ratio"] = (
            ctrls["pid"]["sync_error_rms_mm"] / ctrls["ladrc"]["sync_error_rms_mm"]
        )
        checks[f"pid / ladrc sync_error_max_mm >= {goals.min_pid_to_ladrc_ratio}"] = (
            ratio >= goals.min_pid_to_ladrc_ratio
        )
    report["goals"] = checks
    met = all(checks.values())
    report["goals_met"] = met
    return report, met
