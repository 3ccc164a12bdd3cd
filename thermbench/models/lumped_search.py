"""Identifying the lumped network (:class:`~thermbench.models.lumped.LumpedThermalNetwork`): the
nonlinear search over its time constants, exponent and terms, and the choice of its node count and
sensors by cross-validated RMSE.

Identification (variable projection, as :mod:`thermbench.models.physics`). The
output is linear in the gains ``c``, ``c_a``, the offset ``d`` and the geometric
polynomial ``G``: for given nonlinear parameters (log τ_i, p, log τ_a) they are
the least-squares solution, so the nonlinear search
(:func:`scipy.optimize.least_squares`, trust-region reflective within bounds) sees
only the residual of that solution. The starts are the best ``n_starts`` points of
a deterministic grid (eight log-spaced values per τ, ascending τ combinations;
three exponents; four τ_a), each evaluated by the same inner least squares.
Each search stops at a relative change of 1e-6 in the cost or the parameters: the
cost has flat valleys (two time constants trading places with their gains) along
which tighter tolerances take several times more evaluations for an RMSE change
below 1e-6. Nothing is random.
"""

from __future__ import annotations

import itertools
import math
import time

import numpy as np
from numpy.polynomial import Polynomial
from scipy.linalg import LinAlgError, cho_factor, cho_solve
from scipy.optimize import least_squares
from sklearn.linear_model import LinearRegression

from ..bench.splits import row_folds
from ..data.dataset import Dataset
from .base import ModelError, _name, readings, require, temperatures_at
from .mlr import lstsq_fit
from .params import check_params
from .spindle_terms import SPINDLE_TERMS, base_id, make_term

_GRID_TAU = 8  # log-spaced start values per time constant
_GRID_TAU_A = 4  # start values of the ambient lag
_GRID_P = 3  # start values of the exponent


