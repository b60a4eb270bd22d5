"""Cross-process tests on ``udp_multicast`` and ``wara_udp``, only inside a private
network namespace.

The namespace is made with ``unshare --user --map-root-user --net`` and gets its own
loopback with multicast routed to it; the root namespace's network is never touched.
Where the namespace cannot be made (no user namespaces, no ``unshare``/``ip``), the
test is skipped with the reason.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from plc_bridge.bus import DATAGRAM_RCVBUF_BYTES
from tests.cli_helpers import run_tree
from wara.demo_two_process import NETNS_SETUP, UNSHARE, netns_problem

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[1]


def _in_private_netns(command: str, timeout: float) -> subprocess.CompletedProcess[str]:
    argv = [*UNSHARE, "sh", "-c", f"{NETNS_SETUP} && {command}"]
    return run_tree(argv, timeout)


@pytest.fixture(scope="module")
def netns() -> None:
    problem = netns_problem()
    if problem is not None:
        pytest.skip(f"udp_multicast cross-process test needs a private netns: {problem}")


@pytest.mark.realtime
@pytest.mark.parametrize("interface", ["udp_multicast", "wara_udp"])
def test_ipc_and_plc_processes_talk_across_processes(netns: None, interface: str) -> None:
    proc = _in_private_netns(
        f"exec {sys.executable} -m tests.udp_multicast_peer ipc 1.5 {interface}", timeout=120
    )
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["ever_ok"] and result["state"] in ("OK", "DEGRADED"), result
    assert result["positions_valid"] and result["max_position_error_m"] <= 0.5e-6
    assert result["echoed_command_position_m"] == pytest.approx(0.1 + 0.01 * 0.5, abs=1e-5)
    assert result["status_mode"] == "ATTITUDE_ADJUST"
    assert result["unknown_id"] == 0 and result["crc_error"] == 0
    if interface == "udp_multicast":
        # The multicast socket echoes our own frames: the link drops and counts them.
        assert result["own_echo"] > 0 and result["bus"] == "UdpMulticastBus"
    else:
        # wara_udp skips them by sender id before the link sees them.
        assert result["bus"] == "WaraUdpBus"
        assert result["own_echo"] == 0 and result["bus_own_skipped"] > 0
    # A receive buffer for seconds of traffic, not the default's 0.1 s (bus.py).
    rmem_max = int(Path("/proc/sys/net/core/rmem_max").read_text())
    assert result["rcvbuf_bytes"] >= min(DATAGRAM_RCVBUF_BYTES, rmem_max), result
