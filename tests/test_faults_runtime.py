"""The C runtime's sensor checks and bounds (embedded/src/tb_faults.c, ``tb_replay --faults``) against the
Python ones (thermbench/bench/faults.py FaultMonitor, Bounds) and a hand computation: the faults file
an export writes, read back as the C runtime reads it (float32), over the shipped real spindle test's
stepped tail with each of the four faults planted into it (deployed.plant_fault), in double precision
and in single precision (the Cortex-M4F build)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from thermbench.bench.deployed import FAULT_KINDS, plant_fault
from thermbench.bench.faults import Bounds, FaultMonitor, SensorLimits
from thermbench.export import export_model, read_manifest, runtime
from thermbench.export.directory import replay_inputs
from thermbench.export.faultfile import FAULTS_FILE, read_faults, write_faults
from thermbench.export.fileformat import ModelFileError


@pytest.fixture(scope="module")
def fl_export(tmp_path_factory):
    """ch5 of fl_thermal: linear_history fitted on the five constant-speed blocks, exported with them."""
    from thermbench.bench.datasets import load_benchmark
    from thermbench.bench.splits import dataset_view
    from thermbench.models.linear_history import LinearHistory

    ds = dataset_view(load_benchmark("fl_thermal"), "ch5", True, True)
    blocks = [r for r in ds.run_ids if ds.metadata.runs[r].condition is not None]
    (tail,) = [r for r in ds.run_ids if r not in blocks]
    out = tmp_path_factory.mktemp("faults") / "lh"
    export_model(LinearHistory().fit(ds, blocks), out, "lh", ds=ds)
    return ds, tail, out, read_manifest(out)


def _python(limits: SensorLimits, bounds: Bounds, samples: pd.DataFrame, sensors, raw_total) -> tuple[list[str], np.ndarray, np.ndarray]:
    """FaultMonitor stepped sample by sample: each sample's rules as tb_replay writes them (a digit per
    sensor); the C runtime's raw totals on the replaced readings bounded by Bounds.apply."""
    codes = {None: "0", "open": "1", "range": "2", "rate": "3", "stuck": "4", "others": "5"}
    m = FaultMonitor(limits)
    rules = []
    for t, T in zip(samples["t_s"].to_numpy(float), samples[sensors].to_numpy(float)):
        m.step(t, T)
        rules.append("".join(codes[f] for f in m.fault))
    bounded, acted = bounds.apply(samples["t_s"].to_numpy(float), raw_total)
    return rules, bounded, acted


def test_the_faults_file_holds_the_manifest_s_limits_and_bounds(fl_export):
    ds, tail, out, man = fl_export
    f = man["faults"]
    assert f["file"] == FAULTS_FILE and f["bytes"] == (out / FAULTS_FILE).stat().st_size
    limits, bounds = read_faults(out / FAULTS_FILE, man["temperatures"])
    want = SensorLimits.from_dict(f["limits"])
    assert limits.sensors == want.sensors
    for key in ("rise_lo_K", "rise_hi_K", "rate_max_K_h", "flat_s", "icpt", "coef", "tol_K", "start_offset_K", "rate_tol"):
        a, b = getattr(limits, key), getattr(want, key)
        assert (np.isinf(a) == np.isinf(b)).all(), key
        np.testing.assert_allclose(np.where(np.isinf(a), 0, a), np.where(np.isinf(b), 0, b), rtol=1e-6, atol=1e-6, err_msg=key)
    assert bounds.max_um == pytest.approx(f["bounds"]["max_um"], rel=1e-6)
    assert bounds.rate_um_s == pytest.approx(f["bounds"]["rate_um_s"], rel=1e-6)


