"""Multiple linear regression thermal error models, in the three published forms.

* :class:`MLRSeed001` - seed 001 §3 eq. 1 / §5.1.1 eq. 12: the error is the axis
  position times a polynomial in the nut temperature plus a linear bed term,
  ``E = (a_m Tn^m + ... + a1 Tn + b1 Tb + c) Px``, with the geometric error the
  quartic through the 0-min readings (seed 001 eq. 11).
* :class:`MLRSeed002` - seed 002 §2.3.2 eq. 6-11: every measuring cycle's error
  curve is a straight line in (P - P0); slope and intercept are each linear in the
  temperature rises of the selected sensitive points (``RegressX``, ``RegressJ``);
  the geometric error is the cubic fit of the mean de-sloped residual (eq. 7).
* :class:`MLRSeed004` - seed 004 (mounting-aware): a line (fixed-free,
  fixed-supported) or a parabola (fixed-fixed) per cycle, every curve coefficient
  linear in the temperatures, the geometric error the mean residual at each
  measuring point (or its polynomial, seed 004 eq. 6).

All regressions are ordinary least squares (:func:`numpy.linalg.lstsq`) on
column-scaled regressors. Temperatures are the rises ΔT above each run's first
(filtered) sample (:func:`~thermbench.models.base.temperatures_at`); seed 001 §3
states ΔT and T give the same fit (only the coefficients differ), and seed 004's
regression on T is the same linear model up to the constant.
"""

from __future__ import annotations

from abc import abstractmethod
import warnings
from typing import Annotated, Any, Optional, Sequence

import numpy as np
import pandas as pd
from annotated_types import Ge, Le

from ..data.dataset import Dataset
from .base import (
    fallback,
    is_fixed_point,
    ModelError,
    ThermalErrorModel,
    check_sensors,
    readings,
    require,
    sensors_at,
    sensors_by_location,
    temperatures_at,
)
from .params import Degree, Int, Number, Params, Selection, SensorNames, check_params
from .sensor_choice import choose_sensors
from .separation import (
    cold_reference_geometric,
    curve_at,
    curve_degree,
    cycle_curves,
    geometric_from_residuals,
    shape_degree,
)

__all__ = ["MLRSeed001", "MLRSeed002", "MLRSeed004", "lstsq_fit"]

SEED004_LOCATIONS = ("fixed_bearing_housing", "nut_housing", "free_bearing_housing")


# -------------------------------------------------------------- parameters ---
class MLRSeed001Params(Params):
    degree: Annotated[Int, Ge(1), Le(4)]  # seed 001 §3: m <= 4
    nut_sensor: Optional[str]
    bed_sensor: Optional[str]
    origin_mm: Optional[Number]
    preprocess: Any  # checked by thermbench.preprocess.filters.resolve_steps


class _CurveParams(Params):
    sensors: Optional[SensorNames]
    preprocess: Any
    origin_mm: Number
    geometric_degree: Optional[Degree]


class MLRSeed002Params(_CurveParams):
    selection: Selection


class MLRSeed004Params(_CurveParams):
    mounting: Optional[str]  # checked by separation.shape_degree


# ----------------------------------------------------------------- helpers ---
def sensor_list(name: str, value) -> list[str] | None:
    """A list of sensor names from a list/tuple/ListConfig (a lone string is one sensor)."""
    if value is None:
        return None
    if isinstance(value, str):
        return [value]
    try:
        out = [str(s) for s in value]
    except TypeError:
        raise ModelError(f"{name} must be a list of sensor names or None, got {value!r}") from None
    if len(set(out)) != len(out):
        raise ModelError(f"{name}: a sensor is listed twice: {out}")
    return out


