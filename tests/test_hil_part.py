"""The simulator's arc part: bolted to its ring (its pose frozen, its weight on the
pads falling as the platform lowers), a new one set down by a crane; and the plant's
integration, stable at rest with the part on, bolted or gone (docs/hil.md, "The part",
"Integration")."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import pytest

from config import ProjectConfig, load_project, units
from hil_sim.placement import bolt_part, pose_from_home
from hil_sim.rig import Rig, rotation
from hil_sim.walking import _XW, WalkingRig

RIGS = (Rig, WalkingRig)


@pytest.fixture(scope="module")
def project() -> ProjectConfig:
    return load_project(None)


def rk4_amplification(rig: Rig) -> float:
    """The largest |R(h lambda)| of RK4 over the eigenvalues of the rig's linearization
    at its present state (finite differences of :meth:`Rig.derivative`): above 1, a mode
    the step cannot integrate."""
    y0 = rig.y.copy()
    f0 = rig.derivative(y0)
    jac = np.empty((y0.size, y0.size))
    for j in range(y0.size):
        e = max(1e-9, 1e-7 * abs(y0[j]))
        y = y0.copy()
        y[j] += e
        jac[:, j] = (rig.derivative(y) - f0) / e
    z = np.linalg.eigvals(jac) * rig.step_s
    return float(np.abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24).max())


def platform_height_m(rig: Rig) -> float:
    """The upper platform's origin (the part's pads' centre) above its home height, in
    the tunnel base frame: both layers' heave and attitude."""
    q = rig.q
    o = np.asarray(rig.cfg.layers.upper.origin_in_lower_m, dtype=float)
    return float(q[0] + (rotation(q[1], q[2]) @ (o + np.array([0.0, 0.0, q[3]])) - o)[2])


def _states(rig: Rig) -> Iterator[str]:
    """The rig with its part carried, bolted (on its pads), and gone from the platform."""
    yield "carried"
    bolt_part(rig.cfg, rig)
    yield "bolted"
    rig._pads[5, 4] = 0.0  # the platform lowered clear of it
    yield "clear"


@pytest.mark.parametrize("cls", RIGS)
def test_the_step_integrates_every_mode_at_rest(project: ProjectConfig, cls: type[Rig]) -> None:
    rig = cls(project)
    for state in _states(rig):
        assert rk4_amplification(rig) <= 1.0 + 1e-9, state


@pytest.mark.parametrize("cls", RIGS)
def test_without_the_friction_bound_the_friction_modes_diverge(
    project: ProjectConfig, cls: type[Rig]
) -> None:
    """The cause the bound removes: the smoothed Coulomb friction's slope at rest, 2 kN
    over 0.1 mm/s, on the platforms' inertia. Without the part (bolted, the platform
    clear of it) the fastest mode's step amplification is in the hundreds or more."""
    rig = cls(project)
    bolt_part(project, rig)
    rig._pads[5, 4] = 0.0
    rig._p[18] = rig._p_nominal[18]
    assert rk4_amplification(rig) > 100.0


def test_the_bound_slows_only_what_it_must(project: ProjectConfig) -> None:
    """The standalone cylinders keep their friction; the platforms' rods are smoothed
    more without the part (its inertia gone) than with it."""
    rig = Rig(project)
    nominal = rig._p_nominal[18]
    loaded = rig._p[18].copy()
    assert np.all(loaded[~rig.platform_mask] == nominal[~rig.platform_mask])
    bolt_part(project, rig)
    bolted = rig._p[18].copy()
    plat = rig.platform_mask
    assert np.all(bolted[plat] > loaded[plat]) and np.all(loaded[plat] >= nominal[plat])
    assert np.all(bolted[plat] < 1e-3)  # the smoothing stays well below a mm/s


