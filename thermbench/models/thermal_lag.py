"""Thermal-lag regression: the thermal error as a sum of first-order responses to measured inputs.

Thermal error is a lagged response to heat (the adaptive ARX models with automatic
input selection of the ETH Zurich machine-tool group write it as a sum of first-order responses
to measured temperatures and operating signals). Here::

    E(t) = b + Σ_g Σ_τ w_gτ · lag_τ(u_g)(t)

* ``u_g``: an input, the rise ΔT of a temperature sensor above the run's first sample, or an
  operating signal of the process log (spindle speed, feed) divided by its largest training
  value; ``lag_0`` is the input itself;
* ``lag_τ``: the exact first-order filter of time constant τ run forward in time from 0 at the
  run's start (the input held over each sample interval, :func:`first_order_lag`), as the
  compensator runs it sample by sample;
* the inputs are chosen **as groups** (an input enters or leaves with all its lags) by stepwise
  selection: forward, each step the group that lowers the cross-validated RMSE most, stopping when
  no group lowers it by ``min_gain``, an earlier group leaving when it no longer earns that; of the
  models visited, the smallest within one standard error (over the folds) of the lowest RMSE is
  kept (:func:`_forward_groups`); the weights by ridge regression on standardised lags, the
  penalty ``alpha`` from ``alphas`` and the set of time constants from ``taus_s`` chosen by the
  same cross-validation over **whole runs** (:func:`thermbench.bench.splits.row_folds`: each run held
  out once up to 6 runs, else 3 folds of runs; one run: 5 contiguous blocks), never on rows of
  a run the fold trains on.

With ``select=False`` there is no selection: every candidate input enters with every lag of the
chosen set, the ridge penalty keeping the weights of inputs that do not help small ("a ridge on
first-order lags" of every sensor, one of the linear-with-history models that held up on real
tests); the penalty and the time constants are chosen together over the same folds of whole
runs, scored as scikit-learn's GridSearchCV scores them (:func:`grid_choice`). This is the
``thermal_lag`` family of ``conf/model``: a machine's sensors move together, and on correlated
inputs shrinkage predicts more stably than a subset chosen from a few runs (Breiman 1996,
*Heuristics of instability and stabilization in model selection*, Ann. Statist. 24(6)); the
stepwise selection is ``thermal_lag_stepwise``.

With ``start=True`` (and ``select=False``) the state each run starts from enters too
(:func:`start_state`), in one of two forms chosen by the same folds and score as the penalty:
each sensor's first reading above the reference (the ambient sensor; with none, the sensors' mean),
or, with an ambient sensor, the machine's one level (:data:`START_MEAN`: the mean first reading of
the other sensors above the ambient's, the heat the machine stores). A level per sensor and time
constant is many weights learnt from one start vector per training run, and a machine's sensors
start warm together: the one level asks the runs for one profile per time constant. Each form
enters only where the training runs start apart (``START_MIN_RUNS``, ``START_MIN_SPREAD_K``).

Along an axis with several measuring targets, the position P and P x each lag join the features
(the slope of a thermal error that grows along the axis). Fitted: ``inputs_`` (the chosen
inputs, in the order they entered), ``taus_s_``, ``alpha_``, ``selection_`` (each step: the
input added, ``-input`` removed or ``(every input)``, and the cross-validated RMSE after it; the
model kept is one of them), ``cv_rmse_um_``, ``coef_``/``intercept_``
(on the standardised features ``mean_``/``scale_``).
"""

from __future__ import annotations

from typing import Annotated, Literal, Optional, Sequence

import numpy as np
from annotated_types import Ge, Gt, Len
from numpy.polynomial import Polynomial
from scipy.signal import lfilter
from sklearn.cross_decomposition import PLSRegression
from sklearn.linear_model import RidgeCV
from sklearn.model_selection import GridSearchCV
from sklearn.pipeline import make_pipeline
from sklearn.preprocessing import StandardScaler

from ..data.dataset import Dataset
from .base import Inputs, ModelError, ThermalErrorModel, _name, derived, readings, sensor_series
from .params import Bool, Expect, Int, Params, check_params

__all__ = ["START", "START_MEAN", "ThermalLag", "first_order_lag", "grid_choice", "linear_fit", "start_state"]

