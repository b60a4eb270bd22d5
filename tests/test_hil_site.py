"""``wara hil``'s rig choice and the site's acts over its socket (``--site-socket``):
the crane and the crew of the two-process ring cycle (docs/hil.md, "The part")."""

from __future__ import annotations

import json
import socket
import threading
import uuid
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
import yaml

from config import ProjectConfig, load_project
from config.hil_scenario import HilScenario, load_hil_scenario
from hil_sim.placement import pose_from_home
from hil_sim.simulator import HilSimulator
from hil_sim.site import MAX_LINE, SiteServer
from wara.commands.hil import rig_scenario
from wara.walk import walk_scenario

REPO = Path(__file__).resolve().parents[1]


def test_the_rig_is_the_walking_one_for_a_project_that_walks(
    project: ProjectConfig, tmp_path: Path
) -> None:
    assert rig_scenario(project, HilScenario(), None).plant.contact is True
    assert rig_scenario(project, HilScenario(), "attitude").plant.contact is False
    # a scenario that says which rig keeps it, unless --rig says otherwise
    path = tmp_path / "rigid.yaml"
    path.write_text(yaml.safe_dump({"name": "rigid", "plant": {"contact": False}}))
    rigid = load_hil_scenario(path)
    assert rig_scenario(project, rigid, None).plant.contact is False
    assert rig_scenario(project, rigid, "walking").plant.contact is True
    # a scenario that sets other plant keys only does not choose the rig
    path.write_text(yaml.safe_dump({"name": "coarse", "plant": {"step_ms": 0.5}}))
    coarse = rig_scenario(project, load_hil_scenario(path), None)
    assert coarse.plant.contact is True and coarse.plant.step_ms == 0.5
    # a project that cannot walk gets the attitude rig
    still = project.model_copy(update={"walking": None})
    assert rig_scenario(still, HilScenario(), None).plant.contact is False


def test_wara_hil_refuses_the_walking_rig_for_a_project_without_walking(tmp_path: Path) -> None:
    from wara.cli import main

    data = yaml.safe_load((REPO / "config/projects/shanghai_airport_link.yaml").read_text())
    data.pop("walking")
    data.pop("frames")
    data["cycle"]["walk_steps"] = 0
    path = tmp_path / "still.yaml"
    path.write_text(yaml.safe_dump(data))
    load_project(path)  # a valid project that does not walk
    args = ["hil", "--config", str(path), "--lockstep", "--duration", "0.01", "--quiet"]
    assert main([*args, "--rig", "walking"]) == 2
    assert main(args) == 0  # its default: the attitude rig


class _Client:
    def __init__(self, path: Path) -> None:
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        self.sock.connect(str(path))
        self.file = self.sock.makefile("rb")

    def ask(self, line: bytes) -> dict[str, Any]:
        self.sock.sendall(line + b"\n")
        out: dict[str, Any] = json.loads(self.file.readline())
        return out

    def act(self, name: str, **args: Any) -> dict[str, Any]:
        return self.ask(json.dumps({"act": name, **args}).encode())

    def close(self) -> None:
        self.file.close()
        self.sock.close()


def test_the_site_acts_are_done_between_scans(project: ProjectConfig, tmp_path: Path) -> None:
    channel = f"site-{uuid.uuid4().hex}"
    sim = HilSimulator(project, can.Bus(interface="virtual", channel=channel), walk_scenario())
    site = SiteServer(sim, tmp_path / "site.sock")
    site.start()
    answers: dict[str, dict[str, Any]] = {}
    done = threading.Event()

    def client() -> None:
        c = _Client(tmp_path / "site.sock")
        try:
            answers["part"] = c.act("part")
            answers["load_carried"] = c.act("load")
            answers["bolt"] = c.act("bolt")
            answers["bolt_again"] = c.act("bolt")
            answers["part_bolted"] = c.act("part")
            answers["bad_duration"] = c.act("load", duration_s=-1)
            answers["load"] = c.act("load", duration_s=2)
            answers["unknown"] = c.act("lift")
            answers["not_json"] = c.ask(b"{bolt")
            answers["long"] = c.ask(b"x" * (2 * MAX_LINE))
        finally:
            c.close()
            done.set()

    t = threading.Thread(target=client)
    t.start()
    frozen = None
    try:
        while not done.is_set():  # the simulator's thread: scans, acts between them
            sim.step(sim.cycle_s)
            site.between_scans()
            if frozen is None and sim.rig.part_state == "bolted":
                frozen = pose_from_home(project, sim.rig)
    finally:
        t.join(10)
        site.close()
        sim.close()
    a = answers
    assert a["part"]["ok"] and a["part"]["state"] == "carried"
    assert a["part"]["load_n"] == pytest.approx(project.workpiece_mass_kg * 9.81, rel=0.01)
    assert not a["load_carried"]["ok"] and "carries a part" in a["load_carried"]["error"]
    assert a["bolt"]["ok"] and a["bolt"]["state"] == "bolted"
    assert not a["bolt_again"]["ok"] and "bolted, not carried" in a["bolt_again"]["error"]
    # the bolted pose is frozen: the same later, and what the simulator's truth says
    assert a["part_bolted"]["r"] == a["bolt"]["r"] and a["part_bolted"]["t"] == a["bolt"]["t"]
    assert frozen is not None
    assert np.allclose(a["bolt"]["r"], frozen[0], atol=0) and a["bolt"]["t"] == frozen[1].tolist()
    assert a["part_bolted"]["t_s"] >= a["bolt"]["t_s"]
    assert not a["bad_duration"]["ok"] and "duration_s" in a["bad_duration"]["error"]
    assert a["load"]["ok"] and a["load"]["state"] == "loading"
    assert not a["unknown"]["ok"] and "unknown act 'lift'" in a["unknown"]["error"]
    assert not a["not_json"]["ok"] and "not JSON" in a["not_json"]["error"]
    assert not a["long"]["ok"] and "longer than" in a["long"]["error"]
    assert np.asarray(a["bolt"]["r"]).shape == (3, 3) and len(a["bolt"]["t"]) == 3
    assert not (tmp_path / "site.sock").exists()  # removed on close
