"""A stacked ensemble: a weighted sum of models of other families, the weights fitted on their out-of-run predictions.

With a few training runs, picking the single family of lowest cross-validated error picks noise as
often as skill, while a combination of several reasonable models averages their errors out (on a
real five-run test, non-negative stacking of four linear-with-history models and their plain mean
both beat picking the best of them). So::

    E(t, x) = Σ_i w_i · E_i(t, x),   w_i ≥ 0,   Σ_i w_i = 1

* ``E_i``: member ``i``'s full prediction (thermal and geometric), the member fitted on every training
  run;
* ``w``: non-negative least squares (:func:`scipy.optimize.nnls`, Lawson and Hanson) of the measured
  error on the members' **out-of-run** predictions: each training run predicted by members fitted
  without it (:func:`thermbench.bench.splits.row_folds` through scikit-learn's ``cross_val_predict``, the run
  the group), so a member that fits its training runs well but holds up badly gets little weight;
  no intercept (a constant would be a model of its own), and the weights scaled to sum to one (as the
  SuperLearner's NNLS combination does: van der Laan, Polley and Hubbard 2007, *Super Learner*): a sum
  below one would shrink every member's answer toward no compensation, a gain fitted on the few
  out-of-run predictions, i.e. a model of its own too; so the stack is a weighted average of its
  members, never outside the range of their answers;
* the fallback is the plain mean (``w_i = 1/n``): with one training run (no run to hold out), or when the
  least squares give every member zero weight; ``stacking="mean"`` asks for it.

The C runtime runs it as the ``ENSEMBLE`` kind (``embedded/src/tb_kind_ensemble.c``): the members' own
model files carried in one file, each run by its own kind, the weighted sum of their answers; so it
exports when every member does. Its intervals, probe updates and guard are those of any model: the
benchmark calibrates them on its predictions.

Fitted: ``members_`` (each fitted on every training run), ``weights_``, ``stacking_`` (what set the
weights), ``member_names_``, ``member_cv_rmse_um_`` (each member's out-of-run RMSE) and
``cv_rmse_um_`` (the weighted sum's, with the weights fitted on those same predictions: optimistic).
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Sequence

import numpy as np
from annotated_types import Len
from numpy.polynomial import Polynomial
from pydantic import AfterValidator
from scipy.optimize import nnls
from sklearn.base import clone

from ..data.dataset import Dataset
from .base import Inputs, ModelError, ThermalErrorModel
from .params import Expect, Params, check_params

__all__ = ["StackedEnsemble", "member_label", "stack_weights"]


def _models(v):
    for m in v:
        if not isinstance(m, ThermalErrorModel):
            raise ValueError(f"{type(m).__name__} is not a thermbench model")
    return v


class StackedEnsembleParams(Params):
    members: Annotated[Sequence[Any], Len(min_length=1, max_length=8), AfterValidator(_models),
                       Expect("a list of 1 to 8 thermbench models (each a config with its _target_)")]  # fmt: skip
    stacking: Annotated[Literal["nnls", "mean"], Expect("nnls (non-negative weights on out-of-run predictions) or mean")]


def stack_weights(P: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, str]:
    """Non-negative weights of the columns of ``P`` (one member's out-of-run predictions each) that fit
    ``y`` in least squares, scaled to sum to one, or the plain mean when they are all zero: (weights,
    what set them)."""
    w, _ = nnls(np.asarray(P, dtype=float), np.asarray(y, dtype=float))
    if not np.isfinite(w).all() or w.sum() <= 0:
        return np.full(P.shape[1], 1.0 / P.shape[1]), "mean (the least squares gave every member zero weight)"
    return w / w.sum(), "nnls"


def _plain(v):
    """A parameter value as plain lists and short numbers, to compare and to print."""
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, (float, np.floating)):
        v = float(f"{float(v):.6g}")
        return int(v) if v.is_integer() else v
    return v


def member_label(m) -> str:
    """A member named by its family and the parameters it sets away from the family's defaults, e.g.
    ``LinearHistory(estimator='pls', delays_s=[[0, 900, 1800, 3600]])``: what tells two members of one
    family apart in the weights a report prints."""
    defaults = type(m)().get_params(deep=False)
    diff = {k: _plain(v) for k, v in m.get_params(deep=False).items() if _plain(v) != _plain(defaults.get(k))}
    text = ", ".join(f"{k}={v!r}" for k, v in diff.items())
    return f"{type(m).__name__}({text})" if diff else type(m).__name__


class StackedEnsemble(ThermalErrorModel):
    """A weighted sum of thermbench models, the weights non-negative and fitted on out-of-run
    predictions (module docstring).

    Parameters
    ----------
    members : list of ThermalErrorModel
        The models combined (cloned at fit), e.g. ``[LinearHistory(), ThermalLag()]``.
    stacking : "nnls" or "mean"
        How the weights are set: non-negative least squares on out-of-run predictions, or the plain mean.
    """

    #: the benchmark's choice prefers it to any single family it cannot tell apart from the best (0, below
    #: the linear families' 1; ThermalErrorModel.complexity): averaging lowers the variance of what it
    #: combines rather than adding flexibility, and on few runs that variance is what a pick gets wrong
    complexity = 0
    params_model = StackedEnsembleParams

    def __init__(self, members=(), stacking="nnls"):
        self.members = members
        self.stacking = stacking

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        from sklearn.model_selection import cross_val_predict

        from ..bench.splits import DatasetRef, RunsRegressor, row_folds, run_rows

        p = check_params(self, self.params_model)
        names = []
        for m in p.members:
            base = member_label(m)
            names.append(base if base not in names else f"{base}#{sum(n.split('#')[0] == base for n in names) + 1}")
        self.member_names_ = names
        X, y, groups = run_rows(ds, runs)
        if len(runs) > 1:  # every training run predicted by members fitted without it
            folds = row_folds(groups)
            P = np.column_stack([cross_val_predict(RunsRegressor(m, DatasetRef(ds)), X, y, groups=groups, cv=folds)
                                 for m in p.members])  # fmt: skip
            if not np.isfinite(P).all():
                raise ModelError(f"a member's out-of-run predictions on runs {runs} are not finite")
            self.member_cv_rmse_um_ = [float(np.sqrt(np.mean((P[:, i] - y) ** 2))) for i in range(P.shape[1])]
            if p.stacking == "nnls":
                self.weights_, self.stacking_ = stack_weights(P, y)
            else:
                self.weights_, self.stacking_ = np.full(P.shape[1], 1.0 / P.shape[1]), "mean (as asked)"
            self.cv_rmse_um_ = float(np.sqrt(np.mean((P @ self.weights_ - y) ** 2)))
        else:
            self.member_cv_rmse_um_ = [float("nan")] * len(p.members)
            self.weights_ = np.full(len(p.members), 1.0 / len(p.members))
            self.stacking_ = "mean (one training run: no run to hold out)"
            self.cv_rmse_um_ = float("nan")
        self.members_ = [clone(m).fit(ds, runs) for m in p.members]
        self.geometric_ = Polynomial([0.0])

    @classmethod
    def of_fitted(cls, names: Sequence[str], fitted: Sequence[ThermalErrorModel], weights, how: str,
                  cv_rmse_um: float = float("nan")) -> "StackedEnsemble":  # fmt: skip
        """The ensemble of models already fitted on the same runs and weights already fitted (the
        benchmark's stack of every family, thermbench/bench/stack.py): its parameters are the members'
        unfitted clones (a refit stacks them anew), its fitted state theirs. ``how``: what set the
        weights (``stacking_``)."""
        if not fitted or len(fitted) != len(names) or len(fitted) != len(weights):
            raise ModelError(f"of_fitted: {len(names)} names, {len(fitted)} models and {len(weights)} weights")
        runs = [list(m.train_runs_) for m in fitted]
        if any(sorted(r) != sorted(runs[0]) for r in runs):
            raise ModelError(f"of_fitted: the members were fitted on different runs: {runs}")
        self = cls(members=[clone(m) for m in fitted], stacking="nnls")
        self.member_names_ = list(names)
        self.members_ = list(fitted)
        self.weights_ = np.asarray(weights, dtype=float)
        self.stacking_ = how
        self.member_cv_rmse_um_ = [float("nan")] * len(fitted)
        self.cv_rmse_um_ = float(cv_rmse_um)
        self.geometric_ = Polynomial([0.0])
        self.train_runs_ = runs[0]
        self.channel_ = getattr(fitted[0], "channel_", None)
        return self

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        out = np.zeros(np.asarray(t_s).size)
        for w, m in zip(self.weights_, self.members_):
            if w != 0:
                out += w * np.asarray(m.predict_at(ds, run, t_s, axis_mm), dtype=float)
        return out

    def fit_summary(self) -> str:
        self._check_fitted()
        parts = ", ".join(f"{n} {w:.3f}" for n, w in zip(self.member_names_, self.weights_))
        return f"weights {parts} ({self.stacking_} on out-of-run predictions)"

    def _model_inputs(self) -> Inputs:
        ins = [m.required_inputs() for m in self.members_]
        return Inputs(sensors=tuple(dict.fromkeys(s for i in ins for s in i.sensors)),
                      motion=any(i.motion for i in ins), ambient=any(i.ambient for i in ins),
                      operating=tuple(dict.fromkeys(c for i in ins for c in i.operating)))  # fmt: skip

    def export_encoding(self, channels, period_s, where):
        """The C runtime's ``ENSEMBLE`` kind (:func:`thermbench.export.encoding.encode_ensemble`)."""
        from ..export.encoding import encode_ensemble

        return encode_ensemble(self, channels, period_s, where)
