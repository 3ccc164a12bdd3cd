"""The robustness benchmark (thermbench.bench): train-state x test-state matrices,
global and bank models, the chosen model, report/MLflow/export outputs, resume from cache."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from thermbench import bench as bm
from thermbench.config import ConfigError, load_config
from thermbench.outputs import RECORD, OutputRefused
from thermbench.experiment import fit_evaluate, group_option, load_split, model_from_config

STATES = ["state1", "state2", "state3", "state4", "state5"]
VALID = ["valid1", "valid2", "valid3", "valid4"]


@pytest.fixture()
def data_env(seed001_data_root, monkeypatch):
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    return seed001_data_root


@pytest.fixture()
def task_out(data_env):
    return bm.run_task(
        dataset_cfg=group_option("dataset", "seed001_vmc_x"),
        family="mlr_seed002",
        model_cfg=group_option("model", "mlr_seed002"),
        approaches=["single", "global", "bank"],
        classifier_cfg=group_option("classifier", "proximity"),
        seed=0,
    )


def test_task_builds_the_train_test_matrix_global_and_bank(task_out, data_env):
    res = task_out["results"]
    single = res[res["approach"] == "single"]
    # one model per loading state, each scored on all 9 runs
    assert sorted(single["train"].unique()) == STATES
    assert single.groupby("train")["run_id"].nunique().eq(9).all()
    # exactly the training state is "own"; validation runs are never own
    own = single[single["own"]]
    assert (own["train"] == own["run_id"]).all() and len(own) == 5
    assert set(res.loc[res["run_id"].isin(VALID), "kind"]) == {"validation"}
    assert not res.loc[res["run_id"].isin(VALID), "own"].any()
    # the single-state cell equals an independent fit on that state scored on that run
    ds = load_split(group_option("dataset", "seed001_vmc_x")).dataset
    _, ref, _ = fit_evaluate(model_from_config("mlr_seed002"), ds, ["state3"], ["valid2"])
    cell = single[(single["train"] == "state3") & (single["run_id"] == "valid2")].iloc[0]
    assert cell["max_abs_residual_um"] == pytest.approx(ref["max_abs_residual_um"].iloc[0], rel=1e-9)
    # global: one model on all states; bank: the single models + classifier
    for approach in ("global", "bank"):
        g = res[res["approach"] == approach]
        assert len(g) == 9 and set(g.loc[g["own"], "run_id"]) == set(STATES)
    assert set(task_out["models"]) == {"global", "bank"}
    assert sorted(task_out["models"]["bank"].labels_) == STATES
    # curves only for validation runs of global and bank
    cur = task_out["curves"]
    assert set(cur["run_id"]) == set(VALID) and set(cur["approach"]) == {"global", "bank"}
    assert (cur["before_um"] >= 0).all() and (cur["after_um"] >= 0).all()


def test_choose_takes_best_worst_case_validation_rate():
    rows = []
    for fam, app, rates in [("a", "global", [0.9, 0.5]), ("b", "bank", [0.8, 0.7]), ("c", "single", [0.99, 0.99])]:
        for run, r in zip(["v1", "v2"], rates):
            rows.append(dict(dataset="d", family=fam, approach=app, run_id=run, kind="validation",
                             compensation_rate=r, max_abs_residual_um=10 * (1 - r)))
    chosen = bm.choose(pd.DataFrame(rows))
    # b's worst (0.7) beats a's worst (0.5); single models are never candidates
    assert chosen[["family", "approach"]].values.tolist() == [["b", "bank"]]


def test_choose_never_picks_a_flagged_model():
    """Best on validation but worse than no compensation on its own training run (a), or NaN on
    one run (b): neither is chosen; c, worse on validation but sound, is. Hand-made rows."""
    rows = []
    for fam, own_rate, v_rates in [("a", -0.2, [0.95, 0.95]), ("b", 0.9, [0.9, float("nan")]), ("c", 0.8, [0.6, 0.5])]:
        rows.append(dict(dataset="d", family=fam, approach="global", train="all", run_id="s1", kind="state", own=True,
                         compensation_rate=own_rate, rmse_um=1.0, max_abs_residual_um=1.0))
        for run, r in zip(["v1", "v2"], v_rates):
            rows.append(dict(dataset="d", family=fam, approach="global", train="all", run_id=run, kind="validation",
                             own=False, compensation_rate=r, rmse_um=r, max_abs_residual_um=10 * (1 - r)))
    res = pd.DataFrame(rows)
    assert bm.choose(res)[["family"]].values.ravel().tolist() == ["c"]
    flags = bm.flagged(res)
    assert flags[("d", "a", "global", "all")] == ["worse than no compensation on its own training run(s) ['s1'] "
                                                  "(rate -20.0 % on s1)"]
    assert flags[("d", "b", "global", "all")] == ["non-finite score on run(s) ['v2']"]
    assert ("d", "c", "global", "all") not in flags
    # nothing sound left: no model is chosen for the dataset
    assert bm.choose(res[res["family"] != "c"]).empty


def _cfg(tmp_path, *extra):
    return load_config(
        "benchmark",
        [
            "datasets=[seed001_vmc_x]",
            "families=[mlr_seed001,mlr_seed002]",
            "bank_families=[mlr_seed002]",
            "n_jobs=1",
            "progress=false",
            f"cache_dir={tmp_path}/cache",
            f"report_dir={tmp_path}/reports",
            f"export_dir={tmp_path}/models",
            f"tracking.uri=sqlite:///{tmp_path}/mlflow.db",
            f"tracking.artifact_root={tmp_path}/art",
            *extra,
        ],
        return_hydra_config=True,
    )


def test_benchmark_end_to_end_report_mlflow_models_and_resume(tmp_path, data_env, monkeypatch, capsys):
    import mlflow
    from mlflow import MlflowClient

    from thermbench import tracking

    planted = tmp_path / "lab notes.txt"  # a user's file beside the output directories
    planted.write_text("calibration of sensor T3 drifted on day 2\n")
    res = bm.benchmark(_cfg(tmp_path))
    assert planted.read_text() == "calibration of sensor T3 drifted on day 2\n"
    out = capsys.readouterr().out
    assert "mlr_seed001" in out and "report:" in out
    report = (tmp_path / "reports" / "report.md").read_text()
    assert "seed001_vmc_x" in report and "figures/" in report
    # the frame of every score, per dataset (format 1: the error as read, cold cycle = geometric error)
    row = next(ln for ln in report.splitlines() if ln.startswith(("| scored on ", "- **scored on**: ")))
    assert "seed001_vmc_x: the error as read (each run's cold measuring cycle is the geometric error" in row
    # the seed 001 finding: MLR of seed 001 fails across moving states; its matrix has a negative cell
    results = pd.read_csv(MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/mlflow.db").download_artifacts(
        res.mlflow_run_id, "results.csv", str(tmp_path)))
    m1 = results[(results["family"] == "mlr_seed001") & (results["approach"] == "single") & ~results["own"]]
    assert m1["compensation_rate"].min() < 0
    # models saved, the chosen one marked, registered with alias champion, loadable, same predictions
    manifest = yaml.safe_load((tmp_path / "models" / "manifest.yaml").read_text())
    chosen = [k for k, v in manifest.items() if v["chosen"]]
    assert len(chosen) == 1 and chosen[0].startswith("seed001_vmc_x__")
    tracking.connect({"uri": f"sqlite:///{tmp_path}/mlflow.db", "experiment": "thermbench"})
    # these are not the shipped settings: registered under their own alias, the demo's 'champion' is left alone
    assert res.outputs["seed001_vmc_x"] == f"models:/thermbench-seed001_vmc_x@{bm.output_name(_cfg(tmp_path))}"
    champion = tracking.load_model(res.outputs["seed001_vmc_x"])
    saved = __import__("joblib").load(tmp_path / "models" / manifest[chosen[0]]["file"])
    ds = load_split(group_option("dataset", "seed001_vmc_x")).dataset
    np.testing.assert_allclose(champion.predict(ds, "valid1"), saved.predict(ds, "valid1"))
    # the MLflow run carries the report and the headline metrics
    run = mlflow.get_run(res.mlflow_run_id)
    assert any(k.endswith("validation_worst_compensation_rate") for k in run.data.metrics)
    arts = [a.path for a in MlflowClient().list_artifacts(res.mlflow_run_id, "report")]
    assert "report/report.md" in arts
    # the answer: the report's first table, the terminal's last lines and the parent run's metrics say the same
    lines = report.splitlines()
    assert lines[2].startswith("| dataset, channel ") and "| deploy " in lines[2]
    cells = [c.strip() for c in lines[4].strip("|").split("|")]  # the first case: case, deploy, median, worst, ...
    tail = out.rstrip().splitlines()
    head = max(k for k, ln in enumerate(tail) if ln == "the model to deploy, and its RMSE on runs it never saw")
    row = tail[head + 3]  # the title, the header, the rule, then the first case
    assert row.split()[0] == cells[0] and all(f" {c} " in f"{row} " for c in cells[1:])
    assert all(ln.startswith("- ") for ln in tail[-4:])  # its notes end the output: the answer is the last screen
    paths = [k for k, ln in enumerate(tail) if ln.startswith(("report: ", "models: ", "mlflow run: ", "registered: "))]
    assert len(paths) == 4 and max(paths) < head
    assert f"mlflow run: {res.mlflow_run_id}" in tail
    assert f"{run.data.metrics[f'{cells[0]}/held_out_median_rmse_um']:.2f}" == cells[2]
    assert f"{run.data.metrics[f'{cells[0]}/uncompensated_median_rmse_um']:.2f}" == cells[7]
    assert f"{run.data.metrics[f'{cells[0]}/as_deployed_median_rmse_um']:.2f}" == cells[4]  # the choice as deployed
    # one nested run per (dataset, family, approach) under the benchmark run
    children = MlflowClient().search_runs(
        [run.info.experiment_id], filter_string=f"tags.mlflow.parentRunId = '{res.mlflow_run_id}'")
    assert {(c.data.tags["model"], c.data.tags["approach"]) for c in children} == {
        ("mlr_seed001", "single"), ("mlr_seed001", "global"), ("mlr_seed001", "as_deployed"),
        ("mlr_seed002", "single"), ("mlr_seed002", "global"), ("mlr_seed002", "as_deployed"), ("mlr_seed002", "bank"),
        ("mlr_seed002", "bank_soft"), ("stack", "global")}  # the stack of the two candidate families
    # the dataset, as an MLflow dataset input of the benchmark run and of each cell: its name,
    # the content hash of its data (loaded here) as the digest, its directory as the source
    for r in [run, *children]:
        (inp,) = MlflowClient().get_run(r.info.run_id).inputs.dataset_inputs
        assert (inp.dataset.name, inp.dataset.digest) == ("seed001_vmc_x", ds.content_hash())
        assert json.loads(inp.dataset.source) == {"uri": str((data_env / "seed001_vmc_x").resolve())}
        assert {t.key: t.value for t in inp.tags} == {"mlflow.data.context": "training"}
    # run again (e.g. after an interruption): every (dataset, family) task comes from the
    # cache, nothing is refitted, and the report and the MLflow run are made again
    (tmp_path / "reports" / "report.md").unlink()
    monkeypatch.setattr(bm.run, "fit_evaluate", lambda *a, **k: (_ for _ in ()).throw(AssertionError("refitted")))
    again = bm.benchmark(_cfg(tmp_path))
    assert again.mlflow_run_id != res.mlflow_run_id
    assert (tmp_path / "reports" / "report.md").exists()
    assert again.metrics == pytest.approx(res.metrics)
    # a user's file inside the report directory: the next benchmark refuses before any work
    (tmp_path / "reports" / "my_review.md").write_text("fig 3 is wrong\n")
    with pytest.raises(OutputRefused, match=r"reports: holds 1 file\(s\) thermbench did not write there"):
        bm.benchmark(_cfg(tmp_path))
    assert (tmp_path / "reports" / "my_review.md").read_text() == "fig 3 is wrong\n"


def test_each_benchmark_setting_gets_its_own_output_set():
    """The shipped settings write reports/benchmark and models/benchmark; other settings (not
    mere run options) get a name of their own, so they never replace the demo's outputs."""
    stock = load_config("benchmark")
    assert bm.output_dirs(stock) == (Path("reports/benchmark"), Path("models/benchmark"))
    assert bm.output_name(load_config("benchmark", ["n_jobs=1", "progress=false", "seed=0"])) == "benchmark"
    other = bm.output_name(load_config("benchmark", ["seed=1"]))
    assert other.startswith("benchmark-") and other != bm.output_name(load_config("benchmark", ["seed=2"]))
    assert bm.output_dirs(load_config("benchmark", ["name=mine"])) == (Path("reports/mine"), Path("models/mine"))
    with pytest.raises(ConfigError, match="config key 'name'"):
        bm.output_name(load_config("benchmark", ["name='../x'"]))


