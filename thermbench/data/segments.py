"""Loading conditions derived from an operating signal: segments of a run.

A real thermal test rarely declares one loading condition per run. A 46-hour spindle
test runs "4 h at 1250 rpm, then 4 h stopped", "4 h at 2500 rpm, then 4 h stopped", ...
and ends with a stepped duty cycle, all in one record. :func:`derive_segments` cuts such
a record into *segments* by reading one operating signal (spindle speed in rpm, or an
axis feed in mm/min, signed or not), so that each segment can be used like a declared
loading condition, and :func:`segment_name` gives each one a default run id
(``s01_1250rpm``, ``s06_varying``).

A segment is one operating period followed by the rest after it::

    |-- initial rest --|== operation ==|---- rest ----|== operation ==|-- rest --|
                       ^start_s        ^on_end_s      ^end_s = next start_s      ^end_s (last sample)
                       |<------------ segment 0 ----->|<------- segment 1 ------>|

Notation: ``t`` the sample times (s), ``v`` the signal, ``dt`` the median sample
interval. A run of consecutive samples ``i..j`` *lasts* ``t[j] - t[i] + dt`` (``k * dt``
for ``k`` evenly spaced samples).

Algorithm
---------

1. **Stop threshold.** ``thr = stop_below`` if given, else 2 % of the signal's robust
   maximum, ``vmax`` = the 99th percentile of ``|v|`` (the maximum of ``|v|`` if that
   percentile is 0). A sample *operates* when ``|v| > thr``; the absolute value makes a
   signed velocity (``+F`` / ``-F`` strokes) work like a speed. All levels below are
   magnitudes. The default threshold assumes the record operates somewhere: for a
   record that may only hold the noise of a stopped machine, pass ``stop_below``
   (otherwise the noise itself sets the threshold; an all-zero signal gives ``[]``).
2. **Smoothing.** ``|v|`` is smoothed by a centred moving median over ``w`` samples,
   ``w = max(3, round(window_s / dt))`` made odd (default ``window_s = 5 * dt``, so
   ``w = 5``), the ends padded with the first/last value. A sample operates *after
   smoothing* when its smoothed ``|v|`` exceeds ``thr``, i.e. when most of the ``w`` samples
   around it operate: single-sample glitches and stops shorter than about half a window
   (axis reversals) vanish here.
3. **Short periods and short stops.** The smoothed indicator is cut into runs of
   operating and stopped samples. While some run lasts less than ``min_duration_s``
   (default ``10 * w * dt``, i.e. 10 windows), the shortest such run (the earliest one on
   a tie) is absorbed into its neighbours, which then form one run of their state. A
   short operating run inside a rest (a measuring cycle: short motions, the
   interferometer's target visits) thus becomes rest and starts no segment; a short
   stop inside an operating period (a dwell at an axis reversal, a pause) does not end
   it. The stopped runs at the very beginning and the very end of the record are never
   absorbed (they may be short); an operating run there is, when it is short. At the
   end every operating run and every stop between two of them lasts at least
   ``min_duration_s``.
4. **Segments.** Each remaining operating run, plus the rest that follows it, is one
   :class:`Segment`: ``start_s`` is the time of its first operating sample, ``on_end_s``
   the time of the first sample of the rest after it (so operation is
   ``[start_s, on_end_s)`` and ``on_end_s - start_s`` its duration; the last sample if
   the record ends while operating), ``end_s`` the next segment's ``start_s`` (the last
   sample for the last segment). Segments are half-open, contiguous intervals.
   **The data before the first operating run (the initial rest, typically the cold
   measuring cycle) belongs to no segment**; :func:`initial_rest` returns its span.
   A record without an operating run has no segments (``[]``).
5. **Levels.** Within an operating run, the *operating samples* are those whose smoothed
   ``|v|`` exceeds ``thr`` (bridged stops are left out); ``y`` are their smoothed
   values. Starting with the run's first operating sample, a level's reference ``r`` is
   the median of ``y`` over the level's first ``min_duration_s``. The level ends where
   the first stretch of consecutive operating samples begins in which every ``y``
   differs from ``r`` by more than ``tol(r) = max(rel_tol * |r|, 0.01 * vmax)`` and which
   lasts at least ``min_duration_s``; the next level starts with that stretch, and so
   on. A first level shorter than ``min_duration_s`` (a short start-up at another
   speed) joins the second. Each level's value is the median of the raw ``|v|`` of the
   samples of its span that operate (``|v| > thr``); then, while two neighbouring
   levels' values ``a``, ``b`` differ by no more than ``tol(max(a, b))``, they merge (the
   value is recomputed over the union). Short excursions (shorter than
   ``min_duration_s``) stay part of the level they interrupt.
6. **Kind.** One level: ``kind="constant"``, ``level`` = that median (the median of the
   raw operating samples of the whole operating run), ``levels=(level,)``. Several:
   ``kind="varying"``, ``level=None``, ``levels`` the level values in time order.

Inputs are checked first (a :class:`ValueError` says what is wrong): ``t_s`` and ``value``
must be one-dimensional, of equal length, at least 3 samples, finite, and ``t_s``
strictly increasing; ``stop_below`` and ``min_duration_s`` must be finite and not
negative, ``window_s`` finite and positive, ``rel_tol`` finite and not negative.

Choosing the parameters: ``min_duration_s`` must be longer than the longest measuring
cycle during a rest and the longest pause inside operation, and shorter than the
shortest block (and the shortest step of a stepped cycle) to be found. The defaults
(5 samples window, 10 windows minimum) suit a record sampled every few seconds to a
minute with blocks of at least an hour; for a record sampled at 1 Hz with measuring
cycles of several minutes, pass ``min_duration_s`` explicitly. The run time is linear
in the number of samples (0.1 to 0.2 s for a million on a desktop machine).
"""

