"""Seed 003 auto-regressive model: recovers a known ARX process driven by the feed,
and predicts a different feed schedule by free-run simulation, without sensors; on a
spindle test with history (readings long after the log starts) it recovers hand-written
first-order modes and predicts a held-out program; the output-error refinement."""

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate
from numpy.polynomial import polynomial as P
from omegaconf import OmegaConf
from sklearn.base import clone

from tests.synth import make_dataset
from thermbench.data.dataset import Dataset
from thermbench.data.schema import Metadata
from thermbench.data.views import channel_view
from thermbench.models.autoregressive import AutoRegressiveSeed003, parse_operating
from thermbench.models.base import FallbackWarning, ModelError

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
    m = AutoRegressiveSeed003(na=2, nb=2).fit(ds, ["train1", "train2"])  # TRUTH's orders
    assert m.shape_degree_ == 1  # fixed_free: a line
    for i, key in enumerate(("c0", "c1")):
        np.testing.assert_allclose(m.ar_coef_[i], TRUTH[key]["a"], rtol=1e-6)
        np.testing.assert_allclose(m.input_coef_[i][:, 0], TRUTH[key]["b"], rtol=1e-6)
        assert abs(m.offset_[i]) < 1e-6 * np.max(np.abs(TRUTH[key]["b"])) * 6000
        assert np.all(np.abs(m.ar_roots_[i]) < 1)
    np.testing.assert_allclose(np.sort(np.abs(m.ar_roots_[0])), [0.5, 0.7], rtol=1e-6)


def test_free_run_prediction_on_another_schedule(data):
    sched, ds, truth = data
    m = AutoRegressiveSeed003(na=2, nb=2).fit(ds, ["train1", "train2"])
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
    with pytest.raises(ModelError, match=r"^AutoRegressiveSeed003\.criterion: expected one of \['equation', 'output'\], got 'free'$"):
        AutoRegressiveSeed003(criterion="free").fit(ds, "train1")
    with pytest.raises(ModelError, match="mounting"):
        AutoRegressiveSeed003(mounting="loose").fit(ds, "train1")
    with pytest.raises(ModelError, match="not fitted"):
        AutoRegressiveSeed003().predict(ds, "test")
    short, _ = arx_dataset({"s": schedule(4, 7)})  # 4 grid steps < 4 unknowns (na=2, nb=1) + 1
    with pytest.raises(ModelError, match="too few samples.*grid steps.*sample_s=600"):
        AutoRegressiveSeed003().fit(short)


def test_clone_get_params():
    m = AutoRegressiveSeed003(na=3, nb=1, sample_s=300.0, operating=("load_N",), criterion="equation",
                              mounting="fixed_fixed", geometric_degree=4, origin_mm=-10.0)  # fmt: skip
    c = clone(m)
    assert c.get_params() == m.get_params() and not hasattr(c, "ar_coef_")


def test_hydra_instantiate_and_fit(data):
    _, ds, _ = data
    m = instantiate(OmegaConf.load(CONF / "ar_seed003.yaml"))
    assert type(m) is AutoRegressiveSeed003
    assert m.get_params() == AutoRegressiveSeed003().get_params()
    m = instantiate(OmegaConf.load(CONF / "ar_seed003.yaml"), operating=OmegaConf.create(["feed_mm_min"]), nb=2)
    m.fit(ds, ["train1", "train2"])  # a ListConfig operating works (nb=2: TRUTH's orders)
    np.testing.assert_allclose(m.ar_coef_[0], TRUTH["c0"]["a"], rtol=1e-6)


# ------------------------------------------------------------- history ---
# A spindle test seen at one fixed point (format 2 channel view, like fl_thermal): the process log
# starts cold at 0 s, the readings of a run only later (a segment with its history). The truth is
# written out here: first-order thermal modes τ dθ/dt = K·u − θ under a spindle speed held constant
# per 600-s block, in closed form block by block.
LOG_S = 15.0  # process and reading period (s), as the fl_thermal logger
SPEEDS_RPM = np.array([0.0, 1250.0, 2500.0, 3750.0, 5000.0])
Z0_UM = 3.0  # the reading of the cold machine at 0 s: the reference of the whole test
MODES = ((3000.0, 2.0e-3), (20000.0, 3.0e-3))  # (τ s, K µm/rpm): a fast and a slow mode


