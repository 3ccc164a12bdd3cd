"""The state a run starts from (thermal_lag's start inputs) and the choice by the worst held-out run,
checked against a planted analytic truth (a warm start relaxing as 1 - exp(-t / tau)), against a
brute-force scikit-learn computation of the per-run held-out errors, and against the C runtime
(THERMAL_LAG layout 2) at every reading in both precisions."""

from __future__ import annotations

import numpy as np
import pytest

from tests.synth import rise
from tests.test_lumped import spindle_dataset
from thermbench.bench.metrics import evaluate
from thermbench.models.base import ModelError
from thermbench.models.thermal_lag import ThermalLag, first_order_lag, grid_choice, start_state

DT_S = 60.0
TAU_S = 3600.0
NOISE_UM = 0.05
#: each run's stored heat at its start (K above ambient at the warm sensor), its heating amplitude and timing
SPECS = [(0.0, 4.0, 600, 12000), (3.0, 6.0, 1800, 9000), (6.0, 3.0, 300, 18000), (1.5, 5.0, 3600, 14000),
         (4.5, 2.0, 900, 20000)]  # fmt: skip


def _runs(seed=0):
    """T_a reads the ambient plus the run's stored heat h plus its own heating; the error is
    2 x lag_3600 of the heating minus 1.5 x h (1 - exp(-t / 3600)) (the stored heat flowing out,
    0 at the first reading, which the readings count from) plus noise; T_b starts 0.5 K warmer from run
    to run and wanders, T_amb is 20 °C."""
    rng = np.random.default_rng(seed)
    runs = {}
    for k, (h, amp, on, off) in enumerate(SPECS):
        t = np.arange(0.0, 6 * 3600.0 + 1, DT_S)
        heat = rise(t, amp, 1200.0, on, off)
        err = 2.0 * first_order_lag(t, heat, TAU_S) - 1.5 * h * (1 - np.exp(-t / TAU_S)) + NOISE_UM * rng.standard_normal(t.size)
        runs[f"r{k}"] = {"t_s": t, "spindle_rpm": np.full(t.size, 1000.0), "read_t_s": t, "error_um": err,
                         "T_a_C": 20.0 + h + heat, "T_b_C": 21.0 + 0.5 * k + 0.3 * np.sin(t / 4000.0 + k), "T_amb_C": np.full(t.size, 20.0)}  # fmt: skip
    return runs


@pytest.fixture(scope="module")
def warm():
    return spindle_dataset(_runs(), sensors={"T_a": "spindle", "T_b": "structure", "T_amb": "ambient"}, operating=[])


def _rmse(m, ds, run):
    return float(evaluate(m, ds, [run])["rmse_um"].iloc[0])


def test_the_start_state_is_the_level_above_ambient_relaxing_with_each_time_constant(warm):
    m = ThermalLag(taus_s=[[0.0, 900.0, TAU_S]], select=False, start=True).fit(warm, ["r0", "r1", "r2", "r3"])
    assert m.start_reference_ == "T_amb"
    assert "start:T_a" in m.inputs_ and "start:T_b" in m.inputs_ and "start:T_amb" not in m.inputs_
    t = np.arange(0.0, 6 * 3600.0 + 1, DT_S)
    for tau in (900.0, TAU_S):  # h (1 - exp(-t / tau)) of run r2 (h = 6 K), by hand
        np.testing.assert_allclose(m._lags(warm, "r2", "start:T_a", [tau], t)[:, 0], 6.0 * (1 - np.exp(-t / tau)), atol=1e-9)
        np.testing.assert_allclose(start_state(t, 6.0, tau), 6.0 * (1 - np.exp(-t / tau)), atol=1e-12)
    level_b = 21.0 + 0.5 * 2 + 0.3 * np.sin(2.0) - 20.0  # T_b's first reading above the ambient's, run r2
    np.testing.assert_allclose(m._lags(warm, "r2", "start:T_b", [TAU_S], t)[:, 0], level_b * (1 - np.exp(-t / TAU_S)), atol=1e-9)
    # the model reads the reference sensor too, whatever the weights
    assert set(m.required_inputs().sensors) == {"T_a", "T_b", "T_amb"}


