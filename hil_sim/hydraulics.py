"""Valve-controlled differential cylinders (model.md section 9), vectorized over N cylinders.

The model, per cylinder (SI units; ``x`` is the rod position, 0 = fully retracted):

- valve: second-order spool ``x_v'' = w_v^2 (u x_v,max - x_v) - 2 zeta_v w_v x_v'``
  driven by the normalized command ``u`` in [-1, 1] (clipped), spool opening limited
  to ``+-x_v,max`` in the flows;
- orifice flows (critically lapped, matched edges): spool positive P->A and B->T,
  negative A->T and P->B, ``Q = C_d w x_v sqrt(2 dp / rho)`` with the square root
  regularized near zero pressure drop, see :func:`signed_sqrt`;
- continuity with internal and external leakage and the bulk modulus;
- force balance ``m v' = p_A A_A - p_B A_B - B v - F_c(v) - F_load + F_stop(x, v)``.

Every model function below is pure, takes floats or equally shaped float64 arrays
(one element per cylinder) and works the same for both, so the full-rig simulator can
call them with rod positions and velocities imposed by its rigid platforms. They are
compiled with numba (:func:`hil_sim._jit.jit`: NumPy's float error model, so the loops
over the cylinders vectorize); :class:`CylinderBank` integrates standalone cylinders (rod plus
lumped load mass) with fixed-step RK4 inside one compiled kernel.

Over 500 lines because the vectorized model and the compiled RK4 kernel of the standalone
cylinders share one set of formulas, kept in one module.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import fsolve

from config import units
from config.derived import viscous_damping_n_s_m
from config.schema import Cylinder, CylinderPlant, Hydraulics
from hil_sim._jit import jit

FloatArray = NDArray[np.float64]

#: Rows of :attr:`CylinderBank.state` (shape (6, N)).
STATE_NAMES: tuple[str, ...] = ("spool_m", "spool_rate_m_s", "x_m", "v_m_s", "p_a_pa", "p_b_pa")
N_STATES = len(STATE_NAMES)


# --------------------------------------------------------------------------- pure functions


@jit
def clip_symmetric(value, limit):
    """``clip(value, -limit, limit)`` written with ``abs`` (works on floats and arrays)."""
    return 0.5 * (np.abs(value + limit) - np.abs(value - limit))


@jit
def signed_sqrt(dp, regularization_pa):
    """``sign(dp) sqrt(|dp|)``, regularized: ``dp / (dp^2 + d^2)^(1/4)``.

    Smooth through zero with a finite slope ``1/sqrt(d)`` there; the relative error is
    ``(1 + (d/dp)^2)^(-1/4) - 1``, i.e. below 1e-4 for ``|dp| > 50 d``.
    """
    return dp / np.sqrt(np.sqrt(dp * dp + regularization_pa * regularization_pa))


@jit
def valve_derivative(spool_m, spool_rate_m_s, command, spool_max_m, omega_rad_s, zeta):
    """Second-order spool dynamics; ``command`` is clipped to [-1, 1] (the amplifier)."""
    target = clip_symmetric(command, 1.0) * spool_max_m
    accel = (
        omega_rad_s * omega_rad_s * (target - spool_m) - 2.0 * zeta * omega_rad_s * spool_rate_m_s
    )
    return spool_rate_m_s, accel


@jit
def orifice_flows(
    spool_m, p_a_pa, p_b_pa, spool_max_m, orifice_coeff, supply_pa, tank_pa, regularization_pa
):
    """Flow into the cap chamber ``Q_A`` and out of the rod chamber ``Q_B`` (m^3/s).

    ``orifice_coeff = C_d w sqrt(2 / rho)``; spool positive connects P->A and B->T,
    negative A->T and P->B. A reversed pressure drop reverses the flow (no check valve).
    """
    xv = clip_symmetric(spool_m, spool_max_m)
    xp = 0.5 * (xv + np.abs(xv))
    xn = xv - xp
    reg = regularization_pa
    q_a = orifice_coeff * (
        xp * signed_sqrt(supply_pa - p_a_pa, reg) + xn * signed_sqrt(p_a_pa - tank_pa, reg)
    )
    q_b = orifice_coeff * (
        xp * signed_sqrt(p_b_pa - tank_pa, reg) + xn * signed_sqrt(supply_pa - p_b_pa, reg)
    )
    return q_a, q_b


#: Below this pressure (Pa) the oil's entrained air makes a chamber soft: a falling
#: pressure slows to a stop at zero instead of going below it (a chamber pulled open
#: cavitates; a parked cylinder loaded from above with both ports locked, its rod side).
#: Above it (the tank's 0.3 MPa is 15 times it) the oil's stiffness is whole.
CAVITATION_PA = 2.0e4


@jit
def _falling(dp, p):
    """``dp`` (Pa/s) where it lowers a pressure ``p``: scaled by the stiffness left to the
    oil there, ``r (2 - r)`` with ``r = p / CAVITATION_PA`` in 0..1 (whole above it,
    none at zero, smooth at both ends), scalars or arrays; a few flops, no
    transcendental (the rig's RK4 calls it 38 times a stage)."""
    r = np.minimum(np.maximum(p, 0.0) / CAVITATION_PA, 1.0)
    return dp - np.minimum(dp, 0.0) * (1.0 - r) * (1.0 - r)


@jit
def chamber_pressure_derivatives(
    x_m,
    v_m_s,
    p_a_pa,
    p_b_pa,
    q_a_m3_s,
    q_b_m3_s,
    area_a_m2,
    area_b_m2,
    stroke_m,
    dead_volume_a_m3,
    dead_volume_b_m3,
    bulk_modulus_pa,
    internal_leakage,
    external_leakage,
):
    """Continuity of the two chambers (model.md section 9), Pa/s.

    ``(V_A0 + A_A x)/beta dp_A/dt = Q_A - A_A v - C_il (p_A - p_B) - C_el p_A`` and
    ``(V_B0 + A_B (L - x))/beta dp_B/dt = -Q_B + A_B v + C_il (p_A - p_B) - C_el p_B``;
    a falling pressure stops at zero (:data:`CAVITATION_PA`).
    """
    leak = internal_leakage * (p_a_pa - p_b_pa)
    vol_a = dead_volume_a_m3 + area_a_m2 * x_m
    vol_b = dead_volume_b_m3 + area_b_m2 * (stroke_m - x_m)
    dp_a = (
        bulk_modulus_pa / vol_a * (q_a_m3_s - area_a_m2 * v_m_s - leak - external_leakage * p_a_pa)
    )
    dp_b = (
        bulk_modulus_pa / vol_b * (-q_b_m3_s + area_b_m2 * v_m_s + leak - external_leakage * p_b_pa)
    )
    return _falling(dp_a, p_a_pa), _falling(dp_b, p_b_pa)


@jit
def rod_force_n(p_a_pa, p_b_pa, area_a_m2, area_b_m2):
    """Hydraulic force on the rod, positive extending: ``p_A A_A - p_B A_B``."""
    return p_a_pa * area_a_m2 - p_b_pa * area_b_m2


@jit
def friction_force_n(v_m_s, viscous_n_s_m, coulomb_n, coulomb_velocity_m_s):
    """Viscous plus smoothed Coulomb friction, opposing the motion: ``B v + F_c tanh-like``."""
    smooth_sign = v_m_s / np.sqrt(v_m_s * v_m_s + coulomb_velocity_m_s * coulomb_velocity_m_s)
    return viscous_n_s_m * v_m_s + coulomb_n * smooth_sign


@jit
def end_stop_force_n(x_m, v_m_s, stroke_m, stiffness_n_m, damping_n_s_m):
    """Stiff spring-damper end stops at x = 0 and x = L (positive pushes towards extension).

    The damping acts only while in contact (smoothly switched in over 1 um of penetration).
    """
    below = 0.5 * (np.abs(x_m) - x_m)
    beyond = 0.5 * (np.abs(x_m - stroke_m) + x_m - stroke_m)
    depth = below + beyond
    contact = depth / (depth + 1e-6)
    return stiffness_n_m * (below - beyond) - damping_n_s_m * contact * v_m_s


@jit
def cylinder_derivative(
    spool_m,
    spool_rate_m_s,
    x_m,
    v_m_s,
    p_a_pa,
    p_b_pa,
    command,
    load_force_n,
    area_a_m2,
    area_b_m2,
    stroke_m,
    dead_volume_a_m3,
    dead_volume_b_m3,
    bulk_modulus_pa,
    internal_leakage,
    external_leakage,
    orifice_coeff,
    spool_max_m,
    valve_omega_rad_s,
    valve_zeta,
    supply_pa,
    tank_pa,
    regularization_pa,
    mass_kg,
    viscous_n_s_m,
    coulomb_n,
    coulomb_velocity_m_s,
    stop_stiffness_n_m,
    stop_damping_n_s_m,
):
    """Time derivative of the six states of a standalone cylinder (rod plus load mass).

    Argument order after the states, ``command`` and ``load_force_n`` is that of the
    fields of :class:`CylinderParams`.
    """
    d_spool, d_rate = valve_derivative(
        spool_m, spool_rate_m_s, command, spool_max_m, valve_omega_rad_s, valve_zeta
    )
    q_a, q_b = orifice_flows(
        spool_m, p_a_pa, p_b_pa, spool_max_m, orifice_coeff, supply_pa, tank_pa, regularization_pa
    )
    dp_a, dp_b = chamber_pressure_derivatives(
        x_m,
        v_m_s,
        p_a_pa,
        p_b_pa,
        q_a,
        q_b,
        area_a_m2,
        area_b_m2,
        stroke_m,
        dead_volume_a_m3,
        dead_volume_b_m3,
        bulk_modulus_pa,
        internal_leakage,
        external_leakage,
    )
    force = (
        rod_force_n(p_a_pa, p_b_pa, area_a_m2, area_b_m2)
        - friction_force_n(v_m_s, viscous_n_s_m, coulomb_n, coulomb_velocity_m_s)
        - load_force_n
        + end_stop_force_n(x_m, v_m_s, stroke_m, stop_stiffness_n_m, stop_damping_n_s_m)
    )
    return d_spool, d_rate, v_m_s, force / mass_kg, dp_a, dp_b


# --------------------------------------------------------------------------- parameters


@dataclass(frozen=True)
class PlantOptions:
    """Numerical choices of the model that the machine configuration does not carry.

    - ``sqrt_regularization_pa``: ``d`` of :func:`signed_sqrt` (20 kPa: flows are exact
      to 1e-4 above 1 MPa of pressure drop);
    - ``coulomb_velocity_m_s``: velocity over which Coulomb friction changes sign;
    - ``end_stop_stiffness_n_m`` and ``end_stop_damping_ratio``: the contact at either end.
    """

    sqrt_regularization_pa: float = 2e4
    coulomb_velocity_m_s: float = 1e-4
    end_stop_stiffness_n_m: float = 2e9
    end_stop_damping_ratio: float = 0.7


@dataclass(frozen=True)
class CylinderParams:
    """Per-cylinder parameters in SI, each a float64 array of shape (N,).

    The field order is the argument order of :func:`cylinder_derivative` after
    ``load_force_n``; :meth:`matrix` stacks them in that order for the compiled kernel.
    """

    area_a_m2: FloatArray
    area_b_m2: FloatArray
    stroke_m: FloatArray
    dead_volume_a_m3: FloatArray
    dead_volume_b_m3: FloatArray
    bulk_modulus_pa: FloatArray
    internal_leakage_m3_s_pa: FloatArray
    external_leakage_m3_s_pa: FloatArray
    orifice_coeff: FloatArray
    spool_max_m: FloatArray
    valve_omega_rad_s: FloatArray
    valve_zeta: FloatArray
    supply_pa: FloatArray
    tank_pa: FloatArray
    regularization_pa: FloatArray
    mass_kg: FloatArray
    viscous_n_s_m: FloatArray
    coulomb_n: FloatArray
    coulomb_velocity_m_s: FloatArray
    stop_stiffness_n_m: FloatArray
    stop_damping_n_s_m: FloatArray

    @property
    def n(self) -> int:
        return int(self.area_a_m2.shape[0])

    def matrix(self) -> FloatArray:
        """Shape (n_fields, N), rows in field order."""
        rows = [getattr(self, f.name) for f in dataclasses.fields(self)]
        return np.ascontiguousarray(np.vstack(rows), dtype=np.float64)

    def select(self, index: int) -> CylinderParams:
        """The parameters of one cylinder as a bank of one."""
        return CylinderParams(
            **{f.name: getattr(self, f.name)[index : index + 1] for f in dataclasses.fields(self)}
        )

    @classmethod
    def from_config(
        cls,
        cylinders: Sequence[Cylinder],
        hydraulics: Hydraulics,
        plants: Sequence[CylinderPlant] | None = None,
        options: PlantOptions | None = None,
    ) -> CylinderParams:
        """Build from the schema: geometry from ``Cylinder``, Table-3 values from
        ``CylinderPlant`` (each cylinder's own ``plant``, else ``plants[i]``, else the
        hydraulics' ``cylinder_defaults``), supply, oil and valve from ``Hydraulics``.
        """
        opt = options or PlantOptions()
        cols: dict[str, list[float]] = {f.name: [] for f in dataclasses.fields(cls)}
        for i, cyl in enumerate(cylinders):
            plant = cyl.plant or (plants[i] if plants is not None else hydraulics.cylinder_defaults)
            orifice = (
                hydraulics.discharge_coefficient
                * plant.area_gradient_m
                * math.sqrt(2.0 / hydraulics.oil_density_kg_m3)
            )
            valve_omega = 2.0 * math.pi * hydraulics.valve_natural_frequency_hz
            stop_k = opt.end_stop_stiffness_n_m
            values = {
                "area_a_m2": cyl.cap_area_m2,
                "area_b_m2": cyl.rod_area_m2,
                "stroke_m": cyl.stroke_m,
                "dead_volume_a_m3": plant.dead_volume_m3,
                "dead_volume_b_m3": plant.dead_volume_m3,
                "bulk_modulus_pa": hydraulics.bulk_modulus_pa,
                "internal_leakage_m3_s_pa": plant.internal_leakage_m3_s_pa,
                "external_leakage_m3_s_pa": plant.external_leakage_m3_s_pa,
                "orifice_coeff": orifice,
                "spool_max_m": hydraulics.valve_max_opening_m,
                "valve_omega_rad_s": valve_omega,
                "valve_zeta": hydraulics.valve_damping_ratio,
                "supply_pa": hydraulics.supply_pressure_pa,
                "tank_pa": hydraulics.tank_pressure_pa,
                "regularization_pa": opt.sqrt_regularization_pa,
                "mass_kg": plant.moving_mass_kg,
                "viscous_n_s_m": viscous_damping_n_s_m(cyl, plant, hydraulics),
                "coulomb_n": plant.coulomb_friction_n,
                "coulomb_velocity_m_s": opt.coulomb_velocity_m_s,
                "stop_stiffness_n_m": stop_k,
                "stop_damping_n_s_m": 2.0
                * opt.end_stop_damping_ratio
                * math.sqrt(stop_k * plant.moving_mass_kg),
            }
            for name, value in values.items():
                cols[name].append(float(value))
        return cls(**{name: np.asarray(v, dtype=np.float64) for name, v in cols.items()})


def derivative(
    state: FloatArray, command: FloatArray, load_force_n: FloatArray, params: CylinderParams
) -> FloatArray:
    """Vectorized :func:`cylinder_derivative`: ``state`` (6, N) -> d(state)/dt (6, N)."""
    args = [*state, command, load_force_n]
    args += [getattr(params, f.name) for f in dataclasses.fields(params)]
    out = cylinder_derivative(*args)
    return np.vstack([np.broadcast_to(o, state.shape[1:]) for o in out])


# --------------------------------------------------------------------------- integrator


@jit
def _rk4_advance(state, command, load, p, h, n_steps):
    """Advance ``state`` (6, N) in place by ``n_steps`` RK4 steps of ``h`` seconds.

    ``command`` and ``load`` (N,) are held constant (zero-order hold).
    """
    n = state.shape[1]
    for i in range(n):
        a0 = p[0, i]
        a1 = p[1, i]
        a2 = p[2, i]
        a3 = p[3, i]
        a4 = p[4, i]
        a5 = p[5, i]
        a6 = p[6, i]
        a7 = p[7, i]
        a8 = p[8, i]
        a9 = p[9, i]
        a10 = p[10, i]
        a11 = p[11, i]
        a12 = p[12, i]
        a13 = p[13, i]
        a14 = p[14, i]
        a15 = p[15, i]
        a16 = p[16, i]
        a17 = p[17, i]
        a18 = p[18, i]
        a19 = p[19, i]
        a20 = p[20, i]
        u = command[i]
        f = load[i]
        s0 = state[0, i]
        s1 = state[1, i]
        s2 = state[2, i]
        s3 = state[3, i]
        s4 = state[4, i]
        s5 = state[5, i]
        for _ in range(n_steps):
            k10, k11, k12, k13, k14, k15 = cylinder_derivative(
                s0, s1, s2, s3, s4, s5, u, f, a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10,
                a11, a12, a13, a14, a15, a16, a17, a18, a19, a20,
            )  # fmt: skip
            hh = 0.5 * h
            k20, k21, k22, k23, k24, k25 = cylinder_derivative(
                s0 + hh * k10, s1 + hh * k11, s2 + hh * k12, s3 + hh * k13, s4 + hh * k14,
                s5 + hh * k15, u, f, a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11, a12,
                a13, a14, a15, a16, a17, a18, a19, a20,
            )  # fmt: skip
            k30, k31, k32, k33, k34, k35 = cylinder_derivative(
                s0 + hh * k20, s1 + hh * k21, s2 + hh * k22, s3 + hh * k23, s4 + hh * k24,
                s5 + hh * k25, u, f, a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11, a12,
                a13, a14, a15, a16, a17, a18, a19, a20,
            )  # fmt: skip
            k40, k41, k42, k43, k44, k45 = cylinder_derivative(
                s0 + h * k30, s1 + h * k31, s2 + h * k32, s3 + h * k33, s4 + h * k34,
                s5 + h * k35, u, f, a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11, a12,
                a13, a14, a15, a16, a17, a18, a19, a20,
            )  # fmt: skip
            h6 = h / 6.0
            s0 += h6 * (k10 + 2.0 * k20 + 2.0 * k30 + k40)
            s1 += h6 * (k11 + 2.0 * k21 + 2.0 * k31 + k41)
            s2 += h6 * (k12 + 2.0 * k22 + 2.0 * k32 + k42)
            s3 += h6 * (k13 + 2.0 * k23 + 2.0 * k33 + k43)
            s4 += h6 * (k14 + 2.0 * k24 + 2.0 * k34 + k44)
            s5 += h6 * (k15 + 2.0 * k25 + 2.0 * k35 + k45)
        state[0, i] = s0
        state[1, i] = s1
        state[2, i] = s2
        state[3, i] = s3
        state[4, i] = s4
        state[5, i] = s5


class CylinderBank:
    """N standalone cylinders (each rod with its lumped load mass), fixed-step RK4.

    >>> bank = CylinderBank(params, step_s=0.5e-3)          # doctest: +SKIP
    >>> u_hold = bank.hold_at(np.array([0.01, 0.01]), load) # doctest: +SKIP
    >>> bank.advance(np.array([0.2, 0.2]), load, 1e-3)      # doctest: +SKIP
    """

    def __init__(self, params: CylinderParams, step_s: float = 0.5e-3) -> None:
        if not 1e-6 <= step_s <= 1e-3:
            raise ValueError(
                f"step_s must be within 1 us .. 1 ms (0.1-0.5 ms advised), got {step_s}"
            )
        self.params = params
        self.step_s = float(step_s)
        self._p = params.matrix()
        self.state: FloatArray = np.zeros((N_STATES, params.n))
        self.state[4] = params.tank_pa
        self.state[5] = params.tank_pa
        self.t_s = 0.0

    @property
    def n(self) -> int:
        return self.params.n

    @property
    def spool_m(self) -> FloatArray:
        return self.state[0]

    @property
    def x_m(self) -> FloatArray:
        return self.state[2]

    @property
    def v_m_s(self) -> FloatArray:
        return self.state[3]

    @property
    def p_a_pa(self) -> FloatArray:
        return self.state[4]

    @property
    def p_b_pa(self) -> FloatArray:
        return self.state[5]

    def flows_m3_s(self) -> tuple[FloatArray, FloatArray]:
        """Present valve flows ``(Q_A into the cap side, Q_B out of the rod side)``."""
        p = self.params
        q_a, q_b = orifice_flows(
            self.state[0],
            self.state[4],
            self.state[5],
            p.spool_max_m,
            p.orifice_coeff,
            p.supply_pa,
            p.tank_pa,
            p.regularization_pa,
        )
        return np.asarray(q_a), np.asarray(q_b)

    def advance(self, command: FloatArray, load_force_n: FloatArray, duration_s: float) -> None:
        """Integrate ``duration_s`` (a whole number of steps) with command and load held."""
        n_steps = round(duration_s / self.step_s)
        if n_steps < 1 or abs(n_steps * self.step_s - duration_s) > 1e-9 * max(duration_s, 1.0):
            raise ValueError(
                f"duration_s ({duration_s}) must be a whole number of steps of {self.step_s} s"
            )
        self.advance_steps(command, load_force_n, n_steps)

    def advance_steps(self, command: FloatArray, load_force_n: FloatArray, n_steps: int) -> None:
        """Integrate ``n_steps`` RK4 steps with command (N,) and load force (N,) held."""
        u = np.ascontiguousarray(command, dtype=np.float64)
        f = np.ascontiguousarray(load_force_n, dtype=np.float64)
        _rk4_advance(self.state, u, f, self._p, self.step_s, n_steps)
        self.t_s += n_steps * self.step_s

    def hold_at(self, x_m: FloatArray, load_force_n: FloatArray) -> FloatArray:
        """Put every cylinder at rest at ``x_m`` under ``load_force_n``, in equilibrium.

        The valve holds the load against leakage with a small opening; returns that
        holding command (normalized), which a controller takes over bumplessly.
        """
        x = np.broadcast_to(np.asarray(x_m, dtype=np.float64), (self.n,))
        f = np.broadcast_to(np.asarray(load_force_n, dtype=np.float64), (self.n,))
        commands = np.zeros(self.n)
        for i in range(self.n):
            spool, p_a, p_b = rest_equilibrium(self.params.select(i), float(x[i]), float(f[i]))
            self.state[:, i] = (spool, 0.0, x[i], 0.0, p_a, p_b)
            commands[i] = spool / self.params.spool_max_m[i]
        return commands


def rest_equilibrium(
    params: CylinderParams, x_m: float, load_force_n: float
) -> tuple[float, float, float]:
    """Spool opening and chamber pressures that hold one cylinder still at ``x_m``.

    Solves ``Q_A = leakage_A``, ``Q_B = leakage_B`` and ``p_A A_A - p_B A_B = F_load``
    (no friction at rest). Raises ``ValueError`` if the supply cannot hold the load.
    """
    a_a = float(params.area_a_m2[0])
    a_b = float(params.area_b_m2[0])
    c_il = float(params.internal_leakage_m3_s_pa[0])
    c_el = float(params.external_leakage_m3_s_pa[0])
    k_or = float(params.orifice_coeff[0])
    xv_max = float(params.spool_max_m[0])
    p_s = float(params.supply_pa[0])
    p_t = float(params.tank_pa[0])
    reg = float(params.regularization_pa[0])
    stroke = float(params.stroke_m[0])
    stop = float(end_stop_force_n(x_m, 0.0, stroke, float(params.stop_stiffness_n_m[0]), 0.0))
    scale = units.MPA  # the pressure unknowns in MPa

    def residual(z: FloatArray) -> list[float]:
        spool = z[0] * xv_max
        p_a = z[1] * scale
        p_b = z[2] * scale
        q_a, q_b = orifice_flows(spool, p_a, p_b, xv_max, k_or, p_s, p_t, reg)
        leak = c_il * (p_a - p_b)
        return [
            float(q_a - leak - c_el * p_a) * 1e4,
            float(-q_b + leak - c_el * p_b) * 1e4,
            float(p_a * a_a - p_b * a_b - load_force_n + stop) / (a_a * scale),
        ]

    p_b0 = 0.5 * (p_s + p_t)
    guess = np.array([0.05, (load_force_n - stop + p_b0 * a_b) / a_a / scale, p_b0 / scale])
    sol, _info, ok, msg = fsolve(residual, guess, full_output=True, xtol=1e-12)
    if ok != 1 or max(abs(r) for r in residual(sol)) > 1e-6:
        raise ValueError(f"no rest equilibrium at x = {x_m} m under {load_force_n} N: {msg}")
    return float(sol[0] * xv_max), float(sol[1] * scale), float(sol[2] * scale)
