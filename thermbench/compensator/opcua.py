"""The OPC UA side of the compensator (asyncua): security settings, connecting (and saying
why a server refused), resolving ``nsu=`` node ids, the :class:`Session` that checks the
nodes on connect and reads them each cycle, the :class:`GuardedWriter` that writes only the
configured outputs, and turning a :class:`~.control.Cycle` into the values it writes."""

from __future__ import annotations

import asyncio
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

from .control import Cycle, CycleLogic, Reading
from .errorline import Line
from .errors import CompensatorError, RefusedWrite
from .nodes import LENGTH_UNITS, SLOPE_UNITS, Nodes

CLIENT_APP_URI = "urn:thermbench:compensator"


# write results that no reconnection will cure: the set-up is wrong
FATAL_WRITE = ("BadTypeMismatch", "BadUserAccessDenied", "BadNotWritable", "BadOutOfRange", "BadNodeIdUnknown",
               "BadWriteNotSupported", "BadIndexRangeInvalid")  # fmt: skip


def _ua():
    from asyncua import ua

    return ua


def data_type_name(node_id) -> str:
    """A DataType attribute's NodeId as a reader knows it: a standard type (namespace 0) by its
    name (``Int32``, ``Float``, ``Double``), any other as its string form (``ns=2;i=3002``)."""
    if node_id is None:
        return "none (the node has no data type)"
    identifier = getattr(node_id, "Identifier", None)
    if getattr(node_id, "NamespaceIndex", None) == 0 and isinstance(identifier, int):
        name = _ua().ObjectIdNames.get(identifier)
        if name:
            return name
    to_string = getattr(node_id, "to_string", None)
    return f"{to_string() if callable(to_string) else node_id} (not a standard type)"


class GuardedWriter:
    """Writes only the configured output nodes; anything else is refused before the network."""

    def __init__(self, client, outputs: Mapping[str, str]) -> None:
        self.client = client
        self.outputs = dict(outputs)
        self.allowed = frozenset(outputs.values())

    async def write_node(self, node_id: str, variant) -> None:
        if node_id not in self.allowed:
            raise RefusedWrite(f"refused to write node {node_id!r}: not one of the configured outputs {sorted(self.allowed)}")
        await self.client.write_values([self.client.get_node(node_id)], [_ua().DataValue(variant)])

    async def write(self, values: Mapping[str, Any]) -> None:
        """Write ``output name -> ua.Variant`` in one request."""
        ids = []
        for name in values:
            if name not in self.outputs:
                raise RefusedWrite(f"refused to write output {name!r}: not configured in the nodes file")
            ids.append(self.outputs[name])
        if ids:
            await self.client.write_values([self.client.get_node(i) for i in ids], [_ua().DataValue(v) for v in values.values()])


#: refusals that are about something else than the certificates (the identity, the address space, load)
NOT_CERTIFICATES = ("BadUserAccessDenied", "BadIdentityTokenInvalid", "BadIdentityTokenRejected", "BadNodeIdUnknown",
                    "BadTooManySessions", "BadServerHalted", "BadTimeout")


def _connection_errors() -> tuple[type[BaseException], ...]:
    """What a lost or refused connection raises (asyncua's status-code errors included)."""
    return (OSError, asyncio.TimeoutError, _ua().UaError)


def _seconds(dt) -> float | None:
    return None if dt is None else dt.timestamp()


def _reading(dv) -> Reading:
    ts = _seconds(dv.SourceTimestamp) or _seconds(dv.ServerTimestamp)
    v = dv.Value.Value if dv.Value is not None else None
    return Reading(v, ts, dv.StatusCode.is_good() if dv.StatusCode is not None else True)


