"""The user's input files and settings, read strictly and reported by name.

* nodes and station files are read by the strict YAML loader (no aliases, anchors or
  duplicate keys; one line naming the file and the line);
* a negative sensor noise is refused, naming the config key and what it takes;
* a sensor column a dataset holds but does not declare is ignored with a warning naming the
  file and the column;
* ``thermbench replay`` warns when the dataset is of another machine than the model's;
* on connecting, a wrong output data type is named (Int32), not shown as a raw NodeId, and a
  missing node names the nodes file and the key as written in it (against sim-cnc's server).

Everything here runs in seconds: small files in tmp_path, a three-run analytic dataset, and
sim-cnc's address space for a stand-in machine (no simulation, no exported model).
"""

from __future__ import annotations

import asyncio
import socket
import sys
import warnings
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest
import yaml

from thermbench.cli import main
from thermbench.compensator.errors import CompensatorError
from thermbench.compensator.opcua import Security, Session
from thermbench.compensator.nodes import NodesError, load_nodes
from thermbench.compensator.simcnc import SimCnc, nodes_yaml
from thermbench.compensator.station import StationError, load_station
from thermbench.config import ConfigError
from thermbench.data.io import DatasetWarning, load_dataset, save_dataset

sys.path.insert(0, str(Path(__file__).parent))
from synth import analytic_dataset, rise  # noqa: E402

SENSORS = ["T_nut", "T_bed"]


