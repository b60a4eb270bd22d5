"""Where the machine stands, surveyed (curves.md section 3; docs/curves.md "Walking on a
curve"): ``wara ctl locate`` sets the service's ``on_axis``, checked and refused where
a walk's end would overwrite it; the next walk steers from it; the simulated surveyor of
``wara cycle`` sees M through two prisms with the survey's noise and gives it to the
service."""

from __future__ import annotations

import contextlib
import importlib
import json
import math
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import can
import numpy as np
import pytest
from structlog.testing import capture_logs

from config import ProjectConfig, load_project, units
from ipc_app.planner.steering import OnAxis, on_axis_at_start
from ipc_app.planner.walk import WalkPlan
from ipc_app.service.app import service_handlers
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import Request, dispatch, parse
from ipc_app.service.motions.walk import WalkMotion, plan_walk_here
from plc_bridge.link import IpcLink
from tests.machine_inputs import machine_inputs
from wara.cli import main
from wara.cycle import (
    LOCATE_GATE_SIGMA,
    _Cycle,
    machine_survey_sigma,
    machine_truth,
    simulated_machine_survey,
)
from wara.walk import against_axis

PROJECTS = Path(__file__).resolve().parents[1] / "config" / "projects"


class InProcessPlanner:
    """The planner's blocking ``call`` run in this process (the walk's plan)."""

    def __init__(self, cfg: ProjectConfig) -> None:
        self.cfg = cfg

    def submit(self, *a: Any, **k: Any) -> bool:
        return False

    def poll(self) -> None:
        return None

    def call(self, fn: str, *args: Any, **kwargs: Any) -> Any:
        module, name = fn.split(":")
        return getattr(importlib.import_module(module), name)(self.cfg, *args, **kwargs)


@contextlib.contextmanager
def _core(cfg: ProjectConfig, channel: str) -> Iterator[ServiceCore]:
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        core = ServiceCore(cfg, IpcLink(cfg, bus, clock=lambda: 0.0), InProcessPlanner(cfg))
        core._inputs = machine_inputs(cfg)  # a healthy machine at mid-stroke, standing
        yield core
    finally:
        bus.shutdown()


@pytest.fixture
def core() -> Iterator[ServiceCore]:
    with _core(load_project(None), "locate-test") as c:
        yield c


def _locate(**fields: Any) -> bytes:
    return json.dumps({"cmd": "locate", **fields}).encode()


GOOD = {"chainage_m": 812.4, "heading_error_deg": -0.02, "lateral_mm": 3.5}


def test_a_locate_request_is_checked() -> None:
    assert parse(_locate(**GOOD)) == Request("locate", (812.4, -0.02, 3.5))
    for fields, why in [
        ({}, "'chainage_m' must be a finite number in m, got None"),
        ({**GOOD, "lateral_mm": None}, "'lateral_mm' must be a finite number in mm"),
        ({"chainage_m": 1.0, "lateral_mm": 0.0}, "'heading_error_deg' must be a finite number"),
        ({**GOOD, "chainage_m": "812"}, "'chainage_m' must be a finite number in m"),
        ({**GOOD, "heading_error_deg": True}, "'heading_error_deg' must be a finite number"),
        ({**GOOD, "chainage_m": 2e6}, "'chainage_m' must be within -1e+06..1e+06 m"),
        ({**GOOD, "heading_error_deg": 5.5}, "'heading_error_deg' must be within -5..5 deg"),
        ({**GOOD, "lateral_mm": -501}, "'lateral_mm' must be within -500..500 mm"),
    ]:
        out = parse(_locate(**fields))
        assert isinstance(out, dict) and out["code"] == "bad_request", fields
        assert why in out["error"], out["error"]
    # JSON's NaN, Infinity and a number too large for a float: not finite
    for raw in (b"NaN", b"Infinity", b"-Infinity", b"1e999"):
        line = b'{"cmd": "locate", "chainage_m": 1, "heading_error_deg": ' + raw
        out = parse(line + b', "lateral_mm": 0}')
        assert isinstance(out, dict) and out["code"] == "bad_request", raw
        assert "'heading_error_deg' must be a finite number in deg" in out["error"]


