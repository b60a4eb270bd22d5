"""Linear active disturbance rejection control (LADRC), first and second order.

The plant is taken as ``y^(n) = f + b0 u`` (n = 1 or 2): ``f`` is the "total
disturbance" (everything but ``b0 u``), estimated by a linear extended state observer
(LESO) with state ``z = [y, ..., y^(n-1), f]``. Gao's bandwidth parameterization sets
all observer poles at ``-wo`` and the controller gains from ``wc``:
``kp = wc`` (n = 1); ``kp = wc^2, kd = 2 wc`` (n = 2). The control law cancels the
estimated disturbance: ``u = (kp (r - z1) [- kd z2] - z_last) / b0``.

Discretization (model.md section 10):

- ``"euler"``: forward-Euler observer, ``z[k+1] = (I + A T) z[k] + B T u[k] + L T (y[k] - z1[k])``
  with ``L = [C(n+1, i) wo^i]``; the control uses ``z[k]`` (one sample old); observer
  poles at ``1 - wo T``.
- ``"zoh"``: the exact (zero-order hold) model with a "current" observer (Miklosovic,
  Herbst): the estimate is corrected with ``y[k]`` before computing ``u[k]``, then
  predicted; observer poles at ``exp(-wo T)``. The gains are placed with Ackermann's
  formula and equal Herbst's closed forms (tests/test_ladrc.py checks them).

Reference feed-forward (a decision; model.md is silent): ``update`` takes the
reference's rate ``r'`` where the reference generator knows it (the planner's
trajectory does). With it, the control law is Gao's tracking form
``u = (kp (r - z1) + r' - z2) / b0`` (n = 1) and
``u = (kp (r - z1) + kd (r' - z2) - z3) / b0`` (n = 2, no ``r''`` term): the
feedback only has to correct what the model misses, so a ramp is followed without
the ``r' / kp`` lag of the plain law, and ``wc`` can be chosen for robustness (delay,
the oil-column mode) rather than for tracking. ``r' = 0`` (the default) is the plain
law of model.md.

The command is rate limited, then saturated, and the observer is always fed the
command actually applied, which is what keeps it (and the loop) free of windup.
Start is bumpless: :meth:`LADRC.reset` sets ``z = [y, 0, ..., -b0 u_hold]`` so the
first command equals the held one when the reference equals the measurement.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from config.schema import Ladrc

Discretization = Literal["euler", "zoh"]
FloatArray = NDArray[np.float64]


def eso_matrices(
    order: int, b0: float, wo: float, dt: float, discretization: Discretization
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Discrete LESO ``(Phi, Gamma, L)`` for ``y^(order) = f + b0 u``, poles from ``wo``.

    Euler: ``z+ = Phi z + Gamma u + L (y - z1)``. ZOH current observer: correct
    ``z = z_pred + L (y - z1_pred)``, then ``z_pred+ = Phi z + Gamma u``.
    """
    if order not in (1, 2):
        raise ValueError(f"order must be 1 or 2, got {order}")
    m = order + 1
    a = np.eye(m, k=1)
    b = np.zeros(m)
    b[order - 1] = b0
    if discretization == "euler":
        phi = np.eye(m) + a * dt
        gamma = b * dt
        gain = np.array([math.comb(m, i) * wo**i for i in range(1, m + 1)]) * dt
        return phi, gamma, gain
    if discretization != "zoh":
        raise ValueError(f"discretization must be 'euler' or 'zoh', got {discretization!r}")
    # Exact discretization of the integrator chain: Phi = sum (A T)^k / k!.
    phi = np.zeros((m, m))
    gamma_op = np.zeros((m, m))  # integral of exp(A s) ds over [0, T]
    power = np.eye(m)
    for k in range(m):
        phi += power * dt**k / math.factorial(k)
        gamma_op += power * dt ** (k + 1) / math.factorial(k + 1)
        power = power @ a
    gamma = gamma_op @ b
    # Current observer: error e+ = Phi (I - L C) e. Place eig(Phi - K C) at beta with
    # Ackermann (K = p(Phi) O^-1 e_m), then L = Phi^-1 K.
    beta = math.exp(-wo * dt)
    c = np.zeros(m)
    c[0] = 1.0
    obs = np.vstack([c @ np.linalg.matrix_power(phi, i) for i in range(m)])
    coeffs = np.poly(np.full(m, beta))  # (z - beta)^m
    p_phi = sum(coef * np.linalg.matrix_power(phi, m - i) for i, coef in enumerate(coeffs))
    e_m = np.zeros(m)
    e_m[-1] = 1.0
    k_pred = p_phi @ np.linalg.solve(obs, e_m)
    gain = np.linalg.solve(phi, k_pred)
    return phi, gamma, gain


