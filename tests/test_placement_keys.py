"""Every key under ``placement`` and ``tunnel.alignment``, and the tunnel's inner diameter
(the parts' reference height on its invert), governs something: for each key, the same
situation with the shipped value and with a changed value ends differently."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import pytest

from config import ProjectConfig, load_project, units
from config.schema import (
    Alignment,
    AlignmentPoint,
    HorizontalAlignment,
    Placement,
    PlacementWeights,
    VerticalAlignment,
)
from ipc_app.model.placement import Pose, compose, design_pose, deviation, tunnel_frame
from ipc_app.planner.placement import check_moves, plan_from_deviation
from ipc_app.planner.survey import fit_survey, format_survey, parse_survey_text

FACES = [(4.0, 0.3), (-4.0, 0.3), (3.5, 2.5), (-3.5, 2.5), (0.0, 1.4)]


def _with(cfg: ProjectConfig, key: str, value: Any) -> ProjectConfig:
    section, *rest = key.split(".")
    if section == "tunnel":
        return cfg.model_copy(update={"tunnel": cfg.tunnel.model_copy(update={rest[0]: value})})
    if section == "alignment":
        al = cfg.tunnel.alignment
        assert al is not None
        upd: dict[str, Any] = {rest[0]: value}
        if rest[0] == "points":
            upd["gradient_percent"] = None
        if rest[0] in ("horizontal", "vertical"):  # the axis by chainage: both, in place
            upd = {"gradient_percent": None, "horizontal": _STRAIGHT, "vertical": _SHIPPED_GRADE}
            upd[rest[0]] = value
        tunnel = cfg.tunnel.model_copy(update={"alignment": al.model_copy(update=upd)})
        return cfg.model_copy(update={"tunnel": tunnel})
    pl = cfg.placement
    assert pl is not None
    if rest[0] == "weights":
        pl = pl.model_copy(update={"weights": pl.weights.model_copy(update={rest[1]: value})})
    else:
        pl = pl.model_copy(update={rest[0]: value})
    return cfg.model_copy(update={"placement": pl})


def _target_dev(cfg: ProjectConfig, prev: Pose) -> tuple[float, ...]:
    p = plan_from_deviation(cfg, 5, prev)
    return tuple(round(v, 9) for v in deviation(p.target, p.design))


def lever_arm(cfg: ProjectConfig) -> Any:
    target = compose(design_pose(cfg, 5), Pose(yaw=units.deg(0.1)))
    checks, _ = check_moves(cfg, 5, target)
    return round(next(c for c in checks if c.group == "rotation").extensions_mm[0], 6)


def reference_height(cfg: ProjectConfig) -> Any:
    return design_pose(cfg, 5).z


def target_gap(cfg: ProjectConfig) -> Any:
    return round(plan_from_deviation(cfg, 5, Pose()).figures.max_gap_m, 9)


def correction_mm(cfg: ProjectConfig) -> Any:
    return _target_dev(cfg, Pose(y=units.mm(6.0)))


def correction_deg(cfg: ProjectConfig) -> Any:
    return _target_dev(cfg, Pose(yaw=units.deg(0.2)))


def _lateral_trade(cfg: ProjectConfig) -> Any:
    """Steering back from 6 mm with a bound that does not bind: the weights decide."""
    return _target_dev(_with(cfg, "placement.max_correction_per_ring_mm", 10.0), Pose(y=0.006))


def _yaw_trade(cfg: ProjectConfig) -> Any:
    """A previous part turned by 0.03 deg: an even gap against a small angle."""
    return _target_dev(cfg, Pose(yaw=units.deg(0.03)))


def survey_residual(cfg: ProjectConfig) -> Any:
    lines = format_survey(cfg, 4, design_pose(cfg, 4), FACES).splitlines()
    cells = lines[3].split(",")
    cells[5] = f"{float(cells[5]) + 0.02:.4f}"
    lines[3] = ",".join(cells)
    return fit_survey(cfg, 4, parse_survey_text("\n".join(lines))).accepted


def friction(cfg: ProjectConfig) -> Any:
    checks, _ = check_moves(cfg, 5, design_pose(cfg, 5))
    return round(next(c for c in checks if c.group == "lateral").pressure_mpa or 0.0, 9)


def gradient(cfg: ProjectConfig) -> Any:
    checks, _ = check_moves(cfg, 5, design_pose(cfg, 5))
    return tuple(round(e, 9) for c in checks[:2] for e in c.extensions_mm)


def first_chainage(cfg: ProjectConfig) -> Any:
    text = format_survey(load_project(), 4, design_pose(load_project(), 4), FACES)
    return round(fit_survey(cfg, 4, parse_survey_text(text)).pose.x, 9)


def points(cfg: ProjectConfig) -> Any:
    return round(tunnel_frame(cfg, 5).pitch, 12)


_TABLE = (
    AlignmentPoint(chainage_m=0.0, x_m=0.0, y_m=0.0, z_m=0.0),
    AlignmentPoint(chainage_m=100.0, x_m=100.0, y_m=0.0, z_m=-1.0),
)


def heading(cfg: ProjectConfig) -> Any:
    return round(tunnel_frame(cfg, 5).yaw, 12)


_STRAIGHT = HorizontalAlignment.model_validate(
    {"elements": [{"start_chainage_m": 0.0, "kind": "straight"}]}
)
_SHIPPED_GRADE = VerticalAlignment.model_validate(
    {"elements": [{"start_chainage_m": 0.0, "gradient_percent": -0.3}]}
)
_ARC = HorizontalAlignment.model_validate(
    {"elements": [{"start_chainage_m": 0.0, "kind": "arc", "radius_m": 400.0}]}
)
_RISING = VerticalAlignment.model_validate(
    {"elements": [{"start_chainage_m": 0.0, "gradient_percent": 1.0}]}
)

CASES: dict[str, tuple[Any, Callable[[ProjectConfig], Any]]] = {
    "placement.rotation_lever_arm_m": (2.0, lever_arm),
    "tunnel.inner_diameter_m": (10.0, reference_height),
    "placement.target_gap_mm": (3.0, target_gap),
    "placement.max_correction_per_ring_mm": (1.0, correction_mm),
    "placement.max_correction_per_ring_deg": (0.02, correction_deg),
    "placement.weights.misalignment": (3.0, _lateral_trade),
    "placement.weights.centreline_deviation": (3.0, _lateral_trade),
    "placement.weights.gap": (10.0, _yaw_trade),
    "placement.weights.angle": (10.0, _yaw_trade),
    "placement.survey_max_residual_mm": (30.0, survey_residual),
    "placement.slide_friction_coefficient": (0.1, friction),
    "alignment.first_ring_chainage_m": (1.0, first_chainage),
    "alignment.gradient_percent": (0.5, gradient),
    "alignment.points": (_TABLE, points),
    "alignment.horizontal": (_ARC, heading),
    "alignment.vertical": (_RISING, points),
}


def _keys() -> set[str]:
    keys = {f"placement.{k}" for k in Placement.model_fields if k != "weights"}
    keys |= {f"placement.weights.{k}" for k in PlacementWeights.model_fields}
    keys |= {f"alignment.{k}" for k in Alignment.model_fields}
    return keys | {"tunnel.inner_diameter_m"}


def test_every_placement_key_has_a_case() -> None:
    assert set(CASES) == _keys()


@pytest.mark.parametrize("key", sorted(CASES))
def test_changing_the_key_changes_the_behaviour(key: str) -> None:
    cfg = load_project()
    value, situation = CASES[key]
    assert situation(cfg) != situation(_with(cfg, key, value))
