"""``wara bench transport --json``: the cross-process CAN transports, cost per frame and
per loop cycle: python-can's ``udp_multicast`` against our ``wara_udp``.

Runs in a private network namespace (``unshare --user --map-root-user --net``, the same
probe and loopback set-up as ``wara demo --two-process``): the multicast never leaves it.
Both transports are measured in the same run, alternating rounds, best round kept (this
class of machine is shared and noisy); the goal is the *ratio*:

- ``send_us_per_frame``: ``bus.send(msg, timeout=0)`` of one classic frame;
- ``recv_us_per_frame``: ``bus.recv(0.0)`` draining the socket, per frame another bus
  sent; the receiver's own looped-back frames are in the socket too (one for every
  three, about the IPC's share of the traffic): python-can hands them out (the link
  then drops them as ``own_echo``), ``wara_udp`` skips them inside;
- ``link_cycle_us``: the IPC side of one 200 Hz cycle (``poll`` + positions, pressures,
  status + ``send_valve_commands``) with the PLC side sending at its cycle times under a
  simulated clock, both links on real sockets in this process.

``ok``: ``wara_udp`` cheaper per received frame and per link cycle. Without a
namespace (no user namespaces, no ``unshare``/``ip``) it prints the reason with
``"ok": false``.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from typing import Any

import can
import numpy as np

from config import load_project, units
from config.schema import ProjectConfig
from plc_bridge import open_bus
from wara.benches.can import ipc_side_cycles

TRANSPORTS = ("udp_multicast", "wara_udp")
GROUP = "239.74.163.2"


def run(args: argparse.Namespace) -> dict[str, Any]:
    from wara.demo_two_process import NETNS_SETUP, UNSHARE, _env, _quote, netns_problem

    problem = netns_problem()
    if problem is not None:
        return {"bench": "transport", "ok": False, "error": problem}
    inner = [sys.executable, "-m", "wara.benches.transport"]
    if getattr(args, "config", None):
        inner += ["--config", str(args.config)]
    if getattr(args, "quick", False):
        inner.append("--quick")
    script = f"{NETNS_SETUP} && exec {' '.join(_quote(a) for a in inner)}"
    proc = subprocess.run(
        [*UNSHARE, "sh", "-c", script], capture_output=True, text=True, env=_env(), check=False
    )
    if proc.returncode != 0:
        err = proc.stderr.strip().splitlines()[-1:] or [f"exit code {proc.returncode}"]
        return {"bench": "transport", "ok": False, "error": err[0]}
    result: dict[str, Any] = json.loads(proc.stdout)
    return result


def _config(base: ProjectConfig, interface: str, port: int) -> ProjectConfig:
    data = base.model_dump()
    data["can"].update(interface=interface, channel=GROUP, udp_port=port)
    return ProjectConfig.model_validate(data)


def _frame(i: int) -> can.Message:
    return can.Message(
        arbitration_id=0x100 + i % 16, data=bytes(range(8)), is_extended_id=False, check=False
    )


def _frame_costs(cfg: ProjectConfig, n: int, batch: int = 120) -> tuple[float, float]:
    """(send, recv) microseconds per frame, one round of ``n`` frames in batches (a
    batch, with the receiver's own frames, fits the default socket receive buffer)."""
    rx = open_bus(cfg.can)
    tx = open_bus(cfg.can)
    send_s = recv_s = 0.0
    sent = own = got = 0
    try:
        msgs = [_frame(i) for i in range(batch)]
        while sent < n:
            t0 = time.perf_counter()
            for m in msgs:
                tx.send(m, timeout=0.0)
            send_s += time.perf_counter() - t0
            sent += batch
            for m in msgs[: batch // 3]:  # the receiver's own frames, looped back to it
                rx.send(m, timeout=0.0)
                own += 1
            time.sleep(0.005)  # all delivered to the receiving socket
            t0 = time.perf_counter()
            while rx.recv(0.0) is not None:
                got += 1
            recv_s += time.perf_counter() - t0
        python_can = cfg.can.interface == "udp_multicast"  # hands out its own frames
        expected = sent + (own if python_can else 0)
        if got != expected:
            raise RuntimeError(f"{cfg.can.interface}: {got} of {expected} frames received")
        return units.to_us(send_s / sent), units.to_us(recv_s / sent)
    finally:
        rx.shutdown()
        tx.shutdown()


def _link_cycles(cfg: ProjectConfig, cycles: int) -> tuple[float, float]:
    """(median microseconds of the IPC side of one cycle, frames read per cycle)."""
    return ipc_side_cycles(
        cfg, cycles, lambda side, clock: side.from_config(cfg, clock=clock), pause_s=0.0002
    )


def measure(config: str | None, quick: bool) -> dict[str, Any]:
    base = load_project(config)
    n, rounds, cycles = (300, 3, 200) if quick else (1000, 7, 1000)
    cfgs = {t: _config(base, t, 43200 + i) for i, t in enumerate(TRANSPORTS)}
    best: dict[str, dict[str, float]] = {
        t: {"send_us_per_frame": np.inf, "recv_us_per_frame": np.inf, "link_cycle_us": np.inf}
        for t in TRANSPORTS
    }
    frames_per_cycle: dict[str, float] = {}
    for _ in range(rounds):
        for t in TRANSPORTS:  # alternate: both see the same machine conditions
            s, r = _frame_costs(cfgs[t], n)
            b = best[t]
            b["send_us_per_frame"] = min(b["send_us_per_frame"], s)
            b["recv_us_per_frame"] = min(b["recv_us_per_frame"], r)
        for t in TRANSPORTS:
            c, f = _link_cycles(cfgs[t], cycles // rounds + 1)
            best[t]["link_cycle_us"] = min(best[t]["link_cycle_us"], c)
            frames_per_cycle[t] = f
    old, new = best["udp_multicast"], best["wara_udp"]
    period_us = units.to_us(base.control.period_s)
    return {
        "bench": "transport",
        "period_us": period_us,
        "frames": n,
        "rounds": rounds,
        "transports": {
            t: {k: round(v, 3) for k, v in best[t].items()}
            | {"link_percent_of_period": round(100 * best[t]["link_cycle_us"] / period_us, 2)}
            | {"frames_received_per_cycle": round(frames_per_cycle[t], 2)}
            for t in TRANSPORTS
        },
        "speedup": {
            k: round(old[k] / new[k], 2)
            for k in ("send_us_per_frame", "recv_us_per_frame", "link_cycle_us")
        },
        "ok": old["recv_us_per_frame"] > new["recv_us_per_frame"]
        and old["link_cycle_us"] > new["link_cycle_us"],
        "quick": quick,
    }


def main() -> None:
    p = argparse.ArgumentParser(description="(inside the private netns) measure and print")
    p.add_argument("--config", default=None)
    p.add_argument("--quick", action="store_true")
    a = p.parse_args()
    print(json.dumps(measure(a.config, a.quick)))


if __name__ == "__main__":
    main()
