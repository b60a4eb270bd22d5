"""What the service shows of itself: each cycle's figures, published by the loop as one
reference replaced whole (:meth:`StatusBoard.publish`, with the run record's row), and
the status built from them on request in the caller's thread
(:meth:`StatusBoard.snapshot`), so the loop does not pay for the status dict or the
achieved attitude.
"""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from config import units
from config.schema import ProjectConfig
from ipc_app.control.attitude import AttitudeController
from ipc_app.model.composition import check_attitude
from ipc_app.model.kinematics import fit_layer
from ipc_app.service.loop import ChangeGate
from ipc_app.service.machine_io import MachineInputs
from ipc_app.service.modes import PACKML_STATES, Mode, ModeMachine
from ipc_app.service.motion import Motion, MotionStats
from ipc_app.service.record import RunRecorder
from plc_bridge.link import IpcLink, LinkState

#: Numeric mode in the run record (``mode_code`` column): the PackML state number.
MODE_CODES = {m: PACKML_STATES[str(m)] for m in Mode}


class Published(NamedTuple):
    """One cycle's figures for :meth:`StatusBoard.snapshot`."""

    modes: dict[str, Any]
    now: float
    x: np.ndarray
    link: LinkState
    metrics: dict[str, Any]
    motion: MotionStats
    loop: dict[str, Any]
    ride: tuple[int, int]


def record_columns(cfg: ProjectConfig) -> list[str]:
    """Columns of the per-cycle run record (after ``t_s``)."""
    ids = list(cfg.layers.lower.cylinders) + list(cfg.layers.upper.cylinders)
    return (
        ["mode_code", "valves_enabled"]
        + [f"x_{c}_mm" for c in ids]
        + [f"ref_{c}_mm" for c in ids]
        + [f"u_{c}" for c in ids]
        + ["twist_lower_mm", "twist_upper_mm", "sync_lower_mm", "sync_upper_mm"]
    )


class StatusBoard:
    """The last cycle's figures of one service and its status built from them."""

    def __init__(
        self, cfg: ProjectConfig, attitude: AttitudeController, record: RunRecorder | None
    ) -> None:
        self.cfg = cfg
        self.attitude = attitude
        self.record = record
        self.active = attitude.layers["lower"] + attitude.layers["upper"]
        self.active_ids = [(i, cfg.cylinders_by_can_index[i].id) for i in self.active]
        self.half = np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])
        self.published: Published | None = None
        #: the mode's changes, for a status that waits for the next one (ChangeGate)
        self.state_changes = ChangeGate()
        self._seen_mode: Mode | None = None

    def publish(
        self,
        modes: ModeMachine,
        now: float,
        x: np.ndarray,
        u: np.ndarray,
        lstate: LinkState,
        ref_now: np.ndarray | None,
        stats: MotionStats,
        loop: dict[str, Any],
        ride: tuple[int, int],
    ) -> None:
        """The cycle's figures (copies of what the loop goes on mutating) and its row of
        the run record."""
        enabled = modes.valves_enabled
        if modes.mode is not self._seen_mode:
            self._seen_mode = modes.mode
            self.state_changes.changed()
        self.published = Published(
            modes=modes.snapshot(),
            now=now,
            x=x,
            link=lstate,
            metrics=dict(self.attitude.metrics),
            motion=MotionStats(**vars(stats)),  # a copy (copy.copy: 4x the time)
            loop=loop,
            ride=ride,
        )
        if self.record is None:
            return
        # The row on plain floats (the values numpy's indexing gave, without an array
        # per column group).
        active = self.active
        xs = x.tolist()
        if not enabled:
            refs = xs
        elif ref_now is not None:
            refs = ref_now.tolist()
        else:
            refs = self.attitude.references(now).tolist()
        us = u.tolist()
        to_mm = units.to_mm
        met = self.attitude.metrics
        self.record.sample(
            now,
            [
                float(MODE_CODES[modes.mode]),
                float(enabled),
                *[to_mm(xs[i]) for i in active],
                *[to_mm(refs[i]) for i in active],
                *[us[i] for i in active],
                to_mm(met["lower"].twist_m),
                to_mm(met["upper"].twist_m),
                to_mm(met["lower"].sync_error_m),
                to_mm(met["upper"].sync_error_m),
            ],
        )

    def snapshot(
        self,
        link: IpcLink,
        inp: MachineInputs | None,
        motion: Motion | None,
        cycle: dict[str, Any] | None,
    ) -> dict[str, Any]:
        """The status: the last published cycle, the readings ``inp`` (the same or the
        next cycle's), the active motion's part and the ring cycle's."""
        pub = self.published
        if pub is None:
            return {"mode": str(Mode.STOPPED)}
        snap = dict(pub.modes)
        x = pub.x
        snap.update(
            time_s=pub.now,
            link=str(pub.link.name),
            positions_mm={
                cid: (units.to_mm(float(x[i])) if np.isfinite(x[i]) else None)
                for i, cid in self.active_ids
            },
            sync_error_mm={k: units.to_mm(m.sync_error_m) for k, m in pub.metrics.items()},
            twist_mm={k: units.to_mm(m.twist_m) for k, m in pub.metrics.items()},
            motion=self.motion_dict(pub.motion, x),
            link_health={"state": pub.link.name},
            # read from the link's counters here, in the caller's thread, not per cycle
            link_rx=link.rx_counters(),
            loop=pub.loop,
            ride_through={"suspends": pub.ride[0], "resumes": pub.ride[1]},
        )
        if inp is not None:
            p, ok = inp.pressures.value, inp.positions.valid
            snap["pressures_pa"] = {
                cid: [float(v) if math.isfinite(v) else None for v in p[i].tolist()]
                for i, cid in self.active_ids
            }
            snap["positions_valid"] = {cid: bool(ok[i]) for i, cid in self.active_ids}
        part = motion.status() if motion is not None else None
        if part is not None:
            snap[motion.name] = part  # type: ignore[union-attr]
        if cycle is not None:
            snap["cycle"] = cycle
        return snap

    def achieved_attitude_deg(self, x: np.ndarray) -> tuple[float, float]:
        """Workpiece (roll, pitch) from measured rod positions (sensor view)."""
        lo, up = self.attitude.layers["lower"], self.attitude.layers["upper"]
        half = self.half
        ll, ul = self.cfg.layers.lower, self.cfg.layers.upper
        fl = fit_layer(x[lo] - half[lo], ll.a_m, ll.b_m)
        fu = fit_layer(x[up] - half[up], ul.a_m, ul.b_m)
        chk = check_attitude(
            (self.cfg.base.roll_rad, self.cfg.base.pitch_rad),
            (float(fl.roll), float(fl.pitch)),
            (float(fu.roll), float(fu.pitch)),
            (0.0, 0.0),
        )
        return units.to_deg(chk.roll), units.to_deg(chk.pitch)

    def motion_dict(self, m: MotionStats, x: np.ndarray) -> dict[str, Any]:
        out: dict[str, Any] = {
            "target_deg": list(m.target_deg),
            "duration_s": m.duration_s,
            "max_twist_mm": units.to_mm(m.max_twist_m),
            "max_sync_error_mm": units.to_mm(m.max_sync_error_m),
            "hold_sync_error_mm": units.to_mm(m.hold_sync_error_m),
            "hold_samples": m.hold_samples,
        }
        if np.all(np.isfinite(x[self.active])):
            roll, pitch = self.achieved_attitude_deg(x)
            out["achieved_deg"] = [roll, pitch]
        return out
