"""A lab's log sampled slower than the C runtime takes (a sample at least every 60 s): filled in for the
parity replay as the compensator would sample, checked by hand; and, where the files are bound to the
log's own period, the runtime's refusal said in one line."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from tests.test_lumped import spindle_dataset
from thermbench.export.encoding import ExportError
from thermbench.export.parity import _sampling_failure
from thermbench.export.runtime import RuntimeFailed
from thermbench.export.samples import FILL_STEP_S, MAX_GAP_S, runtime_log


def _slow(step_s=300.0, n=5):
    t = np.arange(n) * step_s
    runs = {r: {"t_s": t, "spindle_rpm": np.array([0.0, 1000, 1000, 3000, 0][:n]), "read_t_s": t,
                "error_um": np.zeros(n), "T_a_C": 20.0 + np.arange(n) * 1.5} for r in ("a", "b")}  # fmt: skip
    return spindle_dataset(runs, sensors={"T_a": "spindle"}, operating=[])


def test_a_slow_log_is_filled_in_evenly_and_linearly_and_the_logged_samples_stay():
    ds = _slow()
    out, widest = runtime_log(ds, ["a"])
    assert widest == 300.0 and out is not ds and ds.process_run("a").shape[0] == 5  # the dataset is not changed
    a = out.process_run("a")
    # each 300 s gap in ceil(300 / 59.4) = 6 steps of 50 s: 4 gaps x 5 inserted samples + the 5 logged ones
    assert np.allclose(np.diff(a["t_s"]), 50.0) and len(a) == 25 and FILL_STEP_S < MAX_GAP_S == 60.0
    logged = a[a["t_s"].isin(ds.process_run("a")["t_s"])]
    pd.testing.assert_frame_equal(logged.reset_index(drop=True), ds.process_run("a"), check_dtype=False)
    # by hand: T_a rises 1.5 K per 300 s, so 0.25 K per 50 s; the speed 1000 -> 3000 rpm between 600 and 900 s
    np.testing.assert_allclose(a["T_a_C"], 20.0 + 0.25 * np.arange(25))
    assert float(a.loc[a["t_s"] == 750.0, "spindle_rpm"].iloc[0]) == pytest.approx(2000.0)
    assert (a["run_id"] == "a").all()
    assert len(out.process_run("b")) == 5  # a run not replayed keeps its log
    fast, w = runtime_log(_slow(step_s=30.0), ["a", "b"])
    assert w == 30.0 and fast.process_run("a").shape[0] == 5  # within the runtime's gap: as it is


def test_a_period_bound_files_refusal_of_a_slow_log_is_one_line_naming_the_run_and_the_gap():
    ds = _slow()
    s = ds.process_run("a")
    said = _sampling_failure(RuntimeFailed("tb_replay: sample t=300: error -12: log not sampled at the model's period"),
                             ds, "a", s)  # fmt: skip
    assert isinstance(said, ExportError) and "\n" not in str(said)
    assert "run 'a' is logged up to 300 s apart; the C runtime takes a sample at least every 60 s" in str(said)
    assert "export.verify=false" in str(said)
    other = RuntimeFailed("tb_replay: error -3")
    assert _sampling_failure(other, ds, "a", s) is other  # any other failure as it is
    fast = _slow(step_s=30.0)
    grid = RuntimeFailed("tb_replay: sample t=30: error -12: log not sampled at the model's period")
    assert _sampling_failure(grid, fast, "a", fast.process_run("a")) is grid  # off the period's grid, not a gap