def test_locate_sets_where_the_machine_stands_and_says_what_it_replaced(
    core: ServiceCore,
) -> None:
    """Through the service's handlers: deg and mm on the channel, SI in the core; the
    reply gives what it set, the estimate before (the start's at first) and the change;
    logged."""
    handlers = service_handlers(lambda: core, lambda: None)  # type: ignore[arg-type,return-value]
    assert core.on_axis is None
    with capture_logs() as logs:
        out = dispatch(handlers, _locate(**GOOD))
    assert out["ok"] is True, out
    assert core.on_axis is not None
    assert core.on_axis.chainage_m == 812.4
    assert core.on_axis.heading_error_rad == pytest.approx(units.deg(-0.02))
    assert core.on_axis.lateral_m == pytest.approx(units.mm(3.5))
    start = on_axis_at_start(core.cfg).to_dict()
    assert out["on_axis"] == GOOD and out["replaced"] == start
    assert out["change"] == {k: pytest.approx(GOOD[k] - start[k]) for k in GOOD}
    assert next(e for e in logs if e["event"] == "locate")["on_axis"] == GOOD
    assert core.snapshot()["on_axis"] == GOOD  # `wara ctl status` shows it
    again = dispatch(handlers, _locate(chainage_m=814.4, heading_error_deg=0, lateral_mm=0))
    assert again["replaced"] == GOOD and again["change"]["heading_error_deg"] == 0.02


@pytest.mark.parametrize("heading_deg", [0.03, -0.2])
def test_the_next_walk_steers_from_the_surveyed_heading(
    core: ServiceCore, heading_deg: float
) -> None:
    """A survey's heading error is steered back by the next walk's first step (on the
    straight axis, on it: the turn is the correction, bounded per step)."""
    assert core.cfg.walking is not None
    bound = core.cfg.walking.max_heading_correction_per_step_rad
    assert core.locate(OnAxis(10.0, units.deg(heading_deg), 0.0))["ok"] is True
    plan = plan_walk_here(core, 2)
    assert isinstance(plan, WalkPlan)
    first = plan.turns[0]
    want = -math.copysign(min(bound, units.deg(abs(heading_deg))), heading_deg)
    assert first.axis_turn_rad == 0.0
    assert first.correction_rad == pytest.approx(want) and first.turn_rad == first.correction_rad
    assert first.after.chainage_m == pytest.approx(10.0 + core.cfg.walking.step_length_m)


def test_locate_is_refused_while_a_walk_has_not_ended(core: ServiceCore) -> None:
    """A walk executing, held, suspended or stopped part-way sets ``on_axis`` at its end
    from the turns it measured: a survey meanwhile is refused, saying so; once it has
    ended, the survey is taken."""
    plan = plan_walk_here(core, 1)
    assert isinstance(plan, WalkPlan)
    walk = WalkMotion(core, plan)
    core.motions.active = walk
    out = core.locate(OnAxis(5.0))
    assert out["ok"] is False and out["code"] == "refused"
    assert out["error"].startswith("locate refused: the walk (1 step(s) forward of 2.000 m)")
    assert "its end sets where the machine stands" in out["error"]
    assert core.on_axis is None
    walk._walked()  # its end (no step finished: where it stood)
    assert not walk.on_axis_pending
    assert core.locate(OnAxis(5.0))["ok"] is True and core.on_axis == OnAxis(5.0)


def test_locate_is_refused_without_a_walking_section() -> None:
    cfg = load_project(None)
    still = cfg.model_copy(update={"walking": None})
    with _core(still, "locate-no-walking") as core:
        handlers = service_handlers(lambda: core, lambda: None)  # type: ignore[arg-type,return-value]
        out = dispatch(handlers, _locate(**GOOD))
        assert out == {
            "ok": False,
            "code": "refused",
            "error": "locate refused: the project has no frames and walking sections: it "
            "cannot walk",
        }
        assert core.on_axis is None


