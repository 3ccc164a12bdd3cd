"""The linear-with-history family (thermbench/models/linear_history.py) and its C kind LINEAR_HISTORY.

Checked against what is known independently: the delay line against the exact delayed value of a
linear input and a hand computation; the fitted family against an error planted as a delayed rise
(the continuous function, not the delay line); the C runtime (a second implementation of the line
and the weights) against Python at every reading in both precisions, on a log whose sample times are
irregular and off the line's grid."""

from __future__ import annotations

import numpy as np
import pytest
from sklearn.base import clone

from tests.synth import rise
from tests.test_lumped import spindle_dataset
from thermbench.metrics import evaluate
from thermbench.models.base import ModelError
from thermbench.models.linear_history import LinearHistory, delay_line

NOISE_UM = 0.05
DELAY_TRUE_S = 1800.0
SPECS = [(4.0, 600, 12000, 2.0, 3000, 15000), (6.0, 1800, 9000, 1.0, 600, 20000), (3.0, 300, 18000, 3.0, 6000, 10000),
         (5.0, 3600, 14000, 2.5, 1200, 8000), (2.0, 900, 20000, 1.5, 2400, 16000)]  # fmt: skip
SENSORS = {"T_a": "spindle", "T_b": "structure", "T_c": "ambient"}


def test_the_delay_line_gives_a_linear_input_exactly_delayed_on_an_irregular_log():
    rng = np.random.default_rng(1)
    t = 100.0 + np.cumsum(rng.uniform(5.0, 25.0, 400))  # irregular, off any 60 s grid
    u = 3.0 + 0.002 * (t - t[0])
    out = delay_line(t, u, [0.0, 60.0, 900.0], 60.0)
    assert np.array_equal(out[:, 0], u)  # a delay of 0: the input itself
    for k, d in ((1, 60.0), (2, 900.0)):
        late = t - d >= t[0]
        np.testing.assert_allclose(out[late, k], 3.0 + 0.002 * (t[late] - d - t[0]), rtol=0, atol=1e-12)
        assert np.all(out[~late, k] == 3.0)  # before the first sample: its value


def test_the_delay_line_by_hand():
    # samples at 0, 7, 15, 30 s of 0, 7, 23, 8; a line of 10 s holds v(0) = 0, v(10) = 7 + 3/8 * 16 = 13,
    # v(20) = 23 - 5/15 * 15 = 18, v(30) = 8; 10 s earlier at 30 s: v(20) = 18; at 15 s: 5 s, 0.5 x 13 = 6.5
    t, u = np.array([0.0, 7.0, 15.0, 30.0]), np.array([0.0, 7.0, 23.0, 8.0])
    out = delay_line(t, u, [10.0], 10.0)[:, 0]
    np.testing.assert_allclose(out, [0.0, 0.0, 6.5, 18.0], atol=1e-12)


def _runs(specs, seed=0):
    """Spindle runs on an irregular 10-20 s log: the error = 2.0 x the rise of T_a 30 min earlier
    (the continuous function) + 1.0 x the rise of T_b now + noise; T_c wanders and plays no part."""
    rng = np.random.default_rng(seed)
    runs = {}
    for k, (amp_a, on_a, off_a, amp_b, on_b, off_b) in enumerate(specs):
        t = np.concatenate([[0.0], np.cumsum(rng.uniform(10.0, 20.0, 1500))])
        t = t[t <= 6 * 3600.0]
        ta, tb = rise(t, amp_a, 1200.0, on_a, off_a), rise(t, amp_b, 900.0, on_b, off_b)
        tc = 0.8 * np.sin(t / 5000.0 + k) + 0.02 * rng.standard_normal(t.size)
        err = 2.0 * rise(t - DELAY_TRUE_S, amp_a, 1200.0, on_a, off_a) + tb + NOISE_UM * rng.standard_normal(t.size)
        runs[f"r{k}"] = {"t_s": t, "spindle_rpm": np.full(t.size, 1000.0 * (k + 1)), "read_t_s": t, "error_um": err,
                         "T_a_C": 20 + ta, "T_b_C": 21 + tb, "T_c_C": 20.5 + tc - tc[0]}  # fmt: skip
    return runs


@pytest.fixture(scope="module")
def planted():
    return spindle_dataset(_runs(SPECS), sensors=SENSORS, operating=["spindle_rpm"])


def test_it_finds_the_planted_delay_and_reaches_the_noise_floor_where_the_rises_now_do_not(planted):
    m = LinearHistory().fit(planted, ["r0", "r1", "r2", "r3"])
    assert DELAY_TRUE_S in m.delays_s_ and m.inputs_ == ["T_a", "T_b", "T_c"]  # every sensor, no selection
    rmse = evaluate(m, planted, ["r4"])["rmse_um"].iloc[0]
    now_only = LinearHistory(delays_s=[[0.0]]).fit(planted, ["r0", "r1", "r2", "r3"])
    rmse_now = evaluate(now_only, planted, ["r4"])["rmse_um"].iloc[0]
    assert rmse < 3 * NOISE_UM < rmse_now / 5
    # its own cross-validation chose the set and penalty of the lowest held-out RMSE it measured
    best = min(m.cv_results_, key=lambda r: r["cv_rmse_um"])
    assert (best["delays_s"], best["alpha"], best["cv_rmse_um"]) == (m.delays_s_, m.alpha_, m.cv_rmse_um_)
    line = m.fit_summary()
    later = [round(d) for d in m.delays_s_ if d > 0]
    assert 1800 in later and line.startswith(f"every input (3) now and {later} s earlier (a delay line of 60 s)")


def test_it_is_a_scikit_learn_estimator_and_refuses_a_step_longer_than_a_delay(planted):
    m = LinearHistory(delays_s=[[0.0, 600.0]], delay_step_s=30.0)
    c = clone(m)
    assert c.get_params() == m.get_params() and set(c.get_params()) == {"sensors", "operating", "delays_s",
                                                                        "delay_step_s", "alphas"}  # fmt: skip
    with pytest.raises(ModelError, match=r"LinearHistory.delay_step_s: 900 s is longer than the shortest delay 600 s"):
        LinearHistory(delays_s=[[0.0, 600.0]], delay_step_s=900.0).fit(planted, ["r0", "r1"])
    with pytest.raises(ModelError, match=r"LinearHistory.delays_s"):
        LinearHistory(delays_s=[[0.0, -60.0]]).fit(planted, ["r0", "r1"])


@pytest.mark.parametrize("operating", [[], ["spindle_rpm"]])
def test_the_c_runtime_kind_reproduces_python_in_both_precisions(planted, operating, tmp_path):
    """LINEAR_HISTORY (embedded/src/tb_kind_linear_history.c): the export's parity check replays the
    held-out run through the C runtime; double to 1e-9 µm, float within 0.01 µm, at every reading."""
    from thermbench.export import export_model

    m = LinearHistory(operating=operating).fit(planted, ["r0", "r1", "r2", "r3"])
    man = export_model(m, tmp_path / "lh", "lh", ds=planted, heldout=["r4"])
    p = man["parity"]["model"]
    assert man["kind"] == "LINEAR_HISTORY" and p["n_readings"] > 1000
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01
    assert p["heldout_rmse_um_c"] == pytest.approx(evaluate(m, planted, ["r4"])["rmse_um"].iloc[0], abs=1e-9)
    assert man["operating"] == operating
