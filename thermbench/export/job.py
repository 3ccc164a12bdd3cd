"""``thermbench export``: the Hydra job (``conf/export.yaml``) over :func:`export_model`.

Sources, in order of precedence: ``export.model_uri`` / ``export.name`` (an MLflow
model: its run id and metrics go into the manifest), else ``export.source``: a
directory written by ``thermbench benchmark`` (``manifest.yaml``; ``export.select``
picks ``all``, the ``chosen`` ones or a list of keys) or one fitted model file
(``.joblib``). Each model is exported to ``<out_dir>/<key>``, where ``out_dir`` is
``export.out_dir`` or ``exports/<name of the source>`` (``exports/benchmark`` for the demo's
``models/benchmark``). The whole ``out_dir`` is one output (:func:`thermbench.outputs.output_dir`):
an export replaces the folders of the previous export there and removes those it no longer
makes, so no stale folder looks current; a directory holding anything else is refused.
"""

from __future__ import annotations

import json
import re
import sys
from pathlib import Path
from typing import Any

import joblib
import pandas as pd
import yaml
from omegaconf import DictConfig, OmegaConf

from ..bench import datasets
from ..config import ConfigError
from ..outputs import check_output_dir, output_dir
from .budget import TARGETS, TargetRefused
from .bundle import ExportOptions, export_model
from .encoding import ExportError

KEYS = {"source", "select", "model_uri", "name", "alias", "dataset", "channel", "out_dir", "lssvm_reduced_size", "onnx",
        "verify", "parity_tol_um", "target", "seed", "force", "n_jobs", "interval_level", "interval_kappa"}  # fmt: skip


def _options(e: dict) -> ExportOptions:
    size = e.get("lssvm_reduced_size")
    if size is not None and (isinstance(size, bool) or not isinstance(size, int) or size < 1):
        raise ConfigError(f"config key 'export.lssvm_reduced_size': expected null or an integer >= 1, got {size!r}")
    tol = e.get("parity_tol_um", 0.01)
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not tol > 0:
        raise ConfigError(f"config key 'export.parity_tol_um': expected a number > 0, got {tol!r}")
    for k in ("onnx", "verify"):
        if not isinstance(e.get(k, True), bool):
            raise ConfigError(f"config key 'export.{k}': expected true or false, got {e.get(k)!r}")
    seed = e.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int):
        raise ConfigError(f"config key 'export.seed': expected an integer, got {seed!r}")
    target = e.get("target", "host")
    if target not in TARGETS:
        raise ConfigError(f"config key 'export.target': expected one of {sorted(TARGETS)}, got {target!r}")
    level, kappa = e.get("interval_level"), e.get("interval_kappa", 1.0)
    if level is not None and (isinstance(level, bool) or not isinstance(level, (int, float)) or not 0 < level < 1):
        raise ConfigError(f"config key 'export.interval_level': expected null or a number between 0 and 1, got {level!r}")
    if isinstance(kappa, bool) or not isinstance(kappa, (int, float)) or not kappa >= 0:
        raise ConfigError(f"config key 'export.interval_kappa': expected a number >= 0, got {kappa!r}")
    return ExportOptions(size, seed, bool(e.get("onnx", True)), bool(e.get("verify", True)), float(tol), target,
                         None if level is None else float(level), float(kappa))  # fmt: skip


def _dataset_names() -> list[str]:
    from ..config import config_dir

    return sorted(p.stem for p in (config_dir() / "dataset").glob("*.yaml"))


