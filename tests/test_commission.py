"""``wara commission``: the dossier of a project (docs/commissioning.md, decision 0027).

The metro example project in the quick form is fit (exit 0), its page self-contained
and its JSON listing every item with its verdict; a part too heavy for the supply and a
contradictory key are not fit (exit 1) with the item's reason naming the leg or the key,
and the other items still judged; a YAML that does not parse is exit 2 in one line. The
HFDU example project in the default form (3 steps, 4 rings, 20 campaign runs) is fit.
"""

from __future__ import annotations

import json
import re
from pathlib import Path
from typing import Any

import pytest
import yaml

from config import default_project_path
from config.loader import validate_data
from config.schema import ProjectConfig
from ipc_app.planner.walk import plan_walk
from tests.cli_helpers import run_main, run_wara
from wara.commission import (
    FIT,
    ITEMS,
    NOT_FIT,
    SKIPPED,
    Item,
    budgets,
    capacity,
    delay_margin,
    steered_start,
    worst_cases,
)
from wara.commission_runs import campaign_spec, cycle_steps, goal_rows

METRO = default_project_path().with_name("metro_light_part.yaml")


def metro_data() -> dict[str, Any]:
    data = yaml.safe_load(METRO.read_text(encoding="utf-8"))
    assert isinstance(data, dict)
    return data


def write(tmp_path: Path, name: str, data: dict[str, Any]) -> Path:
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return path


def heavy_data(mass_kg: float) -> dict[str, Any]:
    """The metro project with its part (the upper layer's body ``workpiece``) at
    ``mass_kg``."""
    data = metro_data()
    (part,) = [b for b in data["layers"]["upper"]["bodies"] if b["name"] == "workpiece"]
    part["mass_kg"] = mass_kg
    return data


def self_contained(page: str) -> list[str]:
    """What the page would fetch: every ``src``/``href`` that is not inline data or an
    anchor on the page, ``<link>`` and CSS ``url()``/``@import``."""
    found = [
        v
        for v in re.findall(r"""\b(?:src|href)\s*=\s*["']?([^"'\s>]+)""", page, re.I)
        if not (v.startswith("data:") or v.startswith("#"))
    ]
    found += re.findall(r"<link\b[^>]*>|@import|url\(", page, re.I)
    return found


# ------------------------------------------------------------------ in process, fast


def test_the_worst_cases_are_the_steepest_grades_of_the_alignment() -> None:
    data = metro_data()
    cfg = validate_data(ProjectConfig, data, "metro")
    cases = worst_cases(cfg)
    # as written (0.11 deg): the -0.2 % gradient's exact pitch (0.1146) is within the
    # cross-check's 0.01 deg of it, no case of its own
    assert len(cases) == 1
    data["base"]["pitch_deg"] = 0.1
    cases = worst_cases(validate_data(ProjectConfig, data, "metro"))
    assert cases[1].cfg.base.pitch_deg == pytest.approx(0.11459, abs=1e-4)
    data["base"]["pitch_deg"] = 0.11
    data["tunnel"]["alignment"] = {
        "points": [
            {"chainage_m": 0, "x_m": 0, "y_m": 0, "z_m": 0},
            {"chainage_m": 100, "x_m": 100, "y_m": 0, "z_m": 1.0},
            {"chainage_m": 200, "x_m": 200, "y_m": 0, "z_m": -2.0},
        ]
    }
    cfg = validate_data(ProjectConfig, data, "metro")
    pitches = sorted(c.cfg.base.pitch_deg for c in worst_cases(cfg)[1:])
    assert pitches == pytest.approx([-0.5729, 1.7180], abs=1e-3)  # +1 % and -3 %


def test_the_tightest_curve_is_a_worst_case_where_the_step_turns_its_most() -> None:
    """The curved example project: its 400 m arc (ring 1 on it) on the 3 % grade is a
    case, and there each step turns ``step / R`` plus the bounded correction, each way;
    the capacity item plans it (and a straight project has no such case)."""
    path = default_project_path().with_name("curved_grade_heavy_part.yaml")
    cfg = validate_data(ProjectConfig, yaml.safe_load(path.read_text(encoding="utf-8")), "c")
    (curve,) = [c for c in worst_cases(cfg) if c.curve is not None]
    radius, chainage = curve.curve
    assert radius == 400.0 and chainage == pytest.approx(2.0)  # one step in from ring 1
    assert curve.cfg.base.pitch_deg == pytest.approx(-1.7184, abs=1e-3)  # rising 3 %
    # the grades are those the rings lie on: the approach's 0.3 % behind ring 1 is no case
    assert [c.cfg.base.pitch_deg for c in worst_cases(cfg)][1:] == pytest.approx(
        [-1.7184], abs=1e-3
    )
    assert cfg.walking is not None
    most = cfg.walking.step_length_m / radius + cfg.walking.max_heading_correction_per_step_rad
    for direction, sign in (("forward", 1.0), ("back", -1.0)):
        w = plan_walk(curve.cfg, 1, steered_start(curve, direction), direction=direction)
        assert w.feasible
        assert w.turns[0].turn_rad == pytest.approx(sign * most, rel=1e-3)
    item = Item("capacity", "capacity")
    capacity(cfg, item)
    turning = [r for r in item.rows if r["case"] == curve.label and "turning" in r["plan"]]
    assert len(turning) == 2 and item.status == FIT
    metro = validate_data(ProjectConfig, metro_data(), "metro")
    assert all(c.curve is None for c in worst_cases(metro))


