"""PSO-tuned LSSVM (seed 002 eq. 12-14): solver identities, PSO tuning, the thermal model."""

from __future__ import annotations

import logging
import os
import logging.config
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from sklearn.base import clone
from sklearn.exceptions import NotFittedError
from sklearn.kernel_ridge import KernelRidge

from tests.synth import analytic_dataset, rise
from thermbench.bench.metrics import evaluate
from thermbench.models.base import ModelError
from thermbench.models import lssvm
from thermbench.models.lssvm import DEFAULT_PSO_OPTIONS, LSSVMRegressor, PSOLSSVM, tune_lssvm

CONF = Path(__file__).resolve().parents[1] / "conf" / "model" / "lssvm.yaml"


# --------------------------------------------------------------------------- solver
@pytest.fixture(scope="module")
def xy():
    rng = np.random.default_rng(42)
    X = rng.normal(size=(40, 3)) * [1.0, 5.0, 0.2] + [3.0, -1.0, 10.0]
    y = np.sin(X[:, 0]) + 0.1 * X[:, 1] + rng.normal(scale=0.1, size=40) + 4.0
    return X, y


def _standardise(X):
    sd = X.std(axis=0)
    return (X - X.mean(axis=0)) / sd


def _rbf(A, B, sigma2):
    d2 = ((A[:, None, :] - B[None, :, :]) ** 2).sum(axis=-1)
    return np.exp(-d2 / (2 * sigma2))


def test_solver_matches_dense_kkt_solve(xy):
    X, y = xy
    gamma, sigma2 = 7.3, 2.1
    m = LSSVMRegressor(gamma=gamma, sigma2=sigma2).fit(X, y)
    # independent: the full bordered KKT system of seed 002 eq. 13, dense solve
    Z = _standardise(X)
    n = len(y)
    M = np.zeros((n + 1, n + 1))
    M[0, 1:] = M[1:, 0] = 1.0
    M[1:, 1:] = _rbf(Z, Z, sigma2) + np.eye(n) / gamma
    sol = np.linalg.solve(M, np.concatenate([[0.0], y]))
    b, alpha = sol[0], sol[1:]
    assert m.b_ == pytest.approx(b, abs=1e-8)
    np.testing.assert_allclose(m.alpha_, alpha, atol=1e-8)
    # eq. 14 prediction at new points, written out independently
    Xn = X[:5] + 0.37
    Zn = (Xn - X.mean(axis=0)) / X.std(axis=0)
    np.testing.assert_allclose(m.predict(Xn), _rbf(Zn, Z, sigma2) @ alpha + b, atol=1e-8)


def test_solver_matches_kernel_ridge_after_eliminating_b(xy):
    """Eliminating b from eq. 13: with A = K + I/γ, α = A⁻¹(y - b·1) and 1ᵀα = 0 give
    b = 1ᵀA⁻¹y / 1ᵀA⁻¹1. Kernel ridge (no intercept, alpha = 1/γ) computes A⁻¹·(target)."""
    X, y = xy
    gamma, sigma2 = 35.0, 0.8
    m = LSSVMRegressor(gamma=gamma, sigma2=sigma2).fit(X, y)
    Z = _standardise(X)
    kr = lambda target: KernelRidge(alpha=1 / gamma, kernel="rbf", gamma=1 / (2 * sigma2)).fit(Z, target)  # noqa: E731
    eta = kr(y).dual_coef_
    nu = kr(np.ones_like(y)).dual_coef_
    b = eta.sum() / nu.sum()
    assert m.b_ == pytest.approx(b, abs=1e-8)
    np.testing.assert_allclose(m.alpha_, eta - b * nu, atol=1e-8)
    # and the LSSVM is kernel ridge on the bias-removed targets, plus b
    kr_b = kr(y - b)
    np.testing.assert_allclose(m.alpha_, kr_b.dual_coef_, atol=1e-8)
    Zn = Z[:7] * 0.9
    Xn = Zn * X.std(axis=0) + X.mean(axis=0)
    np.testing.assert_allclose(m.predict(Xn), kr_b.predict(Zn) + b, atol=1e-8)