#: the prefix of a start-state input's name (``start:<sensor>``, :func:`start_state`)
START = "start:"
#: the start state of the machine as one level: the mean first reading of the sensors other than the
#: ambient above the ambient's (the heat the machine stores, one number a run)
START_MEAN = START + "(mean)"
#: a start state enters when at least this many training runs start with levels that span START_MIN_SPREAD_K
#: (three points show a slope and its scatter; 1 K is ten steps of a 0.1 K reading, well above a sensor's
#: offset drift between runs)
START_MIN_RUNS = 3
START_MIN_SPREAD_K = 1.0

#: the default candidate sets of time constants (s): the rise alone, then 30 min, then 15 min /
#: 1 h, then 15 min / 1 h / 4 h beside it (a spindle test's drift moves over minutes to hours)
DEFAULT_TAUS_S = ((0.0,), (0.0, 1800.0), (0.0, 900.0, 3600.0), (0.0, 900.0, 3600.0, 14400.0))


def first_order_lag(t_s: np.ndarray, u: np.ndarray, tau_s: float) -> np.ndarray:
    """``y' = (u - y) / τ`` from ``y = 0`` before the first sample, exact for an input held at
    each sample's value over the interval that ends there: ``y_k = a_k y_{k-1} + (1 - a_k) u_k``,
    ``a_k = exp(-(t_k - t_{k-1}) / τ)`` (the first sample: ``y_0 = 0``: the machine had not
    started). ``tau_s = 0``: the input itself."""
    u = np.asarray(u, dtype=float)
    if tau_s == 0:
        return u.copy()
    t = np.asarray(t_s, dtype=float)
    if t.size == 0:
        return np.zeros(0)
    dt = np.diff(t)
    y = np.zeros(u.size)
    if dt.size and np.allclose(dt, dt[0], rtol=1e-9, atol=0.0):  # a regular log: one linear filter
        a = float(np.exp(-dt[0] / tau_s))
        y[1:] = lfilter([1.0 - a], [1.0, -a], u[1:])
        return y
    a = np.exp(-dt / tau_s)
    for k in range(1, u.size):
        y[k] = a[k - 1] * y[k - 1] + (1.0 - a[k - 1]) * u[k]
    return y


def start_state(t_s: np.ndarray, level_K: float, tau_s: float) -> np.ndarray:
    """The start state of one sensor through the lag of time constant ``tau_s``: its level above
    the reference at the run's first sample, ``level_K`` (the ambient sensor's first reading, or
    with no ambient sensor the mean first reading of the candidate sensors), held as the input of
    :func:`first_order_lag` from 0: ``level_K (1 - exp(-(t - t_0) / tau))`` on a regular log.

    A run that starts warm (a new shift, a restart after a stop) carries heat that flows out over
    the machine's time constants while the run's own heat flows in; its readings count from the
    first one, so what the stored heat does to them is 0 at the start and grows as it relaxes,
    which is this form for a first-order element (seed 000 §3.1: the screw's temperature field as
    first-order responses). The input itself (tau 0, a constant offset at the start) is left out:
    the readings count from the run's first."""
    t = np.asarray(t_s, dtype=float)
    return first_order_lag(t, np.full(t.size, float(level_K)), tau_s)


def _kept(inputs: Sequence[str], taus: Sequence[float]) -> np.ndarray:
    """The feature columns (input-major, one per time constant) that enter: all but a start-state
    input's tau-0 column (:func:`start_state`)."""
    return np.array([not (name.startswith(START) and float(t) == 0.0) for name in inputs for t in taus], dtype=bool)


class ThermalLagParams(Params):
    sensors: Annotated[Optional[Annotated[Sequence[str], Len(min_length=1)]],
                       Expect("None or a non-empty list of sensor names")]  # fmt: skip
    operating: Annotated[Optional[Sequence[str]], Expect("None or a list of process columns")]
    taus_s: Annotated[Sequence[Annotated[Sequence[Annotated[float, Ge(0)]], Len(min_length=1)]], Len(min_length=1),
                      Expect("a non-empty list of sets of time constants in seconds, each >= 0")]  # fmt: skip
    alphas: Annotated[Sequence[Annotated[float, Gt(0)]], Len(min_length=1), Expect("a non-empty list of penalties > 0")]
    max_inputs: Annotated[Int, Ge(1)]
    min_gain: Annotated[float, Ge(0), Expect("a fraction >= 0 (0.02: a 2 % lower cross-validated RMSE)")]
    select: Bool
    start: Bool
    score: Annotated[Literal["mean", "worst"], Expect("'mean' or 'worst'")]


