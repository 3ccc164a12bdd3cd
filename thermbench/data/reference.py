"""Thermal error from interferometer data via the cold reference (seed 002 §3.1,
seed 004): the errors are not re-zeroed after the cold measurement, so the
thermal part at a target is the reading minus the mean of that target's
readings in the run's first measuring cycle(s) (the cold reference)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .io import Dataset


def cold_reference(errors_run: pd.DataFrame) -> pd.Series:
    """Per target, the mean reading of the cold reference cycles (before any
    target is read for the second time after the first cycle of other targets).

    The reference cycles are those whose readings come before the run's first
    feed motion that is not a measuring move; without the process log we take
    the readings up to the first time gap larger than twice the median gap
    between consecutive readings of one cycle.
    """
    t = errors_run["t_s"].to_numpy()
    if len(t) < 2:
        return errors_run.groupby("target_mm")["error_um"].mean()
    gaps = np.diff(t)
    typical = np.median(gaps)
    big = np.flatnonzero(gaps > 2.5 * typical)
    end = big[0] + 1 if big.size else len(t)
    ref = errors_run.iloc[:end]
    return ref.groupby("target_mm")["error_um"].mean()


def thermal_errors(ds: Dataset) -> pd.DataFrame:
    """The errors table with ``thermal_um`` = error - cold reference at the same target."""
    parts = []
    for run_id in ds.run_ids:
        er = ds.errors_run(run_id)
        ref = cold_reference(er)
        er = er.assign(thermal_um=er["error_um"] - er["target_mm"].map(ref).fillna(0.0).to_numpy())
        parts.append(er)
    return pd.concat(parts, ignore_index=True)


def run_summary(ds: Dataset) -> pd.DataFrame:
    """One row per run: duration, condition, max |thermal error| measured."""
    te = thermal_errors(ds)
    rows = []
    for run_id, run in ds.metadata.runs.items():
        pr = ds.process_run(run_id)
        tr = te[te["run_id"] == run_id]
        c = run.condition
        rows.append(
            {
                "run_id": run_id,
                "duration_h": float(pr["t_s"].iloc[-1] - pr["t_s"].iloc[0]) / 3600.0,
                "stroke_mm": c.stroke_mm,
                "start_mm": c.start_mm,
                "end_mm": c.end_mm,
                "feed_mm_min": c.feed_mm_min,
                "readings": len(tr),
                "max_thermal_error_um": float(tr["thermal_um"].abs().max()),
            }
        )
    return pd.DataFrame(rows)
