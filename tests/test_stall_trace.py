"""WARA_STALL_TRACE_MS: a loop cycle that stalls dumps every thread's stack."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from config.stall import ENV, StallTrace

CHILD = textwrap.dedent(
    """
    import time
    from config.stall import StallTrace

    def stuck_in_a_cycle():
        time.sleep(0.4)

    with StallTrace() as stall:
        for k in range(20):
            stall.arm()
            time.sleep(0.002)  # cycles that come round in time: nothing dumped
        stall.arm()
        stuck_in_a_cycle()
    print("done")
    """
)


def _child(env_value: str | None) -> subprocess.CompletedProcess[str]:
    import os

    env = {k: v for k, v in os.environ.items() if k != ENV}
    if env_value is not None:
        env[ENV] = env_value
    return subprocess.run(
        [sys.executable, "-c", CHILD], env=env, capture_output=True, text=True, timeout=60
    )


def test_a_stalled_cycle_dumps_the_stack_that_stalls() -> None:
    out = _child("100")
    assert out.returncode == 0 and out.stdout.strip() == "done"
    assert out.stderr.count("Timeout (0:00:00.100000)!") == 1
    assert "stuck_in_a_cycle" in out.stderr


def test_off_by_default() -> None:
    out = _child(None)
    assert out.returncode == 0 and out.stderr == ""


@pytest.mark.parametrize("bad", ["soon", "-5", "inf"])
def test_a_bad_value_is_named(bad: str, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(ENV, bad)
    with pytest.raises(ValueError, match=ENV):
        StallTrace()