def test_kkt_residual_identity_and_zero_sum(xy):
    X, y = xy
    gamma = 12.0
    m = LSSVMRegressor(gamma=gamma, sigma2=1.5).fit(X, y)
    # ξ_i = α_i / γ: the training residual y - f(x_i) is α/γ
    np.testing.assert_allclose(m.predict(X), y - m.alpha_ / gamma, atol=1e-9)
    assert abs(m.alpha_.sum()) < 1e-9 * max(1.0, np.abs(m.alpha_).sum())


def test_standardise_makes_feature_units_irrelevant_and_sizes(xy):
    X, y = xy
    Xs = X * [1000.0, 1.0, 0.001]  # same data in other units
    a = LSSVMRegressor(gamma=20.0, sigma2=1.0).fit(X, y)
    b = LSSVMRegressor(gamma=20.0, sigma2=1.0).fit(Xs, y)
    np.testing.assert_allclose(a.predict(X[:6] + 0.1), b.predict((X[:6] + 0.1) * [1000.0, 1.0, 0.001]), atol=1e-9)
    # without standardising the units matter
    c = LSSVMRegressor(gamma=20.0, sigma2=1.0, standardize=False).fit(Xs, y)
    assert not np.allclose(c.predict(Xs[:6]), a.predict(X[:6]), atol=1e-3)
    # every sample is a support vector; deployed storage: 40x3 SVs + 40 α + b + σ² + mean/scale (3+3)
    assert a.n_support_ == 40
    assert a.memory_bytes_ == 8 * (120 + 40 + 1 + 1 + 6)


def test_regressor_bad_input(xy):
    X, y = xy
    with pytest.raises(ModelError, match="gamma"):
        LSSVMRegressor(gamma=0.0).fit(X, y)
    with pytest.raises(ModelError, match="sigma2"):
        LSSVMRegressor(sigma2=-1.0).fit(X, y)
    with pytest.raises(ModelError, match="y"):
        LSSVMRegressor().fit(X, y[:-1])
    with pytest.raises(NotFittedError):
        LSSVMRegressor().predict(X)
    with pytest.raises(ModelError, match="features"):
        LSSVMRegressor().fit(X, y).predict(X[:, :2])


# --------------------------------------------------------------------------- PSO
@pytest.fixture(scope="module")
def series():
    rng = np.random.default_rng(3)
    t = np.linspace(0, 1, 90)
    X = np.column_stack([np.sin(3 * t), t**2])
    y = 5 * np.sin(4 * X[:, 0]) + 2 * X[:, 1] + rng.normal(scale=0.05, size=t.size)
    return X, y


def _val_rmse(X, y, gamma, sigma2, n_val):
    m = LSSVMRegressor(gamma=gamma, sigma2=sigma2).fit(X[:-n_val], y[:-n_val])
    return float(np.sqrt(np.mean((y[-n_val:] - m.predict(X[-n_val:])) ** 2)))


def test_pso_deterministic_and_leaves_global_state(series, tmp_path, monkeypatch):
    X, y = series
    monkeypatch.chdir(tmp_path)
    root = logging.getLogger()
    handlers = list(root.handlers)
    np.random.seed(123)
    state = np.random.get_state()
    kw = dict(n_particles=8, iters=6, val_fraction=0.2)
    r1 = tune_lssvm(X, y, seed=7, **kw)
    r2 = tune_lssvm(X, y, seed=7, **kw)
    assert (r1.gamma, r1.sigma2) == (r2.gamma, r2.sigma2)
    np.testing.assert_array_equal(r1.cost_history, r2.cost_history)
    # numpy's global RNG, the root logger and the working directory are as before
    after = np.random.get_state()
    assert after[0] == state[0] and np.array_equal(after[1], state[1]) and after[2:] == state[2:]
    assert root.handlers == handlers
    assert list(tmp_path.iterdir()) == []


def test_pso_no_worse_than_corners_or_default(series):
    X, y = series
    n_val = 18  # 0.2 * 90: the last block of rows
    gb, sb = (1e-1, 1e4), (1e-2, 1e3)
    r = tune_lssvm(X, y, gb, sb, n_particles=10, iters=10, val_fraction=0.2, seed=0)
    assert r.val_mask.sum() == n_val and r.val_mask[-n_val:].all()
    # the reported cost is the true hold-out RMSE of the returned parameters
    assert r.val_rmse == pytest.approx(_val_rmse(X, y, r.gamma, r.sigma2, n_val), rel=1e-9)
    assert gb[0] <= r.gamma <= gb[1] and sb[0] <= r.sigma2 <= sb[1]
    others = [_val_rmse(X, y, g, s, n_val) for g in gb for s in sb] + [_val_rmse(X, y, 10.0, 1.0, n_val)]
    assert r.val_rmse <= min(others) + 1e-12
    hist = r.cost_history
    assert hist.size == 10 and np.all(np.diff(hist) <= 1e-15) and hist[-1] == pytest.approx(r.val_rmse)


