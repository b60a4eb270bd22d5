"""The control socket with a fake service: protocol, permissions, errors, `wara ctl`."""

from __future__ import annotations

import contextlib
import dataclasses
import json
import os
import socket
import stat
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from structlog.testing import capture_logs

from config import load_project
from ipc_app.service.app import CtlWatch, service_handlers, watched_step
from ipc_app.service.ctl import (
    CtlError,
    CtlHandlers,
    CtlServer,
    CtlUnavailable,
    default_socket_path,
    dispatch,
    parse,
    request,
)
from ipc_app.service.interlocks import Cause, Interlock
from ipc_app.service.loop import ChangeGate
from ipc_app.service.modes import Mode, ModeMachine, UnitMode
from ipc_app.service.sdnotify import SystemdNotifier
from wara.cli import main


class FakeService:
    """The mode machine behind the handlers, as the real service will wire it."""

    def __init__(self) -> None:
        self.causes: list[Cause] = []
        self.modes = ModeMachine(active_causes=lambda: list(self.causes))
        self.modes.boot_complete()
        self.calls: list[tuple[str, Any]] = []

    def adjust(self, roll: float, pitch: float) -> dict[str, Any]:
        self.calls.append(("adjust", (roll, pitch)))
        if roll > 20:
            return {
                "ok": False,
                "code": "infeasible",
                "error": "target not reachable",
                "reasons": ["upper_1 beyond its stroke"],
            }
        out = self.modes.request_adjust(roll, pitch)
        if not out.accepted:
            return {"ok": False, "code": "refused", "error": out.message}
        return {"mode": str(out.mode), "request_id": 1}

    def status(self) -> dict[str, Any]:
        snap = self.modes.snapshot()
        snap["loop"] = {"jitter_p99_ms": 0.25, "overruns": 0}
        return snap

    def stop(self) -> dict[str, Any]:
        return self.modes.stop().to_dict()

    def reset(self) -> dict[str, Any]:
        out = self.modes.reset()
        return out.to_dict() | (
            {} if out.accepted else {"ok": False, "code": "refused", "error": out.message}
        )

    def _outcome(self, out: Any) -> dict[str, Any]:
        return out.to_dict() | (
            {} if out.accepted else {"ok": False, "code": "refused", "error": out.message}
        )

    def clear(self) -> dict[str, Any]:
        return self._outcome(self.modes.clear())

    def hold(self) -> dict[str, Any]:
        return self._outcome(self.modes.hold())

    def unhold(self) -> dict[str, Any]:
        return self._outcome(self.modes.unhold())

    def unit_mode(self, unit: str) -> dict[str, Any]:
        return self._outcome(self.modes.set_unit_mode(UnitMode(unit)))

    def jog(self, cylinder: str, distance_mm: float) -> dict[str, Any]:
        self.calls.append(("jog", (cylinder, distance_mm)))
        return self._outcome(self.modes.jog(f"{cylinder} {distance_mm:+.2f} mm"))

    def handlers(self) -> CtlHandlers:
        return CtlHandlers(
            self.adjust,
            self.status,
            self.stop,
            self.reset,
            self.clear,
            self.hold,
            self.unhold,
            self.unit_mode,
            self.jog,
        )


@pytest.fixture
def short_tmp() -> Iterator[Path]:
    # AF_UNIX paths are limited to 107 bytes; pytest's tmp_path can be longer
    import tempfile

    with tempfile.TemporaryDirectory(prefix="wara-ctl-") as d:
        yield Path(d)


@pytest.fixture
def served(short_tmp: Path) -> Iterator[tuple[FakeService, Path]]:
    # capture_logs keeps the in-process server's log lines off stdout, which the
    # `wara ctl` tests read
    with capture_logs():
        svc = FakeService()
        path = short_tmp / "run" / "ctl.sock"
        server = CtlServer(svc.handlers(), path)
        server.start()
        yield svc, path
        server.stop()


def test_socket_is_owner_only_in_a_private_dir(served: tuple[FakeService, Path]) -> None:
    _, path = served
    st = path.stat()
    assert stat.S_ISSOCK(st.st_mode)
    assert stat.S_IMODE(st.st_mode) == 0o600
    assert st.st_uid == os.getuid()
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700


