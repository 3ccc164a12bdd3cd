"""The OPC UA compensator against ``sim-cnc`` on 127.0.0.1: the closed loop reduces the
simulated error by what ``thermbench replay`` predicts (value and error-line forms),
faults (server restart, NaN / out-of-range sensors, frozen data), security
(user/password, Basic256Sha256 sign-and-encrypt with pinned certificates) and the
refusal to write any node but the configured ones.

Everything runs in one event loop per test: the server and the client are both asyncua
(the client steps the exported model in the C runtime through ctypes).
"""

from __future__ import annotations

import asyncio
import json
import math
import socket

import numpy as np
import pandas as pd
import pytest
import yaml

from thermbench.cli import main
from thermbench.compensator.certs import make_certificates
from thermbench.compensator.client import Compensator
from thermbench.compensator.errors import CompensatorError, RefusedWrite
from thermbench.compensator.control import Flags
from thermbench.compensator.simcnc import SimCnc, SimCncError, build_machine, nodes_yaml, serve
from thermbench.bench.datasets import load_benchmark
from thermbench.export.replay import replay_run

pytestmark = pytest.mark.timing  # real-time closed loops: run alone (see the Makefile)

RUN = "valid1"
HELD, STALE, INPUT_HELD = int(Flags.HELD), int(Flags.STALE), int(Flags.INPUT_HELD)
DISCONNECTED, RESTARTED = int(Flags.DISCONNECTED), int(Flags.RESTARTED)


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def ds(seed001_data_root):
    return load_benchmark("seed001_vmc_x", seed001_data_root)


@pytest.fixture(scope="module")
def machine(ds):
    """valid1's first 15 minutes, simulated by sim-cnc (not read from the dataset)."""
    return build_machine({"benchmark": "seed001_vmc_x", "run": RUN, "duration_s": 900})


@pytest.fixture
def nodes_file(machine, tmp_path):
    p = tmp_path / "nodes.yaml"
    p.write_text(yaml.safe_dump(nodes_yaml(machine)))
    return p


def _time_steps_within(log: pd.DataFrame, rate_um_s: float, period_s: float = 1.0) -> bool:
    """Between consecutive cycles at the same axis position, the written value changed by at
    most rate x machine time (at most one sample period per cycle): the limit on change in time."""
    v = log.dropna(subset=["value_um"])
    same = np.diff(v["axis_mm"].to_numpy()) == 0
    dv, dt = np.abs(np.diff(v["value_um"].to_numpy())), np.minimum(np.diff(v["t_s"].to_numpy()), period_s)
    dt = np.where(np.isfinite(dt), dt, period_s)
    return bool(same.sum() > 10 and np.all(dv[same] <= rate_um_s * dt[same] + 1e-9))


def fault_window(log: pd.DataFrame, rows: pd.DataFrame, length_s: float, step_s: float = 1.0) -> tuple[float, float]:
    """Check that a block of consecutive cycles saw a fault of ``length_s`` machine seconds on a
    ``step_s`` sample grid, by what the loop logged, whatever its pace: the block's cycles read
    samples inside the fault (its span at most length - step), and the cycles either side of it
    read samples outside (their span at least the length). A loaded host's loop reads fewer
    samples, so the block's ends lie anywhere in those gaps; no count of cycles is asked for.
    Returns the gaps before and after the block (machine s)."""
    assert len(rows) and (np.diff(rows.index) == 1).all(), "not one block of consecutive cycles"
    t = log["t_s"]
    i0, i1 = rows.index[0], rows.index[-1]
    assert i0 - 1 in t.index and i1 + 1 in t.index, "the block is at the log's edge: no cycle either side"
    assert t[i1] - t[i0] <= length_s - step_s + 1e-6, (t[i0], t[i1])
    assert t[i1 + 1] - t[i0 - 1] >= length_s - 1e-6, (t[i0 - 1], t[i1 + 1])
    return float(t[i0] - t[i0 - 1]), float(t[i1 + 1] - t[i1])


def replay_as_stepped(model_dir, ds, log: pd.DataFrame, **kw) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The loop's fresh cycles and the C runtime's answers at the same machine times, stepped with
    exactly the samples the loop read (a loaded host's loop may skip a sample: its model steps over
    it, zero-order hold, and so does this reference): thermbench replay --live of those samples."""
    from thermbench.export.directory import replay_dir
    from thermbench.export.samples import process_samples

    samples = process_samples(ds, RUN)
    fresh = log[((log["flags"] & HELD) == 0) & log["predicted_um"].notna()]
    k = np.floor(fresh["t_s"].to_numpy() + 1e-3)  # the model's last grid point (1 s) at each cycle
    seen = np.floor(log["t_s"].dropna().to_numpy() + 1e-3)  # every sample the loop stepped (held cycles too)
    played = samples[samples["t_s"].isin(seen)].reset_index(drop=True)
    q = pd.DataFrame({"t_s": k, "axis_mm": fresh["axis_mm"].to_numpy()})
    return fresh, replay_dir(model_dir, ds, RUN, q, samples=played, live=True, **kw)


def _cycle_starts(log: pd.DataFrame, period_s: float, attempts: np.ndarray) -> np.ndarray:
    """Every logged cycle's start on the event loop's clock. The log gives them from the loop's
    start (cycle k starts late_ms after k x period); that start is the offset that puts every
    reconnection attempt (loop times) on a logged cycle start, to the log's 1 us."""
    rel = log["cycle"].to_numpy() * period_s + log["late_ms"].to_numpy() / 1e3
    for r in rel:
        t0 = attempts[0] - r
        if np.all(np.abs(attempts[:, None] - t0 - rel[None, :]).min(axis=1) < 2e-6):
            return t0 + rel
    raise AssertionError("the reconnection attempts are not at logged cycle starts")


