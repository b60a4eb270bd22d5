"""Statics of the two layers: the load on each cylinder (model.md section 5).

Each platform with everything it carries is a rigid body; lateral forces are taken by
guides at the platform centre, rods push along the layer's base z axis at ``T_i = R p_i``.
Three equilibrium equations in four rod forces; the layer takes the minimum-norm solution
``F = A^T (A A^T)^-1 rhs`` (equal rod stiffness).

With the symmetric action points ``A A^T`` is block diagonal and the minimum-norm
solution has the closed form used in :func:`rod_forces` (derivation in
docs/model-choices.md; the test suite checks it against a generic least-norm solve).
"""

from __future__ import annotations

import functools
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from config import units
from config.derived import without_rods
from config.schema import WORKPIECE_BODY, Body, ProjectConfig
from ipc_app.model.kinematics import Array, S, T, Vec, rotate, rotate_t


class MassProperties(NamedTuple):
    """Total mass and centre of gravity of a set of point masses (platform frame)."""

    mass_kg: float
    cog_m: tuple[float, float, float]


def lump(bodies: tuple[Body, ...]) -> MassProperties:
    """Combine point masses into one (the statics need only mass and COG)."""
    m = sum(b.mass_kg for b in bodies)
    if m <= 0:
        return MassProperties(0.0, (0.0, 0.0, 0.0))
    c = tuple(sum(b.mass_kg * b.cog_m[k] for b in bodies) / m for k in range(3))
    return MassProperties(m, (c[0], c[1], c[2]))


def unloaded_upper_bodies(cfg: ProjectConfig) -> tuple[Body, ...]:
    """The upper layer's bodies without the workpiece (the body named
    :data:`~config.schema.WORKPIECE_BODY`): what the platform carries once the part is
    fixed in the ring. A project without such a body cannot say (ValueError)."""
    bodies = cfg.layers.upper.bodies
    rest = tuple(b for b in bodies if b.name != WORKPIECE_BODY)
    if len(rest) == len(bodies):
        raise ValueError(
            f"the project's upper layer has no body named {WORKPIECE_BODY!r}: "
            "it cannot walk unloaded"
        )
    return rest


def gravity_in(roll: ArrayLike, pitch: ArrayLike, g_parent: Vec) -> Vec:
    """Gravity expressed in a frame rotated by R(roll, pitch) from its parent."""
    return rotate_t(roll, pitch, g_parent)


def rod_forces(
    roll: ArrayLike,
    pitch: ArrayLike,
    a: float,
    b: float,
    mass_kg: ArrayLike,
    cog: Vec,
    g_base: Vec,
) -> Array:
    """Minimum-norm rod forces (N, shape ``(..., 4)``) of one layer.

    ``roll``, ``pitch``: platform attitude relative to the layer base; ``cog``: centre of
    gravity of everything the platform carries, in the platform frame; ``g_base``:
    gravity in the layer's base frame.
    """
    m = np.asarray(mass_kg, dtype=float)
    cr, sr = np.cos(roll), np.sin(roll)
    cp, sp = np.cos(pitch), np.sin(pitch)
    r = rotate(roll, pitch, cog)
    # Gravity moment about the platform centre: M (r x g_b), x and y components.
    mom_x = m * (r.y * g_base.z - r.z * g_base.y)
    mom_y = m * (r.z * g_base.x - r.x * g_base.z)
    rhs0 = -m * g_base.z
    rhs1 = -mom_x
    rhs2 = -mom_y
    alpha = cp * a  # T_x,i = alpha s_i + beta t_i
    beta = sp * sr * b
    gamma = cr * b  # T_y,i = gamma t_i
    f0 = np.asarray(rhs0 / 4.0)[..., None]
    ft = np.asarray(rhs1 / (4.0 * gamma))[..., None]
    fs = np.asarray((beta * rhs1 + gamma * rhs2) / (4.0 * gamma * alpha))[..., None]
    return f0 + T * ft - S * fs


def equilibrium_matrix(roll: float, pitch: float, a: float, b: float) -> Array:
    """The 3x4 matrix A of the equilibrium equations (scalar; for checks and reports)."""
    t = rotate(roll, pitch, Vec(S * a, T * b, np.zeros(4)))
    return np.vstack([np.ones(4), t.y, -t.x])