def test_pso_fixed_parameter_and_bad_bounds(series):
    X, y = series
    r = tune_lssvm(X, y, gamma_bounds=(50.0, 50.0), n_particles=5, iters=4, seed=1)
    assert r.gamma == 50.0
    with pytest.raises(ModelError, match="gamma_bounds"):
        tune_lssvm(X, y, gamma_bounds=(10.0, 1.0))
    with pytest.raises(ModelError, match="sigma2_bounds"):
        tune_lssvm(X, y, sigma2_bounds=(0.0, 1.0))
    with pytest.raises(ModelError, match="val_fraction"):
        tune_lssvm(X, y, val_fraction=1.0)
    with pytest.raises(ModelError, match=r"^tune_lssvm\.options: expected None or a mapping with the numbers c1, c2 "
                                         r"and w, got \{'c1': 1\.0\}$"):
        tune_lssvm(X, y, options={"c1": 1.0})
    with pytest.raises(ModelError, match=r"^tune_lssvm\.n_particles: expected an integer >= 1, got True$"):
        tune_lssvm(X, y, n_particles=True)
    with pytest.raises(ModelError, match=r"^tune_lssvm\.seed: expected an integer 0\.\.4294967295, got -1$"):
        tune_lssvm(X, y, seed=-1)
    # equal bounds fix a parameter here (gamma_bounds above); val_fraction is unused with a val_mask
    mask = np.arange(len(y)) >= 70
    assert tune_lssvm(X, y, n_particles=3, iters=2, val_fraction=None, val_mask=mask).val_mask.sum() == 20


# --------------------------------------------------------------------------- thermal model
NOISE_UM = 0.3


def _truth(T, P):
    d1, d2 = T["T1"] - 20.0, T["T2"] - 21.0
    geometric = 1.5 * np.sin(P / 90.0) + 2e-3 * P
    thermal = (0.9 * d1 + 0.08 * d1**2) * P / 100.0 + 3.0 * np.tanh(d2 / 2.0) + 0.4 * d1 * d2 / 4
    return geometric + thermal


TEMPS = {
    "r1": {
        "T1": lambda t: 20.0 + rise(t, 8.0, 2500.0, 0.0, 9000.0),
        "T2": lambda t: 21.0 + rise(t, 4.0, 900.0, 600.0, 9000.0),
    },
    "r2": {"T1": lambda t: 20.0 + rise(t, 5.0, 3500.0), "T2": lambda t: 21.0 + rise(t, 6.0, 1500.0)},
}


@pytest.fixture(scope="module")
def clean_ds():
    return analytic_dataset({"r1": TEMPS["r1"]}, lambda T, P, run: _truth(T, P), noise_um=NOISE_UM, seed=5)


@pytest.fixture(scope="module")
def fitted(clean_ds):
    return PSOLSSVM(preprocess=None, sensors=["T1", "T2"], n_particles=10, iters=10, seed=0).fit(clean_ds, ["r1"])


@pytest.fixture
def user_logging():
    """A user's logging set-up: a handler on the root logger and a level on a named logger."""
    root, named = logging.getLogger(), logging.getLogger("a_user_app.part")
    saved = (list(root.handlers), root.level, named.level)
    records: list[str] = []

    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())

    handler = Keep(level=logging.DEBUG)
    root.addHandler(handler)
    named.setLevel(logging.DEBUG)
    yield SimpleNamespace(root=root, named=named, handler=handler, records=records)
    root.removeHandler(handler)
    named.setLevel(saved[2])


