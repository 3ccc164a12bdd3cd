"""The compensator against an OPC UA server of another stack: node-opcua (Node.js), started by
the test on 127.0.0.1 (tests/node_opcua/server.js; `make test` installs it with `npm ci`).

The server plays the first 5 minutes of the benchmark run valid1 (simulated by sim-cnc's
machine, 100x real time) as Double input nodes whose source timestamps are the samples' machine
times, and records every write to its Double and Int32 output nodes. It offers only Basic256Sha256
SignAndEncrypt with user/password and trusts only the test's client certificate. The nodes file
names the nodes by namespace URI (nsu=...), which the compensator resolves against node-opcua's
own namespace array. Missing Node.js or node-opcua fails the test (it is not skipped).
"""

from __future__ import annotations

import asyncio
import json
import os
import shutil
import socket
import subprocess
import time
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from thermbench.compensator.certs import make_certificates
from thermbench.compensator.client import Compensator
from thermbench.compensator.errors import CompensatorError
from thermbench.compensator.simcnc import build_machine
from tests.test_compensator import fault_window

pytestmark = pytest.mark.timing  # a real-time loop: run alone (see the Makefile)

SERVER_DIR = Path(__file__).resolve().parent / "node_opcua"
URI = "urn:a-vendor:machine"
PASSWORD_ENV = "TB_NODE_OPCUA_PASSWORD"


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.fixture(scope="module")
def node():
    exe = shutil.which("node")
    if exe is None or not (SERVER_DIR / "node_modules" / "node-opcua").is_dir():
        pytest.fail("Node.js and node-opcua are needed: make test installs node-opcua (npm ci in tests/node_opcua)")
    return exe


@pytest.fixture(scope="module")
def machine():
    return build_machine({"benchmark": "seed001_vmc_x", "run": "valid1", "duration_s": 300})


@pytest.fixture(scope="module")
def pki(tmp_path_factory):
    root = tmp_path_factory.mktemp("pki")
    return make_certificates(root / "ok"), make_certificates(root / "stranger")


class NodeServer:
    """tests/node_opcua/server.js in a subprocess, with its config and files in ``tmp``."""

    def __init__(self, node: str, machine, certs, tmp: Path, port: int | None = None, faults: dict | None = None) -> None:
        self.tmp, self.port = tmp, port or _port()
        for f in ("ready.txt",):
            (tmp / f).unlink(missing_ok=True)
        cols = [("t_s", "t_s"), ("Position_mm", "axis_mm"), ("Feed_mm_min", "feed_mm_min")]
        cols += [(f"{s}_C", f"{s}_C") for s in machine.sensors]
        self.cfg = {
            "port": self.port, "uri": URI, "columns": [{"name": n} for n, _ in cols],
            "samples": machine.samples[[c for _, c in cols]].to_numpy().tolist(), "speed": 100.0, "linger_s": 0.3,
            "pki": str(tmp / "server_pki"), "trusted_clients": [str(certs["client_certificate"])],
            "certificate": str(certs["server_certificate"]), "private_key": str(certs["server_private_key"]),
            "application_uri": "urn:thermbench:sim-cnc", "user": "operator", "password_env": PASSWORD_ENV,
            "writes": str(tmp / "writes.jsonl"), "ready": str(tmp / "ready.txt"),
            "faults": faults or {"sensor": [], "freeze": []},
        }  # fmt: skip
        (tmp / "server.json").write_text(json.dumps(self.cfg))
        env = {**os.environ, PASSWORD_ENV: "s3cret"}
        self.log = open(tmp / "node.log", "a")
        self.proc = subprocess.Popen([node, str(SERVER_DIR / "server.js"), str(tmp / "server.json")], env=env,
                                     stdout=self.log, stderr=subprocess.STDOUT, start_new_session=True)  # fmt: skip
        deadline = time.monotonic() + 60
        while not (tmp / "ready.txt").exists():
            if self.proc.poll() is not None or time.monotonic() > deadline:
                self.stop()
                pytest.fail(f"node-opcua server did not start:\n{(tmp / 'node.log').read_text()[-3000:]}")
            time.sleep(0.05)
        self.endpoint = f"opc.tcp://127.0.0.1:{self.port}/sim"

    def writes(self) -> list[dict]:
        path = self.tmp / "writes.jsonl"
        return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []

    def stop(self) -> None:
        if self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        self.log.close()


def nodes_file(tmp: Path, machine, done: bool = True) -> Path:
    ns = f"nsu={URI};s="
    nodes = {"inputs": {"axis_mm": f"{ns}X.Position_mm", "feed_mm_min": f"{ns}X.Feed_mm_min",
                        "done": f"{ns}Machine.ProgramDone", "temperatures": {s: f"{ns}X.{s}_C" for s in machine.sensors}},
             "outputs": {"value": {"node": f"{ns}X.TempComp_um", "unit": "um"}, "status": f"{ns}X.TempComp_Status"}}  # fmt: skip
    if not done:  # the loop runs on after the program's end (until duration_s)
        del nodes["inputs"]["done"]
    p = tmp / "nodes.yaml"
    p.write_text(yaml.safe_dump(nodes))
    return p


