"""Campaign specs, draws, the results directory and the report, without a cluster
(test_campaign_dask.py runs campaigns on a real LocalCluster)."""

from __future__ import annotations

import copy
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from config import ConfigError
from tests.campaign_helpers import SMALL_SPEC, write_spec
from tests.cli_helpers import REPO, run_main
from wara.campaign.engine import (
    compact,
    done_indices,
    payload_of,
    read_results,
    write_manifest,
    write_row,
)
from wara.campaign.report import lower_bound, percentile_figure, summary, write_html
from wara.campaign.spec import load_campaign, zero_failure_runs


def _spec(**changes: Any) -> dict[str, Any]:
    data = copy.deepcopy(SMALL_SPEC)
    data.update(changes)
    return data


def _event(kind: str, **fields: Any) -> dict[str, Any]:
    return {
        "event": {"kind": kind, **fields},
        "start_s": {"dist": "uniform", "low": 1, "high": 2},
        "duration_s": {"dist": "uniform", "low": 0.5, "high": 1},
    }


def test_zero_failure_run_counts() -> None:
    assert zero_failure_runs(0.99, 0.95) == 299
    assert zero_failure_runs(0.9973, 0.90) == 852
    assert zero_failure_runs(0.9, 0.9) == 22


def test_the_shipped_spec_asks_for_299_runs() -> None:
    c = load_campaign(REPO / "config" / "campaigns" / "shanghai_airport_link.yaml")
    assert c.run_count == 299
    assert c.project_file.endswith("shanghai_airport_link.yaml")


def test_lower_bound_zero_failures_and_clopper_pearson() -> None:
    from scipy.stats import binom

    assert lower_bound(299, 0, 0.95) == pytest.approx(0.05 ** (1 / 299))
    assert lower_bound(299, 0, 0.95) > 0.99 > lower_bound(298, 0, 0.95)
    # Clopper-Pearson: at the bound, n - f or more passes has probability 1 - confidence
    p = lower_bound(100, 3, 0.95)
    assert binom.sf(96, 100, p) == pytest.approx(0.05, rel=1e-6)
    assert lower_bound(10, 10, 0.95) == 0.0


def test_draws_depend_only_on_seed_and_index(tmp_path: Path) -> None:
    c = load_campaign(write_spec(tmp_path))
    big = load_campaign(write_spec(tmp_path, _spec(requirement={"runs": 50}), "big.yaml"))
    a, b = c.draw(2), big.draw(2)
    assert a.params == b.params and a.targets == b.targets and a.sim_seed == b.sim_seed
    assert a.params != c.draw(3).params
    other = load_campaign(write_spec(tmp_path, _spec(seed=12), "other.yaml"))
    assert other.draw(2).params != a.params


def test_draws_reach_the_simulated_machine_only(tmp_path: Path) -> None:
    c = load_campaign(write_spec(tmp_path))
    d = c.draw(0)
    bulk = d.params["hydraulics.bulk_modulus_mpa"]
    assert 500 <= bulk <= 1200
    assert d.sim_project.hydraulics.bulk_modulus_mpa == bulk
    assert c.project.hydraulics.bulk_modulus_mpa == 700  # the service's project as written
    mass = d.sim_project.layers.upper.bodies[0].mass_kg
    assert mass == pytest.approx(d.params["layers.upper.bodies[0].mass_kg"])
    assert d.scenario.sensors.position.noise_um == d.params["sim.sensors.position.noise_um"]


def test_events_get_random_times_or_nan_when_they_do_not_happen(tmp_path: Path) -> None:
    c = load_campaign(write_spec(tmp_path, _spec(requirement={"runs": 40})))
    starts = []
    for i in range(40):
        d = c.draw(i)
        s = d.params["event0_plc_stall_start_s"]
        if math.isnan(s):
            assert d.scenario.events == ()
        else:
            (ev,) = d.scenario.events
            assert ev.kind == "plc_stall" and ev.start_s == s
            assert ev.end_s == pytest.approx(s + d.params["event0_plc_stall_duration_s"])
            starts.append(s)
    assert 5 < len(starts) < 35 and len(set(starts)) == len(starts)
    assert all(0.5 <= s <= 2.0 for s in starts)


