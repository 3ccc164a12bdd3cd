"""Accuracy metrics, the one definition used everywhere (models, experiments, reports).

The residual is measured minus predicted positioning error. The scale it is
judged against is the measured *thermal* error (reading minus the cold
reference), as seeds 000 and 002 report it:

* ``rmse_um``, ``max_abs_residual_um``, ``pv_residual_um`` (peak-to-valley of the residual);
* ``compensation_rate`` = 1 - max|residual| / max|thermal error| (seed 000 §5, seed 002 §3);
* ``residual_fraction_of_pv`` = max|residual| / P-V of the thermal error, the
  quantity behind seed 000's "residual within 15 % of the P-V" criterion.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd


def residual_metrics(measured_um, predicted_um, thermal_um=None) -> dict[str, float]:
    """Metrics of ``measured - predicted``; ``thermal_um`` is the measured thermal
    error the rates refer to (default: ``measured_um`` itself)."""
    m = np.asarray(measured_um, dtype=float).ravel()
    p = np.asarray(predicted_um, dtype=float).ravel()
    th = m if thermal_um is None else np.asarray(thermal_um, dtype=float).ravel()
    if m.shape != p.shape or m.shape != th.shape:
        raise ValueError(f"measured, predicted and thermal must have equal length, got {m.size}, {p.size}, {th.size}")
    if m.size == 0:
        raise ValueError("no samples to score")
    if not (np.all(np.isfinite(p))):
        raise ValueError(f"predictions contain {int(np.sum(~np.isfinite(p)))} non-finite value(s)")
    r = m - p
    max_err = float(np.max(np.abs(th)))
    pv_err = float(np.ptp(th))
    max_res = float(np.max(np.abs(r)))
    return {
        "rmse_um": float(np.sqrt(np.mean(r**2))),
        "rms_error_um": float(np.sqrt(np.mean(m**2))),  # the rmse_um of no compensation
        "max_abs_residual_um": max_res,
        "pv_residual_um": float(np.ptp(r)),
        "max_abs_error_um": max_err,
        "pv_error_um": pv_err,
        "compensation_rate": 1.0 - max_res / max_err if max_err > 0 else float("nan"),
        "residual_fraction_of_pv": max_res / pv_err if pv_err > 0 else float("nan"),
    }


def cycle_curves(readings: pd.DataFrame, predicted_um) -> pd.DataFrame:
    """Per measuring cycle of one run: ``before_um`` = max |thermal error| (uncompensated)
    and ``after_um`` = max |measured - predicted| (compensated), at the cycle's mean time."""
    from ..data.reference import reading_cycles

    cyc = readings["cycle"].to_numpy() if "cycle" in readings.columns else reading_cycles(readings)
    df = pd.DataFrame(
        {
            "cycle": cyc,
            "t_s": readings["t_s"].to_numpy(),
            "before_um": np.abs(readings["thermal_um"].to_numpy()),
            "after_um": np.abs(readings["error_um"].to_numpy() - np.asarray(predicted_um, dtype=float)),
        }
    )
    return df.groupby("cycle").agg(t_s=("t_s", "mean"), before_um=("before_um", "max"), after_um=("after_um", "max")).reset_index()


def evaluate(model, dataset, runs: Sequence[str] | None = None, curves: bool = False):
    """One row of :func:`residual_metrics` per run for a fitted model (a run where the model
    predicts a non-finite value scores NaN, ``nonfinite_predictions`` counts them); with ``curves=True``
    also the per-cycle before/after table of :func:`cycle_curves` (``run_id`` column)."""
    from ..data.reference import thermal_errors

    te = thermal_errors(dataset)
    rows, parts = [], []
    for run in runs if runs is not None else dataset.run_ids:
        tr = te[te["run_id"] == run]
        pred = np.asarray(model.predict(dataset, run), dtype=float)
        bad = int(np.sum(~np.isfinite(pred)))
        if bad:  # a model that predicts NaN/inf on a run scores NaN there (never chosen nor registered)
            nan = dict.fromkeys(residual_metrics(tr["error_um"], np.zeros_like(pred), tr["thermal_um"]), float("nan"))
            rows.append({"run_id": run, **nan, "nonfinite_predictions": bad})
        else:
            rows.append({"run_id": run, **residual_metrics(tr["error_um"], pred, tr["thermal_um"]), "nonfinite_predictions": 0})
        if curves:
            parts.append(cycle_curves(tr, pred).assign(run_id=run))
    if not curves:
        return pd.DataFrame(rows)
    return pd.DataFrame(rows), pd.concat(parts, ignore_index=True)