def _client_cfg(tmp_path, **kw):
    cfg = {"period_s": 0.004, "log": str(tmp_path / "cycles.csv"), "rate_limit_um_s": 20.0, "stale_after_s": 2.0,
           "reconnect": {"initial_s": 0.05, "max_s": 0.4, "factor": 2.0}}  # fmt: skip
    cfg.update(kw)
    return cfg


async def _closed_loop(machine, model_dir, nodes, tmp_path, sim_kw=None, **client_kw):
    port = _port()
    ep = f"opc.tcp://127.0.0.1:{port}/sim"
    scfg = {"endpoint": ep, "run": RUN, "speed": 100.0, "linger_s": 0.3, "out_dir": str(tmp_path / "sim"), **(sim_kw or {})}
    ready = asyncio.Event()
    server = asyncio.ensure_future(serve(scfg, machine, ready))
    await asyncio.wait([asyncio.ensure_future(ready.wait()), server], return_when=asyncio.FIRST_COMPLETED)
    if server.done():
        server.result()  # the server failed to start: raise its error
    comp = Compensator(model_dir, ep, nodes, _client_cfg(tmp_path, **client_kw))
    summary = await comp.run()
    figures = await server
    return figures, summary, pd.read_csv(tmp_path / "cycles.csv")


def test_sim_cnc_runs_the_benchmark_run_the_model_was_checked_on(machine, ds):
    """The simulated run is the benchmark dataset's valid1 (each run draws its own seeded stream)."""
    pr = ds.process_run(RUN)
    pr = pr[pr["t_s"] <= 900].reset_index(drop=True)
    for col in ("t_s", "axis_mm", "feed_mm_min", "T_nut_C", "T_bed_C"):
        np.testing.assert_array_equal(machine.samples[col].to_numpy(), pr[col].to_numpy())
    er = ds.errors_run(RUN)
    np.testing.assert_array_equal(machine.readings["error_um"].to_numpy(), er[er["t_s"] <= 900]["error_um"].to_numpy())
    # the simulator also knows the error at every sample's position: at the readings it is the
    # interferometer's value without its noise (conf/instruments/realistic.yaml: 0.2 µm)
    at = np.interp(machine.readings["t_s"], machine.samples["t_s"], machine.sample_error_um)
    dwell = machine.readings["t_s"].isin(machine.samples["t_s"]) & np.isclose(
        np.interp(machine.readings["t_s"], machine.samples["t_s"], machine.samples["axis_mm"]), machine.readings["target_mm"])
    assert dwell.sum() >= 10
    assert np.max(np.abs((at - machine.readings["error_um"])[dwell])) < 1.5


def test_closed_loop_reduces_the_error_as_replay_predicts(machine, seed001_exports, nodes_file, tmp_path):
    note = tmp_path / "shift log.txt"  # a user's file beside sim-cnc's out_dir and the compensator's log
    note.write_text("operator: spindle warm-up skipped\n")
    nodes_before = nodes_file.read_bytes()
    f, s, log = asyncio.run(_closed_loop(machine, seed001_exports / "mlr", nodes_file, tmp_path))
    assert note.read_text() == "operator: spindle warm-up skipped\n" and nodes_file.read_bytes() == nodes_before
    from thermbench.data.io import load_dataset

    rep = replay_run(seed001_exports / "mlr", tmp_path / "sim" / "dataset", RUN)["figures"]
    assert f["before_max_abs_um"] == rep["before_max_abs_um"] > 15.0
    assert f["after_max_abs_um"] < 0.5 * f["before_max_abs_um"]  # the loop compensates
    assert f["samples_after_rms_um"] < 0.5 * f["samples_before_max_abs_um"]
    # ... as replay says: at every cycle the loop's prediction is the C runtime's, replaying exactly the
    # samples the loop read (how many it read, and so how close the machine comes to replay_run's figures
    # over every sample, depends on the host's pace: 0.105 µm apart once under load)
    fresh, ref = replay_as_stepped(seed001_exports / "mlr", load_dataset(tmp_path / "sim" / "dataset"), log)
    assert len(fresh) > 10 and (ref["rc"] == 0).all()
    np.testing.assert_allclose(fresh["predicted_um"].to_numpy(), ref["total_um"].to_numpy(), rtol=0, atol=1e-6)
    # ... and the machine applied, at each reading, a value the loop had written by then (machine time)
    rd = pd.read_csv(tmp_path / "sim" / "readings.csv")
    wrote = log.dropna(subset=["value_um"])
    for t_r, applied in rd.loc[rd["applied_um"] != 0, ["t_s", "applied_um"]].itertuples(index=False):
        assert applied in set(wrote.loc[wrote["t_s"] <= t_r, "value_um"]), (t_r, applied)
    assert (rd["applied_um"] != 0).sum() >= 0.5 * len(rd)
    # the log has one line per cycle, and the program was read to its end
    assert len(log) == s["cycles"] and s["flags"].get("DISCONNECTED", 0) == 0
    assert s["ended"] == "the machine's program is done" and log["t_s"].max() >= machine.samples["t_s"].iloc[-1] - 1
    assert _time_steps_within(log, 20.0)  # the compensation never changed in time faster than the limit


