"""What a run records of its dataset (MLflow dataset inputs) and the threads its
fits get (every family on the thread count its job was given, so parallel jobs never
oversubscribe the cores).

The datasets are small hand-made ones (tests.test_history.two_blocks: a spindle test of two
heating blocks, 800 rows), so each test takes a few seconds."""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import joblib
import numpy as np
import pytest
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from threadpoolctl import threadpool_info

from tests.test_history import two_blocks
from thermbench import experiment, tracking
from thermbench.config import load_config
from thermbench.data import load_dataset
from thermbench.experiment import build_model, dataset_view, group_option, job_threads, run_workers, worker_threads
from thermbench.models.base import fit_threads, thread_budget
from thermbench.models.baseline import SensorRegressor

MACHINE = "vmc_spindle"  # tests.test_dataset_v2.SPINDLE_META


def pools() -> dict[tuple[str, str], int]:
    """The threads of every OpenMP and BLAS thread pool loaded in this process."""
    return {(i["user_api"], i["filepath"]): i["num_threads"] for i in threadpool_info()
            if i["user_api"] in ("openmp", "blas")}  # fmt: skip


def pools_and_budget() -> tuple[dict, int | None]:
    """What a benchmark worker sees (run there by joblib): its thread pools and thread budget."""
    return pools(), fit_threads()


@pytest.fixture
def fit_spy(monkeypatch):
    """Each SensorRegressor fit (the baselines, baseline_hgb's OpenMP booster among them)
    records the thread pools and the budget it runs with, inside the fit."""
    seen = []
    real = SensorRegressor._fit

    def spy(self, ds, runs):
        seen.append((pools(), fit_threads()))
        return real(self, ds, runs)

    monkeypatch.setattr(SensorRegressor, "_fit", spy)
    return seen


# ------------------------------------------------------------ thread limits ---
def test_a_fit_runs_on_the_thread_count_its_job_gives(tmp_path, fit_spy):
    hist = dataset_view(two_blocks(tmp_path), "Z", segments=True, history=True)
    model = build_model(group_option("model", "baseline_hgb"), seed=0)
    before = pools()
    assert {api for api, _ in before} == {"openmp", "blas"}  # HistGradientBoosting's OpenMP is loaded
    with thread_budget(1):
        model.fit(hist, ["low"])
    (inside, budget), = fit_spy
    assert budget == 1
    assert inside.keys() == before.keys() and set(inside.values()) == {1}
    assert pools() == before  # the job's limit ends with the job
    # and the fitted booster is the same as one fitted with the libraries' defaults
    again = build_model(group_option("model", "baseline_hgb"), seed=0).fit(hist, ["low"])
    assert fit_spy[1] == (before, None)
    np.testing.assert_allclose(model.predict(hist, "high"), again.predict(hist, "high"), rtol=1e-9, atol=1e-9)


def test_the_fit_wrapper_limits_pools_the_budget_did_not_see(tmp_path, fit_spy):
    """A family that loads a thread pool on first use (torch's own OpenMP) loads it after the job
    set its budget: the fit itself (ThermalErrorModel.fit) limits whatever is loaded then."""
    from threadpoolctl import threadpool_limits

    hist = dataset_view(two_blocks(tmp_path), "Z", segments=True, history=True)
    model = build_model(group_option("model", "baseline_ols"), seed=0)
    with thread_budget(1):
        with threadpool_limits(limits=2):  # as a pool loaded (at its default) after the budget began
            model.fit(hist, ["low"])
    (inside, budget), = fit_spy
    assert budget == 1 and set(inside.values()) == {1}


