"""The HFDU example project on its derived tuning, in lockstep (docs/control.md, "Tuning
from the plant"): another power unit (21 MPa), a softer oil column (400 MPa effective,
2 L hoses) and 180 mm legs. With the shipped project's former fixed 6/12 rad/s its hold
tolerated 10 ms of extra delay; derived, the attitude examples pass, the hold is stable
with the project's required delay, and a ring cycle walks one step there, places the
part and walks back unloaded within the walk's goals.

One set-up per run (module fixtures), several assertions on each.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from config import default_project_path, load_project
from ipc_app.control.tuning import derive
from ipc_app.service.worker import PlannerWorker
from wara.cycle import run_cycle
from wara.demo import run_demo
from wara.goals import step_time_limit_s
from wara.studies.delay_margin import run_one

pytestmark = pytest.mark.slow

HFDU = default_project_path().with_name("shanghai_hfdu_power_unit.yaml")


@pytest.fixture(scope="module")
def attitude() -> dict[str, Any]:
    return run_demo(str(HFDU), mode="lockstep")


@pytest.fixture(scope="module")
def cycle(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    db = Path(tmp_path_factory.mktemp("hfdu")) / "a.sqlite"
    return run_cycle(str(HFDU), 1, db_path=db, cfg=load_project(HFDU))


@pytest.fixture(scope="module")
def planner() -> Iterator[PlannerWorker]:
    w = PlannerWorker(str(HFDU), timeout_s=60.0)
    w.start()
    yield w
    w.close()


def test_the_attitude_examples_pass_on_the_derived_tuning(attitude: dict[str, Any]) -> None:
    assert attitude["passed"], attitude.get("error") or attitude["fault_reasons"]
    assert attitude["final_mode"] == "COMPLETE"
    for ex in attitude["examples"]:
        assert ex["passed"]
        assert ex["max_sync_error_mm"] < 0.1  # against the 2 mm interlock


def test_the_hold_keeps_the_required_delay_margin(planner: PlannerWorker) -> None:
    cfg = load_project(HFDU)
    assert all(lt.source == "derived" for lt in derive(cfg).loops)
    run = run_one(cfg, planner, cfg.control.delay_margin_ms, hold_s=15.0)
    assert run.reached_target and run.stable, run
    assert run.mode == "COMPLETE" and not run.faults


def test_a_ring_cycle_walks_there_and_back_unloaded_within_the_goals(
    cycle: dict[str, Any],
) -> None:
    assert cycle["error"] is None, cycle["error"]
    assert cycle["fault_reasons"] == [], cycle["fault_reasons"]
    (ring,) = cycle["rings"]
    assert set(ring["walks"]) == {"walk", "walk_back"}
    cfg = load_project(HFDU)
    assert cfg.walking is not None
    overload = cfg.walking.overload_percent / 100
    for steps in ring["walks"].values():
        (step,) = steps
        assert step["max_leg_force_ratio"] <= overload
        assert step["max_leg_sync_error_mm"] <= cfg.walking.leg_sync_band_mm
        assert step["min_stability_margin_m"] >= cfg.walking.min_stability_margin_m
        assert step["duration_s"] <= step_time_limit_s(cfg)  # the step-time goal
    assert ring["passed"] and cycle["passed"]
