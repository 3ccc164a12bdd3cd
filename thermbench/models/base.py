"""The one interface every thermal-error model family implements.

A model is a scikit-learn style estimator: the constructor only stores
hyper-parameters (so ``get_params``/``set_params``/``clone`` work), ``fit``
learns from runs of a validated :class:`~thermbench.data.Dataset` and returns
``self``. It then predicts the *positioning* error (geometric + thermal, µm,
measured minus commanded) at any (t, axis position) of a run, and the
compensation table over the travel at every time step (seed 000 §4.3).

Subclasses implement ``_fit(ds, runs)``, ``_predict_thermal(ds, run, t_s,
axis_mm)`` and ``required_inputs()``; the geometric part is a fitted
:class:`numpy.polynomial.Polynomial` in the axis position held in
``geometric_`` (each family separates it the way its seed does:
:mod:`thermbench.models.separation`).
"""

from __future__ import annotations

import contextlib
import contextvars
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Iterator, Mapping, Sequence

import numpy as np
import pandas as pd
from numpy.polynomial import Polynomial
from sklearn.base import BaseEstimator
from threadpoolctl import threadpool_limits

import thermbench

from ..data.dataset import Dataset
from ..data.reference import thermal_errors


class ModelError(ValueError):
    """A model cannot do what was asked (bad input, unfitted model, ...); the message says why."""


class FallbackWarning(UserWarning):
    """A model took a default because the dataset lacks what it prefers (no sensor at
    ``ambient``: a constant ambient); ``thermbench train`` prints each one."""


def fallback(message: str) -> None:
    """Warn that a model fell back to a default (:class:`FallbackWarning`)."""
    import warnings

    warnings.warn(message, FallbackWarning, stacklevel=3)


#: the threads each OpenMP and BLAS thread pool may use in this job (:func:`thread_budget`);
#: None: the libraries' own default (every core)
_THREADS: contextvars.ContextVar[int | None] = contextvars.ContextVar("thermbench_threads", default=None)


#: a job that shows fit progress (:func:`show_fit_progress`): tqdm's ``disable`` for its bars (None: on a
#: terminal only); unset: no bars (the benchmark's workers, tests, the library used directly)
_PROGRESS: contextvars.ContextVar[tuple[bool | None] | None] = contextvars.ContextVar("thermbench_fit_progress",
                                                                                     default=None)  # fmt: skip
#: a fit's progress bar appears only once the fit has run this long
FIT_PROGRESS_DELAY_S = 10.0


@contextlib.contextmanager
def show_fit_progress(disable: bool | None = None) -> Iterator[None]:
    """In the block, a fit that runs longer than :data:`FIT_PROGRESS_DELAY_S` (an LSSVM's swarm,
    a network's epochs) shows a progress bar on stderr (:func:`fit_progress`); ``disable`` as
    tqdm takes it (None: on a terminal only). ``thermbench train`` fits in one."""
    token = _PROGRESS.set((disable,))
    try:
        yield
    finally:
        _PROGRESS.reset(token)


@contextlib.contextmanager
def fit_progress(total: int, desc: str, unit: str) -> Iterator:
    """The step counter of one fit's loop (``total`` steps of ``unit``): yields ``step(n=1)``.
    A tqdm bar, drawn only inside :func:`show_fit_progress` and only after
    :data:`FIT_PROGRESS_DELAY_S`, removed when the fit ends."""
    shown = _PROGRESS.get()
    if shown is None:
        yield lambda n=1: None
        return
    from tqdm.auto import tqdm

    bar = tqdm(total=total, desc=desc, unit=unit, delay=FIT_PROGRESS_DELAY_S, disable=shown[0], leave=False)
    try:
        yield bar.update
    finally:
        bar.close()


def n_workers(n_jobs: int) -> int:
    """The workers ``n_jobs`` means, counted as joblib counts it (-1: one per core of the machine,
    -2: all but one, ...)."""
    if n_jobs < 0:
        import joblib

        return max(1, joblib.cpu_count() + 1 + n_jobs)
    return max(1, int(n_jobs))


