"""Both sides of the link as separate processes on ``udp_multicast`` or ``wara_udp`` (run
by ``tests/test_plc_udp_multicast.py`` inside a private network namespace only).

``python -m tests.udp_multicast_peer ipc SECONDS [INTERFACE]`` starts the PLC side as a
child process (same interface),
runs the IPC side for a while and prints one JSON line with what it saw. The PLC
child reports the valve command it received for cylinder 0 back as the rod position
of cylinder 18, so one run checks both directions.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time

import can
import numpy as np

from config import ProjectConfig, load_project
from plc_bridge import IpcLink, LinkState, Mode, PlcLink, PlcStatus

GROUP = "239.74.163.2"
X = np.linspace(0.01, 0.19, 19)


def config(interface: str) -> ProjectConfig:
    data = load_project().model_dump()
    data["can"].update(interface=interface, channel=GROUP, udp_port=43117)
    return ProjectConfig.model_validate(data)


#: how long a peer waits for the other one to come up (a loaded machine starts an
#: interpreter with NumPy in seconds)
START_S = 30.0


def run_plc(seconds: float, interface: str) -> None:
    """Answer the IPC until it has gone quiet after talking (or ``seconds`` if it never
    talks): its valve command 0 echoed in position 18."""
    plc = PlcLink.from_config(config(interface))
    plc.set_status(PlcStatus(mode=Mode.ATTITUDE_ADJUST, pump_running=True, supply_pressure_pa=16e6))
    x = X.copy()
    heard = False
    t_end = time.monotonic() + seconds
    while time.monotonic() < t_end:
        plc.poll()
        u0 = plc.valve_commands().value[0]
        x[18] = X[18] if np.isnan(u0) else 0.1 + 0.01 * u0
        plc.set_positions_m(x)
        if not np.isnan(u0):
            heard = True
        elif heard and plc.ipc_timeout():
            break  # the IPC has finished
        time.sleep(0.001)
    plc.close()


def rcvbuf_bytes(bus: can.BusABC) -> int:
    with socket.socket(fileno=os.dup(bus.fileno())) as sock:
        return int(sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF))


def run_ipc(seconds: float, interface: str) -> int:
    child = subprocess.Popen(
        [sys.executable, "-m", "tests.udp_multicast_peer", "plc", str(seconds + START_S), interface]
    )
    try:
        ipc = IpcLink.from_config(config(interface))
        ipc.set_control(mode=Mode.ATTITUDE_ADJUST, enable=True)
        u = np.zeros(19)
        u[0] = 0.5
        ok_since = None
        # ``seconds`` of exchange once the PLC is up (the link OK), at most START_S waiting
        t_end = time.monotonic() + START_S
        while time.monotonic() < t_end:
            ipc.poll()
            ipc.send_valve_commands(u)
            if ipc.state() is LinkState.OK and ok_since is None:
                ok_since = time.monotonic()
                t_end = ok_since + seconds
            time.sleep(0.005)
        x = ipc.positions_m()
        st = ipc.status()
        h = ipc.health()
        print(
            json.dumps(
                {
                    "state": ipc.state().value,
                    "ever_ok": ok_since is not None,
                    "positions_valid": bool(x.valid.all()),
                    "max_position_error_m": float(np.nanmax(np.abs(x.value[:18] - X[:18]))),
                    "echoed_command_position_m": float(x.value[18]),
                    "status_mode": None if st is None else st.mode.name,
                    "own_echo": h["rx"].get("own_echo", 0),
                    "unknown_id": h["rx"].get("unknown_id", 0),
                    "accepted": h["rx"].get("accepted", 0),
                    "crc_error": h["rx"].get("crc_error", 0),
                    "rcvbuf_bytes": rcvbuf_bytes(ipc.bus),
                    "bus": type(ipc.bus).__name__,
                    "bus_own_skipped": getattr(ipc.bus, "own_skipped", None),
                }
            )
        )
        ipc.close()
    finally:
        child.wait(timeout=START_S)
    return child.returncode


if __name__ == "__main__":
    role, seconds = sys.argv[1], float(sys.argv[2]) if len(sys.argv) > 2 else 1.5
    interface = sys.argv[3] if len(sys.argv) > 3 else "udp_multicast"
    if role == "plc":
        run_plc(seconds, interface)
    else:
        sys.exit(run_ipc(seconds, interface))