def resume_from_controller(logic: CycleLogic, current: Mapping[str, Any], nodes: Nodes, prefix: str = "") -> None:
    """Make ``logic`` ramp from the compensation the controller holds (``current``: the output
    nodes' values read when the session opened, keyed ``<prefix><output name>``), not from zero."""
    o = nodes.outputs

    def num(key, factor):
        v = current.get(prefix + key)
        return float(v) / factor if isinstance(v, (int, float)) and math.isfinite(float(v)) else None

    value = num("value", LENGTH_UNITS[o.value.unit]) if o.value else None
    line = None
    if o.line:
        off, slope = num("offset", LENGTH_UNITS[o.line.offset.unit]), num("slope", SLOPE_UNITS[o.line.slope.unit])
        ref = num("ref", LENGTH_UNITS[o.line.ref.unit])
        if None not in (off, slope, ref):
            line = Line(off, slope, ref / 1e3)
    logic.resume(value, line)


def output_variants(c: Cycle, nodes: Nodes, output: str) -> dict[str, Any]:
    """The values one cycle writes, in each node's unit (nothing before the first prediction)."""
    ua = _ua()
    dbl = ua.VariantType.Double
    out: dict[str, Any] = {}
    o = nodes.outputs
    if output in ("value", "both") and c.value_um is not None:
        out["value"] = ua.Variant(c.value_um * LENGTH_UNITS[o.value.unit], dbl)
    if output in ("line", "both") and c.line is not None:
        out["offset"] = ua.Variant(c.line.offset_um * LENGTH_UNITS[o.line.offset.unit], dbl)
        out["slope"] = ua.Variant(c.line.slope_um_per_m * SLOPE_UNITS[o.line.slope.unit], dbl)
        out["ref"] = ua.Variant(c.line.ref_mm * 1e3 * LENGTH_UNITS[o.line.ref.unit], dbl)
    if o.status:
        out["status"] = ua.Variant(int(c.flags), ua.VariantType.Int32)
    return out


@dataclass
class Security:
    user: str | None = None
    password_env: str = "THERMBENCH_OPCUA_PASSWORD"
    policy: str | None = None
    mode: str = "SignAndEncrypt"
    certificate: str | None = None
    private_key: str | None = None
    server_certificate: str | None = None

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None) -> "Security":
        cfg = dict(cfg or {})
        unknown = sorted(set(cfg) - set(cls.__dataclass_fields__))
        if unknown:
            raise CompensatorError(f"config key(s) {['security.' + k for k in unknown]}: unknown; "
                                   f"known: {sorted(cls.__dataclass_fields__)}")  # fmt: skip
        s = cls(**cfg)
        if s.policy not in (None, "Basic256Sha256"):
            raise CompensatorError(f"config key 'security.policy': expected null or Basic256Sha256, got {s.policy!r}")
        if s.mode not in ("Sign", "SignAndEncrypt"):
            raise CompensatorError(f"config key 'security.mode': expected Sign or SignAndEncrypt, got {s.mode!r}")
        if s.policy:
            for key in ("certificate", "private_key"):
                p = getattr(s, key)
                if not p or not Path(p).is_file():
                    raise CompensatorError(f"config key 'security.{key}': {p!r} is not a file "
                                           "(make a pair with `thermbench certs DIR`)")  # fmt: skip
            if s.server_certificate and not Path(s.server_certificate).is_file():
                raise CompensatorError(f"config key 'security.server_certificate': {s.server_certificate!r} is not a file")
        if s.user and not s.policy:
            raise CompensatorError("config key 'security.user': a password is never sent unencrypted; set "
                                   "security.policy=Basic256Sha256 with the certificates (thermbench certs DIR)")  # fmt: skip
        if s.policy and not s.server_certificate:
            raise CompensatorError("config key 'security.server_certificate': the server's certificate to pin is needed "
                                   "with security.policy (without it any server could pose as the machine)")  # fmt: skip
        if s.user and not os.environ.get(s.password_env):
            raise CompensatorError(f"config key 'security.user' is set, so the password is read from the environment "
                                   f"variable {s.password_env} (security.password_env), which is not set")  # fmt: skip
        return s


