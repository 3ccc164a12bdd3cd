"""One compensator process for several channels over several endpoints (``thermbench station``,
thermbench/compensator/station.py), against two sim-cnc machines: axis X on endpoint a, axis Y on
endpoint b, and X's bed sensor read from b, as a separate temperature logger would be. Killing b
holds Y (DISCONNECTED) and X's bed input only (INPUT_HELD): X goes on compensating on a."""

from __future__ import annotations

import asyncio

import numpy as np
import pandas as pd
import pytest
import yaml

from thermbench.compensator.control import Flags
from thermbench.compensator.simcnc import NAMESPACE, SimCnc, build_machine, nodes_yaml
from thermbench.compensator.station import Station, StationError, load_station
from tests.test_compensator import _port

# a real-time loop, but its checks are of flags and values, not of timing: it runs in the parallel suite
pytestmark = pytest.mark.realtime


@pytest.fixture(scope="module")
def machines():
    return (build_machine({"benchmark": "seed001_vmc_x", "run": "valid1", "duration_s": 900}),
            build_machine({"benchmark": "seed001_vmc_x", "run": "valid2", "duration_s": 900}))  # fmt: skip


def _station_file(tmp_path, model, ports, machines) -> "Path":
    a, b = machines
    nx, ny = nodes_yaml(a, "X", probe=True), nodes_yaml(b, "Y")  # X's touch probe on a
    for n in (nx, ny):
        n["inputs"].pop("done")
        n["outputs"].pop("line")
    nx["inputs"]["temperatures"]["T_bed"] = f"b::nsu={NAMESPACE};s=Y.T_bed_C"  # from the other server
    (tmp_path / "nodes_x.yaml").write_text(yaml.safe_dump(nx))
    (tmp_path / "nodes_y.yaml").write_text(yaml.safe_dump(ny))
    spec = {"period_s": 0.02, "log_dir": str(tmp_path / "logs"), "status_every_s": 0.5, "duration_s": 5.0,
            "reconnect": {"initial_s": 0.1, "max_s": 0.4},
            "endpoints": {"a": {"url": f"opc.tcp://127.0.0.1:{ports[0]}/a"}, "b": {"url": f"opc.tcp://127.0.0.1:{ports[1]}/b"}},
            "channels": {"X": {"model": str(model), "nodes": "nodes_x.yaml", "endpoint": "a"},
                         "Y": {"model": str(model), "nodes": "nodes_y.yaml", "endpoint": "b",
                               "config": {"rate_limit_um_s": 5.0}}}}  # fmt: skip
    p = tmp_path / "station.yaml"
    p.write_text(yaml.safe_dump(spec))
    return p


