"""Cross-validation over runs (issue 38): which runs each fold trains on and which it holds out.

Thermal data are time series: a fold never splits a run, it holds whole runs out
(scikit-learn's group splitters with the run as the group):

* ``loro``: each run held out once (:class:`sklearn.model_selection.LeaveOneGroupOut`); the
  default for a dataset whose loading states are its runs (no declared validation runs);
* ``group_kfold``: ``k`` folds of whole runs (:class:`sklearn.model_selection.GroupKFold`);
* ``declared``: the dataset's own split, its loading states against its validation runs
  (``dataset.validation``: fl_thermal's stepped tail), one fold.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from sklearn.model_selection import GroupKFold, LeaveOneGroupOut

from .experiment import ExperimentError

CV_KINDS = ("loro", "group_kfold", "declared")


@dataclass(frozen=True)
class Fold:
    """One fold: its name (the held-out run, ``a+b`` for several), the runs it trains on and
    the runs it holds out."""

    name: str
    train: tuple[str, ...]
    held_out: tuple[str, ...]


def resolve_cv(cv: str | None, validation: Sequence[str]) -> str:
    """``cv`` as given, or for null: ``declared`` when the dataset declares validation runs,
    ``loro`` otherwise."""
    if cv is None:
        return "declared" if validation else "loro"
    if cv not in CV_KINDS:
        raise ExperimentError(f"config key 'cv': expected one of {', '.join(CV_KINDS)} or null, got {cv!r}")
    return cv


def folds(runs: Sequence[str], validation: Sequence[str], cv: str, k: int = 5) -> list[Fold]:
    """The folds of ``cv`` over ``runs`` (the runs with readings, in dataset order);
    ``validation``: the declared held-out runs (``declared`` only)."""
    runs = list(runs)
    if cv == "declared":
        if not validation:
            raise ExperimentError("config key 'cv': declared, but the dataset declares no validation runs "
                                  "(dataset.validation); use cv=loro")  # fmt: skip
        return [Fold("+".join(validation), tuple(r for r in runs if r not in validation), tuple(validation))]
    if len(runs) < 2:
        raise ExperimentError(f"config key 'cv': {cv} needs at least 2 runs with readings, the dataset has {len(runs)}")
    if cv == "loro":
        splitter = LeaveOneGroupOut()
    else:
        if isinstance(k, bool) or not isinstance(k, int) or not 2 <= k <= len(runs):
            raise ExperimentError(f"config key 'cv_folds': expected an integer from 2 to the number of runs "
                                  f"({len(runs)}), got {k!r}")  # fmt: skip
        splitter = GroupKFold(n_splits=k)
    idx = np.arange(len(runs))
    out = []
    for train, test in splitter.split(idx, groups=idx):
        held = tuple(runs[i] for i in sorted(test))
        out.append(Fold("+".join(held), tuple(runs[i] for i in sorted(train)), held))
    return out


#: an outer fold's training runs up to this many: the inner cross-validation holds each out once
INNER_LORO_MAX_RUNS = 6
#: more training runs: this many inner folds of whole runs (GroupKFold)
INNER_FOLDS = 3


def inner_folds(train: Sequence[str]) -> list[Fold]:
    """The inner cross-validation of one outer fold, on its training runs only (the nested choice
    never sees the runs the fold holds out): each run held out once for up to
    :data:`INNER_LORO_MAX_RUNS` runs, else :data:`INNER_FOLDS` folds of whole runs. None for
    fewer than 2 runs (nothing to choose on)."""
    train = list(train)
    if len(train) < 2:
        return []
    if len(train) <= INNER_LORO_MAX_RUNS:
        return folds(train, [], "loro")
    return folds(train, [], "group_kfold", k=INNER_FOLDS)
