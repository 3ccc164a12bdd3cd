"""Own data end to end, as a lab would go: its files imported (tests/labfiles.py), a model trained
and scored with MLflow tracking, exported with the C-vs-Python parity check, with no benchmark
dataset name anywhere: the export finds the training dataset in the MLflow run."""

from __future__ import annotations

from pathlib import Path

import mlflow
import numpy as np
import pytest

from tests import labfiles
from tests.test_tracking import _end_active_runs, compose
from thermbench import experiment
from thermbench.data.importer import import_dataset
from thermbench.export.job import run_export


@pytest.fixture(scope="module")
def lab_store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("own")
    ds = import_dataset(labfiles.write_lab_files(tmp / "files"), tmp / "lab_x")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp)
        cfg = compose("train", tmp, "dataset=path", f"dataset.source.path={tmp / 'lab_x'}", "train=warmup_6000",
                      "model=mlr_seed002")  # fmt: skip
        try:
            res = experiment.train(cfg)
        finally:
            _end_active_runs()
    return tmp, ds, res


def test_train_names_the_registered_model_after_dataset_channel_and_content(lab_store, capsys):
    tmp, ds, res = lab_store
    reg = res.outputs["registered"]
    # models:/thermbench-<machine.name>-<channel>-<content hash>-<model>/1
    assert reg == f"models:/thermbench-lab_x-X-{ds.channel_view('X').content_hash()[:8]}-mlr_seed002/1"
    # the bidirectional readings' thermal error alone is modelled: the residual is far below the 4 µm reversal
    assert res.metrics["own_mean_rmse_um"] < 1.0


@pytest.fixture(scope="module")
def lab_export(lab_store):
    """``thermbench export`` of the registered model, no dataset named: it comes from the run."""
    tmp, ds, res = lab_store
    uri = res.outputs["registered"]
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp)
        cfg = compose("export", tmp, f"export.model_uri={uri}", f"export.out_dir={tmp / 'exports'}")
        mlflow.set_tracking_uri(f"sqlite:///{tmp}/mlflow.db")
        try:
            table, _ = run_export(cfg)
        finally:
            _end_active_runs()
    return table


def test_export_reads_the_training_dataset_from_the_run_and_checks_parity(lab_store, lab_export):
    uri = lab_store[2].outputs["registered"]
    row = lab_export.iloc[0]
    assert row["model"] == uri.removeprefix("models:/").replace("/", "_")
    # the parity check ran on the dataset the run logged: a finite difference, in nm
    assert np.isfinite(row["parity_max_abs_diff_nm"]) and row["parity_max_abs_diff_nm"] < 10.0
    assert np.isfinite(row["heldout_rmse_um"])


def test_train_prints_the_inputs_used_and_every_fallback(lab_store, capsys):
    tmp, ds, _ = lab_store
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(tmp)
        # seed 004 regresses on the fixed-bearing, nut and free-bearing housings; the lab has only the nut
        cfg = compose("train", tmp, "dataset=path", f"dataset.source.path={tmp / 'lab_x'}", "train=warmup_6000",
                      "model=mlr_seed004", "tracking.register=false")  # fmt: skip
        try:
            experiment.train(cfg)
        finally:
            _end_active_runs()
    err = capsys.readouterr().err
    assert ("[train] warning: mlr_seed004: sensors: no sensor at ['fixed_bearing_housing', 'free_bearing_housing']; "
            "the regression uses ['T_nut'] only") in err  # fmt: skip
    assert "[train] mlr_seed004 uses sensors T_nut" in err


def test_replay_of_the_export_on_the_lab_data_and_on_a_log_without_readings(lab_store, lab_export, tmp_path):
    import shutil

    from thermbench.export.replay import format_replay, replay_run, write_replay

    tmp, ds, res = lab_store
    exported = [Path(lab_export.iloc[0]["dir"])]
    out = replay_run(exported[0], tmp / "lab_x", "warmup_6000")
    assert out["figures"]["channel"] == "X" and out["figures"]["n_readings"] == len(ds.errors)
    # the C runtime's residual RMS equals the Python model's (train scored it)
    assert out["figures"]["after_rmse_um"] == pytest.approx(res.metrics["own_mean_rmse_um"], abs=0.01)
    # the same process log without readings: valid, and the replay gives the compensation alone
    log = tmp_path / "log_only"
    log.mkdir()
    for f in ("metadata.yaml", "process.parquet"):
        shutil.copy(tmp / "lab_x" / f, log / f)
    bare = replay_run(exported[0], log, "warmup_6000")
    assert bare["figures"]["n_readings"] == 0 and len(bare["compensation"]) == len(ds.process)
    np.testing.assert_allclose(bare["compensation"]["compensation_um"], out["compensation"]["compensation_um"])
    assert "no readings" in format_replay(bare["figures"])
    write_replay(bare, tmp_path / "replay")
    assert (tmp_path / "replay" / "compensation.png").is_file()
