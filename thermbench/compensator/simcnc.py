"""``thermbench sim-cnc``: a simulated CNC axis behind an OPC UA server, for closing the
compensation loop on one machine.

The machine runs one run of a dataset's protocol:

* ``benchmark=<benchmark dataset>`` (default ``seed001_vmc_x``): the run is simulated by the ball-screw
  simulator (seed 000 §3, :func:`thermbench.sim.scenario.simulate_dataset` with just
  that run: the same numbers as the benchmark dataset), so the thermal error is known at
  every position and time, not only at the interferometer readings;
* ``data_dir=<dataset>``: a dataset in the contract format is played back (the error is
  then known at its readings only).

Its clock runs at ``speed`` times real time (1 = real time). At each process-log sample
the server publishes the axis position, feed, load, the measuring flag and every
temperature sensor, each stamped with the machine time as source timestamp (start of
the clock + sample time: the compensator reads machine time from it). By default the
program starts when a client first reads the machine (``start: on_compensator``), so the
compensator sees the whole run, as ``thermbench replay`` does.

The compensation written to the server is applied to the simulated axis as a
controller does: the value added to the position set point, so the axis's error
becomes ``error + compensation``. The machine takes the error line (SINUMERIK SD43900
offset at SD43920, gradient SD43910: ``comp(x) = offset + slope (x - ref)``) when all
three have been written, else the position value (``apply: auto``; or ``line`` /
``value``). Every interferometer reading of the run is scored with the compensation in
force at its time; with the simulator, so is every sample at the axis position.

At the end (``out_dir``): ``closed_loop.json`` (before/after figures, the same as
``thermbench replay`` computes), ``readings.csv``, ``samples.csv`` and ``dataset/`` (the
run as played, in the contract format: ``thermbench replay MODEL out_dir/dataset --run
RUN`` gives what the loop should achieve).
"""

from __future__ import annotations

import asyncio
import datetime as _dt
import json
import math
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd
from ..data.safe_yaml import dump_yaml

from ..outputs import check_output_dir, check_output_file, output_dir, write_text
from .nodes import LENGTH_UNITS, SLOPE_UNITS

NAMESPACE = "urn:thermbench:sim-cnc"
SERVER_APP_URI = "urn:thermbench:sim-cnc:server"

# writable nodes and their units (what --write-nodes puts in nodes.yaml)
COMP_VALUE = ("TempComp_um", "um")
COMP_OFFSET = ("SD43900_TEMP_COMP_ABS_VALUE", "mm")
COMP_SLOPE = ("SD43910_TEMP_COMP_SLOPE", "ratio")
COMP_REF = ("SD43920_TEMP_COMP_REF_POSITION", "mm")
COMP_STATUS = "TempComp_Status"
PROBE = ("Probe_um", "um")  # a touch probe's reading: the thermal error (the model's sign), stamped when taken


class SimCncError(ValueError):
    """A sim-cnc set-up that cannot work (names the config key or file)."""


