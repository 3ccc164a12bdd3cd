"""Temperature preprocessing (seed 002 §2.3.1): limit filter, Kalman filter, per-run
application, sensor clustering, grey relational analysis and sensitive-point selection.

Expected values come from hand calculation or from independent implementations written
here, not from the code under test."""

import math

import numpy as np
import pandas as pd
import pytest
from sklearn.base import clone

from thermbench.preprocess import (
    KalmanFilter,
    LimitFilter,
    PreprocessError,
    Selection,
    cluster_sensors,
    filter_process,
    grey_relational_grade,
    select_sensitive_points,
)

R_PAPER, Q_PAPER = 8.8706, 1e-3  # seed 002 §2.3.1


# ---------------------------------------------------------------- limit filter (eq. 1)


def test_limit_filter_removes_spike_and_dropout_exactly():
    clean = np.full(40, 21.5)
    clean[25:] = 21.5 + 0.01 * np.arange(15)  # a slow rise after the faults
    raw = clean.copy()
    raw[5] += 6.0  # one-sample spike
    raw[12:17] = 85.0  # 5-sample dropout
    y = LimitFilter(limit_C=2.0).transform(raw, column="T1_C")
    np.testing.assert_array_equal(y, clean)
    assert raw[5] == 27.5 and raw[12] == 85.0  # input not modified


def test_limit_filter_holds_last_accepted_value_on_a_ramp():
    clean = 20.0 + 0.05 * np.arange(30)
    raw = clean.copy()
    raw[10:15] = 85.0
    raw[20] = 14.0  # a negative spike
    y = LimitFilter().transform(raw)
    expected = clean.copy()
    expected[10:15] = clean[9]  # held at the last accepted reading 20.45
    expected[20] = clean[19]
    np.testing.assert_array_equal(y, expected)
    assert expected[10] == pytest.approx(20.45)


def test_limit_filter_passes_slow_noisy_ramp_unchanged():
    rng = np.random.default_rng(1)
    x = 20.0 + 0.02 * np.arange(2000) + rng.normal(0, 0.1, 2000)  # steps of ~0.15 °C << 2 °C
    np.testing.assert_array_equal(LimitFilter().transform(x), x)


def test_limit_filter_step_equal_to_limit_is_accepted_and_above_is_not():
    x = np.array([10.0, 12.0, 14.0001, 14.0])
    np.testing.assert_array_equal(LimitFilter(limit_C=2.0).transform(x), [10.0, 12.0, 12.0, 14.0])


def test_max_hold_accepts_a_genuine_step_after_n_samples():
    rng = np.random.default_rng(2)
    x = np.r_[np.full(10, 20.0), np.full(20, 30.0)] + rng.normal(0, 0.05, 30)
    paper = LimitFilter().transform(x)  # the paper's rule holds the old level forever
    np.testing.assert_array_equal(paper[10:], np.full(20, x[9]))
    y = LimitFilter(max_hold=3).transform(x)
    np.testing.assert_array_equal(y[:10], x[:10])
    np.testing.assert_array_equal(y[10:13], np.full(3, x[9]))  # held for 3 samples
    np.testing.assert_array_equal(y[13:], x[13:])  # the 4th reading at the new level is accepted


def test_max_hold_still_rejects_a_dropout_no_longer_than_max_hold():
    clean = np.full(30, 22.0)
    raw = clean.copy()
    raw[10:15] = 85.0
    np.testing.assert_array_equal(LimitFilter(max_hold=5).transform(raw), clean)
    # a level that scatters by more than the limit is never "persistent"
    raw2 = clean.copy()
    raw2[10:20] = [85.0, 0.0] * 5
    np.testing.assert_array_equal(LimitFilter(max_hold=2).transform(raw2), clean)


# ---------------------------------------------------------------- Kalman filter (eq. 2-3)