class LADRC:
    """Discrete LADRC of one axis; ``update(reference, measurement) -> command``.

    Arguments: ``order`` 1 or 2; ``b0`` the input gain of ``y^(n) = f + b0 u``;
    ``wc``, ``wo`` controller and observer bandwidths (rad/s); ``dt`` the sample period
    (s); ``u_min``, ``u_max`` the command limits; ``discretization`` ``"euler"`` or
    ``"zoh"``; ``rate_limit`` the largest command change per second (``None``: none).
    """

    def __init__(
        self,
        order: int,
        b0: float,
        wc: float,
        wo: float,
        dt: float,
        u_min: float = -1.0,
        u_max: float = 1.0,
        discretization: Discretization = "zoh",
        rate_limit: float | None = None,
    ) -> None:
        if order not in (1, 2):
            raise ValueError(f"order must be 1 or 2, got {order}")
        for name, value in (("b0", b0), ("wc", wc), ("wo", wo), ("dt", dt)):
            if not value > 0:
                raise ValueError(f"{name} must be > 0, got {value}")
        if not u_min < u_max:
            raise ValueError(f"u_min ({u_min}) must be below u_max ({u_max})")
        if rate_limit is not None and not rate_limit > 0:
            raise ValueError(f"rate_limit must be > 0 or None, got {rate_limit}")
        self.order = order
        self.b0 = float(b0)
        self.wc = float(wc)
        self.wo = float(wo)
        self.dt = float(dt)
        self.u_min = float(u_min)
        self.u_max = float(u_max)
        self.discretization: Discretization = discretization
        self.rate_limit = rate_limit
        self._du_max = math.inf if rate_limit is None else rate_limit * dt
        phi, gamma, gain = eso_matrices(order, b0, wo, dt, discretization)
        self._phi = [[float(v) for v in row] for row in phi]
        self._gamma = [float(v) for v in gamma]
        self._gain = [float(v) for v in gain]
        self._current = discretization == "zoh"
        self.kp = wc if order == 1 else wc * wc
        self.kd = 0.0 if order == 1 else 2.0 * wc
        self._z = [0.0] * (order + 1)  # estimate at the present sample
        self._zp = [0.0] * (order + 1)  # prediction for the next sample
        self._u = 0.0
        self._started = False

    @classmethod
    def from_config(
        cls,
        cfg: Ladrc,
        b0: float,
        dt: float,
        u_min: float = -1.0,
        u_max: float = 1.0,
        *,
        wc: float | None = None,
        wo: float | None = None,
    ) -> LADRC:
        """Build from the ``control.ladrc`` section of a project or scenario; ``wc`` and
        ``wo`` (the loop's tuning, :mod:`ipc_app.control.tuning`) where the section
        leaves them to be derived."""
        wc = cfg.wc_rad_s if wc is None else wc
        wo = cfg.wo_rad_s if wo is None else wo
        if wc is None or wo is None:
            raise ValueError(
                "control.ladrc.wc_rad_s / wo_rad_s not given: pass the derived bandwidths "
                "(ipc_app.control.tuning.position_bandwidths)"
            )
        return cls(
            order=cfg.order,
            b0=b0,
            wc=wc,
            wo=wo,
            dt=dt,
            u_min=u_min,
            u_max=u_max,
            discretization=cfg.discretization,
            rate_limit=cfg.rate_limit_per_s,
        )

    @property
    def z(self) -> FloatArray:
        """Observer estimate ``[y, (y'), f]`` used for the latest command."""
        return np.array(self._z)

    @property
    def command(self) -> float:
        """The latest command (after rate limit and saturation)."""
        return self._u

    @property
    def holding_command(self) -> float:
        """The command that holds the plant at rest against the disturbance the observer
        has learned (``-f / b0``): the motion's share of :attr:`command` left out."""
        return -self._z[-1] / self.b0

    def reset(self, measurement: float, command: float = 0.0) -> None:
        """Bumpless (re)start: observer at ``y``, at rest, holding ``command``."""
        u = min(max(float(command), self.u_min), self.u_max)
        z = [float(measurement)] + [0.0] * self.order
        z[-1] = -self.b0 * u  # at rest y^(n) = 0 = f + b0 u
        self._z = list(z)
        self._zp = list(z)
        self._u = u
        self._started = True

    def set_observer(self, wo: float) -> None:
        """Change the observer's bandwidth (rad/s) from the next sample on; the estimate
        and the command carry over (bumpless: the state does not depend on ``wo``)."""
        if not wo > 0:
            raise ValueError(f"wo must be > 0, got {wo}")
        if wo == self.wo:
            return
        phi, gamma, gain = eso_matrices(self.order, self.b0, wo, self.dt, self.discretization)
        self.wo = float(wo)
        self._phi = [[float(v) for v in row] for row in phi]
        self._gamma = [float(v) for v in gamma]
        self._gain = [float(v) for v in gain]

    def apply(self, command: float) -> float:
        """The command actually applied this period instead of the latest ``update``'s
        (a modal controller that sets one mode of several loops' commands itself):
        saturated, fed to the observer's prediction in its place (the prediction is
        linear in the command) and taken as the latest command for the rate limit."""
        u = min(max(float(command), self.u_min), self.u_max)
        du = u - self._u
        self._zp = [zp + gm * du for zp, gm in zip(self._zp, self._gamma, strict=True)]
        self._u = u
        return u

    def update(
        self,
        reference: float,
        measurement: float,
        reference_rate: float = 0.0,
        known_disturbance: float = 0.0,
    ) -> float:
        """One sample: read ``measurement``, return the command for this period.

        ``reference_rate``: ``d reference / dt`` (feed-forward; 0: the plain law).
        ``known_disturbance``: the part of ``f`` known from elsewhere (units of
        ``y^(n)``, held over the period): the observer's model carries it, so its last
        state estimates only the rest, and the control law cancels both (0: none).
        """
        if not self._started:
            self.reset(measurement)
        zp = self._zp
        g = self._gain
        innovation = float(measurement) - zp[0]
        # Written out for n = 1 and n = 2: this runs once per cylinder per period.
        # Current observer: correct with y[k] now; Euler: correct the next prediction.
        now, later = (innovation, 0.0) if self._current else (0.0, innovation)
        if self.order == 1:
            z = [zp[0] + g[0] * now, zp[1] + g[1] * now]
            f_all = z[1] + known_disturbance
            u0 = (self.kp * (reference - z[0]) + reference_rate - f_all) / self.b0
        else:
            z = [zp[0] + g[0] * now, zp[1] + g[1] * now, zp[2] + g[2] * now]
            u0 = (
                self.kp * (reference - z[0])
                + self.kd * (reference_rate - z[1])
                - z[2]
                - known_disturbance
            ) / self.b0
        last = self._u
        if u0 > last + self._du_max:
            u0 = last + self._du_max
        elif u0 < last - self._du_max:
            u0 = last - self._du_max
        u = self.u_max if u0 > self.u_max else (self.u_min if u0 < self.u_min else u0)
        phi = self._phi
        gamma = self._gamma
        if self.order == 1:
            nxt = [
                phi[0][0] * z[0] + phi[0][1] * z[1] + gamma[0] * u + g[0] * later,
                phi[1][0] * z[0] + phi[1][1] * z[1] + gamma[1] * u + g[1] * later,
            ]
            if known_disturbance:
                nxt[0] += self.dt * known_disturbance
        else:
            nxt = [
                phi[i][0] * z[0] + phi[i][1] * z[1] + phi[i][2] * z[2] + gamma[i] * u + g[i] * later
                for i in range(3)
            ]
            if known_disturbance:
                nxt[0] += 0.5 * self.dt * self.dt * known_disturbance
                nxt[1] += self.dt * known_disturbance
        self._z = z
        self._zp = nxt
        self._u = u
        return u
