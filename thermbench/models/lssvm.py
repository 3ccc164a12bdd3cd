"""PSO-tuned least-squares SVM regression of the thermal error (seed 002 §2.3.2 part 2, eq. 12-14).

Three layers:

* :class:`LSSVMRegressor`: a plain scikit-learn regressor on arrays. The LSSVM of
  seed 002 eq. 12-13 (``y(x) = wᵀΦ(x) + b``; minimise ``½wᵀw + ½c Σ ξ_i²`` subject
  to ``y_i = wᵀΦ(x_i) + b + ξ_i`` — the paper prints ``Σ ξ_i``, the LSSVM has the
  squared slack) with the RBF kernel of eq. 14, ``K(x, x_i) = exp(-||x - x_i||² / (2σ²))``.
  Its Lagrangian gives the KKT system ``[[0, 1ᵀ], [1, K + I/γ]] [b; α] = [0; y]``
  (γ = the paper's penalty ``c``; ``gamma``/``sigma2`` after the paper's ``gam``/``sig2``;
  the kernel is eq. 14's exp(-d²/(2σ²)), whereas LS-SVMlab's RBF is exp(-d²/sig2): the
  paper's sig2 = 0.01 is σ² = 0.005 here), and the model ``f(x) = Σ α_i K(x_i, x) + b`` (eq. 14).
* :func:`tune_lssvm`: particle-swarm search (``pyswarms.single.GlobalBestPSO``) of
  (log10 γ, log10 σ²) minimising the RMSE on a hold-out set (seed 002 Fig. 14:
  "iterative adaptive particles screen the parameters of the kernel function and
  penalty coefficients").
* :class:`PSOLSSVM`: the thermal-error model family. The geometric error is separated
  as in seed 002 eq. 6-7 (a straight line fitted to every measuring cycle; the mean
  residual per measuring point, fitted by a cubic, is the geometric error) and the
  LSSVM learns ``error - geometric(P)`` from the ΔT of the chosen sensors and the
  position P.
"""

from __future__ import annotations

import contextlib
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any, Mapping, Optional, Sequence

import numpy as np
import scipy.linalg
from annotated_types import Ge, Gt, Lt
from pydantic import AfterValidator
from scipy.spatial.distance import cdist
from sklearn.base import BaseEstimator, RegressorMixin
from sklearn.utils.validation import check_is_fitted
from threadpoolctl import threadpool_limits

from ..data.dataset import Dataset
from .base import ModelError, ThermalErrorModel, fit_progress, readings, validation_mask, require, temperatures_at
from .params import (
    Bool,
    Degree,
    Expect,
    Int,
    Number,
    Params,
    PositiveNumber,
    Seed,
    Selection,
    SensorNames,
    check_params,
    pair_bounds,
    validate,
)
from .sensor_choice import choose_sensors
from .separation import line_separated_geometric

#: Standard constriction coefficients of the PSO (Clerc & Kennedy 2002); seed 002 gives none.
DEFAULT_PSO_OPTIONS = {"c1": 1.49445, "c2": 1.49445, "w": 0.729}


# ---------------------------------------------------------------------------
# parameters (checked at fit: thermbench.models.params)
# ---------------------------------------------------------------------------
class LSSVMRegressorParams(Params):
    gamma: PositiveNumber
    sigma2: PositiveNumber
    standardize: Bool


def _pso_options(opts):
    missing = {"c1", "c2", "w"} - set(opts)
    if missing:
        raise ValueError(f"missing {sorted(missing)}")
    return opts


Count = Annotated[Int, Ge(1)]
Fraction = Annotated[Number, Gt(0), Lt(1)]


class TuneParams(Params):
    """The settings of :func:`tune_lssvm` (equal bounds fix that parameter)."""

    gamma_bounds: pair_bounds(strict=False)
    sigma2_bounds: pair_bounds(strict=False)
    n_particles: Count
    iters: Count
    val_fraction: Fraction = 0.25  # checked only without a val_mask
    seed: Seed
    options: Annotated[Optional[Mapping[str, Number]], AfterValidator(lambda o: o if o is None else _pso_options(o)),
                       Expect("None or a mapping with the numbers c1, c2 and w")]  # fmt: skip
    standardize: Bool


