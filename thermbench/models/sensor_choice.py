"""Choosing the temperature sensors a data-driven model uses: the given ones (checked), or the
temperature-sensitive points of seed 002 §2.3.1 picked on the training runs."""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

from ..data.dataset import Dataset
from .base import ModelError, _name, check_sensors, is_fixed_point, readings, require, temperatures_at
from .separation import cycle_curves


def choose_sensors(
    ds: Dataset,
    runs: Sequence[str],
    sensors: Sequence[str] | None,
    selection: dict | None,
    preprocess,
    key: str = "sensors",
) -> list[str]:
    """The sensors a data-driven model uses: ``sensors`` when given (checked), else
    the temperature-sensitive points of seed 002 §2.3.1 picked on the training runs:
    clustering of the (filtered) non-ambient sensors, one per cluster by the score
    of ``selection['method']`` against the slope of the measured thermal error."""
    if isinstance(sensors, str):
        sensors = [sensors]
    if sensors is not None:
        if len(sensors) == 0:
            raise ModelError(f"{key}: an empty list; name at least one sensor or pass None to select")
        return check_sensors(ds, list(sensors), key)
    from ..preprocess.selection import select_sensitive_points

    cand = [s for s, loc in ds.metadata.sensors.items() if loc != "ambient"]
    if not cand:
        raise ModelError(f"{key}: the dataset {_name(ds)} has no temperature sensors besides the ambient")
    opts = dict(selection or {})
    n_clusters = opts.pop("n_clusters", 2)
    rd = readings(ds, runs)
    fixed = is_fixed_point(ds)  # at a fixed point the drift itself, along an axis the slope of the error line
    curves, _ = cycle_curves(rd, 0 if fixed else 1)
    temps = np.vstack([temperatures_at(ds, r, cand, g["t_s"], preprocess) for r, g in curves.groupby("run_id", sort=False)])
    require(len(curves), 3, "measuring cycles for sensor selection")
    # a sensor that never moves over the training runs (a drive temperature read in whole degrees that
    # stayed put) carries nothing to cluster or rank: it is not a candidate
    moving = np.ptp(temps, axis=0) > 0
    if not moving.any():
        raise ModelError(f"{key}: no temperature sensor of the dataset {_name(ds)} besides the ambient changes over "
                         f"the training runs {list(runs)}; nothing to select from")  # fmt: skip
    cand, temps = [c for c, m in zip(cand, moving) if m], temps[:, moving]
    slope = curves["c0" if fixed else "c1"].to_numpy()
    # the slope falls as the screw heats when the fixed end is on the positive side (Pf > 0):
    # orient it to rise with temperature, since grey relational grades compare shapes, not |r|
    if np.corrcoef(slope, temps.mean(axis=1))[0, 1] < 0:
        slope = -slope
    sel = select_sensitive_points(
        pd.DataFrame(temps, columns=cand), slope, n_clusters=min(n_clusters, len(cand)), **opts
    )
    return list(sel.selected)
