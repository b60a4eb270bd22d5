"""``wara soak``: the two-process form moving between planner-feasible targets; the
latency reconstruction from the run record; a short soak (slow)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from config import load_project
from tests.cli_helpers import run_wara
from wara.commands.soak import (
    PITCH_DEG,
    ROLL_DEG,
    TargetDrawer,
    jitter_figures,
    latency_ms,
)
from wara.demo_two_process import netns_problem

REPO = Path(__file__).resolve().parents[1]
P = 0.005


def test_latency_on_the_deadline_grid() -> None:
    # deadlines t0 + n*P; wake-ups 0, 0.1, 0.3 ms late, then a skip of two periods
    # (cycle 3 overran), then 4 ms late (preempted in the sleep, no skip)
    t = np.array([0.0, P + 0.0001, 2 * P + 0.0003, 5 * P + 0.0002, 6 * P + 0.004])
    lat = latency_ms(t, P)
    np.testing.assert_allclose(lat, [0.0, 0.1, 0.3, 0.2, 4.0], atol=1e-6)


def test_jitter_max_takes_the_loop_reports_too() -> None:
    lat = np.linspace(0.0, 4.0, 1001)
    p999, mx = jitter_figures(lat, 19.0)
    assert p999 == pytest.approx(3.996) and mx == 19.0
    assert jitter_figures(lat, None)[1] == 4.0
    assert jitter_figures(lat, 1.0)[1] == 4.0
    assert jitter_figures(np.zeros(0), None) == (None, None)


def test_targets_are_feasible_and_seeded() -> None:
    from ipc_app.planner import plan

    cfg = load_project()
    a = TargetDrawer(cfg, seed=3)
    b = TargetDrawer(cfg, seed=3)
    ta = [a.next() for _ in range(4)]
    assert ta == [b.next() for _ in range(4)]
    assert len(set(ta)) == 4
    upper = lower = (0.0, 0.0, 0.0, 0.0)
    for roll, pitch in ta:
        assert abs(roll) <= ROLL_DEG and abs(pitch) <= PITCH_DEG
        p = plan(cfg, roll, pitch, start_upper_m=upper, start_lower_m=lower)
        assert p.feasible
        upper, lower = tuple(p.upper.displacement_m), tuple(p.lower.displacement_m)


def test_minutes_must_be_positive() -> None:
    from wara.cli import main

    assert main(["soak", "--minutes", "0"]) == 2
    with pytest.raises(SystemExit) as exc:  # argparse: a NaN is no number
        main(["soak", "--minutes", "nan"])
    assert exc.value.code == 2


@pytest.mark.realtime
@pytest.mark.slow
def test_a_short_soak() -> None:
    problem = netns_problem()
    if problem is not None:
        pytest.skip(f"wara soak needs a private netns: {problem}")
    proc = run_wara(["soak", "--minutes", "0.5", "--json", "--seed", "1"], timeout_s=600)
    out = json.loads(proc.stdout)
    assert "error" not in out, (out, proc.stderr[-2000:])
    assert out["moves"] >= 1
    assert out["cycles"] > 1000 and out["record_cycles"] >= out["cycles"]
    assert out["jitter_p999_ms"] is not None and out["jitter_max_ms"] >= out["jitter_p999_ms"]
    assert out["exit_codes"] == {"service": 0, "simulator": 0}
    assert "wara soak: move 1 to" in proc.stderr
    assert out["latched_faults"] == [], (out["latched_faults"], proc.stderr[-2000:])
    assert out["passed"] and proc.returncode == 0, proc.stderr[-2000:]


def test_the_next_target_starts_where_the_rods_are() -> None:
    cfg = load_project()
    by_id = {c.id: c for c in cfg.cylinders}
    d = TargetDrawer(cfg, seed=0)
    ids = list(cfg.layers.lower.cylinders) + list(cfg.layers.upper.cylinders)
    pos = {i: by_id[i].stroke_mm / 2 + 10.0 * k for k, i in enumerate(ids)}
    d.start_from({"positions_mm": pos})
    np.testing.assert_allclose(d.lower, [0.0, 0.01, 0.02, 0.03], atol=1e-12)
    np.testing.assert_allclose(d.upper, [0.04, 0.05, 0.06, 0.07], atol=1e-12)
    d.start_from({"positions_mm": {**pos, ids[0]: None}})  # an invalid reading: kept
    np.testing.assert_allclose(d.lower, [0.0, 0.01, 0.02, 0.03], atol=1e-12)