def security(certs, server_certs) -> dict:
    return {"user": "operator", "policy": "Basic256Sha256", "certificate": str(certs["client_certificate"]),
            "private_key": str(certs["client_private_key"]), "server_certificate": str(server_certs["server_certificate"])}  # fmt: skip


def test_the_loop_against_node_opcua_writes_what_it_computes(node, machine, pki, seed001_exports, tmp_path, monkeypatch):
    ok, stranger = pki
    monkeypatch.setenv("THERMBENCH_OPCUA_PASSWORD", "s3cret")
    srv = NodeServer(node, machine, ok, tmp_path)
    try:
        refused = {}
        for name, sec in {"untrusted certificate": security(stranger, ok), "not the pinned server": security(ok, stranger),
                          "wrong password": {**security(ok, ok), "password_env": "TB_WRONG"}}.items():  # fmt: skip
            monkeypatch.setenv("TB_WRONG", "guess")
            try:
                asyncio.run(Compensator(seed001_exports / "mlr", srv.endpoint, nodes_file(tmp_path, machine),
                                        {"period_s": 0.01, "log": str(tmp_path / f"{name}.csv"), "security": sec}).run())  # fmt: skip
            except CompensatorError as exc:
                refused[name] = str(exc)
        cfg = {"period_s": 0.01, "log": str(tmp_path / "cycles.csv"), "security": security(ok, ok), "status_every_s": 0.5}
        lines: list[str] = []  # what the command prints
        summary = asyncio.run(Compensator(seed001_exports / "mlr", srv.endpoint, nodes_file(tmp_path, machine), cfg,
                                          say=lines.append).run())  # fmt: skip
    finally:
        srv.stop()
    # every security refusal named in one line
    assert set(refused) == {"untrusted certificate", "not the pinned server", "wrong password"}, refused
    assert "the server refused this client's certificate" in refused["untrusted certificate"]
    assert "the server's certificate is not the pinned one" in refused["not the pinned server"]
    assert "BadUserAccessDenied" in refused["wrong password"] or "BadIdentityTokenRejected" in refused["wrong password"]
    assert all("\n" not in m for m in refused.values())
    # the loop ran to the program's end and compensated, saying so as it went
    assert summary["ended"] == "the machine's program is done"
    assert lines[0] == f"connected to {srv.endpoint}: {2 + len(machine.sensors) + 1} inputs, outputs value, status"
    status = [ln for ln in lines[1:] if ln.startswith("cycle ")]
    log = pd.read_csv(tmp_path / "cycles.csv")
    # one status line per status_every_s (0.5 s) of the loop's wall time, said at the end of the first cycle
    # past it: between two lines 0.5 s plus at most the longest step between cycles, as the log shows them
    wall_s = log["wall_s"].iloc[-1] - log["wall_s"].iloc[0]
    step_s = log["wall_s"].diff().max()
    assert wall_s / (0.5 + step_s) - 2 <= len(status) <= wall_s / 0.5 + 1, (len(status), wall_s, step_s)
    assert all(" ms mean, " in ln and "; compensation " in ln for ln in status)
    ok_cycles = log[log["flag_names"] == "OK"]
    # once every input has arrived, every cycle compensates, to the program's end. How many cycles fit in
    # the program's 3 s of wall time depends on the host (CI on 2026-11-29: 96 of 30 ms each, here about
    # 250), so none is counted: what the cycles read is checked (machine time, below)
    first_ok = log.index[log["flag_names"] == "OK"][0]
    assert (log.loc[first_ok:, "flag_names"] == "OK").all(), log["flag_names"].value_counts().to_dict()
    assert ok_cycles["t_s"].nunique() >= 2, log["flag_names"].value_counts().to_dict()
    # the program starts at the loop's first read (not at the server's start, which the refused clients
    # before it would eat into: the CI run of 2026-11-29 saw the loop join at 150 s), so it is seen to its end
    assert ok_cycles["t_s"].max() >= 250 and ok_cycles["t_s"].is_monotonic_increasing
    assert np.all(np.isfinite(ok_cycles["value_um"])) and np.abs(ok_cycles["value_um"]).max() > 3.0  # a warming axis
    # node-opcua received exactly what the compensator logged: the Double bit for bit, the flags as Int32
    writes = srv.writes()
    doubles = [w["value"] for w in writes if w["node"] == "TempComp_um"]
    ints = [w["value"] for w in writes if w["node"] == "TempComp_Status"]
    assert {w["dataType"] for w in writes if w["node"] == "TempComp_um"} == {"Double"}
    assert {w["dataType"] for w in writes if w["node"] == "TempComp_Status"} == {"Int32"}
    assert doubles == log["value_um"].tolist()
    assert ints == log["flags"].astype(int).tolist()


