"""A HIL simulator with an IPC peer and a sniffer on a private ``virtual`` channel."""

from __future__ import annotations

import uuid
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from config import ProjectConfig
from config.hil_scenario import HilScenario
from hil_sim.simulator import HilSimulator
from plc_bridge import IpcLink, Mode

DT = 0.005  # the IPC's loop period (200 Hz)


@dataclass
class Bench:
    sim: HilSimulator
    ipc: IpcLink
    sniff: can.BusABC
    seen: Counter[str] = field(default_factory=Counter)
    log: list[tuple[float, str]] = field(default_factory=list)

    def start(self, mode: Mode = Mode.ATTITUDE_ADJUST, enable: bool = True) -> None:
        self.ipc.set_control(mode=mode, enable=enable)

    def run(
        self,
        seconds: float,
        u: Sequence[float] | np.ndarray | None = None,
        ipc_alive: bool = True,
        each: Callable[[Bench], None] | None = None,
    ) -> None:
        cmd = np.zeros(19) if u is None else np.asarray(u, dtype=float)
        cat = self.sim.catalog
        for _ in range(round(seconds / DT)):
            if ipc_alive:
                self.ipc.poll()
                self.ipc.send_valve_commands(cmd)
            self.sim.step(DT)
            while (msg := self.sniff.recv(0.0)) is not None:
                spec = cat.by_id(msg.arbitration_id)
                name = "error_frame" if msg.is_error_frame else spec.name if spec else "?"
                self.seen[name] += 1
                self.log.append((self.sim.t_s, name))
            if each is not None:
                each(self)

    def close(self) -> None:
        self.ipc.close()
        self.sim.close()
        self.sniff.shutdown()


def make_bench(cfg: ProjectConfig, events: Sequence[dict[str, Any]] = (), **scenario: Any) -> Bench:
    sc = HilScenario.model_validate({"events": list(events), **scenario})
    channel = f"hil-{uuid.uuid4().hex}"
    sim = HilSimulator(cfg, can.Bus(interface="virtual", channel=channel), sc)
    ipc = IpcLink(cfg, can.Bus(interface="virtual", channel=channel), clock=sim.clock)
    sniff = can.Bus(interface="virtual", channel=channel)
    return Bench(sim, ipc, sniff)
