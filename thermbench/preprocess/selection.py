"""Temperature-sensitive point selection: single-linkage clustering + grey relational analysis
(seed 002 §2.3.1, eq. 4-5).

The paper groups the temperature sensors by the shape of their temperature trend with
single-linkage hierarchical clustering (four clusters), ranks them by the grey
relational grade between each sensor's trend and the slope of the thermal positioning
error, and keeps the best-ranked sensor of each cluster. :func:`select_sensitive_points`
does that, with Pearson correlation and LASSO as alternative scores.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from numbers import Integral, Real

import numpy as np
import pandas as pd
from scipy.cluster.hierarchy import fcluster, linkage
from scipy.spatial.distance import squareform

from .filters import PreprocessError

__all__ = ["METHODS", "Selection", "cluster_sensors", "grey_relational_grade", "select_sensitive_points"]

METHODS = ("gra", "correlation", "lasso")
MIN_SAMPLES = 3


@dataclass
class Selection:
    """Result of :func:`select_sensitive_points`.

    selected : the chosen columns, one per cluster, ordered by score (descending).
    clusters : the clusters (column names, in ``temps`` column order).
    scores : per considered column, its grey relational grade / |Pearson r| / |standardised LASSO coefficient|.
    method : the scoring method used.
    """

    selected: list[str]
    clusters: list[list[str]]
    scores: dict[str, float]
    method: str


def _check_temps(temps, what: str = "temps") -> pd.DataFrame:
    if not isinstance(temps, pd.DataFrame):
        raise PreprocessError(
            f"{what}: expected a pandas DataFrame (one column per sensor), got {type(temps).__name__}"
        )
    if temps.shape[1] == 0:
        raise PreprocessError(f"{what}: no sensor columns")
    if len(set(temps.columns)) != temps.shape[1]:
        dup = next(c for c in temps.columns if list(temps.columns).count(c) > 1)
        raise PreprocessError(f"{what}: column {dup!r} appears twice")
    for c in temps.columns:
        s = temps[c]
        if not pd.api.types.is_numeric_dtype(s) or pd.api.types.is_bool_dtype(s):
            raise PreprocessError(f"{what}: column {c!r}: expected numeric values, got dtype {s.dtype}")
        v = s.to_numpy(dtype=float)
        bad = ~np.isfinite(v)
        if bad.any():
            i = int(np.argmax(bad))
            raise PreprocessError(f"{what}: column {c!r}, row {i}: value {v[i]}; expected finite values")
    if len(temps) < MIN_SAMPLES:
        raise PreprocessError(f"{what}: {len(temps)} samples (rows); at least {MIN_SAMPLES} are needed")
    for c in temps.columns:
        v = temps[c].to_numpy(dtype=float)
        if np.ptp(v) == 0:
            raise PreprocessError(
                f"{what}: column {c!r} is constant ({v[0]}); it has no trend to cluster or rank - exclude it"
            )
    return temps


def _check_cluster_args(n_clusters, distance_threshold, n_sensors: int) -> None:
    if (n_clusters is None) == (distance_threshold is None):
        raise PreprocessError(
            "give exactly one of n_clusters or distance_threshold "
            f"(got n_clusters={n_clusters!r}, distance_threshold={distance_threshold!r}; "
            "set n_clusters=None to cut by distance)"
        )
    if n_clusters is not None:
        if isinstance(n_clusters, bool) or not isinstance(n_clusters, Integral) or n_clusters < 1:
            raise PreprocessError(f"n_clusters must be an int >= 1, got {n_clusters!r}")
        if n_clusters > n_sensors:
            raise PreprocessError(f"n_clusters={n_clusters} is more than the {n_sensors} sensor columns")
    else:
        d = distance_threshold
        if isinstance(d, bool) or not isinstance(d, Real) or not math.isfinite(d) or d < 0:
            raise PreprocessError(f"distance_threshold must be a finite number >= 0 (1 - |r| units), got {d!r}")


def cluster_sensors(
    temps: pd.DataFrame, n_clusters: int | None = None, distance_threshold: float | None = None
) -> list[list[str]]:
    """Group sensors by the shape of their temperature trend, seed 002 §2.3.1 (single linkage).

    ``temps`` has one column per sensor and one row per time sample. The distance
    between two sensors is ``1 - |r|`` with ``r`` the Pearson correlation of their
    series. The paper clusters "the trend of the temperature rise" and does not state
    its metric; correlation compares trend shapes independent of each sensor's level
    and span (an ambient-coupled bed sensor at 21 °C and a bearing at 35 °C with the same
    rise shape belong together), and for standardised series ``1 - r`` is a monotone
    function of their Euclidean distance, so single linkage gives the same tree as on
    standardised series. The absolute value treats a mirrored trend as redundant
    information, which it is for a linear model.

    Tree: ``scipy.cluster.hierarchy.linkage(method="single")`` (the paper: "category
    spacing equal to the minimum distance between two categories"). Cut with
    ``n_clusters`` (``fcluster(criterion="maxclust")``, which can return fewer clusters
    when merge heights tie) or ``distance_threshold`` (``criterion="distance"``, in
    ``1 - |r|`` units); give exactly one.

    Returns the clusters as lists of column names, each in ``temps`` column order,
    ordered by their first member's position in ``temps``.
    """
    temps = _check_temps(temps)
    names = list(temps.columns)
    _check_cluster_args(n_clusters, distance_threshold, len(names))
    if len(names) == 1:
        return [names]
    r = np.corrcoef(temps.to_numpy(dtype=float), rowvar=False)
    dist = np.clip(1.0 - np.abs(r), 0.0, 1.0)
    dist = (dist + dist.T) / 2.0
    np.fill_diagonal(dist, 0.0)
    Z = linkage(squareform(dist, checks=False), method="single")
    if n_clusters is not None:
        labels = fcluster(Z, t=n_clusters, criterion="maxclust")
    else:
        labels = fcluster(Z, t=float(distance_threshold), criterion="distance")
    clusters: dict[int, list[str]] = {}
    for name, lab in zip(names, labels, strict=True):
        clusters.setdefault(int(lab), []).append(name)
    return list(clusters.values())  # dict keeps first-appearance order


def _minmax(v: np.ndarray, what: str) -> np.ndarray:
    """Min-max normalise each column of a 2-D array (or a 1-D array) to [0, 1]."""
    lo, hi = v.min(axis=0), v.max(axis=0)
    span = np.atleast_1d(hi - lo)
    if np.any(span == 0):
        where = what if v.ndim == 1 else f"{what} column {int(np.argmax(span == 0))}"
        raise PreprocessError(f"{where} is constant; min-max normalisation needs a varying sequence")
    return (v - lo) / (hi - lo)


def grey_relational_grade(reference: np.ndarray, candidates: np.ndarray, xi: float = 0.5) -> np.ndarray:
    """Grey relational grade of each candidate sequence to ``reference``, seed 002 §2.3.1 eq. 4-5.

    ``reference`` has shape (n,); ``candidates`` has shape (n, m), one candidate per
    column (a 1-D ``candidates`` is one candidate). Every sequence is first min-max
    normalised to [0, 1]: the paper does not state its normalisation, and min-max
    (unlike division by the mean or the first value) works for sequences whose mean is
    near zero, such as error slopes, and makes the grade invariant to each sequence's
    units and offset. A consequence: a sequence that falls while the reference rises
    gets a low grade (GRA measures shape similarity, not |correlation|).

    With ``Δi(k) = |y(k) - xi(k)|`` on the normalised sequences, eq. 5::

        γ(y(k), xi(k)) = (min_i min_k Δi(k) + ξ max_i max_k Δi(k)) / (Δi(k) + ξ max_i max_k Δi(k))

    where the min and max run over *all* candidates (so a grade depends on the
    candidate set), and eq. 4: ``γ(y, xi) = mean_k γ(y(k), xi(k))``. If every Δ is 0
    all grades are 1. ``xi`` (the paper's distinguishing coefficient η) must lie in
    (0, 1]; 0.5 is the usual value. Returns shape (m,).
    """
    if isinstance(xi, bool) or not isinstance(xi, Real) or not (0.0 < xi <= 1.0):
        raise PreprocessError(f"xi (distinguishing coefficient) must be in (0, 1], got {xi!r}")
    y = np.asarray(reference, dtype=float)
    x = np.asarray(candidates, dtype=float)
    if y.ndim != 1:
        raise PreprocessError(f"reference: expected a 1-D sequence, got shape {y.shape}")
    if x.ndim == 1:
        x = x[:, None]
    if x.ndim != 2 or x.shape[0] != y.size:
        raise PreprocessError(
            f"candidates: expected shape ({y.size}, m) (one candidate per column, as many rows as reference), "
            f"got {np.shape(candidates)}"
        )
    if x.shape[1] == 0:
        raise PreprocessError("candidates: no candidate columns")
    if y.size < 2:
        raise PreprocessError(f"reference: {y.size} samples; at least 2 are needed")
    if not np.isfinite(y).all():
        raise PreprocessError(f"reference: row {int(np.argmax(~np.isfinite(y)))} is not finite")
    if not np.isfinite(x).all():
        i, j = np.argwhere(~np.isfinite(x))[0]
        raise PreprocessError(f"candidates: column {j}, row {i} is not finite")
    delta = np.abs(_minmax(y, "reference")[:, None] - _minmax(x, "candidates"))
    dmin, dmax = delta.min(), delta.max()
    if dmax == 0:
        return np.ones(x.shape[1])
    coef = (dmin + xi * dmax) / (delta + xi * dmax)
    return coef.mean(axis=0)


def _lasso_scores(X: np.ndarray, y: np.ndarray, seed: int) -> np.ndarray:
    from sklearn.linear_model import LassoCV
    from sklearn.model_selection import KFold

    Xs = (X - X.mean(axis=0)) / X.std(axis=0)
    ys = (y - y.mean()) / y.std()
    cv = KFold(n_splits=min(5, len(ys)), shuffle=False)  # contiguous blocks of time
    model = LassoCV(cv=cv, random_state=seed, max_iter=100_000).fit(Xs, ys)
    return np.abs(model.coef_)


def select_sensitive_points(
    temps: pd.DataFrame,
    target: np.ndarray,
    method: str = "gra",
    n_clusters: int | None = 4,
    distance_threshold: float | None = None,
    xi: float = 0.5,
    exclude: Sequence[str] = (),
    seed: int = 0,
) -> Selection:
    """Pick one temperature-sensitive sensor per cluster, seed 002 §2.3.1 (eq. 4-5).

    ``temps``: one column per sensor, one row per time sample (the paper uses each
    sensor's temperature trend). ``target``: the series the sensors should explain, one
    value per row (the paper: the slope of the thermal positioning error over the
    stroke at each time). ``exclude``: columns left out of clustering and scoring (the
    paper drops the ambient and machine-foot sensors).

    Steps: cluster the remaining sensors (:func:`cluster_sensors`, ``n_clusters`` or
    ``distance_threshold``), score each sensor against ``target`` and keep the
    highest-scoring sensor of each cluster (ties: the first in column order).
    Scores by ``method``:

    - ``"gra"``: grey relational grade (:func:`grey_relational_grade`, coefficient ``xi``);
    - ``"correlation"``: |Pearson r| with the target;
    - ``"lasso"``: |coefficient| of ``LassoCV`` on standardised temperatures and target,
      5 contiguous (unshuffled) folds, ``random_state=seed``. Of several near-identical
      sensors LASSO keeps one and may zero the others, or a whole cluster (all 0: the
      first in column order is picked).

    The result is deterministic.
    """
    if method not in METHODS:
        raise PreprocessError(f"method must be one of {list(METHODS)}, got {method!r}")
    if isinstance(seed, bool) or not isinstance(seed, Integral):
        raise PreprocessError(f"seed must be an int, got {seed!r}")
    if not isinstance(temps, pd.DataFrame):
        raise PreprocessError(f"temps: expected a pandas DataFrame (one column per sensor), got {type(temps).__name__}")
    if isinstance(exclude, str):
        exclude = [exclude]
    exclude = list(exclude)
    for c in exclude:
        if c not in temps.columns:
            raise PreprocessError(f"exclude: column {c!r} is not in temps; columns: {list(temps.columns)}")
    kept = temps.drop(columns=exclude)
    if kept.shape[1] == 0:
        raise PreprocessError(f"exclude: every column of temps is excluded ({exclude}); nothing to select")

    y = np.asarray(target, dtype=float)
    if y.ndim != 1:
        raise PreprocessError(f"target: expected a 1-D series (one value per row of temps), got shape {y.shape}")
    if y.size != len(kept):
        raise PreprocessError(f"target: length {y.size} does not match the {len(kept)} rows of temps")
    if not np.isfinite(y).all():
        raise PreprocessError(f"target: row {int(np.argmax(~np.isfinite(y)))} is not finite")
    if isinstance(n_clusters, Integral) and not isinstance(n_clusters, bool) and len(kept) < n_clusters:
        raise PreprocessError(f"temps: {len(kept)} samples (rows) is fewer than n_clusters={n_clusters}")
    kept = _check_temps(kept)
    if np.ptp(y) == 0:
        raise PreprocessError(f"target is constant ({y[0]}); there is nothing to relate the sensors to")

    clusters = cluster_sensors(kept, n_clusters=n_clusters, distance_threshold=distance_threshold)
    X = kept.to_numpy(dtype=float)
    if method == "gra":
        s = grey_relational_grade(y, X, xi=xi)
    elif method == "correlation":
        r = np.corrcoef(np.column_stack([y, X]), rowvar=False)[0, 1:]
        s = np.abs(r)
    else:
        s = _lasso_scores(X, y, int(seed))
    names = list(kept.columns)
    scores = {c: float(v) for c, v in zip(names, s, strict=True)}
    pos = {c: i for i, c in enumerate(names)}
    best = [max(cl, key=lambda c: (scores[c], -pos[c])) for cl in clusters]
    selected = sorted(best, key=lambda c: (-scores[c], pos[c]))
    return Selection(selected=selected, clusters=clusters, scores=scores, method=method)