def speed_profile(hours, seed):
    """A stepped spindle program: random speeds held for 1..12 blocks of 600 s (rpm per block)."""
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < hours * 3600 / STEP:
        out += [float(rng.choice(SPEEDS_RPM))] * int(rng.integers(1, 13))
    return np.array(out[: int(hours * 3600 / STEP)])


def first_order(t_s, levels_rpm, tau_s, gain_um_per_rpm):
    """θ(t) of τ dθ/dt = K·u − θ from θ(0) = 0, u = levels_rpm[k] on [600 k, 600 (k+1)):
    θ(t) = θ(s)·e^{−(t−s)/τ} + K·u·(1 − e^{−(t−s)/τ}) inside the block starting at s."""
    t = np.asarray(t_s, dtype=float)
    theta = np.zeros(t.size)
    start = 0.0
    for k, u in enumerate(levels_rpm):
        s = STEP * k
        inside = (t >= s) & (t < s + STEP)
        decay = np.exp(-(t[inside] - s) / tau_s)
        theta[inside] = start * decay + gain_um_per_rpm * u * (1.0 - decay)
        start = start * np.exp(-STEP / tau_s) + gain_um_per_rpm * u * (1.0 - np.exp(-STEP / tau_s))
    theta[t >= STEP * len(levels_rpm)] = start
    return theta


def response(t_s, levels_rpm, modes=MODES):
    return sum(first_order(t_s, levels_rpm, tau, k) for tau, k in modes)


def arx_of_modes(modes=MODES):
    """The exact ARX on the 600-s grid: per mode θ_i(k) = α_i θ_i(k−1) + β_i u(k), α = e^{−600/τ},
    β = K(1 − α); their sum has a = (α1 + α2, −α1 α2), b = (β1 + β2, −(β1 α2 + β2 α1))."""
    (al1, be1), (al2, be2) = [(np.exp(-STEP / tau), k * (1 - np.exp(-STEP / tau))) for tau, k in modes]
    return (al1 + al2, -al1 * al2), (be1 + be2, -(be1 * al2 + be2 * al1))


