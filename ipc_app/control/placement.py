"""The placement move's sequencer (placement.md section 2; docs/placement.md).

Two phases, each checked before it starts:

1. ``attitude``: the attitude layers follow the planned trajectory to the target's roll
   and pitch in the world, the lower layer's references shifted by the target's height
   (:meth:`AttitudeController.set_offset`: the four legs heave together while the layers
   turn); then :data:`SETTLE_S` [0] of settling;
2. ``slide``: the rotation pair, the lateral pair and the central axis on one time
   scaling to their planned extensions (:class:`SlideController`), while the attitude
   layers hold their end point. The lateral pair's and the central axis' extensions are
   corrected for the lever arm of the layers' end attitudes (:func:`lever_corrected`):
   the lower layer turns the upper one about its own origin,
   ``layers.upper.origin_in_lower_m`` (0.9 m) below the part's reference point, which a
   split of the roll or pitch between the layers would otherwise carry sideways (0.5 mm
   for 0.035 deg on each layer in opposite senses); then :data:`SETTLE_S` [1] of
   settling, and further until every slide axis has stayed within
   :data:`SETTLED_BAND_M` of its goal for :data:`SETTLED_FOR_S` (a suspension late in
   the motion, whose resume restarts the controllers at the measurement, gets the time
   to bring the part back), at most :data:`SETTLE_MAX_S` in all.

After the second phase the sequencer is ``done`` and holds both sets where they ended.
The caller (the service's step, or the lockstep move of ``wara place run``) reads the
rods, calls :meth:`PlacementSequencer.update`, writes the commands, and switches the
link's active group when :attr:`PlacementSequencer.phase` changes
(:meth:`PlacementSequencer.active_group`): the attitude cylinders at the loop rate in
the first phase, the slide axes in the second (the attitude layers then hold on their
slower frames: both at the loop rate would load the bus over ``can.max_bus_load_percent``).

Work per cycle is bounded: one trajectory sample, one time-scaling sample, thirteen
controller updates.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from config.schema import ProjectConfig
from ipc_app.control.attitude import AttitudeController
from ipc_app.control.slide import SlideController
from ipc_app.model.kinematics import attitude_matrix
from ipc_app.planner.trajectory import Trajectory

FloatArray = NDArray[np.float64]

#: The phases, in order.
PHASES: tuple[str, ...] = ("attitude", "slide")
#: Settling after each phase before the next starts (s).
SETTLE_S: tuple[float, float] = (1.0, 2.0)
#: The slide phase ends once every slide axis has stayed this close to its goal (m) ...
SETTLED_BAND_M = 0.02e-3
#: ... for this long (s) ...
SETTLED_FOR_S = 0.25
#: ... or, settled or not, this long after its motion ended (s).
SETTLE_MAX_S = 10.0


def lever_corrected(
    cfg: ProjectConfig, trajectory: Trajectory, extensions_m: dict[str, tuple[float, ...]]
) -> dict[str, tuple[float, ...]]:
    """The slide extensions that put the part's reference point where ``extensions_m``
    would with level layers, at the trajectory's end attitudes.

    The reference point sits at ``t = R_L (o + R_U s) - o`` from its home position
    (besides the lower layer's heave): ``R_L``, ``R_U`` the layers' end attitudes
    (``Ry(pitch) Rx(roll)``, model.md), ``o = layers.upper.origin_in_lower_m`` and ``s``
    the slide's ``(x, y, 0)``: the central axis' extension and the lateral pair's mean.
    The planned extensions take ``t = s``; this solves ``t_xy = s_planned`` for ``s`` and
    moves both lateral cylinders and the central axis by the difference. The rotation
    pair is left as planned (the layers' attitudes do not turn the part about z)."""
    if not ("lateral" in extensions_m and "central_axis" in extensions_m):
        return extensions_m
    r_l = attitude_matrix(trajectory.lower.roll1, trajectory.lower.pitch1)
    r_u = attitude_matrix(trajectory.upper.roll1, trajectory.upper.pitch1)
    o = np.asarray(cfg.layers.upper.origin_in_lower_m, dtype=float)
    lat = extensions_m["lateral"]
    (cx,) = extensions_m["central_axis"]
    want = np.array([cx, float(np.mean(lat))])
    lever = (r_l @ o - o)[:2]
    m = (r_l @ r_u)[:2, :2]
    s = np.linalg.solve(m, want - lever)
    dx, dy = float(s[0] - want[0]), float(s[1] - want[1])
    out = dict(extensions_m)
    out["lateral"] = tuple(e + dy for e in lat)
    out["central_axis"] = (cx + dx,)
    return out


class PlacementSequencer:
    """Runs one placement move: attitude and height, then yaw, lateral and gap."""

    def __init__(
        self,
        cfg: ProjectConfig,
        period_s: float,
        attitude: AttitudeController,
        trajectory: Trajectory,
        heave_m: float,
        extensions_m: dict[str, tuple[float, ...]],
    ) -> None:
        self.attitude = attitude
        self.slide = SlideController(cfg, period_s)
        extensions_m = lever_corrected(cfg, trajectory, extensions_m)
        why = self.slide.check(extensions_m)
        if why:
            raise ValueError("; ".join(why))
        self.trajectory = trajectory
        self.heave_m = heave_m
        self.extensions_m = extensions_m
        self.phase = 0
        self.done = False
        self.phase_started_s = 0.0
        #: machine time of each finished phase (s), by name
        self.phase_times_s: dict[str, float] = {}
        self.max_sync_error_m = 0.0
        self.last_refs: FloatArray | None = None
        #: since when every slide axis is within :data:`SETTLED_BAND_M` (None: it is not)
        self._settled_since: float | None = None
        #: whether the slide phase ended settled (None: not ended yet)
        self.settled: bool | None = None

    @property
    def phase_name(self) -> str:
        return "done" if self.done else PHASES[self.phase]

    def active_group(self) -> list[int]:
        """The cylinders whose frames run at the loop rate in the present phase."""
        att = self.attitude.layers["lower"] + self.attitude.layers["upper"]
        return att if self.phase == 0 else list(self.slide.active)

    def watched(self) -> list[int]:
        """The cylinders whose positions must be fresh (every one the phase regulates)."""
        att = self.attitude.layers["lower"] + self.attitude.layers["upper"]
        return att if self.phase == 0 else att + list(self.slide.active)

    def start(self, t_now: float, x_rod_m: FloatArray) -> None:
        """Engage the attitude phase at the measured rods."""
        self.attitude.set_offset("lower", self.heave_m)
        self.attitude.engage(x_rod_m, t_now, self.trajectory)
        self.phase = 0
        self.phase_started_s = t_now

    def resume(self, x_rod_m: FloatArray, shift_s: float) -> None:
        """After a hold or suspension: the slide's clock shifted by the time stopped and
        its controllers reset at the measurement (the attitude layers are resumed by
        their owner, :meth:`AttitudeController.resume`)."""
        self.phase_started_s += shift_s
        if self.phase == 1:
            self.slide.t_start += shift_s
            self.slide.reset(np.asarray(x_rod_m, dtype=float))
            self._settled_since = None

    def finish(self) -> None:
        """The lower layer's offset back to none (a later adjustment plans from the rods)."""
        self.attitude.set_offset("lower", 0.0)

    def update(self, t_now: float, x_rod_m: FloatArray) -> FloatArray:
        """Valve commands (19 values in [-1, 1]) for this cycle; advances the phase."""
        att = self.attitude
        x = np.asarray(x_rod_m, dtype=float)
        u = att.update(t_now, x)
        refs = att.last_references
        if self.phase == 1:
            u = u + self.slide.update(t_now, x)
            self.max_sync_error_m = max(self.max_sync_error_m, self.slide.sync_error_m)
            if refs is not None:
                ref_s, _ = self.slide.references(t_now)
                refs = refs.copy()
                refs[self.slide.active] = ref_s[self.slide.active]
        for m in att.metrics.values():
            self.max_sync_error_m = max(self.max_sync_error_m, m.sync_error_m)
        self.last_refs = refs
        if self.done:
            return u
        if self.phase == 0:
            if t_now - att.t_start >= self.trajectory.duration_s + SETTLE_S[0]:
                att.hold(att.final_references())
                self.phase_times_s[PHASES[0]] = t_now - self.phase_started_s
                self.slide.engage(x, t_now, self.extensions_m)
                self.phase = 1
                self.phase_started_s = t_now
        else:
            after = t_now - self.slide.t_start - self.slide.duration_s
            off = self.slide.goal_error_m(x)
            if off > SETTLED_BAND_M or after < 0.0:
                self._settled_since = None
            elif self._settled_since is None:
                self._settled_since = t_now
            settled = self._settled_since is not None and t_now - self._settled_since >= (
                SETTLED_FOR_S
            )
            if after >= SETTLE_S[1] and (settled or after >= SETTLE_MAX_S):
                self.phase_times_s[PHASES[1]] = t_now - self.phase_started_s
                self.settled = settled
                self.done = True
        return u
