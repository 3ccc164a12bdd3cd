"""The benchmark's cells on a real Dask cluster (executor=dask): a scheduler and two worker processes
on localhost, one of them killed while it runs a cell; the job finishes and its results.csv equals a
local run's in every column but the wall times."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import distributed
import pandas as pd
import pytest

from thermbench import bench as bm
from thermbench.config import load_config
from thermbench.errors import ExperimentError

DASK = [sys.executable, "-m", "distributed.cli.dask_scheduler"]
WORKER = [sys.executable, "-m", "distributed.cli.dask_worker"]
WALL_TIMES = ["fit_s"]  # the only columns a cell's timing writes


def _cfg(tmp_path: Path, name: str, *extra):
    return load_config(
        "benchmark",
        [
            "datasets=[seed001_vmc_x]",
            "families=[mlr_seed001,mlr_seed002,physics]",
            "bank_families=[mlr_seed002]",
            "progress=false",
            f"cache_dir={tmp_path}/{name}/cache",
            f"report_dir={tmp_path}/{name}/reports",
            f"export_dir={tmp_path}/{name}/models",
            f"tracking.uri=sqlite:///{tmp_path}/{name}/mlflow.db",
            f"tracking.artifact_root={tmp_path}/{name}/art",
            "tracking.register=false",
            *extra,
        ],
        return_hydra_config=True,
    )


@pytest.fixture()
def cluster(tmp_path):
    """A scheduler and two single-threaded worker processes without nannies (a killed one stays dead),
    started from another working directory: (scheduler file, worker processes)."""
    where = tmp_path / "cluster"
    where.mkdir()
    sched_file = where / "scheduler.json"
    env = {k: v for k, v in os.environ.items() if k != "THERMBENCH_DATA"}  # the tasks carry absolute paths
    procs = [subprocess.Popen([*DASK, "--scheduler-file", str(sched_file), "--port", "0", "--no-dashboard"],
                              cwd=where, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)]  # fmt: skip
    try:
        for _ in range(600):
            if sched_file.exists() and sched_file.stat().st_size:
                break
            time.sleep(0.1)
        workers = [subprocess.Popen([*WORKER, "--scheduler-file", str(sched_file), "--nthreads", "1", "--no-nanny",
                                     "--no-dashboard", "--local-directory", str(where / f"w{i}")],
                                    cwd=where, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
                   for i in range(2)]  # fmt: skip
        procs += workers
        with distributed.Client(scheduler_file=str(sched_file), timeout="60s") as c:
            c.wait_for_workers(2, timeout=120)
        yield sched_file, workers
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
            p.wait()


def _kill_a_busy_worker(sched_file: Path, workers, killed: dict) -> None:
    """Watch the scheduler; SIGKILL the first worker seen running a cell (the cells it held are lost)."""
    by_pid = {p.pid: p for p in workers}
    with distributed.Client(scheduler_file=str(sched_file), timeout="60s") as c:
        pid_of = c.run(os.getpid)  # worker address -> its process
        deadline = time.monotonic() + 600
        while time.monotonic() < deadline and not killed:
            for addr, keys in c.processing().items():
                pid = pid_of.get(addr)
                if keys and pid in by_pid:
                    by_pid[pid].send_signal(signal.SIGKILL)
                    killed.update(addr=addr, keys=list(keys), pid=pid)
                    return
            time.sleep(0.05)


def test_a_benchmark_on_dask_with_a_killed_worker_equals_the_local_run(tmp_path, seed001_data_root, monkeypatch,
                                                                        cluster):  # fmt: skip
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    sched_file, workers = cluster
    killed: dict = {}
    watcher = threading.Thread(target=_kill_a_busy_worker, args=(sched_file, workers, killed), daemon=True)
    watcher.start()
    bm.benchmark(_cfg(tmp_path, "dask", "executor=dask", f"executor.address={sched_file}"))
    watcher.join(timeout=5)
    assert killed, "no worker was seen running a cell"
    assert sum(p.poll() is None for p in workers) == 1  # the job finished on the one left
    bm.benchmark(_cfg(tmp_path, "local", "n_jobs=2"))  # the same cells in local joblib workers
    got = pd.read_csv(tmp_path / "dask" / "reports" / "results.csv")
    want = pd.read_csv(tmp_path / "local" / "reports" / "results.csv")
    assert len(want) > 50 and set(want["family"]) >= {"mlr_seed001", "mlr_seed002", "physics"}
    # the same numbers up to the order of a BLAS reduction (one thread per cell in both)
    pd.testing.assert_frame_equal(got.drop(columns=WALL_TIMES), want.drop(columns=WALL_TIMES), check_exact=False,
                                  rtol=1e-9, atol=1e-12)  # fmt: skip
    # every cell, the killed worker's too, is in the cache the workers share: a re-run fits nothing
    cached = list((tmp_path / "dask" / "cache" / "joblib").rglob("output.pkl"))
    assert len(cached) == 3


def test_executor_errors_are_one_line(tmp_path, seed001_data_root, monkeypatch):
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    with pytest.raises(ExperimentError, match="executor.address.*no Dask scheduler at tcp://127.0.0.1:9"):
        bm.benchmark(_cfg(tmp_path, "x", "executor=dask", "executor.address=tcp://127.0.0.1:9",
                          "executor.connect_timeout_s=2"))  # fmt: skip
    with pytest.raises(ExperimentError, match="executor.n_workers.*integer >= 1, got 0"):
        bm.benchmark(_cfg(tmp_path, "y", "executor=dask", "executor.n_workers=0"))


def test_a_cell_on_a_dask_worker_keeps_its_joblib_calls_to_itself():
    """joblib inside a Dask task would send nested calls (scikit-learn's cross_val_predict) back to the
    cluster with their data; a cell runs them in its own worker, one after the other, as a local worker does."""
    import joblib

    from thermbench.bench.parallel import _call_limited

    def nested_backend():
        with joblib.parallel_config(backend="dask"):  # what joblib picks inside a Dask task
            return type(_call_limited(lambda: joblib.parallel.get_active_backend()[0], 1, (), {})).__name__

    with distributed.Client(n_workers=1, threads_per_worker=1, processes=False, dashboard_address=None) as c:
        assert c.submit(nested_backend).result() == "SequentialBackend"
        assert nested_backend() == "DaskDistributedBackend"  # outside a worker: untouched
