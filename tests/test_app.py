"""The Hydra jobs on the command line (thermbench.app): multirun with the basic and joblib
launchers, Ctrl-C and resume, the sweep and cluster-launcher configs, and user mistakes.

Every command runs as ``python -m thermbench.cli`` in a tmp dir with the MLflow store and
the Hydra output directories overridden into it, and ``THERMBENCH_DATA`` pointing at the
session's seed 001 dataset. Models: ``mlr_seed001`` / ``mlr_seed002`` (well under a second
to fit).
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections import Counter
from itertools import product
from pathlib import Path

import pytest
from mlflow import MlflowClient
from omegaconf import OmegaConf

from thermbench.app import _sweep_size
from thermbench.config import load_config

MODELS = ["mlr_seed001", "mlr_seed002"]
STATES = ["state1", "state2"]
SWEEP_2X2 = ["-m", f"model={','.join(MODELS)}", f"train={','.join(STATES)}"]


# ---------------------------------------------------------------- helpers ---
def store_overrides(tmp: Path) -> list[str]:
    """The store and Hydra's outputs in ``tmp``; jobs score two validation runs only (faster)."""
    return [f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"tracking.artifact_root={tmp}/art",
            f"hydra.run.dir={tmp}/run", f"hydra.sweep.dir={tmp}/sweep", "eval=valid1+valid2"]


@pytest.fixture
def env(seed001_data_root):
    e = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR" and not k.startswith("MLFLOW_")}
    e["THERMBENCH_DATA"] = str(seed001_data_root)
    return e


def cli(args: list[str], tmp: Path, env: dict, timeout: float = 300) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "thermbench.cli", *args], cwd=tmp, env=env,
                          capture_output=True, text=True, timeout=timeout)


def finished_runs(tmp: Path) -> list:
    c = MlflowClient(tracking_uri=f"sqlite:///{tmp}/mlflow.db")
    exp = c.get_experiment_by_name("thermbench")
    if exp is None:
        return []
    return c.search_runs([exp.experiment_id], filter_string="attributes.status = 'FINISHED'", max_results=1000)


def job_results(sweep: Path) -> dict[str, dict]:
    """result.json of each job directory, keyed by the job's overrides (``model=... train=...``)."""
    out = {}
    for res in sorted(sweep.glob("*/result.json")):
        ov = OmegaConf.load(res.parent / ".hydra" / "overrides.yaml")
        key = " ".join(o for o in ov if o.startswith(("model=", "train=")))
        out[key] = json.loads(res.read_text())
    return out


def summary_rows(stdout: str) -> list[str]:
    """The rows of the sweep summary table printed at the end (header dropped)."""
    assert "[sweep] summary" in stdout, stdout[-2000:]
    lines = [ln for ln in stdout.split("[sweep] summary", 1)[1].splitlines() if ln.strip()]
    assert lines[0].split()[:3] == ["job", "model", "train"], lines[0]
    return lines[1:]


def summary_rows_of(stdout: str) -> list[str]:
    """The rows of the sweep summary table, whatever the swept keys (header dropped)."""
    assert "[sweep] summary" in stdout, stdout[-2000:]
    lines = [ln for ln in stdout.split("[sweep] summary", 1)[1].splitlines() if ln.strip()]
    assert lines[0].split()[0] == "job", lines[0]
    return lines[1:]


def expected_keys(models=MODELS, states=STATES) -> set[str]:
    return {f"model={m} train={s}" for m, s in product(models, states)}