from __future__ import annotations

import heapq
import math
import re
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import median_filter

from .limits import RUN_ID_MAX_LEN, RUN_ID_RE

__all__ = ["Segment", "derive_segments", "initial_rest", "segment_name"]

STOP_FRACTION = 0.02  # default stop threshold: 2 % of the robust maximum
ROBUST_PERCENTILE = 99.0  # the robust maximum: this percentile of |value|
FLOOR_FRACTION = 0.01  # absolute floor of the level tolerance: 1 % of the robust maximum
WINDOW_SAMPLES = 5  # default smoothing window, in median sample intervals
MIN_WINDOW_SAMPLES = 3
MIN_DURATION_WINDOWS = 10  # default min_duration_s, in (effective) windows
DEFAULT_REL_TOL = 0.05
_CHUNK0 = 4096  # first chunk of the level scan (doubled while no change is decided)


@dataclass(frozen=True)
class Segment:
    """One operating period of a run and the rest after it (module docstring, step 4).

    ``index``: 0-based order in the run. ``start_s``: first operating sample.
    ``on_end_s``: end of operation = first sample of the rest after it (the last sample
    when the record ends while operating). ``end_s``: the next segment's ``start_s``, or
    the record's last sample. ``kind``: ``"constant"`` (one level) or ``"varying"``
    (several levels without a stop in between). ``level``: the level (median of the
    operating samples' magnitudes) for ``"constant"``, ``None`` for ``"varying"``.
    ``levels``: the levels in time order (one for ``"constant"``).
    """

    index: int
    start_s: float
    on_end_s: float
    end_s: float
    kind: str
    level: float | None
    levels: tuple[float, ...]

    @property
    def on_duration_s(self) -> float:
        """How long the segment operates, ``on_end_s - start_s``."""
        return self.on_end_s - self.start_s

    @property
    def duration_s(self) -> float:
        """The segment's span, ``end_s - start_s``."""
        return self.end_s - self.start_s


@dataclass(frozen=True)
class _Setup:
    t: np.ndarray
    mag: np.ndarray  # |value|
    smooth: np.ndarray  # moving median of |value|
    dt: float
    thr: float
    vmax: float
    min_dur: float
    rel_tol: float


# ------------------------------------------------------------------ inputs ---
def _array(x, name: str) -> np.ndarray:
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be numeric: {str(e).splitlines()[0] if str(e) else type(e).__name__}") from None
    if a.ndim != 1:
        raise ValueError(f"{name} must be one-dimensional, got shape {a.shape}")
    return a


def _param(x, name: str, *, positive: bool) -> float | None:
    if x is None:
        return None
    if isinstance(x, bool):
        raise ValueError(f"{name} must be a number, got {x!r}")
    try:
        f = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {type(x).__name__}") from None
    if not math.isfinite(f):
        raise ValueError(f"{name} must be finite, got {f}")
    if positive and f <= 0:
        raise ValueError(f"{name} must be positive, got {f}")
    if f < 0:
        raise ValueError(f"{name} must not be negative, got {f}")
    return f


