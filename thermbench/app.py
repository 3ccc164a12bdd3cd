"""Hydra entry points of ``thermbench train|evaluate|benchmark|export``: thin layers over
:mod:`thermbench.experiment` and :mod:`thermbench.benchmark`.

Each job composes ``conf/<job>.yaml`` with the command-line overrides, so ``-m`` multirun,
``hydra/launcher=joblib`` (local parallelism), ``hydra/launcher=cluster`` (SLURM through
submitit), ``--cfg job`` and ``--help`` all work as in any Hydra app.
:class:`SweepProgress` reports progress per job and overall and ends a sweep with a summary
table in the terminal.
"""

from __future__ import annotations

import json
import math
import signal
import sys
from pathlib import Path
from typing import Any, Callable

import hydra
import pandas as pd
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from ._atomic import write_text_atomic
from .config import ConfigError, config_dir
from .experiment import HEADLINE, hydra_runtime

#: set when a multirun ended with failed jobs (the command then exits with 2)
_FAILED_JOBS: list[str] = []


def _jobs() -> dict[str, Callable]:
    from . import benchmark, experiment

    return {"train": experiment.train, "evaluate": experiment.evaluate, "benchmark": benchmark.benchmark,
            "export": experiment.export}


def user_errors() -> tuple[type[BaseException], ...]:
    """Exceptions that are user mistakes: reported in one line, no traceback."""
    from .data.io import DatasetError
    from .experiment import ExperimentError
    from .export import ExportError, ModelFileError, RuntimeFailed, RuntimeUnavailable
    from .models.base import ModelError
    from .tracking import TrackingError

    return (ConfigError, DatasetError, ExperimentError, ModelError, TrackingError, FileNotFoundError, ExportError,
            ModelFileError, RuntimeUnavailable, RuntimeFailed)  # fmt: skip


def print_result(res) -> None:
    """The terminal summary of one job."""
    with pd.option_context("display.width", 120, "display.max_columns", 20, "display.float_format", "{:.3f}".format):
        if res.job != "benchmark":  # the benchmark prints its own one-screen summary
            print(res.table.to_string(index=False))
    for k in HEADLINE:
        if k in res.metrics:
            print(f"  {k}: {res.metrics[k]:.3f}")
    if res.mlflow_run_id:
        print(f"  mlflow run: {res.mlflow_run_id}")
    for k, v in res.outputs.items():
        print(f"  {k}: {v}")


def run(job: str, argv: list[str]) -> int:
    """Run Hydra job ``job`` with command-line arguments ``argv`` (overrides, ``-m``, ...)."""
    fn = _jobs()[job]
    errors = user_errors()

    def task(cfg: DictConfig) -> Any:
        try:
            res = fn(cfg)
        except errors as exc:
            print(f"thermbench {job}: error: {exc}", file=sys.stderr, flush=True)
            hc = hydra_runtime()
            if hc is None or str(hc.mode) != "RunMode.MULTIRUN":
                sys.exit(2)
            # in a sweep the other jobs go on; the summary lists this one as failed
            failed = {"job": job, "error": str(exc), "skipped": False, "metrics": {}}
            write_text_atomic(Path(hc.runtime.output_dir) / "result.json", json.dumps(failed))
            return None
        print_result(res)
        return res.metrics

    main = hydra.main(version_base="1.3", config_path=str(config_dir()), config_name=job)(task)
    interrupted = []

    def on_sigint(signum, frame):  # remember it: Hydra may wrap the KeyboardInterrupt in its own error
        interrupted.append(signum)
        signal.default_int_handler(signum, frame)

    _FAILED_JOBS.clear()
    saved, saved_handler = sys.argv, signal.getsignal(signal.SIGINT)
    sys.argv = [f"thermbench-{job}", *argv]
    try:
        signal.signal(signal.SIGINT, on_sigint)
    except ValueError:  # not the main thread: leave signals alone
        pass
    code = 0
    try:
        main()
    except SystemExit as exc:
        code = int(exc.code or 0) if isinstance(exc.code, int) else 1
    except KeyboardInterrupt:
        interrupted.append(signal.SIGINT)
    finally:
        sys.argv = saved
        try:
            signal.signal(signal.SIGINT, saved_handler)
        except ValueError:
            pass
    if interrupted:  # Ctrl-C: one line, no traceback; the interrupted MLflow run is marked FAILED
        resume = " (run the same command again to resume: finished runs are skipped)" if job in ("train", "benchmark") else ""
        print(f"thermbench {job}: interrupted{resume}", file=sys.stderr, flush=True)
        return 130
    if code == 0 and _FAILED_JOBS:
        return 2
    return code