class ThermalLag(ThermalErrorModel):
    """Thermal-lag regression (module docstring).

    Parameters
    ----------
    sensors : list of str or None
        The temperature sensors whose rises are candidate inputs; None: every sensor.
    operating : list of str or None
        Process columns that are candidate inputs too; None: the dataset's operating inputs
        (``metadata.operating``); ``[]``: none.
    taus_s : list of lists of float
        Candidate sets of time constants (s); 0 is the input itself. One set is chosen.
    alphas : list of float
        Candidate ridge penalties (on standardised lags).
    max_inputs : int
        At most this many inputs enter.
    min_gain : float
        An input enters only when it lowers the cross-validated RMSE by this fraction.
    select : bool
        False: no selection, every candidate input enters (``max_inputs`` and ``min_gain`` unused).
    start : bool
        True: the state each run starts from enters too (:func:`start_state`), through the time
        constants above 0 (with ``select=False`` only).
    score : {'mean', 'worst'}
        How the penalty and the time constants are chosen over the folds of whole runs (with
        ``select=False``): the lowest mean held-out mean square, or the lowest worst held-out run's
        (one training run: the mean over its blocks, which are not runs).
    """

    complexity = 1  # ThermalErrorModel.complexity

    params_model = ThermalLagParams

    def __init__(self, sensors=None, operating=None, taus_s=DEFAULT_TAUS_S, alphas=tuple(np.logspace(-3, 3, 13)),
                 max_inputs=6, min_gain=0.02, select=True, start=False, score="mean"):  # fmt: skip
        self.sensors = sensors
        self.operating = operating
        self.taus_s = taus_s
        self.alphas = alphas
        self.max_inputs = max_inputs
        self.min_gain = min_gain
        self.select = select
        self.start = start
        self.score = score

    # ------------------------------------------------------------ features ---
    def _input_series(self, ds: Dataset, run: str, name: str) -> tuple[np.ndarray, np.ndarray]:
        """(t, u) of input ``name`` over the run's log: a sensor's rise, a sensor's start state
        (``START`` + name, :func:`start_state`), or an operating column scaled."""
        if self.is_start_input(name):
            levels, refs = self.start_sensors(name), list(self._start_references())
            s = sensor_series(ds, run, list(dict.fromkeys([*levels, *refs])), None)
            first = {c: float(s[ds.metadata.sensor_column(c)].iloc[0]) if len(s) else 0.0 for c in [*levels, *refs]}
            t = s["t_s"].to_numpy(dtype=float)
            level = float(np.mean([first[c] for c in levels])) - float(np.mean([first[c] for c in refs]))
            return t, np.full(t.size, level)
        if name in self.sensor_names_:
            s = sensor_series(ds, run, [name], None)
            col = s[ds.metadata.sensor_column(name)].to_numpy(dtype=float)
            return s["t_s"].to_numpy(dtype=float), col - (col[0] if col.size else 0.0)
        pr = ds.process_run(run)
        if name not in pr.columns:
            raise ModelError(f"operating: column {name!r} is not in the process log of run {run!r}; "
                             f"columns: {list(pr.columns)}")  # fmt: skip
        u = np.asarray(pr[name], dtype=float)
        if not np.isfinite(u).all():
            raise ModelError(f"operating: column {name!r} of run {run!r} has non-numeric or missing values")
        return pr["t_s"].to_numpy(dtype=float), u / self.scale_of_[name]

    def _lags(self, ds: Dataset, run: str, name: str, taus: Sequence[float], t_s: np.ndarray) -> np.ndarray:
        """The lags of input ``name`` at times ``t_s`` of ``run``, one column per τ (computed once)."""

        def make():
            t, u = self._input_series(ds, run, name)
            return t, {tau: first_order_lag(t, u, tau) for tau in self.all_taus_}

        key = ("thermal_lag", run, name, self.scale_of_.get(name, 1.0), tuple(self.all_taus_),
               (self._start_references(), tuple(self.start_sensors(name))) if self.is_start_input(name) else None)
        t, by_tau = derived(ds, key, make, copy=False)
        return np.column_stack([np.interp(t_s, t, by_tau[tau]) for tau in taus])

    def _features(self, ds: Dataset, run: str, inputs: Sequence[str], taus, t_s, axis_mm) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        cols = [self._lags(ds, run, name, taus, t) for name in inputs]
        z = np.hstack(cols) if cols else np.zeros((t.size, 0))
        z = z[:, _kept(inputs, taus)]
        if not self.uses_position_:
            return z
        p = np.asarray(axis_mm, dtype=float)[:, None]
        return np.hstack([p, z, p * z])

    def _start_references(self) -> tuple[str, ...]:
        """The sensors whose mean first reading a start state counts from: the ambient sensor, or
        every candidate sensor when there is none."""
        return (self.start_reference_,) if self.start_reference_ is not None else tuple(self.sensor_names_)

    def _start_varies(self, ds: Dataset, runs: list[str], name: str) -> bool:
        """Whether the training runs start differently enough for the start state ``name`` to say
        anything: at least ``START_MIN_RUNS`` runs whose levels span ``START_MIN_SPREAD_K`` (runs that
        all start alike, or the segments of one test that keep its log from its start, carry a start
        state that is only a function of time, which a model would extrapolate as a trend)."""
        if len(runs) < START_MIN_RUNS:
            return False
        levels = [self._input_series(ds, r, name)[1][:1] for r in runs]
        levels = np.concatenate(levels) if levels else np.zeros(0)
        return levels.size >= START_MIN_RUNS and float(np.ptp(levels)) >= START_MIN_SPREAD_K

    # ----------------------------------------------------------------- fit ---
    def _set_inputs(self, ds: Dataset, runs: list[str], p) -> tuple[list[str], list[str]]:
        """The sensors and operating columns of parameters ``p`` (checked against the dataset), each
        operating signal's scale (its largest training value, ``scale_of_``) and ``sensor_names_``."""
        sensors = list(ds.metadata.sensors) if p.sensors is None else list(p.sensors)
        unknown = [s for s in sensors if s not in ds.metadata.sensors]
        if unknown:
            raise ModelError(f"sensors: {unknown} are not sensors of the dataset {_name(ds)}; it has "
                             f"{list(ds.metadata.sensors)}")  # fmt: skip
        operating = list(ds.metadata.operating_inputs() if p.operating is None else p.operating)
        operating = [c for c in operating if c not in sensors]
        if not sensors and not operating:
            raise ModelError(f"the dataset {_name(ds)} has no temperature sensor and no operating input: "
                             "nothing to regress on")  # fmt: skip
        self.sensor_names_ = sensors
        self.start_reference_ = None
        if getattr(p, "start", False):
            amb = [s for s in sensors if ds.metadata.sensors[s] == "ambient"]
            self.start_reference_ = amb[0] if amb else None
        self.scale_of_ = {}
        for c in operating:  # each operating signal over its largest training value
            top = 0.0
            for run in runs:
                pr = ds.process_run(run)
                if c not in pr.columns:
                    raise ModelError(f"operating: column {c!r} is not in the process log of run {run!r}; "
                                     f"columns: {list(pr.columns)}")  # fmt: skip
                top = max(top, float(np.nanmax(np.abs(np.asarray(pr[c], dtype=float)), initial=0.0)))
            self.scale_of_[c] = top if top > 0 else 1.0
        return sensors, operating

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        from ..bench.splits import row_folds

        p = check_params(self, self.params_model)
        sensors, operating = self._set_inputs(ds, runs, p)
        if p.start and p.select:
            raise ModelError("start: the start state enters with select: false (every input), not with stepwise selection")
        others = [s for s in sensors if s != self.start_reference_]
        starts = [START + s for s in others] if p.start else []
        if starts and not any(t > 0 for s in p.taus_s for t in s):
            raise ModelError("start: the start state enters through time constants above 0; taus_s has none")
        # the two forms of the start state (module docstring): each sensor's level, and with an ambient
        # sensor and two others or more the machine's mean level too; each only where the runs start apart
        forms = {"each": [name for name in starts if self._start_varies(ds, runs, name)]}
        if starts and self.start_reference_ is not None and len(others) > 1 and self._start_varies(ds, runs, START_MEAN):
            forms["mean"] = [START_MEAN]
        forms = {k: v for k, v in forms.items() if v} or {"none": []}
        candidates = sensors + operating + list(dict.fromkeys(n for v in forms.values() for n in v))
        self.all_taus_ = sorted({float(t) for s in p.taus_s for t in s})
        rd = readings(ds, runs)
        self.uses_position_ = np.unique(rd["target_mm"].to_numpy()).size > 1
        y = rd["error_um"].to_numpy(dtype=float)
        run_of = rd["run_id"].to_numpy()
        # every candidate's lags at every reading, once: column (input, tau)
        full = {name: np.vstack([self._lags(ds, r, name, self.all_taus_, rd.loc[run_of == r, "t_s"].to_numpy())
                                 for r in runs]) for name in candidates}  # fmt: skip
        pos = rd["target_mm"].to_numpy(dtype=float)[:, None]
        folds = row_folds(run_of)
        if not p.select:  # every candidate, the penalty, the time constants and the start form over whole runs

            def features(inputs, taus) -> np.ndarray:  # as _features lays them out, from the lags computed above
                idx = [self.all_taus_.index(float(t)) for t in taus]
                z = np.hstack([full[name][:, idx] for name in inputs])[:, _kept(inputs, taus)]
                return np.hstack([pos, z, pos * z]) if self.uses_position_ else z

            sets = [t for t in p.taus_s if not starts or any(v > 0 for v in t)]  # the start state needs a lag
            best, self.cv_results_ = None, []
            for form, names in forms.items():  # grid_choice per form (the same folds and score), the lowest
                inputs = sensors + operating + names
                choice, results = grid_choice(lambda taus: features(inputs, taus), sets, y, folds, "ridge", p.alphas,
                                              score=p.score if len(runs) > 1 else "mean",
                                              groups=run_of)  # one run: its blocks are no runs, the mean of them  # fmt: skip
                self.cv_results_ += [r | {"start": form} for r in results]
                if best is None or choice[0] < best[0][0]:
                    best = (choice, form, inputs)
            (self.cv_rmse_um_, self.taus_s_, self.alpha_), self.start_form_, self.inputs_ = best
            self.selection_ = [("(every input)", self.cv_rmse_um_)]
            self.mean_, self.scale_, self.coef_, self.intercept_ = linear_fit(features(self.inputs_, self.taus_s_), y,
                                                                              "ridge", self.alpha_)  # fmt: skip
            self.geometric_ = Polynomial([0.0])
            return
        self.start_form_ = "none"
        best = None
        for taus in p.taus_s:
            idx = [self.all_taus_.index(float(t)) for t in taus]
            blocks = {name: full[name][:, idx] for name in candidates}
            if self.uses_position_:
                blocks = {name: np.hstack([b, pos * b]) for name, b in blocks.items()}
            fixed = pos if self.uses_position_ else np.zeros((y.size, 0))
            chosen, score, steps, lowest = _forward_groups(blocks, fixed, y, folds, p.alphas, p.max_inputs, p.min_gain)
            if best is None or lowest < best[0]:  # the time constants whose selection reached the lowest RMSE
                best = (lowest, tuple(float(t) for t in taus), score, chosen, steps)
        _, self.taus_s_, (self.cv_rmse_um_, self.alpha_), self.inputs_, self.selection_ = best
        X = np.vstack([self._features(ds, r, self.inputs_, self.taus_s_, rd.loc[run_of == r, "t_s"].to_numpy(),
                                      rd.loc[run_of == r, "target_mm"].to_numpy()) for r in runs])  # fmt: skip
        self.mean_, self.scale_, self.coef_, self.intercept_ = _ridge(X, y, self.alpha_)
        self.geometric_ = Polynomial([0.0])

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        X = self._features(ds, run, self.inputs_, self.taus_s_, t_s, axis_mm)
        return ((X - self.mean_) / self.scale_) @ self.coef_ + self.intercept_

    def fit_summary(self) -> str:
        self._check_fitted()
        return (f"chose inputs {self.inputs_} at time constants {[round(t) for t in self.taus_s_]} s, ridge alpha "
                f"{self.alpha_:g}; cross-validated RMSE over whole runs {self.cv_rmse_um_:.3f} µm")

    def export_encoding(self, channels, period_s, where):
        """The C runtime's ``THERMAL_LAG`` kind (:func:`thermbench.export.lag_encoding.encode_thermal_lag`)."""
        from ..export.lag_encoding import encode_thermal_lag

        return encode_thermal_lag(self, channels, period_s, where)

    @staticmethod
    def is_start_input(name: str) -> bool:
        """Whether input ``name`` is a sensor's start state (:func:`start_state`)."""
        return name.startswith(START)

    def start_sensors(self, name: str) -> list[str]:
        """The sensors whose mean first reading the start-state input ``name`` is: one sensor, or for
        :data:`START_MEAN` every candidate sensor but the reference."""
        if name == START_MEAN:
            return [s for s in self.sensor_names_ if s not in self._start_references()]
        return [name[len(START):]]

    def kept_columns(self) -> np.ndarray:
        """Which of the fitted model's feature columns (inputs x time constants, input-major) enter."""
        self._check_fitted()
        return _kept(self.inputs_, self.taus_s_)

    def _model_inputs(self) -> Inputs:
        sensors = [i for i in self.inputs_ if i in self.sensor_names_]
        starts = [s for i in self.inputs_ if self.is_start_input(i) for s in self.start_sensors(i)]
        if starts:  # the start state reads its reference too
            sensors += [*starts, *self._start_references()]
        return Inputs(sensors=tuple(dict.fromkeys(sensors)),
                      operating=tuple(i for i in self.inputs_ if i not in self.sensor_names_ and not self.is_start_input(i)))  # fmt: skip


