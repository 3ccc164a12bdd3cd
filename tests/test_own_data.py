"""Own data end to end, as a lab would go: its files imported (tests/labfiles.py), a model trained
and scored with MLflow tracking, exported with the C-vs-Python parity check, with no benchmark
dataset name anywhere: the export finds the training dataset in the MLflow run."""

from __future__ import annotations

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


def test_export_reads_the_training_dataset_from_the_run_and_checks_parity(lab_store, monkeypatch):
    tmp, ds, res = lab_store
    monkeypatch.chdir(tmp)
    uri = res.outputs["registered"]
    cfg = compose("export", tmp, f"export.model_uri={uri}", f"export.out_dir={tmp / 'exports'}")
    mlflow.set_tracking_uri(f"sqlite:///{tmp}/mlflow.db")
    try:
        table, out = run_export(cfg)
    finally:
        _end_active_runs()
    row = table.iloc[0]
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
