"""``wara bench harness --json``: how fast the lockstep harness runs, and how a campaign
scales on Dask.

- ``lockstep``: Example 1 (roll 2, pitch 1 deg) from the level start, planned, moved,
  settled and held, on :class:`wara.harness.Harness` in lockstep in this process (one
  thread; the planner in its own process, started before the clock starts), as a
  campaign task runs it (no trace). ``realtime_factor_cpu`` is simulated time over this
  process's CPU time (what one core gives, whatever else the machine runs; goal >= 20);
  ``realtime_factor_wall`` over the wall time. ``cpu_split_s``: where the CPU time went,
  from a second run with each call timed by ``time.process_time`` (the headline run
  carries no timers): the simulator's PLC scans (``simulator``), of them the compiled
  scans (``compiled_scans``: the emulated PLC and the plant in machine code,
  :mod:`hil_sim.plc_fast`), the plant kernel called from Python (``plant_kernel``: the
  scans that run as Python) and the rest, the simulator's Python (``plc_scan_python``:
  the frames in and out through the wire, the Python scans); the service core's steps
  (``service_core``: the IPC's link, codec and supervision, the controllers, the
  interlocks); the harness's own loop (``rest``). ``cpu_share``: each over that run's
  CPU time (``split_run_cpu_s``).
- ``campaign``: a small campaign (short targets, ``runs`` runs) on an embedded
  LocalCluster of 1 and of 2 worker processes, timed from the first submit (cluster up,
  workers warmed): runs per minute, and the engine's overhead as a share of task time,
  ``(workers x elapsed - sum(task wall time)) / sum(task wall time)``, split into
  ``tail_share`` (a worker idle after its last run because none is left for it: the
  campaign's granularity) and
  ``engine_gap_share`` (the rest: scheduling, transfer and the client writing the Parquet
  files), each over the task time (goal < 5 %).

``--quick``: two runs per campaign instead of six. The machine is shared: compare
ratios, and say how loaded it was (``load_average``).

``--baseline DIR [--runs N]``: the ``lockstep`` part of this checkout against another
revision's checkout in DIR, in one run: N rounds (default 5), each one ``lockstep`` of
this checkout and one of DIR's (alternating which goes first), each in a fresh
interpreter: DIR's own (``DIR/.venv/bin/python``) where it has one. The headline:
``realtime_factor_cpu`` of this and of the baseline (medians over the rounds) and
``ratio`` (the median of the rounds' ratios this / baseline, with their range); each
checkout's median ``cpu_share``. No campaign part.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from config import load_project
from config.loader import default_project_path

EXAMPLE = (2.0, 1.0)

#: The campaign of the throughput figures: short targets, no dispersion that slows a run.
_SPEC: dict[str, Any] = {
    "name": "bench",
    "kind": "nominal",
    "seed": 3,
    "run": {"targets": 1, "roll_deg": [-1.0, 1.0], "pitch_deg": [-0.5, 0.5]},
    "dispersions": {
        "hydraulics.bulk_modulus_mpa": {"dist": "uniform", "low": 500, "high": 1200},
    },
}


def lockstep(config_path: str | None) -> dict[str, Any]:
    from ipc_app.service.logs import configure_logging
    from ipc_app.service.worker import PlannerWorker
    from wara.harness import Harness

    logs = configure_logging("ERROR")
    path = config_path or str(default_project_path())
    cfg = load_project(path)
    planner = PlannerWorker(path)
    planner.start()
    try:
        warm = Harness(cfg, path, mode="lockstep", planner=planner, trace=False)
        warm.advance(0.1)  # the compiled plant loaded from numba's cache
        warm.close()
        res, sim_s, cpu, wall = _example_run(cfg, path, planner, None)
        split = dict.fromkeys(("simulator", "compiled_scans", "plant_kernel", "service_core"), 0.0)
        _, _, timed_cpu, _ = _example_run(cfg, path, planner, split)
    finally:
        planner.close()
        logs.stop()
    # the simulator's scans less the machine code: its Python (the frames through the
    # wire, the Python scans); the rest: the harness's own loop and the logs
    split["plc_scan_python"] = split["simulator"] - split["compiled_scans"] - split["plant_kernel"]
    split["rest"] = timed_cpu - split["simulator"] - split["service_core"]
    return {
        "example": list(EXAMPLE),
        "passed": res.passed,
        "simulated_s": round(sim_s, 3),
        "cpu_s": round(cpu, 3),
        "wall_s": round(wall, 3),
        "realtime_factor_cpu": round(sim_s / cpu, 2),
        "realtime_factor_wall": round(sim_s / wall, 2),
        "goal_realtime_factor": 20,
        "cpu_split_s": {k: round(v, 3) for k, v in split.items()},
        "cpu_share": {k: round(v / timed_cpu, 3) for k, v in split.items()},
        "split_run_cpu_s": round(timed_cpu, 3),
    }


def _example_run(
    cfg: Any, path: str, planner: Any, split: dict[str, float] | None
) -> tuple[Any, float, float, float]:
    """One timed run of the example from a new harness: (result, simulated s, CPU s,
    wall s). ``split``: time the parts' calls into it (a second run: the headline run
    carries no timers)."""
    import hil_sim.plc_fast
    from ipc_app.service.modes import Mode
    from wara.harness import Harness

    h = Harness(cfg, path, mode="lockstep", planner=planner, trace=False)
    kernel = hil_sim.plc_fast.run_scans
    try:
        if split is not None:
            _time_calls(h.sim, "step", split, "simulator")
            _time_calls(hil_sim.plc_fast, "run_scans", split, "compiled_scans")
            _time_calls(h.sim.rig, "advance", split, "plant_kernel")
            _time_calls(h.core, "step", split, "service_core")
        c0, w0 = time.process_time(), time.perf_counter()
        h.wait_for(Mode.IDLE, 20.0)
        res = h.run_example(*EXAMPLE)
        cpu, wall = time.process_time() - c0, time.perf_counter() - w0
        return res, h.sim.t_s, cpu, wall
    finally:
        hil_sim.plc_fast.run_scans = kernel
        h.close()


def _time_calls(obj: Any, name: str, acc: dict[str, float], key: str) -> None:
    """Add the CPU time of every call of ``obj.name`` to ``acc[key]`` (an instance or
    module attribute over the function: the harness, the simulator and its compiled
    scans call it through ``obj``)."""
    method = getattr(obj, name)
    clock = time.process_time

    def timed(*args: Any) -> Any:
        t0 = clock()
        try:
            return method(*args)
        finally:
            acc[key] += clock() - t0

    setattr(obj, name, timed)


def campaign(workers: int, runs: int) -> dict[str, Any]:
    from config.loader import validate_data
    from wara.campaign.engine import run_campaign
    from wara.campaign.spec import Campaign, CampaignSpec

    data = dict(_SPEC, requirement={"runs": runs})
    spec = validate_data(CampaignSpec, data, "bench spec")
    c = Campaign(spec, "bench spec", Path("."))
    with tempfile.TemporaryDirectory(prefix="wara-bench-campaign-") as tmp:
        o = run_campaign(c, Path(tmp) / "camp", workers=workers, progress=False)
    busy = o.workers * o.elapsed_s
    return {
        "workers": o.workers,
        "runs": o.written,
        "failed": o.failures,
        "elapsed_s": round(o.elapsed_s, 2),
        "runs_per_minute": round(60.0 * o.written / o.elapsed_s, 2) if o.elapsed_s else None,
        "mean_task_s": round(o.task_s / max(1, o.written), 2),
        "engine_overhead_share": round((busy - o.task_s) / o.task_s, 4) if o.task_s else None,
        # of it, the tail (a worker idle after its last run: none left for it) and the
        # rest, the engine's own gaps between runs, both as shares of task time
        "tail_share": round(o.tail_s / o.task_s, 4) if o.task_s else None,
        "engine_gap_share": round(g, 4) if (g := o.gap_share) is not None else None,
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    if getattr(args, "baseline", None) is not None:
        return run_against(args)
    from wara.extras import require_campaign

    require_campaign()
    quick = bool(getattr(args, "quick", False))
    runs = 2 if quick else 6
    out: dict[str, Any] = {"load_average": [round(x, 2) for x in os.getloadavg()]}
    out["lockstep"] = lockstep(getattr(args, "config", None))
    out["campaign"] = [campaign(1, runs), campaign(2, runs)]
    one, two = out["campaign"]
    if one["runs_per_minute"] and two["runs_per_minute"]:
        out["scaling_2_vs_1"] = round(two["runs_per_minute"] / one["runs_per_minute"], 2)
    out["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    return out


#: run in a fresh interpreter of the checkout measured: its ``lockstep`` as JSON
_LOCKSTEP_CMD = (
    "import json, sys; from wara.benches.harness import lockstep; "
    "print(json.dumps(lockstep(sys.argv[1] or None)))"
)


def _lockstep_in(checkout: Path, config_path: str | None) -> dict[str, Any]:
    """``lockstep`` in a fresh interpreter of ``checkout`` (its own ``.venv`` where it
    has one, else this interpreter with the checkout first on the path)."""
    checkout = checkout.resolve()
    venv = checkout / ".venv" / "bin" / "python"
    python = str(venv) if venv.is_file() else sys.executable
    cfg = str(Path(config_path).resolve()) if config_path else ""
    env = dict(os.environ, PYTHONPATH=str(checkout))
    # cwd: `-c` puts the working directory first on sys.path, ahead of PYTHONPATH
    out = subprocess.run(
        [python, "-c", _LOCKSTEP_CMD, cfg],
        env=env,
        cwd=checkout,
        capture_output=True,
        text=True,
        check=False,
    )
    if out.returncode != 0:
        tail = out.stderr.strip().splitlines()[-1:] or ["no output"]
        raise RuntimeError(f"bench harness in {checkout} failed: {tail[0]}")
    result: dict[str, Any] = json.loads(out.stdout.strip().splitlines()[-1])
    return result


def run_against(args: argparse.Namespace) -> dict[str, Any]:
    """``--baseline DIR``: this checkout's lockstep and DIR's, interleaved (module
    docstring)."""
    from wara.cli import UsageError

    here = Path(__file__).resolve().parents[2]
    base_dir = Path(args.baseline)
    if not (base_dir / "wara" / "benches" / "harness.py").is_file():
        raise UsageError(f"--baseline {base_dir}: not a checkout with wara/benches/harness.py")
    rounds = int(args.runs or 5)
    config_path = getattr(args, "config", None)
    load_before = [round(x, 2) for x in os.getloadavg()]
    this: list[dict[str, Any]] = []
    base: list[dict[str, Any]] = []
    for i in range(rounds):
        order = [(here, this), (base_dir, base)]
        for checkout, into in order if i % 2 == 0 else order[::-1]:
            into.append(_lockstep_in(checkout, config_path))
        ratio = this[-1]["realtime_factor_cpu"] / base[-1]["realtime_factor_cpu"]
        print(
            f"wara bench harness: round {i + 1}/{rounds}: realtime factor (CPU) "
            f"{this[-1]['realtime_factor_cpu']} against {base[-1]['realtime_factor_cpu']}: "
            f"{ratio:.2f}",
            file=sys.stderr,
        )
    ratios = [
        a["realtime_factor_cpu"] / b["realtime_factor_cpu"] for a, b in zip(this, base, strict=True)
    ]

    def median_of(runs: list[dict[str, Any]], key: str) -> float:
        return round(statistics.median(r[key] for r in runs), 2)

    def shares(runs: list[dict[str, Any]]) -> dict[str, float]:
        return {
            k: round(statistics.median(r["cpu_share"][k] for r in runs), 3)
            for k in runs[0]["cpu_share"]
        }

    return {
        "bench": "harness",
        "against": str(base_dir),
        "rounds": rounds,
        "load_average": load_before,
        "load_average_after": [round(x, 2) for x in os.getloadavg()],
        "realtime_factor_cpu": {
            "this": median_of(this, "realtime_factor_cpu"),
            "baseline": median_of(base, "realtime_factor_cpu"),
        },
        "ratio": round(statistics.median(ratios), 3),
        "ratio_range": [round(min(ratios), 3), round(max(ratios), 3)],
        "ratio_per_round": [round(r, 3) for r in ratios],
        "passed": {
            "this": all(r["passed"] for r in this),
            "baseline": all(r["passed"] for r in base),
        },
        "cpu_share": {"this": shares(this), "baseline": shares(base)},
        "realtime_factor_cpu_per_round": {
            "this": [r["realtime_factor_cpu"] for r in this],
            "baseline": [r["realtime_factor_cpu"] for r in base],
        },
    }
