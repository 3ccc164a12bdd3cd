"""Prediction intervals and the training envelope: a model that knows when it may be wrong.

**The envelope** (:class:`Envelope`) is what a model saw while it was fitted: per temperature
sensor it reads, the range of its rise above the run's first reading (K) and of its rate of
change (K/h, a first-order high-pass of time constant :data:`RATE_WINDOW_S`), and per operating
signal (e.g. ``spindle_rpm``) its range, all from the process log as logged. :meth:`Envelope.distance` says how far a reading's inputs are outside it, in units of
each range's width (0 inside); a reading outside is *extrapolating* (the compensator's
``EXTRAPOLATING`` flag).

**The interval** is split conformal prediction over whole runs (Vovk, Gammerman & Shafer,
*Algorithmic Learning in a Random World*, 2005; Lei et al., *Distribution-free predictive
inference for regression*, JASA 2018): the calibration scores are a model's residuals on
runs it was not fitted on (the inner folds of the cross-validation over runs), normalised by
the distance of their inputs to the envelope of the runs it *was* fitted on,

    score = |residual| / (1 + kappa * distance),

and the half-width at a new reading is ``q * (1 + kappa * distance)``, ``q`` the
⌈(n + 1)·level⌉-th smallest score: a nominal ``level`` interval that holds on an unseen run as
far as runs are exchangeable, and widens where the inputs leave what the model saw.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

__all__ = ["Envelope", "EnvelopeGuard", "conformal_quantile", "half_widths", "interval_scores", "rise_and_rate", "RATE_WINDOW_S"]

#: the time constant of a sensor's rate of change (:func:`rise_and_rate`)
RATE_WINDOW_S = 600.0
#: the narrowest range a distance is measured in: a rise or rate range narrower than this (a steady
#: block) does not make a small step outside it look far
MIN_WIDTH = {"rise": 0.5, "rate": 0.5}  # K, K/h
#: an operating signal's narrowest range, as a fraction of its largest magnitude seen (at least 1)
MIN_WIDTH_OPERATING = 0.05


@dataclass
class Envelope:
    """The ranges of a model's inputs over the runs it was fitted on (module docstring).

    ``names``: ``rise:<sensor>``, ``rate:<sensor>`` and ``op:<column>``; ``lo`` / ``hi`` their
    ranges; ``width`` the width a distance is measured in."""

    sensors: tuple[str, ...] = ()
    operating: tuple[str, ...] = ()
    names: list[str] = field(default_factory=list)
    lo: np.ndarray = field(default_factory=lambda: np.zeros(0))
    hi: np.ndarray = field(default_factory=lambda: np.zeros(0))
    width: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @staticmethod
    def features(ds, run: str, t_s, sensors: Sequence[str], operating: Sequence[str] = ()) -> np.ndarray:
        """The envelope's inputs at times ``t_s`` of ``run``, from its process log as logged (what
        the compensator reads): each sensor's rise and rate (:func:`rise_and_rate`), then each
        operating signal; shape (n, 2 * len(sensors) + len(operating))."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        pr = ds.process_run(run)
        tp = pr["t_s"].to_numpy(dtype=float)
        cols = []
        if sensors:
            T = np.column_stack([pr[ds.metadata.sensor_column(s)].to_numpy(dtype=float) for s in sensors])
            rise, rate = rise_and_rate(tp, T)
            cols += [np.column_stack([np.interp(t, tp, c) for c in x.T]) for x in (rise, rate)]
        if operating:
            cols.append(np.column_stack([np.interp(t, tp, pr[c].to_numpy(dtype=float)) for c in operating]))
        return np.hstack(cols) if cols else np.zeros((t.size, 0))

    @classmethod
    def fit(cls, ds, runs: Sequence[str], sensors: Sequence[str], operating: Sequence[str] = ()) -> "Envelope":
        """The envelope of ``runs`` at their readings' times."""
        sensors, operating = tuple(sensors), tuple(operating)
        F = np.vstack([cls.features(ds, r, ds.errors_run(r)["t_s"].to_numpy(dtype=float), sensors, operating)
                       for r in runs])  # fmt: skip
        names = [f"rise:{s}" for s in sensors] + [f"rate:{s}" for s in sensors] + [f"op:{c}" for c in operating]
        if F.shape[0] == 0:
            raise ValueError("an envelope of no readings")
        with np.errstate(invalid="ignore"):  # a sensor's gaps (NaN) are not a range
            lo, hi = np.nan_to_num(np.nanmin(F, axis=0)), np.nan_to_num(np.nanmax(F, axis=0))
        floor = np.array([MIN_WIDTH["rise"]] * len(sensors) + [MIN_WIDTH["rate"]] * len(sensors)
                         + [max(MIN_WIDTH_OPERATING * max(abs(a), abs(b)), 1.0) for a, b in
                            zip(lo[2 * len(sensors):], hi[2 * len(sensors):])])  # fmt: skip
        return cls(sensors, operating, names, lo, hi, np.maximum(hi - lo, floor))

    def distance(self, F: np.ndarray) -> np.ndarray:
        """Per row of ``F`` (:meth:`features`), the largest exceedance of any input beyond its range,
        in widths of that range (0 inside the envelope)."""
        F = np.atleast_2d(np.asarray(F, dtype=float))
        if F.shape[1] == 0:
            return np.zeros(F.shape[0])
        over = np.maximum(F - self.hi, 0.0) + np.maximum(self.lo - F, 0.0)
        return (over / self.width).max(axis=1)

    def outside(self, F: np.ndarray) -> list[list[str]]:
        """Per row, the inputs outside their range."""
        F = np.atleast_2d(np.asarray(F, dtype=float))
        out = (F > self.hi) | (F < self.lo)
        return [[n for n, o in zip(self.names, row) if o] for row in out]

    def to_dict(self) -> dict[str, Any]:
        return {"sensors": list(self.sensors), "operating": list(self.operating), "names": list(self.names),
                "lo": self.lo.tolist(), "hi": self.hi.tolist(), "width": self.width.tolist()}  # fmt: skip

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "Envelope":
        return cls(tuple(d["sensors"]), tuple(d["operating"]), list(d["names"]), np.asarray(d["lo"], dtype=float),
                   np.asarray(d["hi"], dtype=float), np.asarray(d["width"], dtype=float))  # fmt: skip


