"""MLflow tracking: where runs go, what each run records, and how a sweep resumes.

* ``conf/tracking/embedded.yaml`` (default): a sqlite store in the project
  directory (``mlflow.db``, files in ``mlartifacts/``), no server needed.
* ``tracking=server tracking.uri=http://host:port``: a tracking server, checked
  with ``GET /health`` before any work starts (:func:`connect`), so an
  unreachable server fails in seconds, not after an hour of training.

Every run records the flattened resolved config as params, metrics, artifacts,
the tags of :func:`standard_tags` (git commit, dataset hash, thermbench
version, config hash) and its dataset as an MLflow dataset input
(:func:`log_dataset`: the Dataset column of the MLflow UI). :func:`config_hash`
is what lets an interrupted sweep resume: a job whose hash already has a
FINISHED run is skipped (:func:`finished_run`).

Models are logged as MLflow pyfunc models (:mod:`thermbench.mlflow_pyfunc`)
and registered; :func:`load_model` takes ``models:/<name>@<alias>`` (or any
model URI) back to the fitted thermbench model.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import subprocess
import tempfile
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any, Mapping

import joblib
import yaml

from . import __version__
from .data.safe_yaml import dump_yaml

LOG = logging.getLogger(__name__)
PYFUNC_CODE = Path(__file__).with_name("mlflow_pyfunc.py")
#: config keys that do not change a job's result (left out of the resume hash)
NON_RESULT_KEYS = ("tracking", "hydra", "report_dir", "export_dir", "n_jobs", "progress", "cache_dir", "force")


class TrackingError(RuntimeError):
    """Tracking cannot work as configured; the message names the config key."""


def _quiet_mlflow() -> None:
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "1")
    os.environ.setdefault("MLFLOW_HTTP_REQUEST_TIMEOUT", "30")
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    for name in ("mlflow", "alembic", "mlflow.store.db.utils", "matplotlib"):
        logging.getLogger(name).setLevel(logging.WARNING)
    # thermbench models take a process log, not a fixed-schema frame: no signature to infer
    logging.getLogger("mlflow.pyfunc").setLevel(logging.ERROR)


def resolve_uri(uri: str, base_dir: str | Path | None = None) -> str:
    """``sqlite:///relative.db`` and plain paths are taken relative to ``base_dir`` (cwd)."""
    base = Path(base_dir or os.getcwd())
    if uri.startswith("sqlite:///") and not uri.startswith("sqlite:////"):
        return f"sqlite:///{(base / uri[len('sqlite:///'):]).resolve()}"
    if "://" not in uri:
        return (base / uri).resolve().as_uri()
    return uri


def check_server(uri: str, timeout_s: float = 5.0) -> None:
    """Raise :class:`TrackingError` unless the MLflow server at ``uri`` answers ``/health``."""
    url = uri.rstrip("/") + "/health"
    try:
        with urllib.request.urlopen(url, timeout=timeout_s) as resp:
            if resp.status != 200:
                raise TrackingError(f"tracking.uri={uri}: {url} answered HTTP {resp.status}, not an MLflow server?")
    except (urllib.error.URLError, OSError, TimeoutError) as exc:
        reason = getattr(exc, "reason", exc)
        raise TrackingError(
            f"tracking.uri={uri}: MLflow server unreachable ({reason}). Start it "
            f"(mlflow server --host 127.0.0.1 --port 5000) or drop tracking.uri to use the embedded store "
            f"(tracking=embedded). Nothing was trained."
        ) from None


#: what MLflow 3 stores runs in, when its own list cannot be read
_SCHEMES = ("databricks", "databricks-uc", "file", "http", "https", "mssql", "mysql", "postgresql", "sqlite", "uc")


