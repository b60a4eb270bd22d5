"""The design axis by chainage (docs/curves.md): arcs, clothoids, grades and vertical
curves, their contiguity, and the rings laid along the axis."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from pydantic import ValidationError

from config import ProjectConfig, load_project, units
from config.alignment import along_axis_m, invert_rise_m, start_chainage_m
from config.schema import Alignment
from ipc_app.model.placement import (
    Pose,
    axis_pose,
    chainage_along,
    compose,
    design_pose,
    face_corners,
    face_points,
    ring_chainage_m,
    to_ring_frame,
    tunnel_frame,
)
from ipc_app.planner.placement import joint_opening, plan_from_deviation
from ipc_app.planner.survey import fit_survey, format_survey, parse_survey_text

R = 400.0


def _axis(h: list[dict[str, Any]], v: list[dict[str, Any]], **start: float) -> Alignment:
    z = {"z_m": start.pop("z_m")} if "z_m" in start else {}
    return Alignment.model_validate(
        {"horizontal": {**start, "elements": h}, "vertical": {**z, "elements": v}}
    )


def _curve(radius: float = R, grade: float = 0.0) -> Alignment:
    return _axis(
        [
            {"start_chainage_m": -50, "kind": "straight"},
            {"start_chainage_m": 0, "kind": "arc", "radius_m": radius},
        ],
        [{"start_chainage_m": -50, "gradient_percent": grade}],
        x_m=-50.0,
        z_m=-0.5 * grade,
    )


@pytest.mark.parametrize("radius", [R, -R, 300.0])
def test_an_arcs_heading_changes_by_s_over_r_and_its_points_lie_on_the_circle(
    radius: float,
) -> None:
    axis = _curve(radius)
    centre = np.array([0.0, radius])  # the arc starts at the origin heading +x
    for s in (0.0, 2.0, 7.3, 40.0, 150.0):
        p = axis_pose(axis, s)
        assert p.yaw == pytest.approx(s / radius, abs=1e-12)
        assert np.linalg.norm(p.position[:2] - centre) == pytest.approx(abs(radius), abs=1e-9)
        assert p.z == pytest.approx(0.0) and p.pitch == pytest.approx(0.0)
    # the straight before it: the heading it starts with, on the x axis
    before = axis_pose(axis, -20.0)
    assert before.yaw == 0.0 and before.position == pytest.approx([-20.0, 0.0, 0.0])
    # a positive radius turns left (+y), a negative one right
    assert math.copysign(1.0, axis_pose(axis, 30.0).y) == math.copysign(1.0, radius)


def test_the_frame_at_a_chainage_is_the_axis_tangent_with_y_horizontal() -> None:
    axis = _curve(R, grade=3.0)
    p = axis_pose(axis, 20.0)
    m = p.matrix
    assert m[2, 1] == pytest.approx(0.0, abs=1e-12)  # T's y horizontal (to the left)
    assert p.pitch == pytest.approx(-math.atan(0.03))  # rising: a negative pitch
    q = axis_pose(axis, 20.001)
    tangent = (q.position - p.position) / np.linalg.norm(q.position - p.position)
    assert tangent == pytest.approx(m[:, 0], abs=1e-5)


def test_a_clothoid_turns_the_curvature_linearly_between_its_neighbours() -> None:
    a = 200.0
    length = a * a / R  # 100 m from a straight into the 400 m arc
    axis = _axis(
        [
            {"start_chainage_m": 0, "kind": "straight"},
            {"start_chainage_m": 10, "kind": "clothoid", "clothoid_parameter_m": a},
            {"start_chainage_m": 10 + length, "kind": "arc", "radius_m": R},
        ],
        [{"start_chainage_m": 0, "gradient_percent": 0.0}],
    )
    for u in (0.0, 25.0, 60.0, length):
        assert axis_pose(axis, 10 + u).yaw == pytest.approx(u * u / (2 * a * a), abs=1e-12)
    # the clothoid's end is continuous with the arc: the arc's heading goes on by s/R
    assert axis_pose(axis, 10 + length + 30).yaw == pytest.approx(length / (2 * R) + 30 / R)
    # its point: the clothoid's series x = u - u^5 / (40 A^4), y = u^3 / (6 A^2) - ...
    u = length
    p = axis_pose(axis, 10 + u)
    x = u - u**5 / (40 * a**4) + u**9 / (3456 * a**8) - u**13 / (599040 * a**12)
    y = u**3 / (6 * a**2) - u**7 / (336 * a**6) + u**11 / (42240 * a**10)
    assert p.position[:2] == pytest.approx([10 + x, y], abs=1e-9)


def test_a_vertical_curves_grade_changes_linearly_and_its_level_is_continuous() -> None:
    rv = 3000.0  # from 0.3 % to 3 %: 81 m
    axis = _axis(
        [{"start_chainage_m": 0, "kind": "straight"}],
        [
            {"start_chainage_m": 0, "gradient_percent": 0.3},
            {"start_chainage_m": 100, "radius_m": rv},
            {"start_chainage_m": 181, "gradient_percent": 3.0},
        ],
    )

    def grade(c: float) -> float:
        return -math.tan(axis_pose(axis, c).pitch)

    for c in (100.0, 120.0, 150.5, 181.0):
        assert grade(c) == pytest.approx(0.003 + (c - 100) / rv, abs=1e-12)
    assert grade(50.0) == pytest.approx(0.003) and grade(300.0) == pytest.approx(0.03)
    z_end = 0.3 + 0.003 * 81 + 81**2 / (2 * rv)
    assert axis_pose(axis, 181.0).z == pytest.approx(z_end, abs=1e-12)
    assert axis_pose(axis, 281.0).z == pytest.approx(z_end + 3.0, abs=1e-12)


def test_the_invert_rises_over_its_grades_plane_on_a_vertical_curve_only() -> None:
    """curves.md section 3: the invert under each frame follows the axis's grade at its
    chainage; what the simulator's feet stand on is its rise above the start's grade."""
    rv = 3000.0
    h = [{"start_chainage_m": -200, "kind": "straight"}]
    v = [
        {"start_chainage_m": -200, "gradient_percent": 0.3},
        {"start_chainage_m": -100, "radius_m": rv},  # a sag: 0.3 % to 3 % over 81 m
        {"start_chainage_m": -19, "gradient_percent": 3.0},
    ]
    x = np.linspace(-8.0, 8.0, 33)
    on_grade = _axis(h, v)  # ring 1 at chainage 0, on the 3 % grade
    assert np.abs(invert_rise_m(on_grade, x)).max() < 1e-12
    assert np.all(invert_rise_m(None, x) == 0.0)
    in_curve = on_grade.model_copy(update={"first_ring_chainage_m": -60.0})
    assert start_chainage_m(in_curve) == -60.0 and start_chainage_m(None) == 0.0
    g0 = 0.003 + 40.0 / rv
    cos_a = 1.0 / math.hypot(1.0, g0)
    assert invert_rise_m(in_curve, x) == pytest.approx(
        (x * cos_a) ** 2 / (2.0 * rv) * cos_a, abs=1e-9
    )  # 10.7 mm 8 m ahead
    # a table of points: the kink's rise beyond it, none before
    table = Alignment.model_validate(
        {
            "points": [
                {"chainage_m": -10, "x_m": -10, "y_m": 0, "z_m": 0.0},
                {"chainage_m": 2, "x_m": 2, "y_m": 0, "z_m": 0.0},
                {"chainage_m": 20, "x_m": 20, "y_m": 0, "z_m": 0.18},
            ]
        }
    )
    assert invert_rise_m(table, np.array([-5.0, 1.0, 6.0])) == pytest.approx(
        [0.0, 0.0, 0.04], abs=1e-9
    )


def test_rings_are_laid_along_the_axis_not_the_chainage_in_plan() -> None:
    axis = _curve(R, grade=3.0)
    c = chainage_along(axis, 0.0, 2.0)
    assert c == pytest.approx(2.0 / math.hypot(1.0, 0.03), abs=1e-9)
    assert along_axis_m(axis.vertical, 0.0, c) == pytest.approx(2.0, abs=1e-9)  # type: ignore[arg-type]
    # 3D distance between the two points on the arc: a chord of the 2 m axis length
    d = np.linalg.norm(axis_pose(axis, c).position - axis_pose(axis, 0.0).position)
    assert d == pytest.approx(2.0, abs=1e-4)


CONTIGUITY = [
    (  # a clothoid too long for its parameter
        [
            {"start_chainage_m": 0, "kind": "straight"},
            {"start_chainage_m": 10, "kind": "clothoid", "clothoid_parameter_m": 200},
            {"start_chainage_m": 120, "kind": "arc", "radius_m": 400},
        ],
        [{"start_chainage_m": 0, "gradient_percent": 0}],
        r"horizontal\.elements\[1\] \(clothoid from chainage 10 m\): is 110 m long .* "
        r"elements\[2\] should start at 110\.000 m",
    ),
    (  # elements out of order
        [
            {"start_chainage_m": 0, "kind": "straight"},
            {"start_chainage_m": 0, "kind": "arc", "radius_m": 400},
        ],
        [{"start_chainage_m": 0, "gradient_percent": 0}],
        r"horizontal\.elements\[1\] \(arc from chainage 0 m\): does not start after",
    ),
    (  # a clothoid at the end
        [
            {"start_chainage_m": 0, "kind": "straight"},
            {"start_chainage_m": 10, "kind": "clothoid", "clothoid_parameter_m": 200},
        ],
        [{"start_chainage_m": 0, "gradient_percent": 0}],
        r"elements\[1\] .*cannot be first or last",
    ),
    (  # a vertical curve shorter than its radius makes it
        [{"start_chainage_m": 0, "kind": "straight"}],
        [
            {"start_chainage_m": 0, "gradient_percent": 0.3},
            {"start_chainage_m": 100, "radius_m": 3000},
            {"start_chainage_m": 150, "gradient_percent": 3.0},
        ],
        r"vertical\.elements\[1\] \(vertical curve from chainage 100 m\): is 50 m long .* "
        r"elements\[2\] should start at 181\.000 m",
    ),
    (  # a vertical curve not between two grades
        [{"start_chainage_m": 0, "kind": "straight"}],
        [
            {"start_chainage_m": 0, "gradient_percent": 0.3},
            {"start_chainage_m": 9, "radius_m": 3e3},
        ],
        r"vertical\.elements\[1\] .*joins a grade before it to one after it",
    ),
]


@pytest.mark.parametrize(("h", "v", "message"), CONTIGUITY)
def test_elements_that_do_not_join_are_refused_naming_the_element(
    h: list[dict[str, Any]], v: list[dict[str, Any]], message: str
) -> None:
    with pytest.raises(ValidationError, match=message):
        _axis(h, v)


@pytest.mark.parametrize(
    ("element", "message"),
    [
        ({"kind": "arc"}, "an arc gives radius_m"),
        ({"kind": "arc", "radius_m": 0}, "an arc gives radius_m"),
        ({"kind": "straight", "radius_m": 400}, "a straight gives neither"),
        ({"kind": "clothoid", "radius_m": 400}, "a clothoid gives clothoid_parameter_m"),
    ],
)
def test_an_elements_keys_match_its_kind(element: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        _axis(
            [{"start_chainage_m": 0, **element}], [{"start_chainage_m": 0, "gradient_percent": 0}]
        )


def test_one_form_of_the_axis_and_horizontal_with_vertical() -> None:
    h = {"elements": [{"start_chainage_m": 0, "kind": "straight"}]}
    with pytest.raises(ValidationError, match="horizontal and vertical: give both"):
        Alignment.model_validate({"horizontal": h})
    with pytest.raises(ValidationError, match="give either gradient_percent"):
        Alignment.model_validate(
            {
                "gradient_percent": 1.0,
                "horizontal": h,
                "vertical": {"elements": [{"start_chainage_m": 0, "gradient_percent": 1.0}]},
            }
        )


def test_the_straight_forms_are_unchanged() -> None:
    straight = Alignment(gradient_percent=-0.3)
    p = axis_pose(straight, 10.0)
    t = np.array([1.0, 0.0, -0.003]) / math.hypot(1.0, 0.003)
    assert p.position == pytest.approx(10.0 * t) and p.yaw == 0.0
    assert chainage_along(straight, 4.0, 2.0) == 6.0


# --------------------------------------------------------------------------- the parts' taper


def _on_curve(radius: float, taper_mm: float, grade: float = 0.0) -> ProjectConfig:
    cfg = load_project()
    tunnel = cfg.tunnel.model_copy(update={"alignment": _curve(radius, grade)})
    part = cfg.workpiece.model_copy(update={"taper_mm": taper_mm})
    return cfg.model_copy(update={"tunnel": tunnel, "workpiece": part})


def _design_gaps_mm(cfg: ProjectConfig, ring: int) -> np.ndarray:
    design = design_pose(cfg, ring)
    prev = to_ring_frame(cfg, design_pose(cfg, ring - 1), ring - 1, ring)
    d = design.apply(face_corners(cfg, front=False)) - prev.apply(face_corners(cfg, front=True))
    return np.asarray(units.to_mm(d[:, 0]))


@pytest.mark.parametrize("radius", [R, -R, 300.0])
def test_rectangular_parts_open_w_l_over_r_and_the_matching_taper_closes_it(
    radius: float,
) -> None:
    w, length = 2.0, 9.5
    opening = units.to_mm(w * length / abs(radius))  # 47.5 mm at 400 m
    gaps = _design_gaps_mm(_on_curve(radius, 0.0), 4)
    # corners (+y, -y) bottom and top: the outside of the curve opens, the inside overlaps
    assert gaps.max() - gaps.min() == pytest.approx(opening, rel=1e-3)
    outside = 1 if radius > 0 else 0
    assert gaps[outside] > 0 > gaps[1 - outside]
    # the taper that closes it has the sign of the radius: the inner end narrower
    closed = _design_gaps_mm(_on_curve(radius, math.copysign(opening, radius)), 4)
    assert np.ptp(closed) < 1e-3 * opening and abs(closed).max() < 1e-3 * opening
    wrong = _design_gaps_mm(_on_curve(radius, -math.copysign(opening, radius)), 4)
    assert np.ptp(wrong) == pytest.approx(2 * opening, rel=1e-3)


def test_a_tapered_parts_faces_are_its_width_less_taper_y_over_l() -> None:
    cfg = _on_curve(R, 40.0)
    front = face_points(cfg, [(4.75, 0.0), (-4.75, 0.0), (0.0, 1.0)])
    rear = face_points(cfg, [(4.75, 0.0), (-4.75, 0.0), (0.0, 1.0)], front=False)
    widths = front[:, 0] - rear[:, 0]
    assert widths == pytest.approx([2.0 - 0.02, 2.0 + 0.02, 2.0])  # left end narrower
    assert face_corners(cfg, front=True)[:, 0] == pytest.approx([0.99, 1.01, 0.99, 1.01])


def test_on_a_curve_the_target_yaw_follows_the_axis_and_tapered_parts_close_the_joint() -> None:
    cfg = _on_curve(R, 47.5, grade=3.0)
    plan = plan_from_deviation(cfg, 3, Pose())
    assert plan.feasible, plan.reasons
    # in the project frame the target's yaw is the axis's heading at the part's mid-width
    al = cfg.tunnel.alignment
    assert al is not None
    mid = chainage_along(al, ring_chainage_m(cfg, 3), 1.0)
    heading = axis_pose(al, mid).yaw
    assert compose(tunnel_frame(cfg, 3), plan.design).yaw == pytest.approx(heading, abs=1e-12)
    # the target: within the planner's evening of the gap (0.05 mm at the part's ends)
    assert compose(tunnel_frame(cfg, 3), plan.target).yaw == pytest.approx(heading, abs=2e-5)
    assert axis_pose(al, mid).yaw == pytest.approx(mid / R)
    t4 = plan.judged
    assert t4["min_gap_mm"]["value"] >= 0.0 and t4["min_gap_mm"]["passed"]
    assert t4["max_gap_mm"]["value"] <= cfg.acceptance.max_gap_mm
    assert t4["max_gap_mm"]["value"] - t4["min_gap_mm"]["value"] < 0.1


def test_rectangular_parts_on_a_curve_are_refused_naming_the_curve_and_the_taper() -> None:
    cfg = _on_curve(R, 0.0)
    plan = plan_from_deviation(cfg, 3, Pose())
    assert not plan.feasible
    assert plan.binding is not None and plan.binding.name.startswith(("max_gap", "no overlap"))
    assert plan.reasons[0].startswith(
        "the joint opens 47.5 mm on a 400 m curve to the left with rectangular parts "
        "(workpiece.taper_mm); a taper of 47.5 mm closes it: "
    )
    j = joint_opening(cfg, 3)
    assert j.radius_m == pytest.approx(R) and j.taper_needed_mm == pytest.approx(47.5, abs=0.01)
    # a part tapered the wrong way round: the curve to the right needs the negative taper
    wrong = plan_from_deviation(_on_curve(-R, 47.5), 3, Pose())
    assert (
        "the joint opens 95.0 mm on a 400 m curve to the right with parts tapered 47.5 mm"
        in (wrong.reasons[0])
    )
    assert "a taper of -47.5 mm closes it" in wrong.reasons[0]
    # a refusal that is no curve's doing says nothing of one
    straight = plan_from_deviation(load_project(), 3, Pose(y=units.mm(9.0)))
    assert not straight.feasible and "the joint opens" not in straight.reasons[0]


def test_a_survey_of_a_tapered_part_on_the_curve_fits_its_pose() -> None:
    """The survey's points on the front face lie on the tapered face (face_points): the
    fit recovers the part's pose in its ring's tunnel frame on the curve and the grade."""
    cfg = _on_curve(R, 47.5, grade=3.0)
    pose = design_pose(cfg, 4).deviated(Pose(0.0, 0.002, -0.001, 0.0, 0.0, units.deg(0.02)))
    faces = [(4.0, 0.3), (-4.0, 0.3), (3.5, 2.5), (-3.5, 2.5), (0.0, 1.4)]
    fit = fit_survey(cfg, 4, parse_survey_text(format_survey(cfg, 4, pose, faces)))
    assert fit.accepted, fit.reasons
    assert np.allclose(fit.pose, pose, atol=1e-4)
