"""The three multiple-linear-regression forms (seed 001, 002, 004) recover known truths."""

from pathlib import Path

import numpy as np
import pytest
from hydra.utils import instantiate
from numpy.polynomial import polynomial as P
from omegaconf import OmegaConf
from sklearn.base import clone

from tests.synth import analytic_dataset, rise
from thermbench.models.base import ModelError
from thermbench.models.mlr import MLRSeed001, MLRSeed002, MLRSeed004

CONF = Path(__file__).resolve().parents[1] / "conf" / "model"
TARGETS = np.arange(0.0, 501.0, 50.0)


def rms(x):
    return float(np.sqrt(np.mean(np.square(x))))


# ------------------------------------------------------------------ seed 001 ---
# truth: E = (a2 ΔTn² + a1 ΔTn + b1 ΔTb)·P + quartic geometric (c = 0: the cold
# readings are pure geometric error, as seed 001 eq. 11 assumes)
A1, A2, B1 = 8.0e-3, -3.0e-4, 2.5e-3  # µm/mm per °C, per °C²
D = (1.5, 2.0e-2, -1.0e-4, 2.0e-7, -1.5e-10)  # quartic geometric, µm vs mm


def seed001_temps():
    # heating starts at 200 s, after the cold measuring cycle (11 targets x 8 s)
    return {
        "r1": {"Tn": lambda t: 20 + rise(t, 9.0, 1800, 200, 9000), "Tb": lambda t: 20 + rise(t, 1.5, 5000, 200)},
        "r2": {"Tn": lambda t: 20 + rise(t, 5.0, 1200, 200), "Tb": lambda t: 20 + rise(t, 2.5, 2500, 200, 7000)},
    }


def seed001_error(T, p, run):
    dn, db = T["Tn"] - 20.0, T["Tb"] - 20.0
    return (A2 * dn**2 + A1 * dn + B1 * db) * p + P.polyval(p, D)


@pytest.fixture(scope="module")
def ds001():
    ds = analytic_dataset(seed001_temps(), seed001_error, targets_mm=TARGETS)
    ds.metadata.sensors["Tb"] = "bed"  # Tn stays at nut_housing
    return ds


def test_seed001_recovers_coefficients_and_geometric(ds001):
    m = MLRSeed001(preprocess=None, degree=2).fit(ds001)  # sensors resolved by location
    assert (m.nut_sensor_, m.bed_sensor_) == ("Tn", "Tb")
    assert set(m.coef_) == {"a1", "a2", "b1", "c"}
    for k, v in {"a1": A1, "a2": A2, "b1": B1}.items():
        assert m.coef_[k] == pytest.approx(v, rel=1e-6)
    assert abs(m.coef_["c"]) < 1e-9
    x = np.linspace(0, 500, 37)
    np.testing.assert_allclose(m.geometric_um(x), P.polyval(x, D), atol=1e-7)
    # prediction at an arbitrary (t, P) equals the truth
    t = np.array([500.0, 3000.0, 9500.0, 14000.0])
    xs = np.array([25.0, 480.0, 333.0, 120.0])
    T = {s: np.array([f(ti) for ti in t]) for s, f in seed001_temps()["r2"].items()}
    np.testing.assert_allclose(m.predict_at(ds001, "r2", t, xs), seed001_error(T, xs, "r2"), atol=1e-6)


def test_seed001_with_noise_leaves_noise(ds001):
    noisy = analytic_dataset(seed001_temps(), seed001_error, targets_mm=TARGETS, noise_um=0.5, seed=3)
    m = MLRSeed001(preprocess=None, degree=2, nut_sensor="Tn", bed_sensor="Tb").fit(noisy)
    resid = np.concatenate([noisy.errors_run(r)["error_um"] - m.predict(noisy, r) for r in noisy.run_ids])
    assert 0.4 < rms(resid) < 0.65  # ≈ the injected 0.5 µm noise
    # and the prediction is close to the noise-free truth
    clean = np.concatenate([ds001.errors_run(r)["error_um"] for r in ds001.run_ids])
    pred = np.concatenate([m.predict(noisy, r) for r in noisy.run_ids])
    assert rms(pred - clean) < 0.25