def _nodes(tmp_path, text: str, name: str = "nodes.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD_NODES = """\
inputs:
  axis_mm: "ns=2;s=X.Position_mm"
  feed_mm_min: "ns=2;s=X.Feed_mm_min"
  temperatures:
    T_nut: "ns=2;s=X.T_nut_C"
outputs:
  value: {node: "ns=2;s=X.TempComp_um", unit: um}
"""


# ------------------------------------------------------------ strict YAML ---
def test_a_good_nodes_file_still_loads_and_remembers_where_each_node_is_set(tmp_path):
    nodes = load_nodes(_nodes(tmp_path, GOOD_NODES), ["T_nut"])
    assert nodes.input_ids()["T_nut_C"] == "ns=2;s=X.T_nut_C"
    assert nodes.where("T_nut_C") == f"{tmp_path / 'nodes.yaml'}: key inputs.temperatures.T_nut"
    assert nodes.where("value", output=True) == f"{tmp_path / 'nodes.yaml'}: key outputs.value.node"


@pytest.mark.parametrize(
    "text, problem",
    [
        (GOOD_NODES.replace('  feed_mm_min: "ns=2;s=X.Feed_mm_min"\n',
                            '  feed_mm_min: "ns=2;s=X.Feed_mm_min"\n  axis_mm: "ns=2;s=Y.Position_mm"\n'),
         "line 4: duplicate key 'axis_mm' (first at line 2): each key may appear once in a mapping"),
        (GOOD_NODES.replace('  axis_mm: "ns=2;s=X.Position_mm"', '  axis_mm: &x "ns=2;s=X.Position_mm"')
                   .replace('  feed_mm_min: "ns=2;s=X.Feed_mm_min"', "  feed_mm_min: *x"),
         "line 2: anchor &x refused"),
        (GOOD_NODES.replace('  feed_mm_min: "ns=2;s=X.Feed_mm_min"', "  feed_mm_min: *x"),
         "line 3: alias *x refused"),
        (GOOD_NODES.replace('"ns=2;s=X.T_nut_C"', "!!python/object:os.system x"), "line 5: tag '!!python/object:os.system' refused"),
    ],
)  # fmt: skip
def test_a_nodes_file_with_a_duplicate_key_or_an_alias_is_refused_naming_the_file(tmp_path, text, problem):
    path = _nodes(tmp_path, text)
    with pytest.raises(NodesError) as exc:
        load_nodes(path, ["T_nut"])
    msg = str(exc.value)
    assert msg.startswith(f"{path}: {problem}"), msg
    assert "\n" not in msg


def test_a_nodes_file_too_large_or_not_utf8_is_refused_naming_the_file(tmp_path):
    big = _nodes(tmp_path, GOOD_NODES + "#" * (1024 * 1024) + "\n", "big.yaml")
    with pytest.raises(NodesError, match=rf"^{big}: 1\.0 MiB is too large for a nodes file \(at most 1\.0 MiB"):
        load_nodes(big, ["T_nut"])
    latin = tmp_path / "latin.yaml"
    latin.write_bytes(GOOD_NODES.encode() + b"# caf\xe9\n")
    with pytest.raises(NodesError, match=rf"^{latin}: line 8: not UTF-8 text \(byte 0xe9\); save the file as UTF-8$"):
        load_nodes(latin, ["T_nut"])


def test_the_command_line_reports_a_duplicate_key_in_one_line(tmp_path, capsys, monkeypatch):
    from thermbench.export import native

    # a stand-in for the exported model (a real one costs a fit and a compile): the nodes file is read next
    monkeypatch.setattr(native, "LiveModel", lambda model_dir: SimpleNamespace(temperatures=["T_nut"], needs_load=False))
    path = _nodes(tmp_path, GOOD_NODES + "inputs: {}\n")
    code = main(["compensator", str(tmp_path / "model"), "--endpoint", "opc.tcp://127.0.0.1:1", "--nodes", str(path)])
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2
    assert err == [f"thermbench: error: {path}: line 8: duplicate key 'inputs' (first at line 1): each key may "
                   "appear once in a mapping"], err  # fmt: skip


def test_a_station_file_with_an_alias_or_a_duplicate_key_is_refused_naming_the_file(tmp_path):
    alias = _nodes(tmp_path, "endpoints: &e {x: {url: opc.tcp://a:1}}\nchannels: *e\n", "station.yaml")
    with pytest.raises(StationError, match=rf"^{alias}: line 1: anchor &e refused"):
        load_station(alias)
    dup = _nodes(tmp_path, "endpoints: {x: {url: opc.tcp://a:1}}\nchannels: {a: {}}\nchannels: {b: {}}\n", "dup.yaml")
    with pytest.raises(StationError, match=rf"^{dup}: line 3: duplicate key 'channels' \(first at line 2\)"):
        load_station(dup)


def test_the_pyfunc_reads_its_metadata_strictly(tmp_path):
    from thermbench.data.errors import DatasetError
    from thermbench.mlflow_pyfunc import ThermbenchPyfunc

    meta = tmp_path / "dataset_metadata.yaml"
    meta.write_text("format: thermbench-dataset/1\nmachine: &m {name: a, axis: X}\nother: *m\n")
    context = SimpleNamespace(artifacts={"model": str(tmp_path / "model.joblib"), "metadata": str(meta)})
    import joblib

    joblib.dump({"a": 1}, tmp_path / "model.joblib")
    with pytest.raises(DatasetError, match=rf"^{meta}: line 2: anchor &m refused"):
        ThermbenchPyfunc().load_context(context)
    meta.write_text("format: thermbench-dataset/1\nmachine: {name: a, axis: X}\n")
    model = ThermbenchPyfunc()
    model.load_context(context)
    assert model.metadata == {"format": "thermbench-dataset/1", "machine": {"name": "a", "axis": "X"}}


def test_what_thermbench_writes_the_strict_reader_reads_back_as_written():
    from thermbench.data.safe_yaml import dump_yaml, load_yaml

    # strings that YAML 1.1 (yaml.safe_dump) leaves unquoted but the strict reader would take for
    # numbers, beside ones that are numbers, and texts that look like dates or hex
    doc = {"config_hash": "1234e56789012345", "run": "1e5", "neg": "-2E3", "hexlike": "0x1F", "date": "2024-03-04",
           "number": 1e-5, "count": 3, "plain": "abc", "nested": [{"id": "7e7"}]}
    assert "config_hash: 1234e56789012345\n" in yaml.safe_dump(doc)  # the writer the fix replaces
    assert load_yaml(yaml.safe_dump(doc))[0]["config_hash"] == float("inf")  # ... and what the reader made of it
    text = dump_yaml(doc, sort_keys=False)
    assert load_yaml(text)[0] == doc and yaml.safe_load(text) == doc


def test_a_cached_datasets_hash_is_read_strictly(tmp_path):
    from thermbench.data.safe_yaml import dump_yaml
    from thermbench.bench.datasets import _cached_hash, _cached_import

    d = tmp_path / "ds"
    d.mkdir()
    (d / "metadata.yaml").write_text(dump_yaml({"simulation": {"config_hash": "1234e56789012345"},
                                                "imported": {"sha256": "00ab"}}))  # fmt: skip
    assert _cached_hash(d) == "1234e56789012345"
    assert _cached_import(d) == "00ab"
    # written unquoted by an earlier thermbench: read as a number, not trusted, the dataset is rebuilt
    (d / "metadata.yaml").write_text("simulation: {config_hash: 1234e56789012345}\n")
    assert _cached_hash(d) is None
    (d / "metadata.yaml").write_text("simulation: {config_hash: abc}\nsimulation: {config_hash: abc}\n")
    assert _cached_hash(d) is None  # a duplicate key: not trusted, the dataset is rebuilt
    assert _cached_hash(tmp_path / "none") is None


# ------------------------------------------------------------- instruments ---
def _user_error(capsys, argv: list[str]) -> str:
    code = main(argv)
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert code == 2, err
    assert len(err) == 1, err
    return err[0]


@pytest.mark.parametrize(
    "override, expected",
    [
        ("instruments.sensor.noise_C=-0.1",
         "thermbench: error: config key 'instruments.sensor.noise_C': expected a number >= 0, got -0.1"),
        ("instruments.sensor.quantum_C=-0.0625",
         "thermbench: error: config key 'instruments.sensor.quantum_C': expected a number >= 0, got -0.0625"),
        ("instruments.sensor.noise_C=nan",
         "thermbench: error: config key 'instruments.sensor.noise_C': expected a number >= 0, got nan"),
        ("instruments.interferometer.noise_um=-0.2",
         "thermbench: error: config key 'instruments.interferometer.noise_um': expected a number >= 0, got -0.2"),
    ],
)  # fmt: skip
def test_a_negative_instrument_noise_is_refused_naming_the_key(tmp_path, monkeypatch, capsys, override, expected):
    monkeypatch.chdir(tmp_path)
    assert _user_error(capsys, ["simulate", override]) == expected
    assert not any(tmp_path.iterdir())  # refused before anything was simulated or written


def test_the_sensor_spec_takes_zero_and_refuses_a_negative():
    from thermbench.sim.instruments import Interferometer, SensorSpec

    assert SensorSpec(noise_C=0.0, quantum_C=0.0).noise_C == 0.0
    with pytest.raises(ValueError, match=r"^noise_C: expected a number >= 0, got -0\.1$"):
        SensorSpec(noise_C=-0.1)
    with pytest.raises(ValueError, match=r"^dropout_len_s: expected a number >= 0, got 'long'$"):
        SensorSpec(dropout_len_s="long")
    with pytest.raises(ValueError, match=r"^noise_um: expected a number >= 0, got -1$"):
        Interferometer(noise_um=-1)


# --------------------------------------------------------------- datasets ---
def _analytic(tmp_path: Path, runs=("a", "b", "c")):
    temps = {r: {"T_nut": (lambda t, a=a: 20 + rise(t, a, 1800.0)), "T_bed": (lambda t: 20 + 0.1 * np.sin(t / 3000.0))}
             for r, a in zip(runs, (3.0, 5.0, 4.0))}  # fmt: skip
    return analytic_dataset(temps, lambda T, x, run: 2.0 * (T["T_nut"] - 20) * x / 500, duration_s=2 * 3600)


def test_an_undeclared_sensor_column_is_ignored_with_a_warning_naming_file_and_column(tmp_path):
    ds = _analytic(tmp_path, runs=("a",))
    ds.process["T_extra_C"] = 21.0
    ds.process["T_spare_C"] = 22.0
    save_dataset(ds, tmp_path / "x")
    with pytest.warns(DatasetWarning) as caught:
        loaded = load_dataset(tmp_path / "x")
    assert [str(w.message) for w in caught if w.category is DatasetWarning] == [
        f"{tmp_path / 'x' / 'process.csv'}: column 'T_extra_C' is not declared in metadata.yaml; ignored "
        "(declare sensor 'T_extra' under 'sensors' to use it)",
        f"{tmp_path / 'x' / 'process.csv'}: column 'T_spare_C' is not declared in metadata.yaml; ignored "
        "(declare sensor 'T_spare' under 'sensors' to use it)",
    ]
    assert caught[0].filename == __file__  # the warning points at the caller of load_dataset
    assert loaded.sensor_columns == ["T_nut_C", "T_bed_C"]
    # a dataset that declares every column loads without a word
    save_dataset(_analytic(tmp_path, runs=("a",)), tmp_path / "clean")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        load_dataset(tmp_path / "clean")


def test_the_command_line_says_the_warning_in_one_line(tmp_path):
    import subprocess
    import sys

    ds = _analytic(tmp_path, runs=("a",))
    ds.process["T_extra_C"] = 21.0
    save_dataset(ds, tmp_path / "x")
    p = subprocess.run([sys.executable, "-m", "thermbench", "validate", str(tmp_path / "x")], capture_output=True,
                       text=True, timeout=120)
    assert p.returncode == 0, p.stderr
    assert p.stderr.splitlines() == [
        f"thermbench: warning: {tmp_path / 'x' / 'process.csv'}: column 'T_extra_C' is not declared in metadata.yaml; "
        "ignored (declare sensor 'T_extra' under 'sensors' to use it)"]


def test_a_format_2_dataset_warns_too_and_a_declared_operating_column_is_not_a_sensor(tmp_path):
    ds = _analytic(tmp_path, runs=("a",))
    meta = ds.metadata.model_dump(mode="json", exclude_none=True)
    meta["format"] = "thermbench-dataset/2"
    meta["parts"] = ["axis"]
    meta["operating"] = ["feed_mm_min", "coolant_C"]
    meta["channels"] = {"X": {"kind": "along_axis", "direction": "X", "location": "table"}}
    d = tmp_path / "v2"
    d.mkdir()
    (d / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    process = ds.process.assign(coolant_C=18.0, T_extra_C=21.0)
    process.to_parquet(d / "process.parquet", index=False)
    ds.errors.to_csv(d / "errors.csv", index=False)
    with pytest.warns(DatasetWarning) as caught:
        load_dataset(d)
    assert [str(w.message) for w in caught if w.category is DatasetWarning] == [
        f"{d / 'process.parquet'}: column 'T_extra_C' is not declared in metadata.yaml; ignored "
        "(declare sensor 'T_extra' under 'sensors' to use it)"]


# ----------------------------------------------------------------- replay ---
@pytest.fixture(scope="module")
def exported_mlr(tmp_path_factory):
    """An MLR model of a three-run analytic dataset (machine 'synthetic', axis X), exported
    without the parity check, and the dataset it was trained on."""
    from thermbench.export import export_model
    from thermbench.export.bundle import ExportOptions
    from thermbench.models.mlr import MLRSeed002

    root = tmp_path_factory.mktemp("replay")
    save_dataset(_analytic(root), root / "data")
    ds = load_dataset(root / "data")
    export_model(MLRSeed002().fit(ds, ["a", "b"]), root / "model", "mlr", ds, ["c"], options=ExportOptions(verify=False))
    return root


def _other_machine(root: Path, name: str, axis: str = "X") -> Path:
    import shutil

    other = root / f"data_{name}_{axis}"
    if not other.exists():
        shutil.copytree(root / "data", other)
        meta = yaml.safe_load((other / "metadata.yaml").read_text())
        meta["machine"] = {"name": name, "axis": axis}
        (other / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False))
    return other


def test_replay_warns_when_the_dataset_is_of_another_machine(exported_mlr):
    from thermbench.export.replay import MachineMismatchWarning, replay_run

    root = exported_mlr
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the model's own machine: no warning at all
        same = replay_run(root / "model", root / "data", "c")
    other = _other_machine(root, "vmc2")
    with pytest.warns(MachineMismatchWarning) as caught:
        res = replay_run(root / "model", other, "c")
    assert [str(w.message) for w in caught] == [
        f"model {root / 'model'} was trained on machine 'synthetic' (axis X) ({root / 'model' / 'manifest.json'}, "
        f"training.machine), but {other / 'metadata.yaml'} is of machine 'vmc2' (axis X): the "
        "compensation is replayed on a machine the model was not fitted to"]
    assert caught[0].filename == __file__
    assert res["figures"]["after_max_abs_um"] == same["figures"]["after_max_abs_um"]  # a warning, not a refusal
    with pytest.warns(MachineMismatchWarning, match=r"machine 'synthetic' \(axis X\) .* is of machine 'synthetic' \(axis Y\)"):
        replay_run(root / "model", _other_machine(root, "synthetic", "Y"), "c")


def test_an_export_without_the_machine_falls_back_to_its_training_dataset(exported_mlr, tmp_path):
    """A model exported before the manifest recorded ``training.machine``: its training dataset
    (``training.dataset``) names the machine."""
    import json
    import shutil

    from thermbench.export.replay import MachineMismatchWarning, replay_run

    model = tmp_path / "model"
    shutil.copytree(exported_mlr / "model", model)
    man = json.loads((model / "manifest.json").read_text())
    assert man["training"].pop("machine") == {"name": "synthetic", "axis": "X"}  # what the export records
    (model / "manifest.json").write_text(json.dumps(man))
    other = _other_machine(exported_mlr, "vmc2")
    with pytest.warns(MachineMismatchWarning) as caught:
        replay_run(model, other, "c")
    assert str(caught[0].message).startswith(
        f"model {model} was trained on machine 'synthetic' (axis X) (its training dataset "
        f"{exported_mlr / 'data' / 'metadata.yaml'}), but {other / 'metadata.yaml'} is of machine 'vmc2' (axis X)")


def test_the_replay_command_warns_and_replays(exported_mlr, tmp_path, monkeypatch):
    from thermbench.export.replay import MachineMismatchWarning

    monkeypatch.chdir(tmp_path)
    other = _other_machine(exported_mlr, "vmc2")
    with pytest.warns(MachineMismatchWarning, match="is of machine 'vmc2'"):
        code = main(["replay", str(exported_mlr / "model"), str(other), "--run", "c", "--out", str(tmp_path / "r")])
    assert code == 0
    assert (tmp_path / "r" / "replay.json").is_file()


# ------------------------------------------------- messages on connecting ---
def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _stand_in_machine():
    """What sim-cnc's address space needs of a machine: its samples (no load), readings, sensors."""
    samples = pd.DataFrame({"t_s": [0.0, 1.0], "axis_mm": [0.0, 1.0], "feed_mm_min": [60.0, 60.0],
                            **{f"{s}_C": [20.0, 20.0] for s in SENSORS}})  # fmt: skip
    return SimpleNamespace(samples=samples, readings=pd.DataFrame({"t_s": []}), sensors=list(SENSORS))


def _refusals(tmp_path, files: dict[str, dict]) -> dict[str, str]:
    """Open a session on sim-cnc's server with each nodes file; the CompensatorError of each."""

    async def scenario():
        ep = f"opc.tcp://127.0.0.1:{_port()}/sim"
        srv = SimCnc(_stand_in_machine(), {"endpoint": ep, "run": "r"})
        await srv.start_server()
        out = {}
        try:
            for name, spec in files.items():
                path = tmp_path / f"{name}.yaml"
                path.write_text(yaml.safe_dump(spec, sort_keys=False))
                session = Session(ep, load_nodes(path, SENSORS), Security.from_config(None), timeout_s=5.0)
                try:
                    await session.open()
                    out[name] = None
                except CompensatorError as exc:
                    out[name] = str(exc)
                finally:
                    await session.close()
        finally:
            await srv.stop_server()
        return ep, out

    return asyncio.run(scenario())


def test_connecting_names_the_data_type_and_the_file_and_key_of_a_missing_node(tmp_path):
    good = nodes_yaml(_stand_in_machine())
    good["inputs"]["load_N"] = None
    wrong_type = yaml.safe_load(yaml.safe_dump(good))
    wrong_type["outputs"] = {"value": {"node": "nsu=urn:thermbench:sim-cnc;s=X.TempComp_Status", "unit": "um"}}
    missing = yaml.safe_load(yaml.safe_dump(good))
    missing["inputs"]["temperatures"]["T_ambient"] = "nsu=urn:thermbench:sim-cnc;s=X.T_ambient_C"
    no_output = yaml.safe_load(yaml.safe_dump(good))
    no_output["outputs"]["status"] = "nsu=urn:thermbench:sim-cnc;s=X.NoSuchStatus"
    ep, refused = _refusals(tmp_path, {"good": good, "wrong_type": wrong_type, "missing": missing, "no_output": no_output})
    assert refused["good"] is None
    assert refused["wrong_type"] == (
        f"{tmp_path / 'wrong_type.yaml'}: key outputs.value.node: output value node "
        "'nsu=urn:thermbench:sim-cnc;s=X.TempComp_Status' has data type Int32; the compensator writes Double")
    assert refused["missing"] == (
        f"{tmp_path / 'missing.yaml'}: key inputs.temperatures.T_ambient: input T_ambient_C node "
        f"'nsu=urn:thermbench:sim-cnc;s=X.T_ambient_C' does not exist on {ep}")
    assert refused["no_output"].startswith(
        f"{tmp_path / 'no_output.yaml'}: key outputs.status: output status node "
        f"'nsu=urn:thermbench:sim-cnc;s=X.NoSuchStatus' does not exist on {ep} (BadNodeIdUnknown)")
    assert all("\n" not in m for m in refused.values() if m)


def test_data_types_are_named_not_shown_as_node_ids():
    from asyncua import ua

    from thermbench.compensator.opcua import data_type_name

    assert data_type_name(ua.NodeId(ua.ObjectIds.Int32, 0)) == "Int32"
    assert data_type_name(ua.NodeId(ua.ObjectIds.Float, 0)) == "Float"
    assert data_type_name(ua.NodeId(ua.ObjectIds.UInt32, 0)) == "UInt32"
    assert data_type_name(ua.NodeId(3002, 2)) == "ns=2;i=3002 (not a standard type)"
    assert data_type_name(None) == "none (the node has no data type)"
