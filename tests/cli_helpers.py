"""Running the ``wara`` command from tests: in-process through :func:`wara.cli.main`
(stdout and stderr captured, usable inside hypothesis tests where the capsys fixture is
not), or as a subprocess through ``sys.executable -m wara``."""

from __future__ import annotations

import contextlib
import io
import os
import subprocess
import sys
from pathlib import Path

from wara.cli import main

REPO = Path(__file__).resolve().parents[1]


def run_main(args: list[str]) -> tuple[int, str, str]:
    """``(exit code, stdout, stderr)`` of ``wara ARGS`` run in this process."""
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        code = main(args)
    return code, out.getvalue(), err.getvalue()


def run_wara(
    args: list[str], timeout_s: float = 120, cwd: Path = REPO
) -> subprocess.CompletedProcess[str]:
    """``wara ARGS`` as a child process of this checkout (its PYTHONPATH; run in ``cwd``,
    default the checkout's directory), text output captured, never checked."""
    return subprocess.run(
        [sys.executable, "-m", "wara", *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        check=False,
    )