def _setup(t_s, value, stop_below, window_s, min_duration_s, rel_tol) -> _Setup:
    t = _array(t_s, "t_s")
    v = _array(value, "value")
    if t.size != v.size:
        raise ValueError(f"t_s and value differ in length ({t.size} and {v.size} samples)")
    if t.size < 3:
        raise ValueError(f"at least 3 samples are needed, got {t.size}")
    for a, name in ((t, "t_s"), (v, "value")):
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise ValueError(f"{name} holds {bad.size} non-finite value(s) (NaN or inf), the first at sample {bad[0]}")
    steps = np.diff(t)
    bad = np.flatnonzero(steps <= 0)
    if bad.size:
        i = bad[0]
        raise ValueError(
            f"t_s must be strictly increasing: sample {i + 1} ({t[i + 1]!r}) does not come after sample {i} ({t[i]!r})"
        )
    stop_below = _param(stop_below, "stop_below", positive=False)
    window_s = _param(window_s, "window_s", positive=True)
    min_duration_s = _param(min_duration_s, "min_duration_s", positive=False)
    rel_tol = _param(rel_tol, "rel_tol", positive=False)
    if rel_tol is None:
        raise ValueError("rel_tol must be a number, got None")

    dt = float(np.median(steps))
    mag = np.abs(v)
    vmax = float(np.percentile(mag, ROBUST_PERCENTILE))
    if vmax == 0.0:
        vmax = float(mag.max())
    thr = STOP_FRACTION * vmax if stop_below is None else stop_below
    if window_s is None:
        window_s = WINDOW_SAMPLES * dt
    ratio = window_s / dt  # may be inf for an absurd window_s
    w = 2 * t.size + 1 if ratio >= 2 * t.size + 1 else max(MIN_WINDOW_SAMPLES, int(round(ratio)))
    w += 1 - w % 2  # odd, and at most 2 n + 1 samples (an absurd window_s would not fit in memory)
    min_dur = MIN_DURATION_WINDOWS * w * dt if min_duration_s is None else min_duration_s
    smooth = median_filter(mag, size=w, mode="nearest")
    return _Setup(t=t, mag=mag, smooth=smooth, dt=dt, thr=thr, vmax=vmax, min_dur=min_dur, rel_tol=rel_tol)


# --------------------------------------------------------- operating runs ---
def _operating_runs(s: _Setup) -> list[tuple[int, int]]:
    """Index ranges ``[i0, i1)`` of the operating runs after steps 2 and 3."""
    on = s.smooth > s.thr
    if not on.any():
        return []
    n = on.size
    cut = np.flatnonzero(on[1:] != on[:-1]) + 1
    start = np.concatenate(([0], cut))
    state = on[start]
    start, state = _absorb_rounds(s, start, state, n)
    start, state = _absorb_heap(s, start.tolist(), state.tolist(), n)
    end = start[1:] + [n]
    return [(a, b) for a, b, on_ in zip(start, end, state) if on_]


def _durations(s: _Setup, start: np.ndarray, n: int) -> np.ndarray:
    end = np.append(start[1:], n)
    return s.t[end - 1] - s.t[start] + s.dt


def _eligible(s: _Setup, dur: np.ndarray, state: np.ndarray) -> np.ndarray:
    """Runs that may be absorbed: shorter than min_duration_s, and not a stopped run at
    either end of the record."""
    el = dur < s.min_dur
    el[0] &= bool(state[0])
    el[-1] &= bool(state[-1])
    return el


