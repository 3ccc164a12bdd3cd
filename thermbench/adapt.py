"""Online updates of a model's prediction from occasional measurements (probe readings).

A shop that measures anyway (a touch probe on a reference artefact every hour, a test cut)
gets a reading ``(t_s, measured_um)`` of the very error the model predicts. :class:`ProbeFilter`
turns those readings into a correction of the model's output, by a Kalman filter on two
states (the adaptive thermal models updated from intermittent on-machine measurements of the
ETH Zurich machine-tool group; Kalman's linear filter in its textbook form):

    measured(t) = (1 + gain) * predicted(t) + bias + v,       v ~ N(0, r_um2)
    bias and gain walk at random between probes:             Var[Δbias] = q_bias_um2_per_h * Δt_h,
                                                             Var[Δgain] = q_gain_per_h * Δt_h

so a probe pulls the bias (and, once predictions of different size have been probed, the
gain) toward the measured error, and between probes the corrected prediction is
``(1 + gain) * predicted + bias``, with a variance ``H P Hᵀ`` (``H = [1, predicted]``) that
grows with the time since the last probe: what the prediction interval and the ``uncertainty``
probe trigger read. The filter does not move the state between probes (a random walk has no
drift), so a correction at time ``t`` is a pure function of the state and ``t``: the C runtime
(``tb_probe``) answers the same way.

Units: the bias and the readings in µm, the gain dimensionless, times in seconds, the process
noise per hour (``q_bias_um2_per_h`` in µm²/h, ``q_gain_per_h`` in 1/h), the measurement
noise ``r_um2`` in µm².
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, fields
from typing import Any, Mapping

import numpy as np

__all__ = ["ProbeParams", "ProbeFilter", "apply_probes"]


class ProbeParamsError(ValueError):
    """A probe filter setting that cannot work (names the config key)."""


@dataclass(frozen=True)
class ProbeParams:
    """The filter's noise model. Defaults: see ``conf/probe.yaml`` (measured on fl_thermal's
    training blocks by ``benchmarks/bench_probes.py --noise``)."""

    q_bias_um2_per_h: float = 1.0  # how fast the model's offset wanders between probes
    q_gain_per_h: float = 1e-4  # how fast its scale wanders (a gain std of 1 % after an hour)
    r_um2: float = 0.1  # a probe reading's own scatter (the dataset's repeatability), squared
    bias0_um: float = 3.0  # the offset's std before the first probe (the model's held-out RMSE)
    gain0: float = 0.1  # the gain's std before the first probe

    def __post_init__(self) -> None:
        for f in fields(self):
            v = getattr(self, f.name)
            if not isinstance(v, (int, float)) or isinstance(v, bool) or not math.isfinite(v) or v < 0:
                raise ProbeParamsError(f"config key 'probe.{f.name}': expected a finite number >= 0, got {v!r}")
        if self.r_um2 <= 0:
            raise ProbeParamsError(f"config key 'probe.r_um2': expected a number > 0 (a reading is never exact), got {self.r_um2!r}")

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None) -> "ProbeParams":
        cfg = dict(cfg or {})
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ProbeParamsError(f"config key(s) {['probe.' + k for k in unknown]}: unknown; known: {sorted(known)}")
        return cls(**{k: float(v) if isinstance(v, int) and not isinstance(v, bool) else v for k, v in cfg.items()})

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


class ProbeFilter:
    """The bias + gain Kalman filter of the module docstring, for one channel.

    ``correct(t_s, predicted_um)`` gives the corrected prediction and its variance at ``t_s``
    (no state change); ``probe(t_s, predicted_um, measured_um)`` takes a reading (``predicted_um``
    is the model's uncorrected prediction at the reading's time) and returns the innovation.
    Times must not go back between probes. ``state()`` / ``from_state()`` carry the filter over
    a restart."""

    def __init__(self, params: ProbeParams | None = None, t0_s: float = 0.0) -> None:
        self.params = params or ProbeParams()
        p = self.params
        self.x = np.zeros(2)  # bias_um, gain
        self.P = np.diag([p.bias0_um**2, p.gain0**2])
        self.t_s = float(t0_s)  # the time the state refers to (its last probe, or the start)
        self.n_probes = 0

    def _P_at(self, t_s: float) -> np.ndarray:
        dt_h = max(float(t_s) - self.t_s, 0.0) / 3600.0
        p = self.params
        return self.P + np.diag([p.q_bias_um2_per_h * dt_h, p.q_gain_per_h * dt_h])

    def correct(self, t_s: float, predicted_um: float) -> tuple[float, float]:
        """The corrected prediction (µm) at ``t_s`` and its variance (µm², the filter's own: not
        counting the model's error that the bias and gain do not capture)."""
        H = np.array([1.0, float(predicted_um)])
        P = self._P_at(t_s)
        return float(predicted_um * (1.0 + self.x[1]) + self.x[0]), float(H @ P @ H)

    def probe(self, t_s: float, predicted_um: float, measured_um: float) -> float:
        """Take a probe reading; returns its innovation (measured minus corrected, µm)."""
        if not (math.isfinite(t_s) and math.isfinite(predicted_um) and math.isfinite(measured_um)):
            raise ValueError(f"a probe reading must be finite: t_s={t_s}, predicted_um={predicted_um}, measured_um={measured_um}")
        if t_s < self.t_s:
            raise ValueError(f"a probe at {t_s} s is older than the filter's state ({self.t_s} s)")
        H = np.array([1.0, float(predicted_um)])
        P = self._P_at(t_s)
        corrected = float(predicted_um * (1.0 + self.x[1]) + self.x[0])
        innovation = float(measured_um) - corrected
        S = float(H @ P @ H) + self.params.r_um2
        K = P @ H / S
        self.x = self.x + K * innovation
        I_KH = np.eye(2) - np.outer(K, H)
        self.P = I_KH @ P @ I_KH.T + self.params.r_um2 * np.outer(K, K)  # Joseph form: stays symmetric, positive
        self.t_s = float(t_s)
        self.n_probes += 1
        return innovation

    def state(self) -> dict[str, Any]:
        return {"bias_um": float(self.x[0]), "gain": float(self.x[1]), "P": self.P.tolist(), "t_s": self.t_s,
                "n_probes": self.n_probes, "params": self.params.as_dict()}  # fmt: skip

    @classmethod
    def from_state(cls, state: Mapping[str, Any]) -> "ProbeFilter":
        f = cls(ProbeParams(**state["params"]), float(state["t_s"]))
        f.x = np.array([float(state["bias_um"]), float(state["gain"])])
        f.P = np.asarray(state["P"], dtype=float).reshape(2, 2)
        f.n_probes = int(state["n_probes"])
        return f


def apply_probes(t_s: np.ndarray, predicted_um: np.ndarray, probes: np.ndarray, measured_um: np.ndarray,
                 params: ProbeParams | None = None) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """The corrected predictions of one run and their variances, the readings where ``probes``
    is true taken as probes in time order. A reading's own correction is the one before its
    probe (what the compensator applied when it was taken)."""
    t = np.asarray(t_s, dtype=float)
    p = np.asarray(predicted_um, dtype=float)
    m = np.asarray(measured_um, dtype=float)
    probes = np.asarray(probes, dtype=bool)
    f = ProbeFilter(params, float(t[0]) if t.size else 0.0)
    out, var = np.empty_like(p), np.empty_like(p)
    for i in range(t.size):
        out[i], var[i] = f.correct(t[i], p[i])
        if probes[i]:
            f.probe(t[i], p[i], m[i])
    return out, var
