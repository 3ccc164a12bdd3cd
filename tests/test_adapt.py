"""The probe filter (thermbench/adapt.py) against a second implementation: the joint
maximum-a-posteriori estimate of the whole random walk of (bias, gain) from every probe so far,
one dense least-squares problem (the Kalman filter's estimate at the last probe is its last
state, and its covariance the matching block of the inverse information matrix), and against a
hand computation of the scalar case."""

from __future__ import annotations

import json

import numpy as np
import pytest

from thermbench.bench.adapt import ProbeFilter, ProbeParams, ProbeParamsError, apply_probes


def joint_map(t_s, predicted, measured, p: ProbeParams, t0_s: float):
    """States z = [x_0, x_1 .. x_n] (x = bias, gain) at t0 and each probe; the prior N(0, P0) on
    x_0, the random walk x_k - x_{k-1} ~ N(0, Q dt_k), the readings y_k - p_k = [1, p_k] x_k + v."""
    n = len(t_s)
    N = 2 * (n + 1)
    A = np.zeros((N, N))
    b = np.zeros(N)
    A[:2, :2] += np.diag([1 / p.bias0_um**2, 1 / p.gain0**2])
    prev = t0_s
    for k in range(1, n + 1):
        dt_h = (t_s[k - 1] - prev) / 3600.0
        prev = t_s[k - 1]
        Qi = np.diag([1 / (p.q_bias_um2_per_h * dt_h), 1 / (p.q_gain_per_h * dt_h)])
        i, j = slice(2 * k - 2, 2 * k), slice(2 * k, 2 * k + 2)
        A[i, i] += Qi
        A[j, j] += Qi
        A[i, j] -= Qi
        A[j, i] -= Qi
        H = np.array([1.0, predicted[k - 1]])
        A[j, j] += np.outer(H, H) / p.r_um2
        b[j] += H * (measured[k - 1] - predicted[k - 1]) / p.r_um2
    z = np.linalg.solve(A, b)
    cov = np.linalg.inv(A)
    return z[-2:], cov[-2:, -2:]


def test_the_filter_is_the_joint_estimate_of_the_random_walk():
    rng = np.random.default_rng(3)
    p = ProbeParams(q_bias_um2_per_h=0.7, q_gain_per_h=2e-3, r_um2=0.2, bias0_um=2.5, gain0=0.15)
    t0 = 100.0
    t = t0 + np.cumsum(rng.uniform(600, 5400, 9))
    pred = rng.uniform(-20, 30, t.size)
    meas = 1.1 * pred + 1.5 + rng.normal(0, 0.4, t.size)
    f = ProbeFilter(p, t0)
    for k in range(t.size):
        f.probe(t[k], pred[k], meas[k])
        x, P = joint_map(t[: k + 1], pred[: k + 1], meas[: k + 1], p, t0)
        assert np.allclose(f.x, x, rtol=1e-9, atol=1e-10)
        assert np.allclose(f.P, P, rtol=1e-8, atol=1e-12)
    # between probes: the state stands, the variance of the corrected value grows by H Q dt Hᵀ
    later = t[-1] + 1800.0
    value, var = f.correct(later, 4.0)
    H = np.array([1.0, 4.0])
    assert value == pytest.approx(4.0 * (1 + x[1]) + x[0], rel=1e-12)
    assert var == pytest.approx(H @ (P + np.diag([0.7, 2e-3]) * 0.5) @ H, rel=1e-9)


def test_one_probe_on_the_bias_alone_by_hand():
    """gain0 = 0 and q_gain = 0: a scalar filter. A probe at the start with prior σ0² = 4 and
    r = 1: gain K = 4/5, the bias takes 4/5 of the residual, its variance 4·1/5 = 0.8; an hour
    later the variance is 0.8 + q_bias."""
    p = ProbeParams(q_bias_um2_per_h=0.5, q_gain_per_h=0.0, r_um2=1.0, bias0_um=2.0, gain0=0.0)
    f = ProbeFilter(p, 0.0)
    innovation = f.probe(0.0, 10.0, 13.0)
    assert innovation == pytest.approx(3.0)
    assert f.x[0] == pytest.approx(2.4) and f.x[1] == 0.0
    value, var = f.correct(3600.0, 7.0)
    assert value == pytest.approx(9.4) and var == pytest.approx(0.8 + 0.5)


def test_apply_probes_uses_a_reading_only_after_it_is_taken_and_recovers_a_constant_offset():
    t = np.arange(0.0, 8 * 3600.0, 15.0)
    pred = 10 * np.sin(t / 7000.0)
    meas = pred + 2.0
    probes = np.zeros(t.size, bool)
    probes[:: 240] = True  # one an hour
    p = ProbeParams(q_bias_um2_per_h=0.01, q_gain_per_h=1e-6, r_um2=0.01, bias0_um=5.0, gain0=0.05)
    out, var, probed = apply_probes(t, pred, meas, p, schedule=probes)
    assert np.array_equal(probed, probes)
    assert out[0] == pred[0]  # the first reading's correction is the one before its own probe
    assert out[1] == pytest.approx(pred[1] + 2.0 * 25 / 25.01, rel=1e-6)  # σ0² = 25, r = 0.01: the bias takes 25/25.01
    assert np.abs(out[-1000:] - meas[-1000:]).max() < 0.02  # after a few probes the offset is known
    last = np.flatnonzero(probes)[-1]
    assert var[last + 1] < var[1] < var[0]  # each probe narrows what the next reading's correction may be off by