def test_seed001_origin_moves_the_zero(ds001):
    # the same truth written about origin 100 mm is not in the P·f(T) class unless origin is moved
    def err(T, p, run):
        dn, db = T["Tn"] - 20.0, T["Tb"] - 20.0
        return (A1 * dn + B1 * db) * (p - 100.0) + P.polyval(p, D)

    ds = analytic_dataset(seed001_temps(), err, targets_mm=TARGETS)
    m0 = MLRSeed001(preprocess=None, degree=1, nut_sensor="Tn", bed_sensor="Tb").fit(ds)
    m1 = MLRSeed001(preprocess=None, degree=1, nut_sensor="Tn", bed_sensor="Tb", origin_mm=100.0).fit(ds)
    r0 = rms(ds.errors["error_um"] - np.concatenate([m0.predict(ds, r) for r in ds.run_ids]))
    r1 = rms(ds.errors["error_um"] - np.concatenate([m1.predict(ds, r) for r in ds.run_ids]))
    assert r1 < 1e-6 < 0.1 < r0
    assert m1.coef_["a1"] == pytest.approx(A1, rel=1e-6)


@pytest.mark.parametrize("degree", [0, 5, 2.5, True])
def test_seed001_bad_degree(ds001, degree):
    with pytest.raises(ModelError, match="degree"):
        MLRSeed001(degree=degree).fit(ds001)


def test_seed001_bad_sensors(ds001):
    with pytest.raises(ModelError, match="nut_sensor.*nope"):
        MLRSeed001(nut_sensor="nope").fit(ds001)
    with pytest.raises(ModelError, match="bed_sensor"):
        MLRSeed001(nut_sensor="Tn", bed_sensor="Tn").fit(ds001)
    no_bed = analytic_dataset(seed001_temps(), seed001_error, targets_mm=TARGETS, duration_s=3600)
    with pytest.raises(ModelError, match="bed_sensor.*bed"):  # all its sensors are at nut_housing
        MLRSeed001().fit(no_bed)
    with pytest.raises(ModelError, match="origin_mm"):
        MLRSeed001(origin_mm="zero").fit(ds001)


# ------------------------------------------------------------------ seed 002 ---
K_SLOPE = (2.0e-3, 4.0e-3, -1.5e-3)  # const, per ΔS1, per ΔS2 (µm/mm)
K_INT = (0.5, 1.2, 2.5)  # µm
G3 = (-3.0, 3.7e-2, -8.9e-5, 5.2e-8)  # seed 002 eq. 7-like cubic


def seed002_temps():
    return {
        "a": {"S1": lambda t: 21 + rise(t, 6.0, 1500, 0, 9000), "S2": lambda t: 21 + rise(t, 2.0, 6000)},
        "b": {"S1": lambda t: 22 + rise(t, 3.0, 900), "S2": lambda t: 22 + rise(t, 3.0, 3000, 0, 8000)},
    }


def seed002_error(T, p, run, p0=0.0):
    d1, d2 = T["S1"] - T["S1"][0], T["S2"] - T["S2"][0]  # T[.][0] is the t=0 reading: the start temperature
    slope = K_SLOPE[0] + K_SLOPE[1] * d1 + K_SLOPE[2] * d2
    inter = K_INT[0] + K_INT[1] * d1 + K_INT[2] * d2
    return slope * (p - p0) + inter + P.polyval(p, G3)


def _cycle_dataset(temps, error_fn, **kw):
    # read_gap_s = 0: a cycle's readings share one time, so a cycle curve is exactly
    # the truth at that time (the hypothesis of the curve-per-cycle models)
    return analytic_dataset(temps, error_fn, targets_mm=TARGETS, read_gap_s=0.0, **kw)


def test_seed002_recovers_slope_and_intercept_regressions():
    ds = _cycle_dataset(seed002_temps(), seed002_error)
    m = MLRSeed002(preprocess=None, sensors=["S1", "S2"]).fit(ds)
    assert m.sensors_ == ["S1", "S2"]
    # the line fit of every cycle also takes the cubic's straight-line part over the targets
    l0, l1 = P.polyfit(TARGETS, P.polyval(TARGETS, G3), 1)
    np.testing.assert_allclose(m.slope_coef_, [K_SLOPE[0] + l1, *K_SLOPE[1:]], rtol=1e-6)
    np.testing.assert_allclose(m.intercept_coef_, [K_INT[0] + l0, *K_INT[1:]], rtol=1e-6)
    # geometric = the cubic without its line part (eq. 7), anywhere on the travel
    x = np.linspace(0, 500, 41)
    np.testing.assert_allclose(m.geometric_um(x), P.polyval(x, G3) - (l0 + l1 * x), atol=1e-7)
    # total prediction at arbitrary (t, P) = truth
    t = np.array([100.0, 5000.0, 11000.0])
    xs = np.array([10.0, 260.0, 495.0])
    T = {s: np.array([f(0.0), *[f(ti) for ti in t]]) for s, f in seed002_temps()["b"].items()}
    truth = seed002_error(T, np.r_[0.0, xs], "b")[1:]
    np.testing.assert_allclose(m.predict_at(ds, "b", t, xs), truth, atol=1e-6)


