"""LADRC and the PID baseline on plants whose answer is known exactly."""

from __future__ import annotations

import math

import numpy as np
import pytest

from config import ProjectConfig
from ipc_app.control import LADRC, PID, cylinder_b0, eso_matrices


class ChainPlant:
    """``y^(n) = f + b u`` integrated exactly over a sample with ``u`` held (ZOH)."""

    def __init__(self, order: int, b: float, f: float = 0.0, y0: float = 0.0) -> None:
        self.order, self.b, self.f = order, b, f
        self.y, self.dy = y0, 0.0

    def step(self, u: float, dt: float) -> None:
        a = self.f + self.b * u
        if self.order == 1:
            self.y += a * dt
        else:
            self.y += self.dy * dt + 0.5 * a * dt * dt
            self.dy += a * dt


def test_public_api_of_the_issue() -> None:
    ctrl = LADRC(
        order=2, b0=3.0, wc=5.0, wo=20.0, dt=1e-3, u_min=-1.0, u_max=1.0, discretization="euler"
    )
    ctrl.reset(0.5)
    assert ctrl.z.shape == (3,)
    assert ctrl.z[0] == 0.5
    assert isinstance(ctrl.update(0.5, 0.5), float)
    with pytest.raises(ValueError, match="order"):
        LADRC(order=3, b0=1.0, wc=1.0, wo=1.0, dt=1e-3)
    with pytest.raises(ValueError, match="u_min"):
        LADRC(order=1, b0=1.0, wc=1.0, wo=1.0, dt=1e-3, u_min=1.0, u_max=-1.0)


@pytest.mark.parametrize("wo", [25.0, 80.0, 400.0])
def test_zoh_current_observer_gains_equal_herbst(wo: float) -> None:
    dt = 1e-3
    beta = math.exp(-wo * dt)
    _, _, l1 = eso_matrices(1, 0.05, wo, dt, "zoh")
    np.testing.assert_allclose(l1, [1 - beta**2, (1 - beta) ** 2 / dt], rtol=1e-9)
    _, _, l2 = eso_matrices(2, 0.05, wo, dt, "zoh")
    herbst2 = [1 - beta**3, 1.5 * (1 - beta) ** 2 * (1 + beta) / dt, (1 - beta) ** 3 / dt**2]
    np.testing.assert_allclose(l2, herbst2, rtol=1e-9)


@pytest.mark.parametrize("order", [1, 2])
def test_observer_poles(order: int) -> None:
    dt, wo = 1e-3, 60.0
    c = np.zeros(order + 1)
    c[0] = 1.0
    phi, _, gain = eso_matrices(order, 2.0, wo, dt, "zoh")
    eig = np.linalg.eigvals(phi @ (np.eye(order + 1) - np.outer(gain, c)))
    np.testing.assert_allclose(eig, math.exp(-wo * dt), atol=2e-4 * order)
    phi, _, gain = eso_matrices(order, 2.0, wo, dt, "euler")
    eig = np.linalg.eigvals(phi - np.outer(gain, c))
    np.testing.assert_allclose(eig, 1 - wo * dt, atol=2e-4 * order)
    assert gain[0] == pytest.approx((order + 1) * wo * dt)


@pytest.mark.parametrize("discretization", ["euler", "zoh"])
@pytest.mark.parametrize("order", [1, 2])
def test_leso_converges_to_a_constant_disturbance(order: int, discretization: str) -> None:
    """A constant unknown ``f`` is estimated exactly and rejected with zero error."""
    dt, b, f = 1e-3, 2.0, 0.7
    plant = ChainPlant(order, b, f)
    ctrl = LADRC(
        order, b0=b, wc=8.0, wo=40.0, dt=dt, u_min=-5, u_max=5, discretization=discretization
    )  # type: ignore[arg-type]
    r = 0.3
    for _ in range(6000):
        plant.step(ctrl.update(r, plant.y), dt)
    assert ctrl.z[-1] == pytest.approx(f, abs=1e-6)
    assert plant.y == pytest.approx(r, abs=1e-9)
    assert ctrl.command == pytest.approx(-f / b, abs=1e-6)


@pytest.mark.parametrize("discretization", ["euler", "zoh"])
def test_second_order_ladrc_follows_the_critically_damped_response(discretization: str) -> None:
    """Exactly known plant ``y'' = b0 u``: the loop is ``y'' = wc^2 (r - y) - 2 wc y'``,
    whose step response is ``1 - (1 + wc t) e^(-wc t)``."""
    dt, wc, b0 = 1e-4, 10.0, 4.0
    plant = ChainPlant(2, b0)
    ctrl = LADRC(
        2, b0=b0, wc=wc, wo=10 * wc, dt=dt, u_min=-1e3, u_max=1e3, discretization=discretization
    )  # type: ignore[arg-type]
    ctrl.reset(0.0)
    worst = 0.0
    for k in range(1, 10_001):
        plant.step(ctrl.update(1.0, plant.y), dt)
        t = k * dt
        worst = max(worst, abs(plant.y - (1 - (1 + wc * t) * math.exp(-wc * t))))
    assert worst < 3e-3  # of a unit step
    assert plant.y == pytest.approx(1 - 11 * math.exp(-10.0), abs=1e-3)


