"""The one place where engineering units from the YAML become SI.

Code works in SI (m, rad, N, Pa, kg, s). Configuration keys carry their unit in the
name (``bore_mm``, ``supply_pressure_mpa``); the schema's SI properties convert with
these helpers and nothing else does.
"""

from __future__ import annotations

import math

G = 9.80665  # standard gravity, m/s^2 (model.md section 1)

MM = 1e-3  # m per mm
MPA = 1e6  # Pa per MPa
KN = 1e3  # N per kN
L_PER_MIN = 1e-3 / 60.0  # m^3/s per l/min
LITRE = 1e-3  # m^3 per l
MS = 1e-3  # s per ms
UM = 1e-6  # m per um
US = 1e-6  # s per us
NS = 1e-9  # s per ns
KPA = 1e3  # Pa per kPa


def mm(value_mm: float) -> float:
    """Millimetres to metres."""
    return value_mm * MM


def to_mm(value_m: float) -> float:
    """Metres to millimetres."""
    return value_m / MM


def ms(value_ms: float) -> float:
    """Milliseconds to seconds."""
    return value_ms * MS


def to_ms(value_s: float) -> float:
    """Seconds to milliseconds."""
    return value_s / MS


def to_us(value_s: float) -> float:
    """Seconds to microseconds."""
    return value_s / US


def to_kn(value_n: float) -> float:
    """Newton to kilonewton."""
    return value_n / KN


def um(value_um: float) -> float:
    """Micrometres to metres."""
    return value_um * UM


def kpa(value_kpa: float) -> float:
    """Kilopascal to pascal."""
    return value_kpa * KPA


def mpa(value_mpa: float) -> float:
    """Megapascal to pascal."""
    return value_mpa * MPA


def to_mpa(value_pa: float) -> float:
    """Pascal to megapascal."""
    return value_pa / MPA


def deg(value_deg: float) -> float:
    """Degrees to radians."""
    return math.radians(value_deg)


def to_deg(value_rad: float) -> float:
    """Radians to degrees."""
    return math.degrees(value_rad)


def circle_area_m2(diameter_m: float) -> float:
    """Area of a circle of the given diameter."""
    return math.pi * diameter_m * diameter_m / 4.0


def annulus_area_m2(bore_m: float, rod_m: float) -> float:
    """Rod-side (annulus) area of a differential cylinder."""
    return circle_area_m2(bore_m) - circle_area_m2(rod_m)
