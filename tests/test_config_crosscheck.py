"""The cross-checks between keys (config/crosscheck.py): each refuses a project that
breaks it, in one line naming both keys; the shipped projects keep every one; the docs
table lists them all."""

from __future__ import annotations

import copy
import itertools
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

import ipc_app.model.statics
import ipc_app.model.support
import plc_bridge.busload
from config import ConfigError, crosscheck, load_project
from config.loader import default_project_path
from wara.cli import main

REPO = Path(__file__).resolve().parents[1]
PROJECTS = sorted((REPO / "config" / "projects").glob("*.yaml"))
SHIPPED: dict[str, Any] = yaml.safe_load(default_project_path().read_text(encoding="utf-8"))

Edit = Callable[[dict[str, Any]], None]


def _set(path: str, value: Any) -> Edit:
    def edit(d: dict[str, Any]) -> None:
        *head, last = path.split(".")
        for k in head:
            d = d[k]
        d[last] = value

    return edit


def _add_workpiece_mass(mass: float) -> Edit:
    return _set("workpiece.mass_kg", mass)


def _pitch_table(d: dict[str, Any]) -> None:
    """A points table rising 1 m in 100 m (-0.573 deg of base pitch) with the shipped
    +0.17 deg pitch."""
    d["tunnel"]["alignment"] = {
        "points": [
            {"chainage_m": 0.0, "x_m": 0.0, "y_m": 0.0, "z_m": 0.0},
            {"chainage_m": 100.0, "x_m": 100.0, "y_m": 0.0, "z_m": 1.0},
        ]
    }


def _axis(
    radius_m: float,
    taper_mm: float,
    grades: tuple[float, ...] = (-0.3,),
    vertical_radius_m: float = 2000.0,
) -> Edit:
    """The axis by chainage: a straight to chainage 0 (behind ring 1), then an arc of
    ``radius_m``; ``grades`` from chainage -50, each joined to the next by a vertical curve
    of ``vertical_radius_m`` from chainage 100 (the first is the shipped -0.3 %: the
    shipped base pitch); parts tapered ``taper_mm``."""

    def edit(d: dict[str, Any]) -> None:
        vertical: list[dict[str, float]] = [
            {"start_chainage_m": -50.0, "gradient_percent": grades[0]}
        ]
        at = 100.0
        for g0, g1 in itertools.pairwise(grades):
            vertical.append({"start_chainage_m": at, "radius_m": vertical_radius_m})
            at += vertical_radius_m * abs(g1 - g0) / 100.0
            vertical.append({"start_chainage_m": at, "gradient_percent": g1})
            at += 100.0
        d["tunnel"]["alignment"] = {
            "horizontal": {
                "x_m": -50.0,
                "elements": [
                    {"start_chainage_m": -50.0, "kind": "straight"},
                    {"start_chainage_m": 0.0, "kind": "arc", "radius_m": radius_m},
                ],
            },
            "vertical": {"elements": vertical},
        }
        d["workpiece"]["taper_mm"] = taper_mm

    return edit


