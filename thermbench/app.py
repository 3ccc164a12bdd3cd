"""Hydra entry points of ``thermbench train|evaluate|benchmark|export``: thin layers over
:mod:`thermbench.experiment` and :mod:`thermbench.bench`.

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
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

import hydra
from hydra.experimental.callback import Callback
from omegaconf import DictConfig, OmegaConf

from .outputs import write_text_atomic
from .config import ConfigError, compose_checked, config_dir
from .errors import one_line, report, stdout_closed, user_errors  # user_errors: the CLI's and the jobs' one definition

if TYPE_CHECKING:
    import pandas as pd

# pandas, scikit-learn, MLflow (thermbench.experiment) are imported when a job runs: a
# mistake on the command line is reported before any of that is loaded.


def hydra_runtime():
    """The running Hydra job's config (:func:`thermbench.experiment.hydra_runtime`)."""
    from .experiment import hydra_runtime

    return hydra_runtime()

#: set when a multirun ended with failed jobs (the command then exits with 2)
_FAILED_JOBS: list[str] = []
#: ... and those that failed on an unexpected exception, a bug (exit code 1)
_CRASHED_JOBS: list[str] = []


def _jobs() -> dict[str, Callable]:
    from . import experiment
    from .bench.job import benchmark

    return {"train": experiment.train, "evaluate": experiment.evaluate, "benchmark": benchmark,
            "export": experiment.export}


def print_result(res) -> None:
    """The terminal summary of one job."""
    import pandas as pd

    from .experiment import HEADLINE

    if res.job == "benchmark":  # it prints its own summary, paths included, and the answer last
        return
    with pd.option_context("display.width", 120, "display.max_columns", 20, "display.float_format", "{:.3f}".format):
        print(res.table.to_string(index=False))
    for k in HEADLINE:
        if k in res.metrics:
            print(f"  {k}: {res.metrics[k]:.3f}")
    if res.mlflow_run_id:
        print(f"  mlflow run: {res.mlflow_run_id}")
    for k, v in res.outputs.items():
        print(f"  {k}: {v}")


def check_command_line(job: str, argv: list[str]) -> None:
    """The overrides of ``thermbench <job> argv`` composed and checked before Hydra starts
    anything, every job of a ``-m`` sweep included: a mistake is one :class:`ConfigError`
    line (with a did-you-mean). ``--help``, ``--info``, ``--shell-completion``, another
    config directory or a malformed command line are left to Hydra; ``--cfg`` shows a
    config with its ``???`` values."""
    import contextlib
    import io

    from hydra._internal.utils import get_args_parser

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            args = get_args_parser().parse_args(argv)
    except SystemExit as exc:  # --version (Hydra prints it), or a malformed command line
        usage = [ln for ln in err.getvalue().splitlines() if ": error: " in ln]
        if exc.code and usage:
            raise ConfigError(f"{usage[-1].split(': error: ', 1)[1]} (see thermbench {job} --help)") from None
        return
    # Hydra's own usage rules, which it reports with a traceback
    if args.resolve and args.cfg is None and not args.help:
        raise ConfigError("--resolve goes with --cfg (e.g. --cfg job --resolve)")
    modes = [m for m, on in (("--run", args.run), ("-m/--multirun", args.multirun), ("--cfg", args.cfg is not None),
                             ("--info", args.info is not None), ("--shell-completion", args.shell_completion)) if on]  # fmt: skip
    if len(modes) > 1 and not args.help and not args.hydra_help:
        raise ConfigError(f"{' and '.join(modes)} cannot be combined: give one of them")
    if (args.help or args.hydra_help or args.shell_completion or args.info is not None or args.config_path
            or args.config_dir or args.experimental_rerun):  # fmt: skip
        return
    compose_checked(args.config_name or job, args.overrides, multirun=bool(args.multirun),
                    require_values=args.cfg is None)  # fmt: skip
    if args.cfg is None:
        _check_hydra_dirs(args.config_name or job, args.overrides, bool(args.multirun))


def _check_hydra_dirs(name: str, overrides: list[str], multirun: bool) -> None:
    """Hydra's run (or sweep) directory must not be, contain or lie in a dataset, nor hold
    files other than an earlier Hydra job's (:func:`thermbench.outputs.check_hydra_dir`)."""
    from .config import load_config
    from .outputs import OutputRefused, check_hydra_dir

    mine = [o for o in overrides if o.lstrip("+~").startswith(("hydra.", "hydra/"))]
    cfg = load_config(name, mine, return_hydra_config=True)
    key = "hydra.sweep.dir" if multirun else "hydra.run.dir"
    for sub in ("hydra.output_subdir", "hydra.sweep.subdir"):  # where Hydra writes inside that directory
        value = OmegaConf.select(cfg, sub, throw_on_resolution_failure=False)
        if sub == "hydra.sweep.subdir" and not any(o.lstrip("+~").startswith(sub) for o in mine):
            continue  # the default, ${hydra.job.num}: resolved by Hydra per job
        if value is not None and (Path(str(value)).is_absolute() or ".." in Path(str(value)).parts):
            raise ConfigError(f"config key '{sub}': {value!r} must be a relative path inside {key} (no '..')")
    try:
        where = OmegaConf.select(cfg, key)
    except Exception as exc:  # an interpolation that cannot be resolved, e.g. an unset ${oc.env:...}
        raise ConfigError(f"config key '{key}': {one_line(exc)}") from None
    try:
        check_hydra_dir(Path(str(where)), key)
    except OutputRefused as exc:
        raise ConfigError(str(exc)) from None