def _items(e: dict, cfg: DictConfig) -> list[tuple[str, Any, dict]]:
    """(key, fitted model, source info) of every model to export."""
    from .. import tracking

    if e.get("model_uri") or e.get("name"):
        import mlflow

        tracking.connect(cfg.tracking)
        uri = tracking.model_uri(e.get("name"), e.get("alias"), e.get("model_uri"))
        model = tracking.load_model(uri)
        run_id = mlflow.models.get_model_info(uri).run_id
        run = mlflow.get_run(run_id) if run_id else None
        metrics = dict(run.data.metrics) if run else {}
        params = dict(run.data.params) if run else {}
        key = e.get("name") or str(uri).removeprefix("models:/").removeprefix("runs:/")
        key = re.sub(r"[^A-Za-z0-9_.-]+", "_", str(key)).strip("._") or "model"  # models:/name/1 -> name_1
        return [(key, model, {"uri": uri, "mlflow_run_id": run_id, "metrics": metrics,
                              "dataset_name": params.get("dataset.name") or params.get("dataset"),
                              "dataset_config": _run_dataset_config(run_id)})]  # fmt: skip
    src = Path(str(e.get("source") or ""))
    if src.is_file():
        if src.suffix != ".joblib":
            raise ConfigError(f"config key 'export.source': {src} is not a fitted model file (.joblib) or a model directory")
        return [(src.stem, joblib.load(src), {"file": str(src)})]
    if not src.is_dir():
        raise ConfigError(
            f"config key 'export.source': {src} does not exist; run `thermbench benchmark` first (it writes "
            "models/benchmark), or name a fitted model file (.joblib), or set export.model_uri / export.name"
        )
    mpath = src / "manifest.yaml"
    if not mpath.exists():
        raise ConfigError(f"config key 'export.source': {src} has no manifest.yaml (a directory written by thermbench benchmark)")
    manifest = yaml.safe_load(mpath.read_text(encoding="utf-8")) or {}
    sel = e.get("select", "all")
    if sel == "all":
        keys = list(manifest)
    elif sel == "chosen":
        keys = [k for k, v in manifest.items() if v.get("chosen")]
        if not keys:
            raise ConfigError(f"config key 'export.select': chosen, but {mpath} marks no model chosen (chosen: true); "
                              f"name the models instead, e.g. export.select=[{next(iter(manifest), 'KEY')}]")  # fmt: skip
    elif isinstance(sel, (list, tuple)):
        keys = [str(k) for k in sel]
        unknown = [k for k in keys if k not in manifest]
        if unknown:
            raise ConfigError(f"config key 'export.select': {unknown} are not in {mpath}; it has {list(manifest)}")
    else:
        raise ConfigError(f"config key 'export.select': expected all, chosen or a list of keys, got {sel!r}")
    out = []
    for k in keys:
        entry = manifest[k]
        f = src / entry["file"]
        if not f.exists():
            raise ConfigError(f"{mpath}: {k}: file {f} is missing")
        info = {"file": str(f), "metrics": dict(entry.get("metrics") or {}), "mlflow_run_id": entry.get("mlflow_run_id"),
                "dataset_name": entry.get("dataset"), "dataset_path": entry.get("dataset_path"),
                "chosen": bool(entry.get("chosen"))}  # fmt: skip
        out.append((k, joblib.load(f), info))
    return out


def run_export(cfg: DictConfig) -> tuple[pd.DataFrame, dict]:
    e = OmegaConf.to_container(cfg.export, resolve=True) if isinstance(cfg.export, DictConfig) else dict(cfg.export)
    unknown = sorted(set(e) - KEYS)
    if unknown:
        raise ConfigError(f"config key(s) {['export.' + k for k in unknown]} unknown; known: {sorted(KEYS)}")
    opts = _options(e)
    force = e.get("force", False)
    if not isinstance(force, bool):
        raise ConfigError(f"config key 'export.force': expected true or false, got {force!r}")
    out_root = Path(str(e.get("out_dir") or f"exports/{_source_name(e)}"))
    check_output_dir(out_root, "exports", force=force, force_option="export.force=true")  # before any model is read
    items = _items(e, cfg)
    with output_dir(out_root, "exports", force=force, force_option="export.force=true") as stage:
        rows = _export_all(items, e, opts, stage, out_root)
    out = {"dir": str(out_root)}
    if len(rows) == 1:  # what replay and the compensator take: the model's own directory
        out["model_dir"] = rows[0]["dir"]
    return pd.DataFrame(rows), out


