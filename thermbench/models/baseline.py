"""Baselines: what a user would pick instead of a thermal error model family.

The methods of the peers, so every thermbench family is compared in the same tables with
what an engineer without thermbench would try first: a scikit-learn regressor on the rises
of **all** temperature sensors above the run's first reading, with no sensor selection, no
filtering, no physics and no memory (the source repository of the measured spindle test,
``thermbench/realdata/fl_thermal/SOURCE.md``, tuned a random forest and XGBoost on its
sixteen temperatures):

* ``baseline_ols``: ordinary least squares (:class:`sklearn.linear_model.LinearRegression`);
* ``baseline_rf``: :class:`sklearn.ensemble.RandomForestRegressor` (seeded);
* ``baseline_hgb``: :class:`sklearn.ensemble.HistGradientBoostingRegressor` (seeded);
* ``baseline_ridge``: what a careful user writes in ten lines: :class:`~sklearn.preprocessing.StandardScaler`
  and :class:`~sklearn.linear_model.RidgeCV` (alphas 1e-3..1e3, 13 on a log scale) on the rises and
  the same rises 30 min earlier (``lags_s``: a thermal lag, zero before the run's first 30 min).

:class:`SensorRegressor` wraps any scikit-learn regressor. Features at a reading (t, P):
the rises ΔT_j(t) of every sensor of the dataset (or of ``sensors``), and with ``lags_s`` the
same rises ``lag`` seconds earlier, ΔT_j(t - lag) (0 before the run's first sample); on an axis with
several measuring targets also the position P and, for the linear model, P·ΔT_j (a thermal
error that grows along the axis). The target is the reading itself (``error_um``); the
geometric part is left in the regressor (``geometric_`` is 0), as a user fitting a
regressor to the raw readings would.

Threads: an estimator's OpenMP and BLAS pools (``baseline_hgb``'s booster is OpenMP-parallel)
run with the thread count of the job that fits it, like every family's
(:func:`thermbench.models.base.thread_budget`, applied by ``ThermalErrorModel.fit``).
"""

from __future__ import annotations

from typing import Annotated, Any, Optional, Sequence

import numpy as np
from annotated_types import Gt, Len
from numpy.polynomial import Polynomial
from pydantic import AfterValidator
from sklearn.base import clone, is_regressor

from ..data.dataset import Dataset
from .base import Inputs, ModelError, ThermalErrorModel, readings, temperatures_at
from .params import Bool, Expect, Params, Seed, check_params

__all__ = ["SensorRegressor"]


def _regressor(est):
    """A scikit-learn regressor, or a pipeline that ends in one (``is_regressor``)."""
    try:
        ok = is_regressor(est)
    except AttributeError:  # not a scikit-learn estimator at all
        ok = False
    if not ok:
        raise ValueError("not a regressor")
    return est


class SensorRegressorParams(Params):
    estimator: Annotated[Any, AfterValidator(_regressor), Expect("a scikit-learn regressor (or a pipeline ending in one)")]
    sensors: Annotated[Optional[Annotated[Sequence[str], Len(min_length=1)]],
                       Expect("None or a non-empty list of sensor names")]  # fmt: skip
    seed: Optional[Seed]  # the estimator's random_state
    interactions: Bool
    lags_s: Annotated[Sequence[Annotated[float, Gt(0)]], Expect("a list of lags in seconds, each > 0")]


class SensorRegressor(ThermalErrorModel):
    """A scikit-learn regressor on the temperature rises of all sensors (module docstring).

    Parameters
    ----------
    estimator : scikit-learn regressor
        Cloned at fit (e.g. ``RandomForestRegressor(n_estimators=100, random_state=0)``).
    sensors : list of str or None
        The sensors whose rises are the features; None: every sensor of the dataset.
    seed : int or None
        Set as the estimator's ``random_state`` when it has one (``thermbench train`` and
        ``benchmark`` set it from their top-level ``seed``).
    interactions : bool
        With several measuring targets: also P·ΔT_j (for a linear estimator).
    lags_s : list of float
        Also the rises this many seconds earlier, one set per lag (0 before the run's first
        sample: the rise of a machine that had not started).

    Fitted: ``estimator_``, ``sensors_``, ``targets_mm_`` (the distinct measuring targets),
    ``uses_position_`` and ``geometric_`` (0: the regressor predicts the whole reading).

    ``reference_only``: the benchmark reports it beside the families and never chooses it.
    """

    complexity = 1  # ThermalErrorModel.complexity

    reference_only = True
    params_model = SensorRegressorParams

    def __init__(self, estimator=None, sensors=None, seed=None, interactions=False, lags_s=()):
        self.estimator = estimator
        self.sensors = sensors
        self.seed = seed
        self.interactions = interactions
        self.lags_s = lags_s

    def _features(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        # np.interp holds the first sample before it: a rise of 0 before the run's first sample
        dT = np.hstack([temperatures_at(ds, run, self.sensors_, t - lag, preprocess=None, delta=True)
                        for lag in (0.0, *self.lags_s)])  # fmt: skip
        if not self.uses_position_:
            return dT
        p = np.asarray(axis_mm, dtype=float)[:, None]
        parts = [dT, p] + ([p * dT] if self.interactions else [])
        return np.hstack(parts)

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        p = check_params(self, self.params_model)
        sensors = list(ds.metadata.sensors) if p.sensors is None else list(p.sensors)
        if not sensors:
            raise ModelError(f"the dataset has no temperature sensors; {type(self).__name__} needs some")
        self.sensors_ = sensors
        rd = readings(ds, runs)
        self.targets_mm_ = np.unique(rd["target_mm"].to_numpy())
        self.uses_position_ = self.targets_mm_.size > 1
        X, y = [], []
        for run in runs:
            r = rd[rd["run_id"] == run]
            X.append(self._features(ds, run, r["t_s"].to_numpy(), r["target_mm"].to_numpy()))
            y.append(r["error_um"].to_numpy())
        est = clone(p.estimator)
        if p.seed is not None and "random_state" in est.get_params():
            est.set_params(random_state=p.seed)
        est.fit(np.vstack(X), np.concatenate(y))
        self.estimator_ = est
        self.geometric_ = Polynomial([0.0])

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        return np.asarray(self.estimator_.predict(self._features(ds, run, t_s, axis_mm)), dtype=float)

    def _model_inputs(self) -> Inputs:
        return Inputs(sensors=tuple(self.sensors_))
