"""``wara bench step``: the CPU of ``ServiceCore.step`` per mode, in lockstep."""

from __future__ import annotations

import json
import logging

import pytest
import structlog

from wara.cli import main


@pytest.mark.slow
def test_wara_bench_step_reports_every_mode(capsys: pytest.CaptureFixture[str]) -> None:
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    try:
        assert main(["bench", "step", "--json", "--quick"]) == 0
    finally:  # the bench configures process-wide logging, as the service would
        structlog.reset_defaults()
        root.handlers[:] = handlers
        root.setLevel(level)
    out = json.loads(capsys.readouterr().out)  # logs went to stderr
    assert out["bench"] == "step" and out["final_mode"] == "COMPLETE"
    assert {"IDLE", "STARTING", "EXECUTE", "COMPLETE"} <= set(out["modes"])
    adjusting = out["modes"]["EXECUTE"]
    assert adjusting["steps"] > 1000  # the whole 6.1 s motion at 200 Hz
    for figures in [*out["modes"].values(), out["all"]]:
        assert 0 < figures["cpu_p50_ms"] <= figures["cpu_p99_ms"] <= figures["cpu_max_ms"]