def check_uri_scheme(uri: str, shown: str | None = None) -> None:
    """Raise :class:`TrackingError` (naming ``tracking.uri``) unless MLflow has a tracking
    store for the scheme of ``uri`` (checked before MLflow is pointed at it, which would
    otherwise fail later with MLflow's own traceback). ``shown``: the URI as the user wrote it."""
    try:
        from mlflow.tracking._tracking_service.utils import _tracking_store_registry

        schemes = sorted(k for k in _tracking_store_registry._registry if k)  # plugins included
    except Exception:  # a private name of MLflow's: fall back to the documented schemes
        schemes = list(_SCHEMES)
    try:
        from mlflow.utils.uri import get_uri_scheme

        scheme = uri if uri in ("databricks", "databricks-uc", "uc") else get_uri_scheme(uri)
    except Exception:  # MLflow refuses the URI itself, e.g. an unknown database dialect (mysqlx://)
        scheme = uri.split("://", 1)[0] if "://" in uri else None
    if scheme and scheme not in schemes:
        raise TrackingError(
            f"config key 'tracking.uri': {shown or uri}: unsupported URI scheme {scheme!r}; MLflow takes "
            f"{', '.join(schemes)} (e.g. sqlite:///mlflow.db, or http://host:port for a server)"
        )


def connect(tcfg: Mapping[str, Any], base_dir: str | Path | None = None) -> str:
    """Point MLflow at ``tcfg.uri`` (checking a server first); return the experiment id."""
    _quiet_mlflow()
    import mlflow
    from mlflow import MlflowClient

    uri = str(tcfg.get("uri") or "")
    if not uri:
        raise TrackingError("config key 'tracking.uri': expected a URI (sqlite:///mlflow.db or http://host:port)")
    given, uri = uri, resolve_uri(uri, base_dir)
    check_uri_scheme(uri, given)
    if uri.startswith(("http://", "https://")):
        check_server(uri, float(tcfg.get("timeout_s", 5.0)))
    mlflow.set_tracking_uri(uri)
    mlflow.set_registry_uri(uri)
    name = str(tcfg.get("experiment") or "thermbench")
    try:
        client = MlflowClient()
        exp = client.get_experiment_by_name(name)
        if exp is not None:
            return exp.experiment_id
        root = tcfg.get("artifact_root")
        # a server keeps the files of its experiments itself: a local root would put them on this machine
        remote = uri.startswith(("http://", "https://"))
        loc = resolve_uri(str(root), base_dir) if root and not remote else None
        try:
            return client.create_experiment(name, artifact_location=loc)
        except Exception:  # created meanwhile by a parallel job of the same sweep
            exp = client.get_experiment_by_name(name)
            if exp is None:
                raise
            return exp.experiment_id
    except TrackingError:
        raise
    except Exception as exc:
        raise TrackingError(f"tracking.uri={uri}: cannot open the tracking store: {exc}") from None


def flatten(cfg: Mapping[str, Any]) -> dict[str, str]:
    """The nested config as ``{"model.gamma": "10.0", ...}`` (MLflow params are strings).

    Lists and empty mappings are kept as JSON (``"[]"``, ``"{}"``), so every leaf of the
    config is a param."""
    out: dict[str, str] = {}

    def walk(node: Any, key: str) -> None:
        if isinstance(node, Mapping) and (node or not key):
            for k, v in node.items():
                walk(v, f"{key}.{k}" if key else str(k))
            return
        s = json.dumps(node, default=str) if isinstance(node, (list, tuple, Mapping)) else str(node)
        out[key[:250]] = s[:6000]

    walk(dict(cfg), "")
    return out