def _absorb_rounds(s: _Setup, start: np.ndarray, state: np.ndarray, n: int):
    """Step 3, vectorised while it pays: each round absorbs, at once, every eligible run
    that comes before its eligible neighbours in the order (duration, start). The
    shortest-first rule absorbs exactly these runs too (a run shorter than its neighbours
    stays so while others are absorbed, and absorptions of runs that are not neighbours
    commute), so the rounds reach the state the rule reaches; the rest is left to
    :func:`_absorb_heap` once rounds absorb few runs."""
    while start.size > 1:
        dur = _durations(s, start, n)
        el = _eligible(s, dur, state)
        if not el.any():
            break
        # before the left neighbour: strictly shorter (a tie goes to the earlier run);
        # before the right neighbour: not longer
        left = np.ones_like(el)
        left[1:] = ~el[:-1] | (dur[1:] < dur[:-1])
        right = np.ones_like(el)
        right[:-1] = ~el[1:] | (dur[:-1] <= dur[1:])
        flip = el & left & right
        k = int(np.count_nonzero(flip))
        state = state ^ flip
        keep = np.ones(state.size, dtype=bool)
        keep[1:] = state[1:] != state[:-1]
        start, state = start[keep], state[keep]
        if k < max(64, start.size // 64):
            break
    return start, state


def _absorb_heap(s: _Setup, start: list, state: list, n: int):
    """Step 3 proper: while some eligible run is shorter than min_duration_s, absorb the
    shortest (the earliest on a tie) into its neighbours."""
    t, dt, min_dur = s.t, s.dt, s.min_dur
    r = len(start)
    end = start[1:] + [n]  # exclusive
    dur = (t[np.asarray(end) - 1] - t[np.asarray(start)] + dt).tolist()
    prev = list(range(-1, r - 1))
    nxt = list(range(1, r + 1))
    nxt[-1] = -1
    alive = [True] * r

    def eligible(i: int) -> bool:  # stopped runs at either end of the record are never absorbed
        return dur[i] < min_dur and (state[i] or (prev[i] != -1 and nxt[i] != -1))

    heap = [(dur[i], start[i], i) for i in range(r) if eligible(i)]
    heapq.heapify(heap)
    while heap:
        d, _, i = heapq.heappop(heap)
        if not alive[i] or d != dur[i] or not eligible(i):
            continue
        p, q = prev[i], nxt[i]
        if p == -1 and q == -1:  # the whole record is one short operating run: all rest
            return [0], [False]
        if p == -1 or q == -1:  # a short operating run at an end joins the rest beside it
            k = q if p == -1 else p
            start[k], end[k] = min(start[k], start[i]), max(end[k], end[i])
            if p == -1:
                prev[k] = -1
            else:
                nxt[k] = -1
            alive[i] = False
        else:  # p, i, q become one run of p's (= q's) state
            end[p] = end[q]
            nq = nxt[q]
            nxt[p] = nq
            if nq != -1:
                prev[nq] = p
            alive[i] = alive[q] = False
            k = p
        dur[k] = float(t[end[k] - 1] - t[start[k]] + dt)
        if eligible(k):
            heapq.heappush(heap, (dur[k], start[k], k))
    keep = [i for i in range(r) if alive[i]]
    return [start[i] for i in keep], [state[i] for i in keep]


# ------------------------------------------------------------------ levels ---
def _tol(s: _Setup, ref):
    return np.maximum(s.rel_tol * np.abs(ref), FLOOR_FRACTION * s.vmax)


def _next_change(s: _Setup, y: np.ndarray, ty: np.ndarray, k: int) -> int | None:
    """Index (into ``y``) where the level starting at ``k`` ends, or None (step 5)."""
    m = y.size
    first = int(np.searchsorted(ty, ty[k] + s.min_dur, side="left"))
    ref = float(np.median(y[k : max(first, k + 1)]))
    tol = float(_tol(s, ref))
    chunk = max(_CHUNK0, 4 * (first - k))
    while True:
        e = min(m, k + 1 + chunk)
        dev = np.abs(y[k + 1 : e] - ref) > tol
        if dev.any():
            d = np.diff(np.concatenate(([False], dev, [False])).astype(np.int8))
            rs = np.flatnonzero(d == 1) + k + 1  # first sample of each deviating stretch
            re_ = np.flatnonzero(d == -1) + k + 1  # one past its last sample
            lasts = ty[re_ - 1] - ty[rs] + s.dt
            ok = np.flatnonzero(lasts >= s.min_dur)
            if ok.size:
                return int(rs[ok[0]])
        if e == m:
            return None
        chunk *= 2


def _levels(s: _Setup, i0: int, i1: int) -> tuple[float, ...]:
    """The level values of the operating run ``[i0, i1)`` in time order (step 5)."""
    t, mag, sm, thr = s.t[i0:i1], s.mag[i0:i1], s.smooth[i0:i1], s.thr
    sel = sm > thr
    y, ty = sm[sel], t[sel]
    raw_on = mag > thr
    if y.size == 0:  # cannot happen for a run of smoothed operating samples; defensive
        return (float(np.median(mag)),)
    bounds = [0]
    while (j := _next_change(s, y, ty, bounds[-1])) is not None:
        bounds.append(j)
    if len(bounds) > 1 and ty[bounds[1] - 1] - ty[0] + s.dt < s.min_dur:
        del bounds[1]  # a short first level joins the second
    # spans in time: level k covers [ty[bounds[k]], ty[bounds[k + 1]])
    edges = [ty[b] for b in bounds[1:]]
    cut = np.searchsorted(t, edges, side="left").tolist()
    spans = list(zip([0] + cut, cut + [t.size]))

    def value(a: int, b: int) -> float:
        part = mag[a:b][raw_on[a:b]]
        return float(np.median(part if part.size else sm[a:b]))

    vals = [value(a, b) for a, b in spans]
    merged = True
    while merged and len(spans) > 1:
        merged = False
        for k in range(len(spans) - 1):
            a, b = vals[k], vals[k + 1]
            if abs(a - b) <= float(_tol(s, max(a, b))):
                spans[k : k + 2] = [(spans[k][0], spans[k + 1][1])]
                vals[k : k + 2] = [value(*spans[k])]
                merged = True
                break
    return tuple(vals)


# --------------------------------------------------------------------- API ---
def derive_segments(
    t_s,
    value,
    *,
    stop_below: float | None = None,
    window_s: float | None = None,
    min_duration_s: float | None = None,
    rel_tol: float = DEFAULT_REL_TOL,
) -> list[Segment]:
    """Segments of a record from its operating signal (the algorithm: module docstring).

    ``t_s``: sample times in s, strictly increasing. ``value``: the operating signal
    (spindle speed, axis feed; signed or not). ``stop_below``: the stop threshold
    (default 2 % of the 99th percentile of ``|value|``). ``window_s``: the moving-median
    window (default 5 median sample intervals; at least 3 samples). ``min_duration_s``:
    the shortest operating period, stop inside operation and level that counts (default
    10 windows). ``rel_tol``: relative tolerance of a level (floor 1 % of the robust
    maximum). Data before the first segment (the initial rest) is in no segment: see
    :func:`initial_rest`. No operation at all gives ``[]``.
    """
    s = _setup(t_s, value, stop_below, window_s, min_duration_s, rel_tol)
    runs = _operating_runs(s)
    t, n = s.t, s.t.size
    out = []
    for k, (i0, i1) in enumerate(runs):
        levels = _levels(s, i0, i1)
        constant = len(levels) == 1
        out.append(
            Segment(
                index=k,
                start_s=float(t[i0]),
                on_end_s=float(t[min(i1, n - 1)]),
                end_s=float(t[runs[k + 1][0]] if k + 1 < len(runs) else t[-1]),
                kind="constant" if constant else "varying",
                level=levels[0] if constant else None,
                levels=levels,
            )
        )
    return out


def initial_rest(
    t_s,
    value,
    *,
    stop_below: float | None = None,
    window_s: float | None = None,
    min_duration_s: float | None = None,
    rel_tol: float = DEFAULT_REL_TOL,
) -> tuple[float, float] | None:
    """The span ``(t_s[0], start)`` of the rest before the first segment (the cold state,
    in no segment), with the same parameters as :func:`derive_segments`: ``start`` is the
    first segment's ``start_s`` (the rest is ``[t_s[0], start)``), or the last sample when
    nothing operates (the whole record is rest). ``None`` when the record starts operating.
    """
    s = _setup(t_s, value, stop_below, window_s, min_duration_s, rel_tol)
    runs = _operating_runs(s)
    t0 = float(s.t[0])
    if not runs:
        return (t0, float(s.t[-1]))
    if runs[0][0] == 0:
        return None
    return (t0, float(s.t[runs[0][0]]))


def segment_name(seg: Segment, unit: str) -> str:
    """A default run id for a segment: ``s01_1250rpm`` (1-based number, the level rounded
    to an integer, then ``unit``) for a constant segment, ``s06_varying`` for a varying
    one. ``unit`` is reduced to the run-id alphabet (``"mm/min"`` -> ``mm_min``,
    ``"µm"`` -> ``um``) and shortened so that the name is a valid run id
    (:data:`thermbench.data.limits.RUN_ID_PATTERN`).
    """
    if not isinstance(seg, Segment):
        raise ValueError(f"seg must be a Segment, got {type(seg).__name__}")
    if not isinstance(unit, str):
        raise ValueError(f"unit must be a string, got {type(unit).__name__}")
    if isinstance(seg.index, bool) or not isinstance(seg.index, (int, np.integer)) or seg.index < 0:
        raise ValueError(f"segment index must be a non-negative integer, got {seg.index!r}")
    prefix = f"s{int(seg.index) + 1:02d}_"
    if seg.kind == "varying":
        name = prefix + "varying"
    elif seg.kind == "constant":
        if seg.level is None or not math.isfinite(float(seg.level)):
            raise ValueError(f"a constant segment needs a finite level, got {seg.level!r}")
        base = prefix + str(int(round(float(seg.level))))
        u = re.sub(r"[^A-Za-z0-9_.-]+", "_", unit.replace("µ", "u").replace("μ", "u")).strip("_.")
        name = (base + u[: max(0, RUN_ID_MAX_LEN - len(base))]).rstrip(".")
    else:
        raise ValueError(f"segment kind must be 'constant' or 'varying', got {seg.kind!r}")
    if len(name) > RUN_ID_MAX_LEN or RUN_ID_RE.fullmatch(name) is None:
        raise ValueError(f"cannot make a valid run id for segment {seg.index} (got {name!r})")
    return name
