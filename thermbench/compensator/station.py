"""``thermbench station STATION.yaml``: one compensator process for several axes and spindle
channels, reading from more than one OPC UA endpoint.

A machine has more than one thermally drifting part (the feed axes, the spindle), and its
temperatures often come from a separate logger, not from the CNC. The station file names the
endpoints and the channels::

    period_s: 0.1
    log_dir: station_logs            # <channel>.csv per channel (+ .summary.json), station.summary.json
    status_every_s: 5.0
    endpoints:
      cnc: {url: "opc.tcp://cnc:4840"}                       # security: as thermbench compensator's
      logger: {url: "opc.tcp://logger:4841", security: {...}, read: subscribe}
    channels:
      X:                              # a feed axis
        model: exports/x_axis         # thermbench export
        nodes: nodes_x.yaml           # as for thermbench compensator; an input node id may name another
        endpoint: cnc                 #   endpoint: "logger::ns=2;s=T_nut" (outputs go to the channel's endpoint)
        output: value
        config: {rate_limit_um_s: 10} # conf/compensator.yaml keys of this channel's cycle rules
      spindle_z:                      # a spindle channel: a model with operating inputs (spindle_rpm)
        model: exports/spindle_z
        nodes: nodes_spindle.yaml
        endpoint: cnc

Every cycle takes the inputs of every connected endpoint, runs each
channel's :class:`~thermbench.compensator.control.CycleLogic`, and writes each endpoint's
outputs in one request. Inputs come from an OPC UA subscription (``read: subscribe``, the
default: the server publishes every change of value or timestamp each period, so no read
request sits in the cycle; the connection is probed every second in the background) or from one
read request per cycle (``read: poll``, as ``thermbench compensator`` does). **A fault holds only what it touches**: an endpoint that is down holds
the channels that write to it (``DISCONNECTED|HELD``) and, for the channels that only read from
it, those inputs (``INPUT_HELD``, their last good values); a bad sensor holds that channel's
input; each endpoint reconnects on its own with back-off.
"""

from __future__ import annotations

import asyncio
import collections
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from ..outputs import check_output_file, write_text
from .control import Cycle, CycleLogic, Flags, flag_names
from .cyclelog import STATS_CYCLES, CycleLog, Ring, cycle_stats
from .deadlines import Deadlines
from .errors import CompensatorError
from .opcua import Security, Session, _connection_errors, output_variants, resume_from_controller
from .nodes import Nodes, NodesError, load_nodes, read_yaml_file
from .settings import Settings, _num

SEP = "::"  # "<endpoint>::<node id>": an input node on another endpoint than its channel's


class StationError(CompensatorError):
    """A station file that cannot work (names the file and key)."""


class EndpointNodes:
    """What one endpoint's session reads and writes for every channel (``<channel>/<name>``)."""

    def __init__(self) -> None:
        self.ins: dict[str, str] = {}
        self.outs: dict[str, str] = {}

    def input_ids(self) -> dict[str, str]:
        return dict(self.ins)

    def output_ids(self) -> dict[str, str]:
        return dict(self.outs)


@dataclass
class Channel:
    name: str
    endpoint: str
    output: str
    nodes: Nodes
    logic: CycleLogic
    model: Any
    inputs: dict[str, tuple[str, str]] = field(default_factory=dict)  # input name -> (endpoint, session key)
    log: CycleLog | None = None
    last: Cycle | None = None
    counts: collections.Counter = field(default_factory=collections.Counter)


@dataclass
class Endpoint:
    name: str
    url: str
    sec: Security
    nodes: EndpointNodes
    session: Session | None = None
    connecting: asyncio.Task | None = None
    backoff_s: float = 0.0
    next_try: float = 0.0
    last_error: str | None = None


def _key(spec: Mapping[str, Any], key: str, where: str, kind: type | tuple = str):
    v = spec.get(key)
    if not isinstance(v, kind) or isinstance(v, bool) and kind is not bool:
        raise StationError(f"{where}: key {key!r}: expected {getattr(kind, '__name__', kind)}, got {v!r}")
    return v


