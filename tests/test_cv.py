"""Cross-validation over runs (thermbench/bench/splits.py): whole runs held out, each once, and
the benchmark's held-out scores checked against scikit-learn fitted by hand on the same runs."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.linear_model import LinearRegression

from tests.test_benchmark_own import lathe  # noqa: F401  (the fixture: shape 1 imported)
from tests.test_import_shapes import DAYS, _day
from thermbench import bench as bm
from thermbench.bench.splits import folds, resolve_cv
from thermbench.experiment import ExperimentError, dataset_option, group_option

RUNS = ["a", "b", "c", "d", "e"]


def test_loro_holds_each_run_out_once_and_trains_on_the_others():
    fs = folds(RUNS, [], "loro")
    assert [f.held_out for f in fs] == [(r,) for r in RUNS]
    assert all(set(f.train) == set(RUNS) - set(f.held_out) for f in fs)
    assert [f.name for f in fs] == RUNS


def test_group_kfold_splits_whole_runs_into_disjoint_folds():
    fs = folds(RUNS, [], "group_kfold", k=2)
    assert len(fs) == 2
    held = [r for f in fs for r in f.held_out]
    assert sorted(held) == RUNS  # each run held out exactly once
    assert all(not set(f.train) & set(f.held_out) and set(f.train) | set(f.held_out) == set(RUNS) for f in fs)
    # a fold of several runs is named by its place, not by its runs joined (43 runs: 500 characters)
    assert [f.name for f in fs] == ["fold 1 of 2", "fold 2 of 2"]


def test_the_report_lists_each_folds_runs_once():
    import pandas as pd

    from thermbench.report.markdown import folds_md

    rows = [("d", "fold 1 of 2", r, "validation") for r in ("a", "c")] * 2 + \
        [("d", "fold 2 of 2", r, "validation") for r in ("b", "d", "e")] + [("d", "", "a", "state")]
    md = folds_md(pd.DataFrame(rows, columns=["dataset", "fold", "run_id", "kind"]).assign(channel="all"))
    assert md[0] == "## Folds" and "- **d**: fold 1 of 2: a, c; fold 2 of 2: b, d, e" in md
    loro = pd.DataFrame([("d", r, r, "validation") for r in RUNS], columns=["dataset", "fold", "run_id", "kind"])
    assert folds_md(loro) == []  # each fold is named by its one run: nothing to list


def test_declared_is_the_datasets_own_split_and_null_picks_by_the_dataset():
    (f,) = folds(RUNS, ["e"], "declared")
    assert f.name == "e" and f.held_out == ("e",) and f.train == tuple(RUNS[:4])
    assert resolve_cv(None, ["tail"]) == "declared" and resolve_cv(None, []) == "loro"


@pytest.mark.parametrize("call, message", [
    (lambda: resolve_cv("kfold", []), "config key 'cv': expected one of loro, group_kfold, declared or null, got 'kfold'"),
    (lambda: folds(RUNS, [], "declared"), "config key 'cv': declared, but the dataset declares no validation runs"),
    (lambda: folds(RUNS, [], "group_kfold", k=6), "config key 'cv_folds': expected an integer from 2 to the number of runs (5), got 6"),
    (lambda: folds(["a"], [], "loro"), "config key 'cv': loro needs at least 2 runs with readings, the dataset has 1"),
])
def test_mistakes_are_one_line(call, message):
    with pytest.raises(ExperimentError) as exc:
        call()
    assert str(exc.value).startswith(message)


def test_loro_scores_of_least_squares_equal_sklearn_fitted_by_hand(lathe):  # noqa: F811
    """baseline_ols, global, leave-one-run-out on the three days of shape 1: each held-out day's
    RMSE equals LinearRegression fitted on the other two days' rises (computed from the numbers
    written into the workbook) and scored on that day's drift from its first reading."""
    _, dcfg = dataset_option(str(lathe), "datasets")
    out = bm.run_task(dcfg, "baseline_ols", group_option("model", "baseline_ols"), ["global"], None, seed=0,
                      channel="dia", cv="loro")  # fmt: skip
    res = out["results"]
    assert out["cv"] == "loro" and set(res["kind"]) == {"validation"} and not res["own"].any()
    assert list(res["fold"]) == list(res["run_id"]) == ["Day_1", "Day_2", "Day_3"]
    days = {d.replace(" ", "_"): _day(k, n, zero) for k, (d, (n, zero)) in enumerate(DAYS.items())}
    for held in days:
        X = np.vstack([t - t[0] for d, (t, _) in days.items() if d != held])
        y = np.concatenate([u - u[0] for d, (_, u) in days.items() if d != held])
        t, u = days[held]
        pred = LinearRegression().fit(X, y).predict(t - t[0])
        rmse = float(np.sqrt(np.mean((pred - (u - u[0])) ** 2)))
        assert res.set_index("run_id").loc[held, "rmse_um"] == pytest.approx(rmse, rel=1e-9)
    assert out["models"]["global"].train_runs_ == ["Day_1", "Day_2", "Day_3"]  # the model to deploy: every run