@dataclass
class Machine:
    """One run to play: the process samples (with ``measuring``), the readings (with
    ``thermal_um``), the error at each sample's position (NaN when unknown) and its dataset."""

    run: str
    samples: pd.DataFrame
    readings: pd.DataFrame
    sample_error_um: np.ndarray
    sensors: list[str]
    dataset: Any
    sample_thermal_um: np.ndarray | None = None  # the thermal part of sample_error_um (no geometric error): a probe's reading

    def probes(self, every_s: float) -> pd.DataFrame:
        """What a touch probe reads every ``every_s`` machine seconds (the first one ``every_s``
        after the run starts): the thermal error (µm, the dataset's and the model's sign) at the
        first sample at or after each time, where the axis then is; a played-back dataset, whose
        error is known at its readings only, gives the first reading's ``thermal_um`` instead."""
        simulated = self.sample_thermal_um is not None and np.isfinite(self.sample_thermal_um).all()
        src = self.samples if simulated else self.readings
        t = src["t_s"].to_numpy(dtype=float)
        x = src["axis_mm" if simulated else "target_mm"].to_numpy(dtype=float)
        v = self.sample_thermal_um if simulated else src["thermal_um"].to_numpy(dtype=float)
        t0 = float(self.samples["t_s"].iloc[0])
        due = t0 + every_s * np.arange(1, int((t[-1] - t0) // every_s) + 1) if t.size else np.zeros(0)
        k = np.unique(np.searchsorted(t, due - 1e-9))
        k = k[k < t.size]
        return pd.DataFrame({"t_s": t[k], "axis_mm": x[k], "measured_um": v[k]})


def build_machine(cfg: Mapping[str, Any]) -> Machine:
    """The run sim-cnc plays, from ``benchmark`` (simulated) or ``data_dir`` (played back)."""
    from ..data.io import Dataset, load_dataset
    from ..data.reference import thermal_errors
    from ..config import with_defaults
    from ..export.samples import process_samples

    cfg = with_defaults("sim_cnc", cfg)
    run = str(cfg.get("run") or "")
    if not run:
        raise SimCncError("config key 'run': which run of the dataset the machine runs (e.g. run=valid1)")
    err_fn = thermal_fn = None
    if cfg.get("data_dir"):
        ds = load_dataset(Path(str(cfg["data_dir"])))
        if run not in ds.run_ids:
            raise SimCncError(f"config key 'run': {run!r} is not a run of {cfg['data_dir']}; its runs: {ds.run_ids}")
    else:
        from ..bench import datasets
        from ..sim.scenario import simulate_dataset

        key = str(cfg.get("benchmark") or "")
        if key not in datasets.names():
            raise SimCncError(f"config key 'benchmark': {key!r} is not a benchmark dataset; known: {datasets.names()}")
        ds, summary = simulate_dataset(datasets.benchmark_config(key), runs_only=[run])
        hist, geo = summary["histories"][run], summary["geometric"]

        def thermal_fn(t, x):
            return hist.error_um(t, x)

        def err_fn(t, x):
            return thermal_fn(t, x) + geo(x)

    dur = cfg.get("duration_s")
    if dur is not None:
        dur = float(dur)
        if not dur > 0:
            raise SimCncError(f"config key 'duration_s': must be > 0 s, got {dur}")
        pr = ds.process[(ds.process["run_id"] != run) | (ds.process["t_s"] <= dur)]
        er = ds.errors[(ds.errors["run_id"] != run) | (ds.errors["t_s"] <= dur)]
        ds = Dataset(ds.metadata, pr.reset_index(drop=True), er.reset_index(drop=True), path=ds.path)
    # just this run, as a dataset of its own (what the loop is compared against)
    pr = ds.process[ds.process["run_id"] == run].reset_index(drop=True)
    er = ds.errors[ds.errors["run_id"] == run].reset_index(drop=True)
    meta = ds.metadata.model_copy(deep=True)
    meta.runs = {run: meta.runs[run]}
    one = Dataset(meta, pr, er, path=ds.path)
    samples = process_samples(one, run)
    te = thermal_errors(one)
    t, x = samples["t_s"].to_numpy(), samples["axis_mm"].to_numpy()
    e = err_fn(t, x) if err_fn is not None else np.full(t.size, np.nan)
    th = np.asarray(thermal_fn(t, x), dtype=float) if thermal_fn is not None else None
    return Machine(run, samples, te, np.asarray(e, dtype=float), list(one.metadata.sensors), one, th)


def nodes_yaml(machine: Machine, axis: str = "X", probe: bool = False) -> dict:
    """The nodes file of this server's address space (``thermbench compensator --nodes``). The
    node ids carry the namespace URI (``nsu=urn:thermbench:sim-cnc;s=...``), which the
    compensator resolves to this server's index when it connects. ``probe``: the server has the
    probe node (``probe_every_s``), and the compensator takes it."""
    ns = f"nsu={NAMESPACE};s="
    inputs = {"axis_mm": f"{ns}{axis}.Position_mm", "feed_mm_min": f"{ns}{axis}.Feed_mm_min",
              "load_N": f"{ns}{axis}.Load_N" if "load_N" in machine.samples else None,
              "measuring": f"{ns}{axis}.Measuring", "done": f"{ns}Machine.ProgramDone",
              "temperatures": {s: f"{ns}{axis}.{s}_C" for s in machine.sensors}}  # fmt: skip
    if probe:
        inputs["probe"] = f"{ns}{axis}.{PROBE[0]}"
    outputs = {"value": {"node": f"{ns}{axis}.{COMP_VALUE[0]}", "unit": COMP_VALUE[1]},
               "line": {"offset": {"node": f"{ns}{axis}.{COMP_OFFSET[0]}", "unit": COMP_OFFSET[1]},
                        "slope": {"node": f"{ns}{axis}.{COMP_SLOPE[0]}", "unit": COMP_SLOPE[1]},
                        "ref": {"node": f"{ns}{axis}.{COMP_REF[0]}", "unit": COMP_REF[1]}},
               "status": f"{ns}{axis}.{COMP_STATUS}"}  # fmt: skip
    return {"inputs": inputs, "outputs": outputs}


def _password(sec: Mapping[str, Any]) -> str:
    env = str(sec.get("password_env") or "THERMBENCH_OPCUA_PASSWORD")
    pw = os.environ.get(env)
    if not pw:
        raise SimCncError(f"config key 'security.user' is set, so the password is read from the environment variable "
                          f"{env} (security.password_env), which is not set")  # fmt: skip
    return pw


class _Users:
    """asyncua user manager: exactly one user name and password (compared in constant time)."""

    def __init__(self, user: str, password: str) -> None:
        self.user, self.password = user, password

    def get_user(self, iserver, username=None, password=None, certificate=None):
        import hmac

        from asyncua.crypto.permission_rules import User, UserRole

        if username == self.user and password is not None and hmac.compare_digest(str(password).encode(), self.password.encode()):
            return User(role=UserRole.User)
        return None


def _trusted_only(paths: list[str]):
    """A certificate validator that admits exactly the given client certificates."""
    from asyncua import ua
    from asyncua.crypto import uacrypto
    from asyncua.common.utils import ServiceError

    allowed = set()
    for p in paths:
        if not Path(p).is_file():
            raise SimCncError(f"config key 'security.trusted_clients': {p!r} is not a file")
        data = Path(p).read_bytes()
        cert = uacrypto.x509_from_der(data) if not data.startswith(b"-----") else uacrypto.x509_from_pem(data)
        allowed.add(cert.fingerprint(uacrypto.hashes.SHA256()))

    async def validate(cert, app_description) -> None:
        if cert.fingerprint(uacrypto.hashes.SHA256()) not in allowed:
            raise ServiceError(ua.StatusCodes.BadCertificateUntrusted)

    return validate


def _faults(spec, sensors: list[str]) -> dict[str, list[dict]]:
    """``faults``: ``sensor: [{sensor, from_s, to_s, value}]`` publishes ``value`` (e.g. .nan,
    or out of range) for a sensor in that window of machine time; ``freeze: [{from_s,
    to_s}]`` publishes nothing new in that window (the timestamps go stale)."""
    spec = dict(spec or {})
    unknown = sorted(set(spec) - {"sensor", "freeze"})
    if unknown:
        raise SimCncError(f"config key(s) {['faults.' + k for k in unknown]}: unknown; known: faults.sensor, faults.freeze")
    out: dict[str, list[dict]] = {"sensor": [], "freeze": []}
    for kind, need in (("sensor", {"sensor", "from_s", "to_s", "value"}), ("freeze", {"from_s", "to_s"})):
        for i, f in enumerate(spec.get(kind) or []):
            f = dict(f)
            if set(f) != need:
                raise SimCncError(f"config key 'faults.{kind}[{i}]': expected keys {sorted(need)}, got {sorted(f)}")
            if kind == "sensor" and f["sensor"] not in sensors:
                raise SimCncError(f"config key 'faults.sensor[{i}].sensor': {f['sensor']!r} is not a sensor; known: {sensors}")
            f["from_s"], f["to_s"] = float(f["from_s"]), float(f["to_s"])
            out[kind].append(f)
    return out


class SimCnc:
    """The server and its machine clock (see the module docstring)."""

    def __init__(self, machine: Machine, cfg: Mapping[str, Any]) -> None:
        from ..config import with_defaults

        self.m = machine
        self.cfg = with_defaults("sim_cnc", cfg)
        self.endpoint = str(self.cfg.get("endpoint") or "opc.tcp://127.0.0.1:4840/thermbench/sim-cnc")
        self.speed = float(self.cfg.get("speed", 1.0))
        if not self.speed > 0:
            raise SimCncError(f"config key 'speed': must be > 0 (1 = real time), got {self.speed}")
        self.start_mode = str(self.cfg.get("start", "on_compensator"))
        if self.start_mode not in ("on_compensator", "immediate"):
            raise SimCncError(f"config key 'start': expected on_compensator or immediate, got {self.start_mode!r}")
        self.apply = str(self.cfg.get("apply", "auto"))
        if self.apply not in ("auto", "value", "line"):
            raise SimCncError(f"config key 'apply': expected auto, value or line, got {self.apply!r}")
        self.axis = str(self.cfg.get("axis", "X"))
        self.linger_s = float(self.cfg.get("linger_s", 1.0))
        self.faults = _faults(self.cfg.get("faults"), machine.sensors)
        pe = self.cfg.get("probe_every_s")
        if pe is not None and (isinstance(pe, bool) or not isinstance(pe, (int, float)) or not pe > 0):
            raise SimCncError(f"config key 'probe_every_s': expected a time > 0 s (or null: no probe), got {pe!r}")
        self.probe_plan = machine.probes(float(pe)) if pe is not None else None  # (t_s, axis_mm, measured_um) rows
        self.probes_published = 0
        self.server = None
        self.history = self.cfg.get("history", False)
        if self.history not in (False, True, "changes"):
            raise SimCncError(f"config key 'history': expected false, true (every value published) or changes (a value "
                              f"when it changes, as a data-change historian stores it), got {self.history!r}")  # fmt: skip
        self.history_keys: list[str] = []
        self.history_last: dict[str, Any] = {}  # with history=changes: the last value stored per input
        self.k = 0
        self.started = asyncio.Event()
        self.first_read = asyncio.Event()
        self.finished = asyncio.Event()
        self.applied_readings = np.full(len(machine.readings), np.nan)
        self.applied_samples = np.full(len(machine.samples), np.nan)

    # ------------------------------------------------------------ address space ---
    async def start_server(self) -> None:
        from asyncua import Server, ua

        sec = dict(self.cfg.get("security") or {})
        if sec.get("user") and not sec.get("certificate"):
            raise SimCncError("config key 'security.user': a password is never taken unencrypted; set security.certificate "
                              "and security.private_key (thermbench certs DIR)")  # fmt: skip
        users = _Users(str(sec["user"]), _password(sec)) if sec.get("user") else None
        server = Server(user_manager=users)
        await server.init()
        server.set_endpoint(self.endpoint)
        server.set_server_name("thermbench sim-cnc")
        await server.set_application_uri(SERVER_APP_URI)
        if sec.get("certificate") or sec.get("private_key"):
            for key in ("certificate", "private_key"):
                if not sec.get(key) or not Path(str(sec[key])).is_file():
                    raise SimCncError(f"config key 'security.{key}': {sec.get(key)!r} is not a file")
            await server.load_certificate(str(sec["certificate"]))
            await server.load_private_key(str(sec["private_key"]))
            policies = [ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt]
            if sec.get("allow_none", False):
                policies.append(ua.SecurityPolicyType.NoSecurity)
            server.set_security_policy(policies)
            if sec.get("trusted_clients"):
                server.set_certificate_validator(_trusted_only([str(p) for p in sec["trusted_clients"]]))
        else:
            server.set_security_policy([ua.SecurityPolicyType.NoSecurity])
        server.set_identity_tokens([ua.UserNameIdentityToken] if users else [ua.AnonymousIdentityToken])
        extra = self.cfg.get("extra_namespaces") or []
        if not isinstance(extra, (list, tuple)) or not all(isinstance(u, str) and u for u in extra):
            raise SimCncError(f"config key 'extra_namespaces': expected a list of namespace URIs, got {extra!r}")
        for uri in extra:  # before ours: our index moves up by one each
            await server.register_namespace(str(uri))
        idx = await server.register_namespace(NAMESPACE)
        objs = server.nodes.objects
        mach = await objs.add_object(ua.NodeId("Machine", idx), "Machine")
        ax = await objs.add_object(ua.NodeId(self.axis, idx), f"{self.axis}Axis")
        dbl = ua.VariantType.Double

        async def var(parent, name, value, vtype=dbl, writable=False):
            node = await parent.add_variable(ua.NodeId(name, idx), name.split(".")[-1], ua.Variant(value, vtype))
            if writable:
                await node.set_writable()
            return node.nodeid

        a = self.axis
        self.ids = {"time": await var(mach, "Machine.Time_s", 0.0), "done": await var(mach, "Machine.ProgramDone", False,
                                                                                        ua.VariantType.Boolean),
                    "speed": await var(mach, "Machine.Speed", self.speed),
                    "axis_mm": await var(ax, f"{a}.Position_mm", 0.0), "feed_mm_min": await var(ax, f"{a}.Feed_mm_min", 0.0),
                    "measuring": await var(ax, f"{a}.Measuring", False, ua.VariantType.Boolean),
                    "error_um": await var(ax, f"{a}.Error_um", math.nan), "residual_um": await var(ax, f"{a}.Residual_um", math.nan)}  # fmt: skip
        if "load_N" in self.m.samples:
            self.ids["load_N"] = await var(ax, f"{a}.Load_N", 0.0)
        if self.probe_plan is not None:
            self.ids["probe"] = await var(ax, f"{a}.{PROBE[0]}", math.nan)
        for s in self.m.sensors:
            self.ids[f"{s}_C"] = await var(ax, f"{a}.{s}_C", 0.0)
        self.comp = {"value": await var(ax, f"{a}.{COMP_VALUE[0]}", math.nan, writable=True),
                     "offset": await var(ax, f"{a}.{COMP_OFFSET[0]}", math.nan, writable=True),
                     "slope": await var(ax, f"{a}.{COMP_SLOPE[0]}", math.nan, writable=True),
                     "ref": await var(ax, f"{a}.{COMP_REF[0]}", math.nan, writable=True),
                     "status": await var(ax, f"{a}.{COMP_STATUS}", -1, ua.VariantType.Int32, writable=True)}  # fmt: skip
        from asyncua.common.callback import CallbackType

        def on_read(event, dispatcher) -> None:
            if event.is_external:
                self.first_read.set()

        server.subscribe_server_callback(CallbackType.PostRead, on_read)
        try:
            await server.start()
            if self.history:  # OPC UA Historical Access on the inputs: a compensator back from an outage replays it
                # Stored at the source, every value as published (true) or each value when it changes (changes:
                # a data-change historian, whose history has no point while an input stands still), as a
                # controller's historian logs it. The server's own data-change historising samples through a
                # subscription (a queue of one per 10 ms publish), so a burst of samples (a loaded host
                # catching up) would keep only the last.
                self.history_keys = ["axis_mm", "feed_mm_min", "measuring",
                                     *[k for k in self.ids if k.endswith("_C") or k == "load_N"]]  # fmt: skip
                for k in self.history_keys:
                    node = server.get_node(self.ids[k])
                    await node.write_attribute(ua.AttributeIds.Historizing, ua.DataValue(True))
                    for attr in (ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel):
                        await node.set_attr_bit(attr, ua.AccessLevel.HistoryRead)
                    await server.iserver.history_manager.storage.new_historized_node(self.ids[k], None)
        except OSError as exc:
            raise SimCncError(f"config key 'endpoint': cannot serve {self.endpoint}: {exc}") from None
        self.server = server

    async def stop_server(self) -> None:
        if self.server is not None:
            await self.server.stop()
            self.server = None

    # --------------------------------------------------------------- machine ---
    def _read(self, key: str):
        dv = self.server.read_attribute_value(self.comp[key])
        return None if dv.Value is None else dv.Value.Value

    def compensation_um(self, x_mm) -> np.ndarray:
        """The compensation the machine applies at ``x_mm`` now (0 before any is written)."""
        x = np.asarray(x_mm, dtype=float)
        line = [self._read(k) for k in ("offset", "slope", "ref")]
        line_ok = all(v is not None and math.isfinite(float(v)) for v in line)
        value = self._read("value")
        value_ok = value is not None and math.isfinite(float(value))
        if (self.apply == "line" or (self.apply == "auto" and line_ok)) and line_ok:
            off = float(line[0]) / LENGTH_UNITS[COMP_OFFSET[1]]
            slope = float(line[1]) / SLOPE_UNITS[COMP_SLOPE[1]]
            ref_mm = float(line[2]) / LENGTH_UNITS[COMP_REF[1]] / 1e3
            return off + slope * 1e-3 * (x - ref_mm)
        if self.apply in ("value", "auto") and value_ok:
            return np.full(x.shape, float(value) / LENGTH_UNITS[COMP_VALUE[1]])
        return np.zeros(x.shape)

    async def _publish(self, k: int, base: _dt.datetime) -> None:
        from asyncua import ua

        row = self.m.samples.iloc[k]
        t = float(row["t_s"])
        ts = base + _dt.timedelta(seconds=t - float(self.m.samples["t_s"].iloc[0]))
        now = _dt.datetime.now(_dt.timezone.utc)
        comp = float(self.compensation_um(row["axis_mm"]))
        self.applied_samples[k] = comp
        err = float(self.m.sample_error_um[k])
        vals = {"time": t, "axis_mm": float(row["axis_mm"]), "feed_mm_min": float(row["feed_mm_min"]),
                "measuring": bool(row["measuring"]), "error_um": err, "residual_um": err + comp}  # fmt: skip
        if "load_N" in self.ids:
            vals["load_N"] = float(row["load_N"])
        for s in self.m.sensors:
            vals[f"{s}_C"] = float(row[f"{s}_C"])
        for f in self.faults["sensor"]:
            if f["from_s"] <= t < f["to_s"]:
                vals[f"{f['sensor']}_C"] = float(f["value"])
        for key, v in vals.items():
            vt = ua.VariantType.Boolean if isinstance(v, bool) else ua.VariantType.Double
            dv = ua.DataValue(ua.Variant(v, vt), SourceTimestamp=ts, ServerTimestamp=now)
            await self.server.write_attribute_value(self.ids[key], dv)
            unchanged = self.history == "changes" and key in self.history_last and self.history_last[key] == v
            if key in self.history_keys and not unchanged:
                self.history_last[key] = v
                await self.server.iserver.history_manager.storage.save_node_value(self.ids[key], dv)
        await self._publish_probe(t, base)

    async def _publish_probe(self, t: float, base: _dt.datetime) -> None:
        """The newest probe reading taken by machine time ``t``, stamped with its own time (a probe
        cycle's result, which the PLC publishes once the cycle is done)."""
        from asyncua import ua

        plan = self.probe_plan
        if plan is None:
            return
        n = int(np.searchsorted(plan["t_s"].to_numpy(), t + 1e-9, side="right"))
        if n <= self.probes_published:
            return
        self.probes_published = n
        t_p, v = float(plan["t_s"].iloc[n - 1]), float(plan["measured_um"].iloc[n - 1])
        ts = base + _dt.timedelta(seconds=t_p - float(self.m.samples["t_s"].iloc[0]))
        dv = ua.DataValue(ua.Variant(v, ua.VariantType.Double), SourceTimestamp=ts,
                          ServerTimestamp=_dt.datetime.now(_dt.timezone.utc))  # fmt: skip
        await self.server.write_attribute_value(self.ids["probe"], dv)

    def _score_readings(self, upto_t: float) -> None:
        rd = self.m.readings
        t = rd["t_s"].to_numpy()
        todo = np.flatnonzero(np.isnan(self.applied_readings) & (t <= upto_t))
        if todo.size:
            self.applied_readings[todo] = self.compensation_um(rd["target_mm"].to_numpy()[todo])

    async def run_clock(self) -> None:
        """Publish sample 0, wait for the start, then every sample at its (scaled) time."""
        from asyncua import ua

        loop = asyncio.get_running_loop()
        base = _dt.datetime.now(_dt.timezone.utc)
        await self._publish(0, base)
        if self.start_mode == "on_compensator":
            await self.first_read.wait()
        self.started.set()
        t = self.m.samples["t_s"].to_numpy()
        wall0 = loop.time()  # machine time t[k] is published at wall0 + (t[k] - t[0]) / speed, stamped base + t[k] - t[0]
        await self._publish(0, base)
        for k in range(1, len(t)):
            due = wall0 + (t[k] - t[0]) / self.speed
            now = loop.time()
            if due > now:
                await asyncio.sleep(due - now)
            self._score_readings(t[k])  # readings up to this sample, with the compensation in force now
            if any(f["from_s"] <= t[k] < f["to_s"] for f in self.faults["freeze"]):
                continue  # the controller's data freezes: nothing new is published (stale timestamps)
            await self._publish(k, base)
            self.k = k
        self._score_readings(math.inf)
        await self.server.write_attribute_value(self.ids["done"], ua.DataValue(ua.Variant(True, ua.VariantType.Boolean)))
        self.finished.set()

    # --------------------------------------------------------------- results ---
    def results(self) -> dict:
        from ..export.replay import compensation_figures

        rd = self.m.readings[["t_s", "target_mm", "error_um", "thermal_um"]].copy()
        rd["applied_um"] = np.nan_to_num(self.applied_readings, nan=0.0)
        rd["predicted_um"] = -rd["applied_um"]  # the error the applied compensation stands for
        rd["residual_um"] = rd["error_um"] + rd["applied_um"]
        f = {"run": self.m.run, "speed": self.speed, "apply": self.apply, "n_readings": len(rd),
             "n_samples": len(self.m.samples), **compensation_figures(rd)}  # fmt: skip
        sm = self.m.samples[["t_s", "axis_mm"]].copy()
        sm["applied_um"] = self.applied_samples
        sm["error_um"] = self.m.sample_error_um
        sm["residual_um"] = sm["error_um"] + sm["applied_um"]
        ok = np.isfinite(sm["residual_um"].to_numpy())
        if ok.any():
            f["samples_before_max_abs_um"] = float(np.max(np.abs(sm["error_um"].to_numpy()[ok])))
            f["samples_after_max_abs_um"] = float(np.max(np.abs(sm["residual_um"].to_numpy()[ok])))
            f["samples_after_rms_um"] = float(np.sqrt(np.mean(sm["residual_um"].to_numpy()[ok] ** 2)))
        if self.probe_plan is not None:
            f["n_probes"] = self.probes_published
        pr = self.probe_plan.iloc[: self.probes_published] if self.probe_plan is not None else None
        return {"figures": f, "readings": rd, "samples": sm, "probes": pr}

    def write_results(self, out_dir: Path, force: bool = False) -> Path:
        from ..data.io import save_dataset

        res = self.results()
        with output_dir(out_dir, "sim-cnc", force=force, force_option="force=true") as tmp:
            (tmp / "closed_loop.json").write_text(json.dumps(res["figures"], indent=2, default=float) + "\n", encoding="utf-8")
            res["readings"].to_csv(tmp / "readings.csv", index=False)
            res["samples"].to_csv(tmp / "samples.csv", index=False)
            if res["probes"] is not None:  # what the probe read (thermbench replay --probes takes this file)
                res["probes"].to_csv(tmp / "probes.csv", index=False)
            save_dataset(self.m.dataset, tmp / "dataset", file_format="csv")
        return Path(out_dir)


async def serve(cfg: Mapping[str, Any], machine: Machine | None = None, ready: asyncio.Event | None = None) -> dict:
    """Run the server until the program ends (plus ``linger_s``); write ``out_dir``; return the figures."""
    machine = machine or build_machine(cfg)
    sim = SimCnc(machine, cfg)
    cfg = sim.cfg
    out = Path(str(cfg.get("out_dir") or f"sim_cnc/{machine.run}"))
    force = cfg.get("force", False)
    if not isinstance(force, bool):
        raise SimCncError(f"config key 'force': expected true or false, got {force!r}")
    check_output_dir(out, "sim-cnc", force=force, force_option="force=true")  # refused now, not after the run
    if cfg.get("write_nodes"):
        check_output_file(Path(str(cfg["write_nodes"])), "nodes")
    try:  # a results directory that cannot be written fails now, not after the run
        out.parent.mkdir(parents=True, exist_ok=True)
        tempfile.TemporaryFile(dir=out.parent).close()
    except OSError as exc:
        raise SimCncError(f"config key 'out_dir': cannot write in {out.parent}: {exc.strerror or exc}") from None
    await sim.start_server()
    try:
        if cfg.get("write_nodes"):  # written once the server listens: the file appearing means "connect now"
            nodes = nodes_yaml(machine, sim.axis, probe=sim.probe_plan is not None)
            write_text(Path(str(cfg["write_nodes"])), dump_yaml(nodes, sort_keys=False), "nodes")
        if ready is not None:
            ready.set()
        await sim.run_clock()
        await asyncio.sleep(sim.linger_s)
    finally:
        await sim.stop_server()
    sim.write_results(out, force)
    return {**sim.results()["figures"], "out_dir": str(out)}


def format_figures(f: dict) -> str:
    lines = [f"sim-cnc run {f['run']} at {f['speed']:g}x real time: {f['n_samples']} samples, {f['n_readings']} readings",
             f"  readings before: max |error| {f['before_max_abs_um']:.2f} µm; after (closed loop): max {f['after_max_abs_um']:.2f} µm, "
             f"RMS {f['after_rmse_um']:.2f} µm; compensation rate {100 * f['compensation_rate']:.1f} %"]  # fmt: skip
    if "samples_after_max_abs_um" in f:
        lines.append(f"  at the axis position, every sample: max |error| {f['samples_before_max_abs_um']:.2f} -> "
                     f"{f['samples_after_max_abs_um']:.2f} µm (RMS after {f['samples_after_rms_um']:.2f} µm)")  # fmt: skip
    if "out_dir" in f:
        lines.append(f"  -> {f['out_dir']}")
    return "\n".join(lines)
