"""``wara bench demo --runs N [--cpu-hog] --json``: the README's main command, N times.

Each run is ``wara demo --json`` (the default form: the ring cycles in simulated time;
``--realtime``: ``wara demo --realtime --json``, on the wall clock, one process) started
as a user starts it, a new interpreter through ``sys.executable -m
wara``, in a directory of its own (the demo writes ``./wara-demo``), one after another.
Per run: exit code, wall time, the verdict and, for a run that did not pass, the reason
(the demo's own one-line reason: the cycle's error or the service's latched faults, or
the ring that missed its goals; the end of its stderr when it printed no JSON), and what
the run rode through (the service's ``ride_through`` suspends/resumes, the loop's
overruns and its longest cycle).

``--cpu-hog``: a CPU-bound process pinned to one CPU runs beside the demos for the whole
bench (a busy neighbour, as on a shared IPC). ``--quick``: the demo with ``--rings 1``
(with ``--attitude``: ``--examples 1``). ``--attitude``: ``wara demo --attitude --json``,
the attitude examples.
Progress on stderr, one JSON object on stdout.

Goals: every run passes on a quiet machine; with ``--cpu-hog`` at least 95 % pass and a
run that fails fails fast (exits within :data:`FAIL_FAST_S` with its reason).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

#: A run that does not pass must end within this long after its first example started
#: failing; the bench reports the longest wall time of a failed run against it.
FAIL_FAST_S = 120.0
#: A run longer than this is killed and counted as a failure.
RUN_TIMEOUT_S = 900.0

_HOG = "import os, sys\nos.sched_setaffinity(0, {int(sys.argv[1])})\nwhile True:\n    pass\n"


def demo_command(
    config: str | None, *, quick: bool, attitude: bool = False, realtime: bool = False
) -> list[str]:
    """The README's main command as this interpreter runs it, with ``--json``."""
    cmd = [sys.executable, "-m", "wara", "demo", "--json"]
    if attitude:
        cmd += ["--attitude"]
    elif realtime:
        cmd += ["--realtime"]
    if config:
        cmd += ["--config", config]
    if quick:
        cmd += ["--examples", "1"] if attitude else ["--rings", "1"]
    return cmd


@contextlib.contextmanager
def cpu_hog(enabled: bool) -> Iterator[int | None]:
    """A busy loop pinned to the last CPU this process may use; yields that CPU."""
    if not enabled:
        yield None
        return
    cpu = max(os.sched_getaffinity(0))
    proc = subprocess.Popen([sys.executable, "-c", _HOG, str(cpu)], stdin=subprocess.DEVNULL)
    try:
        yield cpu
    finally:
        proc.kill()
        proc.wait(10.0)


def one_run(cmd: list[str], env: dict[str, str]) -> dict[str, Any]:
    """Run the demo once (in a temporary directory); what a user would see, condensed."""
    with tempfile.TemporaryFile() as err, tempfile.TemporaryDirectory() as cwd:
        t0 = time.monotonic()
        try:
            proc = subprocess.run(
                cmd, stdout=subprocess.PIPE, stderr=err, env=env, timeout=RUN_TIMEOUT_S,
                cwd=cwd,
            )  # fmt: skip
            code, out = proc.returncode, proc.stdout.decode(errors="replace")
        except subprocess.TimeoutExpired as exc:
            code = None
            out = (exc.stdout or b"").decode(errors="replace")
        wall = time.monotonic() - t0
        err.seek(0)
        stderr_tail = err.read().decode(errors="replace").strip().splitlines()[-3:]
    try:
        summary: dict[str, Any] = json.loads(out)
    except json.JSONDecodeError:
        summary = {}
    passed = code == 0 and bool(summary.get("passed"))
    loop = summary.get("loop") or {}
    rt = summary.get("ride_through") or {}
    reason = ""
    if not passed:
        if code is None:
            reason = f"killed after {RUN_TIMEOUT_S:g} s"
        elif summary:
            from wara.demo import failure_reason

            reason = failure_reason(summary)
        else:
            reason = f"exit {code}, no JSON: " + " | ".join(stderr_tail)
    return {
        "exit_code": code,
        "wall_s": round(wall, 2),
        "passed": passed,
        "reason": reason,
        "suspends": int(rt.get("suspends", 0)),
        "resumes": int(rt.get("resumes", 0)),
        "overruns": loop.get("overruns"),
        "worst_cycle_ms": loop.get("worst_overrun_cycle_ms"),
        "jitter_p99_ms": loop.get("jitter_p99_ms"),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    runs = int(getattr(args, "runs", None) or 5)
    if runs < 1:
        from wara.cli import UsageError

        raise UsageError("--runs must be at least 1")
    cmd = demo_command(
        getattr(args, "config", None),
        quick=bool(getattr(args, "quick", False)),
        attitude=bool(getattr(args, "attitude", False)),
        realtime=bool(getattr(args, "realtime", False)),
    )
    repo = str(Path(__file__).resolve().parents[2])
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(
        dict.fromkeys([repo, *filter(None, env.get("PYTHONPATH", "").split(os.pathsep))])
    )
    hog = bool(getattr(args, "cpu_hog", False))
    load_before = [round(x, 2) for x in os.getloadavg()]
    results: list[dict[str, Any]] = []
    with cpu_hog(hog) as hog_cpu:
        for i in range(runs):
            r = one_run(cmd, env)
            results.append(r)
            print(
                f"wara bench demo: run {i + 1}/{runs}: "
                f"{'passed' if r['passed'] else 'FAILED'} exit {r['exit_code']} "
                f"{r['wall_s']:.1f} s, suspends {r['suspends']}, overruns {r['overruns']}"
                + (f": {r['reason']}" if r["reason"] else ""),
                file=sys.stderr,
                flush=True,
            )
    walls = [r["wall_s"] for r in results]
    failed = [r for r in results if not r["passed"]]
    passes = runs - len(failed)
    return {
        "bench": "demo",
        "command": ["wara", *cmd[3:]],
        "runs": runs,
        "passes": passes,
        "pass_fraction": passes / runs,
        "cpu_hog": {"cpu": hog_cpu} if hog else None,
        "cpus": len(os.sched_getaffinity(0)),
        "load_average_before": load_before,
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "wall_s": {
            "min": min(walls),
            "median": statistics.median(walls),
            "max": max(walls),
        },
        "failed_wall_s_max": max((r["wall_s"] for r in failed), default=None),
        "suspends_total": sum(r["suspends"] for r in results),
        "resumes_total": sum(r["resumes"] for r in results),
        "failure_reasons": [r["reason"] for r in failed],
        "per_run": results,
        "goal": {
            "pass_fraction": 0.95 if hog else 1.0,
            "fail_fast_s": FAIL_FAST_S,
            "met": passes / runs >= (0.95 if hog else 1.0)
            and all(r["wall_s"] <= FAIL_FAST_S for r in failed),
        },
    }
