"""Sensor faults at the compensator (thermbench/bench/faults.py, deployed.py): detection, replacement, bounds.

The faults are planted into the shipped real spindle test (fl_thermal: five constant-speed blocks
to fit the limits on, the stepped tail to plant into), so the truth of each check is what was
planted, at the sample it was planted; the clean tail is a real run no sensor of which is faulty.
"""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from thermbench.bench.deployed import deployed_predictions, plant_fault, without_sensors
from thermbench.bench.faults import PLAUSIBLE_C, Bounds, FaultMonitor, SensorLimits, _may_fire, _others_lines
from thermbench.bench.metrics import residual_metrics
from thermbench.data.reference import thermal_errors


@pytest.fixture(scope="module")
def fl():
    from thermbench.bench.datasets import load_benchmark
    from thermbench.bench.splits import dataset_view

    ds = dataset_view(load_benchmark("fl_thermal"), "ch5", True, True)
    blocks = [r for r in ds.run_ids if ds.metadata.runs[r].condition is not None]
    (tail,) = [r for r in ds.run_ids if r not in blocks]
    limits = SensorLimits.fit(ds, blocks, list(ds.metadata.sensors))
    return ds, blocks, tail, limits


def _monitor(ds, run, limits) -> tuple[FaultMonitor, np.ndarray]:
    m = FaultMonitor(limits)
    pr = ds.process_run(run)
    cols = [ds.metadata.sensor_column(s) for s in limits.sensors]
    t = pr["t_s"].to_numpy(dtype=float)
    for tk, Tk in zip(t, pr[cols].to_numpy(dtype=float)):
        m.step(tk, Tk)
    return m, t


def _onset(ds, tail) -> float:
    """An hour into the tail's readings (the tail's log starts with the test)."""
    return float(ds.errors_run(tail)["t_s"].min()) + 3600.0


def _ridge_line(R: np.ndarray, i: int, others: list[int]) -> np.ndarray:
    """scikit-learn's ridge on standardised columns, the penalty 1 % of the rows (RIDGE_SHARE: 1 % of
    each variance), mapped back to the raw rises: [intercept, weights of ``others``]."""
    from sklearn.linear_model import Ridge
    from sklearn.preprocessing import StandardScaler

    sc = StandardScaler().fit(R[:, others])
    r = Ridge(alpha=0.01 * len(R)).fit(sc.transform(R[:, others]), R[:, i])
    w = r.coef_ / sc.scale_
    return np.concatenate([[r.intercept_ - sc.mean_ @ w], w])