class PSOLSSVMParams(Params):
    sensors: Optional[SensorNames]
    selection: Selection
    preprocess: Any  # checked by thermbench.preprocess.filters.resolve_steps
    gamma: Optional[PositiveNumber]
    sigma2: Optional[PositiveNumber]
    gamma_bounds: pair_bounds()
    sigma2_bounds: pair_bounds()
    n_particles: Count
    iters: Count
    val_fraction: Fraction
    seed: Seed
    geometric_degree: Degree
    max_samples: Annotated[Int, Ge(10)]


# ---------------------------------------------------------------------------
# the LSSVM itself (seed 002 eq. 12-14)
# ---------------------------------------------------------------------------
def rbf_kernel(A: np.ndarray, B: np.ndarray, sigma2: float) -> np.ndarray:
    """RBF kernel matrix ``K[i, j] = exp(-||A_i - B_j||² / (2σ²))`` (seed 002 eq. 14)."""
    return np.exp(-cdist(A, B, "sqeuclidean") / (2.0 * sigma2))


def _solve_kkt(K: np.ndarray, y: np.ndarray, gamma: float) -> tuple[np.ndarray, float]:
    """Solve ``[[0, 1ᵀ], [1, K + I/γ]] [b; α] = [0; y]`` (seed 002 eq. 13).

    Cholesky route: ``A = K + I/γ`` is symmetric positive definite (K is PSD, γ > 0);
    with ``A η = y`` and ``A ν = 1`` the second block row gives ``α = η - b ν`` and the
    first (``1ᵀα = 0``) gives ``b = 1ᵀη / 1ᵀν``. Falls back to a symmetric solve of
    the bordered system if the factorisation fails numerically.
    """
    n = y.size
    A = K + np.eye(n) / gamma
    try:
        c = scipy.linalg.cho_factor(A, lower=True, check_finite=False)
        sol = scipy.linalg.cho_solve(c, np.column_stack([y, np.ones(n)]), check_finite=False)
        eta, nu = sol[:, 0], sol[:, 1]
        b = float(eta.sum() / nu.sum())
        return eta - b * nu, b
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        M = np.zeros((n + 1, n + 1))
        M[0, 1:] = 1.0
        M[1:, 0] = 1.0
        M[1:, 1:] = A
        s = scipy.linalg.solve(M, np.concatenate([[0.0], y]), assume_a="sym")
        return s[1:], float(s[0])


