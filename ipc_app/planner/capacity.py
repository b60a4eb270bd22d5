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

The rating (``rated_pressure_mpa``) and the pressure interlock's limit
(``safety.max_pressure_mpa``) stay limits of their own where they are the lower. Every
planner judges its pressures with these functions.
"""

from __future__ import annotations

from typing import Literal

from config import units
from config.schema import Hydraulics, ProjectConfig

#: What a cylinder does in a plan: moves its load, or holds it (and takes it in force
#: control at the walk's ramp).
Duty = Literal["moves", "holds"]


def available_pressure_pa(hydraulics: Hydraulics, duty: Duty = "moves") -> float:
    """The pressure a cylinder can get (Pa): the supply less the load-sensing margin
    when it moves its load, the supply when it holds it."""
    if duty == "holds":
        return hydraulics.supply_pressure_pa
    return hydraulics.supply_pressure_pa - hydraulics.load_sensing_margin_pa


def pressure_limit_pa(cfg: ProjectConfig, duty: Duty = "moves") -> float:
    """The most a plan may ask of a cylinder of that duty (Pa): what it can get, or its
    rating or the pressure interlock's limit where that is lower."""
    h = cfg.hydraulics
    return min(available_pressure_pa(h, duty), h.rated_pressure_pa, _interlock_pa(cfg))


def _interlock_pa(cfg: ProjectConfig) -> float:
    return units.mpa(cfg.safety.max_pressure_mpa)


def pressure_reason(
    cfg: ProjectConfig,
    cylinder: str,
    force_n: float,
    pressure_pa: float,
    duty: Duty = "moves",
) -> str | None:
    """Why ``cylinder``, pushing ``force_n`` at ``pressure_pa``, cannot (``None``: it can):
    the cylinder, its force, the pressure it needs and what the supply gives (or the
    rating or the interlock's limit, where that binds)."""
    if pressure_pa <= pressure_limit_pa(cfg, duty):
        return None
    h = cfg.hydraulics
    need = f"{cylinder} needs {units.to_mpa(pressure_pa):.2f} MPa for {units.to_kn(force_n):.1f} kN"
    if pressure_pa > _interlock_pa(cfg) and _interlock_pa(cfg) < min(
        available_pressure_pa(h, duty), h.rated_pressure_pa
    ):
        return (
            f"pressure: {need}, above the pressure interlock's "
            f"{cfg.safety.max_pressure_mpa:g} MPa (safety.max_pressure_mpa)"
        )
    avail = available_pressure_pa(h, duty)
    if pressure_pa <= avail:
        return f"pressure: {need}, above its rated {h.rated_pressure_mpa:g} MPa"
    if duty == "holds":
        return (
            f"pressure: {need} to hold its load, above the {units.to_mpa(avail):.2f} MPa "
            f"the supply gives a standing cylinder (the {h.supply_pressure_mpa:g} MPa "
            f"supply itself)"
        )
    return (
        f"pressure: {need}, above the {units.to_mpa(avail):.2f} MPa the supply gives "
        f"({h.supply_pressure_mpa:g} MPa supply less the {h.load_sensing_margin_mpa:g} MPa "
        f"load-sensing margin)"
    )
