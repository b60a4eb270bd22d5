"""Delay margin of the attitude loop: how much extra sensor delay the hold tolerates.

The lockstep demo (simulator and service in one thread, virtual bus) closes the loop
with the least delay the system can have: positions sampled at the PLC scan, read by
the service in the next control period. On the machine (socketcan, the PLC's scan and
frame cycle unsynchronized with the IPC's loop) and across two processes
(``wara demo --two-process``) the positions are up to a period or two older, and the
age varies. A tuning that is stable only without that delay rocks the loaded lower
platform in its roll mode until the sync-error interlock stops the machine (as
``wc 12, wo 25`` without feed-forward does across two processes).

This study runs the lockstep harness once per delay, with the simulator's wire holding
every ``PLC_RodPos_*`` frame back by that delay (``delay`` fault of the HIL scenario):
one target (Example 1 by default), then a hold of ``hold_s``; the hold is *stable* when
the service is still COMPLETE (holding) at the end and the largest sync error of either layer over
the last half of the hold is within the standstill goal (0.07 mm).

``sim_speed`` below 1 runs the simulator slower than the service's clock (simulated
seconds per second of it), as ``wara hil --realtime`` runs on an emulated CPU: the rig's
dynamics, its oil-column mode included, then take longer on the clock the loop runs on
(docs/kernel-tests.md, the slowed project of the HIL over vcan0). The delays are the
simulator's: seen from the service a delay is ``delay / sim_speed``.

Beside the lockstep runs it reports each loop's modelled delay margin against the
project's ``control.delay_margin_ms`` (:mod:`ipc_app.control.tuning`: the position loop
of each cylinder group, the walk's force loops): their bandwidths, where they come from
(derived, or the YAML key) and the rule that bounds them.

    wara sim delay-margin                       # shipped project, 0-50 ms
    wara sim delay-margin --config my.yaml --delays-ms 0,5,10 --json
    wara sim delay-margin --config slow.yaml --sim-speed 0.5 --delays-ms 0,50,100
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

from config import units
from config.hil_scenario import HilScenario
from config.loader import validate_data
from config.schema import ProjectConfig
from ipc_app.control.tuning import MARGIN_FACTOR, MODE_GAIN, derive, rule_broken
from ipc_app.service.modes import Mode
from ipc_app.service.worker import PlannerWorker
from wara.goals import SYNC_TOL_MM
from wara.harness import Harness
from wara.studies import DEFAULT_DELAYS_MS


@dataclass
class DelayRun:
    delay_ms: float
    reached_target: bool = False
    attitude_error_deg: float = math.nan
    max_twist_mm: float = math.nan
    hold_sync_error_mm: dict[str, float] = field(default_factory=dict)
    mode: str = ""
    faults: list[str] = field(default_factory=list)
    #: (interlock, where) of each latched cause, for code (``faults`` is for people)
    fault_keys: list[tuple[str, str]] = field(default_factory=list)
    stable: bool = False


def run_one(
    cfg: ProjectConfig,
    planner: PlannerWorker,
    delay_ms: float,
    *,
    target: tuple[float, float] = (2.0, 1.0),
    hold_s: float = 20.0,
    sim_speed: float = 1.0,
) -> DelayRun:
    """One lockstep run with every position frame ``delay_ms`` late (0: none), the
    simulator at ``sim_speed`` of the service's clock."""
    events: list[dict[str, Any]] = []
    if delay_ms > 0:
        events.append(
            {"kind": "delay", "start_s": 0.0, "delay_ms": delay_ms, "messages": ["PLC_RodPos_*"]}
        )
    scenario = validate_data(HilScenario, {"events": events}, "delay-margin scenario")
    harness = Harness(cfg, mode="lockstep", scenario=scenario, planner=planner, sim_speed=sim_speed)
    out = DelayRun(delay_ms)
    try:
        if not harness.wait_for(Mode.IDLE, 20.0):
            raise RuntimeError(f"service did not come up: {harness.core.modes.snapshot()}")
        res = harness.run_example(*target)
        out.reached_target = harness.core.modes.mode == Mode.COMPLETE
        out.attitude_error_deg = res.attitude_error_deg
        out.max_twist_mm = res.max_twist_mm
        start = len(harness.trace.t)
        held = 0.0
        while out.reached_target and held < hold_s and harness.core.modes.mode == Mode.COMPLETE:
            step = min(1.0, hold_s - held)  # one second at a time: stop at a fault
            harness.advance(step)
            held += step
        sync = np.asarray(harness.trace.sync_mm[start:])
        if len(sync):
            last_half = sync[len(sync) // 2 :]
            out.hold_sync_error_mm = {
                "lower": float(last_half[:, 0].max()),
                "upper": float(last_half[:, 1].max()),
            }
        out.mode = harness.core.modes.mode.name
        out.faults = list(harness.core.modes.fault_reasons)
        out.fault_keys = [(str(f.interlock), f.where) for f in harness.core.modes.faults]
    finally:
        harness.close()
    out.stable = (
        out.reached_target
        and out.mode == Mode.COMPLETE.name
        and bool(out.hold_sync_error_mm)
        and max(out.hold_sync_error_mm.values()) <= SYNC_TOL_MM
    )
    return out


def run_study(
    cfg: ProjectConfig,
    config_path: str | None = None,
    *,
    delays_ms: Sequence[float] = DEFAULT_DELAYS_MS,
    target: tuple[float, float] = (2.0, 1.0),
    hold_s: float = 20.0,
    required_ms: float | None = None,
    progress: Callable[[str], None] | None = None,
    sim_speed: float = 1.0,
) -> dict[str, Any]:
    """Every delay in turn, and the loops' modelled margins; the JSON-ready report
    (``passed``: the hold stable up to ``required_ms``, default the project's
    ``control.delay_margin_ms``, and every loop's modelled margin at least that)."""
    say = progress or (lambda _s: None)
    if required_ms is None:
        required_ms = cfg.control.delay_margin_ms
    loops = loop_margins(cfg, required_ms)
    planner = PlannerWorker(config_path, timeout_s=60.0)
    planner.start()
    runs: list[DelayRun] = []
    try:
        for d in sorted(delays_ms):
            say(f"{d:g} ms of extra position delay: target {target}, hold {hold_s:g} s")
            runs.append(run_one(cfg, planner, d, target=target, hold_s=hold_s, sim_speed=sim_speed))
            r = runs[-1]
            say(f"{d:g} ms: {'stable' if r.stable else 'NOT stable'} ({r.mode})")
    finally:
        planner.close()
    margin = None
    for r in runs:  # the largest delay with every smaller tested delay stable too
        if not r.stable:
            break
        margin = r.delay_ms
    tested_required = [r for r in runs if r.delay_ms <= required_ms]
    ladrc = cfg.control.ladrc
    return {
        "controller": cfg.control.controller,
        "ladrc": ladrc.model_dump(),
        "coupling_lambda": cfg.control.sync.coupling_lambda,
        "target_deg": list(target),
        "hold_s": hold_s,
        "sim_speed": sim_speed,
        "sync_tolerance_mm": SYNC_TOL_MM,
        "runs": [asdict(r) for r in runs],
        "delay_margin_ms": margin,
        "required_ms": required_ms,
        "loops": loops,
        "passed": bool(tested_required)
        and any(r.delay_ms >= required_ms for r in runs)
        and all(r.stable for r in tested_required)
        and all(lp["meets_required"] for lp in loops),
    }


def loop_margins(cfg: ProjectConfig, required_ms: float) -> list[dict[str, Any]]:
    """Each loop's tuning and modelled delay margin (:func:`ipc_app.control.tuning.derive`)
    and the rule's margins for ``required_ms`` (``breaks``: ``"delay"``, ``"mode"`` or
    ``""``)."""
    out = []
    for lt in derive(cfg).loops:
        have = units.to_ms(lt.delay_margin_s)
        breaks = rule_broken(lt.plant, lt.wc_rad_s, lt.wo_rad_s, units.ms(required_ms))
        out.append(
            {
                "group": lt.group,
                "kind": lt.kind,
                "wc_rad_s": lt.wc_rad_s,
                "wo_rad_s": lt.wo_rad_s,
                "source": lt.source,
                "bound": lt.bound,
                "mode_rad_s": lt.plant.mode_rad_s if math.isfinite(lt.plant.mode_rad_s) else None,
                "mode_gain": round(lt.mode_gain, 4),
                "model_delay_margin_ms": round(have, 1) if math.isfinite(have) else None,
                "breaks": breaks,
                "meets_required": not breaks,
            }
        )
    return out


def render(report: dict[str, Any]) -> str:
    lines = [
        f"{'delay ms':>8} {'target':>7} {'att. err deg':>12} {'max twist mm':>12} "
        f"{'hold sync lower/upper mm':>25}  mode / verdict",
    ]
    lines.append("-" * len(lines[0]))
    for r in report["runs"]:
        hs = r["hold_sync_error_mm"]
        sync = f"{hs['lower']:.4f} / {hs['upper']:.4f}" if hs else "n/a"
        if r["stable"]:
            verdict = "stable"
        elif r["faults"]:
            verdict = "NOT stable: " + "; ".join(r["faults"])
        elif not r["reached_target"]:
            verdict = "NOT stable: target not reached"
        else:
            verdict = f"NOT stable: hold sync error above {report['sync_tolerance_mm']} mm"
        lines.append(
            f"{r['delay_ms']:>8g} {'yes' if r['reached_target'] else 'no':>7} "
            f"{r['attitude_error_deg']:>12.5f} {r['max_twist_mm']:>12.4f} {sync:>25}  "
            f"{r['mode']} / {verdict}"
        )
    lines += ["", render_loops(report["loops"], report["required_ms"])]
    margin = report["delay_margin_ms"]
    speed = report["sim_speed"]
    lines += [
        "",
        *(
            [f"simulator at {speed:g} of the service's clock (the delays are the simulator's)"]
            if speed != 1
            else []
        ),
        f"delay margin: {'none' if margin is None else f'{margin:g} ms'} "
        f"(largest tested delay with the hold stable at it and every smaller one); "
        f"required {report['required_ms']:g} ms",
        "PASSED" if report["passed"] else "FAILED",
    ]
    return "\n".join(lines)


def render_loops(loops: list[dict[str, Any]], required_ms: float) -> str:
    """The loops' table: bandwidths, source, bound, modelled margin, the rule kept."""
    head = (
        f"{'loop':<24} {'wc':>6} {'wo':>6} {'mode rad/s':>10} {'gain@mode':>9} "
        f"{'model margin ms':>15}  source / bound"
    )
    lines = [
        f"loops (the loop model; the rule: margin >= {MARGIN_FACTOR:g} x {required_ms:g} ms, "
        f"gain at an oil-column mode in reach <= {MODE_GAIN:g})",
        head,
        "-" * len(head),
    ]
    for lp in loops:
        mode = "-" if lp["mode_rad_s"] is None else f"{lp['mode_rad_s']:.1f}"
        have = lp["model_delay_margin_ms"]
        margin = "inf" if have is None else f"{have:.1f}"
        ok = f"  BREAKS the rule ({lp['breaks']})" if lp["breaks"] else ""
        bound = f" / {lp['bound']}" if lp["bound"] else ""
        lines.append(
            f"{lp['group'] + ' ' + lp['kind']:<24} {lp['wc_rad_s']:>6g} {lp['wo_rad_s']:>6g} "
            f"{mode:>10} {lp['mode_gain']:>9.3f} {margin:>15}  {lp['source']}{bound}{ok}"
        )
    return "\n".join(lines)
