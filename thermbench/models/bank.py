"""A bank of per-condition models switched by a motion classifier (seed 002 §2.4-2.5).

Seed 002 finds that one thermal error model does not hold across motion conditions
(§2.3, §3: MLR 88.69 % on its own condition), so it fits one model per known
condition (Table 5), classifies the current motion (stroke, position, feed) with
the proximity naive-Bayes rule of eq. 15-19 and loads the matching model at run
time (§2.5, "dynamic loading"). :class:`ConditionBank` does the same with any
thermbench model family and any scikit-learn classifier:

* ``fit(ds, runs)`` groups the training runs by identical declared condition
  (``metadata.runs[r].condition``), fits ``clone(model)`` per group and fits the
  classifier on the motion features of the groups' runs, one row per ``step_s``
  window of ``window_s`` (:func:`thermbench.classify.window_features`, measuring
  cycles left out); :meth:`ConditionBank.fit_from_fitted` builds the bank from
  models already fitted and fits only the classifier.
* At (t, x) of a run the condition at t is the class of the motion window ending at
  the last ``step_s`` grid point <= t (held through stops and before the first
  motion: no condition, since a compensator cannot know the class of motion still to
  come; the axis is then taken as cold, thermal error 0, and only the geometric part
  is predicted), and the prediction is that condition's model's.
"""

from __future__ import annotations

from numbers import Real
from typing import Mapping

import numpy as np
import pandas as pd
from sklearn.base import clone

from ..classify import ProximityNaiveBayes, learned_features, measuring_intervals, window_features
from ..data.io import Dataset
from .base import Inputs, ModelError, ThermalErrorModel, check_runs

__all__ = ["ConditionBank"]


class MeanGeometric:
    """The mean of several fitted geometric-error callables (axis_mm -> µm)."""

    def __init__(self, parts):
        self.parts = list(parts)

    def __call__(self, axis_mm) -> np.ndarray:
        x = np.asarray(axis_mm, dtype=float)
        return np.mean([np.asarray(p(x), dtype=float) for p in self.parts], axis=0)


def _condition_key(ds: Dataset, run: str) -> tuple[float, float, float, float]:
    c = ds.metadata.runs[run].condition
    return (float(c.stroke_mm), float(c.start_mm), float(c.end_mm), float(c.feed_mm_min))


