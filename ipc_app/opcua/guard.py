"""What asyncua's server lets through and W-ARa's must not (docs/hostile-input.md, OPC UA).

asyncua keeps a SecurityPolicy None channel for discovery whatever the endpoints say, and
on it creates and activates sessions (a password in clear, every value readable); it
answers a Sign-only OpenSecureChannel with silence (the client waits out its timeout);
and a connection that never sends Hello holds one of ``max_connections`` for good. Here:

- a channel is opened only as None (discovery: GetEndpoints and FindServers, nothing
  else) or as SignAndEncrypt with the configured policy; any other OpenSecureChannel is
  answered at once with an Error message (``Bad_SecurityModeRejected``, an unknown
  policy ``Bad_SecurityPolicyRejected``) and the connection closed;
- every other request on a None channel, CreateSession and ActivateSession first, gets a
  ServiceFault ``Bad_SecurityModeRejected``;
- the UserName token policy asks for the password encrypted with the server's policy
  (not ``#None``), and a UserName token with a clear password is refused;
- a connection without Hello after ``opcua.hello_timeout_s`` is closed, one without an
  activated session after ``opcua.session_activate_timeout_s`` too (asyncua's own
  activation watchdog), and at ``max_connections`` a new connection evicts the oldest one
  that has not got that far (no Hello first, then no activated session), so silent
  sockets cannot lock out a client that completes its handshake.
"""

from __future__ import annotations

import asyncio
import socket
import time
from dataclasses import dataclass
from typing import Any

import structlog
from asyncua import Server, ua
from asyncua.common.utils import Buffer, ServiceError
from asyncua.crypto import uacrypto
from asyncua.crypto.security_policies import SecurityPolicyNone
from asyncua.server.binary_server_asyncio import BinaryServer, OPCUAProtocol
from asyncua.server.uaprocessor import UaProcessor
from asyncua.ua.ua_binary import struct_from_binary, uatcp_to_binary

log = structlog.get_logger("wara.opcua.guard")

NONE_URI = SecurityPolicyNone.URI
#: The requests served on a None channel (discovery).
DISCOVERY = frozenset(
    ua.NodeId(t)  # type: ignore[arg-type]
    for t in (
        ua.ObjectIds.GetEndpointsRequest_Encoding_DefaultBinary,
        ua.ObjectIds.FindServersRequest_Encoding_DefaultBinary,
        ua.ObjectIds.CloseSecureChannelRequest_Encoding_DefaultBinary,
    )
)
#: Refusals of one kind are logged at most once per this many seconds (with a count).
LOG_EVERY_S = 10.0


@dataclass(frozen=True)
class Guard:
    """The settings the connections are held to."""

    policy_uris: frozenset[str]  #: the configured policies (SignAndEncrypt only)
    hello_timeout_s: float


class _Refused(Exception):
    def __init__(self, code: int, why: str) -> None:
        super().__init__(why)
        self.code = code


class _Counts:
    """Counts refusals per kind; logs the first of a kind and then every LOG_EVERY_S."""

    def __init__(self) -> None:
        self.n: dict[str, int] = {}
        self.logged: dict[str, float] = {}

    def note(self, kind: str, **fields: Any) -> None:
        self.n[kind] = self.n.get(kind, 0) + 1
        now = time.monotonic()
        if now - self.logged.get(kind, -LOG_EVERY_S) >= LOG_EVERY_S:
            self.logged[kind] = now
            log.warning(kind, count=self.n[kind], **fields)


COUNTS = _Counts()


class _Processor(UaProcessor):
    """asyncua's processor, held to :class:`Guard`."""

    def __init__(self, guard: Guard, *args: Any) -> None:
        super().__init__(*args)
        self.guard = guard
        self.hello_done = False

    def _secure(self) -> bool:
        p = self._connection.security_policy
        return p.Mode == ua.MessageSecurityMode.SignAndEncrypt and p.URI in self.guard.policy_uris

    def _send_error(self, code: int, why: str) -> None:
        err = ua.ErrorMessage(ua.StatusCode(code), why)  # type: ignore[arg-type]
        self._transport.write(uatcp_to_binary(ua.MessageType.Error, err))  # type: ignore[arg-type]

    async def process(self, header: Any, body: Buffer) -> bool:
        try:
            if header.MessageType == ua.MessageType.Hello:
                self.hello_done = True
            elif not self.hello_done:
                raise _Refused(ua.StatusCodes.BadTcpMessageTypeInvalid, "no Hello first")
            elif header.MessageType == ua.MessageType.SecureOpen and not self._connection.is_open():
                algo = struct_from_binary(ua.AsymmetricAlgorithmHeader, body.copy(header.body_size))
                uri = algo.SecurityPolicyURI
                if uri != NONE_URI and uri not in self.guard.policy_uris:
                    raise _Refused(
                        ua.StatusCodes.BadSecurityPolicyRejected, f"security policy {uri} refused"
                    )
            return bool(await super().process(header, body))
        except _Refused as exc:
            COUNTS.note("opcua_connection_refused", peer=str(self.name), reason=str(exc))
            self._send_error(exc.code, str(exc))
            return False

    def open_secure_channel(self, algohdr: Any, seqhdr: Any, body: Buffer) -> None:
        if not self._connection.is_open():
            req = struct_from_binary(ua.OpenSecureChannelRequest, body.copy())
            mode = req.Parameters.SecurityMode
            uri = algohdr.SecurityPolicyURI
            ok = (uri == NONE_URI and mode == ua.MessageSecurityMode.None_) or (
                uri in self.guard.policy_uris and mode == ua.MessageSecurityMode.SignAndEncrypt
            )
            if not ok:
                raise _Refused(
                    ua.StatusCodes.BadSecurityModeRejected,
                    f"security mode {mode.name} with {uri.rsplit('#', 1)[-1]} refused:"
                    " SignAndEncrypt only (None for discovery)",
                )
        super().open_secure_channel(algohdr, seqhdr, body)

    async def _process_message(self, typeid: Any, requesthdr: Any, seqhdr: Any, body: Any) -> Any:
        if typeid not in DISCOVERY and not self._secure():
            COUNTS.note(
                "opcua_insecure_request_refused",
                peer=str(self.name),
                request=ua.ObjectIdNames.get(typeid.Identifier, str(typeid.Identifier)),
            )
            raise ServiceError(ua.StatusCodes.BadSecurityModeRejected)
        return await super()._process_message(typeid, requesthdr, seqhdr, body)


