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

__all__ = ["ProbeParams", "ProbeFilter", "ProbePlan", "apply_probes", "estimate_noise", "naive_probes", "probe_replays",
           "probe_schedule", "trigger_level"]


class ProbeParamsError(ValueError):
    """A probe filter setting that cannot work (names the config key)."""


@dataclass(frozen=True)
class ProbeParams:
    """The filter's noise model. Defaults (also ``probe`` in ``conf/compensator.yaml``): measured on
    fl_thermal's training blocks, the median over its five channels of :func:`estimate_noise` of
    physics_spindle_hybrid's leave-one-block-out residuals at a one-hour interval
    (``python benchmarks/bench_probes.py --families physics_spindle_hybrid``: 9.0 µm²/h, 0.0022 µm²,
    6.3 µm); the gain's are not identifiable from residuals and are chosen."""

    q_bias_um2_per_h: float = 9.0  # how fast the model's offset wanders between probes
    q_gain_per_h: float = 1e-4  # how fast its scale wanders (a gain std of 1 % after an hour)
    r_um2: float = 0.0022  # a probe reading's own scatter (the dataset's repeatability), squared
    bias0_um: float = 6.3  # the offset's std before the first probe (the model's held-out RMSE)
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


def apply_probes(t_s: np.ndarray, predicted_um: np.ndarray, measured_um: np.ndarray, params: ProbeParams | None = None,
                 schedule: np.ndarray | None = None, trigger_um: float | None = None,
                 widen: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """One run's corrected predictions, their variances and the readings taken as probes, in
    time order: those where ``schedule`` is true, and (``trigger_um``) any whose corrected
    prediction's standard deviation, the reading's scatter included (``sqrt(var + r_um2)``),
    times ``widen`` (the interval's widening ``1 + kappa * distance`` outside the training
    envelope; none: 1) exceeds ``trigger_um``: probing when the interval's half-width is wide,
    which it is sooner where the inputs leave the envelope. A reading's own correction is the
    one before its probe (what the compensator applied when it was taken)."""
    t = np.asarray(t_s, dtype=float)
    p = np.asarray(predicted_um, dtype=float)
    m = np.asarray(measured_um, dtype=float)
    sched = np.zeros(t.size, bool) if schedule is None else np.asarray(schedule, dtype=bool)
    w = np.ones(t.size) if widen is None else np.asarray(widen, dtype=float)
    f = ProbeFilter(params, float(t[0]) if t.size else 0.0)
    r = f.params.r_um2
    out, var, probed = np.empty_like(p), np.empty_like(p), np.zeros(t.size, dtype=bool)
    for i in range(t.size):
        out[i], var[i] = f.correct(t[i], p[i])
        if sched[i] or (trigger_um is not None and math.sqrt(var[i] + r) * w[i] > trigger_um):
            f.probe(t[i], p[i], m[i])
            probed[i] = True
    return out, var, probed

def semivariogram(runs: list[tuple[np.ndarray, np.ndarray]], lag_s: float) -> float:
    """½ E[(d(t + lag) - d(t))²] over the residual series ``runs`` ((t_s, residual_um) per run, each
    sampled evenly), the pairs ``lag_s`` apart (to the nearest sample) within each run."""
    num, n = 0.0, 0
    for t, d in runs:
        t, d = np.asarray(t, dtype=float), np.asarray(d, dtype=float)
        if t.size < 2:
            continue
        k = max(int(round(lag_s / float(np.median(np.diff(t))))), 1)
        if k >= t.size:
            continue
        diff = d[k:] - d[:-k]
        num += 0.5 * float(np.sum(diff**2))
        n += diff.size
    if n == 0:
        raise ValueError(f"no pair of residuals {lag_s:g} s apart within a run: the runs are too short")
    return num / n


def estimate_noise(runs: list[tuple[np.ndarray, np.ndarray]], every_s: float, gain0: float = 0.1,
                   q_gain_per_h: float = 1e-4) -> ProbeParams:  # fmt: skip
    """The filter's noise from a model's residuals on runs it was not fitted on ((t_s, residual_um)
    per run: cross-validation over runs, never the run to be scored), by the semivariogram γ of the
    residual: a random-walk bias plus white reading scatter has γ(Δ) = r + q·Δ/2, so

    * ``r_um2`` = γ at one sample's lag (the scatter between neighbouring readings: the
      repeatability of reading and prediction together),
    * ``q_bias_um2_per_h`` = 2 (γ(every_s) - r) / every_h: the wander over the probe interval the
      filter will bridge (a residual that is no random walk is matched where it matters),
    * ``bias0_um`` = the residuals' RMS (the offset before any probe).

    The gain's prior and wander are not identifiable from residuals alone: given (``gain0``,
    ``q_gain_per_h``)."""
    if not runs:
        raise ValueError("no residual runs to estimate the probe noise from")
    steps = [float(np.median(np.diff(np.asarray(t, dtype=float)))) for t, _ in runs if len(t) > 1]
    r = semivariogram(runs, min(steps))
    g = semivariogram(runs, every_s)
    q = max(2.0 * (g - r), 0.0) / (every_s / 3600.0)
    rms = float(np.sqrt(np.mean(np.concatenate([np.asarray(d, dtype=float) ** 2 for _, d in runs]))))
    return ProbeParams(q_bias_um2_per_h=q, q_gain_per_h=q_gain_per_h, r_um2=max(r, 1e-6), bias0_um=rms, gain0=gain0)


def probe_schedule(t_s: np.ndarray, every_s: float) -> np.ndarray:
    """The readings a probe every ``every_s`` takes: the first reading, then the first reading at or
    after each ``every_s`` since the run's first (a boolean mask)."""
    t = np.asarray(t_s, dtype=float)
    mask = np.zeros(t.size, dtype=bool)
    if t.size == 0:
        return mask
    due = np.arange(t[0], t[-1] + 1e-9, float(every_s))
    idx = np.unique(np.searchsorted(t, due - 1e-9))
    mask[idx[idx < t.size]] = True
    return mask


def naive_probes(predicted_um: np.ndarray, measured_um: np.ndarray, schedule: np.ndarray) -> np.ndarray:
    """The naive peer: the last probe's residual (measured - predicted) added to every later
    prediction (a reading's own correction is the one before its probe)."""
    p = np.asarray(predicted_um, dtype=float)
    m = np.asarray(measured_um, dtype=float)
    sched = np.asarray(schedule, dtype=bool)
    idx = np.flatnonzero(sched)
    offset = np.zeros(p.size)
    for a, b in zip(idx, list(idx[1:]) + [p.size]):
        offset[a + 1 : b + 1] = m[a] - p[a]
    return p + offset


def gp_refit(model, ds, run: str, t_s, axis_mm, measured_um, schedule) -> np.ndarray:
    """The GP-refit peer: the recalibration of petrkaftan/Thermal_Compensation (a Gaussian process
    refitted on all data so far), made realistic: it sees only the probe readings, not the error
    at every sample. ``model``: a fitted :class:`~thermbench.models.gp.GaussianProcessLag`; at each
    probe of ``schedule`` (a mask over the run's readings) its GP is refitted on its training
    readings plus every probe so far, with the kernel its fit found (a refit is one Cholesky
    factorisation, as a compensator could afford), and predicts the readings after the probe up
    to the next one (a reading's own prediction is the one before its probe)."""
    from sklearn.base import clone

    x = np.asarray(axis_mm, dtype=float)
    Z = model._X(ds, run, np.asarray(t_s, dtype=float), x)
    geo = model.geometric_um(x)
    y = np.asarray(measured_um, dtype=float) - geo  # the GP's part of the error
    pred = np.asarray(model.gp_.predict(Z), dtype=float)
    idx = np.flatnonzero(np.asarray(schedule, dtype=bool))
    base = clone(model.gp_).set_params(kernel=model.gp_.kernel_, optimizer=None, n_restarts_optimizer=0)
    for i, (a, b) in enumerate(zip(idx, list(idx[1:]) + [y.size - 1])):
        if b <= a:
            continue
        probes = idx[: i + 1]
        gp = clone(base).fit(np.vstack([model.train_Z_, Z[probes]]), np.concatenate([model.train_y_um_, y[probes]]))
        pred[a + 1 : b + 1] = gp.predict(Z[a + 1 : b + 1])
    return pred + geo


@dataclass(frozen=True)
class ProbePlan:
    """How the benchmark probes a held-out run (config key ``probe``): a schedule per ``every_s``,
    and with ``trigger: uncertainty`` also the filter probing when its standard deviation exceeds
    ``threshold_um`` (null: the one it reaches just before a scheduled probe of the first
    ``every_s``, on the calibration runs). ``noise``: the filter's :class:`ProbeParams` (null:
    :func:`estimate_noise` on each fold's calibration residuals)."""

    every_s: tuple[float, ...] = (3600.0,)
    trigger: str | None = "uncertainty"
    threshold_um: float | None = None
    noise: ProbeParams | None = None

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any] | None) -> "ProbePlan":
        cfg = dict(cfg or {})
        known = {"every_s", "trigger", "threshold_um", "noise"}
        unknown = sorted(set(cfg) - known)
        if unknown:
            raise ProbeParamsError(f"config key(s) {['probe.' + k for k in unknown]}: unknown; known: {sorted(known)}")
        every = cfg.get("every_s", [3600.0])
        every = [every] if isinstance(every, (int, float)) and not isinstance(every, bool) else every
        if (not isinstance(every, (list, tuple)) or not every
                or not all(isinstance(e, (int, float)) and not isinstance(e, bool) and math.isfinite(e) and e > 0 for e in every)):  # fmt: skip
            raise ProbeParamsError(f"config key 'probe.every_s': expected a probe interval in seconds (> 0) or a "
                                   f"non-empty list of them, got {cfg.get('every_s')!r}")  # fmt: skip
        trigger = cfg.get("trigger", "uncertainty")
        if trigger not in (None, "uncertainty"):
            raise ProbeParamsError(f"config key 'probe.trigger': expected null or uncertainty, got {trigger!r}")
        thr = cfg.get("threshold_um")
        if thr is not None and (isinstance(thr, bool) or not isinstance(thr, (int, float)) or not thr > 0):
            raise ProbeParamsError(f"config key 'probe.threshold_um': expected null or a number > 0, got {thr!r}")
        noise = cfg.get("noise")
        return cls(tuple(float(e) for e in every), trigger, None if thr is None else float(thr),
                   None if noise is None else ProbeParams.from_config(noise))  # fmt: skip


