"""The ring cycle as a request of the service (``wara ctl cycle``): its phases in order,
the part on the platform it starts from, the operator's fixing confirmation, the
release that lowers the platform off the bolted part (and stops when the part is not
fixed), the survey it waits for, a stop in a phase, and bad input (docs/placement.md).
The machine stands at its ring here (``walk_steps`` 0); the walks: tests/test_ring_cycle.py."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from config import load_project
from hil_sim.placement import pose_from_home
from ipc_app.model.placement import Pose, compose, sheet_deviation
from ipc_app.planner.placement import home_pose
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import CtlHandlers, Request, dispatch, parse
from ipc_app.service.cycle import PHASES, RECORD_KEYS, RingCycle, previous_from_deviation
from ipc_app.service.modes import Mode
from ipc_app.service.record import RunRecorder
from tests.test_ring_cycle import _place_harness
from wara.cycle import simulated_survey
from wara.harness import Harness


class _Records:
    """A RingRecords sink that keeps what it was given."""

    def __init__(self) -> None:
        self.written: list[tuple[int, dict[str, float | None], dict[str, Any]]] = []

    def write(self, ring: int, values: dict[str, float | None], attached: dict[str, Any]) -> str:
        self.written.append((ring, values, attached))
        return "memory"


def _run_until(h: Harness, cyc: RingCycle, phase: str, limit_s: float = 60.0) -> None:
    """Tick the cycle between simulated periods until it is in ``phase`` (or ends)."""
    t_end = h.sim.t_s + limit_s
    while cyc.active and cyc.phase != phase and h.sim.t_s < t_end:
        cyc.tick()
        if cyc.active and cyc.phase != phase:
            h.advance(h.period)
    assert cyc.phase == phase, (cyc.phase, cyc.error)


def _events(tmp_path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (tmp_path / "run" / "events.jsonl").open()]


@pytest.mark.slow
def test_the_cycle_waits_for_the_operator_and_the_survey(tmp_path: Path) -> None:
    """The phases in order; ``fixing`` holds the pose until the operator confirms
    (audited, with their name), ``survey`` until a survey is submitted (a bad one is
    refused and the cycle keeps waiting); the record goes to the sink with the plan and
    the as-built pose; a confirmation out of its phase is refused."""
    cfg = load_project(None)
    h, rec = _place_harness(tmp_path)
    records = _Records()
    try:
        previous = previous_from_deviation(cfg, 3, sheet_deviation(2, -2, 0, 0, 0))
        out = h.core.request_cycle(3, previous, records, drive=False, walk_steps=0)
        assert out == {"ok": True, "ring": 3, "phase": "load"}
        again = h.core.request_cycle(3, previous, records, drive=False)
        assert again["ok"] is False and "ring 3's cycle is in load" in again["error"]
        cyc = h.core.ring_cycle
        assert cyc is not None
        assert h.core.submit_survey(pose=Pose())["code"] == "refused"  # not in survey yet
        _run_until(h, cyc, "place")  # the part on the platform: its pressures
        assert cyc.phase_times_s["load"] == pytest.approx(1.0, abs=0.02)  # LOAD_SETTLED_S
        _run_until(h, cyc, "fixing")
        assert h.core.modes.mode == Mode.COMPLETE and h.core.modes.valves_enabled
        h.advance(2.0)  # no confirmation: the pose stays held
        cyc.tick()
        status = h.core.snapshot()["cycle"]
        assert (status["phase"], status["waiting_for"]) == (
            "fixing",
            "operator confirmation (wara ctl confirm-fixed)",
        )
        h.sim.bolt_part()  # the crew's bolts
        r, t = pose_from_home(cfg, h.sim.rig)
        as_built = compose(home_pose(cfg, 3), Pose.from_matrix(r, t))
        assert h.core.confirm_fixed("operator A")["ok"] is True
        assert h.core.confirm_fixed("operator A")["code"] == "refused"  # once
        assert cyc.phase == "release"
        cyc.tick()
        h.advance(h.period)
        assert h.core.modes.mode == Mode.EXECUTE and h.core.releaser is not None
        assert h.core.snapshot()["release"]["phase"] == "lowering"
        _run_until(h, cyc, "survey", limit_s=30.0)
        assert h.core.modes.mode == Mode.IDLE and not h.core.modes.valves_enabled  # stopped
        fig = cyc.release_figures
        assert 1.0 < fig["released_at_mm"] < 2.5 and fig["travel_mm"] > fig["released_at_mm"] + 4.9
        assert h.sim.rig.part_load_n == 0.0  # the platform clear of the part
        pts = simulated_survey(cfg, 3, as_built, np.random.default_rng(0))
        few = h.core.submit_survey(points=pts[:3])
        assert few["ok"] is False and few["code"] == "bad_request"
        assert few["error"].startswith("survey: the points lie on one line")
        assert cyc.phase == "survey"
        far = [p.__class__(p.line, p.name, p.face, (p.measured[0] + 5.0, *p.measured[1:]))
               for p in pts]  # fmt: skip
        assert h.core.submit_survey(points=far)["code"] == "refused"  # another ring's face
        good = h.core.submit_survey(points=pts)
        assert good["ok"] and good["rms_residual_mm"] < 3.0
        cyc.tick()
        assert cyc.done and cyc.error is None and cyc.phase == "done"
    finally:
        h.close()
        rec.stop()
    assert set(cyc.phase_times_s) == set(PHASES)
    ((ring, values, attached),) = records.written
    assert ring == 3 and set(values) == set(RECORD_KEYS)
    assert attached["kind"] == "ring_cycle" and attached["plan"]["ring"] == 3
    assert attached["cycle"]["fixed_by"] == "operator A"
    assert attached["cycle"]["release"] == fig
    # the as-built pose as the store keeps it (mm, deg; a round trip to SI is not exact)
    assert attached["as_built_pose"] == cyc.surveyed.to_dict()
    evs = _events(tmp_path)
    phases = [e["phase"] for e in evs if e["kind"] == "cycle_phase"]
    assert phases == list(PHASES)
    (audit,) = [e for e in evs if e["kind"] == "audit"]
    assert (audit["user"], audit["action"]) == ("operator A", "confirm_fixed")
    (end,) = [e for e in evs if e["kind"] == "cycle_end"]
    assert end["error"] is None and end["phase"] == "done"
    kinds = [e["kind"] for e in evs]
    assert {"release", "release_phase", "release_done"} <= set(kinds)


def _cycle_in_fixing(tmp_path: Path) -> tuple[Harness, RunRecorder, _Records, RingCycle]:
    """A ring cycle standing at its ring (no walk) on the placement harness, run until
    its part waits in ``fixing``."""
    cfg = load_project(None)
    h, rec = _place_harness(tmp_path)
    records = _Records()
    previous = previous_from_deviation(cfg, 2, Pose())
    assert h.core.request_cycle(2, previous, records, drive=False, walk_steps=0)["ok"]
    cyc = h.core.ring_cycle
    assert cyc is not None
    _run_until(h, cyc, "fixing")
    return h, rec, records, cyc


@pytest.mark.slow
def test_a_part_not_fixed_stops_the_release_with_its_interlock(tmp_path: Path) -> None:
    """The operator confirms a part whose bolts do not hold (here: none): the platform
    lowers its whole travel with the part's weight still on it, the ``release``
    interlock stops the machine (ABORTED, valves closed, the part held on the
    platform), and the cycle ends in ``release`` with that cause, nothing recorded."""
    h, rec, records, cyc = _cycle_in_fixing(tmp_path)
    try:
        x0 = h.sim.rig.rod_positions_m[h.sim.rig.upper_index].mean()
        assert h.core.confirm_fixed("operator A")["ok"]  # but nobody bolted it
        t_end = h.sim.t_s + 30.0
        while cyc.active and h.sim.t_s < t_end:
            cyc.tick()
            h.advance(h.period)
        assert h.core.modes.mode == Mode.ABORTED and not h.core.modes.valves_enabled
        (reason,) = h.core.modes.fault_reasons
        assert reason.startswith("release: upper_") and "(above the limit 10.00 mm)" in reason
        assert cyc.stopped_in_phase == "release" and "release" in (cyc.error or "")
        lowered = x0 - h.sim.rig.rod_positions_m[h.sim.rig.upper_index].mean()
        assert 0.0099 < lowered < 0.0105  # stopped at its travel, the part still on it
        assert h.sim.rig.part_state == "carried"
    finally:
        h.close()
        rec.stop()
    assert records.written == []


@pytest.mark.slow
def test_a_motion_not_ended_in_max_motion_min_ends_the_cycle(tmp_path: Path) -> None:
    """``cycle.max_motion_min`` bounds each motion the cycle asks for: 0.1 min lets the
    placement (some 5 s here) through and ends the release (some 8 s) when it runs
    out: the cycle ends in ``release`` naming the limit, the machine stopped."""
    cfg = load_project(None)
    assert cfg.cycle is not None
    short = cfg.model_copy(update={"cycle": cfg.cycle.model_copy(update={"max_motion_min": 0.1})})
    h = Harness(short, None, mode="lockstep")
    try:
        h.start()
        assert h.wait_for(Mode.IDLE, 20.0), h.fault_note()
        previous = previous_from_deviation(short, 2, Pose())
        assert h.core.request_cycle(2, previous, _Records(), drive=False, walk_steps=0)["ok"]
        cyc = h.core.ring_cycle
        assert cyc is not None
        _run_until(h, cyc, "fixing")
        h.sim.bolt_part()
        assert h.core.confirm_fixed("operator A")["ok"]
        t_end = h.sim.t_s + 20.0
        while cyc.active and h.sim.t_s < t_end:
            cyc.tick()
            h.advance(h.period)
        assert cyc.stopped_in_phase == "release" and cyc.error == "release did not end within 6 s"
        h.advance(h.period)
        assert h.core.modes.mode == Mode.IDLE and not h.core.modes.valves_enabled
    finally:
        h.close()


@pytest.mark.slow
def test_a_stop_in_fixing_ends_the_cycle_holding_safely(tmp_path: Path) -> None:
    """``wara ctl stop`` while the part waits for its bolts: the valves close, the
    cycle ends in ``fixing`` (named), nothing is recorded, a confirmation is refused."""
    h, rec, records, cyc = _cycle_in_fixing(tmp_path)
    try:
        h.core.stop("operator stop (test)")
        h.advance(0.2)
        assert h.core.modes.mode == Mode.IDLE and not h.core.modes.valves_enabled
        assert not cyc.active and cyc.stopped_in_phase == "fixing"
        assert cyc.error == "stopped: operator stop (test)"
        refusal = h.core.confirm_fixed("operator A")
        assert refusal["code"] == "refused"  # and says why: the cycle ended, not its phase
        assert refusal["error"] == (
            "confirm-fixed refused: ring 2's cycle ended in fixing: stopped: operator stop (test)"
        )
        assert h.core.snapshot()["cycle"]["error"] == cyc.error
    finally:
        h.close()
        rec.stop()
    assert records.written == []
    (end,) = [e for e in _events(tmp_path) if e["kind"] == "cycle_end"]
    assert end["phase"] == "fixing" and end["error"].startswith("stopped")


@pytest.mark.slow
def test_a_refused_survey_leaves_the_cycle_waiting_for_another(tmp_path: Path) -> None:
    """In ``survey``, through the service's own handlers and the reply encoder: a pose of
    1e300 (the ``--from-store`` form), points with a coordinate of 1e308 (once answered
    ``{"ok": true, "rms_residual_mm": NaN}`` and the record never written) and a part
    turned 15 deg are each refused with their reason; the cycle stays in ``survey`` and
    takes the good survey that follows, and the record is written."""
    from ipc_app.service.app import service_handlers
    from ipc_app.service.ctl import _line

    cfg = load_project(None)
    h, rec, records, cyc = _cycle_in_fixing(tmp_path)
    handlers = service_handlers(lambda: h.core, lambda: None, records=records)  # type: ignore[arg-type,return-value]

    def send(req: dict[str, Any]) -> dict[str, Any]:
        raw = _line(dispatch(handlers, json.dumps(req).encode()))
        reply: dict[str, Any] = json.loads(raw, parse_constant=lambda c: pytest.fail(c))
        return reply

    try:
        h.sim.bolt_part()
        r, t = pose_from_home(cfg, h.sim.rig)
        as_built = compose(home_pose(cfg, 2), Pose.from_matrix(r, t))
        assert h.core.confirm_fixed("operator A")["ok"]
        _run_until(h, cyc, "survey", limit_s=30.0)
        pts = simulated_survey(cfg, 2, as_built, np.random.default_rng(0))
        rows = [[p.name, *p.face, *p.measured] for p in pts]
        out = send({"cmd": "survey", "pose": [1e300] * 6})
        assert out["ok"] is False and out["code"] == "refused"
        assert out["error"].startswith("survey refused: the part is 1.41e+300 mm across")
        huge = [*rows[:-1], [*rows[-1][:5], 1e308]]
        out = send({"cmd": "survey", "points": huge})
        assert out == {
            "ok": False,
            "code": "bad_request",
            "error": f"survey: point {len(rows)}: z_m: 1e+308 m is outside -10000..10000 m",
        }
        turned = compose(as_built, Pose(0.0, 0.0, 0.0, 0.0, 0.0, np.radians(15.0)))
        tp = simulated_survey(cfg, 2, turned, np.random.default_rng(0))
        out = send({"cmd": "survey", "points": [[p.name, *p.face, *p.measured] for p in tp]})
        assert out["code"] == "refused" and "turned yaw +15.0 deg" in out["error"]
        cyc.tick()
        assert cyc.active and cyc.phase == "survey" and records.written == []
        good = send({"cmd": "survey", "points": rows})
        assert good["ok"] is True and 0.0 < good["rms_residual_mm"] < 3.0
        cyc.tick()
        assert cyc.done and cyc.error is None
    finally:
        h.close()
        rec.stop()
    ((ring, values, _attached),) = records.written
    assert ring == 2 and all(v is None or np.isfinite(v) for v in values.values())


def test_cycle_requests_are_checked() -> None:
    ok = parse(b'{"cmd": "cycle", "ring": 5, "previous_deviation": [6, -6, 0, 0, 0.03]}')
    assert ok == Request("cycle", (5, (6.0, -6.0, 0.0, 0.0, 0.03), None, True))
    req = parse(
        b'{"cmd": "cycle", "ring": 5, "previous_pose": [1000, 2, -6250, 0, 0, 0],'
        b' "walk_steps": 2, "walk_back_unloaded": false}'
    )
    assert req == Request("cycle", (5, (1000.0, 2.0, -6250.0, 0.0, 0.0, 0.0), 2, False))
    assert parse(b'{"cmd": "confirm_fixed", "user": "ann"}') == Request("confirm_fixed", ("ann",))
    pt = b'["P1", 4.0, 0.3, 7.98, 4.0, -5.97]'
    assert parse(b'{"cmd": "survey", "points": [' + pt + b"]}") == Request(
        "survey", ((("P1", 4.0, 0.3, 7.98, 4.0, -5.97),), None)
    )
    for bad, why in [
        (b'{"cmd": "cycle", "ring": 1}', "'ring' must be an integer 2..99999"),
        (b'{"cmd": "cycle", "ring": 3, "previous_deviation": [1, 2]}', "must be 5 numbers"),
        (
            b'{"cmd": "cycle", "ring": 3, "previous_deviation": [0,0,0,0,0],'
            b' "previous_pose": [0,0,0,0,0,0]}',
            "not both",
        ),
        (b'{"cmd": "cycle", "ring": 3, "walk_steps": -1}', "'walk_steps' must be an integer"),
        (b'{"cmd": "cycle", "ring": 3, "walk_back_unloaded": 1}', "true or false"),
        (b'{"cmd": "confirm_fixed"}', "'user' must be a name"),
        (b'{"cmd": "survey"}', "give 'points' or 'pose'"),
        (b'{"cmd": "survey", "points": []}', "a list of 1..200 points"),
        (b'{"cmd": "survey", "points": [["P1", 1, 2]]}', "point 1: [name, face_y_m"),
        (b'{"cmd": "survey", "points": [["P1", 1, 2, 3, "x", 5]]}', "finite number"),
        (b'{"cmd": "survey", "pose": [0, 0]}', "'pose' must be 6 numbers"),
    ]:
        out = parse(bad)
        assert isinstance(out, dict) and out["code"] == "bad_request", bad
        assert why in out["error"], out["error"]
    handlers = CtlHandlers(adjust=lambda r, p: {}, status=dict, stop=dict, reset=dict)
    out = dispatch(handlers, b'{"cmd": "confirm_fixed", "user": "ann"}')
    assert out["code"] == "bad_request" and "not supported" in out["error"]


def test_a_cycle_is_refused_where_it_cannot_run() -> None:
    """Without an acceptance store for the records, or in a mode other than IDLE and
    COMPLETE, the request is refused before anything moves; the operator's requests
    without a cycle too."""
    import can

    from ipc_app.service.app import service_handlers
    from plc_bridge.link import IpcLink

    class NoPlanner:
        def submit(self, *a: Any, **k: Any) -> bool:
            return False

        def poll(self) -> None:
            return None

    cfg = load_project(None)
    bus = can.Bus(interface="virtual", channel="service-cycle-refusals")
    try:
        core = ServiceCore(cfg, IpcLink(cfg, bus, clock=lambda: 0.0), NoPlanner())
        handlers = service_handlers(lambda: core, lambda: None)  # type: ignore[arg-type,return-value]
        out = dispatch(handlers, b'{"cmd": "cycle", "ring": 3}')
        assert out["ok"] is False and "no acceptance store" in out["error"]
        out = core.request_cycle(3, Pose(), _Records(), drive=False)
        assert out["code"] == "refused" and "the service is STOPPED" in out["error"]
        assert core.request_cycle(1, Pose(), _Records())["code"] == "bad_request"
        assert "no cycle" in core.confirm_fixed("ann")["error"]
        assert "no cycle" in core.submit_survey(pose=Pose())["error"]
    finally:
        bus.shutdown()


def test_wara_ctl_cycle_bad_input_exits_2_before_anything_is_sent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    from wara.cli import main

    monkeypatch.setenv("WARA_CTL_SOCKET", str(tmp_path / "none.sock"))  # no service there
    bad = tmp_path / "bad.csv"
    bad.write_text("point,face_y_m,face_z_m,x_m,y_m,z_m\nP1,4,0.3,abc,4,-6\n", encoding="utf-8")
    for argv, text in [
        (["ctl", "cycle", "--ring", "1"], "--ring must be within 2..99999, got 1"),
        (["ctl", "cycle", "--ring", "3", "--walk-steps", "-1"], "--walk-steps must be within"),
        (["ctl", "cycle", "--ring", "3", "--previous-deviation", "1,2"], "expects five numbers"),
        (
            ["ctl", "cycle", "--ring", "3", "--from-store", "--db", str(tmp_path / "x.sqlite")],
            "no acceptance database here",
        ),
        (["ctl", "survey", str(bad)], "line 2: x_m: 'abc' is not a number"),
        (["ctl", "survey", str(tmp_path / "missing.csv")], "missing.csv"),
        (["ctl", "walk", "--steps", "1", "--direction", "up"], "--direction must be one of"),
    ]:
        assert main(argv) == 2, argv
        assert text in capsys.readouterr().err, argv
