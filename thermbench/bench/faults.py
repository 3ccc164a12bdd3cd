"""Sensor faults at the compensator: each sensor checked sample by sample, a faulty one replaced, the correction bounded.

A linear model weights every sensor it reads; when one of them comes loose (it reads the air, a
local heat source, a broken wire), the correction follows it: on a real lathe test one sensor rose
38 K where it rises 5 K in every other run, and the model it fed moved the tool by 354 µm where
the thermal error was 54 µm. Stock controllers bound the compensation (SINUMERIK MD32760 limits
its rate; TwinCAT likewise). Here the rules and their thresholds come from the training runs'
process logs as logged (what the compensator reads), never from the run being compensated.

**Detection** (:class:`SensorLimits` fitted, :class:`FaultMonitor` stepped per sample), per sensor:

* ``open``: a reading that is not a finite number or lies outside ``PLAUSIBLE_C`` (an open or
  shorted RTD or thermocouple reads its transmitter's over- or under-range: PT100 transmitters
  read 850 °C or -200 °C);
* ``range``: the rise above the run's first sample beyond the training runs' range by more than
  the range's width (at least ``RANGE_MIN_K``): a run may heat more than any training run did, by
  as much again, before a sensor is judged;
* ``rate``: the rate of change (the envelope's first-order high-pass,
  :func:`thermbench.bench.intervals.rise_and_rate`, K/h) beyond ``RATE_FACTOR`` x the largest the
  training runs show plus ``RATE_MIN_K_H``: a jump, which no machine's mass makes;
* ``stuck``: the reading unchanged for longer than ``STUCK_FACTOR`` x the longest unchanged
  stretch of the training runs (at least ``STUCK_MIN_S``) while the rise the other sensors predict
  for it moved by more than ``STUCK_MOVE_K`` since (a machine at a steady state holds its readings
  for longer than any training run did, but a sensor whose neighbours say it warmed or cooled by
  that much does not hold its last digit; the prediction's offset, which the ``others`` tolerance
  allows for, cancels in a change); a sensor no other predicts is judged on the time alone, and one
  that never moved in training is never judged stuck;
* ``others``: each sensor's rise as the other sensors' rises predict it, a least-squares line
  fitted on the training runs (the sensors of one machine heat together); the sensor is faulty when
  its rise departs from that prediction by more than ``OTHERS_FACTOR`` x the largest departure of a
  training run held out of the fit (at least ``OTHERS_MIN_K``), and departs most of all sensors
  relative to that tolerance (a fault in one sensor moves the others' predictions by its weight in
  them, its own by all of it). The same holds of the rates (the lines without their intercept
  predict each sensor's rate from the others' rates): a sensor whose rate departs from the
  others' prediction by more than ``OTHERS_FACTOR`` x the largest such departure of a held-out
  training run (at least ``RATE_OTHERS_MIN_K_H``) is faulty too, which judges a drift long before
  its rise has departed by the rise's tolerance. A sensor already judged faulty enters the
  others' predictions as it is reconstructed (below).

A sensor judged faulty stays faulty for the rest of the run (latched): a sensor that read wrong
once is not trusted again without an operator. **Degradation**: from that sample on, the model is
given in its place the reading the other sensors predict (the same line: sensor reconstruction
from the correlation of the sensors, Dunia, Qin, Edgar and McAvoy, *Identification of faulty
sensors using principal component analysis*, AIChE J. 42(10), 1996), the faulty ones among them
as they are reconstructed; a sensor no other predicts is held at its last trusted reading. Every
family reads its inputs so, whatever it is.

**Bounds** (:class:`Bounds`): the correction never exceeds ``max_um`` in magnitude (default
``BOUND_FACTOR`` x the largest |error| of the training runs: the largest drift seen plus a
margin) and never changes faster than ``rate_um_s`` (default ``RATE_BOUND_FACTOR`` x the largest
change of the training runs' error over ``RATE_WINDOW_S``, per second).

:mod:`thermbench.bench.deployed` runs a fitted model as the compensator runs it, with these
rules, and plants the faults the tests and ``benchmarks/bench_faults.py`` plant.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from .intervals import RATE_WINDOW_S, rise_and_rate

__all__ = ["Bounds", "FaultMonitor", "SensorLimits", "fault_summary", "RULES"]

#: a temperature outside this range is no temperature of a machine tool: an open or shorted sensor (°C)
PLAUSIBLE_C = (-40.0, 150.0)
#: where a sensor faulty from a run's first sample starts when no sensor is plausible then (°C)
UNKNOWN_START_C = 20.0
#: the smallest margin beyond the training rise range (K)
RANGE_MIN_K = 3.0
#: the rate rule: this many times the training runs' largest |rate|, plus RATE_MIN_K_H
RATE_FACTOR = 2.0
RATE_MIN_K_H = 5.0
#: the stuck rule: this many times the longest unchanged stretch of the training runs, at least STUCK_MIN_S
STUCK_FACTOR = 2.0
STUCK_MIN_S = 1800.0
#: ... and while the others predict it moved by more than this since (K)
STUCK_MOVE_K = 2.0
#: the others' lines: ridge on standardised rises, the penalty this share of each variance (sensors that
#: heat together are nearly collinear: unpenalised, a line can weight one neighbour ten times over and
#: pass its fault on many times over)
RIDGE_SHARE = 0.01
#: the others rule: this many times the largest departure of a held-out training run, at least OTHERS_MIN_K
#: (a few training runs show only a few departures, and every sensor of a machine is judged at once)
OTHERS_FACTOR = 3.0
OTHERS_MIN_K = 2.0
#: ... and of the rates (K/h): a few times the rate one 0.1 K step of a reading makes (0.1 K x 3600 s/h / 600 s)
RATE_OTHERS_MIN_K_H = 2.0
#: the value bound: this many times the largest |thermal error| of the training runs
BOUND_FACTOR = 1.5
#: the rate bound: this many times the largest change of the training error over RATE_WINDOW_S
RATE_BOUND_FACTOR = 2.0

#: the rules, in the order a sample is checked (the first that fires names the fault)
RULES = ("open", "range", "rate", "stuck", "others")


@dataclass
class SensorLimits:
    """What the training runs say of each sensor (module docstring): the fitted side of the rules.

    Per sensor ``i`` of ``sensors``: ``rise_lo_K`` / ``rise_hi_K`` (K), ``rate_max_K_h`` (K/h, the largest
    |rate|), ``flat_s`` (the longest unchanged stretch, s; inf when it never moved); its rise as
    the others predict it, ``icpt[i] + coef[i] @ rise`` (``coef[i, i] = 0``), and the departure
    beyond which it is faulty, ``tol_K[i]`` (inf: no other sensor predicts it), and that of its rate
    from the others' rates, ``rate_tol_K_h[i]`` (inf, or None for every sensor: no such rule); ``start_offset_K[i]``,
    how far its first reading lies above the others' mean at a run's start (the mean over the runs:
    where a sensor is faulty from the first sample, the reading it is reconstructed from)."""

    sensors: tuple[str, ...]
    rise_lo_K: np.ndarray
    rise_hi_K: np.ndarray
    rate_max_K_h: np.ndarray
    flat_s: np.ndarray
    icpt: np.ndarray
    coef: np.ndarray
    tol_K: np.ndarray
    start_offset_K: np.ndarray | None = None
    tau_s: float = RATE_WINDOW_S
    rate_tol_K_h: np.ndarray | None = None

    @classmethod
    def fit(cls, ds, runs: Sequence[str], sensors: Sequence[str]) -> "SensorLimits":
        """The limits of ``sensors`` over the process logs of ``runs``."""
        sensors = tuple(sensors)
        n = len(sensors)
        rises, rates, flats, run_of, starts = [], [], np.zeros(n), [], []
        for run in runs:
            t, T = _log(ds, run, sensors)
            if t.size == 0:
                continue
            starts.append(T[0])
            rise, rate = rise_and_rate(t, T)
            rises.append(rise)
            rates.append(rate)
            run_of += [run] * t.size
            flats = np.maximum(flats, _longest_flat(t, T))
        if not rises:
            raise ValueError(f"no process-log samples of sensors {list(sensors)} in runs {list(runs)}")
        R, D = np.vstack(rises), np.vstack(rates)
        with np.errstate(invalid="ignore"):
            rise_lo_K, rise_hi_K = np.nanmin(R, axis=0), np.nanmax(R, axis=0)
            rate_max_K_h = np.nanmax(np.abs(D), axis=0)
        moved = rise_hi_K > rise_lo_K
        flat_s = np.where(moved, flats, np.inf)
        icpt, coef, tol, rate_tol = _others_lines(R, np.asarray(run_of), moved, D)
        S = np.vstack(starts)  # each run's first reading: how far each sensor starts from the others' mean
        with np.errstate(invalid="ignore"):
            others_mean = (np.nansum(S, axis=1, keepdims=True) - S) / max(n - 1, 1)
            offset = np.nan_to_num(np.nanmean(S - others_mean, axis=0)) if n > 1 else np.zeros(n)
        return cls(sensors, rise_lo_K, rise_hi_K, rate_max_K_h, flat_s, icpt, coef, tol, offset, RATE_WINDOW_S, rate_tol)

    # the thresholds the rules use, from the fitted limits
    @property
    def range_margin_K(self) -> np.ndarray:
        return np.maximum(self.rise_hi_K - self.rise_lo_K, RANGE_MIN_K)

    @property
    def rate_limit_K_h(self) -> np.ndarray:
        return RATE_FACTOR * self.rate_max_K_h + RATE_MIN_K_H

    @property
    def stuck_after_s(self) -> np.ndarray:
        return np.maximum(STUCK_FACTOR * self.flat_s, STUCK_MIN_S)

    @property
    def rate_tol(self) -> np.ndarray:
        """``rate_tol_K_h``, inf where there is none."""
        return np.full(len(self.sensors), np.inf) if self.rate_tol_K_h is None else self.rate_tol_K_h

    def to_dict(self) -> dict[str, Any]:
        def finite(a):  # JSON has no inf
            return [None if not math.isfinite(v) else float(v) for v in a]

        return {"sensors": list(self.sensors), "rise_lo_K": self.rise_lo_K.tolist(), "rise_hi_K": self.rise_hi_K.tolist(),
                "rate_max_K_h": self.rate_max_K_h.tolist(), "flat_s": finite(self.flat_s), "icpt": self.icpt.tolist(),
                "coef": self.coef.tolist(), "tol_K": finite(self.tol_K),
                "start_offset_K": (self.start_offset_K if self.start_offset_K is not None else np.zeros(len(self.sensors))).tolist(),
                "tau_s": self.tau_s, "rate_tol_K_h": finite(self.rate_tol)}  # fmt: skip

    @classmethod
    def from_dict(cls, d: Mapping[str, Any]) -> "SensorLimits":
        def inf(a):
            return np.array([np.inf if v is None else float(v) for v in a])

        n = len(d["sensors"])
        return cls(tuple(d["sensors"]), np.asarray(d["rise_lo_K"], float), np.asarray(d["rise_hi_K"], float),
                   np.asarray(d["rate_max_K_h"], float), inf(d["flat_s"]), np.asarray(d["icpt"], float),
                   np.asarray(d["coef"], float).reshape(n, n), inf(d["tol_K"]),
                   np.asarray(d.get("start_offset_K", np.zeros(n)), float), float(d.get("tau_s", RATE_WINDOW_S)),
                   inf(d["rate_tol_K_h"]) if d.get("rate_tol_K_h") is not None else None)  # fmt: skip


def _others_lines(R: np.ndarray, run_of: np.ndarray, moved: np.ndarray, D: np.ndarray | None = None):
    """Per sensor, its rise by ridge regression (``RIDGE_SHARE``) on the other moving sensors' rises (rows of ``R``,
    samples x sensors, of the runs ``run_of``), and its tolerance: ``OTHERS_FACTOR`` x the largest
    departure on a run held out of the fit (the line fitted on the other runs; with one run, on
    itself), at least ``OTHERS_MIN_K``; with the rates ``D`` (rows as ``R``'s), the same of the rate
    predicted by the line without its intercept, at least ``RATE_OTHERS_MIN_K_H`` (inf without
    ``D``). The fits come from each run's sums of products (the normal equations), so a run held
    out costs a small solve. Returns (icpt, coef, tol, rate_tol)."""
    n = R.shape[1]
    icpt, coef, tol, rate_tol = np.zeros(n), np.zeros((n, n)), np.full(n, np.inf), np.full(n, np.inf)
    ok = np.isfinite(R).all(axis=1)
    if D is not None:
        ok &= np.isfinite(D).all(axis=1)
        D = D[ok]
    R, run_of = R[ok], run_of[ok]
    runs = list(dict.fromkeys(run_of.tolist()))
    X = np.column_stack([np.ones(R.shape[0]), R])  # column 0 the intercept, 1 + k sensor k
    rows = {r: run_of == r for r in runs}
    gram = {r: X[rows[r]].T @ X[rows[r]] for r in runs}
    total = sum(gram.values()) if runs else np.zeros((n + 1, n + 1))

    def line(G, i, others):  # ridge on standardised rises, the penalty RIDGE_SHARE of each variance
        cols = [0, *[1 + k for k in others]]
        N = G[0, 0]
        m = G[0, cols[1:]] / N
        C = G[np.ix_(cols[1:], cols[1:])] / N - np.outer(m, m)
        c = G[cols[1:], 1 + i] / N - m * G[0, 1 + i] / N
        w = np.linalg.solve(C + RIDGE_SHARE * np.diag(np.maximum(np.diag(C), 1e-12)), c)
        return cols, np.concatenate([[G[0, 1 + i] / N - m @ w], w])

    for i in range(n):
        others = [k for k in range(n) if k != i and moved[k]]
        if not moved[i] or not others or R.shape[0] < len(others) + 2:
            continue
        cols, w = line(total, i, others)
        icpt[i], coef[i, others] = w[0], w[1:]
        worst = worst_rate = 0.0
        for r in runs if len(runs) > 1 else [None]:
            test = rows[r] if r is not None else np.ones(R.shape[0], bool)
            _, wr = line(total - gram[r], i, others) if r is not None else (cols, w)
            worst = max(worst, float(np.max(np.abs(R[test, i] - X[test][:, cols] @ wr))))
            if D is not None:
                worst_rate = max(worst_rate, float(np.max(np.abs(D[test, i] - D[test][:, others] @ wr[1:]))))
        tol[i] = max(OTHERS_FACTOR * worst, OTHERS_MIN_K)
        if D is not None:
            rate_tol[i] = max(OTHERS_FACTOR * worst_rate, RATE_OTHERS_MIN_K_H)
    return icpt, coef, tol, rate_tol


class FaultMonitor:
    """The rules of :class:`SensorLimits` followed sample by sample (module docstring), as the
    compensator follows them: :meth:`step` takes a sample's temperatures (°C, the limits' sensor
    order) and returns those the model is to read, a faulty sensor's replaced. ``fault[i]`` is the
    rule that judged sensor ``i`` faulty (None: healthy), ``onset_s[i]`` the sample's time."""

    def __init__(self, limits: SensorLimits) -> None:
        self.lim = limits
        self.reset()

    def reset(self) -> None:
        n = len(self.lim.sensors)
        self.T0_C = np.full(n, np.nan)  # the run's first plausible reading of each sensor
        self.e = np.full(n, np.nan)  # the rate's exponential average
        self.t_last: float | None = None
        self.last_value_C = np.full(n, np.nan)
        self.changed_s = np.zeros(n)
        self.predicted_at_change = np.full(n, np.nan)  # the others' prediction of the rise when it last changed
        self.trusted_C = np.full(n, np.nan)  # the last reading of each sensor judged healthy
        self.fault: list[str | None] = [None] * n
        self.onset_s = np.full(n, np.nan)

    @property
    def faulty(self) -> list[str]:
        return [s for s, f in zip(self.lim.sensors, self.fault) if f is not None]

    @classmethod
    def run(cls, limits: SensorLimits, t_s, temps_C) -> tuple[np.ndarray, "FaultMonitor"]:
        """A whole log (``temps_C``: samples x sensors) through a new monitor: the temperatures the
        model is to read, and the monitor after the last sample. The same as :meth:`step` sample by
        sample; a log on which no rule comes near firing (checked on whole arrays, with a margin for
        rounding) is returned as it is without the per-sample loop; the monitor returned then says
        which sensors were judged faulty (none) and where the rises counted from, and is not to be
        stepped further."""
        t = np.asarray(t_s, dtype=float).ravel()
        T = np.asarray(temps_C, dtype=float)
        n = len(limits.sensors)
        if T.shape != (t.size, n):
            raise ValueError(f"a log of {t.size} samples x {n} sensors {list(limits.sensors)} was expected, got an array "
                             f"of shape {T.shape}")  # fmt: skip
        if t.size > 1 and not (np.diff(t) > 0).all():
            raise ValueError("the log's times must increase from sample to sample")
        m = cls(limits)
        if t.size and not _may_fire(limits, t, T):
            m.T0_C, m.t_last = T[0].copy(), float(t[-1])
            return T.copy(), m
        used = np.vstack([m.step(tk, Tk) for tk, Tk in zip(t, T)]) if t.size else T.copy()
        return used, m

    def step(self, t_s: float, temps_C) -> np.ndarray:
        lim = self.lim
        T = np.asarray(temps_C, dtype=float).ravel().copy()
        n = T.size
        lo_c, hi_c = PLAUSIBLE_C
        plausible = np.isfinite(T) & (T >= lo_c) & (T <= hi_c)
        if self.t_last is None and not plausible.all():  # faulty from the first sample: where it would start,
            # by the others' mean and the training runs' offset from it (it stays faulty: latched)
            ref = float(np.mean(T[plausible])) if plausible.any() else UNKNOWN_START_C
            offset = lim.start_offset_K if lim.start_offset_K is not None else np.zeros(n)
            self.T0_C[~plausible] = ref + offset[~plausible]
            self.e[~plausible] = self.T0_C[~plausible]
        first = plausible & ~np.isfinite(self.T0_C)  # the rises count from each sensor's first plausible reading
        self.T0_C[first] = T[first]
        self.e[first] = T[first]
        if self.t_last is not None and t_s > self.t_last:
            a = 1.0 - math.exp(-(t_s - self.t_last) / lim.tau_s)
            go = plausible & ~first
            self.e[go] += a * (T[go] - self.e[go])
        if self.t_last is None:
            self.changed_s[:] = t_s
        self.t_last = float(t_s)
        changed = ~(T == self.last_value_C)
        self.changed_s[changed] = t_s
        self.last_value_C = T.copy()
        rise = T - self.T0_C
        rate = (T - self.e) * (3600.0 / lim.tau_s)
        margin = lim.range_margin_K
        known = np.where(np.isfinite(rise), rise, 0.0)
        self._reconstruct(known)
        predicted = lim.icpt + lim.coef @ known  # each sensor's rise as the others predict it
        self.predicted_at_change[changed | ~np.isfinite(self.predicted_at_change)] = predicted[
            changed | ~np.isfinite(self.predicted_at_change)]
        for i in range(n):
            if self.fault[i] is not None:
                continue
            why = None
            if not plausible[i]:
                why = "open"
            elif rise[i] > lim.rise_hi_K[i] + margin[i] or rise[i] < lim.rise_lo_K[i] - margin[i]:
                why = "range"
            elif abs(rate[i]) > lim.rate_limit_K_h[i]:
                why = "rate"
            elif t_s - self.changed_s[i] > lim.stuck_after_s[i] and (
                    not math.isfinite(lim.tol_K[i]) or abs(predicted[i] - self.predicted_at_change[i]) > STUCK_MOVE_K):
                why = "stuck"
            if why is not None:
                self.fault[i], self.onset_s[i] = why, float(t_s)
        used = np.where(np.isfinite(rise), rise, 0.0)  # the rises the model reads: a faulty sensor's reconstructed
        self._reconstruct(used)
        rates = np.where(np.isfinite(rate), rate, 0.0)  # and the rates, a faulty sensor's as the others' predict it
        self._reconstruct(rates, rates=True)
        healthy = np.array([f is None for f in self.fault])
        depart = np.where(healthy, self._departures(used, rates), 0.0)
        if depart.size and depart.max() > 1.0:  # the sensor whose reconstruction explains the departures best
            j = self._culprit(used, rates, healthy)
            self.fault[j], self.onset_s[j] = "others", float(t_s)
            self._reconstruct(used)
        for i in range(n):
            if self.fault[i] is None:
                self.trusted_C[i] = T[i]
        base = np.where(np.isfinite(self.T0_C), self.T0_C, T)
        return np.where(healthy & np.array([f is None for f in self.fault]), T, base + used)

    def _departures(self, rise: np.ndarray, rates: np.ndarray, signed: bool = False) -> np.ndarray:
        """Per sensor, the larger of its rise's and its rate's departure from the others' prediction,
        each over its tolerance (0 where there is no such line); ``signed``: the two as a pair
        (2 x sensors, with their signs) instead."""
        lim = self.lim
        with np.errstate(invalid="ignore", divide="ignore"):
            d = np.vstack([(rise - (lim.icpt + lim.coef @ rise)) / lim.tol_K, (rates - lim.coef @ rates) / lim.rate_tol])
        d = np.where(np.isfinite(d), d, 0.0)
        return d if signed else np.abs(d).max(axis=0)

    def _culprit(self, rise: np.ndarray, rates: np.ndarray, healthy: np.ndarray) -> int:
        """Of the healthy sensors, the one that, read as the others predict it (its rise and its rate),
        leaves the smallest sum of squared departures (relative to their tolerances) over the other
        healthy sensors: the reconstruction-based identification of Dunia et al. (a fault moves every
        line that weights the faulty sensor, so the sensor departing most need not be the faulty one)."""
        lim = self.lim
        best, score = -1, math.inf
        for j in np.flatnonzero(healthy & np.isfinite(lim.tol_K)):
            u, ur = rise.copy(), rates.copy()
            u[j] = lim.icpt[j] + lim.coef[j] @ u
            ur[j] = lim.coef[j] @ ur
            d = self._departures(u, ur, signed=True)
            keep = healthy.copy()
            keep[j] = False
            left = float(np.sum(d[:, keep] ** 2))
            if left < score:
                best, score = int(j), left
        return best

    def _reconstruct(self, values: np.ndarray, rates: bool = False) -> None:
        """The faulty sensors' rises in ``values`` (in place) as the others predict them (the faulty
        ones among the others as reconstructed: a few passes of the same lines), a sensor no other
        predicts at its last trusted rise; ``rates``: the rates instead, by the lines without their
        intercept, from 0 (a sensor no other predicts is held: no rate)."""
        bad = [i for i, f in enumerate(self.fault) if f is not None]
        if not bad:
            return
        lim = self.lim
        for i in bad:  # the start: the last trusted rise (no rate)
            ok = not rates and np.isfinite(self.trusted_C[i]) and np.isfinite(self.T0_C[i])
            values[i] = self.trusted_C[i] - self.T0_C[i] if ok else 0.0
        icpt = np.zeros_like(lim.icpt) if rates else lim.icpt
        for _ in range(3 if len(bad) > 1 else 1):
            for i in bad:
                if math.isfinite(lim.tol_K[i]):
                    values[i] = icpt[i] + lim.coef[i] @ values


