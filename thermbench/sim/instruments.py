"""Measuring instruments of the simulator: temperature sensors and the laser interferometer.

* Sensors read lumped housing nodes (:class:`~thermbench.sim.parts.Housing`) with
  noise, the DS18B20's 0.0625 °C quantisation (seed 002 §3.1) and optional
  spikes and dropouts, the artefacts seed 002's limit filter exists for (§2.3.1).
  A dropout reads 85.0 °C, the DS18B20's power-on value, for a few samples.
* The interferometer reads the thermal error plus the geometric pitch error
  (not re-zeroed after the cold reference): a cubic in position (seed 002 eq. 7)
  plus a periodic lead error, plus noise.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


class FieldValueError(ValueError):
    """A constructor argument is out of range; ``field`` names it, so the config layer can name the
    whole key (``config key 'instruments.sensor.noise_C': expected a number >= 0, got -0.1``)."""

    def __init__(self, field: str, problem: str):
        self.field = field
        self.problem = problem
        super().__init__(f"{field}: {problem}")


def _at_least_zero(value: object, key: str) -> None:
    """``value`` must be a finite number >= 0 (a standard deviation, a step, a rate); ``key``
    names it (``noise_C``)."""
    ok = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not ok or not 0 <= value < math.inf:
        raise FieldValueError(key, f"expected a number >= 0, got {value!r}")


@dataclass(frozen=True)
class SensorSpec:
    """A temperature sensor (DS18B20 class): white noise of standard deviation ``noise_C``,
    rounding to ``quantum_C``, spikes of ``spike_C`` and dropouts (config ``instruments.sensor``).
    The noise, the quantum, the rates and the dropout length are >= 0 (0: none)."""

    noise_C: float = 0.03
    quantum_C: float = 0.0625
    spike_rate_per_h: float = 0.0
    spike_C: float = 6.0
    dropout_rate_per_h: float = 0.0
    dropout_len_s: float = 5.0
    dropout_value_C: float = 85.0

    def __post_init__(self) -> None:
        # built from config key 'instruments.sensor' (thermbench.sim.scenario names it)
        for key in ("noise_C", "quantum_C", "spike_rate_per_h", "dropout_rate_per_h", "dropout_len_s"):
            _at_least_zero(getattr(self, key), key)

    def read(self, true_C: np.ndarray, t_s: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        y = np.asarray(true_C, dtype=float).copy()
        if self.noise_C > 0:
            y += rng.normal(0.0, self.noise_C, y.shape)
        if self.quantum_C > 0:
            y = np.round(y / self.quantum_C) * self.quantum_C
        hours = (t_s[-1] - t_s[0]) / 3600.0 if len(t_s) > 1 else 0.0
        if self.spike_rate_per_h > 0:
            for i in rng.choice(len(y), size=rng.poisson(self.spike_rate_per_h * hours), replace=True):
                y[i] += self.spike_C * rng.choice((-1.0, 1.0))
        if self.dropout_rate_per_h > 0:
            dt = float(np.median(np.diff(t_s))) if len(t_s) > 1 else 1.0
            n = max(1, int(round(self.dropout_len_s / dt)))
            for i in rng.choice(len(y), size=rng.poisson(self.dropout_rate_per_h * hours), replace=True):
                y[i : i + n] = self.dropout_value_C
        return y


@dataclass(frozen=True)
class GeometricError:
    """Pitch error of the cold screw: poly_um[k] * P^k (P in mm, seed 002 eq. 7)
    + amplitude sin(2 pi P / period)."""

    poly_um: tuple[float, ...] = ()
    periodic_amp_um: float = 0.0
    periodic_period_mm: float = 10.0

    def __call__(self, target_mm) -> np.ndarray:
        p = np.asarray(target_mm, dtype=float)
        out = np.zeros_like(p)
        for k, c in enumerate(self.poly_um):
            out = out + c * p**k
        if self.periodic_amp_um:
            out = out + self.periodic_amp_um * np.sin(2 * np.pi * p / self.periodic_period_mm)
        return out


@dataclass(frozen=True)
class Interferometer:
    """The laser interferometer: the error plus the geometric one plus white noise of standard
    deviation ``noise_um`` (>= 0; config key ``instruments.interferometer.noise_um``)."""

    noise_um: float = 0.2
    geometric: GeometricError = field(default_factory=GeometricError)

    def __post_init__(self) -> None:
        _at_least_zero(self.noise_um, "noise_um")

    def read(self, thermal_um: np.ndarray, target_mm: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        y = np.asarray(thermal_um, dtype=float) + self.geometric(target_mm)
        if self.noise_um > 0:
            y = y + rng.normal(0.0, self.noise_um, y.shape)
        return y