def load_station(path: str | Path) -> dict:
    path = Path(path)
    if not path.is_file():
        raise StationError(f"{path}: no such station file (see thermbench/compensator/station.py for its form)")
    spec = read_yaml_file(path, "a station file", StationError) or {}
    if not isinstance(spec, dict):
        raise StationError(f"{path}: expected a mapping with endpoints and channels")
    unknown = sorted(set(spec) - {"period_s", "log_dir", "status_every_s", "timeout_s", "reconnect", "endpoints", "channels",
                                  "duration_s", "max_cycles"})  # fmt: skip
    if unknown:
        raise StationError(f"{path}: unknown key(s) {unknown}")
    for key in ("endpoints", "channels"):
        if not isinstance(spec.get(key), dict) or not spec[key]:
            raise StationError(f"{path}: key {key!r}: expected a mapping of at least one {key[:-1]}")
    spec["_dir"] = path.parent
    spec["_path"] = path
    return spec


class Station:
    """The loop over every channel and endpoint (module docstring); :meth:`run` returns the summary."""

    def __init__(self, spec: Mapping[str, Any], say: Callable[[str], None] | None = None) -> None:
        from ..config import with_defaults
        from ..export.native import LiveModel

        where = str(spec.get("_path", "station"))
        base = Path(spec.get("_dir", "."))
        self.period_s = _num(spec, "period_s", 0.1)
        self.status_every_s = _num(spec, "status_every_s", 5.0)
        self.timeout_s = _num(spec, "timeout_s", 2.0)
        rc = dict(spec.get("reconnect") or {})
        self.backoff0 = _num(rc, "initial_s", 0.2, name="reconnect.initial_s")
        self.backoff_max = _num(rc, "max_s", 10.0, name="reconnect.max_s")
        self.backoff_factor = _num(rc, "factor", 2.0, name="reconnect.factor")
        self.duration_s = None if spec.get("duration_s") is None else _num(spec, "duration_s", 1.0)
        self.max_cycles = None if spec.get("max_cycles") is None else int(_num(spec, "max_cycles", 1))
        self.log_dir = Path(str(spec.get("log_dir") or "station_logs"))
        self.say = say
        self.endpoints: dict[str, Endpoint] = {}
        for name, ep in spec["endpoints"].items():
            w = f"{where}: endpoints.{name}"
            if not isinstance(ep, dict):
                raise StationError(f"{w}: expected a mapping with url (and security)")
            url = _key(ep, "url", w)
            try:
                sec = Security.from_config(ep.get("security"))
            except CompensatorError as exc:
                raise StationError(f"{w}: {exc}") from None
            self.endpoints[str(name)] = Endpoint(str(name), url, sec, EndpointNodes(), backoff_s=self.backoff0)
        self.channels: list[Channel] = []
        for name, ch in spec["channels"].items():
            w = f"{where}: channels.{name}"
            if not isinstance(ch, dict):
                raise StationError(f"{w}: expected a mapping with model, nodes, endpoint")
            if "/" in str(name) or SEP in str(name):
                raise StationError(f"{w}: a channel name may not contain '/' or '::'")
            endpoint = _key(ch, "endpoint", w)
            if endpoint not in self.endpoints:
                raise StationError(f"{w}: key 'endpoint': {endpoint!r} is not one of the endpoints {sorted(self.endpoints)}")
            output = str(ch.get("output", "value"))
            cfg = with_defaults("compensator", {**dict(ch.get("config") or {}), "output": output})
            model = LiveModel(base / _key(ch, "model", w))
            try:
                nodes = load_nodes(base / _key(ch, "nodes", w), model.temperatures, model.needs_load, output, model.operating)
            except NodesError as exc:
                raise StationError(f"{w}: {exc}") from None
            logic = CycleLogic(model, Settings.from_config(cfg), output, has_load=model.needs_load,
                               has_measuring=nodes.inputs.measuring is not None)  # fmt: skip
            c = Channel(str(name), endpoint, output, nodes, logic, model)
            for iname, nid in nodes.input_ids().items():
                ep_name, node = endpoint, nid
                if SEP in nid:
                    ep_name, node = nid.split(SEP, 1)
                    if ep_name not in self.endpoints:
                        raise StationError(f"{w}: input {iname} {nid!r}: {ep_name!r} is not one of the endpoints "
                                           f"{sorted(self.endpoints)}")  # fmt: skip
                key = f"{name}/{iname}"
                self.endpoints[ep_name].nodes.ins[key] = node
                c.inputs[iname] = (ep_name, key)
                if ep_name != endpoint:
                    logic.foreign.add(iname)
            for oname, nid in nodes.output_ids().items():
                if SEP in nid:
                    raise StationError(f"{w}: output {oname} {nid!r}: outputs go to the channel's endpoint ({endpoint}); "
                                       "no '<endpoint>::' prefix")  # fmt: skip
                self.endpoints[endpoint].nodes.outs[f"{name}/{oname}"] = nid
            self.channels.append(c)
        names = [c.name for c in self.channels]
        for p in [self.log_dir / "station.summary.json", *(self.log_dir / f"{n}.csv" for n in names)]:
            check_output_file(p, "compensator-log" if p.suffix == ".csv" else "compensator-summary")
        for name, ep in self.endpoints.items():
            mode = spec["endpoints"][name].get("read", "subscribe")
            if mode not in ("subscribe", "poll"):
                raise StationError(f"{where}: endpoints.{name}: key 'read': expected subscribe or poll, got {mode!r}")
            ep.session = Session(ep.url, ep.nodes, ep.sec, self.timeout_s,
                                 subscribe_ms=1e3 * self.period_s if mode == "subscribe" else None)  # fmt: skip
        self.stop_requested = False

    def _say(self, line: str) -> None:
        if self.say is not None:
            self.say(line)

    def stop(self, reason: str = "stopped") -> None:
        self.stop_requested = True

    async def _open_all(self) -> None:
        """The first connection to every endpoint must succeed: a wrong URL or credential is a set-up error."""
        for ep in self.endpoints.values():
            try:
                await ep.session.open()
            except CompensatorError:
                raise
            except Exception as exc:
                raise StationError(f"endpoint {ep.name}: cannot connect to {ep.url}: {type(exc).__name__}: {exc}") from None

    async def _read(self, ep: Endpoint):
        return await ep.session.read()

    async def run(self) -> dict:
        for c in self.channels:
            c.log = CycleLog(self.log_dir / f"{c.name}.csv", c.logic.names)
        try:
            await self._open_all()
        except BaseException:
            for c in self.channels:
                c.log.close()
            for ep in self.endpoints.values():
                await ep.session.close()
            raise
        for ep in self.endpoints.values():
            self._resume_channels(ep)
        self._say(f"connected to {len(self.endpoints)} endpoint(s) ({', '.join(self.endpoints)}): {len(self.channels)} "
                  f"channels ({', '.join(c.name for c in self.channels)})")  # fmt: skip
        loop = asyncio.get_running_loop()
        durations, lates, starts, index = (Ring(STATS_CYCLES) for _ in range(4))
        window: list[float] = []
        sched = Deadlines(self.period_s, loop.time(), self.max_cycles, self.duration_s)
        next_status = loop.time() + self.status_every_s
        ended = "stopped"
        try:
            while not self.stop_requested:
                k, deadline = sched.k, sched.deadline
                wait = sched.wait_s(loop.time())
                if wait > 0:
                    await asyncio.sleep(wait)
                begin = loop.time()
                self._reconnect(begin)
                live = [ep for ep in self.endpoints.values() if ep.session.client is not None]
                got = await asyncio.gather(*(self._read(ep) for ep in live), return_exceptions=True)
                readings: dict[str, Any] = {}
                for ep, r in zip(live, got):
                    if isinstance(r, BaseException):
                        if not isinstance(r, _connection_errors()):
                            raise r
                        await self._lost(ep, r, begin)
                    else:
                        readings.update(r)
                        ep.backoff_s = self.backoff0  # it worked: the next outage backs off afresh
                writes: dict[str, dict] = collections.defaultdict(dict)
                wall = time.time()
                for c in self.channels:
                    ep = self.endpoints[c.endpoint]
                    if ep.session.client is None:
                        cy = c.logic.hold(Flags.DISCONNECTED, c.last.t_s if c.last is not None else math.nan)
                    else:
                        mine = {iname: readings.get(key) for iname, (_, key) in c.inputs.items()}
                        cy = c.logic.cycle({n: r for n, r in mine.items() if r is not None}, begin, wall)
                        for oname, v in output_variants(cy, c.nodes, c.output).items():
                            writes[c.endpoint][f"{c.name}/{oname}"] = v
                    c.last = cy
                    for f in Flags:
                        if f.value and cy.flags & f.value:
                            c.counts[f.name] += 1
                for name, values in writes.items():
                    ep = self.endpoints[name]
                    if ep.session.client is None:
                        continue
                    try:
                        await ep.session.write(values)
                    except _connection_errors() as exc:
                        for c in self.channels:
                            if c.endpoint == name:
                                c.logic.undo()
                        await self._lost(ep, exc, begin)
                end = loop.time()
                cyc_ms, late_ms = 1e3 * (end - begin), 1e3 * (begin - deadline)
                for ring, v in zip((durations, lates, starts, index), (cyc_ms, late_ms, begin, k)):
                    ring.append(v)
                for c in self.channels:
                    c.log.write(wall, k, c.last, late_ms, cyc_ms)
                window.append(cyc_ms)
                if end >= next_status:
                    self._say(self.status_line(k, window))
                    window.clear()
                    next_status = end + self.status_every_s
                over = sched.next(end)
                if over:
                    ended = over
                    break
        except asyncio.CancelledError:
            ended = "interrupted"
            raise
        finally:
            for c in self.channels:
                c.log.close()
            for ep in self.endpoints.values():
                if ep.connecting is not None:
                    ep.connecting.cancel()
                await ep.session.close()
            self.summary = {"period_s": self.period_s, "ended": ended, "endpoints": {n: e.url for n, e in self.endpoints.items()},
                            "channels": {c.name: {"model": c.model.manifest.get("name"), "endpoint": c.endpoint,
                                                  "flags": dict(c.counts), "log": str(self.log_dir / f"{c.name}.csv")}
                                         for c in self.channels},
                            "last_errors": {n: e.last_error for n, e in self.endpoints.items() if e.last_error},
                            "skipped_deadlines": sched.skipped,
                            **cycle_stats(durations.values(), lates.values(), index.values(), starts.values(), self.period_s)}  # fmt: skip
            import json

            write_text(self.log_dir / "station.summary.json", json.dumps(self.summary, indent=2, default=float) + "\n",
                       "compensator-summary")  # fmt: skip
        return self.summary

    def _reconnect(self, now: float) -> None:
        for ep in self.endpoints.values():
            if ep.connecting is not None and ep.connecting.done():
                exc = ep.connecting.exception()
                ep.connecting = None
                if exc is None:
                    self._say(f"reconnected to {ep.name} ({ep.url})")
                    for c in self.channels:
                        if any(e == ep.name for e, _ in c.inputs.values()):
                            c.logic.reconnected()
                    self._resume_channels(ep)  # a restarted controller may hold another value
                else:
                    ep.last_error = f"reconnecting: {type(exc).__name__}: {exc}"
                    ep.next_try = now + ep.backoff_s
                    ep.backoff_s = min(ep.backoff_s * self.backoff_factor, self.backoff_max)
            if ep.session.client is None and ep.connecting is None and now >= ep.next_try:
                ep.connecting = asyncio.ensure_future(ep.session.open())

    def _resume_channels(self, ep: Endpoint) -> None:
        """The channels writing to ``ep`` ramp from what its controller holds, not from zero."""
        for c in self.channels:
            if c.endpoint == ep.name:
                resume_from_controller(c.logic, ep.session.current, c.nodes, prefix=f"{c.name}/")

    async def _lost(self, ep: Endpoint, exc: BaseException, now: float) -> None:
        ep.last_error = f"{type(exc).__name__}: {exc}"
        await ep.session.close()
        ep.next_try = now + ep.backoff_s
        self._say(f"lost {ep.name} ({ep.url}): {ep.last_error}; holding what it touches")

    def status_line(self, k: int, cycle_ms) -> str:
        ms = np.asarray(cycle_ms, dtype=float)
        parts = []
        for c in self.channels:
            cy = c.last
            v = "-" if cy is None or cy.value_um is None or not math.isfinite(cy.value_um) else f"{cy.value_um:+.2f} um"
            parts.append(f"{c.name} {v} {flag_names(cy.flags) if cy is not None else '-'}")
        return f"cycle {k + 1}: {ms.mean():.2f} ms mean, {ms.max():.2f} ms max over {ms.size} cycles; " + " | ".join(parts)


def run_station(path, overrides: Mapping[str, Any] | None = None, say=None) -> dict:
    spec = {**load_station(path), **dict(overrides or {})}
    return asyncio.run(Station(spec, say=say).run())


def format_summary(s: dict) -> str:
    if not s.get("cycles"):
        return "station: no cycles ran"
    c = s["cycle_ms"]
    lines = [f"station: {s['cycles']} cycles at {1e3 * s['period_s']:.0f} ms over {len(s['channels'])} channels, "
             f"{len(s['endpoints'])} endpoints; cycle time p50 {c['p50']:.2f} ms, p99 {c['p99']:.2f} ms, max {c['max']:.2f} ms; "
             f"ended: {s['ended']}"]  # fmt: skip
    for name, ch in s["channels"].items():
        flags = ", ".join(f"{k} {v}" for k, v in sorted(ch["flags"].items())) or "none"
        lines.append(f"  {name} ({ch['model']}, {ch['endpoint']}): flags {flags}; log {ch['log']}")
    return "\n".join(lines)
