"""End-to-end walks in lockstep: the walking rig and the service on the virtual bus.

Short steps (``walking.step_length_mm: 200``) keep each case to about a minute; the
phases, the checks and their reactions are those of the full 2 m step. Each interlock's
case states the number of cycles within which its reaction comes, and reads the run
record for it.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from config import load_project
from config.hil_scenario import HilScenario
from ipc_app.control.tuning import touchdown_speed_m_s
from ipc_app.planner.walk import plan_walk
from ipc_app.service.core import ServiceCore
from ipc_app.service.interlocks import Interlock
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from tests.cli_helpers import run_wara_observed
from wara.goals import step_time_limit_s
from wara.harness import Harness
from wara.walk import run_walk

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "config" / "projects" / "shanghai_airport_link.yaml"
PERIOD_S = 0.005


def project(tmp_path: Path, **walking: Any) -> str:
    d = yaml.safe_load(SHIPPED.read_text(encoding="utf-8"))
    d["walking"].update({"step_length_mm": 200, **walking})
    path = tmp_path / "short.yaml"
    path.write_text(yaml.safe_dump(d), encoding="utf-8")
    return str(path)


def events(run_dir: Path) -> list[dict[str, Any]]:
    lines = (run_dir / "events.jsonl").read_text(encoding="utf-8").splitlines()
    return [json.loads(line) for line in lines if line.strip()]


def recorder(tmp_path: Path, config: str) -> RunRecorder:
    return RunRecorder(tmp_path / "run", ServiceCore.record_columns(load_project(config)))


def walk(
    tmp_path: Path, config: str, scenario: dict[str, Any] | None = None, **kw: Any
) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    sc = HilScenario.model_validate(scenario) if scenario else None
    with recorder(tmp_path, config) as rec:
        out = run_walk(config, 1, scenario=sc, record=rec, **kw)
    return out, events(tmp_path / "run")


def phase_starts(evs: list[dict[str, Any]]) -> dict[str, float]:
    return {e["phase"]: e["t_s"] for e in evs if e["kind"] == "walk_phase"}


def fault(evs: list[dict[str, Any]]) -> dict[str, Any]:
    (first, *_) = [e for e in evs if e["kind"] == "fault"]
    return first


def test_a_short_step_completes_with_every_phase_in_the_record(tmp_path: Path) -> None:
    out, evs = walk(tmp_path, project(tmp_path), plot_dir=tmp_path / "plots")
    assert out["final_mode"] == "COMPLETE", out["fault_reasons"]
    assert list(phase_starts(evs)) == ["1", "2", "3", "4", "5", "6", "7a", "7b", "7c", "8"]
    (done,) = [e for e in evs if e["kind"] == "walk_done"]
    assert done["steps"][0]["max_leg_force_ratio"] <= 1.10
    assert abs(out["distance_m"] - 0.2) <= 0.005  # simulator truth
    for e in evs:
        if e["kind"] == "walk_phase":
            assert e["bus_load_percent"] <= 50.0
    # walk.png: forces, rods, margin, the part's turn in each transfer, the phases
    (png,) = out["plots"]
    assert Path(png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_a_hole_under_a_foot_stops_the_lowering(tmp_path: Path) -> None:
    """sub_leg_1 stands at world (0.1 + 1.9, +0.95) after S advanced: a hole there. The
    touch-down interlock trips when the lowering has gone ``touchdown_travel_mm`` below
    the expected ground without a touch: within the phase's duration (fast part, then
    2 x 10 mm at the touch-down speed) plus 4 cycles of its start (measured: 2)."""
    hole = {"kind": "ground", "x_from_m": 1.8, "x_to_m": 2.2, "y_from_m": 0.6, "y_to_m": 1.3,
            "offset_mm": -500.0}  # fmt: skip
    config = project(tmp_path)
    walking = load_project(config).walking
    assert walking is not None
    out, evs = walk(tmp_path, config, {"events": [hole]})
    assert out["final_mode"] == "ABORTED"
    f = fault(evs)
    assert f["interlock"] == str(Interlock.TOUCHDOWN) and f["where"] == "sub_leg_1"
    t2 = phase_starts(evs)["2"]
    # trapezoid to 40 mm, then 20 mm slow
    lowering_s = (
        (50 - 10) / 20 + 20 / 20 + 2 * 10 / (1e3 * touchdown_speed_m_s(load_project(config)))
    )
    assert f["t_s"] - t2 <= lowering_s + 4 * PERIOD_S
    assert f["t_s"] - t2 >= lowering_s - 0.5  # not before the lowering ran out


def test_an_obstacle_under_a_foot_stops_the_lowering_before_any_overload(
    tmp_path: Path,
) -> None:
    """The invert 25 mm higher under sub_leg_1 (an obstacle): its foot meets it in the
    fast part of S's lowering, 25 mm above the expected ground, above the 10 mm window.
    The touch-down interlock stops the walk on that leg with its height, and no overload
    of M's legs comes first (the pressing foot is in the body's equilibrium: without it
    the M leg across took the foot's push over its share and tripped the overload)."""
    bump = {"kind": "ground", "x_from_m": 1.8, "x_to_m": 2.2, "y_from_m": 0.6, "y_to_m": 1.3,
            "offset_mm": 25.0}  # fmt: skip
    out, evs = walk(tmp_path, project(tmp_path), {"events": [bump]})
    assert out["final_mode"] == "ABORTED"
    faults = [e for e in evs if e["kind"] == "fault"]
    assert {e["interlock"] for e in faults} == {str(Interlock.TOUCHDOWN)}, out["fault_reasons"]
    f = faults[0]
    assert f["where"] == "sub_leg_1"
    assert 20.0 <= f["first"] <= 26.0  # its height above the expected ground, mm
    assert "obstacle" in f["text"]
    assert f["t_s"] < phase_starts(evs)["2"] + (50 - 10) / 20 + 20 / 20  # in the fast part


