"""``thermbench compensator MODEL_DIR --endpoint opc.tcp://HOST:PORT --nodes nodes.yaml``.

An OPC UA client (asyncua) beside the machine, the role of seed 002's STM32
compensator (§2.5, Fig. 14: it reads the CNC's axis state and temperatures and writes
the compensation back over OPC UA). Every cycle (``period_s`` of the client's clock,
scheduled on absolute deadlines so the cycle never drifts) it

1. reads the input nodes of ``nodes.yaml`` in one request (values and source timestamps);
2. runs :class:`~thermbench.compensator.control.CycleLogic`: input guard, the exported
   model stepped in the C runtime (:class:`thermbench.export.native.LiveModel`), rate limit;
3. writes the compensation, as the value at the current position and/or the error line
   (offset, slope, reference position) a stock controller takes, and the status flags;
4. appends one line to the cycle log (CSV, flushed every cycle).

A lost connection is retried in the background with exponential back-off while the
cycles go on, flagged ``DISCONNECTED`` with the compensation held at its last good value
(written again as soon as the server is back). Writes go through :class:`GuardedWriter`,
which refuses any node but the configured outputs.

Security: user name and password (the password from an environment variable, never
from a file), and ``Basic256Sha256`` sign-and-encrypt with the client's certificate and
the server certificate it pins (``thermbench certs`` makes self-signed pairs).
"""

from __future__ import annotations

import asyncio
import collections
import csv
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..outputs import OutputStream, check_output_file, write_text
from .control import TB_MAX_GAP_S, Cycle, CycleLogic, Deadlines, Flags, Line, Reading, Settings, _num, flag_names
from .state import StateError, StateStore
from .nodes import LENGTH_UNITS, SLOPE_UNITS, Nodes, load_nodes

CLIENT_APP_URI = "urn:thermbench:compensator"
STATS_CYCLES = 100_000  # the run's summary covers the last this many cycles


class CompensatorError(ValueError):
    """A compensator set-up that cannot work (names the config key, file or node)."""


class RefusedWrite(Exception):
    """The compensator was asked to write a node that is not one of its configured outputs
    (a programming error: never taken for a lost connection)."""


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


class CycleLog:
    """The per-cycle CSV log (one line per cycle, flushed each time)."""

    def __init__(self, path: Path, inputs: list[str]) -> None:
        self.path = Path(path)
        self.inputs = inputs
        self.out = OutputStream(self.path, "compensator-log")  # never over a file thermbench did not write
        self.fh = self.out.fh
        self.w = csv.writer(self.fh)
        self.w.writerow(["wall_s", "cycle", "t_s", "late_ms", "cycle_ms", *inputs, "held", "value_um", "offset_um",
                         "slope_um_per_m", "ref_mm", "predicted_um", "label", "rc", "flags", "flag_names"])  # fmt: skip

    def write(self, wall_s: float, k: int, c: Cycle, late_ms: float, cycle_ms: float) -> None:
        ln = c.line
        self.w.writerow([f"{wall_s:.6f}", k, _f(c.t_s), f"{late_ms:.3f}", f"{cycle_ms:.3f}",
                         *[_f(c.inputs.get(n)) for n in self.inputs], ";".join(c.held), _f(c.value_um),
                         _f(ln.offset_um if ln else None), _f(ln.slope_um_per_m if ln else None), _f(ln.ref_mm if ln else None),
                         _f(c.predicted_um), c.label, c.rc, c.flags, flag_names(c.flags)])  # fmt: skip

    def close(self) -> None:
        self.out.close()


def _f(v) -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else repr(float(v))


