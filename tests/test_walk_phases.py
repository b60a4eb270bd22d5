"""The walk's phases by kind (ipc_app/control/walk/phases.py, docs/walking.md): the
table the sequencer runs each phase of a plan by agrees with the plan, forward and
back: each phase's kind and frame are what its name says, its standing frame the one
the plan stands on, and in a preload or a transfer the plan's forces move from the
releasing frame to the receiving one."""

from __future__ import annotations

import numpy as np
import pytest

from config import ProjectConfig
from ipc_app.control.walk import PHASES, PhaseKind
from ipc_app.planner import walk as planner
from ipc_app.planner.walk import DIRECTIONS, plan_walk

#: the frame a phase's name ends with
FRAME_LETTER = {"S": "sub_leg", "M": "main_leg"}


def test_the_table_has_a_row_for_every_phase_the_planner_names() -> None:
    assert list(PHASES) == list(planner.PHASES)
    for kind in PhaseKind:
        assert any(role.kind is kind for role in PHASES.values()), kind
    for role in PHASES.values():
        assert sorted(role.frame + role.standing) == list(range(8))


@pytest.mark.parametrize("direction", DIRECTIONS)
def test_each_phase_runs_by_the_kind_and_frames_of_the_plan(
    project: ProjectConfig, direction: str
) -> None:
    plan = plan_walk(project, 2, direction=direction)
    ids = plan.leg_ids
    travel = tuple(c.id for c in project.cylinders_by_can_index if c.role == "travel")
    for ph in plan.phases:
        role = PHASES[ph.key]
        frame = tuple(ids[j] for j in role.frame)
        standing = tuple(ids[j] for j in role.standing)
        words = ph.name.replace(" back", "").split()
        verb = {"advance": "travel", "move": "travel"}.get(words[0], words[0])
        assert verb == role.kind.value, ph.key
        assert all(c.startswith(FRAME_LETTER[words[-1]]) for c in frame), ph.key
        if role.kind is PhaseKind.TRAVEL:
            assert ph.standing == standing and ph.moving == travel, ph.key
        elif role.kind in (PhaseKind.LOWER, PhaseKind.LIFT):
            assert ph.standing == standing and ph.moving == frame, ph.key
        else:  # both frames on the invert, the load going from one to the other
            assert set(ph.standing) == set(ids), ph.key
            first, last = ph.leg_forces_n[0], ph.leg_forces_n[-1]
            assert np.all(last[list(role.frame)] > first[list(role.frame)]), ph.key
            assert np.all(last[list(role.standing)] < first[list(role.standing)]), ph.key