def test_with_the_start_state_a_warm_start_is_predicted_to_the_noise_floor_and_without_it_is_not(warm):
    train, held = ["r0", "r1", "r2", "r3"], "r4"
    sets = [[0.0, TAU_S]]
    cold = ThermalLag(taus_s=sets, select=False).fit(warm, train)
    hot = ThermalLag(taus_s=sets, select=False, start=True).fit(warm, train)
    assert _rmse(hot, warm, held) < 3 * NOISE_UM
    assert _rmse(cold, warm, held) > 10 * NOISE_UM  # the stored heat (4.5 K of r4) flows out unseen


def test_with_no_ambient_sensor_the_reference_is_the_mean_first_reading_of_the_sensors():
    ds = spindle_dataset(_runs(), sensors={"T_a": "spindle", "T_b": "structure"}, operating=[])
    m = ThermalLag(sensors=["T_a", "T_b"], taus_s=[[0.0, TAU_S]], select=False, start=True).fit(ds, ["r0", "r1", "r2"])
    assert m.start_reference_ is None
    t = np.arange(0.0, 6 * 3600.0 + 1, DT_S)
    a0, b0 = 20.0 + 3.0, 21.0 + 0.5 + 0.3 * np.sin(1.0)  # run r1's first readings
    level = a0 - (a0 + b0) / 2
    np.testing.assert_allclose(m._lags(ds, "r1", "start:T_a", [TAU_S], t)[:, 0], level * (1 - np.exp(-t / TAU_S)), atol=1e-9)


def test_runs_that_start_alike_or_too_few_runs_carry_no_start_state(warm):
    """A start state whose levels span less than 1 K over the training runs (the segments of one test
    that keep its log from its start start alike), or fewer than three runs: no such input."""
    runs = _runs()
    for r in runs.values():  # every run starts from the same stored heat, T_b alike
        r["T_a_C"] = r["T_a_C"] - r["T_a_C"][0] + 23.0
        r["T_b_C"] = r["T_b_C"] - r["T_b_C"][0] + 21.5
    alike = spindle_dataset(runs, sensors={"T_a": "spindle", "T_b": "structure", "T_amb": "ambient"}, operating=[])
    m = ThermalLag(taus_s=[[0.0, TAU_S]], select=False, start=True).fit(alike, ["r0", "r1", "r2", "r3"])
    assert not [i for i in m.inputs_ if i.startswith("start:")]
    two = ThermalLag(taus_s=[[0.0, TAU_S]], select=False, start=True).fit(warm, ["r1", "r2"])
    assert not [i for i in two.inputs_ if i.startswith("start:")]
    three = ThermalLag(taus_s=[[0.0, TAU_S]], select=False, start=True).fit(warm, ["r0", "r1", "r2"])
    assert [i for i in three.inputs_ if i.startswith("start:")] == ["start:T_a", "start:T_b"]


def test_the_c_runtime_carries_the_start_state_at_every_reading_in_both_precisions(warm, tmp_path):
    """THERMAL_LAG layout 2: the start state captured at the first sample (the rises' reference) in C,
    a second implementation of the inputs and the lags; the export's parity replays the held-out run."""
    from thermbench.export import export_model
    from thermbench.export import fileformat

    m = ThermalLag(taus_s=[[0.0, 900.0, TAU_S]], select=False, start=True).fit(warm, ["r0", "r1", "r2", "r3"])
    man = export_model(m, tmp_path / "tl", "tl", ds=warm, heldout=["r4"])
    p = man["parity"]["model"]
    assert man["kind"] == "THERMAL_LAG" and p["n_readings"] > 300
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01
    assert p["heldout_rmse_um_c"] == pytest.approx(_rmse(m, warm, "r4"), abs=1e-9)
    assert p["heldout_rmse_um_c"] < 3 * NOISE_UM
    assert fileformat.read(tmp_path / "tl" / "model.tbm").version == 2


def test_the_start_state_is_refused_with_stepwise_selection_in_one_line(warm):
    with pytest.raises(ModelError, match=r"^start: the start state enters with select: false"):
        ThermalLag(select=True, start=True).fit(warm, ["r0", "r1"])
    with pytest.raises(ModelError, match=r"^start: the start state enters through time constants above 0"):
        ThermalLag(taus_s=[[0.0]], select=False, start=True).fit(warm, ["r0", "r1"])


