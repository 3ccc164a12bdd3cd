"""Linear with history: ridge regression on every sensor's rise now and some minutes earlier.

What held up best on real thermal tests that thermbench never saw was not a selected
few inputs but all of them, each with its recent history, under shrinkage: the ridge baseline
(:mod:`thermbench.models.baseline`) on the rises and the rises 30 min earlier. This family makes
that a deployable candidate::

    E(t, x) = b + Σ_j Σ_d w_jd · ΔT_j(t - d)   [+ x · (b' + Σ w'_jd · ΔT_j(t - d)) along an axis]

* ``ΔT_j``: the rise of **every** temperature sensor of the dataset (or of ``sensors``) above the
  run's first sample; with ``operating`` also one operating signal over its largest training value;
* ``d``: a delay (s) from a candidate set, 0 the rise now. The delayed rise is read from a
  **delay line** kept at a coarse step ``delay_step_s``, as the compensator keeps it (an hour at
  15 s would be 240 values per sensor; at 60 s it is 62): the rise at the grid times
  ``t0 + m h`` (linear between the samples around each, :func:`delay_line`), the delayed rise
  linear between them, the run's first value before ``t0``; so a delay costs
  ``ceil(d_max / h) + 2`` numbers per input, and the C runtime's ``LINEAR_HISTORY`` kind
  (``embedded/src/tb_kind_linear_history.c``) computes the same numbers;
* no input selection: the ridge penalty keeps the weights of inputs that do not help small, where
  a selection on few runs keeps whatever fitted them (with four training runs a stepwise
  choice is itself noise);
* the penalty ``alpha`` (from ``alphas``) and the set of delays (from ``delays_s``) are chosen
  together by cross-validation over **whole runs**, scored as scikit-learn's
  :class:`~sklearn.model_selection.GridSearchCV` scores a :class:`~sklearn.preprocessing.StandardScaler`
  + :class:`~sklearn.linear_model.Ridge` pipeline (every penalty from one decomposition per fold,
  :func:`~thermbench.models.thermal_lag.grid_choice`), its folds those of
  :func:`thermbench.bench.splits.row_folds` (scikit-learn's ``LeaveOneGroupOut`` up to 6 runs, else
  ``GroupKFold``; one run: 5 contiguous blocks), never rows of a run the fold trains on;
* ``estimator="pls"``: partial least squares (:class:`~sklearn.cross_decomposition.PLSRegression` on the
  standardised features) instead of the ridge, its number of components (from ``components``) chosen
  the same way; its answer is read back as weights on the same features
  (:func:`~thermbench.models.thermal_lag.linear_fit`), so it exports as the same kind;
* ``cv="gcv"`` (ridge): the penalty by :class:`~sklearn.linear_model.RidgeCV`'s efficient
  leave-one-reading-out error, as ``baseline_ridge`` chooses it (that baseline made deployable, one of
  the stacked ensemble's members); it holds no run out, so it is not the default.

The features are computed at the samples of the run's log and interpolated linearly to a reading's
time, as the runtime interpolates its prediction between samples. Fitted: ``inputs_`` (every
input), ``delays_s_``, ``alpha_``, ``cv_rmse_um_``, ``cv_results_`` (per delay set and penalty,
the held-out RMSE), ``mean_``/``scale_``/``coef_``/``intercept_`` (the ridge on standardised
features: per input its delays, input-major; along an axis ``[x, those, x * those]``), ``alpha_`` or
``n_components_`` (the other None).
"""

from __future__ import annotations

from typing import Annotated, Literal, Optional, Sequence

import numpy as np
from annotated_types import Ge, Gt, Len
from numpy.polynomial import Polynomial

from ..data.dataset import Dataset
from .base import ModelError, derived, readings
from .params import Expect, Int, Params, check_params
from .thermal_lag import ThermalLag, grid_choice, linear_fit

__all__ = ["LinearHistory", "RidgeHistory", "delay_line"]

#: candidate sets of delays (s): the rise alone; with 30 min; with 15 min, 30 min and 1 h
DEFAULT_DELAYS_S = ((0.0,), (0.0, 1800.0), (0.0, 900.0, 1800.0, 3600.0))


