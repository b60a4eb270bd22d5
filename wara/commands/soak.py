"""``wara soak --minutes M [--json]``: the two-process form, moving for M minutes.

The simulator and the service run as two processes on a UDP multicast CAN bus in a
private network namespace (as ``wara demo --two-process``, :mod:`wara.demo_two_process`).
The soak moves the machine from target to target across the reachable workspace
(roll ``±ROLL_DEG``, pitch ``±PITCH_DEG``): each target is drawn at random (``--seed``)
and kept only if the planner finds it feasible from where the previous one ends (after
:data:`MAX_DRAWS` infeasible draws, the move to level); it goes
to the service through its control socket (as ``wara ctl adjust``), the soak waits for
COMPLETE, holds ``HOLD_S`` and draws the next, until the time is up.

Reported (JSON on stdout with ``--json``, else a few lines; a progress line on stderr per
move and every ~10 s): moves done and refused, loop cycles and overruns after start-up
(the service's own counts), the loop's wake-up latency (jitter) p99.9 and max, suspends
and resumes ridden through (the service status' ``ride_through``; 0 where it has none),
and the latched faults (when and why). After a latched fault the soak resets the service
(``wara ctl reset``) and goes on; it ends at :data:`MAX_FAULTS` of them or when the
reset does not bring the service back. Exit 0 only with no latched fault and every
move done; 1 otherwise; 2 when the namespace cannot be made.

Jitter p99.9 is taken over every cycle of the soak from the run record's ``samples.csv``
(one row per cycle, ``t_s`` the wake-up time): the loop's deadlines lie on the grid
``t_0 + n * period`` (the loop skips whole periods after an overrun), so each row's
latency is its distance above the last grid point not taken by an earlier row (exact
while wake-ups are less than a period late; a lower bound for a later one, which reads
as a skip). The max is the larger of that and the loop's own ``jitter_max_ms`` reports
(every 5 s over the last 4096 cycles, so every cycle is in one).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from config import units
from config.numbers import decimal, integer
from wara.cli import EXIT_FAILED, EXIT_OK, EXIT_USAGE, UsageError
from wara.extras import require_realtime_simulator
from wara.loop_phases import latency_ms, record_times

#: The workspace the targets are drawn from (the planner bench's), degrees.
ROLL_DEG = 8.0
PITCH_DEG = 4.0
#: Standstill held at each target before the next move.
HOLD_S = 2.0
#: Progress line at least this often.
PROGRESS_EVERY_S = 10.0
#: Draws per target before the soak gives up finding a feasible one.
MAX_DRAWS = 50
#: After a latched fault the soak resets the service and goes on; it ends at this many.
MAX_FAULTS = 5
#: Targets the service may refuse (infeasible from where it measures) before the end.
MAX_REFUSED = 10


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("soak", help="two-process soak: move across the workspace for M minutes")
    p.add_argument("--minutes", type=decimal, required=True, metavar="M", help="soak length")
    p.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    p.add_argument("--seed", type=integer, default=0, help="seed of the random targets")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument(
        "--transport",
        choices=("wara_udp", "udp_multicast"),
        default="wara_udp",
        help="the cross-process CAN interface",
    )
    p.add_argument("--no-pin", action="store_true", help="leave CPU placement to the scheduler")
    p.add_argument("--inside-netns", default=None, metavar="DIR", help=argparse.SUPPRESS)
    p.add_argument("--keep-dir", default=None, metavar="DIR", help=argparse.SUPPRESS)
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from wara import demo_two_process as d2

    if not (math.isfinite(args.minutes) and args.minutes > 0):
        raise UsageError("--minutes must be a positive number")
    require_realtime_simulator()
    if args.inside_netns is None:
        inner = ["soak", "--minutes", repr(args.minutes), "--seed", str(args.seed)]
        if args.json:
            inner.append("--json")
        try:
            return d2.run_in_netns(
                inner,
                args.config,
                keep_dir=Path(args.keep_dir) if args.keep_dir else None,
                transport=args.transport,
                pin=not args.no_pin,
            )
        except d2.NetnsUnavailable as exc:
            print(f"wara soak: needs a private network namespace: {exc}", file=sys.stderr)
            return EXIT_USAGE
    try:
        summary = soak(Path(args.inside_netns), args.config, args.minutes * 60.0, args.seed)
    except (d2.TwoProcessError, d2.CtlError) as exc:
        print(f"wara soak: failed: {exc}", file=sys.stderr)
        if args.json:
            print(json.dumps({"passed": False, "error": str(exc)}))
        return EXIT_FAILED
    print(json.dumps(summary, indent=2) if args.json else render(summary))
    return EXIT_OK if summary["passed"] else EXIT_FAILED


def _say(text: str) -> None:
    print(f"wara soak: {text}", file=sys.stderr, flush=True)


class NoTarget(Exception):
    """The planner found no feasible target in :data:`MAX_DRAWS` draws."""


class TargetDrawer:
    """Random targets the planner finds feasible from where the previous one ends."""

    def __init__(self, cfg: Any, seed: int) -> None:
        self.cfg = cfg
        self.rng = np.random.default_rng(seed)
        self.upper: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self.lower: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
        self.infeasible = 0
        #: Moves to level taken because :data:`MAX_DRAWS` draws were all infeasible.
        self.to_level = 0

    def start_from(self, status: dict[str, Any]) -> None:
        """The next target is planned from the rods' measured positions (the service's
        status, mm from the retracted end), where the service plans it from too."""
        pos = status.get("positions_mm") or {}
        by_id = {c.id: c for c in self.cfg.cylinders}

        def layer(ids: Any) -> tuple[float, float, float, float] | None:
            if len(ids) != 4 or any(pos.get(i) is None for i in ids):
                return None
            d = [units.mm(float(pos[i])) - by_id[i].stroke_m / 2 for i in ids]
            return (d[0], d[1], d[2], d[3])

        up, lo = layer(self.cfg.layers.upper.cylinders), layer(self.cfg.layers.lower.cylinders)
        if up is not None and lo is not None:
            self.upper, self.lower = up, lo

    def next(self) -> tuple[float, float]:
        from ipc_app.planner import plan

        for _ in range(MAX_DRAWS):
            roll = round(float(self.rng.uniform(-ROLL_DEG, ROLL_DEG)), 2)
            pitch = round(float(self.rng.uniform(-PITCH_DEG, PITCH_DEG)), 2)
            p = plan(self.cfg, roll, pitch, start_upper_m=self.upper, start_lower_m=self.lower)
            if p.feasible:
                self.upper = tuple(p.upper.displacement_m)  # type: ignore[assignment]
                self.lower = tuple(p.lower.displacement_m)  # type: ignore[assignment]
                return roll, pitch
            self.infeasible += 1
        # A pose from which the random draws are all infeasible (rods near their planning
        # limits) still has a way back: the move to level.
        p = plan(self.cfg, 0.0, 0.0, start_upper_m=self.upper, start_lower_m=self.lower)
        if p.feasible:
            self.upper = tuple(p.upper.displacement_m)  # type: ignore[assignment]
            self.lower = tuple(p.lower.displacement_m)  # type: ignore[assignment]
            self.to_level += 1
            return 0.0, 0.0
        raise NoTarget(f"no feasible target in {MAX_DRAWS} draws, nor the move to level")


def jitter_figures(
    latency_ms_: np.ndarray, reported_max_ms: float | None
) -> tuple[float | None, float | None]:
    """(p99.9, max) of the soak's wake-up latency: p99.9 over the record's cycles, the max
    also over the loop's own reports (which see latencies beyond a period exactly)."""
    p999 = float(np.percentile(latency_ms_, 99.9)) if latency_ms_.size else None
    maxima = [float(reported_max_ms)] if reported_max_ms is not None else []
    if latency_ms_.size:
        maxima.append(float(latency_ms_.max()))
    return p999, (max(maxima) if maxima else None)