def test_star_paths_draw_each_cylinder_from_the_drawn_defaults(tmp_path: Path) -> None:
    spec = _spec(
        dispersions={
            "hydraulics.cylinder_defaults.coulomb_friction_n": {
                "dist": "uniform",
                "low": 1000,
                "high": 2000,
            },
            "cylinders[*].plant.internal_leakage_m3_s_pa": {
                "dist": "lognormal",
                "mean": 0.0,
                "std": 0.5,
                "factor": True,
            },
        }
    )
    d = load_campaign(write_spec(tmp_path, spec)).draw(1)
    cyl = d.sim_project.cylinders
    leaks = [c.plant.internal_leakage_m3_s_pa for c in cyl if c.plant is not None]
    assert len(leaks) == len(cyl) and len(set(leaks)) == len(cyl)
    friction = d.params["hydraulics.cylinder_defaults.coulomb_friction_n"]
    assert all(c.plant is not None and c.plant.coulomb_friction_n == friction for c in cyl)


def test_bounds_redraw_inside_min_max(tmp_path: Path) -> None:
    spec = _spec(
        dispersions={
            "hydraulics.bulk_modulus_mpa": {
                "dist": "normal",
                "mean": 700,
                "std": 400,
                "min": 600,
                "max": 800,
            }
        },
        requirement={"runs": 30},
    )
    c = load_campaign(write_spec(tmp_path, spec))
    vals = np.array([c.draw(i).params["hydraulics.bulk_modulus_mpa"] for i in range(30)])
    assert vals.min() >= 600 and vals.max() <= 800 and vals.std() > 20