def test_a_part_too_heavy_for_the_supply_is_refused_by_the_capacity_item() -> None:
    """60 t on the metro machine: a standing sub leg needs more than the 16 MPa supply
    (the walk planner's refusal, as ``wara walk plan`` exits 3 with it)."""
    cfg = validate_data(ProjectConfig, heavy_data(60_000), "heavy")
    item = Item("capacity", "capacity")
    capacity(cfg, item)
    assert item.status == NOT_FIT
    assert any(re.search(r"walk 1 step \w+, loaded: .*sub_leg_\d needs \d+\.\d\d MPa", r)
               for r in item.reasons), item.reasons  # fmt: skip
    walk_rows = [r for r in item.rows if r["plan"].startswith("walk")]
    assert any(r["peak_mpa"] > r["limit_mpa"] == 16.0 for r in walk_rows)
    light = Item("capacity", "capacity")
    capacity(validate_data(ProjectConfig, metro_data(), "metro"), light)
    assert light.status == FIT and not light.reasons
    assert all(r["feasible"] and r["peak_mpa"] < r["limit_mpa"] for r in light.rows)


def test_a_cycle_budget_the_walks_fill_is_not_fit() -> None:
    data = metro_data()
    ok = Item("budgets", "budgets")
    budgets(validate_data(ProjectConfig, data, "metro"), ok)
    assert ok.status == FIT and ok.figures["left_s"] > 0
    data["cycle"]["max_cycle_time_min"] = 3.0  # the walks there and back take 3.3 min
    tight = Item("budgets", "budgets")
    budgets(validate_data(ProjectConfig, data, "metro"), tight)
    assert tight.status == NOT_FIT
    (reason,) = tight.reasons
    assert reason.startswith("cycle.max_cycle_time_min: 3 min leaves no time to place")


def test_the_campaign_spec_loads_for_the_project_and_draws_within_its_values() -> None:
    """The dossier's campaign (run by the default form, not here): a nominal spec of
    the project that `wara campaign run` loads; its dispersions factors of the project's
    own values; judged on the attitude goals."""
    from wara.campaign.spec import campaign_from_data

    cfg = validate_data(ProjectConfig, metro_data(), "metro")
    c = campaign_from_data(campaign_spec(cfg, str(METRO), 5), "commission", METRO.parent)
    assert c.run_count == 5 and c.spec.kind == "nominal"
    assert set(c.limits) == {"attitude_error_deg", "max_twist_mm", "sync_error_mm"}
    for i in range(5):
        params = c.draw(i).params
        part = params["layers.upper.bodies[0].mass_kg"] / cfg.workpiece_mass_kg
        assert 0.9 < part < 1.1
        bulk = params["hydraulics.bulk_modulus_mpa"] / cfg.hydraulics.bulk_modulus_mpa
        assert 0.6 <= bulk <= 1.0
        assert -3.0 <= params["target0_roll_deg"] <= 5.0


def test_a_loop_tuned_past_its_delay_margin_is_not_fit_naming_the_keys() -> None:
    data = metro_data()
    data["control"]["ladrc"].update({"wc_rad_s": 40.0, "wo_rad_s": 80.0})
    item = Item("delay-margin", "delay margin")
    delay_margin(validate_data(ProjectConfig, data, "metro"), item)
    assert item.status == NOT_FIT
    (reason,) = item.reasons
    assert reason.startswith("control.ladrc.wc_rad_s 40, control.ladrc.wo_rad_s 80: the ")
    assert any(r["breaks"] for r in item.rows) and not all(r["breaks"] for r in item.rows)


