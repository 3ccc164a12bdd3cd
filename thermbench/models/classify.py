"""Classifying the motion condition of a feed axis (seed 002 §2.4, eq. 15-19, Tables 5-6).

Seed 002 models the thermal error separately under each of a few known motion
conditions and, at run time, picks the model whose condition is closest to the
current motion (working stroke A, machining position B = P_start + P_end, feed C).
This module holds :class:`ProximityNaiveBayes` - the paper's proximity naive-Bayes
classifier (eq. 15-19), usable from a config alone (Table 5: ``conf/classifier/seed002.yaml``)
or fitted on motion features of labelled runs of any grid; with ``factors`` it applies
eq. 15-19 to operating columns (a spindle test's ``spindle_rpm``; one factor: the nearest
known speed) - and the factors and proximities of eq. 15-16 it computes. The motion
features of a run's log it classifies online are in :mod:`thermbench.models.motion_windows`;
one motion classified as a text table (``thermbench classify``) in
:mod:`thermbench.models.classify_one`.

Reading of the (garbled) equations of seed 002 §2.4:

* eq. 15: the proximity of a motion parameter to each known level is the inverse
  distance, ``P_A(x) = 1/|A - x|`` for x in {50, 100, 300} mm,
  ``P_B(y) = 1/|P_start + P_end - y|`` for y in {0, 650, 1300} mm (left end, middle,
  right end of the 0-650 mm travel, doubled because B is a sum of two positions),
  ``P_C(z) = 1/|C - z|`` for z in {800, 2000, 4000} mm/min. The paper prints 40000
  as the last feed level; Table 5 says 4000 mm/min and with 40000 Table 6 row 7
  (310 mm, 330-640 mm, 3400 mm/min -> #9) would be classified #6, so 4000 is used.
* eq. 16: each factor's proximities are normalised over its levels,
  ``P(level n | φ) = P_n / Σ_m P_m``; an exact match (distance 0) gives that level
  probability 1 and the others 0 (the paper: "if A is 50, 100, and 300 ... the
  current stroke probability is 1").
* eq. 17-18: priors ``P(#K) = 1/K``; the conditional probability of a level given
  condition #K is 1 when #K has that level (Table 5), else 0.
* eq. 19: the paper sums ("converts the series into a matrix summation"):
  ``score_K = Σ_φ P(level_φ(#K) | φ) + P(#K)``, and the class is ``argmax_K score_K``.

With this reading, Table 6 rows 1, 3, 4, 6, 7 come out as printed; rows 2 and 5
come out #7 where the paper prints #2 and #3 (see ``tests/test_classify.py``: in both
rows the printed class shares its position and feed levels with #1 but has a
stroke level farther from the given stroke, so no monotone proximity can rank it
above #1).
"""

from __future__ import annotations

from numbers import Real
from typing import Mapping

import numpy as np
import pandas as pd
from sklearn.base import BaseEstimator, ClassifierMixin

import thermbench

from ..config import ConfigError
from ..errors import UserError

__all__ = [
    "FEATURES",
    "ClassifierError",
    "ProximityNaiveBayes",
    "learned_features",
    "linear_membership",
    "operating_factors",
]

FEATURES = ("stroke_mm", "start_mm", "end_mm", "feed_mm_min")
FACTORS = ("stroke", "position", "feed")  # A, B = P_start + P_end, C of seed 002 eq. 15
_FACTOR_KEYS = {"stroke": "stroke_mm", "position": "position_mm", "feed": "feed_mm_min"}
_PARAM = {"stroke": "stroke_levels_mm", "position": "position_levels_mm", "feed": "feed_levels_mm_min"}


class ClassifierError(UserError):
    """A motion to classify that cannot be right (``thermbench classify --stroke ...``, a
    motion feature out of range): reported in one line, naming the value."""


def _config_error(param: str, message: str) -> ConfigError:
    """A classifier parameter of ``conf/classifier/*.yaml`` that cannot be right: the
    message names the config key ``classifier.<param>``."""
    return ConfigError(f"config key 'classifier.{param}': {message}")