def cycle_stats(durations_ms, late_ms, index, starts_s, period_s: float) -> dict:
    """Cycle-time distribution and schedule drift of a run of cycles: ``index`` is each
    cycle's deadline number (deadline = start + index * period), so the mean period is the
    slope of start time over it and the drift the trend of the start lateness over the run."""
    d = np.asarray(durations_ms, dtype=float)
    lt = np.asarray(late_ms, dtype=float)
    st = np.asarray(starts_s, dtype=float)
    k = np.asarray(index, dtype=float)
    if d.size == 0:
        return {"cycles": 0}
    q = np.percentile(d, [50, 90, 99])
    lq = np.percentile(lt, [50, 99])
    fit = d.size > 2 and k[-1] > k[0]
    slope = float(np.polyfit(k, st - st[0], 1)[0]) if fit else float("nan")
    trend = float(np.polyfit(k, lt, 1)[0]) * (k[-1] - k[0]) if fit else float("nan")
    return {"cycles": int(d.size), "cycle_ms": {"p50": q[0], "p90": q[1], "p99": q[2], "max": float(d.max()),
                                                "mean": float(d.mean())},
            "late_ms": {"p50": lq[0], "p99": lq[1], "max": float(lt.max())},
            "over_period": int(np.sum(d > 1e3 * period_s)),
            "mean_period_ms": 1e3 * slope, "drift_ms": trend}  # fmt: skip


class Ring:
    """The last ``n`` values of a float series in a buffer allocated once (the loop's
    statistics take no memory per cycle, however long it runs)."""

    def __init__(self, n: int) -> None:
        self.buf = np.full(n, np.nan)  # written now: the pages are resident from the start, not one by one
        self.n = 0

    def append(self, v: float) -> None:
        self.buf[self.n % self.buf.size] = v
        self.n += 1

    def values(self) -> np.ndarray:
        if self.n <= self.buf.size:
            return self.buf[: self.n].copy()
        i = self.n % self.buf.size
        return np.concatenate([self.buf[i:], self.buf[:i]])

    def __len__(self) -> int:
        return self.n