def test_namespace_uris_resolve_on_a_server_that_numbers_its_namespaces_differently(machine, seed001_exports,
                                                                                    nodes_file, tmp_path):
    """sim-cnc with two other namespaces registered first: its own URI is index 4, not 2. The
    nodes file names the namespace by URI (nsu=...), so the compensator finds its nodes and the
    loop compensates; the same file with the index hard-coded as 2 (another vendor's namespace
    there) is refused on connecting, naming the node."""
    nodes = yaml.safe_load(nodes_file.read_text())
    assert nodes["inputs"]["axis_mm"] == "nsu=urn:thermbench:sim-cnc;s=X.Position_mm"
    hard = tmp_path / "nodes_ns2.yaml"
    hard.write_text(nodes_file.read_text().replace("nsu=urn:thermbench:sim-cnc;", "ns=2;"))

    async def both():
        port = _port()
        ep = f"opc.tcp://127.0.0.1:{port}/sim"
        scfg = {"endpoint": ep, "run": RUN, "speed": 100.0, "linger_s": 0.3, "out_dir": str(tmp_path / "sim"),
                "extra_namespaces": ["urn:a-vendor:plc", "urn:a-vendor:drives"]}  # fmt: skip
        ready = asyncio.Event()
        server = asyncio.ensure_future(serve(scfg, machine, ready))
        await ready.wait()
        with pytest.raises(CompensatorError) as exc:
            await Compensator(seed001_exports / "mlr", ep, hard, _client_cfg(tmp_path, log=str(tmp_path / "bad.csv"))).run()
        summary = await Compensator(seed001_exports / "mlr", ep, nodes_file, _client_cfg(tmp_path)).run()
        return str(exc.value), summary, await server

    refused, s, f = asyncio.run(both())
    # the file and the key as written in it, then the node
    assert refused.startswith(f"{hard}: key outputs.value.node: output value node 'ns=2;s=X.TempComp_um'"), refused
    assert "does not exist on opc.tcp://127.0.0.1:" in refused, refused
    assert "\n" not in refused
    assert s["ended"] == "the machine's program is done" and s["flags"].get("DISCONNECTED", 0) == 0
    assert f["after_max_abs_um"] < 0.5 * f["before_max_abs_um"]


def test_error_line_output_feeds_a_stock_controller(machine, seed001_exports, nodes_file, tmp_path):
    """output=line: offset/slope/reference (SD43900/SD43910/SD43920) fitted over the travel;
    the machine applies only that line."""
    f, s, log = asyncio.run(_closed_loop(machine, seed001_exports / "mlr", nodes_file, tmp_path, sim_kw={"apply": "line"},
                                         output="line", line={"travel_mm": [0.0, 550.0], "n_points": 12, "ref_mm": 0.0}))  # fmt: skip
    rep = replay_run(seed001_exports / "mlr", tmp_path / "sim" / "dataset", RUN)["figures"]
    last = log.dropna(subset=["offset_um"]).iloc[-1]
    assert last["ref_mm"] == 0.0 and log["value_um"].isna().all()
    assert f["after_max_abs_um"] < 0.5 * f["before_max_abs_um"]
    # a straight line cannot follow the model's curvature along the axis: within 1 µm RMS of replay
    assert f["after_rmse_um"] < rep["after_rmse_um"] + 1.0


def test_faulty_sensors_and_frozen_data_are_held_and_flagged(ds, seed001_exports, nodes_file, tmp_path):
    faults = {"sensor": [{"sensor": "T_nut", "from_s": 100, "to_s": 160, "value": math.nan},
                         {"sensor": "T_bed", "from_s": 200, "to_s": 230, "value": 500.0}],
              "freeze": [{"from_s": 300, "to_s": 400}]}  # fmt: skip
    m = build_machine({"data_dir": str(ds.path), "run": RUN, "duration_s": 500})  # played back from the dataset
    no_status = yaml.safe_load(nodes_file.read_text())
    del no_status["outputs"]["status"]  # optional: the machine still starts (on the first read)
    nodes_file.write_text(yaml.safe_dump(no_status))
    f, s, log = asyncio.run(_closed_loop(m, seed001_exports / "mlr", nodes_file, tmp_path,
                                         sim_kw={"faults": faults}, stale_after_s=0.3, rate_limit_um_s=2.0))  # fmt: skip
    # the log's t_s counts from the loop's first cycle, the faults from the program's start (the server's
    # first read, a few samples apart either way): each fault window is found in the log as
    # the one block of cycles holding its sensor, as long as the fault in machine time
    def window(sensor: str) -> pd.DataFrame:
        return log[log["held"].fillna("").str.split(";").map(lambda h: sensor in h)]

    nan_win = window("T_nut_C")
    nan_in, _ = fault_window(log, nan_win, 60.0)
    assert nan_win["held"].eq("T_nut_C").all() and (nan_win["flags"] & INPUT_HELD).all()
    before = log.loc[nan_win.index[0] - 1, "T_nut_C"]
    assert (nan_win["T_nut_C"] == before).all()  # held at the last good value
    hot = window("T_bed_C")
    hot_in, _ = fault_window(log, hot, 30.0)
    # 100 s after the first (each window's first cycle lies within the gap before it of its fault's start)
    assert 100.0 - nan_in - 1e-6 <= hot["t_s"].iloc[0] - nan_win["t_s"].iloc[0] <= 100.0 + hot_in + 1e-6
    assert hot["held"].eq("T_bed_C").all() and (hot["T_bed_C"] < 80).all()
    stale = log[(log["flags"] & STALE) > 0]
    assert len(stale) >= 2 and (stale["flags"] & HELD).all()
    assert stale["value_um"].nunique() == 1  # the compensation held at one value while the data was frozen
    assert _time_steps_within(log, 2.0)  # never faster than the rate limit, faults or not
    assert (log[log["t_s"] > 420]["flags"] & (STALE | INPUT_HELD)).eq(0).all()  # recovered


