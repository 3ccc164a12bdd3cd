"""Plain experiment functions; the CLI and the Hydra jobs (:mod:`thermbench.app`) are thin layers over these.

* :func:`train` — fit one model (``conf/model``) on some loading states of a dataset
  (``conf/dataset``), score it on every run, track everything in MLflow, register the model.
* :func:`evaluate` — score a registered/logged model on a dataset.
* the robustness comparison is :func:`thermbench.benchmark.benchmark`.
* :func:`export` — a registered model (``models:/<name>@<alias>``) to a model file.

Each takes the composed config (a ``DictConfig``) and returns a :class:`JobResult`.
:func:`cross_condition` and :func:`fit_evaluate` are the building blocks tests call directly.
"""

from __future__ import annotations

import difflib
import json
import logging
import sys
import tempfile
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Sequence

import joblib
import numpy as np
import pandas as pd
import yaml
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from sklearn.base import clone

from . import tracking
from ._atomic import write_text_atomic
from .config import config_dir
from .metrics import evaluate as evaluate_runs
from .models.base import FallbackWarning, n_workers, show_fit_progress, thread_budget, threads_per_worker
from .outputs import output_dir

LOG = logging.getLogger(__name__)


#: the metrics a job's terminal summary and a sweep's summary table show
#: the metrics a job's summary and a sweep's table show: the held-out RMSE (on the validation runs) first
HEADLINE = ("validation_mean_rmse_um", "validation_worst_compensation_rate", "validation_max_abs_residual_um", "unseen_worst_compensation_rate",
            "unseen_max_abs_residual_um", "own_mean_rmse_um", "fit_s")


def hydra_runtime():
    """The running Hydra job's config (``HydraConfig``), or None outside ``hydra.main``."""
    try:
        from hydra.core.hydra_config import HydraConfig

        hc = HydraConfig.get()
        hc.runtime.output_dir  # noqa: B018 -- a config left behind by an earlier in-process Hydra call has none
        return hc
    except Exception:
        return None


def job_threads(hc=None, cores: int | None = None) -> int:
    """The threads (per OpenMP and BLAS thread pool) this job may use: the cores it sees
    (``cores``; default :func:`joblib.cpu_count`, which honours CPU affinity and a cgroup quota)
    shared with the jobs a Hydra multirun runs beside it on this machine
    (``hydra/launcher=joblib``: ``hydra.launcher.n_jobs`` at once), and at most the launcher's
    ``cpus_per_task`` (submitit) when it sets one. ``hc``: the Hydra config (default: the
    running job's, :func:`hydra_runtime`); outside Hydra every core."""
    if cores is None:
        cores = joblib.cpu_count()
    cores = max(1, int(cores))
    hc = hydra_runtime() if hc is None else hc
    launcher = OmegaConf.select(hc, "launcher", default=None) if hc is not None else None
    if launcher is None:
        return cores
    mode = OmegaConf.select(hc, "mode", default=None)
    multirun = getattr(mode, "name", str(mode).rsplit(".", 1)[-1]) == "MULTIRUN"
    if multirun and str(launcher.get("_target_", "")).endswith(".JoblibLauncher"):
        cores = threads_per_worker(cores, int(launcher.get("n_jobs") or -1))
    per_task = launcher.get("cpus_per_task")
    if multirun and isinstance(per_task, int) and not isinstance(per_task, bool) and per_task > 0:
        cores = min(cores, per_task)
    return cores


def worker_threads(n_jobs: int, n_tasks: int, cores: int | None = None) -> int:
    """The threads each of ``n_jobs`` parallel workers may use (per OpenMP and BLAS thread
    pool): the job's cores (:func:`job_threads`, or ``cores``) shared by the workers that run
    at once (at most one per task), so workers x threads never exceeds them. ``n_jobs`` counts
    as joblib counts it (-1: one worker per core, -2: all but one, ...)."""
    cores = job_threads() if cores is None else int(cores)
    return threads_per_worker(cores, min(n_workers(n_jobs), max(1, n_tasks)))