# ---------------------------------------------------------------- features ---
def motion_factors(X) -> np.ndarray:
    """The three factors of seed 002 eq. 15 per row of ``X``, shape (n, 3):
    stroke A (``stroke_mm``), position B = P_start + P_end (``start_mm + end_mm``,
    or ``2 * centre_mm``) and feed C (``feed_mm_min``).

    ``X`` is a DataFrame (or a mapping of columns); a missing column, NaN or a
    negative stroke/feed is a ValueError naming the column and row.
    """
    if isinstance(X, Mapping) and not isinstance(X, pd.DataFrame):
        X = pd.DataFrame({k: np.atleast_1d(v) for k, v in X.items()})
    if not isinstance(X, pd.DataFrame):
        raise ValueError(
            f"motion features must be a DataFrame with columns stroke_mm, feed_mm_min and start_mm + end_mm "
            f"(or centre_mm), got {type(X).__name__}"
        )
    missing = [c for c in ("stroke_mm", "feed_mm_min") if c not in X.columns]
    if {"start_mm", "end_mm"} <= set(X.columns):
        pos_cols = ["start_mm", "end_mm"]
    elif "centre_mm" in X.columns:
        pos_cols = ["centre_mm"]
    else:
        pos_cols = []
        missing.append("start_mm + end_mm (or centre_mm)")
    if missing:
        raise ValueError(f"motion features: missing column(s) {missing}; got columns {list(X.columns)}")
    cols = {
        c: pd.to_numeric(X[c], errors="coerce").to_numpy(dtype=float) for c in ["stroke_mm", "feed_mm_min", *pos_cols]
    }
    for c, v in cols.items():
        bad = np.flatnonzero(~np.isfinite(v))
        if bad.size:
            raise ClassifierError(f"motion features: column {c!r} has a missing/non-numeric value at row {bad[0]}")
    for c in ("stroke_mm", "feed_mm_min"):
        bad = np.flatnonzero(cols[c] < 0)
        if bad.size:
            raise ClassifierError(f"motion features: {c} must be >= 0, got {cols[c][bad[0]]} at row {bad[0]}")
    pos = cols["start_mm"] + cols["end_mm"] if pos_cols == ["start_mm", "end_mm"] else 2.0 * cols["centre_mm"]
    return np.column_stack([cols["stroke_mm"], pos, cols["feed_mm_min"]])


def learned_features(windows: pd.DataFrame) -> pd.DataFrame:
    """The features a learned classifier is trained on: ``stroke_mm``, ``centre_mm``
    = (start + end) / 2 and ``feed_mm_min`` (what the bank feeds any classifier;
    :class:`ProximityNaiveBayes` reads ``centre_mm`` as B = 2 * centre)."""
    f = motion_factors(windows)
    return pd.DataFrame({"stroke_mm": f[:, 0], "centre_mm": f[:, 1] / 2.0, "feed_mm_min": f[:, 2]})


# ----------------------------------------------------------- the classifier ---
def operating_factors(X, columns) -> np.ndarray:
    """The factors of seed 002 eq. 15 when the condition is an operating input: one
    column of ``X`` per name in ``columns`` (e.g. ``spindle_rpm``), shape (n, len(columns)).

    ``X`` is a DataFrame (or a mapping of columns); a missing column or a NaN is a
    ValueError naming the column (and row)."""
    if isinstance(X, Mapping) and not isinstance(X, pd.DataFrame):
        X = pd.DataFrame({k: np.atleast_1d(v) for k, v in X.items()})
    if not isinstance(X, pd.DataFrame):
        raise ValueError(f"operating features must be a DataFrame with columns {list(columns)}, got {type(X).__name__}")
    missing = [c for c in columns if c not in X.columns]
    if missing:
        raise ValueError(f"operating features: missing column(s) {missing}; got columns {list(X.columns)}")
    out = np.column_stack([pd.to_numeric(X[c], errors="coerce").to_numpy(dtype=float) for c in columns])
    for j, c in enumerate(columns):
        bad = np.flatnonzero(~np.isfinite(out[:, j]))
        if bad.size:
            raise ClassifierError(f"operating features: column {c!r} has a missing/non-numeric value at row {bad[0]}")
    return out