@pytest.mark.parametrize("flags, tol_um", [((), 1e-9), (("-DTB_SINGLE",), 1e-3)])
@pytest.mark.parametrize("kind", ["clean", *FAULT_KINDS])
def test_c_checks_and_bounds_equal_python_at_every_sample(fl_export, kind, flags, tol_um):
    """Each fault planted into sensor t2 an hour into the tail: at every sample the C runtime's rule of
    every sensor is Python's (the same rule, at the same sample: none on the clean tail, t2's from the
    planted onset on), and its bounded correction is the Python bounds' on the totals of the model
    reading what Python's monitor gave it (the model's own C/Python parity is tests/test_parity.py's)."""
    ds, tail, out, man = fl_export
    sensors = list(man["temperatures"])
    onset = float(ds.errors_run(tail)["t_s"].min()) + 3600.0
    d = ds if kind == "clean" else plant_fault(ds, tail, "t2", kind, onset)
    files, samples, temps, _ = replay_inputs(out, d, tail)
    q = pd.DataFrame({"t_s": samples["t_s"].to_numpy(float), "axis_mm": 0.0})
    exe = runtime.build("tb_replay", list(flags))
    c = runtime.replay(files, samples, temps, q, exe=exe, live=True, faults=out / FAULTS_FILE)
    limits, bounds = read_faults(out / FAULTS_FILE, sensors)
    cols = temps[: len(sensors)]
    used, mon = FaultMonitor.run(limits, samples["t_s"].to_numpy(float), samples[cols].to_numpy(float))
    replaced = samples.copy()
    replaced[cols] = used
    raw = runtime.replay(files, replaced, temps, q, exe=exe, live=True)
    rules, bounded, acted = _python(limits, bounds, samples, cols, raw["total_um"].to_numpy(float))
    assert c["rules"].tolist() == rules
    # the model read what Python's monitor gave it: its unbounded totals are those on the replaced readings
    np.testing.assert_allclose(c["total_um"].to_numpy(float), raw["total_um"].to_numpy(float), rtol=0, atol=tol_um)
    got = c["bounded_um"].to_numpy(float)
    assert (np.isnan(got) == np.isnan(bounded)).all()
    np.testing.assert_allclose(got[~np.isnan(got)], bounded[~np.isnan(bounded)], rtol=0, atol=tol_um)
    assert (c["bounded"].to_numpy() == acted.astype(int)).mean() > (1.0 if not flags else 0.999) - 1e-12
    i = sensors.index("t2")
    if kind == "clean":
        assert set("".join(rules)) == {"0"}
    else:  # the planted fault, in t2 only, judged at or after the onset
        assert mon.faulty == ["t2"] and {r[:i] + r[i + 1:] for r in rules} == {"0" * (len(sensors) - 1)}
        first = int(np.flatnonzero(c["rules"].str[i] != "0")[0])
        assert c["t_s"].iloc[first] >= onset and c["t_s"].iloc[first] == mon.onset_s[i]
    assert np.nanmax(np.abs(got)) <= bounds.max_um * (1 + 1e-6)
    dt = np.diff(c["t_s"].to_numpy(float))
    assert np.nanmax(np.abs(np.diff(got)) - bounds.rate_um_s * dt) <= tol_um


def _hand_limits() -> SensorLimits:
    """Two sensors, B's rise the others' line 0.5 + 2 A (tolerance 2 K), A's 0 + 0.5 B (2 K); rises of
    0 to 4 K (range margin 4 K), rates up to 10 K/h (limit 25 K/h), unchanged for at most 1000 s
    (stuck after 2000 s)."""
    return SensorLimits(("A", "B"), np.array([0.0, 0.0]), np.array([4.0, 4.0]), np.array([10.0, 10.0]), np.array([1000.0, 1000.0]),
                        np.array([0.0, 0.5]), np.array([[0.0, 0.5], [2.0, 0.0]]), np.array([2.0, 2.0]), np.array([0.0, 0.0]), 600.0)  # fmt: skip