def kalman_information_form(z, R, Q):
    """Textbook 1x1-matrix Kalman filter in information form, from a diffuse prior
    (zero information) at k = 0; written independently of the code under test."""
    A = H = np.eye(1)
    Rm, Qm = np.array([[R]]), np.array([[Q]])
    x = np.zeros((1, 1))
    info = np.zeros((1, 1))  # P^-1 of the prior at k = 0: no information
    out = []
    for k, zk in enumerate(z):
        if k > 0:  # time update in covariance form
            P_prior = A @ np.linalg.inv(info) @ A.T + Qm
            x = A @ x
            info_prior = np.linalg.inv(P_prior)
        else:
            info_prior = info
        info = info_prior + H.T @ np.linalg.inv(Rm) @ H  # P^-1 = P⁻^-1 + H' R^-1 H
        P = np.linalg.inv(info)
        # x = P (P⁻^-1 x⁻ + H' R^-1 z)
        x = P @ (info_prior @ x + H.T @ np.linalg.inv(Rm) @ np.array([[zk]]))
        out.append(x[0, 0])
    return np.array(out)


@pytest.mark.parametrize("R,Q", [(R_PAPER, Q_PAPER), (0.01, 1e-4), (1.0, 2.0)])
def test_kalman_matches_independent_information_form(R, Q):
    rng = np.random.default_rng(3)
    t = np.arange(1500)
    z = 20.0 + 3.0 * (1 - np.exp(-t / 400)) + rng.normal(0, 0.3, t.size)
    y = KalmanFilter(R=R, Q=Q).transform(z, column="T1_C")
    np.testing.assert_allclose(y, kalman_information_form(z, R, Q), rtol=0, atol=1e-12)


def test_kalman_first_steps_by_hand():
    # x0 = z0, P0 = R; k = 1: P⁻ = R + Q, K = (R + Q) / (2R + Q)
    R, Q = 2.0, 0.5
    y = KalmanFilter(R=R, Q=Q).transform([10.0, 20.0, 20.0])
    K1 = 2.5 / 4.5
    assert y[0] == 10.0
    assert y[1] == pytest.approx(10.0 + K1 * 10.0, abs=1e-14)
    P1 = (1 - K1) * 2.5
    K2 = (P1 + Q) / (P1 + Q + R)
    assert y[2] == pytest.approx(y[1] + K2 * (20.0 - y[1]), abs=1e-14)


def test_kalman_reduces_white_noise_on_constant_signal():
    rng = np.random.default_rng(4)
    truth = 25.0
    z = truth + rng.normal(0, 0.1, 5000)
    y = KalmanFilter().transform(z)  # paper parameters
    raw_rms = np.sqrt(np.mean((z - truth) ** 2))
    filt_rms = np.sqrt(np.mean((y - truth) ** 2))
    assert raw_rms == pytest.approx(0.1, rel=0.05)
    assert filt_rms < 0.25 * raw_rms


@pytest.mark.parametrize("R,Q", [(R_PAPER, Q_PAPER), (0.5, 0.05)])
def test_kalman_gain_converges_to_analytic_steady_state(R, Q):
    # P⁻ = P⁻ R / (P⁻ + R) + Q  ->  P⁻² - Q P⁻ - Q R = 0
    P_inf = (Q + math.sqrt(Q * Q + 4 * Q * R)) / 2
    K_inf = P_inf / (P_inf + R)
    rng = np.random.default_rng(5)
    z = rng.normal(0, 1.0, 4000)
    y = KalmanFilter(R=R, Q=Q).transform(z)
    gains = (y[1:] - y[:-1]) / (z[1:] - y[:-1])  # x_k = x_{k-1} + K_k (z_k - x_{k-1})
    np.testing.assert_allclose(gains[-100:], K_inf, rtol=1e-8)
    if R == R_PAPER:
        assert K_inf == pytest.approx(math.sqrt(Q / R), rel=0.01)  # Q << R


def test_kalman_per_channel_override_applies_to_its_column_only():
    rng = np.random.default_rng(6)
    z = 20.0 + rng.normal(0, 0.5, 300)
    kf = KalmanFilter(per_channel={"T2_C": {"R": 0.01}})
    np.testing.assert_allclose(kf.transform(z, column="T2_C"), kalman_information_form(z, 0.01, Q_PAPER), atol=1e-12)
    np.testing.assert_allclose(kf.transform(z, column="T1_C"), kalman_information_form(z, R_PAPER, Q_PAPER),
                               atol=1e-12)  # fmt: skip
    np.testing.assert_allclose(kf.transform(z), kalman_information_form(z, R_PAPER, Q_PAPER), atol=1e-12)