def test_save_models_replaces_the_directory(tmp_path, data_env):
    """A second save leaves no model of the first behind, and the manifest marks the chosen one."""
    from thermbench.experiment import save_models

    ds = load_split(group_option("dataset", "seed001_vmc_x")).dataset
    a = model_from_config("mlr_seed002").fit(ds, ["state1"])
    b = model_from_config("mlr_seed001").fit(ds, ["state2"])
    save_models({"old": a}, tmp_path / "m")
    save_models({"new": b, "other": a}, tmp_path / "m", chosen=["new"])
    assert sorted(p.name for p in (tmp_path / "m").iterdir()) == [RECORD, "manifest.yaml", "new.joblib", "other.joblib"]
    manifest = yaml.safe_load((tmp_path / "m" / "manifest.yaml").read_text())
    assert manifest["new"]["chosen"] and not manifest["other"]["chosen"]
    assert manifest["new"]["train_runs"] == ["state2"]


def test_top_level_seed_and_preprocess_reach_models_inside_a_bank():
    """`seed=` and `preprocess=` are given to every model that takes them, also the one a
    bank clones per condition (otherwise a seed sweep over a bank would fit the same thing)."""
    from thermbench.experiment import build_model
    from thermbench.preprocess.filters import LimitFilter

    bank_cfg = {"_target_": "thermbench.models.bank.ConditionBank", "model": group_option("model", "lssvm")}
    m = build_model(bank_cfg, preprocess_steps=[{"_target_": "thermbench.preprocess.filters.LimitFilter", "limit_C": 3.0}], seed=7)
    assert m.model.seed == 7
    assert len(m.model.preprocess) == 1 and isinstance(m.model.preprocess[0], LimitFilter)
    assert m.model.preprocess[0].limit_C == 3.0
    plain_model = build_model(group_option("model", "gru"), seed=11)
    assert plain_model.seed == 11