def lstsq_fit(X: np.ndarray, y: np.ndarray, names: Sequence[str], what: str) -> np.ndarray:
    """Least squares ``X @ coef ≈ y`` by :func:`numpy.linalg.lstsq` on max-abs scaled
    columns (the scaling only improves conditioning; the solution is the same).

    A rank-deficient design (a regressor that does not vary, or two that move
    together on the training runs) warns and returns the minimum-norm solution.
    """
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float)
    if not (np.isfinite(X).all() and np.isfinite(y).all()):
        raise ModelError(f"{what}: the regressors or targets contain NaN/inf (check the temperature/operating data)")
    scale = np.max(np.abs(X), axis=0)
    scale[scale == 0] = 1.0
    sol, _, rank, _ = np.linalg.lstsq(X / scale, y, rcond=None)
    if rank < X.shape[1]:
        warnings.warn(
            f"{what}: the regressors {list(names)} are linearly dependent on the training data "
            f"(rank {rank} of {X.shape[1]}); the minimum-norm least-squares solution is used, "
            "its coefficients are not unique",
            RuntimeWarning,
            stacklevel=3,
        )
    return sol / (scale[:, None] if sol.ndim == 2 else scale)


def _rise_at(ds: Dataset, frame: pd.DataFrame, sensors: list[str], preprocess) -> np.ndarray:
    """ΔT of ``sensors`` at the ``t_s`` of every row of ``frame`` (rows of several runs), in row order."""
    out = np.empty((len(frame), len(sensors)))
    for run, g in frame.groupby("run_id", sort=False):
        idx = np.flatnonzero((frame["run_id"] == run).to_numpy())
        out[idx] = temperatures_at(ds, str(run), sensors, g["t_s"].to_numpy(), preprocess)
    return out


