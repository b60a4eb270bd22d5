"""Bandwidths and speeds from the plant (docs/control.md, "Tuning from the plant").

Offline and pure: from a project it derives, for each cylinder group, the position
loop's LADRC bandwidths (``control.ladrc``), for the legs the walk's force loops'
(``walking.force_wc_rad_s`` / ``force_wo_rad_s``) and the touch-down speed
(``walking.touchdown_speed_mm_s``). A key given in the YAML overrides the derived
value (for every group); left out, the value is derived.

**The plant of a loop** (:class:`LoopPlant`): the valve (``hydraulics.valve_*``: a
second-order lag), the cylinder's rate gain ``b0`` (:func:`cylinder_b0`; a force loop's
``b0`` times the leg's stiffness against the invert), the oil column's mode under the
load the group carries (:func:`group_loads`: the statics' heaviest share of a group's
cylinder; its stiffness the lowest over the stroke, :func:`config.derived.hydraulic_stiffness_n_m`;
its damping the plant's viscous damping at that load), the loop period and the age of
the measurement at the loop's read: one period for a frame at the loop rate (the rods),
plus half the frame cycle beyond it for a slower frame held between samples (the
pressures, ``PLC_Pressure_*`` of the DBC). With the discrete LADRC (zoh, the current
observer) and, in a synchronized group, its relative modes (the dual error's
``1 + lambda`` on the proportional gain), that is a linear loop model whose delay margin
:func:`delay_margin_s` computes.

**The rule** (:func:`derive`), for each loop: the observer's bandwidth ``wo`` is the
largest (on a :data:`GRID_RAD_S` grid, from :data:`MIN_WO_RAD_S`) that keeps

1. the modelled delay margin at least :data:`MARGIN_FACTOR` times the project's
   ``control.delay_margin_ms`` (nominally stable first);
2. the loop's gain at the oil column's mode at most :data:`MODE_GAIN`, where the
   measurement's age and the required delay turn the mode's phase by half a radian or more
   (:data:`MODE_REACH_RAD`; at 50 rad/s, 20 ms is 1 rad): a resonance the delay can
   turn to any phase is stabilized by gain;
3. ``wo`` at most :data:`VALVE_FRACTION` of the valve's bandwidth;

and the controller's ``wc`` is :data:`WC_RATIO` of it. The touch-down speed
(:func:`touchdown_speed_m_s`): what a foot's force adds to its touch rise
(``walking.touch_mpa`` over the cap) while the loop cannot yet see it, the leg's
stiffness on the invert times the speed times :data:`TOUCH_CYCLES` pressure cycles,
stays within :data:`TOUCH_HEADROOM` of the overload limit's headroom on the smallest
share (the machine unloaded).

:func:`delay_margin_problem` is the project's check: a loop whose tuning (explicit or
derived) breaks the rule's margins (1 and 2) for ``control.delay_margin_ms``, named with
its keys.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Iterable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from config import units
from config.derived import (
    hydraulic_stiffness_n_m,
    travel_reach_m,
    viscous_damping_n_s_m,
    without_rods,
)
from config.schema import Body, Cylinder, ProjectConfig
from ipc_app.control.ladrc import eso_matrices
from ipc_app.control.plant_gain import cylinder_b0

FloatArray = NDArray[np.float64]
ComplexArray = NDArray[np.complex128]

#: rule 1: the modelled delay margin at least this times ``control.delay_margin_ms``.
#: The model is linear; the friction at the rods makes the hold hunt at rest, and that
#: hunting passes the standstill goal (0.07 mm) at 0.6-0.75 of the modelled margin
#: (docs/decisions/0023-tuning-from-the-plant.md, the lockstep measurements).
MARGIN_FACTOR = 2.0
#: rule 2: the loop's gain at the oil column's mode at most this (14 dB below 1)
MODE_GAIN = 0.2
#: rule 2 applies to a mode whose phase the age and the required delay turn by this much
#: or more (below it the delay margin of rule 1 covers the mode)
MODE_REACH_RAD = 0.5
#: rule 3: the observer at most this share of the valve's bandwidth
VALVE_FRACTION = 0.1
#: the controller's bandwidth over the observer's: with the dual error's
#: ``lambda = 1`` the coupled loop's crossover is then near ``wo``
WC_RATIO = 0.5
#: derived bandwidths are multiples of this (rounded down)
GRID_RAD_S = 0.5
#: no loop is tuned slower than this (a derived value below it is refused)
MIN_WO_RAD_S = 2.0
#: the touch-down: the share of the overload limit's headroom above the touch force that
#: a foot's force may use before its force loop holds it (the rest: the standing frame's
#: twist, the rods' friction)
TOUCH_HEADROOM = 0.75
#: the time a foot presses on unseen, in pressure frame cycles (plus two loop periods):
#: the touch rise is judged on the 50 ms samples against a held free-rod baseline;
#: measured 0.16 s on the HFDU example at 4.5 mm/s (19 kN above its touch force)
TOUCH_CYCLES = 3
#: derived touch-down speeds are multiples of this, m/s (rounded down)
TOUCH_GRID_M_S = 0.1e-3
#: the CAN messages whose age the loops see
POSITION_FRAME = "PLC_RodPos_0"
PRESSURE_FRAME = "PLC_Pressure_0"


@dataclass(frozen=True)
class LoopPlant:
    """What one loop's model needs (SI units; the measured quantity ``y``)."""

    #: ``dy/dt`` per unit valve command (m/s, or N/s for a force)
    b0: float
    #: the oil column's mode under the load, rad/s (``inf``: none in this loop)
    mode_rad_s: float
    mode_damping: float
    valve_rad_s: float
    valve_damping: float
    period_s: float
    #: the measurement's age at the loop's read, s
    age_s: float
    #: the dual error's factor on the relative modes (``1 + lambda``; 1: alone)
    coupling: float = 1.0