@pytest.mark.parametrize(
    ("change", "expected"),
    [
        ({"colour": "red"}, "colour: unknown key"),
        ({"run": {"kind": "swim"}}, "run.kind must be attitude_targets, walk or ring_cycle"),
        ({"run": {"kind": "walk", "steps": 4}}, "run.walk.steps"),
        ({"run": {"kind": "walk", "targets": 1}}, "run.walk.targets: unknown key"),
        (
            {"run": {"kind": "walk"}, "requirement": {"limits": {"sync_error_mm": 0.07}}},
            "unknown figure 'sync_error_mm' of a walk run",
        ),
        (
            {"run": {"kind": "ring_cycle", "previous_y_mm": [3, -3]}},
            "previous_y_mm: [3.0, -3.0] must be [low, high]",
        ),
        (
            {"dispersions": {"hydraulics.bulk_modulus": {"dist": "uniform", "low": 1, "high": 2}}},
            "dispersions.hydraulics.bulk_modulus: hydraulics.bulk_modulus: no such key",
        ),
        (
            {"dispersions": {"layers.upper.bodies[7].mass_kg": {"dist": "normal", "mean": 1}}},
            "normal needs std",
        ),
        (
            {
                "dispersions": {
                    "layers.upper.bodies[7].mass_kg": {"dist": "uniform", "low": 1, "high": 2}
                }
            },
            "layers.upper.bodies[7]: no such element",
        ),
        (
            {"dispersions": {"project.name": {"dist": "uniform", "low": 1, "high": 2}}},
            "project.name: is 'Shanghai Airport Link', not a number",
        ),
        (
            {
                "dispersions": {
                    "hydraulics.bulk_modulus_mpa": {"dist": "uniform", "low": 1e5, "high": 2e5}
                }
            },
            "hydraulics.bulk_modulus_mpa",
        ),
        (
            {"dispersions": {"a.b": {"dist": "uniform", "low": 2, "high": 1}}},
            "low (2.0) must be below high (1.0)",
        ),
        (
            {
                "dispersions": {
                    "layers.upper.bodies[0].cog_m[0]": {
                        "dist": "normal",
                        "mean": 0.0,
                        "std": 0.1,
                        "min": 5,
                        "max": 6,
                    }
                }
            },
            "dispersions.layers.upper.bodies[0].cog_m[0]: min/max keep 0.00% of the normal "
            "draws (mean 0.0, std 0.1); at least 2% are needed",
        ),
        (
            {
                "events": [
                    {
                        "event": {"kind": "drop"},
                        "start_s": {"dist": "choice", "values": [1, 2], "min": 3, "max": 4},
                    }
                ]
            },
            "events[0].start_s: min/max keep 0.00% of the choice draws",
        ),
        ({"requirement": {"limits": {"speed": 1}}}, "limits: unknown figure 'speed'"),
        ({"kind": "worst"}, "kind: "),
        # a nominal campaign: only what a healthy machine shows, within the project's bounds
        (
            {"kind": "nominal"},
            "kind: nominal: events[0] (plc_stall): duration_s up to 0.04; within the "
            "specification at most 0.015 (can.stale_cycles loop periods",
        ),
        (
            {"kind": "nominal", "events": [_event("bus_off")]},
            "kind: nominal: events[0] (bus_off): a fault, not a dispersion within the "
            "specification (a nominal campaign draws delay, drop, plc_stall, ground): put it "
            "in a campaign of kind: fault",
        ),
        (
            {"kind": "nominal", "events": [_event("drop", rate=0.005)]},
            "events[0] (drop): max_burst not given; within the specification at most 1 "
            "(can.max_delta_counter - 1",
        ),
        (
            {"kind": "nominal", "events": [_event("drop", max_burst=1, rate=0.05)]},
            "events[0] (drop): rate up to 0.05; within the specification at most 0.01",
        ),
        (
            {
                "kind": "nominal",
                "events": [
                    {
                        **_event("delay"),
                        "fields": {"delay_ms": {"dist": "normal", "mean": 5, "std": 1}},
                    }
                ],
            },
            "events[0] (delay): delay_ms unbounded (give its distribution a max); within the "
            "specification at most 20 (control.delay_margin_ms",
        ),
        ({"requirement": {"probability": 1.0}}, "requirement.probability"),
        ({"tune": {"parameters": {"planner.min_rod_force_kn": [1, 5]}}}, "only control.* keys"),
        (
            {
                "events": [
                    {
                        "event": {"kind": "meteor"},
                        "start_s": {"dist": "uniform", "low": 0, "high": 1},
                    }
                ]
            },
            "event.kind must be one of",
        ),
        (
            {
                "events": [
                    {
                        "event": {"kind": "drop", "start_s": 3},
                        "start_s": {"dist": "uniform", "low": 0, "high": 1},
                    }
                ]
            },
            "the times are drawn",
        ),
    ],
)
def test_bad_specs_are_one_line_errors(
    tmp_path: Path, change: dict[str, Any], expected: str
) -> None:
    path = write_spec(tmp_path, _spec(**change))
    with pytest.raises(ConfigError) as exc:
        load_campaign(path)
    assert expected in str(exc.value)
    code, out, err = run_main(["campaign", "run", str(path), "--out", str(tmp_path / "o")])
    assert code == 2 and out == ""
    assert err.startswith("wara: configuration error: ") and expected in err
    assert not (tmp_path / "o").exists()


def test_bad_arguments_exit_2(tmp_path: Path) -> None:
    spec = str(write_spec(tmp_path))
    with pytest.raises(SystemExit) as exc:
        run_main(["campaign", "run", spec])
    assert exc.value.code == 2
    code, _, err = run_main(["campaign", "run", spec, "--out", "x", "--workers", "0"])
    assert code == 2 and "--workers must be 1..256" in err
    code, _, err = run_main(["campaign", "report", str(tmp_path / "nothing")])
    assert code == 2 and "not a campaign directory" in err


# --------------------------------------------------------------------------- results


def _row(c: Any, i: int, *, passed: bool = True, margin: float = 0.5) -> dict[str, Any]:
    d = c.draw(i)
    row: dict[str, Any] = {"run": i, "seed": d.sim_seed}
    row.update({f"p.{k}": v for k, v in d.params.items()})
    bulk = d.params["hydraulics.bulk_modulus_mpa"]
    row.update(
        {
            "attitude_error_deg": 1e-5,
            "max_twist_mm": 0.01,
            "sync_error_mm": 0.07 * (1 - margin),
            "max_sync_error_mm": 0.1,
            "duration_s": 3.0,
            "margin": margin if passed else -0.1 - bulk / 1e4,
            "passed": passed,
            "status": "passed" if passed else "over_limit",
            "note": "" if passed else "sync_error_mm 0.08 > 0.07",
            "fault_reasons": "",
            "final_mode": "COMPLETE",
            "sim_time_s": 9.0,
            "wall_s": 1.0,
            "worker": "w",
        }
    )
    return row


