"""A run of a dataset as the C runtime is fed and asked it: its process samples (with the
``measuring`` flag) and its readings as queries."""

from __future__ import annotations

import numpy as np
import pandas as pd

from ..models.motion_windows import measuring_intervals


def process_samples(ds, run: str) -> pd.DataFrame:
    """The run's process log with ``measuring`` (inside a measuring cycle: what the
    compensator knows and leaves out of the motion features)."""
    pr = ds.process_run(run).copy()
    t = pr["t_s"].to_numpy()
    meas = np.zeros(t.size, dtype=bool)
    for a, b in measuring_intervals(pr, ds.errors_run(run)):
        meas |= (t >= a) & (t <= b)
    pr["measuring"] = meas
    return pr


def readings_queries(ds, run: str) -> pd.DataFrame:
    er = ds.errors_run(run)
    return pd.DataFrame({"t_s": er["t_s"].to_numpy(), "axis_mm": er["target_mm"].to_numpy(), "error_um": er["error_um"].to_numpy()})