def threads_per_worker(cores: int, n_jobs: int) -> int:
    """The threads each of ``n_jobs`` parallel workers (:func:`n_workers`) may use so that
    workers x threads never exceeds ``cores``: ``max(1, cores // workers)``."""
    return max(1, int(cores) // n_workers(n_jobs))


def fit_threads() -> int | None:
    """The thread count the running job gave (:func:`thread_budget`), None outside one."""
    return _THREADS.get()


@contextlib.contextmanager
def thread_budget(threads: int | None) -> Iterator[None]:
    """Run the block on at most ``threads`` threads per OpenMP and BLAS thread pool: the job
    that dispatches fits (``thermbench train``, each benchmark worker) says how many cores it
    was given, and every family runs with that many, so parallel jobs never oversubscribe the
    cores (an OpenMP booster left at its default took 26-37 s instead of 0.1 s per fit with two
    jobs on two cores). The pools loaded now are limited for the whole block (predictions,
    metrics); :meth:`ThermalErrorModel.fit` applies the limit again around each fit, so the pools
    a family loads on first use (e.g. torch's OpenMP) are limited there too. None: no limit."""
    if threads is None:
        yield
        return
    threads = max(1, int(threads))
    token = _THREADS.set(threads)
    try:
        with threadpool_limits(limits=threads):
            yield
    finally:
        _THREADS.reset(token)


def _pairs(t_s, axis_mm) -> tuple[np.ndarray, np.ndarray]:
    """(t, x) broadcast against each other, as flat float arrays."""
    t, x = np.broadcast_arrays(np.atleast_1d(np.asarray(t_s, dtype=float)), np.asarray(axis_mm, dtype=float))
    return t.ravel().astype(float), x.ravel().astype(float)


@dataclass(frozen=True)
class Inputs:
    """What a fitted model must be fed at run time (what a compensator wires up).

    Every model takes the time and the axis position of the point to compensate.
    Beyond that: ``sensors``: sensor names of the dataset metadata (process columns
    ``<name>_C``); ``motion``: the history of axis position and feed since the run
    (machine) started cold, which drives heat-source models; ``ambient``: one of
    ``sensors`` is the ambient temperature; ``operating``: process columns used as
    operating parameters (seed 003).
    """

    sensors: tuple[str, ...] = ()
    motion: bool = False
    ambient: bool = False
    operating: tuple[str, ...] = ()


@dataclass
class CompensationTable:
    """Predicted error over an axis grid at each time step (seed 000 §4.3).

    ``error_um[i, j]`` is the error at ``t_s[i]``, ``axis_mm[j]``; the CNC applies
    ``compensation_um = -error_um``, interpolated in time and position (:meth:`at`).
    """

    t_s: np.ndarray
    axis_mm: np.ndarray
    error_um: np.ndarray

    @property
    def compensation_um(self) -> np.ndarray:
        return -self.error_um

    def at(self, t_s, axis_mm) -> np.ndarray:
        """Bilinear interpolation of the table (what the compensator does in real time)."""
        t, x = _pairs(t_s, axis_mm)
        i = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, max(len(self.t_s) - 2, 0))
        j = np.clip(np.searchsorted(self.axis_mm, x, side="right") - 1, 0, max(len(self.axis_mm) - 2, 0))
        i1 = np.minimum(i + 1, len(self.t_s) - 1)
        j1 = np.minimum(j + 1, len(self.axis_mm) - 1)
        wt = np.clip((t - self.t_s[i]) / np.where(i1 > i, self.t_s[i1] - self.t_s[i], 1.0), 0.0, 1.0)
        wx = np.clip((x - self.axis_mm[j]) / np.where(j1 > j, self.axis_mm[j1] - self.axis_mm[j], 1.0), 0.0, 1.0)
        e = self.error_um
        top = e[i, j] * (1 - wx) + e[i, j1] * wx
        bot = e[i1, j] * (1 - wx) + e[i1, j1] * wx
        return top * (1 - wt) + bot * wt


def check_runs(ds: Dataset, runs: Sequence[str] | str | None) -> list[str]:
    """The run ids asked for (all when None), each checked to exist in ``ds``."""
    if not isinstance(ds, Dataset):
        raise ModelError(f"expected a thermbench Dataset, got {type(ds).__name__}")
    if runs is None:
        return ds.run_ids
    runs = [runs] if isinstance(runs, str) else [str(r) for r in runs]
    if not runs:
        raise ModelError("no runs given to fit on")
    unknown = [r for r in runs if r not in ds.metadata.runs]
    if unknown:
        raise ModelError(f"run(s) {unknown} not in dataset {_name(ds)}; runs: {ds.run_ids}")
    return runs


