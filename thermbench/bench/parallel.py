"""Where every job that fits models in parallel dispatches them (the benchmark's tasks, a
multirun's jobs, the export's models): each worker on its share of the job's cores, so parallel
workers never oversubscribe them (:func:`thermbench.models.base.thread_budget`)."""

from __future__ import annotations

import contextlib
import os
import sys
from typing import Iterator, Mapping, Sequence

import joblib
from omegaconf import OmegaConf

from ..errors import ExperimentError
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


def _in_dask_worker() -> bool:
    if "distributed" not in sys.modules:
        return False
    try:
        sys.modules["distributed"].get_worker()
        return True
    except ValueError:
        return False


def _call_limited(fn, threads: int, args: tuple, kwargs: Mapping):
    """``fn(*args, **kwargs)`` with every fit (and whatever else runs there) on ``threads`` threads. On a Dask
    worker the joblib calls inside it (scikit-learn's cross-validation) run in it, one after the other, as
    they do in a local joblib worker: joblib would otherwise send them, with their data, back to the cluster."""
    with thread_budget(threads), (joblib.parallel_config(backend="sequential") if _in_dask_worker()
                                  else contextlib.nullcontext()):  # fmt: skip
        return fn(*args, **kwargs)


def run_workers(fn, calls: Sequence[tuple[tuple, Mapping]], n_jobs: int, ordered: bool = True,
                threads: int | None = None):
    """``fn(*args, **kwargs)`` for each ``(args, kwargs)`` of ``calls``, each on its worker's
    share of the cores (:func:`worker_threads`; ``threads``: that many instead): one after the other
    in this process for ``n_jobs=1`` (lazily), else in ``n_jobs`` joblib workers (of the active joblib
    backend: a Dask cluster inside :meth:`DaskExecutor.session`), results in the calls' order
    (``ordered``) or as they finish. Where every job that fits models in parallel dispatches them."""
    calls = list(calls)
    threads = worker_threads(n_jobs, len(calls)) if threads is None else int(threads)
    if n_jobs == 1:
        return (_call_limited(fn, threads, a, k) for a, k in calls)
    how = "generator" if ordered else "generator_unordered"
    work = (joblib.delayed(_call_limited)(fn, threads, a, k) for a, k in calls)
    return joblib.Parallel(n_jobs=n_jobs, return_as=how)(work)


class LocalExecutor:
    """The cells in ``n_jobs`` joblib worker processes on this machine (the default)."""

    def __repr__(self) -> str:
        return "LocalExecutor()"

    @contextlib.contextmanager
    def session(self, n_jobs: int) -> Iterator[tuple[int, int | None]]:
        """(the joblib ``n_jobs``, the threads per cell: None for each worker's share of the cores)."""
        yield n_jobs, None


class DaskExecutor:
    """The cells on a Dask cluster (`distributed`), through joblib's Dask backend: each cell is pure
    (a dataset path and its configs in, rows out), so the scheduler re-runs the cells of a worker it
    loses, and the job's cell cache (``cache_dir``, on a filesystem the workers share) keeps every
    cell done for a re-run.

    Parameters
    ----------
    address : str or None
        A running scheduler (``tcp://host:8786``), or a scheduler file (``dask scheduler
        --scheduler-file F``) when it names an existing ``.json`` file; None: a cluster started here,
        ``cluster`` or a ``LocalCluster``.
    n_workers : int
        Worker processes of the ``LocalCluster`` (with neither ``address`` nor ``cluster``).
    threads_per_worker : int
        Threads of each ``LocalCluster`` worker: the cells it runs at once.
    threads_per_cell : int
        The threads (per OpenMP and BLAS pool) each cell fits with: a worker's cores over the cells it
        runs at once.
    cluster : mapping or None
        A cluster to start (``_target_``, e.g. ``dask_jobqueue.SLURMCluster`` and its settings),
        instantiated when the job starts and closed when it ends.
    jobs : int
        The queue jobs ``cluster`` is scaled to (``cluster.scale(jobs=...)``).
    connect_timeout_s : float
        How long to wait for the scheduler at ``address``.
    """

    def __init__(self, address=None, n_workers=2, threads_per_worker=1, threads_per_cell=1, cluster=None, jobs=1,
                 connect_timeout_s=30.0):  # fmt: skip
        self.address = address
        self.n_workers = n_workers
        self.threads_per_worker = threads_per_worker
        self.threads_per_cell = threads_per_cell
        self.cluster = cluster
        self.jobs = jobs
        self.connect_timeout_s = connect_timeout_s

    def __repr__(self) -> str:
        where = self.address or (dict(self.cluster).get("_target_") if self.cluster else f"LocalCluster({self.n_workers})")
        return f"DaskExecutor({where})"

    def _check(self) -> None:
        for key in ("n_workers", "threads_per_worker", "threads_per_cell", "jobs"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ExperimentError(f"config key 'executor.{key}': expected an integer >= 1, got {v!r}")
        t = self.connect_timeout_s
        if isinstance(t, bool) or not isinstance(t, (int, float)) or not t > 0:
            raise ExperimentError(f"config key 'executor.connect_timeout_s': expected a number of seconds > 0, got {t!r}")
        if self.address is not None and not isinstance(self.address, str):
            raise ExperimentError(f"config key 'executor.address': expected a scheduler address or file, got {self.address!r}")

    @contextlib.contextmanager
    def session(self, n_jobs: int) -> Iterator[tuple[int, int | None]]:
        """Connect (or start the cluster), and route joblib to it: (-1: every thread of the cluster,
        ``threads_per_cell``)."""
        self._check()
        try:
            from distributed import Client, LocalCluster
        except ImportError:
            raise ExperimentError("config key 'executor': dask needs the cluster extra: pip install 'thermbench[cluster]'") from None
        with contextlib.ExitStack() as stack:
            if self.address is not None:
                file = self.address.endswith(".json") and os.path.isfile(self.address)
                try:
                    client = Client(scheduler_file=self.address) if file else Client(self.address, timeout=f"{self.connect_timeout_s}s")
                except (OSError, TimeoutError) as exc:
                    raise ExperimentError(f"config key 'executor.address': no Dask scheduler at {self.address}: "
                                          f"{' '.join(str(exc).split())}") from None  # fmt: skip
            else:
                if self.cluster is not None:
                    from hydra.utils import instantiate

                    cluster = stack.enter_context(instantiate(dict(self.cluster), _convert_="all"))
                    cluster.scale(jobs=self.jobs)
                else:
                    cluster = stack.enter_context(LocalCluster(n_workers=self.n_workers, processes=True,
                                                               threads_per_worker=self.threads_per_worker,
                                                               dashboard_address=None))  # fmt: skip
                client = Client(cluster)
            stack.enter_context(client)
            stack.enter_context(joblib.parallel_config(backend="dask"))
            yield -1, int(self.threads_per_cell)