def test_filters_are_sklearn_estimators():
    kf = KalmanFilter(R=1.0, Q=0.1, per_channel={"a": {"Q": 0.2}})
    assert kf.get_params() == {"R": 1.0, "Q": 0.1, "per_channel": {"a": {"Q": 0.2}}}
    assert clone(kf).get_params() == kf.get_params()
    assert LimitFilter(limit_C=3.0, max_hold=4).get_params() == {"limit_C": 3.0, "max_hold": 4}
    # constructors only store: bad values surface in transform
    LimitFilter(limit_C=-1.0)
    KalmanFilter(R=0.0)


@pytest.mark.parametrize(
    "filt,match",
    [
        (LimitFilter(limit_C=0.0), "limit_C"),
        (LimitFilter(limit_C=float("nan")), "limit_C"),
        (LimitFilter(max_hold=0), "max_hold"),
        (LimitFilter(max_hold=2.5), "max_hold"),
        (KalmanFilter(R=-1.0), "R must be"),
        (KalmanFilter(Q=0.0), "Q must be"),
        (KalmanFilter(per_channel={"T1_C": {"r": 1.0}}), "unknown key 'r'"),
        (KalmanFilter(per_channel={"T1_C": {"Q": -2.0}}), r"per_channel\['T1_C'\]: Q must be"),
        (KalmanFilter(per_channel=[("T1_C", 1.0)]), "per_channel must be a dict"),
    ],
)
def test_bad_filter_parameters_are_named(filt, match):
    with pytest.raises(PreprocessError, match=match) as exc:
        filt.transform(np.ones(5), column="T1_C")
    assert isinstance(exc.value, ValueError)


@pytest.mark.parametrize("filt", [LimitFilter(), KalmanFilter()])
def test_nan_input_names_column_and_first_bad_row(filt):
    x = np.array([20.0, 20.1, 20.2, np.nan, 20.3, np.nan])
    with pytest.raises(ValueError, match=r"'T3_C'.*row 3\b"):
        filt.transform(x, column="T3_C")
    with pytest.raises(PreprocessError, match="1-D"):
        filt.transform(np.ones((3, 2)), column="T3_C")


# ---------------------------------------------------------------- filter_process


def _process():
    rng = np.random.default_rng(7)
    n_a, n_b = 200, 150
    return pd.DataFrame(
        {
            "run_id": ["a"] * n_a + ["b"] * n_b,
            "t_s": np.r_[np.arange(n_a), np.arange(n_b)].astype(float),
            "axis_mm": np.linspace(0, 500, n_a + n_b),
            "T1_C": np.r_[20.0 + rng.normal(0, 0.1, n_a), 30.0 + rng.normal(0, 0.1, n_b)],
            "T2_C": np.r_[22.0 + rng.normal(0, 0.1, n_a), 21.0 + rng.normal(0, 0.1, n_b)],
        },
        index=np.arange(100, 100 + n_a + n_b),
    )


def test_filter_process_filters_each_run_afresh():
    proc = _process()
    before = proc.copy()
    out = filter_process(proc, ["T1_C"], [LimitFilter(), KalmanFilter()])
    pd.testing.assert_frame_equal(proc, before)  # input untouched
    b = out["run_id"] == "b"
    # run b starts 10 °C above run a: a leaking limit filter would hold it at 20 °C,
    # a leaking Kalman filter would start it at 20 °C and crawl up
    assert out.loc[b, "T1_C"].iloc[0] == proc.loc[b, "T1_C"].iloc[0]
    assert abs(out.loc[b, "T1_C"].mean() - 30.0) < 0.05
    assert out.loc[~b, "T1_C"].iloc[0] == proc.loc[~b, "T1_C"].iloc[0]
    # run b filtered inside the log equals run b filtered on its own (independent formula)
    np.testing.assert_allclose(
        out.loc[b, "T1_C"].to_numpy(), kalman_information_form(proc.loc[b, "T1_C"].to_numpy(), R_PAPER, Q_PAPER),
        atol=1e-12,
    )  # fmt: skip
    # other columns, index and order are unchanged
    pd.testing.assert_frame_equal(out.drop(columns="T1_C"), proc.drop(columns="T1_C"))
    assert out["T1_C"].std() < proc["T1_C"].std()


