"""The baselines (thermbench/models/baseline.py): what a user fits instead, checked against hand
computations and against scikit-learn run directly on the shipped workbook."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from sklearn.base import clone
from sklearn.ensemble import RandomForestRegressor
from sklearn.linear_model import LinearRegression

from tests.test_history import two_blocks
from thermbench.experiment import build_model, dataset_view, group_option, load_split
from thermbench.models.base import ModelError
from thermbench.models.baseline import SensorRegressor

WORKBOOK = Path(__file__).resolve().parents[1] / "thermbench/realdata/fl_thermal/data.xlsx"
TAIL_START_S = 144465.0  # SOURCE.md: the stepped duty cycle
FIRST_BLOCK_S = 465.0


def test_constructor_stores_parameters_and_clone_works():
    m = SensorRegressor(estimator=LinearRegression(), sensors=["a"], seed=3)
    assert m.get_params()["sensors"] == ["a"] and m.get_params()["seed"] == 3
    assert clone(m).get_params()["seed"] == 3
    assert SensorRegressor.reference_only  # the benchmark never deploys a baseline


def test_bad_parameters_are_one_line(tmp_path):
    hist = dataset_view(two_blocks(tmp_path), "Z", segments=True, history=True)
    with pytest.raises(ModelError, match=r"^SensorRegressor\.estimator: expected a scikit-learn regressor \(or a pipeline ending in one\), got None$"):
        SensorRegressor().fit(hist, ["low"])
    with pytest.raises(ModelError, match=r"^SensorRegressor\.sensors: expected None or a non-empty list of sensor names, got 'T_front'$"):
        SensorRegressor(estimator=LinearRegression(), sensors="T_front").fit(hist, ["low"])


def test_seeded_forest_repeats_and_the_seed_matters(tmp_path):
    hist = dataset_view(two_blocks(tmp_path), "Z", segments=True, history=True)
    rf = SensorRegressor(estimator=RandomForestRegressor(n_estimators=5, max_features=1, bootstrap=True))
    a = clone(rf).set_params(seed=1).fit(hist, ["low"]).predict(hist, "high")
    b = clone(rf).set_params(seed=1).fit(hist, ["low"]).predict(hist, "high")
    np.testing.assert_array_equal(a, b)
    # build_model hands the top-level seed to the forest's random_state
    m = build_model(group_option("model", "baseline_rf"), seed=7)
    assert m.get_params()["seed"] == 7


def test_ols_on_all_sixteen_reproduces_sklearn_on_the_workbook():
    """``baseline_ols`` trained on the five constant-speed blocks of the measured spindle test
    (history view: rises and drift from the first row of the test) against scikit-learn run
    directly on the workbook's columns, the same rows: a second implementation of the whole
    chain (import, channel view, segments, references, features). The source README's quick
    reference (train on everything before 144 465 s, which adds the 465 s at rest before the
    first block) is 6.3 / 4.5 / 5.7 / 5.9 / 8.8 µm."""
    df = pd.read_excel(WORKBOOK)
    df.columns = ["t", "rpm", *[f"ch{i}" for i in range(1, 6)], *[f"t{i}" for i in range(1, 17)]]
    temps = df[[f"t{i}" for i in range(1, 17)]].to_numpy()
    X = temps - temps[0]
    t = df["t"].to_numpy()
    train = (t >= FIRST_BLOCK_S) & (t < TAIL_START_S)
    tail = t >= TAIL_START_S
    readme = {"ch1": 6.3, "ch2": 4.5, "ch3": 5.7, "ch4": 5.9, "ch5": 8.8}
    model = build_model(group_option("model", "baseline_ols"), seed=0)
    for ch in ["ch1", "ch3", "ch5"]:
        y = df[ch].to_numpy() - df[ch].iloc[0]
        direct = LinearRegression().fit(X[train], y[train]).predict(X[tail])
        rmse_direct = float(np.sqrt(np.mean((direct - y[tail]) ** 2)))
        split = load_split({**group_option("dataset", "fl_thermal"), "channel": ch})
        fitted = clone(model).fit(split.dataset, split.states)
        er = split.dataset.errors_run("tail")
        assert er["t_s"].min() == TAIL_START_S
        pred = fitted.predict(split.dataset, "tail")
        rmse = float(np.sqrt(np.mean((pred - er["error_um"].to_numpy()) ** 2)))
        assert rmse == pytest.approx(rmse_direct, abs=1e-6)
        assert abs(rmse - readme[ch]) < 0.25


def _ridge_by_hand(X: np.ndarray, y: np.ndarray, train: np.ndarray, test: np.ndarray) -> float:
    """The ten-line ridge baseline: standardised features, RidgeCV over 13 alphas 1e-3..1e3; held-out RMSE."""
    from sklearn.linear_model import RidgeCV
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    m = make_pipeline(StandardScaler(), RidgeCV(alphas=np.logspace(-3, 3, 13))).fit(X[train], y[train])
    return float(np.sqrt(np.mean((m.predict(X[test]) - y[test]) ** 2)))


def test_ridge_with_a_30_min_lag_reproduces_the_independent_figures_on_the_workbook():
    """``baseline_ridge``: the rises of the sixteen sensors and the same rises 30 min earlier (0 before
    the test's first 30 min), ridge over 13 alphas. Measured independently on the tail
    (train on everything before 144 465 s, rises from the first row): 2.38 / 1.92 / 1.73 / 1.78 /
    2.32 µm. The family, trained on the five constant-speed blocks (from 465 s), must equal the ten
    lines run directly on the workbook's columns over the same rows, and stay near those figures."""
    df = pd.read_excel(WORKBOOK)
    df.columns = ["t", "rpm", *[f"ch{i}" for i in range(1, 6)], *[f"t{i}" for i in range(1, 17)]]
    t = df["t"].to_numpy(dtype=float)
    temps = df[[f"t{i}" for i in range(1, 17)]].to_numpy()
    rise = temps - temps[0]
    step = int(round(1800.0 / np.median(np.diff(t))))  # 120 rows of 15 s
    earlier = np.vstack([np.zeros((step, 16)), rise[:-step]])
    X = np.hstack([rise, earlier])
    tail = t >= TAIL_START_S
    issue = {"ch1": 2.38, "ch2": 1.92, "ch3": 1.73, "ch4": 1.78, "ch5": 2.32}
    model = build_model(group_option("model", "baseline_ridge"), seed=0)
    for ch, figure in issue.items():
        y = df[ch].to_numpy() - df[ch].iloc[0]
        assert _ridge_by_hand(X, y, ~tail, tail) == pytest.approx(figure, abs=0.005)  # the ten lines reproduce the independent figures
        split = load_split({**group_option("dataset", "fl_thermal"), "channel": ch})
        fitted = clone(model).fit(split.dataset, split.states)
        er = split.dataset.errors_run("tail")
        rmse = float(np.sqrt(np.mean((fitted.predict(split.dataset, "tail") - er["error_um"].to_numpy()) ** 2)))
        assert rmse == pytest.approx(_ridge_by_hand(X, y, (t >= FIRST_BLOCK_S) & ~tail, tail), abs=1e-6)
        assert abs(rmse - figure) < 0.1


def test_lagged_rises_are_the_rises_that_much_earlier_and_zero_before_the_run(tmp_path):
    hist = dataset_view(two_blocks(tmp_path), "Z", segments=True, history=True)
    m = SensorRegressor(estimator=LinearRegression(), lags_s=[600.0]).fit(hist, ["low"])
    run = "high"
    pr = hist.process_run(run)
    t = pr["t_s"].to_numpy()
    F = m._features(hist, run, t, np.zeros(t.size))
    n = len(m.sensors_)
    T = pr[[hist.metadata.sensor_column(s) for s in m.sensors_]].to_numpy()
    rise = T - T[0]
    np.testing.assert_allclose(F[:, :n], rise)
    for k in range(t.size):  # by hand: the rise at t - 600 s, 0 before the run's first sample
        back = t[k] - 600.0
        want = np.zeros(n) if back <= t[0] else np.array([np.interp(back, t, rise[:, j]) for j in range(n)])
        np.testing.assert_allclose(F[k, n:], want, atol=1e-12)
    with pytest.raises(ModelError, match=r"^SensorRegressor\.lags_s: expected a list of lags in seconds, each > 0"):
        SensorRegressor(estimator=LinearRegression(), lags_s=[0.0]).fit(hist, ["low"])
    with pytest.raises(ModelError, match=r"^SensorRegressor\.estimator: expected a scikit-learn regressor"):
        SensorRegressor(estimator=object()).fit(hist, ["low"])
