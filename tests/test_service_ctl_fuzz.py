"""Hypothesis fuzzing of the control socket against a running CtlServer wired to a running
service core (the service's own handlers, its loop at 200 Hz, a PLC peer on a virtual bus).

Random bytes, random JSON, random verbs and arguments, lines cut into random pieces,
several clients at once, and disconnects at every byte (close, reset, half-close). Each
client is answered (one JSON reply with ``ok`` per line) or closed; after each example
``status`` answers, the server is healthy and the loop runs.

``WARA_FUZZ_EXAMPLES=N`` runs N examples per test instead of the default (the figures in
docs/hostile-input.md were taken so).
"""

from __future__ import annotations

import json
import os
import socket
import tempfile
import threading
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from structlog.testing import capture_logs

from config import load_project
from ipc_app.service.app import service_handlers
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import COMMANDS, CtlServer, request
from ipc_app.service.loop import FixedRateLoop
from ipc_app.service.worker import PlanResult
from plc_bridge import IpcLink, PlcLink, PlcStatus

pytestmark = pytest.mark.slow

EXAMPLES = int(os.environ.get("WARA_FUZZ_EXAMPLES", "40"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=timedelta(seconds=10),  # a hang fails the example instead of the run
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


class NoPlan:
    """The planner worker's interface, answering every target as infeasible at once."""

    def __init__(self) -> None:
        self._pending: list[int] = []

    def submit(
        self, request_id: int, roll_deg: float, pitch_deg: float, *_: Any, **__: Any
    ) -> bool:
        self._pending.append(request_id)
        return True

    def poll(self) -> PlanResult | None:
        if not self._pending:
            return None
        rid = self._pending.pop(0)
        return PlanResult(rid, False, ("fuzz: no plan",), None, None, None, 0.0)


@dataclass
class Live:
    server: CtlServer
    loop: FixedRateLoop
    core: ServiceCore
    cycles: list[int]


@pytest.fixture(scope="module")
def live() -> Iterator[Live]:
    cfg = load_project()
    channel = f"ctl-fuzz-{uuid.uuid4().hex}"
    plc = PlcLink(cfg, can.Bus(interface="virtual", channel=channel))
    link = IpcLink(cfg, can.Bus(interface="virtual", channel=channel))
    plc.set_status(PlcStatus(pump_running=True, drives_enabled=True))
    plc.set_positions_m(np.array([c.stroke_m / 2 for c in cfg.cylinders_by_can_index]))
    cycles = [0]
    with tempfile.TemporaryDirectory(prefix="wara-fuzz-") as d, capture_logs():
        core = ServiceCore(cfg, link, NoPlan())

        def step(k: int, now: float) -> None:
            plc.poll(now)
            core.step(k, now)
            cycles[0] += 1

        loop = FixedRateLoop(step, cfg.control.period_s, gc_mode="slack", freeze_heap=False)
        server = CtlServer(service_handlers(lambda: core, lambda: server, 0.5), Path(d) / "c")
        server.start()
        loop.start()
        yield Live(server, loop, core, cycles)
        print(f"ctl fuzz: server counters {server.health()}")  # `pytest -s` shows them
        loop.stop()
        server.stop()
        link.close()
        plc.close()


def _alive(live: Live) -> None:
    """The service answers status, its channel is healthy and its loop goes on."""
    before = live.cycles[0]
    reply = request("status", socket_path=live.server.path, timeout_s=5, retry_s=1)
    assert reply["ok"] and "mode" in reply and reply["ctl"]["state"] == "ok"
    assert live.server.healthy and live.loop.running and live.loop.error is None
    for _ in range(200):  # goes on (a busy shared machine may hold it up a while)
        if live.cycles[0] > before:
            break
        threading.Event().wait(0.01)
    assert live.cycles[0] > before


# --------------------------------------------------------------------------- strategies

json_values = st.recursive(
    st.none()
    | st.booleans()
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.integers(min_value=-(10**30), max_value=10**30)
    | st.text(max_size=12),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
verbs = st.sampled_from(COMMANDS) | st.text(max_size=10) | json_values
numbers = (
    st.floats(min_value=-100, max_value=100)
    | st.floats(allow_nan=True, allow_infinity=True)
    | st.integers(min_value=-(10**400), max_value=10**400)
    | json_values
)
requests_ = st.fixed_dictionaries(
    {"cmd": verbs},
    optional={"roll_deg": numbers, "pitch_deg": numbers, "extra": json_values},
).map(lambda d: json.dumps(d).encode())
lines = st.one_of(
    requests_,
    requests_,
    json_values.map(lambda v: json.dumps(v).encode()),
    st.binary(max_size=200),
    st.integers(1, 4000).map(lambda n: b"[" * n),  # nested past the recursion limit
    st.integers(1, 4000).map(lambda n: b'{"cmd":' * n + b"1" + b"}" * n),
    st.just(b'{"cmd": "status"}'),
    st.just(b'{"cmd": "stop"}'),
)
endings = st.sampled_from(["read", "read", "close", "reset"])


@st.composite
def clients(draw: st.DrawFn) -> tuple[bytes, list[int], str]:
    """One client: its bytes, where they are cut into separate sends, how it ends."""
    parts = draw(st.lists(lines, min_size=1, max_size=5))
    seps = draw(
        st.lists(
            st.sampled_from([b"\n", b"\r\n", b"", b"\n\n"]),
            min_size=len(parts),
            max_size=len(parts),
        )
    )
    payload = b"".join(p + s for p, s in zip(parts, seps, strict=True))
    cuts = sorted(set(draw(st.lists(st.integers(0, len(payload)), max_size=4))))
    ending = draw(endings)
    if ending != "read" and payload:
        payload = payload[: draw(st.integers(0, len(payload)))]  # disconnect mid-way
    return payload, cuts, ending


def _expected(payload: bytes) -> int:
    """Replies owed for a payload sent whole and half-closed: one per non-blank line."""
    return sum(1 for seg in payload.split(b"\n") if seg.strip())


def _connect(path: Path) -> socket.socket:
    """Connect as `wara ctl` does: a full listen queue (this process's clients outrun the
    server thread, which waits for the GIL) is retried for a bounded time."""
    for _ in range(500):
        s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
        s.settimeout(5)
        try:
            s.connect(str(path))
        except BlockingIOError:
            s.close()
            threading.Event().wait(0.01)
            continue
        return s
    raise AssertionError("the listen queue stayed full for 5 s")


def _finish(s: socket.socket, payload: bytes, ending: str) -> None:
    if ending == "reset":
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\0\0\0\0\0\0\0")
        s.close()
        return
    if ending == "close":
        s.close()
        return
    s.shutdown(socket.SHUT_WR)
    data = b""
    while chunk := s.recv(65536):
        data += chunk
    s.close()
    replies = [json.loads(x) for x in data.splitlines()]
    assert all(isinstance(r, dict) and isinstance(r.get("ok"), bool) for r in replies)
    assert all(r["ok"] or isinstance(r.get("error"), str) for r in replies)
    assert len(replies) == _expected(payload), (payload[:200], replies[:5])


# --------------------------------------------------------------------------- the tests


@FUZZ
@given(st.lists(clients(), min_size=1, max_size=4))
def test_any_clients_are_answered_or_closed_and_the_service_goes_on(
    live: Live, cs: list[tuple[bytes, list[int], str]]
) -> None:
    socks = [_connect(live.server.path) for _ in cs]
    try:
        # interleave the clients' pieces: piece k of every client, then k + 1, ...
        pieces = [
            [p[a:b] for a, b in zip([0, *cuts], [*cuts, len(p)], strict=True)] for p, cuts, _ in cs
        ]
        for k in range(max(len(x) for x in pieces)):
            for s, ps in zip(socks, pieces, strict=True):
                if k < len(ps) and ps[k]:
                    s.sendall(ps[k])
        for s, (payload, _, ending) in zip(socks, cs, strict=True):
            _finish(s, payload, ending)
    finally:
        for s in socks:
            s.close()
    _alive(live)


@FUZZ
@given(st.binary(min_size=1, max_size=4096))
def test_random_bytes_in_one_send(live: Live, payload: bytes) -> None:
    with _connect(live.server.path) as s:
        s.sendall(payload)
        _finish(s, payload, "read")
    _alive(live)


REQUESTS = (
    b'{"cmd": "status"}\n{"cmd": "adjust", "roll_deg": 1.5, "pitch_deg": -0.5}\n'
    b'{"cmd": "reset"}\n{"cmd": "stop"}\n'
)


@pytest.mark.parametrize("ending", ["close", "reset", "read"])
def test_a_disconnect_at_every_byte(live: Live, ending: str) -> None:
    for k in range(len(REQUESTS) + 1):
        with _connect(live.server.path) as s:
            s.sendall(REQUESTS[:k])
            _finish(s, REQUESTS[:k], ending)
    _alive(live)
    assert live.server.health()["internal_errors"] == 0