def test_slip_when_the_travel_force_passes_the_feet_friction(tmp_path: Path) -> None:
    """An obstacle against S (180 kN on each travel rod from 2 s): the travel force
    passes the standing feet's friction (0.4 x 710 kN); stop within 400 cycles."""
    load = [
        {"kind": "load_step", "cylinder": c, "force_kn": 180.0, "start_s": 2.0}
        for c in ("travel_1", "travel_2")
    ]
    out, evs = walk(tmp_path, project(tmp_path), {"events": load})
    assert out["final_mode"] == "ABORTED"
    f = fault(evs)
    assert f["interlock"] == str(Interlock.SLIP), out["fault_reasons"]
    assert f["t_s"] - 2.0 <= 400 * PERIOD_S


def test_overload_of_a_standing_leg(tmp_path: Path) -> None:
    """Five tonnes set down over main_leg_1 at 2 s while M stands: its force passes 110 %
    of its share; stop within 40 cycles (pressures arrive every 50 ms)."""
    load = {"kind": "load_step", "layer": "lower", "mass_kg": 5000.0,
            "cog_m": [2.8, 1.4, 0.5], "start_s": 2.0}  # fmt: skip
    _out, evs = walk(tmp_path, project(tmp_path), {"events": [load]})
    f = fault(evs)
    assert f["interlock"] == str(Interlock.OVERLOAD) and f["where"] == "main_leg_1"
    assert f["t_s"] - 2.0 <= 40 * PERIOD_S


