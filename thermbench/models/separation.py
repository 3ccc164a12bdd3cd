"""Separating the geometric (pitch) error from the thermal error, the ways the seeds do it.

* Cold reference (seed 001 eq. 11; seed 000): the error measured at 0 min, fitted
  by a polynomial in position, is the geometric error; the rest is thermal.
* Curve-shape separation (seed 004; seed 002 eq. 6-7): every measuring cycle's
  error curve is fitted by the shape the mounting implies (a straight line for
  fixed-free and fixed-supported, a parabola for fixed-fixed; seed 002 uses a
  line). The fit is the thermal part; the mean residual at each measuring point
  over all cycles is the geometric error, itself fitted by a polynomial (seed 002
  eq. 7: a cubic).

And the degree of the thermal error curve a dataset implies (:func:`curve_degree`).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from numpy.polynomial import Polynomial

from ..data.dataset import Dataset
from .base import ModelError, is_fixed_point, polynomial_fit

SHAPE_DEGREE = {"fixed_free": 1, "fixed_supported": 1, "fixed_fixed": 2}


def curve_at(coef: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Per row, the polynomial with ascending coefficients ``coef[i]`` evaluated at ``p[i]``."""
    coef = np.asarray(coef, dtype=float)
    return np.sum(coef * np.asarray(p, dtype=float)[:, None] ** np.arange(coef.shape[1])[None, :], axis=1)


def cold_reference_geometric(rd: pd.DataFrame, degree: int = 4) -> Polynomial:
    """Polynomial in position through the cold reference readings (cycle 0 of
    every run): seed 001 eq. 11, E_p = d4 Px^4 + ... + d0."""
    ref = rd[rd["cycle"] == 0]
    return polynomial_fit(ref["target_mm"].to_numpy(), ref["error_um"].to_numpy(), degree, "the cold reference")


def shape_degree(mounting: str) -> int:
    """Degree of the thermal error curve in position for a mounting (seed 004)."""
    if mounting not in SHAPE_DEGREE:
        raise ModelError(f"mounting must be one of {sorted(SHAPE_DEGREE)}, got {mounting!r}")
    return SHAPE_DEGREE[mounting]


def curve_degree(ds: Dataset, mounting: str | None = None) -> int:
    """Degree of the thermal error curve over the measuring points: 0 at a fixed point
    (the drift itself), else the shape the screw mounting implies (seed 004), a straight
    line (seed 002) when the dataset has no screw block."""
    if is_fixed_point(ds):
        return 0
    if mounting is not None:
        return shape_degree(mounting)
    return shape_degree(ds.metadata.screw.mounting) if ds.metadata.screw is not None else 1


def cycle_curves(rd: pd.DataFrame, degree: int, origin_mm: float = 0.0) -> tuple[pd.DataFrame, np.ndarray]:
    """Fit every (run, cycle) error curve by a polynomial of ``degree`` in (P - origin).

    Returns one row per cycle (``run_id``, ``cycle``, ``t_s`` = mean reading time,
    ``c0`` .. ``c<degree>`` ascending coefficients) and the residual of every reading.
    Cycles with fewer than degree + 2 distinct targets are dropped (residual NaN).
    Degree 0 (a fixed measuring point: the curve is the reading itself) keeps every cycle.
    """
    if degree == 0:  # the curve is the cycle's mean reading: no fit needed (a fixed point: one reading a cycle)
        g = rd.groupby(["run_id", "cycle"], sort=False)
        mean = g["error_um"].transform("mean").to_numpy()
        agg = g.agg(t_s=("t_s", "mean"), c0=("error_um", "mean")).reset_index()
        if agg.empty:
            raise ModelError("too few samples: no measuring cycle has 2 or more distinct targets")
        agg["t_s"] = agg["t_s"].astype(float)
        return agg[["run_id", "cycle", "t_s", "c0"]], rd["error_um"].to_numpy(dtype=float) - mean
    rows = []
    resid = np.full(len(rd), np.nan)
    for (run, cyc), g in rd.groupby(["run_id", "cycle"], sort=False):
        p = g["target_mm"].to_numpy() - origin_mm
        if degree > 0 and np.unique(p).size < degree + 2:
            continue
        coef = np.polynomial.polynomial.polyfit(p, g["error_um"].to_numpy(), degree)
        resid[g.index.to_numpy()] = g["error_um"].to_numpy() - np.polynomial.polynomial.polyval(p, coef)
        rows.append({"run_id": run, "cycle": cyc, "t_s": float(g["t_s"].mean()), **{f"c{i}": c for i, c in enumerate(coef)}})
    if not rows:
        raise ModelError(f"too few samples: no measuring cycle has {degree + 2} or more distinct targets")
    return pd.DataFrame(rows), resid


def line_separated_geometric(rd: pd.DataFrame, degree: int | None = 3, origin_mm: float = 0.0):
    """Seed 002 eq. 6-7 in one call: a line per measuring cycle, then the mean
    residual per measuring point fitted by a polynomial of ``degree`` (one measuring
    point: its curve is the reading, the geometric error 0)."""
    _, resid = cycle_curves(rd, 0 if rd["target_mm"].nunique() == 1 else 1, origin_mm)
    return geometric_from_residuals(rd, resid, degree)


class TargetTable:
    """Geometric error as per-target values, linear in between (a pitch table)."""

    def __init__(self, axis_mm: np.ndarray, error_um: np.ndarray) -> None:
        self.axis_mm = np.asarray(axis_mm, dtype=float)
        self.error_um = np.asarray(error_um, dtype=float)

    def __call__(self, x: np.ndarray) -> np.ndarray:
        return np.interp(x, self.axis_mm, self.error_um)


def geometric_from_residuals(rd: pd.DataFrame, resid: np.ndarray, degree: int | None):
    """The geometric error as the mean residual at each measuring point (seed 004),
    fitted by a polynomial of ``degree`` (seed 002 eq. 7: 3); ``None`` keeps the
    per-target means as a :class:`TargetTable` (piecewise linear)."""
    ok = ~np.isnan(resid)
    means = pd.Series(resid[ok]).groupby(rd["target_mm"].to_numpy()[ok]).mean()
    if means.size == 1:  # one measuring point (a fixed-point channel): a constant
        return Polynomial([float(means.iloc[0])])
    if degree is None:
        return TargetTable(means.index.to_numpy(), means.to_numpy())
    return polynomial_fit(means.index.to_numpy(), means.to_numpy(), degree, "the geometric error")