@dataclass(frozen=True)
class GroupLoad:
    """The load of one cylinder group: the heaviest share of one of its cylinders."""

    group: str
    cylinder: Cylinder
    load_kg: float
    #: where the load comes from (the statics' case, or the plant's lumped mass)
    case: str
    stiffness_n_m: float
    mode_rad_s: float
    mode_damping: float
    #: the relative modes' load per cylinder, kg, where it is not the common one (the
    #: travel pair turning M, the heavier frame: :func:`turn_plant`)
    relative_kg: float | None = None


@dataclass(frozen=True)
class LoopTuning:
    """One loop's bandwidths, where they come from and what they leave."""

    group: str
    kind: str  # "position" or "force"
    wc_rad_s: float
    wo_rad_s: float
    #: "derived", or the YAML keys that set them
    source: str
    #: the rule that bounds the derived ``wo``: "delay", "mode", "valve" or "" (overridden)
    bound: str
    delay_margin_s: float
    mode_gain: float
    plant: LoopPlant


@dataclass(frozen=True)
class Tuning:
    """Every loop of a project (:func:`derive`)."""

    loops: tuple[LoopTuning, ...]
    loads: tuple[GroupLoad, ...]
    #: the walk's touch-down speed, m/s, and where it comes from (None: no walk)
    touchdown_speed_m_s: float | None
    touchdown_source: str
    required_s: float

    def loop(self, group: str, kind: str = "position") -> LoopTuning:
        for lt in self.loops:
            if lt.group == group and lt.kind == kind:
                return lt
        raise KeyError(f"no {kind} loop for group {group!r}")


# ----------------------------------------------------------------------- the model


