"""Auto-regressive thermal error model driven by operating parameters (seed 003).

Seed 003 is a fragment. What it states: the thermal error is "characterized by
an auto regressive model based on spindle rotation speed"; the errors and the
speed are "sampled by every 10 min"; no temperature sensors are used (their
wiring and cost are the problem the paper avoids); the error at other
coordinates comes from "an interpolating function" over a few measuring points;
the compensation is computed "as soon as the workpiece NC machining program is
made", i.e. ahead, from the planned operation only. The model equations are in
the missing part.

Our reading (:class:`AutoRegressiveSeed003`), for a feed axis:

* the thermal error curve over the axis is described per measuring cycle by
  polynomial coefficients ``c_i`` in (P - origin): a line, or a parabola for a
  fixed-fixed screw (seed 004's shapes, :func:`~thermbench.models.separation.cycle_curves`);
  the cold-state coefficients (cycle 0) are subtracted so that every run starts
  from ``c(0) = 0``;
* each coefficient series, interpolated linearly onto a uniform grid
  ``t_k = t_start + k·sample_s`` (600 s, seed 003's 10 min), follows an ARX model
  ``c(k) = Σ_{i=1..na} a_i c(k-i) + Σ_{j=0..nb-1} b_j·u(k-j) + d``,
  where ``u(k)`` is the vector of operating parameters averaged over the interval
  ``[t_{k-1}, t_k)`` (the feed in place of seed 003's spindle speed; any numeric
  process column, and powers of one written ``"feed_mm_min^2"``); before the run
  start the machine is at rest and cold: ``c(k) = 0, u(k) = 0`` for ``k <= 0``;
* the parameters are fitted by least squares (:func:`numpy.linalg.lstsq`) on all
  grid steps of the training runs, one ARX per coefficient;
* a prediction is a free-run simulation from ``c(0) = 0`` driven by ``u`` alone
  (no measured error, no temperature: what seed 003 can compute from the
  planned program), linearly interpolated in time;
* the geometric error is the mean residual of the cycle curves at each measuring
  point (seed 004) plus the mean cold-state curve of the training runs.
"""

from __future__ import annotations

import re

import numpy as np
import pandas as pd

from ..data.io import Dataset
from .base import Inputs, ModelError, curve_degree, ThermalErrorModel, readings, require
from .mlr import check_degree_or_none, check_int, check_real, lstsq_fit
from .separation import curve_at, cycle_curves, geometric_from_residuals, shape_degree

__all__ = ["AutoRegressiveSeed003", "parse_operating"]

_TERM = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\^\s*([0-9]*\.?[0-9]+))?\s*$")


def parse_operating(operating) -> list[tuple[str, float]]:
    """``("feed_mm_min", "feed_mm_min^2")`` -> ``[("feed_mm_min", 1.0), ("feed_mm_min", 2.0)]``."""
    if isinstance(operating, str):
        operating = [operating]
    try:
        terms = [str(o) for o in operating]
    except TypeError:
        raise ModelError(f"operating must be a list of process column names, got {operating!r}") from None
    if not terms:
        raise ModelError("operating: an empty list; name at least one process column (e.g. 'feed_mm_min')")
    out = []
    for term in terms:
        m = _TERM.match(term)
        if m is None:
            raise ModelError(f"operating: {term!r} is not '<column>' or '<column>^<power>' (e.g. 'feed_mm_min^2')")
        power = float(m.group(2)) if m.group(2) else 1.0
        if power <= 0:
            raise ModelError(f"operating: the power in {term!r} must be > 0")
        out.append((m.group(1), power))
    if len(set(out)) != len(out):
        raise ModelError(f"operating: a term is listed twice: {terms}")
    return out


class _GeometricPlusCurve:
    """Geometric error = residual-based part + the mean cold-state curve polynomial in (x - origin)."""

    def __init__(self, base, coef: np.ndarray, origin_mm: float) -> None:
        self.base = base
        self.coef = np.asarray(coef, dtype=float)
        self.origin_mm = float(origin_mm)

    def __call__(self, x):
        x = np.asarray(x, dtype=float)
        return self.base(x) + np.polynomial.polynomial.polyval(x - self.origin_mm, self.coef)


