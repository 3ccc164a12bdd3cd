"""Auto-regressive thermal error model driven by operating parameters (seed 003).

Seed 003 is a fragment. What it states: the thermal error is "characterized by
an auto regressive model based on spindle rotation speed"; the errors and the
speed are "sampled by every 10 min"; no temperature sensors are used (their
wiring and cost are the problem the paper avoids); the thermal drifts are the
coordinates "deviated from the cold condition"; the error at other coordinates
comes from "an interpolating function" over a few measuring points; the
compensation is computed "as soon as the workpiece NC machining program is
made", i.e. ahead, from the planned operation only. The model equations are in
the missing part.

Our reading (:class:`AutoRegressiveSeed003`):

* the thermal error curve over the measuring points is described per measuring cycle
  by polynomial coefficients ``c_i`` in (P - origin): a line, or a parabola for a
  fixed-fixed screw (seed 004's shapes, :func:`~thermbench.models.separation.cycle_curves`);
  at a fixed point (a spindle's drift at the test mandrel) the drift itself, ``c_0``.
  The curves are fitted to ``thermal_um``, the readings' thermal error as the dataset
  defines it (:func:`~thermbench.models.base.readings`): today's runs count it from their
  cold first cycle (so c = 0 there: the numbers of the former "error minus cycle 0"),
  a segment with its history (``split_segments(ds, history=True)``) from the first
  reading of the whole test, long before the segment's first reading;
* each coefficient series, interpolated linearly between the cycles onto a uniform grid
  ``t_k = t_0 + k·sample_s`` (600 s, seed 003's 10 min) that starts at the process
  log's first sample ``t_0``, follows an ARX model
  ``c(k) = Σ_{i=1..na} a_i c(k-i) + Σ_{j=0..nb-1} b_j·u(k-j) + d``,
  where ``u(k)`` is the vector of operating parameters averaged over
  ``[t_{k-1}, t_k)`` (seed 003's spindle speed, the feed on a feed axis; any numeric
  process column, and powers of one written ``"spindle_rpm^2"``); before ``t_0`` the
  machine is at rest and cold: ``c(k) = 0, u(k) = 0`` for ``k <= 0``;
* c is known only inside the span of a run's readings. When they start with the process
  (the first cycle within one grid step of ``t_0``: today's runs) c is 0 at ``t_0`` and
  interpolated to the first cycle, and the rows k = 1, 2, ... use the rest history. With
  a history lead-in (readings from, say, 20 000 s of a log from 0 s) c between 0 s and
  the first reading is unknown, neither 0 nor the first reading: the equation-error rows
  are the k whose c(k), c(k-1)..c(k-na) all lie inside the readings' span, their u from
  the log (the history);
* ``criterion="equation"``: the parameters are the least-squares (:func:`numpy.linalg.lstsq`)
  solution of those rows, one ARX per coefficient. ``criterion="output"`` (default):
  from that solution, :func:`scipy.optimize.least_squares` minimises the free-run error
  instead, Σ (simulated c(k) - measured c(k))² over the measured grid steps, each run
  simulated from c = 0 at its log's start through its history. The AR part is searched
  through its reflection coefficients bounded to (-1, 1), so every trial is stable; a
  search that ends at that bound (the runs ask for a drift that never settles) keeps the
  equation-error fit, with a :class:`~thermbench.models.base.FallbackWarning`;
* a prediction is a free-run simulation from c = 0 at the log's first sample driven by
  ``u`` alone, through the history into the readings (no measured error, no
  temperature: what seed 003 can compute from the planned program), linearly
  interpolated in time;
* the geometric error is the mean residual of the cycle curves at each measuring point
  (seed 004) plus the mean reference curve of the training runs (reading - ``thermal_um``:
  a run's cold cycle; for segments with their history the test's first reading), so a
  prediction is reference + simulated thermal error.

Measured on fl_thermal (a real 46 h spindle test, ``load_benchmark("fl_thermal")``,
channels ch1..ch5 at the test mandrel, ``spindle_rpm`` the only input): trained on the five
constant-speed blocks (segments with their history), the stepped tail (t >= 144 465 s)
predicted free-run from 0 s; RMSE (µm) against the readings counted from the test's first row:

=========================================  ====  ====  ====  ====  ====
setting (sample_s 600 s, operating rpm)     ch1   ch2   ch3   ch4   ch5
=========================================  ====  ====  ====  ====  ====
equation, na=2, nb=2 (the former default)   3.5   3.7  20.8  21.0  16.1
equation, na=2, nb=1                        3.4   3.6  19.8  20.1  19.7
output, na=1, nb=1                          3.8   4.1  18.2  18.5  12.7
output, na=2, nb=1 (the default)            3.8   4.1  18.1  18.4   4.6
output, na=2, nb=2                          3.5   3.7  45.2  45.0   9.0
output, na=2, nb=1, rpm^2 only              2.8   3.2  21.0  21.1   7.3
output, na=2, nb=1, rpm + rpm^2             3.2   3.8  21.4  21.5   4.1
OLS on the 16 temperatures (reference)      6.3   4.5   5.7   5.9   8.8
random forest (reference)                   7.4   8.8   6.6   6.7   3.9
=========================================  ====  ====  ====  ====  ====

* The output-error fit does not depend on ``sample_s`` (600, 300, 120 and 60 s give the
  same tail RMSE within 0.1 µm); the equation-error fit gains at most 1 µm from shorter
  steps. Seed 003's 600 s stays.
* Output error with nb >= 2 overfits: b_0 ≈ -b_1 (a response to speed *changes*) and a
  slow mode that extrapolates badly (ch3/ch4 45 µm) or ends at the stability bound
  (ch1/ch2 fall back to the equation-error fit). na=2, nb=1 is the best setting on the
  tail, and trained on one block at a time it always fits (the equation-error fit is
  unstable on ch5 for the 1250, 2500 and 3500 rpm blocks).
* Speed powers: rpm² alone suits ch1/ch2 (2.8/3.2 µm), rpm + rpm² ch5 (4.1), each at the
  expense of other channels; rpm alone is the best compromise. One block at a single
  speed cannot separate rpm from rpm² (the output-error search leaves that direction at
  the equation-error split).
* Leave one block out (train on four blocks, predict the fifth, 600 s) the two criteria
  are close on average (output na=2, nb=1: 4.0/4.8/16.0/15.9/9.5 µm; equation:
  4.0/4.7/13.8/13.8/12.5 µm): the gain of the output error is in the long free run.
* ch3/ch4 (Y) are not a function of the spindle speed alone: they drift over the test in
  a way speed cannot explain (the temperature models do much better there), the limit of
  seed 003's setting.
* The equation-error fit is fragile: splitting into segments costs it the rows at each
  boundary and moves ch5 (16.1 µm with the segments, 10.5 µm with one training run from
  0 s); the output-error fit gives 4.6 µm both ways.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Optional

import numpy as np
import pandas as pd
from scipy.optimize import least_squares
from annotated_types import Ge
from scipy.signal import lfilter

from ..data.dataset import Dataset
from .base import Inputs, ModelError, ThermalErrorModel, fallback, readings, require
from .mlr import lstsq_fit
from .params import Degree, Int, Number, Params, PositiveNumber, check_params
from .separation import curve_at, curve_degree, cycle_curves, geometric_from_residuals

__all__ = ["AutoRegressiveSeed003", "parse_operating"]

_TERM = re.compile(r"^\s*([A-Za-z_][A-Za-z0-9_]*)\s*(?:\^\s*([0-9]*\.?[0-9]+))?\s*$")
CRITERIA = ("equation", "output")
_KAPPA_MAX = 1.0 - 1e-6  # output-error search: |reflection coefficient| bound (a root within 1e-6 of |z| = 1)
_ROOT_MAX = 1.0 - 1e-5  # an output-error fit that ends with a root beyond this wants an unstable model
_RCOND = 1e-3  # output-error search: input directions with a relative singular value below this stay fixed


def _step_up(kappa: np.ndarray) -> np.ndarray:
    """AR coefficients a (c(k) = Σ a_i c(k-i) + ...) from reflection coefficients κ (Levinson
    step-up of A(z) = 1 - Σ a_i z^-i); every |κ_m| < 1 gives a stable A (Schur-Cohn)."""
    alpha = np.zeros(0)
    for k in np.asarray(kappa, dtype=float):
        alpha = np.r_[alpha + k * alpha[::-1], k]
    return -alpha


def _max_root(a: np.ndarray) -> float:
    """The largest |root| of z^na - a_1 z^(na-1) - ... - a_na (0 without an AR part)."""
    a = np.asarray(a, dtype=float)
    return float(np.max(np.abs(np.roots(np.r_[1.0, -a])))) if a.size else 0.0


def _reflection(a: np.ndarray) -> np.ndarray:
    """Reflection coefficients of A(z) = 1 - Σ a_i z^-i (Levinson step-down, the inverse of
    :func:`_step_up`); a stage with |κ| >= 1 (an unstable A) is clipped to go on."""
    alpha = -np.asarray(a, dtype=float)
    out = np.zeros(alpha.size)
    for m in range(alpha.size, 0, -1):
        k = float(np.clip(alpha[-1], -_KAPPA_MAX, _KAPPA_MAX))
        out[m - 1] = k
        alpha = (alpha[:-1] - k * alpha[:-1][::-1]) / (1.0 - k * k)
    return out


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
    """Geometric error = residual-based part + the mean reference curve polynomial in (x - origin)."""

    def __init__(self, base, coef: np.ndarray, origin_mm: float) -> None:
        self.base = base
        self.coef = np.asarray(coef, dtype=float)
        self.origin_mm = float(origin_mm)

    def __call__(self, x):
        x = np.asarray(x, dtype=float)
        return self.base(x) + np.polynomial.polynomial.polyval(x - self.origin_mm, self.coef)


@dataclass
class _Series:
    """One training run on the ARX grid (index k, t_k = t_0 + k·sample_s, t_0 = the log's first sample)."""

    run: str
    U: np.ndarray  # (K+1, n_u): u(k), U[0] = 0 (nothing before the log)
    C: np.ndarray  # (K+1, D+1): the measured thermal coefficients c(k); NaN where unknown
    ee_rows: np.ndarray  # k whose equation-error regressors are all measured
    oe_rows: np.ndarray  # k >= 1 with a measured c(k)


def _curves(rd: pd.DataFrame, degree: int, origin_mm: float, column: str) -> tuple[pd.DataFrame, np.ndarray]:
    """:func:`~thermbench.models.separation.cycle_curves` of ``column``; at a fixed point
    (degree 0) the same numbers computed without a loop over the (many) cycles."""
    frame = rd if column == "error_um" else rd.assign(error_um=rd[column].to_numpy())
    if degree > 0:
        return cycle_curves(frame, degree, origin_mm)
    g = frame.groupby(["run_id", "cycle"], sort=False)
    curves = g.agg(t_s=("t_s", "mean"), c0=("error_um", "mean")).reset_index()
    resid = frame["error_um"].to_numpy() - g["error_um"].transform("mean").to_numpy()
    return curves[["run_id", "cycle", "t_s", "c0"]], resid


class AutoRegressiveSeed003Params(Params):
    na: Degree
    nb: Annotated[Int, Ge(1)]
    sample_s: PositiveNumber
    operating: Any  # checked by parse_operating
    criterion: Literal[CRITERIA]
    mounting: Optional[str]  # checked by separation.shape_degree
    geometric_degree: Optional[Degree]
    origin_mm: Number


class AutoRegressiveSeed003(ThermalErrorModel):
    """Seed 003 auto-regressive (ARX) thermal error model without temperature sensors.

    See the module docstring for the model, why it is our reading of the seed 003
    fragment, and what was measured on the fl_thermal spindle test.

    Parameters
    ----------
    na : int, >= 0
        Order of the auto-regressive part (past coefficients c(k-1)..c(k-na)).
    nb : int, >= 1
        Order of the input part (u(k)..u(k-nb+1)).
    sample_s : float, > 0
        Grid step in seconds (seed 003: "sampled by every 10 min", 600 s).
    operating : list of str or None
        Process columns averaged per interval as inputs, ``"col^p"`` for the average of
        col**p (e.g. ``["spindle_rpm", "spindle_rpm^2"]``); None: the dataset's operating inputs.
    criterion : {"equation", "output"}
        ``"equation"``: the equation-error (ARX) least-squares fit; ``"output"`` (default,
        the better on the measured spindle test, module docstring): that fit refined by
        minimising the free-run simulation error (output error) with
        :func:`scipy.optimize.least_squares`, the criterion of a model that is only ever
        run free (seed 003 predicts from the planned program).
    mounting : str or None
        Curve shape override (None: the dataset's screw mounting; a fixed point: degree 0).
    geometric_degree : int or None
        None keeps the per-target geometric table, an int fits a polynomial to it.
    origin_mm : float
        Where P - origin = 0 in the curve polynomials.

    Attributes
    ----------
    ar_coef_ : ndarray (n_coef, na)
        a_i per curve coefficient.
    input_coef_ : ndarray (n_coef, nb, n_u)
        b_j per input.
    offset_ : ndarray (n_coef,)
        d.
    ar_roots_ : list of ndarray
        Roots of z^na - a_1 z^(na-1) - ... - a_na per coefficient.
    reference_coef_ : ndarray (n_coef,)
        The mean reference curve (reading - ``thermal_um``) of the training runs.
    free_run_rmse_ : dict
        Per coefficient (``"c0"``, ...), the RMS free-run error on the measured training
        grid steps after the fit, in µm/mm^i for ``c_i`` (µm for the drift at a fixed point).

    Fitting raises :class:`ModelError` when a fitted AR part is not stable (a root on
    or outside the unit circle; output error: both fits): its free-run simulation would
    diverge.
    """

    complexity = 1  # ThermalErrorModel.complexity

    params_model = AutoRegressiveSeed003Params
    needs = ("operating",)  # its only inputs: the operating columns (its own parameter or the dataset's)

    def __init__(
        self,
        na=2,
        nb=1,
        sample_s=600.0,
        operating=None,
        criterion="output",
        mounting=None,
        geometric_degree=None,
        origin_mm=0.0,
    ):
        self.na = na
        self.nb = nb
        self.sample_s = sample_s
        self.operating = operating
        self.criterion = criterion
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

    def _series(self, ds: Dataset, run: str, cr: pd.DataFrame, names_c: list[str]) -> _Series | None:
        """The run's measured coefficient series and inputs on its grid (None: no grid step).

        The grid starts at the log's first sample t_0 (seed 003's free run starts there).
        c(k) is the thermal curve interpolated linearly between the measuring cycles, known
        only inside their span; when the first cycle lies within one grid step of t_0 (the
        readings start with the process, today's runs), c = 0 at t_0 and at rest before it."""
        t0 = float(ds.process_run(run)["t_s"].iloc[0])
        tc = cr["t_s"].to_numpy(dtype=float)
        cc = cr[names_c].to_numpy(dtype=float)
        rest = bool(tc[0] - t0 <= self.sample_ + 1e-9)
        if rest and tc[0] > t0:
            tc, cc = np.r_[t0, tc], np.vstack([np.zeros((1, cc.shape[1])), cc])
        grid = self._grid(t0, float(tc[-1]), cover=False)
        if grid.size < 2:
            return None
        known = (grid >= (t0 if rest else tc[0]) - 1e-9) & (grid <= tc[-1] + 1e-9)
        C = np.full((grid.size, cc.shape[1]), np.nan)
        for i in range(cc.shape[1]):
            C[known, i] = np.interp(grid[known], tc, cc[:, i])
        U = np.vstack([np.zeros((1, len(self.operating_))), self._inputs(ds, run, grid)])
        ks = np.arange(1, grid.size)
        oe = ks[known[1:]]
        if rest:
            ee = oe  # c(k <= 0) = 0: the machine at rest before the log starts
        else:  # every c(k-1)..c(k-na) measured
            k_first = int(np.argmax(known))
            ee = oe[oe - self.na_ >= k_first]
        return _Series(run, U, C, ee, oe)

    def _design(self, s: _Series, i: int) -> np.ndarray:
        """phi(k) = [c(k-1)..c(k-na), u(k)..u(k-nb+1), 1] of the equation-error rows of ``s``
        for coefficient ``i``; histories before the log are at rest (0)."""
        na, nb = self.na_, self.nb_
        ks = s.ee_rows
        cpad = np.r_[np.zeros(na), np.nan_to_num(s.C[:, i], nan=0.0)]
        upad = np.vstack([np.zeros((nb, s.U.shape[1])), s.U])
        cols = [cpad[ks - j + na][:, None] for j in range(1, na + 1)]
        cols += [upad[ks - j + nb] for j in range(nb)]
        cols.append(np.ones((ks.size, 1)))
        return np.hstack(cols)

    # --- the recursion ----------------------------------------------------
    def _free_run(self, U: np.ndarray, a: np.ndarray, B: np.ndarray, d: float) -> np.ndarray:
        """c(k), k = 0..K, of c(k) = Σ a_i c(k-i) + Σ_j b_j·u(k-j) + d from c(0) = 0, at rest
        before (c, u = 0 for k <= 0): the free run of seed 003, driven by ``U`` alone."""
        f = np.full(U.shape[0] - 1, float(d))
        for m in range(U.shape[1]):
            f += lfilter(B[:, m], [1.0], U[1:, m])
        return np.r_[0.0, lfilter([1.0], np.r_[1.0, -np.asarray(a, dtype=float)], f)]

    def _split(self, theta: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        na, nb, nu = self.na_, self.nb_, len(self.operating_)
        return theta[:na], theta[na : na + nb * nu].reshape(nb, nu), float(theta[-1])

    def _free_run_jacobian(self, U: np.ndarray, a: np.ndarray, y: np.ndarray) -> np.ndarray:
        """d c(k) / d theta (k = 0..K) of :meth:`_free_run`: each column the recursion's
        filter 1/A(q) applied to the shifted output, the shifted inputs and ones."""
        K = U.shape[0] - 1
        den = np.r_[1.0, -np.asarray(a, dtype=float)]

        def delayed(x, n):  # x(k - n), k = 1..K, at rest before k = 1
            return np.r_[np.zeros(min(n, K)), x[: max(K - n, 0)]]

        cols = [delayed(y[1:], i) for i in range(1, self.na_ + 1)]
        cols += [delayed(U[1:, m], j) for j in range(self.nb_) for m in range(U.shape[1])]
        cols.append(np.ones(K))
        J = np.column_stack([lfilter([1.0], den, c) for c in cols])
        return np.vstack([np.zeros((1, J.shape[1])), J])

    def _output_error_fit(self, series: list[_Series], i: int, theta0: np.ndarray, Phi: np.ndarray) -> np.ndarray:
        """Output-error refinement of coefficient ``i``'s ARX: minimise Σ (free run - measured
        c)² over the measured grid steps of the training runs by
        :func:`scipy.optimize.least_squares`, from the equation-error solution ``theta0``.

        * The AR part is searched through its reflection coefficients κ_1..κ_na, bounded to
          (-1, 1): every trial polynomial is stable (Schur-Cohn), so the free run never
          diverges during the search; an unstable ``theta0`` starts from its reflection
          coefficients clipped into the bounds.
        * The input part (b, d) moves only along the directions the training data determine:
          the right singular vectors of the (max-abs scaled) input columns of the
          equation-error design ``Phi`` above ``_RCOND`` of the largest. Speed powers measured
          at a single speed (one block: rpm and rpm² move together) stay at the equation-error
          split instead of drifting to large opposite values that cancel on the training runs
          and explode at other speeds."""
        na = self.na_
        targets = [s.C[s.oe_rows, i] for s in series]
        G = Phi[:, na:]
        scale = np.max(np.abs(G), axis=0)
        scale[scale == 0] = 1.0
        _, sv, vt = np.linalg.svd(G / scale, full_matrices=False)
        P = vt[sv > _RCOND * sv[0]].T / scale[:, None]  # z -> the change of (b, d)
        x0 = np.r_[np.clip(_reflection(theta0[:na]), -(1.0 - 2e-6), 1.0 - 2e-6), np.zeros(P.shape[1])]

        def theta_of(x):
            return np.r_[_step_up(x[:na]), theta0[na:] + P @ x[na:]]

        def resid(x):
            a, B, d = self._split(theta_of(x))
            return np.concatenate([self._free_run(s.U, a, B, d)[s.oe_rows] - c for s, c in zip(series, targets)])

        def jac(x):
            a, B, d = self._split(theta_of(x))
            J = np.vstack([self._free_run_jacobian(s.U, a, self._free_run(s.U, a, B, d))[s.oe_rows] for s in series])
            parts = [J[:, na:] @ P]
            if na:  # chain rule through a(κ): a is affine in each κ_m, so a unit difference is exact
                da = np.column_stack([_step_up(x[:na] + e) - a for e in np.eye(na)])
                parts.insert(0, J[:, :na] @ da)
            return np.hstack(parts)

        lo = np.r_[np.full(na, -_KAPPA_MAX), np.full(P.shape[1], -np.inf)]
        sol = least_squares(resid, x0, jac=jac, bounds=(lo, -lo), method="trf", x_scale="jac")
        best = sol.x if sol.cost <= 0.5 * np.sum(resid(x0) ** 2) else x0
        return theta_of(best)

    # --- fit --------------------------------------------------------------
    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        p = check_params(self, self.params_model)
        self.na_, self.nb_, self.sample_ = p.na, p.nb, p.sample_s
        origin, gdeg = p.origin_mm, p.geometric_degree
        # None: the dataset's operating inputs (feed on an axis, spindle speed on a spindle)
        self.operating_ = parse_operating(self.operating if self.operating is not None else ds.metadata.operating_inputs())
        degree = curve_degree(ds, self.mounting)
        self.origin_ = origin
        names_c = [f"c{i}" for i in range(degree + 1)]

        rd = readings(ds, runs)
        if rd.empty:
            raise ModelError(f"too few samples: runs {runs} have no error readings to fit on")
        # the thermal curve of every cycle, from thermal_um as the dataset defines it (seed 003's
        # "drifts ... deviated from the cold condition"; with a history, from the whole run's reference)
        curves, _ = _curves(rd, degree, origin, "thermal_um")
        _, resid = _curves(rd, degree, origin, "error_um")
        series, refs = [], []
        for run in runs:
            cr = curves[curves["run_id"] == run].sort_values("t_s", kind="stable")
            if cr.empty:
                continue
            refs.append(self._reference_curve(rd[rd["run_id"] == run], degree, origin, run))
            s = self._series(ds, run, cr, names_c)
            if s is not None:
                series.append(s)
        n_rows = sum(s.ee_rows.size for s in series)
        nu = len(self.operating_)
        require(
            n_rows,
            self.na_ + self.nb_ * nu + 2,
            f"grid steps (sample_s={self.sample_:g} s) with a measured error curve in runs {runs} "
            f"for an ARX fit with na={self.na_}, nb={self.nb_}, {nu} input(s)",
        )
        term_names = (
            [f"a{i}" for i in range(1, self.na_ + 1)]
            + [f"b{j}[{c}^{p:g}]" for j in range(self.nb_) for c, p in self.operating_]
            + ["d"]
        )
        ar = np.zeros((degree + 1, self.na_))
        inp = np.zeros((degree + 1, self.nb_, nu))
        off = np.zeros(degree + 1)
        roots, free_rmse = [], {}
        for i in range(degree + 1):
            Phi = np.vstack([self._design(s, i) for s in series])
            target = np.concatenate([s.C[s.ee_rows, i] for s in series])
            theta = lstsq_fit(Phi, target, term_names, f"ARX fit of curve coefficient c{i}")
            if self.criterion == "output":  # the equation-error solution is only the starting point
                theta = self._refine(series, i, theta, Phi)
            else:
                self._check_stable(i, theta[: self.na_], 1.0)
            a, B, d = self._split(theta)
            ar[i], inp[i], off[i] = a, B, d
            roots.append(np.roots(np.r_[1.0, -a]) if self.na_ else np.zeros(0))
            err = np.concatenate([self._free_run(s.U, a, B, d)[s.oe_rows] - s.C[s.oe_rows, i] for s in series])
            free_rmse[f"c{i}"] = float(np.sqrt(np.mean(err**2))) if err.size else float("nan")
        self.ar_coef_, self.input_coef_, self.offset_, self.ar_roots_ = ar, inp, off, roots
        self.free_run_rmse_ = free_rmse
        self.shape_degree_ = degree
        self.reference_coef_ = np.mean(refs, axis=0)
        self.geometric_ = _GeometricPlusCurve(geometric_from_residuals(rd, resid, gdeg), self.reference_coef_, origin)

    def _refine(self, series: list[_Series], i: int, theta_ee: np.ndarray, Phi: np.ndarray) -> np.ndarray:
        """The output-error solution; when its search ends at the stability bound (the training
        runs ask for a drift that never settles: a root at |z| = 1) the stable equation-error
        solution instead, with a :class:`~thermbench.models.base.FallbackWarning`; both unstable:
        the 'unstable' line."""
        theta = self._output_error_fit(series, i, theta_ee, Phi)
        if _max_root(theta[: self.na_]) < _ROOT_MAX:
            return theta
        if _max_root(theta_ee[: self.na_]) < 1.0:
            fallback(
                f"criterion: the output-error fit of curve coefficient c{i} ends at the stability bound "
                f"(a root at |z| = {_max_root(theta[: self.na_]):.6f}); using the stable equation-error fit"
            )
            return theta_ee
        self._check_stable(i, theta[: self.na_], _ROOT_MAX)
        return theta  # not reached: _check_stable raised

    def _check_stable(self, i: int, a: np.ndarray, limit: float) -> None:
        """A root of z^na - a_1 z^(na-1) - ... at or beyond ``limit`` is one line: the data ask
        for a free run that diverges (output error: its search stopped at the stability bound)."""
        r = np.roots(np.r_[1.0, -np.asarray(a, dtype=float)]) if a.size else np.zeros(0)
        if r.size and np.max(np.abs(r)) >= limit:
            raise ModelError(
                f"the fitted auto-regressive part of curve coefficient c{i} is unstable: roots "
                f"{np.round(r, 6).tolist()} (|z| >= {limit:g}) for a = {np.round(a, 6).tolist()}; a free-run "
                f"simulation would diverge. Use a smaller na, a longer sample_s, or longer training runs "
                f"that include cooling"
            )

    @staticmethod
    def _reference_curve(rd_run: pd.DataFrame, degree: int, origin: float, run: str) -> np.ndarray:
        """The run's reference (reading - thermal_um: the cold cycle of a run that starts
        cold, the first reading of the whole test for a segment with its history) as a
        polynomial of ``degree`` in (P - origin), fitted to its per-target values."""
        ref = (rd_run["error_um"] - rd_run["thermal_um"]).groupby(rd_run["target_mm"].to_numpy()).mean()
        if ref.size <= degree:
            raise ModelError(
                f"run {run!r}: its reference (reading - thermal_um) is known at {ref.size} distinct "
                f"target(s); a degree-{degree} error curve needs {degree + 1}"
            )
        p = ref.index.to_numpy(dtype=float) - origin
        return np.polynomial.polynomial.polyfit(p, ref.to_numpy(), degree)

    # --- predict ----------------------------------------------------------
    def simulate(self, dataset: Dataset, run: str) -> tuple[np.ndarray, np.ndarray]:
        """Free-run simulation over the run's whole process log (its history included):
        grid times and the thermal curve coefficients, shape (n_grid, degree+1), from
        c = 0 at the log's first sample, driven by the operating inputs alone (seed 003)."""
        self._check_fitted()
        pr = dataset.process_run(run)
        t0, t1 = float(pr["t_s"].iloc[0]), float(pr["t_s"].iloc[-1])
        grid = self._grid(t0, t1, cover=True)
        if grid.size < 2:
            grid = np.array([t0, t0 + self.sample_])
        # the last (partial) interval ends with the log, its final sample included
        edges = np.minimum(grid, np.nextafter(t1, np.inf))
        U = np.vstack([np.zeros((1, len(self.operating_))), self._inputs(dataset, run, edges)])
        C = np.column_stack(
            [
                self._free_run(U, self.ar_coef_[i], self.input_coef_[i], self.offset_[i])
                for i in range(self.shape_degree_ + 1)
            ]
        )
        return grid, C

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        grid, C = self.simulate(ds, run)
        c = np.column_stack([np.interp(t_s, grid, C[:, i]) for i in range(C.shape[1])])
        return curve_at(c, axis_mm - self.origin_)
