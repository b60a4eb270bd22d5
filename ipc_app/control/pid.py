"""PID baseline with the same command handling as :class:`ipc_app.control.LADRC`.

``u = kp e + I + D``; the derivative acts on the measurement (no kick on reference
steps) through a first-order filter; the command is rate limited then saturated,
and the integrator winds back by back-calculation, ``I += ki T e + (T / Tt)(u - v)``
with ``v`` the unlimited output and ``Tt = Ti`` (``sqrt(Ti Td)`` with a D term), so it
stops growing as soon as the command is limited.
"""

from __future__ import annotations

import math

from config.schema import Pid


class PID:
    """Discrete PID of one axis; ``update(reference, measurement) -> command``.

    Gains in command units: ``kp`` per metre of error, ``ki`` per metre-second,
    ``kd`` per metre per second. ``derivative_filter_hz`` is the corner of the
    derivative's low-pass; ``rate_limit`` the largest command change per second.
    """

    def __init__(
        self,
        kp: float,
        ki: float,
        kd: float,
        dt: float,
        u_min: float = -1.0,
        u_max: float = 1.0,
        rate_limit: float | None = None,
        derivative_filter_hz: float = 20.0,
    ) -> None:
        if min(kp, ki, kd) < 0:
            raise ValueError(f"gains must be >= 0, got kp={kp} ki={ki} kd={kd}")
        if not dt > 0:
            raise ValueError(f"dt must be > 0, got {dt}")
        if not u_min < u_max:
            raise ValueError(f"u_min ({u_min}) must be below u_max ({u_max})")
        if rate_limit is not None and not rate_limit > 0:
            raise ValueError(f"rate_limit must be > 0 or None, got {rate_limit}")
        self.kp, self.ki, self.kd, self.dt = float(kp), float(ki), float(kd), float(dt)
        self.u_min, self.u_max = float(u_min), float(u_max)
        self.rate_limit = rate_limit
        self._du_max = math.inf if rate_limit is None else rate_limit * dt
        tau_d = 1.0 / (2.0 * math.pi * derivative_filter_hz)
        self._alpha = dt / (dt + tau_d)
        if ki > 0:
            ti = kp / ki if kp > 0 else dt
            td = kd / kp if kp > 0 else 0.0
            self.tracking_time_s = math.sqrt(ti * td) if td > 0 else ti
        else:
            self.tracking_time_s = math.inf
        self._aw = dt / self.tracking_time_s
        self.integral = 0.0
        self._rate = 0.0
        self._y_prev = 0.0
        self._u = 0.0
        self._started = False

    @classmethod
    def from_config(
        cls,
        cfg: Pid,
        dt: float,
        u_min: float = -1.0,
        u_max: float = 1.0,
        rate_limit: float | None = None,
    ) -> PID:
        """Build from the ``control.pid`` section of a project or scenario."""
        return cls(
            kp=cfg.kp_per_m,
            ki=cfg.ki_per_m_s,
            kd=cfg.kd_s_per_m,
            dt=dt,
            u_min=u_min,
            u_max=u_max,
            rate_limit=rate_limit,
            derivative_filter_hz=cfg.derivative_filter_hz,
        )

    @property
    def command(self) -> float:
        return self._u

    @property
    def holding_command(self) -> float:
        """The command that holds the plant at rest: the integrator's part."""
        return self.integral

    def reset(self, measurement: float, command: float = 0.0) -> None:
        """Bumpless (re)start: the integrator holds ``command``, the derivative is at rest."""
        u = min(max(float(command), self.u_min), self.u_max)
        self.integral = u
        self._rate = 0.0
        self._y_prev = float(measurement)
        self._u = u
        self._started = True

    def update(self, reference: float, measurement: float, reference_rate: float = 0.0) -> float:
        """One sample. ``reference_rate`` is accepted for the common interface and not
        used: the PID is the paper's feedback-only baseline."""
        if not self._started:
            self.reset(measurement)
        y = float(measurement)
        e = reference - y
        rate = -(y - self._y_prev) / self.dt
        self._rate += self._alpha * (rate - self._rate)
        self._y_prev = y
        v = self.kp * e + self.integral + self.kd * self._rate
        du = v - self._u
        u = v
        if du > self._du_max:
            u = self._u + self._du_max
        elif du < -self._du_max:
            u = self._u - self._du_max
        u = min(max(u, self.u_min), self.u_max)
        self.integral += self.ki * self.dt * e + self._aw * (u - v)
        self._u = u
        return u