def test_server_restart_reconnects_with_backoff_and_holds_the_compensation(machine, seed001_exports, nodes_file, tmp_path):
    async def fresh_after_restart(log_path, n=20, timeout_s=30.0):
        """Wait until the log shows the new timeline and then n fresh (not held) cycles."""
        end = asyncio.get_running_loop().time() + timeout_s
        while asyncio.get_running_loop().time() < end:
            await asyncio.sleep(0.2)
            log = pd.read_csv(log_path)
            r = log.index[(log["flags"] & RESTARTED) > 0]
            if len(r) and ((log.loc[r[0]:, "flags"] & HELD) == 0).sum() >= n:
                return
        raise AssertionError("no fresh compensation after the server came back")

    opens = []  # per connection attempt: (its start, when it ended, whether it connected), loop time

    async def scenario():
        port = _port()
        ep = f"opc.tcp://127.0.0.1:{port}/sim"
        cfg = {"endpoint": ep, "run": RUN, "speed": 20.0, "start": "immediate"}
        a = SimCnc(machine, cfg)
        await a.start_server()
        clock = asyncio.ensure_future(a.run_clock())
        comp = Compensator(seed001_exports / "mlr", ep, nodes_file, _client_cfg(tmp_path, period_s=0.01))
        loop, session_open = asyncio.get_running_loop(), comp.session.open

        async def recorded_open():
            t0 = loop.time()
            try:
                await session_open()
            except Exception:
                opens.append((t0, loop.time(), False))
                raise
            opens.append((t0, loop.time(), True))

        comp.session.open = recorded_open
        task = asyncio.ensure_future(comp.run())
        await asyncio.sleep(1.0)
        clock.cancel()
        await a.stop_server()  # the server goes away ...
        end = loop.time() + 30.0  # (a guard against a hang, not a speed limit)
        while sum(not ok for *_, ok in opens) < 6:  # ... for six failed attempts, however long they take ...
            assert loop.time() < end and not task.done(), "the compensator does not retry"
            await asyncio.sleep(0.05)
        b = SimCnc(machine, cfg)  # ... and comes back with its machine clock restarted
        await b.start_server()
        clock = asyncio.ensure_future(b.run_clock())
        try:
            await fresh_after_restart(tmp_path / "cycles.csv")
        finally:
            comp.stop()
            summary = await task
            clock.cancel()
            await b.stop_server()
        return comp, summary

    comp, s = asyncio.run(scenario())
    log = pd.read_csv(tmp_path / "cycles.csv")
    down = log[(log["flags"] & DISCONNECTED) > 0]
    assert len(down) >= len(comp.connect_attempts) and (down["flags"] & HELD).all()  # each attempt began in such a cycle
    last_good = log.loc[: down.index[0] - 1].dropna(subset=["value_um"])["value_um"].iloc[-1]
    assert (down["value_um"] == last_good).all()  # held at the last good value
    assert s["flags"]["reconnects"] >= 1 and s["flags"]["connection_lost"] >= 1 and s["ended"] == "stopped"
    # back-off (reconnect: initial_s 0.05, factor 2, max_s 0.4): after the k-th failed attempt the
    # next one is due min(0.05 * 2^k, 0.4) s after the cycle that saw the failure, and starts at
    # the first cycle on or after that time. Checked on the loop's own clock against its cycles, not
    # against fixed seconds, so a slow machine (late cycles) cannot make it fail.
    attempts = np.array(comp.connect_attempts)  # the loop time of each reconnection attempt's cycle
    failed_at = np.array([t1 for _, t1, ok in opens[1:-1]])
    assert [ok for *_, ok in opens] == [True] + [False] * failed_at.size + [True]  # start-up, outage, back
    assert attempts.size == failed_at.size + 1 >= 7
    starts = _cycle_starts(log, 0.01, attempts)
    tol = 2e-6  # the log's late_ms has 1 us steps
    for k, (failed, attempt) in enumerate(zip(failed_at, attempts[1:])):
        due = min(0.05 * 2.0**k, 0.4) - tol  # 0.05, 0.1, 0.2, 0.4, 0.4, 0.4, ... (uncapped: 0.8, 1.6)
        seen = starts[np.searchsorted(starts, failed)]  # the first cycle after the failure ...
        j = np.searchsorted(starts, attempt - tol)  # ... and the cycle of the next attempt
        assert starts[j - 1] - seen < due + 2 * tol and attempt - seen >= due, (k, seen, starts[j - 1], attempt)
    after = log.loc[down.index[-1] + 1:]
    assert (after["flags"] & RESTARTED).any()  # the server's clock restarted: a new timeline
    assert _time_steps_within(log, 20.0)  # and the compensation never stepped, across the outage too


@pytest.fixture(scope="module")
def certs(tmp_path_factory):
    root = tmp_path_factory.mktemp("pki")
    return make_certificates(root / "ok"), make_certificates(root / "stranger")


