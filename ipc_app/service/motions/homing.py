"""Homing (``wara ctl home``): each attitude layer to its reference stroke, level, at rest.

The machine needs it after commissioning and after a fault: the eight attitude cylinders
go from where they stand to mid-stroke (the reference of every plan, extension 0), so
both layers end parallel to their bases and the workpiece at the base's attitude, then
hold there (COMPLETE). The walk's legs and travel rods and the slide axes do not move.

The path is a straight line in the cylinders' extensions, ``d_i(t) = d_i(0) (1 - s(t))``
on the planner's time scaling (``planner.trajectory.profile``): every cylinder starts and
stops together, a layer's twist and heave shrink with ``s``, and the rod speed, the
acceleration and the pump's flow stay within ``planner.trajectory.max_rod_speed_mm_s``,
``max_rod_accel_mm_s2`` and ``hydraulics.pump_flow_l_min`` as for a planned adjustment
(the same bounds as :func:`~ipc_app.planner.trajectory.plan_trajectory`, exact here: the
path's derivative in ``s`` is constant). It starts at the rods measured when the loop
takes the request; in PRODUCTION or MANUAL, from IDLE or COMPLETE.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from config import units
from ipc_app.control.attitude import AttitudeController
from ipc_app.planner.trajectory import time_scaling, time_scaling_at
from ipc_app.service.machine_io import MachineInputs
from ipc_app.service.motion import Motion, Service
from ipc_app.service.motions.attitude import LayersMotion
from ipc_app.service.requests import Reply


class HomePath:
    """The eight extensions (m from mid-stroke; four per layer) from their start to 0 on
    one time scaling: the trajectory interface (``duration_s``, ``sample``,
    ``positions``) the attitude controller follows."""

    def __init__(
        self, start_lower: list[float], start_upper: list[float], duration_s: float, profile: str
    ) -> None:
        self._lower, self._upper = start_lower, start_upper
        self.duration_s = duration_s
        self._profile = profile

    def _s(self, t: float) -> tuple[float, float]:
        if self.duration_s <= 0.0:
            return 1.0, 0.0
        s, ds = time_scaling_at(self._profile, t / self.duration_s)
        return s, ds / self.duration_s

    def positions(self, t: float) -> tuple[list[float], list[float]]:
        s, _ = self._s(t)
        return [d * (1.0 - s) for d in self._lower], [d * (1.0 - s) for d in self._upper]

    def sample(self, t: float) -> tuple[list[float], list[float], list[float], list[float]]:
        s, rate = self._s(t)
        lo, up = self._lower, self._upper
        return (
            [d * (1.0 - s) for d in lo],
            [d * (1.0 - s) for d in up],
            [-d * rate for d in lo],
            [-d * rate for d in up],
        )


class HomingMotion(LayersMotion):
    """See the module docstring."""

    name = "home"
    answers_hmi = False  # the HMI has no homing request

    def __init__(self, svc: Service, attitude: AttitudeController) -> None:
        super().__init__(attitude)
        cfg = svc.cfg
        traj = cfg.planner.trajectory
        self.profile = traj.profile
        self.v_max, self.a_max = traj.max_rod_speed_m_s, traj.max_rod_accel_m_s2
        self.pump_m3_s = cfg.hydraulics.pump_flow_m3_s
        by_index = cfg.cylinders_by_can_index
        self.half = np.array([c.stroke_m / 2 for c in by_index])
        self.cap_m2 = np.array([c.cap_area_m2 for c in by_index])
        _, ds, dds = time_scaling(self.profile, np.linspace(0.0, 1.0, 2001))
        #: the profile's peak ds/dtau and |d2s/dtau2|
        self.c_v, self.c_a = float(np.max(ds)), float(np.max(np.abs(dds)))
        self.home_path: HomePath | None = None
        #: the workpiece's attitude at home: the base's (both layers parallel to it)
        self.target_deg = (units.to_deg(cfg.base.roll_rad), units.to_deg(cfg.base.pitch_rad))

    @classmethod
    def prepare(cls, svc: Service, *args: Any) -> Motion | Reply:
        return cls(svc, svc.attitude)

    def describe(self) -> str:
        return "each attitude layer to mid-stroke, level"

    def accepted(self) -> dict[str, Any]:
        return {"duration_s": self.home_path.duration_s if self.home_path else 0.0}

    def duration_s(self, d: np.ndarray, idx: list[int]) -> float:
        """The shortest time for extensions ``d`` (of cylinders ``idx``) to reach 0 on
        the profile within the rod speed, the pump's flow and the acceleration."""
        longest = float(np.max(np.abs(d)))
        flow = float(np.sum(self.cap_m2[idx] * np.maximum(-d, 0.0)))  # extending rods
        return max(
            self.c_v * longest / self.v_max,
            self.c_v * flow / self.pump_m3_s,
            float(np.sqrt(self.c_a * longest / self.a_max)),
        )

    def path_from(self, inp: MachineInputs) -> Any:
        x = inp.positions.value
        lo, up = self.attitude.layers["lower"], self.attitude.layers["upper"]
        idx = lo + up
        d = x[idx] - self.half[idx]
        self.home_path = HomePath(
            d[:4].tolist(), d[4:].tolist(), self.duration_s(d, idx), self.profile
        )
        return self.home_path

    def status(self) -> dict[str, Any] | None:
        p = self.home_path
        if p is None:
            return None
        lo, up = p.positions(0.0)
        return {
            "duration_s": round(p.duration_s, 3),
            "from_mm": round(units.to_mm(max(abs(v) for v in lo + up)), 3),
        }