def test_a_run_file_is_written_once_and_compacted_in_order(tmp_path: Path) -> None:
    c = load_campaign(write_spec(tmp_path))
    out = tmp_path / "camp"
    write_manifest(out, c, payload_of(c))
    assert write_row(out, _row(c, 2))
    assert write_row(out, _row(c, 0))
    assert not write_row(out, _row(c, 2, margin=0.1))  # a redone run counts once
    assert done_indices(out) == {0, 2}
    compact(out)
    rows = read_results(out)
    assert [r["run"] for r in rows] == [0, 2] and rows[1]["margin"] == 0.5
    assert not list((out / "runs").glob("*.tmp"))


@pytest.mark.slow  # subprocesses or a run of many seconds: not in the fast lane
def test_report_verdict_drivers_and_html(tmp_path: Path) -> None:
    spec = _spec(requirement={"runs": 40})
    c = load_campaign(write_spec(tmp_path, spec))
    out = tmp_path / "camp"
    write_manifest(out, c, payload_of(c))
    # failures wherever the bulk modulus is low: the report must name it as the driver
    for i in range(40):
        fails = c.draw(i).params["hydraulics.bulk_modulus_mpa"] < 650
        write_row(out, _row(c, i, passed=not fails, margin=0.2 + i / 100))
    s = summary(out)
    v = s["verdict"]
    f = v["failures"]
    assert 0 < f < 40 and v["runs"] == 40 and not v["shown"]
    assert v["lower_bound"] == pytest.approx(lower_bound(40, f, 0.95))
    assert s["drivers"][0]["parameter"] == "hydraulics.bulk_modulus_mpa"
    assert s["drivers"][0]["rho_failure"] < -0.5
    assert all(
        not w["passed"] for w in [{"passed": x["status"] == "passed"} for x in s["worst_runs"][:f]]
    )
    page = write_html(out).read_text()
    assert page.count("data:image/png;base64,") == 5  # 3 figures, margin, scatter
    assert "hydraulics.bulk_modulus_mpa" in page and "<img" in page
    code, text, _ = run_main(["campaign", "report", str(out)])
    assert code == 1 and "requirement NOT shown" in text and "Clopper-Pearson" in text


def test_whether_an_event_happened_is_ranked_as_a_driver(tmp_path: Path) -> None:
    """The report ranked an event only by its times over the runs where it happened; a
    campaign failing whenever the PLC stalled at all named no driver for it."""
    from wara.campaign.report import drivers

    c = load_campaign(write_spec(tmp_path, _spec(requirement={"runs": 40})))
    rows = []
    for i in range(40):
        row = _row(c, i)
        stalled = math.isfinite(row["p.event0_plc_stall_start_s"])
        rows.append(_row(c, i, passed=not stalled, margin=0.3))
    assert 5 < sum(not r["passed"] for r in rows) < 35
    lead = drivers(rows)[0]
    assert lead["parameter"] == "event0_plc_stall happened" and lead["runs"] == 40
    assert lead["rho_failure"] == pytest.approx(1.0)


