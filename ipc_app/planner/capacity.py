"""What pressure a cylinder can get, and the refusal of a plan that needs more.

A load-sensing pump holds its outlet the load-sensing margin
(``hydraulics.load_sensing_margin_mpa``) above the highest load pressure it feeds, up to
its setting, the supply (``hydraulics.supply_pressure_mpa``). What a cylinder can get
depends on what it does (docs/model-choices.md, "Capacity"):

- it **moves** its load at the planned speed (attitude adjustment, the placement's
  moves, the slide axes): the valve needs the margin across its metering edge for the
  planned flow, so the load pressure may reach the supply less the margin;
- it **holds** its load, or takes it in force control at the walk's force ramp (the
  standing legs of a walk, the legs being preloaded or loaded): no flow but the ramp's
  trickle, so the load pressure may reach the supply itself, not above (above it the
  valve could not push oil in: the leg could neither correct a sag nor take more load).

The rating (``rated_pressure_mpa``) stays a limit of its own where it is the lower.
Every planner judges its pressures with these functions.
"""

from __future__ import annotations

from typing import Literal

from config import units
from config.schema import Hydraulics

#: What a cylinder does in a plan: moves its load, or holds it (and takes it in force
#: control at the walk's ramp).
Duty = Literal["moves", "holds"]


def available_pressure_pa(hydraulics: Hydraulics, duty: Duty = "moves") -> float:
    """The pressure a cylinder can get (Pa): the supply less the load-sensing margin
    when it moves its load, the supply when it holds it."""
    if duty == "holds":
        return hydraulics.supply_pressure_pa
    return hydraulics.supply_pressure_pa - hydraulics.load_sensing_margin_pa


def pressure_limit_pa(hydraulics: Hydraulics, duty: Duty = "moves") -> float:
    """The most a plan may ask of a cylinder of that duty (Pa): what it can get, or its
    rating where that is lower."""
    return min(available_pressure_pa(hydraulics, duty), hydraulics.rated_pressure_pa)


def pressure_reason(
    hydraulics: Hydraulics,
    cylinder: str,
    force_n: float,
    pressure_pa: float,
    duty: Duty = "moves",
) -> str | None:
    """Why ``cylinder``, pushing ``force_n`` at ``pressure_pa``, cannot (``None``: it can):
    the cylinder, its force, the pressure it needs and what the supply gives (or its
    rating, where that binds)."""
    if pressure_pa <= pressure_limit_pa(hydraulics, duty):
        return None
    need = f"{cylinder} needs {units.to_mpa(pressure_pa):.2f} MPa for {units.to_kn(force_n):.1f} kN"
    avail = available_pressure_pa(hydraulics, duty)
    if pressure_pa <= avail:
        return f"pressure: {need}, above its rated {hydraulics.rated_pressure_mpa:g} MPa"
    supply = hydraulics.supply_pressure_mpa
    if duty == "holds":
        return (
            f"pressure: {need} to hold its load, above the {units.to_mpa(avail):.2f} MPa "
            f"the supply gives a standing cylinder (the {supply:g} MPa supply itself)"
        )
    return (
        f"pressure: {need}, above the {units.to_mpa(avail):.2f} MPa the supply gives "
        f"({supply:g} MPa supply less the {hydraulics.load_sensing_margin_mpa:g} MPa "
        f"load-sensing margin)"
    )