def test_seed002_p0_and_noise():
    def err(T, p, run):
        return seed002_error(T, p, run, p0=250.0)

    noisy = _cycle_dataset(seed002_temps(), err, noise_um=0.3, seed=5)
    m = MLRSeed002(preprocess=None, sensors=["S1", "S2"], origin_mm=250.0).fit(noisy)
    resid = np.concatenate([noisy.errors_run(r)["error_um"] - m.predict(noisy, r) for r in noisy.run_ids])
    assert 0.22 < rms(resid) < 0.36  # ≈ 0.3 µm noise
    # temperature coefficients still close (noise-limited)
    np.testing.assert_allclose(m.slope_coef_[1:], K_SLOPE[1:], rtol=0.05)
    np.testing.assert_allclose(m.intercept_coef_[1:], K_INT[1:], rtol=0.05)


def test_seed002_selects_sensors_when_none():
    ds = _cycle_dataset(seed002_temps(), seed002_error)
    m = MLRSeed002(preprocess=None, selection={"n_clusters": 1, "method": "correlation"}).fit(ds)
    assert len(m.sensors_) == 1 and m.sensors_[0] in ("S1", "S2")
    assert m.required_inputs().sensors == tuple(m.sensors_)


def test_seed002_bad_input():
    ds = _cycle_dataset(seed002_temps(), seed002_error, duration_s=1500)  # 3 cycles per run
    with pytest.raises(ModelError, match="sensors.*nope"):
        MLRSeed002(sensors=["S1", "nope"]).fit(ds)
    with pytest.raises(ModelError, match="geometric_degree"):
        MLRSeed002(sensors=["S1"], geometric_degree=-1).fit(ds)
    with pytest.raises(ModelError, match="too few samples.*cycles"):
        MLRSeed002(sensors=["S1", "S2"]).fit(ds, ["a"])  # 3 cycles, 3 unknowns + 1 needed


# ------------------------------------------------------------------ seed 004 ---
SENS4 = ("Tf", "Tn", "Tr")
# rows: c0 (µm), c1 (µm/mm), c2 (µm/mm²); columns: const, per ΔTf, ΔTn, ΔTr
K4 = np.array(
    [
        [0.3, 1.5, 1.0, -0.8],
        [2.0e-3, 6.0e-3, 3.0e-3, 2.0e-3],
        [-1.0e-6, -1.2e-5, -2.0e-5, -8.0e-6],
    ]
)
GTAB = np.array([0.0, 0.8, -0.4, 1.1, 0.2, -0.9, 0.5, 1.3, -0.2, 0.6, -0.7])  # per target, µm


def seed004_temps():
    return {
        "w1": {"Tf": lambda t: 20 + rise(t, 7.0, 1500), "Tn": lambda t: 20 + rise(t, 5.0, 3000, 0, 10000),
               "Tr": lambda t: 20 + rise(t, 3.0, 5500)},  # fmt: skip
        "w2": {"Tf": lambda t: 20 + rise(t, 4.0, 2500, 0, 8000), "Tn": lambda t: 20 + rise(t, 6.0, 1200),
               "Tr": lambda t: 20 + rise(t, 2.0, 4000)},  # fmt: skip
    }


def seed004_error(T, p, run):
    dT = np.column_stack([np.ones(p.size), *[T[s] - 20.0 for s in SENS4]])
    c = dT @ K4.T
    g = GTAB[np.searchsorted(TARGETS, p)]
    return c[:, 0] + c[:, 1] * p + c[:, 2] * p**2 + g


@pytest.fixture(scope="module")
def ds004():
    ds = _cycle_dataset(seed004_temps(), seed004_error, mounting="fixed_fixed")
    ds.metadata.sensors.update(Tf="fixed_bearing_housing", Tn="nut_housing", Tr="free_bearing_housing")
    return ds