# ------------------------------------------------------------------ multirun ---
def test_multirun_basic_launcher(tmp_path, env):
    sweep = tmp_path / "sweep"
    # a leftover of an older multirun into the same sweep dir: not part of this sweep's progress or summary
    stale = sweep / "9"
    (stale / ".hydra").mkdir(parents=True)
    (stale / ".hydra" / "overrides.yaml").write_text("- model=mlr_seed004\n- train=state5\n")
    (stale / "result.json").write_text(json.dumps({"job": "train", "skipped": False, "metrics": {"fit_s": 1.0}}))
    (sweep / "multirun.yaml").write_text("hydra: {}\n")  # Hydra writes it into every sweep directory
    os.utime(stale / "result.json", (time.time() - 3600, time.time() - 3600))

    proc = cli(["train", *SWEEP_2X2, *store_overrides(tmp_path)], tmp_path, env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "[sweep] 4 jobs" in proc.stdout
    progress = [ln.rsplit(";", 1)[1].strip() for ln in proc.stdout.splitlines() if ln.startswith("[sweep] job #")]
    assert progress == [f"{i}/4 finished" for i in range(1, 5)]
    shutil.rmtree(stale)
    # each job's line says what it found: the RMSE on its held-out (validation) runs, as its result.json has it
    found = {ln.split("(", 1)[1].split(")", 1)[0]: ln.split("held-out RMSE ", 1)[1].split(" µm")[0]
             for ln in proc.stdout.splitlines() if ln.startswith("[sweep] job #")}  # fmt: skip
    results = job_results(sweep)
    assert len(found) == 4 and {k: f"{v['metrics']['validation_mean_rmse_um']:.2f}" for k, v in results.items()} == {
        " ".join(o for o in k.split() if o.startswith(("model=", "train="))): v for k, v in found.items()}
    header = proc.stdout.split("[sweep] summary", 1)[1].strip().splitlines()[0].split()
    assert "validation_mean_rmse_um" in header  # and the final table

    assert sorted(p.name for p in sweep.iterdir() if p.is_dir()) == ["0", "1", "2", "3"]
    results = job_results(sweep)
    assert set(results) == expected_keys()
    assert not any(r["skipped"] for r in results.values())

    rows = summary_rows(proc.stdout)
    assert len(rows) == 4
    assert {tuple(r.split()[1:3]) for r in rows} == set(product(MODELS, STATES))

    runs = finished_runs(tmp_path)
    assert len(runs) == 4
    assert len({r.data.tags["thermbench.config_hash"] for r in runs}) == 4
    assert {(r.data.tags["model"], r.data.params["train"]) for r in runs} == set(product(MODELS, STATES))
    assert {r["mlflow_run_id"] for r in results.values()} == {r.info.run_id for r in runs}
    assert not (tmp_path / "outputs").exists() and not (tmp_path / "multirun").exists()


def test_multirun_joblib_launcher(tmp_path, env):
    args = ["train", "-m", f"model={','.join(MODELS)}", "train=state2", "hydra/launcher=joblib",
            "hydra.launcher.n_jobs=2", *store_overrides(tmp_path)]
    proc = cli(args, tmp_path, env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "Joblib.Parallel(n_jobs=2" in proc.stdout
    sweep = tmp_path / "sweep"
    launcher = OmegaConf.load(sweep / "multirun.yaml").hydra.launcher
    assert launcher._target_.endswith("JoblibLauncher") and launcher.n_jobs == 2

    results = job_results(sweep)
    assert set(results) == expected_keys(states=["state2"])
    runs = finished_runs(tmp_path)
    assert {r.info.run_id for r in runs} == {r["mlflow_run_id"] for r in results.values()}
    assert {r.data.tags["model"] for r in runs} == set(MODELS)
    assert len(summary_rows(proc.stdout)) == 2


def test_interrupted_sweep_resumes_without_duplicates(tmp_path, env):
    args = [sys.executable, "-m", "thermbench.cli", "train", *SWEEP_2X2, *store_overrides(tmp_path)]
    first_done = tmp_path / "sweep" / "0" / "result.json"
    with open(tmp_path / "out1.txt", "w") as out, open(tmp_path / "err1.txt", "w") as err:
        proc = subprocess.Popen(args, cwd=tmp_path, env=env, stdout=out, stderr=err)
        try:
            deadline = time.monotonic() + 240
            while not first_done.exists():
                assert proc.poll() is None, f"sweep ended before its first job finished:\n{(tmp_path / 'err1.txt').read_text()}"
                assert time.monotonic() < deadline, "first job did not finish in 240 s"
                time.sleep(0.02)
            proc.send_signal(signal.SIGINT)
            rc = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
    err1 = (tmp_path / "err1.txt").read_text()
    assert rc == 130, err1[-3000:]
    assert "thermbench train: interrupted" in err1 and "Traceback" not in err1

    done_before = finished_runs(tmp_path)
    k = len(done_before)
    assert 1 <= k < 4  # job 0 finished, the interrupt stopped the sweep before the end

    proc2 = cli(["train", *SWEEP_2X2, *store_overrides(tmp_path)], tmp_path, env)
    assert proc2.returncode == 0, proc2.stderr[-3000:]
    assert proc2.stdout.count("[train] skipped:") == k

    results = job_results(tmp_path / "sweep")
    assert set(results) == expected_keys()
    skipped = {key for key, r in results.items() if r["skipped"]}
    assert len(skipped) == k
    assert {results[key]["mlflow_run_id"] for key in skipped} == {r.info.run_id for r in done_before}
    assert len(summary_rows(proc2.stdout)) == 4

    runs = finished_runs(tmp_path)
    per_hash = Counter(r.data.tags["thermbench.config_hash"] for r in runs)
    assert len(per_hash) == 4 and set(per_hash.values()) == {1}
    assert {r.info.run_id for r in runs} == {r["mlflow_run_id"] for r in results.values()}


def test_submitit_local_sweep_runs_each_job_in_its_own_process_and_resumes(tmp_path, env):
    """A real 2-job sweep through Hydra's submitit launcher in its local mode (what
    ``hydra/launcher=cluster`` does on SLURM, with the local executor): each job is a separate
    process started by submitit from its pickled job file, tracked in MLflow. Ctrl-C (SIGINT to
    the whole process group, as a terminal sends it) after job 0 finished stops the sweep with
    exit 130; the same command again resumes it: job 0 is skipped (its MLflow run reused) and
    job 1 runs to the end. Job 1 is the same LSSVM with 4000 PSO iterations instead of 1
    (about 25 s more of fitting; with 1500 it once finished within the moment between the check and the interrupt on a loaded machine), so it is still running when job 0 is done."""
    args = ["train", "-m", "hydra/launcher=submitit_local", "model=lssvm", "model.iters=1,4000", "model.n_particles=5",
            "train=state2", *store_overrides(tmp_path)]  # fmt: skip
    sweep = tmp_path / "sweep"
    with open(tmp_path / "out1.txt", "w") as out, open(tmp_path / "err1.txt", "w") as err:
        proc = subprocess.Popen([sys.executable, "-m", "thermbench.cli", *args], cwd=tmp_path, env=env, stdout=out,
                                stderr=err, start_new_session=True)  # fmt: skip
        try:
            deadline = time.monotonic() + 240
            # job 0 done: its result.json written and its process through (submitit pickled its
            # result), so the interrupt cannot catch it half-way
            while not ((sweep / "0" / "result.json").exists() and list((sweep / ".submitit").glob("[0-9]*/*_result.pkl"))):
                assert proc.poll() is None, f"sweep ended before job 0 finished:\n{(tmp_path / 'err1.txt').read_text()}"
                assert time.monotonic() < deadline, "job 0 did not finish in 240 s"
                time.sleep(0.02)
            assert not (sweep / "1" / "result.json").exists(), "job 1 finished as early as job 0: make it slower"
            os.killpg(proc.pid, signal.SIGINT)
            rc = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    err1 = (tmp_path / "err1.txt").read_text()
    assert rc == 130, err1[-3000:]
    assert "thermbench train: interrupted" in err1
    assert "Submitit 'local' sweep output dir" in (tmp_path / "out1.txt").read_text()

    # submitit's job files: one folder per job (its local job id is the job's pid), the pickled job
    # submitted, and each job's own logs
    jobs = sorted((sweep / ".submitit").glob("[0-9]*/*_submitted.pkl"))
    assert len(jobs) == 2
    ids = {p.parent.name for p in jobs}
    assert len(ids) == 2 and str(proc.pid) not in ids  # two processes, neither the launcher
    logs = {p.name: p.read_text() for p in sorted((sweep / ".submitit").glob("*/*_log.*"))}
    shown = "\n".join(f"--- {name}\n{text[-2500:]}" for name, text in logs.items())
    # the jobs' own output went to submitit's logs
    assert any("[train] lssvm uses sensors" in text for text in logs.values()), shown

    done_before = finished_runs(tmp_path)
    assert len(done_before) == 1 and done_before[0].data.params["model.iters"] == "1"
    job0 = json.loads((sweep / "0" / "result.json").read_text())
    assert job0["mlflow_run_id"] == done_before[0].info.run_id

    proc2 = cli(args, tmp_path, env)  # the same command: resume
    assert proc2.returncode == 0, proc2.stderr[-3000:]
    assert len(summary_rows_of(proc2.stdout)) == 2
    r0 = json.loads((sweep / "0" / "result.json").read_text())
    r1 = json.loads((sweep / "1" / "result.json").read_text())
    assert r0["skipped"] and r0["mlflow_run_id"] == done_before[0].info.run_id
    assert not r1["skipped"]
    assert len({p.parent.name for p in (sweep / ".submitit").glob("[0-9]*/*_submitted.pkl")}) == 4  # 2 more jobs
    assert len(list((sweep / ".submitit").glob("[0-9]*/*_result.pkl"))) >= 2  # submitit's results of the resumed jobs

    runs = finished_runs(tmp_path)
    assert sorted(r.data.params["model.iters"] for r in runs) == ["1", "4000"]
    assert len({r.data.tags["thermbench.config_hash"] for r in runs}) == 2
    assert {r.info.run_id for r in runs} == {r0["mlflow_run_id"], r1["mlflow_run_id"]}
    c = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/mlflow.db")
    exp = c.get_experiment_by_name("thermbench")
    statuses = Counter(r.info.status for r in c.search_runs([exp.experiment_id], max_results=100))
    assert statuses["FINISHED"] == 2 and statuses["RUNNING"] == 0  # the interrupted attempt is closed, not left running


def test_unreachable_server_stops_a_sweep_before_any_job(tmp_path, env):
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))  # bound, not listening: connections are refused
        uri = f"http://127.0.0.1:{s.getsockname()[1]}"
        proc = cli(["train", *SWEEP_2X2, "tracking=server", f"tracking.uri={uri}", f"hydra.sweep.dir={tmp_path}/sweep"],
                   tmp_path, env, timeout=120)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and f"tracking.uri={uri}" in lines[0], proc.stderr
    assert "Launching" not in proc.stdout and not list(tmp_path.rglob("result.json"))