def test_filter_process_applies_per_channel_overrides_and_step_order():
    proc = _process()
    kf = KalmanFilter(per_channel={"T2_C": {"R": 0.02, "Q": 0.01}})
    out = filter_process(proc, ["T1_C", "T2_C"], [kf])
    for run in ("a", "b"):
        m = proc["run_id"] == run
        expected_t2 = kalman_information_form(proc.loc[m, "T2_C"].to_numpy(), 0.02, 0.01)
        np.testing.assert_allclose(out.loc[m, "T2_C"], expected_t2, atol=1e-12)
        np.testing.assert_allclose(out.loc[m, "T1_C"],
                                   kalman_information_form(proc.loc[m, "T1_C"].to_numpy(), R_PAPER, Q_PAPER),
                                   atol=1e-12)  # fmt: skip
    # limit first, then Kalman: the spike never reaches the Kalman filter
    proc.loc[proc.index[50], "T1_C"] = 85.0
    out_lk = filter_process(proc, ["T1_C"], [LimitFilter(), KalmanFilter()])
    out_kl = filter_process(proc, ["T1_C"], [KalmanFilter(), LimitFilter()])
    a = (proc["run_id"] == "a").to_numpy()
    assert out_lk["T1_C"].to_numpy()[a][50:60].max() < 20.5
    assert out_kl["T1_C"].to_numpy()[a][50:60].max() > 21.0  # K ~ 1/50 of the 65 °C spike leaks in


def test_filter_process_missing_column_names_it_and_lists_temperatures():
    with pytest.raises(PreprocessError, match=r"'T9_C'.*\['T1_C', 'T2_C'\]"):
        filter_process(_process(), ["T1_C", "T9_C"], [LimitFilter()])
    with pytest.raises(PreprocessError, match="string 'T1_C'"):
        filter_process(_process(), "T1_C", [LimitFilter()])


def test_filter_process_nan_names_column_and_run():
    proc = _process()
    proc.loc[proc.index[205], "T2_C"] = np.nan  # row 5 of run b
    with pytest.raises(PreprocessError, match=r"'T2_C', run 'b', row 205"):
        filter_process(proc, ["T1_C", "T2_C"], [LimitFilter(), KalmanFilter()])


def test_filter_process_nan_after_filtering_names_column_and_run():
    class Breaks:
        def transform(self, x, column=""):
            y = np.array(x, dtype=float)
            if y[0] > 25:
                y[3] = np.nan
            return y

    with pytest.raises(PreprocessError, match=r"'T1_C', run 'b'.*nan"):
        filter_process(_process(), ["T1_C"], [Breaks()])


def test_filter_process_rejects_interleaved_runs():
    proc = _process()
    proc = pd.concat([proc.iloc[:100], proc.iloc[250:], proc.iloc[100:250]])
    with pytest.raises(PreprocessError, match="run 'a'.*not contiguous"):
        filter_process(proc, ["T1_C"], [LimitFilter()])


# ---------------------------------------------------------------- clustering


def _three_groups(n=300, seed=8):
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n)
    shapes = {
        "exp": 1 - np.exp(-t / 0.1),  # fast saturating rise (bearing)
        "sin": np.sin(2 * np.pi * 2 * t),  # cycling (ambient-like)
        "late": t**4,  # late rise (slow body)
    }
    cols = {}
    for shape, (lvl, amp) in zip(shapes, [(20.0, 5.0), (22.0, 1.0), (25.0, 3.0)], strict=True):
        for j in range(3):
            cols[f"{shape}{j}_C"] = lvl + 3 * j + amp * (1 + 0.5 * j) * shapes[shape] + rng.normal(0, 0.02, n)
    names = ["exp0_C", "sin0_C", "late0_C", "exp1_C", "sin1_C", "late1_C", "exp2_C", "sin2_C", "late2_C"]
    return pd.DataFrame({c: cols[c] for c in names})