def _run_dataset_config(run_id: str | None) -> dict | None:
    """The ``dataset`` section of the config an MLflow run logged (``config.yaml``): how the
    model's training dataset was loaded, own data included."""
    if not run_id:
        return None
    import mlflow

    try:
        text = mlflow.artifacts.load_text(f"runs:/{run_id}/config.yaml")
    except Exception:  # a run logged by something else: no config, the other ways apply
        return None
    cfg = yaml.safe_load(text) or {}
    d = cfg.get("dataset") if isinstance(cfg, dict) else None
    return d if isinstance(d, dict) and isinstance(d.get("source"), dict) else None


_SPLITS: dict = {}  # per process: dataset config (JSON) -> Split, loaded once for all the models trained on it


def _load_split_cached(cfg: dict):
    from ..bench.splits import load_split

    k = json.dumps(cfg, sort_keys=True, default=str)
    if k not in _SPLITS:
        _SPLITS[k] = load_split(cfg)
    return _SPLITS[k]


def _dataset_config(e: dict, info: dict, key: str, model=None) -> tuple[str | None, dict | None]:
    """(name, dataset config) of the dataset the model was trained on, or (None, None):
    ``export.dataset`` (a conf/dataset option or a dataset directory; a directory's name is
    None: the loaded split names it), else the MLflow run's logged dataset config, else the
    dataset directory the benchmark's manifest names (``dataset_path``), else the benchmark
    dataset the key names. Checked here, loaded by :func:`_load_split_cached`."""
    from ..config import group_option
    from ..bench.splits import dataset_config_for, dataset_option

    given = e.get("dataset")
    logged = info.pop("dataset_config", None)
    name = info.pop("dataset_name", None)
    path = info.pop("dataset_path", None)
    if not given and logged is None and path:  # a benchmark on a dataset directory: the manifest says where it was
        if not (Path(str(path)) / "metadata.yaml").is_file():
            raise ConfigError(f"{key}: its training dataset {path!r} (from the manifest) is not a dataset directory "
                              "here; set export.dataset to the dataset's path")  # fmt: skip
        given = path
    if given:
        option, cfg = dataset_option(str(given), "export.dataset")
        if option is None:  # a directory: its own channel unless one is given
            cfg["channel"] = e.get("channel")
        elif e.get("channel") is not None:
            cfg["channel"] = e.get("channel")
        return option, dataset_config_for(model, cfg, "export.channel")
    if logged is not None:
        src = logged["source"]
        if src.get("_target_") == "thermbench.data.io.load_dataset" and not Path(str(src.get("path"))).is_dir():
            raise ConfigError(f"{key}: its training dataset {src.get('path')!r} (from the MLflow run) is not a "
                              "directory here; set export.dataset to the dataset's path")  # fmt: skip
        if e.get("channel") is not None:
            logged = {**logged, "channel": e.get("channel")}
        return None, logged
    name = name or datasets.of_key(key)
    if name:  # the model's own channel of a multi-channel dataset (a benchmark key names the dataset only)
        return str(name), dataset_config_for(model, dict(group_option("dataset", str(name))))
    return None, None


def _source_name(e: dict) -> str:
    """The default export folder's name: the registered model or URI, else the source's name."""
    if e.get("model_uri") or e.get("name"):
        raw = str(e.get("name") or e.get("model_uri")).replace("models:/", "").replace("runs:/", "")
    else:
        raw = Path(str(e.get("source") or "model")).stem
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", raw).strip("._") or "model"