def test_a_histogram_of_values_far_below_their_limit_shows_them_scaled_too() -> None:
    """Values of 1e-5 against a limit of 0.01: 30 bins over the values alone were too
    thin to see on the axis the limit's line stretches to 0.01."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from wara.campaign.report import histogram

    fig, ax = plt.subplots()
    v = np.full(50, 1e-5) + np.linspace(0, 1e-6, 50)
    inset = histogram(ax, v, 0.01)
    bars = [b for b in ax.patches if b.get_height() > 0]
    assert sum(b.get_height() for b in bars) == 50
    assert min(b.get_width() for b in bars) >= 0.01 / 30 * 0.99  # one bin of the axis
    # and the values' own distribution on an axis scaled to them (1e-5 .. 1.1e-5)
    assert inset is not None
    lo, hi = inset.get_xlim()
    assert 0.9e-5 < lo < 1e-5 and 1.1e-5 <= hi < 1.2e-5, (lo, hi)
    assert sum(b.get_height() for b in inset.patches) == 50
    assert len([b for b in inset.patches if b.get_height() > 0]) > 10
    plt.close(fig)
    # values spread up to the limit need no inset
    fig, ax = plt.subplots()
    assert histogram(ax, np.linspace(0, 0.009, 50), 0.01) is None
    plt.close(fig)


def test_walk_and_ring_cycle_runs_are_judged_by_their_goals(tmp_path: Path) -> None:
    from wara.campaign.run import RunOutcome, row_of
    from wara.goals import step_time_limit_s

    c = load_campaign(write_spec(tmp_path, _spec(run={"kind": "walk", "steps": 2})))
    walking = c.project.walking
    assert walking is not None
    assert c.limits["max_leg_force_ratio"] == walking.overload_percent / 100 == 1.10
    assert c.limits["min_stability_margin_m"] == walking.min_stability_margin_m == 0.25
    assert c.limits["distance_error_mm"] == pytest.approx(5.0)
    step_s = step_time_limit_s(c.project)  # the planned step and its touch-downs
    assert c.limits["max_step_duration_s"] == step_s and 130.0 < step_s < 140.0
    assert "target0_roll_deg" not in c.draw(0).params  # a walk draws no targets
    figures = {
        "distance_error_mm": 0.7,
        "max_leg_sync_error_mm": 0.08,
        "max_travel_sync_error_mm": 0.004,
        "max_transfer_attitude_change_deg": 0.005,
        "max_leg_force_ratio": 1.075,
        "min_stability_margin_m": 0.874,
        "max_step_duration_s": step_s - 2.0,
    }
    row = row_of(c, c.draw(0), RunOutcome(dict(figures), done=True), wall_s=1.0, worker="w")
    assert row["passed"] and row["margin"] == pytest.approx(2.0 / step_s)  # the time
    # the stability margin is a lower bound: below it fails, named with "<"
    low = row_of(
        c, c.draw(0), RunOutcome({**figures, "min_stability_margin_m": 0.2}, done=True),
        wall_s=1.0, worker="w",
    )  # fmt: skip
    assert not low["passed"] and low["status"] == "over_limit"
    assert low["note"] == "min_stability_margin_m 0.2 < 0.25"
    assert low["margin"] == pytest.approx(0.2 / 0.25 - 1.0)

    ring = load_campaign(
        write_spec(tmp_path, _spec(run={"kind": "ring_cycle", "previous_y_mm": [-6, 6]}), "r.yaml")
    )
    assert ring.limits["vertical_misalignment_mm"] == 8  # the project's Table 4
    assert ring.limits["position_error_mm"] == 1.0 and ring.limits["cycle_time_s"] == 900.0
    d = ring.draw(3)
    assert -6 <= d.params["previous_y_mm"] <= 6 and d.previous_mm[0] == d.params["previous_y_mm"]
    assert d.params["previous_z_mm"] == 0.0


def _short_walk_project(tmp_path: Path) -> str:
    """The shipped project with 200 mm steps and a one-step ring cycle (a run in seconds)."""
    import yaml

    d = yaml.safe_load((REPO / "config/projects/shanghai_airport_link.yaml").read_text())
    d["walking"]["step_length_mm"] = 200
    d["cycle"]["walk_steps"] = 1
    path = tmp_path / "short.yaml"
    path.write_text(yaml.safe_dump(d))
    return path.name


@pytest.mark.slow
def test_a_walk_run_and_a_ring_cycle_run_on_a_drawn_machine(tmp_path: Path) -> None:
    """One run of each kind as a campaign worker runs it (lockstep, the drawn machine,
    a PLC stall while S travels): every figure measured, within the goals."""
    from wara.campaign.run import run_one

    stall = {
        "event": {"kind": "plc_stall"},
        "start_s": {"dist": "uniform", "low": 2.0, "high": 3.0},
        "duration_s": {"dist": "uniform", "low": 0.01, "high": 0.03},
    }
    project = _short_walk_project(tmp_path)
    walk = load_campaign(
        write_spec(tmp_path, _spec(project=project, run={"kind": "walk"}, events=[stall]), "w.yaml")
    )
    row = run_one(walk, 1)
    assert row["status"] == "ridden_through", row["note"]  # the stall happened
    assert 0.0 <= row["distance_error_mm"] <= 5.0 and row["min_stability_margin_m"] > 0.25
    assert 1.0 < row["max_leg_force_ratio"] <= 1.10 and row["p.event0_plc_stall_start_s"] > 2.0
    assert row["sim_time_s"] > row["max_step_duration_s"] > 10.0

    ring = load_campaign(
        write_spec(
            tmp_path,
            _spec(project=project, run={"kind": "ring_cycle", "previous_y_mm": [-3, 3]}, events=[]),
            "r.yaml",
        )
    )
    row = run_one(ring, 0)
    assert row["status"] == "passed", row["note"]
    assert row["position_error_mm"] <= 1.0 and row["angle_error_deg"] <= 0.01
    assert abs(row["p.previous_y_mm"]) <= 3.0 and row["vertical_misalignment_mm"] <= 8.0


def test_percentile_of_a_higher_is_better_figure_takes_the_low_tail() -> None:
    rows = [{"min_stability_margin_m": 0.8}] * 99 + [{"min_stability_margin_m": math.nan}]
    assert percentile_figure(rows, "min_stability_margin_m", 0.5) == 0.8
    assert percentile_figure(rows, "min_stability_margin_m", 0.999) == -math.inf


def test_percentile_figure_counts_unfinished_runs_as_worst() -> None:
    rows = [{"margin": 0.5, "sync_error_mm": 0.01}] * 99 + [
        {"margin": -1.0, "sync_error_mm": math.nan}
    ]
    assert percentile_figure(rows, "margin", 0.99) < 0.5
    assert percentile_figure(rows, "sync_error_mm", 0.5) == 0.01
    assert percentile_figure(rows, "sync_error_mm", 0.999) == math.inf


def test_without_the_campaign_extra_it_names_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import sys

    monkeypatch.setitem(sys.modules, "distributed", None)
    code, out, err = run_main(["campaign", "report", str(tmp_path)])
    assert code == 2 and out == ""
    assert err.strip() == (
        "wara campaign: error: wara campaign needs distributed, which is not installed: "
        "install with pip install -e '.[campaign]'"
    )


def test_engine_overhead_is_split_into_the_tail_and_the_engines_gaps(tmp_path: Path) -> None:
    """Two workers for 10 s: one ran 4 + 5 s and got its last at 9.5 s, the other ran
    6 s and was done at 6.2 s (no run left for it): the tail is 0.5 + 3.8 s, the engine's
    gaps between runs the rest, 10 + 10 - 4.3 - 15 = 0.7 s, over 15 s of runs."""
    from wara.campaign.engine import Outcome

    o = Outcome(tmp_path, 3, 0, written=3, elapsed_s=10.0, task_s=15.0, workers=2)
    o.last_done_s = {"w1": 9.5, "w2": 6.2}
    assert o.tail_s == pytest.approx(0.5 + 3.8)
    assert o.gap_share == pytest.approx(0.7 / 15.0)
    # a worker that got no run at all is idle for the whole campaign: tail, not engine
    o.workers = 3
    assert o.tail_s == pytest.approx(0.5 + 3.8 + 10.0)
    assert o.gap_share == pytest.approx(0.7 / 15.0)


def test_the_spec_says_which_kind_of_campaign_it_is(tmp_path: Path) -> None:
    data = _spec()
    del data["kind"]
    with pytest.raises(ConfigError, match=r"kind: .*required"):
        load_campaign(write_spec(tmp_path, data))
    # the shipped nominal campaigns' events are within the shipped project's bounds; each
    # fault campaign's link losses reach past its ride-through: a nominal and a fault
    # campaign for each motion (the attitude adjustment, the walk, the ring cycle)
    shipped = sorted((REPO / "config/campaigns").glob("*.yaml"))
    pairs = {(c.spec.run.kind, c.spec.kind): c for c in map(load_campaign, shipped)}
    assert len(pairs) == len(shipped) == 6
    for run in ("attitude_targets", "walk", "ring_cycle"):
        assert (run, "nominal") in pairs
        faults = pairs[(run, "fault")]
        kinds = {ev.event["kind"] for ev in faults.spec.events}
        assert kinds >= {"plc_stall", "drop", "bus_off", "sensor", "holding_valve_leak"}, run


def test_a_fault_run_is_judged_on_the_reaction() -> None:
    """Ridden through and within the goals; or the safe state with a cause the faults
    that happened may latch, except after a link loss within the ride-through's bound."""
    from wara.campaign.kinds import judge_fault

    def judge(happened: list[tuple[str, float]], done: bool, *causes: str) -> tuple[bool, str]:
        v = judge_fault(happened, done, [], list(causes), 80.0)
        return v.passed, v.status

    assert judge([("plc_stall", 0.1)], True) == (True, "ridden_through")
    assert judge([], True) == (True, "passed")
    assert judge([("plc_stall", 0.4)], False, "plc heartbeat") == (True, "safe_state")
    assert judge([("plc_silent", math.nan)], False, "sensor timeout") == (True, "safe_state")
    assert judge([("plc_stall", 0.06)], False, "plc heartbeat") == (False, "not_ridden_through")
    # beyond the heartbeat's reach, though within safety.max_suspend_ms: the safe state
    assert judge([("plc_stall", 0.139)], False, "plc heartbeat") == (True, "safe_state")
    assert judge([("stuck_valve", 1.0)], False, "tracking error") == (True, "safe_state")
    assert judge([("sensor", 1.0)], False, "overload") == (False, "wrong_cause")
    # a stuck reading in valid frames: the loops' errors latch
    assert judge([("sensor", 1.0)], False, "sync error") == (True, "safe_state")
    assert judge([("plc_stall", 0.4)], False, "planner") == (False, "wrong_cause")
    assert judge([("drop", 1.0)], False) == (False, "not_finished")
    over = judge_fault([("plc_stall", 0.1)], True, ["max_leg_force_ratio 1.12 > 1.1"], [], 250)
    assert (over.passed, over.status) == (False, "over_limit")  # a resume into an overload