class _Protocol(OPCUAProtocol):
    """One connection: closed without Hello after ``hello_timeout_s``; at
    ``max_connections`` the oldest connection not yet as far as an activated session
    makes way for it."""

    def __init__(self, guard: Guard, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.guard = guard
        self.opened_s = time.monotonic()
        self._hello_timer: asyncio.TimerHandle | None = None

    def stage(self) -> int:
        """0 no Hello yet, 1 no activated session yet, 2 a session activated."""
        p = self.processor
        if not isinstance(p, _Processor) or not p.hello_done:
            return 0
        return 2 if p.session is not None and p.session.is_activated() else 1

    def evict(self, why: str) -> None:
        COUNTS.note("opcua_connection_closed", peer=str(self.peer_name), reason=why)
        if self in self.clients:
            self.clients.remove(self)
        if self.transport is not None:
            self.transport.abort()

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.peer_name = transport.get_extra_info("peername")
        if len(self.clients) >= self.iserver.max_connections:
            pending = [c for c in self.clients if isinstance(c, _Protocol) and c.stage() < 2]
            if not pending:
                COUNTS.note(
                    "opcua_connection_closed",
                    peer=str(self.peer_name),
                    reason=f"max_connections ({self.iserver.max_connections}) sessions active",
                )
                transport.close()
                return
            oldest = min(pending, key=lambda c: (c.stage(), c.opened_s))
            oldest.evict(f"evicted at max_connections ({self.iserver.max_connections})")
        self.transport = transport  # type: ignore[assignment]
        self.processor = _Processor(self.guard, self.iserver, self.transport, self.limits)
        self.processor.set_policies(self.policies)
        self.iserver.asyncio_transports.append(transport)
        self.clients.append(self)
        self._task = asyncio.create_task(self._process_received_message_loop())
        loop = asyncio.get_running_loop()
        self._hello_timer = loop.call_later(self.guard.hello_timeout_s, self._hello_overdue)
        if self.iserver.max_pending_activation_seconds > 0:
            self._activation_watchdog_task = asyncio.create_task(self._activation_watchdog())

    def _hello_overdue(self) -> None:
        if self.stage() == 0 and self.transport is not None:
            self.evict(f"no Hello within {self.guard.hello_timeout_s:g} s")

    def connection_lost(self, ex: BaseException | None) -> None:
        if self._hello_timer is not None:
            self._hello_timer.cancel()
        super().connection_lost(ex)


class _BinaryServer(BinaryServer):
    def __init__(self, guard: Guard, *args: Any) -> None:
        super().__init__(*args)
        self.guard = guard

    def _make_protocol(self) -> OPCUAProtocol:
        return _Protocol(
            self.guard,
            iserver=self.iserver,
            policies=self._policies,
            clients=self.clients,
            closing_tasks=self.closing_tasks,
            limits=self.limits,
        )


def encrypted_user_tokens(endpoints: list[ua.EndpointDescription]) -> None:
    """Each endpoint's UserName token policy asks for the password encrypted with the
    endpoint's own policy (asyncua leaves ``#None`` on a SignAndEncrypt endpoint)."""
    for edp in endpoints:
        for tok in edp.UserIdentityTokens:
            if tok.TokenType == ua.UserTokenType.UserName:
                tok.SecurityPolicyUri = edp.SecurityPolicyUri


class GuardedServer(Server):
    """asyncua's Server with the connections held to ``guard``."""

    def __init__(self, guard: Guard, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.guard = guard
        clear_ok = self.iserver.decrypt_user_token

        def decrypt_user_token(isession: Any, token: ua.UserNameIdentityToken) -> tuple[str, str]:
            if not token.EncryptionAlgorithm:
                COUNTS.note("opcua_login_refused", reason="password not encrypted")
                raise ServiceError(ua.StatusCodes.BadIdentityTokenInvalid)
            return clear_ok(isession, token)

        self.iserver.decrypt_user_token = decrypt_user_token  # type: ignore[method-assign]

    async def start(self) -> None:
        """As :meth:`Server.start`, with :class:`_BinaryServer` and the token policies."""
        if self.iserver.certificate is not None:
            uacrypto.check_certificate(
                self.iserver.certificate, self._application_uri, socket.gethostname()
            )
        await self._setup_server_nodes()
        encrypted_user_tokens(self.iserver.endpoints)
        await self.iserver.start()
        try:
            host, port = self._get_bind_socket_info()
            self.bserver = _BinaryServer(self.guard, self.iserver, host, port, self.limits)
            self.bserver.set_policies(self._policies)
            await self.bserver.start()
        except Exception:
            await self.iserver.stop()
            raise