class ConditionBank(ThermalErrorModel):
    """One model per motion condition, chosen at run time by a classifier (seed 002 §2.4-2.5).

    Parameters
    ----------
    model : ThermalErrorModel
        An unfitted model, cloned and fitted per condition (hydra builds it from a
        nested ``_target_``).
    classifier : scikit-learn classifier or None
        Fitted on the window features ``stroke_mm``, ``centre_mm`` = (start + end) / 2
        and ``feed_mm_min`` (:func:`thermbench.classify.learned_features`) with the
        condition labels; None: :class:`~thermbench.classify.ProximityNaiveBayes`
        with its levels taken from the training conditions. Its classes must be
        the bank's condition labels (a classifier with preset conditions, e.g.
        ``conf/classifier/seed002.yaml`` with labels #1..#9, is an error).
    window_s : float
        Length of the motion window classified (the features of (t - window_s, t]).
    step_s : float
        The classification grid: every ``step_s`` from the run's first sample.
    min_moving_s : float
        A window with less motion than this (outside measuring cycles) is a stop:
        the last class is held.

    Fitted attributes: ``models_`` (label -> fitted model), ``labels_``,
    ``classifier_``, ``group_runs_`` (label -> runs), ``geometric_`` (the mean of
    the models' geometric parts; the thermal part is the chosen model's full
    prediction minus it, so geometric + thermal is the chosen model's prediction).
    """

    def __init__(self, model=None, classifier=None, window_s=600.0, step_s=60.0, min_moving_s=60.0):
        self.model = model
        self.classifier = classifier
        self.window_s = window_s
        self.step_s = step_s
        self.min_moving_s = min_moving_s

    # --- checks -------------------------------------------------------------
    def _check_params(self) -> None:
        for name in ("window_s", "step_s"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, Real) or not np.isfinite(v) or v <= 0:
                raise ModelError(f"{name} must be a number > 0, got {v!r}")
        v = self.min_moving_s
        if isinstance(v, bool) or not isinstance(v, Real) or not np.isfinite(v) or v < 0:
            raise ModelError(f"min_moving_s must be a number >= 0, got {v!r}")
        clf = self.classifier
        if clf is not None and not (hasattr(clf, "fit") and hasattr(clf, "predict") and hasattr(clf, "get_params")):
            raise ModelError(
                f"classifier must be a scikit-learn classifier (fit/predict/get_params), got {type(clf).__name__}"
            )

    # --- fitting ------------------------------------------------------------
    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        self._check_params()
        if not isinstance(self.model, ThermalErrorModel):
            raise ModelError(
                f"model must be an unfitted thermbench model (ThermalErrorModel), got {type(self.model).__name__}"
            )
        groups: dict[tuple, list[str]] = {}
        for r in runs:
            groups.setdefault(_condition_key(ds, r), []).append(r)
        models = {}
        for members in groups.values():
            label = "+".join(members)
            models[label] = clone(self.model).fit(ds, members)
        self._build(ds, models)

    def fit_from_fitted(self, dataset: Dataset, fitted: Mapping[str, ThermalErrorModel]) -> "ConditionBank":
        """The bank of already-fitted models ``fitted`` (label -> model; each model's
        ``train_runs_`` are its condition's runs); only the classifier is fitted, on
        the motion windows of those runs. The models are used as they are (not copied)."""
        for attr in [a for a in vars(self) if a.endswith("_") and not a.startswith("__")]:
            delattr(self, attr)
        self._check_params()
        if not isinstance(fitted, Mapping) or not fitted:
            raise ModelError("fit_from_fitted: give a non-empty mapping label -> fitted model")
        seen: dict[str, str] = {}
        for label, m in fitted.items():
            if not isinstance(m, ThermalErrorModel):
                raise ModelError(f"fit_from_fitted: {label!r} is a {type(m).__name__}, not a thermbench model")
            if not hasattr(m, "train_runs_"):
                raise ModelError(f"fit_from_fitted: the model for {label!r} is not fitted")
            for r in check_runs(dataset, m.train_runs_):
                if r in seen:
                    raise ModelError(
                        f"fit_from_fitted: run {r!r} trained both {seen[r]!r} and {label!r}; "
                        "each run must belong to one condition"
                    )
                seen[r] = str(label)
        self._build(dataset, {str(k): v for k, v in fitted.items()})
        self.train_runs_ = list(seen)
        return self

    def _build(self, ds: Dataset, models: dict[str, ThermalErrorModel]) -> None:
        rows, labels = [], []
        for label, m in models.items():
            n = 0
            for r in m.train_runs_:
                w = self._windows(ds, r)
                w = w[w["moving"]]
                rows.append(w)
                labels += [label] * len(w)
                n += len(w)
            if n == 0:
                raise ModelError(
                    f"condition {label!r}: its run(s) {list(m.train_runs_)} have no motion windows "
                    f"(>= {self.min_moving_s} s of motion in {self.window_s} s outside measuring cycles) "
                    "to train the classifier on"
                )
        X = learned_features(pd.concat(rows, ignore_index=True))
        clf = clone(self.classifier) if self.classifier is not None else ProximityNaiveBayes()
        try:
            clf.fit(X, np.asarray(labels, dtype=object))
        except ValueError as exc:
            raise ModelError(f"classifier {type(clf).__name__}: {exc}") from exc
        classes = [str(c) for c in getattr(clf, "classes_", [])]
        unknown = sorted(set(classes) - set(models))
        if unknown or not classes:
            raise ModelError(
                f"classifier {type(clf).__name__} labels {unknown or classes} are not conditions of the bank "
                f"{list(models)}; a classifier with preset conditions (e.g. conf/classifier/seed002.yaml) "
                "cannot label these runs: use one fitted on them (conf/classifier/proximity.yaml or learned.yaml)"
            )
        self.models_ = models
        self.labels_ = list(models)
        self.group_runs_ = {k: list(m.train_runs_) for k, m in models.items()}
        self.classifier_ = clf
        self.geometric_ = MeanGeometric([m.geometric_ for m in models.values()])

    # --- classification -----------------------------------------------------
    def _grid(self, ds: Dataset, run: str) -> np.ndarray:
        pr = ds.process_run(run)
        if pr.empty:
            raise ModelError(f"run {run!r} has no process samples")
        t0, t1 = float(pr["t_s"].iloc[0]), float(pr["t_s"].iloc[-1])
        return np.arange(t0, t1 + 1e-9, float(self.step_s))

    def _windows(self, ds: Dataset, run: str, grid: np.ndarray | None = None) -> pd.DataFrame:
        pr = ds.process_run(run)
        grid = self._grid(ds, run) if grid is None else grid
        ex = measuring_intervals(pr, ds.errors_run(run))
        w = window_features(pr, grid, window_s=float(self.window_s), exclude=ex, min_moving_s=float(self.min_moving_s))
        w.insert(0, "t_s", grid)
        return w

    def condition_track(self, dataset: Dataset, run: str) -> pd.DataFrame:
        """The classification grid of ``run``: ``t_s``, the window features, ``moving``,
        ``raw_label`` (the classifier's label of moving windows, else None) and ``label``
        (the condition used from that time on: held through stops; None before the
        first classified window — no look-ahead)."""
        self._check_fitted()
        run = check_runs(dataset, run)[0]
        w = self._windows(dataset, run)
        raw = np.full(len(w), None, dtype=object)
        mv = w["moving"].to_numpy()
        if not mv.any():
            raise ModelError(
                f"run {run!r} has no motion outside measuring cycles (>= {self.min_moving_s} s in a "
                f"{self.window_s} s window): the bank cannot classify its condition"
            )
        raw[mv] = np.asarray(self.classifier_.predict(learned_features(w[mv])), dtype=object).astype(str)
        held = pd.Series(raw, dtype=object).ffill()  # missing (None) until the first classified window
        w["raw_label"] = raw
        w["label"] = held.to_numpy()
        return w

    def conditions_at(self, dataset: Dataset, run: str, t_s) -> np.ndarray:
        """The condition label used at each time ``t_s`` of ``run`` (the label of the
        last grid point <= t; None before the first classified window)."""
        tr = self.condition_track(dataset, run)
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).ravel()
        i = np.clip(np.searchsorted(tr["t_s"].to_numpy(), t, side="right") - 1, 0, len(tr) - 1)
        return np.array([v if isinstance(v, str) else None for v in tr["label"].to_numpy()[i]], dtype=object)

    # --- prediction ---------------------------------------------------------
    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        labels = self.conditions_at(ds, run, t_s)
        out = np.zeros(t_s.size)  # no condition yet: a cold axis, no thermal error
        for lab in {lab for lab in labels if lab is not None}:
            m = labels == lab
            full = self.models_[lab].predict_at(ds, run, t_s[m], axis_mm[m])
            out[m] = full - self.geometric_(axis_mm[m])
        return out

    def _model_inputs(self) -> Inputs:
        sensors, operating, ambient = [], [], False
        for m in self.models_.values():
            inp = m.required_inputs()
            sensors += [s for s in inp.sensors if s not in sensors]
            operating += [c for c in inp.operating if c not in operating]
            ambient = ambient or inp.ambient
        return Inputs(sensors=tuple(sensors), motion=True, ambient=ambient, operating=tuple(operating))