def _residual(X: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``y − X c`` of the linear least-squares solution ``c`` (the projection of variable
    projection): column-scaled semi-normal equations with one refinement step (as accurate
    as QR for these few, scaled columns, and several times faster on 10⁴ readings), plain
    :func:`numpy.linalg.lstsq` when the Gram matrix is near singular."""
    s = np.max(np.abs(X), axis=0)
    s[s == 0] = 1.0
    xs = X / s
    try:
        cf = cho_factor(xs.T @ xs, check_finite=False)
        d = np.abs(np.diag(cf[0]))
        if d.min() < 1e-6 * d.max():  # condition number of the Gram matrix > 1e12
            raise LinAlgError("near singular")
        c = cho_solve(cf, xs.T @ y, check_finite=False)
        r = y - xs @ c
        return r - xs @ cho_solve(cf, xs.T @ r, check_finite=False)
    except LinAlgError:
        return y - xs @ np.linalg.lstsq(xs, y, rcond=None)[0]



class _NetworkSearch:
    """The identification of :class:`~thermbench.models.lumped.LumpedThermalNetwork` (a base class of
    it: these methods read and set its parameters and fitted attributes, and call its simulation)."""

    # --------------------------------------------------------- selection ---
    def _select(self, ds: Dataset, runs: list[str], n: int) -> tuple[float, list[str] | None, list]:
        """For ``n`` nodes: the network identified on the operating input alone, then the sensors
        (``sensors="auto"``: forward selection by cross-validated RMSE, see ``max_sensors``;
        else the given ones) scored with it. Returns (cross-validated RMSE, sensors, steps)."""
        k_max = check_params(self, self.params_model).max_sensors
        auto = self.sensors == "auto"
        cands = list(ds.metadata.sensors) if auto else self._sensor_names(ds)
        if auto and not cands:
            raise ModelError(f"sensors: 'auto' needs temperature sensors; the dataset {_name(ds)} has none")
        rd = readings(ds, runs)
        scored = [r for r in runs if (rd["run_id"] == r).any()]
        times = {r: rd.loc[rd["run_id"] == r, "t_s"].to_numpy(dtype=float) for r in scored}
        rises = np.vstack([temperatures_at(ds, r, cands, times[r], self.preprocess, delta=True) for r in scored])
        y = np.concatenate([rd.loc[rd["run_id"] == r, "error_um"].to_numpy(dtype=float) for r in scored])
        run_of = np.concatenate([np.full(times[r].size, r, dtype=object) for r in scored])
        folds = row_folds(run_of)  # whole runs held out (one run: five consecutive parts of it)

        def network_on(train_runs: list[str]) -> np.ndarray:
            """The network identified on the operating input alone on ``train_runs``, simulated at every reading."""
            base = type(self)(**{**self.get_params(), "sensors": None, "n_nodes": n})
            base._identify(ds, train_runs, [], n)
            base.train_runs_ = list(train_runs)
            return np.vstack([base.simulate(ds, r, times[r]) for r in scored])

        # each fold's network identified on its own training runs (its time constants and exponent never
        # see the runs it holds out); one run: identified on it, only the gains are cross-validated
        every = network_on(scored)
        phis = [network_on(list(dict.fromkeys(run_of[tr]))) if len(scored) > 1 else every for tr, _ in folds]

        def cv_rmse(cols: list[int]) -> float:  # the gains by least squares on each fold's training rows
            sq = 0.0
            for (tr, te), phi in zip(folds, phis):
                X = np.column_stack([phi, rises[:, cols], np.ones(y.size)])
                fit = LinearRegression(fit_intercept=False).fit(X[tr], y[tr])
                sq += float(np.sum((fit.predict(X[te]) - y[te]) ** 2))
            return math.sqrt(sq / y.size)

        if not auto:  # the given sensors: only scored
            return cv_rmse(list(range(len(cands)))), None, []
        chosen: list[int] = []
        best = cv_rmse(chosen)
        steps = [("(operating input only)", best)]
        while len(chosen) < min(k_max, len(cands)):
            score, j = min((cv_rmse(chosen + [j]), j) for j in range(len(cands)) if j not in chosen)
            if score > 0.97 * best:
                break
            chosen.append(j)
            best = score
            steps.append((cands[j], score))
        return best, [cands[j] for j in chosen], steps

    def _identify(self, ds: Dataset, runs: list[str], sensors: list[str] | None = None, n_nodes: int = 2) -> None:
        t_start = time.perf_counter()
        prm = check_params(self, self.params_model)
        self.n_nodes_ = n_nodes
        self.step_ = prm.step_s
        n_starts = prm.n_starts
        tau_lo, tau_hi = prm.tau_bounds_s
        if prm.exponent is None and prm.exponent_bounds is None:
            raise ModelError(f"{type(self).__name__}.exponent_bounds: expected (lo, hi) with 0 < lo < hi to identify "
                             "the exponent (exponent is None), got None")  # fmt: skip
        p_lo, p_hi = prm.exponent_bounds or (None, None)  # used when the exponent is identified
        self.exponent_fixed_ = prm.exponent
        self.fractional_ = self.exponent_fixed_ is None or not float(self.exponent_fixed_).is_integer()
        self.operating_ = self._operating_name(ds, prm.operating)
        self.ambient_sensor_ = self._ambient_name(ds)
        self.ambient_location_ = ds.metadata.sensors.get(self.ambient_sensor_) if self.ambient_sensor_ else None
        self.sensors_ = list(sensors) if sensors is not None else self._sensor_names(ds)

        rd = readings(ds, runs)
        u_max = 0.0
        for run in runs:  # every training run's log is checked, and sets the scale
            u_max = max(u_max, float(np.max(np.abs(self._operating_values(ds, run, self.operating_, self.fractional_)[1]))))
        if prm.u_ref is None:
            if u_max <= 0.0:
                raise ModelError(f"operating: column {self.operating_!r} is zero in every training run {runs}: "
                                 "there is no heat input to identify the network from (u_ref cannot be its maximum)")  # fmt: skip
            self.u_ref_ = u_max
        else:
            self.u_ref_ = prm.u_ref

        # geometric columns in the scaled position (along an axis; none at a fixed point)
        x = rd["target_mm"].to_numpy(dtype=float)
        lo, hi = float(x.min()) if x.size else 0.0, float(x.max()) if x.size else 0.0
        gdeg = prm.geometric_degree
        if hi <= lo:
            gdeg = 0  # a fixed point: no geometric part
        else:
            n_x = np.unique(x).size
            if n_x <= gdeg:
                raise ModelError(f"geometric_degree: {gdeg} needs more than {gdeg} distinct targets, the readings have {n_x}")
        xs = (x - 0.5 * (lo + hi)) / (0.5 * (hi - lo)) if hi > lo else np.zeros_like(x)
        geo = np.column_stack([xs**k for k in range(1, gdeg + 1)]) if gdeg else np.zeros((x.size, 0))

        self.terms_ = self._make_terms(ds)
        n_term_cols = sum(len(t.gains) for t in self.terms_)
        zn, is_log, lb, ub = self._search_space(tau_lo, tau_hi, p_lo, p_hi)
        free = self._free(zn)
        n_lin = self.n_nodes_ + (self.ambient_sensor_ is not None) + n_term_cols + len(self.sensors_) + 1 + gdeg
        require(len(rd), n_lin + int(free.sum()) + 1, f"readings in runs {runs}")
        drives, order, rises = [], [], []
        for run in runs:
            m = (rd["run_id"] == run).to_numpy()
            if m.any():
                drives.append(self._drive(ds, run, rd.loc[m, "t_s"].to_numpy(dtype=float)))
                rises.append(self._rises(ds, run, rd.loc[m, "t_s"].to_numpy(dtype=float)))
                order.append(np.flatnonzero(m))
        order = np.concatenate(order)
        rises = np.vstack(rises)
        y = rd["error_um"].to_numpy(dtype=float)[order]
        geo = geo[order]
        if not np.isfinite(y).all():
            raise ModelError("error_um of the training readings has NaN/inf values")

        n_eval = 0

        def solve(z):
            nonlocal n_eval
            n_eval += 1
            return _residual(self._design(drives, z, geo, rises), y)

        grid = self._start_grid(zn, is_log, lb, ub, p_lo, p_hi)
        costs = np.array([np.sum(solve(z) ** 2) for z in grid])
        best, z = None, grid[int(np.argmin(costs))].copy()
        self.optimizer_message_ = "nothing identified: every nonlinear parameter held"
        if free.any():
            for i in np.argsort(costs, kind="stable")[:n_starts]:
                z0 = grid[i]

                def solve_free(zf, z0=z0):
                    zz = z0.copy()
                    zz[free] = zf
                    return solve(zz)

                x0 = np.clip(z0[free], lb[free], ub[free])
                res = least_squares(solve_free, x0, bounds=(lb[free], ub[free]), method="trf", x_scale=1.0, ftol=1e-6, xtol=1e-6)
                if best is None or res.cost < best.cost:
                    best = res
                    z = z0.copy()
                    z[free] = res.x
            self.optimizer_message_ = str(best.message)

        # canonical form: τ ascending, gains re-solved (the span is the same)
        z = z.copy()
        if free[: self.n_nodes_].all():
            z[: self.n_nodes_] = np.sort(z[: self.n_nodes_])
        tau, p, tau_a, own = self._unpack(z)
        self.terms_ = [t.with_params(o) for t, o in zip(self.terms_, own)]
        X = self._design(drives, z, geo, rises)
        names = [f"c{i + 1}" for i in range(self.n_nodes_)] + (["c_a"] if tau_a is not None else [])
        names += [f"{t.key}.{g}" for t in self.terms_ for g in t.gains]
        names += [f"s_{x}" for x in self.sensors_] + ["d"]
        names += [f"g{k}" for k in range(1, gdeg + 1)]
        coef = lstsq_fit(X, y, names, "lumped network gains")
        n = self.n_nodes_
        self.tau_s_ = tau
        self.exponent_ = float(p)
        self.gains_um_ = coef[:n].copy()
        self.ambient_tau_s_ = tau_a
        self.ambient_gain_um_per_C_ = float(coef[n]) if tau_a is not None else None
        na = n + (tau_a is not None)
        self.term_gains_ = {}
        for t in self.terms_:
            self.term_gains_[t.key] = {g: float(coef[na + j]) for j, g in enumerate(t.gains)}
            na += len(t.gains)
        k = len(self.sensors_)
        self.sensor_gains_um_per_C_ = coef[na : na + k].copy()
        self.offset_um_ = float(coef[na + k])
        gcoef = np.r_[0.0, coef[na + k + 1 :]]
        self.geometric_ = Polynomial(gcoef, domain=[lo, hi], window=[-1.0, 1.0]) if gdeg else Polynomial([0.0])
        self._coef_ = coef[: na + k + 1]
        self._n_states_ = na
        self._z_ = z
        self.params_ = {nm: float(np.exp(v)) if lg else float(v) for nm, v, lg in zip(zn, z, is_log)}
        self.n_params_ = n_lin + int(free.sum())
        self.rmse_um_ = float(np.sqrt(np.mean((y - X @ coef) ** 2)))
        self.n_evaluations_ = n_eval
        self.fit_s_ = time.perf_counter() - t_start

    # ------------------------------------------------ terms and the search ---
    def _make_terms(self, ds: Dataset) -> list:
        """The ``terms`` (:mod:`thermbench.models.spindle_terms`) checked against the dataset."""
        out = []
        for tid, params in dict(self.terms or {}).items():
            if base_id(tid) not in SPINDLE_TERMS:
                raise ModelError(f"{type(self).__name__}.terms: unknown term {tid!r}; known: {sorted(SPINDLE_TERMS)}")
            try:
                term = make_term(tid, **dict(params or {}))
            except ValueError as exc:
                raise ModelError(f"{type(self).__name__}.terms: {exc}") from None
            if term.choice:
                sig = term.params.get(term.choice)
                allowed = (["speed"] if "speed" == term.defaults.get(term.choice) else []) + list(ds.metadata.sensors)
                if sig not in allowed:
                    raise ModelError(f"{type(self).__name__}.terms.{tid}.{term.choice}: {sig!r} is not one of {allowed}")
            out.append(term)
        return out

    def _search_space(self, tau_lo, tau_hi, p_lo, p_hi):
        """Names, log flags and bounds of the search vector z: log τ_1..n | p | log τ_a | each
        term's nonlinear parameters (in log where the term says so)."""
        zn = [f"tau{i + 1}" for i in range(self.n_nodes_)]
        is_log = [True] * self.n_nodes_
        lb = [math.log(tau_lo)] * self.n_nodes_
        ub = [math.log(tau_hi)] * self.n_nodes_
        if self.exponent_fixed_ is None:
            zn.append("exponent")
            is_log.append(False)
            lb.append(p_lo)
            ub.append(p_hi)
        if self.ambient_sensor_ is not None:
            zn.append("tau_a")
            is_log.append(True)
            lb.append(math.log(tau_lo))
            ub.append(math.log(tau_hi))
        for t in self.terms_:
            for name in t.nonlinear:
                lo_, hi_ = t.bounds[name]
                lg = name in t.log_params
                zn.append(f"{t.key}.{name}")
                is_log.append(lg)
                lb.append(math.log(lo_) if lg else lo_)
                ub.append(math.log(hi_) if lg else hi_)
        return zn, is_log, np.array(lb), np.array(ub)

    def _free(self, zn: list[str]) -> np.ndarray:
        """Which entries of z are identified (``identify``; None: all)."""
        if self.identify is None:
            return np.ones(len(zn), dtype=bool)
        ident = [str(x) for x in self.identify]
        if bad := sorted(set(ident) - set(zn)):
            raise ModelError(f"{type(self).__name__}.identify: unknown parameter(s) {bad}; this network has {zn}")
        return np.array([nm in ident for nm in zn], dtype=bool)

    def _start_grid(self, zn, is_log, lb, ub, p_lo, p_hi) -> list[np.ndarray]:
        """Start points of the search: ``initial`` where given (one value), else the deterministic
        grid of the base (eight log-spaced τ per node, ascending; three exponents; four τ_a) and
        each term's own ``starts`` (its values in ``terms`` when given)."""
        init = dict(self.initial or {})
        if bad := sorted(set(init) - set(zn)):
            raise ModelError(f"{type(self).__name__}.initial: unknown parameter(s) {bad}; this network has {zn}")
        conv = {nm: (math.log(float(v)) if lg else float(v)) for nm, lg in zip(zn, is_log) if (v := init.get(nm)) is not None}
        n = self.n_nodes_
        axes = []
        if all(f"tau{i + 1}" in conv for i in range(n)):
            axes.append([tuple(conv[f"tau{i + 1}"] for i in range(n))])
        else:
            tau_grid = np.log(np.exp(np.linspace(lb[0], ub[0], _GRID_TAU + 2)[1:-1]))  # as the grid always was, to the bit
            # distinct, ascending τ: the order does not matter (module docstring); n_nodes <= 6 < 8
            axes.append(list(itertools.combinations(tau_grid, n)))
        if self.exponent_fixed_ is None:
            axes.append([(conv["exponent"],)] if "exponent" in conv else [(v,) for v in np.linspace(p_lo, p_hi, _GRID_P + 2)[1:-1]])
        if self.ambient_sensor_ is not None:
            i = zn.index("tau_a")
            axes.append([(conv["tau_a"],)] if "tau_a" in conv else [(v,) for v in np.linspace(lb[i], ub[i], _GRID_TAU_A + 2)[1:-1]])
        given = dict(self.terms or {})
        for t in self.terms_:
            for name in t.nonlinear:
                key, lg = f"{t.key}.{name}", name in t.log_params
                if key in conv:
                    values = [conv[key]]
                elif name in dict(given.get(t.key) or {}) or not t.starts.get(name):
                    values = [math.log(t.params[name]) if lg else t.params[name]]
                else:
                    values = [math.log(v) if lg else float(v) for v in t.starts[name]]
                axes.append([(v,) for v in values])
        return [np.concatenate(c) for c in itertools.product(*axes)]