def training_runs(ds: Dataset, runs: Sequence[str] | str | None) -> list[str]:
    """The runs a family fits on (:func:`check_runs`), each once, in the dataset's order (``metadata.runs``:
    the order the lab's files give them, never the order of their names as text): what a family learns
    depends on the set of its training runs, not on the order a caller lists them in (a validation hold-out
    of the last runs, folds of whole runs, a seeded shuffle of the rows all see the same runs in the same
    order)."""
    asked = set(check_runs(ds, runs))
    return [r for r in ds.run_ids if r in asked]


def check_sensors(ds: Dataset, sensors: Sequence[str], key: str = "sensors") -> list[str]:
    """Sensor names that the dataset has; a missing one is an error naming it."""
    have = list(ds.metadata.sensors)
    missing = [s for s in sensors if s not in have]
    if missing:
        raise ModelError(
            f"{key}: sensor(s) {missing} not in dataset {_name(ds)}; it has {have} (metadata 'sensors')"
        )
    return list(sensors)


def sensors_by_location(ds: Dataset, locations: Sequence[str]) -> list[str]:
    """The dataset's first sensor at each of ``locations`` (locations it lacks are skipped)."""
    out = []
    for loc in locations:
        name = next((n for n, where in ds.metadata.sensors.items() if where == loc), None)
        if name is not None:
            out.append(name)
    return out


def sensors_at(ds: Dataset, sensor: str, locations: Sequence[str]) -> str:
    """The dataset's sensor at the first of ``locations`` it has (e.g. 'nut_housing')."""
    found = sensors_by_location(ds, locations)
    if found:
        where = ds.metadata.sensors[found[0]]
        if where != locations[0]:
            fallback(f"{sensor}: no sensor at {locations[0]!r}; using {found[0]!r} at {where!r}")
        return found[0]
    raise ModelError(
        f"{sensor}: the dataset {_name(ds)} has no sensor at {list(locations)}; "
        f"sensors: {dict(ds.metadata.sensors)}; name one explicitly"
    )


def require(n: int, minimum: int, what: str) -> None:
    if n < minimum:
        raise ModelError(f"too few samples: {n} {what}, need at least {minimum}")


def _name(ds: Dataset) -> str:
    return str(ds.path) if ds.path is not None else ds.metadata.machine.name


def derived(ds: Dataset, key: tuple, make, copy: bool = True):
    """What is derived from a dataset, computed once per dataset object and shared (data
    flows one way: a loaded dataset is not changed, so the thermal errors, the measuring
    cycles and the filtered sensor series made from it stay valid). Returns a copy, or
    (``copy=False``) the shared object, which the caller must not change."""
    memo = ds.__dict__.setdefault("_derived", {})
    if key not in memo:
        memo[key] = make()
    return memo[key].copy() if copy else memo[key]


def readings(ds: Dataset, runs: Sequence[str]) -> pd.DataFrame:
    """The interferometer readings of ``runs`` with ``thermal_um`` (reading minus
    the run's cold reference at the same target) and the measuring ``cycle``, **run by run in the
    order of** ``runs`` (each run's readings in the errors table's order): a family that stacks its
    features run by run (``for r in runs``) pairs them with these rows, whatever order the dataset's
    tables hold the runs in (computed once per dataset and runs: :func:`derived`)."""
    return derived(ds, ("readings", tuple(runs)), lambda: _readings(ds, runs))


def _readings(ds: Dataset, runs: Sequence[str]) -> pd.DataFrame:
    te = thermal_errors(ds)  # with each reading's measuring cycle (data.reference.reading_cycles)
    rows = te.groupby("run_id", sort=False).indices
    at = [rows[r] for r in dict.fromkeys(runs) if r in rows]
    return te.iloc[np.concatenate(at) if at else np.zeros(0, dtype=int)].reset_index(drop=True)


def sensor_series(ds: Dataset, run: str, sensors: Sequence[str], preprocess) -> pd.DataFrame:
    """The run's process log (``t_s`` and ``<sensor>_C`` columns), filtered by ``preprocess``
    (seed 002 §2.3.1: ``"default"``, ``None`` or a list of filters), with a clear error
    for missing sensors or NaN left after filtering."""
    if preprocess is None or isinstance(preprocess, str):  # a named chain: the same filters every time
        key = ("sensor_series", run, tuple(sensors), preprocess)
        return derived(ds, key, lambda: _sensor_series(ds, run, sensors, preprocess))
    return _sensor_series(ds, run, sensors, preprocess)