class Compensator:
    """The control loop (see the module docstring); :meth:`run` returns the summary."""

    def __init__(self, model_dir: str | Path, endpoint: str, nodes_path: str | Path, cfg: Mapping[str, Any],
                 say: Callable[[str], None] | None = None) -> None:
        """``say``: where ``connected``, the status lines (every ``status_every_s``) and the
        reconnections go (the command prints them; None: silent)."""
        from ..config import with_defaults
        from ..export.native import LiveModel

        cfg = with_defaults("compensator", cfg)
        self.period_s = _num(cfg, "period_s", 0.1)
        self.output = str(cfg.get("output", "value"))
        self.model = LiveModel(model_dir)
        self.nodes = load_nodes(nodes_path, self.model.temperatures, self.model.needs_load, self.output,
                                getattr(self.model, "operating", []))  # fmt: skip
        self.logic = CycleLogic(self.model, Settings.from_config(cfg), self.output, has_load=self.model.needs_load,
                                has_measuring=self.nodes.inputs.measuring is not None)  # fmt: skip
        self.sec = Security.from_config(cfg.get("security"))
        self.endpoint = endpoint
        self.timeout_s = _num(cfg, "timeout_s", 2.0)
        rc = dict(cfg.get("reconnect") or {})
        self.backoff0 = _num(rc, "initial_s", 0.2, name="reconnect.initial_s")
        self.backoff_max = _num(rc, "max_s", 10.0, name="reconnect.max_s")
        self.backoff_factor = _num(rc, "factor", 2.0, name="reconnect.factor")
        if self.backoff_factor < 1 or self.backoff_max < self.backoff0:
            raise CompensatorError("config key 'reconnect': expected factor >= 1 and max_s >= initial_s, got "
                                   f"factor {self.backoff_factor}, initial_s {self.backoff0}, max_s {self.backoff_max}")  # fmt: skip
        max_cycles = None if cfg.get("max_cycles") is None else _num(cfg, "max_cycles", 1)
        if max_cycles is not None and (not math.isfinite(max_cycles) or max_cycles != int(max_cycles)):
            raise CompensatorError(f"config key 'max_cycles': expected null or a whole number > 0, got {max_cycles}")
        self.max_cycles = None if max_cycles is None else int(max_cycles)
        self.duration_s = None if cfg.get("duration_s") is None else _num(cfg, "duration_s", 1.0)
        self.status_every_s = _num(cfg, "status_every_s", 5.0)
        self.say = say
        self.log_path = Path(str(cfg.get("log", "compensator_log.csv")))
        check_output_file(self.log_path, "compensator-log")  # refused before anything connects
        check_output_file(self.log_path.with_suffix(".summary.json"), "compensator-summary")
        st = dict(cfg.get("state") or {})
        self.state_every_s = _num(st, "every_s", 5.0, name="state.every_s")
        self.state_max_gap_s = _num(st, "max_gap_s", 60.0, name="state.max_gap_s")
        self.state_agree_C = _num(st, "agree_C", 2.0, name="state.agree_C")
        self.state_history = bool(st.get("history", True))
        if self.state_max_gap_s > TB_MAX_GAP_S:
            raise CompensatorError(f"config key 'state.max_gap_s': at most {TB_MAX_GAP_S:g} s (the longest gap the C "
                                   f"runtime bridges), got {self.state_max_gap_s:g}")  # fmt: skip
        self.store = StateStore(str(st["path"])) if st.get("path") else None
        self.logic.keep_stepped = self.store is not None
        try:
            self.saved_state = self.store.load() if self.store is not None else None
        except StateError as exc:
            raise CompensatorError(str(exc)) from None
        self.resume_pending = self.store is not None
        self._flag_next = 0  # a flag for the next cycle (RESUMED)
        self.session = Session(endpoint, self.nodes, self.sec, self.timeout_s)
        self.stop_requested = False
        self.stop_reason = "stopped"
        self.connect_attempts: collections.deque = collections.deque(maxlen=1000)  # loop times of reconnection attempts
        self.last_error: str | None = None
        self.summary: dict | None = None

    def _say(self, line: str) -> None:
        if self.say is not None:
            self.say(line)

    def _resume_from_controller(self) -> None:
        """Ramp from what the controller holds (read when the session opened), not from zero."""
        resume_from_controller(self.logic, self.session.current, self.nodes)

    async def run(self) -> dict:
        """Connect (the first connection must succeed: a wrong endpoint or credentials are a
        set-up error), then cycle until done / max_cycles / duration_s / :meth:`stop`. The
        summary is written beside the log however the loop ends (also on Ctrl-C)."""
        try:
            log = CycleLog(self.log_path, self.logic.names)
        except OSError as exc:
            raise CompensatorError(f"config key 'log': cannot write {self.log_path}: {exc.strerror or exc}") from None
        try:
            await self.session.open()
        except CompensatorError:
            log.close()
            raise
        except Exception as exc:
            log.close()
            code = type(exc).__name__ if isinstance(exc, _ua().UaStatusCodeError) else None
            certificates = code not in NOT_CERTIFICATES  # stacks report a certificate refusal in many ways
            why = await explain_security_refusal(self.endpoint, self.session.sec, self.session.timeout_s) if certificates else None
            if why and code:
                why = f"{why} ({code})"
            raise CompensatorError(f"cannot connect to {self.endpoint}: {why or f'{type(exc).__name__}: {exc}'}") from None
        self._resume_from_controller()
        self._say(f"connected to {self.endpoint}: {len(self.session.inputs)} inputs, outputs "
                  f"{', '.join(self.nodes.output_ids())}")  # fmt: skip
        loop = asyncio.get_running_loop()
        durations, lates, starts, index = (Ring(STATS_CYCLES) for _ in range(4))
        window: list[float] = []  # cycle times since the last status line
        next_status = loop.time() + self.status_every_s
        next_state = loop.time() + self.state_every_s
        counts = collections.Counter()
        connecting: asyncio.Task | None = None
        backoff, next_try = self.backoff0, 0.0
        sched = Deadlines(self.period_s, loop.time(), self.max_cycles, self.duration_s)
        ended = None
        task = asyncio.current_task()
        try:
            while not self.stop_requested:
                if getattr(task, "cancelling", lambda: 0)():  # a cancellation some library call swallowed
                    raise asyncio.CancelledError
                k, deadline = sched.k, sched.deadline
                wait = sched.wait_s(loop.time())
                if wait > 0:
                    await asyncio.sleep(wait)
                begin = loop.time()
                done = False
                if connecting is not None and connecting.done():  # a reconnection attempt has ended
                    exc = connecting.exception()
                    connecting = None
                    if exc is None:
                        self._say(f"reconnected to {self.endpoint}")
                        counts["reconnects"] += 1
                        self.logic.reconnected()
                        self._resume_from_controller()  # a restarted controller may hold another value
                    else:
                        self.last_error = f"reconnecting: {type(exc).__name__}: {exc}"
                        next_try = begin + backoff
                        backoff = min(backoff * self.backoff_factor, self.backoff_max)
                if self.session.client is None and connecting is None and begin >= next_try:
                    connecting = asyncio.ensure_future(self.session.open())
                    self.connect_attempts.append(begin)
                if self.session.client is None:
                    c = self.logic.hold(Flags.DISCONNECTED)
                else:
                    c = None
                    try:
                        readings = await self.session.read()
                        if self.resume_pending:
                            await self._resume_or_cold(readings, begin)
                        c = self.logic.cycle(readings, begin, time.time())
                        c.flags, self._flag_next = int(c.flags | self._flag_next), 0
                        await self.session.write(output_variants(c, self.nodes, self.output))
                        done = bool(readings.get("done") and readings["done"].value)
                        backoff = self.backoff0  # a full cycle worked: the next outage starts the back-off afresh
                    except _connection_errors() as exc:
                        counts["connection_lost"] += 1
                        self.last_error = f"{type(exc).__name__}: {exc}"
                        self.logic.undo()  # what this cycle computed was not written
                        await self.session.close()
                        next_try = loop.time() + backoff
                        c = self.logic.hold(Flags.DISCONNECTED, c.t_s if c is not None else math.nan)
                end = loop.time()
                cyc_ms, late_ms = 1e3 * (end - begin), 1e3 * (begin - deadline)
                durations.append(cyc_ms)
                lates.append(late_ms)
                starts.append(begin)
                index.append(k)
                for f in Flags:
                    if f.value and c.flags & f.value:
                        counts[f.name] += 1
                if c.flags & Flags.RESTARTED:
                    self._say(f"COLD RESTART at machine time {c.t_s:.0f} s: the model restarted (a gap longer than the "
                              "runtime bridges, or the server's clock restarted); it starts from the machine as it is "
                              "now (flag COLD from here on)")  # fmt: skip
                if self.store is not None and end >= next_state:
                    self._save_state()
                    next_state = end + self.state_every_s
                log.write(time.time(), k, c, late_ms, cyc_ms)
                window.append(cyc_ms)
                if end >= next_status:
                    self._say(status_line(k, c, window))
                    window.clear()
                    next_status = end + self.status_every_s
                over = sched.next(end)
                if done:
                    ended = "the machine's program is done"
                    break
                if over:
                    ended = over
                    break
        except asyncio.CancelledError:
            ended = "interrupted"
            raise
        except BaseException as exc:
            ended = f"error: {type(exc).__name__}: {exc}"
            raise
        finally:
            log.close()
            if self.store is not None and not self.resume_pending:
                self._save_state()
                self.store.close()
            if connecting is not None:
                connecting.cancel()
            await self.session.close()
            if sched.skipped:
                counts["skipped_deadlines"] = sched.skipped
            self.summary = {"endpoint": self.endpoint, "model": self.model.manifest.get("name"), "period_s": self.period_s,
                            "output": self.output, "log": str(self.log_path), "ended": ended or self.stop_reason, "flags": dict(counts),
                            "last_error": self.last_error,
                            **cycle_stats(durations.values(), lates.values(), index.values(), starts.values(), self.period_s)}  # fmt: skip
            write_text(self.log_path.with_suffix(".summary.json"), json.dumps(self.summary, indent=2, default=float) + "\n",
                       "compensator-summary")
        return self.summary

    def _save_state(self) -> None:
        self.store.sync(self.logic.stepped, self.logic.starts)
        self.store.save({**self.logic.state(), "model": self.model.manifest.get("name"), "saved_utc": time.time()})

    async def _resume_or_cold(self, readings, now_wall_s: float) -> None:
        """At the first reading: go on from the saved state (warm), replay an outage longer than
        the runtime bridges from the server's history (OPC UA Historical Access) when it keeps one,
        or start cold; saying which."""
        self.resume_pending = False
        saved = self.saved_state
        if saved is None:  # the first start: nothing says the machine ran before
            self._say(f"starting fresh: no saved state at {self.store.path} (the machine as it is now is the model's zero)")
            self.store.sync(self.logic.stepped, self.logic.starts)
            return
        state, rows = saved
        ts = self.logic._machine_ts(readings, now_wall_s, time.time())
        now = {n: float(r.value) for n, r in readings.items() if r is not None and isinstance(r.value, (int, float))}
        warm, why = self.logic.resume_decision(state, rows, ts, now, self.state_max_gap_s, self.state_agree_C)
        if not warm and self.state_history and why.startswith("the saved state is ") and "old" in why:
            missed, note = await self._history_rows(state, rows, ts)
            if missed:
                rows = np.vstack([rows, np.asarray(missed, dtype=float)])
                state = {**state, "last_ts": float(state["t0_ts"]) + missed[-1][0] * self.logic.period_s}
                warm, why2 = self.logic.resume_decision(state, rows, ts, now, self.state_max_gap_s, self.state_agree_C)
                why = (f"{why}: the outage replayed from the server's history ({len(missed)} samples), {why2}" if warm
                       else f"{why}; after the server's history: {why2}")  # fmt: skip
            else:
                why = f"{why}, and {note}"
        if warm:
            self.logic.warm_start(state, rows)
            self._resume_from_controller()  # what the controller holds now, if it says, is where the ramp starts
            self._flag_next = Flags.RESUMED
            self._say(f"resumed the model state of {self.store.path}: {why}")
        else:
            self.logic.cold = True
            self._say(f"COLD START: {why}; the model starts from the machine as it is now, and a machine still warm "
                      "from before reads as its zero (flag COLD on every cycle of this run)")  # fmt: skip
        self.store.sync(self.logic.stepped, self.logic.starts)

    async def _history_rows(self, state: dict, rows, ts_now: float) -> tuple[list[tuple], str]:
        """The samples the model missed (grid points after the saved state, before now), from the
        server's raw history of every input (each value held until the next, as the loop holds
        them); ([], why not) when the server keeps none or it has a hole longer than the runtime
        bridges."""
        import datetime as dt

        ua = _ua()
        lg = self.logic
        t0, p = float(state["t0_ts"]), lg.period_s
        k_last, k_now = int(rows[-1][0]), math.floor((ts_now - t0) / p + 1e-3)
        if k_now - k_last <= 1:
            return [], "no sample is missing"
        start = dt.datetime.fromtimestamp(float(state["last_ts"]), dt.timezone.utc)
        end = dt.datetime.fromtimestamp(ts_now, dt.timezone.utc)
        series: dict[str, tuple[np.ndarray, list]] = {}
        for name, node in zip(self.session.inputs, self.session.input_nodes):
            if name in ("done", "heartbeat"):
                continue
            try:
                dvs = await asyncio.wait_for(node.read_raw_history(start, end), 10 * self.timeout_s)
            except (ua.UaStatusCodeError, asyncio.TimeoutError) as exc:
                return [], f"the server keeps no history of {name} ({type(exc).__name__})"
            pts = sorted((dv.SourceTimestamp.timestamp(), dv.Value.Value) for dv in dvs
                         if dv.SourceTimestamp is not None and dv.Value is not None and dv.StatusCode.is_good())  # fmt: skip
            if not pts:
                return [], f"the server's history of {name} is empty for the outage"
            t = np.array([q[0] for q in pts])
            holes = np.diff(np.concatenate([[float(state["last_ts"])], t, [ts_now]]))
            if holes.max() > self.state_max_gap_s:
                return [], f"the server's history of {name} has a hole of {holes.max():.0f} s"
            series[name] = (t, [q[1] for q in pts])
        n0 = len(lg.STATE_COLUMNS)
        last = rows[-1]
        held = {"axis_mm": last[1], "feed_mm_min": last[2], "load_N": last[3], "measuring": last[4],
                **{f"{s}_C": last[n0 + j] for j, s in enumerate(lg.model.temperatures)},
                **{o: last[n0 + len(lg.model.temperatures) + j] for j, o in enumerate(lg.operating)}}  # fmt: skip
        out = []
        for k in range(k_last + 1, k_now):
            t = t0 + k * p
            v = dict(held)
            for name, (ts, vals) in series.items():
                i = int(np.searchsorted(ts, t + 1e-3 * p)) - 1  # the grid's tolerance: stamps carry float rounding
                if i >= 0:
                    v[name] = float(vals[i])
            out.append((k, v["axis_mm"], v["feed_mm_min"], v.get("load_N", 0.0), float(bool(v.get("measuring", 0.0))),
                        *[v[f"{s}_C"] for s in lg.model.temperatures], *[v[o] for o in lg.operating]))  # fmt: skip
        return out, ""

    def stop(self, reason: str = "stopped") -> None:
        """End the loop after the current cycle (the summary says ``reason``)."""
        self.stop_reason = reason
        self.stop_requested = True