def _call_limited(fn, threads: int, args: tuple, kwargs: Mapping):
    """``fn(*args, **kwargs)`` with every fit (and whatever else runs there) on ``threads`` threads."""
    with thread_budget(threads):
        return fn(*args, **kwargs)


def run_workers(fn, calls: Sequence[tuple[tuple, Mapping]], n_jobs: int, ordered: bool = True):
    """``fn(*args, **kwargs)`` for each ``(args, kwargs)`` of ``calls``, each on its worker's
    share of the cores (:func:`worker_threads`): one after the other in this process for
    ``n_jobs=1`` (lazily), else in ``n_jobs`` joblib workers, results in the calls' order
    (``ordered``) or as they finish. Where every job that fits models in parallel dispatches them."""
    calls = list(calls)
    threads = worker_threads(n_jobs, len(calls))
    if n_jobs == 1:
        return (_call_limited(fn, threads, a, k) for a, k in calls)
    how = "generator" if ordered else "generator_unordered"
    work = (joblib.delayed(_call_limited)(fn, threads, a, k) for a, k in calls)
    return joblib.Parallel(n_jobs=n_jobs, return_as=how)(work)


class ExperimentError(ValueError):
    """A user mistake in an experiment config; the message names the key."""


@dataclass
class JobResult:
    """What a job hands back: the terminal table, headline metrics, where things went."""

    job: str
    table: pd.DataFrame
    metrics: dict[str, float] = field(default_factory=dict)
    skipped: bool = False
    mlflow_run_id: str | None = None
    outputs: dict[str, str] = field(default_factory=dict)

    def to_json(self) -> str:
        return json.dumps(
            {
                "job": self.job,
                "skipped": self.skipped,
                "mlflow_run_id": self.mlflow_run_id,
                "metrics": self.metrics,
                "outputs": self.outputs,
                "table": json.loads(self.table.to_json(orient="records")),
            },
            indent=1,
        )


# ----------------------------------------------------------------- config ---
def model_from_config(name_or_cfg) -> object:
    """A model from ``conf/model/<name>.yaml`` (or a config mapping with ``_target_``)."""
    if isinstance(name_or_cfg, str):
        path = config_dir() / "model" / f"{name_or_cfg}.yaml"
        if not path.exists():
            known = sorted(p.stem for p in (config_dir() / "model").glob("*.yaml"))
            raise ExperimentError(f"model {name_or_cfg!r}: no {path}; known models: {known}")
        name_or_cfg = OmegaConf.load(path)
    return instantiate(name_or_cfg, _convert_="all")


def group_option(group: str, name: str) -> dict:
    """The plain config of option ``name`` of group ``group`` (``conf/<group>/<name>.yaml``)."""
    path = config_dir() / group / f"{name}.yaml"
    if not path.exists():
        known = sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))
        raise ExperimentError(f"config key '{group}': no option {name!r}; known: {known}")
    return OmegaConf.to_container(OmegaConf.load(path), resolve=True)


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


def choice(cfg: DictConfig, group: str, default: str = "custom") -> str:
    """The option picked for ``group`` (``hydra.runtime.choices``), as ``model=lssvm`` names it."""
    hc = hydra_runtime()
    if hc is not None and group in hc.runtime.choices:
        return str(hc.runtime.choices[group])
    node = OmegaConf.select(cfg, f"hydra.runtime.choices.{group}", default=None)
    return str(node) if node is not None else default


def plain(cfg: DictConfig | Mapping) -> dict:
    """The resolved config as plain data, without the ``hydra`` node."""
    if isinstance(cfg, DictConfig):
        return {
            str(k): OmegaConf.to_container(cfg[k], resolve=True) if OmegaConf.is_config(cfg[k]) else cfg[k]
            for k in cfg
            if k != "hydra"
        }
    return {k: v for k, v in dict(cfg).items() if k != "hydra"}


def _parameters(target) -> list[str] | None:
    """The keyword parameters ``target`` (a class or function) takes; None when it takes any
    (``**kwargs``) or its signature cannot be read."""
    import inspect

    try:
        sig = inspect.signature(target)
    except (TypeError, ValueError):
        return None
    if any(p.kind is inspect.Parameter.VAR_KEYWORD for p in sig.parameters.values()):
        return None
    return [n for n, p in sig.parameters.items() if p.kind in (p.POSITIONAL_OR_KEYWORD, p.KEYWORD_ONLY)]


