"""A grey-box lumped thermal network for a spindle, identified from measured drift.

Lumped-capacitance thermal networks (a few heat capacities joined by thermal
resistances, heated by the bearing friction, losing heat to the surroundings) are
the standard grey-box description of a motor spindle's thermal behaviour in the
literature; thermbench's own physics for the ball screw is the seed 000 §3
finite-difference model (:mod:`thermbench.models.physics`). Seed 003 drives a
spindle's thermal error by the spindle speed alone, with an auto-regressive model
(:mod:`thermbench.models.autoregressive`); this family keeps that input (no
temperature sensors needed) but gives the dynamics a physical structure: a short
chain of first-order thermal nodes whose time constants are identified.

The model (:class:`LumpedThermalNetwork`)
-----------------------------------------
Heat input, from an operating signal ``u(t)`` of the process log (spindle speed)::

    q(t) = (u(t) / u_ref) ** p                     (dimensionless, 1 at u = u_ref)

A chain of ``n`` nodes, each a first-order lag of the one before (rises above the
cold state, all zero at the start of the process log)::

    dθ1/dt = (q − θ1) / τ1
    dθi/dt = (θ_{i−1} − θi) / τi        i = 2..n

i.e. ``dθ/dt = A θ + B q`` with ``A`` lower bidiagonal (``A_ii = −1/τi``,
``A_{i,i−1} = 1/τi``) and ``B = e1/τ1``. The displacement at a reading is::

    E(t, x) = Σ_i c_i θ_i(t) [+ c_a θ_a(t)] + d + G(x)

with the optional measured drive ``θ_a``: the rise of a structure/ambient sensor
above its first sample in the log, through its own lag ``dθa/dt = (ΔT_s − θa)/τa``.

Why this form. A physical RC ladder (node 1 heated, node i exchanging heat with
nodes i±1, the last node with the ambient) has n distinct real negative
eigenvalues, so every node temperature, and every linear combination of them, is
``Σ_j g_j·L_j[q]`` with ``L_j`` the first-order lag of time constant ``τ_j`` (its
eigen-modes). The cascade above with free gains c spans exactly that set: by
partial fractions, ``span{L_1, L_1 L_2, ..., L_1...L_n} = span{L_1, ..., L_n}``
for distinct τ. So the cascade with free output gains represents every ladder's
displacement response, with n time constants instead of 2n−1 capacities and
resistances (which the displacement alone cannot identify). The exchange with the
ambient is what makes every eigenvalue strictly negative: each node relaxes to a
finite rise under a constant heat input (unit static gain per node), and all
rises are counted from the ambient at rest. A varying ambient or structure
temperature enters through the measured drive θ_a. The cascade (rather than a
parallel sum of lags) stays well defined when two τ coincide (it then holds the
``t·exp(−t/τ)`` mode) and is what a compensator runs (one lag after another).
After identification the τ are reported in ascending order (the gains re-solved
at the sorted τ, the same fit: the span does not depend on the order).

Simulation. The operating samples, turned into heat ``q`` sample by sample, are
held from one sample to the next (zero-order hold) and averaged exactly over the
intervals of a uniform grid of ``step_s`` from the run's FIRST PROCESS SAMPLE; the
chain is discretised exactly for an input constant over each step (matrix
exponential of the augmented ``[[A, B], [0, 0]]·step_s``; the discrete ``A_d`` is
lower triangular, so the nodes are computed one after another by first-order
:func:`scipy.signal.lfilter` sections); the node states are interpolated linearly
in time to the reading times. A run's process log may start long before its first
reading (the history, or lead-in, of a segment of a long test): the simulation
always starts at the log's first sample and only the readings are fitted and
predicted. Before the log starts the machine is taken at rest (θ = 0); after it
ends, the last operating value is held (:mod:`thermbench.models.lumped_drive`).

Identification: :mod:`thermbench.models.lumped_search` (variable projection, as
:mod:`thermbench.models.physics`).

The target is ``error_um`` of the training readings. At a fixed-point channel (a
spindle's drift at the test mandrel, every ``target_mm`` 0) the geometric part is
``Polynomial([0.0])`` and the offset ``d`` is part of the thermal part (as the
MLR families' regression constant), so ``predict`` = geometric + thermal is the
fitted value. On an along-axis channel the thermal part is the same at every
target (a limitation: the model has no spatial shape) and ``G`` is a polynomial of
``geometric_degree`` in position without constant term, fitted jointly.
"""