# ------------------------------------------------------------ nested choice ---
def _inner(rows):
    import pandas as pd

    return pd.DataFrame([{"dataset": "d", "channel": "all", "fold": fo, "family": f, "approach": a,
                          "inner_fold": ifo, "run_id": r, "rmse_um": v} for fo, f, a, ifo, r, v in rows])  # fmt: skip


def test_the_nested_choice_takes_the_lowest_mean_inner_rmse_of_complete_finite_candidates():
    rows = []
    for fold in ("A", "B"):
        runs = [r for r in ("A", "B", "C") if r != fold]
        for k, r in enumerate(runs):
            rows += [(fold, "lssvm", "global", r, r, 1.0 + k), (fold, "mlp", "global", r, r, 0.5 + 3 * k)]
            rows += [(fold, "gru", "global", r, r, 0.1)] if k == 0 else []  # incomplete: not a candidate
            rows += [(fold, "mlr", "bank", r, r, float("nan") if k else 0.01)]  # non-finite: not a candidate
    choice = bm.nested_choice(_inner(rows))
    # means: lssvm (1, 2) -> 1.5 (standard error 0.5: the bar 2.0), mlp (0.5, 3.5) -> 2.0, at the bar;
    # equally simple (both 3), the lower mean wins
    assert list(zip(choice["fold"], choice["family"], choice["approach"])) == [("A", "lssvm", "global"), ("B", "lssvm", "global")]
    assert list(choice["inner_median_rmse_um"]) == [1.5, 1.5] and list(choice["bar_um"]) == [2.0, 2.0]
    blocked = bm.nested_choice(_inner(rows), blocked=[("d", "lssvm", "global")])
    assert set(blocked["family"]) == {"mlp"}


def test_the_nested_choice_prefers_the_simpler_within_one_standard_error_of_the_lowest():
    """By hand, four inner held-out runs: lssvm 1.0, 1.2, 0.8, 1.0 (mean 1.0, standard error
    sqrt(0.08 / 3) / 2 = 0.0816); linear_history 1.05 everywhere (mean 1.05 <= the bar 1.0816:
    the simpler one is chosen); in a second fold linear_history 1.10 (above the bar: lssvm stays)."""
    rows = []
    for k, (a, b) in enumerate(zip((1.0, 1.2, 0.8, 1.0), (1.05, 1.05, 1.05, 1.05))):
        rows += [("F1", "lssvm", "global", f"i{k}", f"r{k}", a), ("F1", "linear_history", "global", f"i{k}", f"r{k}", b)]
        rows += [("F2", "lssvm", "global", f"i{k}", f"r{k}", a), ("F2", "linear_history", "global", f"i{k}", f"r{k}", 1.10)]
    choice = bm.nested_choice(_inner(rows)).set_index("fold")
    se = np.sqrt(0.08 / 3) / 2
    assert choice.loc["F1", "bar_um"] == pytest.approx(1.0 + se, abs=1e-12)
    assert (choice.loc["F1", "family"], choice.loc["F1", "best_family"]) == ("linear_history", "lssvm")
    assert choice.loc["F2", "family"] == "lssvm"
    assert bm.model_complexity("linear_history", "global") == 1 < bm.model_complexity("physics_spindle", "global") == 2
    assert bm.model_complexity("lssvm", "global") == 3 < bm.model_complexity("lssvm", "bank") == 4
    assert bm.model_complexity("ensemble", "global") == 0 == bm.model_complexity("ridge_history", "global")  # preferred under the bar