def _job_failed(job: str, exc: BaseException, unexpected: bool) -> None:
    """Record a failed job of a sweep in its ``result.json``: the summary lists it as failed."""
    hc = hydra_runtime()
    message = f"unexpected {type(exc).__name__}: {one_line(exc)} (a bug: traceback above)" if unexpected else one_line(exc)
    failed = {"job": job, "error": message, "unexpected": unexpected, "skipped": False, "metrics": {}}
    write_text_atomic(Path(hc.runtime.output_dir) / "result.json", json.dumps(failed))


def _in_sweep() -> bool:
    hc = hydra_runtime()
    return hc is not None and str(hc.mode) == "RunMode.MULTIRUN"


def run(job: str, argv: list[str]) -> int:
    """Run Hydra job ``job`` with command-line arguments ``argv`` (overrides, ``-m``, ...).

    Exit codes: 0 done; 2 a user mistake (one line on stderr), or a sweep with failed jobs;
    1 an unexpected exception (a bug: its traceback is printed; in a sweep the other jobs
    still run); 130 interrupted."""
    # Hydra's parser takes the overrides in one run: `key=a -m key2=b` would be refused
    flags = ("-m", "--multirun", "-r", "--run", "--resolve")
    argv = [a for a in argv if a in flags] + [a for a in argv if a not in flags]
    try:
        check_command_line(job, argv)
    except ConfigError as exc:
        return report(f"thermbench {job}", exc)

    def task(cfg: DictConfig) -> Any:
        try:
            res = _jobs()[job](cfg)
            print_result(res)
        except BrokenPipeError:  # the reader of stdout went away (| head)
            raise stdout_closed() from None
        except user_errors() as exc:
            if not _in_sweep():
                sys.exit(report(f"thermbench {job}", exc))
            # in a sweep the other jobs go on; the summary lists this one as failed
            report(f"thermbench {job}", exc)
            _job_failed(job, exc, unexpected=False)
            return None
        except Exception as exc:
            if not _in_sweep():
                raise  # a bug: Hydra prints its traceback, exit code 1
            # a bug in one job of a sweep: its traceback now, the other jobs still run,
            # the summary marks it and the command ends with exit code 1
            traceback.print_exc()
            sys.stderr.flush()
            _job_failed(job, exc, unexpected=True)
            return None
        return res.metrics

    main = hydra.main(version_base="1.3", config_path=str(config_dir()), config_name=job)(task)
    interrupted = []

    def on_sigint(signum, frame):  # remember it: Hydra may wrap the KeyboardInterrupt in its own error
        interrupted.append(signum)
        signal.default_int_handler(signum, frame)

    _FAILED_JOBS.clear()
    _CRASHED_JOBS.clear()
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
    if code == 0 and _CRASHED_JOBS:
        return 1
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
        metrics = json.loads(mine.read_text(encoding="utf-8")).get("metrics", {}) if mine.exists() else {}
        held = metrics.get("validation_mean_rmse_um")  # what the job found: its score on the runs it held out
        found = f"; held-out RMSE {held:.2f} µm" if held is not None else ("; no validation runs" if state == "done" else "")
        print(f"[sweep] job #{hc.job.num} {state} ({overrides}){found}; {done}/{n if n is not None else '?'} finished",
              flush=True)  # fmt: skip

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        import pandas as pd

        sweep_dir = Path(str(config.hydra.sweep.dir))
        table = sweep_table(sweep_dir)
        if table.empty:
            return
        with pd.option_context("display.width", 160, "display.max_columns", 30, "display.float_format", "{:.3f}".format):
            print("\n[sweep] summary\n" + table.to_string(index=False), flush=True)
        if "error" in table:
            failed = table.loc[table["error"].notna(), "job"].tolist()
            _FAILED_JOBS.extend(failed)
            _CRASHED_JOBS.extend(p.parent.name for p in _results(sweep_dir)
                                 if json.loads(p.read_text(encoding="utf-8")).get("unexpected"))  # fmt: skip
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
    import pandas as pd

    from .experiment import HEADLINE

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