# -------------------------------------------------------------- seed 001 ---
class MLRSeed001(ThermalErrorModel):
    """Seed 001 multiple regression, eq. 1 and eq. 12.

    ``E(t, Px) = E_p(Px) + (a_m ΔTn^m + ... + a_1 ΔTn + b_1 ΔTb + c) · (Px - origin_mm)``

    * ``E_p`` is the geometric error, ``d4 Px^4 + ... + d0`` through the 0-min
      (cold reference, cycle 0) readings of the training runs (seed 001 eq. 11,
      §5.1: "used to compensate 0 min errors").
    * The thermal part is fitted by least squares to ``error_um - E_p(P)`` over all
      readings of the training runs (seed 001 §3: "determined using the least square
      method").
    * ``Tn`` = the nut sensor (seed 001 sensor 1), ``Tb`` = the bed sensor near the
      bearing block (sensor 2). Eq. 12 takes Tn to the 4th power and Tb linear
      (``degree`` = m, 1..4; seed 001 §3: m <= 4).
    * Temperature rises ΔT (above the run's first sample) replace T: seed 001 §3
      says ΔT gives the same fit with other coefficients. It is also a numerical
      necessity: at ~20-30 °C the columns T, T², T³, T⁴ each change by only a few
      per cent over a test and are almost collinear (on the seed001_vmc_x state 1
      readings the column-scaled eq. 12 design has condition number 1.3e6 in T,
      1.1e3 in ΔT; unscaled, T⁴ ~ 4e5 makes it far worse). When training runs
      start at different temperatures ΔT also removes that run-to-run offset.
    * ``Px`` is the axis coordinate (seed 001: "real-time position of x-axis");
      ``origin_mm`` moves the point where the thermal error is forced to zero;
      None (default) puts it at the screw's fixed end when the dataset declares
      it (``screw.fixed_end_axis_mm``), where seed 001 §4 integrates the
      elongation from; with Px from an origin away from the fixed end, eq. 12
      cannot represent the elongation of the screw between the two.

    Parameters: ``degree`` (m), ``nut_sensor`` / ``bed_sensor`` (None: the
    dataset's sensor at location ``nut_housing`` / ``bed``, else ``ambient``), ``origin_mm``,
    ``preprocess`` (temperature filters, seed 002 §2.3.1: "default" = limit +
    Kalman, None = none, or a list of filters).

    Fitted: ``coef_`` = {"a1".."am", "b1", "c"} (µm/mm per °C^i, µm/mm per °C,
    µm/mm), ``nut_sensor_``, ``bed_sensor_``, ``sensors_``, ``geometric_``.
    """

    complexity = 1  # ThermalErrorModel.complexity

    needs = ("along_axis",)  # eq. 12: the thermal error is a slope times (Px - origin)
    params_model = MLRSeed001Params

    def __init__(self, degree=4, nut_sensor=None, bed_sensor=None, origin_mm=None, preprocess="default"):
        self.degree = degree
        self.nut_sensor = nut_sensor
        self.bed_sensor = bed_sensor
        self.origin_mm = origin_mm
        self.preprocess = preprocess

    def _design(self, dT: np.ndarray, p: np.ndarray) -> np.ndarray:
        m = self.degree_
        cols = [dT[:, 0] ** i for i in range(1, m + 1)] + [dT[:, 1], np.ones(len(p))]
        return np.column_stack(cols) * (p - self.origin_)[:, None]

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        p = check_params(self, self.params_model)
        degree = p.degree
        origin = p.origin_mm
        if origin is None:  # Px from the fixed end, where seed 001 §4 integrates the elongation from
            origin = float((ds.metadata.screw.fixed_end_axis_mm if ds.metadata.screw is not None else None) or 0.0)
        nut = p.nut_sensor if p.nut_sensor is not None else sensors_at(ds, "nut_sensor", ["nut_housing"])
        bed = p.bed_sensor
        if bed is None:  # seed 001 sensor 2 is a reference temperature (eq. 2); the ambient will do
            bed = sensors_at(ds, "bed_sensor", ["bed", "ambient"])
        check_sensors(ds, [nut], "nut_sensor")
        check_sensors(ds, [bed], "bed_sensor")
        if nut == bed:
            raise ModelError(f"nut_sensor and bed_sensor are the same sensor {nut!r}; seed 001 needs two")
        rd = readings(ds, runs)
        names = [f"a{i}" for i in range(1, degree + 1)] + ["b1", "c"]
        require(len(rd), len(names) + 1, f"readings for the seed 001 regression with degree={degree}")
        geometric = cold_reference_geometric(rd, 4)  # seed 001 eq. 11
        p = rd["target_mm"].to_numpy()
        dT = _rise_at(ds, rd, [nut, bed], self.preprocess)
        self.degree_, self.origin_ = degree, origin
        y = rd["error_um"].to_numpy() - geometric(p)
        coef = lstsq_fit(self._design(dT, p), y, names, "seed 001 regression")
        self.coef_ = {k: float(v) for k, v in zip(names, coef)}
        self._coef_vector_ = coef
        self.nut_sensor_, self.bed_sensor_ = nut, bed
        self.sensors_ = [nut, bed]
        self.geometric_ = geometric

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        dT = temperatures_at(ds, run, self.sensors_, t_s, self.preprocess)
        return self._design(dT, axis_mm) @ self._coef_vector_