# -------------------------------------------------------------- callbacks ---
def _sweep_size(config: DictConfig) -> int | None:
    """Number of jobs of a basic-sweeper multirun (command-line sweeps x hydra.sweeper.params)."""
    try:
        from hydra.core.override_parser.overrides_parser import OverridesParser

        given = list(config.hydra.overrides.task)
        node = config.hydra.sweeper.get("params")
        params = OmegaConf.to_container(node, resolve=False) if node else {}
        keys = {o.split("=", 1)[0].lstrip("+~") for o in given}
        given += [f"{k}={v}" for k, v in params.items() if k not in keys]
        parsed = OverridesParser.create().parse_overrides(given)
        return math.prod(len(list(o.sweep_string_iterator())) for o in parsed if o.is_sweep_override())
    except Exception:
        return None


class SweepProgress(Callback):
    """Progress per job and overall during a multirun; a summary table at the end.

    The table reads each job's ``result.json`` (written by every job, skipped ones too),
    so it works with any launcher, including parallel and cluster ones.
    """

    def on_multirun_start(self, config: DictConfig, **kwargs: Any) -> None:
        from . import tracking

        try:  # an unreachable tracking server stops the sweep before any job starts
            tracking.connect(config.tracking)
        except tracking.TrackingError as exc:
            print(f"thermbench: error: {exc}", file=sys.stderr, flush=True)
            sys.exit(2)
        n = _sweep_size(config)
        sweep_dir = Path(str(config.hydra.sweep.dir))
        sweep_dir.mkdir(parents=True, exist_ok=True)
        write_text_atomic(sweep_dir / "sweep_size.txt", str(n if n is not None else "?"))
        print(f"[sweep] {n if n is not None else '?'} jobs -> {sweep_dir}", flush=True)

    def on_job_end(self, config: DictConfig, job_return: Any, **kwargs: Any) -> None:
        hc = config.hydra
        if str(hc.mode) != "RunMode.MULTIRUN":
            return
        sweep_dir = Path(str(hc.sweep.dir))
        done = len(_results(sweep_dir))
        size = sweep_dir / "sweep_size.txt"
        n = size.read_text(encoding="utf-8").strip() if size.exists() else None
        status = getattr(job_return, "status", None)
        mine = Path(str(hc.runtime.output_dir)) / "result.json"
        user_error = mine.exists() and "error" in json.loads(mine.read_text(encoding="utf-8"))
        state = "failed" if user_error or (status is not None and status.name == "FAILED") else "done"
        overrides = " ".join(hc.overrides.task)
        print(f"[sweep] job #{hc.job.num} {state} ({overrides}); {done}/{n if n is not None else '?'} finished", flush=True)

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        table = sweep_table(Path(str(config.hydra.sweep.dir)))
        if table.empty:
            return
        with pd.option_context("display.width", 160, "display.max_columns", 30, "display.float_format", "{:.3f}".format):
            print("\n[sweep] summary\n" + table.to_string(index=False), flush=True)
        if "error" in table:
            failed = table.loc[table["error"].notna(), "job"].tolist()
            _FAILED_JOBS.extend(failed)
            if failed:
                print(f"[sweep] {len(failed)} job(s) failed: {', '.join(failed)} (see the error column)", flush=True)


def _results(sweep_dir: Path) -> list[Path]:
    """The ``result.json`` files written by this multirun: a sweep rerun into the same
    ``hydra.sweep.dir`` (a resume) leaves older ones, which predate its ``sweep_size.txt``."""
    size = sweep_dir / "sweep_size.txt"
    since = size.stat().st_mtime_ns if size.exists() else 0
    return [p for p in sweep_dir.glob("*/result.json") if p.stat().st_mtime_ns >= since]


def sweep_table(sweep_dir: Path) -> pd.DataFrame:
    """One row per finished job of a sweep directory (of its latest multirun): its overrides
    and headline metrics."""
    rows = []
    for res_path in sorted(_results(sweep_dir), key=lambda p: int(p.parent.name) if p.parent.name.isdigit() else 0):
        res = json.loads(res_path.read_text(encoding="utf-8"))
        ov_path = res_path.parent / ".hydra" / "overrides.yaml"
        ov = OmegaConf.load(ov_path) if ov_path.exists() else []
        row: dict[str, Any] = {"job": res_path.parent.name}
        row.update(dict(o.split("=", 1) for o in ov if "=" in o))
        row["skipped"] = res.get("skipped", False)
        row.update({k: res["metrics"][k] for k in HEADLINE if k in res.get("metrics", {})})
        if res.get("error"):
            row["error"] = res["error"]
        rows.append(row)
    return pd.DataFrame(rows)