def test_a_leg_out_of_band_holds_its_group_and_it_goes_on(tmp_path: Path) -> None:
    """sub_leg_2's valve sticks closed for 1 s while S lowers: the group holds within one
    cycle of leaving the 2 mm band, goes on once back inside, and the walk completes."""
    cfg = project(tmp_path)
    stuck = {"kind": "stuck_valve", "cylinder": "sub_leg_2", "opening": 0.0,
             "start_s": 7.6, "end_s": 8.6}  # fmt: skip
    out, evs = walk(tmp_path, cfg, {"events": [stuck]})
    assert out["final_mode"] == "COMPLETE", out["fault_reasons"]
    holds = [e for e in evs if e["kind"] == "walk_sync_hold"]
    goes = [e for e in evs if e["kind"] == "walk_sync_continue"]
    assert holds and goes and holds[0]["phase"] == "2" and holds[0]["group"] == "legs"
    assert 7.6 <= holds[0]["t_s"] <= 8.6 and goes[0]["t_s"] > holds[0]["t_s"]
    assert holds[0]["sync_mm"] <= 2.0 + 20 * PERIOD_S  # one cycle at 20 mm/s past the band


def test_a_leg_out_of_band_too_long_is_latched(tmp_path: Path) -> None:
    cfg = project(tmp_path, sync_band_timeout_s=1.0)
    stuck = {"kind": "stuck_valve", "cylinder": "sub_leg_2", "opening": 0.0, "start_s": 7.6}
    _out, evs = walk(tmp_path, cfg, {"events": [stuck]})
    f = fault(evs)
    assert f["interlock"] == str(Interlock.SYNC_BAND)
    # the group holds, creeps back inside, holds again...: latched 1 s after the last hold
    hold = [e for e in evs if e["kind"] == "walk_sync_hold" and e["t_s"] <= f["t_s"]][-1]
    assert 1.0 <= f["t_s"] - hold["t_s"] <= 1.0 + 2 * PERIOD_S


def test_stop_and_resume_mid_phase(tmp_path: Path) -> None:
    """A stop (hold) in phase 1, 0.2 s held, resume: the check passes and the same phase
    goes on (each phase once in the record); the step completes. (Held longer, the
    standing legs sink through the rig's piston leakage, about 3 mm/s at their load, and
    the check refuses: docs/walking.md.)"""
    state: dict[str, Any] = {}

    def act(h: Harness) -> None:
        t = h.sim.t_s
        if "held" not in state and t >= 3.0:
            state["held"] = h.core.request_hold(wait_s=0.0)
        elif "held" in state and "resumed" not in state and t >= 3.2:
            state["resumed"] = h.core.request_unhold(wait_s=0.0)

    cfg = project(tmp_path)
    out, evs = walk(tmp_path, cfg, on_cycle=act)
    assert out["final_mode"] == "COMPLETE", out["fault_reasons"]
    modes = [
        (e["event"], e["to_mode"])
        for e in evs
        if e["kind"] == "mode" and e["event"] in ("hold", "unhold")
    ]
    assert modes == [("hold", "HELD"), ("unhold", "EXECUTE")]
    phases = [e["phase"] for e in evs if e["kind"] == "walk_phase"]
    assert phases.count("1") == 1
    assert abs(out["distance_m"] - 0.2) <= 0.005


def test_a_link_loss_while_travelling_is_ridden_through(tmp_path: Path) -> None:
    """Both directions of the wire stalled for 60 ms while the travel pair moves at full
    speed (phase 1): the service suspends, the PLC hears nothing and the pair coasts on
    its last command (about 3 mm past where the service stopped it); once the frames are
    fresh the walk's resume check passes (the travel pair's coasting allowance: the
    travel speed times the PLC's command timeout, plus the height tolerance) and the same
    phase goes on. The generic check (every rod within the 2 mm sync band of its stop
    reference) latched this (`travel_1 2.78 mm`) in a real-time walk."""
    stall = {"kind": "wire_stall", "start_s": 3.0, "end_s": 3.06, "direction": "both"}
    out, evs = walk(tmp_path, project(tmp_path), {"events": [stall]})
    assert out["final_mode"] == "COMPLETE", out["fault_reasons"]
    kinds = [e["kind"] for e in evs]
    assert kinds.count("suspended") >= 1 and kinds.count("resumed") == kinds.count("suspended")
    phases = [e["phase"] for e in evs if e["kind"] == "walk_phase"]
    assert phases.count("1") == 1
    assert abs(out["distance_m"] - 0.2) <= 0.005


