"""Prediction intervals and the training envelope (thermbench/intervals.py): the envelope
and the conformal quantile by hand, and the benchmark's coverage_90 / half_width_um recomputed from
fits made by hand on the same runs."""

from __future__ import annotations

import math

import numpy as np
import pytest
from sklearn.base import clone

from tests.test_benchmark_own import lathe  # noqa: F401  (the fixture: shape 1 imported)
from thermbench import bench as bm
from thermbench.experiment import ExperimentError, build_model, dataset_option, group_option
from thermbench.bench.intervals import Envelope, conformal_quantile, half_widths, interval_scores
from thermbench.bench.splits import load_split


def test_the_conformal_quantile_is_the_ceil_n_plus_one_level_th_smallest():
    s = np.arange(1.0, 20.0)  # 19 scores: ⌈20 · 0.9⌉ = 18th smallest
    assert conformal_quantile(s[::-1], 0.9) == 18.0
    assert conformal_quantile([1.0, 2.0, 3.0], 0.9) == math.inf  # ⌈4 · 0.9⌉ = 4 > 3: too few for 90 %
    assert conformal_quantile([3.0, np.nan, 1.0, 2.0, 5.0, 4.0, 6.0, 7.0, 8.0, 9.0], 0.5) == 5.0  # NaN ignored: n = 9, 5th
    with pytest.raises(ValueError, match="between 0 and 1"):
        conformal_quantile(s, 1.0)
    assert np.allclose(interval_scores([-2.0, 3.0], [0.0, 0.5], kappa=2.0), [2.0, 1.5])
    assert np.allclose(half_widths(1.5, [0.0, 0.5], kappa=2.0), [1.5, 3.0])


def test_the_envelope_by_hand():
    env = Envelope(("a",), ("rpm",), ["rise:a", "rate:a", "op:rpm"], np.array([0.0, -1.0, 1000.0]),
                   np.array([4.0, 3.0, 3000.0]), np.array([4.0, 4.0, 2000.0]))  # fmt: skip
    F = np.array([[2.0, 0.0, 2000.0],  # inside
                  [6.0, 0.0, 2000.0],  # rise 2 K over a 4 K range: 0.5
                  [2.0, -3.0, 4000.0]])  # rate 2 K/h under (0.5), rpm 1000 over a 2000 range (0.5)
    assert np.allclose(env.distance(F), [0.0, 0.5, 0.5])
    assert env.outside(F) == [[], ["rise:a"], ["rate:a", "op:rpm"]]
    assert np.allclose(Envelope.from_dict(env.to_dict()).distance(F), env.distance(F))


def test_the_rate_of_a_steady_ramp_and_the_rise_by_hand():
    """A ramp of 6 K/h from 20 °C, sampled every 10 s: the rise is T - 20; the high-pass rate
    (T - e)/tau of an exponential average e obeys e' = (T - e)/tau, whose solution for a ramp
    r·t is T - e = r·tau·(1 - exp(-t/tau)) (to the step's discretisation): 6 K/h after a few tau."""
    from thermbench.bench.intervals import rise_and_rate

    t = np.arange(0.0, 6000.0, 10.0)
    T = 20.0 + 6.0 * t / 3600.0
    rise, rate = rise_and_rate(t, T[:, None], tau_s=600.0)
    assert np.allclose(rise[:, 0], T - 20.0)
    assert np.allclose(rate[:, 0], 6.0 * (1 - np.exp(-t / 600.0)), atol=0.06)
    # the sampled recursion's steady lag of a ramp: T - e = r·Δ·q/(1 - q), q = exp(-Δ/tau) (≈ r·(tau - Δ/2))
    q = np.exp(-10.0 / 600.0)
    assert rate[-1, 0] == pytest.approx(6.0 * 10.0 * q / (1 - q) / 600.0, rel=1e-4)


def test_the_envelope_of_a_dataset_is_its_rises_and_rates(lathe):  # noqa: F811
    """Fitted on one day of shape 1, the envelope's ranges are that day's rises and rates at its
    readings (each sensor's log as written: rise above the first sample, the high-pass rate)."""
    from thermbench.bench.intervals import rise_and_rate

    _, dcfg = dataset_option(str(lathe), "datasets")
    ds = load_split({**dcfg, "channel": "dia"}).dataset
    run = ds.run_ids[0]
    sensor = next(iter(ds.metadata.sensors))
    env = Envelope.fit(ds, [run], [sensor])
    pr = ds.process_run(run)
    tp, T = pr["t_s"].to_numpy(float), pr[ds.metadata.sensor_column(sensor)].to_numpy(float)
    t = ds.errors_run(run)["t_s"].to_numpy(float)
    rise, rate = (np.interp(t, tp, x[:, 0]) for x in rise_and_rate(tp, T[:, None]))
    assert env.names == [f"rise:{sensor}", f"rate:{sensor}"]
    assert env.lo == pytest.approx([rise.min(), rate.min()]) and env.hi == pytest.approx([rise.max(), rate.max()])
    assert rise.max() == pytest.approx(np.interp(t, tp, T).max() - T[0])
    assert env.distance(Envelope.features(ds, run, t, [sensor])).max() == 0.0  # its own readings are inside