def test_first_order_ladrc_follows_the_exponential() -> None:
    dt, wc, b0 = 1e-4, 12.0, 0.05
    plant = ChainPlant(1, b0)
    ctrl = LADRC(1, b0=b0, wc=wc, wo=8 * wc, dt=dt, u_min=-1e3, u_max=1e3)
    worst = 0.0
    for k in range(1, 5001):
        plant.step(ctrl.update(0.01, plant.y), dt)
        worst = max(worst, abs(plant.y - 0.01 * (1 - math.exp(-wc * k * dt))))
    assert worst < 1e-5  # 0.1 % of the step


@pytest.mark.parametrize("order", [1, 2])
def test_reference_feedforward_removes_the_ramp_lag(order: int) -> None:
    """A ramp ``r = v t``: the plain law lags by ``v / kp`` (first order) or
    ``kd v / kp`` (second order); with ``r'`` fed forward the error goes to zero."""
    dt, wc, b0, v = 1e-3, 6.0, 0.05, 0.01  # 10 mm/s
    lags = {}
    for ff in (False, True):
        plant = ChainPlant(order, b0)
        ctrl = LADRC(order, b0=b0, wc=wc, wo=4 * wc, dt=dt, u_min=-1e3, u_max=1e3)
        for k in range(4000):  # 4 s: far past the transients
            r = v * k * dt
            plant.step(ctrl.update(r, plant.y, v if ff else 0.0), dt)
        lags[ff] = v * 3999 * dt - plant.y
    expected = v / wc if order == 1 else 2 * wc * v / wc**2
    assert lags[False] == pytest.approx(expected, rel=0.05)
    assert abs(lags[True]) < 0.01 * lags[False]


def test_bumpless_start_and_rate_limit() -> None:
    dt = 1e-3
    ctrl = LADRC(1, b0=0.05, wc=12.0, wo=25.0, dt=dt, rate_limit=20.0)
    ctrl.reset(0.25, command=0.3)
    assert ctrl.update(0.25, 0.25) == pytest.approx(0.3, abs=1e-12)
    commands = [ctrl.update(0.35, 0.25) for _ in range(20)]  # 100 mm step
    steps = np.diff([0.3, *commands])
    assert np.max(np.abs(steps)) <= 20.0 * dt + 1e-12
    assert commands[-1] == pytest.approx(0.3 + 20 * 20.0 * dt)  # ramping, not jumping


@pytest.mark.parametrize("order", [1, 2])
def test_saturation_feeds_the_observer_the_limited_command(order: int) -> None:
    """A large step saturates the command; the observer is fed what was applied, so
    its disturbance estimate stays at the truth (0): no windup, and the loop settles.
    (A saturated double integrator overshoots whatever the observer does; a first-order
    loop must not.)"""
    dt, b = 1e-3, 1.0
    plant = ChainPlant(order, b)
    ctrl = LADRC(order, b0=b, wc=5.0, wo=30.0, dt=dt, u_min=-0.2, u_max=0.2)
    us, f_hat, ys = [], [], []
    for _ in range(20_000):
        u = ctrl.update(1.0, plant.y)
        plant.step(u, dt)
        us.append(u)
        f_hat.append(ctrl.z[-1])
        ys.append(plant.y)
    assert max(abs(u) for u in us) <= 0.2
    assert sum(1 for u in us if abs(u) == 0.2) > 1000  # it really saturated
    assert max(abs(f) for f in f_hat) < 1e-6
    if order == 1:
        assert max(ys) < 1.0 + 1e-9
    assert ys[-1] == pytest.approx(1.0, abs=1e-6)


def _pi_step(pid: PID | None, kp: float, ki: float, dt: float, u_lim: float) -> list[float]:
    plant = ChainPlant(1, 1.0)
    integral = 0.0
    ys = []
    for _ in range(20_000):
        e = 1.0 - plant.y
        if pid is not None:
            u = pid.update(1.0, plant.y)
        else:  # naive PI: integrates regardless of saturation
            integral += ki * dt * e
            u = min(max(kp * e + integral, -u_lim), u_lim)
        plant.step(u, dt)
        ys.append(plant.y)
    return ys