def test_a_short_plc_stall_while_m_lowers_is_ridden_through_on_a_drawn_machine() -> None:
    """Run 61 of the walk campaign as it was (a step forward, its events within the step;
    a drawn machine, the invert 6.3 mm lower from x = 4.42 m on): the PLC stalls 29 ms
    while M lowers (7a), at t = 100.87 s then, as much later now as the force ramps'
    blends before 7a made the step. The ride-through's resume check takes the rods (all
    within their tolerances) and leaves the legs' forces to the overload and transfer
    checks; the step completes within every goal. With the forces in the check
    (`main_leg_1` 19.6 kN changed, the limit 11.9 kN: the lowering legs settling as the
    valves closed) the walk latched."""
    from config.loader import read_yaml
    from wara.campaign.run import run_one
    from wara.campaign.spec import campaign_from_data

    path = ROOT / "config" / "campaigns" / "shanghai_airport_link_walk.yaml"
    data = read_yaml(path)
    data["run"].pop("and_back", None)
    for ev in data["events"]:
        if ev["start_s"].get("high") is not None:
            ev["start_s"]["high"] = 110
    c = campaign_from_data(data, str(path), path.parent)
    d = c.draw(61)
    assert d.params["event3_plc_stall_start_s"] == pytest.approx(100.873, abs=1e-3)
    cfg = load_project(None)
    assert cfg.walking is not None
    plan = plan_walk(cfg, 1)
    later_s = 0.0
    for ph in plan.phases:
        if ph.key in ("3", "4"):  # S's preload and transfer: each one blend longer
            line_s = float(np.abs(ph.leg_forces_n[-1] - ph.leg_forces_n[0]).max())
            later_s += ph.duration_s - line_s / cfg.walking.force_ramp_n_s
    events = [
        ev.model_copy(update={"start_s": ev.start_s + later_s, "end_s": ev.end_s + later_s})
        if ev.kind == "plc_stall"
        else ev
        for ev in d.scenario.events
    ]
    d.scenario = d.scenario.model_copy(update={"events": tuple(events)})
    c.draw = lambda _i: d  # type: ignore[method-assign]
    row = run_one(c, 61)
    assert row["status"] == "passed", (row["note"], row["fault_reasons"])


def test_upper_platform_frames_lost_while_walking_drive_nothing(tmp_path: Path) -> None:
    """70 % of the upper platform's position frames lost for 10 s of the walk (outside
    the active group it runs at its slow 50 ms cycle, so its positions go stale for
    hundreds of ms at a time): a cylinder whose position is not valid is not driven,
    and its hold goes on from the last valid value when one comes. The step completes
    and the upper rods end where the same walk without the loss leaves them. (A stale
    position read as 0 drove them out and the main legs' forces past 110 %.)"""
    drop = {"kind": "drop", "start_s": 1.0, "end_s": 11.0, "rate": 0.7,
            "messages": ["PLC_RodPos_4", "PLC_RodPos_5"]}  # fmt: skip
    config = project(tmp_path)
    ends = []
    for k, scenario in enumerate((None, {"events": [drop]})):
        last: dict[str, Any] = {}

        def watch(h: Harness, last: dict[str, Any] = last) -> None:
            last["x"] = h.sim.rig.rod_positions_m[8:12].copy()  # upper_1..4

        out, _evs = walk(tmp_path / str(k), config, scenario, on_cycle=watch)
        assert out["final_mode"] == "COMPLETE", out["fault_reasons"]
        assert abs(out["distance_m"] - 0.2) <= 0.005
        ends.append(last["x"])
    assert abs(ends[1] - ends[0]).max() < 1e-4  # m