from __future__ import annotations

import math
from typing import Annotated, Any, Literal, Mapping, Optional, Sequence, Union

import numpy as np
import pandas as pd
from annotated_types import Ge, Le, Len
from scipy import sparse
from scipy.linalg import expm
from scipy.signal import lfilter
from threadpoolctl import threadpool_limits

from ..data.dataset import Dataset
from .base import Inputs, ModelError, ThermalErrorModel, _name, fallback, readings, sensor_series, temperatures_at
from .lumped_drive import _Drive, _zoh_average
from .lumped_search import _NetworkSearch
from .params import Degree, Expect, Int, Params, PositiveNumber, check_params, pair_bounds

__all__ = ["LumpedThermalNetwork", "chain_matrices"]

MOTION_COLUMNS = ("feed_mm_min", "axis_mm")  # an operating input that is the motion itself


def chain_matrices(tau_s, step_s: float) -> tuple[np.ndarray, np.ndarray]:
    """Exact zero-order-hold discretisation ``(A_d, B_d)`` of the node chain
    ``dθ1/dt = (q − θ1)/τ1, dθi/dt = (θ_{i−1} − θi)/τi`` over ``step_s``:
    ``θ[k+1] = A_d θ[k] + B_d q[k]`` for ``q`` constant over the step."""
    tau = np.asarray(tau_s, dtype=float)
    n = tau.size
    m = np.zeros((n + 1, n + 1))
    m[np.arange(n), np.arange(n)] = -1.0 / tau
    m[np.arange(1, n), np.arange(n - 1)] = 1.0 / tau[1:]
    m[0, n] = 1.0 / tau[0]
    e = expm(m * step_s)
    return e[:n, :n], e[:n, n]


NodeCount = Annotated[Int, Ge(1), Le(6)]


class LumpedThermalNetworkParams(Params):
    n_nodes: Annotated[
        Union[NodeCount, Annotated[list[NodeCount], Len(min_length=1)]],
        Expect("an integer 1..6 or a non-empty list of them"),
    ]
    operating: Annotated[
        Optional[Union[str, Annotated[list[str], Len(1, 1)]]],
        Expect("one process column name (e.g. 'spindle_rpm') or None"),
    ]
    u_ref: Optional[PositiveNumber]
    exponent: Optional[PositiveNumber]
    exponent_bounds: Optional[pair_bounds()]  # needed when the exponent is identified (exponent None)
    tau_bounds_s: pair_bounds()
    ambient_sensor: Optional[str]  # None, "auto" or a sensor of the dataset (checked at fit)
    preprocess: Any  # checked by thermbench.preprocess.filters.resolve_steps
    step_s: PositiveNumber
    n_starts: Annotated[Int, Ge(1)]
    geometric_degree: Degree
    sensors: Annotated[
        Optional[Union[Literal["all", "auto"], Annotated[Sequence[str], Len(min_length=1)]]],
        Expect("None, 'all', 'auto' or a non-empty list of sensor names"),
    ]
    max_sensors: Annotated[Int, Ge(1)]
    terms: Annotated[
        Optional[Mapping[str, Optional[Mapping[str, Any]]]],
        Expect("None or {term: {parameter: value}} of thermbench.models.spindle_terms"),
    ]
    identify: Annotated[Optional[Sequence[str]], Expect("None (all) or a list of parameter names, e.g. [tau1, exponent]")]
    initial: Annotated[Optional[Mapping[str, PositiveNumber]], Expect("None or {parameter: start value}")]


