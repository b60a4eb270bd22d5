"""deploy/: the systemd unit verifies cleanly, networkd files have the right keys,
install.sh's dry run shows every step and changes nothing."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from config import ProjectConfig

REPO = Path(__file__).resolve().parents[1]
DEPLOY = REPO / "deploy"
UNIT = DEPLOY / "wara-ipc.service"
SYSTEMD_ANALYZE = shutil.which("systemd-analyze")


def parse_ini(path: Path) -> dict[str, list[tuple[str, str]]]:
    """systemd's INI dialect: repeated keys allowed, '#'/';' comments, no interpolation."""
    sections: dict[str, list[tuple[str, str]]] = {}
    current: list[tuple[str, str]] | None = None
    for n, raw in enumerate(path.read_text().splitlines(), start=1):
        line = raw.strip()
        if not line or line[0] in "#;":
            continue
        if line.startswith("[") and line.endswith("]"):
            current = sections.setdefault(line[1:-1], [])
            continue
        assert current is not None, f"{path.name}:{n}: key outside a section"
        assert "=" in line, f"{path.name}:{n}: expected KEY=VALUE, got {line!r}"
        key, value = line.split("=", 1)
        current.append((key.strip(), value.strip()))
    return sections


def keys(sections: dict[str, list[tuple[str, str]]], section: str) -> dict[str, str]:
    return dict(sections.get(section, []))


