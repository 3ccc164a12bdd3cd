"""The benchmark on a dataset with several error channels: one task per (dataset, channel,
family), rows labelled by channel, one chosen model per channel, never a baseline; and the
settings a dataset option gives a family (``benchmark_models``)."""

from __future__ import annotations

import pandas as pd
import pytest

from tests.test_benchmark import _cfg
from thermbench import bench as bm
from thermbench.config import group_option
from thermbench.experiment import ExperimentError


def test_one_task_per_channel_and_family_and_families_a_spindle_cannot_serve_said_once(tmp_path, capsys):
    cfg = _cfg(tmp_path, "datasets=[fl_thermal]", "families=[baseline_ols,physics,mlr_seed001]", "bank_families=[]")
    todo = bm.tasks(cfg)
    assert [(t["channel"], t["family"]) for t in todo] == [(f"ch{i}", "baseline_ols") for i in range(1, 6)]
    assert all(t["dataset_cfg"]["channel"] == t["channel"] for t in todo)
    err = capsys.readouterr().err
    assert err.count("skipped physics on fl_thermal") == 1 and err.count("skipped mlr_seed001 on fl_thermal") == 1
    out = bm.run_task(**{**todo[2], "approaches": ["global"], "verbose": False})
    res = out["results"]
    assert set(res["channel"]) == {"ch3"} and set(res["run_id"]) >= {"tail"}
    assert out["channel"] == "ch3"


def _row(case, family, approach, rate, channel="all", kind="validation", run="v"):
    return {"dataset": case, "channel": channel, "family": family, "approach": approach, "train": "all",
            "run_id": run, "kind": kind, "own": False, "compensation_rate": rate, "max_abs_residual_um": 1 - rate,
            "rmse_um": 1 - rate, "nonfinite_predictions": 0}  # fmt: skip


def test_choose_per_channel_and_never_a_baseline():
    rows = [
        _row("spin", "baseline_rf", "global", 0.9, "ch1"), _row("spin", "mlr", "global", 0.5, "ch1"),
        _row("spin", "mlr", "bank", 0.6, "ch1"), _row("spin", "mlr", "global", 0.7, "ch2"),
        _row("spin", "ar", "global", 0.2, "ch2"), _row("axis", "mlr", "global", 0.4),
        _row("spin", "mlr", "single", 0.99, "ch2"),  # never a candidate: which state would you train on?
    ]  # fmt: skip
    chosen = bm.choose(pd.DataFrame(rows), exclude=["baseline_rf"])
    got = {r.case: (r.family, r.approach) for r in chosen.itertuples()}
    assert got == {"spin-ch1": ("mlr", "bank"), "spin-ch2": ("mlr", "global"), "axis": ("mlr", "global")}
    assert bm.case_label("spin", "ch1") == "spin-ch1" and bm.case_label("axis", "all") == "axis"
    assert bm.reference_only("baseline_ols") and not bm.reference_only("mlr_seed002")


def test_a_dataset_option_gives_a_family_its_settings():
    dcfg = {"benchmark_models": {"lssvm": {"max_samples": 300}}}
    assert bm.model_config("lssvm", dcfg, "d")["max_samples"] == 300
    assert bm.model_config("gru", dcfg, "d") == group_option("model", "gru")
    with pytest.raises(ExperimentError, match=r"key 'benchmark_models.lsvm': no model option 'lsvm'; did you mean 'lssvm'"):
        bm.model_config("gru", {"benchmark_models": {"lsvm": {}}}, "d")
    with pytest.raises(ExperimentError, match=r"key 'benchmark_models.lssvm.max_sample': conf/model/lssvm.yaml has no"):
        bm.model_config("lssvm", {"benchmark_models": {"lssvm": {"max_sample": 3}}}, "d")


def test_a_model_of_several_runs_is_judged_on_them_together():
    """Hand-made rows: a global model leaves 2 µm on a block whose drift peaks at 1 µm (rate
    -100 % there) but 3 µm on a block of 20 µm: over its training runs taken together it
    compensates (1 - 3/20 = 85 %), so it is not flagged; one trained on the small block alone is."""
    from thermbench.experiment import model_flags

    rows = pd.DataFrame([
        dict(run_id="small", own=True, rmse_um=1.0, max_abs_residual_um=2.0, max_abs_error_um=1.0, compensation_rate=-1.0),
        dict(run_id="big", own=True, rmse_um=1.0, max_abs_residual_um=3.0, max_abs_error_um=20.0, compensation_rate=0.85),
    ])  # fmt: skip
    assert model_flags(rows) == []
    assert model_flags(rows.iloc[:1]) == ["worse than no compensation on its own training run(s) ['small'] "
                                          "(rate -100.0 % on small)"]  # fmt: skip
    rows.loc[1, "max_abs_residual_um"] = 25.0  # now worse than the largest drift itself
    assert "over them taken together" in model_flags(rows)[0]
