"""Thermal error from interferometer data via the cold reference (seed 002 §3.1,
seed 004): the errors are not re-zeroed after the cold measurement, so the
thermal part at a target is the reading minus the mean of that target's
readings in the run's first measuring cycle(s) (the cold reference)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from .io import Dataset


def measuring_cycles(t_s: np.ndarray, target_mm: np.ndarray) -> np.ndarray:
    """Cycle index of each reading of one run: a new cycle starts when a target
    repeats within the current cycle or after a pause longer than 2.5 times
    the median gap between readings."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(target_mm, dtype=float)
    out = np.zeros(len(t), dtype=int)
    if len(t) < 2:
        return out
    typical = np.median(np.diff(t))
    seen: set[float] = {float(x[0])}
    c = 0
    for k in range(1, len(t)):
        if float(x[k]) in seen or t[k] - t[k - 1] > 2.5 * typical:
            c += 1
            seen = set()
        seen.add(float(x[k]))
        out[k] = c
    return out


def cold_reference(errors_run: pd.DataFrame) -> pd.Series:
    """Per target, the mean reading of the run's first measuring cycle (the cold
    reference, :func:`measuring_cycles` cycle 0)."""
    cyc = measuring_cycles(errors_run["t_s"].to_numpy(), errors_run["target_mm"].to_numpy())
    return errors_run[cyc == 0].groupby("target_mm")["error_um"].mean()


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
