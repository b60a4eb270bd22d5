"""``wara bench hil --json``: how much faster than real time the HIL simulator runs.

- ``plant_realtime_factor``: the rig alone (19 cylinders, two platforms, RK4 at the
  scenario's step), advanced one PLC scan at a time;
- ``realtime_factor``: the whole simulator (plant, transducers, PLC emulation,
  python-can ``virtual`` bus), with an IPC peer sending valve commands at the loop
  rate on the same bus; the peer's own time is not counted (in a real-time run it
  has the other core);
- ``contact_plant_realtime_factor``, ``contact_realtime_factor``: the same with the
  walking rig (``plant.contact``: the body on eight legs with foot contact, friction,
  both frames in world x; hil_sim/walking.py).

Goal: ``realtime_factor >= 5`` with and without contact. Best of three rounds (a shared
machine is noisy).
"""

from __future__ import annotations

import argparse
import time
import uuid
from typing import Any

import can
import numpy as np

from config import load_project
from config.hil_scenario import HilScenario, load_hil_scenario
from config.schema import N_CYLINDERS
from hil_sim.rig import Rig
from hil_sim.simulator import HilSimulator
from hil_sim.walking import WalkingRig
from plc_bridge import IpcLink, Mode

GOAL = 5.0


def run(args: argparse.Namespace) -> dict[str, Any]:
    cfg = load_project(getattr(args, "config", None))
    quick = bool(getattr(args, "quick", False))
    scenario = load_hil_scenario(getattr(args, "scenario", None))
    seconds = 1.0 if quick else 5.0
    plant = scenario.plant
    u = np.zeros(N_CYLINDERS)
    u[8:12] = [0.2, 0.1, -0.1, 0.05]
    u[0:4] = [0.1, -0.05, 0.05, 0.0]

    walking = scenario.model_copy(update={"plant": plant.model_copy(update={"contact": True})})
    # warm-up: numba compiles (or loads its cache) here, outside the timing
    _full(cfg, scenario, 0.05, u)
    _full(cfg, walking, 0.05, u)
    per_scan = round(plant.plc_cycle_ms / plant.step_ms)
    n_scans = round(seconds / plant.plc_cycle_s)
    rtf: dict[str, float] = {}
    for name, cls in (("rigid", Rig), ("contact", WalkingRig)):
        rig = cls(cfg, plant.step_s, plant.rod_mass_for(cfg), plant.load_holding_valves)
        rig.ports_open[:] = 1.0
        rig.command[:] = u
        rtf[name] = 0.0
        for _ in range(3):
            t0 = time.perf_counter()
            for _ in range(n_scans):
                rig.advance(per_scan)
            rtf[name] = max(rtf[name], seconds / (time.perf_counter() - t0))
    plant_rtf = rtf["rigid"]
    full_rtf = max(_full(cfg, scenario, seconds, u) for _ in range(3))
    contact_rtf = max(_full(cfg, walking, seconds, u) for _ in range(3))
    return {
        "bench": "hil",
        "cylinders": N_CYLINDERS,
        "platforms": 2,
        "step_ms": plant.step_ms,
        "plc_cycle_ms": plant.plc_cycle_ms,
        "loop_rate_hz": cfg.control.loop_rate_hz,
        "simulated_s": seconds,
        "plant_realtime_factor": round(plant_rtf, 2),
        "realtime_factor": round(full_rtf, 2),
        "contact_plant_realtime_factor": round(rtf["contact"], 2),
        "contact_realtime_factor": round(contact_rtf, 2),
        "goal_realtime_factor": GOAL,
        "ok": min(full_rtf, contact_rtf) >= GOAL,
        "quick": quick,
    }


def _full(cfg: Any, scenario: HilScenario, seconds: float, u: np.ndarray) -> float:
    channel = f"bench-hil-{uuid.uuid4().hex}"
    sim = HilSimulator(cfg, can.Bus(interface="virtual", channel=channel), scenario)
    ipc = IpcLink(cfg, can.Bus(interface="virtual", channel=channel), clock=sim.clock)
    ipc.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
    dt = cfg.control.period_s
    try:
        for _ in range(round(seconds / dt)):
            ipc.poll()
            ipc.send_valve_commands(u)
            sim.step(dt)
    finally:
        ipc.close()
        sim.close()
    return sim.realtime_factor