def test_cluster_sensors_recovers_three_trend_groups():
    temps = _three_groups()
    expected = {frozenset(f"{s}{j}_C" for j in range(3)) for s in ("exp", "sin", "late")}
    clusters = cluster_sensors(temps, n_clusters=3)
    assert {frozenset(c) for c in clusters} == expected
    # order: by first member's column position, members in column order
    assert clusters == [
        ["exp0_C", "exp1_C", "exp2_C"],
        ["sin0_C", "sin1_C", "sin2_C"],
        ["late0_C", "late1_C", "late2_C"],
    ]
    # cut by distance (1 - |r|): within a group r ~ 0.999, between groups far lower
    assert {frozenset(c) for c in cluster_sensors(temps, distance_threshold=0.05)} == expected
    assert len(cluster_sensors(temps, n_clusters=1)) == 1


def test_cluster_sensors_is_single_linkage_and_chains():
    # u, v, w: zero-mean, orthogonal, equal-norm series, so a sensor cos(a) u + sin(a) v has
    # correlation cos(a - b) with the sensor at angle b, i.e. distance 1 - |cos(a - b)|.
    n = 360
    t = np.arange(n) / n
    u, v, w = np.sin(2 * np.pi * t), np.cos(2 * np.pi * t), np.sin(4 * np.pi * t)
    cols = {f"c{j}_C": 20 + np.cos(np.radians(15 * j)) * u + np.sin(np.radians(15 * j)) * v for j in range(5)}
    c4 = np.cos(np.radians(60)) * u + np.sin(np.radians(60)) * v
    for j, phi in enumerate([40, 45]):
        cols[f"d{j}_C"] = 30 + np.cos(np.radians(phi)) * c4 + np.sin(np.radians(phi)) * w
    temps = pd.DataFrame(cols)
    # chain c0..c4: neighbours 1 - cos 15° = 0.034 apart, ends 1 - cos 60° = 0.5 apart;
    # d0, d1 are 1 - cos 5° = 0.004 apart and 1 - cos 40° = 0.234 from c4 (their nearest).
    # Single linkage (nearest neighbours) keeps the chain whole; a complete-linkage tree
    # would split it, since its diameter 0.5 exceeds the 0.234 gap to the d pair.
    expected = [[f"c{j}_C" for j in range(5)], ["d0_C", "d1_C"]]
    assert cluster_sensors(temps, n_clusters=2) == expected
    assert cluster_sensors(temps, distance_threshold=0.1) == expected
    assert cluster_sensors(temps, distance_threshold=0.3) == [list(temps.columns)]


def test_cluster_sensors_bad_input():
    temps = _three_groups()
    temps["dead_C"] = 21.0
    with pytest.raises(PreprocessError, match="'dead_C' is constant"):
        cluster_sensors(temps, n_clusters=3)
    temps = _three_groups()
    with pytest.raises(PreprocessError, match="exactly one of n_clusters or distance_threshold"):
        cluster_sensors(temps)
    with pytest.raises(PreprocessError, match="exactly one of n_clusters or distance_threshold"):
        cluster_sensors(temps, n_clusters=3, distance_threshold=0.1)
    with pytest.raises(PreprocessError, match="n_clusters=10 is more than the 9"):
        cluster_sensors(temps, n_clusters=10)
    temps.iloc[4, 2] = np.nan
    with pytest.raises(PreprocessError, match="'late0_C', row 4"):
        cluster_sensors(temps, n_clusters=3)


# ---------------------------------------------------------------- grey relational analysis (eq. 4-5)


def test_gra_grade_of_reference_with_itself_is_one():
    y = np.array([0.3, 0.1, 0.7, 0.2, 0.9])
    np.testing.assert_allclose(grey_relational_grade(y, y[:, None]), [1.0])
    np.testing.assert_allclose(grey_relational_grade(y, y), [1.0])  # 1-D = one candidate