def check_targets(node, key: str) -> None:
    """Every ``_target_`` in the config ``node`` (at config key ``key``) can be imported and
    takes the keys given with it, checked before anything is instantiated: a typo such as
    ``+model.bogus=1`` is an :class:`ExperimentError` naming the key and the parameters
    there are, not Hydra's ``TypeError`` traceback from inside the constructor."""
    import difflib

    from hydra._internal.utils import _locate  # what instantiate() uses, without its error log

    if isinstance(node, Mapping):
        target = node.get("_target_")
        if target is not None:
            try:
                obj = _locate(str(target))
            except Exception as exc:
                why = exc.__cause__ or exc
                raise ExperimentError(f"config key '{key}._target_': cannot import {target!r}: {why}") from None
            names = _parameters(obj)
            given = [str(k) for k in node if not (str(k).startswith("_") and str(k).endswith("_"))]
            bad = [k for k in given if names is not None and k not in names]
            if bad:
                owner = getattr(obj, "__name__", str(target))
                near = difflib.get_close_matches(bad[0], names, n=1)
                hint = f" (did you mean {near[0]!r}?)" if near else ""
                raise ExperimentError(f"config key '{key}.{bad[0]}': {owner} has no parameter {bad[0]!r}{hint}; "
                                      f"its parameters: {', '.join(names)}")  # fmt: skip
        for k, v in node.items():
            if not str(k).startswith("_"):
                check_targets(v, f"{key}.{k}")
    elif isinstance(node, (list, tuple)):
        for i, v in enumerate(node):
            check_targets(v, f"{key}[{i}]")


def build_model(model_cfg: Mapping, preprocess_steps=None, seed: int | None = None, key: str = "model"):
    """Instantiate a model config; ``preprocess_steps`` (a list of filter configs) replaces
    the model's own preprocessing when not None; ``seed`` goes to models that take one.
    ``key``: where the model config sits in the job's config (named in a mistake's message)."""
    model_cfg = OmegaConf.to_container(model_cfg, resolve=True) if OmegaConf.is_config(model_cfg) else dict(model_cfg)
    check_targets(model_cfg, key)
    if preprocess_steps is not None:
        check_targets(list(preprocess_steps), "preprocess.steps")
    model = instantiate(model_cfg, _convert_="all")
    params = model.get_params(deep=True)  # deep: the models inside a bank get them too

    def keys(name: str) -> list[str]:
        return [k for k in params if k == name or k.endswith(f"__{name}")]

    if preprocess_steps is not None:
        for k in keys("preprocess"):
            model.set_params(**{k: [instantiate(s) for s in preprocess_steps]})
    if seed is not None:
        model.set_params(**{k: int(seed) for k in keys("seed")})
    return model


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
        from .errors import user_errors

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
    from .data.views import channel_view, split_segments

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
    if history:  # the thermal error of the whole run first, then the segments with their past
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


# ------------------------------------------------------- fit and evaluate ---
def describe_inputs(inp) -> str:
    """One line: the sensors, operating inputs and motion a fitted model reads."""
    parts = [f"sensors {', '.join(inp.sensors)}" if inp.sensors else "no temperature sensors"]
    if inp.operating:
        parts.append(f"operating inputs {', '.join(inp.operating)}")
    if inp.motion:
        parts.append("the motion log (axis position, feed)")
    if inp.ambient:
        parts.append("an ambient sensor")
    return "; ".join(parts)


def fit_evaluate(model, dataset, train_runs: Sequence[str], eval_runs: Sequence[str] | None = None, curves: bool = False):
    """Fit ``clone(model)`` on ``train_runs``; return the fitted model, one metrics row per
    evaluated run (``own`` marks training runs, ``fit_s`` the fitting time) and, with
    ``curves=True``, the per-cycle before/after table."""
    m = clone(model)
    t0 = time.perf_counter()
    m.fit(dataset, list(train_runs))
    fit_s = time.perf_counter() - t0
    out = evaluate_runs(m, dataset, eval_runs, curves=curves)
    res, cur = out if curves else (out, None)
    res.insert(1, "own", res["run_id"].isin(list(train_runs)))
    res["train"] = "+".join(train_runs)
    res["fit_s"] = fit_s
    return m, res, cur