# ------------------------------------------------- seeds 002 and 004 ---
class _CurveRegression(ThermalErrorModel):
    """Shared by seeds 002 and 004: every measuring cycle's error curve is a
    polynomial in (P - origin) (degree from :meth:`_curve_degree`), each curve
    coefficient is linear in the ΔT of the sensors (:meth:`_pick_sensors`) at the
    cycle's mean time, and the geometric error is the mean residual per measuring
    point (optionally a polynomial of ``geometric_degree``)."""

    complexity = 1  # ThermalErrorModel.complexity

    @abstractmethod
    def _curve_degree(self, ds: Dataset) -> int:
        """Degree of each cycle's curve in position."""

    @abstractmethod
    def _pick_sensors(self, ds: Dataset, runs: list[str]) -> list[str]:
        """The sensors the coefficients are regressed on."""

    def _fit(self, ds: Dataset, runs: list[str]) -> None:
        p = check_params(self, self.params_model)
        origin, gdeg = p.origin_mm, p.geometric_degree
        degree = self._curve_degree(ds)
        sensors = self._pick_sensors(ds, runs)
        rd = readings(ds, runs)
        curves, resid = cycle_curves(rd, degree, origin)
        require(len(curves), len(sensors) + 2, f"measuring cycles for the curve-coefficient regression on {sensors}")
        geometric = geometric_from_residuals(rd, resid, gdeg)
        X = np.column_stack([np.ones(len(curves)), _rise_at(ds, curves, sensors, self.preprocess)])
        Y = curves[[f"c{i}" for i in range(degree + 1)]].to_numpy()
        what = f"{type(self).__name__} curve-coefficient regression"
        self.curve_coef_ = lstsq_fit(X, Y, ["const", *sensors], what).T  # row i: [k_i0, k_i1, ...] for c_i
        self.shape_degree_ = degree
        self.sensors_ = list(sensors)
        self.origin_ = origin
        self.geometric_ = geometric

    def _predict_thermal(self, ds: Dataset, run: str, t_s: np.ndarray, axis_mm: np.ndarray) -> np.ndarray:
        X = np.column_stack([np.ones(t_s.size), temperatures_at(ds, run, self.sensors_, t_s, self.preprocess)])
        return curve_at(X @ self.curve_coef_.T, axis_mm - self.origin_)


# -------------------------------------------------------------- seed 002 ---
class MLRSeed002(_CurveRegression):
    """Seed 002 multiple linear regression with geometric/thermal separation, eq. 6-11.

    ``e(P, ΔT) = RegressX(ΔT)·(P - P0) + RegressJ(ΔT) + Fitting(P - P0)`` (eq. 6, 11)

    1. Every measuring cycle's error curve is fitted by a straight line in
       ``P - P0`` (``P0`` = ``origin_mm``, seed 002: "the machine origin
       coordinates"): slope and intercept per cycle.
    2. The geometric error ``Fitting`` is the mean, per measuring point, of the
       residual of those lines ("converted into horizontal curves with a one-time
       fitted slope of 0"), fitted by a cubic (eq. 7; ``geometric_degree``; None
       keeps the per-point table).
    3. Slope and intercept of each cycle are regressed linearly on the temperature
       rises ΔT of the selected sensors at the cycle's mean time (eq. 8-10:
       ``RegressX = k0 + Σ k_i ΔTEMP_i``, ``RegressJ`` likewise).

    Because the lines are fitted to the whole positioning error, the regression
    constants (ΔT = 0) also carry the linear part of the cold geometric error (as
    in the paper: eq. 9's constant -5.03 µm next to eq. 7's -3.02 µm);
    ``predict_thermal_at`` is therefore "the part that is not ``Fitting``".

    Parameters: ``sensors`` (None: seed 002 §2.3.1 sensitive-point selection on
    the training runs, options in ``selection`` for
    :func:`~thermbench.models.sensor_choice.choose_sensors`), ``preprocess``,
    ``origin_mm`` (P0), ``geometric_degree`` (3, eq. 7).

    Fitted: ``slope_coef_``, ``intercept_coef_`` (arrays ``[const, one per
    sensor]``, µm/mm and µm, per °C), ``sensors_``, ``geometric_``.
    """

    params_model = MLRSeed002Params

    def __init__(self, sensors=None, selection=None, preprocess="default", origin_mm=0.0, geometric_degree=3):
        self.sensors = sensors
        self.selection = selection
        self.preprocess = preprocess
        self.origin_mm = origin_mm
        self.geometric_degree = geometric_degree

    def _curve_degree(self, ds: Dataset) -> int:
        return 0 if is_fixed_point(ds) else 1  # eq. 6: one line per measuring cycle; a fixed point: its drift

    def _pick_sensors(self, ds: Dataset, runs: list[str]) -> list[str]:
        sel = dict(self.selection) if self.selection is not None else None
        return choose_sensors(ds, runs, sensor_list("sensors", self.sensors), sel, self.preprocess)

    @property
    def slope_coef_(self) -> np.ndarray:
        """eq. 8, RegressX: ``[const, one per sensor]`` (µm/mm, per °C); zeros at a fixed point."""
        return self.curve_coef_[1] if len(self.curve_coef_) > 1 else np.zeros_like(self.curve_coef_[0])

    @property
    def intercept_coef_(self) -> np.ndarray:
        """eq. 9, RegressJ: ``[const, one per sensor]`` (µm, per °C)."""
        return self.curve_coef_[0]