class MachineStatics:
    """Rod forces of both layers for given layer attitudes (vectorized).

    Heave is kept at zero during attitude adjustment (model.md section 3), so the platform
    origins sit at mid-stroke and the upper base centre stays at ``origin_in_lower_m``.
    ``unloaded``: the upper platform without the workpiece (:func:`unloaded_upper_bodies`).
    """

    def __init__(self, cfg: ProjectConfig, unloaded: bool = False) -> None:
        lo, up = cfg.layers.lower, cfg.layers.upper
        self.a_lower, self.b_lower = lo.a_m, lo.b_m
        self.a_upper, self.b_upper = up.a_m, up.b_m
        self.lower_own = lump(lo.bodies)
        self.upper = lump(unloaded_upper_bodies(cfg) if unloaded else up.bodies)
        self._cfg, self._unloaded = cfg, unloaded
        self.origin_upper = up.origin_in_lower_m
        #: an attitude cylinder's rod and piston (``hydraulics.rod_mass_kg``)
        self.rod_mass_kg = cfg.hydraulics.rod_mass_kg
        g = np.asarray(-units.G)
        zero = np.asarray(0.0)
        self.g_base = gravity_in(cfg.base.roll_rad, cfg.base.pitch_rad, Vec(zero, zero, g))

    def forces(
        self,
        lower_roll: ArrayLike,
        lower_pitch: ArrayLike,
        upper_roll: ArrayLike,
        upper_pitch: ArrayLike,
    ) -> tuple[Array, Array]:
        """``(F_lower, F_upper)``, each ``(..., 4)`` in N (compression positive)."""
        mu, cu = self.upper.mass_kg, self.upper.cog_m
        cu_vec = Vec(np.asarray(cu[0]), np.asarray(cu[1]), np.asarray(cu[2]))
        g_upper = gravity_in(lower_roll, lower_pitch, self.g_base)
        f_upper = rod_forces(
            upper_roll, upper_pitch, self.a_upper, self.b_upper, mu, cu_vec, g_upper
        )
        # Upper bodies placed in the lower platform frame at o_U + R_U c.
        ru = rotate(upper_roll, upper_pitch, cu_vec)
        o = self.origin_upper
        ml, cl = self.lower_own
        m = ml + mu
        cog = Vec(
            (ml * cl[0] + mu * (o[0] + ru.x)) / m,
            (ml * cl[1] + mu * (o[1] + ru.y)) / m,
            (ml * cl[2] + mu * (o[2] + ru.z)) / m,
        )
        f_lower = rod_forces(
            lower_roll, lower_pitch, self.a_lower, self.b_lower, m, cog, self.g_base
        )
        return f_lower, f_upper

    @functools.cached_property
    def upper_rodless(self) -> MassProperties:
        """:attr:`upper` less the four rods its bodies weigh in
        (:func:`config.derived.without_rods`): the platform on the rods, each rod's weight
        on its own cylinder."""
        rodless = without_rods(self._cfg, "upper")
        if self._unloaded:
            rodless = tuple(b for b in rodless if b.name != WORKPIECE_BODY)
        return lump(rodless)

    def upper_cylinder_forces(
        self,
        lower_roll: ArrayLike,
        lower_pitch: ArrayLike,
        upper_roll: ArrayLike,
        upper_pitch: ArrayLike,
    ) -> Array:
        """The upper cylinders' hydraulic forces at rest, ``(..., 4)`` in N: the share
        of the platform's bodies less the rods they weigh in, plus each cylinder's own rod
        and piston (``hydraulics.rod_mass_kg``) along its axis, the upper base's z. What
        the rods' pressures carry (``p_A A_A - p_B A_B``) when the platform stands still."""
        g_upper = gravity_in(lower_roll, lower_pitch, self.g_base)
        m, c = self.upper_rodless
        c_vec = Vec(np.asarray(c[0]), np.asarray(c[1]), np.asarray(c[2]))
        f_upper = rod_forces(upper_roll, upper_pitch, self.a_upper, self.b_upper, m, c_vec, g_upper)
        return f_upper - self.rod_mass_kg * np.asarray(g_upper.z)[..., None]


def home_cap_pressures_pa(cfg: ProjectConfig) -> dict[str, float]:
    """Each attitude cylinder's cap pressure (Pa) under the nominal load: both layers
    level on their bases (the home pose, as the machine stands at boot), the rod forces
    of :meth:`MachineStatics.forces` over the cap areas, as the planner computes its
    pressures (:class:`ipc_app.planner.problem.AttitudeProblem`). Keyed by cylinder id,
    the lower layer's first."""
    f_lower, f_upper = MachineStatics(cfg).forces(0.0, 0.0, 0.0, 0.0)
    out: dict[str, float] = {}
    for layer, forces in ((cfg.layers.lower, f_lower), (cfg.layers.upper, f_upper)):
        for cid, f in zip(layer.cylinders, np.asarray(forces, dtype=float), strict=True):
            out[cid] = float(f) / cfg.cylinder(cid).cap_area_m2
    return out
