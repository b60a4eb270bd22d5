"""The OPC UA server's users: names, roles and scrypt password hashes in a JSON file
outside the project YAML, readable by the service's user only (mode 0600).

Roles: ``viewer`` browses, reads and subscribes; ``operator`` also calls the methods
(start, stop, hold, unhold, reset); ``engineer`` may do what an operator may.
``wara opcua adduser`` writes the file (:func:`add_user`); the server loads it once at
start (:func:`load_users`) and checks each password with :meth:`Users.check`.
"""

from __future__ import annotations

import contextlib
import hashlib
import hmac
import json
import os
import re
import secrets
import stat
from dataclasses import dataclass
from pathlib import Path

ROLES = ("viewer", "operator", "engineer")
#: Roles that may call the methods that move or stop the machine.
CONTROL_ROLES = frozenset({"operator", "engineer"})
#: scrypt parameters (RFC 7914): 16 MiB of memory and about 50 ms per check here
SCRYPT_N, SCRYPT_R, SCRYPT_P = 2**14, 8, 1
NAME_RE = re.compile(r"^[A-Za-z0-9_.@-]{1,40}$")
MIN_PASSWORD_CHARS = 8


class UsersError(Exception):
    """The users file cannot be used (one line: the file and what is wrong)."""


@dataclass(frozen=True)
class User:
    name: str
    role: str
    salt: bytes
    digest: bytes
    n: int = SCRYPT_N
    r: int = SCRYPT_R
    p: int = SCRYPT_P

    def to_json(self) -> dict[str, object]:
        return {
            "role": self.role,
            "scrypt": {
                "salt": self.salt.hex(),
                "hash": self.digest.hex(),
                "n": self.n,
                "r": self.r,
                "p": self.p,
            },
        }


def _hash(password: str, salt: bytes, n: int, r: int, p: int) -> bytes:
    return hashlib.scrypt(password.encode(), salt=salt, n=n, r=r, p=p, maxmem=2**26, dklen=32)


def make_user(name: str, role: str, password: str) -> User:
    if not NAME_RE.match(name):
        raise UsersError(f"user name {name!r}: 1-40 of letters, digits and _ . @ -")
    if role not in ROLES:
        raise UsersError(f"role {role!r}: one of {', '.join(ROLES)}")
    if len(password) < MIN_PASSWORD_CHARS:
        raise UsersError(f"password: at least {MIN_PASSWORD_CHARS} characters")
    salt = secrets.token_bytes(16)
    return User(name, role, salt, _hash(password, salt, SCRYPT_N, SCRYPT_R, SCRYPT_P))


@dataclass(frozen=True)
class Users:
    by_name: dict[str, User]

    def check(self, name: str | None, password: str | None) -> User | None:
        """The user when the password is theirs, else None (same work either way)."""
        user = self.by_name.get(name or "")
        if user is None or password is None:
            _hash(password or "", b"\0" * 16, SCRYPT_N, SCRYPT_R, SCRYPT_P)  # no timing hint
            return None
        got = _hash(password, user.salt, user.n, user.r, user.p)
        return user if hmac.compare_digest(got, user.digest) else None


def load_users(path: str | Path) -> Users:
    """Read the users file; refused when others than its owner may read it."""
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise UsersError(
            f"{p}: no users file (create it with `wara opcua adduser NAME --role operator`)"
        ) from None
    except OSError as exc:
        raise UsersError(f"{p}: {exc.strerror or exc}") from None
    if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise UsersError(f"{p}: mode {stat.S_IMODE(st.st_mode):04o}, must be 0600 (chmod 600 {p})")
    try:
        data = json.loads(p.read_text())
        users = {}
        for name, entry in data["users"].items():
            sc = entry["scrypt"]
            if entry["role"] not in ROLES or not NAME_RE.match(name):
                raise ValueError(f"user {name!r}: bad name or role {entry['role']!r}")
            users[name] = User(
                name,
                entry["role"],
                bytes.fromhex(sc["salt"]),
                bytes.fromhex(sc["hash"]),
                int(sc["n"]),
                int(sc["r"]),
                int(sc["p"]),
            )
    except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise UsersError(f"{p}: not a users file: {exc}") from None
    return Users(users)


def add_user(path: str | Path, name: str, role: str, password: str) -> bool:
    """Add or replace ``name`` in the users file (created 0600); True if it was new."""
    p = Path(path)
    user = make_user(name, role, password)
    existing = load_users(p).by_name if p.exists() else {}
    new = name not in existing
    existing[name] = user
    p.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
    text = json.dumps({"users": {k: u.to_json() for k, u in sorted(existing.items())}}, indent=2)
    tmp = p.with_name(p.name + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    try:
        with os.fdopen(fd, "w") as f:
            f.write(text + "\n")
        os.chmod(tmp, 0o600)
        os.replace(tmp, p)
    finally:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
    return new
