"""A bank of per-condition models switched by a condition classifier (seed 002 §2.4-2.5).

Seed 002 finds that one thermal error model does not hold across motion conditions
(§2.3, §3: MLR 88.69 % on its own condition), so it fits one model per known
condition (Table 5), classifies the current motion (stroke, position, feed) with
the proximity naive-Bayes rule of eq. 15-19 and loads the matching model at run
time (§2.5, "dynamic loading"). :class:`ConditionBank` does the same with any
thermbench model family and any scikit-learn classifier:

* ``fit(ds, runs)`` groups the training runs by identical declared condition
  (``metadata.runs[r].condition``), fits ``clone(model)`` per group and fits the
  classifier on the motion features of the groups' runs, one row per ``step_s``
  window of ``window_s`` (:func:`thermbench.models.motion_windows.window_features`, measuring
  cycles left out); :meth:`ConditionBank.fit_from_fitted` builds the bank from
  models already fitted and fits only the classifier.
* At (t, x) of a run the condition at t is the class of the motion window ending at
  the last ``step_s`` grid point <= t (held through stops and before the first
  motion: no condition, since a compensator cannot know the class of motion still to
  come; the axis is then taken as cold, thermal error 0, and only the geometric part
  is predicted), and the prediction is that condition's model's.

Beyond the axis motion of seed 002:

* **Operating conditions.** When the training runs' declared conditions are levels of
  operating inputs (``runs.<id>.condition: {spindle_rpm: 2500}``, a spindle test split
  into constant-speed segments) instead of a stroke/position/feed, the window feature is
  the time-weighted mean of each input over the running samples (> 0) of the window
  (:func:`thermbench.models.motion_windows.operating_window_features`), and the default
  :class:`~thermbench.models.classify.ProximityNaiveBayes` works on those columns (one factor of
  eq. 15: a speed between known speeds goes to the nearest one).
* **Readings span.** The classifier is trained only on the log from each training run's
  first reading on (a segment split with its history carries the log of earlier
  segments, at other speeds, before it); the live track at prediction runs from the
  process start.
* **Soft bank** (``blend="soft"``): instead of switching, the members are blended by the
  classifier's probabilities of the same window, prediction(t) = Σ_k P_k(t) model_k(t),
  held through stops like the label; no thermal error before the first classified window.
"""

from __future__ import annotations

from typing import Annotated, Any, Literal, Mapping, Optional

import numpy as np
import pandas as pd
from annotated_types import Ge
from pydantic import AfterValidator, model_validator
from sklearn.base import clone

from .classify import ProximityNaiveBayes, learned_features
from .motion_windows import measuring_intervals, operating_window_features, window_features
from ..data.dataset import Dataset
from .base import Inputs, ModelError, ThermalErrorModel, check_runs
from .params import Expect, Number, Params, PositiveNumber, check_params

__all__ = ["BLENDS", "ConditionBank", "condition_inputs"]


class MeanGeometric:
    """The mean of several fitted geometric-error callables (axis_mm -> µm)."""

    def __init__(self, parts):
        self.parts = list(parts)

    def __call__(self, axis_mm) -> np.ndarray:
        x = np.asarray(axis_mm, dtype=float)
        return np.mean([np.asarray(p(x), dtype=float) for p in self.parts], axis=0)


MOTION_KEYS = ("stroke_mm", "start_mm", "end_mm", "feed_mm_min")  # a seed 002 (format 1) condition
BLENDS = ("hard", "soft")


def _condition_key(ds: Dataset, run: str) -> tuple[float, float, float, float]:
    c = ds.metadata.runs[run].condition
    return (float(c.stroke_mm), float(c.start_mm), float(c.end_mm), float(c.feed_mm_min))


def _operating_key(ds: Dataset, run: str, inputs: tuple[str, ...]) -> tuple:
    lv = ds.metadata.runs[run].condition.levels()
    return tuple((c, lv.get(c)) for c in inputs)