def _check_levels(name: str, value) -> np.ndarray | None:
    if value is None:
        return None
    try:
        arr = np.asarray(list(value), dtype=float)
    except (TypeError, ValueError):
        raise _config_error(name, f"{name} must be a list of numbers or None, got {value!r}") from None
    if arr.size == 0 or not np.all(np.isfinite(arr)):
        raise _config_error(name, f"{name} must be a non-empty list of finite numbers or None, got {value!r}")
    if np.unique(arr).size != arr.size:
        raise _config_error(name, f"{name} has repeated levels: {arr.tolist()}")
    return np.sort(arr)


def _merge_levels(values: np.ndarray, tolerance: float, pairwise: bool = False) -> np.ndarray:
    """Distinct values of a factor; values within ``tolerance`` * max|value| of the
    previous one (sorted) are one level (their mean). ``pairwise``: within ``tolerance``
    times the larger of the two neighbours instead (operating levels, which span a
    decade: 3500 and 3750 rpm are two levels, though 250 rpm is 5 % of 5000)."""
    v = np.sort(np.asarray(values, dtype=float))
    if pairwise:
        tol = tolerance * np.maximum(np.abs(v[1:]), np.abs(v[:-1]))
    else:
        tol = tolerance * max(float(np.max(np.abs(v))), 1e-12)
    groups = np.split(v, np.flatnonzero(np.diff(v) > tol) + 1)
    return np.array([g.mean() for g in groups])