def test_inner_folds_never_hold_or_train_on_the_outer_held_out_run(lathe):  # noqa: F811
    _, dcfg = dataset_option(str(lathe), "datasets")
    out = bm.run_task(dcfg, "mlr_seed002", group_option("model", "mlr_seed002"), ["global"], None, seed=0,
                      channel="dia", cv="loro")  # fmt: skip
    inner, every = out["inner"][out["inner"]["fold"] != bm.DEPLOY_FOLD], out["inner"][out["inner"]["fold"] == bm.DEPLOY_FOLD]
    assert set(inner["fold"]) == {"Day_1", "Day_2", "Day_3"}
    # the deployed model's choice: the inner folds over every run, each held out once
    assert sorted(every["run_id"]) == ["Day_1", "Day_2", "Day_3"] and set(every["inner_fold"]) == set(every["run_id"])
    for fold, g in inner.groupby("fold"):
        assert fold not in set(g["run_id"]) and fold not in set(g["inner_fold"])  # what the choice scores on
        assert sorted(g["run_id"]) == sorted({"Day_1", "Day_2", "Day_3"} - {fold})  # each other run once
    base = bm.run_task(dcfg, "baseline_ols", group_option("model", "baseline_ols"), ["global"], None, seed=0,
                       channel="dia", cv="loro")  # fmt: skip
    assert base["inner"].empty  # a baseline is never chosen: no inner folds spent on it


def test_the_held_out_summary_against_a_hand_count():
    import pandas as pd

    rows = []
    for fold, (chosen, ridge, none) in {"r1": (1.0, 2.0, 10.0), "r2": (3.0, 2.5, 12.0), "r3": (1.5, 1.0, 1.2)}.items():
        for fam, v in (("lssvm", chosen), ("baseline_ridge", ridge), ("baseline_ols", ridge + 1)):
            rows.append({"dataset": "d", "channel": "all", "family": fam, "approach": "global", "kind": "validation",
                         "fold": fold, "run_id": fold, "rmse_um": v, "rms_error_um": none})  # fmt: skip
    choice = pd.DataFrame({"case": "d", "fold": ["r1", "r2", "r3"], "family": "lssvm", "approach": "global"})
    (row,) = bm.held_out_summary(pd.DataFrame(rows), choice, ["baseline_ridge", "baseline_ols"]).to_dict("records")
    assert row["folds"] == 3 and row["best_baseline"] == "baseline_ridge (global)"
    assert (row["chosen_median_rmse_um"], row["chosen_worst_rmse_um"]) == (1.5, 3.0)
    assert (row["baseline_median_rmse_um"], row["baseline_worst_rmse_um"]) == (2.0, 2.5)
    assert (row["none_median_rmse_um"], row["none_worst_rmse_um"]) == (10.0, 12.0)
    assert row["beat_best_baseline"] == "1/3" and row["beat_no_compensation"] == "2/3"


def test_a_choice_that_ties_the_best_baseline_by_rounding_does_not_beat_it():
    """ridge_history is baseline_ridge's model in another implementation: their held-out RMSE differ
    by ~1e-12 µm, a tie; "beat" counts a lower RMSE by more than one part in a million only."""
    import pandas as pd

    rows = []
    for fold, (ridge, twin) in {"r1": (2.0, 2.0 - 1e-12), "r2": (2.5, 2.5 * (1 - 1e-4)), "r3": (1.0, 1.0 + 1e-12)}.items():
        for fam, v in (("ridge_history", twin), ("baseline_ridge", ridge)):
            rows.append({"dataset": "d", "channel": "all", "family": fam, "approach": "global", "kind": "validation",
                         "fold": fold, "run_id": fold, "rmse_um": v, "rms_error_um": 2.0})  # fmt: skip
    choice = pd.DataFrame({"case": "d", "fold": ["r1", "r2", "r3"], "family": "ridge_history", "approach": "global"})
    (row,) = bm.held_out_summary(pd.DataFrame(rows), choice, ["baseline_ridge"]).to_dict("records")
    assert row["beat_best_baseline"] == "1/3"  # r2 only: 1e-4 below
    assert row["beat_no_compensation"] == "1/3"  # r1's 2.0 - 1e-12 against 2.0 is a tie; r3's 1.0 is below
    t = bm.held_out_table(pd.DataFrame(rows), choice, ["baseline_ridge"]).set_index("model")
    assert t.loc["ridge_history (global)", "beat_best_baseline"] == "1/3"


