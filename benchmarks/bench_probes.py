"""Probe readings on the measured spindle test's unseen tail: RMSE against probes per hour.

For each channel of ``fl_thermal`` and each family given: the family fitted on the five
constant-speed blocks predicts the stepped tail (never trained on); the probe filter's noise
(thermbench/bench/adapt.py :func:`estimate_noise`) is estimated from the family's residuals on the
training blocks, each predicted by a fit without it (leave one block out: nothing of the tail);
then the tail is replayed with a probe every ``every_s`` (the first at the tail's start), the
probes being the tail's own readings at those times, and **scored on the other readings only**:

* ``open``: no probe;
* ``naive``: the last probe's residual added to every later prediction (a peer method);
* ``adaptive``: the bias + gain Kalman filter;
* ``trigger``: the filter, probing when its standard deviation exceeds the one it reaches
  just before a scheduled probe on the training blocks (median), no schedule;
* ``oracle``: the best constant offset per probe interval, chosen with hindsight from the tail
  itself (not a method: the bound a bias correction alone cannot beat);
* ``oracle_gain``: the best bias and gain per probe interval, with hindsight (least squares on the
  tail's readings in it): the bound of the filter's own correction, ``(1 + gain)·predicted + bias``;
* ``gp_refit`` (family ``gp`` only): the GP refitted on its training readings plus the probes so
  far (:func:`thermbench.bench.adapt.gp_refit`, a second peer method).

    python benchmarks/bench_probes.py [--families physics_spindle_hybrid,baseline_ridge] [--every 7200,3600,1800]

``--smooth-s 0,300,1200``: a diagnostic, not a method: replay every column above with the
prediction first smoothed causally (an exponential moving average with that time constant, 0: as
predicted; the leave-one-block-out residuals the same way). The family's prediction follows its
sensors' noise, which the measured error does not have; this shows how much of each channel's
error at a given probe interval that noise is. Picking the constant by its score on the tail
would be tuning on the tail: the table gives every constant asked for.

``--figure PATH``: also draw the first family's prediction on one channel's tail (``--figure-channel``):
open loop with its 90 % interval, and with a probe every ``--every``'s second interval (hourly by
default), the filter's corrected prediction with its own 90 % interval; both intervals conformal,
calibrated on the training blocks' leave-one-block-out residuals (replayed with the same probes for
the adaptive one), nothing of the tail (docs/intervals.md shows it).
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np
import pandas as pd

CHANNELS = ["ch1", "ch2", "ch3", "ch4", "ch5"]


def rmse(a, b) -> float:
    return float(np.sqrt(np.mean((np.asarray(a) - np.asarray(b)) ** 2)))


def channel_runs(family: str, ch: str, seed: int):
    """(tail t, measured, predicted) and the training blocks' ``(t, measured, predicted)``, each predicted by a fit without it."""
    from sklearn.base import clone

    from thermbench.config import group_option
    from thermbench.experiment import build_model
    from thermbench.bench.splits import load_split

    split = load_split({**group_option("dataset", "fl_thermal"), "channel": ch})
    ds = split.dataset
    model = build_model(group_option("model", family), seed=seed)
    fitted = clone(model).fit(ds, split.states)
    tail = ds.errors_run(split.validation[0])
    pred = np.asarray(fitted.predict(ds, split.validation[0]), dtype=float)
    loro = []
    for r in split.states:
        m = clone(model).fit(ds, [s for s in split.states if s != r])
        e = ds.errors_run(r)
        loro.append((e["t_s"].to_numpy(float), e["error_um"].to_numpy(float), np.asarray(m.predict(ds, r), dtype=float)))
    out = tail["t_s"].to_numpy(float), tail["error_um"].to_numpy(float), pred, loro
    if not hasattr(fitted, "train_Z_"):  # not a GP: no refit peer
        return (*out, None)
    from thermbench.bench.adapt import gp_refit

    def refit(sched):
        return gp_refit(fitted, ds, split.validation[0], out[0], tail["target_mm"].to_numpy(float), out[1], sched)

    return (*out, refit)


def smooth(t_s: np.ndarray, x: np.ndarray, tau_s: float) -> np.ndarray:
    """A causal exponential moving average of ``x`` with time constant ``tau_s`` (0: ``x`` itself)."""
    if tau_s <= 0:
        return x
    return pd.Series(x).ewm(halflife=pd.Timedelta(seconds=tau_s * np.log(2)), times=pd.to_datetime(t_s, unit="s")).mean().to_numpy()


