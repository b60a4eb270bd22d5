"""The hydraulic plant (hil_sim.hydraulics, sensors, disturbances) against closed forms."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import expm

from config import ProjectConfig
from config.derived import hydraulic_natural_frequency_rad_s, viscous_damping_n_s_m
from config.scenario import load_scenario
from hil_sim.disturbances import LoadStep, band_limited_noise, load_profile
from hil_sim.hydraulics import (
    CylinderBank,
    CylinderParams,
    chamber_pressure_derivatives,
    derivative,
    orifice_flows,
    signed_sqrt,
)
from hil_sim.sensors import PositionTransducer


@pytest.fixture(scope="module")
def table3() -> CylinderParams:
    """Paper Table 3, No.1 and No.2 cylinders, from the shipped scenario."""
    sc = load_scenario()
    return CylinderParams.from_config([c.cylinder for c in sc.cylinders], sc.hydraulics)


def test_parameters_come_from_the_config(project: ProjectConfig) -> None:
    cyl = project.cylinder("main_leg_1")
    p = CylinderParams.from_config([cyl], project.hydraulics)
    plant = project.hydraulics.cylinder_defaults
    assert p.area_a_m2[0] == pytest.approx(math.pi * 0.16**2 / 4)
    assert p.area_b_m2[0] == pytest.approx(math.pi * (0.16**2 - 0.11**2) / 4)
    assert p.bulk_modulus_pa[0] == 700e6
    assert p.internal_leakage_m3_s_pa[0] == 7.2e-12
    assert p.orifice_coeff[0] == pytest.approx(0.61 * 0.026 * math.sqrt(2 / 850))
    # zeta -> B = 2 zeta sqrt(k_h m), k_h at mid-stroke
    w_h = hydraulic_natural_frequency_rad_s(cyl, plant, project.hydraulics)
    b = viscous_damping_n_s_m(cyl, plant, project.hydraulics)
    assert b == pytest.approx(2 * 0.65 * plant.moving_mass_kg * w_h)
    assert p.viscous_n_s_m[0] == pytest.approx(b)
    # model.md: about 9 t per cylinder gives roughly 12-14 Hz (here at mid-stroke)
    assert 10.0 < w_h / (2 * math.pi) < 15.0


def test_signed_sqrt_is_smooth_and_exact_away_from_zero() -> None:
    reg = 2e4
    dp = np.array([-5e6, -1e6, 0.0, 1e6, 5e6])
    got = signed_sqrt(dp, reg)
    exact = np.sign(dp) * np.sqrt(np.abs(dp))
    assert got[2] == 0.0
    np.testing.assert_allclose(got[[0, 1, 3, 4]], exact[[0, 1, 3, 4]], rtol=1e-4)
    # finite slope through zero
    assert float(signed_sqrt(1.0, reg)) == pytest.approx(1.0 / math.sqrt(reg), rel=1e-6)


@pytest.mark.slow
def test_orifice_flows_switch_edges_with_the_spool_sign(table3: CylinderParams) -> None:
    p = table3.select(0)
    args = (p.spool_max_m, p.orifice_coeff, p.supply_pa, p.tank_pa, p.regularization_pa)
    q_a, q_b = orifice_flows(2e-4, 6e6, 2e6, *args)
    k = p.orifice_coeff[0] * 2e-4
    assert float(q_a[0]) == pytest.approx(k * math.sqrt(16e6 - 6e6), rel=1e-4)  # P -> A
    assert float(q_b[0]) == pytest.approx(k * math.sqrt(2e6 - 0.3e6), rel=1e-4)  # B -> T
    q_a, q_b = orifice_flows(-2e-4, 6e6, 2e6, *args)
    assert float(q_a[0]) == pytest.approx(-k * math.sqrt(6e6 - 0.3e6), rel=1e-4)  # A -> T
    assert float(q_b[0]) == pytest.approx(-k * math.sqrt(16e6 - 2e6), rel=1e-4)  # P -> B
    # beyond the full opening the area stops growing
    q_full, _ = orifice_flows(p.spool_max_m, 6e6, 2e6, *args)
    q_over, _ = orifice_flows(3 * p.spool_max_m, 6e6, 2e6, *args)
    assert float(q_over[0]) == pytest.approx(float(q_full[0]))


def test_steady_velocity_matches_the_closed_form(table3: CylinderParams) -> None:
    """Leak-free cylinder, constant spool: ``A_A v = K sqrt(p_s - p_A)``,
    ``A_B v = K sqrt(p_B - p_T)`` and the force balance give a quadratic in v."""
    p = dataclasses.replace(
        table3.select(0),
        internal_leakage_m3_s_pa=np.zeros(1),
        external_leakage_m3_s_pa=np.zeros(1),
    )
    load = 60e3
    u = 0.4
    bank = CylinderBank(p, step_s=0.25e-3)
    bank.hold_at(np.array([0.1]), np.array([load]))
    bank.advance(np.array([u]), np.array([load]), 3.0)
    k = float(p.orifice_coeff[0]) * u * float(p.spool_max_m[0])
    a_a, a_b = float(p.area_a_m2[0]), float(p.area_b_m2[0])
    ps, pt = float(p.supply_pa[0]), float(p.tank_pa[0])
    b, fc = float(p.viscous_n_s_m[0]), float(p.coulomb_n[0])
    qa = (a_a**3 + a_b**3) / k**2
    qc = load + fc + a_b * pt - a_a * ps
    v = (-b + math.sqrt(b * b - 4 * qa * qc)) / (2 * qa)
    assert float(bank.v_m_s[0]) == pytest.approx(v, rel=2e-4)
    assert float(bank.p_a_pa[0]) == pytest.approx(ps - (a_a * v / k) ** 2, rel=1e-3)
    assert float(bank.p_b_pa[0]) == pytest.approx(pt + (a_b * v / k) ** 2, rel=1e-3)


def test_blocked_valve_compression_conserves_oil_mass(table3: CylinderParams) -> None:
    """Valve shut, no leakage, rod pushed in at a fixed speed: the oil mass in the cap
    chamber is constant, so ``p_A = p_0 + beta ln(V_0 / V)`` (linear bulk modulus)."""
    p = table3.select(0)
    v = -0.02  # m/s, retracting into the closed cap chamber
    x0, pa0, pb0 = 0.4, 5e6, 2e6

    def rhs(t: float, y: np.ndarray) -> list[float]:
        x = x0 + v * t
        q_a, q_b = orifice_flows(0.0, y[0], y[1], *_valve(p))
        dp_a, dp_b = chamber_pressure_derivatives(
            x, v, y[0], y[1], q_a, q_b, *_chambers(p, leakage=False)
        )
        return [float(dp_a[0]), float(dp_b[0])]

    sol = solve_ivp(rhs, (0.0, 0.05), [pa0, pb0], rtol=1e-11, atol=1e-3, dense_output=True)
    beta = float(p.bulk_modulus_pa[0])
    for t in (0.01, 0.03, 0.05):
        vol0 = float(p.dead_volume_a_m3[0] + p.area_a_m2[0] * x0)
        vol = float(p.dead_volume_a_m3[0] + p.area_a_m2[0] * (x0 + v * t))
        assert sol.sol(t)[0] == pytest.approx(pa0 + beta * math.log(vol0 / vol), rel=1e-8)
    assert sol.sol(0.05)[0] > pa0 + 1.5e6  # 1 mm of a 160 mm bore into 9 l: +1.56 MPa


def test_blocked_valve_leakage_decay_matches_the_linear_solution(table3: CylinderParams) -> None:
    """Valve shut, rod clamped: the pressures relax through the internal and external
    leakage as the linear system ``V/beta dp/dt = -C p`` says."""
    p = table3.select(1)
    x = 0.3
    beta = float(p.bulk_modulus_pa[0])
    c_il = float(p.internal_leakage_m3_s_pa[0])
    c_el = float(p.external_leakage_m3_s_pa[0])
    v_a = float(p.dead_volume_a_m3[0] + p.area_a_m2[0] * x)
    v_b = float(p.dead_volume_b_m3[0] + p.area_b_m2[0] * (p.stroke_m[0] - x))
    m = np.array(
        [
            [-(c_il + c_el) * beta / v_a, c_il * beta / v_a],
            [c_il * beta / v_b, -(c_il + c_el) * beta / v_b],
        ]
    )
    y0 = np.array([9e6, 3e6])

    def rhs(t: float, y: np.ndarray) -> list[float]:
        q_a, q_b = orifice_flows(0.0, y[0], y[1], *_valve(p))
        dp_a, dp_b = chamber_pressure_derivatives(x, 0.0, y[0], y[1], q_a, q_b, *_chambers(p))
        return [float(dp_a[0]), float(dp_b[0])]

    sol = solve_ivp(rhs, (0.0, 2.0), y0, rtol=1e-10, atol=1e-3, dense_output=True)
    for t in (0.1, 0.5, 2.0):
        np.testing.assert_allclose(sol.sol(t), expm(m * t) @ y0, rtol=1e-7)
    assert sol.sol(2.0)[0] < 0.5 * y0[0]  # the paper's leakage is not small


@pytest.mark.slow
def test_rest_equilibrium_holds_still(table3: CylinderParams) -> None:
    bank = CylinderBank(table3, step_s=0.5e-3)
    load = np.array([88.3e3, 95.1e3])
    hold = bank.hold_at(np.array([0.01, 0.3]), load)
    assert np.all(hold > 0)  # the valve feeds the cap side against leakage
    d = derivative(bank.state, hold, load, table3)
    assert np.max(np.abs(d[4:])) < 1.0  # Pa/s
    assert np.max(np.abs(d[3])) < 1e-9
    bank.advance(hold, load, 1.0)
    np.testing.assert_allclose(bank.x_m, [0.01, 0.3], atol=1e-7)


def test_kernel_matches_the_vectorized_model(table3: CylinderParams) -> None:
    """One compiled RK4 step equals an RK4 step of :func:`derivative` in NumPy."""
    bank = CylinderBank(table3, step_s=0.5e-3)
    bank.hold_at(np.array([0.2, 0.25]), np.array([80e3, 90e3]))
    bank.state[0] += np.array([1e-5, -2e-5])
    bank.state[3] += np.array([0.01, -0.01])
    s = bank.state.copy()
    u, f, h = np.array([0.3, -0.2]), np.array([80e3, 90e3]), bank.step_s
    k1 = derivative(s, u, f, table3)
    k2 = derivative(s + 0.5 * h * k1, u, f, table3)
    k3 = derivative(s + 0.5 * h * k2, u, f, table3)
    k4 = derivative(s + h * k3, u, f, table3)
    expected = s + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    bank.advance_steps(u, f, 1)
    np.testing.assert_allclose(bank.state, expected, rtol=1e-12, atol=1e-15)


def test_rk4_step_converges(table3: CylinderParams) -> None:
    """0.5 ms and 0.1 ms agree to well under a micrometre over a fast 0.5 s move."""
    finals = []
    for step in (0.5e-3, 0.1e-3):
        bank = CylinderBank(table3, step_s=step)
        load = np.array([88.3e3, 95.1e3])
        bank.hold_at(np.array([0.1, 0.1]), load)
        for k in range(500):
            u = np.full(2, 0.6 if k < 250 else -0.6)
            bank.advance(u, load, 1e-3)
        finals.append(bank.x_m.copy())
    np.testing.assert_allclose(finals[0], finals[1], atol=2e-7)


def test_end_stop_holds_the_rod(table3: CylinderParams) -> None:
    bank = CylinderBank(table3, step_s=0.25e-3)
    load = np.array([88.3e3, 95.1e3])
    bank.hold_at(np.array([0.002, 0.002]), load)
    for _ in range(500):
        bank.advance(np.full(2, -0.5), load, 1e-3)
    assert np.all(bank.x_m > -1e-3)
    assert np.all(np.abs(bank.v_m_s) < 1e-3)


def test_position_transducer_is_seeded_and_quantized() -> None:
    a = PositionTransducer(2, 1e-6, 2e-6, seed=3)
    b = PositionTransducer(2, 1e-6, 2e-6, seed=3)
    x = np.array([0.1, 0.2])
    ra = np.array([a.read(x) for _ in range(5000)])
    rb = np.array([b.read(x) for _ in range(5000)])
    np.testing.assert_array_equal(ra, rb)
    np.testing.assert_allclose(np.round(ra / 1e-6) * 1e-6, ra, atol=1e-12)
    assert np.std(ra[:, 0]) == pytest.approx(2e-6, rel=0.1)
    assert np.mean(ra[:, 1]) == pytest.approx(0.2, abs=1e-7)


def test_band_limited_noise_has_its_rms_and_band() -> None:
    dt = 1e-3
    noise = band_limited_noise(200_000, dt, 2500.0, 1.0, np.random.default_rng(1))
    assert np.sqrt(np.mean(noise**2)) == pytest.approx(2500.0)
    spectrum = np.abs(np.fft.rfft(noise)) ** 2
    freq = np.fft.rfftfreq(noise.size, dt)
    assert spectrum[freq > 10.0].sum() < 1e-3 * spectrum.sum()


def test_load_profile_steps_and_noise_start() -> None:
    dt = 1e-3
    loads = load_profile(
        10_000,
        dt,
        [80e3, 90e3],
        steps=[LoadStep(2.0, 1, 5e3)],
        noise_rms_n=1e3,
        noise_bandwidth_hz=2.0,
        noise_start_s=5.0,
        seed=4,
    )
    t = np.arange(10_000) * dt
    assert np.all(loads[t < 5.0, 0] == 80e3)
    assert np.all(loads[(t >= 2.0) & (t < 5.0), 1] == 95e3)
    assert np.all(loads[t < 2.0, 1] == 90e3)
    after = loads[t >= 5.0] - np.array([80e3, 95e3])
    assert np.sqrt(np.mean(after**2, axis=0)) == pytest.approx([1e3, 1e3])
    assert abs(np.corrcoef(after.T)[0, 1]) < 0.5  # independent per cylinder


def _valve(p: CylinderParams) -> tuple[np.ndarray, ...]:
    return (p.spool_max_m, p.orifice_coeff, p.supply_pa, p.tank_pa, p.regularization_pa)


def _chambers(p: CylinderParams, leakage: bool = True) -> tuple[np.ndarray, ...]:
    zero = np.zeros(1)
    return (
        p.area_a_m2,
        p.area_b_m2,
        p.stroke_m,
        p.dead_volume_a_m3,
        p.dead_volume_b_m3,
        p.bulk_modulus_pa,
        p.internal_leakage_m3_s_pa if leakage else zero,
        p.external_leakage_m3_s_pa if leakage else zero,
    )
