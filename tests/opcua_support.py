"""Shared pieces of the OPC UA tests: a stand-in service on a real control socket, the
server process with its users and certificates, client certificates, the Node client."""

from __future__ import annotations

import contextlib
import os
import shutil
import socket
import subprocess
import threading
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ipc_app.opcua.process import OpcUaProcess
from ipc_app.opcua.users import add_user
from ipc_app.service.ctl import CtlHandlers, CtlServer

NODE_DIR = Path(__file__).parent / "opcua_client"
CLIENT_URI = "urn:wara:test:node-client"
PASSWORDS = {"op": "operator-pass", "vi": "viewer-pass", "en": "engineer-pass"}
ROLES = {"op": "operator", "vi": "viewer", "en": "engineer"}


@dataclass
class FakeService:
    """The control channel's commands on a tiny PackML mode machine (IDLE, EXECUTE,
    HELD, STOPPED), recording every command and audit entry it receives."""

    mode: str = "IDLE"
    unit_mode: str = "PRODUCTION"
    target: list[float] | None = None
    calls: list[tuple[Any, ...]] = field(default_factory=list)
    audits: list[tuple[str, str, str]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def status(self) -> dict[str, Any]:
        with self.lock:
            return {
                "mode": self.mode,
                "unit_mode": self.unit_mode,
                "since_s": 1.0,
                "valves_enabled": self.mode == "EXECUTE",
                "faults": [],
                "target_deg": self.target,
                "motion": {"achieved_deg": [0.5, -0.25]},
                "positions_mm": {"main_leg_1": 400.0},
                "pressures_pa": {"main_leg_1": [5.0e6, 1.0e6]},
                "positions_valid": {"main_leg_1": True},
                "sync_error_mm": {"lower": 0.01, "upper": 0.02},
                "twist_mm": {"lower": 0.003, "upper": 0.004},
                "link": "OK",
                "loop": {"period_ms": 5.0, "compute_p99_ms": 0.8, "cycles": 10, "overruns": 0},
            }

    def _set(self, name: str, mode: str, allowed: tuple[str, ...]) -> dict[str, Any]:
        with self.lock:
            self.calls.append((name,))
            if self.mode not in allowed:
                return {"ok": False, "code": "refused", "error": f"{name} refused in {self.mode}"}
            self.mode = mode
            return {"mode": mode}

    def adjust(self, roll: float, pitch: float) -> dict[str, Any]:
        with self.lock:
            self.calls.append(("adjust", roll, pitch))
            if self.mode != "IDLE":
                return {"ok": False, "code": "refused", "error": f"adjust refused in {self.mode}"}
            self.mode, self.target = "EXECUTE", [roll, pitch]
            return {"mode": "EXECUTE"}

    def walk(
        self, steps: int, direction: str = "forward", unloaded: bool = False
    ) -> dict[str, Any]:
        with self.lock:
            self.calls.append(("walk", steps))
            if self.mode != "IDLE":
                return {"ok": False, "code": "refused", "error": f"walk refused in {self.mode}"}
            self.mode = "EXECUTE"
            return {"mode": "EXECUTE"}

    def set_unit_mode(self, unit_mode: str) -> dict[str, Any]:
        with self.lock:
            self.calls.append(("unit_mode", unit_mode))
            self.unit_mode = unit_mode
            return {"mode": self.mode, "unit_mode": unit_mode}

    def audit(self, user: str, action: str, result: str) -> dict[str, Any]:
        with self.lock:
            self.audits.append((user, action, result))
        return {}

    def handlers(self) -> CtlHandlers:
        return CtlHandlers(
            adjust=self.adjust,
            walk=self.walk,
            status=self.status,
            stop=lambda: self._set("stop", "IDLE", ("IDLE", "EXECUTE", "HELD", "COMPLETE")),
            reset=lambda: self._set("reset", "IDLE", ("STOPPED",)),
            hold=lambda: self._set("hold", "HELD", ("EXECUTE",)),
            unhold=lambda: self._set("unhold", "EXECUTE", ("HELD",)),
            clear=lambda: self._set("clear", "STOPPED", ("ABORTED",)),
            unit_mode=self.set_unit_mode,
            audit=self.audit,
        )


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def make_client_cert(path_dir: Path, name: str = "client") -> tuple[Path, Path]:
    from ipc_app.opcua import pki

    return pki.client_cert(path_dir, name, CLIENT_URI)


@dataclass
class Rig:
    service: FakeService
    ctl: CtlServer
    server: OpcUaProcess
    url: str
    port: int
    pki_dir: Path
    cert: Path  #: a trusted client certificate
    key: Path
    untrusted_cert: Path
    untrusted_key: Path
    config: Path


def write_config(tmp: Path, port: int, **opcua: Any) -> Path:
    import yaml

    from config.loader import default_project_path

    data = yaml.safe_load(default_project_path().read_text())
    data["opcua"] = {
        "enabled": True,
        "host": "127.0.0.1",
        "port": port,
        "users_file": str(tmp / "users.json"),
        "pki_dir": str(tmp / "pki"),
        **opcua,
    }
    path = tmp / "project.yaml"
    path.write_text(yaml.safe_dump(data))
    return path


@contextlib.contextmanager
def rig(tmp: Path, **opcua: Any) -> Iterator[Rig]:
    """A stand-in service on a control socket and the OPC UA server process on a free
    port, users op/vi/en, a trusted and an untrusted client certificate."""
    from ipc_app.opcua import pki

    for name, pw in PASSWORDS.items():
        add_user(tmp / "users.json", name, ROLES[name], pw)
    pki.create_server_cert(tmp / "pki")
    cert, key = make_client_cert(tmp / "client", "trusted")
    ucert, ukey = make_client_cert(tmp / "client", "untrusted")
    pki.trust(tmp / "pki", cert)
    port = free_port()
    cfg = write_config(tmp, port, **opcua)
    svc = FakeService()
    ctl = CtlServer(svc.handlers(), tmp / "ctl.sock")
    ctl.bind()
    ctl.start()
    log = (tmp / "opcua.log").open("w")
    proc = OpcUaProcess(cfg, tmp / "ctl.sock", stderr=log)
    try:
        url = proc.start(timeout_s=60)
        yield Rig(svc, ctl, proc, url, port, tmp / "pki", cert, key, ucert, ukey, cfg)
    finally:
        proc.stop()
        ctl.stop()
        log.close()


def node_available() -> str | None:
    """Why the Node client cannot run here, or None."""
    if shutil.which("node") is None:
        return "node is not installed"
    if not (NODE_DIR / "node_modules" / "node-opcua-client").is_dir():
        return f"node-opcua-client is not installed (npm ci in {NODE_DIR})"
    return None


def run_node(script: str, *args: str, timeout_s: float = 300.0) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["node", str(NODE_DIR / script), *args],
        capture_output=True,
        text=True,
        timeout=timeout_s,
        cwd=NODE_DIR,
        env={**os.environ, "NODE_OPTIONS": ""},
    )