def test_fit_leaves_numpy_global_rng_and_logging_alone(clean_ds, user_logging, tmp_path, monkeypatch):
    """pyswarms runs with numpy's global generator seeded and its logging set-up pointed (LOG_CFG)
    at an incremental config that changes nothing: during the fit (seen from the solver every
    particle calls) logging.config.dictConfig is the real function and the user's handlers are in
    place; after it numpy's global generator is in the state it was (the next draws are the ones
    it would have given), LOG_CFG is as it was, the user's handlers, levels and named logger are
    intact and still hear; nothing is written to the working directory (no report.log)."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("LOG_CFG", "/a/users/own/logging.yaml")  # a user's own value survives the fit
    real_dict_config = logging.config.dictConfig
    log = user_logging
    handlers, root_level = list(log.root.handlers), log.root.level
    np.random.seed(2024)
    before = np.random.get_state()

    def same_state(state) -> bool:
        return state[0] == before[0] and np.array_equal(state[1], before[1]) and state[2:] == before[2:]

    seen = []
    solve = lssvm._solve_kkt
    calls = []
    real = logging.config.dictConfig

    def counting_dict_config(config):  # pyswarms' Reporter calls it: it must get the harmless config
        calls.append(config)
        return real(config)

    monkeypatch.setattr(logging.config, "dictConfig", counting_dict_config)

    def spy(K, y, gamma):
        seen.append((logging.config.dictConfig is counting_dict_config, list(log.root.handlers) == handlers,
                     os.environ.get("LOG_CFG") == str(lssvm.PYSWARMS_LOGGING)))  # fmt: skip
        return solve(K, y, gamma)

    monkeypatch.setattr(lssvm, "_solve_kkt", spy)
    m = PSOLSSVM(preprocess=None, sensors=["T1", "T2"], n_particles=6, iters=4, seed=0).fit(clean_ds, ["r1"])
    assert m.pso_cost_history_.size == 4 and len(seen) > 6 * 4
    assert all(dc for dc, _, _ in seen) and all(h for _, h, _ in seen)
    assert sum(env for _, _, env in seen) >= 6 * 4  # every particle of the search ran inside pyswarms' context
    assert calls and all(c == {"version": 1, "incremental": True} for c in calls)  # pyswarms built its reporters
    monkeypatch.setattr(logging.config, "dictConfig", real)
    assert logging.config.dictConfig is real_dict_config
    assert same_state(np.random.get_state())
    expected = np.random.RandomState()
    expected.set_state(before)
    assert np.random.random_sample(5).tolist() == expected.random_sample(5).tolist()
    assert os.environ["LOG_CFG"] == "/a/users/own/logging.yaml"
    assert log.root.handlers == handlers and log.root.level == root_level
    assert log.named.level == logging.DEBUG and not log.named.disabled
    log.named.debug("still heard")
    assert log.records[-1] == "still heard"
    assert list(tmp_path.iterdir()) == []


def test_same_seed_same_fit_other_seed_other_search(clean_ds, fitted):
    kw = dict(preprocess=None, sensors=["T1", "T2"], n_particles=10, iters=10)
    np.random.seed(1)  # the global generator's state does not matter
    again = PSOLSSVM(seed=0, **kw).fit(clean_ds, ["r1"])
    assert (again.gamma_, again.sigma2_, again.val_rmse_um_) == (fitted.gamma_, fitted.sigma2_, fitted.val_rmse_um_)
    np.testing.assert_array_equal(again.pso_cost_history_, fitted.pso_cost_history_)
    np.testing.assert_array_equal(again.predict(clean_ds, "r1"), fitted.predict(clean_ds, "r1"))
    np.random.seed(99)
    other = PSOLSSVM(seed=1, **kw).fit(clean_ds, ["r1"])
    assert (other.gamma_, other.sigma2_) != (fitted.gamma_, fitted.sigma2_)
    assert not np.array_equal(other.pso_cost_history_, fitted.pso_cost_history_)


def test_recovers_smooth_nonlinear_truth(clean_ds, fitted):
    m = fitted
    res = evaluate(m, clean_ds, ["r1"]).iloc[0]
    assert res["rmse_um"] <= 1.5 * NOISE_UM
    # it learnt the function, not the noise: against the noise-free truth it is as close
    er = clean_ds.errors_run("r1")
    T = {s: TEMPS["r1"][s](er["t_s"].to_numpy()) for s in ("T1", "T2")}
    truth = _truth(T, er["target_mm"].to_numpy())
    assert np.sqrt(np.mean((m.predict(clean_ds, "r1") - truth) ** 2)) <= NOISE_UM
    assert m.required_inputs().sensors == ("T1", "T2")
    n = len(er)
    assert m.n_support_ == n and m.memory_bytes_ == 8 * (n * 3 + n + 2 + 6)
    assert m.pso_cost_history_.size == 10 and m.gamma_ > 0 and m.sigma2_ > 0
    assert m.regressor_.gamma == m.gamma_


def test_fixed_hyperparameters_skip_pso_and_subsample(clean_ds):
    m = PSOLSSVM(preprocess=None, sensors=["T1", "T2"], gamma=100.0, sigma2=2.0, max_samples=50, seed=3).fit(clean_ds, "r1")
    assert m.pso_cost_history_.size == 0 and (m.gamma_, m.sigma2_) == (100.0, 2.0)
    assert m.subsampled_ and m.n_support_ == 50
    m2 = clone(m).fit(clean_ds, "r1")
    np.testing.assert_array_equal(m.regressor_.alpha_, m2.regressor_.alpha_)
    m3 = clone(m).set_params(seed=4).fit(clean_ds, "r1")
    assert not np.array_equal(m.regressor_.X_fit_, m3.regressor_.X_fit_)


def test_clone_get_params_and_hydra():
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    m = PSOLSSVM(sensors=["T1"], gamma=5.0, iters=3)
    c = clone(m)
    assert c.get_params() == m.get_params() and c is not m
    assert c.set_params(sigma2=0.5).sigma2 == 0.5
    built = instantiate(OmegaConf.load(CONF))
    assert isinstance(built, PSOLSSVM)
    defaults = PSOLSSVM().get_params()
    got = built.get_params()
    assert set(got) == set(defaults)
    for k, v in defaults.items():
        assert (list(got[k]) if isinstance(v, tuple) else got[k]) == (list(v) if isinstance(v, tuple) else v), k
    clone(built)


def test_bad_inputs(clean_ds):
    with pytest.raises(ModelError, match="nope"):
        PSOLSSVM(sensors=["T1", "nope"], gamma=1.0, sigma2=1.0).fit(clean_ds, "r1")
    with pytest.raises(ModelError, match="not fitted"):
        PSOLSSVM(sensors=["T1"]).predict(clean_ds, "r1")
    with pytest.raises(ModelError, match="fit"):
        PSOLSSVM().required_inputs()
    for bad, name in [
        ({"gamma_bounds": (10.0, 1.0)}, "gamma_bounds"),
        ({"sigma2_bounds": (-1.0, 5.0)}, "sigma2_bounds"),
        ({"gamma_bounds": (5.0, 5.0)}, "gamma_bounds"),
        ({"gamma": -3.0}, "gamma"),
        ({"val_fraction": 1.5}, "val_fraction"),
        ({"n_particles": 0}, "n_particles"),
        ({"seed": -1}, "seed"),  # numpy's generators take 0..2**32-1
    ]:
        with pytest.raises(ModelError, match=rf"^PSOLSSVM\.{name}: expected "):
            PSOLSSVM(sensors=["T1"], **bad).fit(clean_ds, "r1")


def test_too_few_samples():
    tiny = analytic_dataset(
        {"r": TEMPS["r2"]}, lambda T, P, run: _truth(T, P), duration_s=1500, targets_mm=(0, 250, 500)
    )  # 3 cycles x 3 targets = 9 readings
    with pytest.raises(ModelError, match="too few samples"):
        PSOLSSVM(sensors=["T1"], gamma=1.0, sigma2=1.0).fit(tiny, "r")
    one_cycle = analytic_dataset({"r": TEMPS["r2"]}, lambda T, P, run: _truth(T, P), duration_s=600)
    with pytest.raises(ModelError, match="too few samples.*2 measuring cycles"):
        PSOLSSVM(sensors=["T1"]).fit(one_cycle, "r")
    # with both hyper-parameters given, no hold-out is needed
    m = PSOLSSVM(sensors=["T1"], gamma=10.0, sigma2=1.0).fit(one_cycle, "r")
    assert m.n_support_ == 11


def test_a_long_swarm_shows_its_progress_only_when_a_job_asks(clean_ds, capsys, monkeypatch):
    """Fits longer than 10 s show progress (in thermbench train); the delay set to 0 here.
    One step per swarm iteration, as many as ``iters``; outside show_fit_progress nothing is drawn."""
    from thermbench.models import base

    import tqdm.auto

    monkeypatch.setattr(base, "FIT_PROGRESS_DELAY_S", 0.0)
    counted = []

    class Counting(tqdm.auto.tqdm):  # the steps each bar counted
        def close(self):
            counted.append((self.desc, self.n, self.total))  # (tqdm closes a bar twice: its own and ours)
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Counting)
    PSOLSSVM(preprocess=None, sensors=["T1", "T2"], n_particles=4, iters=7, seed=0).fit(clean_ds, ["r1"])
    assert "LSSVM swarm" not in capsys.readouterr().err
    with base.show_fit_progress(disable=False):
        PSOLSSVM(preprocess=None, sensors=["T1", "T2"], n_particles=4, iters=7, seed=0).fit(clean_ds, ["r1"])
    err = capsys.readouterr().err
    assert "LSSVM swarm" in err and set(counted) == {("LSSVM swarm", 7, 7)}


def test_validation_holds_whole_runs_out_counted_by_hand():
    """base.validation_mask: whole training runs from the end, closest to the fraction of readings,
    the first run always kept; one run: its last cycles (a block)."""
    import pandas as pd

    from thermbench.models.base import validation_mask

    rd = pd.DataFrame({"run_id": np.repeat(["a", "b", "c", "d"], [10, 10, 10, 10]), "cycle": np.tile(np.arange(10), 4)})
    held = lambda f: sorted(set(rd.loc[validation_mask(rd, f), "run_id"]))  # noqa: E731
    assert held(0.25) == ["d"] and held(0.5) == ["c", "d"] and held(0.9) == ["b", "c", "d"] and held(0.0) == []
    one = rd[rd["run_id"] == "a"].reset_index(drop=True)
    assert list(np.flatnonzero(validation_mask(one, 0.2))) == [8, 9]


def test_run_grouped_validation_does_not_pick_the_overfit_that_random_rows_pick():
    """A planted case: the error is a smooth function of the temperature plus, in each run,
    a slow drift of its own (autocorrelated in time, unrelated to the temperature). Validated on
    random rows, the swarm picks a narrow kernel that follows each run's drift between its
    neighbours; validated on whole runs, a wider one. On a run neither saw, the run-grouped choice is better."""
    from thermbench.models.lssvm import LSSVMRegressor

    rng = np.random.default_rng(0)  # the same outcome with seeds 0..3 (held-out-run RMSE 0.36-0.77 vs 0.92-2.78 µm)
    X, y, run = [], [], []
    for r in range(5):
        t = np.linspace(0, 1, 120)
        temp = 4 * (1 - np.exp(-3 * t)) + rng.uniform(-0.5, 0.5) + 0.3 * np.sin(9 * t + r)
        drift = np.cumsum(rng.standard_normal(t.size)) * 0.1  # the run's own slow wander
        X.append(np.column_stack([temp, t]))
        y.append(2.0 * temp + 0.3 * temp**2 + drift)
        run.append(np.full(t.size, r))
    X, y, run = np.vstack(X), np.concatenate(y), np.concatenate(run)
    train, new = run < 4, run == 4
    Xt, yt, rt = X[train], y[train], run[train]
    random_rows = np.zeros(rt.size, dtype=bool)
    random_rows[rng.choice(rt.size, rt.size // 4, replace=False)] = True
    whole_run = rt == 3
    picks = {}
    for name, mask in (("random rows", random_rows), ("whole run", whole_run)):
        res = tune_lssvm(Xt, yt, (0.1, 1e4), (1e-3, 1e3), n_particles=12, iters=15, seed=0, val_mask=mask)
        fit = LSSVMRegressor(gamma=res.gamma, sigma2=res.sigma2).fit(Xt, yt)
        picks[name] = (res.sigma2, float(np.sqrt(np.mean((fit.predict(X[new]) - y[new]) ** 2))))
    assert picks["random rows"][0] < picks["whole run"][0]  # the narrower kernel on random rows
    assert picks["whole run"][1] < picks["random rows"][1]  # and it does worse on a run it never saw
