"""``wara bench opcua --json``: the loop with and without 10 OPC UA clients, in one run.

The two-process form (``wara demo --two-process``: simulator and service over UDP
multicast in a private network namespace, the loop thread on a CPU of its own). In one
run of the pair: phase ``without`` (no OPC UA server at all) and phase ``with`` (the OPC
UA server process on the service's control socket and 10 clients, asyncua, one process,
each subscribed at 10 Hz to the attitude, the PackML state and every cylinder position);
each phase runs the same adjustment cycles (adjust, COMPLETE, stop to IDLE). The phases
alternate over ``ROUNDS`` rounds in the order without-with, with-without, ... (so a drift
of the machine's load weighs on both alike). Per phase the loop's compute p99 and
overruns (the service's own reports, as the two-process demo judges them); per round the
ratio with/without of the compute p99, and its median over the rounds; for the ``with``
phases the latency from each PackML state change in the loop to its notification at a
client (p50/p99/max; goal p99 < 200 ms).

``--quick``: one round of 2 cycles per phase instead of 3 rounds of 6. Progress on stderr.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from config import load_project, units
from wara import demo_two_process as d2
from wara.demo import stderr_progress

CLIENTS = 10
ROUNDS = 3
LATENCY_GOAL_S = 0.2
TARGETS = ((1.0, 0.5), (-1.0, 0.5))
USER, PASSWORD = "bench", "bench-password"
CLIENT_URI = "urn:wara:bench:client"


def run(args: argparse.Namespace) -> dict[str, Any] | None:
    from wara.extras import require, require_realtime_simulator

    require_realtime_simulator()
    require("asyncua", "wara bench opcua")
    if getattr(args, "inside_netns", None):
        try:
            result = inside(
                Path(args.inside_netns),
                args.config,
                2 if args.quick else 6,
                1 if args.quick else ROUNDS,
            )
        except (d2.TwoProcessError, OSError, ValueError) as exc:  # e.g. a fault latched
            result = {"bench": "opcua", "passed": False, "error": str(exc),
                      "load_average": list(os.getloadavg())}  # fmt: skip
        (Path(args.inside_netns) / "bench-opcua.json").write_text(json.dumps(result))
        return None
    with tempfile.TemporaryDirectory(prefix="wara-bench-opcua-") as tmp:
        work = Path(tmp)
        inner = ["bench", "opcua", "--json", *(["--quick"] if args.quick else [])]
        code = d2.run_in_netns(inner, args.config, keep_dir=work)
        out = work / "bench-opcua.json"
        if not out.exists():
            return {"passed": False, "error": f"the run inside the namespace ended {code}"}
        return dict(json.loads(out.read_text()))


def _prepare(work: Path) -> tuple[list[str], list[str]]:
    """Users, certificates and the port; the server's and the clients' arguments."""
    from ipc_app.opcua import pki
    from ipc_app.opcua.users import add_user

    add_user(work / "users.json", USER, "viewer", PASSWORD)
    pki.create_server_cert(work / "pki")
    cert, key = pki.client_cert(work / "client", "bench-client", CLIENT_URI)
    pki.trust(work / "pki", cert)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = int(s.getsockname()[1])
    server = ["--users-file", str(work / "users.json"), "--pki-dir", str(work / "pki"),
              "--port", str(port), "--host", "127.0.0.1"]  # fmt: skip
    url = f"opc.tcp://127.0.0.1:{port}/wara/"
    return server, [url, str(cert), str(key), USER, PASSWORD, str(CLIENTS)]


def _cycles(svc: Any, watch: Any, n: int, say: Any) -> None:
    for i in range(n):
        roll, pitch = TARGETS[i % 2]
        reply = svc.call("adjust", roll_deg=roll, pitch_deg=pitch)
        if not reply.get("ok"):
            raise d2.TwoProcessError(f"adjust refused: {reply.get('error')}")
        st = svc.wait(_seeing(watch, "COMPLETE", "ABORTED"), 120.0)
        if st is None or st.get("mode") != "COMPLETE":
            raise d2.TwoProcessError(
                f"cycle {i}: {st and (st.get('mode'), st.get('fault_reasons'))}"
            )
        time.sleep(1.0)
        svc.call("stop")
        svc.wait(_seeing(watch, "IDLE"), 30.0)
        say(f"cycle {i + 1}/{n} done")


def _seeing(watch: Any, *modes: str) -> Callable[[dict[str, Any]], bool]:
    """A wait condition: one of ``modes`` reached (the loop reports noted on the way)."""

    def pred(st: dict[str, Any]) -> bool:
        watch.see(st)
        return st.get("mode") in modes

    return pred


def _next_report(svc: Any, watch: Any) -> None:
    """Wait for the service's next loop report (a baseline first when there is none)."""
    n = len(watch.reports) if watch.baseline is not None else -1

    def pred(st: dict[str, Any]) -> bool:
        watch.see(st)
        return watch.baseline is not None and len(watch.reports) > n

    svc.wait(pred, 30.0, poll_s=0.2)


def _feed_reports(log_path: Path) -> list[dict[str, Any]]:
    """The OPC UA server's ``opcua_feed`` log lines (its status and write timings)."""
    out = []
    for line in log_path.read_text(encoding="utf-8", errors="replace").splitlines():
        with contextlib.suppress(ValueError):
            rec = json.loads(line)
            if isinstance(rec, dict) and rec.get("event") == "opcua_feed":
                out.append({k: v for k, v in rec.items() if k not in ("event", "level", "logger")})
    return out