def test_a_part_set_down_off_its_yaml_cog_walks_on_the_measured_load(tmp_path: Path) -> None:
    """The simulated part 0.15 m further left and 0.1 m further back than the YAML says
    (and 2 % heavier): the service's statics take the machine's weight and COG from M's
    standing legs at the start (docs/walking.md, "The measured load"), so the legs'
    shares are judged against the machine as it is, and the step completes below the
    overload. (On the YAML's statics `main_leg_2` read 110.06 % of its share while S
    advanced, and the overload latched.)"""
    config = project(tmp_path)
    cfg = load_project(config)
    d = cfg.model_dump(mode="json")
    part = d["layers"]["upper"]["bodies"][0]
    assert part["name"] == "workpiece"
    part["mass_kg"] *= 1.02
    part["cog_m"] = [part["cog_m"][0] - 0.1, part["cog_m"][1] + 0.15, part["cog_m"][2]]
    from config.schema import ProjectConfig

    sim_cfg = ProjectConfig.model_validate(d)
    out = run_walk(config, 1, sim_cfg=sim_cfg)
    assert out["final_mode"] == "COMPLETE", out["fault_reasons"]
    (step,) = out["steps"]
    assert step["max_leg_force_ratio"] <= 1.08 and step["passed"]


def test_resume_refused_when_a_leg_sank_while_stopped(tmp_path: Path) -> None:
    state: dict[str, Any] = {}

    def act(h: Harness) -> None:
        t = h.sim.t_s
        if "held" not in state and t >= 3.0:
            state["held"] = h.core.request_hold()
        elif "held" in state and "unhold" not in state and t >= 3.2:
            state["unhold"] = h.core.request_unhold()
        elif "unhold" in state and "mode" not in state and t >= 3.3:
            state["mode"] = h.core.modes.mode
            h.core.modes.stop("test: the walk ends")

    leak = {"kind": "holding_valve_leak", "cylinder": "main_leg_1", "leakage_m3_s_pa": 1e-10,
            "start_s": 3.05}  # fmt: skip
    out, evs = walk(tmp_path, project(tmp_path), {"events": [leak]}, on_cycle=act)
    assert state["mode"] is Mode.HELD  # the resume was refused
    (refused,) = [e for e in evs if e["kind"] == "walk_resume_refused"]
    assert refused["reason"].startswith("walk resume check: main_leg_1")
    assert out["final_mode"] == "IDLE"


def test_a_walk_that_cannot_keep_the_margin_is_refused_before_anything_moves(
    tmp_path: Path,
) -> None:
    cfg = project(tmp_path, min_stability_margin_m=0.9)
    run = subprocess.run(
        [sys.executable, "-m", "wara", "walk", "--steps", "1", "--lockstep", "--json",
         "--config", cfg],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
    )  # fmt: skip
    assert run.returncode == 3, run.stderr[-2000:]
    out = json.loads(run.stdout)
    assert out["refused"]["constraint"] == "stability_margin"
    assert out["distance_m"] == 0.0 and out["steps"] == []
    assert "walk refused: stability_margin" in run.stderr


def test_attitude_adjustment_from_the_walks_end_state(tmp_path: Path) -> None:
    """After a step (M standing, S lifted) an adjustment plans from the measured state,
    runs on the attitude group and reaches its target."""
    cfg = project(tmp_path)
    result: dict[str, Any] = {}

    def act(h: Harness) -> None:
        if h.core.modes.mode is Mode.COMPLETE and "adjust" not in result:
            result["adjust"] = h.core.request_adjust(1.0, 0.5)
            ok = h.wait_for(Mode.EXECUTE, 60.0) and h.wait_for(Mode.COMPLETE, 120.0)
            h.advance(2.0)
            truth = h.sim.truth()
            result["ok"] = ok
            result["achieved"] = (truth.workpiece_roll_rad, truth.workpiece_pitch_rad)
            result["active"] = h.core.active

    out, _evs = walk(tmp_path, cfg, on_cycle=act)
    assert result["adjust"]["ok"] and result["ok"], out["fault_reasons"]
    roll, pitch = (v * 57.29577951308232 for v in result["achieved"])
    assert abs(roll - 1.0) <= 0.01 and abs(pitch - 0.5) <= 0.01