class LSSVMRegressor(RegressorMixin, BaseEstimator):
    """Least-squares SVM regression with the RBF kernel (seed 002 eq. 12-14).

    Parameters
    ----------
    gamma : penalty factor γ (the paper's ``c`` / ``gam``), > 0.
    sigma2 : RBF kernel width σ² (the paper's ``sig2``), > 0, in the units of the
        (standardised, when ``standardize``) inputs squared.
    standardize : scale each input to zero mean and unit standard deviation before
        the kernel (the mean/scale are stored and applied at prediction).

    Fitted attributes: ``X_fit_`` (the standardised training inputs = the support
    vectors), ``gamma_``, ``sigma2_`` (the values fitted with), ``alpha_`` (n,),
    ``b_``, ``mean_``, ``scale_``, ``n_support_`` (the
    LSSVM is not sparse: every training sample is a support vector, so this is n),
    ``memory_bytes_``: what a deployed model must store as float64 — the support
    vectors (n·d), α (n), b, σ² and the input mean and scale (2d):
    ``8·(n·d + n + 2 + 2d)``.
    """

    params_model = LSSVMRegressorParams

    def __init__(self, gamma: float = 10.0, sigma2: float = 1.0, standardize: bool = True):
        self.gamma = gamma
        self.sigma2 = sigma2
        self.standardize = standardize

    @staticmethod
    def _check_X(X, what: str) -> np.ndarray:
        X = np.asarray(X, dtype=float)
        if X.ndim != 2:
            raise ModelError(f"{what}: expected a 2-D array (n_samples, n_features), got shape {X.shape}")
        if not np.all(np.isfinite(X)):
            raise ModelError(f"{what}: {int(np.sum(~np.isfinite(X)))} non-finite value(s)")
        return X

    def fit(self, X, y) -> "LSSVMRegressor":
        p = check_params(self, self.params_model)
        gamma, sigma2 = p.gamma, p.sigma2
        X = self._check_X(X, "X")
        y = np.asarray(y, dtype=float)
        if y.ndim != 1 or y.size != X.shape[0]:
            raise ModelError(f"y: expected shape ({X.shape[0]},) to match X, got {y.shape}")
        if not np.all(np.isfinite(y)):
            raise ModelError(f"y: {int(np.sum(~np.isfinite(y)))} non-finite value(s)")
        require(X.shape[0], 2, "training samples for the LSSVM")
        n, d = X.shape
        if p.standardize:
            self.mean_ = X.mean(axis=0)
            sd = X.std(axis=0)
            self.scale_ = np.where(sd > 0, sd, 1.0)
        else:
            self.mean_ = np.zeros(d)
            self.scale_ = np.ones(d)
        self.X_fit_ = (X - self.mean_) / self.scale_
        self.gamma_, self.sigma2_ = gamma, sigma2
        self.alpha_, self.b_ = _solve_kkt(rbf_kernel(self.X_fit_, self.X_fit_, sigma2), y, gamma)
        self.n_features_in_ = d
        self.n_support_ = n
        self.memory_bytes_ = 8 * (n * d + n + 2 + 2 * d)
        return self

    def predict(self, X) -> np.ndarray:
        """``f(x) = Σ α_i K(x_i, x) + b`` (seed 002 eq. 14)."""
        check_is_fitted(self, "alpha_")
        X = self._check_X(X, "X")
        if X.shape[1] != self.n_features_in_:
            raise ModelError(f"X has {X.shape[1]} features, the LSSVM was fitted with {self.n_features_in_}")
        Z = (X - self.mean_) / self.scale_
        return rbf_kernel(Z, self.X_fit_, self.sigma2_) @ self.alpha_ + self.b_


# ---------------------------------------------------------------------------
# PSO tuning
# ---------------------------------------------------------------------------
@dataclass
class TuneResult:
    """Outcome of :func:`tune_lssvm`: the best ``gamma``/``sigma2``, their validation
    RMSE, the best cost after every PSO iteration and the validation mask used."""

    gamma: float
    sigma2: float
    val_rmse: float
    cost_history: np.ndarray
    val_mask: np.ndarray = field(repr=False)


#: an incremental logging config that changes nothing, given to pyswarms through LOG_CFG
PYSWARMS_LOGGING = Path(__file__).with_name("pyswarms_logging.yaml")


@contextlib.contextmanager
def _pyswarms_private(seed: int):
    """Yield ``pyswarms.single.GlobalBestPSO`` seeded with ``seed``, with the process's global
    state given back exactly afterwards.

    pyswarms draws every random number (swarm, velocities, updates) from numpy's global
    generator, and its ``Reporter`` configures logging at import and in every optimiser,
    topology and handler it builds: ``logging.config.dictConfig`` of the root logger (a stream
    handler and a ``report.log`` file), unless the ``LOG_CFG`` environment variable names a
    logging config file, which it loads instead. Here ``LOG_CFG`` names
    :data:`PYSWARMS_LOGGING`, an incremental config with no handlers or loggers: dictConfig runs
    and changes nothing, so the user's handlers, levels and working directory are untouched.
    numpy's global generator is seeded with ``seed`` for the search; its state and ``LOG_CFG``
    are restored exactly afterwards (``np.random.get_state``/``set_state``)."""
    saved_env = os.environ.get("LOG_CFG")
    saved_rng = np.random.get_state()
    os.environ["LOG_CFG"] = str(PYSWARMS_LOGGING)
    try:
        from pyswarms.single.global_best import GlobalBestPSO

        np.random.seed(seed)
        yield GlobalBestPSO
    finally:
        np.random.set_state(saved_rng)
        if saved_env is None:
            os.environ.pop("LOG_CFG", None)
        else:
            os.environ["LOG_CFG"] = saved_env


