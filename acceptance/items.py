"""The control items of a ring acceptance survey (paper Table 4).

Each item's ``key`` is at once the CSV column, the database column, the ``wara
acceptance add`` option (with dashes) and the tolerance key in the project YAML's
``acceptance`` section, so there is one vocabulary from the survey sheet to the report.

Values stay in the units of their names (mm, deg): the survey records them that way
and the tolerances are given that way, so nothing here converts units.

The accepted text of a value (CSV cell, ``wara acceptance add`` option) is
:data:`NUMBER_SYNTAX`: ASCII digits with an optional sign, decimal point and exponent
(``8``, ``-8.5``, ``.5``, ``+1.2e-3``). Digit separators (``1_0``, ``1,0``), digits of other
scripts, ``inf`` and ``nan`` are refused. A value beyond the item's ``plausible_abs``
(ten times the paper's Table 4 tolerance) is a typo, not a survey, and is refused too.
A ring number is :data:`RING_SYNTAX`: 1 to :data:`MAX_RING`, ASCII digits only.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from config.numbers import DECIMAL_SYNTAX

#: A value as the survey writes it: ASCII, optional sign, decimal point and exponent
#: (the one number syntax of the code, :mod:`config.numbers`).
NUMBER_SYNTAX = DECIMAL_SYNTAX
#: A ring number: ASCII digits only.
RING_SYNTAX = re.compile(r"[0-9]{1,9}")
#: The highest ring number (a 2 m ring: 200 km of tunnel).
MAX_RING = 99_999


@dataclass(frozen=True)
class ControlItem:
    """One row of paper Table 4.

    ``required``: every ring record must carry a value (the five linear items).
    ``signed``: the value carries a direction and may be negative; it is judged by its
    magnitude. An unsigned item (the gap between blocks) must be >= 0.
    ``plausible_abs``: the largest magnitude a survey can record: ten times the paper's
    Table 4 tolerance (the angles, whose Table 4 values are lost: 10 deg).
    """

    key: str
    label: str
    unit: str
    required: bool
    signed: bool
    plausible_abs: float

    def check(self, value: float) -> float:
        """``value`` if it is a plausible survey value of this item, else ValueError."""
        if not (-self.plausible_abs <= value <= self.plausible_abs):  # NaN fails too
            raise ValueError(
                f"{self.key}: got {value!r}: outside the plausible range "
                f"±{self.plausible_abs:g} {self.unit} (ten times the Table 4 tolerance)"
            )
        if not self.signed and value < 0:
            raise ValueError(f"{self.key}: got {value!r}: expected a value >= 0 ({self.unit})")
        return value

    def parse(self, text: str) -> float:
        """A value in :data:`NUMBER_SYNTAX`, checked; ValueError names the item."""
        if NUMBER_SYNTAX.fullmatch(text) is None:
            hint = " (use a decimal point, e.g. 8.5)" if "," in text else ""
            raise ValueError(
                f"{self.key}: {_shown(text)} is not a number "
                f"(ASCII digits, optional sign, decimal point and exponent){hint}"
            )
        return self.check(float(text))


def _shown(text: str) -> str:
    return repr(text) if len(text) <= 40 else repr(text[:37] + "...")


def parse_ring(text: str) -> int:
    """A ring number in :data:`RING_SYNTAX`, 1..MAX_RING; ValueError otherwise."""
    if RING_SYNTAX.fullmatch(text) is None:
        raise ValueError(f"ring: {_shown(text)} is not a ring number (ASCII digits 1-{MAX_RING})")
    return check_ring(int(text))


def check_ring(ring: object) -> int:
    """``ring`` if it is a whole number 1..MAX_RING, else ValueError."""
    if isinstance(ring, bool) or not isinstance(ring, int) or not 1 <= ring <= MAX_RING:
        raise ValueError(f"ring: got {ring!r}: expected a whole number from 1 to {MAX_RING}")
    return ring


ITEMS: tuple[ControlItem, ...] = (
    ControlItem("vertical_misalignment_mm", "Vertical misalignment", "mm", True, True, 80.0),
    ControlItem("horizontal_misalignment_mm", "Horizontal misalignment", "mm", True, True, 80.0),
    ControlItem("max_gap_mm", "Maximum gap between blocks", "mm", True, False, 100.0),
    ControlItem(
        "centreline_deviation_x_mm", "Deviation from tunnel centreline (x)", "mm", True, True, 50.0
    ),
    ControlItem(
        "centreline_deviation_y_mm", "Deviation from tunnel centreline (y)", "mm", True, True, 50.0
    ),
    ControlItem("pitch_angle_deg", "Pitch angle", "deg", False, True, 10.0),
    ControlItem("tilt_angle_deg", "Tilt angle", "deg", False, True, 10.0),
    ControlItem("rotation_angle_deg", "Rotation angle", "deg", False, True, 10.0),
)

ITEM_KEYS: tuple[str, ...] = tuple(i.key for i in ITEMS)
REQUIRED_KEYS: tuple[str, ...] = tuple(i.key for i in ITEMS if i.required)
ITEMS_BY_KEY: dict[str, ControlItem] = {i.key: i for i in ITEMS}