async def connect_client(endpoint: str, sec: Security, timeout_s: float):
    """A connected asyncua client with the configured identity and security."""
    from asyncua import Client, ua
    from asyncua.crypto.security_policies import SecurityPolicyBasic256Sha256

    client = Client(endpoint, timeout=timeout_s)
    client.application_uri = CLIENT_APP_URI
    if sec.user:
        client.set_user(sec.user)
        client.set_password(os.environ[sec.password_env])
    if sec.policy:
        await client.set_security(SecurityPolicyBasic256Sha256, certificate=sec.certificate, private_key=sec.private_key,
                                  server_certificate=sec.server_certificate, mode=getattr(ua.MessageSecurityMode, sec.mode))  # fmt: skip
    try:
        await asyncio.wait_for(client.connect(), timeout_s)
    except BaseException:  # a timed-out or refused attempt must not leave its socket open
        await _quiet_disconnect(client)
        raise
    return client


def resolve_node_id(node_id: str, namespaces: Sequence[str], where: str, source: str = "nodes file") -> str:
    """``node_id`` with a namespace URI (``nsu=<uri>;s=...``, the form that is the same on every
    server) as the namespace index this server gives that URI (``ns=<index>;s=...``); any other
    form as given. ``namespaces`` is the server's NamespaceArray; ``where`` names the node in a
    mistake's message (a URI the server does not have), ``source`` the file and key it is set
    at (``nodes.yaml: key inputs.temperatures.T_nut``)."""
    if not node_id.startswith("nsu="):
        return node_id
    uri, sep, rest = node_id[len("nsu="):].partition(";")
    if not sep or not rest or not uri:
        raise CompensatorError(f"{source}: {where} node {node_id!r}: expected nsu=<namespace URI>;<identifier>, "
                               "e.g. nsu=urn:thermbench:sim-cnc;s=X.Position_mm")  # fmt: skip
    uri = uri.replace("%3B", ";").replace("%25", "%")  # OPC UA Part 6 5.3.1.10: ';' and '%' escaped in the URI
    if uri not in namespaces:
        raise CompensatorError(f"{source}: {where} node {node_id!r}: the server has no namespace {uri!r}; "
                               f"its namespaces: {list(namespaces)}")  # fmt: skip
    return f"ns={list(namespaces).index(uri)};{rest}"


def _certificate_der(path: str) -> bytes:
    """A certificate file (PEM or DER) as DER bytes."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    data = Path(path).read_bytes()
    cert = x509.load_pem_x509_certificate(data) if b"-----BEGIN" in data else x509.load_der_x509_certificate(data)
    return cert.public_bytes(Encoding.DER)


def _thumbprint(der: bytes) -> str:
    """The SHA-1 thumbprint OPC UA tools show for a certificate (colon-separated hex)."""
    import hashlib

    return ":".join(f"{b:02X}" for b in hashlib.sha1(der).digest())


async def explain_security_refusal(endpoint: str, sec: "Security", timeout_s: float) -> str | None:
    """Why a secured connection failed, in one line, when it is the certificates: asyncua reports
    an untrusted client certificate as a bare ``AssertionError`` (the server closes the channel)
    and a server whose certificate is not the pinned one as a decryption error. The server's
    certificate is read from its endpoints (GetEndpoints, which needs no security) and compared
    with the pinned one: different, the server is not the pinned one; the same, the server refused
    this client's certificate. None when there is no security or the endpoints cannot be read."""
    if not sec.policy or not sec.server_certificate or not sec.certificate:
        return None
    from asyncua import Client

    try:
        pinned = _certificate_der(sec.server_certificate)
        endpoints = await asyncio.wait_for(Client(endpoint, timeout=timeout_s).connect_and_get_server_endpoints(), timeout_s)
    except Exception:  # the server is not answering at all: the original error says more
        return None
    presented = next((bytes(e.ServerCertificate) for e in endpoints if e.ServerCertificate), None)
    if presented is None:
        return None
    try:
        presented = _certificate_der_bytes(presented)
    except ValueError:
        return None
    if presented != pinned:
        return (f"the server's certificate is not the pinned one (security.server_certificate={sec.server_certificate}, "
                f"SHA-1 {_thumbprint(pinned)}); {endpoint} presents SHA-1 {_thumbprint(presented)}: pin the machine's "
                "current certificate if it was renewed, else this is not the machine")  # fmt: skip
    mine = _certificate_der(sec.certificate)
    return (f"the server refused this client's certificate (security.certificate={sec.certificate}, SHA-1 "
            f"{_thumbprint(mine)}): add it to the server's trusted client certificates")  # fmt: skip


