"""``wara demo`` (the README's main command) in its lockstep form, as a user runs it:
stdout is the table or one JSON object (the service's log goes to stderr), every
example meets its goals, ``--plot`` writes the figure."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from wara.demo import ATTITUDE_TOL_DEG, EXAMPLES, SYNC_TOL_MM, TWIST_TOL_MM

REPO = Path(__file__).resolve().parents[1]


def test_lockstep_demo_json_and_plot(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "wara", "demo", "--lockstep", "--json", "--plot", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=REPO,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        check=False,
    )
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