def _per_run_mse(X, y, groups, alpha, folds=None):
    """Each run's held-out mean square of StandardScaler + Ridge fitted on the runs outside its fold
    (``folds``: lists of runs; None: each run alone), by scikit-learn."""
    from sklearn.linear_model import Ridge
    from sklearn.pipeline import make_pipeline
    from sklearn.preprocessing import StandardScaler

    out = {}
    for fold in folds or [[r] for r in np.unique(groups)]:
        tr = ~np.isin(groups, fold)
        fit = make_pipeline(StandardScaler(), Ridge(alpha=alpha)).fit(X[tr], y[tr])
        for r in fold:
            te = groups == r
            out[r] = float(np.mean((y[te] - fit.predict(X[te])) ** 2))
    return out


def test_the_worst_run_choice_is_the_penalty_of_the_lowest_worst_held_out_run_by_scikit_learn():
    """grid_choice(score="worst") against a brute-force scikit-learn computation of every run's
    held-out error; on a design where the mean and the worst pick different penalties."""
    alphas = [0.01, 1.0, 30.0, 1000.0]
    for seed in range(50):
        rng = np.random.default_rng(seed)
        groups = np.repeat([f"g{i}" for i in range(5)], 40)
        X = rng.standard_normal((groups.size, 6))
        X[groups == "g2"] *= 3.0  # one run whose inputs reach further
        y = X @ rng.standard_normal(6) + rng.standard_normal(groups.size) * 2.0
        per = {a: _per_run_mse(X, y, groups, a) for a in alphas}
        worst = min(alphas, key=lambda a: max(per[a].values()))
        mean = min(alphas, key=lambda a: np.mean(list(per[a].values())))
        if worst != mean:
            break
    else:
        pytest.fail("no design among 50 where the mean and the worst pick differently")
    folds = [(np.flatnonzero(groups != r), np.flatnonzero(groups == r)) for r in np.unique(groups)]
    (rmse, _, a), _ = grid_choice(lambda h: X, [[0.0]], y, folds, "ridge", alphas, score="worst", groups=groups)
    assert a == worst and rmse == pytest.approx(np.sqrt(max(per[worst].values())), rel=1e-9)
    (rmse, _, a), _ = grid_choice(lambda h: X, [[0.0]], y, folds, "ridge", alphas)
    assert a == mean and rmse == pytest.approx(np.sqrt(np.mean(list(per[mean].values()))), rel=1e-9)
    # with folds of several runs, the worst is still that of one run, not of a fold's pooled rows
    three = [["g0", "g1"], ["g2", "g3"], ["g4"]]
    per3 = {a: _per_run_mse(X, y, groups, a, three) for a in alphas}
    worst3 = min(alphas, key=lambda a: max(per3[a].values()))
    folds3 = [(np.flatnonzero(~np.isin(groups, f)), np.flatnonzero(np.isin(groups, f))) for f in three]
    (rmse, _, a), _ = grid_choice(lambda h: X, [[0.0]], y, folds3, "ridge", alphas, score="worst", groups=groups)
    assert a == worst3 and rmse == pytest.approx(np.sqrt(max(per3[worst3].values())), rel=1e-9)


def test_a_thermal_lag_file_of_layout_1_still_loads_and_answers_as_layout_2(warm, tmp_path):
    """A THERMAL_LAG file written before the start state (layout 1: no reference after wB) answers
    as the same model written in layout 2, at every reading, in the C runtime."""
    import pandas as pd

    from thermbench.export import export_model, fileformat
    from thermbench.export.directory import replay_inputs
    from thermbench.export.runtime import replay

    m = ThermalLag(taus_s=[[0.0, TAU_S]], select=False).fit(warm, ["r0", "r1", "r2", "r3"])
    export_model(m, tmp_path / "tl", "tl", ds=warm, heldout=["r4"])
    v2 = fileformat.read(tmp_path / "tl" / "model.tbm")
    assert v2.version == 2
    old = tmp_path / "v1.tbm"
    fileformat.write(old, v2.kind, v2.dims, v2.payload[:-1], version=1)  # layout 1 ends at wB
    files, samples, temps, _ = replay_inputs(tmp_path / "tl", warm, "r4", "model", None, None)
    t = warm.errors[warm.errors["run_id"] == "r4"]["t_s"].to_numpy(dtype=float)
    queries = pd.DataFrame({"t_s": t, "axis_mm": np.zeros(t.size)})
    a = replay(files, samples, temps, queries)
    b = replay([old], samples, temps, queries)
    assert (a["rc"] == 0).all() and (b["rc"] == 0).all()
    np.testing.assert_array_equal(a["thermal_um"].to_numpy(), b["thermal_um"].to_numpy())
    assert np.isfinite(a["thermal_um"]).all() and np.ptp(a["thermal_um"].to_numpy()) > 1.0  # a real answer, not a constant