def test_a_step_forward_then_back_ends_where_it_started(tmp_path: Path) -> None:
    """A step forward, then one back (the gait mirrored): each meets the step's goals
    and the machine ends within 5 mm of its start in world x (simulator truth)."""
    out, evs = walk(tmp_path, project(tmp_path), directions=("forward", "back"))
    assert out["passed"], (out["fault_reasons"], out["steps"])
    assert [r["direction"] for r in out["steps"]] == ["forward", "back"]
    assert out["steps"][1]["distance_m"] == pytest.approx(-0.2, abs=0.005)
    assert abs(out["distance_m"]) <= 0.005
    walks = [e for e in evs if e["kind"] == "walk"]
    assert [(e["direction"], e["unloaded"]) for e in walks] == [
        ("forward", False),
        ("back", False),
    ]
    back_t = walks[1]["t_s"]
    names = [e["name"] for e in evs if e["kind"] == "walk_phase" and e["t_s"] >= back_t]
    assert names[0] == "lower S" and names[4] == "move M back" and names[-1] == "move S back"


def _hmi_walk(tmp_path: Path, walk_steps: int) -> tuple[Harness, list[dict[str, Any]], Any]:
    """The HMI asks for a walk through the PLC (PLC_HmiTarget, TargetRequest WALK) at 0.5 s;
    run until the walk executes (or 3 s)."""
    from wara.walk import walk_scenario

    cfg_path = project(tmp_path)
    cfg = load_project(cfg_path)
    ev = {"kind": "hmi_target", "at_s": 0.5, "request": "walk", "walk_steps": walk_steps}
    sc = walk_scenario(HilScenario.model_validate({"events": [ev]}))
    with recorder(tmp_path, cfg_path) as rec:
        h = Harness(cfg, cfg_path, mode="lockstep", scenario=sc, record=rec)
        try:
            h.start()
            assert h.wait_for(Mode.IDLE, 20.0)
            started = h.wait_for(Mode.EXECUTE, 3.0)
            h.advance(0.5)
            spool = float(abs(h.sim.rig.spool_m).max())  # every valve's spool, m
            word = h.core.handshake.word
            out = (started, h.core.modes.mode, word.ack_seq, word.ack_status, spool)
        finally:
            h.close()
    return h, events(tmp_path / "run"), out


def test_the_hmi_asks_for_a_walk_through_the_plc_and_it_starts(tmp_path: Path) -> None:
    from plc_bridge.link import TargetAck

    h, evs, (started, mode, ack_seq, ack_status, _spool) = _hmi_walk(tmp_path, 1)
    assert started and mode is Mode.EXECUTE
    assert h.sim.hmi_issued == [1] and (ack_seq, ack_status) == (1, TargetAck.ACCEPTED)
    assert [e["steps"] for e in evs if e["kind"] == "walk"] == [1]
    assert [e["phase"] for e in evs if e["kind"] == "walk_phase"][:1] == ["1"]


def test_a_malformed_hmi_walk_request_is_refused_with_its_reason_and_nothing_moves(
    tmp_path: Path,
) -> None:
    from plc_bridge.link import TargetAck

    _h, evs, (started, mode, ack_seq, ack_status, spool) = _hmi_walk(tmp_path, 0)
    assert not started and mode is Mode.IDLE
    assert (ack_seq, ack_status) == (1, TargetAck.REJECTED)
    (refused,) = [e for e in evs if e["kind"] == "hmi_refused"]
    assert refused["reason"] == "HMI walk refused: WalkSteps 0 (a walk is 1..3 steps)"
    assert not [e for e in evs if e["kind"] in ("walk", "walk_phase")]
    assert spool == 0.0  # every valve closed: nothing is driven