def test_gra_affine_copy_outranks_noisy_unrelated():
    rng = np.random.default_rng(9)
    t = np.linspace(0, 1, 200)
    y = np.exp(-3 * t) + 0.2 * t  # a decreasing slope series, as in the paper
    cands = np.column_stack([rng.normal(0, 1, t.size), 5.0 * y + 30.0, 0.5 * y - 2.0 + rng.normal(0, 0.05, t.size)])
    g = grey_relational_grade(y, cands)
    assert g[1] > g[2] > g[0]
    # min-max normalisation: a positive affine copy is identical to the reference, so its
    # Δ is 0 everywhere and every coefficient is (Δmin + ξΔmax)/(0 + ξΔmax) = 1 (Δmin = 0)
    assert g[1] == pytest.approx(1.0, abs=1e-12)


def test_gra_eq5_hand_example_with_zero_min():
    # y = [0,1,2] -> [0, .5, 1];  x1 = [1,3,2] -> [0, 1, .5];  x2 = [0,0,1] -> [0, 0, 1]
    # Δ1 = [0, .5, .5], Δ2 = [0, .5, 0];  Δmin = 0, Δmax = .5;  ξ Δmax = .25
    # γ = (0 + .25) / (Δ + .25):  Δ = 0 -> 1, Δ = .5 -> 1/3
    # grade1 = (1 + 1/3 + 1/3) / 3 = 5/9;  grade2 = (1 + 1/3 + 1) / 3 = 7/9
    g = grey_relational_grade(np.array([0.0, 1.0, 2.0]), np.array([[1.0, 0.0], [3.0, 0.0], [2.0, 1.0]]), xi=0.5)
    np.testing.assert_allclose(g, [5 / 9, 7 / 9], rtol=1e-14)


def test_gra_eq5_hand_example_with_nonzero_min_and_xi():
    # y = [0,1,2,3] -> [0, 1/3, 2/3, 1]
    # x1 = [1,0,3,2] -> [1/3, 0, 1, 2/3]   Δ1 = [1/3, 1/3, 1/3, 1/3]
    # x2 = [2,0,3,1] -> [2/3, 0, 1, 1/3]   Δ2 = [2/3, 1/3, 1/3, 2/3]
    # Δmin = 1/3 (over both candidates and all k), Δmax = 2/3
    y = np.array([0.0, 1.0, 2.0, 3.0])
    X = np.array([[1.0, 2.0], [0.0, 0.0], [3.0, 3.0], [2.0, 1.0]])
    # ξ = 0.5: γ = (1/3 + 1/3) / (Δ + 1/3): Δ = 1/3 -> 1, Δ = 2/3 -> 2/3
    # grade1 = 1, grade2 = (2/3 + 1 + 1 + 2/3) / 4 = 5/6
    np.testing.assert_allclose(grey_relational_grade(y, X, xi=0.5), [1.0, 5 / 6], rtol=1e-14)
    # ξ = 0.4: ξΔmax = 4/15, numerator 1/3 + 4/15 = 9/15: Δ = 5/15 -> 1, Δ = 10/15 -> 9/14
    # grade2 = (2 + 2 * 9/14) / 4 = 23/28
    np.testing.assert_allclose(grey_relational_grade(y, X, xi=0.4), [1.0, 23 / 28], rtol=1e-14)
    # ξ = 1: numerator 1/3 + 2/3 = 1: Δ = 2/3 -> 1 / (4/3) = 3/4; grade2 = (2 + 1.5) / 4 = 7/8
    np.testing.assert_allclose(grey_relational_grade(y, X, xi=1.0), [1.0, 7 / 8], rtol=1e-14)
    # invariant to each sequence's units and offset (min-max normalisation)
    np.testing.assert_allclose(grey_relational_grade(10 * y - 4, X * [2.0, 0.1] + [20.0, 35.0], xi=0.5),
                               [1.0, 5 / 6], rtol=1e-14)  # fmt: skip


