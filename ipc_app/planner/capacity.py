"""What pressure a cylinder can get, and the refusal of a plan that needs more.

A cylinder's chamber gets at most the supply less the load-sensing margin
(``hydraulics.supply_pressure_mpa - hydraulics.load_sensing_margin_mpa``): the
load-sensing pump holds its outlet that margin above the highest load pressure, and the
outlet cannot exceed the supply, so a load needing more is not lifted, however high the
cylinders are rated. The rating (``rated_pressure_mpa``) stays a limit of its own where
it is the lower. Every planner (attitude, walk, placement: legs, upper cylinders, slide
axes) judges its pressures with these functions.
"""

from __future__ import annotations

from config import units
from config.schema import Hydraulics


def available_pressure_pa(hydraulics: Hydraulics) -> float:
    """The pressure a cylinder can get (Pa): the supply less the load-sensing margin."""
    return hydraulics.supply_pressure_pa - hydraulics.load_sensing_margin_pa


def pressure_limit_pa(hydraulics: Hydraulics) -> float:
    """The most a plan may ask of a cylinder (Pa): what it can get, or its rating where
    that is lower."""
    return min(available_pressure_pa(hydraulics), hydraulics.rated_pressure_pa)


def pressure_reason(
    hydraulics: Hydraulics, cylinder: str, force_n: float, pressure_pa: float
) -> str | None:
    """Why ``cylinder``, pushing ``force_n`` at ``pressure_pa``, cannot (``None``: it can):
    the cylinder, its force, the pressure it needs and what the supply gives (or its
    rating, where that binds)."""
    if pressure_pa <= pressure_limit_pa(hydraulics):
        return None
    need = f"{cylinder} needs {units.to_mpa(pressure_pa):.2f} MPa for {units.to_kn(force_n):.1f} kN"
    avail = available_pressure_pa(hydraulics)
    if pressure_pa > avail:
        return (
            f"pressure: {need}, above the {units.to_mpa(avail):.2f} MPa the supply gives "
            f"({hydraulics.supply_pressure_mpa:g} MPa supply less the "
            f"{hydraulics.load_sensing_margin_mpa:g} MPa load-sensing margin)"
        )
    return f"pressure: {need}, above its rated {hydraulics.rated_pressure_mpa:g} MPa"
