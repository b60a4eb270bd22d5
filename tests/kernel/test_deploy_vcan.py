"""``deploy/install.sh --vcan`` for real, in the kernel VM, then vcan0 from the files it
installed.

The VM has no systemd as PID 1, so the script runs up to its first ``systemctl`` (step
5, ``daemon-reload``) and stops there; everything before it is done for real: the
``wara`` user, the venv under /opt/wara, /etc/wara/project.yaml (validated), the
networkd files, the modules-load file and the unit. Then what systemd would do at boot
is done by hand with the same programs: ``systemd-modules-load`` loads vcan from
/etc/modules-load.d/wara-vcan.conf and ``systemd-networkd`` (started directly) creates
vcan0 from the installed .netdev and brings it up from the .network.

Only in the VM (it changes users, /etc and /opt); the VM's root is a throw-away overlay.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from plc_bridge.bus import socketcan_available
from tests.kernel import vm_only_reason

REPO = Path(__file__).resolve().parents[2]
DEPLOY = REPO / "deploy"
NET = Path("/etc/systemd/network")
PROJECT = REPO / "config" / "projects" / "shanghai_airport_link.yaml"

_REASON = vm_only_reason()
pytestmark = pytest.mark.skipif(_REASON is not None, reason=str(_REASON))


def _sh(
    *argv: str, check: bool = False, timeout: float = 120.0, cwd: str | None = None
) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        argv, capture_output=True, text=True, timeout=timeout, check=check, cwd=cwd
    )


def _unmask_passwd_files() -> None:
    """virtme-ng hides /etc/shadow and /etc/gshadow behind bind mounts; useradd replaces
    them by rename, which a mount point refuses. Unmount the masks (the guest's /etc is
    a throw-away overlay, nothing reaches the host)."""
    for f in ("/etc/shadow", "/etc/gshadow"):
        if _sh("mountpoint", "-q", f).returncode == 0:
            _sh("umount", f, check=True)


def _link(name: str) -> dict[str, Any] | None:
    p = _sh("ip", "-json", "-details", "link", "show", "dev", name)
    if p.returncode != 0:
        return None
    links: list[dict[str, Any]] = json.loads(p.stdout)
    return links[0] if links else None


def _ensure_vcan0() -> None:
    """Leave vcan0 up for the other kernel tests, whatever happened here."""
    if _link("vcan0") is None:
        _sh("modprobe", "vcan")
        _sh("ip", "link", "add", "dev", "vcan0", "type", "vcan")
    _sh("ip", "link", "set", "vcan0", "up")


def _run_timed(argv: list[str], env: dict[str, str], timeout_s: float, steps: Path) -> Any:
    """Run ``argv``; each stdout line (install.sh's ``+ command`` and ``# step``) goes to
    ``steps`` with the seconds since the start, so a slow step shows in the test's files."""
    t0 = time.monotonic()
    with tempfile.TemporaryFile("w+") as err, steps.open("w") as log:
        proc = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=err, text=True, env=env, bufsize=1
        )
        assert proc.stdout is not None
        out: list[str] = []
        for line in proc.stdout:
            out.append(line)
            log.write(f"{time.monotonic() - t0:8.1f} s  {line}")
            log.flush()
            if time.monotonic() - t0 > timeout_s:
                proc.kill()
                break
        rc = proc.wait()
        log.write(f"{time.monotonic() - t0:8.1f} s  exit {rc}\n")
        err.seek(0)
        return subprocess.CompletedProcess(argv, rc, "".join(out), err.read())


@pytest.fixture(scope="module")
def installed(
    tmp_path_factory: pytest.TempPathFactory,
) -> Iterator[subprocess.CompletedProcess[str]]:
    _unmask_passwd_files()
    env = {**os.environ, **offline_pip_env()}
    steps = tmp_path_factory.mktemp("deploy") / "install-steps.txt"
    argv = [str(DEPLOY / "install.sh"), "--vcan", "--no-start",
            "--wheelhouse", os.environ.get("WARA_VM_WHEELHOUSE", "")]  # fmt: skip
    proc = _run_timed(argv, env, 2400.0, steps)
    try:
        yield proc
    finally:
        _ensure_vcan0()


#: Not lent from the project venv: what install.sh's own steps bring (pip, by ``python3 -m
#: venv``) and the project itself (from its wheel), and setuptools, which it does not need.
NOT_LENT = ("pip", "setuptools", "wheel", "_distutils_hack", "distutils-precedence",
            "wara_control", "__editable__")  # fmt: skip


def offline_pip_env(prefix: Path = Path("/opt/wara")) -> dict[str, str]:
    """Make install.sh's ``pip install`` work without network, and quickly on an emulated
    CPU, as on an IPC image with the dependencies preinstalled: ``PREFIX/deps`` holds a
    link to every distribution of the project venv (numpy, scipy, ...) but pip, setuptools
    and the project, and the prefix's venv is made beforehand (without pip, as ``python3
    -m venv`` would) with a ``.pth`` that puts ``PREFIX/deps`` on its path. pip then finds
    every dependency installed and installs only the package, offline from the wheel
    run_in_vm.py built on the host (``install.sh --wheelhouse $WARA_VM_WHEELHOUSE``)."""
    deps = prefix / "deps"
    deps.mkdir(parents=True, exist_ok=True)
    for entry in Path(sysconfig.get_paths()["purelib"]).iterdir():
        if not entry.name.lower().startswith(NOT_LENT) and not (deps / entry.name).exists():
            (deps / entry.name).symlink_to(entry)
    venv = prefix / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True)
    ver = f"python{sys.version_info.major}.{sys.version_info.minor}"
    (venv / "lib" / ver / "site-packages" / "wara_vm_deps.pth").write_text(f"{deps}\n")
    return {"PIP_NO_CACHE_DIR": "1"}  # the guest's home is on the read-only root


