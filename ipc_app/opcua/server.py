"""The OPC UA server process (asyncua), beside the IPC service.

It never runs in the service's process: it takes the service's status over the control
socket every ``opcua.update_period_ms`` (``status`` is answered by the control channel's
I/O thread from the loop's last published snapshot, so the loop never waits for it) and
sends the methods' commands down the same socket (``adjust``, ``walk``, ``stop``,
``hold``, ``unhold``, ``reset``, ``clear``), each followed by an ``audit`` entry (who, what,
result) that the service logs and writes into its run record.

Security: one endpoint, the configured policy with SignAndEncrypt; client certificates
must be in the trust store (``pki_dir/trusted``); a user name and password is required
(scrypt hashes, :mod:`ipc_app.opcua.users`) unless ``anonymous_read_only`` lets an
anonymous session browse, read and subscribe. Methods: operator and engineer; a viewer
or an anonymous session is refused with BadUserAccessDenied. Writes to the address space
are refused to everyone (every variable is read-only). docs/opcua.md has the model.

Over 500 lines because the security set-up (users, roles, trust store), the address
space built from :mod:`ipc_app.opcua.model`, the methods with their audit, and the feed
are one asyncua server object; the model's table and the users file are modules of
their own.
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
import math
import socket
import time
from collections.abc import Awaitable, Callable
from datetime import UTC
from pathlib import Path
from typing import Any

import structlog
from asyncua import Server, ua
from asyncua.common.utils import ServiceError
from asyncua.crypto.permission_rules import USER_TYPES, PermissionRuleset, UserRole
from asyncua.crypto.permission_rules import User as UaUser
from asyncua.crypto.security_policies import SECURITY_POLICY_TYPE_MAP
from asyncua.crypto.truststore import TrustStore
from asyncua.crypto.validator import CertificateValidator, CertificateValidatorOptions
from asyncua.server.user_managers import UserManager

from config import units
from config.schema import OpcUa, ProjectConfig
from ipc_app.opcua import model as m
from ipc_app.opcua import pki
from ipc_app.opcua.guard import Guard, GuardedServer
from ipc_app.opcua.users import CONTROL_ROLES, Users, UsersError, load_users
from ipc_app.service.ctl import CtlError, request
from ipc_app.service.requests import MAX_WALK_STEPS

log = structlog.get_logger("wara.opcua")

POLICIES = {
    "Basic256Sha256": ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt,
    "Aes128_Sha256_RsaOaep": ua.SecurityPolicyType.Aes128Sha256RsaOaep_SignAndEncrypt,
    "Aes256_Sha256_RsaPss": ua.SecurityPolicyType.Aes256Sha256RsaPss_SignAndEncrypt,
}
VARIANT = {
    "Double": ua.VariantType.Double,
    "Boolean": ua.VariantType.Boolean,
    "String": ua.VariantType.String,
    "LocalizedText": ua.VariantType.LocalizedText,
    "Int32": ua.VariantType.Int32,
    "UInt32": ua.VariantType.UInt32,
    "NodeId": ua.VariantType.NodeId,
}
INITIAL = {
    "Double": math.nan,
    "Boolean": False,
    "String": "",
    "Int32": 0,
    "UInt32": 0,
    "NodeId": ua.NodeId(),
}
MACHINE = "W-ARa"
#: PackMLBaseObjectType's methods that W-ARa does not serve (refused, audited).
PACKML_UNSUPPORTED = {
    "SetMachSpeed": "machine speed",
    "SetProduct": "product",
    "SetParameter": "parameters",
    "RemoteCommand": "remote command interface",
    "SetInterlock": "material interlocks",
}
#: The largest message a client may send (the model's largest read is a few KiB).
MAX_MESSAGE_BYTES = 4 * 1024 * 1024
#: A session unused for longer is closed by the server (a client that vanished).
MAX_SESSION_TIMEOUT_MS = 60_000
#: How long a method waits for the service (adjust waits for the planner's verdict).
METHOD_TIMEOUT_S = 20.0

#: The caller of the request being processed (set by the permission check, which runs in
#: the same task just before the call).
_caller: contextvars.ContextVar[UaUser | None] = contextvars.ContextVar("caller", default=None)


def _nid(ident: str | int, ns: int = 0) -> ua.NodeId:
    """A NodeId (asyncua annotates its fields with its own integer and string types)."""
    return ua.NodeId(ident, ns)  # type: ignore[arg-type]


def _status(code: int) -> ua.StatusCode:
    return ua.StatusCode(code)  # type: ignore[arg-type]


class OpcUaError(Exception):
    """The server cannot start (one line: the file or setting and what is wrong)."""


class _Users(UserManager):
    """Password users from the users file; anonymous only when allowed (read-only)."""

    def __init__(self, users: Users, anonymous: bool) -> None:
        self.users = users
        self.anonymous = anonymous
        self.roles: dict[str, str] = {}

    def get_user(
        self,
        iserver: Any,
        username: str | None = None,
        password: str | None = None,
        certificate: Any = None,
    ) -> UaUser | None:
        if username is None and password is None:
            if self.anonymous:
                return UaUser(role=UserRole.Anonymous, name=None)
            log.warning("opcua_login_refused", user=None, reason="anonymous")
            return None
        user = self.users.check(username, password)
        if user is None:
            log.warning("opcua_login_refused", user=username, reason="wrong user or password")
            return None
        self.roles[user.name] = user.role
        log.info("opcua_login", user=user.name, role=user.role)
        return UaUser(role=UserRole.User, name=user.name)


_READ_ONLY = frozenset(
    _nid(t)
    for t in USER_TYPES
    if t
    not in (
        ua.ObjectIds.WriteRequest_Encoding_DefaultBinary,
        ua.ObjectIds.CallRequest_Encoding_DefaultBinary,
    )
)
_AUTHENTICATED = frozenset(
    _nid(t) for t in USER_TYPES if t != ua.ObjectIds.WriteRequest_Encoding_DefaultBinary
)


class _Rules(PermissionRuleset):
    """Which services a session may use; remembers the caller for the methods."""

    def check_validity(self, user: Any, action_type: Any, body: Any) -> bool:
        _caller.set(user)
        if user is not None and user.role == UserRole.User:
            return action_type in _AUTHENTICATED
        return action_type in _READ_ONLY


class _TrustDir:
    """Client certificates must be in ``trusted/`` (read again whenever it changes, so
    ``wara opcua cert --trust`` needs no restart); an empty store trusts nobody."""

    def __init__(self, path: Path) -> None:
        self.path = path
        path.mkdir(parents=True, exist_ok=True, mode=0o700)
        self._stamp: tuple[int, tuple[str, ...]] | None = None
        self._validator: CertificateValidator | None = None

    async def __call__(self, cert: Any, app: ua.ApplicationDescription) -> None:
        files = tuple(
            sorted(f.name for f in self.path.iterdir() if f.suffix.lower() in (".der", ".pem"))
        )
        stamp = (self.path.stat().st_mtime_ns, files)
        if stamp != self._stamp:
            self._stamp, self._validator = stamp, None
            if files:
                store = TrustStore([self.path], [])
                await store.load()
                self._validator = CertificateValidator(
                    CertificateValidatorOptions.TRUSTED_VALIDATION
                    | CertificateValidatorOptions.PEER_CLIENT,
                    store,
                )
        if self._validator is None:
            log.warning("opcua_certificate_refused", reason=f"nothing trusted in {self.path}")
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)
        await self._validator(cert, app)


def endpoint_url(opc: OpcUa, host: str | None = None) -> str:
    h = host or (socket.gethostname() if opc.host in ("0.0.0.0", "::") else opc.host)
    return f"opc.tcp://{h}:{opc.port}/wara/"


FEED_REPORT_S = 10.0
#: the companion specifications' NodeSets, loaded in this order (nodesets/README.md)
NODESETS = tuple(
    Path(__file__).parent / "nodesets" / f"Opc.Ua.{name}.NodeSet2.xml"
    for name in ("Di", "Machinery", "PackML")
)
#: the feed lets the event loop run (publish, answer) after this many writes
WRITES_PER_YIELD = 16


class _FeedFigures:
    """The feed's timings over one report interval (``opcua_feed`` log line)."""

    def __init__(self, since: float) -> None:
        self.since = since
        self.n = 0
        self.status_max_s = self.write_max_s = self.write_sum_s = 0.0

    def add(self, status_s: float, write_s: float) -> None:
        self.n += 1
        self.status_max_s = max(self.status_max_s, status_s)
        self.write_max_s = max(self.write_max_s, write_s)
        self.write_sum_s += write_s

    def summary(self, now: float, period_s: float) -> dict[str, float]:
        span = now - self.since
        return {
            "updates": self.n,
            "period_ms": round(units.to_ms(span / max(self.n, 1)), 1),
            "configured_period_ms": round(units.to_ms(period_s), 1),
            "status_max_ms": round(units.to_ms(self.status_max_s), 1),
            "write_mean_ms": round(units.to_ms(self.write_sum_s / max(self.n, 1)), 1),
            "write_max_ms": round(units.to_ms(self.write_max_s), 1),
        }