def twenty_sensors():
    """The runs of :func:`_runs` read by twenty sensors, each a gain of T_a's reading, starting 1.5 K
    per run further up or down (alternately) and a little noisy; no ambient sensor."""
    runs, rng = _runs(), np.random.default_rng(1)
    gains = rng.uniform(0.5, 1.5, 20)
    for k, r in enumerate(runs.values()):
        for i in range(20):
            r[f"S{i:02d}_C"] = (20.0 + gains[i] * (r["T_a_C"] - 20.0) + 1.5 * k * (-1) ** i
                                + 0.05 * rng.standard_normal(r["t_s"].size))  # fmt: skip
    return spindle_dataset(runs, sensors={f"S{i:02d}": "structure" for i in range(20)}, operating=[])


def test_twenty_sensors_with_their_start_states_export_within_the_c_runtimes_limits(tmp_path):
    """20 sensors and no ambient one: 40 inputs (each rise and each start state), beyond one input per
    sensor; the C runtime carries them at parity (the reference: the block's mean first reading)."""
    from thermbench.export import export_model

    ds = twenty_sensors()
    m = ThermalLag(taus_s=[[0.0, 900.0, TAU_S]], select=False, start=True).fit(ds, ["r0", "r1", "r2", "r3"])
    assert m.start_reference_ is None and len(m.inputs_) == 40
    man = export_model(m, tmp_path / "tl", "tl", ds=ds, heldout=["r4"])
    p = man["parity"]["model"]
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01


def test_the_start_level_follows_the_sensors_whose_mean_it_counts_from_on_one_dataset():
    """Two fits with different sensor lists on the same dataset object (its derived-value cache
    shared): each start level counts from the mean first reading of its own sensors."""
    ds = spindle_dataset(_runs(), sensors={"T_a": "spindle", "T_b": "structure", "T_c": "structure"}, operating=[])
    t = np.arange(0.0, 6 * 3600.0 + 1, DT_S)
    a0, b0, c0 = 20.0 + 3.0, 21.0 + 0.5 + 0.3 * np.sin(1.0), 20.0  # run r1's first readings (T_c: 20 °C by default)
    two = ThermalLag(sensors=["T_a", "T_b"], taus_s=[[0.0, TAU_S]], select=False, start=True).fit(ds, ["r0", "r1", "r2"])
    three = ThermalLag(sensors=["T_a", "T_b", "T_c"], taus_s=[[0.0, TAU_S]], select=False, start=True).fit(ds, ["r0", "r1", "r2"])
    np.testing.assert_allclose(two._lags(ds, "r1", "start:T_a", [TAU_S], t)[:, 0], (a0 - (a0 + b0) / 2) * (1 - np.exp(-t / TAU_S)), atol=1e-9)
    np.testing.assert_allclose(three._lags(ds, "r1", "start:T_a", [TAU_S], t)[:, 0], (a0 - (a0 + b0 + c0) / 3) * (1 - np.exp(-t / TAU_S)), atol=1e-9)


