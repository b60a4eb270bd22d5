"""``wara bench harness --baseline DIR``: this checkout against another, in one run."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from wara.cli import main

ROOT = Path(__file__).resolve().parents[1]


def test_a_baseline_that_is_no_checkout_is_refused_in_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["bench", "harness", "--baseline", str(tmp_path), "--json"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "not a checkout" in err[0] and str(tmp_path) in err[0]


def test_baseline_and_runs_go_with_the_benches_that_take_them(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["bench", "planner", "--baseline", str(ROOT), "--json"]) == 2
    assert "--baseline goes with" in capsys.readouterr().err
    assert main(["bench", "harness", "--runs", "3", "--json"]) == 2
    assert "--runs goes with" in capsys.readouterr().err


@pytest.mark.slow
def test_the_harness_against_itself_gives_a_ratio_of_its_rounds(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """Against the same checkout: both pass, both factors measured, the median ratio
    within the rounds' range."""
    assert main(["bench", "harness", "--baseline", str(ROOT), "--runs", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["rounds"] == 2 and len(out["ratio_per_round"]) == 2
    assert out["passed"] == {"this": True, "baseline": True}
    assert out["realtime_factor_cpu"]["this"] > 1 and out["realtime_factor_cpu"]["baseline"] > 1
    lo, hi = out["ratio_range"]
    assert lo <= out["ratio"] <= hi