def spindle_history_dataset(profiles, first_reading_s, modes=MODES, noise_um=0.0, seed=0):
    """One whole test per profile (log from 0 s, reference = its first reading, cold), seen through
    the fixed-point channel view, then cut like a segment with its history: the readings of run r
    only from ``first_reading_s[r]`` on, their ``thermal_um`` still counted from 0 s."""
    rng = np.random.default_rng(seed)
    procs, errs = [], []
    for run, levels in profiles.items():
        t = np.arange(0.0, STEP * levels.size, LOG_S)
        rpm = levels[(t // STEP).astype(int)]
        procs.append(pd.DataFrame({"run_id": run, "t_s": t, "spindle_rpm": rpm, "T_amb_C": 20.0}))
        z = Z0_UM + response(t, levels, modes) + noise_um * rng.standard_normal(t.size)
        z[0] = Z0_UM
        errs.append(pd.DataFrame({"run_id": run, "t_s": t, "channel": "Z", "error_um": z}))
    meta = {"format": "thermbench-dataset/2", "machine": {"name": "synthetic_spindle"}, "parts": ["spindle"],
            "sensors": {"T_amb": "ambient"}, "operating": ["spindle_rpm"],
            "channels": {"Z": {"kind": "fixed_point", "direction": "Z", "location": "test_mandrel"}},
            "reference": {"mode": "first_reading"}, "runs": {r: {} for r in profiles}}  # fmt: skip
    process, errors = pd.concat(procs, ignore_index=True), pd.concat(errs, ignore_index=True)
    whole = Dataset(Metadata.model_validate(meta), process, errors)
    view = channel_view(whole, "Z")
    er = view.errors
    keep = er["t_s"].to_numpy() >= er["run_id"].map(first_reading_s).to_numpy()
    return Dataset(view.metadata, view.process, er[keep].reset_index(drop=True), view.path, channel=view.channel)


@pytest.fixture(scope="module")
def history():
    profiles = {"h1": speed_profile(30, 1), "h2": speed_profile(30, 2), "test": speed_profile(30, 9)}
    return profiles, spindle_history_dataset(profiles, {"h1": 20000.0, "h2": 20000.0, "test": 30000.0})


@pytest.mark.parametrize("criterion", ["equation", "output"])
def test_history_recovers_the_modes_and_predicts_a_new_program(history, criterion):
    """Readings only after 20 000 s of a log that starts at 0 s: the fit uses the grid steps whose
    regressors are measured, recovers the ARX of the two modes, and the free run from 0 s of a
    held-out program matches the closed-form response."""
    profiles, ds = history
    m = AutoRegressiveSeed003(na=2, nb=2, operating=["spindle_rpm"], criterion=criterion).fit(ds, ["h1", "h2"])
    a, b = arx_of_modes()
    assert m.shape_degree_ == 0  # a fixed point: the drift itself
    np.testing.assert_allclose(m.ar_coef_[0], a, rtol=1e-6)
    np.testing.assert_allclose(m.input_coef_[0][:, 0], b, rtol=1e-6)
    assert abs(m.offset_[0]) < 1e-6
    er = ds.errors_run("test")
    t = er["t_s"].to_numpy()
    want = response(t, profiles["test"])
    on_grid = np.isclose(t % STEP, 0.0)
    np.testing.assert_allclose(m.predict_thermal_at(ds, "test", t[on_grid], 0.0), want[on_grid], atol=1e-6)
    # between grid steps the free run is interpolated linearly: close to the exponentials
    assert np.max(np.abs(m.predict_thermal_at(ds, "test", t, 0.0) - want)) < 0.1
    # the whole error: reference + thermal
    np.testing.assert_allclose(m.predict(ds, "test")[on_grid], er["error_um"].to_numpy()[on_grid], atol=1e-6)


def test_history_first_reading_is_not_cold(history):
    """The old model subtracted a run's first cycle and started c = 0 there. With a history the
    first reading of the segment is warm: the reference is the test's cold reading (0 s), and
    the model's thermal error at the segment's first reading is the history's, not 0."""
    profiles, ds = history
    er = ds.errors_run("h1")
    t_first, first = float(er["t_s"].iloc[0]), float(er["thermal_um"].iloc[0])
    assert t_first >= 20000.0 and first > 5.0  # warm when the readings start
    m = AutoRegressiveSeed003(na=2, nb=2, operating=["spindle_rpm"]).fit(ds, ["h1", "h2"])
    # the drift from the test's cold reading (reference first_reading, across the segments of the
    # run): the gauge's zero Z0 is not part of it, and neither is the first reading's Z0 + 16 µm
    np.testing.assert_allclose(m.reference_coef_, [0.0], atol=1e-9)
    assert float(m.geometric_um(0.0)) == pytest.approx(0.0, abs=1e-9)
    # (20 000 s lies between grid steps: the free run interpolated linearly there)
    assert m.predict_thermal_at(ds, "h1", t_first, 0.0)[0] == pytest.approx(first, abs=0.05)
    on_grid = np.isclose(er["t_s"].to_numpy() % STEP, 0.0)
    np.testing.assert_allclose(m.predict(ds, "h1")[on_grid], er["error_um"].to_numpy()[on_grid], atol=1e-6)
    # the simulated history runs from c = 0 at the log's start (0 s), where nothing was read
    grid, c = m.simulate(ds, "h1")
    assert grid[0] == 0.0 and c[0, 0] == 0.0
    np.testing.assert_allclose(c[:, 0], response(grid, profiles["h1"]), atol=1e-6)


def test_history_too_short_for_the_orders_is_one_line(history):
    """The equation-error rows need c(k-1)..c(k-na) measured: readings over fewer grid steps than
    the unknowns is the 'too few samples' line, even with a long history before them."""
    profiles, ds = history
    er = ds.errors
    late = er[(er["run_id"] != "h1") | (er["t_s"] >= 107000.0)]  # h1's last readings, 3 grid steps
    short = Dataset(ds.metadata, ds.process, late.reset_index(drop=True), ds.path, channel=ds.channel)
    with pytest.raises(ModelError, match="too few samples: [0-9]+ grid steps.*'h1'"):
        AutoRegressiveSeed003(na=2, nb=2, operating=["spindle_rpm"]).fit(short, ["h1"])


def test_output_error_refinement_under_measurement_noise(history):
    """White noise on the readings biases the equation-error estimate (a noisy c(k-1) is a
    regressor); minimising the free-run error does not, and predicts the held-out program better."""
    profiles, _ = history
    tau, k = 6000.0, 4.0e-3
    ds = spindle_history_dataset(profiles, {"h1": 20000.0, "h2": 20000.0, "test": 30000.0},
                                 modes=((tau, k),), noise_um=1.0, seed=3)  # fmt: skip
    alpha = np.exp(-STEP / tau)
    t = ds.errors_run("test")["t_s"].to_numpy()
    truth = first_order(t, profiles["test"], tau, k)
    rmse, a = {}, {}
    for crit in ("equation", "output"):
        m = AutoRegressiveSeed003(na=1, nb=1, operating=["spindle_rpm"], criterion=crit).fit(ds, ["h1", "h2"])
        a[crit] = m.ar_coef_[0, 0]
        rmse[crit] = float(np.sqrt(np.mean((m.predict_thermal_at(ds, "test", t, 0.0) - truth) ** 2)))
        assert m.free_run_rmse_["c0"] > 0
    assert abs(a["equation"] - alpha) > 0.03  # biased towards a faster decay
    assert abs(a["output"] - alpha) < 0.005
    assert rmse["output"] < 0.3 < 1.0 < rmse["equation"]


def test_output_error_on_an_unstable_process_raises():
    """The output-error search keeps every trial stable; data that want a root beyond the unit
    circle end at the bound, which is the 'unstable' line too."""
    truth = {"c0": {"a": (1.02,), "b": (1.0e-4,), "d": 0.0}, "c1": {"a": (0.5,), "b": (1.0e-6,), "d": 0.0}}
    ds, _ = arx_dataset({"r": schedule(30, 3)}, truth)
    with pytest.raises(ModelError, match="c0 is unstable"):
        AutoRegressiveSeed003(na=1, nb=1, criterion="output").fit(ds)


def test_output_error_matches_equation_error_on_exact_data(data):
    """On data an ARX generates exactly, the output-error refinement stays at the exact solution."""
    _, ds, _ = data
    m = AutoRegressiveSeed003(na=2, nb=2, criterion="output").fit(ds, ["train1", "train2"])
    for i, key in enumerate(("c0", "c1")):
        np.testing.assert_allclose(m.ar_coef_[i], TRUTH[key]["a"], rtol=1e-6)
        np.testing.assert_allclose(m.input_coef_[i][:, 0], TRUTH[key]["b"], rtol=1e-6)
        assert m.free_run_rmse_[key] < 1e-9


def test_output_error_at_the_stability_bound_falls_back(history):
    """A drift that keeps accelerating (not driven by the speed) asks the free-run fit for a root
    beyond the unit circle: its search stops at the bound, and the model keeps the stable
    equation-error fit (noise pulls that one inside), saying so."""
    profiles, _ = history
    ds = spindle_history_dataset({r: profiles[r] for r in ("h1", "h2")}, {"h1": 20000.0, "h2": 20000.0},
                                 noise_um=1.0, seed=5)  # fmt: skip
    drift = 0.05 * (ds.errors["t_s"] / 3600.0) ** 2  # µm, 45 µm after 30 h
    ds.errors["thermal_um"] += drift
    ds.errors["error_um"] += drift
    ee = AutoRegressiveSeed003(na=1, nb=1, operating=["spindle_rpm"], criterion="equation").fit(ds, ["h1", "h2"])
    assert np.abs(ee.ar_roots_[0]).max() < 1.0
    with pytest.warns(FallbackWarning, match="output-error fit of curve coefficient c0 ends at the stability bound"):
        oe = AutoRegressiveSeed003(na=1, nb=1, operating=["spindle_rpm"], criterion="output").fit(ds, ["h1", "h2"])
    np.testing.assert_array_equal(oe.ar_coef_, ee.ar_coef_)
    np.testing.assert_array_equal(oe.input_coef_, ee.input_coef_)