def keep_transfer_force_ratios(out: str) -> None:
    """Hook for :func:`run_wara_observed`: the walk's largest leg force ratio in each of
    M's touch-down (7a), preload (7b) and the transfer to M (7c), written to ``out``."""
    import wara.walk

    inner = wara.walk.run_walk

    def run(*args: Any, on_cycle: Any = None, **kwargs: Any) -> dict[str, Any]:
        worst: dict[str, float] = {}

        def watch(h: Any) -> None:
            if on_cycle is not None:
                on_cycle(h)
            w = h.core.walker
            if w is None or w.run is None or w.run.phase.key not in ("7a", "7b", "7c"):
                return
            fig = w.figures
            ratio = max(f / e for f, e in zip(fig.leg_force_n, fig.expected_n, strict=True))
            key = w.run.phase.key
            worst[key] = max(worst.get(key, 0.0), ratio)

        result = inner(*args, on_cycle=watch, **kwargs)
        Path(out).write_text(json.dumps(worst), encoding="utf-8")
        return result

    wara.walk.run_walk = run


@pytest.fixture(scope="module")
def shipped_steps() -> tuple[subprocess.CompletedProcess[str], dict[str, float]]:
    """`wara walk --steps 3 --lockstep --json` with the shipped project (2 m steps), run
    once as the user runs it, the transfers' force ratios kept by a hook."""
    args = ["walk", "--steps", "3", "--lockstep", "--json"]
    run, worst = run_wara_observed(args, keep_transfer_force_ratios, timeout_s=7200, cwd=ROOT)
    return run, worst or {}


@pytest.mark.slow(seconds=100)
@pytest.mark.xdist_group("shipped_steps")
def test_three_shipped_steps_as_the_user_runs_them(
    shipped_steps: tuple[subprocess.CompletedProcess[str], dict[str, float]],
) -> None:
    """`wara walk --steps 3 --lockstep --json` with the shipped project (2 m steps): the
    goals of the walk (docs/walking.md), exit 0. Measured (docs/figures.md, walk):
    6.000188 m, the transfers' attitude change at most 0.0036 deg (goal 0.01), the
    largest force ratio (less the seals' unseen friction) 1.011 / 0.997 / 0.998, 127.4 s
    a step of 136.2."""
    run, _ = shipped_steps
    out = json.loads(run.stdout)
    assert run.returncode == 0, (out["fault_reasons"], run.stderr[-2000:])
    assert out["passed"] and out["final_mode"] == "COMPLETE"
    assert abs(out["distance_m"] - 6.0) <= 0.005  # simulator truth
    assert len(out["steps"]) == 3
    for st in out["steps"]:
        assert abs(st["distance_m"] - 2.0) <= 0.005
        assert st["max_leg_sync_error_mm"] <= 2.0
        assert st["max_travel_sync_error_mm"] <= 5.0
        assert st["max_transfer_attitude_change_deg"] <= 0.01
        assert st["max_leg_force_ratio"] <= 1.10
        assert st["min_stability_margin_m"] >= 0.25
        # its touch-downs took less than their windows (the goal gives each its whole)
        assert st["duration_s"] <= step_time_limit_s(load_project(None)) - 5.0


@pytest.mark.slow(seconds=100)
@pytest.mark.xdist_group("shipped_steps")
def test_the_shipped_step_completes_below_the_overload(
    shipped_steps: tuple[subprocess.CompletedProcess[str], dict[str, float]],
) -> None:
    """The shipped 2 m steps (the three of the run above), lockstep: through M's
    touch-down (7a) and preload (7b) S stands in position control, its twist held by the
    twist-mode force loop; in the transfer to M (7c) S's releasing loops are told their
    oil columns' decompression (docs/walking.md). Measured: the largest force ratio 1.061
    in 7a, 1.069 in 7b, 1.057 in 7c (7b tripped at 1.1026 with the twist set through S's
    position references, 7c at 1.1088 with the touch-down at 5 mm/s)."""
    run, worst = shipped_steps
    out = json.loads(run.stdout)
    assert out["passed"] and out["final_mode"] == "COMPLETE", out["fault_reasons"]
    assert max(worst.values()) < 1.08 and len(worst) == 3, worst
    assert out["steps"][0]["max_leg_force_ratio"] <= 1.10
