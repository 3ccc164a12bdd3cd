"""``dataset.history``: a derived segment that keeps its past. Its process log starts where its
run starts, its readings are its own, its thermal error and its temperature rises count from the
start of the test; a model is fitted and scored on the segment's readings only."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from tests.test_dataset_v2 import SPINDLE_META, write
from thermbench.data import load_dataset
from thermbench.experiment import ExperimentError, dataset_view
from thermbench.models.base import temperatures_at


def two_blocks(tmp_path):
    """Two heating blocks (1000 rpm, then 3000 rpm), each followed by a stop; the drift of
    channel Z is 2 µm + 0.01 µm/s from the first reading (written here by hand)."""
    t = np.arange(0.0, 8000.0, 10.0)
    rpm = np.select([(t >= 100) & (t < 2000), (t >= 4000) & (t < 6000)], [1000.0, 3000.0], 0.0)
    p = pd.DataFrame({"run_id": "r1", "t_s": t, "spindle_rpm": rpm, "T_front_C": 20.0 + 0.001 * t, "T_amb_C": 20.0})
    e = pd.DataFrame({"run_id": "r1", "t_s": t, "channel": "Z", "error_um": 2.0 + 0.01 * t})
    meta = {**SPINDLE_META, "channels": {"Z": SPINDLE_META["channels"]["Z"]},
            "runs": {"r1": {"segments": ["low", "high"]}}}  # fmt: skip
    return load_dataset(write(tmp_path / "d", meta, p, e))


def test_a_segment_with_history_keeps_the_log_before_it_and_the_whole_runs_reference(tmp_path):
    ds = two_blocks(tmp_path)
    plain = dataset_view(ds, "Z", segments=True, history=False)
    hist = dataset_view(ds, "Z", segments=True, history=True)
    assert plain.run_ids == hist.run_ids == ["low", "high"]
    # without history the second block starts where it starts; with it, its log starts at 0 s
    assert plain.process_run("high")["t_s"].iloc[0] == 4000.0
    assert hist.process_run("high")["t_s"].iloc[0] == 0.0
    # the readings are the segment's own either way
    for view in (plain, hist):
        er = view.errors_run("high")
        assert er["t_s"].min() == 4000.0 and er["t_s"].max() == 7990.0
    # thermal error: from the block's first reading without history, from the test's first with it
    er_p, er_h = plain.errors_run("high"), hist.errors_run("high")
    np.testing.assert_allclose(er_p["thermal_um"], 0.01 * (er_p["t_s"] - 4000.0), atol=1e-9)
    np.testing.assert_allclose(er_h["thermal_um"], 0.01 * er_h["t_s"], atol=1e-9)
    # what is predicted and scored: the drift from the run's first reading (the frame the dataset
    # declares, first_reading), not the reading as read (2 µm of it is the gauge's zero)
    np.testing.assert_allclose(er_h["error_um"], 0.01 * er_h["t_s"], atol=1e-9)
    # temperature rises: from the test's first sample (0.001 K/s since 0 s), not from the block's
    rise = temperatures_at(hist, "high", ["T_front"], [5000.0], preprocess=None)
    assert rise[0, 0] == pytest.approx(5.0)
    rise = temperatures_at(plain, "high", ["T_front"], [5000.0], preprocess=None)
    assert rise[0, 0] == pytest.approx(1.0)


def test_history_is_a_flag_and_needs_segments(tmp_path):
    ds = two_blocks(tmp_path)
    with pytest.raises(ExperimentError, match=r"config key 'dataset.history': expected true or false"):
        dataset_view(ds, "Z", segments=True, history="yes")
    with pytest.raises(ExperimentError, match=r"config key 'dataset.history': true needs dataset.segments=true"):
        dataset_view(ds, "Z", segments=False, history=True)


def test_a_model_scored_on_a_segment_with_history_sees_only_its_readings(tmp_path):
    """A least-squares line in the temperature rise, fitted on block 'low' with history: the
    drift from the first reading (0.01 t µm; the reading is 2 + 0.01 t) is exactly 10 ΔT with
    ΔT = 0.001 t, so it is recovered from the block alone (no intercept: the gauge's 2 µm zero is
    not part of it) and predicts block 'high' exactly (a hand-computed check of what is fitted)."""
    from sklearn.linear_model import LinearRegression

    from thermbench.models.baseline import SensorRegressor

    hist = dataset_view(two_blocks(tmp_path), "Z", segments=True, history=True)
    m = SensorRegressor(estimator=LinearRegression(), sensors=["T_front"]).fit(hist, ["low"])
    assert m.estimator_.coef_[0] == pytest.approx(10.0)
    assert m.estimator_.intercept_ == pytest.approx(0.0, abs=1e-9)
    er = hist.errors_run("high")
    np.testing.assert_allclose(m.predict(hist, "high"), er["error_um"], atol=1e-9)
