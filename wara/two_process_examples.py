"""The attitude examples across two processes: ``wara demo --two-process`` (without
``--rings``).

The simulator (the attitude rig) and the service as two processes on a UDP multicast
bus in a private network namespace (:mod:`wara.demo_two_process`); the examples one
after another through the service's control socket: ``adjust`` -> COMPLETE ->
``settle_s`` of standstill -> the status ``motion`` block; the run kept going until the
measured window spans ``min_run_s`` of loop cycles.

Figures and decisions (docs/realtime.md, "Two processes"):

- achieved attitude: the service's ``motion.achieved_deg``, i.e. from the measured rod
  positions (the sensor view); the simulator's truth is in another process. The goals
  and the judge are the in-process demo's (:func:`wara.examples.judge_example`).
- the loop goal: :data:`~wara.demo_two_process.COMPUTE_P99_GOAL_FRACTION` of the period
  for the worst compute p99 of the reports after start-up, no overrun after start-up,
  and at least ``min_run_s`` of cycles measured (:class:`~wara.demo_two_process.LoopWatch`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any

from config import load_project
from ipc_app.service.core import ServiceCore
from plc_bridge.busload import bus_load
from wara.demo_two_process import (
    COMPUTE_P99_GOAL_FRACTION,
    DEFAULT_TRANSPORT,
    LoopWatch,
    Progress,
    Service,
    TwoProcessError,
    run_in_netns,
    service_and_simulator,
    setting_lines,
    sim_realtime_factor,
)
from wara.examples import EXAMPLES, HOLD_MEASURE_S, ExampleResult, judge_example
from wara.goals import ATTITUDE_GOALS, limits

#: Real-time run the loop goal is judged on (seconds of loop cycles after start-up).
MIN_RUN_S = 60.0
#: Default time each target is held before its figures are read.
DEFAULT_SETTLE_S = ServiceCore.HOLD_SETTLE_S + HOLD_MEASURE_S


def run_two_process(
    config_path: str | None,
    *,
    json_out: bool,
    settle_s: float,
    examples: int,
    min_run_s: float,
    keep_dir: Path | None = None,
    transport: str = DEFAULT_TRANSPORT,
    pin: bool = True,
) -> int:
    """``wara demo --two-process``: make the namespace and re-run inside it; exit code.

    ``pin``: the service's loop thread and the simulator on CPUs of their own (see
    :func:`multicast_config`); ``False`` leaves the placement to the scheduler.

    The inner run prints the table / JSON on this process's stdout. Raises
    :class:`NetnsUnavailable` when the namespace cannot be made.
    """
    inner = [
        "demo",
        "--two-process",
        "--settle-s",
        repr(settle_s),
        "--examples",
        str(examples),
        "--min-run-s",
        repr(min_run_s),
    ]
    if json_out:
        inner.append("--json")
    return run_in_netns(inner, config_path, keep_dir=keep_dir, transport=transport, pin=pin)


def judge(st: dict[str, Any], res: ExampleResult) -> ExampleResult:
    """The example's figures from the service's status ``motion`` block, judged."""
    m = st.get("motion") or {}
    achieved = m.get("achieved_deg")
    if achieved is not None:
        res.set_achieved(float(achieved[0]), float(achieved[1]))
    res.take_motion(m)
    mode = st.get("mode")
    problem = ""
    if mode != "COMPLETE":
        problem = f"mode {mode}: {st.get('fault_reasons') or st.get('message', '')}"
    elif not m.get("hold_samples"):
        problem = "no standstill samples (settle time too short)"
    elif achieved is None:
        problem = "no valid rod positions"
    return judge_example(res, problem=problem)


def _run_example(
    svc: Service, watch: LoopWatch, roll: float, pitch: float, settle_s: float, say: Progress
) -> ExampleResult:
    res = ExampleResult(roll, pitch)
    reply = svc.call("adjust", roll_deg=roll, pitch_deg=pitch)
    if not reply.get("ok"):
        res.note = f"refused: {reply.get('error') or reply.get('reasons')}"
        return res
    say(f"adjusting to ({roll:+.1f}, {pitch:+.1f}) deg")

    def done(st: dict[str, Any]) -> bool:
        watch.see(st)
        if st.get("mode") == "COMPLETE":  # holding *this* target, not the previous one
            target = (st.get("motion") or {}).get("target_deg") or [math.nan, math.nan]
            return abs(target[0] - roll) < 1e-9 and abs(target[1] - pitch) < 1e-9
        return st.get("mode") in ("ABORTED", "IDLE")

    st = svc.wait(done, timeout_s=300.0)
    if st is None or st.get("mode") != "COMPLETE":
        mode = None if st is None else st.get("mode")
        reasons = None if st is None else st.get("fault_reasons")
        res.note = f"did not finish: mode {mode} {reasons or ''}".strip()
        return res
    end = time.monotonic() + settle_s
    while time.monotonic() < end:
        watch.see(svc.status())
        time.sleep(min(0.2, max(0.0, end - time.monotonic())))
    st = svc.status()
    watch.see(st)
    return judge(st, res)


def run_inside_netns(
    workdir: Path,
    config_path: str,
    *,
    settle_s: float = DEFAULT_SETTLE_S,
    examples: Sequence[tuple[float, float]] = EXAMPLES,
    min_run_s: float = MIN_RUN_S,
    progress: Progress | None = None,
) -> dict[str, Any]:
    """Simulator + service as two processes; the JSON-ready summary (``passed``)."""
    say = progress or (lambda _s: None)
    cfg = load_project(config_path)
    period = cfg.control.period_s
    results: list[ExampleResult] = []
    watch = LoopWatch()
    codes: dict[str, int] = {}
    with service_and_simulator(workdir, config_path, say, codes) as (svc, sim, placement):

        def first_report(s: dict[str, Any]) -> bool:
            watch.see(s)
            return watch.baseline is not None

        if svc.wait(first_report, 15.0, poll_s=0.2) is None:
            raise TwoProcessError("the service published no loop statistics in 15 s")
        for roll, pitch in examples:
            results.append(_run_example(svc, watch, roll, pitch, settle_s, say))
            r = results[-1]
            say(
                f"example ({roll:+.1f}, {pitch:+.1f}) deg: "
                f"{'passed' if r.passed else 'FAILED ' + r.note}"
            )
        if min_run_s > 0:
            say(f"keeping the run going until {min_run_s:g} s of loop cycles are measured")

        def long_enough(s: dict[str, Any]) -> bool:
            watch.see(s)
            return bool(watch.reports) and watch.measured_s(period) >= min_run_s

        # At least one report after the examples, so the last motion is in the figures.
        n_before = len(watch.reports)
        if (
            svc.wait(
                lambda s: long_enough(s) and len(watch.reports) > n_before,
                timeout_s=max(min_run_s, 0.0) + 30.0,
                poll_s=0.5,
            )
            is None
        ):
            raise TwoProcessError(
                f"loop reports stopped: {watch.measured_s(period):.1f} s measured"
            )
        final = svc.status()
    loop = watch.summary(period)
    frac = loop["compute_p99_fraction"]
    loop_ok = (
        frac is not None
        and frac < COMPUTE_P99_GOAL_FRACTION
        and loop["overruns"] == 0
        and loop["measured_s"] >= min_run_s
    )
    examples_ok = bool(results) and all(r.passed for r in results)
    lo, up = cfg.layers.lower.cylinders, cfg.layers.upper.cylinders
    active = [c.can_index for c in cfg.cylinders if c.id in (*lo, *up)]
    return {
        "mode": "two-process",
        "bus": f"{cfg.can.interface} {cfg.can.channel}:{cfg.can.udp_port} (private netns)",
        "placement": placement,
        "examples": [asdict(r) for r in results],
        "loop": loop,
        "loop_goal": {
            "compute_p99_fraction_below": COMPUTE_P99_GOAL_FRACTION,
            "overruns_after_startup": 0,
            "min_run_s": min_run_s,
            "passed": loop_ok,
        },
        "final_mode": final.get("mode"),
        "final_fault_reasons": list(final.get("fault_reasons") or []),
        "faults": list(final.get("faults") or []),  # the same, as data (interlock, where)
        "exit_codes": codes,
        "bus_load_percent": bus_load(cfg, active).load_percent,
        "simulator_realtime_factor": sim_realtime_factor(sim.log_path.read_text(errors="replace")),
        "tolerances": limits(ATTITUDE_GOALS),
        "passed": examples_ok and loop_ok,
    }


def render_table(summary: dict[str, Any]) -> str:
    """The in-process demo's table plus the loop goal of the two-process run."""
    from wara.demo import example_rows

    lines = example_rows(summary)
    lp, goal = summary["loop"], summary["loop_goal"]

    def ms(v: float | None) -> str:
        return "n/a" if v is None else f"{v:.3f} ms"

    frac = lp.get("compute_p99_fraction")
    lines += [
        "",
        *setting_lines(summary),
        f"loop: {lp['period_ms']:.1f} ms period, {lp['measured_s']:.1f} s measured after "
        f"start-up ({lp['measured_cycles']} cycles, {lp['reports']} reports); worst p99 of "
        f"the reports: compute {ms(lp['compute_p99_ms'])} "
        + ("" if frac is None else f"({100 * frac:.1f} % of the period) ")
        + f"jitter {ms(lp['jitter_p99_ms'])}; compute max {ms(lp['compute_max_ms'])}",
        f"overruns after start-up {lp['overruns']} (start-up {lp['overruns_startup']}, "
        f"total {lp['overruns_total']}); goal: compute p99 < "
        f"{100 * goal['compute_p99_fraction_below']:.0f} % of the period, 0 overruns in "
        f"{goal['min_run_s']:g} s: {'met' if goal['passed'] else 'NOT MET'}",
        "PASSED" if summary["passed"] else "FAILED",
    ]
    return "\n".join(lines)