def test_benchmark_rejects_unknown_approach_and_stray_bank_family(tmp_path):
    from thermbench.experiment import ExperimentError

    with pytest.raises(ExperimentError, match="'approaches'"):
        bm.tasks(_cfg(tmp_path, "approaches=[single,globl]"))
    with pytest.raises(ExperimentError, match="'bank_families'"):
        bm.tasks(_cfg(tmp_path, "bank_families=[lssvm]"))


def test_results_csv_is_in_the_plans_order_whatever_order_the_tasks_finish_in(tmp_path, data_env, monkeypatch):
    """The workers hand tasks back as they finish (run_workers(ordered=False)); two runs of one
    configuration whose tasks finish in opposite orders write the same results.csv, byte for byte."""
    bm.benchmark(_cfg(tmp_path))
    first = (tmp_path / "reports" / "results.csv").read_bytes()
    real = bm.job._iterate
    finished = []

    def backwards(cfg, todo):  # the last task of the plan finishes first (from the cache: the same numbers)
        outs = list(real(cfg, todo))[::-1]
        finished.extend(o["family"] for o in outs)
        return iter(outs)

    monkeypatch.setattr(bm.job, "_iterate", backwards)
    bm.benchmark(_cfg(tmp_path))
    assert finished == ["mlr_seed002", "mlr_seed001"]  # the plan's order reversed
    assert (tmp_path / "reports" / "results.csv").read_bytes() == first


