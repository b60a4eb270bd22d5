"""The suite's bound on a command that hangs (:func:`tests.cli_helpers.run_tree`): the
command and what it started are killed, and the test fails with what it printed, instead
of waiting on the output's pipes that a surviving grandchild holds open."""

from __future__ import annotations

import subprocess
import time
from pathlib import Path

import pytest

from tests.cli_helpers import run_tree


def test_a_hung_command_and_its_children_are_killed_at_the_timeout(tmp_path: Path) -> None:
    pid_file = tmp_path / "grandchild.pid"
    script = f"sleep 300 & echo $! > {pid_file}; echo started; wait"
    t0 = time.monotonic()
    with pytest.raises(subprocess.TimeoutExpired) as exc:
        run_tree(["sh", "-c", script], 1.0)
    assert time.monotonic() - t0 < 30
    assert "started" in exc.value.output
    grandchild = int(pid_file.read_text())
    deadline = time.monotonic() + 10
    while time.monotonic() < deadline:  # killed; gone once its parent (init) reaps it
        try:
            stat = Path(f"/proc/{grandchild}/stat").read_text()
        except FileNotFoundError:
            break
        if stat.rsplit(")", 1)[1].split()[0] == "Z":
            break
        time.sleep(0.05)
    else:
        pytest.fail(f"the command's child {grandchild} outlived the timeout")


def test_a_command_that_ends_gives_its_output_and_code() -> None:
    proc = run_tree(["sh", "-c", "echo out; echo err >&2; exit 3"], 30)
    assert (proc.returncode, proc.stdout, proc.stderr) == (3, "out\n", "err\n")
