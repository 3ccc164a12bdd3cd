"""Which runs a model is fitted on and scored on, and the data as it saw them: one module the
jobs (:mod:`thermbench.experiment`), the benchmark, the export and the replay share.

* a dataset config (``conf/dataset`` option or a dataset directory, :func:`dataset_option`)
  loaded into a :class:`Split`: its loading states and validation runs (:func:`load_split`);
* the view a model sees of a format 2 dataset: one error channel, the runs split into derived
  segments, with or without each segment's history (:func:`model_view`, checked against the
  config by :func:`dataset_view`; :func:`thermbench.export.replay.replay_view` replays through it);
* cross-validation over runs. Thermal data are time series: a fold never splits a
  run, it holds whole runs out (scikit-learn's group splitters with the run as the group):

  - ``loro``: each run held out once (:class:`sklearn.model_selection.LeaveOneGroupOut`); the
    default for a dataset whose loading states are its runs (no declared validation runs);
  - ``group_kfold``: ``k`` folds of whole runs (:class:`sklearn.model_selection.GroupKFold`);
  - ``declared``: the dataset's own split, its loading states against its validation runs
    (``dataset.validation``: fl_thermal's stepped tail), one fold.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.model_selection import GroupKFold, LeaveOneGroupOut

from ..config import check_targets, config_dir, group_option
from ..errors import ExperimentError


def dataset_option(entry: str, key: str) -> tuple[str | None, dict]:
    """The dataset config an entry names, and its option name: a ``conf/dataset`` option by name,
    or a dataset directory (one holding ``metadata.yaml``), read through the ``path`` option and
    named by its ``machine.name`` (None here). A name that is an option is the option unless it is
    written as a path (``./fl_thermal``). A mistake is one line naming ``key``."""
    names = sorted(p.stem for p in (config_dir() / "dataset").glob("*.yaml"))
    entry = str(entry)
    path = Path(entry)
    if entry in names and "/" not in entry and path.name == entry:
        cfg = group_option("dataset", entry)
        if str((cfg.get("source") or {}).get("path")) == "???":  # the `path` option itself: a directory is wanted
            raise ExperimentError(f"config key '{key}': option {entry!r} reads a dataset directory: give the "
                                  f"directory itself, e.g. {key}=[data/my_axis]")  # fmt: skip
        return entry, cfg
    if not (path / "metadata.yaml").is_file():
        what = "no such directory" if not path.exists() else "no metadata.yaml in it"
        near = difflib.get_close_matches(entry, names, n=1)
        hint = f"; did you mean {near[0]!r}?" if near else ""
        raise ExperimentError(f"config key '{key}': {entry!r} is neither a dataset option ({', '.join(names)}) nor a "
                              f"dataset directory ({what}; a lab's files come in with thermbench import){hint}")  # fmt: skip
    cfg = group_option("dataset", "path")
    cfg["source"] = {**cfg["source"], "path": str(path)}
    return None, cfg


@dataclass
class Split:
    """A loaded dataset with its loading states (trainable) and validation runs (never trained on)."""

    name: str
    dataset: Any
    states: list[str]
    validation: list[str]
    own: bool = False  # loaded from a directory (dataset=path), not a shipped benchmark dataset
    history: bool = False  # dataset.history: segments keep their run's log from the start

    def registry_name(self, model_name: str) -> str:
        """The registered-model name of ``model_name`` fitted on this dataset: never shared by
        models of different datasets (an own dataset's content hash is part of it) or of
        different error channels."""
        parts = ["thermbench", self.name]
        if self.dataset.channel is not None:  # a format 2 channel view
            parts.append(self.dataset.channel)
        if self.own:
            parts.append(self.dataset.content_hash()[:8])
        return "-".join([*parts, model_name])

    def kind(self, run: str) -> str:
        return "validation" if run in self.validation else "state"

    @property
    def label(self) -> str:
        """The dataset's name as the MLflow runs give it (their dataset input): the name, with
        ``-<channel>`` for one error channel of a format 2 dataset (as the benchmark's cases)."""
        channel = self.dataset.channel
        return self.name if channel is None else f"{self.name}-{channel}"


def load_source(dcfg: Mapping):
    """The dataset ``dataset.source`` loads (instantiated), as stored, and the source config."""
    if "source" not in dcfg:
        raise ExperimentError("config key 'dataset.source': expected a loader with _target_")
    source = OmegaConf.to_container(dcfg["source"], resolve=True) if OmegaConf.is_config(dcfg["source"]) else dcfg["source"]
    if not (isinstance(source, Mapping) and source.get("_target_")):
        raise ExperimentError(f"config key 'dataset.source': expected a loader with _target_, got {source!r}")
    check_targets(source, "dataset.source")
    try:
        ds = instantiate(source, _convert_="all")
    except InstantiationException as exc:  # hydra wraps the loader's own (clear) error
        from ..errors import user_errors

        cause = exc.__cause__
        if not isinstance(cause, user_errors()):  # a bug in the loader: its traceback
            raise
        msg = str(cause)  # a dataset, file or config mistake: one line naming it
        raise ExperimentError(msg if msg.startswith("config key") else f"config key 'dataset.source': {msg}") from None
    return ds, source


def load_split(dcfg: Mapping) -> Split:
    """Load ``dataset.source`` (instantiate), take the view the models see (:func:`dataset_view`)
    and check ``dataset.states`` / ``dataset.validation``."""
    dcfg = dict(dcfg)
    ds, source = load_source(dcfg)
    ds = dataset_view(ds, dcfg.get("channel"), dcfg.get("segments", True), dcfg.get("history", False))
    runs = list(ds.run_ids)
    validation = list(dcfg.get("validation") or [])
    scored = set(ds.errors["run_id"]) if len(ds.errors) else set()  # runs without readings: prediction only
    states = list(dcfg.get("states") or [r for r in runs if r not in validation and r in scored])
    for key, lst in (("states", states), ("validation", validation)):
        unknown = [r for r in lst if r not in runs]
        if unknown:
            raise ExperimentError(f"config key 'dataset.{key}': runs {unknown} are not in the dataset; its runs: {runs}")
    both = sorted(set(states) & set(validation))
    if both:
        raise ExperimentError(f"config keys 'dataset.states' and 'dataset.validation' share runs {both}")
    own = str(source.get("_target_")) == "thermbench.data.io.load_dataset"
    return Split(str(dcfg.get("name") or ds.metadata.machine.name), ds, states, validation, own=own,
                 history=bool(dcfg.get("history", False)) and ds.metadata.version == 2)  # fmt: skip


def dataset_view(ds, channel, segments=True, history=False):
    """What the models see of a format 2 dataset (:mod:`thermbench.data.views`): its runs
    split into derived segments (``dataset.segments``) and one error channel
    (``dataset.channel``; null: the only one). ``dataset.history``: each segment keeps the
    log of its run from the start and the whole run's thermal error (temperature rises and
    thermal errors count from the start of the test, as a compensator running since power-on
    sees them); false: each segment counts from its own start. A format 1 dataset is used
    as it is."""
    meta = ds.metadata
    if meta.version == 1:
        if channel is not None and channel not in meta.error_channels():
            raise ExperimentError(f"config key 'dataset.channel': a format 1 dataset has one channel "
                                  f"({next(iter(meta.error_channels()))!r}); leave it null")  # fmt: skip
        return ds
    for key, v in (("segments", segments), ("history", history)):
        if not isinstance(v, bool):
            raise ExperimentError(f"config key 'dataset.{key}': expected true or false, got {v!r}")
    if history and not segments:
        raise ExperimentError("config key 'dataset.history': true needs dataset.segments=true (the history is "
                              "the log before each segment)")  # fmt: skip
    channels = sorted(meta.error_channels())
    if channel is None:
        if len(channels) != 1:
            listed = ",".join(channels) if channels else "(none)"
            raise ExperimentError(f"config key 'dataset.channel': the dataset has {len(channels)} error channels "
                                  f"({listed}); name one, or sweep them: -m dataset.channel={listed}")  # fmt: skip
        channel = channels[0]
    if channel not in channels:
        near = difflib.get_close_matches(str(channel), channels, n=1)
        hint = f"; did you mean {near[0]!r}?" if near else ""
        raise ExperimentError(f"config key 'dataset.channel': no channel {channel!r}; channels: {channels}{hint}")
    return model_view(ds, channel, segments, history)


def model_view(ds, channel: str | None, segments: bool = True, history: bool = False):
    """The data a model sees of format 2 dataset ``ds`` (the config checked by :func:`dataset_view`):
    error ``channel`` (None: the dataset as it is, a log to predict on), the runs split into their
    derived segments (``segments``), each keeping the log of its run from the start and the whole
    run's thermal error (``history``: the thermal error of the whole run first, then the segments
    with their past)."""
    from ..data.views import channel_view, split_segments

    if channel is None:
        return split_segments(ds) if segments else ds
    if history:
        return split_segments(channel_view(ds, channel), history=True)
    if segments:
        ds = split_segments(ds)
    return channel_view(ds, channel)


def dataset_config_for(model, dcfg, key: str = "dataset.channel") -> dict:
    """``dcfg`` with the error channel ``model`` was fitted on (``channel_``) when none is given;
    a different one is one line: scoring a Z model on Y compares unlike quantities."""
    d = OmegaConf.to_container(dcfg, resolve=True) if OmegaConf.is_config(dcfg) else dict(dcfg)
    fitted = getattr(model, "channel_", None)
    if fitted is None:
        return d
    if d.get("channel") is None:
        d["channel"] = fitted
    elif d["channel"] != fitted:
        raise ExperimentError(f"config key {key!r}: the model predicts error channel {fitted!r} (it was fitted on "
                              f"it), not {d['channel']!r}; leave the key out to score it on {fitted!r}")  # fmt: skip
    return d


def resolve_runs(spec, split: Split, key: str) -> list[str]:
    """``all`` = every loading state; ``a+b`` or a list = those runs; null = every run with
    readings (a format 2 run without readings is for prediction and replay only)."""
    with_readings = set(split.dataset.errors["run_id"]) if len(split.dataset.errors) else set()
    if spec is None:
        runs = [r for r in split.dataset.run_ids if r in with_readings]
        if not runs:
            raise ExperimentError(f"config key '{key}': no run of dataset {split.name!r} has readings to score")
        return runs
    if isinstance(spec, str):
        spec = split.states if spec == "all" else [s for s in spec.split("+") if s]
    runs = [str(r) for r in spec]
    unknown = [r for r in runs if r not in split.dataset.run_ids]
    if unknown or not runs:
        raise ExperimentError(
            f"config key '{key}': runs {unknown or runs} not in dataset {split.name!r}; "
            f"its loading states: {split.states}, validation runs: {split.validation}, or 'all'"
        )
    bare = [r for r in runs if r not in with_readings]
    if bare:
        raise ExperimentError(f"config key '{key}': runs {bare} of dataset {split.name!r} have no readings "
                              "(prediction and replay only): nothing to fit or score there")  # fmt: skip
    return runs


# ------------------------------------------------- cross-validation over runs ---
CV_KINDS = ("loro", "group_kfold", "declared")


@dataclass(frozen=True)
class Fold:
    """One fold: its name (the held-out run; ``fold 3 of 5`` when it holds out several, whose runs
    the report lists once), the runs it trains on and the runs it holds out."""

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
    splits = list(splitter.split(idx, groups=idx))
    for i, (train, test) in enumerate(splits, 1):
        held = tuple(runs[j] for j in sorted(test))
        name = held[0] if len(held) == 1 else f"fold {i} of {len(splits)}"
        out.append(Fold(name, tuple(runs[j] for j in sorted(train)), held))
    return out


def outer_folds(split: "Split", cv: str | None, k: int = 5) -> tuple[str, list[Fold], list[Fold]]:
    """``cv`` resolved (:func:`resolve_cv`), its folds over the split's runs with readings (none for
    ``declared``: the loading states are fitted once and every run is scored) and the outer folds a
    choice is made for and scored on: the folds, or for ``declared`` the loading states against the
    validation runs (none when the dataset declares no validation runs)."""
    ds = split.dataset
    cv = resolve_cv(cv, split.validation)
    scored = set(ds.errors["run_id"]) if len(ds.errors) else set()
    cv_folds = [] if cv == "declared" else folds([r for r in ds.run_ids if r in scored], split.validation, cv, k)
    outer = cv_folds or ([Fold("+".join(split.validation), tuple(split.states), tuple(split.validation))]
                         if split.validation else [])  # fmt: skip
    return cv, cv_folds, outer


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


#: one run only: validation on this many contiguous blocks of it (a time series is never shuffled)
SINGLE_RUN_BLOCKS = 5


def row_folds(run_of_row: Sequence[str]) -> list[tuple[np.ndarray, np.ndarray]]:
    """The validation folds of a model's own tuning, as (train rows, held-out rows) index pairs
    over rows whose runs are ``run_of_row``: whole runs held out, as :func:`inner_folds` holds them
    (each run once up to :data:`INNER_LORO_MAX_RUNS` runs, else :data:`INNER_FOLDS` folds of
    runs); a single run: :data:`SINGLE_RUN_BLOCKS` contiguous blocks of it, each held out once.
    Never rows of a run the fold trains on."""
    groups = np.asarray(run_of_row).astype(str)  # run ids, or any labels of them (indices)
    runs = list(dict.fromkeys(groups.tolist()))
    if len(runs) == 1:  # one run: consecutive parts of it
        block = np.minimum((np.arange(groups.size) * SINGLE_RUN_BLOCKS) // max(groups.size, 1), SINGLE_RUN_BLOCKS - 1)
        return [(np.flatnonzero(block != b), np.flatnonzero(block == b)) for b in np.unique(block)]
    return [(np.flatnonzero(np.isin(groups, f.train)), np.flatnonzero(np.isin(groups, f.held_out)))
            for f in inner_folds(runs)]  # fmt: skip


# --------------------------------------------- a thermbench model as a scikit-learn regressor ---
class DatasetRef:
    """A dataset held by reference in an estimator's parameters: :func:`sklearn.base.clone` deep-copies
    every parameter that is not an estimator, and a copy of a 46 h log per fold and candidate is
    what this avoids (a copy of the reference is the reference itself)."""

    def __init__(self, dataset) -> None:
        self.dataset = dataset

    def __deepcopy__(self, memo) -> "DatasetRef":
        return self

    def __repr__(self) -> str:
        return f"DatasetRef({getattr(self.dataset.metadata.machine, 'name', '?')!r})"


def run_rows(ds, runs: Sequence[str]):
    """The readings of ``runs`` as scikit-learn's ``X, y, groups``: ``X`` a frame of ``run_id`` and
    ``row`` (the reading's place in its run, as the run's predictions come: the reference frame
    of :func:`thermbench.data.reference.thermal_errors`), ``y`` the measured error (µm) there,
    ``groups`` the run ids (what a group splitter holds out whole)."""
    import pandas as pd

    from ..data.reference import thermal_errors

    te = thermal_errors(ds)
    parts = [te.loc[te["run_id"] == r, ["run_id", "error_um"]].assign(row=np.arange(int((te["run_id"] == r).sum())))
             for r in runs]  # fmt: skip
    rows = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(columns=["run_id", "error_um", "row"])
    return rows[["run_id", "row"]], rows["error_um"].to_numpy(dtype=float), rows["run_id"].to_numpy()


class RunsRegressor(RegressorMixin, BaseEstimator):
    """A thermbench model (``model``: a :class:`~thermbench.models.base.ThermalErrorModel`) as a
    scikit-learn regressor over readings (:func:`run_rows`), so scikit-learn's group splitters,
    ``cross_val_predict``, ``cross_validate`` and ``GridSearchCV`` drive it over whole runs:
    ``fit(X, y)`` fits a clone of ``model`` on the runs ``X`` names (``y`` is not read: the model
    reads its dataset), ``predict(X)`` predicts each reading from its run's log. ``dataset``: a
    :class:`DatasetRef` (a plain dataset is wrapped), never copied by ``clone``. Its score is R²
    (scikit-learn's default); pass ``scoring="neg_root_mean_squared_error"`` for the RMSE.

        X, y, groups = run_rows(ds, ds.run_ids)
        search = GridSearchCV(RunsRegressor(model, DatasetRef(ds)), {"model__lags_s": [[], [1800]]},
                              cv=LeaveOneGroupOut(), scoring="neg_root_mean_squared_error")
        search.fit(X, y, groups=groups)
    """

    def __init__(self, model=None, dataset=None):
        self.model = model
        self.dataset = dataset

    def _ds(self):
        return self.dataset.dataset if isinstance(self.dataset, DatasetRef) else self.dataset

    def fit(self, X, y=None):
        from sklearn.base import clone

        runs = list(dict.fromkeys(X["run_id"]))
        self.model_ = clone(self.model).fit(self._ds(), runs)
        self.runs_ = runs
        return self

    def predict(self, X):
        from sklearn.utils.validation import check_is_fitted

        check_is_fitted(self, "model_")
        out = np.empty(len(X))
        rows = X["row"].to_numpy()
        for run, idx in X.groupby("run_id", sort=False).indices.items():
            out[idx] = np.asarray(self.model_.predict(self._ds(), run), dtype=float)[rows[idx]]
        return out