def test_security_user_password_and_basic256sha256(machine, seed001_exports, nodes_file, certs, tmp_path, monkeypatch):
    from asyncua import Client, ua

    ok, stranger = certs
    monkeypatch.setenv("THERMBENCH_OPCUA_PASSWORD", "s3cret")

    def sec(c=ok, **kw):
        return {"user": "operator", "policy": "Basic256Sha256", "certificate": str(c["client_certificate"]),
                "private_key": str(c["client_private_key"]), "server_certificate": str(ok["server_certificate"]), **kw}  # fmt: skip

    async def scenario():
        port = _port()
        ep = f"opc.tcp://127.0.0.1:{port}/sim"
        srv = SimCnc(machine, {"endpoint": ep, "run": RUN, "speed": 20.0, "start": "immediate",
                               "security": {"user": "operator", "certificate": str(ok["server_certificate"]),
                                            "private_key": str(ok["server_private_key"]),
                                            "trusted_clients": [str(ok["client_certificate"])]}})  # fmt: skip
        await srv.start_server()
        clock = asyncio.ensure_future(srv.run_clock())
        try:
            comp = Compensator(seed001_exports / "mlr", ep, nodes_file, _client_cfg(tmp_path, period_s=0.01, max_cycles=60,
                                                                                       security=sec()))  # fmt: skip
            s = await comp.run()
            written = srv.server.read_attribute_value(srv.comp["value"]).Value.Value
            refused = {}
            for name, cfg in {"wrong password": sec(password_env="WRONG_PW"), "no encryption": {},
                              "untrusted certificate": sec(stranger),
                              "not the pinned server": sec(server_certificate=str(stranger["server_certificate"]))}.items():  # fmt: skip
                try:
                    await Compensator(seed001_exports / "mlr", ep, nodes_file, _client_cfg(tmp_path, max_cycles=1,
                                                                                           security=cfg)).run()  # fmt: skip
                except CompensatorError as exc:
                    refused[name] = str(exc)
            # an output node of another data type is a set-up error, found when connecting
            wrong = yaml.safe_load(nodes_file.read_text())
            wrong["outputs"] = {"value": {"node": "ns=2;s=X.TempComp_Status", "unit": "um"}}
            (tmp_path / "wrong.yaml").write_text(yaml.safe_dump(wrong))
            with pytest.raises(CompensatorError, match=r"wrong\.yaml: key outputs\.value\.node: output value node "
                                                       r"'ns=2;s=X\.TempComp_Status' has data type Int32; the "
                                                       r"compensator writes Double$"):  # a name, not a NodeId(...)
                await Compensator(seed001_exports / "mlr", ep, tmp_path / "wrong.yaml", _client_cfg(tmp_path, security=sec())).run()
            # Ctrl-C (the task cancelled) still leaves the summary beside the log
            stopped = Compensator(seed001_exports / "mlr", ep, nodes_file, _client_cfg(tmp_path, log=str(tmp_path / "int.csv"),
                                                                                        security=sec()))  # fmt: skip
            t = asyncio.ensure_future(stopped.run())
            end = asyncio.get_running_loop().time() + 60.0  # a guard against a hang, not a speed limit
            while not ((tmp_path / "int.csv").exists() and len((tmp_path / "int.csv").read_text().splitlines()) > 12):
                assert asyncio.get_running_loop().time() < end and not t.done(), "the compensator does not cycle"
                await asyncio.sleep(0.05)
            stopped.stop("interrupted")  # what the command's SIGINT handler does
            await t
            interrupted = json.loads((tmp_path / "int.summary.json").read_text())
            # the compensator writes its outputs and nothing else, even over a good session
            session_writer = None
            c2 = Compensator(seed001_exports / "mlr", ep, nodes_file, _client_cfg(tmp_path, security=sec()))
            await c2.session.open()
            session_writer = c2.session.writer
            feed_id = "ns=2;s=X.Feed_mm_min"
            before = srv.server.read_attribute_value(srv.ids["feed_mm_min"]).Value.Value
            with pytest.raises(RefusedWrite, match="X.Feed_mm_min"):
                await session_writer.write_node(feed_id, ua.Variant(1234.5, ua.VariantType.Double))
            with pytest.raises(RefusedWrite):
                await session_writer.write({"feed": ua.Variant(1.0, ua.VariantType.Double)})
            after = srv.server.read_attribute_value(srv.ids["feed_mm_min"]).Value.Value
            await c2.session.close()
            # and the server itself refuses writes to an input (read-only node)
            raw = Client(ep)
            raw.application_uri = "urn:thermbench:compensator"
            raw.set_user("operator")
            raw.set_password("s3cret")
            await raw.set_security_string(f"Basic256Sha256,SignAndEncrypt,{ok['client_certificate']},"
                                          f"{ok['client_private_key']},{ok['server_certificate']}")  # fmt: skip
            async with raw:
                with pytest.raises(ua.UaStatusCodeError):
                    await raw.get_node(feed_id).write_value(ua.Variant(1.0, ua.VariantType.Double))
            return s, written, refused, before, after, interrupted
        finally:
            clock.cancel()
            await srv.stop_server()

    monkeypatch.setenv("WRONG_PW", "guess")
    s, written, refused, before, after, interrupted = asyncio.run(scenario())
    assert interrupted["ended"] == "interrupted" and interrupted["cycles"] > 10
    assert s["cycles"] == 60 and math.isfinite(written) and written != 0.0
    assert set(refused) == {"wrong password", "no encryption", "untrusted certificate", "not the pinned server"}
    assert all("cannot connect" in m and "\n" not in m for m in refused.values())

    def sha1(path) -> str:  # the thumbprint as OPC UA tools show it, computed by cryptography itself
        from cryptography import x509
        from cryptography.hazmat.primitives import hashes

        data = open(path, "rb").read()
        load = x509.load_pem_x509_certificate if data.startswith(b"-----") else x509.load_der_x509_certificate
        return load(data).fingerprint(hashes.SHA1()).hex(":").upper()

    assert (f"the server refused this client's certificate (security.certificate={stranger['client_certificate']}, "
            f"SHA-1 {sha1(stranger['client_certificate'])}): add it to the server's trusted") in refused["untrusted certificate"]
    assert (f"the server's certificate is not the pinned one (security.server_certificate={stranger['server_certificate']}, "
            f"SHA-1 {sha1(stranger['server_certificate'])}); {refused['not the pinned server'].split('cannot connect to ')[1].split(':')[0]}"
            in refused["not the pinned server"])  # fmt: skip
    assert f"presents SHA-1 {sha1(ok['server_certificate'])}" in refused["not the pinned server"]
    assert "BadUserAccessDenied" in refused["wrong password"]
    assert "No matching endpoints" in refused["no encryption"]  # the server offers sign-and-encrypt only
    # and the client never sends a password unencrypted, nor trusts an unpinned server
    with pytest.raises(CompensatorError, match="never sent unencrypted"):
        Compensator(seed001_exports / "mlr", "opc.tcp://127.0.0.1:1", nodes_file, {"security": {"user": "operator"}})
    with pytest.raises(CompensatorError, match="server_certificate"):
        Compensator(seed001_exports / "mlr", "opc.tcp://127.0.0.1:1", nodes_file, {"security": sec(server_certificate=None)})
    assert "BadCertificateUntrusted" in refused["untrusted certificate"]
    assert after == before


