"""``wara demo`` (the README's main command) in its lockstep form, as a user runs it:
stdout is the table or one JSON object (the service's log goes to stderr), every
example meets its goals, ``--plot`` writes the figure."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from tests.cli_helpers import run_wara
from wara import demo_two_process as d2
from wara.examples import (
    ATTITUDE_TOL_DEG,
    EXAMPLES,
    SYNC_TOL_MM,
    TWIST_TOL_MM,
    ExampleResult,
    judge_example,
)

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_lockstep_demo_json_and_plot(tmp_path: Path) -> None:
    proc = run_wara(["demo", "--lockstep", "--json", "--plot", str(tmp_path)], timeout_s=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = json.loads(proc.stdout)  # nothing but the one object on stdout
    assert out["passed"] is True
    got = [(e["target_roll_deg"], e["target_pitch_deg"]) for e in out["examples"]]
    assert got == list(EXAMPLES)
    for e in out["examples"]:
        assert e["attitude_error_deg"] <= ATTITUDE_TOL_DEG
        assert e["max_twist_mm"] <= TWIST_TOL_MM
        assert e["sync_error_mm"] <= SYNC_TOL_MM
        # the trajectory's speeds fed forward: synchronized within 0.2 mm while moving
        assert e["max_sync_error_mm"] < 0.2, e
        assert e["duration_s"] > 1.0
    assert {"jitter_p99_ms", "overruns"} <= set(out["loop"])
    assert out["plots"] == [str(tmp_path / "demo.png")]
    assert (tmp_path / "demo.png").stat().st_size > 10_000
    assert "wara demo: example (+2.0, +1.0) deg: passed" in proc.stderr


def _result(**figures: float) -> ExampleResult:
    res = ExampleResult(2.0, 1.0)
    res.set_achieved(2.0 + figures.pop("off_deg", 0.0), 1.0)
    res.max_twist_mm = figures.pop("twist_mm", 0.01)
    res.sync_error_mm = figures.pop("sync_mm", 0.01)
    return res


def test_judge_example_passes_within_every_goal_only() -> None:
    assert judge_example(_result()).passed
    edge = _result(off_deg=ATTITUDE_TOL_DEG, twist_mm=TWIST_TOL_MM, sync_mm=SYNC_TOL_MM)
    assert judge_example(edge).passed  # on the goal is within it
    over = judge_example(_result(sync_mm=0.08, twist_mm=0.6))
    assert not over.passed
    assert over.note == "max twist mm 0.6 > 0.5; sync error mm 0.08 > 0.07"
    missing = judge_example(_result(sync_mm=math.nan))
    assert not missing.passed and missing.note == "sync error mm nan > 0.07"


def test_judge_example_fails_with_a_problem_whatever_the_figures() -> None:
    res = judge_example(_result(), problem="did not finish: service FAULT: x")
    assert not res.passed and res.note == "did not finish: service FAULT: x"


def test_both_demo_forms_judge_alike() -> None:
    """The two-process form reads the figures from the service's status and gives them
    to the same judge."""
    motion = {
        "achieved_deg": [2.0, 1.0],
        "max_twist_mm": 0.01,
        "hold_sync_error_mm": 0.08,
        "max_sync_error_mm": 0.1,
        "duration_s": 6.1,
        "hold_samples": 600,
    }
    two = d2._judge({"mode": "COMPLETE", "motion": motion}, ExampleResult(2.0, 1.0))
    one = judge_example(_result(sync_mm=0.08))
    assert (two.passed, two.note) == (one.passed, one.note) == (False, "sync error mm 0.08 > 0.07")
    no_hold = d2._judge({"mode": "COMPLETE", "motion": {**motion, "hold_samples": 0}}, _result())
    assert not no_hold.passed and no_hold.note.startswith("no standstill samples")
    faulted = d2._judge({"mode": "ABORTED", "fault_reasons": ["x"]}, _result())
    assert not faulted.passed and faulted.note == "mode ABORTED: ['x']"