#: rule -> (a change to the shipped project that breaks it, the keys its line names)
BREAKS: dict[str, tuple[Edit, tuple[str, ...]]] = {
    "pressure-limit-within-rating": (
        _set("safety.max_pressure_mpa", 60),
        ("safety.max_pressure_mpa", "hydraulics.rated_pressure_mpa"),
    ),
    "supply-within-rating": (
        _set("hydraulics.supply_pressure_mpa", 25.5),
        ("hydraulics.supply_pressure_mpa", "hydraulics.rated_pressure_mpa"),
    ),
    "stroke-end-margin-within-stroke": (
        _set("safety.stroke_end_margin_mm", 100),
        ("safety.stroke_end_margin_mm", "cylinders[14].stroke_mm", "rotation_1"),
    ),
    "bus-load-within-budget": (
        _set("control.loop_rate_hz", 2000),
        ("can.max_bus_load_percent", "control.loop_rate_hz", "can.bitrate"),
    ),
    "static-pressure-within-limit": (
        _set("safety.max_pressure_mpa", 9.0),
        ("safety.max_pressure_mpa", "layers.*.bodies", "frames.*.bodies", "main_leg_2"),
    ),
    "step-divides-the-ring": (
        _set("walking.step_length_mm", 1500),
        ("walking.step_length_mm", "tunnel.ring_width_m"),
    ),
    "workpiece-mass-is-its-body": (
        _add_workpiece_mass(30000),
        ("workpiece.mass_kg", "layers.upper.bodies[0].mass_kg"),
    ),
    "robot-mass-is-its-bodies": (
        _set("robot.mass_kg", 30000),
        ("robot.mass_kg", "layers.lower.bodies", "frames.sub.bodies"),
    ),
    "base-pitch-is-the-gradient": (
        _set("base.pitch_deg", -0.17),
        ("base.pitch_deg", "tunnel.alignment.gradient_percent"),
    ),
    "rods-within-their-bodies": (
        _set("hydraulics.rod_mass_kg", 1600),
        ("hydraulics.rod_mass_kg", "layers.upper.bodies", "upper_attitude"),
    ),
    "radius-within-the-taper": (
        _set("workpiece.taper_mm", 20),
        ("tunnel.alignment.gradient_percent", "workpiece.taper_mm", "acceptance.max_gap_mm"),
    ),
    "radius-the-machine-takes": (
        _axis(100.0, 190.0),
        (
            "tunnel.alignment.horizontal.elements[1].radius_m",
            "walking.max_yaw_deg",
            "walking.step_length_mm",
        ),
    ),
    "grade-the-machine-takes": (
        _axis(400.0, 47.5, (-0.3, -6.0)),
        ("tunnel.alignment.vertical.elements[2].gradient_percent",),
    ),
    "vertical-curve-the-machine-takes": (
        _axis(400.0, 47.5, (-0.3, 0.3), vertical_radius_m=1000.0),  # 11.5 mm at 4.8 m
        (
            "tunnel.alignment.vertical.elements[1].radius_m",
            "walking.touchdown_travel_mm",
            "layers.lower.half_span_x_m",
            "walking.step_length_mm",
        ),
    ),
    "legs-within-the-envelope": (
        _set("robot.length_mm", 5700),
        ("frames.sub.half_span_x_m", "robot.length_mm", "walking.step_length_mm"),
    ),
    "envelope-fits-the-tunnel": (
        _set("tunnel.inner_diameter_m", 3.5),
        ("robot.width_mm", "robot.height_mm", "tunnel.inner_diameter_m"),
    ),
}


def _write(tmp_path: Path, edit: Edit) -> Path:
    d = copy.deepcopy(SHIPPED)
    edit(d)
    path = tmp_path / "project.yaml"
    path.write_text(yaml.safe_dump(d, sort_keys=False), encoding="utf-8")
    return path


def test_every_rule_has_a_breaking_case_and_a_check() -> None:
    assert set(BREAKS) == {r.name for r in crosscheck.RULES}
    assert all(crosscheck.check_of(r) is not None for r in crosscheck.RULES)
    # the two provided checks come from their modules (imported above)
    assert crosscheck.check_of(crosscheck.RULES[3]) is plc_bridge.busload.check_bus_load
    assert crosscheck.check_of(crosscheck.RULES[4]) is ipc_app.model.support.check_static_pressure


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_a_project_that_breaks_the_rule_is_refused(name: str, tmp_path: Path) -> None:
    edit, keys = BREAKS[name]
    path = _write(tmp_path, edit)
    with pytest.raises(ConfigError) as exc:
        load_project(path)
    lines = str(exc.value).splitlines()
    assert len(lines) == 1, lines
    (line,) = lines
    assert line.startswith(f"{path}: {keys[0]}: "), line
    assert all(k in line for k in keys), line
    assert "expected" in line, line