@pytest.mark.skipif(SYSTEMD_ANALYZE is None, reason="systemd-analyze is not installed")
def test_unit_verifies_without_a_word(tmp_path: Path) -> None:
    # `systemd-analyze verify` checks that ExecStart's binary exists and is executable;
    # /opt/wara/venv/bin/wara only exists on an installed IPC, so the copy under test runs
    # this interpreter instead. Everything else is the shipped file, byte for byte.
    text = UNIT.read_text()
    exec_line = next(ln for ln in text.splitlines() if ln.startswith("ExecStart="))
    assert exec_line == "ExecStart=/opt/wara/venv/bin/wara serve --config /etc/wara/project.yaml"
    copy = tmp_path / "wara-ipc.service"
    copy.write_text(
        text.replace(exec_line, f"ExecStart={sys.executable} -m wara serve --config x.yaml")
    )
    assert SYSTEMD_ANALYZE is not None
    proc = subprocess.run(
        [SYSTEMD_ANALYZE, "verify", str(copy)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout == "" and proc.stderr == ""


def test_unit_has_the_required_settings() -> None:
    s = parse_ini(UNIT)
    svc = keys(s, "Service")
    expected = {
        "Type": "notify",
        "NotifyAccess": "main",
        "Restart": "on-failure",
        "User": "wara",
        "NoNewPrivileges": "yes",
        "ProtectSystem": "strict",
        "ProtectHome": "yes",
        "PrivateTmp": "yes",
        "RuntimeDirectory": "wara",
        "StateDirectory": "wara",
        "LogsDirectory": "wara",
        "LimitMEMLOCK": "infinity",
    }
    assert {k: svc.get(k) for k in expected} == expected
    assert svc["WatchdogSec"].endswith("s") and int(svc["LimitRTPRIO"]) >= 1
    assert set(svc["CapabilityBoundingSet"].split()) == {"CAP_SYS_NICE", "CAP_IPC_LOCK"}
    assert set(svc["AmbientCapabilities"].split()) == {"CAP_SYS_NICE", "CAP_IPC_LOCK"}
    families = set(svc["RestrictAddressFamilies"].split())
    assert {"AF_CAN", "AF_UNIX", "AF_NETLINK", "AF_INET"} <= families
    assert "RestrictRealtime" not in svc  # would forbid SCHED_FIFO
    assert keys(s, "Install") == {"WantedBy": "multi-user.target"}


NETWORK_KEYS = {
    "Match": {"Name"},
    "Link": {"RequiredForOnline"},
    "Network": {"LinkLocalAddressing"},
    "CAN": {"BitRate", "RestartSec"},
    "NetDev": {"Name", "Kind", "Description"},
}


@pytest.mark.parametrize(
    "name", ["80-wara-can0.network", "80-wara-vcan0.netdev", "80-wara-vcan0.network"]
)
def test_networkd_files_parse_with_known_keys(name: str) -> None:
    # systemd-analyze cannot verify networkd files; check sections and keys against
    # systemd.network(5) / systemd.netdev(5).
    s = parse_ini(DEPLOY / "network" / name)
    assert s, f"{name} is empty"
    for section, items in s.items():
        assert section in NETWORK_KEYS, f"{name}: unexpected section [{section}]"
        unknown = {k for k, _ in items} - NETWORK_KEYS[section]
        assert not unknown, f"{name}: [{section}] unknown keys {unknown}"
    iface = "vcan0" if "vcan0" in name else "can0"
    if name.endswith(".netdev"):
        assert keys(s, "NetDev") | {"Description": ""} == {
            "Name": iface,
            "Kind": "vcan",
            "Description": "",
        }
    else:
        assert keys(s, "Match") == {"Name": iface}


def test_can0_bitrate_matches_the_project(project: ProjectConfig) -> None:
    can = keys(parse_ini(DEPLOY / "network" / "80-wara-can0.network"), "CAN")
    assert int(can["BitRate"]) == project.can.bitrate
    assert can["RestartSec"].endswith("ms")


def _install(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        ["bash", str(DEPLOY / "install.sh"), "--dry-run", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


def test_install_dry_run_shows_steps_and_changes_nothing(tmp_path: Path) -> None:
    prefix = tmp_path / "opt-wara"
    proc = _install("--vcan", "--prefix", str(prefix))
    assert proc.returncode == 0, proc.stderr
    out = proc.stdout
    for step in (
        f"+ python3 -m venv {prefix}/venv",
        f"{prefix}/venv/bin/wara config validate /etc/wara/project.yaml",
        "BitRate=500000",
        "80-wara-vcan0.netdev",
        "/etc/systemd/system/wara-ipc.service",
        "+ systemctl enable --now wara-ipc.service",
    ):
        assert step in out, f"missing step {step!r} in:\n{out}"
    assert not prefix.exists()


def _pip_line(out: str) -> str:
    return next(line for line in out.splitlines() if "/venv/bin/pip install" in line)


def test_install_takes_no_extras_unless_asked(tmp_path: Path) -> None:
    """The IPC gets the service alone (no numba, no matplotlib); --extras adds them."""
    plain = _install("--prefix", str(tmp_path))
    assert plain.returncode == 0, plain.stderr
    assert _pip_line(plain.stdout).endswith(str(DEPLOY.parent))
    asked = _install("--prefix", str(tmp_path), "--extras", "plot")
    assert asked.returncode == 0, asked.stderr
    assert _pip_line(asked.stdout).endswith(f"{DEPLOY.parent}[plot]")
    both = _install("--prefix", str(tmp_path), "--extras", "sim,plot")
    assert _pip_line(both.stdout).endswith(f"{DEPLOY.parent}[sim,plot]")


@pytest.mark.parametrize(
    ("extras", "message"),
    [("gui", "unknown extra 'gui' (known: sim, plot, opcua)"), ("sim,", "an empty name")],
)
def test_install_rejects_unknown_extras(extras: str, message: str) -> None:
    proc = _install("--extras", extras)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr


def test_install_with_opcua_creates_the_server_certificate(tmp_path: Path) -> None:
    plain = _install("--prefix", str(tmp_path))
    assert "wara opcua cert" not in plain.stdout
    asked = _install("--prefix", str(tmp_path), "--extras", "opcua")
    assert asked.returncode == 0, asked.stderr
    assert _pip_line(asked.stdout).endswith(f"{DEPLOY.parent}[opcua]")
    assert f"{tmp_path}/venv/bin/wara opcua cert --pki-dir /var/lib/wara/opcua/pki" in asked.stdout


def test_install_rejects_unknown_options() -> None:
    proc = _install("--frobnicate")
    assert proc.returncode == 2 and "unknown option --frobnicate" in proc.stderr


def test_install_from_a_wheelhouse_takes_nothing_from_an_index(tmp_path: Path) -> None:
    """--wheelhouse DIR: offline, the package by name from DIR's wheels, not the source."""
    (tmp_path / "wara_control-0.1.0-py3-none-any.whl").write_bytes(b"")
    proc = _install("--prefix", str(tmp_path / "p"), "--wheelhouse", str(tmp_path),
                    "--extras", "plot")  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert _pip_line(proc.stdout).endswith(
        f"install --quiet --upgrade --no-index --find-links {tmp_path} wara-control[plot]"
    )
    empty = tmp_path / "empty"
    empty.mkdir()
    proc = _install("--wheelhouse", str(empty))
    assert proc.returncode == 2 and "no wara_control-*.whl there" in proc.stderr, proc.stderr