def test_a_dead_endpoint_holds_only_what_it_touches(machines, seed001_exports, tmp_path):
    ports = (_port(), _port())
    path = _station_file(tmp_path, seed001_exports / "mlr", ports, machines)
    lines: list[str] = []

    async def scenario():
        sims = [SimCnc(m, {"endpoint": f"opc.tcp://127.0.0.1:{p}/{n}", "run": m.run, "speed": 20.0, "start": "immediate",
                           "axis": ax, "probe_every_s": 15.0 if ax == "X" else None})
                for m, p, n, ax in zip(machines, ports, "ab", "XY")]  # fmt: skip
        clocks = []
        for s in sims:
            await s.start_server()
            clocks.append(asyncio.ensure_future(s.run_clock()))
        st = Station(load_station(path), say=lines.append)
        task = asyncio.ensure_future(st.run())
        # kill b once both channels have compensated (OK) for 0.5 s: a loaded host may take longer to connect
        ok_since, t0 = None, asyncio.get_running_loop().time()
        while asyncio.get_running_loop().time() - t0 < 3.0:
            await asyncio.sleep(0.02)
            both = bool(st.channels) and all(c.last is not None and c.last.flags & ~int(Flags.PROBE) == 0 for c in st.channels)
            now = asyncio.get_running_loop().time()
            ok_since = (ok_since or now) if both else None
            if ok_since is not None and now - ok_since >= 0.5:
                break
        stop_wall = __import__("time").time()
        clocks[1].cancel()
        await sims[1].stop_server()  # b goes away: Y's controller and X's bed sensor
        summary = await task
        applied = sims[0]._read("value")  # what a holds as X's compensation
        clocks[0].cancel()
        await sims[0].stop_server()
        return summary, stop_wall, applied, sims[0].results()["probes"]

    summary, stop_wall, applied, probes = asyncio.run(scenario())
    x = pd.read_csv(tmp_path / "logs" / "X.csv")
    y = pd.read_csv(tmp_path / "logs" / "Y.csv")
    assert len(x) == len(y) == summary["cycles"] > 10  # one line per channel per cycle
    before_x, before_y = x[x["wall_s"] < stop_wall], y[y["wall_s"] < stop_wall]
    ok = ~int(Flags.PROBE)  # compensating (a cycle that took a probe reading is flagged PROBE, and is as good)
    assert ((before_x["flags"].iloc[-2:] & ok) == 0).all() and ((before_y["flags"].iloc[-2:] & ok) == 0).all()
    # after the kill, from the first cycle that saw it (on the log's cycles, however long the host took to
    # notice: no wall-clock window); the two logs have one line per cycle, so one index serves both
    lost = max(y.index[(y["flags"] & int(Flags.DISCONNECTED)) > 0][0], x.index[x["held"].fillna("") == "T_bed_C"][0])
    assert x.loc[lost, "wall_s"] > stop_wall
    after_x, after_y = x.loc[lost:], y.loc[lost:]
    # Y: its controller is gone: held, disconnected
    assert len(after_y) >= 3 and ((after_y["flags"] & int(Flags.DISCONNECTED)) > 0).all()
    assert ((after_y["flags"] & int(Flags.HELD)) > 0).all()
    # X: only its bed sensor is held (at its last good value); it goes on compensating on a
    assert len(after_x) >= 3 and not ((after_x["flags"] & int(Flags.DISCONNECTED)) > 0).any()
    assert (after_x["held"] == "T_bed_C").all() and ((after_x["flags"] & int(Flags.INPUT_HELD)) > 0).all()
    assert after_x["T_bed_C"].nunique() == 1 and after_x["T_bed_C"].iloc[0] == before_x["T_bed_C"].iloc[-1]
    assert after_x["t_s"].is_monotonic_increasing and after_x["t_s"].iloc[-1] > before_x["t_s"].iloc[-1] + 10
    assert applied == x["value_um"].dropna().iloc[-1]  # a holds the last value X wrote, bit for bit
    assert any(ln.startswith("lost b (") for ln in lines)
    status = [ln for ln in lines if ln.startswith("cycle ")]
    assert status and all(" | Y " in ln and ln.split(": ", 1)[1].count("X ") >= 1 for ln in status)
    assert summary["channels"]["Y"]["flags"]["DISCONNECTED"] == len(y[(y["flags"] & int(Flags.DISCONNECTED)) > 0])
    # X's probe readings (on a, every 15 machine s) correct X alone, each taken once with its value
    took = x[(x["flags"] & int(Flags.PROBE)) > 0]
    # (a machine started before the station: the readings published before X was ready are gone; the
    # last may come after the station's end): from X's first, every one of a's readings, once, in order
    idx = [int(np.flatnonzero(probes["measured_um"].to_numpy() == v)[0]) for v in took["probe_um"]]
    assert len(took) >= 3 and idx == list(range(idx[0], idx[0] + len(took))) and idx[-1] >= len(probes) - 2
    # each taken by the first cycle that read the sample it came with, on one timeline: the station's t_s
    # starts where it joined, at an offset o from a's program time, and then every probe time lies in the
    # gap between the cycle that took it and the one before, shifted by o: o exists (in machine time, so a
    # loaded host's late cycles widen the gaps, not the check; one came 3 s late in CI)
    t_x = x["t_s"].to_numpy()
    pos = x.index.get_indexer(took.index)
    lag = t_x[pos] - probes["t_s"].to_numpy()[idx]  # t_took - t_probe = gap part - o
    gap = np.where(pos >= 2, t_x[pos] - t_x[np.maximum(pos - 2, 0)], np.inf)  # one cycle between at most (a read between two node writes)
    assert -lag.min() <= (gap - lag).min() + 1e-6, (lag, gap)
    after = x[x["t_s"] > took["t_s"].iloc[0]]
    assert (after["correction_um"].abs() > 0).any() and (y["correction_um"].fillna(0) == 0).all()
    assert not ((y["flags"] & int(Flags.PROBE)) > 0).any()


def test_station_file_mistakes_are_one_line(tmp_path, seed001_exports, machines):
    path = _station_file(tmp_path, seed001_exports / "mlr", (1, 2), machines)
    spec = yaml.safe_load(path.read_text())
    spec["channels"]["X"]["endpoint"] = "c"
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(StationError, match=r"channels.X: key 'endpoint': 'c' is not one of the endpoints \['a', 'b'\]"):
        Station(load_station(path))
    spec["channels"]["X"]["endpoint"] = "a"
    nx = yaml.safe_load((tmp_path / "nodes_x.yaml").read_text())
    nx["inputs"]["temperatures"]["T_bed"] = "z::ns=2;s=T"
    (tmp_path / "nodes_x.yaml").write_text(yaml.safe_dump(nx))
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(StationError, match=r"input T_bed_C 'z::ns=2;s=T': 'z' is not one of the endpoints"):
        Station(load_station(path))
    with pytest.raises(StationError, match="no such station file"):
        load_station(tmp_path / "nope.yaml")
