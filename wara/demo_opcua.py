"""``wara demo --opcua``: the OPC UA server beside the demo's service for its duration.

The demo's service core gets a control socket (the service's own handlers,
:func:`ipc_app.service.app.service_handlers`) and the OPC UA server process is started on
it, with a users file holding one demo operator (a fresh random password each run, in a
0600 file) and a server certificate, under ``wara-data/opcua-demo/`` (``$WARA_DATA_DIR``
if set). The progress lines give the endpoint URL, the user and the password file; a
client's certificate must be trusted first (``wara opcua cert --trust``; the line says
how).
"""

from __future__ import annotations

import contextlib
import os
import secrets
from collections.abc import Callable, Iterator
from pathlib import Path

from ipc_app.service.core import ServiceCore
from ipc_app.service.ctl import CtlServer
from ipc_app.service.loop import SlackGate

DEMO_USER = "operator"


def demo_dir() -> Path:
    return Path(os.environ.get("WARA_DATA_DIR") or "wara-data") / "opcua-demo"


@contextlib.contextmanager
def serve_opcua(
    core: ServiceCore,
    config_path: str | None,
    say: Callable[[str], None],
    slack: SlackGate | None = None,
) -> Iterator[str]:
    from ipc_app.opcua import pki
    from ipc_app.opcua.process import OpcUaProcess
    from ipc_app.opcua.users import add_user
    from ipc_app.service.app import service_handlers

    root = demo_dir().resolve()
    root.mkdir(parents=True, exist_ok=True, mode=0o700)
    users, pki_dir, pw_file = root / "users.json", root / "pki", root / f"{DEMO_USER}.password"
    password = secrets.token_urlsafe(12)
    add_user(users, DEMO_USER, "operator", password)
    fd = os.open(pw_file, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w") as f:
        f.write(password + "\n")
    pki.create_server_cert(pki_dir)
    ctl = CtlServer(service_handlers(lambda: core, lambda: ctl, slack=slack), root / "ctl.sock")
    ctl.bind()
    ctl.start()
    proc = OpcUaProcess(
        config_path,
        root / "ctl.sock",
        ["--users-file", str(users), "--pki-dir", str(pki_dir)],
    )
    try:
        url = proc.start()
        say(f"OPC UA server: {url} (SignAndEncrypt, {core.cfg.opcua.security_policy})")
        say(f"OPC UA user {DEMO_USER!r}, password in {pw_file}")
        say(
            f"trust your client's certificate first: wara opcua cert --pki-dir {pki_dir} "
            "--trust CLIENT_CERT.der"
        )
        yield url
    finally:
        proc.stop()
        ctl.stop()