def grid_choice(features, sets, y: np.ndarray, folds, estimator: str, grid: Sequence, cv: str = "runs",
                score: str = "mean", groups=None):
    """The set of history terms (delays or time constants, one of ``sets``) and the hyper-parameter
    (a ridge penalty, or a number of PLS components) of lowest cross-validated RMSE, searched
    together: ((rmse, set, value), every candidate's rmse as dicts). ``features(set)`` gives the
    feature matrix; ``cv="runs"``: the mean held-out mean square over ``folds`` (whole runs), as
    scikit-learn's GridSearchCV scores it (the ridge's penalties from one decomposition per fold);
    ``cv="gcv"`` (ridge only): :class:`~sklearn.linear_model.RidgeCV`'s efficient leave-one-reading-out
    error (generalised cross-validation, as ``baseline_ridge``), which does not hold whole runs out.
    ``score="worst"`` (ridge over runs only): the lowest worst held-out mean square of one run
    (``groups``: each row's run; without it, of one fold) instead of the lowest mean over the folds,
    so that a penalty that buys a lower mean with one run far worse is not chosen (the part from the
    worst day is scrapped; a minimax choice over the held-out runs)."""
    name = "n_components" if estimator == "pls" else "alpha"
    results, best = [], None
    for hist in sets:
        hist = tuple(float(v) for v in hist)
        X = features(hist)
        if estimator == "pls":
            values = sorted({int(k) for k in grid if int(k) <= X.shape[1]}) or [1]
        else:
            values = [float(a) for a in grid]
        if cv == "gcv":
            ridge = make_pipeline(StandardScaler(), RidgeCV(alphas=values)).fit(X, y)[-1]
            rmse = np.full(len(values), np.inf)
            rmse[values.index(float(ridge.alpha_))] = np.sqrt(max(-float(ridge.best_score_), 0.0))
        elif estimator == "ridge":  # what GridSearchCV over StandardScaler + Ridge gives, every penalty from one
            # decomposition per fold (_FoldGram; tests/test_thermal_lag.py checks it against scikit-learn)
            cols = np.arange(X.shape[1])
            if score == "worst":  # each held-out run's mean square, the worst of them
                labels = np.asarray(groups) if groups is not None else None
                mse = [m for tr, te in folds for m in _FoldGram(X, y, tr, te).mse_by(
                    cols, values, labels[te] if labels is not None else np.zeros(len(te)))]  # fmt: skip
                rmse = np.sqrt(np.max(mse, axis=0))
            else:
                mse = [_FoldGram(X, y, tr, te).sse(cols, values) / len(te) for tr, te in folds]
                rmse = np.sqrt(np.mean(mse, axis=0))
        else:
            search = GridSearchCV(make_pipeline(StandardScaler(), PLSRegression(scale=False)),
                                  {"plsregression__n_components": values}, cv=folds,
                                  scoring="neg_mean_squared_error", n_jobs=1, refit=False)  # fmt: skip
            search.fit(X, y)
            rmse = np.sqrt(-np.asarray(search.cv_results_["mean_test_score"], dtype=float))
        results += [{"history": hist, name: v, "cv_rmse_um": float(r)} for v, r in zip(values, rmse) if np.isfinite(r)]
        k = int(np.argmin(rmse))
        if best is None or rmse[k] < best[0]:
            best = (float(rmse[k]), hist, values[k])
    return best, results


