"""Running the ``wara`` command from tests: in-process through :func:`wara.cli.main`
(stdout and stderr captured, usable inside hypothesis tests where the capsys fixture is
not), or as a subprocess through ``sys.executable -m wara`` (:func:`run_wara`), optionally
with a hook that keeps what the command computed besides what it prints
(:func:`run_wara_observed`)."""

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


def run_wara_observed(
    args: list[str], hook: str, out: Path, timeout_s: float = 120, cwd: Path = REPO
) -> subprocess.CompletedProcess[str]:
    """:func:`run_wara` with a hook: the child process calls ``hook``
    (``"module:function"``) with ``out`` first, then runs ``wara ARGS`` as ``python -m
    wara`` would. The hook wraps a function the command calls and writes what it returned
    or saw to ``out``, so that one run serves the tests of its printed output and those of
    the figures behind it (e.g. the summary behind ``wara demo``'s table)."""
    module, func = hook.split(":")
    code = (
        "import runpy, sys\n"
        "from importlib import import_module\n"
        f"getattr(import_module({module!r}), {func!r})({str(out)!r})\n"
        f"sys.argv = ['wara', *{args!r}]\n"
        "runpy.run_module('wara', run_name='__main__', alter_sys=True)\n"
    )
    return subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        check=False,
    )