def _p99(xs: list[float]) -> float:
    return xs[min(len(xs) - 1, int(0.99 * len(xs)))]


def _phase_with(
    svc: Any, watch: Any, work: Path, config_path: str, args: tuple[list[str], list[str]],
    cycles: int, say: Any, k: int,
) -> tuple[dict[str, Any], dict[str, Any]]:  # fmt: skip
    """One ``with`` phase: the server and the clients up, the cycles, both down; the loop's
    summary and the clients' figures (latencies, notifications, the server's feed)."""
    from ipc_app.opcua.process import OpcUaProcess

    server_args, client_args = args
    log_path = work / f"opcua-{k}.log"
    with log_path.open("w", buffering=1) as srv_log:
        srv = OpcUaProcess(config_path, work / "ctl.sock", server_args, stderr=srv_log)
        srv.start()
        clients = subprocess.Popen(
            [sys.executable, "-m", "wara.benches.opcua_clients", *client_args],
            stdout=subprocess.PIPE, text=True, env=d2._env(),
        )  # fmt: skip
        try:
            assert clients.stdout is not None
            if clients.stdout.readline().strip() != "READY":
                raise d2.TwoProcessError("the OPC UA clients did not connect")
            say(f"{CLIENTS} OPC UA clients subscribed")
            summary = _measure(svc, watch, cycles, say)
            clients.terminate()
            out, _ = clients.communicate(timeout=60)
            got = json.loads(out.strip().splitlines()[-1])
        finally:
            if clients.poll() is None:
                clients.kill()
            srv.stop()
    got["server_feed"] = _feed_reports(log_path)
    return summary, got


def _measure(svc: Any, watch: Any, cycles: int, say: Any) -> dict[str, Any]:
    # baseline: the first loop report of this phase
    _next_report(svc, watch)
    _next_report(svc, watch)
    watch.baseline, watch.reports = watch.reports[-1], []
    t0 = time.monotonic()
    _cycles(svc, watch, cycles, say)
    _next_report(svc, watch)
    return {"wall_s": time.monotonic() - t0}


def inside(work: Path, config_path: str, cycles: int, rounds: int = ROUNDS) -> dict[str, Any]:
    say = stderr_progress
    prepared = _prepare(work)
    cfg_period = load_project(config_path).control.period_s
    codes: dict[str, int] = {}
    per_round: list[dict[str, Any]] = []
    lat: list[float] = []
    to_server: list[float] = []
    notifications = 0
    feed: list[dict[str, Any]] = []
    n_clients = 0
    with d2.service_and_simulator(work, config_path, say, codes) as (svc, _sim, placement):
        for r in range(rounds):
            order = ("without", "with") if r % 2 == 0 else ("with", "without")
            phases: dict[str, Any] = {}
            for phase in order:
                say(f"round {r + 1}/{rounds}: {phase} OPC UA")
                watch = d2._LoopWatch()
                if phase == "with":
                    timing, got = _phase_with(
                        svc, watch, work, config_path, prepared, cycles, say, r
                    )
                    lat += got["latencies_s"]
                    to_server += got["to_server_s"]
                    notifications += got["notifications"]
                    n_clients = got["clients"]
                    feed += got["server_feed"]
                else:
                    timing = _measure(svc, watch, cycles, say)
                phases[phase] = watch.summary(cfg_period) | timing
            wo, w = phases["without"].get("compute_p99_ms"), phases["with"].get("compute_p99_ms")
            phases["compute_p99_ratio"] = w / wo if w and wo else None
            per_round.append(phases)
    lat.sort()
    to_server.sort()
    p99 = _p99(lat) if lat else None

    def median_of(phase: str, key: str) -> float | None:
        vals = [x[phase][key] for x in per_round if x[phase].get(key) is not None]
        return statistics.median(vals) if vals else None

    ratios = [x["compute_p99_ratio"] for x in per_round if x["compute_p99_ratio"] is not None]
    return {
        "bench": "opcua",
        "form": "two-process (private netns), OPC UA server a third process",
        "placement": placement,
        "cycles_per_phase": cycles,
        "rounds": per_round,
        # the last round's phases (as before), and the medians over the rounds
        "without": per_round[-1]["without"],
        "with": per_round[-1]["with"],
        "compute_p99_ms": {
            "without": median_of("without", "compute_p99_ms"),
            "with": median_of("with", "compute_p99_ms"),
        },
        "compute_p99_ratio": {
            "per_round": ratios,
            "median": statistics.median(ratios) if ratios else None,
        },
        "overruns": {
            "without": sum(x["without"].get("overruns") or 0 for x in per_round),
            "with": sum(x["with"].get("overruns") or 0 for x in per_round),
        },
        "latency_ms": {
            "samples": len(lat),
            "p50": units.to_ms(statistics.median(lat)) if lat else None,
            "p99": units.to_ms(p99) if p99 is not None else None,
            "max": units.to_ms(lat[-1]) if lat else None,
            "goal_p99_below": units.to_ms(LATENCY_GOAL_S),
            # of it, the part before the server wrote the variable (its ServerTimestamp)
            "to_server_p50": units.to_ms(statistics.median(to_server)) if to_server else None,
            "to_server_p99": units.to_ms(_p99(to_server)) if to_server else None,
        },
        "notifications": notifications,
        "clients": n_clients,
        "server_feed": feed,
        "exit_codes": codes,
        "load_average": list(os.getloadavg()),
        "latency_goal_met": p99 is not None and p99 < LATENCY_GOAL_S,
        "passed": True,
    }