def _sensor_series(ds: Dataset, run: str, sensors: Sequence[str], preprocess) -> pd.DataFrame:
    from ..preprocess.filters import filter_process, resolve_steps

    cols = [ds.metadata.sensor_column(s) for s in check_sensors(ds, sensors)]
    pr = ds.process_run(run)
    out = filter_process(pr, cols, resolve_steps(preprocess))
    return out[["t_s", *cols]]


def temperatures_at(
    ds: Dataset, run: str, sensors: Sequence[str], t_s, preprocess="default", delta: bool = True
) -> np.ndarray:
    """Sensor temperatures at times ``t_s`` of ``run``, shape (n, len(sensors)).

    ``delta``: the rise above the run's first (filtered) sample, ΔT of seed 002
    eq. 10 (seed 001 §3: T or ΔT give the same model up to the constant).
    """
    s = sensor_series(ds, run, sensors, preprocess)
    t = np.asarray(t_s, dtype=float)
    out = np.empty((t.size, len(sensors)))
    for j, s_name in enumerate(sensors):
        y = s[ds.metadata.sensor_column(s_name)].to_numpy()
        out[:, j] = np.interp(t, s["t_s"].to_numpy(), y) - (y[0] if delta else 0.0)
    return out


NEEDS = {
    "screw": "a screw block (metadata 'screw': the ball screw's geometry)",
    "along_axis": "readings along a linear axis at target positions (an along_axis error channel)",
    "operating": "an operating input (metadata 'operating': the process column that drives the heat, e.g. "
    "spindle_rpm), or the family's own 'operating' parameter",
    "sensor_locations": "temperature sensors at the locations it reads (the class's sensor_locations), or the "
    "family's own 'sensors' parameter",
}


def is_fixed_point(ds: Dataset) -> bool:
    """True for a view of a fixed-point channel (a spindle's drift at the test mandrel):
    every reading is at the one position 0.0 (:func:`thermbench.data.views.channel_view`)."""
    if ds.channel is None:
        return False
    return ds.metadata.error_channels()[ds.channel].kind == "fixed_point"


def missing_needs(cls, ds: Dataset, params: Mapping | None = None) -> list[str]:
    """What model class ``cls`` needs (its ``needs``, keys of :data:`NEEDS`) that dataset ``ds``
    lacks. ``params``: the family's parameters (a model's ``get_params()`` or its conf/model
    option): an explicit ``operating`` or ``sensors`` there stands in for the dataset's own."""
    params = params or {}
    out = []
    for need in getattr(cls, "needs", ()):
        if need == "screw" and ds.metadata.screw is None:
            out.append(need)
        elif need == "along_axis" and (is_fixed_point(ds) or not ds.metadata.has_axis):
            out.append(need)
        elif need == "operating" and params.get("operating") is None and not ds.metadata.operating_inputs():
            out.append(need)
        elif need == "sensor_locations" and params.get("sensors") is None and not (
            set(getattr(cls, "sensor_locations", ())) & set(ds.metadata.sensors.values())
        ):
            out.append(need)
    return out


def needs_text(cls, missing: Sequence[str]) -> str:
    """The missing needs of :func:`missing_needs` in words (``sensor_locations`` names the class's)."""
    text = {**NEEDS, "sensor_locations": f"temperature sensors at {', '.join(getattr(cls, 'sensor_locations', ()))} "
                                         "(metadata 'sensors'), or the family's own 'sensors' parameter"}  # fmt: skip
    return "; and ".join(text[m] for m in missing)


def check_needs(model, ds: Dataset) -> None:
    """One line naming what ``model`` needs and ``ds`` lacks (e.g. the screw physics model
    on a spindle test); nothing when it has everything."""
    missing = missing_needs(type(model), ds, model.get_params(deep=False))
    if missing:
        parts = ", ".join(ds.metadata.parts or []) or "a linear axis"
        where = f", channel {ds.channel!r}" if ds.channel else ""
        raise ModelError(f"{type(model).__name__} needs {needs_text(type(model), missing)}; dataset {_name(ds)}{where} "
                         f"(a test of: {parts}) has none")  # fmt: skip