def test_commands_round_trip(served: tuple[FakeService, Path]) -> None:
    svc, path = served
    assert request("status", socket_path=path)["mode"] == "IDLE"
    r = request("adjust", socket_path=path, roll_deg=-3.0, pitch_deg=2.0)
    assert r["ok"] and r["mode"] == "STARTING"
    assert svc.calls == [("adjust", (-3.0, 2.0))]
    assert request("stop", socket_path=path)["mode"] == "IDLE"
    hb = Cause(Interlock.PLC_HEARTBEAT, detail="PLC status lost")
    svc.modes.fault(hb)
    svc.causes.append(hb)
    r = request("reset", socket_path=path)
    assert not r["ok"] and r["code"] == "refused" and hb.text() in r["error"]
    svc.causes.clear()
    assert request("reset", socket_path=path)["mode"] == "IDLE"


def test_bad_requests_get_one_line_errors(served: tuple[FakeService, Path]) -> None:
    svc, path = served
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
        s.settimeout(10)
        s.connect(str(path))
        f = s.makefile("rwb")
        replies = []
        for line in (
            b"not json\n",
            b"[1, 2]\n",
            b'{"cmd": "launch"}\n',
            b'{"cmd": "adjust", "roll_deg": "a lot", "pitch_deg": 0}\n',
            b'{"cmd": "adjust", "roll_deg": NaN, "pitch_deg": 0}\n',
            b'{"cmd": "adjust", "roll_deg": 95, "pitch_deg": 0}\n',
            b'{"cmd": "status"}\n',  # the connection is still usable
        ):
            f.write(line)
            f.flush()
            replies.append(json.loads(f.readline()))
    assert [r["ok"] for r in replies] == [False] * 6 + [True]
    assert all(r["code"] == "bad_request" for r in replies[:6])
    assert "unknown command 'launch'" in replies[2]["error"]
    assert "finite number" in replies[3]["error"] and "finite number" in replies[4]["error"]
    assert svc.calls == []


def test_handler_exception_is_an_internal_error(short_tmp: Path) -> None:
    def boom() -> dict[str, Any]:
        raise RuntimeError("status lock poisoned")

    svc = FakeService()
    h = CtlHandlers(svc.adjust, boom, svc.stop, svc.reset)
    with CtlServer(h, short_tmp / "c.sock") as server:
        r = request("status", socket_path=server.path)
    assert r == {
        "ok": False,
        "code": "internal",
        "error": "status failed in the service: RuntimeError: status lock poisoned",
    }


def test_stale_socket_replaced_live_socket_refused(short_tmp: Path) -> None:
    path = short_tmp / "s.sock"
    stale = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    stale.bind(str(path))
    stale.close()  # file left behind, nobody listening
    svc = FakeService()
    with CtlServer(svc.handlers(), path):
        assert request("status", socket_path=path)["ok"]
        with pytest.raises(CtlError, match="already listens"):
            CtlServer(svc.handlers(), path).start()
    assert not path.exists()  # removed on stop


def test_not_running_is_unavailable(short_tmp: Path) -> None:
    with pytest.raises(CtlUnavailable, match="no W-ARa service listening"):
        request("status", socket_path=short_tmp / "nobody.sock")


def test_default_socket_path_order(tmp_path: Path) -> None:
    assert default_socket_path({"WARA_CTL_SOCKET": "/x/y.sock"}) == Path("/x/y.sock")
    assert default_socket_path({"RUNTIME_DIRECTORY": "/run/wara:/run/other"}) == Path(
        "/run/wara/ctl.sock"
    )
    fallback = default_socket_path({"XDG_RUNTIME_DIR": str(tmp_path)})
    assert fallback.name == "ctl.sock"