def test_ctrl_c_keeps_the_finished_cells_and_says_how_to_resume(tmp_path, data_env, monkeypatch, capsys):
    """Interrupted after its first cell, the job says how many cells are done and where they are kept; the
    same command then fits only the cell left (the first comes from the cache)."""
    real = bm.job._iterate

    def interrupted(cfg, todo):
        it = real(cfg, todo)
        yield next(it)
        raise KeyboardInterrupt

    monkeypatch.setattr(bm.job, "_iterate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        bm.benchmark(_cfg(tmp_path))
    err = capsys.readouterr()
    line = next(x for x in (err.out + err.err).splitlines() if "cells done" in x)
    assert line == (f"benchmark: 1 of 2 cells done, kept in {(tmp_path / 'cache').resolve()}: the same command "
                    "resumes with the 1 cells left")  # fmt: skip
    monkeypatch.setattr(bm.job, "_iterate", real)
    import joblib

    calls = []

    real_call = joblib.memory.MemorizedFunc._call

    def counting(self, *a, **k):  # a cell the cache does not hold is computed through _call
        calls.append(1)
        return real_call(self, *a, **k)

    monkeypatch.setattr(joblib.memory.MemorizedFunc, "_call", counting)
    bm.benchmark(_cfg(tmp_path))
    assert len(calls) == 1