def test_seed004_fixed_fixed_recovers_parabola_regressions(ds004):
    m = MLRSeed004(preprocess=None).fit(ds004)
    assert m.shape_degree_ == 2 and m.sensors_ == list(SENS4)
    # each cycle's parabola also takes the table's parabola part over the targets
    q = P.polyfit(TARGETS, GTAB, 2)
    expected = K4.copy()
    expected[:, 0] += q
    np.testing.assert_allclose(m.curve_coef_, expected, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(m.geometric_um(TARGETS), GTAB - P.polyval(TARGETS, q), atol=1e-8)
    er = ds004.errors_run("w2")
    np.testing.assert_allclose(m.predict(ds004, "w2"), er["error_um"], atol=1e-6)


def test_seed004_forced_line_leaves_larger_residual():
    noisy = _cycle_dataset(seed004_temps(), seed004_error, mounting="fixed_fixed", noise_um=0.2, seed=9)
    sens = list(SENS4)
    par = MLRSeed004(preprocess=None, sensors=sens).fit(noisy)
    line = MLRSeed004(preprocess=None, sensors=sens, mounting="fixed_free").fit(noisy)
    assert line.shape_degree_ == 1
    r_par = rms(np.concatenate([noisy.errors_run(r)["error_um"] - par.predict(noisy, r) for r in noisy.run_ids]))
    r_line = rms(np.concatenate([noisy.errors_run(r)["error_um"] - line.predict(noisy, r) for r in noisy.run_ids]))
    assert 0.14 < r_par < 0.26  # the noise
    assert r_line > 3 * r_par  # the bow a line cannot follow (seed 004's point)


def test_seed004_geometric_polynomial(ds004):
    m = MLRSeed004(preprocess=None, geometric_degree=4).fit(ds004)
    q = P.polyfit(TARGETS, GTAB, 2)
    expected = P.polyval(TARGETS, P.polyfit(TARGETS, GTAB - P.polyval(TARGETS, q), 4))
    np.testing.assert_allclose(m.geometric_um(TARGETS), expected, atol=1e-8)


def test_seed004_bad_input(ds004):
    with pytest.raises(ModelError, match="mounting"):
        MLRSeed004(mounting="clamped").fit(ds004)
    with pytest.raises(ModelError, match="sensors.*T_missing"):
        MLRSeed004(sensors=["Tn", "T_missing"]).fit(ds004)
    only_ambient = _cycle_dataset({"r": {"Ta": lambda t: 20 + 0 * t}}, lambda T, p, r: 0 * p, duration_s=3600)
    only_ambient.metadata.sensors["Ta"] = "ambient"
    with pytest.raises(ModelError, match="MLRSeed004 needs temperature sensors at fixed_bearing_housing.*sensors.*has none"):
        MLRSeed004().fit(only_ambient)
    short = _cycle_dataset(seed004_temps(), seed004_error, mounting="fixed_fixed", duration_s=2000)
    with pytest.raises(ModelError, match="too few samples"):
        MLRSeed004(sensors=list(SENS4)).fit(short, ["w1"])  # 4 cycles < 3 sensors + 2


def test_seed004_benchmark_parabola_beats_line():
    """On the simulated fixed-fixed benchmark the parabola fits its training run better."""
    from thermbench.bench.datasets import load_benchmark
    from thermbench.bench.metrics import evaluate
    from thermbench.preprocess.filters import LimitFilter

    ds = load_benchmark("seed004_ff_x")
    par = MLRSeed004(preprocess=[LimitFilter()]).fit(ds, "warmup_6000")
    line = MLRSeed004(preprocess=[LimitFilter()], mounting="fixed_supported").fit(ds, "warmup_6000")
    e_par = evaluate(par, ds, ["warmup_6000"])["rmse_um"].iloc[0]
    e_line = evaluate(line, ds, ["warmup_6000"])["rmse_um"].iloc[0]
    assert e_par < 0.8 * e_line


# ---------------------------------------------------------------- common API ---
@pytest.mark.parametrize(
    "model",
    [
        MLRSeed001(degree=3, nut_sensor="a", bed_sensor="b", origin_mm=-150.0),
        MLRSeed002(sensors=["x", "y"], selection={"method": "gra"}, origin_mm=5.0, geometric_degree=None),
        MLRSeed004(sensors=["x"], mounting="fixed_fixed", geometric_degree=6, origin_mm=1.0),
    ],
)
def test_clone_get_params(model):
    c = clone(model)
    assert type(c) is type(model)
    assert c.get_params() == model.get_params()
    assert not hasattr(c, "coef_") and not hasattr(c, "train_runs_")


@pytest.mark.parametrize(
    "name, cls", [("mlr_seed001", MLRSeed001), ("mlr_seed002", MLRSeed002), ("mlr_seed004", MLRSeed004)]
)
def test_hydra_instantiate(name, cls):
    m = instantiate(OmegaConf.load(CONF / f"{name}.yaml"))
    assert type(m) is cls
    assert m.get_params() == cls().get_params()


@pytest.mark.parametrize("cls", [MLRSeed001, MLRSeed002, MLRSeed004])
def test_predict_before_fit(cls, ds004):
    with pytest.raises(ModelError, match="not fitted"):
        cls().predict(ds004, "w1")


def test_hydra_config_with_list_sensors_fits(ds004):
    cfg = OmegaConf.load(CONF / "mlr_seed004.yaml")
    cfg.sensors = list(SENS4)
    m = instantiate(cfg).fit(ds004)
    assert m.sensors_ == list(SENS4)
    assert m.required_inputs().sensors == SENS4 and not m.required_inputs().motion