def channel_rows(fam, ch, t, y, p, loro, refit, every_list: str) -> list[dict]:
    """The table's rows of one family and channel (module docstring), ``loro`` the training blocks' residuals."""
    from thermbench.bench.adapt import apply_probes, estimate_noise, naive_probes, probe_schedule, trigger_level

    rows = []
    rows.append(dict(family=fam, channel=ch, method="open", every_s=np.nan, probes=0, rmse_um=rmse(p, y)))
    for every in (float(e) for e in every_list.split(",")):
        params = estimate_noise(loro, every)
        sched = probe_schedule(t, every)
        keep = ~sched
        rows.append(dict(family=fam, channel=ch, method="naive", every_s=every, probes=int(sched.sum()),
                         rmse_um=rmse(naive_probes(p, y, sched)[keep], y[keep])))  # fmt: skip
        seg = np.cumsum(sched)  # the best constant offset per probe interval, with hindsight: a bound
        best = p + pd.Series(y - p).groupby(seg).transform("mean").to_numpy()
        rows.append(dict(family=fam, channel=ch, method="oracle", every_s=every, probes=int(sched.sum()),
                         rmse_um=rmse(best[keep], y[keep])))  # fmt: skip
        aff = p.copy()  # the best bias and gain per probe interval, with hindsight: the filter's own bound
        for k in np.unique(seg):
            m = seg == k
            A = np.c_[np.ones(m.sum()), p[m]]
            aff[m] = p[m] + A @ np.linalg.lstsq(A, (y - p)[m], rcond=None)[0]
        rows.append(dict(family=fam, channel=ch, method="oracle_gain", every_s=every, probes=int(sched.sum()),
                         rmse_um=rmse(aff[keep], y[keep])))  # fmt: skip
        if refit is not None:
            rows.append(dict(family=fam, channel=ch, method="gp_refit", every_s=every, probes=int(sched.sum()),
                             rmse_um=rmse(refit(sched)[keep], y[keep])))  # fmt: skip
        c, _, _ = apply_probes(t, p, y, params, schedule=sched)
        rows.append(dict(family=fam, channel=ch, method="adaptive", every_s=every, probes=int(sched.sum()),
                         rmse_um=rmse(c[keep], y[keep]), q_bias_um2_per_h=params.q_bias_um2_per_h,
                         r_um2=params.r_um2, bias0_um=params.bias0_um))  # fmt: skip
        level = trigger_level(loro, params, every)  # the std just before a scheduled probe, training blocks
        c, _, probed = apply_probes(t, p, y, params, trigger_um=level)
        keep = ~probed
        rows.append(dict(family=fam, channel=ch, method="trigger", every_s=every, probes=int(probed.sum()),
                         rmse_um=rmse(c[keep], y[keep]), trigger_um=level))  # fmt: skip
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default="physics_spindle_hybrid,baseline_ridge")
    ap.add_argument("--every", default="7200,3600,1800", help="probe intervals, s")
    ap.add_argument("--channels", default=",".join(CHANNELS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--smooth-s", default="0", help="time constants (s) of a causal smoothing of the prediction (module docstring)")
    ap.add_argument("--out", default=None, help="write the table as CSV here")
    ap.add_argument("--figure", default=None, help="draw the first family's tail on --figure-channel here (PNG)")
    ap.add_argument("--figure-channel", default="ch3")
    ap.add_argument("--force", action="store_true", help="replace --figure when it exists (a figure this script wrote)")
    args = ap.parse_args()
    if args.figure and Path(args.figure).exists() and not args.force:
        ap.exit(2, f"bench_probes.py: error: --figure {args.figure} exists; add --force to replace it (never a file this "
                   "script did not write)\n")  # fmt: skip
    os.environ.setdefault("THERMBENCH_DATA", str(Path("data/benchmark").resolve()))
    rows = []
    for fam in args.families.split(","):
        for ch in args.channels.split(","):
            t0 = time.perf_counter()
            t, y, p0, loro0, refit = channel_runs(fam, ch, args.seed)
            for tau in (float(x) for x in args.smooth_s.split(",")):
                p = smooth(t, p0, tau)
                loro = [(tr, yr - smooth(tr, pr, tau)) for tr, yr, pr in loro0]
                rows.extend(dict(r, smooth_s=tau) for r in channel_rows(fam, ch, t, y, p, loro, refit if tau <= 0 else None, args.every))
            print(f"{fam} {ch}: {time.perf_counter() - t0:.0f} s", flush=True)
    if args.figure:
        every = [float(e) for e in args.every.split(",")]
        figure(args.families.split(",")[0], args.figure_channel, every[min(1, len(every) - 1)], args.seed, args.figure)
    df = pd.DataFrame(rows)
    if args.out:
        df.to_csv(args.out, index=False)
    with pd.option_context("display.width", 200, "display.max_rows", 500, "display.float_format", "{:.2f}".format):
        for (fam, tau), g in df.groupby(["family", "smooth_s"], sort=False):
            how = f", the prediction smoothed over {tau:g} s" if tau > 0 else ""
            print(f"\n{fam}{how}: tail RMSE (µm) without the probe readings; probes in brackets")
            g = g.assign(col=[m if m == "open" else f"{m} {e / 3600:g}h" for m, e in zip(g["method"], g["every_s"])],
                         cell=[f"{r:.2f} ({n})" for r, n in zip(g["rmse_um"], g["probes"])])  # fmt: skip
            print(g.pivot(index="channel", columns="col", values="cell").to_string())


def figure(family: str, ch: str, every: float, seed: int, path: str) -> None:
    """The tail of ``ch``: measured, open loop and probed (module docstring)."""
    from matplotlib.figure import Figure

    from thermbench.bench.adapt import apply_probes, estimate_noise, probe_schedule
    from thermbench.bench.intervals import conformal_quantile

    t, y, p, loro, _ = channel_runs(family, ch, seed)
    loro = [(tr, yr - pr) for tr, yr, pr in loro]
    params = estimate_noise(loro, every)
    q_open = conformal_quantile(np.concatenate([np.abs(d) for _, d in loro]), 0.9)
    scores = []
    for tr, d in loro:  # the training blocks' residuals replayed with the same probes: the adaptive interval
        c, var, probed = apply_probes(tr, np.zeros_like(d), d, params, schedule=probe_schedule(tr, every))
        scores.append((np.abs(d - c) / np.sqrt(var + params.r_um2))[~probed])
    q_ad = conformal_quantile(np.concatenate(scores), 0.9)
    sched = probe_schedule(t, every)
    c, var, _ = apply_probes(t, p, y, params, schedule=sched)
    hw = q_ad * np.sqrt(var + params.r_um2)
    keep = ~sched
    h = (t - t[0]) / 3600.0
    fig = Figure(figsize=(9.0, 4.2), layout="constrained")
    ax = fig.subplots()
    ax.plot(h, y, ".", color="0.45", markersize=2, label="measured")
    ax.fill_between(h, p - q_open, p + q_open, color="C0", alpha=0.15, linewidth=0)
    ax.plot(h, p, color="C0", linewidth=1.0,
            label=f"open loop: RMSE {rmse(p[keep], y[keep]):.2f} µm, 90 % interval ±{q_open:.2f} µm, "
                  f"inside {np.mean(np.abs(y - p)[keep] <= q_open):.0%}")  # fmt: skip
    ax.fill_between(h, c - hw, c + hw, color="C3", alpha=0.2, linewidth=0)
    ax.plot(h, c, color="C3", linewidth=1.0,
            label=f"a probe every {every / 3600:g} h: RMSE {rmse(c[keep], y[keep]):.2f} µm, mean ±{hw[keep].mean():.2f} µm, "
                  f"inside {np.mean(np.abs(y - c)[keep] <= hw[keep]):.0%}")  # fmt: skip
    ax.plot(h[sched], y[sched], "v", color="C3", markersize=6, label="probe readings (not scored)")
    ax.set_xlabel("hours into the stepped tail (never trained on)")
    ax.set_ylabel(f"{ch} error (µm)")
    ax.set_title(f"fl_thermal {ch}, {family}: prediction, 90 % interval and probe updates", fontsize=10)
    ax.legend(fontsize=7, loc="best")
    ax.grid(alpha=0.3)
    tmp = Path(path).with_name(f".{Path(path).name}.tmp")
    fig.savefig(tmp, dpi=110, format="png")
    os.replace(tmp, path)  # never half-written
    print(f"figure: {path}")


if __name__ == "__main__":
    main()