@pytest.mark.parametrize("family,kappa", [("thermal_lag", 0.0), ("thermal_lag", 5.0), ("baseline_ridge", 5.0),
                                          ("ensemble", 5.0)])  # fmt: skip
def test_benchmark_intervals_equal_the_conformal_interval_made_by_hand(lathe, family, kappa):  # noqa: F811
    """thermal_lag (and a baseline: every family has its interval, though a baseline is never a
    candidate of the choice), global, leave-one-run-out on the three days: for the fold holding out day 1, the
    scores are |residual| / (1 + kappa·distance) of day 2 predicted by a fit on day 3 (distance to
    day 3's envelope) and of day 3 by a fit on day 2, q their ⌈(n+1)·0.9⌉-th smallest; coverage_90
    is the share of day 1's readings within q·(1 + kappa·distance to the envelope of days 2 and 3)
    of the fit on days 2 and 3. kappa 0: no envelope at all."""
    _, dcfg = dataset_option(str(lathe), "datasets")
    cfg = group_option("model", family)
    out = bm.run_task(dcfg, family, cfg, ["global"], None, seed=0, channel="dia", cv="loro",
                      interval={"level": 0.9, "kappa": kappa})  # fmt: skip
    res = out["results"]
    assert out["inner"].empty == (family == "baseline_ridge")  # inner scores: the candidates' only
    ds = load_split({**dcfg, "channel": "dia"}).dataset
    model = build_model(cfg, seed=0)
    days = list(ds.run_ids)

    def residual(train, run):
        m = clone(model).fit(ds, train)
        d = ds.errors_run(run)["error_um"].to_numpy(float) - np.asarray(m.predict(ds, run), dtype=float)
        inputs = m.required_inputs()
        env = Envelope.fit(ds, train, inputs.sensors, inputs.operating)
        F = Envelope.features(ds, run, ds.errors_run(run)["t_s"].to_numpy(float), inputs.sensors, inputs.operating)
        return np.abs(d), env.distance(F)

    widened = False
    for held in days:
        others = [d for d in days if d != held]
        parts = [residual([others[1]], others[0]), residual([others[0]], others[1])]
        scores = np.concatenate([r / (1 + kappa * dist) for r, dist in parts])
        q = np.sort(scores)[math.ceil((scores.size + 1) * 0.9) - 1]
        r, dist = residual(others, held)
        hw = q * (1 + kappa * dist)
        widened |= bool(kappa and (dist > 0).any())
        row = res[(res["fold"] == held) & (res["run_id"] == held)].iloc[0]
        assert row["coverage_90"] == pytest.approx(np.mean(r <= hw))
        assert row["half_width_um"] == pytest.approx(np.mean(hw))
    assert widened or kappa == 0.0  # some day leaves the envelope of the other two: the case is exercised


def test_interval_mistakes_are_one_line():
    for bad, msg in [({"level": 90}, "config key 'interval.level': expected a number between 0 and 1"),
                     ({"kappa": -1}, "config key 'interval.kappa': expected a number >= 0"),
                     ({"width": 1}, "config key(s) ['interval.width']: unknown")]:  # fmt: skip
        with pytest.raises(ExperimentError) as exc:
            bm.interval_settings(bad)
        assert str(exc.value).startswith(msg)