def test_gra_eq5_min_and_max_run_over_all_candidates():
    # y = [0,1,2] -> [0, .5, 1];  x1 = [0,2,1] -> [0, 1, .5];  x2 = [0,1.5,2] -> [0, .75, 1]
    # Δ1 = [0, .5, .5], Δ2 = [0, .25, 0]
    y = np.array([0.0, 1.0, 2.0])
    x2 = np.array([0.0, 1.5, 2.0])
    X = np.column_stack([[0.0, 2.0, 1.0], x2])
    # together: Δmin = 0, Δmax = .5 (from x1), ξΔmax = .25
    # x2: γ = [1, .25/(.25+.25), 1] = [1, 1/2, 1] -> 5/6;  x1: [1, 1/3, 1/3] -> 5/9
    np.testing.assert_allclose(grey_relational_grade(y, X), [5 / 9, 5 / 6], rtol=1e-14)
    # x2 alone: Δmax = .25, ξΔmax = .125: γ = [1, .125/.375, 1] = [1, 1/3, 1] -> 7/9
    np.testing.assert_allclose(grey_relational_grade(y, x2), [7 / 9], rtol=1e-14)


@pytest.mark.parametrize("xi", [0.0, -0.1, 1.5, float("nan")])
def test_gra_xi_out_of_range(xi):
    with pytest.raises(PreprocessError, match="xi"):
        grey_relational_grade(np.arange(4.0), np.arange(4.0), xi=xi)


def test_gra_bad_shapes_and_constant_sequences():
    with pytest.raises(PreprocessError, match=r"candidates: expected shape \(4, m\)"):
        grey_relational_grade(np.arange(4.0), np.ones((5, 2)))
    with pytest.raises(PreprocessError, match="reference is constant"):
        grey_relational_grade(np.ones(4), np.arange(8.0).reshape(4, 2))
    with pytest.raises(PreprocessError, match="candidates column 1 is constant"):
        grey_relational_grade(np.arange(4.0), np.column_stack([np.arange(4.0), np.ones(4)]))


# ---------------------------------------------------------------- sensitive-point selection


def _two_clusters(n=400, seed=10):
    """Cluster A (saturating rise) and cluster B (cycling); inside each cluster the
    sensors share the trend (within-cluster r > 0.7, across |r| < 0.3) but each carries its
    own deterministic wiggle. The target is built from A1 and B2 only, so those are the
    sensors that drive it: inside a cluster only they share the target's wiggles."""
    rng = np.random.default_rng(seed)
    t = np.linspace(0.0, 1.0, n)
    a = 1 - np.exp(-t / 0.15)
    b = np.sin(2 * np.pi * 1.5 * t)
    cols = {}
    for j, f in enumerate([7.0, 11.0, 17.0]):
        cols[f"A{j}_C"] = 20.0 + 4.0 * a + 0.8 * np.sin(2 * np.pi * f * t + j) + rng.normal(0, 0.01, n)
    for j, f in enumerate([5.0, 13.0, 19.0]):
        cols[f"B{j}_C"] = 22.0 + 1.0 * b + 0.3 * np.sin(2 * np.pi * f * t + 2 * j) + rng.normal(0, 0.005, n)
    temps = pd.DataFrame(cols)
    target = 0.8 * (temps["A1_C"] - 20.0) + 2.0 * (temps["B2_C"] - 22.0) + rng.normal(0, 0.01, n)
    return temps, target.to_numpy()


@pytest.mark.parametrize("method", ["gra", "correlation", "lasso"])
def test_select_picks_the_driving_sensor_of_each_cluster(method):
    temps, target = _two_clusters()
    sel = select_sensitive_points(temps, target, method=method, n_clusters=2)
    assert isinstance(sel, Selection) and sel.method == method
    assert sorted(map(sorted, sel.clusters)) == [["A0_C", "A1_C", "A2_C"], ["B0_C", "B1_C", "B2_C"]]
    assert set(sel.selected) == {"A1_C", "B2_C"}
    assert set(sel.scores) == set(temps.columns)
    s = [sel.scores[c] for c in sel.selected]
    assert s == sorted(s, reverse=True)
    assert sel == select_sensitive_points(temps, target, method=method, n_clusters=2)  # deterministic


def test_select_lasso_zeroes_the_passengers():
    temps, target = _two_clusters()
    sc = select_sensitive_points(temps, target, method="lasso", n_clusters=2).scores
    assert min(sc["A1_C"], sc["B2_C"]) > 5 * max(sc[c] for c in ("A0_C", "A2_C", "B0_C", "B1_C"))


