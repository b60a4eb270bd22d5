"""The control items of a ring acceptance survey (paper Table 4).

Each item's ``key`` is at once the CSV column, the database column, the ``wara
acceptance add`` option (with dashes) and the tolerance key in the project YAML's
``acceptance`` section, so there is one vocabulary from the survey sheet to the report.

Values stay in the units of their names (mm, deg): the survey records them that way
and the tolerances are given that way, so nothing here converts units.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ControlItem:
    """One row of paper Table 4.

    ``required``: every ring record must carry a value (the five linear items).
    ``signed``: the value carries a direction and may be negative; it is judged by its
    magnitude. An unsigned item (the gap between blocks) must be >= 0.
    """

    key: str
    label: str
    unit: str
    required: bool
    signed: bool


ITEMS: tuple[ControlItem, ...] = (
    ControlItem("vertical_misalignment_mm", "Vertical misalignment", "mm", True, True),
    ControlItem("horizontal_misalignment_mm", "Horizontal misalignment", "mm", True, True),
    ControlItem("max_gap_mm", "Maximum gap between blocks", "mm", True, False),
    ControlItem(
        "centreline_deviation_x_mm", "Deviation from tunnel centreline (x)", "mm", True, True
    ),
    ControlItem(
        "centreline_deviation_y_mm", "Deviation from tunnel centreline (y)", "mm", True, True
    ),
    ControlItem("pitch_angle_deg", "Pitch angle", "deg", False, True),
    ControlItem("tilt_angle_deg", "Tilt angle", "deg", False, True),
    ControlItem("rotation_angle_deg", "Rotation angle", "deg", False, True),
)

ITEM_KEYS: tuple[str, ...] = tuple(i.key for i in ITEMS)
REQUIRED_KEYS: tuple[str, ...] = tuple(i.key for i in ITEMS if i.required)
ITEMS_BY_KEY: dict[str, ControlItem] = {i.key: i for i in ITEMS}
