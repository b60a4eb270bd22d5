"""An operator's OPC UA client for ``wara bench opcua``: it calls the methods and times
each call to the state notification it brings.

    python -m wara.benches.opcua_caller URL CERT KEY USER PASSWORD

Opens a SignAndEncrypt session, subscribes to ``PackML/Status/StateCurrent`` at 10 Hz
(publishing interval 100 ms, as the bench's other clients), prints ``READY``; then per
line on stdin (``adjust ROLL_RAD PITCH_RAD`` or ``stop``) calls ``StartAdjustment`` or
``Stop`` and prints one JSON line: the method's result, ``call_s`` (the call sent to its
answer), ``notify_s`` (the call sent to the first notification of a StateCurrent other
than the one before the call; null when none came within 10 s), ``written_s`` (the call
sent to the server's write of that value, its ServerTimestamp; CLOCK_MONOTONIC and the
wall clock of the same machine) and the state. End of stdin ends it.
"""

from __future__ import annotations

import asyncio
import json
import sys
import time
from typing import Any

from asyncua import Client, ua

NS = "urn:wara:ipc"
NOTIFY_TIMEOUT_S = 10.0
#: a notification's arrival and the server's write of its value (None: no timestamp)
_Arrival = tuple[float, float | None]


class _State:
    """The latest StateCurrent and a future for the next change: its arrival and the
    server's write of it (its ServerTimestamp), both CLOCK_MONOTONIC."""

    def __init__(self) -> None:
        self.value: int | None = None
        self.waiting: tuple[int | None, asyncio.Future[_Arrival]] | None = None

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        now = time.monotonic()
        self.value = int(val)
        if self.waiting is not None:
            before, fut = self.waiting
            if int(val) != before and not fut.done():
                stamp = data.monitored_item.Value.ServerTimestamp
                written = stamp.timestamp() - (time.time() - now) if stamp is not None else None
                fut.set_result((now, written))


def _nid(ident: str, ns: int) -> ua.NodeId:
    return ua.NodeId(ident, ns)  # type: ignore[arg-type]


async def main(argv: list[str]) -> None:
    url, cert, key, user, pw = argv[:5]
    c = Client(url, timeout=30)
    c.application_uri = "urn:wara:bench:client"
    await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
    c.set_user(user)
    c.set_password(pw)
    loop = asyncio.get_running_loop()
    async with c:
        ns = await c.get_namespace_index(NS)
        machine = c.get_node(_nid("W-ARa", ns))
        state = _State()
        sub = await c.create_subscription(100, state)
        await sub.subscribe_data_change(  # type: ignore[call-overload]
            c.get_node(_nid("W-ARa.PackML.Status.StateCurrent", ns)), sampling_interval=100
        )
        while state.value is None:  # the initial value
            await asyncio.sleep(0.05)
        print("READY", flush=True)
        while True:
            line = await loop.run_in_executor(None, sys.stdin.readline)
            if not line:
                break
            words = line.split()
            fut: asyncio.Future[_Arrival] = loop.create_future()
            state.waiting = (state.value, fut)
            t0 = time.monotonic()
            try:
                if words[0] == "adjust":
                    args = [ua.Variant(float(w), ua.VariantType.Double) for w in words[1:3]]
                    res = await machine.call_method(_nid("W-ARa.StartAdjustment", ns), *args)
                else:
                    res = await machine.call_method(_nid("W-ARa.Stop", ns))
                result: Any = str(res)
            except ua.UaStatusCodeError as exc:
                result = f"error: {ua.StatusCode(exc.code).name}"
            t1 = time.monotonic()
            notify_s: float | None = None
            written_s: float | None = None
            try:
                arrived, written = await asyncio.wait_for(fut, NOTIFY_TIMEOUT_S)
                notify_s = arrived - t0
                written_s = written - t0 if written is not None else None
            except TimeoutError:
                pass
            state.waiting = None
            out = {"cmd": words[0], "result": result, "call_s": t1 - t0, "notify_s": notify_s,
                   "written_s": written_s, "state": state.value}  # fmt: skip
            print(json.dumps(out), flush=True)


if __name__ == "__main__":
    asyncio.run(main(sys.argv[1:]))