class ThermalErrorModel(BaseEstimator, ABC):
    """Base class of all model families (see module docstring).

    ``needs``: what a dataset must have for the family (keys of :data:`NEEDS`); fitting
    on one that lacks it is one line naming what is missing (:func:`check_needs`).

    ``complexity``: 1 (linear in fixed features), 2 (a physical model with a few nonlinear
    parameters) or 3 (a kernel machine or neural network): the benchmark's choice prefers the
    simpler of candidates it cannot tell apart.

    ``params_model``: the family's hyper-parameters as a pydantic model
    (:mod:`thermbench.models.params`), one field per constructor parameter; each family's
    ``_fit`` validates ``get_params()`` with it (:func:`~thermbench.models.params.check_params`)
    before it learns anything.

    ``fit`` checks the runs and what the family needs of the dataset (:func:`check_runs`,
    :func:`check_needs`), forgets an earlier fit, then calls ``_fit`` with at most the threads
    the running job gave (:func:`thread_budget`) in each OpenMP and BLAS thread pool."""

    needs: tuple[str, ...] = ()
    params_model = None
    #: how flexible the family is, for the benchmark's choice (which prefers the simpler of candidates
    #: within one standard error, :func:`thermbench.bench.choice.nested_choice`): 1 linear in fixed features
    #: (the regressions, thermal lags, delays, ARX), 2 a physical model whose few parameters enter
    #: nonlinearly (time constants, a heat exponent), 3 a kernel machine or neural network (the default);
    #: 0 the stacked ensemble (:mod:`thermbench.models.ensemble`) and the ridge baseline made deployable
    #: (:class:`~thermbench.models.linear_history.RidgeHistory`), preferred to any other family within it
    complexity: int = 3

    def fit(self, dataset: Dataset, runs: Sequence[str] | str | None = None) -> "ThermalErrorModel":
        runs = training_runs(dataset, runs)
        check_needs(self, dataset)
        # a refit starts from nothing: a fit that fails half-way leaves an unfitted model
        for attr in [a for a in vars(self) if a.endswith("_") and not a.startswith("__")]:
            delattr(self, attr)
        threads = fit_threads()  # the job's share of the cores (thread_budget); None: no job set one
        with threadpool_limits(limits=threads) if threads is not None else contextlib.nullcontext():
            self._fit(dataset, runs)
        self.train_runs_ = list(runs)
        self.channel_ = dataset.channel  # the error channel of a format 2 dataset it predicts (None: format 1)
        return self

    # --- subclass hooks ---------------------------------------------------
    @abstractmethod
    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        """Learn from ``runs``; must set ``geometric_``."""

    @abstractmethod
    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        """The thermal part of the error at (t, axis) pairs."""

    def _model_inputs(self) -> Inputs:
        """What the fitted model reads; default: the sensors it fitted on (``sensors_``)."""
        return Inputs(sensors=tuple(getattr(self, "sensors_", ())))

    # --- the interface ----------------------------------------------------
    def _check_fitted(self) -> None:
        if not hasattr(self, "train_runs_"):
            raise ModelError(f"{type(self).__name__} is not fitted: call fit(dataset, runs) before predicting")

    def required_inputs(self) -> Inputs:
        """What the fitted model must be fed at run time (:class:`Inputs`)."""
        self._check_fitted()
        return self._model_inputs()

    def fit_summary(self) -> str | None:
        """One line on what the fit chose (a family that selects inputs, time constants or a penalty
        says which; ``thermbench train`` prints it); None: nothing to say."""
        self._check_fitted()
        return None

    def geometric_um(self, axis_mm) -> np.ndarray:
        """The geometric (pitch) error separated at fit time, at ``axis_mm``."""
        self._check_fitted()
        return self.geometric_(np.asarray(axis_mm, dtype=float))

    def predict_thermal_at(self, dataset: Dataset, run: str, t_s, axis_mm) -> np.ndarray:
        """The thermal part of the error at (t, axis) pairs of ``run``."""
        self._check_fitted()
        run = check_runs(dataset, run)[0]
        t, x = _pairs(t_s, axis_mm)
        return np.asarray(self._predict_thermal(dataset, run, t, x), dtype=float)

    def predict_at(self, dataset: Dataset, run: str, t_s, axis_mm) -> np.ndarray:
        """The positioning error (geometric + thermal, µm) at (t, axis) pairs of ``run``."""
        t, x = _pairs(t_s, axis_mm)
        return self.predict_thermal_at(dataset, run, t, x) + self.geometric_um(x)

    def predict(self, dataset: Dataset, run: str) -> np.ndarray:
        """The error at the run's measured (t, target) readings, in the errors-table order."""
        er = dataset.errors_run(check_runs(dataset, run)[0])
        return self.predict_at(dataset, run, er["t_s"].to_numpy(), er["target_mm"].to_numpy())

    def compensation_table(
        self, dataset: Dataset, run: str, axis_mm=None, step_s: float = 60.0
    ) -> CompensationTable:
        """The error over ``axis_mm`` (default: the run's measured targets) every
        ``step_s`` of the run (seed 000 §4.3: the table the CNC interpolates)."""
        run = check_runs(dataset, run)[0]
        if axis_mm is None:
            axis_mm = dataset.errors_run(run)["target_mm"].to_numpy()
        x = np.unique(np.asarray(axis_mm, dtype=float))  # sorted: the table is interpolated
        pr = dataset.process_run(run)
        t0, t1 = float(pr["t_s"].iloc[0]), float(pr["t_s"].iloc[-1])
        if not step_s > 0:
            raise ModelError(f"step_s must be > 0, got {step_s}")
        t = np.append(np.arange(t0, t1, step_s), t1)
        tt = np.repeat(t, x.size)
        xx = np.tile(x, t.size)
        return CompensationTable(t, x, self.predict_at(dataset, run, tt, xx).reshape(t.size, x.size))


