"""Kinematics, composition and statics of model.md sections 1-5."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from config import ProjectConfig, load_project
from ipc_app.model import (
    MachineStatics,
    attitude_matrix,
    check_attitude,
    coplanarity_distance,
    extensions,
    fit_layer,
    solve_lower,
    target_in_base,
    twist,
)
from ipc_app.model.kinematics import S, T, Vec, extensions_at, linked_attitude
from ipc_app.model.statics import equilibrium_matrix, lump

angle = st.floats(-0.25, 0.25)
small = st.floats(-0.05, 0.05)
CFG = load_project()


def test_attitude_matrix_is_ry_times_rx() -> None:
    r, p = 0.1, -0.2
    rx = np.array([[1, 0, 0], [0, math.cos(r), -math.sin(r)], [0, math.sin(r), math.cos(r)]])
    ry = np.array([[math.cos(p), 0, math.sin(p)], [0, 1, 0], [-math.sin(p), 0, math.cos(p)]])
    assert np.allclose(attitude_matrix(r, p), ry @ rx)


@given(angle, angle, small)
def test_extension_is_projection_of_rotated_point(roll: float, pitch: float, z: float) -> None:
    a, b = 2.8, 1.4
    d = extensions(roll, pitch, a, b, z)
    rot = attitude_matrix(roll, pitch)
    for i in range(4):
        p = np.array([S[i] * a, T[i] * b, 0.0])
        assert d[i] == pytest.approx(z + (rot @ p)[2], abs=1e-15)


@given(angle, angle, small)
def test_forward_inverse_round_trip(roll: float, pitch: float, z: float) -> None:
    a, b = 1.6, 1.2
    fit = fit_layer(extensions(roll, pitch, a, b, z), a, b)
    assert float(fit.roll) == pytest.approx(roll, abs=1e-12)
    assert float(fit.pitch) == pytest.approx(pitch, abs=1e-12)
    assert float(fit.heave) == pytest.approx(z, abs=1e-15)
    assert float(fit.twist) == pytest.approx(0.0, abs=1e-15)


@given(angle, angle)
def test_linkage_and_coplanarity_identities(roll: float, pitch: float) -> None:
    a, b = 2.8, 1.4
    d = extensions(roll, pitch, a, b)
    assert d[2] == -d[0] and d[3] == -d[1]  # paper eq. 16, exactly
    assert (d[1] - d[0]) / (2 * a) == pytest.approx(math.sin(pitch), abs=1e-14)
    assert (d[0] + d[1]) / (2 * b) == pytest.approx(math.sin(roll) * math.cos(pitch), abs=1e-14)
    assert float(coplanarity_distance(d, a, b)) == pytest.approx(0.0, abs=1e-15)


@given(angle, angle, small, st.floats(-0.01, 0.01))
def test_extensions_on_floats_are_the_array_form(
    roll: float, pitch: float, z: float, w: float
) -> None:
    a, b = 2.8, 1.4
    want = extensions(roll, pitch, a, b, z, w)
    assert want == pytest.approx(extensions(roll, pitch, a, b, z) + w * np.array([1, -1, 1, -1]))
    assert extensions_at(roll, pitch, a, b, z, w) == pytest.approx(want.tolist(), abs=1e-16)


@given(angle, angle)
def test_linked_attitude_inverts_a_linked_layer(roll: float, pitch: float) -> None:
    a, b = 1.6, 1.2
    d = extensions(roll, pitch, a, b)
    r, p = linked_attitude(d[0], d[1], a, b)
    assert float(r) == pytest.approx(roll, abs=1e-12)
    assert float(p) == pytest.approx(pitch, abs=1e-12)
    fit = fit_layer(d, a, b)  # the least-squares fit of the same extensions
    assert float(fit.roll) == pytest.approx(float(r), abs=1e-15)
    assert float(fit.pitch) == pytest.approx(float(p), abs=1e-15)


@given(angle, angle, st.floats(-0.01, 0.01))
def test_twist_is_the_residual_and_moves_point_four_off_the_plane(
    roll: float, pitch: float, w: float
) -> None:
    a, b = 2.8, 1.4
    d = extensions(roll, pitch, a, b) + w * np.array([1, -1, 1, -1])
    fit = fit_layer(d, a, b)
    assert float(fit.twist) == pytest.approx(w, abs=1e-15)
    assert float(twist(d)) == pytest.approx(w, abs=1e-15)
    assert float(fit.roll) == pytest.approx(roll, abs=1e-12)
    # Independent: distance of point 4 from the plane through points 1-3.
    pts = np.array([[S[i] * a, T[i] * b, d[i]] for i in range(4)])
    n = np.cross(pts[1] - pts[0], pts[2] - pts[0])
    dist = abs(np.dot(pts[3] - pts[0], n)) / np.linalg.norm(n)
    assert float(coplanarity_distance(d, a, b)) == pytest.approx(dist, rel=1e-9, abs=1e-15)


@settings(max_examples=200)
@given(angle, angle, angle, angle, st.floats(-0.02, 0.02), st.floats(-0.02, 0.02))
def test_composition_reaches_target_normal(
    tr: float, tp: float, ur: float, up: float, br: float, bp: float
) -> None:
    v = target_in_base(br, bp, tr, tp)
    low = solve_lower(ur, up, v)
    assert bool(low.solvable)
    check = check_attitude((br, bp), (float(low.roll), float(low.pitch)), (ur, up), (tr, tp))
    assert check.error_rad < 1e-12
    rw = attitude_matrix(br, bp) @ attitude_matrix(float(low.roll), float(low.pitch))
    rw = rw @ attitude_matrix(ur, up)
    assert np.allclose(rw[:, 2], attitude_matrix(tr, tp)[:, 2], atol=1e-12)


def test_composition_takes_the_smaller_root() -> None:
    v = target_in_base(0.0, 0.0, 0.05, 0.02)
    low = solve_lower(0.01, 0.0, v)
    assert abs(float(low.roll)) < 0.1


def test_level_machine_carries_about_48_5_mpa(project: ProjectConfig) -> None:
    fl, fu = MachineStatics(project).forces(0.0, 0.0, 0.0, 0.0)
    total = (fl.sum() + fu.sum()) / project.layers.upper.cap_area_m2
    # reference-machine.md: "the eight cap pressures at a level pose sum to about 48.5 MPa"
    assert total / 1e6 == pytest.approx(48.5, abs=0.3)


@settings(max_examples=100)
@given(angle, angle, angle, angle)
def test_statics_equilibrium_and_minimum_norm(lr: float, lp: float, ur: float, up: float) -> None:
    ms = MachineStatics(CFG)
    fl, fu = ms.forces(lr, lp, ur, up)
    g = 9.80665
    base = attitude_matrix(CFG.base.roll_rad, CFG.base.pitch_rad)
    low = attitude_matrix(lr, lp)
    upm = attitude_matrix(ur, up)
    upper_bodies = CFG.layers.upper.bodies
    lower_bodies = CFG.layers.lower.bodies
    o = np.array(CFG.layers.upper.origin_in_lower_m)
    for f, r_base, r_plat, bodies, a, b, roll, pitch in (
        (
            fu,
            base @ low,
            upm,
            [(x.mass_kg, upm @ np.array(x.cog_m)) for x in upper_bodies],
            1.6,
            1.2,
            ur,
            up,
        ),
        (
            fl,
            base,
            low,
            [(x.mass_kg, low @ np.array(x.cog_m)) for x in lower_bodies]
            + [(x.mass_kg, low @ (o + upm @ np.array(x.cog_m))) for x in upper_bodies],
            2.8,
            1.4,
            lr,
            lp,
        ),
    ):
        del r_plat
        gb = r_base.T @ np.array([0, 0, -g])
        rhs = np.array(
            [
                -sum(m * gb[2] for m, _ in bodies),
                -sum(np.cross(r, m * gb)[0] for m, r in bodies),
                -sum(np.cross(r, m * gb)[1] for m, r in bodies),
            ]
        )
        amat = equilibrium_matrix(roll, pitch, a, b)
        load = abs(rhs[0])
        assert np.max(np.abs(amat @ f - rhs)) < 1e-9 * load
        # Minimum norm: equal to the generic pseudo-inverse solution.
        assert np.allclose(f, np.linalg.pinv(amat) @ rhs, rtol=0, atol=1e-9 * load)


def test_lump_combines_point_masses() -> None:
    m = lump(CFG.layers.upper.bodies)
    assert m.mass_kg == 42350
    assert m.cog_m[1] == pytest.approx(36350 * 0.15 / 42350)


def test_vectorized_matches_scalar() -> None:
    ms = MachineStatics(CFG)
    rolls = np.linspace(-0.1, 0.1, 7)
    fl, fu = ms.forces(rolls, 0.02, -rolls, 0.01)
    for k, r in enumerate(rolls):
        fl1, fu1 = ms.forces(float(r), 0.02, float(-r), 0.01)
        assert np.allclose(fl[k], fl1) and np.allclose(fu[k], fu1)
    assert Vec(np.zeros(1), np.zeros(1), np.zeros(1)).x.shape == (1,)
