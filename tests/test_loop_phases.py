"""Where the loop's time goes: its figures per phase of a run and each overrun explained,
from a run record and the loop's reports (:mod:`wara.loop_phases`), on records built
here with known latencies, overruns and phases."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from wara.loop_phases import grid, latency_ms, phase_figures, record_times, render_phases

P = 0.005  # the shipped 200 Hz


def _times(n: int, skips: dict[int, int], late: dict[int, float]) -> np.ndarray:
    """``n`` wake-ups on the grid from t = 100 s: after row i, ``skips[i]`` periods
    skipped; row i woke ``late[i]`` s after its deadline (else 0.1 ms; row 0 on it: the
    grid's origin)."""
    out, k = [], 0
    for i in range(n):
        out.append(100.0 + k * P + late.get(i, 1e-4 if i else 0.0))
        k += 1 + skips.get(i, 0)
    return np.array(out)


def test_grid_latency_and_skips() -> None:
    t = _times(10, {3: 2}, {5: 0.004})
    n = grid(t, P)
    assert n.tolist() == [0, 1, 2, 3, 6, 7, 8, 9, 10, 11]
    lat = latency_ms(t, P)
    assert lat[5] == pytest.approx(4.0, abs=1e-6)
    assert lat[0] == pytest.approx(0.0) and lat[1] == pytest.approx(0.1, abs=1e-6)


def _report(cycles: int, window: int, p99: float, cmax: float, jmax: float) -> dict[str, float]:
    return {
        "cycles": cycles,
        "window_cycles": window,
        "compute_p50_ms": 0.5,
        "compute_p99_ms": p99,
        "compute_max_ms": cmax,
        "jitter_max_ms": jmax,
    }


def test_phases_and_overruns_explained() -> None:
    # 3000 cycles: start-up to row 199, idle, ring 2's walk from row 400, place from 2000
    late = {2600: 0.0049}  # row 2600 woke 4.9 ms late: with one skip, a late wake-up
    t = _times(3000, {1000: 1, 1500: 2, 2600: 1, 100: 1}, late)
    t0 = float(t[0])

    def at(row: int) -> float:
        return float(t[row]) - 1e-6

    events = [
        {"t_s": at(400), "kind": "cycle_phase", "ring": 2, "phase": "walk"},
        {"t_s": at(990), "kind": "walk_phase", "step": 1, "phase": 3, "name": "transfer"},
        {"t_s": at(1200), "kind": "suspended", "reason": "x"},
        {"t_s": at(2000), "kind": "cycle_phase", "ring": 2, "phase": "place"},
        {"t_s": at(2900), "kind": "cycle_end", "ring": 2},
    ]
    reports = [
        _report(200, 200, 0.9, 1.0, 0.2),  # the baseline: start-up
        _report(1100, 600, 1.2, 11.0, 0.3),  # rows 500-1099: in the walk, a 11 ms step
        _report(1700, 600, 2.5, 16.0, 0.3),  # rows 1100-1699: in the walk
        _report(2700, 600, 0.8, 0.9, 4.9),  # rows 2100-2699: in the place, a late wake-up
        _report(2950, 600, 0.7, 0.9, 0.2),  # rows 2350-2949: overlaps the place and idle
    ]
    fig = phase_figures(t, events, reports, P, baseline_cycles=200)
    by = {p["phase"]: p for p in fig["phases"]}
    assert list(by) == ["start-up", "idle", "walk", "place"]
    walk = by["walk"]
    assert walk["cycles"] == 1600 and walk["overruns"] == 2 and walk["skipped_periods"] == 3
    assert walk["compute_p99_ms"] == 2.5 and walk["compute_max_ms"] == 16.0
    assert walk["compute_windows"] == 2 and not walk["compute_mixed"]
    assert walk["suspends"] == 1
    assert by["place"]["overruns"] == 1 and by["place"]["compute_p99_ms"] == 0.8
    assert by["start-up"]["overruns"] == 1 and fig["start_up_overruns"] == 1
    # idle after the ring (rows 2900-2999) is shorter than every window: mixed figures
    assert by["idle"]["compute_mixed"] and by["idle"]["spans"] == 2
    over = fig["overruns"]
    assert [o["skipped_periods"] for o in over] == [1, 2, 1]
    first, second, third = over
    assert first["phase"] == "walk" and first["ring"] == 2
    assert first["step_at_least_ms"] == pytest.approx(4.9, abs=1e-3)
    assert first["cause"] == "long step" and "walk_phase 1.3 transfer" in first["near"]
    assert second["step_at_least_ms"] == pytest.approx(9.9, abs=1e-3)
    assert second["cause"] == "long step"  # its window has a 16 ms step
    assert third["phase"] == "place" and third["cause"] == "late wake-up"
    assert fig["by_cause"] == {"long step": 2, "late wake-up": 1}
    lines = render_phases(fig, 5.0)
    assert lines[0].startswith("| phase |") and any(ln.startswith("| walk | 8.0 |") for ln in lines)
    assert "overruns after start-up: 3 (late wake-up 1, long step 2); in start-up 1" in lines
    assert sum("t=" in ln for ln in lines) == 3 and f"{float(t[1000]) - t0:8.2f}" in lines[-3]


def test_record_times_ignores_a_half_written_line(tmp_path: Path) -> None:
    (tmp_path / "samples.csv").write_text("t_s,a\n1.0,2\n1.005,3\n1.01")
    assert record_times(tmp_path).tolist() == [1.0, 1.005, 1.01]
    (tmp_path / "samples.csv").write_text("t_s,a\n1.0,2\n1.0x")
    assert record_times(tmp_path).tolist() == [1.0]
