"""The placement on the service (``wara ctl place``) and the ring cycle (``wara cycle``)."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from acceptance.store import AcceptanceStore
from config import ConfigError, ProjectConfig, load_project, units
from config.loader import default_project_path
from hil_sim.placement import pose_from_home
from ipc_app.model.placement import Pose, compose, design_pose, deviation, sheet_deviation
from ipc_app.planner.placement import home_pose, plan_from_deviation
from ipc_app.planner.survey import fit_survey
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import CtlHandlers, Request, dispatch, parse
from ipc_app.service.cycle import PHASES
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from wara.cycle import run_cycle, simulated_survey
from wara.harness import Harness


def test_ctl_place_requests_are_checked() -> None:
    req = parse(b'{"cmd": "place", "ring": 5, "previous_deviation": [6, -6, 0, 0, 0.03]}')
    assert req == Request("place", (5, (6.0, -6.0, 0.0, 0.0, 0.03)))
    assert parse(b'{"cmd": "place", "ring": 3}') == Request("place", (3, (0.0,) * 5))
    for bad, why in [
        (b'{"cmd": "place", "ring": 0}', "'ring' must be an integer 1..99999"),
        (b'{"cmd": "place", "ring": true}', "'ring' must be an integer"),
        (b'{"cmd": "place", "ring": 2, "previous_deviation": [1, 2]}', "five numbers"),
        (b'{"cmd": "place", "ring": 2, "previous_deviation": [1, 2, 3, "x", 5]}', "finite"),
        (b'{"cmd": "place", "ring": 2, "previous_deviation": [90, 0, 0, 0, 0]}', "50 mm"),
    ]:
        out = parse(bad)
        assert isinstance(out, dict) and out["code"] == "bad_request", bad
        assert why in out["error"], out["error"]
    got: list[tuple[int, tuple[float, ...]]] = []

    def place(ring: int, dev: tuple[float, ...]) -> dict[str, object]:
        got.append((ring, dev))
        return {"mode": "EXECUTE"}

    handlers = CtlHandlers(adjust=lambda r, p: {}, status=dict, stop=dict, reset=dict, place=place)
    assert dispatch(handlers, b'{"cmd": "place", "ring": 4}')["ok"] is True
    assert got == [(4, (0.0,) * 5)]


def _place_harness(tmp_path: Path) -> tuple[Harness, RunRecorder]:
    cfg = load_project(None)
    rec = RunRecorder(tmp_path / "run", ServiceCore.record_columns(cfg))
    rec.start()
    h = Harness(cfg, None, mode="lockstep", record=rec)
    h.start()
    assert h.wait_for(Mode.IDLE, 20.0), h.fault_note()
    return h, rec


@pytest.mark.slow
def test_the_service_places_the_part_on_the_planned_target(tmp_path: Path) -> None:
    cfg = load_project(None)
    h, rec = _place_harness(tmp_path)
    dev = sheet_deviation(6, -6, 0, 0, 0.03)
    try:
        out = h.core.request_place(5, dev)
        assert out["ok"], out
        h.advance(h.period)
        assert h.core.modes.mode == Mode.EXECUTE
        assert h.core.snapshot()["place"]["phase"] == "attitude"
        assert h.wait_for(Mode.COMPLETE, 60.0), h.fault_note()
        status = h.core.snapshot()["place"]
        assert status["done"] and set(status["phase_times_s"]) == {"attitude", "slide"}
        h.advance(1.0)  # holding
        r, t = pose_from_home(cfg, h.sim.rig)
        got = compose(home_pose(cfg, 5), Pose.from_matrix(r, t))
    finally:
        h.close()
        rec.stop()
    plan = plan_from_deviation(cfg, 5, dev)
    err = deviation(got, plan.target)
    assert max(abs(units.to_mm(v)) for v in (err.x, err.y, err.z)) <= 1.0
    assert max(abs(units.to_deg(v)) for v in (err.roll, err.pitch, err.yaw)) <= 0.01
    events = [json.loads(line)["kind"] for line in (tmp_path / "run" / "events.jsonl").open()]
    assert {"place", "place_phase", "place_done"} <= set(events)


@pytest.mark.slow
def test_a_placement_rides_through_link_losses_and_ends_on_target() -> None:
    """Eight short losses of the link during the slide phase (frames held 60 ms both
    ways): the service suspends and resumes each time, and the part still ends within
    0.03 mm of its target on the simulator's truth (the goal is 1 mm; what the rods'
    friction leaves at standstill: 0.019 mm with the former fixed 6/12 rad/s, 0.021 mm
    with the derived tunings)."""
    from config.hil_scenario import HilScenario
    from config.loader import validate_data

    cfg = load_project(None)
    starts = (2.0, 2.3, 2.6, 2.9, 3.2, 3.6, 4.0, 4.5)
    events = [
        {"kind": "wire_stall", "start_s": t, "end_s": t + 0.06, "direction": "both"} for t in starts
    ]
    scenario = validate_data(HilScenario, {"events": events}, "test scenario")
    h = Harness(cfg, None, mode="lockstep", scenario=scenario)
    dev = sheet_deviation(4, -4, 0, 0, 0)
    try:
        h.start()
        assert h.wait_for(Mode.IDLE, 20.0), h.fault_note()
        assert h.core.request_place(3, dev)["ok"]
        h.advance(h.period)
        assert h.wait_for(Mode.COMPLETE, 60.0), h.fault_note()
        assert h.core.resumes >= 4 and h.core.resumes == h.core.suspends
        assert h.core.placer is not None and h.core.placer.settled is True
        r, t = pose_from_home(cfg, h.sim.rig)
        got = compose(home_pose(cfg, 3), Pose.from_matrix(r, t))
    finally:
        h.close()
    err = deviation(got, plan_from_deviation(cfg, 3, dev).target)
    assert max(abs(units.to_mm(v)) for v in (err.x, err.y, err.z)) <= 0.03, err.to_dict()


@pytest.mark.slow
def test_a_stop_during_the_placement_holds_with_the_valves_closed(tmp_path: Path) -> None:
    h, rec = _place_harness(tmp_path)
    try:
        assert h.core.request_place(5, sheet_deviation(2, -2, 0, 0, 0))["ok"]
        h.advance(3.5)  # into the slide phase
        assert h.core.snapshot()["place"]["phase"] == "slide"
        h.core.modes.stop("test stop")
        h.advance(0.5)
        assert h.core.modes.mode == Mode.IDLE and not h.core.modes.valves_enabled
        assert h.core.placer is None and "place" not in h.core.snapshot()
        assert sorted(h.core.reader.active) == sorted(h.core.active)  # the attitude group
    finally:
        h.close()
        rec.stop()


@pytest.mark.slow
def test_an_unreachable_placement_is_refused_with_its_binding_limit(tmp_path: Path) -> None:
    h, rec = _place_harness(tmp_path)
    try:
        out = h.core.request_place(3, sheet_deviation(9, -9, 0, 0, 0))
        assert out["ok"] is False and out["code"] == "infeasible"
        assert "centreline_deviation_" in out["error"] and "\n" not in out["error"]
        assert "limit 5, exceeded by 2.000" in out["error"]
        assert h.core.modes.mode == Mode.IDLE
    finally:
        h.close()
        rec.stop()


@pytest.mark.slow
def test_the_ring_cycle_steers_back_and_writes_the_records(tmp_path: Path) -> None:
    db = tmp_path / "acc.sqlite"
    rec_dir = tmp_path / "run"
    cfg = load_project(None)
    rec = RunRecorder(rec_dir, ServiceCore.record_columns(cfg))
    rec.start()
    try:  # standing at the ring (the walks: the 200 mm cycle below)
        out = run_cycle(
            None, 2, first_ring=2, previous_deviation=sheet_deviation(6, -6, 0, 0, 0),
            db_path=db, record=rec, cfg=_cycle_with(walk_steps=0),
        )  # fmt: skip
    finally:
        rec.stop()
    assert out["error"] is None, out["error"]
    assert [r["ring"] for r in out["rings"]] == [2, 3]
    for r in out["rings"]:
        assert r["goals"] and all(g["met"] for g in r["goals"].values()), r["missed"]
        assert set(r["phase_times_s"]) == set(PHASES)
        assert r["cycle_time_s"] <= 15 * 60
        assert r["place_settled"] is True
        # bolted, then released: the platform carried the part's weight, then none
        assert r["platform_part_load_kn"]["bolted"] == pytest.approx(356.5, abs=0.5)
        assert r["platform_part_load_kn"]["released"] == 0.0
        assert 1.0 < r["release"]["released_at_mm"] < 2.5
    # ring 3 began with a new part set down by the crane (its weight ramped on over 5 s)
    assert out["rings"][1]["phase_times_s"]["load"] > 5.0
    dev = [r["as_built_deviation"]["y_mm"] for r in out["rings"]]
    assert 3.0 <= dev[0] <= 5.0 and 1.0 <= dev[1] <= 3.0, dev  # 2 mm per ring toward 0
    assert out["passed"]
    with AcceptanceStore.open(db) as store:
        got = {r.ring: r for r in store.current()}
        assert set(got) == {2, 3}
        assert store.latest_plan(3) is not None
        assert "as_built_pose" in store.latest_plan(3).final_attitude  # type: ignore[union-attr]
    phases = [
        (e["ring"], e["phase"])
        for e in map(json.loads, (rec_dir / "events.jsonl").open())
        if e["kind"] == "cycle_phase"
    ]
    assert phases == [(k, p) for k in (2, 3) for p in PHASES]


@pytest.mark.slow
def test_a_stop_mid_cycle_holds_and_names_the_phase(tmp_path: Path) -> None:
    stopped: list[str] = []

    def stop_in_place(h: Harness, phase: str) -> None:
        if phase == "place" and not stopped and h.core.modes.mode == Mode.EXECUTE:
            h.core.modes.stop("operator stop (test)")
            stopped.append(phase)

    out = run_cycle(
        None, 1, db_path=tmp_path / "a.sqlite", on_cycle=stop_in_place,
        cfg=_cycle_with(walk_steps=0),
    )  # fmt: skip
    assert stopped and not out["passed"]
    assert out["stopped_in_phase"] == "place" and out["error"].startswith("place:")
    assert out["final_mode"] == "IDLE" and out["valves_enabled"] is False
    with AcceptanceStore.open(tmp_path / "a.sqlite") as store:
        assert list(store.current()) == []  # nothing recorded for an unfinished ring


def _wara(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "wara", *args], capture_output=True, text=True, timeout=300
    )


@pytest.mark.slow
@pytest.mark.parametrize(
    ("args", "code", "text"),
    [
        (("--rings", "0"), 2, "--rings must be within 1..50, got 0"),
        (("--previous-deviation", "1,2"), 2, "expects five numbers"),
        (("--previous-deviation", "9,-9,0,0,0"), 3, "7.000, limit 5, exceeded by 2.000"),
    ],
)
def test_wara_cycle_bad_input(tmp_path: Path, args: tuple[str, ...], code: int, text: str) -> None:
    r = _wara("cycle", "--lockstep", "--db", str(tmp_path / "x.sqlite"), *args)
    assert r.returncode == code, r.stderr
    assert text in r.stderr
    assert "Traceback" not in r.stderr


def _cycle_with(**keys: object) -> ProjectConfig:
    cfg = load_project(None)
    assert cfg.cycle is not None
    return cfg.model_copy(update={"cycle": cfg.cycle.model_copy(update=keys)})


@pytest.mark.slow
def test_a_part_whose_centre_of_gravity_is_off_its_design_is_taken_on(tmp_path: Path) -> None:
    """The cycle takes a part on by its weight, not by how the four upper cylinders share
    it: a part as cast with its centre of gravity 0.18 m along and 0.1 m across off the
    YAML's (within the campaigns' draw) moves up to 0.87 MPa between them against the
    0.2 MPa tolerance, and the cycle waited in ``load`` for ever (the ring campaign's runs
    ended after an hour). Placed within Table 4 on the drawn machine."""
    cfg = _cycle_with(walk_steps=0)
    data = cfg.model_dump(mode="json")
    cog = data["layers"]["upper"]["bodies"][0]["cog_m"]
    cog[0], cog[1] = cog[0] + 0.18, cog[1] - 0.1
    sim = ProjectConfig.model_validate(data)
    out = run_cycle(
        None, 1, previous_deviation=sheet_deviation(2, -2, 0, 0, 0), db_path=tmp_path / "a.db",
        cfg=cfg, sim_cfg=sim,
    )  # fmt: skip
    assert out["error"] is None, out["error"]
    (ring,) = out["rings"]
    assert ring["phase_times_s"]["load"] < 5.0, ring["phase_times_s"]
    assert all(g["met"] for g in ring["goals"].values()), ring["missed"]


def test_the_simulated_survey_follows_its_keys() -> None:
    pose = design_pose(load_project(None), 4)
    for n, noise in [(5, 0.0), (12, 1.0)]:
        cfg = _cycle_with(survey_points=n, survey_noise_mm=noise)
        pts = simulated_survey(cfg, 4, pose, np.random.default_rng(1))
        assert len(pts) == n
        fit = fit_survey(cfg, 4, pts)
        rms = units.to_mm(fit.rms_residual_m)
        assert (rms < 0.01) if noise == 0.0 else (0.3 < rms < 3.0), rms


@pytest.mark.slow
def test_the_cycle_keys_govern_the_cycle(tmp_path: Path) -> None:
    cfg = _cycle_with(
        fixing_confirm_after_s=1.5, survey_points=5, survey_noise_mm=0.0, max_cycle_time_min=0.01,
        walk_steps=0,
    )  # fmt: skip
    out = run_cycle(None, 1, db_path=tmp_path / "a.sqlite", cfg=cfg)
    (row,) = out["rings"]
    assert abs(row["phase_times_s"]["fixing"] - 1.5) < 0.02
    assert row["survey_rms_residual_mm"] < 0.01
    assert row["goals"]["cycle_time_s"]["met"] is False and not out["passed"]
    walking: list[bool] = []

    def stop_in_walk(h: Harness, phase: str) -> None:
        if phase == "walk" and h.core.walker is not None and not walking:
            walking.append(True)
            h.core.modes.stop("operator stop (test)")

    out = run_cycle(
        None, 1, db_path=tmp_path / "b.sqlite", cfg=_cycle_with(walk_steps=1),
        on_cycle=stop_in_walk,
    )  # fmt: skip
    assert walking, out["error"]
    assert out["stopped_in_phase"] == "walk"
    assert out["final_mode"] == "IDLE" and out["valves_enabled"] is False


@pytest.mark.parametrize(
    ("change", "text"),
    [
        (lambda d: d.pop("placement"), "cycle needs the placement section"),
        (
            lambda d: (d.pop("walking"), d.pop("frames"), d["cycle"].update(walk_steps=2)),
            "cycle.walk_steps > 0 needs the frames and walking sections",
        ),
        (lambda d: d["cycle"].update(survey_points=3), "cycle.survey_points"),
        (lambda d: d["cycle"].update(fixing_confirm_after_s=0), "cycle.fixing_confirm_after_s"),
        (lambda d: d["cycle"].update(hold_s=1), "cycle.hold_s"),
    ],
)
def test_the_cycle_section_is_validated(tmp_path: Path, change: Any, text: str) -> None:
    data = yaml.safe_load(default_project_path().read_text())
    change(data)
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ConfigError, match=re.escape(text)):
        load_project(path)


@pytest.mark.slow
def test_a_cycle_that_walks_goes_to_the_ring_and_back(tmp_path: Path) -> None:
    """200 mm steps, two rings: one step to the ring with the part, one back without it
    (the gait mirrored, the statics unloaded), a new part set down at the loading point
    before the second ring, which walks loaded again."""
    data = yaml.safe_load(default_project_path().read_text())
    data["walking"]["step_length_mm"] = 200
    data["cycle"]["walk_steps"] = 1
    path = tmp_path / "walks.yaml"
    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    rec = RunRecorder(tmp_path / "run", ServiceCore.record_columns(load_project(path)))
    rec.start()
    try:
        out = run_cycle(
            str(path), 2, db_path=tmp_path / "a.sqlite", cfg=load_project(path), record=rec
        )
    finally:
        rec.stop()
    assert out["error"] is None, out["error"]
    for row in out["rings"]:
        assert row["phase_times_s"]["walk"] > 10 and row["phase_times_s"]["walk_back"] > 10
        # placed after a walk as without one: at its target height, not by the feet's
        # compression (0.9 mm) below it
        assert abs(row["error_from_target"]["z_mm"]) < 0.1
        assert row["platform_part_load_kn"]["released"] == 0.0
        # each walk's step judged as `wara walk` judges it, in the ring's figures
        assert set(row["walks"]) == {"walk", "walk_back"}
        for steps in row["walks"].values():
            (step,) = steps
            assert 1.0 < step["max_leg_force_ratio"] <= 1.10
            assert step["min_stability_margin_m"] >= 0.25
            assert 10 < step["duration_s"] < 120
        # the machine surveyed before the part's survey (docs/curves.md): the truth plus
        # the survey's noise (0.7 mm, 0.014 deg: 7 sigma here), given to the service
        # where it disagrees with its estimate beyond that noise, else the estimate kept
        ms = row["machine_survey"]
        seen = ms.get("surveyed") or ms["on_axis"]
        assert abs(seen["lateral_mm"] - ms["truth"]["lateral_mm"]) < 5.0
        assert abs(seen["heading_error_deg"] - ms["truth"]["heading_error_deg"]) < 0.1
    assert out["rings"][1]["phase_times_s"]["load"] > 5.0  # the crane's 5 s, then settled
    walks = [e for e in map(json.loads, (tmp_path / "run" / "events.jsonl").open())
             if e["kind"] == "walk"]  # fmt: skip
    located = [e for e in map(json.loads, (tmp_path / "run" / "events.jsonl").open())
               if e["kind"] == "locate"]  # fmt: skip
    given = [r["machine_survey"] for r in out["rings"] if "on_axis" in r["machine_survey"]]
    assert [e["on_axis"] for e in located] == [ms["on_axis"] for ms in given]
    assert [(w["direction"], w["unloaded"]) for w in walks] == [
        ("forward", False), ("back", True), ("forward", False), ("back", True),
    ]  # fmt: skip
    assert out["passed"]


@pytest.mark.slow
def test_an_unreachable_target_is_refused_before_the_walk(tmp_path: Path) -> None:
    """The cycle plans the ring's target before it walks to the ring: a previous part
    9 mm off is refused with the binding limit, nothing moved (the shipped 1 step)."""
    out = run_cycle(
        None, 1, db_path=tmp_path / "a.sqlite",
        previous_deviation=sheet_deviation(9, -9, 0, 0, 0),
    )  # fmt: skip
    assert out["refused"] and "exceeded by 2.000" in out["refused"]
    assert out["stopped_in_phase"] == "walk" and out["rings"] == []
    assert out["final_mode"] == "IDLE"