def test_select_exclude_and_distance_threshold():
    temps, target = _two_clusters()
    sel = select_sensitive_points(temps, target, method="correlation", n_clusters=2, exclude=["A1_C"])
    assert "A1_C" not in sel.scores and all("A1_C" not in c for c in sel.clusters)
    assert len(sel.selected) == 2 and "B2_C" in sel.selected
    assert next(c for c in sel.selected if c.startswith("A")) in ("A0_C", "A2_C")
    sel = select_sensitive_points(temps, target, n_clusters=None, distance_threshold=0.5)
    assert set(sel.selected) == {"A1_C", "B2_C"}


def test_select_bad_inputs():
    temps, target = _two_clusters()
    with pytest.raises(PreprocessError, match="length 399 does not match the 400 rows"):
        select_sensitive_points(temps, target[:-1])
    with pytest.raises(PreprocessError, match="method must be one of"):
        select_sensitive_points(temps, target, method="pca")
    with pytest.raises(PreprocessError, match="exclude: column 'T6_C' is not in temps"):
        select_sensitive_points(temps, target, exclude=["T6_C"])
    with pytest.raises(PreprocessError, match="2 samples .* at least 3"):
        select_sensitive_points(temps.iloc[:2], target[:2], n_clusters=2)
    with pytest.raises(PreprocessError, match="3 samples .* fewer than n_clusters=4"):
        select_sensitive_points(temps.iloc[:3], target[:3], n_clusters=4)
    with pytest.raises(PreprocessError, match="n_clusters=7 is more than the 6"):
        select_sensitive_points(temps, target, n_clusters=7)
    with pytest.raises(PreprocessError, match="target is constant"):
        select_sensitive_points(temps, np.ones(len(temps)), n_clusters=2)
    with pytest.raises(PreprocessError, match="xi"):
        select_sensitive_points(temps, target, n_clusters=2, xi=0.0)
    bad = temps.copy()
    bad.loc[7, "B1_C"] = np.nan
    with pytest.raises(PreprocessError, match="'B1_C', row 7"):
        select_sensitive_points(bad, target, n_clusters=2)
    bad = temps.copy()
    bad["foot_C"] = 20.0
    with pytest.raises(PreprocessError, match="'foot_C' is constant"):
        select_sensitive_points(bad, target, n_clusters=2)
    # ... unless excluded, like the paper's machine-foot sensor
    assert set(select_sensitive_points(bad, target, n_clusters=2, exclude=["foot_C"]).selected) == {"A1_C", "B2_C"}


def test_select_correlation_score_is_absolute():
    t = np.linspace(0.0, 1.0, 200)
    target = np.exp(-3 * t)
    temps = pd.DataFrame({"falls_C": 30.0 - 2.0 * target, "wiggle_C": 20.0 + target + 0.3 * np.sin(40 * t)})
    sel = select_sensitive_points(temps, target, method="correlation", n_clusters=1)
    assert sel.scores["falls_C"] == pytest.approx(1.0, abs=1e-12)  # r = -1 exactly
    assert sel.selected == ["falls_C"]


def test_cluster_sensors_mirrored_trend_joins_its_group():
    # distance 1 - |r|: a sensor whose reading falls as the bearing warms (mirrored trend,
    # r = -1 with exp0) carries the same information and joins the exp group
    temps = _three_groups()
    temps["mirror_C"] = 40.0 - 2.0 * temps["exp0_C"]
    clusters = cluster_sensors(temps, n_clusters=3)
    assert ["exp0_C", "exp1_C", "exp2_C", "mirror_C"] in clusters


def test_limit_filter_does_not_freeze_on_a_glitch_at_the_first_sample():
    """A DS18B20 reads 85.0 °C at power-on: a run whose first reading is that value
    must not hold 85 °C for the whole run (the paper's rule alone would)."""
    x = np.r_[85.0, 20.0 + 0.001 * np.arange(50)]
    y = LimitFilter().transform(x)
    np.testing.assert_array_equal(y[1:], x[1:])
    assert y[0] == pytest.approx(np.median(x[1:6]))
