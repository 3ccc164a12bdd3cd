"""Plain experiment functions; the CLI and the Hydra jobs (:mod:`thermbench.app`) are thin layers over these.

* :func:`train` — fit one model (``conf/model``) on some loading states of a dataset
  (``conf/dataset``), score it on every run, track everything in MLflow, register the model.
* :func:`evaluate` — score a registered/logged model on a dataset.
* the robustness comparison is :func:`thermbench.bench.job.benchmark`.
* :func:`export` — a registered model (``models:/<name>@<alias>``) to a model file.

Each takes the composed config (a ``DictConfig``) and returns a :class:`JobResult`.
:func:`cross_condition` and :func:`fit_evaluate` are the building blocks tests call directly.
"""

from __future__ import annotations

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
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from sklearn.base import clone

from . import tracking
from .outputs import write_text_atomic
from .config import check_targets, config_dir, group_option  # noqa: F401  (group_option: the jobs' API)
from .errors import ExperimentError  # noqa: F401  (raised by the jobs; thermbench.errors holds it)
from .bench.parallel import hydra_runtime, job_threads, run_workers, worker_threads  # noqa: F401
from .bench.splits import (  # noqa: F401  (the runs and views the jobs fit and score on: thermbench.bench.splits)
    Split,
    dataset_config_for,
    dataset_option,
    dataset_view,
    load_source,
    load_split,
    resolve_runs,
)
from .bench.metrics import evaluate as evaluate_runs
from .models.base import FallbackWarning, show_fit_progress, thread_budget
from .outputs import output_dir

LOG = logging.getLogger(__name__)


#: the metrics a job's terminal summary and a sweep's summary table show
#: the metrics a job's summary and a sweep's table show: the held-out RMSE (on the validation runs) first
HEADLINE = ("validation_mean_rmse_um", "validation_worst_compensation_rate", "validation_max_abs_residual_um", "unseen_worst_compensation_rate",
            "unseen_max_abs_residual_um", "own_mean_rmse_um", "fit_s")


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
        if (chose := fitted.fit_summary()) is not None:  # e.g. the inputs and time constants thermal_lag chose
            print(f"[train] {model_name} {chose}", file=sys.stderr, flush=True)
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