def proximity(values: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """seed 002 eq. 15-16: the normalised inverse-distance proximity of each value to
    each level, shape (n, n_levels), rows summing to 1; a value equal to a level
    (within 1e-9 of the level scale) gives that level 1 and the others 0."""
    v = np.asarray(values, dtype=float)[:, None]
    lv = np.asarray(levels, dtype=float)[None, :]
    d = np.abs(v - lv)
    exact = d <= 1e-9 * max(1.0, float(np.max(np.abs(lv))))
    inv = np.where(exact, 0.0, 1.0 / np.where(exact, 1.0, d))
    hit = exact.any(axis=1)
    total = inv.sum(axis=1, keepdims=True)
    p = np.where(hit[:, None], exact.astype(float), inv / np.where(total > 0, total, 1.0))
    return p


def linear_membership(values: np.ndarray, levels: np.ndarray) -> np.ndarray:
    """The linear-interpolation weights of each value between the two (sorted) levels
    that bracket it, shape (n, n_levels), rows summing to 1: a value at level i gives
    it 1; between levels i and i + 1 the weights are (L_{i+1} - v) / (L_{i+1} - L_i) and
    (v - L_i) / (L_{i+1} - L_i); below the lowest (above the highest) level, that level 1.
    (Only the two neighbouring levels share a value, unlike eq. 16's inverse distance,
    which gives every level a share however far it is.)"""
    v = np.asarray(values, dtype=float)
    lv = np.asarray(levels, dtype=float)
    out = np.zeros((v.size, lv.size))
    if lv.size == 1:
        out[:] = 1.0
        return out
    vc = np.clip(v, lv[0], lv[-1])
    j = np.clip(np.searchsorted(lv, vc, side="right") - 1, 0, lv.size - 2)
    frac = (vc - lv[j]) / (lv[j + 1] - lv[j])
    rows = np.arange(v.size)
    out[rows, j] = 1.0 - frac
    out[rows, j + 1] += frac
    return out


#: the motion factors of seed 002 eq. 15: (factor, condition key, level parameter)
_MOTION_SPEC = tuple((f, _FACTOR_KEYS[f], _PARAM[f]) for f in FACTORS)
#: what ProximityNaiveBayes.predict_proba returns (parameter ``probability``)
PROBABILITIES = ("score", "proximity", "linear")


class ProximityNaiveBayes(ClassifierMixin, BaseEstimator):
    """The proximity naive-Bayes condition classifier of seed 002 §2.4 (eq. 15-19).

    Parameters
    ----------
    stroke_levels_mm, position_levels_mm, feed_levels_mm_min : list of float or None
        The known levels of the three motion factors (seed 002 eq. 15: stroke A,
        position B = P_start + P_end, feed C). None: the distinct values of that factor
        among the conditions (values closer than ``level_tolerance`` times the largest
        value of the factor are one level). Only with ``factors`` None.
    conditions : mapping label -> {stroke_mm, position_mm, feed_mm_min} or None
        The known conditions (seed 002 Table 5); ``position_mm`` is the P_start +
        P_end reference (``start_mm`` and ``end_mm`` may be given instead). With
        ``factors``: label -> {column: level}. When given, ``fit`` needs no data (and
        ignores any). When None, ``fit(X, y)`` takes each label's condition as the
        median of its rows of ``X``.
    level_tolerance : float
        Relative tolerance merging close condition values into one level (only for
        factors whose levels are None). Motion factors: within ``level_tolerance``
        times the factor's largest value; operating factors: within
        ``level_tolerance`` times the larger of two neighbouring values.
    factors : list of str or None
        None: seed 002's three motion factors (A, B, C above; ``X`` has
        ``stroke_mm``, ``start_mm`` + ``end_mm`` or ``centre_mm``, ``feed_mm_min``).
        Else operating columns (e.g. ``[spindle_rpm]``), each one factor of eq. 15
        read from that column of ``X`` (a spindle test's condition is its speed).
    levels : mapping column -> list of float (or None), or None
        The known levels of each operating factor (only with ``factors``); a factor
        left out or None: the distinct values among the conditions.
    probability : {"score", "proximity", "linear"}
        What :meth:`predict_proba` returns (the weights of a soft bank). ``score``:
        the eq. 19 scores normalised to sum 1 (the paper's own numbers; flat: the
        prior 1/K is added to every score, so with one factor and one condition per
        level no weight is below 1 / (2K), however far the condition). ``proximity``: naive Bayes proper on eq. 16,
        P(#K | x) ∝ Π_φ P(level_φ(#K) | φ) (eq. 17-18 with independent factors, a
        uniform prior; no additive prior). ``linear``: the same product with each
        factor's eq. 16 proximity replaced by :func:`linear_membership` (the two
        levels bracketing the value share it linearly). Where no condition has a
        non-zero product (a motion matching no condition on every factor),
        ``score``. :meth:`predict` is always the eq. 19 argmax.

    Each condition is mapped to its nearest level of each factor (eq. 17-18: the
    conditional probability of that level given the condition is 1, of the others
    0); two conditions on the same levels cannot be told apart and are an error
    naming them. Fitted attributes: ``classes_`` (the labels, in the order of
    ``conditions``, or in the order first met in ``y`` when fitted on data), ``factors_`` (the factor names:
    stroke, position, feed, or the operating columns), ``operating_`` (the operating
    columns, None for the motion factors), ``conditions_`` (DataFrame
    per label: stroke_mm, position_mm, feed_mm_min, or the operating columns),
    ``levels_`` (dict factor -> levels), ``condition_levels_`` ((K, n_factors) level
    index of each condition per factor).
    """

    def __init__(
        self,
        stroke_levels_mm=None,
        position_levels_mm=None,
        feed_levels_mm_min=None,
        conditions=None,
        level_tolerance=0.05,
        factors=None,
        levels=None,
        probability="score",
    ):
        self.stroke_levels_mm = stroke_levels_mm
        self.position_levels_mm = position_levels_mm
        self.feed_levels_mm_min = feed_levels_mm_min
        self.conditions = conditions
        self.level_tolerance = level_tolerance
        self.factors = factors
        self.levels = levels
        self.probability = probability

    # --- parameters ---------------------------------------------------------
    def _operating_columns(self) -> tuple[str, ...] | None:
        """The operating factors (``factors``, checked), None for the motion factors."""
        f = self.factors
        if f is None:
            if self.levels is not None:
                raise _config_error("levels", "levels are the operating factors' levels: set factors (e.g. "
                                    f"[spindle_rpm]) or use stroke_levels_mm/..., got levels={self.levels!r}")  # fmt: skip
            return None
        if isinstance(f, str) or not all(isinstance(c, str) and c for c in f) or not list(f):
            raise _config_error("factors", f"factors must be null (the motion factors) or a non-empty list of "
                                f"operating columns, e.g. [spindle_rpm], got {f!r}")  # fmt: skip
        cols = tuple(f)
        if len(set(cols)) != len(cols):
            raise _config_error("factors", f"factors names a column twice: {list(cols)}")
        motion = [p for p in _PARAM.values() if getattr(self, p) is not None]
        if motion:
            raise _config_error(motion[0], f"{motion[0]} is a motion level; with factors {list(cols)} give "
                                "the levels as levels: {column: [...]}")  # fmt: skip
        if self.levels is not None:
            if not isinstance(self.levels, Mapping):
                raise _config_error("levels", f"levels must be a mapping column -> list of levels, got {self.levels!r}")
            stray = [k for k in self.levels if k not in cols]
            if stray:
                raise _config_error("levels", f"levels names {stray}, which are not among factors {list(cols)}")
        return cols

    def _spec(self, cols: tuple[str, ...] | None) -> tuple[tuple[str, str, str], ...]:
        """(factor, condition key, parameter) per factor."""
        if cols is None:
            return _MOTION_SPEC
        return tuple((c, c, f"levels.{c}") for c in cols)

    def _factor_matrix(self, X, cols: tuple[str, ...] | None) -> np.ndarray:
        return motion_factors(X) if cols is None else operating_factors(X, cols)

    # --- fitting ------------------------------------------------------------
    def _given_conditions(self) -> pd.DataFrame:
        if not isinstance(self.conditions, Mapping) or not self.conditions:
            raise _config_error(
                "conditions",
                f"conditions must be a non-empty mapping label -> {{stroke_mm, position_mm, feed_mm_min}}, "
                f"got {self.conditions!r}",
            )
        rows = {}
        for label, c in self.conditions.items():
            where = f"conditions[{label!r}]"
            if not isinstance(c, Mapping):
                raise _config_error("conditions", f"{where} must be a mapping with stroke_mm, position_mm, feed_mm_min")
            if "position_mm" not in c and not ("start_mm" in c and "end_mm" in c):
                raise _config_error("conditions", f"{where}: missing position_mm (P_start + P_end) or start_mm + end_mm")
            missing = [k for k in ("stroke_mm", "feed_mm_min") if k not in c]
            if missing:
                raise _config_error("conditions", f"{where}: missing {missing}; got keys {sorted(c)}")
            try:
                pos = float(c["position_mm"]) if "position_mm" in c else float(c["start_mm"]) + float(c["end_mm"])
                rows[str(label)] = [float(c["stroke_mm"]), pos, float(c["feed_mm_min"])]
            except (TypeError, ValueError):
                raise _config_error("conditions", f"{where}: values must be numbers, got {dict(c)}") from None
            if not np.all(np.isfinite(rows[str(label)])):
                raise _config_error("conditions", f"{where}: values must be finite, got {dict(c)}")
            if rows[str(label)][0] < 0 or rows[str(label)][2] < 0:
                raise _config_error("conditions", f"{where}: stroke_mm and feed_mm_min must be >= 0, got {dict(c)}")
        return pd.DataFrame.from_dict(rows, orient="index", columns=list(_FACTOR_KEYS.values()))

    def _given_operating_conditions(self, cols: tuple[str, ...]) -> pd.DataFrame:
        if not isinstance(self.conditions, Mapping) or not self.conditions:
            raise _config_error("conditions", f"conditions must be a non-empty mapping label -> {{{', '.join(cols)}}}, "
                                f"got {self.conditions!r}")  # fmt: skip
        rows = {}
        for label, c in self.conditions.items():
            where = f"conditions[{label!r}]"
            if not isinstance(c, Mapping):
                raise _config_error("conditions", f"{where} must be a mapping with {list(cols)}")
            missing = [k for k in cols if k not in c]
            if missing:
                raise _config_error("conditions", f"{where}: missing {missing}; got keys {sorted(c)}")
            try:
                rows[str(label)] = [float(c[k]) for k in cols]
            except (TypeError, ValueError):
                raise _config_error("conditions", f"{where}: values must be numbers, got {dict(c)}") from None
            if not np.all(np.isfinite(rows[str(label)])):
                raise _config_error("conditions", f"{where}: values must be finite, got {dict(c)}")
        return pd.DataFrame.from_dict(rows, orient="index", columns=list(cols))

    def fit(self, X=None, y=None):
        """Set up the condition set: from ``conditions`` (no data needed), or from
        the factor features ``X`` (motion: DataFrame of stroke_mm, start_mm + end_mm or
        centre_mm, feed_mm_min; operating: the ``factors`` columns) with condition
        labels ``y`` (each label's condition is the median of its rows)."""
        for a in [a for a in vars(self) if a.endswith("_") and not a.startswith("__")]:
            delattr(self, a)
        if not isinstance(self.level_tolerance, Real) or not 0 <= self.level_tolerance < 1:
            raise _config_error(
                "level_tolerance", f"level_tolerance must be a number in [0, 1), got {self.level_tolerance!r}"
            )
        if self.probability not in PROBABILITIES:
            raise _config_error("probability", f"probability must be one of {list(PROBABILITIES)}, "
                                f"got {self.probability!r}")  # fmt: skip
        cols = self._operating_columns()
        spec = self._spec(cols)
        if cols is None:
            given = {f: _check_levels(p, getattr(self, p)) for f, _, p in spec}
        else:
            lv = self.levels or {}
            given = {f: _check_levels(p, lv.get(f)) for f, _, p in spec}
        keys = [k for _, k, _ in spec]
        if self.conditions is not None:
            cond = self._given_conditions() if cols is None else self._given_operating_conditions(cols)
        else:
            if X is None or y is None:
                raise _config_error(
                    "conditions",
                    "ProximityNaiveBayes has no conditions: set `conditions` (e.g. conf/classifier/seed002.yaml) "
                    "or fit(X, y) on motion (or operating) features with condition labels",
                )
            F = self._factor_matrix(X, cols)
            y = np.asarray(y).astype(str).ravel()
            if y.size != F.shape[0]:
                raise ValueError(f"fit: X has {F.shape[0]} rows but y has {y.size} labels")
            if y.size == 0:
                raise ValueError("fit: no rows to fit on")
            labels = pd.unique(y)  # in the order first met: a tie of eq. 19 goes to the same class whatever the names
            cond = pd.DataFrame([np.median(F[y == lab], axis=0) for lab in labels], index=labels, columns=keys)
        levels, idx = {}, np.empty((len(cond), len(spec)), dtype=int)
        for j, (f, key, _) in enumerate(spec):
            vals = cond[key].to_numpy()
            tol = float(self.level_tolerance)
            lv = given[f] if given[f] is not None else _merge_levels(vals, tol, pairwise=cols is not None)
            levels[f] = lv
            idx[:, j] = np.argmin(np.abs(vals[:, None] - lv[None, :]), axis=1)
        rows = [tuple(r) for r in idx]
        for k in range(len(rows)):
            same = [cond.index[m] for m in range(len(rows)) if rows[m] == rows[k]]
            if len(same) > 1:
                desc = ", ".join(f"{f} {levels[f][i]:g}" for (f, _, _), i in zip(spec, rows[k]))
                raise _config_error(
                    self._culprit(cond.loc[same], given, spec),
                    f"conditions {same} map to the same levels ({desc}): the classifier cannot tell them apart; "
                    f"levels: " + "; ".join(f"{p}={levels[f].tolist()}" for f, _, p in spec),
                )
        self.classes_ = np.asarray(cond.index.to_numpy(), dtype=object)
        self.factors_ = tuple(f for f, _, _ in spec)
        self.operating_ = cols
        self.conditions_ = cond
        self.levels_ = levels
        self.condition_levels_ = idx
        return self

    def _culprit(self, same: pd.DataFrame, given: dict, spec) -> str:
        """The parameter to change when the conditions ``same`` share their levels: a preset
        condition (``conditions``), else the factor's levels (``*_levels_mm``) or, for levels
        taken from the data, ``level_tolerance``."""
        if self.conditions is not None:
            return "conditions"
        for f, key, param in spec:
            if same[key].nunique() > 1:  # different values on one level of this factor
                return param if given[f] is not None else "level_tolerance"
        return "conditions"

    def _check_fitted(self) -> None:
        if not hasattr(self, "classes_"):
            from sklearn.exceptions import NotFittedError

            raise NotFittedError("ProximityNaiveBayes is not fitted: call fit() (or fit(X, y)) first")

    # --- eq. 15-19 ----------------------------------------------------------
    def _factors_of(self, X) -> np.ndarray:
        return self._factor_matrix(X, self.operating_)

    def level_probabilities(self, X) -> dict[str, np.ndarray]:
        """Per factor, eq. 15-16: the normalised proximity of each row to each level, (n, n_levels)."""
        self._check_fitted()
        F = self._factors_of(X)
        return {f: proximity(F[:, j], self.levels_[f]) for j, f in enumerate(self.factors_)}

    def factor_probabilities(self, X) -> np.ndarray:
        """(n, K, n_factors): for each row and condition, P(level of the condition | factor) per factor."""
        P = self.level_probabilities(X)
        return np.stack([P[f][:, self.condition_levels_[:, j]] for j, f in enumerate(self.factors_)], axis=2)

    def condition_scores(self, X) -> np.ndarray:
        """The raw eq. 19 scores, (n, K): Σ_φ P(level_φ(#K) | φ) + P(#K), P(#K) = 1/K."""
        return self.factor_probabilities(X).sum(axis=2) + 1.0 / len(self.classes_)

    def predict_proba(self, X) -> np.ndarray:
        """(n, K) condition probabilities, per ``probability``: ``score`` (default), the
        eq. 19 scores normalised to sum 1 per row (the paper only takes their argmax);
        ``proximity``, Π_φ of eq. 16 normalised over the conditions; ``linear``, Π_φ
        of :func:`linear_membership` normalised (class docstring)."""
        s = self.condition_scores(X)
        score = s / s.sum(axis=1, keepdims=True)
        if self.probability == "score":
            return score
        if self.probability == "proximity":
            member = self.level_probabilities(X)
        else:
            F = self._factors_of(X)
            member = {f: linear_membership(F[:, j], self.levels_[f]) for j, f in enumerate(self.factors_)}
        w = np.ones_like(s)
        for j, f in enumerate(self.factors_):
            w = w * member[f][:, self.condition_levels_[:, j]]
        total = w.sum(axis=1, keepdims=True)
        return np.where(total > 0, w / np.where(total > 0, total, 1.0), score)

    def predict(self, X) -> np.ndarray:
        """The condition label of each row, ``argmax_K`` of eq. 19."""
        return self.classes_[np.argmax(self.condition_scores(X), axis=1)]


# classify_motion, format_classification moved to thermbench.models.classify_one; measuring_intervals,
# window_features, operating_window_features to thermbench.models.motion_windows
__getattr__ = thermbench.moved_names(__name__)