@pytest.mark.parametrize("family", ["thermal_lag", "ensemble"])
def test_the_adaptive_approach_scores_without_its_probes_and_the_naive_peer_by_hand(lathe, family):  # noqa: F811
    """thermal_lag and the stacked ensemble (probe updates work for it as for any family): approaches global + adaptive, a probe every 600 s on each held-out day (120 s readings):
    the naive peer's RMSE is the one of the fold's fit made by hand, with the last probe's residual
    added from the reading after it, over the readings that were not probes; the adaptive rows
    replay the filter (fixed noise) by hand the same way. Every probe approach is left out of the
    choice of the model to deploy."""
    from thermbench.bench.adapt import ProbeFilter, ProbeParams

    _, dcfg = dataset_option(str(lathe), "datasets")
    cfg = group_option("model", family)
    noise = {"q_bias_um2_per_h": 2.0, "q_gain_per_h": 1e-3, "r_um2": 0.05, "bias0_um": 1.0, "gain0": 0.1}
    out = bm.run_task(dcfg, family, cfg, ["global", "adaptive"], None, seed=0, channel="dia", cv="loro",
                      probe={"every_s": [600], "trigger": "uncertainty", "threshold_um": 0.6, "noise": noise})  # fmt: skip
    res = out["results"]
    assert {"adaptive-600s", "naive_probe-600s", "adaptive-uncertainty", "global", "as_deployed"} == set(res["approach"])
    ds = load_split({**dcfg, "channel": "dia"}).dataset
    model = build_model(cfg, seed=0)
    for held in ds.run_ids:
        e = ds.errors_run(held)
        t, y = e["t_s"].to_numpy(float), e["error_um"].to_numpy(float)
        p = np.asarray(clone(model).fit(ds, [d for d in ds.run_ids if d != held]).predict(ds, held), dtype=float)
        probe = np.isin(t, np.arange(0.0, t[-1] + 1, 600.0))  # readings at 0, 600, 1200 ... s
        naive, off = p.copy(), 0.0
        filt, f = p.copy(), ProbeFilter(ProbeParams(**noise), t[0])
        for i in range(t.size):
            naive[i] += off
            filt[i] = f.correct(t[i], p[i])[0]
            if probe[i]:
                off = y[i] - p[i]
                f.probe(t[i], p[i], y[i])
        keep = ~probe
        rows = res[(res["fold"] == held) & (res["run_id"] == held)].set_index("approach")
        assert rows.loc["naive_probe-600s", "probes"] == probe.sum() >= 4
        assert rows.loc["naive_probe-600s", "rmse_um"] == pytest.approx(np.sqrt(np.mean((naive - y)[keep] ** 2)))
        assert rows.loc["adaptive-600s", "rmse_um"] == pytest.approx(np.sqrt(np.mean((filt - y)[keep] ** 2)))
        assert 0 <= rows.loc["adaptive-600s", "coverage_90"] <= 1 and rows.loc["adaptive-600s", "half_width_um"] > 0
        assert rows.loc["adaptive-uncertainty", "probes"] >= 1
    chosen = bm.choose(res.assign(reference=False), exclude=[])
    assert not chosen["approach"].map(bm.probe_approach).any()


def test_the_streaming_guard_is_the_envelope_of_the_log_sample_by_sample(lathe):  # noqa: F811
    """EnvelopeGuard fed a day's log sample by sample gives, at every sample, the distance the batch
    features of that log give (the same rise and high-pass rate, computed two ways)."""
    from thermbench.bench.intervals import EnvelopeGuard

    _, dcfg = dataset_option(str(lathe), "datasets")
    ds = load_split({**dcfg, "channel": "dia"}).dataset
    sensors = list(ds.metadata.sensors)[:2]
    env = Envelope.fit(ds, [ds.run_ids[0]], sensors)
    run = ds.run_ids[2]  # another day: partly outside the first day's envelope
    pr = ds.process_run(run)
    t = pr["t_s"].to_numpy(float)
    batch = env.distance(Envelope.features(ds, run, t, sensors))
    g = EnvelopeGuard(env)
    stream = [g.step(tt, [pr[ds.metadata.sensor_column(s)].iloc[i] for s in sensors]) for i, tt in enumerate(t)]
    assert np.allclose(stream, batch, atol=1e-12) and (batch > 0).any()


def test_the_export_manifest_carries_the_training_envelope(seed001_exports, seed001_data_root):
    from thermbench.bench import datasets
    from thermbench.export.directory import read_manifest

    man = read_manifest(seed001_exports / "mlr")
    ds = datasets.load_benchmark("seed001_vmc_x", seed001_data_root)
    env = Envelope.from_dict(man["envelope"])
    assert env.sensors == tuple(man["temperatures"]) and man["envelope"]["rate_tau_s"] == 600.0
    # the largest rise of each sensor over the five training states, from the log as written
    for j, s in enumerate(man["temperatures"]):
        col = ds.metadata.sensor_column(s)
        top = []
        for r in man["training"]["runs"]:
            pr, t = ds.process_run(r), ds.errors_run(r)["t_s"].to_numpy(float)
            top.append((np.interp(t, pr["t_s"], pr[col]) - pr[col].iloc[0]).max())
        assert env.hi[j] == pytest.approx(max(top))