def test_cli_errors_name_what_is_wrong(machine, seed001_exports, nodes_file, tmp_path, capsys):
    ep = f"opc.tcp://127.0.0.1:{_port()}/nothing-here"
    assert main(["compensator", str(seed001_exports / "mlr"), "--endpoint", ep, "--nodes", str(nodes_file), "timeout_s=0.5",
                 f"log={tmp_path / 'c.csv'}"]) == 2  # fmt: skip
    assert "cannot connect to " + ep in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text(nodes_file.read_text().replace("T_nut:", "T_other:"))
    assert main(["compensator", str(seed001_exports / "mlr"), "--endpoint", ep, "--nodes", str(bad)]) == 2
    assert "inputs.temperatures" in capsys.readouterr().err
    assert main(["compensator", str(seed001_exports / "mlr"), "--endpoint", ep, "--nodes", str(nodes_file), "perod_s=1"]) == 2
    assert "perod_s" in capsys.readouterr().err
    assert main(["sim-cnc", "run=nope", "duration_s=10"]) == 2
    assert "'nope'" in capsys.readouterr().err
    assert main(["sim-cnc", "security.user=operator"]) == 2  # a password server without encryption
    assert "never taken unencrypted" in capsys.readouterr().err
    assert main(["sim-cnc", "run=nope", "duration_s=10"]) == 2
    assert "'nope'" in capsys.readouterr().err
    with pytest.raises(SimCncError, match=r"faults.sensor\[0\]"):
        SimCnc(machine, {"faults": {"sensor": [{"sensor": "T_x", "from_s": 0, "to_s": 1, "value": 0}]}})
    assert main(["certs", str(tmp_path / "pki")]) == 0
    assert main(["certs", str(tmp_path / "pki")]) == 2
    assert "never overwritten" in capsys.readouterr().err


def test_warm_restart_resumes_and_a_long_outage_starts_cold_loudly(machine, seed001_exports, nodes_file, tmp_path):
    """Three compensator processes against one running machine (10x): the first saves its state;
    the second, started at once, resumes it (says so, first cycle RESUMED, the value the
    controller holds continued); the third, started after more than 60 s of machine time, starts
    cold and says so in one line, every cycle flagged COLD. (At 10x a loaded host has 6 s of wall
    clock to start the second process within the 60 s the runtime bridges.)"""
    state = tmp_path / "state.json"
    said = asyncio.run(_restarted_compensators(machine, seed001_exports / "mlr", nodes_file, tmp_path,
                                               (0.0, 0.0, 7.0), 1.5, speed=10.0, start="immediate"))  # 7 s wall = 70 s machine
    logs = [pd.read_csv(tmp_path / f"run{n}.csv") for n in range(3)]
    first, second, third = logs
    assert any(ln.startswith("starting fresh: no saved state at ") for ln in said[0])  # the first start: nothing saved
    assert not (first["flags"] & int(Flags.COLD)).any()
    resumed = [ln for ln in said[1] if ln.startswith("resumed the model state of ")]
    assert len(resumed) == 1 and "samples re-stepped" in resumed[0]
    assert int(second["flags"].iloc[0]) & int(Flags.RESUMED) and not (second["flags"] & int(Flags.COLD)).any()
    # the controller's value goes on from where the first process left it (rate limit 20 µm/s, 1 s per cycle at most)
    last, nxt = first["value_um"].dropna().iloc[-1], second["value_um"].dropna().iloc[0]
    assert abs(nxt - last) <= 20.0 + 1e-9
    # the machine time goes on too: the second process's t_s continues the first's (same origin)
    # (at or past its last sample: a second process started at once may read the same sample, 0.1 s of wall at 10x)
    assert second["t_s"].iloc[0] >= first["t_s"].iloc[-1] > 0
    cold = [ln for ln in said[2] if ln.startswith("COLD START: the saved state is ")]
    assert len(cold) == 1 and "more than the 60 s the runtime bridges" in cold[0] and "\n" not in cold[0]
    assert (third["flags"] & int(Flags.COLD)).all() and "COLD" in third["flag_names"].iloc[-1]
    saved = json.loads(state.read_text())
    assert saved["rows"] > 0 and saved["cold"] is True