def condition_inputs(ds: Dataset, runs, require: bool = True) -> tuple[str, ...]:
    """What the declared conditions of ``runs`` are levels of: ``()`` for the axis motion
    of seed 002 (stroke_mm, start_mm, end_mm, feed_mm_min: all four, nothing else), else
    the operating columns they name (e.g. ``("spindle_rpm",)``), in order of appearance.

    ``require``: a run without a declared condition is an error (the bank groups runs by
    it); else such runs are skipped and, when none has one, an axis dataset
    (``metadata.has_axis``) is motion and any other its declared operating inputs."""
    kinds: dict[str, list[str]] = {"motion": [], "operating": []}
    cols: list[str] = []
    for r in runs:
        c = ds.metadata.runs[r].condition
        if c is None:
            if require:
                raise ModelError(f"run {r!r} declares no condition (metadata runs.{r}.condition): the bank "
                                 "groups its training runs by their conditions")  # fmt: skip
            continue
        lv = c.levels()
        motion = [k for k in ("stroke_mm", "start_mm", "end_mm") if k in lv]
        if set(lv) == set(MOTION_KEYS):
            kinds["motion"].append(r)
        elif lv and not motion:
            kinds["operating"].append(r)
            cols += [k for k in lv if k not in cols]
        else:
            raise ModelError(f"run {r!r}: condition {lv} is neither an axis motion ({', '.join(MOTION_KEYS)}, all "
                             "four) nor levels of operating inputs only; the bank classifies one or the other")  # fmt: skip
    if kinds["motion"] and kinds["operating"]:
        raise ModelError(f"runs {kinds['motion']} declare axis-motion conditions and runs {kinds['operating']} "
                         f"operating levels ({cols}): the bank classifies one kind of condition")  # fmt: skip
    if kinds["motion"]:
        return ()
    if not cols:  # no run declares a condition (fit_from_fitted on derived groups)
        if ds.metadata.has_axis:
            return ()
        cols = list(ds.metadata.operating_inputs())
        if not cols:
            raise ModelError("the bank's runs declare no condition and the dataset no operating input "
                             "(metadata 'operating'): nothing to classify")  # fmt: skip
    absent = [c for c in cols if c not in ds.process.columns]
    if absent:
        raise ModelError(f"condition input(s) {absent} are not columns of the process log "
                         f"(columns: {list(ds.process.columns)}): the bank cannot follow them")  # fmt: skip
    return tuple(cols)


def _classifier(clf):
    if not (hasattr(clf, "fit") and hasattr(clf, "predict") and hasattr(clf, "get_params")):
        raise ValueError("not a scikit-learn classifier")
    return clf


_MODEL = "an unfitted thermbench model (ThermalErrorModel)"


class ConditionBankParams(Params):
    model: Annotated[Optional[ThermalErrorModel], Expect(_MODEL)]  # None: only for fit_from_fitted
    classifier: Annotated[Optional[Any], AfterValidator(lambda c: c if c is None else _classifier(c)),
                          Expect("None or a scikit-learn classifier (fit/predict/get_params)")]  # fmt: skip
    window_s: PositiveNumber
    step_s: PositiveNumber
    min_moving_s: Annotated[Number, Ge(0)]
    blend: Literal[BLENDS]

    @model_validator(mode="after")
    def _soft_needs_probabilities(self):
        clf = self.classifier
        if self.blend == "soft" and clf is not None and not hasattr(clf, "predict_proba"):
            raise ValueError(f"blend 'soft' needs a classifier with predict_proba; {type(clf).__name__} has none")
        return self


class _FitParams(ConditionBankParams):
    model: Annotated[ThermalErrorModel, Expect(_MODEL)]  # fit() clones it per condition


