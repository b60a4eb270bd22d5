"""Capacity: every planner holds a cylinder to what the supply gives
(:mod:`ipc_app.planner.capacity`), not to its rating: the supply less the load-sensing
margin for a cylinder that moves its load, the supply for one that holds it (a walk's
standing legs); a plan that needs more is refused at plan time naming the cylinder, its
force, the pressure it needs and what the supply gives (exit 3 on the CLI). The walk
plan's force ramps in kN."""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from config import ProjectConfig, default_project_path, load_project, units
from ipc_app.model.placement import Pose
from ipc_app.planner import plan
from ipc_app.planner.capacity import available_pressure_pa, pressure_limit_pa, pressure_reason
from ipc_app.planner.placement import plan_from_deviation
from ipc_app.planner.walk import RAMP_PHASES, plan_walk
from tests.cli_helpers import run_main

#: the refusal's wording: the cylinder, its force, the pressure it needs, what the supply
#: gives a cylinder that moves its load (the shipped 16 MPa less 1.5)
REASON = re.compile(
    r"pressure: .*\b(?P<cid>(main|sub)_leg_\d|upper_\d)\)? needs (?P<mpa>\d+\.\d\d) MPa for "
    r"(?P<kn>\d+\.\d) kN, above the 14\.50 MPa the supply gives \(16 MPa supply less the "
    r"1\.5 MPa load-sensing margin\)"
)
#: ... and one that holds it (a walk's standing leg: the supply itself)
HOLD_REASON = re.compile(
    r"\b(?P<cid>(main|sub)_leg_\d) needs (?P<mpa>\d+\.\d\d) MPa for (?P<kn>\d+\.\d) kN to "
    r"hold its load, above the 16\.00 MPa the supply gives a standing cylinder \(the 16 MPa "
    r"supply itself\)"
)


def heavy_data(mass_kg: float) -> dict[str, Any]:
    """The shipped project's data with the part at ``mass_kg``: the workpiece section
    and the upper layer's body ``workpiece`` (what the statics carry)."""
    data = yaml.safe_load(default_project_path().read_text())
    data["workpiece"]["mass_kg"] = mass_kg
    bodies = data["layers"]["upper"]["bodies"]
    (part,) = [b for b in bodies if b["name"] == "workpiece"]
    part["mass_kg"] = mass_kg
    return data


def heavy(tmp_path: Path, mass_kg: float) -> tuple[Path, ProjectConfig]:
    path = tmp_path / f"part_{mass_kg:.0f}kg.yaml"
    path.write_text(yaml.safe_dump(heavy_data(mass_kg), sort_keys=False))
    return path, load_project(path)


def test_a_moving_cylinder_gets_the_supply_less_the_margin_a_holding_one_the_supply() -> None:
    cfg = load_project()
    h = cfg.hydraulics
    assert available_pressure_pa(h, "moves") == pytest.approx(units.mpa(16.0 - 1.5))
    assert available_pressure_pa(h, "holds") == pytest.approx(units.mpa(16.0))
    for duty in ("moves", "holds"):  # both below the 25 MPa rating and the 24 MPa interlock
        assert pressure_limit_pa(cfg, duty) == available_pressure_pa(h, duty)
    rated_low = cfg.model_copy(
        update={"hydraulics": h.model_copy(update={"rated_pressure_mpa": 15.0})}
    )
    assert pressure_limit_pa(rated_low, "moves") == pytest.approx(units.mpa(14.5))
    assert pressure_limit_pa(rated_low, "holds") == pytest.approx(units.mpa(15.0))
    why = pressure_reason(rated_low, "sub_leg_1", 311e3, units.mpa(15.47), "holds")
    assert why == "pressure: sub_leg_1 needs 15.47 MPa for 311.0 kN, above its rated 15 MPa"
    assert pressure_reason(cfg, "sub_leg_1", 311e3, units.mpa(15.47), "holds") is None
    assert REASON.search(str(pressure_reason(cfg, "upper_1", 311e3, units.mpa(15.47))))
    # the pressure interlock's limit binds where it is the lowest
    tripping = cfg.model_copy(
        update={"safety": cfg.safety.model_copy(update={"max_pressure_mpa": 13.0})}
    )
    assert pressure_limit_pa(tripping, "holds") == pytest.approx(units.mpa(13.0))
    why = pressure_reason(tripping, "sub_leg_1", 270e3, units.mpa(13.43), "holds")
    assert why == (
        "pressure: sub_leg_1 needs 13.43 MPa for 270.0 kN, above the pressure interlock's "
        "13 MPa (safety.max_pressure_mpa)"
    )


def test_the_shipped_plans_keep_within_what_the_supply_gives() -> None:
    cfg = load_project()
    limit = available_pressure_pa(cfg.hydraulics)
    att = plan(cfg, -3.0, 2.0)
    assert att.feasible and att.peak_pressure_pa < 0.6 * limit
    walk = plan_walk(cfg, 1)
    assert walk.feasible
    place = plan_from_deviation(cfg, 2, Pose())
    assert place.feasible
    limits = {a.group: a.pressure_limit_mpa for a in place.actuators}
    assert set(limits.values()) == {14.5}  # legs, upper cylinders and slide axes alike


