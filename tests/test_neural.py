"""The neural family (thermbench/models/neural.py) on analytic data whose truth is known."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.base import clone

from tests.synth import analytic_dataset, rise
from thermbench.models.base import Inputs, ModelError
from thermbench.models.neural import GRUModel, MLPModel

NOISE_UM = 0.3
DURATION_S = 4 * 3600
EVERY_S = 600.0  # one measuring cycle of 11 targets every 10 min -> 24 cycles per run
TARGETS = np.arange(0.0, 501.0, 50.0)
CONF = Path(__file__).resolve().parents[1] / "conf" / "model"

# small, fast settings (the defaults are for the benchmark); the GRU gets patience 200: the
# held-out last cycles of a warm-up run sit on the plateau, where the validation RMSE reaches
# the noise floor long before the transient is fitted
FAST_MLP = dict(hidden=(16, 16), lr=2e-2, max_epochs=600, preprocess=None)  # clean analytic data
FAST_GRU = dict(hidden_size=8, step_s=180.0, lr=2e-2, max_epochs=600, patience=200, preprocess=None)


def geometric_truth(p):
    """A cubic pitch error (µm) that does not depend on temperature."""
    return 2e-7 * (p - 250.0) ** 3 + 1e-5 * p**2


def clean_error(T, p, run):
    """Smooth, nonlinear in the two temperatures, slope in P set by them."""
    a, b = T["Ta"], T["Tb"]
    return 3.0 * np.tanh(a / 3.0) + (0.010 * a + 0.003 * a * b) * p + 0.5 * b + geometric_truth(p)


def _ta(t_on):
    return lambda t: rise(t, 6.0, 1800.0, t_on)


def _tb(t_on):
    return lambda t: rise(t, 3.0, 3600.0, 600.0 + t_on)


@pytest.fixture(scope="module")
def clean_ds():
    # r2 is r1 delayed by 1200 s (same temperatures 1200 s later)
    temps = {"r1": {"Ta": _ta(0.0), "Tb": _tb(0.0)}, "r2": {"Ta": _ta(1200.0), "Tb": _tb(1200.0)}}
    return analytic_dataset(temps, clean_error, duration_s=DURATION_S, every_s=EVERY_S, noise_um=NOISE_UM, seed=1)


# history truth: the error follows a first-order lag (tau = 15 min) of the heated sensor Ta;
# the lag is stored as a hidden channel "L" that the models are not given
TAU_S = 900.0
_TG = np.arange(0.0, DURATION_S + 2.0, 1.0)


def _heat_cool(t):
    return rise(t, 6.0, 1200.0, 0.0, 6000.0)  # heat for 100 min, then cool


def _lag_series():
    a = np.exp(-1.0 / TAU_S)
    x = _heat_cool(_TG)
    out = np.zeros_like(x)
    for i in range(1, x.size):
        out[i] = a * out[i - 1] + (1.0 - a) * x[i]
    return out


_LG = _lag_series()


@pytest.fixture(scope="module")
def lag_ds():
    temps = {"r1": {"Ta": _heat_cool, "L": lambda t: np.interp(t, _TG, _LG)}}
    err = lambda T, p, run: (0.02 * p + 1.0) * T["L"]  # noqa: E731
    return analytic_dataset(temps, err, duration_s=DURATION_S, every_s=EVERY_S, noise_um=NOISE_UM, seed=2)


@pytest.fixture(scope="module")
def mlp_clean(clean_ds):
    return MLPModel(sensors=["Ta", "Tb"], **FAST_MLP).fit(clean_ds, "r1")


@pytest.fixture(scope="module")
def gru_clean(clean_ds):
    return GRUModel(sensors=["Ta", "Tb"], **FAST_GRU).fit(clean_ds, "r1")


def rms_on(model, ds, run):
    r = ds.errors_run(run)["error_um"].to_numpy() - model.predict(ds, run)
    return float(np.sqrt(np.mean(r**2)))


# --- recovery -------------------------------------------------------------------------------
@pytest.mark.parametrize("which", ["mlp", "gru"])
def test_residual_within_1_5x_noise_on_training_condition(which, mlp_clean, gru_clean, clean_ds):
    model = mlp_clean if which == "mlp" else gru_clean
    assert rms_on(model, clean_ds, "r1") <= 1.5 * NOISE_UM
    assert model.required_inputs() == Inputs(sensors=("Ta", "Tb"))


def test_geometric_part_is_seed002_separation(mlp_clean):
    # per-cycle lines absorb the straight-line part of the pitch error; what is left
    # (cubic minus its least-squares line over the targets) is the geometric error
    g = geometric_truth(TARGETS)
    line = np.polyval(np.polyfit(TARGETS, g, 1), TARGETS)
    expected = g - line
    # noise of the mean over 24 cycles: 0.3 / sqrt(24) ≈ 0.06 µm per target
    np.testing.assert_allclose(mlp_clean.geometric_um(TARGETS), expected, atol=0.2)


def test_gru_learns_temperature_history_mlp_cannot(lag_ds):
    er = lag_ds.errors_run("r1")
    truth = er["error_um"].to_numpy()
    # no memoryless function of (Ta, P) fits this truth: a rich least-squares model
    # (degree-8 polynomial in Ta, times 1 and P) already leaves > 1 µm RMS
    ta = _heat_cool(er["t_s"].to_numpy()) / 6.0
    p = er["target_mm"].to_numpy() / 500.0
    basis = np.column_stack([ta**k * p**j for k in range(9) for j in range(2)])
    coef, *_ = np.linalg.lstsq(basis, truth, rcond=None)
    memoryless_floor = float(np.sqrt(np.mean((truth - basis @ coef) ** 2)))
    assert memoryless_floor > 1.0

    # the MLP gets every cycle (no held-out block) and still cannot
    mlp = MLPModel(preprocess=None, sensors=["Ta"], hidden=(16, 16), lr=2e-2, max_epochs=600, val_fraction=0.0).fit(lag_ds, "r1")
    gru = GRUModel(preprocess=None, sensors=["Ta"], hidden_size=8, step_s=120.0, window_s=1800.0, lr=2e-2, max_epochs=600)
    gru.fit(lag_ds, "r1")
    rms_mlp, rms_gru = rms_on(mlp, lag_ds, "r1"), rms_on(gru, lag_ds, "r1")
    assert rms_mlp > 1.0
    assert rms_gru <= 1.5 * NOISE_UM
    assert rms_gru < rms_mlp / 2


@pytest.mark.parametrize("which", ["mlp", "gru"])
def test_predict_uses_the_runs_own_process_log(which, mlp_clean, gru_clean, clean_ds):
    # r2 has r1's temperatures 1200 s later: the prediction at (t + 1200, P) on r2 must be
    # the prediction at (t, P) on r1 (the GRU's history before the start is ΔT = 0 in both)
    model = mlp_clean if which == "mlp" else gru_clean
    t = np.array([30.0, 900.0, 3000.5, 7200.0, 12000.0])
    p = np.array([0.0, 125.0, 250.0, 400.0, 500.0])
    on_r1 = model.predict_at(clean_ds, "r1", t, p)
    on_r2 = model.predict_at(clean_ds, "r2", t + 1200.0, p)
    np.testing.assert_allclose(on_r2, on_r1, rtol=0, atol=1e-9)
    # and it is not the same function of time: r2 at time t is colder than r1 at t
    assert not np.allclose(model.predict_at(clean_ds, "r2", t, p), on_r1, atol=0.5)


def test_gru_compensation_table_matches_pointwise_predictions(gru_clean, clean_ds):
    # the table runs the GRU once per time and reuses it for every position
    x = np.array([0.0, 250.0, 500.0])
    table = gru_clean.compensation_table(clean_ds, "r1", axis_mm=x, step_s=1800.0)
    for i, t in enumerate(table.t_s):
        pointwise = gru_clean.predict_at(clean_ds, "r1", np.full(x.size, t), x)
        np.testing.assert_allclose(table.error_um[i], pointwise, atol=1e-9)


# --- training discipline --------------------------------------------------------------------
def test_early_stopping_stops_and_keeps_best_validation_weights(lag_ds):
    # memoryless net on history data: the held-out cooling cycles stop improving early
    patience = 20
    m = MLPModel(preprocess=None, sensors=["Ta"], hidden=(16, 16), lr=2e-2, max_epochs=3000, patience=patience, min_epochs=0)
    m.fit(lag_ds, "r1")
    assert m.n_epochs_ < 3000
    assert m.n_epochs_ == m.best_epoch_ + patience
    # val_fraction 0.2 of 24 cycles -> the last 5 cycles, starting at 19 * 600 s = 11400 s
    er = lag_ds.errors_run("r1")
    val = er["t_s"].to_numpy() >= 11400.0
    assert val.sum() == 5 * TARGETS.size
    r = er["error_um"].to_numpy() - m.predict(lag_ds, "r1")
    assert np.sqrt(np.mean(r[val] ** 2)) == pytest.approx(m.best_val_rmse_um_, rel=1e-9)
    assert m.n_val_readings_ == 5 * TARGETS.size and m.n_train_readings_ == 19 * TARGETS.size


@pytest.mark.parametrize("cls,kw", [(MLPModel, dict(hidden=(8,))), (GRUModel, dict(hidden_size=4, step_s=300.0))])
def test_same_params_same_bits_and_no_global_side_effects(cls, kw, clean_ds):
    rng_before = torch.get_rng_state().clone()
    threads_before = torch.get_num_threads()
    a = cls(sensors=["Ta", "Tb"], max_epochs=40, seed=3, **kw).fit(clean_ds, "r1")
    # the fit neither used nor changed the global torch RNG, nor the thread count
    assert torch.equal(torch.get_rng_state(), rng_before)
    assert torch.get_num_threads() == threads_before
    torch.rand(5)  # so disturbing the global RNG does not matter
    b = cls(sensors=["Ta", "Tb"], max_epochs=40, seed=3, **kw).fit(clean_ds, "r1")
    c = cls(sensors=["Ta", "Tb"], max_epochs=40, seed=4, **kw).fit(clean_ds, "r1")
    pa, pb, pc = (m.predict(clean_ds, "r2") for m in (a, b, c))
    assert np.array_equal(pa, pb)
    assert not np.allclose(pa, pc)
    assert a.n_parameters_ == sum(p.numel() for p in a.net_.parameters())


def test_gru_trains_in_float32_and_predicts_in_float64(clean_ds, monkeypatch):
    # float32 training steps (2.4x faster per epoch) must not change what the GRU learns beyond
    # rounding: a twin trained in float64 from the same seed predicts the same to far below the
    # noise; the fitted weights are float64 (what prediction and the export read)
    kw = dict(sensors=["Ta", "Tb"], hidden_size=4, step_s=300.0, max_epochs=60, seed=5)
    f32 = GRUModel(**kw).fit(clean_ds, "r1")
    assert GRUModel.TRAIN_DTYPE == torch.float32
    assert all(p.dtype == torch.float64 for p in f32.net_.parameters())
    monkeypatch.setattr(GRUModel, "TRAIN_DTYPE", torch.float64)
    f64 = GRUModel(**kw).fit(clean_ds, "r1")
    p32, p64 = f32.predict(clean_ds, "r2"), f64.predict(clean_ds, "r2")
    assert p32.dtype == np.float64
    assert not np.array_equal(p32, p64)  # the two really trained at different precisions
    assert np.max(np.abs(p32 - p64)) < 0.01  # µm: below the export's parity budget


def test_parameter_counts_match_the_architecture(mlp_clean, gru_clean):
    # MLP 3 -> 16 -> 16 -> 1; GRU: 3 gates x (input + hidden weights + 2 biases), head 8 -> 2
    assert mlp_clean.n_parameters_ == (3 * 16 + 16) + (16 * 16 + 16) + (16 + 1)
    assert gru_clean.n_parameters_ == 3 * (8 * 2 + 8 * 8 + 2 * 8) + (8 * 2 + 2)
    assert gru_clean.n_lags_ == 10 and gru_clean.position_degree_ == 1  # 1800 / 180; fixed-free line


def test_mini_batches_train_too(clean_ds):
    m = MLPModel(preprocess=None, sensors=["Ta", "Tb"], hidden=(16, 16), lr=1e-2, max_epochs=150, batch_size=32).fit(clean_ds, "r1")
    assert rms_on(m, clean_ds, "r1") < 1.5  # an untrained net is off by the ~16 µm spread of the target


# --- sklearn / hydra --------------------------------------------------------------------------
def test_clone_and_get_params():
    m = GRUModel(sensors=["Ta"], hidden_size=4, window_s=600.0, seed=7)
    c = clone(m)
    assert c.get_params() == m.get_params()
    assert c.get_params()["window_s"] == 600.0 and c.get_params()["seed"] == 7
    defaults = MLPModel().get_params()
    assert defaults["hidden"] == (32, 32) and defaults["activation"] == "tanh" and defaults["patience"] == 100
    assert defaults["batch_size"] is None and defaults["val_fraction"] == 0.2 and defaults["geometric_degree"] == 3


def test_clone_of_fitted_model_is_unfitted(mlp_clean):
    c = clone(mlp_clean)
    assert not hasattr(c, "net_")
    with pytest.raises(ModelError, match="not fitted"):
        c.predict_at(None, "r1", 0.0, 0.0)


@pytest.mark.parametrize("name,cls", [("mlp", MLPModel), ("gru", GRUModel)])
def test_hydra_config_builds_the_model_with_its_defaults(name, cls, clean_ds):
    m = instantiate(OmegaConf.load(CONF / f"{name}.yaml"))
    assert type(m) is cls
    got, want = m.get_params(), cls().get_params()
    assert {k: list(v) if isinstance(v, tuple) else v for k, v in want.items()} == got
    m.set_params(sensors=["Ta", "Tb"], max_epochs=3).fit(clean_ds, "r1")
    assert np.all(np.isfinite(m.predict(clean_ds, "r2")))


# --- bad input --------------------------------------------------------------------------------
@pytest.mark.parametrize("cls", [MLPModel, GRUModel])
def test_missing_sensor_is_named(cls, clean_ds):
    with pytest.raises(ModelError, match="T_spindle"):
        cls(sensors=["Ta", "T_spindle"], max_epochs=2).fit(clean_ds, "r1")


def test_too_few_samples():
    temps = {"r1": {"Ta": _ta(0.0), "Tb": _tb(0.0)}}
    one_cycle = analytic_dataset(temps, clean_error, duration_s=300.0, every_s=600.0)
    with pytest.raises(ModelError, match="too few samples.*val_fraction"):
        MLPModel(sensors=["Ta", "Tb"], max_epochs=2).fit(one_cycle, "r1")
    five = analytic_dataset(temps, clean_error, duration_s=300.0, every_s=600.0, targets_mm=(0, 100, 200, 300, 400))
    with pytest.raises(ModelError, match="too few samples"):
        GRUModel(sensors=["Ta", "Tb"], max_epochs=2, val_fraction=0.0).fit(five, "r1")


@pytest.mark.parametrize("cls", [MLPModel, GRUModel])
def test_predict_before_fit(cls, clean_ds):
    with pytest.raises(ModelError, match="not fitted"):
        cls(sensors=["Ta"]).predict(clean_ds, "r1")
    with pytest.raises(ModelError, match="not fitted"):
        cls(sensors=["Ta"]).required_inputs()  # inputs describe a fitted model


@pytest.mark.parametrize(
    "cls,bad,param",
    [
        (MLPModel, dict(lr=0.0), "lr"),
        (MLPModel, dict(val_fraction=1.0), "val_fraction"),
        (MLPModel, dict(hidden=[]), "hidden"),
        (MLPModel, dict(hidden=[8, 0]), "hidden"),
        (MLPModel, dict(activation="softsign"), "activation"),
        (MLPModel, dict(max_epochs=0), "max_epochs"),
        (MLPModel, dict(batch_size=0), "batch_size"),
        (MLPModel, dict(sensors="Ta"), "sensors"),
        (GRUModel, dict(step_s=0.0), "step_s"),
        (GRUModel, dict(window_s=-60.0), "window_s"),
        (GRUModel, dict(hidden_size=0), "hidden_size"),
        (GRUModel, dict(patience=0), "patience"),
        (GRUModel, dict(seed=-1), "seed"),
    ],
)
def test_bad_parameters_name_the_parameter(cls, bad, param, clean_ds):
    kw = {"sensors": ["Ta"], "max_epochs": 2, **bad}
    with pytest.raises(ModelError, match=param):
        cls(**kw).fit(clean_ds, "r1")


def test_benchmark_selection_smoke():
    # sensors=None: the seed 002 §2.3.1 selection picks the inputs on the training run
    from thermbench.bench.datasets import load_benchmark

    ds = load_benchmark("seed002_vmc655h_x")
    m = MLPModel(hidden=(8,), max_epochs=20).fit(ds, "c1")
    non_ambient = {s for s, loc in ds.metadata.sensors.items() if loc != "ambient"}
    assert set(m.sensors_) <= non_ambient and len(m.sensors_) == 2
    assert m.required_inputs().sensors == tuple(m.sensors_)
    assert np.all(np.isfinite(m.predict(ds, "c2")))


def test_fitted_model_pickles(gru_clean, clean_ds):
    import pickle

    back = pickle.loads(pickle.dumps(gru_clean))
    assert np.array_equal(back.predict(clean_ds, "r2"), gru_clean.predict(clean_ds, "r2"))


@pytest.mark.parametrize("cls,kw", [(MLPModel, dict(hidden=(8,))), (GRUModel, dict(hidden_size=4, step_s=300.0))])
def test_preprocess_filters_the_inputs(cls, kw):
    # "spiky" is "clean" with an 85 °C sensor dropout at 2998-3002 s (seed 002 §2.3.1 limit filter)
    from thermbench.preprocess.filters import LimitFilter

    ta = _ta(0.0)

    def spiky(t):
        return np.where((t >= 2998.0) & (t <= 3002.0), 85.0, ta(t))

    temps = {"clean": {"Ta": ta, "Tb": _tb(0.0)}, "spiky": {"Ta": spiky, "Tb": _tb(0.0)}}
    ds = analytic_dataset(temps, clean_error, duration_s=DURATION_S, every_s=EVERY_S)
    t, p = np.full(3, 3000.0), np.array([0.0, 250.0, 500.0])
    filtered = cls(sensors=["Ta", "Tb"], preprocess=[LimitFilter(limit_C=2.0)], max_epochs=30, **kw).fit(ds, "clean")
    # the filter holds the last accepted reading (2997 s): Ta moves ~0.002 °C in those 3 s
    np.testing.assert_allclose(filtered.predict_at(ds, "spiky", t, p), filtered.predict_at(ds, "clean", t, p), atol=0.05)
    raw = cls(sensors=["Ta", "Tb"], preprocess=None, max_epochs=30, **kw).fit(ds, "clean")
    assert np.max(np.abs(raw.predict_at(ds, "spiky", t, p) - raw.predict_at(ds, "clean", t, p))) > 1.0


def test_a_long_training_shows_its_epochs_only_when_a_job_asks(clean_ds, capsys, monkeypatch):
    """Fits longer than 10 s show progress (in thermbench train); the delay set to 0 here.
    One step per epoch: no validation split, so all max_epochs run; none drawn outside show_fit_progress."""
    from thermbench.models import base

    import tqdm.auto

    monkeypatch.setattr(base, "FIT_PROGRESS_DELAY_S", 0.0)
    counted = []

    class Counting(tqdm.auto.tqdm):  # the steps each bar counted
        def close(self):
            counted.append((self.desc, self.n, self.total))  # (tqdm closes a bar twice: its own and ours)
            super().close()

    monkeypatch.setattr(tqdm.auto, "tqdm", Counting)
    kw = dict(preprocess=None, sensors=["Ta", "Tb"], max_epochs=9, min_epochs=1, val_fraction=0.0, seed=0)
    MLPModel(**kw).fit(clean_ds, ["r1"])
    assert "MLPModel fit" not in capsys.readouterr().err
    with base.show_fit_progress(disable=False):
        m = MLPModel(**kw).fit(clean_ds, ["r1"])
    err = capsys.readouterr().err
    assert m.n_epochs_ == 9 and "MLPModel fit" in err and set(counted) == {("MLPModel fit", 9, 9)}
