"""Physical quantities derived from the configuration, shared by the plant and the controller.

``hil_sim`` (the stand-in rig) and ``ipc_app`` (the controller) never import each other;
both need the same few numbers derived from a cylinder's parameters (its hydraulic
stiffness, the valve flow gain). They live here, next to the schema, so there is one
formula for each (docs/hydraulic-plant.md explains them).
"""

from __future__ import annotations

import math
from typing import Literal

from config.schema import WORKPIECE_BODY, Body, Cylinder, CylinderPlant, Hydraulics, ProjectConfig


def chamber_volumes_m3(
    cylinder: Cylinder, plant: CylinderPlant, position_m: float
) -> tuple[float, float]:
    """Cap-side and rod-side oil volumes at rod position ``position_m`` (0 = retracted).

    Each chamber has the plant's ``dead_volume_l`` (valve, hoses, cushion) on top of
    its swept volume.
    """
    v_a = plant.dead_volume_m3 + cylinder.cap_area_m2 * position_m
    v_b = plant.dead_volume_m3 + cylinder.rod_area_m2 * (cylinder.stroke_m - position_m)
    return v_a, v_b


def hydraulic_stiffness_n_m(
    cylinder: Cylinder,
    plant: CylinderPlant,
    hydraulics: Hydraulics,
    position_m: float | None = None,
) -> float:
    """Oil-column stiffness ``k_h = beta (A_A^2 / V_A + A_B^2 / V_B)`` (Merritt).

    ``position_m`` defaults to mid-stroke, where the project evaluates it.
    """
    x = cylinder.stroke_m / 2 if position_m is None else position_m
    v_a, v_b = chamber_volumes_m3(cylinder, plant, x)
    beta = hydraulics.bulk_modulus_pa
    return beta * (cylinder.cap_area_m2**2 / v_a + cylinder.rod_area_m2**2 / v_b)


def hydraulic_natural_frequency_rad_s(
    cylinder: Cylinder,
    plant: CylinderPlant,
    hydraulics: Hydraulics,
    position_m: float | None = None,
) -> float:
    """``omega_h = sqrt(k_h / m)`` with the plant's moving mass (rod plus lumped load)."""
    k_h = hydraulic_stiffness_n_m(cylinder, plant, hydraulics, position_m)
    return math.sqrt(k_h / plant.moving_mass_kg)


def viscous_damping_n_s_m(
    cylinder: Cylinder, plant: CylinderPlant, hydraulics: Hydraulics
) -> float:
    """Viscous damping coefficient ``B = 2 zeta sqrt(k_h m)`` from the paper's damping factor.

    The paper's "viscous damping factor" (0.65 / 0.67, dimensionless) is read as the
    damping ratio ``zeta`` of the hydraulic spring-mass mode; ``k_h`` is taken at
    mid-stroke, so ``B`` is one constant per cylinder.
    """
    k_h = hydraulic_stiffness_n_m(cylinder, plant, hydraulics)
    return 2.0 * plant.damping_ratio * math.sqrt(k_h * plant.moving_mass_kg)


def valve_flow_gain_m3_s(hydraulics: Hydraulics, plant: CylinderPlant) -> float:
    """Flow through one metering edge at full command, at the no-load pressure drop.

    ``K_q = C_d w x_v,max sqrt(2 dp / rho)`` with ``dp = (p_s - p_T) / 2`` (the supply
    pressure shared equally by the two metering edges at no load), i.e.
    ``C_d w x_v,max sqrt((p_s - p_T) / rho)``, in m^3/s per unit normalized command.
    """
    dp = hydraulics.supply_pressure_pa - hydraulics.tank_pressure_pa
    return (
        hydraulics.discharge_coefficient
        * plant.area_gradient_m
        * hydraulics.valve_max_opening_m
        * math.sqrt(dp / hydraulics.oil_density_kg_m3)
    )


# --------------------------------------------------------------------------- the rods' mass

#: Where the bodies of the YAML weigh a cylinder's rod in (docs/model-choices.md, "The
#: machine's mass"): the upper platform's own bodies (not the workpiece) its four
#: cylinders' rods, each frame's bodies its four legs' rods and feet.
RodOwner = Literal["upper", "main", "sub"]
ROD_OWNERS: dict[RodOwner, tuple[str, str]] = {
    "upper": ("layers.upper.bodies", "upper_attitude"),
    "main": ("frames.main.bodies", "main_leg"),
    "sub": ("frames.sub.bodies", "sub_leg"),
}


def owner_bodies(cfg: ProjectConfig, owner: RodOwner) -> tuple[Body, ...]:
    """The bodies that weigh ``owner``'s rods in (none: a project without frames)."""
    if owner == "upper":
        return cfg.layers.upper.bodies
    if cfg.frames is None:
        return ()
    return cfg.frames.main.bodies if owner == "main" else cfg.frames.sub.bodies


def owned_rods_kg(cfg: ProjectConfig, owner: RodOwner) -> float:
    """The mass of the rods ``owner``'s bodies weigh in (``hydraulics.rod_mass_kg`` each;
    0 without those bodies)."""
    if not owner_bodies(cfg, owner):
        return 0.0
    role = ROD_OWNERS[owner][1]
    return sum(1 for c in cfg.cylinders if c.role == role) * cfg.hydraulics.rod_mass_kg


def without_rods(cfg: ProjectConfig, owner: RodOwner) -> tuple[Body, ...]:
    """``owner``'s bodies less the rods they weigh in, each body lighter in proportion to
    its mass (its centre of gravity kept; the workpiece untouched): what a model that
    carries the rods as masses of their own (the simulator's rods and feet) or leaves them
    out (the walk's statics: a leg's rod is not in its load) keeps of them. ValueError
    where the bodies weigh less than their rods (config.crosscheck refuses that)."""
    bodies = owner_bodies(cfg, owner)
    rods = owned_rods_kg(cfg, owner)
    own = sum(b.mass_kg for b in bodies if b.name != WORKPIECE_BODY)
    if rods == 0.0:
        return bodies
    if not rods < own:
        raise ValueError(
            f"{ROD_OWNERS[owner][0]}: {own:g} kg cannot weigh in their rods' {rods:g} kg"
        )
    k = 1.0 - rods / own
    return tuple(
        b if b.name == WORKPIECE_BODY else b.model_copy(update={"mass_kg": b.mass_kg * k})
        for b in bodies
    )


def travel_reach_m(cfg: ProjectConfig) -> float:
    """How far S goes each way along the rails from centred: the shortest travel
    cylinder's half stroke less ``walking.travel_reserve_mm`` (the walk plans within it)."""
    assert cfg.walking is not None
    travel = [c for c in cfg.cylinders if c.role == "travel"]
    return min(c.stroke_m for c in travel) / 2 - cfg.walking.travel_reserve_m