@pytest.mark.parametrize(
    ("mass_kg", "phase", "mpa"), [(60_000, "4", 17.21), (80_000, "4", 21.10), (52_000, "5", 16.47)]
)
def test_the_walk_planner_refuses_a_part_the_supply_cannot_carry(
    tmp_path: Path, mass_kg: float, phase: str, mpa: float
) -> None:
    """A standing sub leg needs more than the 16 MPa supply (the plan's largest leg
    pressure 18.2 MPa at 60 t, 22.3 MPa at 80 t, within the 25 MPa rating): refused at plan
    time, at the first violation along the plan, naming the leg."""
    path, cfg = heavy(tmp_path, mass_kg)
    walk = plan_walk(cfg, 1)
    ref = walk.refusal
    assert ref is not None and ref.constraint == "pressure" and ref.phase == phase
    m = HOLD_REASON.search(ref.message)
    assert m is not None, ref.message
    assert m["cid"] == "sub_leg_2" and float(m["mpa"]) == mpa
    cap = cfg.cylinder("sub_leg_2").cap_area_m2
    assert float(m["mpa"]) == pytest.approx(float(m["kn"]) * 1e3 / cap / 1e6, abs=0.01)
    assert ref.limit == pytest.approx(units.mpa(16.0))
    code, out, _ = run_main(["walk", "plan", "--steps", "1", "--config", str(path), "--json"])
    assert code == 3
    d = json.loads(out)
    assert d["feasible"] is False and HOLD_REASON.search(d["refusal"]["message"])


def test_a_standing_leg_holds_up_to_the_supply(tmp_path: Path) -> None:
    """A 45 t part: the standing legs hold up to 15.1 MPa (S's while M is preloaded), above
    the 14.5 MPa a moving cylinder gets, within the 16 MPa supply (no flow to meter): the
    walk plans. The legs that move (lifted, lowered) carry their feet only."""
    _path, cfg = heavy(tmp_path, 45_000)
    walk = plan_walk(cfg, 1)
    assert walk.feasible, walk.refusal
    peak = max(float((ph.leg_forces_n / cfg.cylinder("sub_leg_2").cap_area_m2).max())
               for ph in walk.phases)  # fmt: skip
    assert units.mpa(14.5) < peak < units.mpa(16.0)


def test_the_attitude_planner_refuses_a_target_the_supply_cannot_reach(tmp_path: Path) -> None:
    """80 t at roll -5, pitch -5 deg: main_leg_2 needs 14.56 MPa (the old check passed it,
    16.1 MPa and more within reach). The attitude statics carry the layers' bodies only
    (not M's and S's frames), so a 60 t part needs at most 12.9 MPa within +-8 deg."""
    path, cfg = heavy(tmp_path, 80_000)
    p = plan(cfg, -5.0, -5.0)
    assert not p.feasible
    found = [m for r in p.reasons if (m := REASON.search(r))]
    assert [m["cid"] for m in found] == ["main_leg_2"], p.reasons
    code, out, _ = run_main(
        ["plan", "--roll-deg", "-5", "--pitch-deg", "-5", "--config", str(path), "--json"]
    )
    assert code == 3
    assert any(REASON.search(r) for r in json.loads(out)["reasons"])


def test_the_placement_planner_refuses_a_move_the_supply_cannot_make(tmp_path: Path) -> None:
    """The placement's attitude is within a few hundredths of a degree of the base: its
    legs reach what the supply gives only at about 95 t (13.4 MPa at 80 t)."""
    path, cfg = heavy(tmp_path, 100_000)
    p = plan_from_deviation(cfg, 2, Pose())
    assert not p.feasible
    assert any(REASON.search(r) for r in p.reasons), p.reasons
    lower = p.actuators[0]
    assert lower.pressure_mpa is not None and lower.pressure_mpa > 14.5
    assert lower.pressure_limit_mpa == 14.5 and lower.reasons
    code, out, _ = run_main(["place", "plan", "--config", str(path), "--json"])
    assert code == 3
    assert any(REASON.search(r) for r in json.loads(out)["reasons"])


def test_the_walk_plans_force_ramps_are_written_in_kn() -> None:
    cfg = load_project()
    walk = plan_walk(cfg, 1)
    phases = walk.to_dict()["phases"]
    ramps = [p for p in phases if p["phase"] in RAMP_PHASES]
    assert {p["phase"] for p in ramps} == {"3", "4", "7b", "7c"}
    for p in ramps:
        assert "start_mm" not in p and "end_mm" not in p
        assert len(p["start_kn"]) == len(p["end_kn"]) == len(p["moving"]) == 8
        assert all(0.0 <= f < 400.0 for f in p["start_kn"] + p["end_kn"])  # kN, not N
    # preload S: the sub legs from nothing to their preload, the whole weight carried
    pre = next(p for p in ramps if p["phase"] == "3")
    assert pre["start_kn"][4:] == [0.0] * 4 and min(pre["end_kn"][4:]) > 10.0
    weight_kn = sum(pre["end_kn"])
    assert weight_kn == pytest.approx(sum(pre["start_kn"]), rel=1e-6)
    assert weight_kn == pytest.approx(sum(pre["leg_forces_end_kn"].values()), abs=0.05)
    moves = [p for p in phases if p["phase"] not in RAMP_PHASES]
    assert all("start_mm" in p and "start_kn" not in p for p in moves)
    travel = next(p for p in moves if p["phase"] == "1")
    assert travel["start_mm"] == [-1000.0, -1000.0] and travel["end_mm"] == [1000.0, 1000.0]