def polynomial_fit(x: np.ndarray, y: np.ndarray, degree: int, what: str) -> Polynomial:
    """Least-squares polynomial (numpy's scaled domain), with a clear error when underdetermined."""
    x = np.asarray(x, dtype=float)
    y = np.asarray(y, dtype=float)
    n_unique = np.unique(x).size
    if n_unique <= degree:
        raise ModelError(f"too few samples: {what} needs more than {degree} distinct positions, got {n_unique}")
    return Polynomial.fit(x, y, degree)


def last_cycles_mask(rd: pd.DataFrame, fraction: float) -> np.ndarray:
    """True for the readings of the last ``fraction`` of the measuring cycles of each
    run (at least one cycle, and at least one stays out); runs with a single cycle
    hold nothing out. A hold-out at the end of each run is an honest extrapolation in time."""
    held = np.zeros(len(rd), dtype=bool)
    if fraction == 0.0:
        return held
    for _, g in rd.groupby("run_id", sort=False):
        cycles = np.unique(g["cycle"].to_numpy())
        if cycles.size < 2:
            continue
        n_val = min(max(1, int(round(fraction * cycles.size))), cycles.size - 1)
        held[g.index.to_numpy()[np.isin(g["cycle"].to_numpy(), cycles[-n_val:])]] = True
    return held


def validation_mask(rd: pd.DataFrame, fraction: float) -> np.ndarray:
    """The readings a family tunes on (early stopping, a swarm's objective), never rows of a run it
    trains on (rows of one time series are autocorrelated, so a hold-out of rows between
    training rows rewards interpolation): with several training runs, **whole runs**, the last
    ones in training order whose readings come closest to ``fraction`` of all (at least one held
    out, at least one kept); with one run, its last ``fraction`` of measuring cycles
    (:func:`last_cycles_mask`: a contiguous block at its end, an extrapolation in time)."""
    runs = list(dict.fromkeys(rd["run_id"]))
    if fraction == 0.0 or len(runs) < 2:
        return last_cycles_mask(rd, fraction)
    sizes = rd.groupby("run_id", sort=False).size()
    target, held, n = fraction * len(rd), [], 0
    for r in reversed(runs[1:]):  # the first run always trains
        if held and abs(n + sizes[r] - target) >= abs(n - target):
            break
        held.append(r)
        n += int(sizes[r])
    return rd["run_id"].isin(held).to_numpy()


# curve_degree moved to thermbench.models.separation, choose_sensors to thermbench.models.sensor_choice
__getattr__ = thermbench.moved_names(__name__)
