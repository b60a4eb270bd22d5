"""Position control of the part's slide axes (placement.md section 2): the rotation pair
(yaw), the lateral pair (y) and the central axis (x, the gap).

Each axis moves from its measured extension to its planned one on the trajectory's time
scaling (``planner.trajectory``: profile, rod speed and acceleration limits), all
starting and stopping together. The pairs are :class:`SyncGroup` s of LADRC (or PID)
controllers as the attitude layers are, synchronized on their tracking errors (the
rotation pair moves in opposition; its sync error is the difference of the two tracking
errors all the same); the central axis is one controller. Every other valve stays
closed. A move is checked against the strokes before it starts
(:meth:`SlideController.engage` refuses, naming the cylinder).

Work per cycle is bounded: one time-scaling sample and five controller updates.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from config import units
from config.schema import ProjectConfig
from ipc_app.control.attitude import cylinder_controller
from ipc_app.control.sync import Controller, SyncGroup
from ipc_app.planner.trajectory import time_scaling_at

FloatArray = NDArray[np.float64]

#: The slide roles, in the order of the moves (yaw and lateral, then the gap).
SLIDE_ROLES: tuple[str, ...] = ("rotation", "lateral", "central_axis")
#: Peak of ds/dtau and d2s/dtau2 of the quintic (10 t^3 - 15 t^4 + 6 t^5).
_QUINTIC_PEAKS = (1.875, 10.0 / math.sqrt(3.0))


class SlideController:
    """Follows a straight move of the slide axes to planned extensions (or holds)."""

    def __init__(self, cfg: ProjectConfig, period_s: float) -> None:
        self.cfg = cfg
        self.n = len(cfg.cylinders)
        ctl = cfg.control
        self.index: dict[str, list[int]] = {}
        self._ctrl: dict[str, list[Controller]] = {}
        self.half = np.zeros(self.n)
        self.limit_m: dict[int, float] = {}
        margin = units.mm(cfg.safety.stroke_end_margin_mm)
        for role in SLIDE_ROLES:
            cyls = sorted((c for c in cfg.cylinders if c.role == role), key=lambda c: c.id)
            self.index[role] = [c.can_index for c in cyls]
            members: list[Controller] = []
            for c in cyls:
                self.half[c.can_index] = c.stroke_m / 2
                self.limit_m[c.can_index] = c.stroke_m / 2 - margin
                members.append(cylinder_controller(cfg, c, period_s))
            self._ctrl[role] = members
        self.groups = {
            r: SyncGroup(m, ctl.sync.scheme, ctl.sync.coupling_lambda)
            for r, m in self._ctrl.items()
            if len(m) > 1
        }
        self.active: list[int] = [i for r in SLIDE_ROLES for i in self.index[r]]
        self.feedforward = ctl.controller == "ladrc" and ctl.ladrc.reference_feedforward
        self.profile = cfg.planner.trajectory.profile
        self.start = np.zeros(self.n)
        self.goal = np.zeros(self.n)
        self.t_start = 0.0
        self.duration_s = 0.0
        #: largest |sync error| of either pair and |reference - measurement| of any axis
        self.sync_error_m = 0.0
        self.tracking_error_m = 0.0

    def check(self, extensions_m: dict[str, tuple[float, ...]]) -> list[str]:
        """The reasons a move to ``extensions_m`` (role -> from mid-stroke) is refused."""
        why = []
        for role, values in extensions_m.items():
            idx = self.index[role]
            if len(values) != len(idx):
                why.append(f"{role}: {len(values)} extensions for {len(idx)} cylinders")
                continue
            for i, e in zip(idx, values, strict=True):
                if not abs(e) <= self.limit_m[i]:
                    cid = self.cfg.cylinders_by_can_index[i].id
                    why.append(
                        f"stroke: {cid} extension {units.to_mm(e):+.1f} mm beyond "
                        f"±{units.to_mm(self.limit_m[i]):.1f} mm (stroke less the end margin)"
                    )
        return why

    def engage(
        self, x_rod_m: FloatArray, t_now: float, extensions_m: dict[str, tuple[float, ...]]
    ) -> float:
        """Start the move from the measured rods to ``extensions_m`` (the roles left out
        hold where they are); returns its duration. ValueError if a stroke would break."""
        why = self.check(extensions_m)
        if why:
            raise ValueError("; ".join(why))
        x = np.asarray(x_rod_m, dtype=float)
        self.start = x.copy()
        self.goal = x.copy()
        for role, values in extensions_m.items():
            for i, e in zip(self.index[role], values, strict=True):
                self.goal[i] = self.half[i] + e
        dist = float(np.max(np.abs(self.goal - self.start)[self.active]))
        opts = self.cfg.planner.trajectory
        if self.profile == "quintic":
            vp, ap = _QUINTIC_PEAKS
        else:
            vp, ap = 1.0 / 0.75, (1.0 / 0.75) / 0.25
        self.duration_s = max(
            vp * dist / opts.max_rod_speed_m_s, math.sqrt(ap * dist / opts.max_rod_accel_m_s2)
        )
        self.t_start = t_now
        self.reset(x)
        return self.duration_s

    def reset(self, x_rod_m: FloatArray) -> None:
        """Every controller reset at its measurement with a zero command (bumpless)."""
        for role, members in self._ctrl.items():
            for c, i in zip(members, self.index[role], strict=True):
                c.reset(float(x_rod_m[i]))

    def goal_error_m(self, x_rod_m: FloatArray) -> float:
        """The largest |goal - measurement| of the moving axes (m)."""
        return max(abs(float(self.goal[i]) - float(x_rod_m[i])) for i in self.active)

    def motion_done(self, t_now: float) -> bool:
        return t_now - self.t_start >= self.duration_s

    def references(self, t_now: float) -> tuple[FloatArray, FloatArray]:
        """Rod references (m from retracted) and their rates, all 19."""
        if self.duration_s <= 0.0:
            return self.goal.copy(), np.zeros(self.n)
        s, ds = time_scaling_at(self.profile, (t_now - self.t_start) / self.duration_s)
        delta = self.goal - self.start
        return self.start + s * delta, delta * (ds / self.duration_s)

    def update(self, t_now: float, x_rod_m: FloatArray) -> FloatArray:
        """Valve commands (19 values in [-1, 1]) for this cycle."""
        ref, rate = self.references(t_now)
        x = np.asarray(x_rod_m, dtype=float)
        u = np.zeros(self.n)
        sync = 0.0
        track = 0.0
        for role in SLIDE_ROLES:
            idx = self.index[role]
            r = [float(ref[i]) for i in idx]
            y = [float(x[i]) for i in idx]
            v = [float(rate[i]) for i in idx] if self.feedforward else None
            if role in self.groups:
                g = self.groups[role]
                cmds = g.commands(r, y, v)
                sync = max(sync, *map(abs, g.last_sync_error))
            else:
                c = self._ctrl[role][0]
                cmds = [c.update(r[0], y[0], 0.0 if v is None else v[0])]
            for i, cmd in zip(idx, cmds, strict=True):
                u[i] = cmd
            track = max(track, *(abs(a - b) for a, b in zip(r, y, strict=True)))
        self.sync_error_m = sync
        self.tracking_error_m = track
        return u