class LumpedThermalNetwork(_NetworkSearch, ThermalErrorModel):
    """Lumped thermal network driven by an operating signal (module docstring).

    Parameters
    ----------
    n_nodes : number of thermal nodes in the chain (1..6; default 2), or a list of
        candidates: each is identified on the operating input alone (with its own sensor
        selection when ``sensors="auto"``) and scored by the same cross-validated RMSE as
        the sensors (see ``max_sensors``: whole runs held out, each fold's network identified
        on its own training runs); the lowest wins (``node_selection_``: each candidate's score).
    operating : process column of the heat-producing operating signal (e.g.
        ``"spindle_rpm"``); None = the dataset's first operating input
        (``metadata.operating_inputs()[0]``).
    u_ref : scale of the operating signal (its unit); None = the largest ``|u|``
        over the training runs (``u_ref_``).
    exponent : the exponent p of ``q = (u/u_ref)^p``; None = identified within
        ``exponent_bounds``; a number = fixed.
    exponent_bounds : (lo, hi) of the identified exponent, 0 < lo < hi.
    tau_bounds_s : (lo, hi) of every time constant (s), 0 < lo < hi.
    ambient_sensor : None (no measured drive), a sensor name, or ``"auto"`` (the
        sensor at location ``ambient``, none if the dataset has none): its rise above
        the first sample of the run's log, through its own identified lag τ_a,
        is an additional regressor.
    sensors : measured boundary temperatures: None (none), a list of sensor names,
        ``"all"`` (every sensor of the dataset) or ``"auto"`` (chosen at fit time, see
        below). Each one's rise above the first sample of the run's log enters the
        displacement with its own gain, unlagged: the structure around the heat path,
        whose temperatures are measured, expands with them, while the nodes stand for the
        unmeasured path from the heat source.
    max_sensors : ``sensors="auto"``: at most this many. The network is identified on the
        operating input alone, then sensors are added one at a time (forward selection),
        each time the one that lowers the cross-validated RMSE most, until none lowers it
        by 3 % or more. The folds are the training runs (leave one loading state out: the
        question the benchmark asks), or five consecutive parts of a single run. The
        network is then identified again with the chosen sensors (``sensor_selection_``
        records each step's sensor and cross-validated RMSE).
    preprocess : filters for the ambient/structure sensors (``"default"`` = limit +
        Kalman of seed 002 §2.3.1; None = none; or a list of filters).
    step_s : simulation step (s); the operating log is averaged over it.
    n_starts : nonlinear searches started from the best points of the start grid.
    geometric_degree : along an axis, the degree of the geometric polynomial in
        position fitted with the gains (no constant term: that is ``d``); unused at a
        fixed point.
    terms : physical terms beyond the node chain, ``{term: {parameter: value}}``
        (:mod:`thermbench.models.spindle_terms`: ``second_heat_path``, ``structure_growth``,
        ``sensor_expansion``, ``stop_drift``): each adds its columns (lagged states) with
        gains of their own; its nonlinear parameters are identified with the base's, from
        the given values or from its own start grid. What ``thermbench diagnose`` names on a
        spindle test; the C runtime has none of them (export refuses).
    identify : the nonlinear parameters identified, by name (``tau1``..``tauN``,
        ``exponent``, ``tau_a``, ``<term>.<parameter>``); None = all. The others are held at
        ``initial`` (or the term's value); every gain is always solved.
    initial : start values by the same names (one start instead of the grid for the
        base when every ``tau<i>`` is given).

    Fitted attributes: ``tau_s_`` (ascending, s), ``exponent_``, ``gains_um_`` (µm
    per unit node rise, one per node), ``ambient_tau_s_`` and
    ``ambient_gain_um_per_C_`` (None without a drive), ``sensors_`` and
    ``sensor_gains_um_per_C_`` (the boundary temperatures), ``offset_um_`` (d),
    ``terms_`` (the terms with their identified parameters), ``term_gains_``,
    ``params_`` (every nonlinear parameter by name), ``n_params_`` (identified numbers),
    ``u_ref_``, ``operating_``, ``ambient_sensor_``, ``rmse_um_`` (training RMSE),
    ``geometric_``, ``n_evaluations_``, ``fit_s_``, ``optimizer_message_``.
    """

    complexity = 2  # ThermalErrorModel.complexity

    needs = ("operating",)  # the heat comes from an operating signal (its own parameter or the dataset's)
    params_model = LumpedThermalNetworkParams

    def __init__(
        self,
        n_nodes=2,
        operating=None,
        u_ref=None,
        exponent=None,
        exponent_bounds=(0.5, 2.5),
        tau_bounds_s=(60.0, 2.0e5),
        ambient_sensor=None,
        preprocess="default",
        step_s=60.0,
        n_starts=3,
        geometric_degree=3,
        sensors=None,
        max_sensors=4,
        terms=None,
        identify=None,
        initial=None,
    ):
        self.n_nodes = n_nodes
        self.operating = operating
        self.u_ref = u_ref
        self.exponent = exponent
        self.exponent_bounds = exponent_bounds
        self.tau_bounds_s = tau_bounds_s
        self.ambient_sensor = ambient_sensor
        self.preprocess = preprocess
        self.step_s = step_s
        self.n_starts = n_starts
        self.geometric_degree = geometric_degree
        self.sensors = sensors
        self.max_sensors = max_sensors
        self.terms = terms
        self.identify = identify
        self.initial = initial

    # ------------------------------------------------------------ checks ---
    def _operating_name(self, ds: Dataset, op: str | list[str] | None) -> str:
        """The operating column (``op``: the checked ``operating`` parameter)."""
        if op is None:
            inputs = ds.metadata.operating_inputs()
            if not inputs:
                raise ModelError(f"operating: the dataset {_name(ds)} declares no operating input (metadata "
                                 f"'operating'); name the process column that drives the heat, e.g. operating=spindle_rpm")  # fmt: skip
            return str(inputs[0])
        return op if isinstance(op, str) else op[0]  # a one-item list (a config list) names one column

    def _operating_values(self, ds: Dataset, run: str, col: str, fractional: bool) -> tuple[np.ndarray, np.ndarray]:
        pr = ds.process_run(run)
        if col not in pr.columns:
            raise ModelError(f"operating: column {col!r} is not in the process log of run {run!r}; "
                             f"columns: {list(pr.columns)}")  # fmt: skip
        t = pr["t_s"].to_numpy(dtype=float)
        u = pd.to_numeric(pr[col], errors="coerce").to_numpy(dtype=float)
        if not np.isfinite(u).all():
            raise ModelError(f"operating: column {col!r} of run {run!r} has non-numeric or missing values")
        if t.size == 0:
            raise ModelError(f"run {run!r} has no process samples: nothing drives the thermal network")
        if fractional and (u < 0).any():
            raise ModelError(f"operating: column {col!r} of run {run!r} is negative (min {u.min():g}); the heat "
                             "(u/u_ref)^p needs u >= 0 when the exponent is identified or not an integer")  # fmt: skip
        return t, u

    def _ambient_name(self, ds: Dataset) -> str | None:
        a = self.ambient_sensor
        if a is None:
            return None
        if a == "auto":
            name = next((s for s, loc in ds.metadata.sensors.items() if loc == "ambient"), None)
            if name is None:
                fallback("ambient_sensor auto: the dataset has no sensor at location 'ambient'; "
                         "the network is driven by the operating input alone")  # fmt: skip
            return name
        if a not in ds.metadata.sensors:
            raise ModelError(f"ambient_sensor: {a!r} is not a sensor of the dataset {_name(ds)}; expected None, "
                             f"'auto' or one of {list(ds.metadata.sensors)}")  # fmt: skip
        return a

    # ------------------------------------------------------- simulation ---
    def _drive(self, ds: Dataset, run: str, t_s: np.ndarray) -> _Drive:
        """The run's operating log on the grid from its first process sample (lead-in
        included), and the grid positions of the times ``t_s``."""
        h = self.step_
        t, u = self._operating_values(ds, run, self.operating_, self.fractional_)
        t0 = float(t[0])
        t_end = max(float(t[-1]), float(np.max(t_s)) if t_s.size else t0)
        n = max(int(math.ceil((t_end - t0) / h - 1e-9)), 1)
        grid = t0 + h * np.arange(n + 1)
        gidx = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 1)
        gfrac = grid - t[gidx]
        def rise_avg(sensor: str) -> np.ndarray:
            s = sensor_series(ds, run, [sensor], self.preprocess)
            ts = s["t_s"].to_numpy(dtype=float)
            y = s[ds.metadata.sensor_column(sensor)].to_numpy(dtype=float)
            sidx = np.clip(np.searchsorted(ts, grid, side="right") - 1, 0, ts.size - 1)
            # before the sensor's first sample: its first value (rise 0)
            return _zoh_average(ts, y - y[0], sidx, np.maximum(grid - ts[sidx], 0.0), h)

        rise = rise_avg(self.ambient_sensor_) if self.ambient_sensor_ is not None else None
        terms = getattr(self, "terms_", [])
        signals = {x: rise_avg(x) for x in dict.fromkeys(x for term in terms for x in term.signals())}
        running = _zoh_average(t, (u > 0).astype(float), gidx, gfrac, h) if terms else None
        pos = np.clip((np.asarray(t_s, dtype=float) - t0) / h, 0.0, float(n))
        k = np.minimum(np.floor(pos).astype(int), n - 1)
        w = pos - k
        rows = np.repeat(np.arange(pos.size), 2)
        cols = np.column_stack([k, k + 1]).ravel()
        vals = np.column_stack([1.0 - w, w]).ravel()
        interp = sparse.csr_matrix((vals, (rows, cols)), shape=(pos.size, n + 1))
        return _Drive(run, h, t, u, gidx, gfrac, rise, interp, signals, running)

    def _states(self, dr: _Drive, tau: np.ndarray, p: float, tau_a: float | None, own: Sequence[dict] = ()) -> np.ndarray:
        """Node rises, the lagged ambient rise and the terms' columns (``own``: each term's
        nonlinear parameters) at the grid times, shape (n_steps+1, m)."""
        q = dr.heat(self.u_ref_, p)
        ad, bd = chain_matrices(tau, dr.h)
        n = tau.size
        x = np.zeros((dr.n_steps + 1, n + (tau_a is not None)))
        for i in range(n):
            w = bd[i] * q
            for j in range(i):
                w = w + ad[i, j] * x[:-1, j]
            x[1:, i] = lfilter([1.0], [1.0, -ad[i, i]], w)
        if tau_a is not None:
            a = math.exp(-dr.h / tau_a)
            x[1:, n] = lfilter([1.0 - a], [1.0, -a], dr.rise_avg)
        terms = getattr(self, "terms_", [])
        if not terms:
            return x
        cols = [term.with_params(o).columns(dr, self.u_ref_, p) for term, o in zip(terms, own or [t.params for t in terms])]
        return np.column_stack([x, *cols])

    def _unpack(self, z: np.ndarray) -> tuple[np.ndarray, float, float | None, list[dict]]:
        """(τ, p, τ_a, each term's nonlinear parameters) of the search vector ``z`` (module docstring)."""
        n = self.n_nodes_
        tau = np.exp(z[:n])
        i = n
        if self.exponent_fixed_ is None:
            p = float(z[i])
            i += 1
        else:
            p = self.exponent_fixed_
        tau_a = None
        if self.ambient_sensor_ is not None:
            tau_a = float(np.exp(z[i]))
            i += 1
        own = []
        for term in getattr(self, "terms_", []):
            o = {}
            for name in term.nonlinear:
                o[name] = float(np.exp(z[i])) if name in term.log_params else float(z[i])
                i += 1
            own.append(o)
        return tau, p, tau_a, own

    def _design(self, drives: list[_Drive], z: np.ndarray, geo: np.ndarray, rises: np.ndarray) -> np.ndarray:
        tau, p, tau_a, own = self._unpack(z)
        phi = np.vstack([dr.at(self._states(dr, tau, p, tau_a, own)) for dr in drives])
        return np.column_stack([phi, rises, np.ones(phi.shape[0]), geo])

    def _sensor_names(self, ds: Dataset) -> list[str]:
        v = self.sensors
        if v is None:
            return []
        if v == "all":
            return list(ds.metadata.sensors)
        if v == "auto":
            raise ModelError("sensors: 'auto' is resolved at fit time")  # never reached: _fit resolves it
        unknown = [x for x in v if x not in ds.metadata.sensors]
        if unknown:
            raise ModelError(f"sensors: {unknown} are not sensors of the dataset {_name(ds)}; "
                             f"it has {list(ds.metadata.sensors)}")  # fmt: skip
        return [str(x) for x in v]

    def _rises(self, ds: Dataset, run: str, t_s: np.ndarray) -> np.ndarray:
        """The boundary temperatures' rises above the first sample of the run's log at ``t_s``."""
        if not self.sensors_:
            return np.zeros((np.size(t_s), 0))
        return temperatures_at(ds, run, self.sensors_, t_s, self.preprocess, delta=True)

    # -------------------------------------------------------------- fit ---
    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        # the matrices are tiny (n+1 square, a few columns): threaded BLAS only costs time
        # (on a busy machine an expm of 3x3 took 16 ms with threads, 15 us without)
        with threadpool_limits(limits=1, user_api="blas"):
            n_nodes = check_params(self, self.params_model).n_nodes
            candidates = n_nodes if isinstance(n_nodes, list) else [n_nodes]
            if len(candidates) == 1 and self.sensors != "auto":
                self._identify(ds, runs, None, candidates[0])
                return
            # the cross-validated RMSE over runs of each node count (with its own sensor selection): the lowest wins
            scored = [(*self._select(ds, runs, n), n) for n in candidates]
            cv, sensors, steps, n = min(scored, key=lambda r: r[0])
            self._identify(ds, runs, sensors, n)
            self.node_selection_ = [(k, score) for score, _, _, k in scored]
            if self.sensors == "auto":
                self.sensor_selection_ = steps

    def gain_basis(self, dataset: Dataset, runs: Sequence[str]) -> tuple[list[str], list[tuple[np.ndarray, np.ndarray, np.ndarray]]]:
        """At the identified nonlinear parameters, the design of the linear part (gains, offset,
        geometric terms) on each of ``runs``: ``(names, [(0, X, y) per run])``, y the run's
        ``error_um``, so that gains g predict ``X @ g`` (the discrepancy workflow re-solves the
        gains on subsets of runs with it, as :meth:`PhysicsModel.gain_basis`)."""
        self._check_fitted()
        out = []
        for run in runs:
            rd = readings(dataset, [run])
            t = rd["t_s"].to_numpy(dtype=float)
            X = np.column_stack([self.simulate(dataset, run, t), self._rises(dataset, run, t), np.ones(t.size)])
            y = rd["error_um"].to_numpy(dtype=float)
            out.append((np.zeros(t.size), X, y))
        names = [f"c{i + 1}" for i in range(self.n_nodes_)] + (["c_a"] if self.ambient_tau_s_ is not None else [])
        names += [f"{t.key}.{g}" for t in self.terms_ for g in t.gains] + [f"s_{x}" for x in self.sensors_] + ["d"]
        return names, out

    # ---------------------------------------------------------- predict ---
    def simulate(self, dataset: Dataset, run: str, t_s) -> np.ndarray:
        """The fitted network's node rises at times ``t_s`` of ``run``, shape (len(t_s), n_nodes
        [+ 1 for the lagged ambient rise]), simulated from the first sample of the run's log."""
        self._check_fitted()
        if self.ambient_sensor_ is not None and self.ambient_sensor_ not in dataset.metadata.sensors:
            raise ModelError(f"the model was identified with ambient_sensor {self.ambient_sensor_!r}, which this "
                             f"dataset lacks; sensors: {list(dataset.metadata.sensors)}")  # fmt: skip
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        dr = self._drive(dataset, run, t)
        tau, p, tau_a, own = self._unpack(self._z_)
        with threadpool_limits(limits=1, user_api="blas"):
            return dr.at(self._states(dr, tau, p, tau_a, own))

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        if t_s.size == 0:
            return np.zeros(0)
        phi = self.simulate(ds, run, t_s)
        na = self._n_states_
        out = phi @ self._coef_[:na] + self._coef_[-1]
        if self.sensors_:
            out = out + self._rises(ds, run, t_s) @ self._coef_[na:-1]
        return out

    #: the exact discretisation of the node chain (:func:`chain_matrices`), for the export's encoder
    chain_matrices = staticmethod(chain_matrices)

    def export_encoding(self, channels, period_s, where):
        """The C runtime's ``LUMPED`` kind (:func:`thermbench.export.lumped_encoding.encode_lumped`)."""
        from ..export.lumped_encoding import encode_lumped

        if getattr(self, "terms_", None):
            raise ModelError(f"the C runtime's LUMPED kind has no terms beyond the node chain; this network has "
                             f"{[t.key for t in self.terms_]}: export it without terms")  # fmt: skip
        return encode_lumped(self, channels, period_s, where)

    def _model_inputs(self) -> Inputs:
        amb = self.ambient_sensor_
        extra = tuple(x for t in getattr(self, "terms_", []) for x in t.signals())
        return Inputs(
            sensors=tuple(dict.fromkeys(((amb,) if amb else ()) + tuple(self.sensors_) + extra)),
            motion=self.operating_ in MOTION_COLUMNS,  # a feed-driven network reads the motion log
            ambient=self.ambient_location_ == "ambient",
            operating=(self.operating_,),
        )