def test_faults_and_a_restart_of_the_node_opcua_server(node, pki, seed001_exports, tmp_path, monkeypatch):
    """The fault tests of the sim-cnc suite against node-opcua: a NaN sensor (held at its last good
    value, INPUT_HELD), frozen data (the timestamps stop: STALE, the compensation held at one
    value), and the server killed and started again on the same port (DISCONNECTED and HELD while
    it is down, then reconnected and RESTARTED: its program starts again)."""
    import threading

    from thermbench.compensator.control import Flags

    ok, _ = pki
    monkeypatch.setenv("THERMBENCH_OPCUA_PASSWORD", "s3cret")
    m = build_machine({"benchmark": "seed001_vmc_x", "run": "valid1", "duration_s": 500})
    faults = {"sensor": [{"column": "T_nut_C", "from_s": 100, "to_s": 160, "value": None}],
              "freeze": [{"from_s": 300, "to_s": 400}]}  # fmt: skip
    srv = NodeServer(node, m, ok, tmp_path, faults=faults)
    servers = [srv]

    def restart():  # 7 s after the loop starts: the first program (500 s at 100x from the first read) is over
        servers[-1].stop()
        time.sleep(0.5)
        servers.append(NodeServer(node, m, ok, tmp_path, port=srv.port, faults={"sensor": [], "freeze": []}))

    cfg = {"period_s": 0.01, "log": str(tmp_path / "cycles.csv"), "security": security(ok, ok), "stale_after_s": 0.3,
           "reconnect": {"initial_s": 0.05, "max_s": 0.4, "factor": 2.0}, "duration_s": 18.0}  # fmt: skip
    nodes = nodes_file(tmp_path, m, done=False)
    timer = threading.Timer(7.0, restart)
    timer.start()
    try:
        summary = asyncio.run(Compensator(seed001_exports / "mlr", srv.endpoint, nodes, cfg).run())
    finally:
        timer.join()
        for s in servers:
            s.stop()
    log = pd.read_csv(tmp_path / "cycles.csv")
    INPUT_HELD, STALE, HELD = int(Flags.INPUT_HELD), int(Flags.STALE), int(Flags.HELD)
    DISCONNECTED, RESTARTED = int(Flags.DISCONNECTED), int(Flags.RESTARTED)
    first = log.loc[: log.index[(log["flags"] & DISCONNECTED) > 0][0] - 1]  # before the restart
    # the log's t_s counts from the loop's first cycle, the faults from the server's program start: the
    # NaN window is found in the log as the one block of cycles holding T_nut_C, 60 s of machine time long
    # (other inputs may be held for a cycle where the freeze ends between two nodes' reads: one node still
    # stamped 300 s, the rest 400 s, the older one stale; the CI run of 2026-11-29 had one such cycle)
    holds_nut = first["held"].fillna("").str.split(";").map(lambda h: "T_nut_C" in h)
    nan_win = first[holds_nut]
    assert nan_win["held"].eq("T_nut_C").all() and (nan_win["flags"] & INPUT_HELD).all()
    fault_window(first, nan_win, 60.0)  # 60 machine s, by the cycles in it and either side
    assert (nan_win["T_nut_C"] == first.loc[nan_win.index[0] - 1, "T_nut_C"]).all()  # held at the last good value
    is_stale = (first["flags"] & STALE) > 0
    start = is_stale.idxmax()
    freeze = first.loc[start:][~is_stale.loc[start:]].index[0]  # the freeze: the first block of stale cycles
    stale = first.loc[start : freeze - 1]
    assert len(stale) >= 2 and (stale["flags"] & HELD).all() and stale["value_um"].nunique() == 1
    assert is_stale.loc[freeze:].any()  # and again once the program is over: nothing new is published
    down = log[(log["flags"] & DISCONNECTED) > 0]
    assert len(down) >= 2 and (down["flags"] & HELD).all() and down["value_um"].nunique() == 1
    after = log.loc[down.index[-1] + 1:]
    # a new timeline: the model restarts on a machine that may be warm, so from then on every cycle says COLD
    restart = after.index[(after["flags"] & RESTARTED) > 0]
    assert len(restart) and ((after["flags"] & HELD) == 0).sum() >= 10
    assert (log.loc[restart[0]:, "flags"] & int(Flags.COLD)).all() and not (log.loc[:10, "flags"] & int(Flags.COLD)).any()
    assert summary["flags"]["reconnects"] >= 1
