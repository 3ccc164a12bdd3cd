"""The motion features of a run's log over a sliding window, as a live compensator computes them
from its own log (seed 002 §2.4's A, B, C; measuring cycles excluded, stops flagged), and the same
for a condition that is an operating input (a spindle test's ``spindle_rpm``): what
:class:`~thermbench.models.classify.ProximityNaiveBayes` classifies at run time.

* :func:`window_features` - the motion features of the last ``window_s`` of a run's motion log
  at given times, and :func:`measuring_intervals`, the time intervals of a run's measuring
  cycles to exclude;
* :func:`operating_window_features` - the time-weighted mean of an operating input over the
  running samples of the window.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from .classify import FEATURES

__all__ = ["measuring_intervals", "operating_window_features", "window_features"]


def measuring_intervals(process_run: pd.DataFrame, errors_run: pd.DataFrame, margin_s: float = 2.0) -> np.ndarray:
    """(n, 2) time intervals of the run's measuring cycles, to leave out of the motion
    features: from the start of the approach to the cycle's first target to the end
    of the return from its last target, plus ``margin_s`` each side.

    The cycles are those of :func:`thermbench.data.reference.reading_cycles` on the
    reading times (not their values: a compensator knows when it measured). The
    approach is the monotone move that ends at the first target's dwell, the return
    the monotone move that starts after the last target's dwell (both can be at the
    work feed, e.g. seed 002 #1 works at the 800 mm/min measuring feed).
    """
    from ..data.reference import reading_cycles

    er_t = errors_run["t_s"].to_numpy(dtype=float)
    if er_t.size == 0:
        return np.empty((0, 2))
    cyc = errors_run["cycle"].to_numpy() if "cycle" in errors_run.columns else reading_cycles(errors_run)
    t = process_run["t_s"].to_numpy(dtype=float)
    x = process_run["axis_mm"].to_numpy(dtype=float)
    n = t.size
    if n < 2:
        return np.empty((0, 2))
    tol = 1e-6 * max(1.0, float(np.max(np.abs(x))))
    d = np.diff(x)
    s = np.where(d > tol, 1, np.where(d < -tol, -1, 0))  # s[i]: move from sample i to i+1
    # runs of equal s: starts[r] / ends[r] are the first / last diff index of run r; run_of[i] the run of i
    change = np.flatnonzero(np.diff(s) != 0) + 1
    starts = np.concatenate([[0], change])
    ends = np.concatenate([change - 1, [s.size - 1]])
    run_of = np.repeat(np.arange(starts.size), ends - starts + 1)
    out = []
    for c in np.unique(cyc):
        ta, tb = er_t[cyc == c].min(), er_t[cyc == c].max()
        # back from the first reading: over the dwell (no move), then over the approach
        k = int(np.clip(np.searchsorted(t, ta, side="right") - 1, 0, n - 1)) - 1  # move into that sample
        for want_dwell in (True, False):
            if k >= 0 and (s[k] == 0) == want_dwell:
                k = starts[run_of[k]] - 1
        t0 = t[k + 1]
        # forward from the last reading: over the dwell, then over the return move
        k = int(np.clip(np.searchsorted(t, tb, side="left"), 0, n - 1))  # move out of that sample
        for want_dwell in (True, False):
            if k <= s.size - 1 and (s[k] == 0) == want_dwell:
                k = ends[run_of[k]] + 1
        t1 = t[min(k, n - 1)]
        out.append((t0 - margin_s, t1 + margin_s))
    return np.asarray(out, dtype=float)


def _cluster_feeds(feed: np.ndarray, moving: np.ndarray, rel_tol: float = 0.01) -> tuple[np.ndarray, np.ndarray]:
    """Integer code per sample of its feed level (-1 when not moving) and the
    levels; feeds within ``rel_tol`` of the previous distinct value are one level."""
    code = np.full(feed.size, -1, dtype=int)
    if not moving.any():
        return code, np.empty(0)
    u = np.unique(feed[moving])
    brk = np.flatnonzero(np.diff(u) > rel_tol * u[1:]) + 1
    group = np.zeros(u.size, dtype=int)
    group[brk] = 1
    group = np.cumsum(group)
    code[moving] = group[np.searchsorted(u, feed[moving])]
    return code, np.array([u[group == g].mean() for g in range(group[-1] + 1)])


def _range_reduce(values: np.ndarray, lo: np.ndarray, hi: np.ndarray, ufunc) -> np.ndarray:
    """ufunc-reduce of values[lo[k]:hi[k]] for each k (lo < hi required where used)."""
    if values.size == 0:
        return np.full(lo.size, np.nan)
    ext = np.append(values, values[-1])
    idx = np.empty(2 * lo.size, dtype=int)
    idx[0::2] = np.clip(lo, 0, values.size - 1)
    idx[1::2] = np.clip(hi, 0, values.size)
    return ufunc.reduceat(ext, idx)[0::2]


def window_features(
    process_run: pd.DataFrame,
    t_s,
    window_s: float = 600.0,
    exclude=None,
    min_moving_s: float = 60.0,
) -> pd.DataFrame:
    """Motion features of the log in (t - window_s, t] for each t (seed 002 §2.4's A,
    B, C as a live compensator computes them from its own motion log).

    Samples that are not moving (feed 0) or fall in an ``exclude`` interval
    [t0, t1] (e.g. :func:`measuring_intervals`) are left out; each sample counts for
    the time to the next one. ``feed_mm_min`` is the dominant feed (the feed level,
    within 1 %, with the most moving time; its time-weighted mean), and ``start_mm``
    / ``end_mm`` the range of the positions sampled at that feed, ``stroke_mm`` their
    difference. ``moving`` is False (and the features NaN) when less than
    ``min_moving_s`` of motion is left in the window.

    At 1 Hz a fast stroke aliases: seed 002 #8 (100 mm at 4000 mm/min, a 3 s period)
    is sampled at 566.7, 633.3 and 600 mm only. Two consecutive samples at feed v
    closer than the path L = v dt have a reversal in between, at (a + b + L)/2 (top)
    or (a + b - L)/2 (bottom); when one of the two lies strictly inside the sampled
    range it is impossible and the other is the turning point, which extends the
    range (#8: 550-650 mm). With two or more reversals between samples (L > stroke,
    e.g. #7: 50 mm at 4000 mm/min) both readings lie outside and are ignored, so #7
    keeps its apparent 600-633 mm (the classifiers see the same in training and use).
    """
    if not window_s > 0:
        raise ValueError(f"window_s must be > 0, got {window_s}")
    for c in ("t_s", "axis_mm", "feed_mm_min"):
        if c not in process_run.columns:
            raise ValueError(
                f"window_features: the process log has no column {c!r}; columns: {list(process_run.columns)}"
            )
    tq = np.atleast_1d(np.asarray(t_s, dtype=float))
    t = process_run["t_s"].to_numpy(dtype=float)
    x = process_run["axis_mm"].to_numpy(dtype=float)
    f = process_run["feed_mm_min"].to_numpy(dtype=float)
    n = t.size
    out = pd.DataFrame(
        {c: np.full(tq.size, np.nan) for c in FEATURES} | {"moving": np.zeros(tq.size, dtype=bool)}
    )
    if n == 0 or tq.size == 0:
        return out
    w = np.diff(t, append=t[-1] + (np.median(np.diff(t)) if n > 1 else 1.0))
    moving = np.isfinite(f) & (f > 0) & np.isfinite(x)
    if exclude is not None:
        ex = np.asarray(exclude, dtype=float).reshape(-1, 2)
        for a, b in ex:
            moving &= ~((t >= a) & (t <= b))
    code, levels = _cluster_feeds(f, moving)
    lo = np.searchsorted(t, tq - window_s, side="right")
    hi = np.searchsorted(t, tq, side="right")
    if levels.size == 0:
        return out
    # per feed level: moving time in each window, via cumulative sums
    onehot = code[:, None] == np.arange(levels.size)[None, :]
    cw = np.vstack([np.zeros((1, levels.size)), np.cumsum(onehot * w[:, None], axis=0)])
    cwf = np.vstack([np.zeros((1, levels.size)), np.cumsum(onehot * (w * np.where(moving, f, 0.0))[:, None], axis=0)])
    time_in = cw[hi] - cw[lo]  # (nq, levels)
    dom = np.argmax(time_in, axis=1)
    rows = np.arange(tq.size)
    tdom = time_in[rows, dom]
    ok = time_in.sum(axis=1) >= min_moving_s
    ok &= tdom > 0
    feed = np.where(ok, (cwf[hi] - cwf[lo])[rows, dom] / np.where(tdom > 0, tdom, 1.0), np.nan)
    start = np.full(tq.size, np.nan)
    end = np.full(tq.size, np.nan)
    # turning points between samples (1 Hz aliasing): a pair of consecutive samples at
    # the same feed that lies closer than the path length L = v dt has a reversal in
    # between, at (a + b + L) / 2 (top) or (a + b - L) / 2 (bottom)
    dt = np.diff(t)
    step = float(np.median(dt)) if n > 1 else 1.0
    L = f[:-1] / 60.0 * dt
    gap = L - np.abs(np.diff(x))
    # the pair and its neighbours moving at one feed (no start or stop next to it)
    same = np.r_[False, code[1:] == code[:-1]]  # same[i]: sample i at the feed of i - 1
    steady = (code[:-1] >= 0) & same[:-1] & same[1:] & np.r_[same[2:], False]
    pair = steady & (dt <= 1.5 * step) & (gap > 0.02 * L + 0.1)
    top = (x[:-1] + x[1:] + L) / 2.0
    bot = (x[:-1] + x[1:] - L) / 2.0
    for g in np.unique(dom[ok]):
        sel = np.flatnonzero(code == g)
        q = np.flatnonzero(ok & (dom == g))
        a = np.searchsorted(sel, lo[q], side="left")
        b = np.searchsorted(sel, hi[q], side="left")
        start[q] = _range_reduce(x[sel], a, b, np.minimum)
        end[q] = _range_reduce(x[sel], a, b, np.maximum)
        pg = np.flatnonzero(pair & (code[:-1] == g))
        if pg.size == 0:
            continue
        pa = np.searchsorted(pg, lo[q], side="left")
        pb = np.searchsorted(pg, hi[q] - 1, side="left")  # pairs (i, i+1) with i + 1 < hi
        for k, qi in enumerate(q):
            idx = pg[pa[k] : pb[k]]
            if idx.size == 0:
                continue
            x0, x1 = start[qi], end[qi]
            tol = 1e-6 * max(1.0, abs(x0), abs(x1))
            # a turning point cannot lie strictly inside the sampled range: when one of the
            # two readings does, the other is the true one (2+ reversals leave both outside)
            t_in, b_in = top[idx] < x1 - tol, bot[idx] > x0 + tol
            up, down = top[idx][b_in & ~t_in], bot[idx][t_in & ~b_in]
            if up.size:
                end[qi] = max(x1, float(up.max()))
            if down.size:
                start[qi] = min(x0, float(down.min()))
    out["stroke_mm"] = end - start
    out["start_mm"] = start + 0.0  # no -0.0
    out["end_mm"] = end + 0.0
    out["feed_mm_min"] = feed
    out["moving"] = ok
    return out


def operating_window_features(
    process_run: pd.DataFrame,
    t_s,
    columns,
    window_s: float = 600.0,
    min_moving_s: float = 60.0,
) -> pd.DataFrame:
    """The operating-input features of the log in (t - window_s, t] for each t: what a
    live compensator classifies when the condition is an operating input (a spindle
    test's speed, seed 002 §2.4's eq. 15 factor read from ``spindle_rpm``) rather than
    the axis motion (:func:`window_features`).

    A sample is *running* when any of ``columns`` is > 0 (finite); each sample counts
    for the time to the next one (the last for the median step). Per column, the
    feature is the time-weighted mean over the window's running samples (one column:
    its mean over the samples where it is > 0), so stops inside the window do not
    dilute the speed. ``moving`` is True when the window holds at least
    ``min_moving_s`` (and more than 0 s) of running time; else the features are NaN
    (a stop: the bank holds the last class).

    Returns a DataFrame with one column per name in ``columns`` and ``moving``.
    """
    if not window_s > 0:
        raise ValueError(f"window_s must be > 0, got {window_s}")
    columns = [str(c) for c in columns]
    if not columns:
        raise ValueError("operating_window_features: give at least one operating column")
    missing = [c for c in ("t_s", *columns) if c not in process_run.columns]
    if missing:
        raise ValueError(
            f"operating_window_features: the process log has no column(s) {missing}; "
            f"columns: {list(process_run.columns)}"
        )
    tq = np.atleast_1d(np.asarray(t_s, dtype=float))
    t = process_run["t_s"].to_numpy(dtype=float)
    V = np.column_stack([process_run[c].to_numpy(dtype=float) for c in columns])
    n = t.size
    out = pd.DataFrame({c: np.full(tq.size, np.nan) for c in columns} | {"moving": np.zeros(tq.size, dtype=bool)})
    if n == 0 or tq.size == 0:
        return out
    w = np.diff(t, append=t[-1] + (np.median(np.diff(t)) if n > 1 else 1.0))
    running = np.all(np.isfinite(V), axis=1) & np.any(V > 0, axis=1)
    rw = np.where(running, w, 0.0)
    lo = np.searchsorted(t, tq - window_s, side="right")
    hi = np.searchsorted(t, tq, side="right")
    cw = np.concatenate([[0.0], np.cumsum(rw)])
    time_in = cw[hi] - cw[lo]
    ok = (time_in >= min_moving_s) & (time_in > 0)
    for j, c in enumerate(columns):
        cv = np.concatenate([[0.0], np.cumsum(rw * np.where(running, V[:, j], 0.0))])
        out[c] = np.where(ok, (cv[hi] - cv[lo]) / np.where(ok, time_in, 1.0), np.nan)
    out["moving"] = ok
    return out