# ------------------------------------------------------------ sweep configs ---
def test_sweep_group_models_x_states_is_a_multirun_by_itself():
    cfg = load_config("train", ["sweep=models_x_states"], return_hydra_config=True)
    assert str(cfg.hydra.mode) == "RunMode.MULTIRUN"
    params = OmegaConf.to_container(cfg.hydra.sweeper.params)
    assert {k: v.split(",") for k, v in params.items()} == {
        "model": ["mlr_seed001", "mlr_seed002", "lssvm", "physics"],
        "train": ["state1", "state3", "state5"],
    }
    assert _sweep_size(cfg) == 4 * 3
    # every swept option exists and every swept run is a loading state of the dataset
    for m in params["model"].split(","):
        assert load_config("train", ["sweep=models_x_states", f"model={m}"]).model._target_.startswith("thermbench.")
    assert set(params["train"].split(",")) <= set(cfg.dataset.states)


def test_sweep_group_noise_x_seeds_composes_with_the_simulated_dataset():
    cfg = load_config("train", ["sweep=noise_x_seeds"], return_hydra_config=True)
    assert str(cfg.hydra.mode) == "RunMode.MULTIRUN"
    assert cfg.hydra.runtime.choices.dataset == "simulated"
    assert cfg.dataset.source._target_ == "thermbench.bench.datasets.simulated"
    params = OmegaConf.to_container(cfg.hydra.sweeper.params)
    assert set(params) == {"dataset.source.sensor_noise_C", "dataset.source.seed"}
    assert _sweep_size(cfg) == 3 * 2
    # each point of the sweep is a valid override of the composed config
    for noise, seed in product(params["dataset.source.sensor_noise_C"].split(","), params["dataset.source.seed"].split(",")):
        point = load_config("train", ["sweep=noise_x_seeds", f"dataset.source.sensor_noise_C={noise}", f"dataset.source.seed={seed}"])
        assert point.dataset.source.sensor_noise_C == float(noise) and point.dataset.source.seed == int(seed)