def test_a_long_outage_is_replayed_from_the_servers_history(machine, seed001_exports, nodes_file, tmp_path):
    """The machine keeps its inputs' history (OPC UA Historical Access) as a data-change historian
    does, a value when it changes: a compensator back after 120 s of machine time (more than the
    60 s the runtime bridges) replays the outage from it and resumes warm, though the feed and the
    measuring flag stood still for more than 60 s of it (no point in their history then: held).
    Its predictions are then thermbench replay's, sample by sample, over the run as the machine
    played it: as if it had never stopped."""
    from thermbench.data.io import load_dataset, save_dataset
    from thermbench.export.directory import replay_dir
    from thermbench.export.samples import process_samples

    said = asyncio.run(_restarted_compensators(machine, seed001_exports / "mlr", nodes_file, tmp_path, (0.0, 6.0), 2.0,
                                               start="on_compensator", history="changes"))  # 6 s wall = 120 s machine
    back = [ln for ln in said[1] if ln.startswith("resumed the model state of ")]
    if not (len(back) == 1 and "the outage replayed from the server's history (" in back[0]):
        pytest.fail("the second compensator said:\n" + "\n".join(said[1]), pytrace=False)  # every word of its reason
    first, second = (pd.read_csv(tmp_path / f"run{n}.csv") for n in (0, 1))
    gap = second["t_s"].iloc[0] - first["t_s"].iloc[-1]
    assert 61 < gap < 400 and not (second["flags"] & int(Flags.COLD)).any()
    # in this outage an input stood still for more than the 60 s the runtime bridges: its history has no
    # point then, which is no hole (a check of each input's own gaps refused such a history)
    t = machine.samples["t_s"].to_numpy()
    out = (t > first["t_s"].iloc[-1]) & (t < second["t_s"].iloc[0])
    still = [c for c in ("feed_mm_min", "measuring") if _longest_constant_s(t[out], machine.samples[c].to_numpy()[out]) > 60]
    assert still, "the outage has no input standing still for a minute: it does not test a change-only history"
    save_dataset(machine.dataset, tmp_path / "ds")
    ds = load_dataset(tmp_path / "ds")
    samples = process_samples(ds, RUN)
    # the samples the model stepped (the state file's record): the loops' own and the outage's from history
    stepped = pd.read_csv(tmp_path / "state.json.samples.csv", header=None)
    k_s = stepped[0].to_numpy()
    outage = (k_s > first["t_s"].max()) & (k_s < second["t_s"].min())
    want_outage = np.arange(np.floor(first["t_s"].max() + 1e-3) + 1, second["t_s"].min())
    np.testing.assert_array_equal(k_s[outage], want_outage)  # the history fills every grid point of the outage
    rows = samples.set_index("t_s").loc[k_s]  # ... with the machine's values there (the dataset's, 1 s samples)
    np.testing.assert_allclose(stepped[[1, 2, 5, 6]].to_numpy(), rows[["axis_mm", "feed_mm_min", "T_nut_C", "T_bed_C"]].to_numpy(),
                               rtol=0, atol=1e-9)  # fmt: skip
    # The reference: the C runtime replaying the run over those samples. A loaded host's loop may miss a
    # sample the machine played (its model then steps over it); with none missed this is replay_run's run.
    played = samples[samples["t_s"].isin(k_s) | (samples["t_s"] > k_s.max())].reset_index(drop=True)
    comp = replay_dir(seed001_exports / "mlr", ds, RUN, played[["t_s", "axis_mm"]], samples=played, live=True)
    comp = comp.set_index("t_s")["total_um"]
    if len(played) == len(samples):
        full = replay_run(seed001_exports / "mlr", tmp_path / "ds", RUN)["compensation"].set_index("t_s")
        np.testing.assert_allclose(comp.fillna(0.0).to_numpy(), -full["compensation_um"].to_numpy(), rtol=0, atol=1e-9)
    # the first run saw the run from its start: replay's numbers, as the closed loop always gave
    f1 = first[(first["flags"] & HELD) == 0]
    k1 = np.floor(f1["t_s"].to_numpy() + 1e-3)
    np.testing.assert_allclose(f1["predicted_um"].to_numpy(), comp.loc[k1].to_numpy(), rtol=0, atol=1e-6)
    fresh = second[(second["flags"] & HELD) == 0]
    k = np.floor(fresh["t_s"].to_numpy() + 1e-3)  # the model's last grid point (1 s) at each cycle
    assert len(fresh) > 50 and set(k) <= set(comp.index)
    np.testing.assert_allclose(fresh["predicted_um"].to_numpy(), comp.loc[k].to_numpy(), rtol=0, atol=1e-6)


def _longest_constant_s(t: np.ndarray, v: np.ndarray) -> float:
    """The longest time ``v`` keeps one value (from its first sample to the first of the next value)."""
    edges = np.concatenate([[0], np.flatnonzero(np.diff(v) != 0) + 1, [len(v) - 1]])
    return float(np.diff(t[edges]).max())