def test_the_cycles_walk_steps_are_judged_on_the_walks_goals() -> None:
    """`wara cycle` judges the rings; the dossier judges their walks' steps too, on the
    walk's goals that the steps' figures give."""
    cfg = validate_data(ProjectConfig, metro_data(), "metro")
    assert cfg.walking is not None
    step = {
        "index": 1, "duration_s": 90.0, "max_leg_sync_error_mm": 0.05,
        "max_travel_sync_error_mm": 0.004, "min_stability_margin_m": 0.9,
        "max_leg_force_ratio": 1.02, "transfer_time_s": 3.0,
    }  # fmt: skip
    over = {**step, "max_leg_force_ratio": cfg.walking.overload_percent / 100 + 0.01}
    rings = [{"ring": 2, "walks": {"walk": [step], "walk_back": [over]}}]
    judged = cycle_steps(cfg, rings)
    assert [j["passed"] for j in judged] == [True, False]
    assert judged[1]["missed"] == ["max_leg_force_ratio 1.11 > 1.1"]
    assert set(judged[0]["goals"]) == {
        "max_leg_sync_error_mm", "max_travel_sync_error_mm", "min_stability_margin_m",
        "max_leg_force_ratio", "max_step_duration_s",
    }  # fmt: skip
    (force,) = [r for r in goal_rows(judged, "step") if r["figure"] == "max_leg_force_ratio"]
    assert force["met"] is False and force["at"] == "step 1 of ring 2's walk_back"


# ------------------------------------------------------------------ the command


def test_a_yaml_that_does_not_parse_is_exit_2_in_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("project: {name: [unclosed\n", encoding="utf-8")
    run = run_wara(["commission", str(bad), "--quick", "--out", str(tmp_path / "o")])
    assert run.returncode == 2, run.stderr
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "bad.yaml: YAML syntax error" in lines[0], lines
    assert not (tmp_path / "o").exists()  # refused before anything was written


def test_bad_arguments_are_exit_2_in_one_line(tmp_path: Path) -> None:
    a_file = tmp_path / "a_file"
    a_file.write_text("", encoding="utf-8")
    for args, want in [
        (["--out", str(a_file)], f"--out {a_file}: File exists"),
        (["--out", str(tmp_path / "o"), "--rings", "0"], "--rings must be within 1..50, got 0"),
        (["--out", str(tmp_path / "o"), "--runs", "-1"], "--runs must be within 0..10000"),
    ]:
        code, out, err = run_main(["commission", str(METRO), "--quick", *args])
        assert (code, out) == (2, ""), err
        (line,) = err.splitlines()
        assert line.startswith(f"wara commission: error: {want}"), err


@pytest.mark.slow
def test_a_contradictory_key_is_not_fit_naming_it_the_other_items_judged(
    tmp_path: Path,
) -> None:
    data = metro_data()
    data["base"]["pitch_deg"] = 1.0  # the alignment's -0.2 % is 0.1146 deg
    path = write(tmp_path, "contradictory.yaml", data)
    out = tmp_path / "dossier"
    code, stdout, err = run_main(["commission", str(path), "--quick", "--quiet", "--out", str(out)])
    assert code == 1, err
    assert re.search(r"^cross-checks +not fit +: base\.pitch_deg", stdout, re.M), stdout
    lines = [ln for ln in err.splitlines() if ln.startswith("wara commission: not fit: ")]
    assert lines[0].startswith("wara commission: not fit: cross-checks: base.pitch_deg: 1 deg")
    d = json.loads((out / "commission.json").read_text())
    status = {i["name"]: i["status"] for i in d["items"]}
    assert status["cross-checks"] == NOT_FIT and d["fit"] is False
    # judged on the schema-valid project all the same
    assert status["capacity"] == status["delay-margin"] == status["budgets"] == FIT
    # the service loads no such project: the runs are not made, and say why
    assert status["walk"] == status["cycle"] == NOT_FIT
    assert status["delay-hold"] == status["campaign"] == SKIPPED  # --quick
    assert "see cross-checks" in d["items"][ITEMS.index("walk")]["reasons"][0]


@pytest.fixture(scope="module")
def metro_dossier(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, str, str, Path]:
    out = Path(tmp_path_factory.mktemp("commission")) / "dossier"
    run = run_wara(["commission", str(METRO), "--quick", "--out", str(out)], timeout_s=1800)
    return run.returncode, run.stdout, run.stderr, out


