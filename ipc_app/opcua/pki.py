"""The OPC UA server's PKI directory (``opcua.pki_dir``)::

    own/cert.der    the server's application instance certificate (self-signed, RSA 2048)
    own/key.pem     its private key (0600)
    trusted/        client certificates the server accepts (DER or PEM), one per file

``wara opcua cert`` creates the server certificate (``deploy/install.sh`` runs it) and
``wara opcua cert --trust FILE`` copies a client's certificate into ``trusted/``. A
client whose certificate is not there is refused (BadSecurityChecksFailed).

Needs the ``opcua`` extra (cryptography, which asyncua brings).
"""

from __future__ import annotations

import ipaddress
import os
import shutil
import socket
from pathlib import Path

APP_URI_PREFIX = "urn:wara:ipc:opcua:"
CERT_DAYS = 3650


class PkiError(Exception):
    """A certificate or the PKI directory cannot be used (one line)."""


def application_uri(hostname: str | None = None) -> str:
    return APP_URI_PREFIX + (hostname or socket.gethostname())


def own_cert(pki_dir: str | Path) -> Path:
    return Path(pki_dir) / "own" / "cert.der"


def own_key(pki_dir: str | Path) -> Path:
    return Path(pki_dir) / "own" / "key.pem"


def trusted_dir(pki_dir: str | Path) -> Path:
    return Path(pki_dir) / "trusted"


def create_server_cert(
    pki_dir: str | Path, *, hostnames: list[str] | None = None, force: bool = False
) -> Path:
    """Write ``own/cert.der`` and ``own/key.pem`` (kept when present unless ``force``)."""
    from asyncua.crypto import cert_gen
    from cryptography import x509
    from cryptography.x509.oid import ExtendedKeyUsageOID

    cert, key = own_cert(pki_dir), own_key(pki_dir)
    if cert.exists() and key.exists() and not force:
        return cert
    host = socket.gethostname()
    names = [host, "localhost", *(hostnames or [])]
    alt: list[x509.GeneralName] = [x509.UniformResourceIdentifier(application_uri(host))]
    for n in dict.fromkeys(names):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(n)))
        except ValueError:
            alt.append(x509.DNSName(n))
    alt.append(x509.IPAddress(ipaddress.ip_address("127.0.0.1")))
    private = cert_gen.generate_private_key()
    c = cert_gen.generate_self_signed_app_certificate(
        private,
        f"W-ARa IPC OPC UA server@{host}",
        {"organizationName": "W-ARa"},
        alt,
        extended=[ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH],
        days=CERT_DAYS,
    )
    from cryptography.hazmat.primitives.serialization import Encoding

    for d in (cert.parent, trusted_dir(pki_dir)):
        d.mkdir(parents=True, exist_ok=True, mode=0o700)
    fd = os.open(key, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(cert_gen.dump_private_key_as_pem(private))
    cert.write_bytes(c.public_bytes(Encoding.DER))
    return cert


def trust(pki_dir: str | Path, cert_file: str | Path) -> Path:
    """Copy a client certificate (DER or PEM) into ``trusted/`` after reading it."""
    from cryptography import x509

    src = Path(cert_file)
    try:
        data = src.read_bytes()
    except OSError as exc:
        raise PkiError(f"{src}: {exc.strerror or exc}") from None
    try:
        (
            x509.load_pem_x509_certificate
            if b"-----BEGIN" in data
            else x509.load_der_x509_certificate
        )(data)
    except ValueError as exc:
        raise PkiError(f"{src}: not an X.509 certificate: {exc}") from None
    dst_dir = trusted_dir(pki_dir)
    dst_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
    dst = dst_dir / src.name
    shutil.copyfile(src, dst)
    return dst


def client_cert(out_dir: str | Path, name: str, uri: str) -> tuple[Path, Path]:
    """A client application certificate and its key (both PEM) for ``uri`` (for test and
    benchmark clients; a real client makes its own)."""
    from asyncua.crypto import cert_gen
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding
    from cryptography.x509.oid import ExtendedKeyUsageOID

    key = cert_gen.generate_private_key()
    cert = cert_gen.generate_self_signed_app_certificate(
        key,
        name,
        {},
        [x509.UniformResourceIdentifier(uri), x509.DNSName("localhost")],
        extended=[ExtendedKeyUsageOID.CLIENT_AUTH],
    )
    d = Path(out_dir)
    d.mkdir(parents=True, exist_ok=True, mode=0o700)
    c, k = d / f"{name}.pem", d / f"{name}-key.pem"
    c.write_bytes(cert.public_bytes(Encoding.PEM))
    fd = os.open(k, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(cert_gen.dump_private_key_as_pem(key))
    return c, k