def test_the_others_lines_are_scikit_learns_ridge_and_nearly_recover_an_exact_mix():
    """C = 1 + 2 A - B exactly over three runs: C's line is scikit-learn's ridge on the standardised
    rises of A and B (penalty 1 % of the rows), which shrinks the mix only a little; no run held out
    departs by more than the floor's worth, so the tolerance is the floor."""
    rng = np.random.default_rng(1)
    A, B = np.cumsum(rng.standard_normal((2, 300)), axis=1)
    R = np.column_stack([A, B, 1.0 + 2.0 * A - B])
    icpt, coef, tol, _ = _others_lines(R, np.repeat(["r1", "r2", "r3"], 100), np.ones(3, bool))
    np.testing.assert_allclose([icpt[2], *coef[2, :2]], _ridge_line(R, 2, [0, 1]), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(coef[2, :2], [2.0, -1.0], rtol=0.05)
    assert tol[2] == 2.0  # OTHERS_MIN_K
    assert coef[0, 0] == coef[1, 1] == coef[2, 2] == 0.0


def test_a_sensor_that_never_moved_is_predicted_by_none_and_never_judged_stuck():
    R = np.column_stack([np.linspace(0, 5, 200), np.zeros(200)])
    icpt, coef, tol, _ = _others_lines(R, np.repeat(["a", "b"], 100), np.array([True, False]))
    assert np.isinf(tol[1]) and np.isinf(tol[0])  # nothing predicts the still one; the moving one has no moving other


def test_the_clean_real_tail_judges_no_sensor_faulty_and_the_model_reads_it_as_logged(fl):
    """The real tail is outside the blocks' envelope on 63 % of its readings (README), yet no
    sensor of it is faulty: no rule may fire, and the model's answer as deployed (without
    bounds) is its raw answer to the digit."""
    ds, blocks, tail, limits = fl
    m, _ = _monitor(ds, tail, limits)
    assert m.faulty == []
    pr = ds.process_run(tail)
    cols = [ds.metadata.sensor_column(s) for s in limits.sensors]
    assert not _may_fire(limits, pr["t_s"].to_numpy(dtype=float), pr[cols].to_numpy(dtype=float))  # no loop needed
    for r in blocks:
        assert _monitor(ds, r, limits)[0].faulty == [], r
    from thermbench.models.linear_history import RidgeHistory

    model = RidgeHistory().fit(ds, blocks)
    dep, mon, acted = deployed_predictions(model, ds, tail, limits, None)
    np.testing.assert_array_equal(dep, model.predict(ds, tail))
    assert mon.faulty == [] and not acted.any()


@pytest.mark.parametrize("kind,rule", [("jump", "range"), ("open", "open")])
@pytest.mark.parametrize("sensor", ["t1", "t5", "t16"])
def test_a_jump_and_an_open_sensor_are_judged_at_the_first_sample_after_the_onset(fl, kind, rule, sensor):
    ds, blocks, tail, limits = fl
    onset = _onset(ds, tail)
    bad = plant_fault(ds, tail, sensor, kind, onset)
    m, t = _monitor(bad, tail, limits)
    i = limits.sensors.index(sensor)
    assert m.faulty == [sensor]
    assert m.fault[i] == rule
    assert m.onset_s[i] == t[t >= onset][0]  # the first sample that carries the fault


def test_a_drift_is_judged_no_later_than_the_range_rule_allows(fl):
    """10 K/h from the onset: judged at the latest when the planted offset alone takes the rise
    past the range rule's threshold, computed here from the blocks' logs (the largest and
    smallest rise of t5 over the five blocks, each block's rise from its own first sample)."""
    ds, blocks, tail, limits = fl
    i = limits.sensors.index("t5")
    col = ds.metadata.sensor_column("t5")
    rises = [ds.process_run(r)[col].to_numpy(dtype=float) - ds.process_run(r)[col].iloc[0] for r in blocks]
    hi, lo = max(r.max() for r in rises), min(r.min() for r in rises)
    assert limits.rise_hi_K[i] == pytest.approx(hi) and limits.rise_lo_K[i] == pytest.approx(lo)
    onset = _onset(ds, tail)
    pr = ds.process_run(tail)
    rise_tail = pr[col].to_numpy(dtype=float) - pr[col].iloc[0]
    t = pr["t_s"].to_numpy(dtype=float)
    threshold = hi + max(hi - lo, 3.0)
    offset = 10.0 * np.maximum(t - onset, 0.0) / 3600.0
    latest = t[(t >= onset) & (np.min(rise_tail[t >= onset]) + offset >= threshold)][0]
    m, _ = _monitor(plant_fault(ds, tail, "t5", "drift", onset), tail, limits)
    assert m.faulty == ["t5"]
    assert onset <= m.onset_s[i] <= latest


def test_a_stuck_sensor_is_judged_once_its_reading_should_have_moved(fl):
    """t5 stuck an hour into the tail while the spindle steps: judged, never before its reading
    stopped; by the stuck rule no sooner than its stated delay."""
    ds, blocks, tail, limits = fl
    onset = _onset(ds, tail)
    m, t = _monitor(plant_fault(ds, tail, "t5", "stuck", onset), tail, limits)
    i = limits.sensors.index("t5")
    assert m.faulty == ["t5"] and m.fault[i] in ("stuck", "others")
    assert m.onset_s[i] >= onset
    if m.fault[i] == "stuck":
        assert m.onset_s[i] - onset >= limits.stuck_after_s[i] - 15.0  # one sample of 15 s


def test_a_faulty_sensor_is_read_as_the_others_predict_it(fl):
    """After an open circuit in t5, the model reads t5 as its first reading plus the rise its
    line on the other sensors gives (the line checked against scikit-learn's ridge on the blocks'
    rises)."""
    ds, blocks, tail, limits = fl
    i = limits.sensors.index("t5")
    cols = [ds.metadata.sensor_column(s) for s in limits.sensors]
    R = np.vstack([ds.process_run(r)[cols].to_numpy(dtype=float) - ds.process_run(r)[cols].to_numpy(dtype=float)[0]
                   for r in blocks])  # fmt: skip
    others = [k for k in range(len(cols)) if k != i]
    w = _ridge_line(R, i, others)
    np.testing.assert_allclose([limits.icpt[i], *limits.coef[i, others]], w, rtol=1e-6, atol=1e-9)
    onset = _onset(ds, tail)
    bad = plant_fault(ds, tail, "t5", "open", onset)
    m = FaultMonitor(limits)
    pr = bad.process_run(tail)
    T = pr[cols].to_numpy(dtype=float)
    out = np.vstack([m.step(tk, Tk) for tk, Tk in zip(pr["t_s"].to_numpy(dtype=float), T)])
    after = pr["t_s"].to_numpy() >= onset
    assert (T[after, i] == 850.0).all() and not (out[after, i] > PLAUSIBLE_C[1]).any()
    rise = T[after][:, others] - T[0, others]
    np.testing.assert_allclose(out[after, i], T[0, i] + w[0] + rise @ w[1:], atol=1e-9)
    np.testing.assert_array_equal(out[:, others], T[:, others])  # the healthy ones as read


def test_bounds_clip_the_value_then_the_rate_by_hand():
    b = Bounds(max_um=10.0, rate_um_s=0.5)
    out, acted = b.apply([0.0, 1.0, 2.0, 3.0, 10.0], [0.0, 5.0, 20.0, 20.0, -30.0])
    # value: 0, 5, 10, 10, -10; rate from the first: 0.5 a second
    np.testing.assert_allclose(out, [0.0, 0.5, 1.0, 1.5, 1.5 - 3.5])
    assert acted.tolist() == [False, True, True, True, True]


def test_bounds_fit_from_the_training_errors(fl):
    """max_um: 1.5 x the largest |thermal error| of the blocks; rate_um_s: 2 x the largest change
    over 600 s (the blocks' readings are every 15 s: 40 readings), per second, by pandas here."""
    ds, blocks, tail, limits = fl
    te = thermal_errors(ds)
    te = te[te["run_id"].isin(blocks)]
    b = Bounds.fit(ds, blocks)
    assert b.max_um == pytest.approx(1.5 * te["thermal_um"].abs().max())
    change = 0.0
    for _, g in te.groupby("run_id"):
        g = g.sort_values("t_s")
        assert np.allclose(np.diff(g["t_s"]), 15.0)
        change = max(change, (g["thermal_um"].shift(-40) - g["thermal_um"]).abs().max())
    assert b.rate_um_s == pytest.approx(2.0 * change / 600.0)


@pytest.mark.parametrize("how", ["reconstruct", "refit"])
@pytest.mark.parametrize("sensor", ["t1", "t5", "t16"])
def test_a_jump_as_deployed_stays_within_its_bounds_and_beats_no_compensation(fl, sensor, how):
    """The raw model follows a 30 K jump (by the sensor's weight in it: t1 and t16 make it worse
    than no compensation); as deployed, from the sample it is judged the model reads the sensor as
    the others predict it (what the export runs) or the family fitted without the sensor takes over,
    every value is within the bounds in value and rate, and the run is compensated better than not
    at all and better than by the raw model."""
    from thermbench.models.linear_history import RidgeHistory

    ds, blocks, tail, limits = fl
    model = RidgeHistory().fit(ds, blocks)
    bounds = Bounds.fit(ds, blocks)
    bad = plant_fault(ds, tail, sensor, "jump", _onset(ds, tail))
    tr = thermal_errors(ds)
    tr = tr[tr["run_id"] == tail]
    none = float(np.sqrt(np.mean(tr["error_um"] ** 2)))
    raw = residual_metrics(tr["error_um"], model.predict(bad, tail), tr["thermal_um"])["rmse_um"]
    fb = without_sensors(model, ds, blocks, (sensor,))
    assert sensor not in fb.required_inputs().sensors
    dep, mon, _ = deployed_predictions(model, bad, tail, limits, bounds, (lambda faulty: fb) if how == "refit" else None)
    assert mon.faulty == [sensor]
    rmse = residual_metrics(tr["error_um"], dep, tr["thermal_um"])["rmse_um"]
    t = tr["t_s"].to_numpy(dtype=float)
    assert np.all(np.abs(dep) <= bounds.max_um + 1e-9)
    assert np.all(np.abs(np.diff(dep)) <= bounds.rate_um_s * np.diff(t) + 1e-9)
    assert rmse < min(none, raw), (raw, none, rmse)
    assert (raw > none) == (sensor != "t5"), (raw, none)


def test_plant_fault_changes_one_sensor_of_one_run_from_the_onset(fl):
    ds, blocks, tail, _ = fl
    onset = _onset(ds, tail)
    col, other = ds.metadata.sensor_column("t5"), ds.metadata.sensor_column("t1")
    before = ds.process_run(tail)
    t = before["t_s"].to_numpy()
    for kind, expect in (("jump", before[col] + 30.0 * (t >= onset)),
                         ("drift", before[col] + 10.0 * np.maximum(t - onset, 0) / 3600.0),
                         ("stuck", np.where(t >= onset, before[col][t >= onset].iloc[0], before[col])),
                         ("open", np.where(t >= onset, 850.0, before[col]))):  # fmt: skip
        bad = plant_fault(ds, tail, "t5", kind, onset)
        np.testing.assert_allclose(bad.process_run(tail)[col], expect)
        pd.testing.assert_series_equal(bad.process_run(tail)[other], before[other])
        pd.testing.assert_frame_equal(bad.process_run(blocks[0]), ds.process_run(blocks[0]))
    pd.testing.assert_series_equal(ds.process_run(tail)[col], before[col])  # the dataset itself untouched


@pytest.mark.parametrize("args,says", [(("t5", "melt"), "fault kind 'melt'"), (("t99", "jump"), "sensor 't99'")])
def test_plant_fault_names_what_is_wrong(fl, args, says):
    ds, _, tail, _ = fl
    with pytest.raises(ValueError, match=says):
        plant_fault(ds, tail, *args, _onset(ds, tail))


def test_the_limits_round_trip_through_json(fl):
    ds, blocks, tail, limits = fl
    back = SensorLimits.from_dict(json.loads(json.dumps(limits.to_dict())))
    onset = _onset(ds, tail)
    bad = plant_fault(ds, tail, "t5", "drift", onset)
    a, b = _monitor(bad, tail, limits)[0], _monitor(bad, tail, back)[0]
    assert a.fault == b.fault and np.array_equal(a.onset_s, b.onset_s, equal_nan=True)


@pytest.mark.parametrize("kind", [None, "jump", "drift", "stuck", "open"])
def test_a_whole_log_through_the_monitor_is_the_monitor_sample_by_sample(fl, kind):
    """FaultMonitor.run skips the per-sample loop on a log where no rule comes near firing; what it
    returns must be what stepping every sample gives, clean or faulty."""
    ds, blocks, tail, limits = fl
    bad = ds if kind is None else plant_fault(ds, tail, "t5", kind, _onset(ds, tail))
    pr = bad.process_run(tail)
    cols = [ds.metadata.sensor_column(s) for s in limits.sensors]
    t, T = pr["t_s"].to_numpy(dtype=float), pr[cols].to_numpy(dtype=float)
    used, m = FaultMonitor.run(limits, t, T)
    one = FaultMonitor(limits)
    stepped = np.vstack([one.step(tk, Tk) for tk, Tk in zip(t, T)])
    np.testing.assert_array_equal(used, stepped)
    assert m.fault == one.fault and np.array_equal(m.onset_s, one.onset_s, equal_nan=True)


@pytest.mark.parametrize("kind", ["jump", "drift", "stuck"])
def test_a_fault_in_one_sensor_judges_that_sensor_and_no_other(fl, kind):
    """Planted into each of six sensors in turn (t1, t4 and t5 nearly collinear: t4's line weights t1
    many times over, so t4 departs first when t1 drifts): the sensor judged faulty is the one planted,
    never a neighbour; a jump and a drift are always judged; a stuck reading is judged whenever, past
    the stuck delay, the rise its line on the clean others gives has moved by more than STUCK_MOVE_K
    since the onset (worked out here from the clean log)."""
    from thermbench.bench.faults import STUCK_MOVE_K

    ds, blocks, tail, limits = fl
    onset = _onset(ds, tail)
    cols = [ds.metadata.sensor_column(c) for c in limits.sensors]
    clean = ds.process_run(tail)
    t = clean["t_s"].to_numpy(dtype=float)
    rise = clean[cols].to_numpy(dtype=float) - clean[cols].to_numpy(dtype=float)[0]
    strict = 0
    for s in ("t1", "t3", "t4", "t5", "t9", "t16"):
        pr = plant_fault(ds, tail, s, kind, onset).process_run(tail)
        _, m = FaultMonitor.run(limits, pr["t_s"].to_numpy(dtype=float), pr[cols].to_numpy(dtype=float))
        if kind != "stuck":
            assert m.faulty == [s], (s, m.faulty)
            continue
        assert m.faulty in ([s], []), (s, m.faulty)
        i = limits.sensors.index(s)
        pred = limits.icpt[i] + rise @ limits.coef[i]
        k0 = np.flatnonzero(t >= onset)[0]
        late = t > t[k0] + limits.stuck_after_s[i]
        if (np.abs(pred[late] - pred[k0]) > STUCK_MOVE_K + 0.5).any():  # clearly should have moved
            assert m.faulty == [s], s
            strict += 1
    assert kind != "stuck" or strict >= 2  # the rule is put to the test on some of them


def test_a_sensor_open_from_the_first_sample_is_never_read_as_open(fl):
    """t5 open from the start: the model never reads 850 °C; it reads t5 where the others' mean and
    the blocks' offset from it put its start, plus the rise the others predict."""
    ds, blocks, tail, limits = fl
    first = float(ds.process_run(tail)["t_s"].iloc[0])
    pr = plant_fault(ds, tail, "t5", "open", first).process_run(tail)
    cols = [ds.metadata.sensor_column(s) for s in limits.sensors]
    used, m = FaultMonitor.run(limits, pr["t_s"].to_numpy(dtype=float), pr[cols].to_numpy(dtype=float))
    i = limits.sensors.index("t5")
    assert m.faulty == ["t5"] and m.fault[i] == "open" and m.onset_s[i] == first
    assert np.isfinite(used).all() and used[:, i].max() < PLAUSIBLE_C[1]
    truth = ds.process_run(tail)[cols[i]].to_numpy(dtype=float)
    assert abs(used[0, i] - truth[0]) < 5.0  # the start estimated within a few K of the real reading


def test_without_sensors_sets_a_list_and_leaves_a_rule_alone(fl):
    """A family whose sensors are None gets the list of those it reads, less the dropped; one whose
    sensors are a rule (physics_spindle_hybrid: 'auto') has no refit without one (None)."""
    from thermbench.models.linear_history import RidgeHistory
    from thermbench.models.lumped import LumpedThermalNetwork

    ds, blocks, _, _ = fl
    fitted = RidgeHistory().fit(ds, blocks)
    alt = without_sensors(fitted, ds, blocks, ("t5", "t99"))
    assert list(alt.required_inputs().sensors) == [s for s in fitted.required_inputs().sensors if s != "t5"]
    assert without_sensors(LumpedThermalNetwork(sensors="auto"), ds, blocks, ("t5",)) is None