def test_held_out_flags_name_worse_than_nothing_and_worse_than_the_best_baseline():
    import pandas as pd

    rows = []
    for fold, (lssvm, ridge, mlp, none) in {"r1": (1.0, 2.0, 0.5, 10.0), "r2": (13.0, 2.5, 1.0, 12.0),
                                            "r3": (3.5, 1.0, 0.9, 5.0)}.items():  # fmt: skip
        for fam, v in (("lssvm", lssvm), ("baseline_ridge", ridge), ("mlp", mlp)):
            rows.append({"dataset": "d", "channel": "all", "family": fam, "approach": "global", "kind": "validation",
                         "fold": fold, "run_id": fold, "rmse_um": v, "rms_error_um": none})  # fmt: skip
    lines = bm.held_out_flags(pd.DataFrame(rows), ["baseline_ridge"])
    # lssvm: 13 > 12 on r2; median 3.5 > the ridge's 2.0. mlp: never worse than either.
    assert lines == ["d/lssvm/global: worse than no compensation on held-out run(s) ['r2']",
                     "d/lssvm/global: median held-out RMSE 3.50 µm, worse than the best baseline baseline_ridge (global) 2.00 µm"]


def test_the_held_out_table_against_a_hand_count(tmp_path):
    """The report's held-out section: one row for the nested choice, one per family and approach, one
    for no compensation, each counted by hand; and write_report puts it in report.md."""
    import pandas as pd

    from thermbench.report import write_report

    rows = []
    for fold, (lssvm, ridge, ols, none) in {"r1": (1.0, 2.0, 3.0, 10.0), "r2": (3.0, 2.5, 3.5, 12.0),
                                            "r3": (1.5, 1.0, 2.0, 1.2)}.items():  # fmt: skip
        for fam, v in (("lssvm", lssvm), ("mlp", lssvm + 0.25), ("baseline_ridge", ridge), ("baseline_ols", ols)):
            rows.append({"dataset": "d", "channel": "all", "family": fam, "approach": "global", "kind": "validation",
                         "fold": fold, "run_id": fold, "train": "all", "own": False, "rmse_um": v, "rms_error_um": none,
                         "compensation_rate": 0.5, "max_abs_residual_um": 2 * v})  # fmt: skip
    # the choice: lssvm in r1 and r3, mlp in r2 (3.25)
    choice = pd.DataFrame({"case": "d", "fold": ["r1", "r2", "r3"], "family": ["lssvm", "mlp", "lssvm"],
                           "approach": "global"})  # fmt: skip
    t = bm.held_out_table(pd.DataFrame(rows), choice, ["baseline_ridge", "baseline_ols"]).set_index("model")
    assert list(t.index) == ["thermbench's choice (nested)", "lssvm (global)", "mlp (global)",
                             "baseline_ridge (global) (baseline), the best baseline", "baseline_ols (global) (baseline)",
                             "no compensation"]  # fmt: skip
    c = t.loc["thermbench's choice (nested)"]  # 1.0, 3.25, 1.5
    assert (c["folds"], c["median_rmse_um"], c["worst_rmse_um"]) == (3, 1.5, 3.25)
    assert (c["beat_no_compensation"], c["beat_best_baseline"]) == ("2/3", "1/3")  # 1.5 > 1.2 on r3; only r1 < ridge
    m = t.loc["mlp (global)"]  # 1.25, 3.25, 1.75
    assert (m["median_rmse_um"], m["beat_no_compensation"], m["beat_best_baseline"]) == (1.75, "2/3", "1/3")
    assert t.loc["baseline_ridge (global) (baseline), the best baseline", "beat_best_baseline"] == "-"
    assert t.loc["baseline_ols (global) (baseline)", "beat_best_baseline"] == "0/3"
    n = t.loc["no compensation"]
    assert (n["median_rmse_um"], n["worst_rmse_um"], n["beat_no_compensation"]) == (10.0, 12.0, "-")
    md = write_report(pd.DataFrame(rows), None, tmp_path / "rep", reference=["baseline_ridge", "baseline_ols"],
                      held_out=bm.held_out_table(pd.DataFrame(rows), choice, ["baseline_ridge", "baseline_ols"])).read_text()
    section = md[md.index("## Held out"):md.index("## The run")]
    lines = [[c.strip() for c in ln.strip("|").split("|")] for ln in section.splitlines() if ln.startswith("|")]
    assert lines[0] == ["model", "folds", "median RMSE µm", "worst RMSE µm", "beat no compensation",
                        "beat the best baseline"]  # fmt: skip
    assert lines[2] == ["thermbench's choice (nested)", "3", "1.50", "3.25", "2/3", "1/3"]


