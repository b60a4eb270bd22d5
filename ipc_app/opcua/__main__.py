"""``python -m ipc_app.opcua --config PATH --socket PATH``: the OPC UA server process.

Prints ``READY <endpoint URL>`` on stdout once it listens; logs are JSON lines on
stderr. Exit 2 with one line when it cannot start (users file, certificate, port).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import signal
import sys
from typing import Any

from config import ConfigError, load_project


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m ipc_app.opcua")
    p.add_argument("--config", default=None)
    p.add_argument("--socket", default=None, help="the service's control socket")
    p.add_argument("--host", default=None)
    p.add_argument("--port", type=int, default=None)
    p.add_argument("--users-file", default=None)
    p.add_argument("--pki-dir", default=None)
    p.add_argument("--log-level", default="INFO")
    args = p.parse_args(argv)
    try:
        cfg = load_project(args.config)
    except ConfigError as exc:
        print(f"opcua: configuration error: {exc}", file=sys.stderr)
        return 2
    over: dict[str, Any] = {
        k: v
        for k, v in (
            ("host", args.host),
            ("port", args.port),
            ("users_file", args.users_file),
            ("pki_dir", args.pki_dir),
        )
        if v is not None
    }
    opc = cfg.opcua.model_copy(update=over)
    try:
        from ipc_app.opcua.server import OpcUaError, OpcUaServer, quiet_asyncua
    except ImportError as exc:
        print(
            f"opcua: the OPC UA server needs the opcua extra (pip install -e '.[opcua]'): {exc}",
            file=sys.stderr,
        )
        return 2
    from ipc_app.service.logs import configure_logging

    handle = configure_logging(args.log_level)
    quiet_asyncua()

    def ready(url: str) -> None:
        print(f"READY {url}", flush=True)

    async def run() -> None:
        srv = OpcUaServer(cfg, args.socket, opc=opc)
        task = asyncio.ensure_future(srv.serve(ready))
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, task.cancel)
        with contextlib.suppress(asyncio.CancelledError):
            await task

    try:
        asyncio.run(run())
    except OpcUaError as exc:
        print(f"opcua: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the port in use, the host unknown
        print(
            f"opcua: cannot listen on {opc.host}:{opc.port}: {exc.strerror or exc}", file=sys.stderr
        )
        return 2
    finally:
        handle.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
