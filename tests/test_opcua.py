"""The OPC UA server: users file, configuration, the model's mapping, the audit path,
and the server process seen by an independent client (node-opcua) and by rude ones."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from config import ConfigError, load_project
from ipc_app.opcua import model as m
from ipc_app.opcua.users import UsersError, add_user, load_users
from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import Request, dispatch, parse
from ipc_app.service.record import RunRecorder, read_run
from tests import opcua_support as S

# ---------------------------------------------------------------------- users file


def test_users_file_is_0600_and_checks_passwords(tmp_path: Path) -> None:
    f = tmp_path / "sub" / "users.json"
    assert add_user(f, "op", "operator", "operator-pass") is True
    assert add_user(f, "vi", "viewer", "viewer-pass") is True
    assert add_user(f, "op", "engineer", "new-operator-pass") is False  # replaced
    assert (f.stat().st_mode & 0o777) == 0o600
    assert "operator-pass" not in f.read_text()
    users = load_users(f)
    assert users.check("op", "operator-pass") is None
    u = users.check("op", "new-operator-pass")
    assert u is not None and u.role == "engineer"
    assert users.check("vi", "viewer-pass") is not None
    assert users.check("nobody", "viewer-pass") is None
    assert users.check("vi", None) is None


def test_users_file_readable_by_others_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "users.json"
    add_user(f, "op", "operator", "operator-pass")
    os.chmod(f, 0o644)
    with pytest.raises(UsersError, match="must be 0600"):
        load_users(f)


@pytest.mark.parametrize(
    ("name", "role", "password", "message"),
    [
        ("op", "admin", "long-enough", "role 'admin'"),
        ("o p", "viewer", "long-enough", "user name"),
        ("op", "viewer", "short", "at least 8"),
    ],
)
def test_adduser_refuses_bad_input(
    tmp_path: Path, name: str, role: str, password: str, message: str
) -> None:
    with pytest.raises(UsersError, match=message):
        add_user(tmp_path / "u.json", name, role, password)


def test_cli_adduser_one_line_errors(tmp_path: Path) -> None:
    p = subprocess.run(
        [sys.executable, "-m", "wara", "opcua", "adduser", "op", "--role", "operator",
         "--users-file", str(tmp_path / "u.json"), "--password-stdin"],
        input="short\n", capture_output=True, text=True, timeout=60,
    )  # fmt: skip
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "at least 8 characters" in p.stderr


def test_cli_adduser_without_a_terminal_is_one_line(tmp_path: Path) -> None:
    """No terminal (stdin a pipe, no controlling tty) and no --password-stdin: one line
    naming the way, exit 2, no users file written (not getpass's traceback)."""
    p = subprocess.run(
        [sys.executable, "-m", "wara", "opcua", "adduser", "op", "--role", "operator",
         "--users-file", str(tmp_path / "u.json")],
        input="", capture_output=True, text=True, timeout=60, start_new_session=True,
    )  # fmt: skip
    assert p.returncode == 2 and p.stderr.count("\n") == 1, p.stderr
    assert "Traceback" not in p.stderr and "--password-stdin" in p.stderr
    assert not (tmp_path / "u.json").exists()


# ---------------------------------------------------------------------- configuration


def test_opcua_off_by_default_and_validated(tmp_path: Path) -> None:
    assert load_project(None).opcua.enabled is False
    cfg = S.write_config(tmp_path, 4840, security_policy="Basic256Sha256")
    assert load_project(cfg).opcua.enabled is True
    for port, bad in ((80, {}), (4840, {"security_policy": "None"}), (4840, {"colour": "red"}),
                      (4840, {"update_period_ms": 1}), (4840, {"hello_timeout_s": 0}),
                      (4840, {"session_activate_timeout_s": 1000})):  # fmt: skip
        path = S.write_config(tmp_path, port, **bad)
        with pytest.raises(ConfigError, match="opcua"):
            load_project(path)


# ---------------------------------------------------------------------- the model


def test_model_values_are_si_and_follow_the_status() -> None:
    cfg = load_project(None)
    model = m.variables(cfg)
    status = S.FakeService(mode="EXECUTE", target=[2.0, 1.0]).status()
    status["faults"] = [{"interlock": "twist", "text": "twist 1.6 mm > 1.5 mm"}]
    vals = dict(zip((v.path for v in model), m.values(model, status), strict=True))
    assert vals[("PackML", "Status", "StateCurrent")] == 6
    # OPC 30050's three state machines, with their states' ids in the PackML NodeSet
    sm = ("PackML", "BaseStateMachine")
    assert [vals[(*sm, "CurrentState")], vals[(*sm, "CurrentState", "Id")]] == [
        "Cleared",
        m.StateRef(m.NS_PACKML, 71),
    ]
    assert vals[(*sm, "MachineState", "CurrentState")] == "Running"
    assert vals[(*sm, "MachineState", "ExecuteState", "CurrentState")] == "Execute"
    assert vals[(*sm, "MachineState", "ExecuteState", "CurrentState", "Id")] == m.StateRef(
        m.NS_PACKML, 36
    )
    item_id = ("MachineryBuildingBlocks", "MachineryItemState", "CurrentState", "Id")
    assert vals[item_id] == m.StateRef(m.NS_MACHINERY, 5006)  # Executing
    assert vals[("MachineryBuildingBlocks", "MachineryItemState", "CurrentState")] == "Executing"
    assert vals[("MachineryBuildingBlocks", "MachineryOperationMode", "CurrentState")] == (
        "Processing"
    )
    assert vals[("Attitude", "TargetRoll")] == pytest.approx(math.radians(2.0))
    assert vals[("Attitude", "MeasuredPitch")] == pytest.approx(math.radians(-0.25))
    assert vals[("Cylinders", "main_leg_1", "Position")] == pytest.approx(0.4)
    assert vals[("Cylinders", "main_leg_1", "CapPressure")] == pytest.approx(5.0e6)
    assert vals[("Cylinders", "main_leg_1", "Valid")] is True
    assert math.isnan(vals[("Cylinders", "main_leg_2", "Position")])  # not in the status
    assert vals[("Groups", "upper", "SyncError")] == pytest.approx(2e-5)
    assert vals[("Loop", "ComputeP99")] == pytest.approx(0.0008)
    assert vals[("Interlocks", "Twist", "Latched")] is True
    assert vals[("Interlocks", "Twist", "Cause")] == "twist 1.6 mm > 1.5 mm"
    assert vals[("Interlocks", "SyncError", "Latched")] is False
    assert vals[("PackML", "Status", "CycleStep")] == -1  # no walk in the status
    status["walk"] = {"steps": 3, "step": 1, "phase": "7a", "phase_name": "lower M"}
    vals = dict(zip((v.path for v in model), m.values(model, status), strict=True))
    assert (vals[("PackML", "Status", "CycleStep")], vals[("PackML", "Status", "CyclePhase")]) == (
        1,
        "7a lower M",
    )
    status["cycle"] = {"ring": 3, "phase": "place", "since_s": 2.0}  # over its walk's
    vals = dict(zip((v.path for v in model), m.values(model, status), strict=True))
    assert (vals[("PackML", "Status", "CycleStep")], vals[("PackML", "Status", "CyclePhase")]) == (
        3,
        "place",
    )
    # ABORTED: the base machine in Aborted, the machine and execute machines inactive
    status["mode"] = "ABORTED"
    vals = dict(zip((v.path for v in model), m.values(model, status), strict=True))
    assert vals[(*sm, "CurrentState")] == "Aborted"
    assert vals[(*sm, "MachineState", "CurrentState")] == ""
    assert vals[(*sm, "MachineState", "ExecuteState", "CurrentState", "Id")] is None
    assert vals[item_id] == m.StateRef(m.NS_MACHINERY, 5004)  # OutOfService
    status["mode"] = "STOPPED"
    vals = dict(zip((v.path for v in model), m.values(model, status), strict=True))
    assert vals[(*sm, "MachineState", "CurrentState")] == "Stopped"
    assert vals[(*sm, "MachineState", "ExecuteState", "CurrentState")] == ""
    ids = {v.path[1] for v in model if v.path[0] == "Cylinders"}
    assert ids == {*cfg.layers.lower.cylinders, *cfg.layers.upper.cylinders}
    assert all(v.unit is not None for v in model if v.kind == "Double")


# ---------------------------------------------------------------------- the audit path


def test_ctl_audit_request_is_checked() -> None:
    assert parse(b'{"cmd": "audit", "user": "op", "action": "Stop", "result": "ok"}') == Request(
        "audit", ("op", "Stop", "ok")
    )
    for bad in (
        b'{"cmd": "audit", "user": "op", "action": "Stop"}',
        b'{"cmd": "audit", "user": "", "action": "Stop", "result": "ok"}',
        b'{"cmd": "audit", "user": "op", "action": "Stop", "result": "' + b"x" * 500 + b'"}',
    ):
        reply = parse(bad)
        assert isinstance(reply, dict) and reply["code"] == "bad_request", bad


def test_audit_goes_into_the_run_record_and_the_log(tmp_path: Path) -> None:
    rec = RunRecorder(tmp_path / "run", ["x"])
    rec.start()
    core: Any = SimpleNamespace(record=rec, _now=12.5)
    handlers = S.FakeService().handlers()
    # the service's handler: ServiceCore.audit
    out = ServiceCore.audit(core, "op", "Stop", "Stop: ok: mode IDLE")
    assert out == {}
    rec.stop()
    events = [e for e in read_run(tmp_path / "run").events if e["kind"] == "audit"]
    assert events == [
        {
            "t_s": 12.5,
            "kind": "audit",
            "user": "op",
            "action": "Stop",
            "result": "Stop: ok: mode IDLE",
        }
    ]
    assert dispatch(handlers, b'{"cmd":"audit","user":"a","action":"b","result":"c"}')["ok"]


# ---------------------------------------------------------------------- with a client


def _node(
    rig: S.Rig, tmp: Path, scenario: str, *user: str, cert: str = "trusted"
) -> dict[str, Any]:
    c, k = (rig.cert, rig.key) if cert == "trusted" else (rig.untrusted_cert, rig.untrusted_key)
    p = S.run_node("client.js", scenario, rig.url, str(c), str(k), str(tmp / f"node-{cert}"), *user)
    try:
        return dict(json.loads(p.stdout.strip().splitlines()[-1]))
    except (ValueError, IndexError):
        raise AssertionError(
            f"no JSON from the node client: {p.stdout!r} {p.stderr[-2000:]}"
        ) from None


needs_node = pytest.mark.skipif(S.node_available() is not None, reason=str(S.node_available()))


@pytest.mark.slow
@needs_node
def test_node_client_browses_subscribes_and_calls(tmp_path: Path) -> None:
    with S.rig(tmp_path) as rig:
        out = _node(rig, tmp_path, "full", "op", S.PASSWORDS["op"])
        assert out["ok"], out
        assert out["browse"] == {
            "identification": "W-ARa",
            "item_state": "NotExecuting",
            "operation_mode": "Processing",
            "packml_state": 4,
            "packml_unit_mode": 1,
            "packml_base": "Cleared",
            "packml_machine": "Running",
            "packml_execute": "Idle",
            "packml_execute_id": "PackML:28",  # the Idle state of the PackML NodeSet
            "item_state_id": "Machinery:5007",  # NotExecuting
        }
        assert out["types"] == {  # instances of the companion NodeSets' types
            "identification": "Machinery:MachineIdentificationType",
            "item_state": "Machinery:MachineryItemState_StateMachineType",
            "operation_mode": "Machinery:MachineryOperationModeStateMachineType",
            "packml": "PackML:PackMLBaseObjectType",
            "packml_status": "PackML:PackMLStatusObjectType",
            "packml_execute": "PackML:PackMLExecuteStateMachineType",
        }
        assert out["roll_unit"] == "rad"
        assert out["states"][0] == 4 and 6 in out["states"] and out["states"][-1] == 4
        assert out["rolls"][0] == pytest.approx(math.radians(0.5))
        assert ("adjust", pytest.approx(math.degrees(0.01)), pytest.approx(math.degrees(0.02))) in (
            rig.service.calls
        )
        audits = rig.service.audits
        assert [(u, a) for u, a, _ in audits] == [("op", "StartAdjustment"), ("op", "Stop")]
        assert all("ok: mode" in r for _, _, r in audits)
        # an engineer may do what an operator may
        rig.service.mode = "IDLE"
        assert _node(rig, tmp_path, "call-start", "en", S.PASSWORDS["en"])["ok"]
        # a walk with its number of steps; 0 steps is refused before the service hears it
        rig.service.mode = "IDLE"
        walk = _node(rig, tmp_path, "call-walk", "op", S.PASSWORDS["op"])
        assert walk["ok"], walk
        assert [c for c in rig.service.calls if c[0] == "walk"] == [("walk", 3)]
        assert [(u, a) for u, a, _ in rig.service.audits[-2:]] == [
            ("op", "StartWalk"),
            ("op", "StartWalk"),
        ]
        assert "refused: Steps must be an integer 1..1000" in rig.service.audits[-2][2]
        # PackMLBaseObjectType's methods: SetUnitMode sets the unit mode (PackML's 2:
        # Maintenance); what W-ARa does not have is refused, audited
        packml = _node(rig, tmp_path, "call-packml", "op", S.PASSWORDS["op"])
        assert packml["ok"], packml
        assert ("unit_mode", "MAINTENANCE") in rig.service.calls
        assert [a for _, a, _ in rig.service.audits[-3:]] == [
            "SetUnitMode",
            "SetUnitMode",
            "SetMachSpeed",
        ]
        assert "W-ARa has no machine speed" in rig.service.audits[-1][2]


@pytest.mark.slow
@needs_node
def test_node_client_is_refused_without_the_right_credentials(tmp_path: Path) -> None:
    with S.rig(tmp_path) as rig:
        anon = _node(rig, tmp_path, "session")
        assert not anon["ok"] and "session refused" in anon["error"], anon
        wrong = _node(rig, tmp_path, "session", "op", "not-the-password")
        assert not wrong["ok"] and "BadUserAccessDenied" in wrong["error"], wrong
        untrusted = _node(rig, tmp_path, "session", "op", S.PASSWORDS["op"], cert="untrusted")
        assert not untrusted["ok"] and "BadCertificateUntrusted" in untrusted["error"], untrusted
        viewer = _node(rig, tmp_path, "call-start", "vi", S.PASSWORDS["vi"])
        assert viewer["session"] and viewer["start"]["status"] == "BadUserAccessDenied", viewer
        assert rig.service.calls == []  # nothing reached the service
        assert rig.service.audits[-1][:2] == ("vi", "StartAdjustment")
        assert "refused" in rig.service.audits[-1][2]


@pytest.mark.slow
@needs_node
def test_anonymous_read_only_reads_but_calls_nothing(tmp_path: Path) -> None:
    with S.rig(tmp_path, anonymous_read_only=True) as rig:
        assert _node(rig, tmp_path, "session")["ok"]
        call = _node(rig, tmp_path, "call-start")
        assert "BadUserAccessDenied" in json.dumps(call), call
        assert rig.service.calls == []


# ---------------------------------------------------------------------- rude clients


async def _asyncua_read(rig: S.Rig, node: str) -> Any:
    from asyncua import Client, ua

    c = Client(rig.url, timeout=10)
    c.application_uri = S.CLIENT_URI
    await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{rig.cert},{rig.key}")
    c.set_user("vi")
    c.set_password(S.PASSWORDS["vi"])
    async with c:
        ns = await c.get_namespace_index(m.NS_WARA)
        return await c.get_node(ua.NodeId(f"W-ARa.{node}", ns)).read_value()


async def _vanish(rig: S.Rig) -> None:
    """Open a session, then drop the TCP connection without closing anything."""
    from asyncua import Client

    for _ in range(40):  # the server may still be closing the 100 connections
        c = Client(rig.url, timeout=10)
        c.application_uri = S.CLIENT_URI
        c.set_user("op")
        c.set_password(S.PASSWORDS["op"])
        try:
            await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{rig.cert},{rig.key}")
            await c.connect()
            break
        except (TimeoutError, OSError):
            await asyncio.sleep(0.5)
    else:
        raise AssertionError("no session after the 100 connects")
    transport = c.uaclient.protocol.transport  # type: ignore[union-attr]
    transport.abort()  # the peer is gone: no CloseSession, no CloseSecureChannel
    await asyncio.sleep(0.2)


def _raw(port: int, data: bytes) -> None:
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall(data)
        s.settimeout(0.5)
        try:
            while s.recv(4096):
                pass
        except (TimeoutError, ConnectionError):
            pass


@pytest.mark.slow
def test_hostile_clients_do_not_stop_the_server(tmp_path: Path) -> None:
    import random
    import struct

    rnd = random.Random(7)
    with S.rig(tmp_path) as rig:
        pid = rig.server.proc.pid if rig.server.proc else None
        assert asyncio.run(_asyncua_read(rig, "PackML.Status.StateCurrent")) == 4
        hello = b"HELF" + struct.pack("<I", 32) + struct.pack("<IIIII", 0, 65536, 65536, 0, 0)
        garbage = [
            b"\x00" * 64,
            b"GET / HTTP/1.1\r\nHost: x\r\n\r\n",
            b"HELF" + struct.pack("<I", 0xFFFFFFF0) + b"\x00" * 20,  # a 4 GiB message announced
            hello[:11],  # truncated
            hello + b"MSGF" + struct.pack("<I", 24) + b"\xff" * 16,  # a message before OPN
            b"OPNF" + struct.pack("<I", 100) + bytes(rnd.getrandbits(8) for _ in range(92)),
            *(bytes(rnd.getrandbits(8) for _ in range(rnd.randrange(1, 400))) for _ in range(20)),
        ]
        for g in garbage:
            _raw(rig.port, g)
        socks = []
        for _ in range(100):  # 100 connects, held open together, then dropped
            with contextlib.suppress(OSError):  # refused beyond max_connections: as meant
                socks.append(socket.create_connection(("127.0.0.1", rig.port), timeout=5))
        for s in socks:
            s.close()
        asyncio.run(_vanish(rig))
        # recovered: the same process serves a new session and still follows the service
        rig.service.mode = "HELD"
        deadline = time.monotonic() + 20
        state = None
        while time.monotonic() < deadline and state != 11:
            state = asyncio.run(_asyncua_read(rig, "PackML.Status.StateCurrent"))
        assert state == 11
        assert rig.server.proc is not None and rig.server.proc.pid == pid
        assert rig.server.restarts == 0
        assert rig.ctl.healthy


def _quick(result: tuple[str, float], code: str) -> None:
    """Refused with ``code``, and at once (not a client's 10 s timeout)."""
    assert result[0] == code and result[1] < 3.0, result


@pytest.mark.realtime
@pytest.mark.slow
def test_no_session_but_on_sign_and_encrypt_and_passwords_always_encrypted(
    tmp_path: Path,
) -> None:
    """A client that forces SecurityPolicy None or Sign (not asyncua's Client, which
    follows the endpoints): on None only discovery is answered, a session's requests with
    an operator's password in clear get Bad_SecurityModeRejected at once, and so does a
    Sign channel; the UserName token policy asks for the password encrypted, and a clear
    one on a SignAndEncrypt channel is refused."""
    from asyncua import Client, ua
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    from ipc_app.opcua import pki
    from tests import opcua_hostile_client as H

    with S.rig(tmp_path) as rig:
        op = ("op", S.PASSWORDS["op"])
        out = asyncio.run(H.session_on_none(rig.url, *op))
        for step in ("create", "activate", "read"):
            _quick(out[step], "BadSecurityModeRejected")
        assert out["endpoints_s"] < 3.0  # discovery on None still answered
        uri = SecurityPolicyBasic256Sha256.URI
        assert [(e.SecurityMode, e.SecurityPolicyUri) for e in out["endpoints"]] == [
            (ua.MessageSecurityMode.SignAndEncrypt, uri)
        ]
        tokens = out["endpoints"][0].UserIdentityTokens
        assert [(t.TokenType, t.SecurityPolicyUri) for t in tokens] == [
            (ua.UserTokenType.UserName, uri)
        ]
        _quick(
            asyncio.run(H.sign_channel(rig.url, pki.own_cert(rig.pki_dir), rig.cert, rig.key)),
            "BadSecurityModeRejected",
        )

        async def token_of_a_real_session() -> Any:
            c = Client(rig.url, timeout=10)
            c.application_uri = S.CLIENT_URI
            await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{rig.cert},{rig.key}")
            c.set_user(op[0])
            c.set_password(op[1])
            async with c:
                token = c.uaclient.protocol.authentication_token  # type: ignore[union-attr]
                # the same session activated again from a None channel: refused
                return await H.activate_on_none(rig.url, token, *op)

        _quick(asyncio.run(token_of_a_real_session()), "BadSecurityModeRejected")

        class ClearPassword(Client):  # sends the password as if the policy were #None
            def server_policy(self, token_type: ua.UserTokenType) -> ua.UserTokenPolicy:
                pol = super().server_policy(token_type)
                pol.SecurityPolicyUri = "http://opcfoundation.org/UA/SecurityPolicy#None"
                return pol

        async def clear_password() -> str:
            c = ClearPassword(rig.url, timeout=10)
            c.application_uri = S.CLIENT_URI
            await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{rig.cert},{rig.key}")
            c.set_user(op[0])
            c.set_password(op[1])
            try:
                await c.connect()
            except ua.UaStatusCodeError as exc:
                return str(ua.StatusCode(exc.code).name)
            await c.disconnect()
            return "ok"

        assert asyncio.run(clear_password()) == "BadIdentityTokenInvalid"
        assert rig.service.calls == []
        # a client that follows the endpoints still gets its session
        assert asyncio.run(_asyncua_read(rig, "PackML.Status.StateCurrent")) == 4


def _closed_within(s: socket.socket, timeout_s: float) -> bool:
    """The server closed ``s`` within ``timeout_s`` (EOF or a reset, after any bytes)."""
    s.settimeout(timeout_s)
    try:
        for _ in range(100):
            if not s.recv(4096):
                return True
    except ConnectionError:
        return True
    except TimeoutError:
        return False
    return False


@pytest.mark.realtime
@pytest.mark.slow
def test_silent_connections_do_not_lock_out_a_client(tmp_path: Path) -> None:
    """100 connections that never send Hello (32 allowed): a good client still connects
    and reads within a few seconds (the oldest silent one makes way), the silent ones are
    closed after ``hello_timeout_s``, one with Hello but no session after
    ``session_activate_timeout_s``."""
    import struct

    with S.rig(tmp_path, hello_timeout_s=1.0, session_activate_timeout_s=3.0) as rig:
        silent = [socket.create_connection(("127.0.0.1", rig.port), timeout=5) for _ in range(100)]
        try:
            t0 = time.monotonic()
            assert asyncio.run(_asyncua_read(rig, "PackML.Status.StateCurrent")) == 4
            assert time.monotonic() - t0 < 5.0
            t1 = time.monotonic()
            assert all(_closed_within(s, 3.0) for s in silent)  # evicted or timed out
            assert time.monotonic() - t1 < 4.0
        finally:
            for s in silent:
                s.close()
        url = rig.url.encode()
        body = struct.pack("<IIIII", 0, 65536, 65536, 0, 0) + struct.pack("<i", len(url)) + url
        with socket.create_connection(("127.0.0.1", rig.port), timeout=5) as s:
            s.sendall(b"HELF" + struct.pack("<I", 8 + len(body)) + body)
            assert s.recv(4)[:3] == b"ACK"
            t2 = time.monotonic()
            assert _closed_within(s, 6.0)
            assert 1.5 < time.monotonic() - t2 < 5.0  # session_activate_timeout_s, not Hello's
        assert rig.server.restarts == 0


@pytest.mark.slow
def test_a_killed_server_process_is_started_again(tmp_path: Path) -> None:
    with S.rig(tmp_path) as rig:
        assert rig.server.proc is not None
        os.kill(rig.server.proc.pid, signal.SIGKILL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and rig.server.restarts == 0:
            time.sleep(0.2)
        assert rig.server.restarts == 1
        assert asyncio.run(_asyncua_read(rig, "PackML.Status.StateCurrent")) == 4


@pytest.mark.slow  # subprocesses or a run of many seconds: not in the fast lane
def test_serve_with_opcua_and_no_users_file_is_one_line(tmp_path: Path) -> None:
    cfg = S.write_config(tmp_path, S.free_port())
    p = subprocess.run(
        [sys.executable, "-m", "wara", "serve", "--config", str(cfg),
         "--socket", str(tmp_path / "ctl.sock")],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert p.returncode == 2, p.stderr
    last = p.stderr.strip().splitlines()[-1]
    assert last.startswith("wara serve: error: the OPC UA server did not start: opcua: ")
    assert "no users file" in last and "wara opcua adduser" in last


class _ScriptedService:
    """The control socket's side `wara bench opcua`'s cycles use (``call``, ``wait``), its
    modes scripted: each adjust ends in the next of ``endings``."""

    def __init__(self, endings: list[dict[str, Any]]) -> None:
        self.endings, self.calls, self.mode = endings, [], "IDLE"
        self.last: dict[str, Any] = {"mode": "IDLE"}

    def call(self, cmd: str, **args: Any) -> dict[str, Any]:
        self.calls.append(cmd)
        after = {"adjust": None, "stop": "IDLE", "clear": "STOPPED", "reset": "IDLE"}[cmd]
        self.mode = after or "ADJUST"
        self.last = {"mode": self.mode}
        return {"ok": True}

    def status(self) -> dict[str, Any]:
        st = self.endings.pop(0) if self.mode == "ADJUST" else self.last
        self.mode, self.last = st["mode"], st
        return st

    def wait(self, pred: Any, timeout_s: float) -> dict[str, Any] | None:
        st = self.status()
        return st if pred(st) else None


def test_bench_opcua_runs_a_cycle_again_after_a_silent_process_stop_only(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A cycle the PLC stopped on a silent IPC is cleared, reset and run again, noted with
    its faults; past ``MAX_SILENT_STOPS`` in a run, or on any other fault, the bench fails
    with the cycle and its cause."""
    from ipc_app.service.interlocks import Interlock
    from plc_bridge.link import Fault
    from wara.benches import opcua as bench
    from wara.demo_two_process import TwoProcessError

    monkeypatch.setattr(bench.time, "sleep", lambda s: None)
    watch = SimpleNamespace(see=lambda st: None)
    silent_ipc = {"interlock": str(Interlock.PLC_FAULT), "where": Fault.IPC_TIMEOUT.name}
    ipc = {"mode": "ABORTED", "fault_reasons": ["plc fault: IPC_TIMEOUT"], "faults": [silent_ipc]}
    done = {"mode": "COMPLETE"}
    svc = _ScriptedService([done, ipc, done])
    silent: list[dict[str, Any]] = []
    bench._cycles(svc, watch, 2, lambda msg: None, silent=silent)
    assert svc.calls == ["adjust", "stop", "adjust", "clear", "reset", "adjust", "stop"]
    assert silent == [{"cycle": 1, "faults": ipc["faults"]}]
    svc = _ScriptedService([ipc] * (bench.MAX_SILENT_STOPS + 1))
    with pytest.raises(TwoProcessError, match=r"cycle 0: .*IPC_TIMEOUT"):
        bench._cycles(svc, watch, 1, lambda msg: None, silent=[])
    over = {"mode": "ABORTED", "fault_reasons": ["overload: sub_leg_1"],
            "faults": [{"interlock": str(Interlock.OVERLOAD), "where": "sub_leg_1"}]}  # fmt: skip
    with pytest.raises(TwoProcessError, match="overload"):
        bench._cycles(_ScriptedService([over]), watch, 1, lambda msg: None, silent=[])


@pytest.mark.realtime
@pytest.mark.slow
def test_bench_opcua_reports_the_loop_and_the_latency_with_its_parts() -> None:
    """`wara bench opcua --json --quick` as a commissioning engineer runs it: the three
    phases' loop figures, the latency of the clients' state notifications and the part of it
    before the server wrote the value, the server's feed reports, and the operator's method
    calls timed to their state notifications (no timing goal)."""
    from wara.benches.opcua import MAX_SILENT_STOPS
    from wara.demo_two_process import netns_problem, silent_process_stop

    why = netns_problem()
    if why is not None:
        pytest.skip(f"the two-process bench needs a private network namespace: {why}")
    run = subprocess.run(
        [sys.executable, "-m", "wara", "bench", "opcua", "--json", "--quick"],
        capture_output=True, text=True, timeout=900, check=False,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr[-3000:]
    out = json.loads(run.stdout)
    assert out["passed"] is True, out.get("error")
    for phase in ("without", "with", "same_load"):
        assert out[phase]["measured_cycles"] > 1000
    # --quick: one round; its ratios of the loop's compute p99, with/without and with/the
    # same CPU load from burners (the CPU share the server and the clients took)
    (rnd,) = out["rounds"]
    for key, base in (("compute_p99_ratio", "without"), ("same_load_ratio", "same_load")):
        assert out[key]["median"] == pytest.approx(
            rnd["with"]["compute_p99_ms"] / rnd[base]["compute_p99_ms"]
        )
    assert 0.0 < out["opcua_cpu_share"] == rnd["same_load"]["cpu_share"] < 2.0
    lat = out["latency_ms"]
    # 2 cycles of 4 changes; a STARTING shorter than the 100 ms publishing interval is
    # overwritten in the client's queue of one before it is sent
    assert lat["samples"] >= 2 * 2 * out["clients"]
    assert 0 < lat["to_server_p50"] <= lat["p50"] <= lat["p99"] <= lat["max"]
    assert out["server_feed"] and all(
        f["configured_period_ms"] == 50.0 and f["updates"] > 0 for f in out["server_feed"]
    )
    # the with phase's cycles driven by the operator's method calls: each StartAdjustment
    # and Stop timed from the call sent to its first state notification at that client
    call = out["call_latency_ms"]
    # a cycle stopped on a silent process (decision 0030) is run again: its adjust counted
    assert len(out["silent_stops"]) <= MAX_SILENT_STOPS
    assert all(silent_process_stop(stop["faults"]) for stop in out["silent_stops"])
    again = sum(1 for stop in out["silent_stops"] if stop["phase"] == "with")
    assert len(out["calls"]) == 2 * 2 + again and call["missed"] == 0
    assert call["samples"] == len(out["calls"]) and call["goal_p99_below"] == 200.0
    figures = [call[k] for k in ("p50", "p99", "max", "call_p50", "call_p99")]
    assert all(isinstance(x, float) and math.isfinite(x) and x > 0 for x in figures)
    assert call["p50"] <= call["p99"] <= call["max"]
    assert call["call_p50"] <= call["call_p99"]
    assert 0 < call["to_server_p50"] <= call["to_server_p99"]
    assert {m: f["samples"] for m, f in call["by_method"].items()} == {
        "StartAdjustment": 2 + again,
        "Stop": 2,
    }
    assert isinstance(out["latency_goal_met"], bool)
    assert isinstance(out["call_latency_goal_met"], bool)


@pytest.mark.realtime
@pytest.mark.slow
def test_demo_with_opcua_serves_the_demo_to_a_client_with_the_printed_credentials(
    tmp_path: Path,
) -> None:
    """`wara demo --opcua` as a commissioning engineer uses it: the printed endpoint, user
    and password file let a client (its certificate trusted as the printed line says)
    open a SignAndEncrypt session and follow the PackML state into Execute and the demo
    to its end. One example (``--examples 1``): the OPC UA side is the same for each, and a
    real-time run on a shared machine is exposed to its stalls for a third as long. On a
    failure the message carries the demo's loop and scheduler figures (``--json``). The
    project is the shipped one on a free port: the shipped 4840 may be taken on this
    machine (another run of this test, another server)."""
    import yaml
    from asyncua import Client

    from config.loader import default_project_path
    from ipc_app.opcua import pki

    cert, key = S.make_client_cert(tmp_path / "client")
    pki.trust(tmp_path / "opcua-demo" / "pki", cert)  # as `wara opcua cert --trust` does
    project = yaml.safe_load(default_project_path().read_text())
    project["opcua"]["port"] = S.free_port()
    config = tmp_path / "project.yaml"
    config.write_text(yaml.safe_dump(project))
    env = dict(os.environ, WARA_DATA_DIR=str(tmp_path))
    demo = subprocess.Popen(
        [sys.executable, "-m", "wara", "demo", "--attitude", "--opcua", "--examples", "1",
         "--json", "--config", str(config)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env,
    )  # fmt: skip
    assert demo.stderr is not None
    lines: list[str] = []
    named = threading.Event()
    found: dict[str, str] = {}

    def drain(stream: Any) -> None:  # all of it, so the demo never blocks on the pipe
        for line in stream:
            lines.append(line)
            if "OPC UA server: " in line:
                found["url"] = line.split("OPC UA server: ", 1)[1].split()[0]
            if "password in " in line:
                found["pw_file"] = line.rsplit("password in ", 1)[1].strip()
            if len(found) == 2:
                named.set()
        named.set()

    reader = threading.Thread(target=drain, args=(demo.stderr,), daemon=True)
    reader.start()
    out: list[str] = []
    assert demo.stdout is not None
    stdout_reader = threading.Thread(target=lambda: out.extend(demo.stdout), daemon=True)
    stdout_reader.start()
    named.wait(300.0)
    assert len(found) == 2, f"the demo did not name its endpoint: {lines[-20:]}"
    url, pw_file = found["url"], found["pw_file"]
    password = Path(pw_file).read_text(encoding="utf-8").strip()

    async def follow() -> list[int]:
        c = Client(url.replace("0.0.0.0", "127.0.0.1"), timeout=30)
        c.application_uri = S.CLIENT_URI
        await c.set_security_string(f"Basic256Sha256,SignAndEncrypt,{cert},{key}")
        c.set_user("operator")
        c.set_password(password)
        seen: list[int] = []
        async with c:
            ns = await c.get_namespace_index("urn:wara:ipc")
            node = c.get_node(f"ns={ns};s=W-ARa.PackML.Status.StateCurrent")
            end = time.monotonic() + 240.0
            while time.monotonic() < end and 6 not in seen:
                seen.append(int(await node.read_value()))
                await asyncio.sleep(0.2)
        return seen

    try:
        seen = asyncio.run(follow())
        demo.wait(timeout=600)
    finally:
        if demo.poll() is None:
            demo.kill()
            demo.wait()
        reader.join(10.0)
        stdout_reader.join(10.0)
    assert 6 in seen, seen  # Execute, while the demo's first example runs
    summary = json.loads("".join(out))
    figures = {k: summary.get(k) for k in ("loop", "realtime", "fault_reasons")}
    assert demo.returncode == 0, f"{figures}\n" + "".join(lines[-20:])
    assert summary["passed"] is True and len(summary["examples"]) == 1


# ---------------------------------------------------------------------- the process


def test_server_process_starts_under_the_normal_scheduler() -> None:
    """The server process (and a restart of it) starts under the normal scheduler even
    when spawned from a SCHED_FIFO thread of the service."""
    from ipc_app.opcua.process import OpcUaProcess

    proc = OpcUaProcess(None, "/nonexistent.sock")
    proc.argv = [sys.executable, "-c", "import time; time.sleep(30)"]
    spawned: list[subprocess.Popen[str]] = []
    fifo: list[bool] = []

    def spawn_as_fifo() -> None:
        # as a restart from a SCHED_FIFO thread of the service would
        with contextlib.suppress(OSError, AttributeError):
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            fifo.append(True)
        spawned.append(proc._spawn())

    t = threading.Thread(target=spawn_as_fifo)
    t.start()
    t.join()
    child = spawned[0]
    try:
        if not fifo:
            pytest.skip("SCHED_FIFO refused here: nothing to inherit")
        assert os.sched_getscheduler(child.pid) == os.SCHED_OTHER
    finally:
        child.kill()
        child.wait()