def test_the_state_carries_over_a_restart():
    p = ProbeParams()
    f = ProbeFilter(p, 0.0)
    f.probe(100.0, 3.0, 5.0)
    f.probe(4000.0, -8.0, -6.5)
    g = ProbeFilter.from_state(json.loads(json.dumps(f.state())))
    assert g.correct(9000.0, 2.0) == f.correct(9000.0, 2.0)
    assert g.probe(9000.0, 2.0, 3.0) == f.probe(9000.0, 2.0, 3.0)
    assert np.array_equal(g.x, f.x) and np.array_equal(g.P, f.P)


def test_bad_settings_and_readings_are_named():
    with pytest.raises(ProbeParamsError, match=r"probe.r_um2.*> 0"):
        ProbeParams(r_um2=0.0)
    with pytest.raises(ProbeParamsError, match=r"probe.q_bias_um2_per_h.*>= 0"):
        ProbeParams.from_config({"q_bias_um2_per_h": -1})
    with pytest.raises(ProbeParamsError, match=r"probe.q_bias.*unknown"):
        ProbeParams.from_config({"q_bias": 1})
    f = ProbeFilter(ProbeParams(), 100.0)
    with pytest.raises(ValueError, match="older"):
        f.probe(50.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="finite"):
        f.probe(200.0, float("nan"), 1.0)


def test_the_noise_estimate_recovers_a_random_walk_and_its_scatter():
    """Residuals made as a random-walk offset (q = 2 µm²/h) plus white scatter (r = 0.09 µm²),
    15 s readings, twenty 8 h runs: the semivariogram gives both back within their sampling error."""
    from thermbench.bench.adapt import estimate_noise

    rng = np.random.default_rng(7)
    runs = []
    for _ in range(20):
        t = np.arange(0.0, 8 * 3600.0, 15.0)
        walk = np.cumsum(rng.normal(0, np.sqrt(2.0 * 15 / 3600), t.size))
        runs.append((t, walk + rng.normal(0, 0.3, t.size)))
    p = estimate_noise(runs, every_s=3600.0)
    assert p.r_um2 == pytest.approx(0.09 + 2.0 * 15 / 3600 / 2, rel=0.1)  # γ(15 s) = r + q·Δ/2
    assert p.q_bias_um2_per_h == pytest.approx(2.0, rel=0.15)
    assert p.bias0_um == pytest.approx(np.sqrt(np.mean(np.concatenate([d for _, d in runs]) ** 2)))


def test_the_schedule_and_the_uncertainty_trigger_by_hand():
    from thermbench.bench.adapt import probe_schedule

    t = np.arange(0.0, 4 * 3600.0 + 1, 60.0)
    sched = probe_schedule(t + 30.0, 3600.0)
    assert np.flatnonzero(sched).tolist() == [0, 60, 120, 180, 240]
    # the bias alone (no gain): before the first probe var = 1 + 0.5·Δt_h; with r = 0.5 the trigger at
    # 1.5 µm fires when 1 + 0.5 Δt_h + 0.5 > 2.25, at Δt_h > 1.5; after a probe at var v (posterior
    # v·r/(v + r)) it fires again when v_post + 0.5 Δt_h + 0.5 > 2.25
    p = ProbeParams(q_bias_um2_per_h=0.5, q_gain_per_h=0.0, r_um2=0.5, bias0_um=1.0, gain0=0.0)
    t = np.arange(0.0, 6 * 3600.0 + 1, 60.0)
    _, var, probed = apply_probes(t, np.zeros(t.size), np.zeros(t.size), p, trigger_um=1.5)
    first = np.flatnonzero(probed)[0]
    assert t[first] == 91 * 60.0  # the first reading past 1.5 h
    v = 1 + 0.5 * t[first] / 3600
    post = v * 0.5 / (v + 0.5)
    wait_h = (2.25 - 0.5 - post) / 0.5
    assert t[np.flatnonzero(probed)[1]] - t[first] == pytest.approx(np.floor(wait_h * 60 + 1) * 60.0)


def test_the_trigger_reads_the_half_width_widened_outside_the_envelope():
    """``widen`` (1 + kappa·distance) multiplies the std the trigger compares: with the std of the
    test above (var = 1 + 0.5·Δt_h + r, r = 0.5) and a widening of 1.2 from 30 min on, the trigger at
    1.5 µm fires at 30 min (1.2²·(1.5 + 0.5·Δt_h) > 2.25 from Δt_h > 0.125, by hand), not at 1.5 h;
    and trigger_level with kappa is the widened std just before the schedule's probes."""
    from thermbench.bench.adapt import trigger_level

    p = ProbeParams(q_bias_um2_per_h=0.5, q_gain_per_h=0.0, r_um2=0.5, bias0_um=1.0, gain0=0.0)
    t = np.arange(0.0, 6 * 3600.0 + 1, 60.0)
    widen = np.where(t >= 1800.0, 1.2, 1.0)
    _, _, probed = apply_probes(t, np.zeros(t.size), np.zeros(t.size), p, trigger_um=1.5, widen=widen)
    assert t[np.flatnonzero(probed)[0]] == 1800.0  # 1.2·sqrt(1.5 + 0.25) = 1.59 > 1.5 at once at 30 min
    _, _, probed = apply_probes(t, np.zeros(t.size), np.zeros(t.size), p, trigger_um=1.65, widen=widen)
    # 1.44·(1.5 + 0.5·Δt_h) > 1.65² = 2.7225 at Δt_h > 0.78125 h = 46.875 min: the first reading after
    assert t[np.flatnonzero(probed)[0]] == 47 * 60.0
    # the level: the median std just before the hourly probes, here all widened by 1 + 0.4·0.5
    dist = np.full(t.size, 0.5)
    lvl0 = trigger_level([(t, np.zeros(t.size))], p, 3600.0)
    lvl = trigger_level([(t, np.zeros(t.size), dist)], p, 3600.0, kappa=0.4)
    assert lvl == pytest.approx(1.2 * lvl0)
