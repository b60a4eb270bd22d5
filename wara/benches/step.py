"""``wara bench step --json``: the CPU of one ``ServiceCore.step`` per mode, in lockstep.

The HIL simulator and the service alternate in one thread on the in-process ``virtual``
bus (:class:`wara.harness.Harness` in ``lockstep``), with the real planner worker process and a
run record in a temporary directory, as in the service: IDLE, then Example 1 (roll 2,
pitch 1 deg) through STARTING, EXECUTE and COMPLETE. Logs go to stderr (JSON lines), the
result to stdout. Each step is timed around
``ServiceCore.step`` only (the simulator's step is not counted): the loop thread's CPU
(``time.thread_time_ns``) and the wall time, as p50 / p99 / max in ms per mode (the mode
at the start of the step) and over all steps. Before the first timed step the start-up
heap is frozen, as the service's loop does.

``--quick``: 0.5 s of IDLE and 1 s of COMPLETE instead of 3 s and 4 s (the motion takes
its 6.1 s either way). Compare figures as ratios within one run or between runs close
in time: the machine is shared.

``--baseline DIR [--runs N]``: this checkout against another revision's checkout in DIR
(e.g. ``git worktree add /tmp/base REV``), in one run: N rounds, each a bench of this
one and one of DIR's (in that order, alternating first), each in a fresh interpreter
on this interpreter's packages, with DIR's project packages first on ``sys.path``. The
result: per round and as the median over rounds, the ratio this / baseline of the CPU
p50 and p99 of all steps and of each mode. The modes are paired by their order in the
bench's sequence (idle, planning, motion, hold), so revisions that name them
differently compare too. Interleaving cancels the machine's drift; the spread of the
per-round ratios says how far to trust the median.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from config import load_project, units
from ipc_app.service.core import ServiceCore
from ipc_app.service.logs import configure_logging
from ipc_app.service.loop import freeze_startup_heap
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder

EXAMPLE = (2.0, 1.0)


def _figures(cpu_ns: list[int], wall_ns: list[int]) -> dict[str, Any]:
    cpu = np.asarray(cpu_ns, dtype=float) * (units.NS / units.MS)
    wall = np.asarray(wall_ns, dtype=float) * (units.NS / units.MS)
    if cpu.size == 0:
        return {"steps": 0}
    return {
        "steps": int(cpu.size),
        "cpu_p50_ms": round(float(np.percentile(cpu, 50)), 4),
        "cpu_p99_ms": round(float(np.percentile(cpu, 99)), 4),
        "cpu_max_ms": round(float(cpu.max()), 4),
        "wall_p50_ms": round(float(np.percentile(wall, 50)), 4),
        "wall_p99_ms": round(float(np.percentile(wall, 99)), 4),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    if getattr(args, "baseline", None) is not None:
        return run_against(args)
    from wara.harness import Harness  # the simulator: only for this bench

    config_path = getattr(args, "config", None)
    quick = bool(getattr(args, "quick", False))
    idle_s, hold_s = (0.5, 1.0) if quick else (3.0, 4.0)
    cfg = load_project(config_path)
    # JSON lines on stderr, as in the service; loggers not cached (no logging per step)
    logging_handle = configure_logging("INFO", cache_loggers=False)
    samples: dict[str, tuple[list[int], list[int]]] = {str(m): ([], []) for m in Mode}
    with tempfile.TemporaryDirectory(prefix="wara-bench-step-") as tmp:
        record = RunRecorder(Path(tmp) / "run", ServiceCore.record_columns(cfg))
        record.start()
        harness = Harness(cfg, config_path, mode="lockstep", record=record)
        core = harness.core
        step = core.step
        timing = [False]
        thread_ns = time.thread_time_ns
        wall_ns = time.perf_counter_ns

        def timed(cycle: int, now: float) -> None:
            if not timing[0]:
                step(cycle, now)
                return
            mode = str(core.modes.mode)
            w0 = wall_ns()
            c0 = thread_ns()
            step(cycle, now)
            c1 = thread_ns()
            w1 = wall_ns()
            cpu, wall = samples[mode]
            cpu.append(c1 - c0)
            wall.append(w1 - w0)

        core.step = timed  # type: ignore[method-assign]
        try:
            harness.start()
            if not harness.wait_for(Mode.IDLE, 20.0):
                raise RuntimeError(f"service did not come up: {core.modes.snapshot()}")
            harness.advance(0.5)  # the first frames of every message, the first status
            freeze_startup_heap()
            timing[0] = True
            harness.advance(idle_s)
            out = core.request_adjust(*EXAMPLE)
            if not out.get("ok"):
                raise RuntimeError(f"adjust refused: {out}")
            if not harness.wait_for(Mode.EXECUTE, 60.0):
                raise RuntimeError(f"no plan: {core.modes.snapshot()}")
            if not harness.wait_for(Mode.COMPLETE, 60.0):
                raise RuntimeError(f"did not finish: {core.modes.snapshot()}")
            harness.advance(hold_s)
            final_mode = str(core.modes.mode)
        finally:
            timing[0] = False
            harness.close()
            record.stop()
            logging_handle.stop()
    modes = {m: _figures(*v) for m, v in samples.items() if v[0]}
    all_cpu = [x for v in samples.values() for x in v[0]]
    all_wall = [x for v in samples.values() for x in v[1]]
    return {
        "bench": "step",
        "example_deg": list(EXAMPLE),
        "period_ms": units.to_ms(cfg.control.period_s),
        "final_mode": final_mode,
        "modes": modes,
        "all": _figures(all_cpu, all_wall),
        "quick": quick,
    }


def _bench_in(checkout: Path | None, quick: bool, config_path: str | None) -> dict[str, Any]:
    """One ``wara bench step --json`` in a fresh interpreter; ``checkout`` first on the
    path (None: this one)."""
    where = (checkout or Path(__file__).resolve().parents[2]).resolve()
    env = dict(os.environ, PYTHONPATH=str(where))
    cmd = [sys.executable, "-m", "wara", "bench", "step", "--json"]
    if quick:
        cmd.append("--quick")
    if config_path:
        cmd += ["--config", str(Path(config_path).resolve())]
    # cwd: `-m` puts the working directory first on sys.path, ahead of PYTHONPATH
    out = subprocess.run(cmd, env=env, cwd=where, capture_output=True, text=True, check=False)
    if out.returncode != 0:
        tail = out.stderr.strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"bench step in {where} failed: {tail[0]}")
    result: dict[str, Any] = json.loads(out.stdout)
    return result


def _ratios(cur: dict[str, Any], base: dict[str, Any]) -> dict[str, dict[str, float]]:
    pairs = [("all", cur["all"], base["all"])]
    if len(cur["modes"]) == len(base["modes"]):  # else the sequences differ: all only
        pairs += [
            (name, cur["modes"][name], b)
            for name, b in zip(cur["modes"], base["modes"].values(), strict=True)
        ]
    out: dict[str, dict[str, float]] = {}
    for name, c, b in pairs:
        out[name] = {k: c[k] / b[k] for k in ("cpu_p50_ms", "cpu_p99_ms") if b.get(k)}
    return out


def run_against(args: argparse.Namespace) -> dict[str, Any]:
    """``--baseline DIR``: this checkout and DIR's, interleaved (module docstring)."""
    base_dir = Path(args.baseline)
    if not (base_dir / "wara" / "benches" / "step.py").is_file():
        raise RuntimeError(f"--baseline {base_dir}: not a checkout with wara/benches/step.py")
    rounds = int(args.runs or 5)
    quick = bool(getattr(args, "quick", False))
    config_path = getattr(args, "config", None)
    per_round: list[dict[str, dict[str, float]]] = []
    for i in range(rounds):
        order = (None, base_dir) if i % 2 == 0 else (base_dir, None)
        res = {str(d): _bench_in(d, quick, config_path) for d in order}
        per_round.append(_ratios(res["None"], res[str(base_dir)]))
        print(f"wara bench step: round {i + 1}/{rounds}: {per_round[-1]['all']}", file=sys.stderr)
    median = {
        name: {
            k: round(float(np.median([r[name][k] for r in per_round])), 3)
            for k in per_round[0][name]
        }
        for name in per_round[0]
    }
    spread = {
        name: {
            k: [
                round(min(r[name][k] for r in per_round), 3),
                round(max(r[name][k] for r in per_round), 3),
            ]
            for k in per_round[0][name]
        }
        for name in per_round[0]
    }
    return {
        "bench": "step",
        "against": str(base_dir),
        "rounds": rounds,
        "quick": quick,
        "ratio_median": median,
        "ratio_range": spread,
    }