@pytest.mark.slow(seconds=120)
@pytest.mark.xdist_group("commission_metro")
def test_the_metro_project_is_fit_to_commission(
    metro_dossier: tuple[int, str, str, Path],
) -> None:
    """`wara commission metro_light_part.yaml --quick`: exit 0, one self-contained page,
    the JSON with each item and its verdict; the progress line on stderr."""
    code, stdout, err, out = metro_dossier
    assert code == 0, (stdout, err[-3000:])
    assert "FIT to commission" in stdout
    assert re.search(r"\] 8/8 elapsed \d+m\d\ds, not fit 0", err), err[-2000:]
    page = (out / "commission.html").read_text(encoding="utf-8")
    assert self_contained(page) == []
    assert page.count("data:image/png;base64,") >= 3  # capacity, walk, cycle
    d = json.loads((out / "commission.json").read_text())
    assert d["fit"] is True and d["not_fit"] == []
    assert [i["name"] for i in d["items"]] == list(ITEMS)
    status = {i["name"]: i["status"] for i in d["items"]}
    assert status == {**dict.fromkeys(ITEMS, FIT), "delay-hold": SKIPPED, "campaign": SKIPPED}
    walk = d["items"][ITEMS.index("walk")]
    assert walk["figures"]["steps"] == 1 and walk["figures"]["passed"] is True
    assert {r["figure"] for r in walk["rows"]} >= {
        "max_leg_force_ratio",
        "max_step_duration_s",
        "the walk's distance_error_mm",  # the whole walk's goals, beside its steps'
        "the walk's heading_error_deg",
    }
    assert abs(walk["figures"]["heading_error_deg"]) < 0.05
    cycle = d["items"][ITEMS.index("cycle")]
    assert len(cycle["figures"]["cycle_time_s"]) == 1 and cycle["figures"]["passed"] is True


@pytest.mark.slow(seconds=300)
def test_the_hfdu_project_in_the_default_form_is_fit_to_commission(tmp_path: Path) -> None:
    """`wara commission shanghai_hfdu_power_unit.yaml` as the docs give it (3 steps, 4
    rings, a 20-run campaign, the delay hold): exit 0, every item fit, the figures of the
    form asked for (its unloaded walks back at the touch-downs: decision 0031)."""
    hfdu = default_project_path().with_name("shanghai_hfdu_power_unit.yaml")
    out = tmp_path / "dossier"
    run = run_wara(["commission", str(hfdu), "--quiet", "--out", str(out)], timeout_s=1800)
    assert run.returncode == 0, (run.stdout[-3000:], run.stderr[-3000:])
    d = json.loads((out / "commission.json").read_text())
    assert d["fit"] is True and d["not_fit"] == []
    assert {i["name"]: i["status"] for i in d["items"]} == dict.fromkeys(ITEMS, FIT)
    fig = {i["name"]: i["figures"] for i in d["items"]}
    assert fig["walk"]["steps"] == 3 and fig["walk"]["passed"] is True
    assert len(fig["cycle"]["cycle_time_s"]) == 4 and fig["cycle"]["passed"] is True
    assert fig["campaign"]["verdict"]["runs"] == 20
    assert fig["campaign"]["status_counts"] == {"passed": 20}


@pytest.mark.slow
@pytest.mark.xdist_group("commission_metro")
def test_the_dossier_opens_in_a_browser(
    metro_dossier: tuple[int, str, str, Path], tmp_path: Path
) -> None:
    """The acceptance report's headless-browser check on the dossier (skipped without
    Chromium)."""
    from tests import test_acceptance_browser as browser

    if browser._browser() is None:
        pytest.skip("no headless Chromium on this machine (Debian: apt-get install -y chromium)")
    _code, _out, _err, out = metro_dossier
    dom, console = browser._open_in_browser(out / "commission.html", tmp_path / "profile")
    assert console == [], console
    assert browser._check(dom) == "ok"


@pytest.mark.slow
def test_a_part_too_heavy_for_the_supply_is_exit_1_naming_the_leg(tmp_path: Path) -> None:
    path = write(tmp_path, "heavy.yaml", heavy_data(60_000))
    out = tmp_path / "dossier"
    run = run_wara(["commission", str(path), "--quick", "--out", str(out)], timeout_s=900)
    assert run.returncode == 1, run.stderr[-2000:]
    capacity_lines = [
        ln for ln in run.stderr.splitlines() if ln.startswith("wara commission: not fit: capacity:")
    ]
    assert capacity_lines and all("sub_leg_" in ln for ln in capacity_lines), capacity_lines
    assert all("MPa" in ln and "supply" in ln for ln in capacity_lines)
    d = json.loads((out / "commission.json").read_text())
    status = {i["name"]: i["status"] for i in d["items"]}
    assert status["capacity"] == NOT_FIT and status["cross-checks"] == FIT
    assert status["walk"] == NOT_FIT  # the service refuses the walk the planner refuses
    page = (out / "commission.html").read_text(encoding="utf-8")
    assert "NOT fit to commission" in page and "sub_leg_" in page