def config_hash(cfg: Mapping[str, Any]) -> str:
    """SHA-256 (16 hex) of the resolved config without the keys that cannot change the result."""
    plain = {k: v for k, v in dict(cfg).items() if k not in NON_RESULT_KEYS}
    blob = json.dumps({"cfg": plain, "version": __version__}, sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def git_commit(path: str | Path | None = None) -> str:
    """The project's git commit (with ``+dirty`` for uncommitted changes), or ``unknown``."""
    where = Path(path or Path(__file__).resolve().parent.parent)
    try:
        sha = subprocess.run(
            ["git", "rev-parse", "HEAD"], cwd=where, capture_output=True, text=True, timeout=10, check=True
        ).stdout.strip()
        # --no-optional-locks: never write .git/index, so a sweep cannot collide with the user's git commands
        dirty = subprocess.run(
            ["git", "--no-optional-locks", "status", "--porcelain", "--untracked-files=no"],
            cwd=where, capture_output=True, text=True, timeout=10,
        ).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def job_dir() -> str:
    """Where this job writes (Hydra's output directory; else the working directory): it names one
    job of one sweep, as the config hash names its configuration."""
    try:
        from hydra.core.hydra_config import HydraConfig

        return str(Path(HydraConfig.get().runtime.output_dir).resolve())
    except Exception:  # not inside a Hydra job
        return str(Path.cwd().resolve())


def close_interrupted(experiment_id: str, cfg_hash: str) -> int:
    """Mark KILLED the runs this same job (config hash and job directory) left RUNNING: an attempt
    killed before it could close its run (submitit sends SIGKILL 1 s after Ctrl-C's SIGINT). Runs
    of other sweeps (another directory), running now or not, are left alone."""
    from mlflow import MlflowClient

    c = MlflowClient()
    d = job_dir().replace("'", "")
    runs = c.search_runs([experiment_id], filter_string=f"tags.`thermbench.config_hash` = '{cfg_hash}' and "
                         f"tags.`thermbench.job_dir` = '{d}' and attributes.status = 'RUNNING'")  # fmt: skip
    for r in runs:
        c.set_terminated(r.info.run_id, "KILLED")
    return len(runs)


def standard_tags(dataset_hash: str | None, cfg_hash: str, job: str) -> dict[str, str]:
    tags = {
        "thermbench.version": __version__,
        "git_commit": git_commit(),
        "thermbench.config_hash": cfg_hash,
        "thermbench.job": job,
        "thermbench.job_dir": job_dir().replace("'", ""),
    }
    if dataset_hash:
        tags["dataset_hash"] = dataset_hash
    return tags


def finished_run(experiment_id: str, cfg_hash: str):
    """The newest FINISHED run with this config hash, or None."""
    from mlflow import MlflowClient

    runs = MlflowClient().search_runs(
        [experiment_id],
        filter_string=f"tags.`thermbench.config_hash` = '{cfg_hash}' and attributes.status = 'FINISHED'",
        max_results=1,
        order_by=["attributes.start_time DESC"],
    )
    return runs[0] if runs else None


#: pandas dtype kind -> MLflow column type (the schema of a logged dataset)
_KIND_TYPES = {"f": "double", "i": "long", "u": "long", "b": "boolean", "M": "datetime"}


def dataset_schema(dataset):
    """The columns of ``dataset``'s process log, then those of its readings table that the
    log lacks (``target_mm``, ``error_um``), as an MLflow :class:`~mlflow.types.Schema`: what
    a run's dataset input shows. Taken from the column types, so it costs nothing on a long log."""
    from mlflow.types import ColSpec, DataType, Schema

    cols: dict[str, str] = {}
    for df in (dataset.process, dataset.errors):
        for name, dtype in df.dtypes.items():
            cols.setdefault(str(name), _KIND_TYPES.get(getattr(dtype, "kind", "O"), "string"))
    return Schema([ColSpec(DataType[t], name) for name, t in cols.items()])


def dataset_input(dataset, name: str, digest: str | None = None):
    """``dataset`` as an MLflow dataset (metadata only: no data is copied): ``name``; as its
    digest the content hash (:meth:`~thermbench.data.Dataset.content_hash`, 16 hex: the
    ``dataset_hash`` tag; an own dataset's registered model names carry its first 8); its
    directory as the source; its columns as the schema (:func:`dataset_schema`). ``digest``:
    the content hash when the caller has it already."""
    from mlflow.data.code_dataset_source import CodeDatasetSource
    from mlflow.data.meta_dataset import MetaDataset
    from mlflow.data.sources import LocalArtifactDatasetSource

    if dataset.path is not None:
        source = LocalArtifactDatasetSource(str(Path(dataset.path).resolve()))
    else:  # built in memory, never written: the code that made it is its source
        source = CodeDatasetSource(tags={})
    return MetaDataset(source, name=str(name), digest=digest or dataset.content_hash(), schema=dataset_schema(dataset))


def log_dataset(dataset, name: str, context: str = "training", digest: str | None = None) -> None:
    """Record ``dataset`` (:func:`dataset_input`) as an input of the active run, with
    ``context`` (``training``, ``evaluation``) as MLflow's ``mlflow.data.context`` tag."""
    import mlflow
    from mlflow.exceptions import MlflowException

    inp = dataset_input(dataset, name, digest)
    for attempt in range(3):
        try:
            mlflow.log_input(inp, context=context)
            return
        except MlflowException as exc:
            # parallel jobs of a sweep logging the same dataset to one store: MLflow looks for it,
            # then inserts it, and the slower job's insert fails on the unique key. The dataset is
            # there now, so another try links it to this run.
            if "UNIQUE constraint failed: datasets" not in str(exc) or attempt == 2:
                raise


def log_config(cfg: Mapping[str, Any]) -> None:
    """The flattened config as params and the resolved config as ``config.yaml``."""
    import mlflow

    items = list(flatten(cfg).items())
    for i in range(0, len(items), 100):
        mlflow.log_params(dict(items[i : i + 100]))
    mlflow.log_text(yaml.safe_dump(dict(cfg), sort_keys=False), "config.yaml")


def log_model(model, dataset, name: str = "model", registered_name: str | None = None):
    """Log a fitted thermbench model as an MLflow pyfunc model (and register it).

    The pyfunc takes a process-log DataFrame (the dataset contract's process
    columns) and returns the predicted error at each row's (t_s, axis_mm).
    """
    import mlflow

    with tempfile.TemporaryDirectory() as tmp:
        mpath = Path(tmp) / "model.joblib"
        joblib.dump(model, mpath)
        meta = Path(tmp) / "dataset_metadata.yaml"
        meta.write_text(dump_yaml(dataset.metadata.model_dump(mode="json"), sort_keys=False), encoding="utf-8")  # read strictly
        return mlflow.pyfunc.log_model(
            name=name,
            python_model=str(PYFUNC_CODE),
            artifacts={"model": str(mpath), "metadata": str(meta)},
            pip_requirements=[f"thermbench=={__version__}"],
            registered_model_name=registered_name,
        )


def register(model_uri: str, registered_name: str) -> str:
    """Register a logged model under ``registered_name``; return the new version."""
    import mlflow

    return str(mlflow.register_model(model_uri, registered_name).version)


def code_version() -> str:
    """SHA-256 (16 hex) of thermbench's Python sources: what the benchmark cache is keyed on."""
    h = hashlib.sha256(__version__.encode())
    root = Path(__file__).resolve().parent
    for p in sorted(root.rglob("*.py")):
        h.update(str(p.relative_to(root)).encode())
        h.update(p.read_bytes())
    return h.hexdigest()[:16]


def set_alias(registered_name: str, alias: str, version: str | int) -> None:
    from mlflow import MlflowClient

    MlflowClient().set_registered_model_alias(registered_name, alias, str(version))


def model_uri(name: str | None = None, alias: str | None = None, uri: str | None = None) -> str:
    """``uri`` as given, else ``models:/<name>@<alias>``."""
    if uri:
        return str(uri)
    if not name:  # thermbench evaluate has these keys at the top, thermbench export under export.
        raise TrackingError(
            "no model to load: set config key 'model_uri' (any MLflow model URI) or 'name' (a registered model, "
            "with 'alias'); for thermbench export they are 'export.model_uri' / 'export.name'"
        )
    return f"models:/{name}@{alias}" if alias else f"models:/{name}/latest"


def load_model(uri: str):
    """The fitted thermbench model behind an MLflow model URI."""
    _quiet_mlflow()
    import mlflow

    try:
        return mlflow.pyfunc.load_model(uri).unwrap_python_model().model
    except Exception as exc:
        raise TrackingError(f"model {uri}: cannot load it from {mlflow.get_tracking_uri()}: {exc}") from None