class OpcUaServer:
    """The server: build the model, feed it from the service, serve the methods."""

    def __init__(
        self,
        cfg: ProjectConfig,
        ctl_socket: str | Path | None,
        *,
        opc: OpcUa | None = None,
    ) -> None:
        self.cfg = cfg
        self.opc = opc or cfg.opcua
        self.ctl_socket = ctl_socket
        self.model = m.variables(cfg)
        self.nodes: list[Any] = []
        self.last: list[Any] = []
        self._ns: dict[str, int] = {}
        self.reachable: Any = None
        self.updates = 0
        self.server: Server | None = None
        self._users: _Users | None = None

    async def build(self) -> Server:
        opc = self.opc
        try:
            users = load_users(opc.users_file)
        except UsersError as exc:
            raise OpcUaError(f"opcua.users_file: {exc}") from None
        cert, key = pki.own_cert(opc.pki_dir), pki.own_key(opc.pki_dir)
        if not (cert.exists() and key.exists()):
            raise OpcUaError(
                f"opcua.pki_dir: no server certificate {cert} (create it with `wara opcua cert`)"
            )
        self._users = _Users(users, opc.anonymous_read_only)
        policy = POLICIES[opc.security_policy]
        guard = Guard(
            policy_uris=frozenset({SECURITY_POLICY_TYPE_MAP[policy][0].URI}),  # type: ignore[attr-defined]
            hello_timeout_s=opc.hello_timeout_s,
        )
        srv = GuardedServer(guard, user_manager=self._users)
        srv.limits.max_message_size = MAX_MESSAGE_BYTES
        srv.limits.max_chunk_count = math.ceil(MAX_MESSAGE_BYTES / srv.limits.max_recv_buffer)
        await srv.init()
        srv.iserver.max_connections = opc.max_connections
        srv.iserver.max_session_timeout_ms = MAX_SESSION_TIMEOUT_MS
        srv.iserver.max_pending_activation_seconds = opc.session_activate_timeout_s
        srv.set_endpoint(f"opc.tcp://{opc.host}:{opc.port}/wara/")
        srv.set_server_name(f"W-ARa IPC ({self.cfg.project.name})")
        host = socket.gethostname()
        await srv.set_application_uri(pki.application_uri(host))
        srv.product_uri = "urn:wara:ipc"
        srv.manufacturer_name = "W-ARa"
        srv.set_security_policy([policy], permission_ruleset=_Rules())  # type: ignore[arg-type]
        tokens: list[type] = [ua.UserNameIdentityToken]
        if opc.anonymous_read_only:
            tokens.append(ua.AnonymousIdentityToken)
        srv.set_identity_tokens(tokens)
        await srv.load_certificate(str(cert))
        await srv.load_private_key(str(key))
        srv.set_certificate_validator(_TrustDir(pki.trusted_dir(opc.pki_dir)))
        await self._model(srv)
        self.server = srv
        return srv

    async def _model(self, srv: Server) -> None:
        for path in NODESETS:  # DI, Machinery, PackML: their types and the Machines folder
            await srv.import_xml(str(path))
        ns = {uri: await srv.get_namespace_index(uri) for uri in m.COMPANIONS}
        ns[m.NS_WARA] = w = await srv.register_namespace(m.NS_WARA)
        self._ns = ns
        machines = await srv.nodes.objects.get_child(
            ua.QualifiedName("Machines", ns[m.NS_MACHINERY])
        )
        machine = await machines.add_object(_nid(MACHINE, w), ua.QualifiedName(MACHINE, w))
        ident = await self._instance(srv, machine, ("Identification",), ns, w)
        from importlib.metadata import PackageNotFoundError, version

        try:
            sw = version("wara-control")
        except PackageNotFoundError:
            sw = "unknown"
        for name, val in (
            ("Manufacturer", ua.LocalizedText("W-ARa")),
            ("Model", ua.LocalizedText("W-ARa walk-through arc-part robot")),
            ("ProductInstanceUri", pki.application_uri()),
            ("SerialNumber", socket.gethostname()),
            ("ComponentName", ua.LocalizedText(self.cfg.project.name)),
            ("Location", self.cfg.project.section),
            ("SoftwareRevision", sw),
        ):
            nid = _nid(f"{MACHINE}.Identification.{name}", w)
            if nid in srv.iserver.aspace:  # a property of MachineIdentificationType
                await srv.get_node(nid).write_value(val)
            else:
                await ident.add_property(nid, ua.QualifiedName(name, ns[m.NS_DI]), val)
        folders: dict[tuple[str, ...], Any] = {(): machine, ("Identification",): ident}
        for var in self.model:
            parent = machine
            for depth in range(1, len(var.path)):
                key = var.path[:depth]
                if key not in folders:
                    folders[key] = await self._instance(srv, folders[key[:-1]], key, ns, w)
                parent = folders[key]
            init: Any = ua.LocalizedText("") if var.kind == "LocalizedText" else INITIAL[var.kind]
            nid = _nid(".".join((MACHINE, *var.path)), w)
            if nid in srv.iserver.aspace:  # a variable of the instance's type
                node = srv.get_node(nid)
                await node.write_value(ua.Variant(init, VARIANT[var.kind]))
            else:
                node = await parent.add_variable(
                    nid,
                    ua.QualifiedName(var.path[-1], ns[var.ns]),
                    ua.Variant(init, VARIANT[var.kind]),
                )
            if var.unit is not None:
                await node.add_property(
                    _nid(".".join((MACHINE, *var.path, "EngineeringUnits")), w),
                    ua.QualifiedName("EngineeringUnits", 0),
                    ua.EUInformation(
                        NamespaceUri="http://www.opcfoundation.org/UA/units/un/cefact",
                        UnitId=var.unit.unit_id,
                        DisplayName=ua.LocalizedText(var.unit.symbol),
                        Description=ua.LocalizedText(var.unit.name),
                    ),
                )
            self.nodes.append(node)
            self.last.append(None)
        self.reachable = await machine.add_variable(
            _nid(f"{MACHINE}.ServiceReachable", w),
            ua.QualifiedName("ServiceReachable", w),
            False,
        )
        await self._methods(machine, w)
        await self._packml(srv, w)

    async def _instance(
        self, srv: Server, parent: Any, key: tuple[str, ...], ns: dict[str, int], w: int
    ) -> Any:
        """The object at ``key`` under the machine: an instance of its companion type
        (:data:`ipc_app.opcua.model.TYPED`: its children get the ids ``W-ARa.<path>``),
        a folder, or a plain object, with its browse name in its specification's
        namespace."""
        nid = _nid(".".join((MACHINE, *key)), w)
        if nid in srv.iserver.aspace:  # a child of a typed instance (PackML's Status, ...)
            return srv.get_node(nid)
        typed = m.TYPED.get(key)
        if typed is not None:
            bname_ns, type_ns, type_id = typed
            return await parent.add_object(
                nid,
                ua.QualifiedName(key[-1], ns[bname_ns]),
                objecttype=_nid(type_id, ns[type_ns]),
            )
        if key[0] in m.COMPANION_ROOTS:
            bname = ua.QualifiedName(key[-1], ns[m.COMPANION_ROOTS[key[0]]])
            return await parent.add_folder(nid, bname)
        return await parent.add_object(nid, ua.QualifiedName(key[-1], w))

    async def _methods(self, machine: Any, w: int) -> None:
        out = [_arg("Result", _nid(ua.ObjectIds.String), "the service's answer")]
        start_in = [
            _arg("Roll", _nid(ua.ObjectIds.Double), "target workpiece roll [rad]"),
            _arg("Pitch", _nid(ua.ObjectIds.Double), "target workpiece pitch [rad]"),
        ]

        async def start(parent: Any, roll: Any, pitch: Any) -> Any:
            r, p = _radians(roll), _radians(pitch)
            if r is None or p is None:
                return await self._refused(
                    "StartAdjustment",
                    "Roll and Pitch must be finite Doubles",
                    ua.StatusCodes.BadInvalidArgument,
                )
            return await self._command(
                f"StartAdjustment(roll={r:.6g} rad, pitch={p:.6g} rad)",
                "adjust",
                {"roll_deg": math.degrees(r), "pitch_deg": math.degrees(p)},
            )

        walk_in = [_arg("Steps", _nid(ua.ObjectIds.UInt32), "steps to walk (1..1000)")]

        async def start_walk(parent: Any, steps: Any) -> Any:
            n = _value(steps)
            if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_WALK_STEPS:
                return await self._refused(
                    "StartWalk",
                    f"Steps must be an integer 1..{MAX_WALK_STEPS}",
                    ua.StatusCodes.BadInvalidArgument,
                )
            return await self._command(f"StartWalk(steps={n})", "walk", {"steps": n})

        methods: list[tuple[str, Callable[..., Awaitable[Any]], list[ua.Argument]]] = [
            ("StartAdjustment", start, start_in),
            ("StartWalk", start_walk, walk_in),
        ]
        for name, cmd in (
            ("Stop", "stop"),
            ("Hold", "hold"),
            ("Unhold", "unhold"),
            ("Reset", "reset"),
            ("Clear", "clear"),
        ):
            methods.append((name, self._simple(name, cmd), []))
        for name, fn, args in methods:
            await machine.add_method(
                _nid(f"{MACHINE}.{name}", w), ua.QualifiedName(name, w), fn, args, out
            )

    async def _packml(self, srv: Server, w: int) -> None:
        """PackMLBaseObjectType's own values and methods: ``SetUnitMode`` sets the unit
        mode as ``wara ctl unit-mode`` does (PackML's numbers, :data:`UNIT_MODES`); the
        others are refused with ``BadNotSupported``: W-ARa has no machine speed, product,
        parameter, remote-command or material-interlock interface."""

        def node(path: str) -> Any:
            return srv.get_node(_nid(f"{MACHINE}.PackML.{path}", w))

        for path, val, vt in (
            ("TagID", MACHINE, ua.VariantType.String),
            ("Status.MachSpeed", 0.0, ua.VariantType.Float),
            ("Status.CurMachSpeed", 0.0, ua.VariantType.Float),
            ("Status.EquipmentBlocked", False, ua.VariantType.Boolean),
            ("Status.EquipmentStarved", False, ua.VariantType.Boolean),
        ):
            await node(path).write_value(ua.Variant(val, vt))
        names = {code: name for name, code in m.UNIT_MODE_CODES.items()}

        async def set_unit_mode(parent: Any, requested: Any) -> Any:
            n = _value(requested)
            if isinstance(n, bool) or n not in names:
                return await self._refused(
                    "SetUnitMode",
                    f"RequestedMode must be one of {sorted(names)} ({', '.join(names.values())})",
                    ua.StatusCodes.BadInvalidArgument,
                )
            return await self._command(
                f"SetUnitMode({n} {names[n]})", "unit_mode", {"unit_mode": names[n]}
            )

        srv.link_method(node("SetUnitMode"), set_unit_mode)
        for name, what in PACKML_UNSUPPORTED.items():
            srv.link_method(node(name), self._unsupported(name, what))

    def _unsupported(self, name: str, what: str) -> Callable[..., Awaitable[Any]]:
        async def call(parent: Any, *_args: Any) -> Any:
            return await self._refused(name, f"W-ARa has no {what}", ua.StatusCodes.BadNotSupported)

        return call

    def _simple(self, name: str, cmd: str) -> Callable[[Any], Awaitable[Any]]:
        async def call(parent: Any) -> Any:
            return await self._command(name, cmd, {})

        return call

    def _who(self) -> tuple[str, str | None]:
        user = _caller.get()
        if user is None or user.role != UserRole.User or self._users is None:
            return "anonymous", None
        return str(user.name), self._users.roles.get(str(user.name))

    async def _refused(self, what: str, why: str, code: int) -> ua.CallMethodResult:
        who, _role = self._who()
        await self._audit(who, what, f"refused: {why}")
        res = ua.CallMethodResult()
        res.StatusCode = _status(code)
        res.OutputArguments = [ua.Variant(why, ua.VariantType.String)]
        return res

    async def _command(self, what: str, cmd: str, args: dict[str, Any]) -> Any:
        who, role = self._who()
        if role not in CONTROL_ROLES:
            return await self._refused(
                what,
                f"{who} ({role or 'no role'}) may not call methods",
                ua.StatusCodes.BadUserAccessDenied,
            )
        try:
            reply = await asyncio.to_thread(
                request, cmd, socket_path=self.ctl_socket, timeout_s=METHOD_TIMEOUT_S, **args
            )
        except CtlError as exc:
            return await self._refused(
                what, f"service unreachable: {exc}", ua.StatusCodes.BadCommunicationError
            )
        if reply.get("ok") is not True:
            code = {
                "infeasible": ua.StatusCodes.BadOutOfRange,
                "bad_request": ua.StatusCodes.BadInvalidArgument,
            }.get(str(reply.get("code")), ua.StatusCodes.BadInvalidState)
            return await self._refused(what, str(reply.get("error", "refused")), code)
        result = f"ok: mode {reply.get('mode', '?')}"
        await self._audit(who, what, result)
        return [ua.Variant(result, ua.VariantType.String)]

    async def _audit(self, who: str, what: str, result: str) -> None:
        log.info("opcua_method", user=who, action=what, result=result)
        try:
            await asyncio.to_thread(
                request,
                "audit",
                socket_path=self.ctl_socket,
                timeout_s=5.0,
                retry_s=1.0,
                user=who[:40],
                action=what.split("(")[0][:40],
                result=f"{what}: {result}"[:400],
            )
        except CtlError as exc:
            log.warning("opcua_audit_not_recorded", error=str(exc))

    # ------------------------------------------------------------------ the feed

    async def update(self, status: dict[str, Any] | None) -> None:
        """Write the variables whose value changed (status None: the service is gone).

        Straight into the address space (``Server.write_attribute_value``: no session,
        no write request built per value), one timestamp for the whole status, in the
        model's order (the states first); every :data:`WRITES_PER_YIELD` writes the event
        loop may publish what is written so far.
        """
        assert self.reachable is not None and self.server is not None
        await self.reachable.write_value(status is not None)
        if status is None:
            return
        stamp = ua.DateTime.now(UTC)
        write = self.server.write_attribute_value
        written = 0
        for i, (var, val) in enumerate(zip(self.model, m.values(self.model, status), strict=True)):
            old = self.last[i]
            if old == val or (
                isinstance(val, float)
                and isinstance(old, float)
                and math.isnan(val)
                and math.isnan(old)
            ):
                continue
            self.last[i] = val
            v = self._variant_value(var.kind, val)
            dv = ua.DataValue(
                ua.Variant(v, VARIANT[var.kind]), SourceTimestamp=stamp, ServerTimestamp=stamp
            )
            await write(self.nodes[i].nodeid, dv)
            written += 1
            if written % WRITES_PER_YIELD == 0:
                await asyncio.sleep(0)
        self.updates += 1

    def _variant_value(self, kind: str, val: Any) -> Any:
        if kind == "LocalizedText":
            return ua.LocalizedText(val)
        if kind == "NodeId":
            return _nid(val.id, self._ns[val.ns]) if val is not None else ua.NodeId()
        return val

    async def feed(self) -> None:
        """The service's status every ``update_period_ms``, and at once at a change of its
        state: each request waits in the service until ``state_seq`` moves past the one
        seen last, at most until the period's end (so a state change reaches the address
        space within milliseconds, not up to a period later)."""
        period = self.opc.update_period_ms / 1000.0
        was_up = None
        seq: int | None = None
        nxt = time.monotonic() + period
        figures = _FeedFigures(time.monotonic())
        while True:
            t0 = time.monotonic()
            wait_ms = units.to_ms(max(0.0, nxt - t0)) if seq is not None else None
            args: dict[str, Any] = {} if wait_ms is None else {"after": seq, "wait_ms": wait_ms}
            try:
                st: dict[str, Any] | None = await asyncio.to_thread(
                    request, "status", socket_path=self.ctl_socket, timeout_s=2.0, retry_s=0.0,
                    **args,
                )  # fmt: skip
            except CtlError as exc:
                st = None
                if was_up is not False:
                    log.warning("opcua_service_unreachable", error=str(exc))
            if st is not None and was_up is not True:
                log.info("opcua_service_reachable")
            was_up = st is not None
            new_seq = st.get("state_seq") if st is not None else None
            changed = seq is not None and new_seq is not None and new_seq != seq
            seq = new_seq
            t1 = time.monotonic()
            waited_s = units.ms(st.get("waited_ms", 0.0)) if st is not None else 0.0
            try:
                await self.update(st)
            except Exception:  # a bug in the model must not end the feed
                log.exception("opcua_update_failed")
            t2 = time.monotonic()
            figures.add(t1 - t0 - waited_s, t2 - t1)  # the status's time, its wait left out
            if t2 - figures.since >= FEED_REPORT_S:
                log.info("opcua_feed", **figures.summary(t2, period))
                figures = _FeedFigures(t2)
            if changed:  # the next request waits out the rest of this period
                continue
            if seq is None:  # the service gone (or too old to count): poll every period
                await asyncio.sleep(max(0.0, nxt - time.monotonic()))
            nxt = max(nxt + period, time.monotonic())

    async def serve(self, ready: Callable[[str], None] | None = None) -> None:
        srv = self.server or await self.build()
        async with srv:
            url = endpoint_url(self.opc)
            log.info(
                "opcua_started",
                endpoint=url,
                policy=self.opc.security_policy,
                anonymous_read_only=self.opc.anonymous_read_only,
            )
            if ready is not None:
                ready(url)
            await self.feed()


def _arg(name: str, dtype: ua.NodeId, text: str) -> ua.Argument:
    a = ua.Argument()
    a.Name = name
    a.DataType = dtype
    a.ValueRank = -1
    a.Description = ua.LocalizedText(text)
    return a


def _value(v: Any) -> Any:
    """A method argument's plain value (asyncua passes a Variant or the value)."""
    return v.Value if isinstance(v, ua.Variant) else v


def _radians(v: Any) -> float | None:
    x = _value(v)
    if isinstance(x, bool) or not isinstance(x, int | float) or not math.isfinite(x):
        return None
    return float(x)


def quiet_asyncua() -> None:
    """asyncua logs every request at INFO: keep its warnings only."""
    logging.getLogger("asyncua").setLevel(logging.WARNING)
