"""N OPC UA clients (asyncua) in one process, for ``wara bench opcua``.

    python -m wara.benches.opcua_clients URL CERT KEY USER PASSWORD N

Each client opens a SignAndEncrypt session, subscribes at 10 Hz (publishing interval
100 ms) to the attitude (target and measured), the PackML state and its time, and every
cylinder's position. It prints ``READY`` once all are subscribed, then on SIGTERM one JSON
object: notifications received, and per PackML state change seen by a client the
latency from the change in the service (``StateSince``, CLOCK_MONOTONIC of the same
machine) to the notification's arrival.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import signal
import sys
import time
from typing import Any

from asyncua import Client, ua

NS = "urn:wara:ipc"
WATCH = (
    "PackML.Status.StateCurrent",
    "PackML.Status.StateSince",
    "Attitude.TargetRoll",
    "Attitude.TargetPitch",
    "Attitude.MeasuredRoll",
    "Attitude.MeasuredPitch",
)


class _Handler:
    """Notes each notification; the state changes' arrival times and every StateSince
    value (the service's transition times), matched at the end (:func:`latencies`)."""

    def __init__(self, state_id: str, since_id: str, out: dict[str, Any]) -> None:
        self.state_id, self.since_id = state_id, since_id
        self.out = out
        self.sinces: set[float] = set()
        self.arrivals: list[float] = []
        self.written: list[float] = []  # each change's ServerTimestamp, CLOCK_MONOTONIC
        self.state: int | None = None

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        now = time.monotonic()
        self.out["notifications"] += 1
        key = node.nodeid.Identifier
        if key == self.since_id and isinstance(val, float) and val == val:
            self.sinces.add(val)
        elif key == self.state_id:
            if self.state is not None and int(val) != self.state:
                self.arrivals.append(now)
                stamp = data.monitored_item.Value.ServerTimestamp
                self.written.append(
                    stamp.timestamp() - (time.time() - now) if stamp is not None else math.nan
                )
            self.state = int(val)

    def latencies(self) -> list[tuple[float, float]]:
        """Per change: (arrival, server's write) less the latest transition before it."""
        out = []
        for t, w in zip(self.arrivals, self.written, strict=True):
            before = [s for s in self.sinces if s <= t]
            if before:
                out.append((t - max(before), w - max(before)))
        return out


handlers: list[_Handler] = []


def _nid(ident: str, ns: int) -> ua.NodeId:
    return ua.NodeId(ident, ns)  # type: ignore[arg-type]


async def client(url: str, cert: str, key: str, user: str, pw: str, out: dict[str, Any]) -> Any:
    c = Client(url, timeout=30)
    c.application_uri = "urn:wara:bench:client"
    await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
    c.set_user(user)
    c.set_password(pw)
    await c.connect()
    ns = await c.get_namespace_index(NS)
    ids = [f"W-ARa.{w}" for w in WATCH]
    h = _Handler(ids[0], ids[1], out)
    handlers.append(h)
    sub = await c.create_subscription(100, h)
    nodes = [c.get_node(_nid(i, ns)) for i in ids]
    cyl = c.get_node(_nid("W-ARa.Cylinders", ns))
    for ch in await cyl.get_children():
        nodes += [
            g for g in await ch.get_children() if (await g.read_browse_name()).Name == "Position"
        ]
    await sub.subscribe_data_change(nodes, sampling_interval=100)  # type: ignore[call-overload]
    return c


async def main(argv: list[str]) -> None:
    url, cert, key, user, pw, n = argv[0], argv[1], argv[2], argv[3], argv[4], int(argv[5])
    out: dict[str, Any] = {"clients": n, "notifications": 0, "latencies_s": []}
    clients = [await client(url, cert, key, user, pw, out) for _ in range(n)]
    print("READY", flush=True)
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    loop.add_signal_handler(signal.SIGTERM, stop.set)
    await stop.wait()
    for c in clients:
        with contextlib.suppress(Exception):
            await c.disconnect()
    pairs = [x for h in handlers for x in h.latencies()]
    out["latencies_s"] = [a for a, _ in pairs]
    out["to_server_s"] = [w for _, w in pairs if w == w]
    print(json.dumps(out), flush=True)


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1:]))
