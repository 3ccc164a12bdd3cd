"""Gaussian-process compensation on the thermal lags: a prediction that knows its own uncertainty.

The public GP compensator (petrkaftan/Thermal_Compensation) regresses the thermal error on the
temperatures with a Gaussian process and reports its predictive standard deviation; here the
features are those of :mod:`thermbench.models.thermal_lag` with its stepwise selection
(``thermal_lag_stepwise``: first-order lags of the inputs it chose, at the time constants it
chose, by cross-validation over whole runs), and the process is
scikit-learn's :class:`~sklearn.gaussian_process.GaussianProcessRegressor` with a kernel of a
linear part, a smooth part and noise::

    k = c_lin · DotProduct + c_rbf · RBF(length) + White(noise)

on standardised features, its hyperparameters by marginal likelihood. A long log is subsampled
(``max_samples`` readings, seeded) for the fit; every reading is predicted. Fitted:
``lag_`` (the :class:`~thermbench.models.thermal_lag.ThermalLag` whose features it uses),
``gp_`` and ``kernel_`` (the kernel with its identified hyperparameters), ``at_bounds_`` (the
hyperparameters that ended at a search bound: scikit-learn warns of each; here they are collected
and said once, by ``fit_summary``, instead of a warning per fit in a benchmark's terminal).
:meth:`GaussianProcessLag.predict_std` gives the predictive standard deviation (µm) at (t, x).
"""

from __future__ import annotations

import re
import warnings
from typing import Annotated, Optional, Sequence

import numpy as np
from annotated_types import Ge, Gt, Len
from numpy.polynomial import Polynomial
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import RBF, ConstantKernel, DotProduct, WhiteKernel

from ..data.dataset import Dataset
from .base import Inputs, ModelError, ThermalErrorModel, readings
from .params import Expect, Int, Params, Seed, check_params
from .thermal_lag import DEFAULT_TAUS_S, ThermalLag

__all__ = ["GaussianProcessLag"]


class GaussianProcessLagParams(Params):
    sensors: Annotated[Optional[Annotated[Sequence[str], Len(min_length=1)]],
                       Expect("None or a non-empty list of sensor names")]  # fmt: skip
    operating: Annotated[Optional[Sequence[str]], Expect("None or a list of process columns")]
    taus_s: Annotated[Sequence[Annotated[Sequence[Annotated[float, Ge(0)]], Len(min_length=1)]], Len(min_length=1),
                      Expect("a non-empty list of sets of time constants in seconds, each >= 0")]  # fmt: skip
    max_inputs: Annotated[Int, Ge(1)]
    max_samples: Annotated[Int, Ge(10)]
    n_restarts: Annotated[Int, Ge(0)]
    seed: Optional[Seed]
    noise_bounds: Annotated[Sequence[Annotated[float, Gt(0)]], Len(min_length=2, max_length=2),
                            Expect("[low, high] of the white-noise level, > 0")]  # fmt: skip