class ConditionBank(ThermalErrorModel):
    """One model per loading condition, chosen (or blended) at run time by a classifier
    (seed 002 §2.4-2.5).

    Parameters
    ----------
    model : ThermalErrorModel
        An unfitted model, cloned and fitted per condition (hydra builds it from a
        nested ``_target_``).
    classifier : scikit-learn classifier or None
        Fitted on the window features with the condition labels: for axis-motion
        conditions ``stroke_mm``, ``centre_mm`` = (start + end) / 2 and ``feed_mm_min``
        (:func:`thermbench.models.classify.learned_features`); for operating conditions the
        operating columns (e.g. ``spindle_rpm``,
        :func:`thermbench.models.motion_windows.operating_window_features`). None:
        :class:`~thermbench.models.classify.ProximityNaiveBayes` with its levels taken from
        the training conditions (seed 002 eq. 15-19); a ProximityNaiveBayes with
        ``factors`` null is given the operating columns as its factors. Its classes
        must be the bank's condition labels (a classifier with preset conditions, e.g.
        ``conf/classifier/seed002.yaml`` with labels #1..#9, is an error).
    window_s : float
        Length of the window classified (the features of (t - window_s, t]).
    step_s : float
        The classification grid: every ``step_s`` from the run's first sample.
    min_moving_s : float
        A window with less motion (outside measuring cycles) or, for operating
        conditions, less running time (input > 0) than this is a stop: the last class
        (probabilities) is held.
    blend : {"hard", "soft"}
        ``hard``: seed 002's switch, the model of the window's class (eq. 19 argmax).
        ``soft``: prediction(t) = Σ_k P_k(t) model_k(t), P the classifier's
        ``predict_proba`` of the same window (for ProximityNaiveBayes its
        ``probability``; the default, eq. 19's normalised ``score``, gives every
        condition a share, with one factor at least 1 / (2K); the sharper
        ``proximity`` and ``linear`` (interpolation between the two known levels
        around the window's value) were measured worse on fl_thermal's stepped tail
        with MLR members: what the blend gains there is mostly the averaging of
        members that extrapolate badly). Both hold through stops and predict no
        thermal error before the first classified window.

    Fitted attributes: ``models_`` (label -> fitted model), ``labels_``,
    ``classifier_``, ``group_runs_`` (label -> runs), ``condition_inputs_`` (``()``:
    axis motion; else the operating columns classified), ``geometric_`` (the mean of
    the models' geometric parts; the thermal part is the chosen model's full
    prediction minus it, so geometric + thermal is the chosen model's prediction; soft:
    Σ_k P_k (model_k - geometric_), so geometric + thermal is Σ_k P_k model_k).
    """

    params_model = ConditionBankParams

    def __init__(self, model=None, classifier=None, window_s=600.0, step_s=60.0, min_moving_s=60.0, blend="hard"):
        self.model = model
        self.classifier = classifier
        self.window_s = window_s
        self.step_s = step_s
        self.min_moving_s = min_moving_s
        self.blend = blend

    # --- fitting ------------------------------------------------------------
    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        check_params(self, _FitParams)
        inputs = condition_inputs(ds, runs)
        groups: dict[tuple, list[str]] = {}
        for r in runs:
            key = _operating_key(ds, r, inputs) if inputs else _condition_key(ds, r)
            groups.setdefault(key, []).append(r)
        models = {}
        for members in groups.values():
            label = "+".join(members)
            models[label] = clone(self.model).fit(ds, members)
        self._build(ds, models, inputs)

    def fit_from_fitted(self, dataset: Dataset, fitted: Mapping[str, ThermalErrorModel]) -> "ConditionBank":
        """The bank of already-fitted models ``fitted`` (label -> model; each model's
        ``train_runs_`` are its condition's runs); only the classifier is fitted, on
        the windows of those runs. The models are used as they are (not copied), so a
        hard and a soft bank can share the same single-condition fits."""
        for attr in [a for a in vars(self) if a.endswith("_") and not a.startswith("__")]:
            delattr(self, attr)
        check_params(self, self.params_model)
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
        inputs = condition_inputs(dataset, list(seen), require=False)
        self._build(dataset, {str(k): v for k, v in fitted.items()}, inputs)
        self.train_runs_ = list(seen)
        self.channel_ = dataset.channel  # as fit() sets it: the error channel of a format 2 dataset
        return self

    def _new_classifier(self, inputs: tuple[str, ...]):
        """A fresh classifier for the bank's kind of condition (class docstring)."""
        if self.classifier is None:
            clf = ProximityNaiveBayes()
        else:
            clf = clone(self.classifier)
        if isinstance(clf, ProximityNaiveBayes):
            if inputs and clf.factors is None:
                motion = [p for p in ("stroke_levels_mm", "position_levels_mm", "feed_levels_mm_min")
                          if getattr(clf, p) is not None]  # fmt: skip
                if motion or clf.conditions is not None:
                    key = motion[0] if motion else "conditions"
                    raise ModelError(f"config key 'classifier.{key}': set for axis-motion conditions, but the bank's "
                                     f"conditions are levels of {list(inputs)}; leave it null")  # fmt: skip
                clf.set_params(factors=list(inputs))
            elif inputs and [str(c) for c in clf.factors] != list(inputs):
                raise ModelError(f"config key 'classifier.factors': {list(clf.factors)}, but the bank's conditions "
                                 f"are levels of {list(inputs)}")  # fmt: skip
            elif not inputs and clf.factors is not None:
                raise ModelError(f"config key 'classifier.factors': {list(clf.factors)} are operating inputs, but "
                                 "the bank's conditions are axis motion (stroke, position, feed); leave it null")  # fmt: skip
        return clf

    def _build(self, ds: Dataset, models: dict[str, ThermalErrorModel], inputs: tuple[str, ...] = ()) -> None:
        rows, labels = [], []
        for label, m in models.items():
            n = 0
            for r in m.train_runs_:
                w = self._windows(ds, r, inputs=inputs, train=True)
                w = w[w["moving"]]
                rows.append(w)
                labels += [label] * len(w)
                n += len(w)
            if n == 0:
                if inputs:
                    running = " or ".join(inputs)
                    what = f"running windows (>= {self.min_moving_s} s of {running} > 0 in {self.window_s} s)"
                else:
                    what = (f"motion windows (>= {self.min_moving_s} s of motion in {self.window_s} s outside "
                            "measuring cycles)")  # fmt: skip
                raise ModelError(
                    f"condition {label!r}: its run(s) {list(m.train_runs_)} have no {what} "
                    "from their first reading on to train the classifier on"
                )
        X = self._features(pd.concat(rows, ignore_index=True), inputs)
        clf = self._new_classifier(inputs)
        if self.blend == "soft" and not hasattr(clf, "predict_proba"):
            raise ModelError(f"blend 'soft' needs a classifier with predict_proba; {type(clf).__name__} has none")
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
        self.condition_inputs_ = tuple(inputs)
        self.classifier_ = clf
        self.geometric_ = MeanGeometric([m.geometric_ for m in models.values()])

    # --- classification -----------------------------------------------------
    def _grid(self, ds: Dataset, run: str) -> np.ndarray:
        pr = ds.process_run(run)
        if pr.empty:
            raise ModelError(f"run {run!r} has no process samples")
        t0, t1 = float(pr["t_s"].iloc[0]), float(pr["t_s"].iloc[-1])
        return np.arange(t0, t1 + 1e-9, float(self.step_s))

    def _windows(
        self, ds: Dataset, run: str, grid: np.ndarray | None = None, inputs: tuple[str, ...] | None = None,
        train: bool = False,
    ) -> pd.DataFrame:  # fmt: skip
        """The window features on the run's grid. ``train``: only the log from the run's
        first reading on and the grid points there (a segment's lead-in, the history of
        earlier segments, is never trained on); today's runs, with readings from their
        start, are unchanged by it."""
        inputs = getattr(self, "condition_inputs_", ()) if inputs is None else inputs
        pr = ds.process_run(run)
        grid = self._grid(ds, run) if grid is None else grid
        er = ds.errors_run(run)
        if not inputs:
            ex = measuring_intervals(pr, er)  # from the whole log: what the compensator knows
        if train and len(er):
            t_first = float(er["t_s"].min())
            pr = pr[pr["t_s"].to_numpy() >= t_first]
            grid = grid[grid >= t_first]
        if inputs:
            w = operating_window_features(pr, grid, inputs, window_s=float(self.window_s),
                                          min_moving_s=float(self.min_moving_s))  # fmt: skip
        else:
            w = window_features(pr, grid, window_s=float(self.window_s), exclude=ex,
                                min_moving_s=float(self.min_moving_s))  # fmt: skip
        w.insert(0, "t_s", grid)
        return w

    @staticmethod
    def _features(windows: pd.DataFrame, inputs: tuple[str, ...]) -> pd.DataFrame:
        """What the classifier sees of moving windows: the motion features
        (:func:`~thermbench.models.classify.learned_features`) or the operating columns."""
        if inputs:
            return windows[list(inputs)].reset_index(drop=True)
        return learned_features(windows)

    def _classified(self, dataset: Dataset, run: str) -> tuple[pd.DataFrame, np.ndarray]:
        """The run's windows and the mask of the classified (moving) ones."""
        self._check_fitted()
        run = check_runs(dataset, run)[0]
        w = self._windows(dataset, run)
        mv = w["moving"].to_numpy()
        if not mv.any():
            if self.condition_inputs_:
                what = f"time with {' or '.join(self.condition_inputs_)} > 0"
            else:
                what = "motion outside measuring cycles"
            raise ModelError(
                f"run {run!r} has no {what} (>= {self.min_moving_s} s in a "
                f"{self.window_s} s window): the bank cannot classify its condition"
            )
        return w, mv

    def condition_track(self, dataset: Dataset, run: str) -> pd.DataFrame:
        """The classification grid of ``run``: ``t_s``, the window features, ``moving``,
        ``raw_label`` (the classifier's label of moving windows, else None) and ``label``
        (the condition used from that time on: held through stops; None before the
        first classified window — no look-ahead)."""
        w, mv = self._classified(dataset, run)
        raw = np.full(len(w), None, dtype=object)
        raw[mv] = np.asarray(self.classifier_.predict(self._features(w[mv], self.condition_inputs_)),
                             dtype=object).astype(str)  # fmt: skip
        held = pd.Series(raw, dtype=object).ffill()  # missing (None) until the first classified window
        w["raw_label"] = raw
        w["label"] = held.to_numpy()
        return w

    def probability_track(self, dataset: Dataset, run: str) -> pd.DataFrame:
        """The classification grid of ``run`` with the classifier's probabilities:
        ``t_s``, the window features, ``moving`` and one column per label (``labels_``
        order) of ``predict_proba`` of the moving windows, held through stops; NaN
        before the first classified window (no look-ahead). What a soft bank blends."""
        w, mv = self._classified(dataset, run)
        classes = [str(c) for c in self.classifier_.classes_]
        P = np.full((len(w), len(self.labels_)), np.nan)
        proba = np.asarray(self.classifier_.predict_proba(self._features(w[mv], self.condition_inputs_)), dtype=float)
        rows = np.flatnonzero(mv)
        for k, lab in enumerate(self.labels_):
            P[rows, k] = proba[:, classes.index(lab)] if lab in classes else 0.0
        held = pd.DataFrame(P, columns=self.labels_).ffill()
        for lab in self.labels_:
            w[lab] = held[lab].to_numpy()
        return w

    def _at(self, track: pd.DataFrame, t_s) -> tuple[np.ndarray, np.ndarray]:
        t = np.atleast_1d(np.asarray(t_s, dtype=float)).ravel()
        i = np.clip(np.searchsorted(track["t_s"].to_numpy(), t, side="right") - 1, 0, len(track) - 1)
        return t, i

    def conditions_at(self, dataset: Dataset, run: str, t_s) -> np.ndarray:
        """The condition label used at each time ``t_s`` of ``run`` (the label of the
        last grid point <= t; None before the first classified window)."""
        tr = self.condition_track(dataset, run)
        _, i = self._at(tr, t_s)
        return np.array([v if isinstance(v, str) else None for v in tr["label"].to_numpy()[i]], dtype=object)

    def probabilities_at(self, dataset: Dataset, run: str, t_s) -> np.ndarray:
        """(n, K) the classifier's probabilities (``labels_`` order) at each time ``t_s``
        of ``run``: those of the last grid point <= t, held through stops; all 0 before
        the first classified window (a cold machine: no thermal error)."""
        tr = self.probability_track(dataset, run)
        _, i = self._at(tr, t_s)
        P = tr[self.labels_].to_numpy(dtype=float)[i]
        return np.nan_to_num(P, nan=0.0)

    # --- prediction ---------------------------------------------------------
    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        out = np.zeros(t_s.size)  # no condition yet: a cold machine, no thermal error
        if getattr(self, "blend", "hard") == "soft":
            P = self.probabilities_at(ds, run, t_s)
            for k, lab in enumerate(self.labels_):
                m = P[:, k] > 0
                if m.any():
                    full = self.models_[lab].predict_at(ds, run, t_s[m], axis_mm[m])
                    out[m] += P[m, k] * (full - self.geometric_(axis_mm[m]))
            return out
        labels = self.conditions_at(ds, run, t_s)
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
        inputs = tuple(getattr(self, "condition_inputs_", ()))
        operating += [c for c in inputs if c not in operating]
        motion = not inputs or any(m.required_inputs().motion for m in self.models_.values())
        return Inputs(sensors=tuple(sensors), motion=motion, ambient=ambient, operating=tuple(operating))