def test_cluster_launcher_config():
    cfg = load_config("train", ["hydra/launcher=cluster"], return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher.cpus_per_task == 2 and launcher.timeout_min == 120
    assert launcher.mem_gb == 8 and launcher.nodes == 1 and launcher.tasks_per_node == 1
    from hydra.utils import get_class, instantiate

    from hydra_plugins.hydra_submitit_launcher.submitit_launcher import SlurmLauncher

    assert get_class(launcher._target_) is SlurmLauncher
    built = instantiate(launcher)  # the config's keys are the launcher's parameters
    assert isinstance(built, SlurmLauncher) and built.params["cpus_per_task"] == 2
    # a command-line partition reaches the launcher
    cfg2 = load_config("train", ["hydra/launcher=cluster", "hydra.launcher.partition=cpu"], return_hydra_config=True)
    assert cfg2.hydra.launcher.partition == "cpu"


# ----------------------------------------------------------- user mistakes ---
def test_unknown_model_option(tmp_path, env):
    proc = cli(["train", "model=nope", *store_overrides(tmp_path)], tmp_path, env, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]  # one line, with the known options
    assert len(lines) == 1 and lines[0].startswith("thermbench train: error: unknown option 'nope' for config group 'model'")
    assert "mlr_seed001" in lines[0]
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "run").exists()  # checked before anything started