def test_the_checks_and_bounds_by_hand(seed001_exports, tmp_path):
    """B reads 20.0 at the first sample, then rises with A as its line says, then jumps by 5 K at
    t = 120 s. Rate there, by hand: (25 - e) * 3600 / 600 with e = 20 + (1 - exp(-60/600)) (B's
    previous reading - 20)... beyond 25 K/h, so rule 'rate' fires at 120 s; from then on the model reads
    B as 20 + 0.5 + 2 (A - 20). A bound of 3 µm and 0.01 µm/s on answers of 0, 10, -10, -10 µm
    a minute apart: 0, 0.6, -0.0 (0.6 - 0.6), -0.6."""
    lim = _hand_limits()
    path = tmp_path / "faults.tbm"
    write_faults(path, lim, Bounds(3.0, 0.01))
    A = [20.0, 20.5, 21.0, 21.5]
    B = [20.0, 21.5, 27.5, 23.5]  # 21.5 = 20 + 0.5 + 2 * 0.5; 27.5: a 5 K jump over the line's 22.5
    samples = pd.DataFrame({"t_s": [0.0, 60.0, 120.0, 180.0], "axis_mm": 0.0, "feed_mm_min": 0.0, "A": A, "B": B})
    # at 60 s each rise lies within 0.25 K of its line (tolerance 2 K): no fault
    a = 1 - math.exp(-60 / 600)
    e60 = 20.0 + a * (21.5 - 20.0)
    rate120 = (27.5 - (e60 + a * (27.5 - e60))) * 3600 / 600
    assert rate120 > 25.0 and (21.5 - e60) * 6 < 25.0  # the rate rule: fires at 120 s, not at 60 s
    m = FaultMonitor(lim)
    read = [m.step(t, [x, y]) for t, x, y in zip(samples["t_s"], A, B)]
    assert m.fault == [None, "rate"] and m.onset_s[1] == 120.0
    np.testing.assert_allclose([r[1] for r in read], [20.0, 21.5, 20.0 + 0.5 + 2 * 1.0, 20.0 + 0.5 + 2 * 1.5])
    # the C runtime: the seed001 model reads two sensors (its T_nut_C and T_bed_C are A and B here)
    q = pd.DataFrame({"t_s": samples["t_s"], "axis_mm": 0.0})
    s = samples.rename(columns={"A": "T_nut_C", "B": "T_bed_C"})
    c = runtime.replay([seed001_exports / "mlr" / "model.tbm"], s, ["T_nut_C", "T_bed_C"], q, live=True, faults=path)
    assert c["rules"].tolist() == ["00", "00", "03", "03"]
    # the bound by hand, on answers set here: tb_faults_bound through the Python reader's Bounds
    _, b = read_faults(path)
    out, acted = b.apply([0.0, 60.0, 120.0, 180.0], [0.0, 10.0, -10.0, -10.0])
    np.testing.assert_allclose(out, [0.0, 0.6, 0.0, -0.6], atol=1e-6)
    assert acted.tolist() == [False, True, True, True]
    # the C bound on the model's own answers: the Python bound of the C totals on the replaced readings
    raw = runtime.replay([seed001_exports / "mlr" / "model.tbm"], s.assign(T_bed_C=[r[1] for r in read]),
                         ["T_nut_C", "T_bed_C"], q, live=True)  # fmt: skip
    want, _ = b.apply(q["t_s"].to_numpy(float), raw["total_um"].to_numpy(float))
    np.testing.assert_allclose(c["bounded_um"].to_numpy(float), want, atol=1e-9)


def test_a_not_a_number_answer_leaves_the_rate_bound_going_from_the_last():
    """An answer that is not finite passes as it is (as tb_faults_bound passes it), acts no bound,
    and the rate bound goes on from the last value."""
    out, acted = Bounds(100.0, 0.1).apply([0.0, 10.0, 20.0, 30.0], [0.0, np.nan, 50.0, 50.0])
    assert np.isnan(out[1]) and not acted[1]
    np.testing.assert_allclose(out[[0, 2, 3]], [0.0, 2.0, 3.0])  # 0.1 µm/s over 20 s, then 10 s
    assert acted.tolist() == [False, False, True, True]
    out, acted = Bounds(100.0, 0.1).apply([0.0, 10.0], [np.inf, 5.0])
    assert np.isinf(out[0]) and not acted[0] and out[1] == 5.0


def test_a_sensor_open_from_the_first_sample_starts_where_the_others_put_it(tmp_path, seed001_exports):
    """B open (NaN) from the first sample: it starts at A's reading plus its start offset (0 here), its
    rule is 'open' at once, and the model reads it as 0.5 + 2 A's rise above that start."""
    lim = _hand_limits()
    path = tmp_path / "faults.tbm"
    write_faults(path, lim, None)
    s = pd.DataFrame({"t_s": [0.0, 60.0], "axis_mm": 0.0, "feed_mm_min": 0.0, "T_nut_C": [20.0, 21.0],
                      "T_bed_C": [np.nan, np.nan]})  # fmt: skip
    q = pd.DataFrame({"t_s": [0.0, 60.0], "axis_mm": 0.0})
    c = runtime.replay([seed001_exports / "mlr" / "model.tbm"], s, ["T_nut_C", "T_bed_C"], q, live=True, faults=path)
    assert c["rules"].tolist() == ["01", "01"]
    m = FaultMonitor(lim)
    read = [m.step(t, T) for t, T in zip([0.0, 60.0], [[20.0, np.nan], [21.0, np.nan]])]
    np.testing.assert_allclose([r[1] for r in read], [20.0 + 0.5, 20.0 + 0.5 + 2.0])
    raw = runtime.replay([seed001_exports / "mlr" / "model.tbm"], s.assign(T_bed_C=[r[1] for r in read]),
                         ["T_nut_C", "T_bed_C"], q, live=True)  # fmt: skip
    np.testing.assert_allclose(c["bounded_um"], raw["total_um"], atol=1e-9)  # no bound in the file: none acts
    assert (c["bounded"] == 0).all()