def cross_condition(model, dataset, train_runs: Sequence[str], eval_runs: Sequence[str] | None = None) -> pd.DataFrame:
    """Fit ``clone(model)`` on ``train_runs``; one metrics row per evaluated run,
    with ``own`` marking the training runs and ``fit_s`` the fitting time."""
    return fit_evaluate(model, dataset, train_runs, eval_runs)[1]


def headline_metrics(rows: pd.DataFrame, validation: Sequence[str] = ()) -> dict[str, float]:
    """Own-run, unseen-run and validation-run aggregates of one fitted model's rows."""
    out: dict[str, float] = {}
    groups = {"own": rows[rows["own"]], "unseen": rows[~rows["own"]], "validation": rows[rows["run_id"].isin(list(validation))]}
    for name, g in groups.items():
        if g.empty:
            continue
        out[f"{name}_mean_rmse_um"] = float(g["rmse_um"].mean())
        out[f"{name}_max_abs_residual_um"] = float(g["max_abs_residual_um"].max())
        out[f"{name}_worst_compensation_rate"] = float(g["compensation_rate"].min())
        out[f"{name}_mean_compensation_rate"] = float(g["compensation_rate"].mean())
    if "fit_s" in rows:
        out["fit_s"] = float(rows["fit_s"].iloc[0])
    return out


def model_flags(rows: pd.DataFrame) -> list[str]:
    """What disqualifies one fitted model (its metrics rows, ``own`` marking its training runs)
    from being registered or chosen: a non-finite score on any run, or an error made worse
    than no compensation on its own training runs taken together: the largest residual over
    them above the largest thermal error over them (a compensation rate < 0 over the training
    runs as one). A model trained on several runs is not flagged for one run whose drift is
    small (the first block of a test) as long as it compensates its training data as a whole."""
    flags = []
    score = rows[[c for c in ("rmse_um", "max_abs_residual_um") if c in rows]].to_numpy(dtype=float)
    bad = rows.loc[~np.isfinite(score).all(axis=1), "run_id"].tolist()
    if bad:
        flags.append(f"non-finite score on run(s) {bad}")
    if "own" not in rows:
        return flags
    own = rows[rows["own"].astype(bool)]
    if own.empty:
        return flags
    resid = own["max_abs_residual_um"].to_numpy(dtype=float)
    if "max_abs_error_um" in own:
        error = own["max_abs_error_um"].to_numpy(dtype=float)
    else:  # from the rate: 1 - resid / error
        error = resid / (1.0 - own["compensation_rate"].to_numpy(dtype=float))
    rate = 1.0 - float(np.max(resid)) / float(np.max(error)) if np.max(error) > 0 else float("nan")
    if rate < 0:
        runs = own["run_id"].tolist()
        where = f"on {runs[0]}" if len(runs) == 1 else "over them taken together"
        flags.append(f"worse than no compensation on its own training run(s) {runs} (rate {100 * rate:.1f} % {where})")
    return flags


def _per_run_metrics(rows: pd.DataFrame) -> dict[str, float]:
    keys = ("rmse_um", "max_abs_residual_um", "compensation_rate", "residual_fraction_of_pv")
    return {f"runs/{r['run_id']}/{k}": float(r[k]) for _, r in rows.iterrows() for k in keys if pd.notna(r[k])}


def _output_dir() -> Path | None:
    hc = hydra_runtime()
    return Path(hc.runtime.output_dir) if hc is not None else None


def _finish(result: JobResult) -> JobResult:
    out = _output_dir()
    if out is not None:
        write_text_atomic(out / "result.json", result.to_json())
    return result