def machine_runs(n_runs=8, n_sensors=6, seed=3):
    """Runs whose error follows the machine's mean stored heat: each of ``n_sensors`` sensors reads the
    ambient (20 °C) plus the run's stored heat h, its own offset from it at the start (±1 K, drawn per
    run and sensor: where the sensor sits) and a gain of the run's heating; the error is 2 x lag_3600 of
    the heating minus 1.5 x (the sensors' mean level above ambient at the start) (1 - exp(-t / 3600))
    plus noise. Returns (runs, each run's mean start level)."""
    rng = np.random.default_rng(seed)
    gains = rng.uniform(0.5, 1.5, n_sensors)
    runs, levels = {}, {}
    for k in range(n_runs):
        h, amp, on, off = rng.uniform(0.0, 6.0), rng.uniform(2.0, 6.0), rng.uniform(300, 3600), rng.uniform(9000, 20000)
        t = np.arange(0.0, 6 * 3600.0 + 1, DT_S)
        heat = rise(t, amp, 1200.0, on, off)
        offsets = rng.uniform(-1.0, 1.0, n_sensors)
        levels[f"m{k}"] = float(np.mean(h + offsets))
        err = (2.0 * first_order_lag(t, heat, TAU_S) - 1.5 * levels[f"m{k}"] * (1 - np.exp(-t / TAU_S))
               + NOISE_UM * rng.standard_normal(t.size))  # fmt: skip
        runs[f"m{k}"] = {"t_s": t, "spindle_rpm": np.full(t.size, 1000.0), "read_t_s": t, "error_um": err,
                         "T_amb_C": np.full(t.size, 20.0)}  # fmt: skip
        for i in range(n_sensors):
            runs[f"m{k}"][f"S{i}_C"] = 20.0 + h + offsets[i] + gains[i] * heat
    return runs, levels


def test_the_machines_mean_start_level_is_chosen_where_the_error_follows_the_stored_heat_and_the_c_runtime_carries_it(tmp_path):
    """The start state as one level, the sensors' mean first reading above the ambient's: chosen over
    each sensor's level by the folds of whole runs where the error follows the machine's mean stored
    heat (six sensors, seven training runs: a level per sensor and lag fits the runs' offsets), the
    level by hand, and the C runtime (each sensor's start state at 1/6 of the mean's weights) at parity."""
    from thermbench.export import export_model
    from thermbench.models.thermal_lag import START_MEAN

    runs, levels = machine_runs()
    ds = spindle_dataset(runs, sensors={**{f"S{i}": "structure" for i in range(6)}, "T_amb": "ambient"}, operating=[])
    train = [f"m{k}" for k in range(7)]
    m = ThermalLag(taus_s=[[0.0, 900.0, TAU_S]], select=False, start=True, score="worst").fit(ds, train)
    assert m.start_form_ == "mean"
    assert [i for i in m.inputs_ if i.startswith("start:")] == [START_MEAN]
    assert {r["start"] for r in m.cv_results_} == {"each", "mean"}  # both forms were scored
    t = np.arange(0.0, 6 * 3600.0 + 1, DT_S)
    np.testing.assert_allclose(m._lags(ds, "m7", START_MEAN, [TAU_S], t)[:, 0], levels["m7"] * (1 - np.exp(-t / TAU_S)), atol=1e-9)
    each = ThermalLag(taus_s=[[0.0, 900.0, TAU_S]], select=False, start=True, score="worst")
    each._set_inputs(ds, train, check_params_of(each))
    assert each.start_sensors(START_MEAN) == [f"S{i}" for i in range(6)]
    held = _rmse(m, ds, "m7")
    assert held < 4 * NOISE_UM
    man = export_model(m, tmp_path / "tl", "tl", ds=ds, heldout=["m7"])
    p = man["parity"]["model"]
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01
    assert p["heldout_rmse_um_c"] == pytest.approx(held, abs=1e-9)


def check_params_of(model):
    from thermbench.models.params import check_params

    return check_params(model, model.params_model)


def test_with_no_ambient_sensor_there_is_no_mean_level_the_sensors_levels_count_from_their_mean():
    """With no ambient sensor the sensors' mean above their own mean is 0: only each sensor's level."""
    runs, _ = machine_runs()
    ds = spindle_dataset(runs, sensors={f"S{i}": "structure" for i in range(6)}, operating=[])
    m = ThermalLag(taus_s=[[0.0, TAU_S]], select=False, start=True).fit(ds, [f"m{k}" for k in range(7)])
    assert m.start_form_ == "each" and {r["start"] for r in m.cv_results_} == {"each"}