def delay_line(t_s: np.ndarray, u: np.ndarray, delays_s: Sequence[float], step_s: float) -> np.ndarray:
    """The input ``u`` logged at ``t_s`` (increasing) delayed by each of ``delays_s``, at the log's
    samples, one column per delay, as a delay line of step ``step_s`` gives it: the line holds
    ``v_m = u(t0 + m step)`` (linear between the two samples around that time) for every grid time
    up to the sample; the delayed value ``u(t - d)`` is linear between the grid values, and the
    first sample's value before ``t0``. A delay of 0 is the input itself; every other delay must be
    at least ``step_s`` (the grid value it needs is then in the line)."""
    t = np.asarray(t_s, dtype=float)
    u = np.asarray(u, dtype=float)
    out = np.empty((t.size, len(delays_s)))
    if t.size == 0:
        return out
    grid = t[0] + step_s * np.arange(int(np.floor((t[-1] - t[0]) / step_s)) + 1)
    v = np.interp(grid, t, u)
    for k, d in enumerate(delays_s):
        out[:, k] = u if d == 0 else np.interp(t - d, grid, v)
    return out


class LinearHistoryParams(Params):
    sensors: Annotated[Optional[Annotated[Sequence[str], Len(min_length=1)]],
                       Expect("None or a non-empty list of sensor names")]  # fmt: skip
    operating: Annotated[Optional[Sequence[str]], Expect("None or a list of process columns")]
    delays_s: Annotated[Sequence[Annotated[Sequence[Annotated[float, Ge(0)]], Len(min_length=1, max_length=8)]],
                        Len(min_length=1), Expect("a non-empty list of sets of 1 to 8 delays in seconds, each >= 0")]  # fmt: skip
    delay_step_s: Annotated[float, Gt(0), Expect("a step in seconds > 0, at most the shortest delay above 0")]
    alphas: Annotated[Sequence[Annotated[float, Gt(0)]], Len(min_length=1), Expect("a non-empty list of penalties > 0")]
    estimator: Annotated[Literal["ridge", "pls"], Expect("ridge or pls")]
    components: Annotated[Sequence[Annotated[Int, Ge(1)]], Len(min_length=1),
                          Expect("a non-empty list of numbers of PLS components, each >= 1")]  # fmt: skip
    cv: Annotated[Literal["runs", "gcv"], Expect("runs (GridSearchCV over whole runs) or gcv (ridge only)")]


