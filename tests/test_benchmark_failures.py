"""One failed cell is one line, never a crash (issue 54): a family that cannot fit or predict on a
fold is recorded in results.csv (kind ``failed``, its reason in ``failure``) and in the report, is no
candidate there, and the benchmark finishes. The data: four runs whose readings are noise that no
temperature explains, so thermal_lag's selection keeps no input and the Gaussian process on its
inputs has nothing to read (a real test of 18 days crashed the benchmark this way, in scikit-learn)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from tests.synth import analytic_dataset, rise
from tests.test_benchmark import _cfg
from thermbench import benchmark as bm
from thermbench.data.io import save_dataset


def _noise_dataset(root):
    temps = {f"r{k}": {"a": lambda t, k=k: 20 + rise(t, 3.0 + k, 1800.0), "b": lambda t, k=k: 21 + rise(t, 1.0 + k, 5400.0)}
             for k in range(4)}  # fmt: skip
    rng = np.random.default_rng(7)
    ds = analytic_dataset(temps, lambda T, P, run: rng.standard_normal(P.size), duration_s=3 * 3600,
                          targets_mm=(0.0,), every_s=300.0)  # fmt: skip
    save_dataset(ds, root / "noise")
    return root / "noise"


def test_a_family_that_cannot_fit_is_one_line_and_a_row_and_the_benchmark_finishes(tmp_path, capsys):
    from thermbench.models.thermal_lag import ThermalLag
    from thermbench.data.io import load_dataset

    path = _noise_dataset(tmp_path)
    ds = load_dataset(path)
    assert ThermalLag().fit(ds, ds.run_ids[:3]).inputs_ == []  # the premise: the selection keeps nothing
    cfg = _cfg(tmp_path, f"datasets=[{path}]", "families=[gp,thermal_lag,baseline_ridge]", "bank_families=[]",
               "approaches=[global]", "cv=loro")  # fmt: skip
    bm.benchmark(cfg)  # no exception: the benchmark finishes
    out = capsys.readouterr().out
    table = pd.read_csv(tmp_path / "reports" / "results.csv")
    failed = table[table["kind"] == "failed"]
    assert set(failed["dataset"]) == {"synthetic"}  # named by its machine
    assert len(failed) and set(failed["family"]) == {"gp"}, failed
    assert failed["failure"].str.contains("the lag selection kept no input").all()
    # every outer fold's fit and the model to deploy (on all runs), each named
    assert set(failed.loc[failed["inner_fold"].isna(), "fold"]) == {*ds.run_ids, "all runs"}
    # one line each on the terminal and in the report
    lines = [ln for ln in out.splitlines() if ln.startswith("could not fit (never a candidate there): ")]
    assert len(lines) == len(failed) and all("\n" not in ln for ln in lines)
    report = (tmp_path / "reports" / "report.md").read_text()
    assert "**could not fit (never a candidate there)**" in report and report.count("- synthetic/gp/global") == len(failed)
    # the families that did fit are scored and one of them is chosen; the GP is never a candidate
    scored = table[(table["kind"] == "validation") & (table["approach"] == "global")]
    assert {"thermal_lag", "baseline_ridge"} <= set(scored["family"]) and "gp" not in set(scored["family"])
    assert "chosen" not in table or not table.loc[table["family"] == "gp", "chosen"].fillna(False).astype(bool).any()