def tune_lssvm(
    X,
    y,
    gamma_bounds=(1e-1, 1e4),
    sigma2_bounds=(1e-2, 1e3),
    n_particles: int = 20,
    iters: int = 30,
    val_fraction: float = 0.25,
    seed: int = 0,
    options: dict | None = None,
    val_mask=None,
    standardize: bool = True,
) -> TuneResult:
    """PSO search of (log10 γ, log10 σ²) minimising the hold-out RMSE of an LSSVM.

    Hold-out: ``val_mask`` (boolean, True = validation row) when given; otherwise
    the LAST ``val_fraction`` of the rows in the given order (a contiguous block: for
    time-ordered thermal data the honest split — the model is judged on later,
    warmer/cooler states it has not seen, not on interleaved neighbours).
    The inputs are standardised with the training rows' statistics, as the final
    LSSVM would be.

    Swarm: ``pyswarms.single.GlobalBestPSO`` with ``options`` (default
    :data:`DEFAULT_PSO_OPTIONS`), positions clipped to the bounds ("nearest"). The
    first particles start at the four corners and the centre of the (log) box, the
    rest uniformly at random, so the result is never worse than those five points.
    A pair of equal bounds fixes that parameter (only the other is searched).
    Deterministic: numpy's global generator (which pyswarms draws from) is seeded with
    ``seed`` and restored exactly afterwards, as is logging (:func:`_pyswarms_private`).
    """
    settings = dict(gamma_bounds=gamma_bounds, sigma2_bounds=sigma2_bounds, n_particles=n_particles, iters=iters,
                    seed=seed, options=options, standardize=standardize)  # fmt: skip
    if val_mask is None:
        settings["val_fraction"] = val_fraction
    p = validate(TuneParams, settings, "tune_lssvm")
    (glo, ghi), (slo, shi) = p.gamma_bounds, p.sigma2_bounds
    X = LSSVMRegressor._check_X(X, "X")
    y = np.asarray(y, dtype=float)
    if y.ndim != 1 or y.size != X.shape[0] or not np.all(np.isfinite(y)):
        raise ModelError(f"y: expected {X.shape[0]} finite values matching X, got shape {y.shape}")
    n = y.size
    if val_mask is None:
        n_val = int(round(p.val_fraction * n))
        val = np.zeros(n, dtype=bool)
        val[n - n_val :] = True
    else:
        val = np.asarray(val_mask, dtype=bool)
        if val.shape != (n,):
            raise ModelError(f"val_mask: expected a boolean array of shape ({n},), got {val.shape}")
    require(int((~val).sum()), 2, "training samples for PSO tuning")
    require(int(val.sum()), 1, "validation samples for PSO tuning")
    opts = dict(DEFAULT_PSO_OPTIONS if p.options is None else p.options)

    Xt, Xv, yt, yv = X[~val], X[val], y[~val], y[val]
    if p.standardize:
        mu, sd = Xt.mean(axis=0), Xt.std(axis=0)
        sd = np.where(sd > 0, sd, 1.0)
        Xt, Xv = (Xt - mu) / sd, (Xv - mu) / sd
    D_tt = cdist(Xt, Xt, "sqeuclidean")  # computed once; each particle only exponentiates
    D_vt = cdist(Xv, Xt, "sqeuclidean")

    lo = np.log10([glo, slo])
    hi = np.log10([ghi, shi])
    free = np.flatnonzero(hi > lo)

    def params(pos: np.ndarray) -> tuple[float, float]:
        v = np.array([glo, slo])  # a fixed parameter keeps its exact value
        v[free] = 10.0 ** np.asarray(pos)
        return float(v[0]), float(v[1])

    def rmse(gamma: float, sigma2: float) -> float:
        try:
            alpha, b = _solve_kkt(np.exp(-D_tt / (2 * sigma2)), yt, gamma)
        except (np.linalg.LinAlgError, scipy.linalg.LinAlgError, ValueError):
            return np.inf
        pred = np.exp(-D_vt / (2 * sigma2)) @ alpha + b
        r = float(np.sqrt(np.mean((yv - pred) ** 2)))
        return r if math.isfinite(r) else np.inf

    if free.size == 0:  # both fixed
        r = rmse(glo, slo)
        return TuneResult(glo, slo, r, np.array([r]), val)

    flo, fhi = lo[free], hi[free]
    # hundreds of small factorisations: BLAS threads cost more than they gain there
    blas = threadpool_limits(limits=1, user_api="blas") if yt.size < 1000 else contextlib.nullcontext()
    with blas, _pyswarms_private(p.seed) as GlobalBestPSO, fit_progress(p.iters, "LSSVM swarm", "iteration") as step:
        corners = np.array(np.meshgrid(*[[a, b] for a, b in zip(flo, fhi)])).reshape(free.size, -1).T
        starts = np.vstack([corners, (flo + fhi) / 2])[: p.n_particles]
        rand = flo + (fhi - flo) * np.random.random_sample((p.n_particles - len(starts), free.size))
        init = np.clip(np.vstack([starts, rand]), flo, fhi)
        opt = GlobalBestPSO(n_particles=p.n_particles, dimensions=int(free.size), options=opts, bounds=(flo, fhi),
                            bh_strategy="nearest", init_pos=init)  # fmt: skip
        def swarm_cost(P: np.ndarray) -> np.ndarray:  # one call per iteration of the swarm
            step()
            return np.array([rmse(*params(q)) for q in P])

        best_cost, best_pos = opt.optimize(swarm_cost, iters=p.iters, verbose=False)
        history = np.asarray(opt.cost_history, dtype=float)
    g, s = params(np.asarray(best_pos, dtype=float))
    return TuneResult(float(g), float(s), float(best_cost), history, val)