def test_benchmark_workers_get_the_cores_divided_by_n_jobs(monkeypatch):
    """Each of n_jobs joblib workers runs under cores // n_jobs threads. joblib's own default
    for its workers yields to the parent's environment: set it to every core here, so only
    thermbench's limit can bring a worker down to its share."""
    cores = joblib.cpu_count()
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, str(cores))
    share = max(1, cores // 2)
    out = list(run_workers(pools_and_budget, [((), {})] * 4, n_jobs=2, ordered=False))
    assert len(out) == 4
    for worker_pools, budget in out:
        assert budget == share
        assert {api for api, _ in worker_pools} >= {"openmp", "blas"}
        assert set(worker_pools.values()) == {share}
    # in this process (n_jobs=1): the whole job's cores
    (mine, budget), = run_workers(pools_and_budget, [((), {})], n_jobs=1)
    assert budget == cores and set(mine.values()) == {cores}


def test_the_benchmark_dispatches_its_tasks_through_run_workers(monkeypatch, tmp_path):
    from omegaconf import OmegaConf

    from thermbench import bench as bm

    seen = []
    monkeypatch.setattr(bm.run, "run_workers", lambda fn, calls, n_jobs, ordered=True, threads=None:
                        seen.append((fn, calls, n_jobs, threads)) or [])  # fmt: skip
    src = {"_target_": "thermbench.data.io.load_dataset", "path": "data/lab"}
    todo = [{"family": "a", "dataset_cfg": {"source": src}}, {"family": "b", "dataset_cfg": {"source": src}}]
    monkeypatch.chdir(tmp_path)
    list(bm.run._iterate(OmegaConf.create({"n_jobs": 2, "cache_dir": None}), todo))
    # the local executor (none configured), each task with its dataset at an absolute path (a worker elsewhere
    # finds it; the cache key is the same wherever the cell runs)
    at = {"_target_": "thermbench.data.io.load_dataset", "path": str(tmp_path / "data" / "lab")}
    assert seen == [(bm.run_task, [((), {"family": f, "dataset_cfg": {"source": at}}) for f in "ab"], 2, None)]


def test_worker_share_of_the_cores():
    assert worker_threads(2, 10, cores=8) == 4
    assert worker_threads(3, 10, cores=8) == 2
    assert worker_threads(4, 2, cores=8) == 4  # two tasks: two workers at once, whatever n_jobs says
    assert worker_threads(8, 10, cores=2) == 1  # never below one thread
    assert worker_threads(1, 10, cores=8) == 8
    assert worker_threads(-1, 100, cores=joblib.cpu_count()) == 1  # -1: one worker per core


def hydra_job(*overrides: str, multirun: bool = True):
    cfg = load_config("train", list(overrides), return_hydra_config=True)
    cfg.hydra.mode = RunMode.MULTIRUN if multirun else RunMode.RUN
    return cfg.hydra


def test_a_job_of_a_parallel_sweep_gets_its_share_of_the_cores():
    launcher = "hydra/launcher=joblib"
    assert job_threads(hydra_job(launcher, "hydra.launcher.n_jobs=2"), cores=8) == 4
    assert job_threads(hydra_job(launcher, "hydra.launcher.n_jobs=3"), cores=8) == 2
    assert job_threads(hydra_job(launcher, "hydra.launcher.n_jobs=-1"), cores=8) == max(1, 8 // joblib.cpu_count())
    assert job_threads(hydra_job(launcher, "hydra.launcher.n_jobs=2", multirun=False), cores=8) == 8
    assert job_threads(hydra_job(), cores=8) == 8  # the basic launcher runs one job at a time
    assert job_threads(hydra_job("hydra/launcher=submitit_local", "hydra.launcher.cpus_per_task=3"), cores=8) == 3


@pytest.fixture
def own_dataset(tmp_path, monkeypatch):
    """The hand-made spindle test written as an own dataset directory (cwd: tmp_path)."""
    monkeypatch.chdir(tmp_path)
    return Path(two_blocks(tmp_path).path)


def train(tmp: Path, data: Path, *extra: str, sweep_job: bool = False):
    """``thermbench train`` of baseline_hgb on the low-speed block of ``data``, into a store in
    ``tmp``; ``sweep_job``: as job 0 of ``thermbench train -m ... hydra/launcher=joblib`` with one
    job per core at once (the Hydra config set as Hydra sets it in a sweep's job)."""
    import mlflow

    cores = joblib.cpu_count()
    sweep = ["hydra/launcher=joblib", f"hydra.launcher.n_jobs={cores}"] if sweep_job else []
    cfg = load_config("train", [f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"tracking.artifact_root={tmp}/art",
                                "dataset=path", f"dataset.source.path={data}", "dataset.channel=Z",
                                "dataset.history=true", "model=baseline_hgb", "train=low", *extra, *sweep],
                      return_hydra_config=True)  # fmt: skip
    old = HydraConfig.instance().cfg
    if sweep_job:
        cfg.hydra.mode = RunMode.MULTIRUN
        cfg.hydra.runtime.output_dir = str(tmp / "sweep" / "0")
        Path(cfg.hydra.runtime.output_dir).mkdir(parents=True)
        HydraConfig.instance().set_config(cfg)
    try:
        return experiment.train(cfg)
    finally:
        HydraConfig.instance().cfg = old
        while mlflow.active_run() is not None:
            mlflow.end_run()


def test_a_train_job_in_a_joblib_sweep_fits_on_its_share(tmp_path, own_dataset, fit_spy):
    res = train(tmp_path, own_dataset, sweep_job=True)
    (inside, budget), = fit_spy
    assert budget == 1 and set(inside.values()) == {1}  # one job per core: one thread each
    assert res.mlflow_run_id and (tmp_path / "sweep" / "0" / "result.json").exists()  # it ran as that job


# ---------------------------------------------------------- dataset inputs ---
def test_train_run_logs_its_dataset_with_the_registry_hash(tmp_path, own_dataset):
    """An own dataset: the run's one dataset input is named as the dataset and channel, its digest
    is the data's content hash (whose first 8 hex the registered model's name carries), its source
    the dataset directory; computed here from the directory, loaded again."""
    from mlflow import MlflowClient  # here: the benchmark workers import this module, and need no MLflow

    res = train(tmp_path, own_dataset)
    view = dataset_view(load_dataset(own_dataset), "Z", segments=True, history=True)
    digest = view.content_hash()
    c = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/mlflow.db")
    (inp,) = c.get_run(res.mlflow_run_id).inputs.dataset_inputs
    assert inp.dataset.name == f"{MACHINE}-Z"
    assert inp.dataset.digest == digest
    assert json.loads(inp.dataset.source) == {"uri": str(own_dataset.resolve())}
    assert {t.key: t.value for t in inp.tags} == {"mlflow.data.context": "training"}
    assert res.outputs["registered"] == f"models:/thermbench-{MACHINE}-Z-{digest[:8]}-baseline_hgb/1"
    assert c.get_run(res.mlflow_run_id).data.tags["dataset_hash"] == digest


def test_the_digest_follows_the_data_not_the_place(tmp_path):
    """The same files elsewhere: the same digest (another source); one byte of a temperature
    changed: another digest."""
    first = Path(two_blocks(tmp_path / "a").path)
    copy = Path(shutil.copytree(first, tmp_path / "b"))
    changed = Path(shutil.copytree(first, tmp_path / "c"))
    text = (changed / "process.csv").read_text()
    row = text.splitlines()[100]
    assert ",20.99," in row  # T_front_C at 990 s: 20.0 + 0.001 * 990
    (changed / "process.csv").write_text(text.replace(row, row.replace(",20.99,", ",20.98,"), 1))
    assert hashlib.sha256((changed / "process.csv").read_bytes()).digest() != hashlib.sha256(
        (first / "process.csv").read_bytes()).digest()

    def made(path: Path):
        return tracking.dataset_input(dataset_view(load_dataset(path), "Z", segments=True, history=True), "d")

    a, b, c = made(first), made(copy), made(changed)
    assert a.digest == b.digest and a.digest != c.digest
    assert (a.source.uri, b.source.uri) == (str(first.resolve()), str(copy.resolve()))