def test_install_runs_every_step_up_to_systemctl(
    installed: subprocess.CompletedProcess[str],
) -> None:
    out = installed.stdout
    steps = [ln for ln in out.splitlines() if ln.startswith("+ ")]
    # Without systemd as PID 1 the first systemctl fails, and set -e stops the script.
    assert installed.returncode != 0, out
    assert steps[-1] == "+ systemctl daemon-reload", (out, installed.stderr[-3000:])
    assert "# 5. service" in out
    for want in ("+ useradd", "+ python3 -m venv /opt/wara/venv",
                 "/opt/wara/venv/bin/pip install --quiet --upgrade --no-index --find-links",
                 "/opt/wara/venv/bin/wara config validate /etc/wara/project.yaml"):  # fmt: skip
        assert any(want in s for s in steps), (want, steps)


def test_user_venv_and_project_are_in_place(installed: subprocess.CompletedProcess[str]) -> None:
    pw = _sh("getent", "passwd", "wara", check=True).stdout.strip().split(":")
    assert pw[5:] == ["/var/lib/wara", "/usr/sbin/nologin"], pw
    assert _sh("getent", "group", "wara").returncode == 0
    assert Path("/etc/wara/project.yaml").read_bytes() == PROJECT.read_bytes()
    assert os.access("/opt/wara/venv/bin/wara", os.X_OK)
    # install.sh ran the installed `wara config validate` on it, and went on (set -e):
    out = installed.stdout
    assert "+ /opt/wara/venv/bin/wara config validate /etc/wara/project.yaml" in out
    assert out.index("# 4. CAN network") > out.index("wara config validate"), out
    # The installed package, not this checkout: its modules live under /opt/wara (found
    # without importing them: an import costs a minute on the emulated CPU).
    find = "import importlib.util as u; print(u.find_spec('plc_bridge').origin)"
    p = _sh("/opt/wara/venv/bin/python", "-c", find, timeout=600.0, cwd="/")  # not the checkout
    assert p.stdout.startswith("/opt/wara/venv/"), p


def test_unit_and_network_files_are_the_shipped_ones(
    installed: subprocess.CompletedProcess[str],
) -> None:
    unit = Path("/etc/systemd/system/wara-ipc.service")
    assert unit.read_bytes() == (DEPLOY / "wara-ipc.service").read_bytes()  # prefix /opt/wara
    analyze = shutil.which("systemd-analyze")
    if analyze is not None:  # the ExecStart binary exists now: the installed unit verifies
        p = _sh(analyze, "verify", str(unit))
        assert p.returncode == 0 and not (p.stdout + p.stderr).strip(), p
    can0 = (NET / "80-wara-can0.network").read_text()
    assert can0 == (DEPLOY / "network" / "80-wara-can0.network").read_text()  # 500 kbit/s
    assert "\nBitRate=500000\n" in can0
    for name in ("80-wara-vcan0.netdev", "80-wara-vcan0.network"):
        assert (NET / name).read_bytes() == (DEPLOY / "network" / name).read_bytes()
    assert Path("/etc/modules-load.d/wara-vcan.conf").read_text() == "vcan\n"


def _networkd() -> str:
    for p in ("/usr/lib/systemd/systemd-networkd", "/lib/systemd/systemd-networkd"):
        if os.access(p, os.X_OK):
            return p
    pytest.fail("systemd-networkd is not installed (Debian: systemd)")


def test_vcan0_comes_up_from_the_installed_files(
    installed: subprocess.CompletedProcess[str],
) -> None:
    # Start from nothing: no vcan0, no vcan module (if nothing else holds it).
    _sh("ip", "link", "del", "dev", "vcan0")
    _sh("modprobe", "-r", "vcan")
    if not Path("/sys/module/vcan").exists():
        load = _sh("/lib/systemd/systemd-modules-load")  # reads /etc/modules-load.d/
        assert load.returncode == 0, load
        assert Path("/sys/module/vcan").exists(), "modules-load.d did not load vcan"
    assert _link("vcan0") is None
    for d in ("/run/systemd/netif/links", "/run/systemd/netif/leases", "/run/systemd/netif/lldp"):
        Path(d).mkdir(parents=True, exist_ok=True)
    networkd = subprocess.Popen(
        [_networkd()],
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        env={**os.environ, "SYSTEMD_LOG_LEVEL": "debug", "SYSTEMD_LOG_TARGET": "console"},
    )
    try:
        end = time.monotonic() + 120.0
        link = None
        while time.monotonic() < end and networkd.poll() is None:
            link = _link("vcan0")
            if link is not None and "UP" in link.get("flags", []):
                break
            time.sleep(0.5)
    finally:
        networkd.terminate()
        try:
            out = networkd.communicate(timeout=30)[0]
        except subprocess.TimeoutExpired:
            networkd.kill()
            out = networkd.communicate()[0]
    assert link is not None, f"networkd did not create vcan0:\n{out[-4000:]}"
    assert link["linkinfo"]["info_kind"] == "vcan"  # Kind=vcan (.netdev)
    assert "UP" in link["flags"], (link, out[-4000:])  # brought up by the .network
    assert link["link_type"] == "can"
    # LinkLocalAddressing=no: networkd gave it no address.
    addr = json.loads(_sh("ip", "-json", "addr", "show", "dev", "vcan0").stdout)
    assert not addr[0].get("addr_info"), addr
    assert "80-wara-vcan0" in out, out[-4000:]  # networkd read the installed files
    # And a CAN socket works on it.
    assert socketcan_available("vcan0") is None