def test_a_dataset_with_nothing_to_classify_skips_the_banks_in_one_line(lathe, tmp_path, capsys):  # noqa: F811
    from tests.test_benchmark import _cfg

    skipped = []
    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[baseline_ols,mlr_seed002]", "bank_families=[mlr_seed002]")
    todo = bm.tasks(cfg, skipped)
    assert all(t["approaches"] == ["single", "global"] for t in todo)
    assert all(t["dataset_cfg"]["name"] == "lathe_d" for t in todo)  # named by its machine
    assert skipped == [f"bank, bank_soft on {lathe}: the bank's runs declare no condition and the dataset no operating "
                       "input (metadata 'operating'): nothing to classify"]  # fmt: skip
    assert capsys.readouterr().err.count("skipped bank, bank_soft") == 1


def test_runs_regressor_is_a_scikit_learn_estimator_over_whole_runs(lathe):  # noqa: F811
    """The thin adapter: clone keeps the dataset by reference; scikit-learn's
    cross_val_predict with LeaveOneGroupOut gives, per held-out run, the RMSE thermbench's own
    scoring (metrics.evaluate) gives for a fit on the other runs; GridSearchCV over a model
    parameter picks the value of smaller held-out RMSE, as the hand loop does."""
    from sklearn.base import clone
    from sklearn.model_selection import GridSearchCV, LeaveOneGroupOut, cross_val_predict

    from thermbench.experiment import build_model, load_split
    from thermbench.bench.metrics import evaluate
    from thermbench.bench.splits import DatasetRef, RunsRegressor, run_rows

    ds = load_split(dataset_option(str(lathe), "datasets")[1]).dataset
    model = build_model(group_option("model", "baseline_ols"), seed=0)
    est = RunsRegressor(model, DatasetRef(ds))
    twin = clone(est)
    assert twin.dataset is est.dataset and twin.model is not est.model and twin.get_params()["model"] is not None
    runs = list(ds.run_ids)
    X, y, groups = run_rows(ds, runs)
    pred = cross_val_predict(est, X, y, groups=groups, cv=LeaveOneGroupOut())
    for r in runs:
        m = groups == r
        by_hand = evaluate(clone(model).fit(ds, [o for o in runs if o != r]), ds, [r])["rmse_um"].iloc[0]
        assert np.sqrt(np.mean((y[m] - pred[m]) ** 2)) == pytest.approx(by_hand, rel=1e-12)

    def loro_rmse(lags):
        m = clone(model).set_params(lags_s=lags)
        return np.mean([evaluate(clone(m).fit(ds, [o for o in runs if o != r]), ds, [r])["rmse_um"].iloc[0]
                        for r in runs])  # fmt: skip

    search = GridSearchCV(est, {"model__lags_s": [[], [600]]}, cv=LeaveOneGroupOut(),
                          scoring="neg_root_mean_squared_error").fit(X, y, groups=groups)  # fmt: skip
    hand = {str(lags): loro_rmse(lags) for lags in ([], [600])}
    assert -search.cv_results_["mean_test_score"] == pytest.approx([hand["[]"], hand["[600]"]], rel=1e-12)
    assert str(search.best_params_["model__lags_s"]) == min(hand, key=hand.get)