def _record_latency(workdir: Path, period_s: float) -> np.ndarray:
    runs = sorted((workdir / "runs").glob("*/samples.csv"))
    if not runs:
        return np.zeros(0)
    return latency_ms(record_times(runs[-1].parent), period_s)


def soak(workdir: Path, config_path: str, duration_s: float, seed: int) -> dict[str, Any]:
    """The soak inside the namespace; the JSON-ready summary (``passed``)."""
    from config import load_project
    from wara import demo_two_process as d2
    from wara.demo import ride_through

    cfg = load_project(config_path)
    period = cfg.control.period_s
    drawer = TargetDrawer(cfg, seed)
    watch = d2.LoopWatch()
    codes: dict[str, int] = {}
    moves: list[dict[str, Any]] = []
    refused: list[str] = []
    faults: list[dict[str, Any]] = []
    final: dict[str, Any] = {}
    stopped: str | None = None
    last_progress = 0.0

    def progress(st: dict[str, Any], force: bool = False) -> None:
        nonlocal last_progress
        now = time.monotonic()
        if not force and now - last_progress < PROGRESS_EVERY_S:
            return
        last_progress = now
        loop = st.get("loop") or {}
        rt = ride_through(st)
        _say(
            f"{now - t_start:6.0f} s: {len(moves)} moves, mode {st.get('mode')}, cycles "
            f"{loop.get('cycles')}, overruns {loop.get('overruns')}, jitter max "
            f"{loop.get('jitter_max_ms', math.nan):.2f} ms, suspends {rt['suspends']}"
        )

    with d2.service_and_simulator(workdir, config_path, _say, codes) as (svc, _sim, placement):

        def first_report(s: dict[str, Any]) -> bool:
            watch.see(s)
            return watch.baseline is not None

        if svc.wait(first_report, 15.0, poll_s=0.2) is None:
            raise d2.TwoProcessError("the service published no loop statistics in 15 s")
        t_start = time.monotonic()
        end = t_start + duration_s

        def latch(st: dict[str, Any] | None, what: str) -> bool:
            """Count a latched fault, reset the service; False when the soak must end."""
            reasons = list((st or {}).get("fault_reasons") or [what])
            faults.append({"at_s": round(time.monotonic() - t_start, 1), "reasons": reasons})
            _say(f"LATCHED FAULT: {'; '.join(reasons)}")
            if len(faults) >= MAX_FAULTS or (st or {}).get("mode") not in ("ABORTED",):
                return False
            svc.call("reset")
            back = svc.wait(lambda s: s.get("mode") in ("IDLE", "COMPLETE"), 10.0)
            _say(f"reset: {'back in ' + back['mode'] if back else 'the service stays faulted'}")
            if back is not None:
                drawer.start_from(back)
            return back is not None

        while time.monotonic() < end:
            try:
                roll, pitch = drawer.next()
            except NoTarget as exc:
                stopped = str(exc)
                _say(f"stopped: {exc}")
                break
            t0 = time.monotonic()
            reply = svc.call("adjust", roll_deg=roll, pitch_deg=pitch)
            if not reply.get("ok"):
                st = svc.status()
                drawer.start_from(st)
                if st.get("mode") in ("ABORTED",):
                    if not latch(st, "refused in ABORTED"):
                        break
                    continue
                why = reply.get("error") or reply.get("reasons") or reply.get("code")
                refused.append(f"({roll:+.2f}, {pitch:+.2f}): {why}")
                _say(f"target ({roll:+.2f}, {pitch:+.2f}) refused: {why}")
                if len(refused) >= MAX_REFUSED:
                    break
                continue

            def settled(st: dict[str, Any], r: float = roll, p: float = pitch) -> bool:
                watch.see(st)
                progress(st)
                mode = st.get("mode")
                if mode == "COMPLETE":
                    tgt = (st.get("motion") or {}).get("target_deg") or [math.nan] * 2
                    return abs(tgt[0] - r) < 1e-9 and abs(tgt[1] - p) < 1e-9
                return mode in ("ABORTED", "IDLE")

            done = svc.wait(settled, timeout_s=300.0, poll_s=0.25)
            if done is None or done.get("mode") != "COMPLETE":
                mode = None if done is None else done.get("mode")
                if not latch(done, f"move ended in {mode}"):
                    break
                continue
            drawer.start_from(done)
            m = done.get("motion") or {}
            moves.append(
                {
                    "target_deg": [roll, pitch],
                    "wall_s": round(time.monotonic() - t0, 2),
                    "duration_s": m.get("duration_s"),
                    "max_sync_error_mm": m.get("max_sync_error_mm"),
                    "max_twist_mm": m.get("max_twist_mm"),
                }
            )
            _say(
                f"move {len(moves)} to ({roll:+.2f}, {pitch:+.2f}) deg done in "
                f"{moves[-1]['wall_s']:.1f} s"
            )
            hold_end = min(end, time.monotonic() + HOLD_S)
            ok = True
            while ok and time.monotonic() < hold_end:
                st = svc.status()
                watch.see(st)
                if st.get("mode") in ("ABORTED",):
                    ok = latch(st, "fault while holding")
                    break
                time.sleep(0.25)
            if not ok:
                break
        # one more loop report, so the last moves are in the figures
        n_reports = len(watch.reports)

        def reported(st: dict[str, Any]) -> bool:
            watch.see(st)
            return len(watch.reports) > n_reports

        svc.wait(reported, 10.0, 0.5)
        final = svc.status()
        watch.see(final)
        if final.get("mode") in ("ABORTED",):
            faults.append(
                {
                    "at_s": round(time.monotonic() - t_start, 1),
                    "reasons": list(final.get("fault_reasons") or []),
                }
            )
        progress(final, force=True)
    lat = _record_latency(workdir, period)
    loop = watch.summary(period)
    jitter_p999, jitter_max = jitter_figures(lat, loop.get("jitter_max_ms"))
    rt = ride_through(final)
    return {
        "mode": "soak (two processes)",
        "minutes": duration_s / 60.0,
        "seed": seed,
        "placement": placement,
        "moves": len(moves),
        "moves_refused": refused,
        "targets_infeasible_skipped": drawer.infeasible,
        "moves_to_level": drawer.to_level,
        "stopped_early": stopped,
        "cycles": loop.get("measured_cycles"),
        "overruns": loop.get("overruns"),
        "overruns_startup": loop.get("overruns_startup"),
        "jitter_p999_ms": jitter_p999,
        "jitter_max_ms": jitter_max,
        "jitter_p99_ms": loop.get("jitter_p99_ms"),
        "compute_p99_ms": loop.get("compute_p99_ms"),
        "record_cycles": int(lat.size),
        "suspends": rt["suspends"],
        "resumes": rt["resumes"],
        "latched_faults": faults,
        "final_mode": final.get("mode"),
        "exit_codes": codes,
        "per_move": moves,
        "passed": not faults and not refused and stopped is None and bool(moves),
    }


def render(s: dict[str, Any]) -> str:
    def ms(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f} ms"

    return "\n".join(
        [
            f"soak: {s['minutes']:g} min, {s['moves']} moves (seed {s['seed']}), "
            f"{s['cycles']} cycles after start-up, overruns {s['overruns']}",
            f"jitter p99.9 {ms(s['jitter_p999_ms'])}, max {ms(s['jitter_max_ms'])}; "
            f"suspends {s['suspends']}, resumes {s['resumes']}",
            f"latched faults: {len(s['latched_faults'])}"
            + "".join(
                f"\n  at {f['at_s']:g} s: {'; '.join(f['reasons'])}" for f in s["latched_faults"]
            ),
            *([f"stopped early: {s['stopped_early']}"] if s["stopped_early"] else []),
            "PASSED" if s["passed"] else "FAILED",
        ]
    )
