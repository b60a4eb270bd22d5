"""The part's release sequencer (ipc_app/control/release.py, docs/placement.md "The
release") on a model of what it meets: the upper rods follow their references, and the
platform's load pressures fall linearly from the loaded statics to the empty ones over
the first :data:`CLEAR_M` of lowering (the bolted part's pads; none when ``bolted`` is
False). Each ``cycle.release_*`` key and ``cycle.platform_pressure_tolerance_mpa``
changes the outcome."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest

from config import ProjectConfig, load_project, units
from ipc_app.control.attitude import AttitudeController
from ipc_app.control.release import (
    RELEASED_FOR_S,
    ReleaseSequencer,
    load_pressures_pa,
    platform_pressures_pa,
    upper_index,
)
from ipc_app.service.interlocks import Interlock, release_cause

PERIOD_S = 0.005
CLEAR_M = 1.8e-3


def _with(**keys: Any) -> ProjectConfig:
    cfg = load_project(None)
    assert cfg.cycle is not None
    return cfg.model_copy(update={"cycle": cfg.cycle.model_copy(update=keys)})


def _pressures(cfg: ProjectConfig, load_pa: np.ndarray) -> np.ndarray:
    """Chamber pressures (19, 2) whose upper load pressures are ``load_pa``."""
    p = np.zeros((len(cfg.cylinders), 2))
    for k, i in enumerate(upper_index(cfg)):
        p[i, 0] = load_pa[k]
    return p


def run(cfg: ProjectConfig, bolted: bool = True, limit_s: float = 60.0) -> ReleaseSequencer:
    """A release on the model until done or out of travel."""
    att = AttitudeController(cfg, PERIOD_S)
    x = np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])
    up = upper_index(cfg)
    att.engage(x, 0.0, None)
    assert cfg.cycle is not None
    speed = cfg.cycle.release_speed_m_s
    empty = platform_pressures_pa(cfg, x, unloaded=True, lowering_speed_m_s=speed)
    loaded = platform_pressures_pa(cfg, x, unloaded=False)
    rel = ReleaseSequencer(cfg, att, empty, platform_pressures_pa(cfg, x, unloaded=True))
    assert rel.check(x) == []
    x0 = float(np.mean(x[up]))
    rel.start(0.0, x, _pressures(cfg, loaded))
    t = 0.0
    while not (rel.done or rel.out_of_travel) and t < limit_s:
        t += PERIOD_S
        lowered = x0 - float(np.mean(x[up]))
        share = max(0.0, 1.0 - lowered / CLEAR_M) if bolted else 1.0
        p = _pressures(cfg, empty + share * (loaded - empty))
        rel.update(t, x, p, True)
        ref = att.last_references
        assert ref is not None
        x = x.copy()
        x[up] = ref[up]  # the rods follow
    return rel


def test_the_platform_lowers_off_the_part_then_clear_of_it() -> None:
    cfg = load_project(None)
    assert cfg.cycle is not None
    rel = run(cfg)
    fig = rel.figures
    assert rel.done and not rel.out_of_travel
    # off once the cylinder the part loads most is within the tolerance of its empty
    # pressure (the tolerance over what the part adds to it, short of the pads' whole
    # travel), held for RELEASED_FOR_S
    loaded = load_pressures_pa(cfg, _pressures(cfg, np.asarray(fig.start_pressure_pa)))
    added = float(np.max(loaded - np.asarray(fig.empty_pressure_pa)))
    off_at = CLEAR_M * (1.0 - cfg.cycle.platform_pressure_tolerance_pa / added)
    held_m = cfg.cycle.release_speed_m_s * RELEASED_FOR_S
    assert fig.released_at_m == pytest.approx(off_at + held_m, abs=0.02e-3)
    assert fig.travel_m == pytest.approx(fig.released_at_m + 5e-3, abs=0.02e-3)
    assert set(rel.phase_times_s) == {"lowering", "clearance"}
    assert rel.phase_times_s["clearance"] == pytest.approx(5.0 + 0.5, abs=0.02)  # + settle
    assert fig.excess_pa <= cfg.cycle.platform_pressure_tolerance_pa
    # the empty platform: 6 t less its four rods, a quarter on each cylinder, and its rod
    assert fig.to_dict()["empty_at_rest_mpa"] == pytest.approx([0.732] * 4, abs=0.001)


def test_a_part_not_fixed_stops_the_release_at_its_travel() -> None:
    cfg = load_project(None)
    rel = run(cfg, bolted=False)
    assert rel.out_of_travel and not rel.done
    assert rel.figures.travel_m == pytest.approx(10e-3, abs=0.01e-3)
    cause = release_cause(rel, [c.id for c in cfg.cylinders_by_can_index])
    assert cause.interlock is Interlock.RELEASE and cause.where.startswith("upper_")
    assert cause.value is not None and cause.value >= 10.0 and cause.limit == 10.0
    assert "the part's weight still on the platform" in cause.text()


@pytest.mark.parametrize(
    ("key", "value", "check"),
    [
        # twice the speed: the lowering phase in about half the time
        ("release_speed_mm_s", 2.0, lambda a, b: b.phase_times_s["lowering"]
         < 0.6 * a.phase_times_s["lowering"]),
        # a further 2 mm instead of 5
        ("release_clearance_mm", 2.0, lambda a, b: b.figures.travel_m
         == pytest.approx(a.figures.travel_m - 3e-3, abs=0.05e-3)),
        # a looser tolerance: off earlier
        ("platform_pressure_tolerance_mpa", 1.0, lambda a, b: b.figures.released_at_m
         < a.figures.released_at_m - 0.2e-3),
        # less travel allowed than the pads need: the interlock
        ("release_max_travel_mm", 1.0, lambda a, b: b.out_of_travel and not a.out_of_travel),
    ],
)  # fmt: skip
def test_each_release_key_governs_the_release(key: str, value: float, check: Any) -> None:
    shipped = run(load_project(None))
    changed = run(_with(**{key: value}))
    assert check(shipped, changed), (key, shipped.figures, changed.figures)


def test_a_release_needs_the_stroke_below_the_upper_rods() -> None:
    cfg = load_project(None)
    att = AttitudeController(cfg, PERIOD_S)
    x = np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index])
    x[upper_index(cfg)[2]] = units.mm(12.0)
    rel = ReleaseSequencer(cfg, att, np.zeros(4))
    (why,) = rel.check(x)
    assert why.startswith("stroke: upper_3 at 12.0 mm from its retracted end")
    assert "needs 20.0 mm" in why  # 10 travel + 5 clearance + the 5 mm end margin
