"""Load of one compensator process serving several channels (``thermbench station``):
three feed axes and five spindle channels at a 100 ms period, and one axis at 10 ms.

    .venv/bin/python benchmarks/bench_station.py [--exports exports/benchmark] [--seconds 30] [--runs 3]

The models are ``make demo``'s exports: ``seed001_vmc_x__mlr_seed002__global`` for each axis and
``fl_thermal-ch1..5__physics_spindle_hybrid__global`` (the measured spindle's five channels:
lumped networks with the spindle speed as operating input) for the spindle channels. The
machine is an asyncua server in its own process with two endpoints, as on a shop floor: the
CNC (axis positions and feeds, spindle speeds, every output node) and a temperature logger
(every sensor), stamping each value every 100 ms with a machine clock running ``--speed`` (10)
times the wall clock, so that the spindles' networks (15 s steps) predict within a run. Each configuration runs
``--runs`` times after a warm-up run; the figures are the median over runs of each run's cycle
time percentiles (``cycle_ms``: read both endpoints, every channel's logic and C runtime, the
writes, the logs).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import multiprocessing
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

NS = "urn:thermbench:bench"
AXIS = "seed001_vmc_x__mlr_seed002__global"
SPINDLES = [f"fl_thermal-ch{i}__physics_spindle_hybrid__global" for i in range(1, 6)]


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _manifest(d: Path) -> dict:
    return json.loads((d / "manifest.json").read_text())


def serve(ports, channels, stop, speed: float = 10.0) -> None:
    """The machine: two asyncua servers (CNC, logger) in this process, values updated every 100 ms
    and stamped with a machine clock ``speed`` times the wall clock (so that the spindles' lumped
    networks, stepped every 15 s of machine time, are predicting within the run)."""
    import datetime as dt

    from asyncua import Server, ua

    async def main():
        servers, nodes = [], {}
        for port, name in zip(ports, ("cnc", "logger")):
            s = Server()
            await s.init()
            s.set_endpoint(f"opc.tcp://127.0.0.1:{port}/{name}")
            s.set_security_policy([ua.SecurityPolicyType.NoSecurity])
            idx = await s.register_namespace(NS)
            obj = await s.nodes.objects.add_object(idx, name)
            servers.append((s, idx, obj))
        (cnc, ic, oc), (log, il, ol) = servers
        for ch, (kind, temps) in channels.items():
            for var in ("Position_mm", "Feed_mm_min", *(["Speed_rpm"] if kind == "spindle" else [])):
                nodes[f"{ch}.{var}"] = await oc.add_variable(ua.NodeId(f"{ch}.{var}", ic), f"{ch}.{var}", 0.0)
            for t in temps:
                nodes[f"{ch}.{t}_C"] = await ol.add_variable(ua.NodeId(f"{ch}.{t}_C", il), f"{ch}.{t}_C", 20.0)
            out = await oc.add_variable(ua.NodeId(f"{ch}.TempComp_um", ic), f"{ch}.TempComp_um", 0.0)
            st = await oc.add_variable(ua.NodeId(f"{ch}.Status", ic), f"{ch}.Status", 0, ua.VariantType.Int32)
            await out.set_writable()
            await st.set_writable()
        for s, _, _ in servers:
            await s.start()
        t0 = time.time()
        try:
            while not stop.is_set():
                t = speed * (time.time() - t0)
                now = dt.datetime.fromtimestamp(t0 + t, dt.timezone.utc)
                for key, node in nodes.items():
                    ch, var = key.split(".", 1)
                    if var == "Position_mm":
                        v = 350.0 + 200.0 * math.sin(t / 50.0 + len(ch)) if channels[ch][0] == "axis" else 0.0
                    elif var == "Feed_mm_min":
                        v = 6000.0 if channels[ch][0] == "axis" else 0.0
                    elif var == "Speed_rpm":
                        v = 3000.0
                    else:
                        v = 20.0 + 3.0 * (1.0 - math.exp(-t / 1800.0)) + 0.1 * (len(key) % 7)
                    srv = cnc if node.nodeid.NamespaceIndex == ic and not key.endswith("_C") else log
                    await srv.write_attribute_value(node.nodeid, ua.DataValue(ua.Variant(v, ua.VariantType.Double),
                                                                              SourceTimestamp=now, ServerTimestamp=now))  # fmt: skip
                await asyncio.sleep(0.1)
        finally:
            for s, _, _ in servers:
                await s.stop()

    asyncio.run(main())


def station_spec(exports: Path, tmp: Path, n_axes: int, n_spindles: int, ports, period_s: float, seconds: float):
    import yaml

    chans, spec_ch = {}, {}
    for i in range(n_axes):
        chans[f"A{i}"] = ("axis", _manifest(exports / AXIS)["temperatures"])
    for j in range(n_spindles):
        chans[f"S{j}"] = ("spindle", _manifest(exports / SPINDLES[j])["temperatures"])
    for ch, (kind, temps) in chans.items():
        ns = f"nsu={NS};s={ch}."
        nodes = {"inputs": {"axis_mm": ns + "Position_mm", "feed_mm_min": ns + "Feed_mm_min",
                            "temperatures": {t: f"logger::{ns}{t}_C" for t in temps}},
                 "outputs": {"value": {"node": ns + "TempComp_um", "unit": "um"}, "status": ns + "Status"}}  # fmt: skip
        if kind == "spindle":
            nodes["inputs"]["operating"] = {"spindle_rpm": ns + "Speed_rpm"}
        (tmp / f"{ch}.yaml").write_text(yaml.safe_dump(nodes))
        model = exports / (AXIS if kind == "axis" else SPINDLES[int(ch[1:])])
        spec_ch[ch] = {"model": str(model), "nodes": str(tmp / f"{ch}.yaml"), "endpoint": "cnc",
                       "config": {"stale_after_s": 5.0}}  # fmt: skip
    spec = {"period_s": period_s, "duration_s": seconds, "status_every_s": 3600.0,
            "endpoints": {"cnc": {"url": f"opc.tcp://127.0.0.1:{ports[0]}/cnc"},
                          "logger": {"url": f"opc.tcp://127.0.0.1:{ports[1]}/logger"}},
            "channels": spec_ch, "_dir": tmp, "_path": tmp / "station.yaml"}  # fmt: skip
    return spec, chans


def measure(exports: Path, n_axes: int, n_spindles: int, period_s: float, seconds: float, runs: int,
            speed: float = 10.0) -> dict:
    from thermbench.compensator.station import Station

    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        ports = (_port(), _port())
        spec, chans = station_spec(exports, tmp, n_axes, n_spindles, ports, period_s, seconds)
        stop = multiprocessing.get_context("fork").Event()
        srv = multiprocessing.get_context("fork").Process(target=serve, args=(ports, chans, stop, speed), daemon=True)
        srv.start()
        deadline = time.time() + 60.0
        for port in ports:  # until both endpoints listen
            while True:
                with socket.socket() as so:
                    if so.connect_ex(("127.0.0.1", port)) == 0:
                        break
                if time.time() > deadline or not srv.is_alive():
                    raise RuntimeError(f"the benchmark's OPC UA server did not start on port {port}")
                time.sleep(0.2)
        out = []
        try:
            for r in range(runs + 1):  # the first is the warm-up
                s = asyncio.run(Station({**spec, "log_dir": str(tmp / f"logs{r}")}).run())
                flags = {ch: v["flags"] for ch, v in s["channels"].items()}
                if r:
                    out.append((s["cycle_ms"], s["cycles"], s["over_period"], flags))
        finally:
            stop.set()
            srv.join(10)
    med = {q: statistics.median(c[q] for c, *_ in out) for q in ("p50", "p90", "p99", "max", "mean")}
    return {"channels": f"{n_axes} axes + {n_spindles} spindle channels", "period_ms": 1e3 * period_s, "runs": runs,
            "cycles_per_run": [n for _, n, _, _ in out], "over_period": [o for *_, o, _ in out], "median_cycle_ms": med,
            "flags_last_run": out[-1][3]}  # fmt: skip


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--exports", default="exports/benchmark")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--speed", type=float, default=10.0, help="machine seconds per wall second of the served clock")
    a = ap.parse_args()
    exports = Path(a.exports)
    missing = [m for m in [AXIS, *SPINDLES] if not (exports / m / "manifest.json").exists()]
    if missing:
        print(f"bench_station: {exports} lacks {missing}; run make demo first (or --exports DIR)", file=sys.stderr)
        return 2
    for n_axes, n_spindles, period in ((3, 5, 0.1), (1, 0, 0.01)):
        r = measure(exports, n_axes, n_spindles, period, a.seconds, a.runs, a.speed)
        m = r["median_cycle_ms"]
        print(f"{r['channels']} at {r['period_ms']:g} ms, {a.runs} runs of {a.seconds:g} s after a warm-up: cycle time "
              f"median of runs p50 {m['p50']:.2f} ms, p90 {m['p90']:.2f} ms, p99 {m['p99']:.2f} ms, max {m['max']:.2f} ms; "
              f"cycles per run {r['cycles_per_run']}, over the period {r['over_period']}")
        print(f"  flags of the last run: {json.dumps(r['flags_last_run'])}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