async def _restarted_compensators(machine, model_dir, nodes_file, tmp_path, pauses_s, duration_s, speed=20.0, **sim_kw):
    """One sim-cnc (``speed`` x real time); a compensator with ``state.path`` started after each pause (wall s), run for
    ``duration_s``; returns what each said (its log is ``run<n>.csv``)."""
    ep = f"opc.tcp://127.0.0.1:{_port()}/sim"
    sim = SimCnc(machine, {"endpoint": ep, "run": RUN, "speed": speed, **sim_kw})
    await sim.start_server()
    clock = asyncio.ensure_future(sim.run_clock())
    said = []
    try:
        for n, pause_s in enumerate(pauses_s):
            await asyncio.sleep(pause_s)
            cfg = _client_cfg(tmp_path, period_s=0.01, log=str(tmp_path / f"run{n}.csv"), duration_s=duration_s,
                              state={"path": str(tmp_path / "state.json"), "every_s": 0.2})  # fmt: skip
            lines: list[str] = []
            await Compensator(model_dir, ep, nodes_file, cfg, say=lines.append).run()
            said.append(lines)
    finally:
        clock.cancel()
        await sim.stop_server()
    return said


def test_probe_node_corrects_the_loop_as_replay_with_the_same_probes(machine, seed001_exports, tmp_path):
    """sim-cnc's touch probe (``probe_every_s``: node X.Probe_um, the thermal error at the axis,
    stamped when taken) feeds the compensator's probe input: each reading is taken once, at its
    source time, and the loop's corrected compensation is what the C runtime gives replaying the
    samples the loop stepped with the probes sim-cnc wrote to probes.csv (``thermbench replay
    --probes``). The probe's values are the simulator's, checked against the interferometer."""
    from thermbench.data.io import load_dataset
    from thermbench.export.directory import replay_dir
    from thermbench.export.samples import process_samples
    from thermbench.export.replay import read_probes
    from thermbench.bench.adapt import ProbeParams
    from thermbench.config import with_defaults

    nodes = tmp_path / "nodes.yaml"
    nodes.write_text(yaml.safe_dump(nodes_yaml(machine, probe=True)))
    f, s, log = asyncio.run(_closed_loop(machine, seed001_exports / "mlr", nodes, tmp_path,
                                         sim_kw={"probe_every_s": 120.0, "speed": 60.0}, period_s=0.01))  # fmt: skip
    probes = read_probes(tmp_path / "sim" / "probes.csv")
    assert f["n_probes"] == len(probes) == 7 and np.allclose(probes["t_s"], 120.0 * np.arange(1, 8))
    # the probe reads the simulator's thermal error: at a dwell on a reading's target, the reading less its noise
    rd = machine.readings.set_index("t_s")
    at = probes[probes["t_s"].isin(rd.index)]
    for _, p in at.iterrows():
        if np.isclose(rd.loc[p["t_s"], "target_mm"], p["axis_mm"]):
            assert abs(rd.loc[p["t_s"], "thermal_um"] - p["measured_um"]) < 1.5
    # each probe taken once, at the cycle that first saw it, with its value
    took = log[(log["flags"] & int(Flags.PROBE)) > 0]
    assert len(took) == len(probes) and s["flags"].get("PROBE", 0) == len(probes)
    np.testing.assert_array_equal(took["probe_um"].to_numpy(), probes["measured_um"].to_numpy())
    assert (took["t_s"].to_numpy() >= probes["t_s"].to_numpy()).all()
    # the reference: the C runtime over the samples the loop stepped, with the same probes and filter
    ds = load_dataset(tmp_path / "sim" / "dataset")
    samples = process_samples(ds, RUN)
    fresh = log[((log["flags"] & HELD) == 0) & log["predicted_um"].notna()]
    k = np.floor(fresh["t_s"].to_numpy() + 1e-3)
    seen = np.floor(log["t_s"].dropna().to_numpy() + 1e-3)  # every sample the loop stepped (held cycles too)
    played = samples[samples["t_s"].isin(seen)].reset_index(drop=True)
    q = pd.DataFrame({"t_s": k, "axis_mm": fresh["axis_mm"].to_numpy()})
    params = ProbeParams.from_config(with_defaults("compensator", {})["probe"])
    # the probes as the loop took them: their times and values, at the axis where the loop then was (a
    # loaded host's loop may miss the sample a probe came with: it sees the probe a sample later, there)
    took_at = probes.assign(axis_mm=took["axis_mm"].to_numpy())
    # each taken by the first cycle that read the sample it came with: at most one cycle before read a sample
    # at or past its time (sim-cnc writes a sample's nodes one by one, so a read may fall between them)
    t_log = log["t_s"].dropna()
    for i, t_p in zip(took.index, probes["t_s"]):
        assert (t_log.loc[: i - 1] >= t_p).sum() <= 1 and t_p <= log.loc[i, "t_s"], (i, t_p)
    ref = replay_dir(seed001_exports / "mlr", ds, RUN, q, samples=played, live=True, probes=took_at, probe_params=params)
    corrected = fresh["predicted_um"].to_numpy() + fresh["correction_um"].to_numpy()
    # a cycle at a probe's own second may have taken it before answering (replay answers first): left out
    away = ~np.isin(k, probes["t_s"].to_numpy())
    assert away.sum() > 100 and np.abs(fresh["correction_um"].to_numpy()[k > probes["t_s"].iloc[0]]).max() > 0.05
    ok = away & (ref["rc"].to_numpy() == 0)
    np.testing.assert_allclose(fresh["predicted_um"].to_numpy()[ok], ref["total_um"].to_numpy()[ok], rtol=0, atol=1e-6)
    np.testing.assert_allclose(corrected[ok], ref["corrected_um"].to_numpy()[ok], rtol=0, atol=1e-3)  # required: <= 0.01
