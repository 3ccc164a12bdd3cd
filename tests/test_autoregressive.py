"""Seed 003 auto-regressive model: recovers a known ARX process driven by the feed,
and predicts a different feed schedule by free-run simulation, without sensors."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate
from numpy.polynomial import polynomial as P
from omegaconf import OmegaConf
from sklearn.base import clone

from tests.synth import make_dataset
from thermbench.models.autoregressive import AutoRegressiveSeed003, parse_operating
from thermbench.models.base import ModelError

CONF = Path(__file__).resolve().parents[1] / "conf" / "model"
STEP = 600.0
TARGETS = np.arange(0.0, 501.0, 50.0)
LEVELS = np.array([0.0, 1500.0, 3000.0, 4500.0, 6000.0])
GEOM = (1.0, 1.0e-2, -4.0e-5, 3.0e-8)  # geometric error, µm vs mm
# truth: per curve coefficient, c(k) = a1 c(k-1) + a2 c(k-2) + b0 u(k) + b1 u(k-1) (+ d)
TRUTH = {
    "c0": {"a": (1.2, -0.35), "b": (2.0e-3, 1.0e-3), "d": 0.0},  # roots 0.7, 0.5; µm per mm/min
    "c1": {"a": (0.8, -0.1), "b": (1.0e-5, 4.0e-6), "d": 0.0},  # µm/mm per mm/min
}


def schedule(n_blocks, seed):
    """A feed level per 600-s block, u(k) for k = 1..n (mm/min)."""
    return np.random.default_rng(seed).choice(LEVELS, size=n_blocks)


def arx(u, a, b, d):
    """The ARX recursion written out directly, at rest before k = 1."""
    c = np.zeros(u.size + 1)
    uu = np.r_[0.0, u]  # uu[k] = u(k), uu[0] = 0
    for k in range(1, c.size):
        c[k] = d
        for i, ai in enumerate(a, start=1):
            c[k] += ai * (c[k - i] if k - i >= 0 else 0.0)
        for j, bj in enumerate(b):
            c[k] += bj * (uu[k - j] if k - j >= 0 else 0.0)
    return c


def arx_run(run, u, truth=TRUTH, cold=(0.4, 2.0e-3)):
    """Process (1 Hz, feed piecewise constant per block, only an ambient sensor) and
    readings: one measuring cycle at every grid time t_k = 600 k (all targets at once),
    error = geometric + cold curve + c0(k) + c1(k)·P."""
    n = u.size
    t = np.arange(0.0, n * STEP + 1.0)
    blk = np.minimum((t // STEP).astype(int), n - 1)
    feed = np.where(t < n * STEP, u[blk], 0.0)
    axis = 250 + 250 * np.sin(2 * np.pi * t / 37.0)
    proc = pd.DataFrame({"run_id": run, "t_s": t, "axis_mm": axis, "feed_mm_min": feed,
                         "spindle_rpm": 1000.0 + 0.5 * feed, "T_amb_C": 20.0})  # fmt: skip
    c = {k: arx(u, v["a"], v["b"], v["d"]) for k, v in truth.items()}
    tk = STEP * np.arange(n + 1)
    rt = np.repeat(tk, TARGETS.size)
    rx = np.tile(TARGETS, tk.size)
    k = np.repeat(np.arange(n + 1), TARGETS.size)
    err = P.polyval(rx, GEOM) + cold[0] + cold[1] * rx + c["c0"][k] + c["c1"][k] * rx
    return proc, pd.DataFrame({"run_id": run, "t_s": rt, "target_mm": rx, "error_um": err}), c


def arx_dataset(schedules, truth=TRUTH):
    ps, es, cs = [], [], {}
    for run, u in schedules.items():
        p, e, c = arx_run(run, u, truth)
        ps.append(p), es.append(e)
        cs[run] = c
    ds = make_dataset(pd.concat(ps), pd.concat(es), {"T_amb": "ambient"})
    return ds, cs


@pytest.fixture(scope="module")
def data():
    sched = {"train1": schedule(30, 1), "train2": schedule(30, 2), "test": schedule(25, 99)}
    return sched, *arx_dataset(sched)


def test_recovers_arx_coefficients(data):
    _, ds, _ = data
    m = AutoRegressiveSeed003().fit(ds, ["train1", "train2"])
    assert m.shape_degree_ == 1  # fixed_free: a line
    for i, key in enumerate(("c0", "c1")):
        np.testing.assert_allclose(m.ar_coef_[i], TRUTH[key]["a"], rtol=1e-6)
        np.testing.assert_allclose(m.input_coef_[i][:, 0], TRUTH[key]["b"], rtol=1e-6)
        assert abs(m.offset_[i]) < 1e-6 * np.max(np.abs(TRUTH[key]["b"])) * 6000
        assert np.all(np.abs(m.ar_roots_[i]) < 1)
    np.testing.assert_allclose(np.sort(np.abs(m.ar_roots_[0])), [0.5, 0.7], rtol=1e-6)


def test_free_run_prediction_on_another_schedule(data):
    sched, ds, truth = data
    m = AutoRegressiveSeed003().fit(ds, ["train1", "train2"])
    c = truth["test"]
    tk = STEP * np.arange(sched["test"].size + 1)
    for x in (0.0, 175.0, 500.0):
        want = c["c0"] + c["c1"] * x
        np.testing.assert_allclose(m.predict_thermal_at(ds, "test", tk, x), want, atol=1e-6)
    # the whole positioning error at the measured readings
    np.testing.assert_allclose(m.predict(ds, "test"), ds.errors_run("test")["error_um"], atol=1e-6)
    # between grid points: linear in time
    mid = 0.5 * (tk[3] + tk[4])
    want_mid = 0.5 * (c["c0"][3] + c["c0"][4]) + 0.5 * (c["c1"][3] + c["c1"][4]) * 300.0
    assert m.predict_thermal_at(ds, "test", mid, 300.0)[0] == pytest.approx(want_mid, abs=1e-6)


def test_prediction_uses_only_the_operating_log(data):
    """Nothing measured in the predicted run is used: replacing its errors changes nothing."""
    sched, ds, _ = data
    m = AutoRegressiveSeed003().fit(ds, ["train1", "train2"])
    before = m.predict_thermal_at(ds, "test", [3000.0, 9000.0], [100.0, 400.0])
    ds.errors.loc[ds.errors["run_id"] == "test", "error_um"] += 1e3
    after = m.predict_thermal_at(ds, "test", [3000.0, 9000.0], [100.0, 400.0])
    ds.errors.loc[ds.errors["run_id"] == "test", "error_um"] -= 1e3
    np.testing.assert_array_equal(before, after)


def test_no_sensors_needed(data):
    _, ds, _ = data
    assert list(ds.metadata.sensors.values()) == ["ambient"]
    with pytest.warns(RuntimeWarning, match="linearly dependent"):  # spindle_rpm is affine in feed here
        m = AutoRegressiveSeed003(operating=["feed_mm_min", "spindle_rpm"], na=1, nb=1).fit(ds, ["train1", "train2"])
    inp = m.required_inputs()
    assert inp.sensors == () and inp.operating == ("feed_mm_min", "spindle_rpm") and inp.motion
    m2 = AutoRegressiveSeed003(operating=("feed_mm_min", "feed_mm_min^2"), na=1, nb=1).fit(ds, ["train1", "train2"])
    assert m2.required_inputs().operating == ("feed_mm_min",)


def test_fixed_fixed_parabola_and_powers():
    """A parabola per cycle (fixed_fixed) and a feed² input, both recovered."""
    truth = {
        "c0": {"a": (0.6,), "b": (1.0e-3,), "d": 0.0},
        "c1": {"a": (0.5,), "b": (2.0e-6,), "d": 0.0},
    }
    sched = {"r1": schedule(30, 5), "r2": schedule(30, 6)}
    ps, es, cs = [], [], {}
    for run, u in sched.items():
        # c2 (µm/mm²) driven by feed²: c2(k) = 0.7 c2(k-1) + 1e-13 u(k)²
        p, e, c = arx_run(run, u, truth)
        c2 = arx(u**2, (0.7,), (1.0e-13,), 0.0)
        k = np.round(e["t_s"].to_numpy() / STEP).astype(int)
        e["error_um"] += c2[k] * e["target_mm"].to_numpy() ** 2
        ps.append(p), es.append(e)
    ds = make_dataset(pd.concat(ps), pd.concat(es), {"T_amb": "ambient"}, mounting="fixed_fixed")
    m = AutoRegressiveSeed003(na=1, nb=1, operating=("feed_mm_min", "feed_mm_min^2")).fit(ds)
    assert m.shape_degree_ == 2
    np.testing.assert_allclose(m.ar_coef_[:, 0], [0.6, 0.5, 0.7], rtol=1e-6)
    np.testing.assert_allclose(m.input_coef_[:, 0, 0], [1.0e-3, 2.0e-6, 0.0], rtol=1e-6, atol=1e-14)
    np.testing.assert_allclose(m.input_coef_[:, 0, 1], [0.0, 0.0, 1.0e-13], rtol=1e-6, atol=1e-18)


def test_unstable_fit_raises():
    truth = {"c0": {"a": (1.02,), "b": (1.0e-4,), "d": 0.0}, "c1": {"a": (0.5,), "b": (1.0e-6,), "d": 0.0}}
    ds, _ = arx_dataset({"r": schedule(30, 3)}, truth)
    with pytest.raises(ModelError, match="c0 is unstable"):
        AutoRegressiveSeed003(na=1, nb=1).fit(ds)


def test_parse_operating():
    assert parse_operating(("feed_mm_min", "load_N^2", "spindle_rpm^1.5")) == [
        ("feed_mm_min", 1.0),
        ("load_N", 2.0),
        ("spindle_rpm", 1.5),
    ]
    for bad in ((), ("feed mm",), ("feed^-1",), ("feed", "feed")):
        with pytest.raises(ModelError, match="operating"):
            parse_operating(bad)


def test_bad_input(data):
    _, ds, _ = data
    with pytest.raises(ModelError, match="operating.*'nope'"):
        AutoRegressiveSeed003(operating=("nope",)).fit(ds, "train1")
    with pytest.raises(ModelError, match="na"):
        AutoRegressiveSeed003(na=-1).fit(ds, "train1")
    with pytest.raises(ModelError, match="nb"):
        AutoRegressiveSeed003(nb=0).fit(ds, "train1")
    with pytest.raises(ModelError, match="sample_s"):
        AutoRegressiveSeed003(sample_s=0.0).fit(ds, "train1")
    with pytest.raises(ModelError, match="mounting"):
        AutoRegressiveSeed003(mounting="loose").fit(ds, "train1")
    with pytest.raises(ModelError, match="not fitted"):
        AutoRegressiveSeed003().predict(ds, "test")
    short, _ = arx_dataset({"s": schedule(4, 7)})  # 4 grid steps < 6 unknowns + 1
    with pytest.raises(ModelError, match="too few samples.*grid steps.*sample_s=600"):
        AutoRegressiveSeed003().fit(short)


def test_clone_get_params():
    m = AutoRegressiveSeed003(na=3, nb=1, sample_s=300.0, operating=("load_N",), mounting="fixed_fixed",
                              geometric_degree=4, origin_mm=-10.0)  # fmt: skip
    c = clone(m)
    assert c.get_params() == m.get_params() and not hasattr(c, "ar_coef_")


def test_hydra_instantiate_and_fit(data):
    _, ds, _ = data
    m = instantiate(OmegaConf.load(CONF / "ar_seed003.yaml"))
    assert type(m) is AutoRegressiveSeed003
    assert m.get_params() == AutoRegressiveSeed003().get_params()
    m = instantiate(OmegaConf.load(CONF / "ar_seed003.yaml"), operating=OmegaConf.create(["feed_mm_min"]))
    m.fit(ds, ["train1", "train2"])  # a ListConfig operating works
    np.testing.assert_allclose(m.ar_coef_[0], TRUTH["c0"]["a"], rtol=1e-6)