def run_compensator(model_dir, endpoint: str, nodes_path, cfg: Mapping[str, Any]) -> dict:
    """Plain entry point (the CLI's): run the loop to its end and return the summary."""
    return asyncio.run(Compensator(model_dir, endpoint, nodes_path, cfg).run())


def status_line(k: int, c, cycle_ms: Sequence[float]) -> str:
    """One line of the running loop: cycles so far, the cycle times since the last line (mean,
    max), machine time, the compensation written and the flags of the latest cycle."""
    names = "|".join(f.name for f in Flags if f.value and c.flags & f.value) or "OK"
    value = "-" if c.value_um is None or not math.isfinite(c.value_um) else f"{c.value_um:+.2f} um"
    ms = np.asarray(cycle_ms, dtype=float)
    t = "-" if c.t_s is None or not math.isfinite(c.t_s) else f"{c.t_s:.0f} s"
    return (f"cycle {k + 1}: {ms.mean():.2f} ms mean, {ms.max():.2f} ms max over {ms.size} cycles; machine time {t}; "
            f"compensation {value}; {names}")  # fmt: skip


def format_summary(s: dict) -> str:
    if not s.get("cycles"):
        return f"compensator: no cycles ran against {s['endpoint']}"
    c, lt = s["cycle_ms"], s["late_ms"]
    flags = ", ".join(f"{k} {v}" for k, v in sorted(s["flags"].items())) or "none"
    return "\n".join([
        f"compensator {s['model']} -> {s['endpoint']}: {s['cycles']} cycles at {1e3 * s['period_s']:.0f} ms ({s['output']})",
        f"  cycle time p50 {c['p50']:.2f} ms, p90 {c['p90']:.2f} ms, p99 {c['p99']:.2f} ms, max {c['max']:.2f} ms; "
        f"start lateness p50 {lt['p50']:.2f} ms, p99 {lt['p99']:.2f} ms; mean period {s['mean_period_ms']:.3f} ms, "
        f"lateness trend over the run {s['drift_ms']:+.2f} ms",
        f"  flags: {flags}; ended: {s['ended']}" + (f"; last connection error: {s['last_error']}" if s.get("last_error") else ""),
        f"  log -> {s['log']} (summary beside it)",
    ])  # fmt: skip