def test_wara_ctl_locate_checks_its_values_before_sending(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("WARA_CTL_SOCKET", str(tmp_path / "none.sock"))  # no service there
    base = ["ctl", "locate", "--chainage", "812.4", "--heading-error", "0.02"]
    for argv, text in [
        ([*base, "--offset", "600"], "--offset must be within -500..500 mm"),
        (["ctl", "locate", "--chainage", "1", "--heading-error", "-7", "--offset", "0"],
         "--heading-error must be within -5..5 deg"),
        ([*base, "--offset", "-3"], "none.sock"),  # checked, sent: nobody listens
    ]:  # fmt: skip
        assert main(argv) == 2, argv
        assert text in capsys.readouterr().err, argv
    with pytest.raises(SystemExit) as exc:
        main([*base, "--offset", "nan"])
    assert exc.value.code == 2


# --------------------------------------------------------------------------- the surveyor


@pytest.mark.parametrize("name", ["shanghai_airport_link", "curved_grade_heavy_part"])
def test_the_machine_survey_is_the_truth_plus_two_prisms_noise(name: str) -> None:
    """Over many draws: centred on the truth against the axis, the heading's spread
    ``sqrt(2) sigma / (2 a_M)``, the offset's ``sigma / sqrt(2)``, the two independent;
    the chainage the one given."""
    cfg = load_project(PROJECTS / f"{name}.yaml")
    assert cfg.cycle is not None
    sigma, a_m = cfg.cycle.survey_noise_m, cfg.layers.lower.a_m
    assert sigma > 0
    chainage = on_axis_at_start(cfg).chainage_m + 6.0
    xy, heading = (5.9, 0.012), 0.004
    truth = against_axis(cfg, chainage, xy, heading)
    m_truth = machine_truth(cfg, chainage, xy, heading)
    assert (m_truth.heading_error_rad, m_truth.lateral_m) == truth
    rng = np.random.default_rng(7)
    n = 5000
    draws = [simulated_machine_survey(cfg, m_truth, rng) for _ in range(n)]
    assert {d.chainage_m for d in draws} == {chainage}
    h = np.array([d.heading_error_rad for d in draws]) - truth[0]
    lat = np.array([d.lateral_m for d in draws]) - truth[1]
    sd_h, sd_lat = math.sqrt(2.0) * sigma / (2.0 * a_m), sigma / math.sqrt(2.0)
    assert abs(h.mean()) < 4 * sd_h / math.sqrt(n) and abs(lat.mean()) < 4 * sd_lat / math.sqrt(n)
    assert h.std() == pytest.approx(sd_h, rel=0.05)
    assert lat.std() == pytest.approx(sd_lat, rel=0.05)
    assert abs(np.corrcoef(h, lat)[0, 1]) < 0.05
    # the same seed, the same survey
    again = simulated_machine_survey(cfg, m_truth, np.random.default_rng(7))
    assert again == draws[0]
    # without noise: the truth against the axis
    quiet = cfg.model_copy(update={"cycle": cfg.cycle.model_copy(update={"survey_noise_mm": 0})})
    exact = simulated_machine_survey(quiet, m_truth, rng)
    assert (exact.heading_error_rad, exact.lateral_m) == truth


def test_the_cycle_surveys_the_machine_into_the_service(core: ServiceCore) -> None:
    """The ring cycle's surveyor (``wara cycle``, in one process): M's truth from the
    simulator against the axis at the service's chainage, given to the service as
    ``locate``; the reply kept with the truth. A rig that does not walk: nothing."""
    cfg = core.cfg
    m_truth = SimpleNamespace(
        plan_xy_m=np.array([[0.01, -0.004], [0.0, 0.0]]), heading_rad=np.array([0.002, 0.0])
    )
    truth: dict[str, Any] = {"walk": m_truth}
    sim = SimpleNamespace(truth=lambda: SimpleNamespace(**truth))
    h: Any = SimpleNamespace(core=core, sim=sim, mode="lockstep", period=cfg.control.period_s)
    cyc = _Cycle(cfg, h, Path("unused.sqlite"), np.random.default_rng(3), print, None)
    got = cyc._locate(2)
    start = on_axis_at_start(cfg)
    assert got is not None and core.on_axis is not None
    assert got["on_axis"] == core.on_axis.to_dict() and got["replaced"] == start.to_dict()
    want = simulated_machine_survey(
        cfg, machine_truth(cfg, start.chainage_m, (0.01, -0.004), 0.002), np.random.default_rng(3)
    )
    assert core.on_axis == want
    assert got["truth"] == OnAxis(start.chainage_m, 0.002, -0.004).to_dict()  # straight axis
    # a survey within 3 sigma of the estimate (0.76 mrad, 2.1 mm here) is not given
    m_truth.heading_rad[0], m_truth.plan_xy_m[0, 1] = want.heading_error_rad + 2e-4, -0.003
    kept = cyc._locate(2)
    assert kept is not None and "on_axis" not in kept and core.on_axis == want
    assert kept["kept"] == want.to_dict()
    sigma_h, sigma_l = machine_survey_sigma(cfg)
    assert abs(kept["surveyed"]["heading_error_deg"] - kept["kept"]["heading_error_deg"]) <= (
        math.degrees(LOCATE_GATE_SIGMA * sigma_h)
    )
    assert sigma_l == pytest.approx(cfg.cycle.survey_noise_m / math.sqrt(2.0))  # type: ignore[union-attr]
    truth["walk"] = None
    assert cyc._locate(2) is None and core.on_axis == want
