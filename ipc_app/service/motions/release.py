"""The part's release (the ring cycle's ``release``): a
:class:`~ipc_app.control.release.ReleaseSequencer` run by the service (placement.md
section 4; :mod:`ipc_app.control.release`).

Prepared in the requesting thread: the empty platform's pressures from the statics at
the measured attitudes, the stroke checked. In the loop the upper platform lowers off
the fixed part until its pressures are the empty platform's, then clear of it, and holds
(COMPLETE); lowered the whole ``cycle.release_max_travel_mm`` with the load still on, the
``release`` interlock stops it.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import structlog

from config import units
from ipc_app.control.release import ReleaseSequencer, platform_pressures_pa
from ipc_app.service.interlocks import Metrics, release_cause
from ipc_app.service.machine_io import MachineInputs
from ipc_app.service.modes import Mode
from ipc_app.service.motion import Command, Effects, Event, Motion, Service, event
from ipc_app.service.requests import Code, Reply

log = structlog.get_logger("wara.service")


class ReleaseMotion(Motion):
    """Ring :attr:`ring`'s part released; see the module docstring."""

    name = "release"

    def __init__(self, svc: Service, ring: int, releaser: ReleaseSequencer) -> None:
        self.attitude = svc.attitude
        self.ring = ring
        self.sequencer = self.releaser = releaser
        self.ids = tuple(c.id for c in svc.cfg.cylinders_by_can_index)

    @classmethod
    def prepare(cls, svc: Service, *args: Any) -> Motion | Reply:
        (ring,) = args
        cfg = svc.cfg
        if cfg.cycle is None:
            return Reply.bad_request("the project has no cycle section: it cannot release")
        inp = svc.inputs
        if inp is None or not inp.positions_valid:
            return Reply.refused("release refused: no valid positions")
        x = inp.positions.value
        try:
            empty = platform_pressures_pa(
                cfg, x, unloaded=True, lowering_speed_m_s=cfg.cycle.release_speed_m_s
            )
            at_rest = platform_pressures_pa(cfg, x, unloaded=True)
        except ValueError as exc:  # no workpiece body
            return Reply.bad_request(f"release refused: {exc}")
        releaser = ReleaseSequencer(cfg, svc.attitude, empty, at_rest)
        why = releaser.check(x)
        if why:
            return Reply.refused("release refused: " + "; ".join(why), Code.INFEASIBLE)
        return cls(svc, ring, releaser)

    def describe(self) -> str:
        return f"ring {self.ring}: the upper platform off the fixed part"

    def accepted(self) -> dict[str, Any]:
        return {"ring": self.ring}

    def metrics(self) -> Mapping[str, Metrics]:
        return self.attitude.metrics

    def start(self, inp: MachineInputs) -> Effects:
        r = self.releaser
        r.start(inp.t, inp.positions.value, inp.pressures.value)
        log.info("release", ring=self.ring)
        return (
            event(
                "release", ring=self.ring, **r.figures.to_dict(),
                speed_mm_s=units.to_mm(r.speed_m_s), tolerance_mpa=units.to_mpa(r.tolerance_pa),
            ),
        )  # fmt: skip

    def update(self, inp: MachineInputs, mode: Mode) -> Command:
        r = self.releaser
        was = (r.phase, r.done)
        p_valid = bool(inp.pressures.valid[r.upper].all())
        x = np.nan_to_num(inp.positions.value, nan=0.0)
        u = r.update(inp.t, x, np.nan_to_num(inp.pressures.value, nan=0.0), p_valid)
        refs = self.attitude.last_references
        if mode != Mode.EXECUTE:
            return Command(u, refs)
        if r.out_of_travel:
            return Command(u, refs, causes=[release_cause(r, self.ids)])
        events: list[Event] = []
        if r.phase != was[0]:
            events.append(event("release_phase", phase=r.phase_name, **r.figures.to_dict()))
        return Command(u, refs, r.done and not was[1], events=events)

    def completed(self, now: float) -> Event | None:
        r = self.releaser
        fig = r.figures.to_dict()
        log.info("release done", **fig)
        return event("release_done", phase_times_s=r.phase_times_s, **fig)

    def stop_point(self, now: float, inp: MachineInputs | None) -> np.ndarray:
        ref = self.attitude.last_references
        return ref if ref is not None else self.attitude.references(now)

    def resume(self, inp: MachineInputs, shift_s: float, held: bool) -> None:
        self.attitude.resume(inp.positions.value, shift_s)
        self.releaser.resume(shift_s)

    def end(self, now: float, mode: Mode, successor: Motion | None) -> Effects:
        return (event("release_end", phase=self.releaser.phase_name, mode=str(mode)),)

    def status(self) -> dict[str, Any] | None:
        r = self.releaser
        return {
            "ring": self.ring,
            "phase": r.phase_name,
            "done": r.done,
            "phase_times_s": {k: round(v, 3) for k, v in r.phase_times_s.items()},
            **r.figures.to_dict(),
        }

    def figures(self) -> dict[str, Any]:
        return self.releaser.figures.to_dict()
