"""The linear-with-history family (thermbench/models/linear_history.py) and its C kind LINEAR_HISTORY.

Checked against what is known independently: the delay line against the exact delayed value of a
linear input and a hand computation; the fitted family against an error planted as a delayed rise
(the continuous function, not the delay line); the C runtime (a second implementation of the line
and the weights) against Python at every reading in both precisions, on a log whose sample times are
irregular and off the line's grid."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.base import clone

from tests.synth import rise
from tests.test_lumped import spindle_dataset
from thermbench.bench.metrics import evaluate
from thermbench.models.base import ModelError
from thermbench.models.linear_history import LinearHistory, delay_line

NOISE_UM = 0.05
DELAY_TRUE_S = 1800.0
SPECS = [(4.0, 600, 12000, 2.0, 3000, 15000), (6.0, 1800, 9000, 1.0, 600, 20000), (3.0, 300, 18000, 3.0, 6000, 10000),
         (5.0, 3600, 14000, 2.5, 1200, 8000), (2.0, 900, 20000, 1.5, 2400, 16000)]  # fmt: skip
SENSORS = {"T_a": "spindle", "T_b": "structure", "T_c": "ambient"}


def test_the_delay_line_gives_a_linear_input_exactly_delayed_on_an_irregular_log():
    rng = np.random.default_rng(1)
    t = 100.0 + np.cumsum(rng.uniform(5.0, 25.0, 400))  # irregular, off any 60 s grid
    u = 3.0 + 0.002 * (t - t[0])
    out = delay_line(t, u, [0.0, 60.0, 900.0], 60.0)
    assert np.array_equal(out[:, 0], u)  # a delay of 0: the input itself
    for k, d in ((1, 60.0), (2, 900.0)):
        late = t - d >= t[0]
        np.testing.assert_allclose(out[late, k], 3.0 + 0.002 * (t[late] - d - t[0]), rtol=0, atol=1e-12)
        assert np.all(out[~late, k] == 3.0)  # before the first sample: its value


def test_the_delay_line_by_hand():
    # samples at 0, 7, 15, 30 s of 0, 7, 23, 8; a line of 10 s holds v(0) = 0, v(10) = 7 + 3/8 * 16 = 13,
    # v(20) = 23 - 5/15 * 15 = 18, v(30) = 8; 10 s earlier at 30 s: v(20) = 18; at 15 s: 5 s, 0.5 x 13 = 6.5
    t, u = np.array([0.0, 7.0, 15.0, 30.0]), np.array([0.0, 7.0, 23.0, 8.0])
    out = delay_line(t, u, [10.0], 10.0)[:, 0]
    np.testing.assert_allclose(out, [0.0, 0.0, 6.5, 18.0], atol=1e-12)


def _runs(specs, seed=0):
    """Spindle runs on an irregular 10-20 s log: the error = 2.0 x the rise of T_a 30 min earlier
    (the continuous function) + 1.0 x the rise of T_b now + noise; T_c wanders and plays no part."""
    rng = np.random.default_rng(seed)
    runs = {}
    for k, (amp_a, on_a, off_a, amp_b, on_b, off_b) in enumerate(specs):
        t = np.concatenate([[0.0], np.cumsum(rng.uniform(10.0, 20.0, 1500))])
        t = t[t <= 6 * 3600.0]
        ta, tb = rise(t, amp_a, 1200.0, on_a, off_a), rise(t, amp_b, 900.0, on_b, off_b)
        tc = 0.8 * np.sin(t / 5000.0 + k) + 0.02 * rng.standard_normal(t.size)
        err = 2.0 * rise(t - DELAY_TRUE_S, amp_a, 1200.0, on_a, off_a) + tb + NOISE_UM * rng.standard_normal(t.size)
        runs[f"r{k}"] = {"t_s": t, "spindle_rpm": np.full(t.size, 1000.0 * (k + 1)), "read_t_s": t, "error_um": err,
                         "T_a_C": 20 + ta, "T_b_C": 21 + tb, "T_c_C": 20.5 + tc - tc[0]}  # fmt: skip
    return runs


@pytest.fixture(scope="module")
def planted():
    return spindle_dataset(_runs(SPECS), sensors=SENSORS, operating=["spindle_rpm"])


def test_it_finds_the_planted_delay_and_reaches_the_noise_floor_where_the_rises_now_do_not(planted):
    m = LinearHistory().fit(planted, ["r0", "r1", "r2", "r3"])
    assert DELAY_TRUE_S in m.delays_s_ and m.inputs_ == ["T_a", "T_b", "T_c"]  # every sensor, no selection
    rmse = evaluate(m, planted, ["r4"])["rmse_um"].iloc[0]
    now_only = LinearHistory(delays_s=[[0.0]]).fit(planted, ["r0", "r1", "r2", "r3"])
    rmse_now = evaluate(now_only, planted, ["r4"])["rmse_um"].iloc[0]
    assert rmse < 3 * NOISE_UM < rmse_now / 5
    # its own cross-validation chose the set and penalty of the lowest held-out RMSE it measured
    best = min(m.cv_results_, key=lambda r: r["cv_rmse_um"])
    assert (best["delays_s"], best["alpha"], best["cv_rmse_um"]) == (m.delays_s_, m.alpha_, m.cv_rmse_um_)
    line = m.fit_summary()
    later = [round(d) for d in m.delays_s_ if d > 0]
    assert 1800 in later and line.startswith(f"every input (3) now and {later} s earlier (a delay line of 60 s)")


def test_it_is_a_scikit_learn_estimator_and_refuses_a_step_longer_than_a_delay(planted):
    m = LinearHistory(delays_s=[[0.0, 600.0]], delay_step_s=30.0)
    c = clone(m)
    assert c.get_params() == m.get_params() and set(c.get_params()) == {
        "sensors", "operating", "delays_s", "delay_step_s", "alphas", "estimator", "components", "cv"}  # fmt: skip
    with pytest.raises(ModelError, match=r"LinearHistory.delay_step_s: 900 s is longer than the shortest delay 600 s"):
        LinearHistory(delays_s=[[0.0, 600.0]], delay_step_s=900.0).fit(planted, ["r0", "r1"])
    with pytest.raises(ModelError, match=r"LinearHistory.delays_s"):
        LinearHistory(delays_s=[[0.0, -60.0]]).fit(planted, ["r0", "r1"])
    with pytest.raises(ModelError, match=r"LinearHistory.cv: gcv is ridge's leave-one-reading-out error"):
        LinearHistory(estimator="pls", cv="gcv").fit(planted, ["r0", "r1"])
    with pytest.raises(ModelError, match=r"LinearHistory.estimator"):
        LinearHistory(estimator="lasso").fit(planted, ["r0", "r1"])


def _design(m, ds, runs):
    from thermbench.models.base import readings

    rd = readings(ds, runs)
    X = np.vstack([m._features(ds, r, m.inputs_, m.delays_s_, g["t_s"].to_numpy(), g["target_mm"].to_numpy())
                   for r, g in rd.groupby("run_id", sort=False)])  # fmt: skip
    return X, rd["error_um"].to_numpy(dtype=float), rd["run_id"].to_numpy()


def test_pls_predicts_as_scikit_learns_own_pipeline_and_its_components_are_chosen_over_whole_runs(planted):
    """The PLS fit is read back as weights on standardised features (so it exports as any linear map):
    its predictions are those of scikit-learn's StandardScaler + PLSRegression, and the number of
    components is the one of lowest RMSE over leave-one-run-out folds, computed here by hand."""
    from sklearn.cross_decomposition import PLSRegression
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    train = ["r0", "r1", "r2", "r3"]
    m = LinearHistory(estimator="pls", delays_s=[[0.0, 1800.0]], components=[1, 2, 3, 6, 50]).fit(planted, train)
    X, y, run_of = _design(m, planted, train)
    by_hand = {}
    for k in (1, 2, 3, 6):  # 50 is more than the 6 features: dropped
        sse = 0.0
        for r in train:
            pipe = make_pipeline(StandardScaler(), PLSRegression(k, scale=False)).fit(X[run_of != r], y[run_of != r])
            sse_r = np.sum((np.ravel(pipe.predict(X[run_of == r])) - y[run_of == r]) ** 2)
            by_hand[k] = by_hand.get(k, []) + [sse_r / np.sum(run_of == r)]
    rmse = {k: float(np.sqrt(np.mean(v))) for k, v in by_hand.items()}
    assert m.n_components_ == min(rmse, key=rmse.get) and m.cv_rmse_um_ == pytest.approx(min(rmse.values()), rel=1e-9)
    assert sorted(r["n_components"] for r in m.cv_results_) == [1, 2, 3, 6] and m.alpha_ is None
    pipe = make_pipeline(StandardScaler(), PLSRegression(m.n_components_, scale=False)).fit(X, y)
    Xh, yh, _ = _design(m, planted, ["r4"])
    np.testing.assert_allclose(m.predict(planted, "r4"), np.ravel(pipe.predict(Xh)), atol=1e-9)
    assert evaluate(m, planted, ["r4"])["rmse_um"].iloc[0] < 3 * NOISE_UM  # the planted delay: within the noise
    assert "PLS with" in m.fit_summary()


def test_gcv_chooses_the_penalty_of_lowest_leave_one_reading_out_error_computed_by_the_hat_matrix(planted):
    """cv="gcv" (baseline_ridge's choice, made deployable): the penalty of lowest leave-one-reading-out
    error, that error computed here from the hat matrix of the ridge with an unpenalised intercept
    (r_i / (1 - h_ii)), not by scikit-learn."""
    train = ["r0", "r1", "r2"]
    alphas = [0.01, 1.0, 100.0]
    m = LinearHistory(cv="gcv", delays_s=[[0.0, 1800.0]], alphas=alphas).fit(planted, train)
    X, y, _ = _design(m, planted, train)
    Z = (X - X.mean(axis=0)) / X.std(axis=0)
    A = np.hstack([np.ones((y.size, 1)), Z])
    loo = {}
    for a in alphas:
        P = np.diag([0.0] + [a] * Z.shape[1])
        H = A @ np.linalg.solve(A.T @ A + P, A.T)
        r = y - H @ y
        loo[a] = float(np.sqrt(np.mean((r / (1.0 - np.diag(H))) ** 2)))
    assert m.alpha_ == min(loo, key=loo.get) and m.cv_rmse_um_ == pytest.approx(min(loo.values()), rel=1e-6)
    assert "leave-one-reading-out (GCV) RMSE" in m.fit_summary()


def test_ridge_history_is_the_ridge_baseline_made_deployable_on_a_log_at_the_delay_lines_step():
    """conf/model/ridge_history.yaml against conf/model/baseline_ridge.yaml (a scikit-learn StandardScaler +
    RidgeCV pipeline on the rises now and 30 min earlier, a second implementation): on a log sampled at
    the delay line's 60 s the line holds every sample, so the two are one model, penalty and predictions;
    it is the reference of the choice (complexity 0) and the C runtime's LINEAR_HISTORY kind."""
    from thermbench.config import group_option
    from thermbench.experiment import build_model
    from thermbench.export.encoding import family_encoder
    from thermbench.models.linear_history import RidgeHistory

    runs = _runs(SPECS)
    for r in runs.values():  # the same runs, logged every 60 s
        t = np.arange(0.0, 6 * 3600.0, 60.0)
        for k in [k for k in r if k != "t_s" and k != "read_t_s"]:
            r[k] = np.interp(t, r["t_s"], r[k])
        r["t_s"] = r["read_t_s"] = t
    ds = spindle_dataset(runs, sensors=SENSORS, operating=["spindle_rpm"])
    train = ["r0", "r1", "r2", "r3"]
    opt = group_option("model", "ridge_history")
    # the baseline's 13 penalties np.logspace(-3, 3, 13), written to 3 digits in the yaml; exact here
    np.testing.assert_allclose(opt["alphas"], np.logspace(-3, 3, 13), rtol=2e-3)
    twin = build_model(opt | {"alphas": list(np.logspace(-3, 3, 13))}, seed=0).fit(ds, train)
    ref = build_model(group_option("model", "baseline_ridge"), seed=0).fit(ds, train)
    assert isinstance(twin, RidgeHistory) and list(twin.delays_s_) == [0.0, 1800.0] and twin.inputs_ == ["T_a", "T_b", "T_c"]
    assert twin.alpha_ == pytest.approx(ref.estimator_[-1].alpha_, rel=1e-12)
    np.testing.assert_allclose(twin.predict(ds, "r4"), ref.predict(ds, "r4"), atol=1e-6)
    assert RidgeHistory.complexity == 0 < LinearHistory.complexity and not getattr(twin, "reference_only", False)
    assert family_encoder(RidgeHistory) is family_encoder(LinearHistory) and twin.export_encoding.__func__ is \
        LinearHistory.export_encoding


@pytest.mark.parametrize("operating", [[], ["spindle_rpm"]])
def test_the_c_runtime_kind_reproduces_python_in_both_precisions(planted, operating, tmp_path):
    """LINEAR_HISTORY (embedded/src/tb_kind_linear_history.c): the export's parity check replays the
    held-out run through the C runtime; double to 1e-9 µm, float within 0.01 µm, at every reading."""
    from thermbench.export import export_model

    m = LinearHistory(operating=operating).fit(planted, ["r0", "r1", "r2", "r3"])
    man = export_model(m, tmp_path / "lh", "lh", ds=planted, heldout=["r4"])
    p = man["parity"]["model"]
    assert man["kind"] == "LINEAR_HISTORY" and p["n_readings"] > 1000
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01
    assert p["heldout_rmse_um_c"] == pytest.approx(evaluate(m, planted, ["r4"])["rmse_um"].iloc[0], abs=1e-9)
    assert man["operating"] == operating