def _export_all(items, e: dict, opts: ExportOptions, stage: Path, out_root: Path) -> list[dict]:
    """Export every item into ``stage/<key>``: what each needs is checked here first (so a
    bad key fails before any work), then the models are exported in ``export.n_jobs``
    processes (joblib; each model's directory is its own; each process on its share of the
    cores: :func:`thermbench.bench.parallel.run_workers`), rows in the items' order."""
    every = e.get("select", "all") == "all" and len(items) > 1
    todo = []
    for key, model, info in items:
        if every:  # select all: what the C runtime cannot run (a baseline, a soft bank) is skipped, and said so
            from .encoding import export_blocker

            why = export_blocker(model)
            if why:
                print(f"thermbench export: skipped {key}: {why}", file=sys.stderr)
                continue
        dname, dcfg = _dataset_config(e, info, key, model)
        if dcfg is None and opts.verify:
            raise ConfigError(
                f"{key}: cannot tell which dataset it was trained on; set export.dataset (a conf/dataset option: "
                f"{_dataset_names()}, or a dataset directory) or export.verify=false"
            )
        todo.append((key, model, info, dname, dcfg))
    if not todo:
        raise ExportError("nothing to export: export.select matched no model")
    n_jobs = e.get("n_jobs", 1)
    if isinstance(n_jobs, bool) or not isinstance(n_jobs, int) or n_jobs == 0 or n_jobs < -1:
        raise ConfigError(f"config key 'export.n_jobs': expected an integer >= 1 (or -1: every core), got {n_jobs!r}")
    from ..bench.parallel import run_workers  # each worker on its share of the cores (thread limits)

    calls = [((*t, opts, stage, out_root, every), {}) for t in todo]
    rows = list(run_workers(_export_one, calls, 1 if len(todo) == 1 else n_jobs))
    rows = [r for r in rows if r is not None]
    if not rows:
        raise ExportError(f"nothing to export: no model meets export.target={opts.target} (the lines above say why)")
    return rows


def _export_one(key: str, model, info: dict, dname: str | None, dcfg: dict | None, opts: ExportOptions, stage: Path,
                out_root: Path, skip_refused: bool = False) -> dict | None:  # fmt: skip
    """One model to ``stage/key``; its row of the summary table (None: refused by the export target
    and ``skip_refused``, said on stderr)."""
    ds, heldout, sp = None, [], None
    if dcfg is not None:
        sp = _load_split_cached(dcfg)
        dname = dname or sp.name
        ds = sp.dataset
        train = set(getattr(model, "train_runs_", []))
        heldout = [r for r in sp.validation if r not in train] or [r for r in ds.run_ids if r not in train]
    training = {"dataset_name": dname, **({"history": True} if sp is not None and sp.history else {})}
    source = {**info, "training": training} if dname else info
    try:
        man = export_model(model, stage / key, key, ds, heldout, source=source, options=opts)
    except TargetRefused as exc:
        if not skip_refused:
            raise
        print(f"thermbench export: skipped {key}: {exc}", file=sys.stderr)
        return None
    files = ([man["bank"]["classifier_file"], *man["bank"]["members"]] if man["kind"] == "bank"
             else list(man["files"].values()))  # fmt: skip
    par = man.get("parity", {}).get("model", {})
    if not man["footprint"]["within_budget"]:
        print(f"thermbench export: warning: {key} exceeds the STM32F407 budget: "
              f"{', '.join(man['footprint']['over_budget'])}", file=sys.stderr)  # fmt: skip
    return {"model": key, "kind": man["kind"], "files": len(files), "bytes": sum(f["bytes"] for f in files),
            "largest_file_bytes": max(f["bytes"] for f in files),
            "parity_max_abs_diff_nm": None if par.get("max_abs_diff_um") is None else 1000 * par["max_abs_diff_um"],
            "heldout_rmse_um": par.get("heldout_rmse_um_c"), "ram_bytes": man["footprint"]["ram_bytes"],
            "within_budget": man["footprint"]["within_budget"], "dir": str(out_root / key)}  # fmt: skip