@pytest.mark.parametrize("cls", RIGS)
def test_a_bolted_part_keeps_its_pose_and_leaves_the_platform_as_it_lowers(
    project: ProjectConfig, cls: type[Rig]
) -> None:
    rig = cls(project)
    up = rig.upper_index
    cap = project.cylinder("upper_1").cap_area_m2
    rig.advance(400)
    pose = bolt_part(project, rig)
    weight = rig.part_mass_kg * units.G
    assert rig.part_state == "bolted" and rig._body_m[rig._part_body] == 0.0
    assert rig.part_load_n == pytest.approx(weight, rel=0.01)  # carried as before
    z0 = platform_height_m(rig)
    rig.ports_open[:] = 1.0
    rig.command[up] = -0.01  # the four upper rods lower slowly, together
    lowering, load, every_pad = [], [], []
    for _ in range(50):
        rig.advance(400)
        lowering.append(z0 - platform_height_m(rig))
        load.append(rig.part_load_n)
        every_pad.append(bool(np.all(rig.pad_force_n > 0.0)))
    lowering_m, load_n = np.array(lowering), np.array(load)
    # linear in the lowering at the four pads' stiffness while every pad touches ...
    touching = np.array(every_pad)
    assert touching.sum() >= 4
    slope = np.polyfit(lowering_m[touching], load_n[touching], 1)[0]
    assert -slope == pytest.approx(4 * rig.pad_stiffness_n_m, rel=0.05)
    # ... and none once clear: about 1.8 mm (the heavier side's pads last)
    clear = lowering_m[np.argmax(load_n == 0.0)]
    assert 1.4e-3 < clear < 2.6e-3 and load_n[-1] == 0.0
    # the pressures those of the empty platform lowering (its statics with the rods'
    # weight, less their friction): within 0.2 MPa of 0.8 MPa on each cylinder
    f = rig.hydraulic_forces_n[up]
    assert np.all(np.abs(f / cap - units.mpa(0.8)) < units.mpa(0.2)), f / cap
    r, t = pose_from_home(project, rig)  # the part stayed where the bolts hold it
    assert np.array_equal(r, pose[0]) and np.array_equal(t, pose[1])


def test_the_pose_follows_the_platform_until_the_part_is_bolted(project: ProjectConfig) -> None:
    rig = Rig(project)
    up = rig.upper_index
    rig.ports_open[:] = 1.0
    rig.command[up] = -0.01
    t0 = pose_from_home(project, rig)[1]
    rig.advance(800)
    t1 = pose_from_home(project, rig)[1]
    assert t1[2] < t0[2] - 1e-4  # carried: it goes down with the platform
    bolt_part(project, rig)
    rig.advance(800)
    assert np.array_equal(pose_from_home(project, rig)[1], t1)


@pytest.mark.parametrize("cls", RIGS)
def test_a_crane_sets_a_new_part_down_over_its_duration(
    project: ProjectConfig, cls: type[Rig]
) -> None:
    rig = cls(project)
    up = rig.upper_index
    bolt_part(project, rig)
    if isinstance(rig, WalkingRig):  # the bolted part no longer rides with M
        assert rig.mass_kg == pytest.approx(71_350.0 - rig.part_mass_kg)
    rig._pads[5, 4] = 0.0  # the platform clear of the bolted part
    rig.advance(12000)  # the unloaded oil columns settle (3 s)
    f_empty = float(rig.rod_forces_n[up].sum())  # net of friction: what holds the platform
    with pytest.raises(ValueError, match="duration_s must be positive"):
        rig.load_part(0.0)
    rig.load_part(2.0)
    assert rig.part_state == "loading" and rig.bolted_pose is None
    assert not rig._pads.any()
    for _ in range(1000):  # 1 s of PLC scans (1 ms: the ramp moves on at each)
        rig.advance(4)
    assert rig.part_load_n == pytest.approx(0.5 * rig.part_mass_kg * units.G, rel=0.01)
    for _ in range(1001):
        rig.advance(4)
    assert rig.part_state == "carried"
    assert rig._body_m[rig._part_body] == rig.part_mass_kg  # at its home COG
    rig.advance(8000)  # the oil columns take it (valves closed: the oil compresses a little)
    rise = float(rig.rod_forces_n[up].sum()) - f_empty
    g_normal = rig.part_mass_kg * units.G * np.cos(project.base.pitch_rad)
    assert rise == pytest.approx(g_normal, rel=0.02)
    if isinstance(rig, WalkingRig):  # M carries it along the tunnel again
        assert rig.mass_kg == pytest.approx(71_350.0)  # 35 t robot (its 12 rods in it) + part


def test_the_part_s_states_are_checked(project: ProjectConfig) -> None:
    rig = Rig(project)
    with pytest.raises(ValueError, match="carries a part"):
        rig.load_part(1.0)
    bolt_part(project, rig)
    with pytest.raises(ValueError, match="the part is bolted, not carried"):
        bolt_part(project, rig)


def test_the_walking_rig_leaves_the_bolted_part_behind(project: ProjectConfig) -> None:
    """Its pads reach the platform only while M stands where the part was bolted."""
    rig = WalkingRig(project)
    bolt_part(project, rig)
    assert rig.part_load_n > 0.0
    rig.y[_XW] += 2 * rig.PADS_REACH_M  # M moved along the tunnel (X_M: the state's slot)
    rig.advance(1)
    assert rig.part_load_n == 0.0 and not rig._pads.any()
    assert rig.part_state == "bolted" and rig.bolted_pose is not None