# ---------------------------------------------------------------------------
# the thermal-error model family
# ---------------------------------------------------------------------------
class PSOLSSVM(ThermalErrorModel):
    """PSO-tuned LSSVM thermal-error model (seed 002 §2.3.2 part 2, eq. 12-14).

    Geometric/thermal separation as seed 002 eq. 6-7: every measuring cycle's error
    curve is fitted by a straight line, the mean residual at each measuring point is
    the geometric error, fitted by a polynomial of ``geometric_degree`` (eq. 7: 3).
    The LSSVM (:class:`LSSVMRegressor`, inputs standardised) then learns the rest,
    ``error_um - geometric(P)``, from the features ``[ΔT of the sensors..., P]``
    (ΔT: rise above the run's first filtered sample, seed 002 eq. 10). Prediction
    returns that LSSVM output as the thermal part; the base class adds the geometric.

    Parameters
    ----------
    sensors : sensor names to use; None selects seed 002's temperature-sensitive
        points on the training runs (``selection`` is passed on, see
        :func:`~thermbench.models.sensor_choice.choose_sensors`).
    preprocess : temperature filters (seed 002 §2.3.1): "default" (limit + Kalman), None, or a list.
    gamma, sigma2 : the LSSVM's penalty factor and kernel width; None (default) =
        tuned by PSO (:func:`tune_lssvm`) within ``gamma_bounds`` / ``sigma2_bounds``
        with ``n_particles``, ``iters`` and ``seed``. Giving one tunes only the other.
    val_fraction : PSO hold-out (:func:`thermbench.models.base.validation_mask`): whole
        training runs, the last ones making up about ``val_fraction`` of the readings;
        with a single run, the last ``val_fraction`` of its measuring cycles (a time
        block). Never rows between training rows of the same run: the tuning rewards
        what holds on another run, not interpolating between neighbouring readings.
        After tuning, the LSSVM is refitted on all training readings.
    max_samples : the LSSVM costs O(n³) time and O(n²) memory; with more readings
        than this a seeded (``seed``) random subset of ``max_samples`` readings is
        used for tuning and fitting (``subsampled_`` records it).

    Fitted attributes: ``sensors_``, ``gamma_``, ``sigma2_``, ``regressor_``,
    ``n_support_``, ``memory_bytes_``, ``pso_cost_history_`` (best validation RMSE
    after each PSO iteration; empty when nothing was tuned), ``val_rmse_um_``,
    ``n_train_samples_``, ``subsampled_``, ``geometric_``.
    """

    params_model = PSOLSSVMParams

    def __init__(
        self,
        sensors: Sequence[str] | None = None,
        selection: dict | None = None,
        preprocess="default",
        gamma: float | None = None,
        sigma2: float | None = None,
        gamma_bounds=(1e-1, 1e4),
        sigma2_bounds=(1e-2, 1e3),
        n_particles: int = 20,
        iters: int = 30,
        val_fraction: float = 0.25,
        seed: int = 0,
        geometric_degree: int = 3,
        max_samples: int = 2000,
    ):
        self.sensors = sensors
        self.selection = selection
        self.preprocess = preprocess
        self.gamma = gamma
        self.sigma2 = sigma2
        self.gamma_bounds = gamma_bounds
        self.sigma2_bounds = sigma2_bounds
        self.n_particles = n_particles
        self.iters = iters
        self.val_fraction = val_fraction
        self.seed = seed
        self.geometric_degree = geometric_degree
        self.max_samples = max_samples

    def _features(self, ds: Dataset, run: str, t_s, axis_mm) -> np.ndarray:
        T = temperatures_at(ds, run, self.sensors_, t_s, self.preprocess)
        return np.column_stack([T, np.asarray(axis_mm, dtype=float)])

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        p = check_params(self, self.params_model)
        rd = readings(ds, runs)
        require(len(rd), 10, "interferometer readings in the training runs")
        self.geometric_ = line_separated_geometric(rd, p.geometric_degree)  # seed 002 eq. 6-7
        self.sensors_ = choose_sensors(ds, runs, self.sensors, self.selection, self.preprocess)

        X = np.empty((len(rd), len(self.sensors_) + 1))
        for r in runs:
            m = (rd["run_id"] == r).to_numpy()
            g = rd[m]
            X[m] = self._features(ds, r, g["t_s"].to_numpy(), g["target_mm"].to_numpy())
        val = validation_mask(rd, p.val_fraction)  # whole training runs held out (one run: its last cycles)
        y = rd["error_um"].to_numpy() - self.geometric_(rd["target_mm"].to_numpy())
        ok = np.all(np.isfinite(X), axis=1) & np.isfinite(y)
        require(int(ok.sum()), 10, "finite (temperature, error) readings in the training runs")

        idx = np.flatnonzero(ok)
        self.subsampled_ = idx.size > p.max_samples
        if self.subsampled_:
            idx = np.sort(np.random.RandomState(p.seed).choice(idx, p.max_samples, replace=False))
        X, y, val = X[idx], y[idx], val[idx]
        self.n_train_samples_ = int(idx.size)

        if p.gamma is None or p.sigma2 is None:
            if not val.any() or val.all():
                raise ModelError(
                    "too few samples: PSO tuning needs a training run with at least 2 measuring cycles "
                    "(the last val_fraction of them is the hold-out); or give both gamma and sigma2"
                )
            gb = p.gamma_bounds if p.gamma is None else (p.gamma, p.gamma)
            sb = p.sigma2_bounds if p.sigma2 is None else (p.sigma2, p.sigma2)
            res = tune_lssvm(X, y, gb, sb, p.n_particles, p.iters, seed=p.seed, val_mask=val)
            self.gamma_, self.sigma2_ = res.gamma, res.sigma2
            self.val_rmse_um_ = res.val_rmse
            self.pso_cost_history_ = res.cost_history
        else:
            self.gamma_, self.sigma2_ = p.gamma, p.sigma2
            self.val_rmse_um_ = float("nan")
            self.pso_cost_history_ = np.array([])
        self.regressor_ = LSSVMRegressor(gamma=self.gamma_, sigma2=self.sigma2_).fit(X, y)
        self.n_support_ = self.regressor_.n_support_
        self.memory_bytes_ = self.regressor_.memory_bytes_

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        return self.regressor_.predict(self._features(ds, run, t_s, axis_mm))