def test_concurrent_clients(served: tuple[FakeService, Path]) -> None:
    _, path = served
    results: list[bool] = []

    def ask() -> None:
        results.append(request("status", socket_path=path)["ok"])

    threads = [threading.Thread(target=ask) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(30)
    assert results == [True] * 6


# --------------------------------------------------------------------------- wara ctl


def test_wara_ctl_status_and_adjust(
    served: tuple[FakeService, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    _, path = served
    assert main(["ctl", "--socket", str(path), "status"]) == 0
    out = capsys.readouterr().out
    assert out.splitlines()[0] == "mode: IDLE"
    assert "loop.jitter_p99_ms: 0.25" in out
    assert main(["ctl", "status", "--json", "--socket", str(path)]) == 0
    assert json.loads(capsys.readouterr().out)["mode"] == "IDLE"
    code = main(["ctl", "adjust", "--roll-deg", "-3", "--pitch-deg", "2", "--socket", str(path)])
    assert code == 0 and "mode: STARTING" in capsys.readouterr().out


def test_wara_ctl_refused_and_infeasible(
    served: tuple[FakeService, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    svc, path = served
    code = main(["ctl", "--socket", str(path), "adjust", "--roll-deg", "30", "--pitch-deg", "0"])
    err = capsys.readouterr().err
    assert code == 3 and "target not reachable" in err and "upper_1 beyond" in err
    svc.modes.fault(Cause(Interlock.TWIST, "upper", 2.0, 1.5))
    code = main(["ctl", "--socket", str(path), "adjust", "--roll-deg", "1", "--pitch-deg", "0"])
    assert code == 1 and "refused in ABORTED" in capsys.readouterr().err
    assert main(["ctl", "--socket", str(path), "stop"]) == 0


def test_wara_ctl_without_service_is_one_line_exit_2(
    short_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["ctl", "--socket", str(short_tmp / "none.sock"), "status"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("wara ctl: error: no W-ARa service")


# --------------------------------------------------------------------------- rude clients


def _connect(path: Path) -> socket.socket:
    s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
    s.settimeout(5)
    s.connect(str(path))
    return s


def _ask(s: socket.socket, line: bytes) -> dict[str, Any]:
    s.sendall(line)
    buf = b""
    while not buf.endswith(b"\n"):
        chunk = s.recv(65536)
        if not chunk:
            break
        buf += chunk
    reply = json.loads(buf)
    assert isinstance(reply, dict)
    return reply


def test_rude_clients_with_every_slot_taken_do_not_end_the_server(
    served: tuple[FakeService, Path],
) -> None:
    _, path = served
    held = [_connect(path) for _ in range(16)]  # every slot (and more than the 8 of old)
    try:
        for _ in range(30):  # connect and close at once, as fast as possible
            with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as r:
                r.settimeout(5)
                r.connect(str(path))
        for _ in range(5):  # and with a reset (SO_LINGER 0) instead of a close
            r = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            r.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, b"\x01\0\0\0\0\0\0\0")
            r.connect(str(path))
            r.close()
        assert request("status", socket_path=path, timeout_s=5)["mode"] == "IDLE"
        assert request("stop", socket_path=path, timeout_s=5)["ok"]
    finally:
        for s in held:
            s.close()


def test_nested_and_oversized_json_are_bad_requests(served: tuple[FakeService, Path]) -> None:
    svc, path = served
    with _connect(path) as s:
        r = _ask(s, b"[" * 50_000 + b"\n")
        assert r["code"] == "bad_request" and "nested too deeply" in r["error"]
        r = _ask(s, b'{"cmd": {"a": ' * 3_000 + b"1" + b"}" * 3_000 + b"\n")
        assert r["code"] == "bad_request"
        r = _ask(s, b'{"cmd": "adjust", "roll_deg": ' + b"7" * 5_000 + b', "pitch_deg": 0}\n')
        assert r["code"] == "bad_request"  # 4300-digit limit of int()
        r = _ask(s, b'{"cmd": "adjust", "roll_deg": 1' + b"0" * 400 + b', "pitch_deg": 0}\n')
        assert r["code"] == "bad_request" and "finite number" in r["error"]
        assert "digits" in r["error"] and len(r["error"]) < 200
        r = _ask(s, b'{"cmd": ["status"]}\n')
        assert r["code"] == "bad_request" and "a list" in r["error"]
        assert _ask(s, b'{"cmd": "status"}\n')["ok"]  # the same connection still works
    assert svc.calls == []


def test_a_line_too_long_is_answered_then_closed(served: tuple[FakeService, Path]) -> None:
    _, path = served
    with _connect(path) as s:
        with contextlib.suppress(OSError):  # the server may close before all is sent
            s.sendall(b"x" * (70 * 1024))
        r = json.loads(s.makefile("rb").readline())
    assert r == {"ok": False, "error": "request line too long", "code": "bad_request"}
    assert request("status", socket_path=path)["ok"]


def test_a_full_listen_queue_is_retried(short_tmp: Path) -> None:
    svc = FakeService()
    server = CtlServer(svc.handlers(), short_tmp / "q.sock", backlog=2)
    server.bind()  # listening, nobody accepting: the queue fills
    results: list[Any] = []

    def ask() -> None:
        try:
            results.append(request("status", socket_path=server.path, timeout_s=10)["ok"])
        except CtlError as exc:
            results.append(exc)

    with capture_logs():
        threads = [threading.Thread(target=ask) for _ in range(10)]
        for t in threads:
            t.start()
        threading.Event().wait(0.3)
        server.start()
        for t in threads:
            t.join(30)
        server.stop()
    assert results == [True] * 10


def test_idle_and_slow_clients_never_lock_out_stop_and_status(
    served: tuple[FakeService, Path],
) -> None:
    svc, path = served
    idle = [_connect(path) for _ in range(16)]
    slow = [_connect(path) for _ in range(16)]
    try:
        for s in slow:
            s.sendall(b'{"cmd": "sta')  # a line that never ends
        for _ in range(3):
            svc.modes.request_adjust(1.0, 0.0)
            assert request("stop", socket_path=path, timeout_s=2, retry_s=0)["mode"] == "IDLE"
            assert request("status", socket_path=path, timeout_s=2, retry_s=0)["ok"]
    finally:
        for s in idle + slow:
            s.close()


def test_blocking_requests_are_bounded_and_never_hold_up_stop(short_tmp: Path) -> None:
    svc = FakeService()
    release = threading.Event()

    def slow_adjust(roll: float, pitch: float) -> dict[str, Any]:
        release.wait(30)
        return {"mode": "STARTING"}

    h = CtlHandlers(slow_adjust, svc.status, svc.stop, svc.reset)
    with capture_logs(), CtlServer(h, short_tmp / "b.sock", max_workers=2) as server:
        waiting = [_connect(server.path) for _ in range(2)]
        for s in waiting:
            s.sendall(b'{"cmd": "adjust", "roll_deg": 1, "pitch_deg": 0}\n')
        threading.Event().wait(0.2)
        r = request("adjust", socket_path=server.path, roll_deg=1.0, pitch_deg=0.0, retry_s=0)
        assert r["code"] == "busy"
        assert request("stop", socket_path=server.path, timeout_s=2, retry_s=0)["ok"]
        assert request("status", socket_path=server.path, timeout_s=2, retry_s=0)["ok"]
        assert server.health()["in_flight"] == 2
        release.set()
        assert [json.loads(s.makefile("rb").readline())["ok"] for s in waiting] == [True, True]
        for s in waiting:
            s.close()
        assert threading.active_count() < 20  # no thread per client


def test_pipelined_requests_and_a_half_closed_last_line_are_answered_in_order(
    served: tuple[FakeService, Path],
) -> None:
    _, path = served
    with _connect(path) as s:
        s.sendall(b'{"cmd": "status"}\n' * 40 + b'{"cmd": "launch"}\n{"cmd": "stop"}')
        s.shutdown(socket.SHUT_WR)
        lines = s.makefile("rb").read().splitlines()
    replies = [json.loads(x) for x in lines]
    assert len(replies) == 42
    assert all(r["ok"] and r["mode"] == "IDLE" for r in replies[:40])
    assert replies[40]["code"] == "bad_request" and replies[41]["ok"]


class _Bug(BaseException):
    """Stands for a defect in the server itself (not caught by its error handling)."""


def test_a_dead_server_thread_is_a_fault_and_is_restarted(
    short_tmp: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    svc = FakeService()
    with capture_logs(), CtlServer(svc.handlers(), short_tmp / "d.sock") as server:
        watch = CtlWatch(server, svc.modes.fault)
        assert watch.check() and server.healthy
        turn = server._turn

        def broken(sel: Any) -> None:
            raise _Bug("selector state corrupted")

        monkeypatch.setattr(server, "_turn", broken)
        assert server._thread is not None
        server._thread.join(5)
        assert server.state() == "dead" and not server.healthy
        monkeypatch.setattr(server, "_turn", turn)
        assert watch.check()  # latched and restarted
        assert server.healthy and server.restarts == 1
        st = request("status", socket_path=server.path)
        assert st["mode"] == "ABORTED"
        assert [(f["interlock"], f["where"]) for f in st["faults"]] == [("control channel", "dead")]
        assert "selector state corrupted" in st["fault_reasons"][0]  # the operator sees why
        assert watch.check() and watch.outages == 1  # once per outage


def test_a_removed_socket_file_is_a_fault_and_is_bound_again(short_tmp: Path) -> None:
    svc = FakeService()
    with capture_logs(), CtlServer(svc.handlers(), short_tmp / "g.sock") as server:
        watch = CtlWatch(server, svc.modes.fault)
        server.path.unlink()
        assert server.state() == "socket_gone"
        assert watch.check()
        assert request("status", socket_path=server.path)["mode"] == "ABORTED"
        assert [(f.interlock, f.where) for f in svc.modes.faults] == [
            (Interlock.CONTROL_CHANNEL, "socket_gone")
        ]


def test_a_stalled_server_stops_the_service(short_tmp: Path) -> None:
    svc = FakeService()
    gate = threading.Event()

    def stuck_status() -> dict[str, Any]:
        gate.wait(30)
        return {}

    h = CtlHandlers(svc.adjust, stuck_status, svc.stop, svc.reset)
    with capture_logs(), CtlServer(h, short_tmp / "t.sock", stall_s=0.3) as server:
        watch = CtlWatch(server, svc.modes.fault)
        with _connect(server.path) as s:
            s.sendall(b'{"cmd": "status"}\n')
            threading.Event().wait(0.8)
            assert server.state() == "stalled"
            assert not watch.check()  # the service stops (systemd restarts it)
            assert svc.modes.mode == "ABORTED"
            gate.set()


def test_the_loop_withholds_the_watchdog_while_the_channel_is_dead(
    short_tmp: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    sd = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sd.bind(str(short_tmp / "notify"))
    sd.settimeout(0.05)
    notifier = SystemdNotifier(str(short_tmp / "notify"), watchdog_usec=20_000)  # 10 ms
    steps: list[float] = []

    def pings(t0: float) -> int:
        n = 0
        for k in range(10):
            step(k, t0 + 0.011 * k)
        with contextlib.suppress(TimeoutError):
            while sd.recv(64) == b"WATCHDOG=1":
                n += 1
        return n

    svc = FakeService()
    with capture_logs(), CtlServer(svc.handlers(), short_tmp / "w.sock") as server:
        step = watched_step(lambda k, t: steps.append(t), notifier, server)
        assert pings(0.0) == 10
        monkeypatch.setattr(server, "_turn", lambda sel: (_ for _ in ()).throw(_Bug("x")))
        assert server._thread is not None
        server._thread.join(5)
        assert pings(1.0) == 0 and len(steps) == 20  # the steps still ran
        monkeypatch.undo()
        assert server.restart()
        assert pings(2.0) == 10
    sd.close()


def test_the_service_handlers_answer_refusals_as_refused(short_tmp: Path) -> None:
    """The core answers with mode-machine outcomes and planner verdicts; on the channel a
    refused reset is ``ok: false`` (exit 1 of `wara ctl reset`), and every refusal has its
    one-line error."""
    svc = FakeService()

    class Core:
        modes = svc.modes
        state_changes = ChangeGate()

        def request_reset(self, wait_s: float = 0.0) -> dict[str, Any]:
            return self.modes.reset().to_dict()

        def request_adjust(self, r: float, p: float, wait_s: float = 0.0) -> dict[str, Any]:
            return {"ok": False, "code": "infeasible", "reasons": ["upper_1 beyond its stroke"]}

        def snapshot(self) -> dict[str, Any]:
            return self.modes.snapshot()

        def stop(self, reason: str) -> dict[str, Any]:
            return self.modes.stop(reason).to_dict()

    core: Any = Core()
    with (
        capture_logs(),
        CtlServer(service_handlers(lambda: core, lambda: server), short_tmp / "h.sock") as server,
    ):
        r = request("reset", socket_path=server.path)
        assert r["ok"] is False and r["code"] == "refused"
        assert r["error"] == "nothing to reset: mode is IDLE"
        r = request("adjust", socket_path=server.path, roll_deg=1.0, pitch_deg=0.0)
        assert r["error"] == "target infeasible: upper_1 beyond its stroke"
        assert request("stop", socket_path=server.path)["ok"] is True
        assert request("status", socket_path=server.path)["ctl"]["state"] == "ok"


def test_wara_ctl_packml_commands(
    served: tuple[FakeService, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    svc, path = served
    sock = ["--socket", str(path)]
    # jog only in MANUAL; the unit mode changes in IDLE
    assert main(["ctl", *sock, "jog", "--cylinder", "main_leg_1", "--distance-mm", "2"]) == 1
    assert "unit mode PRODUCTION" in capsys.readouterr().err
    assert main(["ctl", *sock, "unit-mode", "MANUAL"]) == 0
    assert main(["ctl", *sock, "jog", "--cylinder", "main_leg_1", "--distance-mm", "2"]) == 0
    assert "mode: EXECUTE" in capsys.readouterr().out
    assert svc.calls[-1] == ("jog", ("main_leg_1", 2.0))
    assert main(["ctl", *sock, "unit-mode", "PRODUCTION"]) == 1  # not while moving
    assert main(["ctl", *sock, "hold"]) == 0 and svc.modes.mode is Mode.HELD
    assert main(["ctl", *sock, "unhold"]) == 0 and svc.modes.mode is Mode.EXECUTE
    # a fault: clear, then reset
    svc.modes.fault(Cause(Interlock.TWIST, "upper", 2.0, 1.5))
    capsys.readouterr()
    assert main(["ctl", *sock, "clear"]) == 0 and svc.modes.mode is Mode.STOPPED
    assert main(["ctl", *sock, "reset"]) == 0 and svc.modes.mode is Mode.IDLE
    with pytest.raises(SystemExit) as exc:
        main(["ctl", *sock, "unit-mode", "AUTO"])
    assert exc.value.code == 2
    # the protocol checks the arguments itself
    r = request("jog", socket_path=path, cylinder="main_leg_1", distance_mm=float("nan"))
    assert (
        r["code"] == "bad_request" and "'distance_mm' must be a finite number in mm" in r["error"]
    )
    r = request("unit_mode", socket_path=path, unit_mode=7)
    assert r["code"] == "bad_request"


def test_a_service_without_the_packml_commands_says_so() -> None:
    svc = FakeService()
    h = CtlHandlers(svc.adjust, svc.status, svc.stop, svc.reset)
    r = dispatch(h, b'{"cmd": "hold"}')
    assert r == {
        "ok": False,
        "code": "bad_request",
        "error": "hold is not supported by this service",
    }


@pytest.mark.realtime
def test_a_status_that_waits_returns_at_the_next_change_of_state(short_tmp: Path) -> None:
    """What the OPC UA server asks: a status once ``state_seq`` has moved past the one it
    saw, at most ``wait_ms`` later; it waits in the worker pool, so the I/O thread goes on
    answering other clients meanwhile."""
    svc = FakeService()
    gate = ChangeGate()

    class Core:
        state_changes = gate
        period_s = 0.005

        def snapshot(self) -> dict[str, Any]:
            return svc.modes.snapshot()

    core: Any = Core()
    with (
        capture_logs(),
        CtlServer(service_handlers(lambda: core, lambda: server), short_tmp / "w.sock") as server,
    ):
        first = request("status", socket_path=server.path)
        assert first["state_seq"] == 0 and "waited_ms" not in first
        # no change: back after the wait, with the same count
        t0 = time.monotonic()
        same = request("status", socket_path=server.path, after=0, wait_ms=200)
        assert time.monotonic() - t0 >= 0.2 and same["state_seq"] == 0
        assert same["waited_ms"] >= 200
        # a change while it waits: back at the change, long before the wait's end
        out: list[dict[str, Any]] = []
        waiter = threading.Thread(
            target=lambda: out.append(
                request("status", socket_path=server.path, after=0, wait_ms=1000)
            )
        )
        t0 = time.monotonic()
        waiter.start()
        time.sleep(0.1)
        assert request("status", socket_path=server.path)["ok"] is True  # I/O thread free
        gate.changed()
        waiter.join(5.0)
        assert out[0]["state_seq"] == 1 and time.monotonic() - t0 < 0.9
        # already past: at once
        assert request("status", socket_path=server.path, after=0, wait_ms=1000)["state_seq"] == 1


@pytest.mark.parametrize(
    ("args", "error"),
    [
        ({"after": -1, "wait_ms": 10}, "'after' must be a count"),
        ({"after": True, "wait_ms": 10}, "'after' must be a count"),
        ({"after": 3}, "'wait_ms' must be a finite number in ms"),
        ({"after": 3, "wait_ms": 1001}, "'wait_ms' must be within 0..1000"),
        ({"after": 3, "wait_ms": float("nan")}, "'wait_ms' must be a finite number"),
        ({"wait_ms": 10}, "'after' must be a count"),
    ],
)
def test_a_status_wait_is_checked(args: dict[str, Any], error: str) -> None:
    line = json.dumps({"cmd": "status", **args}).encode()
    got = parse(line)
    assert isinstance(got, dict) and got["code"] == "bad_request", got
    assert got["error"].startswith(error), got["error"]


def test_the_core_counts_its_changes_of_mode(tmp_path: Path) -> None:
    """The loop's side: each cycle whose step changed the mode counts one (the first
    cycle counts the start-up mode)."""
    from wara.harness import Harness

    h = Harness(load_project(None), None, mode="lockstep")
    try:
        h.start()
        assert h.wait_for(Mode.IDLE, 20.0), h.fault_note()
        seen = h.core.state_changes.seq
        assert seen >= 2  # STOPPED (the first cycle), IDLE
        h.advance(0.5)
        assert h.core.state_changes.seq == seen  # no change, no count
        h.core.stop("test")
        h.core.request_adjust(1.0, 0.5)
        h.advance(0.5)
        assert h.core.state_changes.seq > seen
    finally:
        h.close()


def test_status_requests_log_at_debug_other_commands_at_info(short_tmp: Path) -> None:
    """The OPC UA feed's status every 50 ms (with ``after`` and ``wait_ms``) stays out of
    an INFO log; the commands, and a status refused, are still logged at info."""
    svc = FakeService()
    # a status that waits answers at once here
    h = dataclasses.replace(svc.handlers(), status=lambda *args: svc.status())
    with capture_logs() as logs, CtlServer(h, short_tmp / "q.sock") as server:
        request("status", socket_path=server.path)
        request("status", socket_path=server.path, after=0, wait_ms=5)
        request("stop", socket_path=server.path)
        with contextlib.suppress(CtlError):
            request("status", socket_path=server.path, after=-1, wait_ms=5)
    seen = [(e["log_level"], json.loads(e["request"])) for e in logs if e["event"] == "ctl_request"]
    assert [(lvl, r["cmd"], "after" in r) for lvl, r in seen] == [
        ("debug", "status", False),
        ("debug", "status", True),
        ("info", "stop", False),
        ("info", "status", True),  # refused: bad_request
    ]


def test_the_docs_table_is_the_rendering_of_the_protocol() -> None:
    """docs/service.md's command table is ``ctl_protocol.markdown_table()``: every command
    of the protocol, its arguments with their limits, its reply."""
    from ipc_app.service.ctl_protocol import COMMANDS, markdown_table

    doc = Path(__file__).resolve().parents[1] / "docs" / "service.md"
    begin = (
        "<!-- control commands table: generated by "
        "ipc_app.service.ctl_protocol.markdown_table() -->\n"
    )
    end = "<!-- end of control commands table -->"
    text = doc.read_text(encoding="utf-8")
    assert begin in text and end in text
    assert text.split(begin, 1)[1].split(end, 1)[0] == markdown_table(), (
        "docs/service.md's command table differs from the protocol: paste the output of "
        "ipc_app.service.ctl_protocol.markdown_table() between the markers"
    )
    assert all(f"| `{c}` |" in markdown_table() for c in COMMANDS)