@pytest.mark.parametrize("name", sorted(BREAKS))
def test_config_validate_refuses_it_in_one_line_exit_2(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    edit, keys = BREAKS[name]
    path = _write(tmp_path, edit)
    code = main(["config", "validate", str(path)])
    out, err = capsys.readouterr()
    assert code == 2 and out == ""
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(f"wara: configuration error: {path}: {keys[0]}: "), err
    assert all(k in lines[0] for k in keys), err


def test_the_issues_examples() -> None:
    """The figures the issue names: 60 MPa on a 25 MPa rating; a margin longer than the
    stroke; the bus at 1 287 % (2000 Hz on 125 kbit/s); a limit below the static load."""
    cfg = load_project()
    safety, hyd = cfg.safety, cfg.hydraulics

    def with_(**sections: Any) -> Any:
        return cfg.model_copy(update=sections)

    over = with_(safety=safety.model_copy(update={"max_pressure_mpa": 60.0}))
    assert "expected at most 25" in crosscheck.problems(over)[0]
    long = with_(safety=safety.model_copy(update={"stroke_end_margin_mm": 250.0}))
    assert "cylinder rotation_1" in crosscheck.problems(long)[0]
    bus = with_(
        control=cfg.control.model_copy(update={"loop_rate_hz": 2000.0}),
        can=cfg.can.model_copy(update={"bitrate": 125_000}),
    )
    assert plc_bridge.busload.bus_load(bus).load_percent > 1000
    (line,) = crosscheck.problems(bus)
    assert re.search(r"to 12\d\d\.\d %", line), line
    assert crosscheck.problems(
        with_(hydraulics=hyd.model_copy(update={"supply_pressure_mpa": 30.0}))
    )
    low = with_(safety=safety.model_copy(update={"max_pressure_mpa": 6.0}))
    assert "static load pressure of cylinder main_leg_2" in crosscheck.problems(low)[0]


def test_the_shipped_projects_keep_every_rule() -> None:
    assert PROJECTS
    for path in PROJECTS:
        assert crosscheck.problems(load_project(path)) == [], path


def test_the_shipped_margins() -> None:
    """What the shipped values give: the limits the rules hold them to."""
    cfg = load_project()
    assert plc_bridge.busload.bus_load(cfg).load_percent == pytest.approx(44.46, abs=0.01)
    # at boot M's legs carry the whole machine (the frames too): 9.44 MPa at most (the
    # layers' statics alone, model.md's, give 7.48)
    boot = ipc_app.model.support.boot_cap_pressures_pa(cfg)
    assert max(boot.values()) / 1e6 == pytest.approx(9.44, abs=0.01)
    home = ipc_app.model.statics.home_cap_pressures_pa(cfg)
    assert max(home.values()) / 1e6 == pytest.approx(7.48, abs=0.01)
    assert cfg.workpiece.mass_kg is None and cfg.workpiece_mass_kg == 36350
    assert crosscheck.gradient_pitch_deg(-0.3) == pytest.approx(0.1719, abs=1e-4)
    assert crosscheck.machine_bodies_kg(cfg) == cfg.robot.mass_kg == 35000


def test_whole_fractions_of_the_ring_are_steps(tmp_path: Path) -> None:
    """One step a ring or a whole fraction of one (the short walks of the tests: 200 mm)."""
    for step in (2000, 1000, 500, 200, 2000.5):
        load_project(_write(tmp_path, _set("walking.step_length_mm", step)))
    for step in (1500, 1998, 900):
        with pytest.raises(ConfigError, match=r"walking\.step_length_mm"):
            load_project(_write(tmp_path, _set("walking.step_length_mm", step)))


def test_the_pitch_against_a_points_table(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"base\.pitch_deg: .*tunnel\.alignment\.points"):
        load_project(_write(tmp_path, _pitch_table))

    def level(d: dict[str, Any]) -> None:
        _pitch_table(d)
        d["base"]["pitch_deg"] = -0.5729

    load_project(_write(tmp_path, level))


def test_the_workpiece_mass_is_its_bodys(tmp_path: Path) -> None:
    cfg = load_project(_write(tmp_path, _add_workpiece_mass(36350.4)))
    assert cfg.workpiece_mass_kg == 36350

    def no_body(d: dict[str, Any]) -> None:
        d["layers"]["upper"]["bodies"] = [
            b for b in d["layers"]["upper"]["bodies"] if b["name"] != "workpiece"
        ]

    with pytest.raises(ConfigError, match=r"workpiece\.mass_kg: give it, or a body named"):
        load_project(_write(tmp_path, no_body))

    def no_body_but_the_key(d: dict[str, Any]) -> None:
        no_body(d)
        d["workpiece"]["mass_kg"] = 36350

    assert load_project(_write(tmp_path, no_body_but_the_key)).workpiece_mass_kg == 36350


def test_can_busload_reports_the_bus_rule_itself(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = _write(tmp_path, _set("control.loop_rate_hz", 2000))
    assert main(["can", "busload", "--config", str(path)]) == 1
    assert "OVER BUDGET" in capsys.readouterr().out
    other = _write(tmp_path, _set("safety.max_pressure_mpa", 60))
    assert main(["can", "busload", "--config", str(other)]) == 2
    assert "safety.max_pressure_mpa" in capsys.readouterr().err


def test_the_docs_table_lists_every_rule() -> None:
    text = (REPO / "docs" / "config.md").read_text(encoding="utf-8")
    m = re.search(r"<!-- crosscheck-table -->\n(.*?)<!-- /crosscheck-table -->", text, re.S)
    assert m is not None, "docs/config.md: the cross-check table's markers"
    assert m.group(1) == crosscheck.docs_table(), "regenerate: crosscheck.docs_table()"
    for rule in crosscheck.RULES:
        assert f"| `{rule.name}` |" in m.group(1)


def test_a_provider_must_be_the_rules() -> None:
    with pytest.raises(ValueError, match="no cross-check"):
        crosscheck.provide("bus-load-within-budget", "somewhere.else")
    with pytest.raises(ValueError, match="no cross-check"):
        crosscheck.problems(load_project(), skip=("no-such-rule",))


def test_a_retired_key_says_where_its_fact_comes_from(tmp_path: Path) -> None:
    """One key a fact: the part's reference height follows from the inner diameter, the
    lining's outer diameter governs nothing; a file that still gives them is told so."""

    def old(d: dict[str, Any]) -> None:
        d["tunnel"]["outer_diameter_m"] = 13.6
        d["placement"]["reference_height_m"] = -6.25

    path = _write(tmp_path, old)
    with pytest.raises(ConfigError) as exc:
        load_project(path)
    lines = str(exc.value).splitlines()
    assert lines == [
        f"{path}: tunnel.outer_diameter_m: no longer a key: the lining's outer diameter "
        "governs nothing of the machine; leave it out",
        f"{path}: placement.reference_height_m: no longer a key: a part's reference height "
        "is on the invert, derived from tunnel.inner_diameter_m (the inner radius below the "
        "axis); leave it out",
    ]
    assert load_project().reference_height_m == -6.25


def test_the_assembly_time_is_what_a_plan_states_its_solve_time_against() -> None:
    """The paper's Table 2: a solve time as a share of the 5 min assembly task."""
    from ipc_app.planner import plan

    cfg = load_project()
    p = plan(cfg, 2.0, 1.0).to_dict()
    assert p["solve_time_share_of_task_percent"] == pytest.approx(100 * p["solve_time_s"] / 300.0)
    longer = cfg.model_copy(update={"task": cfg.task.model_copy(update={"assembly_time_min": 10})})
    q = plan(longer, 2.0, 1.0).to_dict()
    assert q["solve_time_share_of_task_percent"] == pytest.approx(100 * q["solve_time_s"] / 600.0)


def test_the_envelope_rules_on_other_machines(tmp_path: Path) -> None:
    """The legs within the envelope (a wider sub frame, a longer step); the envelope
    through the parts (a machine taller than the part)."""
    cases = [
        (_set("frames.sub.half_span_y_m", 1.7), r"frames\.sub\.half_span_y_m: 1\.7 m .*width"),
        (_set("walking.step_length_mm", 2000.0), None),
        (_set("robot.height_mm", 2900), r"robot\.height_mm: 2900 mm is not below the part"),
        (_set("robot.width_mm", 9600), r"robot\.width_mm: 9600 mm is not below the part"),
    ]
    for edit, pattern in cases:
        path = _write(tmp_path, edit)
        if pattern is None:
            load_project(path)
            continue
        with pytest.raises(ConfigError, match=pattern):
            load_project(path)