def _plant_matrices(p: LoopPlant) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Continuous ``(A, B, C)``: valve ``[x_v, x_v']``, then the oil column's mode on the
    rate ``[r, r']`` (none: ``r = b0 x_v``), then ``y``."""
    wv, zv = p.valve_rad_s, p.valve_damping
    if math.isfinite(p.mode_rad_s):
        wh, zh = p.mode_rad_s, p.mode_damping
        a = np.zeros((5, 5))
        a[0, 1] = 1.0
        a[1, 0], a[1, 1] = -(wv**2), -2 * zv * wv
        a[2, 3] = 1.0
        a[3, 0], a[3, 2], a[3, 3] = wh**2 * p.b0, -(wh**2), -2 * zh * wh
        a[4, 2] = 1.0
        b = np.array([0.0, wv**2, 0.0, 0.0, 0.0])
        c = np.array([0.0, 0.0, 0.0, 0.0, 1.0])
        return a, b, c
    a = np.zeros((3, 3))
    a[0, 1] = 1.0
    a[1, 0], a[1, 1] = -(wv**2), -2 * zv * wv
    a[2, 0] = p.b0
    return a, np.array([0.0, wv**2, 0.0]), np.array([0.0, 0.0, 1.0])


@functools.lru_cache(maxsize=256)
def _discrete_plant(p: LoopPlant) -> tuple[FloatArray, FloatArray, FloatArray]:
    """The plant with the command held over a period (zero-order hold)."""
    import scipy.linalg  # here: the service's verbs import this module, not scipy

    a, b, c = _plant_matrices(p)
    n = len(b)
    big = np.zeros((n + 1, n + 1))
    big[:n, :n] = a * p.period_s
    big[:n, n] = b * p.period_s
    e = scipy.linalg.expm(big)
    return e[:n, :n], e[:n, n], c


def _controller(
    p: LoopPlant, wc: float, wo: float, coupling: float
) -> tuple[FloatArray, FloatArray, FloatArray, float]:
    """The first-order LADRC (zoh, current observer) from ``y`` to ``u`` (reference 0)
    as ``x+ = A x + B y``, ``u = C x + D y``; ``coupling`` multiplies the proportional
    path (the dual error's relative modes)."""
    phi, gam, g = eso_matrices(1, p.b0, wo, p.period_s, "zoh")
    m = np.eye(2) - np.outer(g, [1.0, 0.0])
    k = -np.array([wc, 1.0]) / p.b0
    c = k @ m
    d = float(k @ g) - wc * (coupling - 1.0) / p.b0
    a = phi @ m + np.outer(gam, c)
    b = phi @ g + gam * d
    return a, b, c, d


def _delay_steps(p: LoopPlant) -> int:
    return max(0, math.ceil(p.age_s / p.period_s - 1e-9))


def closed_loop_stable(p: LoopPlant, wc: float, wo: float, coupling: float = 1.0) -> bool:
    """The discrete closed loop's eigenvalues inside the unit circle (``age_s`` rounded
    up to whole periods)."""
    ap, bp, cp = _discrete_plant(p)
    ac, bc, cc, dc = _controller(p, wc, wo, coupling)
    nd = _delay_steps(p)
    n_p, n_c = len(bp), 2
    n = n_p + n_c + nd
    a = np.zeros((n, n))
    # the measurement the controller reads: the plant's output nd periods ago
    y_row = np.zeros(n)
    if nd == 0:
        y_row[:n_p] = cp
    else:
        y_row[n_p + n_c + nd - 1] = 1.0
    u_row = np.zeros(n)
    u_row[n_p : n_p + n_c] = cc
    u_row += dc * y_row
    a[:n_p, :n_p] = ap
    a[:n_p] += np.outer(bp, u_row)
    a[n_p : n_p + n_c, n_p : n_p + n_c] = ac
    a[n_p : n_p + n_c] += np.outer(bc, y_row)
    if nd:
        a[n_p + n_c, :n_p] = cp
        for i in range(1, nd):
            a[n_p + n_c + i, n_p + n_c + i - 1] = 1.0
    return bool(np.max(np.abs(np.linalg.eigvals(a))) < 1.0)


def _transfer(z: ComplexArray, a: FloatArray, b: FloatArray, c: FloatArray) -> ComplexArray:
    """``c (z I - a)^-1 b`` at every ``z``."""
    m = z[:, None, None] * np.eye(len(b)) - a
    rhs = np.broadcast_to(b[:, None], (len(z), len(b), 1)).astype(np.complex128)
    return np.asarray(np.linalg.solve(m, rhs)[:, :, 0] @ c, dtype=np.complex128)


@functools.lru_cache(maxsize=64)
def _plant_response(p: LoopPlant, w_bytes: bytes) -> ComplexArray:
    """The held plant's response on a frequency grid (kept: it does not depend on the
    controller's bandwidths)."""
    w = np.frombuffer(w_bytes, dtype=np.float64)
    return _transfer(np.exp(1j * w * p.period_s), *_discrete_plant(p))


def loop_response(
    p: LoopPlant, wc: float, wo: float, w: FloatArray, coupling: float = 1.0
) -> ComplexArray:
    """The loop's frequency response ``L`` at ``w`` (rad/s, below Nyquist): the
    controller, the held plant and the measurement's age (negative feedback: the loop
    is ``y -> -L y``)."""
    z = np.exp(1j * w * p.period_s)
    ac, bc, cc, dc = _controller(p, wc, wo, coupling)
    plant = _plant_response(p, w.tobytes()) if len(w) > 8 else _transfer(z, *_discrete_plant(p))
    ctrl = _transfer(z, ac, bc, cc) + dc
    # fractional age beyond the whole periods the stability check rounds to
    return np.asarray(-ctrl * plant * np.exp(-1j * w * p.age_s), dtype=np.complex128)


def _frequencies(p: LoopPlant) -> FloatArray:
    nyquist = math.pi / p.period_s
    return np.asarray(np.logspace(-1.0, math.log10(0.999 * nyquist), 1200), dtype=np.float64)


def delay_margin_s(p: LoopPlant, wc: float, wo: float) -> float:
    """The extra measurement delay the loop tolerates, s (0: unstable without it): the
    smallest over its modes (common; relative, with :attr:`LoopPlant.coupling`) and
    over the loop's gain crossovers of the phase margin there over the frequency."""
    w = _frequencies(p)
    best = math.inf
    for coupling in {1.0, p.coupling}:
        if not closed_loop_stable(p, wc, wo, coupling):
            return 0.0
        ell = loop_response(p, wc, wo, w, coupling)
        mag = np.abs(ell)
        cross = np.nonzero(np.diff(np.sign(mag - 1.0)))[0]
        for i in cross:
            phase = (float(np.angle(ell[i])) + math.pi) % (2 * math.pi)
            best = min(best, phase / float(w[i]))
    return best


def mode_gain(p: LoopPlant, wc: float, wo: float) -> float:
    """The loop's gain at the oil column's mode (the larger of its modes'; 0: no mode)."""
    if not math.isfinite(p.mode_rad_s) or p.mode_rad_s >= math.pi / p.period_s:
        return 0.0
    w = np.array([p.mode_rad_s])
    return max(float(np.abs(loop_response(p, wc, wo, w, c))[0]) for c in {1.0, p.coupling})


def mode_in_reach(p: LoopPlant, required_s: float) -> bool:
    """Rule 2 applies: the mode's phase can turn by half a radian or more with the
    measurement's age and the required delay (:data:`MODE_REACH_RAD`)."""
    return math.isfinite(p.mode_rad_s) and p.mode_rad_s * (p.age_s + required_s) >= MODE_REACH_RAD


# ----------------------------------------------------------------------- the plant


def _frame_cycle_s(cfg: ProjectConfig, frame: str) -> float:
    """The DBC's cycle of ``frame`` while its cylinders are in the active group, s."""
    from plc_bridge.catalog import load_catalog

    return load_catalog().by_name(frame).cycle_in_force_s(True, cfg.control.period_s)


def _measurement_age_s(cfg: ProjectConfig, frame: str) -> float:
    """One loop period, plus half of the frame's cycle (while its group is active)
    beyond it: a frame slower than the loop is held between samples."""
    period = cfg.control.period_s
    return period + max(0.0, _frame_cycle_s(cfg, frame) - period) / 2


def _lowest_stiffness_n_m(cfg: ProjectConfig, cyl: Cylinder) -> float:
    """The oil column's stiffness at its softest point of the stroke (less the ends'
    ``safety.stroke_end_margin_mm``)."""
    margin = min(units.mm(cfg.safety.stroke_end_margin_mm), cyl.stroke_m / 4)
    xs = np.linspace(margin, cyl.stroke_m - margin, 201)
    plant = cfg.plant_of(cyl)
    return min(hydraulic_stiffness_n_m(cyl, plant, cfg.hydraulics, float(x)) for x in xs)


def yaw_inertias_kg_m2(cfg: ProjectConfig) -> tuple[float, float]:
    """The frames' yaw inertias about S's pivot, the worst over S's travel, kg m^2: M
    (its bodies, the platforms and the part, its rods) and S. Each body a plate over its
    layer's or frame's support rectangle at its COG, each rod a point at its leg (the
    controller's model: the simulator has its own, ``hil_sim.walking``)."""
    from ipc_app.model.statics import MachineStatics

    lo, up, sub = cfg.layers.lower, cfg.layers.upper, cfg.walking_sections()[0].sub
    o = MachineStatics(cfg).origin_upper
    rod = cfg.hydraulics.rod_mass_kg

    def plate(
        bodies: Iterable[Body], a: float, b: float, dx: float, dy: float
    ) -> tuple[float, float, float]:
        m = i = mx = 0.0
        for body in bodies:
            x, y = body.cog_m[0] + dx, body.cog_m[1] + dy
            m += body.mass_kg
            mx += body.mass_kg * x
            i += body.mass_kg * ((a * a + b * b) / 3.0 + x * x + y * y)
        return m, mx, i

    def rods(a: float, b: float) -> tuple[float, float, float]:
        return 4 * rod, 0.0, 4 * rod * (a * a + b * b)

    parts = [
        plate(lo.bodies, lo.a_m, lo.b_m, 0.0, 0.0),
        plate(up.bodies, up.a_m, up.b_m, o[0], o[1]),
        plate(without_rods(cfg, "main"), lo.a_m, lo.b_m, 0.0, 0.0),
        rods(lo.a_m, lo.b_m),
    ]
    m_m = sum(p[0] for p in parts)
    mx_m = sum(p[1] for p in parts)
    i_m = sum(p[2] for p in parts)
    reach = travel_reach_m(cfg)
    # about the pivot at (x_S, 0): the parallel axis from M's centre
    i_m_pivot = max(i_m + m_m * x * x - 2.0 * x * mx_m for x in (-reach, reach))
    i_s = plate(without_rods(cfg, "sub"), sub.a_m, sub.b_m, 0.0, 0.0)[2] + rods(sub.a_m, sub.b_m)[2]
    return i_m_pivot, i_s


def _leg_statics_kg(cfg: ProjectConfig) -> dict[str, tuple[float, str]]:
    """The heaviest load (kg) on one cylinder of each group the statics know, and its case."""
    from ipc_app.model.statics import MachineStatics
    from ipc_app.model.support import WalkingMachine, support_forces

    out: dict[str, tuple[float, str]] = {}

    def put(group: str, force_n: float, case: str) -> None:
        kg = force_n / units.G
        if kg > out.get(group, (0.0, ""))[0]:
            out[group] = (kg, case)

    st = MachineStatics(cfg)
    f_lower, _f = st.forces(0.0, 0.0, 0.0, 0.0)
    f_upper = st.upper_cylinder_forces(0.0, 0.0, 0.0, 0.0)
    lower = cfg.cylinder(cfg.layers.lower.cylinders[0]).group
    upper = cfg.cylinder(cfg.layers.upper.cylinders[0]).group
    put(lower, float(np.max(f_lower)), "the lower platform, loaded")
    put(upper, float(np.max(f_upper)), "the upper platform, loaded")
    if not cfg.walks:
        return out
    wm = WalkingMachine(cfg)
    travel = [c for c in cfg.cylinders if c.role == "travel"]
    reach = travel_reach_m(cfg)
    subs = [c for c in cfg.cylinders if c.role == "sub_leg"]
    for x_s in (-reach, 0.0, reach):
        pts = wm.legs_xy(x_s)
        cog = wm.cog(x_s)
        f_m = support_forces(pts[:4], wm.mass_kg, cog, wm.g_base)
        f_s = support_forces(pts[4:], wm.mass_kg, cog, wm.g_base)
        put(lower, float(np.max(f_m)), "the main frame standing alone, loaded")
        if subs:
            put(subs[0].group, float(np.max(f_s)), "the sub frame standing alone, loaded")
    if travel:
        legs = 4 * cfg.hydraulics.rod_mass_kg
        frame_kg = max(wm.main.mass_kg + legs, wm.sub.mass_kg + legs) / len(travel)
        put(travel[0].group, frame_kg * units.G, "the frame the pair moves, loaded")
    return out


#: the frame the travel pair turns: M lifted (phase 6, S standing), S lifted (phase 1)
TURNED_FRAMES: tuple[str, ...] = ("main", "sub")


def _turned_kg(cfg: ProjectConfig, cyl: Cylinder, frame: str = "main") -> float | None:
    """The travel pair's relative mode: the rods against each other turn the lifted frame
    about the pivot (curves.md section 3), on each rod ``I / (2 b_T^2)`` (M with the part
    69 t on the shipped machine, against 31.7 t along the rails; S 4.8 t). None: a
    group whose relative modes move its common load."""
    if cyl.role != "travel" or not cfg.walks:
        return None
    b_t = cfg.walking_sections()[1].travel_half_span_m
    n = sum(1 for c in cfg.cylinders if c.role == "travel")
    return yaw_inertias_kg_m2(cfg)[TURNED_FRAMES.index(frame)] / (n * b_t * b_t)


def group_loads(cfg: ProjectConfig) -> tuple[GroupLoad, ...]:
    """Each cylinder group's load: the statics' heaviest share where the group carries a
    platform or a frame, else the plant's lumped ``moving_mass_kg``; the oil column's
    mode at its softest point under that load, damped by the plant's viscous damping."""
    statics = _leg_statics_kg(cfg)
    out: list[GroupLoad] = []
    seen: set[str] = set()
    for cyl in cfg.cylinders_by_can_index:
        if cyl.group in seen:
            continue
        seen.add(cyl.group)
        plant = cfg.plant_of(cyl)
        kg, case = statics.get(cyl.group, (plant.moving_mass_kg, "the plant's moving_mass_kg"))
        if not kg > 0.0:  # a group the statics load in tension only: its own lumped mass
            kg, case = plant.moving_mass_kg, "the plant's moving_mass_kg"
        k = _lowest_stiffness_n_m(cfg, cyl)
        damping = viscous_damping_n_s_m(cyl, plant, cfg.hydraulics)
        out.append(
            GroupLoad(
                cyl.group, cyl, kg, case, k, math.sqrt(k / kg), damping / (2 * math.sqrt(k * kg)),
                _turned_kg(cfg, cyl),
            )
        )  # fmt: skip
    return tuple(out)


def _valve(cfg: ProjectConfig) -> tuple[float, float]:
    h = cfg.hydraulics
    return 2 * math.pi * h.valve_natural_frequency_hz, h.valve_damping_ratio


def position_plant(cfg: ProjectConfig, load: GroupLoad) -> LoopPlant:
    """A group's position loop (the rods at the loop rate; synchronized if it has more
    than one cylinder). The travel pair's: its common mode (the pair moving the frame;
    the dual error does not act on it), its turn is :func:`turn_plant`'s."""
    n = sum(1 for c in cfg.cylinders if c.group == load.group)
    wv, zv = _valve(cfg)
    coupled = n > 1 and load.relative_kg is None
    return LoopPlant(
        b0=cylinder_b0(load.cylinder, cfg.hydraulics),
        mode_rad_s=load.mode_rad_s,
        mode_damping=load.mode_damping,
        valve_rad_s=wv,
        valve_damping=zv,
        period_s=cfg.control.period_s,
        age_s=_measurement_age_s(cfg, POSITION_FRAME),
        coupling=1.0 + cfg.control.sync.coupling_lambda if coupled else 1.0,
    )


def turn_plant(cfg: ProjectConfig, load: GroupLoad, frame: str = "main") -> LoopPlant:
    """The travel pair's turn of ``frame`` (the lifted one): the rods against each other
    turning it about the pivot (its relative mode, :func:`_turned_kg`), the dual error
    acting on it."""
    cyl = load.cylinder
    kg = _turned_kg(cfg, cyl, frame)
    assert kg is not None
    k = load.stiffness_n_m
    damping_n_s_m = viscous_damping_n_s_m(cyl, cfg.plant_of(cyl), cfg.hydraulics)
    return replace(
        position_plant(cfg, load),
        mode_rad_s=math.sqrt(k / kg),
        mode_damping=damping_n_s_m / (2.0 * math.sqrt(k * kg)),
        coupling=1.0 + cfg.control.sync.coupling_lambda,
    )


def leg_stiffness_n_m(cfg: ProjectConfig, cyl: Cylinder) -> float:
    """A leg's stiffness against the invert: its oil column at mid-stroke in series with
    the foot's contact (``walking.contact``), N/m (what the force loop's ``b0`` uses)."""
    if cfg.walking is None:
        raise ValueError("the project has no walking section")
    k_h = hydraulic_stiffness_n_m(cyl, cfg.plant_of(cyl), cfg.hydraulics)
    return 1.0 / (1.0 / k_h + 1.0 / cfg.walking.contact.stiffness_n_m)


def force_plant(cfg: ProjectConfig, cyl: Cylinder) -> LoopPlant:
    """A leg's force loop: ``b0`` times its stiffness on the invert, on the pressures
    (their frames' age); one leg alone, no oil-column mode of its own (the foot's is
    far above the loop)."""
    wv, zv = _valve(cfg)
    return LoopPlant(
        b0=cylinder_b0(cyl, cfg.hydraulics) * leg_stiffness_n_m(cfg, cyl),
        mode_rad_s=math.inf,
        mode_damping=1.0,
        valve_rad_s=wv,
        valve_damping=zv,
        period_s=cfg.control.period_s,
        age_s=_measurement_age_s(cfg, PRESSURE_FRAME),
    )


# ----------------------------------------------------------------------- the rule


def rule_broken(p: LoopPlant, wc: float, wo: float, required_s: float) -> str:
    """Which margin of the rule (module doc) the tuning breaks: ``"mode"`` (rule 2),
    ``"delay"`` (rule 1), or ``""`` (none)."""
    if mode_in_reach(p, required_s) and mode_gain(p, wc, wo) > MODE_GAIN:
        return "mode"
    if delay_margin_s(p, wc, wo) < MARGIN_FACTOR * required_s:
        return "delay"
    return ""


def fastest_observer(p: LoopPlant, required_s: float) -> tuple[float, str]:
    """The rule: the largest ``wo`` (grid :data:`GRID_RAD_S`) with ``wc = WC_RATIO wo``
    that keeps rules 1-3 (module doc), and the rule that stopped it. Below
    :data:`MIN_WO_RAD_S`: ``(0, rule)``."""

    def fails(wo: float) -> str:
        return rule_broken(p, WC_RATIO * wo, wo, required_s)

    hi = math.floor(VALVE_FRACTION * p.valve_rad_s / GRID_RAD_S)
    lo = math.ceil(MIN_WO_RAD_S / GRID_RAD_S)
    if hi < lo:
        return 0.0, "valve"
    if not fails(hi * GRID_RAD_S):
        return hi * GRID_RAD_S, "valve"
    bound = fails(lo * GRID_RAD_S)
    if bound:
        return 0.0, bound
    # bisection between a passing lo and a failing hi (the rules tighten with wo)
    while hi - lo > 1:
        mid = (lo + hi) // 2
        why = fails(mid * GRID_RAD_S)
        if why:
            hi, bound = mid, why
        else:
            lo = mid
    return lo * GRID_RAD_S, bound or fails(hi * GRID_RAD_S)


def touchdown_speed_m_s(cfg: ProjectConfig) -> float:
    """The walk's touch-down speed: the explicit ``walking.touchdown_speed_mm_s``, else
    derived (:func:`derived_touchdown_speed_m_s`)."""
    if cfg.walking is None:
        raise ValueError("the project has no walking section")
    if cfg.walking.touchdown_speed_mm_s is not None:
        return units.mm(cfg.walking.touchdown_speed_mm_s)
    return derived_touchdown_speed_m_s(cfg)


def smallest_share_n(cfg: ProjectConfig) -> float:
    """The smallest eight-leg share of any leg over the travel (the machine unloaded
    where it can walk so, else loaded), N: the floor the overload judges a touched leg
    against."""
    from ipc_app.model.support import WalkingMachine, support_forces

    if cfg.walking is None:
        raise ValueError("the project has no walking section")
    try:
        wm = WalkingMachine(cfg, unloaded=True)
    except ValueError:  # no workpiece body: it never walks unloaded
        wm = WalkingMachine(cfg)
    reach = travel_reach_m(cfg)
    return min(
        float(np.min(support_forces(wm.legs_xy(x), wm.mass_kg, wm.cog(x), wm.g_base)))
        for x in (-reach, 0.0, reach)
    )


def derived_touchdown_speed_m_s(cfg: ProjectConfig) -> float:
    """``TOUCH_HEADROOM * (overload * F_share - F_touch) / (k_leg * t_touch)``, the
    stiffest leg's, rounded down to :data:`TOUCH_GRID_M_S` (at least one step): a foot
    meeting the invert at that speed adds ``k_leg v t_touch`` to its touch force
    (``touch_mpa`` over the cap) before its force loop holds it, and the sum stays within
    that share of the overload limit's headroom above the touch force, on the smallest
    share the leg is judged against (:func:`smallest_share_n`). ``t_touch``:
    :data:`TOUCH_CYCLES` pressure frame cycles and two loop periods."""
    if cfg.walking is None:
        raise ValueError("the project has no walking section")
    t_touch = TOUCH_CYCLES * _frame_cycle_s(cfg, PRESSURE_FRAME) + 2 * cfg.control.period_s
    limit_n = cfg.walking.overload_percent / 100 * smallest_share_n(cfg)
    speeds = []
    for cyl in cfg.cylinders:
        if cyl.role not in ("main_leg", "sub_leg"):
            continue
        headroom_n = limit_n - units.mpa(cfg.walking.touch_mpa) * cyl.cap_area_m2
        speeds.append(TOUCH_HEADROOM * headroom_n / (leg_stiffness_n_m(cfg, cyl) * t_touch))
    v = round(math.floor(min(speeds) / TOUCH_GRID_M_S) * TOUCH_GRID_M_S, 9)
    return max(v, TOUCH_GRID_M_S)


def _tuned(
    group: str, kind: str, p: LoopPlant, required_s: float, keys: tuple[str, str],
    wc_set: float | None, wo_set: float | None,
) -> LoopTuning:  # fmt: skip
    bound = ""
    if wo_set is None:
        wo, bound = fastest_observer(p, required_s)
        if wo <= 0.0:
            wo = MIN_WO_RAD_S  # the check refuses it (its margin is short)
    else:
        wo = wo_set
    wc = WC_RATIO * wo if wc_set is None else wc_set
    given = [k for k, v in zip(keys, (wc_set, wo_set), strict=True) if v is not None]
    return LoopTuning(
        group, kind, wc, wo, " and ".join(given) if given else "derived", bound,
        delay_margin_s(p, wc, wo), mode_gain(p, wc, wo), p,
    )  # fmt: skip


@functools.lru_cache(maxsize=16)
def derive(cfg: ProjectConfig) -> Tuning:
    """Every loop of the project: the position loop of each group, the force loop of
    each leg group (a walking project), the touch-down speed."""
    required = units.ms(cfg.control.delay_margin_ms)
    lad = cfg.control.ladrc
    loads = group_loads(cfg)
    loops = [
        _tuned(
            ld.group,
            "position",
            position_plant(cfg, ld),
            required,
            ("control.ladrc.wc_rad_s", "control.ladrc.wo_rad_s"),
            lad.wc_rad_s,
            lad.wo_rad_s,
        )
        for ld in loads
    ]
    if cfg.walking is not None:
        w = cfg.walking
        loops += [
            _tuned(
                ld.group,
                f"turn_{frame}",
                turn_plant(cfg, ld, frame),
                required,
                ("walking.turn_wc_rad_s", "walking.turn_wo_rad_s"),
                w.turn_wc_rad_s,
                w.turn_wo_rad_s,
            )
            for ld in loads
            if ld.relative_kg is not None
            for frame in TURNED_FRAMES
        ]
    td: float | None = None
    td_source = ""
    if cfg.walking is not None:
        w = cfg.walking
        for ld in loads:
            if ld.cylinder.role in ("main_leg", "sub_leg"):
                loops.append(
                    _tuned(
                        ld.group,
                        "force",
                        force_plant(cfg, ld.cylinder),
                        required,
                        ("walking.force_wc_rad_s", "walking.force_wo_rad_s"),
                        w.force_wc_rad_s,
                        w.force_wo_rad_s,
                    )
                )
        td = touchdown_speed_m_s(cfg)
        td_source = "derived" if w.touchdown_speed_mm_s is None else "walking.touchdown_speed_mm_s"
    return Tuning(tuple(loops), loads, td, td_source, required)


def position_bandwidths(cfg: ProjectConfig, cyl: Cylinder) -> tuple[float, float]:
    """``(wc, wo)`` of the cylinder's position loop (its group's), rad/s."""
    lt = derive(cfg).loop(cyl.group, "position")
    return lt.wc_rad_s, lt.wo_rad_s


def turn_bandwidths(cfg: ProjectConfig, cyl: Cylinder, frame: str) -> tuple[float, float]:
    """``(wc, wo)`` of the travel pair's turn loop (its rods' difference) while it turns
    ``frame`` ("main" or "sub", :data:`TURNED_FRAMES`), rad/s."""
    lt = derive(cfg).loop(cyl.group, f"turn_{frame}")
    return lt.wc_rad_s, lt.wo_rad_s


def force_bandwidths(cfg: ProjectConfig, cyl: Cylinder) -> tuple[float, float]:
    """``(wc, wo)`` of a leg's force loop (its group's), rad/s."""
    lt = derive(cfg).loop(cyl.group, "force")
    return lt.wc_rad_s, lt.wo_rad_s


def delay_margin_problem(cfg: ProjectConfig) -> str | None:
    """The project's check: ``None``, or the first loop whose tuning breaks the rule's
    stated margin (the modelled delay margin at least twice ``control.delay_margin_ms``,
    the gain at an oil-column mode in reach at most :data:`MODE_GAIN`), in one line
    naming its keys and what the rule would derive."""
    tuning = derive(cfg)
    need_ms = cfg.control.delay_margin_ms
    for lt in tuning.loops:
        broken = rule_broken(lt.plant, lt.wc_rad_s, lt.wo_rad_s, tuning.required_s)
        if not broken:
            continue
        prefix = "walking.force_" if lt.kind == "force" else "control.ladrc."
        keys = f"{prefix}wc_rad_s {lt.wc_rad_s:g}, {prefix}wo_rad_s {lt.wo_rad_s:g}"
        if lt.source == "derived":
            keys += " (derived)"
        have_ms = units.to_ms(lt.delay_margin_s)
        if broken == "mode":
            what = (
                f"a gain of {lt.mode_gain:.2f} at its oil column's mode "
                f"({lt.plant.mode_rad_s:.0f} rad/s), above {MODE_GAIN:g}: with "
                f"control.delay_margin_ms {need_ms:g} ms of delay that mode's phase is "
                f"not known, its gain must keep it stable"
            )
        else:
            have = "no margin (unstable)" if have_ms <= 0 else f"{have_ms:.1f} ms of delay margin"
            what = (
                f"{have} in the loop model, less than {MARGIN_FACTOR:g} x "
                f"control.delay_margin_ms {need_ms:g} ms"
            )
        wo, _bound = fastest_observer(lt.plant, tuning.required_s)
        hint = (
            f"leave them out (derived for {lt.group}: wc {WC_RATIO * wo:g}, wo {wo:g}) or "
            f"lower them"
            if wo > 0
            else "the plant allows no tuning with that margin: lower the delay or the load"
        )
        return f"{keys}: the {lt.group} {lt.kind} loop has {what}; {hint}"
    return None


def derived_value(cfg: ProjectConfig, path: str) -> float:
    """The derived value of a tuning key left out of the YAML (``control.ladrc.wc_rad_s``
    and ``wo_rad_s``: the lower layer's group's; ``walking.force_*``: the main legs';
    ``walking.touchdown_speed_mm_s``), for a search that starts from it."""
    lower = cfg.cylinder(cfg.layers.lower.cylinders[0])
    t = derive(cfg)
    values = {
        "control.ladrc.wc_rad_s": lambda: t.loop(lower.group).wc_rad_s,
        "control.ladrc.wo_rad_s": lambda: t.loop(lower.group).wo_rad_s,
        "walking.force_wc_rad_s": lambda: t.loop(lower.group, "force").wc_rad_s,
        "walking.force_wo_rad_s": lambda: t.loop(lower.group, "force").wo_rad_s,
        "walking.touchdown_speed_mm_s": lambda: units.to_mm(touchdown_speed_m_s(cfg)),
    }
    if path not in values:
        raise KeyError(f"{path} is not a derived tuning key ({', '.join(values)})")
    return float(values[path]())
