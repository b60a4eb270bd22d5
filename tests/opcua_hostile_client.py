"""A client that does what asyncua's ``Client`` will not: open a SecurityPolicy None or a
Sign-only channel whatever the endpoints say, and ask on it for a session with an
operator's password in clear (asyncua's low-level ``UaClient``, no endpoint selection).

Each function returns what the server answered: ``"ok"`` or the status code's name
(``BadSecurityModeRejected``, ...), and the seconds it took to answer.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

from asyncua import ua
from asyncua.client.ua_client import UaClient
from asyncua.common.utils import create_nonce
from asyncua.crypto import uacrypto
from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256, SecurityPolicyNone

TIMEOUT_S = 10.0


def _code(exc: BaseException) -> str:
    if isinstance(exc, ua.UaStatusCodeError):
        return str(ua.StatusCode(exc.code).name)
    return type(exc).__name__


async def _channel(url: str, mode: ua.MessageSecurityMode, policy: Any) -> UaClient:
    u = urlparse(url)
    uc = UaClient(timeout=TIMEOUT_S)
    uc.set_security(policy)
    assert u.hostname is not None and u.port is not None
    await uc.connect_socket(u.hostname, u.port)
    await uc.send_hello(url)
    p = ua.OpenSecureChannelParameters()
    p.ClientProtocolVersion = 0
    p.RequestType = ua.SecurityTokenRequestType.Issue
    p.SecurityMode = mode
    p.RequestedLifetime = 60_000
    p.ClientNonce = create_nonce(policy.secure_channel_nonce_length)
    await uc.open_secure_channel(p)
    return uc


async def none_channel(url: str) -> UaClient:
    """A channel with SecurityPolicy None (as for discovery)."""
    return await _channel(url, ua.MessageSecurityMode.None_, SecurityPolicyNone())


async def sign_channel(url: str, server_cert: Path, cert: Path, key: Path) -> tuple[str, float]:
    """Open a Basic256Sha256 Sign (not Encrypt) channel: the server's answer and its time."""
    policy = SecurityPolicyBasic256Sha256(
        await uacrypto.load_certificate(server_cert),
        await uacrypto.load_certificate(cert),
        await uacrypto.load_private_key(key),
        ua.MessageSecurityMode.Sign,
    )
    t0 = time.monotonic()
    try:
        uc = await _channel(url, ua.MessageSecurityMode.Sign, policy)
    except Exception as exc:
        return _code(exc), time.monotonic() - t0
    uc.disconnect_socket()
    return "ok", time.monotonic() - t0


def _create_params(url: str) -> ua.CreateSessionParameters:
    p = ua.CreateSessionParameters()
    desc = ua.ApplicationDescription()
    desc.ApplicationUri = "urn:wara:test:hostile"
    desc.ApplicationName = ua.LocalizedText("hostile")
    desc.ApplicationType = ua.ApplicationType.Client
    p.ClientDescription = desc
    p.EndpointUrl = url
    p.SessionName = "hostile"
    p.ClientNonce = create_nonce(32)
    p.RequestedSessionTimeout = 60_000
    p.MaxResponseMessageSize = 0
    return p


def _activate_params(user: str, password: str) -> ua.ActivateSessionParameters:
    p = ua.ActivateSessionParameters()
    p.LocaleIds = ["en"]
    tok = ua.UserNameIdentityToken()
    tok.PolicyId = "username"
    tok.UserName = user
    tok.Password = password.encode()  # in clear: the attack
    tok.EncryptionAlgorithm = None
    p.UserIdentityToken = tok
    p.ClientSignature = ua.SignatureData()
    return p


async def timed(coro: Any) -> tuple[str, float]:
    t0 = time.monotonic()
    try:
        await coro
    except Exception as exc:
        return _code(exc), time.monotonic() - t0
    return "ok", time.monotonic() - t0


async def session_on_none(url: str, user: str, password: str) -> dict[str, Any]:
    """On a None channel: CreateSession, ActivateSession (with the password in clear,
    without a session created and with ``auth_token`` if given), a Read, then
    GetEndpoints; each request's answer and time."""
    uc = await none_channel(url)
    out: dict[str, Any] = {}
    try:
        out["create"] = await timed(uc.create_session(_create_params(url)))
        out["activate"] = await timed(uc.activate_session(_activate_params(user, password)))
        rp = ua.ReadParameters()
        rv = ua.ReadValueId()
        rv.NodeId = ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)  # type: ignore[arg-type]
        rv.AttributeId = ua.AttributeIds.Value
        rp.NodesToRead = [rv]
        out["read"] = await timed(uc.read(rp))
        gp = ua.GetEndpointsParameters()
        gp.EndpointUrl = url
        t0 = time.monotonic()
        out["endpoints"] = await uc.get_endpoints(gp)
        out["endpoints_s"] = time.monotonic() - t0
    finally:
        uc.disconnect_socket()
    return out


async def activate_on_none(url: str, auth_token: ua.NodeId, user: str, password: str) -> Any:
    """ActivateSession on a None channel for a session made on a secure one (asyncua's
    reconnect path looks a session up by its authentication token)."""
    uc = await none_channel(url)
    try:
        uc.protocol.authentication_token = auth_token  # type: ignore[union-attr]
        return await timed(uc.activate_session(_activate_params(user, password)))
    finally:
        uc.disconnect_socket()