def linear_fit(X: np.ndarray, y: np.ndarray, estimator: str, value):
    """A linear map on standardised columns, (mean, scale, coef, intercept), from a ridge of penalty
    ``value`` or a PLS regression of ``value`` components; PLS's own coefficients are read back as
    its answers at the origin and at each unit vector, so both are exported alike."""
    if estimator != "pls":
        return _ridge(X, y, float(value))
    mean, scale = _standardise(X)
    pls = PLSRegression(n_components=int(value), scale=False).fit((X - mean) / scale, y)
    intercept = float(np.ravel(pls.predict(np.zeros((1, X.shape[1]))))[0])
    coef = np.ravel(pls.predict(np.eye(X.shape[1]))) - intercept
    return mean, scale, coef, intercept


def _standardise(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each column's mean and standard deviation (a constant column keeps scale 1, as StandardScaler)."""
    mean = X.mean(axis=0) if X.size else np.zeros(X.shape[1])
    scale = X.std(axis=0) if X.size else np.ones(X.shape[1])
    return mean, np.where(scale > 0, scale, 1.0)


def _ridge(X: np.ndarray, y: np.ndarray, alpha: float):
    """Ridge on standardised columns (a constant column keeps scale 1): (mean, scale, coef, intercept)."""
    mean, scale = _standardise(X)
    Z = (X - mean) / scale
    ym = float(y.mean())
    coef = np.linalg.solve(Z.T @ Z + alpha * np.eye(Z.shape[1]), Z.T @ (y - ym)) if Z.shape[1] else np.zeros(0)
    return mean, scale, coef, ym


class _FoldGram:
    """One fold's training sums over every candidate column (the Gram matrix, the column sums and
    squares, and their products with y) and its held-out rows: a ridge on any subset of columns,
    standardised on the fold's training rows, costs a solve of the subset's size."""

    def __init__(self, X: np.ndarray, y: np.ndarray, train: np.ndarray, test: np.ndarray) -> None:
        Xt, yt = X[train], y[train]
        self.n = yt.size
        self.s = Xt.sum(axis=0)
        self.G = Xt.T @ Xt
        self.c = Xt.T @ yt
        self.ys = float(yt.sum())
        self.Xte, self.yte = X[test], y[test]

    def mse_by(self, cols: np.ndarray, alphas: Sequence[float], labels: np.ndarray) -> np.ndarray:
        """Held-out mean squared error of the ridge on ``cols`` per label of the held-out rows
        (``labels``: one per held-out row, e.g. its run): labels x penalties."""
        sq = self.sse(cols, alphas, rows=True)
        keys, inv = np.unique(np.asarray(labels).astype(str), return_inverse=True)
        out = np.zeros((keys.size, sq.shape[1]))
        np.add.at(out, inv, sq)
        return out / np.bincount(inv)[:, None]

    def sse(self, cols: np.ndarray, alphas: Sequence[float], rows: bool = False) -> np.ndarray:
        """Held-out sum of squared errors of the ridge on ``cols``, one per penalty (``rows``: per
        held-out row, rows x penalties)."""
        ym = self.ys / self.n
        if cols.size == 0:
            sq = np.repeat(((self.yte - ym) ** 2)[:, None], len(alphas), axis=1)
            return sq if rows else sq.sum(axis=0)
        mu = self.s[cols] / self.n
        cov = self.G[np.ix_(cols, cols)] - self.n * np.outer(mu, mu)
        sd = np.sqrt(np.clip(np.diag(cov) / self.n, 0.0, None))
        sd = np.where(sd > 0, sd, 1.0)
        A = cov / np.outer(sd, sd)
        b = (self.c[cols] - mu * self.ys) / sd
        Zte = (self.Xte[:, cols] - mu) / sd
        lam, V = np.linalg.eigh(A)  # every penalty from one decomposition: w(a) = V (V'b / (lam + a))
        P, q = Zte @ V, V.T @ b
        W = q[:, None] / (np.clip(lam, 0.0, None)[:, None] + np.asarray(alphas)[None, :])
        sq = (P @ W + (ym - self.yte)[:, None]) ** 2
        return sq if rows else np.sum(sq, axis=0)


def _forward_groups(blocks: dict[str, np.ndarray], fixed: np.ndarray, y: np.ndarray, folds, alphas, max_inputs: int,
                    min_gain: float):  # fmt: skip
    """Stepwise selection of input groups (each ``blocks[name]``: its columns) by the pooled held-out
    RMSE of the ridge over ``folds`` (the best of ``alphas`` at each model): forward, the group that
    lowers it most while one lowers it by ``min_gain``, each entry followed by the removal of any
    earlier group that no longer earns ``min_gain``; ``fixed`` columns are always in. Of the models
    visited (and every input at once), the one kept is the smallest whose held-out mean square is
    within one standard error (over the folds) of the lowest: the one-standard-error rule
    (Hastie, Tibshirani, Friedman, *The Elements of Statistical Learning*, §7.10), so that a group
    whose gain is within the folds' scatter (a selection that fits the few held-out runs, not the
    machine) stays out. Returns (chosen names, (RMSE, alpha), steps [(name or -name, RMSE)], the
    lowest RMSE visited)."""
    names = list(blocks)
    X = np.hstack([fixed, *[blocks[n] for n in names]]) if names else fixed
    start, spans = fixed.shape[1], {}
    for n in names:
        spans[n] = np.arange(start, start + blocks[n].shape[1])
        start += blocks[n].shape[1]
    grams = [_FoldGram(X, y, tr, te) for tr, te in folds]
    n_rows = sum(g.yte.size for g in grams)
    alphas = [float(a) for a in alphas]

    def score(chosen: list[str]) -> tuple[tuple[float, float], np.ndarray]:
        """((pooled RMSE, alpha), each fold's held-out mean square at that alpha)."""
        cols = np.concatenate([np.arange(fixed.shape[1]), *[spans[n] for n in chosen]]).astype(int)
        per_fold = np.array([g.sse(cols, alphas) for g in grams])
        k = int(np.argmin(per_fold.sum(axis=0)))
        return (float(np.sqrt(per_fold[:, k].sum() / n_rows)), alphas[k]), per_fold[:, k] / [g.yte.size for g in grams]

    chosen: list[str] = []
    best, fold_mse = score(chosen)
    visited = [(list(chosen), best, fold_mse)]
    seen = {frozenset()}  # a set of groups is visited once: no step undoes the one before it for ever
    steps = [("(none)", best[0])]

    def lowest_of(moves):  # (score, name) of the move to the lowest RMSE; ties: by name
        moves = list(moves)
        return min(moves, key=lambda m: (m[0][0][0], m[1])) if moves else None

    while len(chosen) < min(max_inputs, len(names)):
        trial = lowest_of((score(chosen + [n]), n) for n in names
                          if n not in chosen and frozenset(chosen + [n]) not in seen)  # fmt: skip
        if trial is None or trial[0][0][0] > (1.0 - min_gain) * best[0]:
            break
        chosen.append(trial[1])
        seen.add(frozenset(chosen))
        (best, fold_mse) = trial[0]
        steps.append((trial[1], best[0]))
        visited.append((list(chosen), best, fold_mse))
        while len(chosen) > 2:  # backward: a group that no longer earns its entry (a greedy first pick that
            # later ones explain better) leaves, as it would not have entered now; then forward again
            drop = lowest_of((score([c for c in chosen if c != n]), n) for n in chosen[:-1]
                             if frozenset(c for c in chosen if c != n) not in seen)  # fmt: skip
            if drop is None or drop[0][0][0] * (1.0 - min_gain) > best[0]:
                break
            seen.add(frozenset(c for c in chosen if c != drop[1]))
            chosen.remove(drop[1])
            (best, fold_mse) = drop[0]
            steps.append((f"-{drop[1]}", best[0]))
            visited.append((list(chosen), best, fold_mse))
    if len(names) > len(chosen):  # every input at once, the ridge alone keeping the weights small
        every, every_mse = score(names)
        steps.append(("(every input)", every[0]))
        visited.append((names, every, every_mse))
    lowest = min(visited, key=lambda v: v[1][0])
    k = len(lowest[2])
    se = float(np.std(lowest[2], ddof=1) / np.sqrt(k)) if k > 1 else 0.0
    within = [v for v in visited if v[1][0] ** 2 <= lowest[1][0] ** 2 + se]
    keep = min(within, key=lambda v: (len(v[0]), v[1][0]))
    return keep[0], keep[1], steps, lowest[1][0]
