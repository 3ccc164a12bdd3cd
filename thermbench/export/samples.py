"""A run of a dataset as the C runtime is fed and asked it: its process samples (with the
``measuring`` flag) and its readings as queries."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

from ..models.motion_windows import measuring_intervals
from .lumped_encoding import MAX_GAP_S  # tb_runtime.h TB_MAX_GAP_S: the compensator samples at least once a minute


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


#: a replayed log's inserted samples are at most this far apart: below MAX_GAP_S by more than the rounding
#: of a time of a day's run in single precision (0.008 s at 72 000 s), which the float build compares
FILL_STEP_S = 0.99 * MAX_GAP_S


def runtime_log(ds, runs: Sequence[str]):
    """The dataset as the compensator would sample the process of ``runs``: where a run's log has a
    gap over :data:`MAX_GAP_S` (a lab's logger every 2 or 5 min), samples are inserted evenly in the
    gap (at most :data:`FILL_STEP_S` apart), each numeric column linear between the two logged
    samples around it and any other column the earlier sample's; the logged samples themselves and
    the readings are unchanged. Returns (the dataset, or ``ds`` itself when no run needs it; the
    largest gap found). The parity check and the target measurement replay this log through both
    the Python model and the C runtime: the same inputs, answered by two implementations."""
    import dataclasses

    parts, widest, changed = [], 0.0, False
    for run, g in ds.process.groupby("run_id", sort=False):
        t = g["t_s"].to_numpy(dtype=float)
        gaps = np.diff(t)
        widest = max(widest, float(gaps.max())) if gaps.size and run in runs else widest
        if run not in runs or not gaps.size or float(gaps.max()) <= MAX_GAP_S:
            parts.append(g)
            continue
        n = np.ceil(gaps / FILL_STEP_S).astype(int)  # steps per gap
        extra = np.concatenate([t[i] + gaps[i] * np.arange(1, n[i]) / n[i] for i in np.flatnonzero(n > 1)])
        tt = np.sort(np.concatenate([t, extra]))
        out = {}
        for c in g.columns:
            col = g[c]
            if c == "t_s":
                out[c] = tt
            elif pd.api.types.is_numeric_dtype(col) and not pd.api.types.is_bool_dtype(col):
                out[c] = np.interp(tt, t, col.to_numpy(dtype=float))
            else:  # the earlier logged sample's value
                out[c] = col.to_numpy()[np.searchsorted(t, tt, side="right") - 1]
        parts.append(pd.DataFrame(out, columns=g.columns))
        changed = True
    if not changed:
        return ds, widest
    return dataclasses.replace(ds, process=pd.concat(parts, ignore_index=True)), widest