def trigger_level(runs: list[tuple], params: ProbeParams, every_s: float, kappa: float = 0.0) -> float:
    """The filter's standard deviation (the reading's scatter included) just before a probe of a
    schedule every ``every_s``, median over the probes after the first of the residual ``runs``
    ((t_s, residual_um) or (t_s, residual_um, distance to their envelope): with ``kappa``, the
    standard deviation times ``1 + kappa * distance``, as :func:`apply_probes` compares it)."""
    before: list[float] = []
    for run in runs:
        t, d = run[0], run[1]
        w = 1.0 + kappa * np.asarray(run[2], dtype=float) if len(run) > 2 and kappa else np.ones(len(t))
        sched = probe_schedule(t, every_s)
        _, var, _ = apply_probes(t, np.zeros_like(d), d, params, schedule=sched)  # a residual: the prediction is 0
        before.extend((np.sqrt(var + params.r_um2) * w)[sched][1:])
    if not before:
        raise ValueError(f"no calibration run is longer than one probe interval ({every_s:g} s)")
    return float(np.median(before))


def probe_replays(t_s, measured_um, predicted_um, plan: ProbePlan, params: ProbeParams,
                  calibration: list[tuple], distance=None, kappa: float = 0.0):  # fmt: skip
    """One held-out run replayed with probes as ``plan`` says: yields (approach, corrected, var,
    probed) for ``adaptive-<every>s`` and ``naive_probe-<every>s`` per schedule, then
    ``adaptive-uncertainty`` (probing when the half-width, widened by ``1 + kappa * distance``
    outside the envelope, exceeds its level); ``var`` is None for the naive peer."""
    t, y, p = (np.asarray(a, dtype=float) for a in (t_s, measured_um, predicted_um))
    for every in plan.every_s:
        sched = probe_schedule(t, every)
        c, var, probed = apply_probes(t, p, y, params, schedule=sched)
        yield f"adaptive-{every:g}s", c, var, probed
        yield f"naive_probe-{every:g}s", naive_probes(p, y, sched), None, sched
    if plan.trigger == "uncertainty":
        level = plan.threshold_um if plan.threshold_um is not None else trigger_level(calibration, params, plan.every_s[0], kappa)
        widen = None if distance is None or not kappa else 1.0 + kappa * np.asarray(distance, dtype=float)
        c, var, probed = apply_probes(t, p, y, params, trigger_um=level, widen=widen)
        yield "adaptive-uncertainty", c, var, probed