class AutoRegressiveSeed003(ThermalErrorModel):
    """Seed 003 auto-regressive (ARX) thermal error model without temperature sensors.

    See the module docstring for the model and why it is our reading of the
    fragment. Parameters:

    * ``na`` (>= 0), ``nb`` (>= 1): orders of the auto-regressive and input parts;
    * ``sample_s``: grid step (seed 003: 10 min);
    * ``operating``: process columns averaged per interval as inputs, ``"col^p"``
      for the average of col**p (e.g. heat ~ feed² terms);
    * ``mounting``: curve shape override (None: the dataset's screw mounting);
    * ``geometric_degree``: None keeps the per-target geometric table, an int fits
      a polynomial to it;
    * ``origin_mm``: where P - origin = 0 in the curve polynomials.

    Fitted: ``ar_coef_`` (n_coef, na) = a_i, ``input_coef_`` (n_coef, nb, n_u) =
    b_j per input, ``offset_`` (n_coef,) = d, ``ar_roots_`` (roots of
    z^na - a_1 z^(na-1) - ... - a_na per coefficient), ``cold_coef_``,
    ``shape_degree_``, ``operating_``, ``geometric_``.
    Fitting raises :class:`ModelError` when a fitted AR part is not stable (a root
    on or outside the unit circle): its free-run simulation would diverge.
    """

    def __init__(
        self,
        na=2,
        nb=2,
        sample_s=600.0,
        operating=None,
        mounting=None,
        geometric_degree=None,
        origin_mm=0.0,
    ):
        self.na = na
        self.nb = nb
        self.sample_s = sample_s
        self.operating = operating
        self.mounting = mounting
        self.geometric_degree = geometric_degree
        self.origin_mm = origin_mm

    def _model_inputs(self) -> Inputs:
        """The operating columns and the motion log; no temperature sensors (seed 003)."""
        ops = getattr(self, "operating_", None) or parse_operating(self.operating or ("feed_mm_min",))
        cols = tuple(dict.fromkeys(c for c, _ in ops))
        return Inputs(operating=cols, motion=True)

    # --- inputs -----------------------------------------------------------
    def _inputs(self, ds: Dataset, run: str, edges: np.ndarray) -> np.ndarray:
        """u(k), k = 1..len(edges)-1: the operating terms averaged over the process
        samples in [edges[k-1], edges[k])."""
        pr = ds.process_run(run)
        t = pr["t_s"].to_numpy()
        cols = []
        for col, power in self.operating_:
            if col not in pr.columns:
                raise ModelError(
                    f"operating: column {col!r} is not in the process log of run {run!r}; "
                    f"columns: {list(pr.columns)}"
                )
            v = pd.to_numeric(pr[col], errors="coerce").to_numpy(dtype=float)
            if not np.isfinite(v).all():
                raise ModelError(f"operating: column {col!r} of run {run!r} has non-numeric or missing values")
            if power != 1.0 and (v < 0).any():
                raise ModelError(f"operating: column {col!r} of run {run!r} is negative; cannot raise it to {power}")
            cols.append(v**power)
        V = np.column_stack(cols)
        n = len(edges) - 1
        U = np.empty((n, V.shape[1]))
        lo = np.searchsorted(t, edges[:-1], side="left")
        hi = np.searchsorted(t, edges[1:], side="left")
        for k in range(n):
            if hi[k] > lo[k]:
                U[k] = V[lo[k] : hi[k]].mean(axis=0)
            else:  # no sample inside the interval: the value interpolated at its middle
                mid = 0.5 * (edges[k] + edges[k + 1])
                U[k] = [np.interp(mid, t, V[:, j]) for j in range(V.shape[1])]
        return U

    def _grid(self, t0: float, t1: float, cover: bool) -> np.ndarray:
        """Grid t0, t0 + Δ, ... up to t1 (``cover``: one more step so t1 is inside)."""
        n = (t1 - t0) / self.sample_
        k = int(np.ceil(n - 1e-9)) if cover else int(np.floor(n + 1e-9))
        return t0 + self.sample_ * np.arange(max(k, 0) + 1)

    def _regressors(self, c_hist: np.ndarray, u_hist: np.ndarray, k: int) -> np.ndarray:
        """phi(k) = [c(k-1)..c(k-na), u(k)..u(k-nb+1), 1]; histories are zero-padded at rest."""
        na, nb = self.na_, self.nb_
        # c_hist[k] = c(k) with c_hist index 0 = k=0; u_hist[k] = u(k), u_hist[0] = 0 (rest)
        cs = [c_hist[k - i] if k - i >= 0 else 0.0 for i in range(1, na + 1)]
        us = [u_hist[k - j] if k - j >= 1 else np.zeros(u_hist.shape[1]) for j in range(nb)]
        return np.concatenate([np.asarray(cs, dtype=float), *us, [1.0]])

    # --- fit --------------------------------------------------------------
    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        self.na_ = check_int("na", self.na, 0)
        self.nb_ = check_int("nb", self.nb, 1)
        self.sample_ = check_real("sample_s", self.sample_s, positive=True)
        origin = check_real("origin_mm", self.origin_mm)
        gdeg = check_degree_or_none("geometric_degree", self.geometric_degree)
        # None: the dataset's operating inputs (feed on an axis, spindle speed on a spindle)
        self.operating_ = parse_operating(self.operating if self.operating is not None else ds.metadata.operating_inputs())
        degree = curve_degree(ds, self.mounting)
        self.origin_ = origin
        names_c = [f"c{i}" for i in range(degree + 1)]

        rd = readings(ds, runs)
        curves, resid = cycle_curves(rd, degree, origin)
        colds, rows_phi, rows_c = [], [], []
        for run in runs:
            cr = curves[curves["run_id"] == run].sort_values("t_s")
            cold = cr[cr["cycle"] == 0]
            if cold.empty:
                raise ModelError(
                    f"run {run!r}: its cold reference cycle (cycle 0) has too few distinct targets for a "
                    f"degree-{degree} curve; the AR model needs it to start from c(0) = 0"
                )
            c0 = cold[names_c].to_numpy()[0]
            colds.append(c0)
            t0 = float(ds.process_run(run)["t_s"].iloc[0])
            later = cr[cr["cycle"] > 0]
            if later.empty:
                continue
            tk = np.r_[t0, cold["t_s"].to_numpy(), later["t_s"].to_numpy()]
            ck = np.vstack([np.zeros((2, degree + 1)), later[names_c].to_numpy() - c0])
            grid = self._grid(t0, float(tk[-1]), cover=False)
            if grid.size < 2:
                continue
            C = np.column_stack([np.interp(grid, tk, ck[:, i]) for i in range(degree + 1)])
            U = np.vstack([np.zeros((1, len(self.operating_))), self._inputs(ds, run, grid)])
            for k in range(1, grid.size):
                # phi uses c(k-1..) from C, the coefficient index picked later
                rows_phi.append((C, U, k))
                rows_c.append(C[k])
        n_unknown = self.na_ + self.nb_ * len(self.operating_) + 1
        require(
            len(rows_c),
            n_unknown + 1,
            f"grid steps (sample_s={self.sample_:g} s) with a measured error curve in runs {runs} "
            f"for an ARX fit with na={self.na_}, nb={self.nb_}, {len(self.operating_)} input(s)",
        )
        Ctarget = np.vstack(rows_c)
        term_names = (
            [f"a{i}" for i in range(1, self.na_ + 1)]
            + [f"b{j}[{c}^{p:g}]" for j in range(self.nb_) for c, p in self.operating_]
            + ["d"]
        )
        nu = len(self.operating_)
        ar = np.zeros((degree + 1, self.na_))
        inp = np.zeros((degree + 1, self.nb_, nu))
        off = np.zeros(degree + 1)
        roots = []
        for i in range(degree + 1):
            Phi = np.vstack([self._regressors(C[:, i], U, k) for C, U, k in rows_phi])
            theta = lstsq_fit(Phi, Ctarget[:, i], term_names, f"ARX fit of curve coefficient c{i}")
            ar[i] = theta[: self.na_]
            inp[i] = theta[self.na_ : self.na_ + self.nb_ * nu].reshape(self.nb_, nu)
            off[i] = theta[-1]
            r = np.roots(np.r_[1.0, -ar[i]]) if self.na_ else np.zeros(0)
            roots.append(r)
            if r.size and np.max(np.abs(r)) >= 1.0:
                raise ModelError(
                    f"the fitted auto-regressive part of curve coefficient c{i} is unstable: roots "
                    f"{np.round(r, 4).tolist()} (|z| >= 1) for a = {np.round(ar[i], 6).tolist()}; a free-run "
                    f"simulation would diverge. Use a smaller na, a longer sample_s, or longer training runs "
                    f"that include cooling"
                )
        self.ar_coef_, self.input_coef_, self.offset_, self.ar_roots_ = ar, inp, off, roots
        self.shape_degree_ = degree
        self.cold_coef_ = np.mean(colds, axis=0)
        self.geometric_ = _GeometricPlusCurve(geometric_from_residuals(rd, resid, gdeg), self.cold_coef_, origin)

    # --- predict ----------------------------------------------------------
    def simulate(self, dataset: Dataset, run: str) -> tuple[np.ndarray, np.ndarray]:
        """Free-run simulation over the run's process log: grid times and the
        coefficients relative to the cold state, shape (n_grid, degree+1)."""
        self._check_fitted()
        pr = dataset.process_run(run)
        t0, t1 = float(pr["t_s"].iloc[0]), float(pr["t_s"].iloc[-1])
        grid = self._grid(t0, t1, cover=True)
        if grid.size < 2:
            grid = np.array([t0, t0 + self.sample_])
        # the last (partial) interval ends with the log, its final sample included
        edges = np.minimum(grid, np.nextafter(t1, np.inf))
        U = np.vstack([np.zeros((1, len(self.operating_))), self._inputs(dataset, run, edges)])
        C = np.zeros((grid.size, self.shape_degree_ + 1))
        for i in range(self.shape_degree_ + 1):
            theta = np.r_[self.ar_coef_[i], self.input_coef_[i].ravel(), self.offset_[i]]
            for k in range(1, grid.size):
                C[k, i] = self._regressors(C[:, i], U, k) @ theta
        return grid, C

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        grid, C = self.simulate(ds, run)
        c = np.column_stack([np.interp(t_s, grid, C[:, i]) for i in range(C.shape[1])])
        return curve_at(c, axis_mm - self.origin_)