def _skip(job: str, run) -> JobResult:
    """The result of a job already finished with the same config hash (from its MLflow run)."""
    table = pd.DataFrame([{k: v for k, v in run.data.metrics.items() if k in HEADLINE}])
    print(f"[{job}] skipped: MLflow run {run.info.run_id} already finished with the same config hash "
          f"(tracking.skip_finished=false reruns it)")
    return _finish(JobResult(job, table, dict(run.data.metrics), skipped=True, mlflow_run_id=run.info.run_id))


def _table(rows: pd.DataFrame, split: Split) -> pd.DataFrame:
    t = rows[["run_id", "own", "rmse_um", "max_abs_residual_um", "max_abs_error_um", "compensation_rate"]].copy()
    t.insert(1, "kind", [split.kind(r) for r in t["run_id"]])
    return t


# -------------------------------------------------------------------- jobs ---
def _log_scores(rows: pd.DataFrame, curves: pd.DataFrame, split: Split, family: str, approach: str, title: str) -> dict:
    """Log a scored model to the active MLflow run: headline and per-run metrics,
    ``results.csv`` and the before/after figure; return the headline metrics."""
    import mlflow

    from .report import curves_figure

    metrics = headline_metrics(rows, split.validation)
    mlflow.log_metrics(metrics | _per_run_metrics(rows))
    mlflow.log_text(rows.to_csv(index=False), "results.csv")
    with tempfile.TemporaryDirectory() as tmp:
        cur = curves.assign(family=family, approach=approach)
        png = curves_figure(cur, list(dict.fromkeys(cur["run_id"])), title, Path(tmp) / "before_after.png")
        mlflow.log_artifact(str(png))
    return metrics


def train(cfg: DictConfig) -> JobResult:
    """Fit ``cfg.model`` on ``cfg.train`` of ``cfg.dataset``, score every run, track and register it."""
    import mlflow

    exp_id = tracking.connect(cfg.tracking)  # fails fast on an unreachable server
    conf = plain(cfg)
    split = load_split(cfg.dataset)
    data_hash = split.dataset.content_hash()
    h = tracking.config_hash(conf | {"dataset_content": data_hash})  # re-measured files are a new job
    if cfg.tracking.get("skip_finished", True) and (done := tracking.finished_run(exp_id, h)) is not None:
        return _skip("train", done)
    model_name = choice(cfg, "model")
    train_runs = resolve_runs(cfg.train, split, "train")
    eval_runs = resolve_runs(cfg.get("eval"), split, "eval")
    steps = OmegaConf.to_container(cfg.preprocess.steps, resolve=True) if cfg.get("preprocess") and cfg.preprocess.get("steps") is not None else None
    model = build_model(conf["model"], steps, cfg.get("seed"))
    run_name = f"{model_name} | {split.name} | {'+'.join(train_runs)}"
    tracking.close_interrupted(exp_id, h)  # an earlier attempt of this job killed mid-run: closed, not left RUNNING
    with mlflow.start_run(experiment_id=exp_id, run_name=run_name) as run:
        mlflow.set_tags(tracking.standard_tags(data_hash, h, "train") | {"model": model_name, "dataset": split.name})
        tracking.log_config(conf)
        tracking.log_dataset(split.dataset, split.label, "training", digest=data_hash)
        # the job's share of the cores (a multirun's parallel jobs share them): every family runs with it
        # a fit longer than 10 s (an LSSVM's swarm, a network's epochs) shows its progress on a terminal
        with warnings.catch_warnings(record=True) as caught, thread_budget(job_threads()), show_fit_progress():
            warnings.simplefilter("always", FallbackWarning)
            fitted, rows, curves = fit_evaluate(model, split.dataset, train_runs, eval_runs, curves=True)
        for w in dict.fromkeys(str(w.message) for w in caught if issubclass(w.category, FallbackWarning)):
            print(f"[train] warning: {model_name}: {w}", file=sys.stderr, flush=True)
        print(f"[train] {model_name} uses {describe_inputs(fitted.required_inputs())}", file=sys.stderr, flush=True)
        metrics = _log_scores(rows, curves, split, model_name, "+".join(train_runs), run_name)
        info = tracking.log_model(fitted, split.dataset)
    outputs = {"model_uri": info.model_uri}
    flags = model_flags(rows)
    for flag in flags:
        print(f"[train] warning: {model_name} on {'+'.join(train_runs)}: {flag}", file=sys.stderr, flush=True)
    if flags:
        outputs["registered"] = "no: " + "; ".join(flags)
    elif cfg.tracking.get("register", True):  # after the run has finished: no version of an unfinished run
        reg = split.registry_name(model_name)
        outputs["registered"] = f"models:/{reg}/{tracking.register(info.model_uri, reg)}"
    return _finish(JobResult("train", _table(rows, split), metrics, mlflow_run_id=run.info.run_id, outputs=outputs))