# -------------------------------------------------------------- seed 004 ---
class MLRSeed004(_CurveRegression):
    """Seed 004 mounting-aware positioning error model.

    ``E(t, P) = Σ_i c_i(T(t)) · (P - origin)^i + G(P)``, with

    * the curve shape from the screw mounting (seed 004 "Modeling method"): a
      straight line (i <= 1) for fixed-free and fixed-supported, a parabola
      (i <= 2) for fixed-fixed; ``mounting`` overrides the dataset's metadata;
    * every measuring cycle's curve fitted by that polynomial (seed 004 Table 1);
    * each coefficient ``c_i`` regressed linearly on the temperatures at the
      cycle's mean time: ``c_i = k_i0 + Σ_j k_ij ΔT_j`` (seed 004: "the
      relationship between coefficients and temperatures" by MLR; three sensors:
      front bearing, nut, rear bearing). Seed 004 regresses on T; we use ΔT,
      which is the same linear model with another constant (k_i0 absorbs Σ k_ij T_j0
      when runs start at the same temperatures);
    * ``G`` the geometric error: the mean residual at each measuring point
      (seed 004), kept as a per-target table (``geometric_degree=None``) or
      fitted by a polynomial (seed 004 eq. 6).

    Parameters: ``sensors`` (None: the dataset's sensors at
    fixed_bearing_housing, nut_housing, free_bearing_housing, those present),
    ``mounting``, ``geometric_degree``, ``preprocess``, ``origin_mm``.

    Fitted: ``curve_coef_`` (shape (degree+1, 1+n_sensors): row i = ``[k_i0,
    k_i1..]`` for ``c_i``), ``shape_degree_``, ``sensors_``, ``geometric_``.
    """

    params_model = MLRSeed004Params
    needs = ("sensor_locations",)  # seed 004's three sensors, or the user's own (``sensors``)
    sensor_locations = SEED004_LOCATIONS

    def __init__(self, sensors=None, mounting=None, geometric_degree=None, preprocess="default", origin_mm=0.0):
        self.sensors = sensors
        self.mounting = mounting
        self.geometric_degree = geometric_degree
        self.preprocess = preprocess
        self.origin_mm = origin_mm

    def _curve_degree(self, ds: Dataset) -> int:
        return curve_degree(ds, self.mounting)

    def _pick_sensors(self, ds: Dataset, runs: list[str]) -> list[str]:
        sensors = sensor_list("sensors", self.sensors)
        if sensors is None:
            sensors = sensors_by_location(ds, SEED004_LOCATIONS)
            absent = [loc for loc in SEED004_LOCATIONS if loc not in ds.metadata.sensors.values()]
            if sensors and absent:
                fallback(f"sensors: no sensor at {absent}; the regression uses {sensors} only")
            if not sensors:
                raise ModelError(
                    f"sensors: the dataset has no sensor at {list(SEED004_LOCATIONS)} "
                    f"(it has {dict(ds.metadata.sensors)}); name the sensors explicitly"
                )
        elif not sensors:
            raise ModelError("sensors: an empty list; name at least one sensor or pass None")
        return check_sensors(ds, sensors, "sensors")