class LinearHistory(ThermalLag):
    """Ridge on every sensor's rise now and at some delays (module docstring).

    Parameters
    ----------
    sensors : list of str or None
        The temperature sensors whose rises are inputs; None: every sensor of the dataset.
    operating : list of str or None
        Process columns that are inputs too (the C runtime carries one); ``[]`` (the default):
        none; None: the dataset's operating inputs.
    delays_s : list of lists of float
        Candidate sets of delays (s); 0 is the rise now. One set is chosen.
    delay_step_s : float
        The delay line's step (s); every delay above 0 is at least this.
    alphas : list of float
        Candidate ridge penalties (on standardised features).
    estimator : "ridge" or "pls"
        The linear fit: ridge regression, or partial least squares (:class:`~sklearn.cross_decomposition.PLSRegression`
        on the standardised features, a few latent directions instead of a penalty).
    components : list of int
        Candidate numbers of PLS components (those above the number of features are dropped).
    cv : "runs" or "gcv"
        How the set of delays and the penalty (or components) are chosen: ``runs``, cross-validation over whole
        runs; ``gcv`` (ridge only), RidgeCV's efficient leave-one-reading-out error, what ``baseline_ridge``
        uses, which does not hold runs out (the delay set of lowest such error).
    """

    params_model = LinearHistoryParams

    def __init__(self, sensors=None, operating=(), delays_s=DEFAULT_DELAYS_S, delay_step_s=60.0,
                 alphas=tuple(np.logspace(-3, 3, 13)), estimator="ridge", components=(1, 2, 3, 4, 6, 8),
                 cv="runs"):  # fmt: skip
        self.sensors = sensors
        self.operating = operating
        self.delays_s = delays_s
        self.delay_step_s = delay_step_s
        self.alphas = alphas
        self.estimator = estimator
        self.components = components
        self.cv = cv

    def _lags(self, ds: Dataset, run: str, name: str, delays: Sequence[float], t_s: np.ndarray) -> np.ndarray:
        """The delayed values of input ``name`` at times ``t_s`` of ``run``, one column per delay
        (computed at the log's samples once, then linear between them)."""

        def make():
            t, u = self._input_series(ds, run, name)
            return t, delay_line(t, u, self.all_delays_, self.step_s_)

        key = ("linear_history", run, name, self.scale_of_.get(name, 1.0), tuple(self.all_delays_), self.step_s_)
        t, lines = derived(ds, key, make, copy=False)
        return np.column_stack([np.interp(t_s, t, lines[:, self.all_delays_.index(float(d))]) for d in delays])

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        from ..bench.splits import row_folds

        p = check_params(self, self.params_model)
        shortest = min((float(d) for s in p.delays_s for d in s if d > 0), default=np.inf)
        if p.delay_step_s > shortest:
            raise ModelError(f"LinearHistory.delay_step_s: {p.delay_step_s:g} s is longer than the shortest delay "
                             f"{shortest:g} s; expected a step at most that")  # fmt: skip
        self.step_s_ = float(p.delay_step_s)
        sensors, operating = self._set_inputs(ds, runs, p)
        self.inputs_ = sensors + operating
        self.all_delays_ = sorted({float(d) for s in p.delays_s for d in s})
        rd = readings(ds, runs)
        self.uses_position_ = np.unique(rd["target_mm"].to_numpy()).size > 1
        y = rd["error_um"].to_numpy(dtype=float)
        run_of = rd["run_id"].to_numpy()

        def features(delays) -> np.ndarray:
            return np.vstack([self._features(ds, r, self.inputs_, delays, rd.loc[run_of == r, "t_s"].to_numpy(),
                                             rd.loc[run_of == r, "target_mm"].to_numpy()) for r in runs])  # fmt: skip

        if p.estimator == "pls" and p.cv == "gcv":
            raise ModelError("LinearHistory.cv: gcv is ridge's leave-one-reading-out error; expected runs with "
                             "estimator pls")  # fmt: skip
        grid = p.components if p.estimator == "pls" else p.alphas
        (self.cv_rmse_um_, self.delays_s_, value), results = grid_choice(features, p.delays_s, y, row_folds(run_of),
                                                                         p.estimator, grid, p.cv)  # fmt: skip
        self.cv_results_ = [{"delays_s": r.pop("history"), **r} for r in results]
        self.alpha_ = float(value) if p.estimator == "ridge" else None
        self.n_components_ = int(value) if p.estimator == "pls" else None
        fitted = linear_fit(features(self.delays_s_), y, p.estimator, value)
        self.mean_, self.scale_, self.coef_, self.intercept_ = fitted
        self.geometric_ = Polynomial([0.0])

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        X = self._features(ds, run, self.inputs_, self.delays_s_, t_s, axis_mm)
        return ((X - self.mean_) / self.scale_) @ self.coef_ + self.intercept_

    def fit_summary(self) -> str:
        self._check_fitted()
        fit = (f"ridge alpha {self.alpha_:g}" if self.n_components_ is None
               else f"PLS with {self.n_components_} components")  # fmt: skip
        cv = "leave-one-reading-out (GCV) RMSE" if self.cv == "gcv" else "cross-validated RMSE over whole runs"
        return (f"every input ({len(self.inputs_)}) now and {[round(d) for d in self.delays_s_ if d > 0]} s earlier "
                f"(a delay line of {self.step_s_:g} s), {fit}; {cv} {self.cv_rmse_um_:.3f} µm")

    def export_encoding(self, channels, period_s, where):
        """The C runtime's ``LINEAR_HISTORY`` kind (:func:`thermbench.export.lag_encoding.encode_linear_history`)."""
        from ..export.lag_encoding import encode_linear_history

        return encode_linear_history(self, channels, period_s, where)


class RidgeHistory(LinearHistory):
    """``baseline_ridge`` made deployable: the benchmark's reference candidate.

    The same model as :class:`LinearHistory` (its parameters, fit, C kind ``LINEAR_HISTORY``);
    ``conf/model/ridge_history.yaml`` sets it up as the ridge baseline is set up: every sensor's rise
    now and 30 min earlier, the penalty by GCV (``cv="gcv"``), one set of delays. It differs in one
    piece of metadata: :attr:`complexity` 0, so the benchmark's choice
    (:func:`thermbench.bench.choice.nested_choice`) takes it, or the stacked ensemble, whenever it is
    within one standard error of the best inner score. A candidate that replaces it must be better
    than the reference by more than the scatter of the score that ranks them; with a few runs the
    choice then falls back to what a careful user would have fitted, not to the luckiest family.
    """

    #: the reference a more flexible candidate must beat by more than one standard error (the ensemble's 0;
    #: ThermalErrorModel.complexity): fixed features, one penalty, nothing chosen across runs
    complexity = 0