def evaluate(cfg: DictConfig) -> JobResult:
    """Score the model ``cfg.model_uri`` (or ``cfg.name``/``cfg.alias``) on ``cfg.dataset``."""
    import mlflow

    exp_id = tracking.connect(cfg.tracking)
    conf = plain(cfg)
    uri = tracking.model_uri(cfg.get("name"), cfg.get("alias"), cfg.get("model_uri"))
    model = tracking.load_model(uri)
    split = load_split(dataset_config_for(model, cfg.dataset))
    runs = resolve_runs(cfg.get("runs"), split, "runs")
    h = tracking.config_hash(conf)
    with mlflow.start_run(experiment_id=exp_id, run_name=f"evaluate {uri} | {split.name}") as run:
        data_hash = split.dataset.content_hash()
        mlflow.set_tags(tracking.standard_tags(data_hash, h, "evaluate") | {"model_uri": uri})
        tracking.log_config(conf)
        tracking.log_dataset(split.dataset, split.label, "evaluation", digest=data_hash)
        with thread_budget(job_threads()):
            rows, curves = evaluate_runs(model, split.dataset, runs, curves=True)
        rows.insert(1, "own", rows["run_id"].isin(getattr(model, "train_runs_", [])))
        metrics = _log_scores(rows, curves, split, type(model).__name__, "evaluated", f"{uri} on {split.name}")
    return _finish(JobResult("evaluate", _table(rows, split), metrics, mlflow_run_id=run.info.run_id))


def export(cfg: DictConfig) -> JobResult:
    """``thermbench export``: fitted models -> export directories for the embedded compensator
    (:mod:`thermbench.export`). The source is the benchmark's model directory (default), a
    fitted model file, or an MLflow model (``export.model_uri`` or ``export.name`` + alias)."""
    from .export.job import run_export

    table, outputs = run_export(cfg)
    return _finish(JobResult("export", table, outputs=outputs))


def save_models(models: Mapping[str, Any], out_dir: Path, chosen: Sequence[str] = (), source: Mapping[str, str] | None = None,
                extra: Mapping[str, Mapping] | None = None, force: bool = False) -> dict[str, Path]:  # fmt: skip
    """Write ``out_dir`` anew: each fitted model as ``<key>.joblib`` plus ``manifest.yaml``
    marking the chosen ones (``extra[key]`` adds entries, e.g. dataset and metrics). One
    output of kind ``models`` (:func:`thermbench.outputs.output_dir`): the files of an
    earlier save there are replaced, those no longer produced removed (no stale or
    half-written files), and a directory holding anything else is refused."""
    out_dir = Path(out_dir)
    manifest = {}
    with output_dir(out_dir, "models", force=force) as tmp:
        for key, m in models.items():
            joblib.dump(m, tmp / f"{key}.joblib")
            inp = m.required_inputs()
            manifest[key] = {
                "file": f"{key}.joblib",
                "chosen": key in chosen,
                "class": f"{type(m).__module__}.{type(m).__name__}",
                "train_runs": list(getattr(m, "train_runs_", [])),
                "sensors": list(inp.sensors),
                "source": (source or {}).get(key, "benchmark"),
                **dict((extra or {}).get(key, {})),
            }
        (tmp / "manifest.yaml").write_text(yaml.safe_dump(manifest, sort_keys=False), encoding="utf-8")
    return {key: out_dir / f"{key}.joblib" for key in models}