def rise_and_rate(t_s: np.ndarray, T_C: np.ndarray, tau_s: float = RATE_WINDOW_S) -> tuple[np.ndarray, np.ndarray]:
    """Per sample of a log (``T_C``: samples x sensors): the rise above the first sample (K) and the
    rate of change (K/h) as a first-order high-pass, ``(T - e) / tau``, ``e`` the exponential
    average of ``T`` with time constant ``tau_s`` (``e_k = e_{k-1} + (1 - exp(-Δt/tau)) (T_k - e_{k-1})``,
    ``e_0 = T_0``): a steady ramp of r K/h reads r once it has run a few ``tau``; it needs no
    window of past samples, so the C runtime keeps one number per sensor for it."""
    t = np.asarray(t_s, dtype=float)
    T = np.asarray(T_C, dtype=float).reshape(t.size, -1)
    if t.size == 0:
        return T.copy(), T.copy()
    dt = np.diff(t)
    a = 1.0 - np.exp(-dt / tau_s)
    e = np.empty_like(T)
    e[0] = T[0]
    if dt.size and np.allclose(dt, dt[0], rtol=1e-9, atol=0.0) and np.isfinite(T).all():  # a regular log: one filter
        from scipy.signal import lfilter

        a0 = float(a[0])
        e[1:] = lfilter([a0], [1.0, -(1.0 - a0)], T[1:], axis=0, zi=((1.0 - a0) * T[0])[None, :])[0]
        return T - T[0], (T - e) * (3600.0 / tau_s)
    for k in range(1, t.size):
        e[k] = e[k - 1] + a[k - 1] * (T[k] - e[k - 1])
    return T - T[0], (T - e) * (3600.0 / tau_s)


def interval_scores(residual_um, distance, kappa: float = 1.0) -> np.ndarray:
    """The conformal scores ``|residual| / (1 + kappa * distance)``."""
    return np.abs(np.asarray(residual_um, dtype=float)) / (1.0 + kappa * np.asarray(distance, dtype=float))


def conformal_quantile(scores, level: float = 0.9) -> float:
    """The ⌈(n + 1)·level⌉-th smallest of ``scores`` (inf when there are too few for ``level``)."""
    s = np.sort(np.asarray(scores, dtype=float)[np.isfinite(scores)])
    if not 0 < level < 1:
        raise ValueError(f"interval level must be between 0 and 1, got {level}")
    k = math.ceil((s.size + 1) * level)
    return float(s[k - 1]) if 1 <= k <= s.size else math.inf


def half_widths(q: float, distance, kappa: float = 1.0) -> np.ndarray:
    """The interval's half-width (µm) at readings ``distance`` from the envelope."""
    return q * (1.0 + kappa * np.asarray(distance, dtype=float))


class EnvelopeGuard:
    """The envelope followed sample by sample, as a compensator (and the C runtime) sees the
    inputs: each sensor's rise above the first sample and its high-pass rate (the recursion of
    :func:`rise_and_rate`), each operating signal as it is. :meth:`step` returns the sample's
    distance to the envelope (0 inside): a reading beyond it is ``EXTRAPOLATING``."""

    def __init__(self, envelope: Envelope, tau_s: float = RATE_WINDOW_S) -> None:
        self.env = envelope
        self.tau_s = float(tau_s)
        self.T0: np.ndarray | None = None
        self.e: np.ndarray | None = None
        self.t_last: float | None = None
        self.distance = 0.0
        self.outside: list[str] = []

    def reset(self) -> None:
        self.T0 = self.e = self.t_last = None

    def step(self, t_s: float, temps_C, operating=()) -> float:
        T = np.asarray(temps_C, dtype=float).ravel()
        if self.T0 is None:
            self.T0, self.e = T.copy(), T.copy()
        elif t_s > self.t_last:
            self.e = self.e + (1.0 - math.exp(-(t_s - self.t_last) / self.tau_s)) * (T - self.e)
        self.t_last = float(t_s)
        F = np.concatenate([T - self.T0, (T - self.e) * (3600.0 / self.tau_s), np.asarray(operating, dtype=float).ravel()])
        self.distance = float(self.env.distance(F[None, :])[0])
        self.outside = self.env.outside(F[None, :])[0] if self.distance > 0 else []
        return self.distance