def test_a_damaged_or_foreign_faults_file_is_refused(fl_export, seed001_exports, tmp_path):
    _, _, out, _ = fl_export
    data = bytearray((out / FAULTS_FILE).read_bytes())
    data[70] ^= 0xFF
    bad = tmp_path / "faults.tbm"
    bad.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="CRC"):
        read_faults(bad)
    s = pd.DataFrame({"t_s": [0.0, 1.0], "axis_mm": 0.0, "feed_mm_min": 0.0, "T_nut_C": 20.0, "T_bed_C": 20.0})
    q = pd.DataFrame({"t_s": [1.0], "axis_mm": [0.0]})
    with pytest.raises(runtime.RuntimeFailed, match="CRC|error -5"):
        runtime.replay([seed001_exports / "mlr" / "model.tbm"], s, ["T_nut_C", "T_bed_C"], q, live=True, faults=bad)
    with pytest.raises(runtime.RuntimeFailed, match="error -4"):  # an envelope file is not a faults file
        runtime.replay([seed001_exports / "mlr" / "model.tbm"], s, ["T_nut_C", "T_bed_C"], q, live=True,
                       faults=seed001_exports / "mlr" / "envelope.tbm")  # fmt: skip
    with pytest.raises(ModelFileError, match="not a faults file"):
        read_faults(seed001_exports / "mlr" / "envelope.tbm")


def test_a_drift_is_judged_by_its_rate_before_its_rise_departs(tmp_path, seed001_exports):
    """Three sensors that move together (each line half the other two), the rises' tolerance wide (100 K)
    and the rates' 5 K/h; C drifts at 10 K/h from the first sample while A and B hold. Its high-pass
    rate, by hand (the average e += (1 - exp(-dt/600)) (T - e), rate = (T - e) 3600/600), passes 5 K/h
    at the sample computed here, long before its 100 K rise tolerance: C, and only C, is judged
    'others' there (its reconstruction explains A's and B's departures; A's or B's would not), in
    Python and in C alike, and from then on the model reads C as A and B put it: 20 °C."""
    lim = SensorLimits(("A", "B", "C"), np.zeros(3), np.full(3, 100.0), np.full(3, 100.0), np.full(3, 1e6), np.zeros(3),
                       np.array([[0.0, 0.5, 0.5], [0.5, 0.0, 0.5], [0.5, 0.5, 0.0]]), np.full(3, 100.0), np.zeros(3), 600.0,
                       np.full(3, 5.0))  # fmt: skip
    t = np.arange(0.0, 3600.0, 60.0)
    c = 20.0 + 10.0 * t / 3600.0
    e, first = 20.0, None
    for k in range(1, t.size):  # the hand computation of C's rate
        e += (1.0 - math.exp(-60.0 / 600.0)) * (c[k] - e)
        if first is None and (c[k] - e) * 6.0 > 5.0:
            first = k
    assert first is not None and t[first] < 1800.0 and c[first] - 20.0 < 100.0
    m = FaultMonitor(lim)
    read = np.array([m.step(tk, [20.0, 20.0, ck]) for tk, ck in zip(t, c)])
    assert m.fault == [None, None, "others"] and m.onset_s[2] == t[first]
    np.testing.assert_allclose(read[first:, 2], 20.0)
    np.testing.assert_allclose(read[:first, 2], c[:first])
    path = tmp_path / "faults.tbm"
    write_faults(path, lim, None)
    # the seed001 model reads two sensors (A and B here); the checks read three, C the third column
    s = pd.DataFrame({"t_s": t, "axis_mm": 0.0, "feed_mm_min": 0.0, "T_nut_C": 20.0, "T_bed_C": 20.0, "C": c})
    got = runtime.replay([seed001_exports / "mlr" / "model.tbm"], s, ["T_nut_C", "T_bed_C", "C"],
                         pd.DataFrame({"t_s": t, "axis_mm": 0.0}), live=True, faults=path)  # fmt: skip
    assert got["rules"].tolist() == ["000"] * first + ["005"] * (t.size - first)
