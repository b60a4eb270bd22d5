"""Running the ``wara`` command from tests: in-process through :func:`wara.cli.main`
(stdout and stderr captured, usable inside hypothesis tests where the capsys fixture is
not), or as a subprocess through ``sys.executable -m wara`` (:func:`run_wara`), optionally
with a hook that keeps what the command computed besides what it prints
(:func:`run_wara_observed`)."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

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
    return run_tree([sys.executable, "-m", "wara", *args], timeout_s, cwd)


def run_wara_observed(
    args: list[str], hook: Callable[[str], None], timeout_s: float = 120, cwd: Path = REPO
) -> tuple[subprocess.CompletedProcess[str], Any]:
    """:func:`run_wara` with a hook, and what the hook saw. The child process calls
    ``hook`` (a module-level function of an importable module) with the path of a file
    first, then runs ``wara ARGS`` as ``python -m wara`` would; the hook wraps a function
    the command calls and writes what it returned or saw to that file as JSON (None if it
    wrote nothing). So one run serves the tests of what the command prints and those of
    the figures behind it (e.g. the summary behind ``wara demo``'s table)."""
    with tempfile.TemporaryDirectory(prefix="wara-observed-") as d:
        seen = Path(d) / "seen.json"
        code = (
            "import runpy, sys\n"
            "from importlib import import_module\n"
            f"import_module({hook.__module__!r}).{hook.__name__}({str(seen)!r})\n"
            f"sys.argv = ['wara', *{args!r}]\n"
            "runpy.run_module('wara', run_name='__main__', alter_sys=True)\n"
        )
        proc = run_tree([sys.executable, "-c", code], timeout_s, cwd)
        return proc, json.loads(seen.read_text(encoding="utf-8")) if seen.exists() else None


def run_tree(
    argv: list[str], timeout_s: float, cwd: Path = REPO
) -> subprocess.CompletedProcess[str]:
    """``argv`` in a session of its own (this checkout on its PYTHONPATH), text output
    captured, never checked. After ``timeout_s`` the whole session is killed (the child
    and whatever it started, which would otherwise hold the output's pipes open and the
    test with them) and :class:`subprocess.TimeoutExpired` raised with what it had
    printed."""
    with subprocess.Popen(
        argv,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=cwd,
        env={**os.environ, "PYTHONPATH": str(REPO)},
        start_new_session=True,
    ) as proc:
        try:
            out, err = proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            out, err = proc.communicate()
            raise subprocess.TimeoutExpired(argv, timeout_s, out, err) from None
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)
