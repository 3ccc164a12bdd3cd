"""The thermal-lag family: exact first-order lags, inputs chosen as groups and the time
constants and penalty chosen by cross-validation over whole runs, checked against a planted lagged
truth computed by an ODE solver (a second implementation of the lag)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from tests.synth import rise
from tests.test_lumped import spindle_dataset
from thermbench.bench.metrics import evaluate
from thermbench.models.base import ModelError
from thermbench.models.thermal_lag import ThermalLag, first_order_lag

DT_S = 60.0
TAU_TRUE_S = 3600.0
NOISE_UM = 0.05


def test_first_order_lag_of_a_step_is_the_exponential_on_regular_and_irregular_logs():
    tau = 900.0
    t = np.arange(0.0, 7200.0 + 1, 60.0)
    u = np.ones_like(t)  # on from the first interval: y(t) = 1 - exp(-t / tau)
    np.testing.assert_allclose(first_order_lag(t, u, tau), 1 - np.exp(-t / tau), atol=1e-12)
    ti = np.cumsum(np.r_[0.0, np.random.default_rng(0).uniform(10, 120, 80)])
    np.testing.assert_allclose(first_order_lag(ti, np.ones_like(ti), tau), 1 - np.exp(-ti / tau), atol=1e-12)
    np.testing.assert_array_equal(first_order_lag(t, u, 0.0), u)


def _lag_ode(t_s: np.ndarray, f, tau_s: float) -> np.ndarray:
    """y' = (f(t) - y) / tau from y(0) = 0, by scipy's ODE solver on the continuous input."""
    sol = solve_ivp(lambda t, y: (f(t) - y) / tau_s, (0.0, float(t_s[-1])), [0.0], t_eval=t_s, rtol=1e-10, atol=1e-12,
                    max_step=30.0)  # fmt: skip
    return sol.y[0]


def _runs(specs, seed=0):
    """Runs of a spindle test: T_a and T_b heat and cool (different timings per run), T_c wanders;
    the error = 2.0 x lag_3600(rise of T_a) + 1.0 x rise of T_b + noise (T_c plays no part)."""
    rng = np.random.default_rng(seed)
    runs = {}
    for k, (amp_a, on_a, off_a, amp_b, on_b, off_b) in enumerate(specs):
        t = np.arange(0.0, 6 * 3600.0 + 1, DT_S)

        def fa(tt, amp_a=amp_a, on_a=on_a, off_a=off_a):
            return rise(tt, amp_a, 1200.0, on_a, off_a)

        ta, tb = fa(t), rise(t, amp_b, 900.0, on_b, off_b)
        tc = 0.8 * np.sin(t / 5000.0 + k) + 0.02 * rng.standard_normal(t.size)
        err = 2.0 * _lag_ode(t, fa, TAU_TRUE_S) + 1.0 * tb + NOISE_UM * rng.standard_normal(t.size)
        runs[f"r{k}"] = {"t_s": t, "spindle_rpm": np.full(t.size, 1000.0 * (k + 1)), "read_t_s": t, "error_um": err,
                         "T_a_C": 20 + ta, "T_b_C": 21 + tb, "T_c_C": 20.5 + tc - tc[0]}  # fmt: skip
    return runs


SPECS = [(4.0, 600, 12000, 2.0, 3000, 15000), (6.0, 1800, 9000, 1.0, 600, 20000), (3.0, 300, 18000, 3.0, 6000, 10000),
         (5.0, 3600, 14000, 2.5, 1200, 8000), (2.0, 900, 20000, 1.5, 2400, 16000)]  # fmt: skip
SENSORS = {"T_a": "spindle", "T_b": "structure", "T_c": "ambient"}


@pytest.fixture(scope="module")
def planted():
    return spindle_dataset(_runs(SPECS), sensors=SENSORS, operating=[])


def test_it_recovers_the_planted_inputs_and_time_constant_and_reaches_the_noise_floor(planted):
    train, held = ["r0", "r1", "r2", "r3"], "r4"
    m = ThermalLag(taus_s=[[0.0], [0.0, 1800.0], [0.0, 3600.0], [0.0, 900.0, 3600.0, 14400.0]]).fit(planted, train)
    assert sorted(m.inputs_) == ["T_a", "T_b"]  # T_c (no part in the error) never enters
    assert 3600.0 in m.taus_s_  # the planted time constant
    assert [s for s, _ in m.selection_][0] == "(none)"  # the path; the model kept is one visited on it
    assert min(abs(v - m.cv_rmse_um_) for _, v in m.selection_) < 1e-12
    rmse = evaluate(m, planted, [held])["rmse_um"].iloc[0]
    assert rmse < 1.5 * NOISE_UM  # the noise floor on a run it never saw
    assert m.required_inputs().sensors == tuple(m.inputs_)


def test_its_validation_folds_hold_whole_runs_out():
    """splits.row_folds, what thermal_lag (and the lumped network's selection) tunes on: each fold
    holds out whole runs and trains on the others only; a single run: contiguous blocks."""
    from thermbench.bench.splits import row_folds

    runs = np.repeat(["a", "b", "c"], 4)
    folds = row_folds(runs)
    assert len(folds) == 3
    for tr, te in folds:  # each fold holds out one whole run and trains on the other two only
        assert len(set(runs[te])) == 1 and not set(runs[te]) & set(runs[tr])
    one = row_folds(np.array(["a"] * 10))  # one run: 5 contiguous blocks
    assert [list(te) for _, te in one] == [[0, 1], [2, 3], [4, 5], [6, 7], [8, 9]]


def test_mistakes_are_one_line(planted):
    with pytest.raises(ModelError, match=r"sensors: \['T_x'\] are not sensors of the dataset"):
        ThermalLag(sensors=["T_x"]).fit(planted, ["r0", "r1"])
    with pytest.raises(ModelError, match="taus_s"):
        ThermalLag(taus_s=[[-1.0]]).fit(planted, ["r0", "r1"])
    with pytest.raises(ModelError, match="operating: column 'feed' is not in the process log"):
        ThermalLag(operating=["feed"]).fit(planted, ["r0", "r1"])


def test_the_fold_ridge_equals_scikit_learn_standardised_on_the_training_rows():
    """_FoldGram's held-out error for any subset of columns and any penalty: scikit-learn's
    StandardScaler (fitted on the fold's training rows) + Ridge, predicting the held-out rows."""
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    from thermbench.models.thermal_lag import _FoldGram

    rng = np.random.default_rng(3)
    X = rng.standard_normal((60, 5)) * [1.0, 10.0, 0.1, 3.0, 1.0] + [0.0, 5.0, -2.0, 0.0, 1.0]
    y = X @ [1.0, 0.2, -3.0, 0.0, 0.5] + 0.3 * rng.standard_normal(60)
    train, test = np.arange(40), np.arange(40, 60)
    g = _FoldGram(X, y, train, test)
    cols, alphas = np.array([0, 2, 3]), [0.01, 1.0, 30.0]
    for a, sse in zip(alphas, g.sse(cols, alphas)):
        pipe = make_pipeline(StandardScaler(), Ridge(alpha=a)).fit(X[np.ix_(train, cols)], y[train])
        assert sse == pytest.approx(float(np.sum((pipe.predict(X[np.ix_(test, cols)]) - y[test]) ** 2)), rel=1e-9)
    assert g.sse(np.array([], dtype=int), [1.0])[0] == pytest.approx(float(np.sum((y[test] - y[train].mean()) ** 2)))


def test_the_gaussian_process_on_the_lags_predicts_and_knows_its_noise(planted):
    """gp: the planted truth on a run it never saw near the noise floor; its predictive standard
    deviation is about the planted noise where the inputs are inside the training range."""
    from thermbench.models.gp import GaussianProcessLag

    m = GaussianProcessLag(max_samples=300, seed=0).fit(planted, ["r0", "r1", "r2", "r3"])
    assert sorted(m.lag_.inputs_) == ["T_a", "T_b"]
    assert evaluate(m, planted, ["r4"])["rmse_um"].iloc[0] < 2.0 * NOISE_UM
    er = planted.errors_run("r4")
    std = m.predict_std(planted, "r4", er["t_s"].to_numpy(), er["target_mm"].to_numpy())
    assert std.shape == (len(er),) and 0.5 * NOISE_UM < float(np.median(std)) < 3 * NOISE_UM
    again = GaussianProcessLag(max_samples=300, seed=0).fit(planted, ["r0", "r1", "r2", "r3"])
    np.testing.assert_array_equal(again.predict(planted, "r4"), m.predict(planted, "r4"))  # seeded
    # a noise bound above the planted noise (its variance is far below 1e-2 of the error's, in the
    # standardised units of normalize_y): the white-noise level ends at that bound; scikit-learn's
    # warning is collected (at_bounds_, said by fit_summary), not passed on
    import warnings

    from sklearn.exceptions import ConvergenceWarning

    clean = GaussianProcessLag(max_samples=60, seed=0, noise_bounds=(1e-2, 1.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error", ConvergenceWarning)
        clean.fit(planted, ["r0", "r1", "r2", "r3"])
    assert "k2__noise_level" in clean.at_bounds_ and "k2__noise_level" in clean.fit_summary()
    from thermbench.export.encoding import ExportError, encode, export_blocker

    # its mean is not exported: refused in one line that says why and what to export instead
    with pytest.raises(ExportError, match=r"^model: the C runtime has no Gaussian-process kind: its mean is a kernel sum "
                                          r"over 300 training readings of \d+ lag states; export thermal_lag"):
        encode(m, where="model")
    assert "no Gaussian-process kind" in export_blocker(m)  # the benchmark never chooses it to deploy


@pytest.fixture(scope="module")
def with_speed():
    """The planted runs with the spindle speed declared as an operating input (a candidate input)."""
    return spindle_dataset(_runs(SPECS), sensors=SENSORS, operating=["spindle_rpm"])


@pytest.mark.parametrize("operating,select", [([], True), (["spindle_rpm"], True), (["spindle_rpm"], False)])
def test_the_c_runtime_kind_reproduces_python_in_both_precisions(planted, with_speed, operating, select, tmp_path):
    """THERMAL_LAG (embedded/src/tb_kind_thermal_lag.c, a second implementation of the lags and the
    weights): the export's parity check replays the held-out run through the C runtime; double to
    1e-9 µm, float within the 0.01 µm tolerance, as Python scores it."""
    from thermbench.export import export_model

    ds = with_speed if operating else planted
    m = ThermalLag(operating=operating, max_inputs=4, min_gain=0.0, select=select).fit(ds, ["r0", "r1", "r2", "r3"])
    assert ("spindle_rpm" in m.inputs_) == bool(operating)  # min_gain 0 or no selection: every input up to 4 enters
    man = export_model(m, tmp_path / "tl", "tl", ds=ds, heldout=["r4"])
    p = man["parity"]["model"]
    assert man["kind"] == "THERMAL_LAG" and p["n_readings"] > 300
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01
    assert p["heldout_rmse_um_c"] == pytest.approx(evaluate(m, ds, ["r4"])["rmse_um"].iloc[0], abs=1e-9)
    assert man["operating"] == operating


def test_two_operating_inputs_are_refused_in_one_line(with_speed):
    from thermbench.export.encoding import ExportError, encode

    m = ThermalLag(operating=["spindle_rpm"], max_inputs=4, min_gain=0.0).fit(with_speed, ["r0", "r1", "r2", "r3"])
    m.inputs_ = [*m.inputs_, "other_rpm"]  # as a model that chose two would be
    with pytest.raises(ExportError, match=r"chose 2 operating inputs \['spindle_rpm', 'other_rpm'\]; the C runtime"):
        encode(m)


def test_train_says_which_inputs_and_time_constants_it_chose(planted):
    m = ThermalLag().fit(planted, ["r0", "r1", "r2", "r3"])
    line = m.fit_summary()
    assert line.startswith(f"chose inputs {m.inputs_} at time constants {[round(t) for t in m.taus_s_]} s, ridge alpha")
    assert "3600" in line and f"{m.cv_rmse_um_:.3f} µm" in line


def test_the_stepwise_selection_drops_a_greedy_decoy_and_keeps_noise_out_within_one_standard_error():
    """_forward_groups on a plain linear design, checked against what the truth is by construction:
    y = A + B + noise; D = 0.6 (A + B) + 0.3 C is the best single input (a greedy first pick) but has
    no place once A and B are in; N1..N6 are pure noise. With min_gain 0, forward selection alone
    would take noise columns for any tiny gain in the held-out RMSE: the one-standard-error rule
    keeps the smallest model as good as the best within the folds' scatter."""
    from thermbench.models.thermal_lag import _forward_groups

    rng = np.random.default_rng(3)
    n_runs, n = 6, 120
    a, b, c = (rng.standard_normal(n_runs * n) for _ in range(3))
    cols = {"A": a, "B": b, "D": 0.6 * (a + b) + 0.3 * c, **{f"N{k}": rng.standard_normal(n_runs * n) for k in range(1, 7)}}
    y = a + b + 0.1 * rng.standard_normal(n_runs * n)
    run = np.repeat(np.arange(n_runs), n)
    folds = [(np.flatnonzero(run != r), np.flatnonzero(run == r)) for r in range(n_runs)]
    blocks = {k: v[:, None] for k, v in cols.items()}
    chosen, (rmse, _), steps, lowest = _forward_groups(blocks, np.zeros((y.size, 0)), y, folds, [1e-3, 1.0], 9, 0.0)
    assert [s for s, _ in steps][1] == "D"  # the decoy enters first ...
    assert "-D" in [s for s, _ in steps]  # ... and leaves once A and B explain it
    assert sorted(chosen) == ["A", "B"]  # the noise columns stay out
    assert lowest <= rmse < 0.11  # the noise floor (0.1), and never below the lowest visited


def test_the_stepwise_selection_ends_when_a_group_changes_nothing_and_min_gain_is_zero():
    """Inputs that change nothing (sensors that never moved: constant columns) enter on a tie when
    min_gain is 0 and leave on the same tie, one for the other: each set of groups is visited once,
    so the selection ends, keeping the input that matters (ties are broken by name: comparing the
    tied moves compared their folds' arrays and raised)."""
    from thermbench.models.thermal_lag import _forward_groups

    rng = np.random.default_rng(5)
    a = rng.standard_normal(400)
    blocks = {"A": a[:, None], "Z1": np.zeros((400, 1)), "Z2": np.zeros((400, 1))}  # two that never moved
    y = 2.0 * a + 0.05 * rng.standard_normal(400)
    run = np.repeat(np.arange(4), 100)
    folds = [(np.flatnonzero(run != r), np.flatnonzero(run == r)) for r in range(4)]
    chosen, (rmse, _), steps, _ = _forward_groups(blocks, np.zeros((400, 0)), y, folds, [1e-3], 3, 0.0)
    assert chosen == ["A"] and rmse < 0.06
    assert len(steps) <= 2 ** len(blocks) + 1  # each set once, plus every input at once


def test_without_selection_every_input_enters_and_the_fit_is_scikit_learns_ridge_over_whole_runs(planted):
    """select=False: every sensor enters with every lag of the chosen set; the time constants and the
    penalty are those of lowest RMSE over leave-one-run-out folds computed here by scikit-learn's
    cross_val_score, and the predictions are those of its StandardScaler + Ridge, on lags laid out here
    from the raw logs (first_order_lag itself is checked against the exponential above)."""
    from sklearn.linear_model import Ridge
    from sklearn.model_selection import LeaveOneGroupOut, cross_val_score
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    train = ["r0", "r1", "r2", "r3"]
    sets, alphas = [[0.0], [0.0, 3600.0]], [0.01, 1.0]
    m = ThermalLag(taus_s=sets, alphas=alphas, select=False).fit(planted, train)
    assert m.inputs_ == ["T_a", "T_b", "T_c"] and m.selection_ == [("(every input)", m.cv_rmse_um_)]

    def design(runs, taus):
        blocks, ys, groups = [], [], []
        for r in runs:
            spec = _runs(SPECS)[r]
            t = spec["t_s"]
            cols = []
            for s in ("T_a", "T_b", "T_c"):
                u = spec[f"{s}_C"] - spec[f"{s}_C"][0]
                for tau in taus:
                    cols.append(first_order_lag(t, u, tau))
            blocks.append(np.column_stack(cols))
            ys.append(spec["error_um"] - spec["error_um"][0])  # readings are relative to the run's first
            groups += [r] * t.size
        return np.vstack(blocks), np.concatenate(ys), np.array(groups)

    scores = {}
    for taus in sets:
        X, y, g = design(train, taus)
        for a in alphas:
            mse = -cross_val_score(make_pipeline(StandardScaler(), Ridge(alpha=a)), X, y, groups=g,
                                   cv=LeaveOneGroupOut(), scoring="neg_mean_squared_error")  # fmt: skip
            scores[(tuple(taus), a)] = float(np.sqrt(mse.mean()))
    taus, alpha = min(scores, key=scores.get)
    assert (m.taus_s_, m.alpha_) == (taus, alpha) and m.cv_rmse_um_ == pytest.approx(scores[(taus, alpha)], rel=1e-9)
    X, y, _ = design(train, taus)
    Xh, yh, _ = design(["r4"], taus)
    pipe = make_pipeline(StandardScaler(), Ridge(alpha=alpha)).fit(X, y)
    np.testing.assert_allclose(m.predict(planted, "r4"), pipe.predict(Xh), atol=1e-9)
    assert m.required_inputs().sensors == ("T_a", "T_b", "T_c")
