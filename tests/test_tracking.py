"""MLflow tracking of thermbench jobs: what a ``train`` run records, the registry and its
pyfunc face, aliases and export, a real tracking server, fail-fast on an unreachable one,
and the config-hash resume (thermbench.tracking, thermbench.experiment).

Everything is written under pytest's tmp dirs: every job gets ``tracking.uri`` /
``tracking.artifact_root`` / ``hydra.*.dir`` overrides and the seed 001 benchmark dataset
is built once per session (``seed001_data_root``). The model is ``mlr_seed001`` (seed 001
eq. 12), which fits in a fraction of a second and is deterministic, so an independent refit
from ``conf/model/mlr_seed001.yaml`` is the reference for every prediction check.
"""

from __future__ import annotations

import hashlib
import json
import os
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from contextlib import contextmanager
from importlib.metadata import version as dist_version
from pathlib import Path
from types import SimpleNamespace

import joblib
import numpy as np
import pandas as pd
import pytest
import yaml
from mlflow import MlflowClient
from omegaconf import OmegaConf

from thermbench import experiment, tracking
from thermbench.config import load_config
from thermbench.data.reference import thermal_errors
from thermbench.bench.datasets import load_benchmark
from thermbench.export import read_manifest, replay_dir
from thermbench.export.samples import readings_queries
from thermbench.tracking import TrackingError

ROOT = Path(__file__).resolve().parent.parent
MODEL = "mlr_seed001"
DATASET = "seed001_vmc_x"
REGISTERED = f"thermbench-{DATASET}-{MODEL}"
STATES = ["state1", "state2", "state3", "state4", "state5"]  # seed 001 Table 1
VALIDATION = ["valid1", "valid2", "valid3", "valid4"]  # seed 001 Table 2
FEW = "eval=valid1+valid2"  # jobs that need no full score table evaluate two runs (a faster job)


# ---------------------------------------------------------------- helpers ---
def store_overrides(tmp: Path, artifacts: bool = True) -> list[str]:
    """Keep the MLflow store and every Hydra output directory under ``tmp``."""
    ov = [f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"hydra.run.dir={tmp}/run", f"hydra.sweep.dir={tmp}/sweep"]
    return ov + ([f"tracking.artifact_root={tmp}/art"] if artifacts else [])


def compose(job: str, tmp: Path, *overrides: str, artifacts: bool = True):
    return load_config(job, [*store_overrides(tmp, artifacts), *overrides], return_hydra_config=True)


def _container(cfg) -> dict:
    return OmegaConf.to_container(cfg, resolve=True)


def store_client(tmp: Path) -> MlflowClient:
    uri = f"sqlite:///{tmp}/mlflow.db"
    return MlflowClient(tracking_uri=uri, registry_uri=uri)


def store_runs(tmp: Path, status: str | None = None) -> list:
    c = store_client(tmp)
    exp = c.get_experiment_by_name("thermbench")
    if exp is None:
        return []
    flt = f"attributes.status = '{status}'" if status else ""
    return c.search_runs([exp.experiment_id], filter_string=flt, max_results=1000)


def reference_fit(ds, train_runs):
    """The same model fitted directly from its config, without any tracking."""
    return experiment.model_from_config(MODEL).fit(ds, list(train_runs))


def use_store(tmp: Path) -> None:
    import mlflow

    uri = f"sqlite:///{tmp}/mlflow.db"
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)


@contextmanager
def closed_port():
    """A local port that refuses connections: bound (so nobody else takes it) but not listening."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        yield s.getsockname()[1]


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _end_active_runs() -> None:
    import mlflow

    while mlflow.active_run() is not None:
        mlflow.end_run()


@pytest.fixture
def workdir(tmp_path, monkeypatch, seed001_data_root):
    """cwd = tmp_path and the session's benchmark root, so nothing lands in the repository."""
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    monkeypatch.chdir(tmp_path)
    yield tmp_path
    _end_active_runs()