def _certificate_der_bytes(data: bytes) -> bytes:
    """DER bytes as sent in an endpoint description (normalised through cryptography)."""
    from cryptography import x509
    from cryptography.hazmat.primitives.serialization import Encoding

    return x509.load_der_x509_certificate(data).public_bytes(Encoding.DER)


class Session:
    """One connection to the machine: its input and output nodes, checked on connect. Node ids
    given with a namespace URI (``nsu=``) are resolved against the server's namespace array on
    every connection (a restarted server may number its namespaces differently)."""

    def __init__(self, endpoint: str, nodes: Nodes, sec: Security, timeout_s: float,
                 subscribe_ms: float | None = None, probe_every_s: float = 1.0) -> None:  # fmt: skip
        """``subscribe_ms``: take the inputs from a subscription (data changes, timestamps included,
        published every ``subscribe_ms``) instead of one read request per cycle; the connection is
        then probed every ``probe_every_s`` in the background (the server's CurrentTime)."""
        self.endpoint, self.nodes, self.sec, self.timeout_s = endpoint, nodes, sec, timeout_s
        self.subscribe_ms, self.probe_every_s = subscribe_ms, probe_every_s
        self.latest: dict[str, Reading] = {}
        self._probe: asyncio.Task | None = None
        self._next_probe = 0.0
        self.client = None
        self.writer: GuardedWriter | None = None
        self.inputs = nodes.input_ids()
        self.current: dict[str, Any] = {}  # the output nodes' values when the session opened

    def _source(self, name: str, output: bool = False) -> str:
        """Where the input (or output) ``name`` is set: ``<nodes file>: key <key path as written>``
        (``inputs.temperatures.T_nut``); ``nodes file`` for nodes not read from one file (a station's)."""
        where = getattr(self.nodes, "where", None)
        return where(name, output) if callable(where) else "nodes file"

    async def open(self) -> None:
        ua = _ua()
        client = await connect_client(self.endpoint, self.sec, self.timeout_s)
        try:
            namespaces = await client.get_namespace_array()
            given = self.nodes.output_ids()
            outs = {name: resolve_node_id(nid, namespaces, f"output {name}", self._source(name, output=True))
                    for name, nid in given.items()}  # fmt: skip
            ids = list(outs.values())
            nodes = [client.get_node(i) for i in ids]
            access = await client.read_attributes(nodes, ua.AttributeIds.UserAccessLevel)
            types = await client.read_attributes(nodes, ua.AttributeIds.DataType)
            for name, nid, dv, ty in zip(outs, given.values(), access, types):
                source = self._source(name, output=True)
                if not dv.StatusCode.is_good():
                    raise CompensatorError(f"{source}: output {name} node {nid!r} does not exist on {self.endpoint} "
                                           f"({dv.StatusCode.name})")  # fmt: skip
                if not int(dv.Value.Value) & ua.AccessLevel.CurrentWrite.mask:
                    raise CompensatorError(f"{source}: output {name} node {nid!r} is not writable for this user on {self.endpoint}")
                status = name.rsplit("/", 1)[-1] == "status"  # a station's outputs are <channel>/<name>
                want = ua.ObjectIds.Int32 if status else ua.ObjectIds.Double
                got = ty.Value.Value
                if got is None or got.Identifier != want or got.NamespaceIndex != 0:
                    raise CompensatorError(f"{source}: output {name} node {nid!r} has data type {data_type_name(got)}; "
                                           f"the compensator writes {'Int32' if status else 'Double'}")  # fmt: skip
            current = await client.read_attributes(nodes)
            self.current = {name: (dv.Value.Value if dv.Value is not None else None) for name, dv in zip(outs, current)}
            self.input_nodes = [client.get_node(resolve_node_id(i, namespaces, f"input {name}", self._source(name)))
                                for name, i in self.inputs.items()]
            first = await client.read_attributes(self.input_nodes)
            for (name, nid), dv in zip(self.inputs.items(), first):
                if dv.StatusCode.value == ua.StatusCodes.BadNodeIdUnknown:
                    raise CompensatorError(f"{self._source(name)}: input {name} node {nid!r} does not exist on {self.endpoint}")
            if self.subscribe_ms is not None:
                self.latest = {name: _reading(dv) for name, dv in zip(self.inputs, first)}
                by_id = {n.nodeid: name for name, n in zip(self.inputs, self.input_nodes)}
                session = self

                class Handler:
                    def datachange_notification(self, node, val, data) -> None:
                        name = by_id.get(node.nodeid)
                        if name is not None:
                            session.latest[name] = _reading(data.monitored_item.Value)

                sub = await client.create_subscription(self.subscribe_ms, Handler())
                trigger = ua.DataChangeFilter(Trigger=ua.DataChangeTrigger.StatusValueTimestamp)  # a new stamp is news
                await sub._subscribe(self.input_nodes, ua.AttributeIds.Value, mfilter=trigger, sampling_interval=0.0)
                self._status_node = client.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_CurrentTime))
        except BaseException:
            await _quiet_disconnect(client)
            raise
        self.client = client
        self.writer = GuardedWriter(client, outs)

    async def read(self) -> dict[str, Reading]:
        if self.subscribe_ms is not None:
            return self._subscribed()
        dvs = await asyncio.wait_for(self.client.read_attributes(self.input_nodes), self.timeout_s)
        return {name: _reading(dv) for name, dv in zip(self.inputs, dvs)}

    def _subscribed(self) -> dict[str, Reading]:
        """The newest value of every input, and the background probe's verdict on the connection."""
        probe, now = self._probe, time.monotonic()
        if probe is not None and probe.done():
            self._probe = None
            exc = probe.exception()
            if exc is not None:
                raise exc if isinstance(exc, _connection_errors()) else ConnectionError(f"probe: {exc}")
        if self._probe is None and now >= self._next_probe:
            self._probe = asyncio.ensure_future(asyncio.wait_for(self._status_node.read_value(), self.timeout_s))
            self._next_probe = now + self.probe_every_s
        elif self._probe is not None and now - self._next_probe + self.probe_every_s > self.timeout_s + 0.5:
            raise asyncio.TimeoutError("the connection probe did not answer")
        return dict(self.latest)

    async def write(self, values: Mapping[str, Any]) -> None:
        ua = _ua()
        try:
            await asyncio.wait_for(self.writer.write(values), self.timeout_s)
        except ua.UaStatusCodeError as exc:
            name = type(exc).__name__
            if name in FATAL_WRITE:
                raise CompensatorError(f"writing the compensation to {self.endpoint} was refused: {name} "
                                       f"({', '.join(f'{k}={self.writer.outputs[k]}' for k in values)})") from None  # fmt: skip
            raise

    async def close(self) -> None:
        if self._probe is not None:
            if self._probe.done():
                self._probe.exception()  # retrieved: a probe that failed is why we close
            else:
                self._probe.cancel()
            self._probe = None
        client, self.client, self.writer = self.client, None, None
        if client is not None:
            await _quiet_disconnect(client)


async def _quiet_disconnect(client) -> None:
    try:
        await asyncio.wait_for(client.disconnect(), 2.0)
    except Exception:  # the connection is gone already: nothing to close
        pass
    try:
        client.disconnect_socket()
    except Exception:  # no socket left
        pass
