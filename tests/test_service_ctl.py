"""The control socket with a fake service: protocol, permissions, errors, `wara ctl`."""

from __future__ import annotations

import json
import os
import socket
import stat
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from structlog.testing import capture_logs

from ipc_app.service.ctl import (
    CtlError,
    CtlHandlers,
    CtlServer,
    CtlUnavailable,
    default_socket_path,
    request,
)
from ipc_app.service.interlocks import Cause, Interlock
from ipc_app.service.modes import ModeMachine
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

    def handlers(self) -> CtlHandlers:
        return CtlHandlers(self.adjust, self.status, self.stop, self.reset)


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
    assert r["ok"] and r["mode"] == "PLANNING"
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
    assert code == 0 and "mode: PLANNING" in capsys.readouterr().out


def test_wara_ctl_refused_and_infeasible(
    served: tuple[FakeService, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    svc, path = served
    code = main(["ctl", "--socket", str(path), "adjust", "--roll-deg", "30", "--pitch-deg", "0"])
    err = capsys.readouterr().err
    assert code == 3 and "target not reachable" in err and "upper_1 beyond" in err
    svc.modes.fault(Cause(Interlock.TWIST, "upper", 2.0, 1.5))
    code = main(["ctl", "--socket", str(path), "adjust", "--roll-deg", "1", "--pitch-deg", "0"])
    assert code == 1 and "refused in FAULT" in capsys.readouterr().err
    assert main(["ctl", "--socket", str(path), "stop"]) == 0


def test_wara_ctl_without_service_is_one_line_exit_2(
    short_tmp: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = main(["ctl", "--socket", str(short_tmp / "none.sock"), "status"])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("wara ctl: error: no W-ARa service")