def test_an_export_calibrates_its_interval_over_its_training_runs(seed001_data_root, tmp_path):
    """export.interval_level: each training run predicted by a fit on the others; with kappa = 0 the
    half-width is the ⌈(n + 1) · 0.9⌉-th smallest |residual| (computed here from fits made by hand),
    and it covers most of valid1, a run none of the fits saw."""
    from thermbench.bench import datasets
    from thermbench.export import ExportOptions, export_model
    from thermbench.models.mlr import MLRSeed002

    ds = datasets.load_benchmark("seed001_vmc_x", seed001_data_root)
    states = ["state1", "state2", "state3", "state4", "state5"]
    man = export_model(MLRSeed002().fit(ds, states), tmp_path / "m", "m", ds, ["valid1"],
                       options=ExportOptions(verify=False, onnx=False, interval_level=0.9, interval_kappa=0.0))  # fmt: skip
    res = np.concatenate([ds.errors_run(r)["error_um"].to_numpy() - MLRSeed002().fit(ds, [o for o in states if o != r]).predict(ds, r)
                          for r in states])  # fmt: skip
    s = np.sort(np.abs(res))
    assert man["interval"]["n_readings"] == s.size and man["interval"]["n_runs"] == 5
    assert man["interval"]["q_um"] == pytest.approx(s[math.ceil((s.size + 1) * 0.9) - 1], rel=1e-12)
    er = ds.errors_run("valid1")
    full = MLRSeed002().fit(ds, states)
    inside = np.abs(er["error_um"].to_numpy() - full.predict(ds, "valid1")) <= man["interval"]["q_um"]
    print(f"valid1 coverage of the exported 90 % interval: {inside.mean():.2f} (q = {man['interval']['q_um']:.2f} um)")
    assert inside.mean() >= 0.7


@pytest.mark.parametrize("key, value, message", [
    ("interval_level", 1.5, "config key 'export.interval_level': expected null or a number between 0 and 1, got 1.5"),
    ("interval_level", True, "config key 'export.interval_level': expected null or a number between 0 and 1, got True"),
    ("interval_kappa", -1, "config key 'export.interval_kappa': expected a number >= 0, got -1"),
])  # fmt: skip
def test_bad_interval_options_are_one_line_config_errors(key, value, message):
    from thermbench.export.job import _options

    with pytest.raises(Exception, match=message.replace("(", r"\(").replace(")", r"\)")):
        _options({key: value})
    assert _options({"interval_level": 0.9}).interval_level == 0.9 and _options({}).interval_level is None


def test_the_gp_refit_peer_is_the_gp_posterior_given_its_probes_by_hand(lathe):  # noqa: F811
    """run_task with the gp family and a probe every 600 s: the gp_refit-600s rows score, on the
    readings that were not probes, a GP conditioned on its training readings plus the probes so
    far. Here that posterior mean is computed by hand (numpy: the kernel matrix solved, y
    standardised over the readings it is fitted on, as normalize_y does) from a fit of the fold's
    runs made by hand."""
    _, dcfg = dataset_option(str(lathe), "datasets")
    cfg = {**group_option("model", "gp"), "max_samples": 60}
    noise = {"q_bias_um2_per_h": 2.0, "q_gain_per_h": 1e-3, "r_um2": 0.05, "bias0_um": 1.0, "gain0": 0.1}
    out = bm.run_task(dcfg, "gp", cfg, ["global", "adaptive"], None, seed=0, channel="dia", cv="loro",
                      probe={"every_s": [600], "trigger": None, "noise": noise})  # fmt: skip
    res = out["results"]
    assert {"adaptive-600s", "naive_probe-600s", "gp_refit-600s", "global", "as_deployed"} == set(res["approach"])
    ds = load_split({**dcfg, "channel": "dia"}).dataset
    model = build_model(cfg, seed=0)
    for held in ds.run_ids:
        e = ds.errors_run(held)
        t, x, y = (e[c].to_numpy(float) for c in ("t_s", "target_mm", "error_um"))
        m = clone(model).fit(ds, [d for d in ds.run_ids if d != held])
        Z = m._X(ds, held, t, x)
        k = m.gp_.kernel_
        pred = np.asarray(m.gp_.predict(Z), dtype=float)
        probe = np.isin(t, np.arange(0.0, t[-1] + 1, 600.0))
        seen = []
        for i in range(t.size):
            if seen:  # the posterior mean given the training readings and the probes before i
                X = np.vstack([m.train_Z_, Z[seen]])
                Y = np.concatenate([m.train_y_um_, y[seen]])
                mu, sd = Y.mean(), Y.std()
                alpha = np.linalg.solve(k(X) + 1e-10 * np.eye(len(X)), (Y - mu) / sd)
                pred[i] = float((k(Z[i : i + 1], X) @ alpha)[0]) * sd + mu
            if probe[i]:
                seen.append(i)
        keep = ~probe
        assert np.abs(pred - m.gp_.predict(Z)).max() > 1e-3  # the probes moved the GP
        row = res[(res["fold"] == held) & (res["run_id"] == held) & (res["approach"] == "gp_refit-600s")].iloc[0]
        assert row["probes"] == probe.sum() >= 4
        assert row["rmse_um"] == pytest.approx(np.sqrt(np.mean((pred - y)[keep] ** 2)), rel=1e-6)
    assert not bm.choose(res.assign(reference=False), exclude=[])["approach"].map(bm.probe_approach).any()
