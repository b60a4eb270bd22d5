"""``wara serve``: run the IPC service (what the systemd unit starts), and beside it, in
its own process, the OPC UA server when the project's ``opcua.enabled`` (docs/opcua.md)."""

from __future__ import annotations

import argparse

from config.numbers import decimal
from ipc_app.service.app import StartupError, run_service
from wara.cli import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("serve", help="run the IPC service: CAN link, planner, control loop")
    p.add_argument("--config", default=None, help="project YAML (default: shipped project)")
    p.add_argument("--socket", default=None, help="control socket path (default: see docs)")
    p.add_argument(
        "--duration-s",
        type=decimal,
        default=None,
        help="stop after this long (for test runs; default: until SIGTERM)",
    )
    p.add_argument(
        "--record-dir",
        default=None,
        help="where run records go (default: $STATE_DIRECTORY/runs or ./wara-data/runs)",
    )
    p.add_argument("--log-level", default="INFO", choices=["DEBUG", "INFO", "WARNING", "ERROR"])
    p.add_argument(
        "--db",
        default=None,
        metavar="PATH",
        help="acceptance store of the ring cycle's records "
        "(default $WARA_DATA_DIR/acceptance.sqlite)",
    )
    p.set_defaults(func=_run)


def _run(args: argparse.Namespace) -> int:
    from pathlib import Path

    from acceptance.store import StoreError, check_store, default_db_path
    from config import load_project
    from wara.ring_records import StoreRecords

    db = Path(args.db) if args.db else default_db_path()
    try:  # before the bus, the socket and the OPC UA server: the records' store
        check_store(db, create=True)
    except StoreError as exc:
        raise UsageError(str(exc)) from None
    opcua = None
    if load_project(args.config).opcua.enabled:
        from ipc_app.opcua.process import OpcUaProcess, OpcUaStartError
        from ipc_app.service.ctl import default_socket_path

        opcua = OpcUaProcess(args.config, args.socket or default_socket_path())
        try:
            opcua.start()
        except OpcUaStartError as exc:
            raise UsageError(str(exc)) from None
    try:
        return run_service(
            args.config,
            socket_path=args.socket,
            duration_s=args.duration_s,
            record_root=args.record_dir,
            log_level=args.log_level,
            ring_records=StoreRecords(db, operator="wara serve (ring cycle)"),
        )
    except StartupError as exc:  # bus, socket or record directory: one line, exit 2
        raise UsageError(str(exc)) from None
    finally:
        if opcua is not None:
            opcua.stop()
