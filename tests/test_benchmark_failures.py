"""One failed cell is one line, never a crash: a family that cannot fit or predict on a
fold is recorded in results.csv (kind ``failed``, its reason in ``failure``) and in the report, is no
candidate there, and the benchmark finishes. The data: four runs whose readings are noise that no
temperature explains, so thermal_lag's selection keeps no input and the Gaussian process on its
inputs has nothing to read (a real test of 18 days crashed the benchmark this way, in scikit-learn)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from tests.synth import analytic_dataset, rise
from tests.test_benchmark import _cfg
from thermbench import bench as bm
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
    findings = (tmp_path / "reports" / "findings.md").read_text()  # the run's lists, linked from report.md
    assert "| could not fit (never a candidate there) | " in report and "[findings.md](findings.md)" in report
    assert "## could not fit (never a candidate there)" in findings and findings.count("- synthetic/gp/global") == len(failed)
    # the families that did fit are scored and one of them is chosen; the GP is never a candidate
    scored = table[(table["kind"] == "validation") & (table["approach"] == "global")]
    assert {"thermal_lag", "baseline_ridge"} <= set(scored["family"]) and "gp" not in set(scored["family"])
    assert "chosen" not in table or not table.loc[table["family"] == "gp", "chosen"].fillna(False).astype(bool).any()


def test_the_deployed_model_is_picked_by_the_rule_the_held_out_figures_score(tmp_path):
    """One choice, used twice: the model exported and marked chosen is what the nested rule
    (the simplest within one standard error of the lowest mean inner RMSE over whole held-out runs) picks on the inner folds of every run, and those
    folds hold each run out once; recomputed here from the inner scores with pandas."""
    import yaml

    path = _noise_dataset(tmp_path)
    cfg = _cfg(tmp_path, f"datasets=[{path}]", "families=[thermal_lag,lssvm,baseline_ridge]", "bank_families=[]",
               "approaches=[global]", "cv=loro")  # fmt: skip
    inner = pd.concat([bm.run_task(**{**t, "approaches": ["global"], "cv": "loro"})["inner"] for t in bm.tasks(cfg)
                       if t["family"] != "baseline_ridge"])  # fmt: skip
    deploy = inner[inner["fold"] == bm.DEPLOY_FOLD]
    assert sorted(deploy.groupby("family")["run_id"].apply(sorted).iloc[0]) == ["r0", "r1", "r2", "r3"]
    # the rule by hand: the lowest mean inner RMSE sets the bar (its mean + standard error over the held-out
    # runs); of those under it, the simplest (thermal_lag is linear: 1; lssvm a kernel machine: 3)
    stats = deploy.groupby("family")["rmse_um"].agg(["mean", "std", "count", "max"])
    best = stats.sort_values(["mean", "max"]).index[0]
    bar = stats.loc[best, "mean"] + stats.loc[best, "std"] / np.sqrt(stats.loc[best, "count"])
    under = stats[stats["mean"] <= bar]
    by_hand = min(under.index, key=lambda f: ({"thermal_lag": 1, "lssvm": 3}[f], under.loc[f, "mean"]))
    # each outer fold's inner folds never see the fold's own run
    for fold, g in inner[inner["fold"] != bm.DEPLOY_FOLD].groupby("fold"):
        assert fold not in set(g["run_id"])
    bm.benchmark(cfg)
    manifest = yaml.safe_load((tmp_path / "models" / "manifest.yaml").read_text())
    chosen = [k for k, v in manifest.items() if v["chosen"]]
    assert chosen == [f"synthetic__{by_hand}__global"], (chosen, stats)
    report = (tmp_path / "reports" / "report.md").read_text()
    line = _run_entry(report, "chosen models")
    assert f"synthetic: {by_hand} (global) (deployed; chosen by the inner cross-validation over every run" in line
    held = _run_entry(report, "held out, synthetic")
    simpler = f", the simplest within one standard error of {best} (global)" if by_hand != best else ""
    assert f"deployed {by_hand} (global){simpler}; 4 folds; choice " in held
    # what the deployed model is made of: the fit summary of the very model saved as chosen
    import joblib

    summary = joblib.load(tmp_path / "models" / f"synthetic__{by_hand}__global.joblib").fit_summary()
    rows = [_run_entry(report, "deployed model, synthetic")] if "deployed model, synthetic" in report else []
    assert (rows and f"{by_hand} (global): {summary}" in rows[0]) if summary else not rows


def _run_entry(report: str, key: str) -> str:
    """The entry ``key`` of the report's run: a table row, or the bullet below the table of a longer value."""
    return next(ln for ln in report.splitlines() if ln.startswith((f"| {key} ", f"- **{key}**: ")))


def test_a_case_without_inner_folds_falls_back_and_says_so():
    nested = pd.DataFrame([{"dataset": "a", "channel": "all", "case": "a", "fold": bm.DEPLOY_FOLD, "family": "f1",
                            "approach": "global", "inner_median_rmse_um": 1.0},
                           {"dataset": "a", "channel": "all", "case": "a", "fold": "r1", "family": "f2",
                            "approach": "global", "inner_median_rmse_um": 0.5}])  # fmt: skip
    rows = [{"dataset": d, "channel": "all", "family": f, "approach": "global", "kind": "validation", "run_id": "v",
             "compensation_rate": rate, "max_abs_residual_um": 1.0, "own": False, "train": "all", "fold": "v"}
            for d, f, rate in [("a", "f1", 0.1), ("a", "f2", 0.9), ("b", "f1", 0.2), ("b", "f2", 0.8)]]  # fmt: skip
    chosen, rest = bm.deployed_choice(nested, pd.DataFrame(rows), baselines=[])
    got = {c: (f, rule) for c, f, rule in chosen[["case", "family", "rule"]].itertuples(index=False)}
    assert got["a"] == ("f1", "nested")  # the deploy fold's pick, not the better validation rate of f2
    assert got["b"][0] == "f2" and got["b"][1].startswith("the best worst-case rate on the validation runs (fewer")
    assert list(rest["fold"]) == ["r1"]
