"""Closed-loop attitude control of the eight attitude cylinders (two linked groups of 4).

The planner's trajectory gives each cylinder's extension from mid-stroke over time; the
wire carries rod positions from the retracted end, so ``x_ref = stroke / 2 + d(t)``.
Each layer is one :class:`SyncGroup` (dual-error feedback, model.md section 10) of
LADRC (or PID) controllers; every other cylinder's valve stays closed (command 0).

With ``control.ladrc.reference_feedforward`` the trajectory's rod speeds go to the
controllers as feed-forward (docs/control.md); the synchronization term stays feedback.

Work per cycle is bounded: one trajectory sample and 8 controller updates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from config.schema import Cylinder, ProjectConfig
from ipc_app.control.ladrc import LADRC
from ipc_app.control.pid import PID
from ipc_app.control.plant_gain import cylinder_b0
from ipc_app.control.sync import Controller, SyncGroup
from ipc_app.control.tuning import position_bandwidths
from ipc_app.model.kinematics import layer_twist
from ipc_app.planner.trajectory import Trajectory

FloatArray = NDArray[np.float64]


def cylinder_controller(cfg: ProjectConfig, cyl: Cylinder, period_s: float) -> Controller:
    """The position controller of one cylinder as ``control`` configures it: LADRC with
    the cylinder's plant gain and its group's bandwidths (:mod:`ipc_app.control.tuning`),
    or PID."""
    ctl = cfg.control
    if ctl.controller == "ladrc":
        b0 = cylinder_b0(cyl, cfg.hydraulics, order=ctl.ladrc.order)
        wc, wo = position_bandwidths(cfg, cyl)
        return LADRC.from_config(ctl.ladrc, b0, period_s, wc=wc, wo=wo)
    return PID.from_config(ctl.pid, period_s, rate_limit=ctl.ladrc.rate_limit_per_s)


class ConstantSpeedPath:
    """Some cylinders of one layer moved by one distance at a constant speed, every other
    cylinder keeping its start displacement: the trajectory interface (``duration_s``,
    ``sample``, ``positions``) of a jog (one cylinder) and of the part's release (the
    upper layer's four). Displacements from mid-stroke [m], four per layer; ``cylinders``:
    positions 0..3 in ``layer``."""

    def __init__(
        self,
        start_lower: Sequence[float],
        start_upper: Sequence[float],
        layer: str,
        cylinders: Sequence[int],
        distance_m: float,
        speed_m_s: float,
    ) -> None:
        self._start = {"lower": list(start_lower), "upper": list(start_upper)}
        self._layer, self._moving = layer, tuple(cylinders)
        self._distance_m = distance_m
        self._v = speed_m_s if distance_m >= 0 else -speed_m_s
        self.duration_s = abs(distance_m) / speed_m_s

    def positions(self, t: float) -> tuple[list[float], list[float]]:
        lo, up = list(self._start["lower"]), list(self._start["upper"])
        d = lo if self._layer == "lower" else up
        tt = min(max(t, 0.0), self.duration_s)
        step = self._distance_m if tt >= self.duration_s else self._v * tt
        for k in self._moving:
            d[k] += step
        return lo, up

    def sample(self, t: float) -> tuple[list[float], list[float], list[float], list[float]]:
        lo, up = self.positions(t)
        vl, vu = [0.0] * 4, [0.0] * 4
        if 0.0 <= t < self.duration_s:
            v = vl if self._layer == "lower" else vu
            for k in self._moving:
                v[k] = self._v
        return lo, up, vl, vu


@dataclass(frozen=True)
class LayerMetrics:
    """What the operator sees of one layer in one cycle (m)."""

    sync_error_m: float  # largest |synchronization error| in the group
    twist_m: float  # |twist| of the measured extensions
    tracking_error_m: float  # largest |reference - measurement|


class AttitudeController:
    """Follows a trajectory (or holds) with the lower and upper synchronization groups."""

    def __init__(self, cfg: ProjectConfig, period_s: float) -> None:
        self.cfg = cfg
        n = len(cfg.cylinders)
        self.n = n
        self.layers: dict[str, list[int]] = {}
        self.half_stroke = np.zeros(n)
        for c in cfg.cylinders:
            self.half_stroke[c.can_index] = c.stroke_m / 2
        self.groups: dict[str, SyncGroup] = {}
        ctl = cfg.control
        for name in ("lower", "upper"):
            ids = getattr(cfg.layers, name).cylinders
            idx = [cfg.cylinder(i).can_index for i in ids]
            self.layers[name] = idx
            members: list[Controller] = []
            for cid in ids:
                members.append(cylinder_controller(cfg, cfg.cylinder(cid), period_s))
            self.groups[name] = SyncGroup(members, ctl.sync.scheme, ctl.sync.coupling_lambda)
        if any(len(idx) != 4 for idx in self.layers.values()):
            raise ValueError("each layer needs exactly 4 attitude cylinders")
        self._half_lists = {k: self.half_stroke[idx].tolist() for k, idx in self.layers.items()}
        #: hand the trajectory's rod speeds to the controllers as feed-forward
        self.feedforward = ctl.controller == "ladrc" and ctl.ladrc.reference_feedforward
        self.trajectory: Trajectory | None = None
        self.t_start = 0.0
        self.hold_ref = np.zeros(n)
        self.metrics: dict[str, LayerMetrics] = {
            k: LayerMetrics(0.0, 0.0, 0.0) for k in ("lower", "upper")
        }
        #: The references of the last :meth:`update` (all 19 cylinders), or None.
        self.last_references: FloatArray | None = None

    def set_offset(self, layer: str, offset_m: float) -> None:
        """Shift a layer's references by ``offset_m`` on every cylinder:
        ``x_ref = stroke / 2 + offset + d(t)`` (a placement's height on the lower layer;
        0 by default). Set it before :meth:`engage` with a trajectory planned from the
        measured start less the offset, so that the move starts where the rods are."""
        idx = self.layers[layer]
        self._half_lists[layer] = (self.half_stroke[idx] + offset_m).tolist()

    # ------------------------------------------------------------------ engage

    def engage(self, x_rod_m: FloatArray, t_now: float, trajectory: Trajectory | None) -> None:
        """Start following ``trajectory`` from now (``None``: hold the present positions).

        Bumpless: every controller is reset at its measurement with a zero command.
        """
        self.trajectory = trajectory
        self.t_start = t_now
        self.hold_ref = np.array(x_rod_m, dtype=float)
        for name, idx in self.layers.items():
            self.groups[name].reset(self.hold_ref[idx])

    def move_layer(self, t_now: float, layer: str, distance_m: float, speed_m_s: float) -> None:
        """From the present references, move every cylinder of ``layer`` by
        ``distance_m`` at ``speed_m_s`` (the other layer held where it is referenced), the
        controllers going on as they are: no reset, the motion starts where the
        references stand (the part's release from the placed pose's hold)."""
        ref = self.references(t_now)
        start = {
            name: [float(ref[i]) - h for i, h in zip(idx, self._half_lists[name], strict=True)]
            for name, idx in self.layers.items()
        }
        self.trajectory = ConstantSpeedPath(  # type: ignore[assignment]
            start["lower"], start["upper"], layer, range(4), distance_m, speed_m_s
        )
        self.t_start = t_now

    def hold(self, x_ref_rod_m: FloatArray) -> None:
        """Keep regulating at fixed references (after a motion: its end point)."""
        self.trajectory = None
        self.hold_ref = np.array(x_ref_rod_m, dtype=float)

    def resume(self, x_rod_m: FloatArray, shift_s: float) -> None:
        """Go on after a suspension or a hold: the trajectory shifted ``shift_s`` later in
        time (it continues from the reference where it stopped) and every controller reset
        at its measurement holding its :attr:`holding_command` from before the stop (the
        observer's disturbance estimate kept, the motion's share of the command left out:
        a layer holding its load against leakage needs the valves open, and would sink
        while the observer learned that again from zero)."""
        self.t_start += shift_s
        x = np.asarray(x_rod_m, dtype=float)
        for name, idx in self.layers.items():
            g = self.groups[name]
            g.reset(x[idx], [c.holding_command for c in g.controllers])

    def motion_done(self, t_now: float) -> bool:
        return self.trajectory is None or t_now - self.t_start >= self.trajectory.duration_s

    def references(self, t_now: float) -> FloatArray:
        """Rod-position references (m from the retracted end) of all 19 cylinders."""
        return self._sample(t_now, False)[0]

    def _sample(
        self, t_now: float, with_rates: bool
    ) -> tuple[FloatArray, dict[str, list[float]], dict[str, list[float]] | None]:
        """This cycle's references: all 19 (array), each layer's four (plain floats), and
        each layer's rod speeds (``with_rates`` and following a trajectory, else None).

        ``x_ref = stroke / 2 + d(t)``, element by element as numpy would add them.
        """
        traj = self.trajectory
        held = self.hold_ref.tolist()
        if traj is None:
            return (
                self.hold_ref.copy(),
                {k: [held[i] for i in idx] for k, idx in self.layers.items()},
                None,
            )
        t = t_now - self.t_start
        rates: dict[str, list[float]] | None = None
        if with_rates:
            d_lower, d_upper, v_lower, v_upper = traj.sample(t)
            rates = {"lower": v_lower, "upper": v_upper}
        else:
            d_lower, d_upper = traj.positions(t)
        per_layer: dict[str, list[float]] = {}
        for name, d in (("lower", d_lower), ("upper", d_upper)):
            h = self._half_lists[name]
            r = [h[0] + d[0], h[1] + d[1], h[2] + d[2], h[3] + d[3]]
            for i, v in zip(self.layers[name], r):  # noqa: B905 - four each
                held[i] = v
            per_layer[name] = r
        return np.array(held), per_layer, rates

    def final_references(self) -> FloatArray:
        """End point of the present trajectory (or the hold references)."""
        if self.trajectory is None:
            return self.hold_ref.copy()
        return self.references(self.t_start + self.trajectory.duration_s)

    # ------------------------------------------------------------------ update

    def update(self, t_now: float, x_rod_m: FloatArray) -> FloatArray:
        """Valve commands (19 values in [-1, 1]) for this cycle."""
        ref, layer_refs, layer_rates = self._sample(t_now, self.feedforward)
        self.last_references = ref
        xs = x_rod_m.tolist()
        u = [0.0] * self.n
        # Four values per layer: plain floats (numpy's per-call overhead dominates here).
        for name, idx in self.layers.items():
            group = self.groups[name]
            y = [xs[i] for i in idx]
            r = layer_refs[name]
            cmds = group.commands(r, y, None if layer_rates is None else layer_rates[name])
            for i, c in zip(idx, cmds):  # noqa: B905 - four each
                u[i] = c
            h = self._half_lists[name]
            self.metrics[name] = LayerMetrics(
                sync_error_m=max(map(abs, group.last_sync_error)),
                twist_m=abs(layer_twist(y[0] - h[0], y[1] - h[1], y[2] - h[2], y[3] - h[3])),
                tracking_error_m=max(
                    abs(r[0] - y[0]), abs(r[1] - y[1]), abs(r[2] - y[2]), abs(r[3] - y[3])
                ),
            )
        return np.array(u)