def test_pid_anti_windup_prevents_the_saturation_overshoot() -> None:
    dt, kp, ki, lim = 1e-3, 2.0, 4.0, 0.2
    pid = PID(kp, ki, 0.0, dt, u_min=-lim, u_max=lim)
    with_aw = _pi_step(pid, kp, ki, dt, lim)
    naive = _pi_step(None, kp, ki, dt, lim)
    overshoot_aw = max(with_aw) - 1.0
    overshoot_naive = max(naive) - 1.0
    assert overshoot_naive > 0.3  # the naive integrator winds up badly
    assert overshoot_aw < 0.25 * overshoot_naive
    assert with_aw[-1] == pytest.approx(1.0, abs=1e-4)
    assert abs(pid.integral) <= lim + 1e-9


def test_pid_bumpless_rate_limit_and_derivative_on_measurement() -> None:
    dt = 1e-3
    pid = PID(100.0, 20.0, 2.0, dt, rate_limit=20.0)
    pid.reset(0.1, command=0.05)
    assert pid.update(0.1, 0.1) == pytest.approx(0.05)
    u = [pid.update(0.2, 0.1) for _ in range(10)]  # reference step: no derivative kick
    assert np.max(np.abs(np.diff([0.05, *u]))) <= 20.0 * dt + 1e-12


def test_b0_from_valve_flow_gain_and_cap_area(project: ProjectConfig) -> None:
    cyl = project.cylinder("main_leg_1")
    hyd = project.hydraulics
    kq = 0.61 * 0.026 * 0.5e-3 * math.sqrt((16e6 - 0.3e6) / 850)
    assert cylinder_b0(cyl, hyd) == pytest.approx(kq / (math.pi * 0.08**2))
    assert 0.04 < cylinder_b0(cyl, hyd) < 0.07  # m/s at full command
    assert cylinder_b0(cyl, hyd, order=2) > 10 * cylinder_b0(cyl, hyd)


@pytest.mark.parametrize("order", [1, 2])
@pytest.mark.parametrize("discretization", ["zoh", "euler"])
def test_apply_feeds_the_observer_the_command_applied(order: int, discretization: str) -> None:
    """A command set after ``update`` (a modal controller's) leaves the loop as if it had
    computed that command itself: its observer's next estimate is that of a loop that
    saturated at it."""
    free = LADRC(order, 2.0, 5.0, 20.0, 0.01, discretization=discretization)  # type: ignore[arg-type]
    u = free.update(1.0, 0.0)
    v = 0.4 * u
    capped = LADRC(order, 2.0, 5.0, 20.0, 0.01, u_max=v, discretization=discretization)  # type: ignore[arg-type]
    assert capped.update(1.0, 0.0) == v
    assert free.apply(v) == v and free.command == v
    free.update(1.0, 0.01)
    capped.update(1.0, 0.01)
    assert free.z == pytest.approx(capped.z, rel=1e-12)  # the same estimate


@pytest.mark.parametrize("order", [1, 2])
def test_a_known_disturbance_is_rejected_before_the_observer_sees_it(order: int) -> None:
    """A disturbance ``f`` that switches on (a rod's decompression as its leg unloads):
    told to the loop as ``known_disturbance``, the observer's model carries it, its last
    state stays at the unknown rest (none here) and the error stays far below the plain
    loop's, which has to estimate ``f`` first; 0 leaves the loop as it was."""
    dt, wc, b0, f = 5e-3, 6.0, 0.05, 2e-3  # 2 mm/s
    worst = {}
    for told in (False, True):
        plant = ChainPlant(order, b0)
        ctrl = LADRC(order, b0=b0, wc=wc, wo=2 * wc, dt=dt, u_min=-1e3, u_max=1e3)
        ctrl.reset(0.0)
        worst[told] = 0.0
        for k in range(600):
            plant.f = f if k >= 100 else 0.0
            u = ctrl.update(0.0, plant.y, 0.0, plant.f if told else 0.0)
            plant.step(u, dt)
            worst[told] = max(worst[told], abs(plant.y))
        assert plant.y == pytest.approx(0.0, abs=1e-4 * f)
        assert ctrl.z[-1] == pytest.approx(0.0 if told else f, abs=1e-3 * f)
    assert worst[False] > 0.01 * f  # some 0.1 s of f before the plain loop caught it
    assert worst[True] < 1e-6 * worst[False]
    plain, zero = (LADRC(order, b0=b0, wc=wc, wo=2 * wc, dt=dt) for _ in range(2))
    for k in range(50):
        y = 1e-3 * math.sin(0.3 * k)
        assert plain.update(0.01, y, 0.1) == zero.update(0.01, y, 0.1, 0.0)