def _may_fire(lim: SensorLimits, t: np.ndarray, T: np.ndarray, slack: float = 1e-6) -> bool:
    """Whether any rule of :meth:`FaultMonitor.step` could fire on the log, every sensor healthy
    (before a first fault nothing is replaced, so the rules see the log as it is): the same tests
    on whole arrays, each threshold lowered by ``slack`` of itself (so rounding never hides one)."""
    lo_c, hi_c = PLAUSIBLE_C
    if not (np.isfinite(T).all() and (T >= lo_c).all() and (T <= hi_c).all()):
        return True
    rise, rate = rise_and_rate(t, T, lim.tau_s)
    margin = lim.range_margin_K
    if ((rise > (lim.rise_hi_K + margin) - slack * np.abs(lim.rise_hi_K + margin)) |
            (rise < (lim.rise_lo_K - margin) + slack * np.abs(lim.rise_lo_K - margin))).any():  # fmt: skip
        return True
    if (np.abs(rate) > lim.rate_limit_K_h * (1.0 - slack)).any():
        return True
    predicted = lim.icpt + rise @ lim.coef.T
    with np.errstate(invalid="ignore", divide="ignore"):
        if (np.abs(rise - predicted) / lim.tol_K > 1.0 - slack).any():
            return True
        if (np.abs(rate - rate @ lim.coef.T) / lim.rate_tol > 1.0 - slack).any():
            return True
    # stuck: the time since each sensor's reading last changed, and the others' prediction then
    changed = np.vstack([np.ones((1, T.shape[1]), bool), T[1:] != T[:-1]])
    idx = np.where(changed, np.arange(t.size)[:, None], 0)
    last = np.maximum.accumulate(idx, axis=0)
    since = t[:, None] - t[last]
    moved = np.abs(predicted - np.take_along_axis(predicted, last, axis=0))
    need = np.where(np.isfinite(lim.tol_K), moved > STUCK_MOVE_K * (1.0 - slack), True)
    return bool(((since > lim.stuck_after_s * (1.0 - slack)) & need).any())


