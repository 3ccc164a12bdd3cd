"""Where every job that fits models in parallel dispatches them (the benchmark's tasks, a
multirun's jobs, the export's models): each worker on its share of the job's cores, so parallel
workers never oversubscribe them (:func:`thermbench.models.base.thread_budget`)."""

from __future__ import annotations

from typing import Mapping, Sequence

import joblib
from omegaconf import OmegaConf

from ..models.base import n_workers, thread_budget, threads_per_worker


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