def test_unknown_training_run(tmp_path, env):
    proc = cli(["train", "train=bogus", *store_overrides(tmp_path)], tmp_path, env, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    errors = [ln for ln in proc.stderr.splitlines() if "error" in ln]
    assert len(errors) == 1, proc.stderr
    assert errors[0].startswith("thermbench train: error:") and "'train'" in errors[0] and "bogus" in errors[0]
    assert not finished_runs(tmp_path) and not list(tmp_path.rglob("result.json"))


def test_a_failing_job_does_not_stop_the_sweep(tmp_path, env):
    """A user mistake in one job of a sweep: the other jobs still run, the summary marks the
    failed one with its one-line error, and the command ends with exit code 2."""
    proc = cli(["train", "-m", "model=mlr_seed002", "train=bogus,state1", *store_overrides(tmp_path)],
               tmp_path, env)
    assert proc.returncode == 2, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    res = job_results(tmp_path / "sweep")
    assert "error" in res["model=mlr_seed002 train=bogus"] and "'train'" in res["model=mlr_seed002 train=bogus"]["error"]
    assert "error" not in res["model=mlr_seed002 train=state1"]
    assert len(finished_runs(tmp_path)) == 1  # the good job ran after the bad one
    assert "1 job(s) failed" in proc.stdout


def test_missing_dataset_path_is_one_line_naming_the_key(tmp_path, env):
    proc = cli(["train", "dataset=path", f"dataset.source.path={tmp_path}/nope", *store_overrides(tmp_path)],
               tmp_path, env, timeout=120)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("thermbench train: error: config key 'dataset.source'"), proc.stderr
    assert "nope" in lines[0]