class GaussianProcessLag(ThermalErrorModel):
    """A Gaussian process on the thermal lags (module docstring).

    Parameters
    ----------
    sensors, operating, taus_s, max_inputs
        The candidate inputs and time constants, as :class:`~thermbench.models.thermal_lag.ThermalLag`
        takes them (which picks the features).
    max_samples : int
        At most this many training readings (a seeded random subset beyond).
    n_restarts : int
        Restarts of the marginal-likelihood optimiser (scikit-learn's ``n_restarts_optimizer``).
    seed : int or None
        The subset and the restarts.
    noise_bounds : [low, high]
        Bounds of the white-noise level (standardised error units).
    """

    params_model = GaussianProcessLagParams

    def __init__(self, sensors=None, operating=None, taus_s=DEFAULT_TAUS_S, max_inputs=6, max_samples=800, n_restarts=0,
                 seed=0, noise_bounds=(1e-5, 1.0)):  # fmt: skip
        self.sensors = sensors
        self.operating = operating
        self.taus_s = taus_s
        self.max_inputs = max_inputs
        self.max_samples = max_samples
        self.n_restarts = n_restarts
        self.seed = seed
        self.noise_bounds = noise_bounds

    def _X(self, ds: Dataset, run: str, t_s, axis_mm) -> np.ndarray:
        lag = self.lag_
        return (lag._features(ds, run, lag.inputs_, lag.taus_s_, t_s, axis_mm) - self.mean_) / self.scale_

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        p = check_params(self, self.params_model)
        self.lag_ = ThermalLag(sensors=p.sensors, operating=p.operating, taus_s=p.taus_s,
                               max_inputs=p.max_inputs).fit(ds, runs)  # fmt: skip
        lag = self.lag_
        rd = readings(ds, runs)
        X = np.vstack([lag._features(ds, r, lag.inputs_, lag.taus_s_, g["t_s"].to_numpy(), g["target_mm"].to_numpy())
                       for r, g in rd.groupby("run_id", sort=False)])  # fmt: skip
        y = np.concatenate([g["error_um"].to_numpy(dtype=float) for _, g in rd.groupby("run_id", sort=False)])
        if X.shape[1] == 0:  # the selection found no input that lowers the held-out error of these runs
            raise ModelError(f"the lag selection kept no input on runs {', '.join(runs)} (no sensor lowered the "
                             f"held-out error of a constant): the Gaussian process has nothing to read")  # fmt: skip
        self.mean_ = X.mean(axis=0)
        sd = X.std(axis=0)
        self.scale_ = np.where(sd > 0, sd, 1.0)
        Z = (X - self.mean_) / self.scale_
        rng = np.random.default_rng(p.seed)
        if y.size > p.max_samples:  # a seeded subset of a long log
            keep = np.sort(rng.choice(y.size, p.max_samples, replace=False))
            Z, y = Z[keep], y[keep]
        kernel = (ConstantKernel(1.0, (1e-3, 1e3)) * DotProduct(sigma_0=1.0, sigma_0_bounds=(1e-3, 1e3))
                  + ConstantKernel(1.0, (1e-3, 1e3)) * RBF(length_scale=3.0, length_scale_bounds=(1e-1, 1e3))
                  + WhiteKernel(0.01, tuple(p.noise_bounds)))  # fmt: skip
        gp = GaussianProcessRegressor(kernel=kernel, normalize_y=True, n_restarts_optimizer=p.n_restarts,
                                      random_state=p.seed)  # fmt: skip
        self.train_Z_, self.train_y_um_ = Z, y  # what the GP was fitted on (a refit adds to it: thermbench.bench.adapt.gp_refit)
        with warnings.catch_warnings(record=True) as caught:  # a hyperparameter at its bound: said once, by fit_summary
            warnings.simplefilter("always", ConvergenceWarning)
            self.gp_ = gp.fit(Z, y)
        self.at_bounds_ = sorted({m.group(1) for w in caught if issubclass(w.category, ConvergenceWarning)
                                  for m in [re.search(r"parameter (\S+) is close", str(w.message))] if m})  # fmt: skip
        for w in caught:  # anything else is passed on as it came
            if not issubclass(w.category, ConvergenceWarning):
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        self.kernel_ = self.gp_.kernel_
        self.geometric_ = Polynomial([0.0])

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        if np.asarray(t_s).size == 0:
            return np.zeros(0)
        return np.asarray(self.gp_.predict(self._X(ds, run, t_s, axis_mm)), dtype=float)

    def predict_std(self, ds: Dataset, run: str, t_s, axis_mm) -> np.ndarray:
        """The predictive standard deviation (µm) at times ``t_s`` and positions ``axis_mm`` of ``run``
        (the white noise included: the spread of a new reading around the prediction)."""
        self._check_fitted()
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        x = np.broadcast_to(np.asarray(axis_mm, dtype=float), t.shape)
        return np.asarray(self.gp_.predict(self._X(ds, run, t, x), return_std=True)[1], dtype=float)

    def fit_summary(self) -> str:
        self._check_fitted()
        bounds = f"; at a search bound (scikit-learn's ConvergenceWarning): {', '.join(self.at_bounds_)}" if self.at_bounds_ else ""
        return f"on the lags of {self.lag_.inputs_} at {[round(t) for t in self.lag_.taus_s_]} s; kernel {self.kernel_}{bounds}"

    def export_encoding(self, channels, period_s, where):
        """Refused, in one line with the reason: the C runtime has no kind for a kernel sum
        over lag states."""
        self._check_fitted()
        raise ModelError(f"the C runtime has no Gaussian-process kind: its mean is a kernel sum over "
                         f"{self.gp_.X_train_.shape[0]} training readings of {self.gp_.X_train_.shape[1]} lag states; "
                         "export thermal_lag (the same lags, weighted linearly) instead")  # fmt: skip

    def _model_inputs(self) -> Inputs:
        return self.lag_._model_inputs()