@pytest.fixture(scope="module")
def trained(tmp_path_factory, seed001_data_root):
    """One ``train`` job (mlr_seed001 on state1) in an embedded store, shared by the read-only checks."""
    tmp = tmp_path_factory.mktemp("trained")
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("THERMBENCH_DATA", str(seed001_data_root))
        mp.chdir(tmp)
        cfg = compose("train", tmp, f"model={MODEL}", "train=state1")
        try:
            res = experiment.train(cfg)
        finally:
            _end_active_runs()
        ds = load_benchmark(DATASET)
    return SimpleNamespace(tmp=tmp, cfg=cfg, res=res, ds=ds, reference=reference_fit(ds, ["state1"]))


@pytest.fixture
def trained_store(trained):
    """The shared store as MLflow's current store (other tests of this worker may have moved it)."""
    use_store(trained.tmp)
    return trained


# ------------------------------------------------ what a train run records ---
def test_train_run_records_config_tags_and_artifacts(trained):
    c = store_client(trained.tmp)
    runs = store_runs(trained.tmp)
    assert [r.info.run_id for r in runs] == [trained.res.mlflow_run_id]
    run = c.get_run(trained.res.mlflow_run_id)
    assert run.info.status == "FINISHED"

    p = run.data.params
    # the flattened resolved config (conf/model/mlr_seed001.yaml, conf/dataset/seed001_vmc_x.yaml)
    assert p["model._target_"] == "thermbench.models.mlr.MLRSeed001"
    assert p["model.degree"] == "4"
    assert p["train"] == "state1"
    assert p["dataset.name"] == DATASET
    assert p["dataset.source.name"] == DATASET
    assert yaml.safe_load(p["dataset.validation"]) == VALIDATION
    assert p["tracking.uri"] == f"sqlite:///{trained.tmp}/mlflow.db"
    assert not [k for k in p if k.startswith("hydra")]

    tags = run.data.tags
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    assert len(head) == 40 and tags["git_commit"] in (head, head + "+dirty")
    assert tags["dataset_hash"] == trained.ds.content_hash()
    assert tags["thermbench.version"] == dist_version("thermbench")
    plain_cfg = load_config("train", store_overrides(trained.tmp) + [f"model={MODEL}", "train=state1"])
    # the resume hash covers the resolved config and the data's content (re-measured files rerun)
    expected = tracking.config_hash(_container(plain_cfg) | {"dataset_content": trained.ds.content_hash()})
    assert tags["thermbench.config_hash"] == expected
    assert tags["model"] == MODEL and tags["dataset"] == DATASET

    names = {f.path for f in c.list_artifacts(run.info.run_id)}
    assert {"config.yaml", "results.csv", "before_after.png"} <= names
    art = Path(c.download_artifacts(run.info.run_id, "", str(trained.tmp / "dl")))
    logged_cfg = yaml.safe_load((art / "config.yaml").read_text())
    assert logged_cfg["model"]["_target_"] == "thermbench.models.mlr.MLRSeed001" and logged_cfg["train"] == "state1"
    assert "hydra" not in logged_cfg
    results = pd.read_csv(art / "results.csv")
    assert sorted(results["run_id"]) == sorted(STATES + VALIDATION)
    assert results.set_index("run_id")["own"].to_dict() == {r: r == "state1" for r in STATES + VALIDATION}
    assert (art / "before_after.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def dataset_inputs(client: MlflowClient, run_id: str) -> list:
    return list(client.get_run(run_id).inputs.dataset_inputs)


def test_train_run_logs_its_dataset_as_an_input(trained, seed001_data_root):
    """The MLflow UI's Dataset column: the run has one dataset input, named as the dataset, its
    digest the data's content hash (the dataset_hash tag), its source the dataset directory, its
    schema the columns of the dataset's tables, in the training context."""
    (inp,) = dataset_inputs(store_client(trained.tmp), trained.res.mlflow_run_id)
    d = inp.dataset
    assert d.name == DATASET
    assert d.digest == trained.ds.content_hash()  # the dataset loaded here, not the job's copy
    assert d.source_type == "local"
    assert json.loads(d.source) == {"uri": str((seed001_data_root / DATASET).resolve())}
    cols = json.loads(d.schema)["mlflow_colspec"]
    ds = trained.ds
    expected = list(ds.process.columns) + [c for c in ds.errors.columns if c not in ds.process.columns]
    assert [c["name"] for c in cols] == expected and {"target_mm", "error_um", "T_nut_C"} <= set(expected)
    types = {c["name"]: c["type"] for c in cols}
    assert types["run_id"] == "string" and types["t_s"] == types["error_um"] == "double"
    assert {t.key: t.value for t in inp.tags} == {"mlflow.data.context": "training"}


def test_logged_metrics_match_an_independent_recomputation(trained):
    """Per-run and headline metrics recomputed by hand (residual = measured - predicted,
    seed 000 §5 / seed 002 §3 compensation rate) from the dataset and the model's predictions."""
    ds, m = trained.ds, trained.reference
    metrics = store_client(trained.tmp).get_run(trained.res.mlflow_run_id).data.metrics
    te = thermal_errors(ds)
    by_run = {}
    for run in ["state1", "state3", *VALIDATION]:
        er = ds.errors_run(run)
        r = er["error_um"].to_numpy() - m.predict_at(ds, run, er["t_s"].to_numpy(), er["target_mm"].to_numpy())
        thermal = te.loc[te["run_id"] == run, "thermal_um"].to_numpy()
        by_run[run] = (np.sqrt(np.mean(r**2)), np.max(np.abs(r)), 1.0 - np.max(np.abs(r)) / np.max(np.abs(thermal)))
        assert metrics[f"runs/{run}/rmse_um"] == pytest.approx(by_run[run][0], rel=1e-9)
        assert metrics[f"runs/{run}/max_abs_residual_um"] == pytest.approx(by_run[run][1], rel=1e-9)
        assert metrics[f"runs/{run}/compensation_rate"] == pytest.approx(by_run[run][2], rel=1e-9)
    # headline: own = the training run; validation = seed 001 Table 2 runs
    assert metrics["own_mean_rmse_um"] == pytest.approx(by_run["state1"][0], rel=1e-9)
    assert metrics["validation_max_abs_residual_um"] == pytest.approx(max(by_run[v][1] for v in VALIDATION), rel=1e-9)
    assert metrics["validation_worst_compensation_rate"] == pytest.approx(min(by_run[v][2] for v in VALIDATION), rel=1e-9)
    # the job's result carries the same headline numbers it logged
    for k, v in trained.res.metrics.items():
        assert metrics[k] == pytest.approx(v, rel=1e-12)


def test_registered_model_loads_back_and_predicts_like_a_direct_fit(trained_store):
    t = trained_store
    assert t.res.outputs["registered"] == f"models:/{REGISTERED}/1"
    versions = store_client(t.tmp).search_model_versions(f"name='{REGISTERED}'")
    assert [(str(v.version), v.run_id) for v in versions] == [("1", t.res.mlflow_run_id)]
    loaded = tracking.load_model(f"models:/{REGISTERED}/1")
    assert type(loaded) is type(t.reference) and loaded.train_runs_ == ["state1"]
    for run in ("state2", "valid4"):
        er = t.ds.errors_run(run)
        args = (t.ds, run, er["t_s"].to_numpy(), er["target_mm"].to_numpy())
        np.testing.assert_allclose(loaded.predict_at(*args), t.reference.predict_at(*args), rtol=0, atol=1e-9)
    with pytest.raises(TrackingError, match="models:/no-such-model/1"):
        tracking.load_model("models:/no-such-model/1")


def test_pyfunc_returns_the_error_at_each_process_log_row(trained_store):
    import mlflow

    t = trained_store
    pf = mlflow.pyfunc.load_model(f"models:/{REGISTERED}/1")
    # one run's process log, no run_id column (a live log)
    log = t.ds.process_run("valid2")
    out = pf.predict(log.drop(columns=["run_id"]))
    expected = t.reference.predict_at(t.ds, "valid2", log["t_s"].to_numpy(), log["axis_mm"].to_numpy())
    assert list(out.columns) == ["error_um"] and len(out) == len(log)
    np.testing.assert_allclose(out["error_um"].to_numpy(), expected, rtol=0, atol=1e-9)
    assert np.ptp(expected) > 10.0  # the check compares a real thermal drift, not zeros

    # two runs in one frame, with a foreign index: each row predicted within its own run, index kept
    both = pd.concat([t.ds.process_run("valid1"), t.ds.process_run("state3")], ignore_index=True)
    both.index = both.index + 10_000
    out2 = pf.predict(both)
    assert out2.index.equals(both.index)
    for run in ("valid1", "state3"):
        rows = both["run_id"] == run
        exp = t.reference.predict_at(t.ds, run, both.loc[rows, "t_s"].to_numpy(), both.loc[rows, "axis_mm"].to_numpy())
        np.testing.assert_allclose(out2.loc[rows, "error_um"].to_numpy(), exp, rtol=0, atol=1e-9)


# ------------------------------------------------------------ alias, export ---
def test_alias_resolves_for_export_and_evaluate(workdir):
    v1 = experiment.train(compose("train", workdir, f"model={MODEL}", "train=state1", FEW))
    v2 = experiment.train(compose("train", workdir, f"model={MODEL}", "train=state2", FEW))
    assert (v1.outputs["registered"], v2.outputs["registered"]) == (f"models:/{REGISTERED}/1", f"models:/{REGISTERED}/2")
    store_client(workdir).set_registered_model_alias(REGISTERED, "champion", "1")  # not the latest version

    out_dir = workdir / "exports"
    res = experiment.export(compose("export", workdir, f"export.name={REGISTERED}", "export.alias=champion",
                                    f"export.out_dir={out_dir}", "export.onnx=false"))
    folder = out_dir / REGISTERED
    assert res.outputs["dir"] == str(out_dir)
    assert sorted(p.name for p in folder.iterdir()) == [".thermbench-output.json", "envelope.tbm", "faults.tbm", "manifest.json", "model.tbm"]
    manifest = read_manifest(folder)
    assert manifest["mlflow_run_id"] == v1.mlflow_run_id  # the run that logged version 1
    assert manifest["source"]["uri"] == f"models:/{REGISTERED}@champion"
    assert manifest["family"] == "thermbench.models.mlr.MLRSeed001" and manifest["training"]["runs"] == ["state1"]
    assert manifest["metrics"] == store_client(workdir).get_run(v1.mlflow_run_id).data.metrics

    # the exported file, run by the C runtime, is version 1 (state1), not the latest (state2) model
    ds = load_benchmark(DATASET)
    q = readings_queries(ds, "valid3")
    c = replay_dir(folder, ds, "valid3", q)["total_um"].to_numpy()
    args = (ds, "valid3", q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
    np.testing.assert_allclose(c, reference_fit(ds, ["state1"]).predict_at(*args), atol=0.01, rtol=0)
    assert np.max(np.abs(c - reference_fit(ds, ["state2"]).predict_at(*args))) > 0.1

    with pytest.raises(TrackingError, match=f"models:/{REGISTERED}@nope"):
        experiment.export(compose("export", workdir, f"export.name={REGISTERED}", "export.alias=nope",
                                  f"export.out_dir={out_dir}"))

    # thermbench evaluate resolves the same alias: it scores version 1 exactly as its train job did
    ev = experiment.evaluate(compose("evaluate", workdir, f"name={REGISTERED}", "alias=champion", "runs=valid1+valid2"))
    scored = store_client(workdir).get_run(ev.mlflow_run_id).data.metrics
    trained_v1 = store_client(workdir).get_run(v1.mlflow_run_id).data.metrics
    for run in ("valid1", "valid2"):
        assert scored[f"runs/{run}/rmse_um"] == pytest.approx(trained_v1[f"runs/{run}/rmse_um"], rel=1e-12)
    # and records what it scored: the table and the before/after figure, and the dataset as its input
    arts = {f.path for f in store_client(workdir).list_artifacts(ev.mlflow_run_id)}
    assert {"results.csv", "before_after.png", "config.yaml"} <= arts
    (inp,) = dataset_inputs(store_client(workdir), ev.mlflow_run_id)
    assert (inp.dataset.name, inp.dataset.digest) == (DATASET, ds.content_hash())
    assert {t.key: t.value for t in inp.tags} == {"mlflow.data.context": "evaluation"}


def test_model_uri_from_config_keys():
    assert tracking.model_uri("m", "champion", None) == "models:/m@champion"
    assert tracking.model_uri("m", None, None) == "models:/m/latest"
    assert tracking.model_uri("m", "champion", "runs:/abc/model") == "runs:/abc/model"
    with pytest.raises(TrackingError, match="'model_uri'.*'name'"):
        tracking.model_uri(None, "champion", None)


# ----------------------------------------------------- a real MLflow server ---
def _mlflow_cli() -> list[str]:
    exe = Path(sys.executable).with_name("mlflow")
    return [str(exe)] if exe.exists() else [sys.executable, "-m", "mlflow"]


def wait_healthy(uri: str, proc: subprocess.Popen, log: Path, what: str, timeout_s: float = 90) -> None:
    """Until ``uri/health`` answers 200; a failure (with the log's tail) if ``proc`` exits or time runs out."""
    deadline = time.monotonic() + timeout_s
    while True:
        if proc.poll() is not None:
            pytest.fail(f"{what} exited ({proc.returncode}):\n{log.read_text()[-3000:]}")
        try:
            with urllib.request.urlopen(uri + "/health", timeout=2) as r:
                if r.status == 200:
                    return
        except OSError:
            pass
        if time.monotonic() > deadline:
            pytest.fail(f"{what} not up in {timeout_s:.0f} s:\n{log.read_text()[-3000:]}")
        time.sleep(0.25)


def stop_group(proc: subprocess.Popen) -> None:
    """SIGTERM to ``proc``'s process group (started with start_new_session), SIGKILL after 15 s."""
    try:
        os.killpg(proc.pid, signal.SIGTERM)
        proc.wait(timeout=15)
    except ProcessLookupError:
        pass
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait(timeout=15)


@contextmanager
def mlflow_server_on(backend_store_uri: str, srv: Path, workers: int = 1):
    """``mlflow server`` on a free local port with ``backend_store_uri`` and proxied artifacts in
    ``srv/artifacts``; yields (uri, srv) once healthy, stops it after."""
    port = free_port()
    cmd = [*_mlflow_cli(), "server", "--host", "127.0.0.1", "--port", str(port), "--backend-store-uri",
           backend_store_uri, "--artifacts-destination", str(srv / "artifacts"), "--workers", str(workers)]  # fmt: skip
    env = {k: v for k, v in os.environ.items() if not k.startswith("MLFLOW_")}
    log = srv / "server.log"
    with open(log, "w") as logf:
        proc = subprocess.Popen(cmd, cwd=srv, env=env, stdout=logf, stderr=subprocess.STDOUT, start_new_session=True)
    uri = f"http://127.0.0.1:{port}"
    try:
        wait_healthy(uri, proc, log, f"mlflow server on {backend_store_uri.split(':', 1)[0]}")
        yield SimpleNamespace(uri=uri, dir=srv)
    finally:
        stop_group(proc)


@pytest.fixture
def mlflow_server(tmp_path_factory):
    """``mlflow server`` on a free local port with its own sqlite store and proxied artifacts."""
    srv = tmp_path_factory.mktemp("server")
    with mlflow_server_on(f"sqlite:///{srv}/srv.db", srv) as server:
        yield server


def test_train_against_a_real_tracking_server(mlflow_server, workdir):
    # the usage to support: only tracking.uri=http://... on top of the default (embedded) tracking group
    cfg = compose("train", workdir, f"tracking.uri={mlflow_server.uri}", f"model={MODEL}",
                  "train=state1", FEW, artifacts=False)
    res = experiment.train(cfg)

    c = MlflowClient(tracking_uri=mlflow_server.uri, registry_uri=mlflow_server.uri)
    exp = c.get_experiment_by_name("thermbench")
    runs = c.search_runs([exp.experiment_id])
    assert [r.info.run_id for r in runs] == [res.mlflow_run_id]
    run = runs[0]
    assert run.info.status == "FINISHED"
    assert run.data.params["tracking.uri"] == mlflow_server.uri
    for k, v in res.metrics.items():
        assert run.data.metrics[k] == pytest.approx(v, rel=1e-12)
    assert {f.path for f in c.list_artifacts(run.info.run_id)} >= {"config.yaml", "results.csv", "before_after.png"}
    versions = c.search_model_versions(f"name='{REGISTERED}'")
    assert [(str(v.version), v.run_id) for v in versions] == [("1", run.info.run_id)]
    # the files went through the server to its artifact store, not to the client's directory
    assert list((mlflow_server.dir / "artifacts").rglob("model.joblib"))
    assert not (workdir / "mlflow.db").exists() and not (workdir / "art").exists()
    assert not (workdir / "mlartifacts").exists()  # the embedded group's artifact_root is not used for a server

    loaded = tracking.load_model(f"models:/{REGISTERED}/1")
    ds = load_benchmark(DATASET)
    er = ds.errors_run("valid1")
    args = (ds, "valid1", er["t_s"].to_numpy(), er["target_mm"].to_numpy())
    np.testing.assert_allclose(loaded.predict_at(*args), reference_fit(ds, ["state1"]).predict_at(*args), atol=1e-9, rtol=0)


# ------------------------------------------------- unreachable server: fail fast ---
def test_unreachable_server_fails_before_any_data_is_loaded(workdir, monkeypatch):
    import thermbench.bench.datasets

    loaded = []
    monkeypatch.setattr(thermbench.bench.datasets, "load_benchmark", lambda *a, **k: loaded.append(a))
    with closed_port() as port:
        uri = f"http://127.0.0.1:{port}"
        cfg = compose("train", workdir, "tracking=server", f"tracking.uri={uri}", artifacts=False)
        t0 = time.monotonic()
        with pytest.raises(TrackingError) as err:
            experiment.train(cfg)
        assert time.monotonic() - t0 < 30.0  # no retries (MLflow's own back-off takes minutes); a loaded host's pace is no test
    assert f"tracking.uri={uri}" in str(err.value) and "\n" not in str(err.value)
    assert loaded == []


def test_server_that_never_answers_fails_after_timeout_s(workdir):
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        s.listen(8)  # connections are accepted by the kernel, nothing ever answers
        uri = f"http://127.0.0.1:{s.getsockname()[1]}"
        t0 = time.monotonic()
        with pytest.raises(TrackingError, match=f"tracking.uri={uri}"):
            tracking.connect({"uri": uri, "timeout_s": 1.0})
        assert 0.9 < time.monotonic() - t0 < 30.0  # waited timeout_s, then no retries (MLflow's own back-off takes minutes)


def test_cli_unreachable_server_exits_2_with_one_line_and_trains_nothing(workdir, seed001_data_root):
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["THERMBENCH_DATA"] = str(seed001_data_root)
    with closed_port() as port:
        uri = f"http://127.0.0.1:{port}"
        t0 = time.monotonic()
        proc = subprocess.run(
            [sys.executable, "-m", "thermbench.cli", "train", "tracking=server", f"tracking.uri={uri}",
             f"hydra.run.dir={workdir}/run"],
            cwd=workdir, env=env, capture_output=True, text=True, timeout=120,
        )
        elapsed = time.monotonic() - t0
    assert proc.returncode == 2, proc.stderr
    assert elapsed < 20.0  # interpreter start-up + a refused connection, no retries
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1, proc.stderr
    assert f"tracking.uri={uri}" in lines[0] and "Traceback" not in proc.stderr
    assert not list(workdir.rglob("result.json"))
    assert not list(workdir.rglob("*.db")) and not (workdir / "mlruns").exists()


# ----------------------------------------------------------------- resume ---
def test_same_config_is_skipped_a_changed_one_is_not(workdir):
    base = [f"model={MODEL}", "train=state1", FEW]
    first = experiment.train(compose("train", workdir, *base))
    assert not first.skipped

    again = experiment.train(compose("train", workdir, *base))
    assert again.skipped and again.mlflow_run_id == first.mlflow_run_id
    for k, v in first.metrics.items():
        assert again.metrics[k] == pytest.approx(v, rel=1e-12)
    assert len(store_runs(workdir)) == 1
    assert len(store_client(workdir).search_model_versions(f"name='{REGISTERED}'")) == 1

    # the tracking location is not part of the config identity: a new artifact root still skips
    moved = experiment.train(compose("train", workdir, *base, f"tracking.artifact_root={workdir}/elsewhere"))
    assert moved.skipped

    param = experiment.train(compose("train", workdir, *base, "model.degree=3"))
    assert not param.skipped
    ids = {first.mlflow_run_id, param.mlflow_run_id}
    assert len(ids) == 2

    rerun = experiment.train(compose("train", workdir, *base, "tracking.skip_finished=false"))
    assert not rerun.skipped and rerun.mlflow_run_id not in ids
    finished = store_runs(workdir, "FINISHED")
    assert len(finished) == 3
    first_hash = store_client(workdir).get_run(first.mlflow_run_id).data.tags["thermbench.config_hash"]
    assert sorted(r.info.run_id for r in finished if r.data.tags["thermbench.config_hash"] == first_hash) == sorted(
        [first.mlflow_run_id, rerun.mlflow_run_id]
    )


def test_only_a_finished_run_counts_as_done(workdir):
    exp_id = tracking.connect({"uri": f"sqlite:///{workdir}/mlflow.db", "artifact_root": str(workdir / "art")})
    c = store_client(workdir)
    for status in ("FAILED", "KILLED", None):  # None: still RUNNING (a killed process)
        r = c.create_run(exp_id, tags={"thermbench.config_hash": "aaaa"})
        if status:
            c.set_terminated(r.info.run_id, status)
    other = c.create_run(exp_id, tags={"thermbench.config_hash": "bbbb"})
    c.set_terminated(other.info.run_id, "FINISHED")
    assert tracking.finished_run(exp_id, "aaaa") is None

    done = c.create_run(exp_id, tags={"thermbench.config_hash": "aaaa"})
    c.set_terminated(done.info.run_id, "FINISHED")
    assert tracking.finished_run(exp_id, "aaaa").info.run_id == done.info.run_id
    assert tracking.finished_run(exp_id, "bbbb").info.run_id == other.info.run_id


def test_config_hash_ignores_tracking_and_hydra_keys_but_not_results_keys():
    base = {"model": {"_target_": "thermbench.models.mlr.MLRSeed001", "degree": 4}, "train": "state1", "seed": 0,
            "dataset": {"name": DATASET}, "tracking": {"uri": "sqlite:///mlflow.db", "experiment": "thermbench"}}
    h = tracking.config_hash(base)
    # SHA-256 of the canonical JSON of the result keys (tracking left out) and the version,
    # computed here: the same in every process (no per-process salt), not merely some hex string
    canonical = json.dumps({"cfg": {k: v for k, v in base.items() if k != "tracking"},
                            "version": dist_version("thermbench")}, sort_keys=True)  # fmt: skip
    assert h == hashlib.sha256(canonical.encode()).hexdigest()[:16]
    assert tracking.config_hash(dict(reversed(list(base.items())))) == h  # key order
    assert tracking.config_hash({**base, "tracking": {"uri": "http://10.0.0.1:5000", "experiment": "x"}}) == h
    assert tracking.config_hash({**base, "hydra": {"run": {"dir": "/somewhere"}, "job": {"num": 3}}}) == h
    assert tracking.config_hash({**base, "model": {**base["model"], "degree": 3}}) != h
    assert tracking.config_hash({**base, "seed": 1}) != h
    assert tracking.config_hash({**base, "train": "state2"}) != h
    assert tracking.config_hash({**base, "dataset": {"name": "seed002_vmc655h_x"}}) != h

    # the same on composed job configs: where runs go is not what they compute
    def composed(*ov):
        return tracking.config_hash(_container(load_config("train", list(ov))))

    embedded = composed("tracking.uri=sqlite:////a/mlflow.db", "tracking.artifact_root=/a/art")
    assert composed("tracking=server", "tracking.uri=http://10.0.0.1:5000") == embedded
    assert composed("tracking.skip_finished=false", "tracking.register=false") == embedded
    assert composed("model.origin_mm=5.0") != embedded
    assert composed("model=mlr_seed001") != embedded


def test_flatten_keeps_every_leaf_as_a_string_param():
    cfg = {"model": {"_target_": "a.B", "gamma": 10.0, "sensors": ["T1", "T2"], "selection": None, "opts": {}},
           "train": "state1", "steps": [{"_target_": "f.K", "R": 8.8706}], "flag": True}
    assert tracking.flatten(cfg) == {
        "model._target_": "a.B",
        "model.gamma": "10.0",
        "model.sensors": '["T1", "T2"]',
        "model.selection": "None",
        "model.opts": "{}",
        "train": "state1",
        "steps": '[{"_target_": "f.K", "R": 8.8706}]',
        "flag": "True",
    }


def test_relative_store_paths_are_taken_from_the_start_directory(tmp_path):
    assert tracking.resolve_uri("sqlite:///mlflow.db", tmp_path) == f"sqlite:///{tmp_path.resolve()}/mlflow.db"
    assert tracking.resolve_uri("sqlite:////abs/m.db", tmp_path) == "sqlite:////abs/m.db"
    assert tracking.resolve_uri("mlartifacts", tmp_path) == (tmp_path / "mlartifacts").resolve().as_uri()
    assert tracking.resolve_uri("http://h:5000", tmp_path) == "http://h:5000"
    with pytest.raises(TrackingError, match="tracking.uri"):
        tracking.connect({"uri": ""})


# --------------------------------------------------- never publish a broken model ---
def test_a_model_with_a_non_finite_score_is_never_registered(workdir, monkeypatch, capsys):
    """A model that predicts NaN on one run (here: on valid2 only) is logged, flagged, and not
    registered: no version of it exists in the registry."""
    import numpy as np

    from thermbench.models.mlr import MLRSeed001

    real = MLRSeed001.predict

    def nan_on_valid2(self, dataset, run_id, *a, **k):
        out = np.asarray(real(self, dataset, run_id, *a, **k), dtype=float)
        return np.full_like(out, np.nan) if run_id == "valid2" else out

    monkeypatch.setattr(MLRSeed001, "predict", nan_on_valid2)
    res = experiment.train(compose("train", workdir, f"model={MODEL}", "train=state1", FEW))
    assert res.outputs["registered"] == "no: non-finite score on run(s) ['valid2']"
    assert "non-finite score on run(s) ['valid2']" in capsys.readouterr().err
    assert store_client(workdir).search_registered_models() == []


def test_an_attempt_killed_mid_run_is_closed_by_the_next_attempt_of_the_same_job(tmp_path, monkeypatch):
    """submitit sends SIGKILL 1 s after Ctrl-C's SIGINT: an attempt still closing its MLflow run
    leaves it RUNNING. The next attempt of the same job (config hash and job directory) marks it
    KILLED; the same configuration running in another sweep's directory is left alone."""
    import mlflow
    from mlflow import MlflowClient

    from thermbench import tracking

    mlflow.set_tracking_uri(f"sqlite:///{tmp_path}/mlflow.db")
    c = MlflowClient()
    exp = c.create_experiment("thermbench")
    mine, other = tmp_path / "sweep" / "1", tmp_path / "other" / "1"
    for d in (mine, other):
        d.mkdir(parents=True)
    monkeypatch.chdir(other)
    elsewhere = c.create_run(exp, tags=tracking.standard_tags(None, "h1", "train")).info.run_id
    monkeypatch.chdir(mine)
    killed = c.create_run(exp, tags=tracking.standard_tags(None, "h1", "train")).info.run_id
    another_config = c.create_run(exp, tags=tracking.standard_tags(None, "h2", "train")).info.run_id
    assert tracking.close_interrupted(exp, "h1") == 1
    status = {r: c.get_run(r).info.status for r in (killed, elsewhere, another_config)}
    assert status == {killed: "KILLED", elsewhere: "RUNNING", another_config: "RUNNING"}


def test_a_dataset_inserted_meanwhile_by_a_parallel_job_is_linked_on_a_second_try(monkeypatch):
    """Two jobs of a joblib sweep log the same dataset to one store: the slower one's insert fails
    on MLflow's unique key (seen in make test). log_dataset tries again and links it; any other
    MLflow error is raised at once."""
    import mlflow
    from mlflow.exceptions import MlflowException

    from thermbench import tracking

    monkeypatch.setattr(tracking, "dataset_input", lambda ds, name, digest=None: ("input", name))
    calls = []

    def flaky(inp, context=None):
        calls.append(inp)
        if len(calls) == 1:
            raise MlflowException("(sqlite3.IntegrityError) UNIQUE constraint failed: datasets.experiment_id, ...")

    monkeypatch.setattr(mlflow, "log_input", flaky)
    tracking.log_dataset(object(), "seed001_vmc_x")
    assert calls == [("input", "seed001_vmc_x")] * 2

    def broken(inp, context=None):
        raise MlflowException("RESOURCE_DOES_NOT_EXIST: run not found")

    monkeypatch.setattr(mlflow, "log_input", broken)
    with pytest.raises(MlflowException, match="run not found"):
        tracking.log_dataset(object(), "seed001_vmc_x")
