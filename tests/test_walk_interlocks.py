"""The walk's interlocks as data and their pure checks (walking.md section 5)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from config import load_project
from config.schema import Walking
from ipc_app.control.walk import WalkFigures
from ipc_app.control.walk.forces import RodFriction
from ipc_app.service.ctl import parse
from ipc_app.service.interlocks import SPECS, Applies, Interlock
from ipc_app.service.walk_interlocks import (
    PHASES_OF,
    WalkLimits,
    walk_causes,
    walk_resume_cause,
)

LEGS = tuple(f"main_leg_{k}" for k in range(1, 5)) + tuple(f"sub_leg_{k}" for k in range(1, 5))
WALK = (
    Interlock.SYNC_BAND,
    Interlock.OVERLOAD,
    Interlock.TOUCHDOWN,
    Interlock.TRANSFER,
    Interlock.STABILITY,
    Interlock.SLIP,
    Interlock.WALK_RESUME,
)


@pytest.fixture(scope="module")
def lim() -> WalkLimits:
    return WalkLimits.from_config(load_project(None))


def fig(**kw: object) -> WalkFigures:
    base: dict[str, object] = {
        "step": 1,
        "phase": "1",
        "leg_force_n": (100e3,) * 8,
        "expected_n": (100e3,) * 8,
        "margin_m": 1.0,
        "margin_ahead_m": 1.0,
        "travel_force_n": 1e3,
        "friction_capacity_n": 280e3,
    }
    base.update(kw)
    return WalkFigures(**base)  # type: ignore[arg-type]


def test_each_walk_interlock_is_data_with_a_walking_key() -> None:
    for il in WALK:
        spec = SPECS[il]
        assert spec.applies is Applies.WALK and spec.key is not None
        section, name = spec.key.split(".")
        assert section == "walking" and name in Walking.model_fields
    assert set(PHASES_OF) == set(WALK) - {Interlock.WALK_RESUME}


def test_a_nominal_cycle_trips_nothing(lim: WalkLimits) -> None:
    for phase in ("1", "2", "3", "4", "5", "6", "7a", "7b", "7c", "8"):
        assert walk_causes(fig(phase=phase), LEGS, lim) == []


def test_sync_band_latches_only_after_its_timeout(lim: WalkLimits) -> None:
    inside = fig(phase="2", out_of_band="legs", out_of_band_s=lim.sync_band_timeout_s - 0.01)
    assert walk_causes(inside, LEGS, lim) == []
    (c,) = walk_causes(
        fig(phase="2", out_of_band="legs", out_of_band_s=lim.sync_band_timeout_s + 0.01), LEGS, lim
    )
    assert c.interlock is Interlock.SYNC_BAND and c.where == "legs"
    # not a phase it watches: a preload holds no position group
    late = fig(phase="3", out_of_band="legs", out_of_band_s=99.0)
    assert walk_causes(late, LEGS, lim) == []


def test_overload_names_the_leg_and_its_percentage(lim: WalkLimits) -> None:
    forces = [100e3] * 8
    forces[5] = 111e3
    (c,) = walk_causes(fig(leg_force_n=tuple(forces)), LEGS, lim)
    assert c.interlock is Interlock.OVERLOAD and c.where == "sub_leg_2"
    assert c.value == pytest.approx(111.0) and c.limit == 110.0
    forces[5] = 109e3
    assert walk_causes(fig(leg_force_n=tuple(forces)), LEGS, lim) == []


def test_a_leg_is_overloaded_only_beyond_what_its_seal_may_hold_unseen(lim: WalkLimits) -> None:
    """A rod at rest holds any force within its seal's Coulomb friction: a leg's
    pressures then read its load give or take that much. The overload judges the force
    less the friction its motion does not tell (docs/walking.md)."""
    forces = [100e3] * 8
    forces[7] = 111.5e3  # 111.5 % on the pressures
    at_rest = (2e3,) * 8  # the whole Coulomb friction unseen
    assert walk_causes(fig(leg_force_n=tuple(forces), friction_unknown_n=at_rest), LEGS, lim) == []
    forces[7] = 112.5e3  # 110.5 % even with the seal holding 2 kN of it
    (c,) = walk_causes(fig(leg_force_n=tuple(forces), friction_unknown_n=at_rest), LEGS, lim)
    assert c.where == "sub_leg_4" and c.value == pytest.approx(110.5)
    assert "112.5 kN, less 2.0 kN its seal may hold, of an expected 100.0 kN" in c.text()
    # the same leg moving: its friction is known from its motion, nothing unseen
    (c,) = walk_causes(fig(leg_force_n=tuple(forces), friction_unknown_n=(0.0,) * 8), LEGS, lim)
    assert c.value == pytest.approx(112.5)


def test_the_friction_a_legs_motion_does_not_tell() -> None:
    """At rest a rod's whole Coulomb friction is unknown (its sign and size: the seal
    holds what it holds), at :attr:`RodFriction.COULOMB_SPEED_M_S` or faster none, in
    between in proportion."""
    coulomb = np.full(8, 2000.0)
    rf = RodFriction(coulomb, np.zeros(8), 0.005)
    x = np.zeros(8)
    rf.restart(0.0, x)
    rf.friction_n()
    assert rf.unknown_n == pytest.approx((2000.0,) * 8)
    speeds = np.array([0.0, 0.25, 0.5, 1.0, -0.25, -1.0, 0.0, 2.0]) * RodFriction.COULOMB_SPEED_M_S
    for k in range(1, 12):  # the window filled at these speeds
        rf.record(k * 0.005, speeds * k * 0.005)
    rf.friction_n()
    assert rf.unknown_n == pytest.approx((2000.0, 1500.0, 1000.0, 0.0, 1500.0, 0.0, 2000.0, 0.0))


def test_touchdown_transfer_stability_and_slip(lim: WalkLimits) -> None:
    (c,) = walk_causes(fig(phase="2", no_touchdown="sub_leg_3"), LEGS, lim)
    assert c.interlock is Interlock.TOUCHDOWN and c.where == "sub_leg_3"
    assert walk_causes(fig(phase="1", no_touchdown="sub_leg_3"), LEGS, lim) == []
    # a foot on the invert above the window: an obstacle, its height above the ground
    (c,) = walk_causes(fig(phase="7a", obstacle=("main_leg_2", 0.0112)), LEGS, lim)
    assert c.interlock is Interlock.TOUCHDOWN and c.where == "main_leg_2"
    assert c.value == pytest.approx(11.2) and c.limit == lim.touchdown_travel_mm
    assert "obstacle" in c.text() and "11.2 mm above the expected ground" in c.text()
    assert walk_causes(fig(phase="3", obstacle=("main_leg_2", 0.0112)), LEGS, lim) == []
    (c,) = walk_causes(fig(phase="4", overdue_s=0.1, share_off=("sub_leg_1", 0.7)), LEGS, lim)
    assert c.interlock is Interlock.TRANSFER and c.where == "sub_leg_1"
    (c,) = walk_causes(fig(margin_ahead_m=0.2), LEGS, lim)
    assert c.interlock is Interlock.STABILITY and c.where == "ahead" and c.value == 0.2
    (c,) = walk_causes(fig(margin_m=-math.inf), LEGS, lim)
    assert c.interlock is Interlock.STABILITY and c.where == "now"
    (c,) = walk_causes(fig(travel_force_n=-300e3), LEGS, lim)
    assert c.interlock is Interlock.SLIP and c.value == pytest.approx(300.0)


def test_resume_check_heights_and_forces(lim: WalkLimits) -> None:
    ids = tuple(f"c{i}" for i in range(19))
    x = [0.4] * 19
    f = [100e3] * 8
    share = [90e3] * 8
    assert walk_resume_cause(x, x, range(14), (), ids, f, f, share, LEGS, lim) is None
    moved = list(x)
    moved[3] += lim.resume_height_m * 1.5
    c = walk_resume_cause(moved, x, range(14), (), ids, f, f, share, LEGS, lim)
    assert c is not None and c.interlock is Interlock.WALK_RESUME and c.where == "c3"
    f2 = list(f)
    f2[6] += 0.2 * 90e3
    c = walk_resume_cause(x, x, range(14), (), ids, f2, f, share, LEGS, lim)
    assert c is not None and c.where == "sub_leg_3"


def test_resume_check_allows_the_travel_pair_its_coasting(lim: WalkLimits) -> None:
    """The shipped allowance: 50 mm/s for the 100 ms command timeout plus 1 mm."""
    assert lim.resume_travel_m == pytest.approx(0.006)
    ids = tuple(f"c{i}" for i in range(19))
    x = [0.4] * 19
    f = [100e3] * 8
    share = [90e3] * 8
    coasted = list(x)
    coasted[14] += 0.9 * lim.resume_travel_m  # a travel rod ran on into the stop
    assert walk_resume_cause(coasted, x, range(14), (14, 15), ids, f, f, share, LEGS, lim) is None
    # the same distance on a leg is refused: heights keep their tolerance
    assert walk_resume_cause(coasted, x, range(15), (), ids, f, f, share, LEGS, lim) is not None
    coasted[15] = x[15] - 1.1 * lim.resume_travel_m
    c = walk_resume_cause(coasted, x, range(14), (14, 15), ids, f, f, share, LEGS, lim)
    assert c is not None and c.where == "c15" and c.limit == pytest.approx(6.0)


def test_ctl_walk_request_is_checked() -> None:
    req = parse(b'{"cmd": "walk", "steps": 3}')
    assert getattr(req, "args", None) == (3, "forward", False)
    req = parse(b'{"cmd": "walk", "steps": 2, "direction": "back", "unloaded": true}')
    assert getattr(req, "args", None) == (2, "back", True)
    for bad in (
        b'{"cmd": "walk"}',
        b'{"cmd": "walk", "steps": 0}',
        b'{"cmd": "walk", "steps": true}',
        b'{"cmd": "walk", "steps": 1, "unloaded": "yes"}',
        b'{"cmd": "walk", "steps": 1, "direction": 3}',
    ):
        out = parse(bad)
        assert isinstance(out, dict) and out["code"] == "bad_request"


def test_a_walk_in_no_known_direction_is_refused_by_the_service() -> None:
    """The control channel passes the direction on; the service refuses one the walk
    planner does not know, before planning, with the known ones named."""
    import can

    from ipc_app.service.core import ServiceCore
    from plc_bridge.link import IpcLink

    cfg = load_project(None)

    class NoPlanner:
        def submit(self, *a: Any, **k: Any) -> bool:
            return False

        def poll(self) -> None:
            return None

    bus = can.Bus(interface="virtual", channel="walk-direction-test")
    core = ServiceCore(cfg, IpcLink(cfg, bus, clock=lambda: 0.0), NoPlanner())
    out = core.request_walk(1, direction="sideways")
    bus.shutdown()
    assert out == {
        "ok": False,
        "code": "bad_request",
        "error": "direction must be one of forward, back, got 'sideways'",
    }


def test_every_walk_phase_keeps_the_bus_within_its_budget() -> None:
    from ipc_app.control.walk import walk_active_group
    from ipc_app.planner.walk import PHASES
    from plc_bridge import bus_load

    cfg = load_project(None)
    groups = {key: tuple(walk_active_group(cfg, key)) for key in PHASES}
    assert groups["1"] != groups["2"] != groups["6"]  # the group changes with the phase
    for key, group in groups.items():
        load = bus_load(cfg, group)
        assert load.ok and load.load_percent <= 50.0, (key, load.load_percent)