def test_the_ride_through_owed_is_bounded_by_the_timeouts_that_latch_while_suspended(
    tmp_path: Path,
) -> None:
    """The heartbeat and the sensor timeout latch in every mode: a loss is owed a
    ride-through only while the last frame's age stays within them (a 20 ms frame cycle
    on the shipped bus: 80 ms), and never beyond safety.max_suspend_ms."""
    import yaml

    from config import load_project
    from wara.campaign.kinds import ride_through_ms

    assert ride_through_ms(load_project()) == pytest.approx(80.0)

    def with_safety(**keys: float) -> float:
        d = yaml.safe_load((REPO / "config/projects/shanghai_airport_link.yaml").read_text())
        d["safety"].update(keys)
        path = tmp_path / "p.yaml"
        path.write_text(yaml.safe_dump(d))
        return ride_through_ms(load_project(path))

    assert with_safety(plc_heartbeat_timeout_ms=200) == pytest.approx(80.0)  # the sensors'
    assert with_safety(plc_heartbeat_timeout_ms=200, sensor_timeout_ms=150) == pytest.approx(130)
    loose = with_safety(plc_heartbeat_timeout_ms=400, sensor_timeout_ms=400)
    assert loose == pytest.approx(250.0)  # safety.max_suspend_ms


@pytest.mark.slow
def test_a_fault_campaigns_run_ends_in_the_safe_state_with_the_right_cause(
    tmp_path: Path,
) -> None:
    """A PLC stall of 0.4-0.6 s during the adjustment, beyond safety.max_suspend_ms: the
    safe state, latched as the link's loss (a pass of a fault campaign)."""
    from wara.campaign.run import run_one

    stall = {
        "event": {"kind": "plc_stall"},
        "start_s": {"dist": "uniform", "low": 2.0, "high": 3.0},
        "duration_s": {"dist": "uniform", "low": 0.4, "high": 0.6},
    }
    c = load_campaign(write_spec(tmp_path, _spec(events=[stall])))
    row = run_one(c, 0)
    assert (row["passed"], row["status"], row["note"]) == (True, "safe_state", "plc heartbeat")
    assert row["fault_reasons"].startswith("plc heartbeat: ") and row["margin"] == -1.0
