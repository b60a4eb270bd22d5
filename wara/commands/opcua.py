"""``wara opcua adduser|cert``: set up the OPC UA server (docs/opcua.md).

``adduser NAME --role viewer|operator|engineer`` adds or replaces a user in the users
file (``opcua.users_file``, created 0600; the password from ``--password-stdin`` or asked
twice). ``cert`` creates the server certificate under ``opcua.pki_dir`` (kept when present
unless ``--force``); ``cert --trust FILE`` adds a client's certificate to the trust store.
"""

from __future__ import annotations

import argparse
import getpass
import sys

from config.schema import OpcUa
from wara.cli import UsageError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("opcua", help="OPC UA server set-up: users and certificates")
    verbs = p.add_subparsers(dest="verb", metavar="VERB")
    verbs.required = True
    a = verbs.add_parser("adduser", help="add or replace a user (scrypt hash, file 0600)")
    a.add_argument("name")
    a.add_argument("--role", required=True, choices=("viewer", "operator", "engineer"))
    a.add_argument("--config", default=None, help="project YAML (its opcua.users_file)")
    a.add_argument("--users-file", default=None, help="instead of opcua.users_file")
    a.add_argument("--password-stdin", action="store_true", help="read the password from stdin")
    a.set_defaults(func=_adduser)
    c = verbs.add_parser("cert", help="create the server certificate; --trust adds a client's")
    c.add_argument("--config", default=None, help="project YAML (its opcua.pki_dir)")
    c.add_argument("--pki-dir", default=None, help="instead of opcua.pki_dir")
    c.add_argument("--hostname", action="append", default=[], help="another name of this host")
    c.add_argument("--force", action="store_true", help="replace an existing certificate")
    c.add_argument("--trust", default=None, metavar="FILE", help="a client certificate to trust")
    c.set_defaults(func=_cert)


def _opc(config: str | None) -> OpcUa:
    from config import load_project

    return load_project(config).opcua


def _adduser(args: argparse.Namespace) -> int:
    from ipc_app.opcua.users import UsersError, add_user

    path = args.users_file or _opc(args.config).users_file
    if args.password_stdin:
        password = sys.stdin.readline().rstrip("\n")
    elif not sys.stdin.isatty():
        raise UsageError(
            "no terminal to ask the password on: pass it on stdin with --password-stdin"
        )
    else:
        try:
            password = getpass.getpass(f"password for {args.name}: ")
            again = getpass.getpass("again: ")
        except (EOFError, KeyboardInterrupt):
            raise UsageError("no password given") from None
        if again != password:
            raise UsageError("the two passwords differ")
    try:
        new = add_user(path, args.name, args.role, password)
    except UsersError as exc:
        raise UsageError(str(exc)) from None
    print(f"{'added' if new else 'replaced'} {args.name} ({args.role}) in {path}")
    return 0


def _cert(args: argparse.Namespace) -> int:
    try:
        from ipc_app.opcua import pki
    except ImportError:
        raise UsageError("install with pip install -e '.[opcua]'") from None
    pki_dir = args.pki_dir or _opc(args.config).pki_dir
    try:
        if args.trust:
            print(f"trusted {pki.trust(pki_dir, args.trust)}")
            return 0
        existed = pki.own_cert(pki_dir).exists() and not args.force
        cert = pki.create_server_cert(pki_dir, hostnames=args.hostname, force=args.force)
    except ImportError:
        raise UsageError("install with pip install -e '.[opcua]'") from None
    except (pki.PkiError, OSError) as exc:
        raise UsageError(str(exc)) from None
    print(f"{'kept' if existed else 'created'} {cert} (trust store: {pki.trusted_dir(pki_dir)})")
    return 0