@dataclass
class Bounds:
    """The correction's bounds: ``|E| <= max_um``, ``|dE/dt| <= rate_um_s`` (module docstring)."""

    max_um: float
    rate_um_s: float

    @classmethod
    def fit(cls, ds, runs: Sequence[str]) -> "Bounds":
        """From the errors of ``runs``: ``BOUND_FACTOR`` x the largest |error| (what a model predicts:
        the thermal error with the run's cold reference), and ``RATE_BOUND_FACTOR`` x the largest
        change of the thermal error over ``RATE_WINDOW_S`` (per second)."""
        from ..data.reference import thermal_errors

        te = thermal_errors(ds)
        te = te[te["run_id"].isin(list(runs))]
        if te.empty or not np.isfinite(te["thermal_um"]).any():
            raise ValueError(f"no thermal error in runs {list(runs)} to bound a correction by")
        top = float(np.nanmax(np.abs(te["error_um"].to_numpy(dtype=float))))  # what is predicted: the whole error
        rate = 0.0
        keys = ["run_id"] + [c for c in ("channel", "target_mm", "direction") if c in te.columns]
        for _, g in te.groupby(keys, sort=False, dropna=False):  # one series per run and measuring position
            g = g.sort_values("t_s")
            t, e = g["t_s"].to_numpy(dtype=float), g["thermal_um"].to_numpy(dtype=float)
            if t.size < 2:
                continue
            later = np.interp(t + RATE_WINDOW_S, t, e, right=np.nan)
            d = np.abs(later - e)[np.isfinite(later)]
            if d.size:
                rate = max(rate, float(d.max()) / RATE_WINDOW_S)
            elif t[-1] > t[0]:  # a run shorter than the window
                rate = max(rate, float(np.ptp(e)) / float(t[-1] - t[0]))
        if top <= 0:
            raise ValueError(f"no thermal error in runs {list(runs)} to bound a correction by")
        return cls(BOUND_FACTOR * top, RATE_BOUND_FACTOR * rate if rate > 0 else math.inf)

    def apply(self, t_s, predicted_um) -> tuple[np.ndarray, np.ndarray]:
        """The predictions at times ``t_s`` (ascending) bounded in value, then in rate from the
        first (the compensator starts where the model does); and per value whether a bound acted.
        A prediction that is not finite (no answer yet) stays so, acts no bound, and the rate
        bound goes on from the last bounded value (``tb_faults_bound`` of the C runtime alike)."""
        t = np.asarray(t_s, dtype=float)
        p = np.asarray(predicted_um, dtype=float)
        out = np.where(np.isfinite(p), np.clip(p, -self.max_um, self.max_um), p)
        acted = np.isfinite(p) & (out != p)
        last = None  # the index of the last finite bounded value
        for k in range(out.size):
            if not np.isfinite(out[k]):
                continue
            if last is not None:
                step = self.rate_um_s * max(t[k] - t[last], 0.0)
                v = min(max(out[k], out[last] - step), out[last] + step)
                if v != out[k]:
                    acted[k] = True
                    out[k] = v
            last = k
        return out, acted


def _log(ds, run: str, sensors: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
    pr = ds.process_run(run)
    cols = [ds.metadata.sensor_column(s) for s in sensors]
    return pr["t_s"].to_numpy(dtype=float), pr[cols].to_numpy(dtype=float).reshape(len(pr), len(cols))


def _longest_flat(t: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Per column of ``T`` (samples x sensors), the longest time its value stays unchanged."""
    out = np.zeros(T.shape[1])
    for i in range(T.shape[1]):
        change = np.flatnonzero(np.diff(T[:, i]) != 0) + 1
        starts = np.concatenate([[0], change])
        ends = np.concatenate([change, [T.shape[0] - 1]])
        if starts.size:
            out[i] = float(np.max(t[ends] - t[starts]))
    return out


def fault_summary(monitor: FaultMonitor | None) -> str:
    """``sensor: rule at t s`` for each sensor judged faulty ('' when none)."""
    if monitor is None:
        return ""
    return "; ".join(f"{s}: {f} at {o:.0f} s" for s, f, o in zip(monitor.lim.sensors, monitor.fault, monitor.onset_s)
                     if f is not None)  # fmt: skip
