"""Segments derived from an operating signal (thermbench.data.segments).

Every expected value comes from the way the test signal was built (block layout,
levels) or from the real measurement's published test plan
(/work/shared/realdata/README.md), never from the code under test.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import openpyxl
import pytest

from thermbench.data.segments import Segment, derive_segments, initial_rest, segment_name

RUN_ID = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9_.-]{0,62}[A-Za-z0-9_-])?")  # the brief's run-id rule
REAL = Path(__file__).resolve().parents[1] / "thermbench" / "realdata" / "fl_thermal" / "data.xlsx"


def build(pieces, dt, rng, *, rel_noise=0.005, stop_noise=1.0):
    """A sampled piecewise-constant signal: ``pieces`` is a list of (duration_s, level).

    Returns t, value and the start time of every piece (from the layout, not measured)."""
    starts = np.concatenate(([0.0], np.cumsum([d for d, _ in pieces])))
    t = np.arange(0.0, starts[-1], dt)
    v = np.zeros_like(t)
    for (d, lvl), a in zip(pieces, starts):
        m = (t >= a) & (t < a + d)
        if lvl == 0:
            v[m] = rng.normal(0.0, stop_noise, m.sum())
        else:
            v[m] = lvl * (1.0 + rng.normal(0.0, rel_noise, m.sum()))
    return t, v, starts[:-1].tolist()


def close(a, b, tol):
    return abs(a - b) <= tol


# ------------------------------------------------------------- synthetic ---
def test_blocks_recovered_with_glitches():
    rng = np.random.default_rng(1)
    dt = 10.0
    window = 5 * dt  # the documented default window
    pieces = [(600, 0), (3600, 1000), (3000, 0), (3600, 3000), (3600, 0), (1800, 2000), (1200, 0)]
    t, v, st = build(pieces, dt, rng)
    # single-sample glitches: drop-outs to 0 while operating, spikes while stopped
    for ts in (1200.0, 2500.0, 8000.0):  # inside the 1000 and 3000 rpm blocks
        v[np.searchsorted(t, ts)] = 0.0
    for ts in (5000.0, 12000.0):  # inside rests
        v[np.searchsorted(t, ts)] = 3000.0
    segs = derive_segments(t, v)
    assert len(segs) == 3
    on_starts = [st[1], st[3], st[5]]
    on_ends = [st[2], st[4], st[6]]
    levels = [1000, 3000, 2000]
    for k, seg in enumerate(segs):
        assert seg.index == k
        assert seg.kind == "constant"
        assert close(seg.start_s, on_starts[k], window)
        assert close(seg.on_end_s, on_ends[k], window)
        assert close(seg.level, levels[k], 0.01 * levels[k])
        assert seg.levels == (seg.level,)
    assert close(segs[0].end_s, on_starts[1], window)
    assert close(segs[1].end_s, on_starts[2], window)
    assert segs[2].end_s == t[-1]
    # the cold rest before the first block belongs to no segment
    rest = initial_rest(t, v)
    assert rest[0] == 0.0 and close(rest[1], 600.0, window)


@pytest.mark.parametrize("seed", range(5))
def test_random_block_layouts(seed):
    rng = np.random.default_rng(100 + seed)
    dt = 10.0
    window = 5 * dt
    n = int(rng.integers(2, 6))
    levels = rng.choice([800.0, 1250.0, 2000.0, 3150.0, 4000.0, 6000.0], size=n)
    pieces = [(float(rng.uniform(300, 3000)), 0)]
    for lvl in levels:
        pieces += [(float(rng.uniform(1500, 6000)), lvl), (float(rng.uniform(1000, 5000)), 0)]
    t, v, st = build(pieces, dt, rng)
    segs = derive_segments(t, v)
    assert len(segs) == n
    for k, seg in enumerate(segs):
        assert seg.kind == "constant"
        assert close(seg.start_s, st[1 + 2 * k], window)
        assert close(seg.on_end_s, st[2 + 2 * k], window)
        assert close(seg.level, levels[k], 0.01 * levels[k])


def test_measuring_cycles_during_rest_start_no_segment():
    rng = np.random.default_rng(2)
    dt = 2.0  # default window 10 s, min_duration 100 s
    F = 800.0
    cycle = [(6, F), (4, 0)] * 5  # 50 s: five short motions with stops at the targets
    pieces = [(300, 0)] + cycle + [(600, 0), (3600, F * 4), (400, 0)] + cycle + [(2000, 0)] + cycle + [(600, 0)]
    t, v, _ = build(pieces, dt, rng)
    block_start = 300 + 50 + 600
    block_end = block_start + 3600
    segs = derive_segments(t, v)
    assert len(segs) == 1
    seg = segs[0]
    assert close(seg.start_s, block_start, 5 * dt)
    assert close(seg.on_end_s, block_end, 5 * dt)  # the cycle 400 s later does not extend it
    assert seg.end_s == t[-1]
    assert close(seg.level, 4 * F, 0.01 * 4 * F)
    rest = initial_rest(t, v)
    assert rest[0] == 0.0 and close(rest[1], block_start, 5 * dt)  # the cold cycle is in the rest


def test_longer_measuring_cycle_needs_min_duration():
    rng = np.random.default_rng(3)
    dt = 1.0  # default window 5 s, min_duration 50 s
    cycle = [(8, 3000.0), (4, 0)] * 10  # 120 s measuring cycle
    pieces = [(600, 0), (3600, 6000.0), (900, 0)] + cycle + [(900, 0), (3600, 6000.0), (600, 0)]
    t, v, st = build(pieces, dt, rng)
    assert len(derive_segments(t, v)) == 3  # with the defaults the cycle is a segment of its own
    segs = derive_segments(t, v, min_duration_s=300.0)
    assert len(segs) == 2
    assert close(segs[0].on_end_s, 600 + 3600, 5 * dt)
    assert close(segs[0].end_s, st[-2], 5 * dt)
    assert close(segs[1].start_s, st[-2], 5 * dt)


def test_brief_dwell_does_not_split_but_long_stop_does():
    rng = np.random.default_rng(4)
    dt = 2.0  # default window 10 s, min_duration 100 s
    pieces = [(500, 0), (1800, 2500.0), (40, 0), (1800, 2500.0), (800, 0)]  # 40 s dwell
    t, v, _ = build(pieces, dt, rng)
    segs = derive_segments(t, v)
    assert len(segs) == 1 and segs[0].kind == "constant"
    assert close(segs[0].start_s, 500, 5 * dt)
    assert close(segs[0].on_end_s, 500 + 1800 + 40 + 1800, 5 * dt)
    assert close(segs[0].level, 2500, 25)
    # the same layout with a stop longer than min_duration_s: two segments
    pieces[2] = (300, 0)
    t, v, _ = build(pieces, dt, rng)
    segs = derive_segments(t, v)
    assert len(segs) == 2
    assert close(segs[0].on_end_s, 2300, 5 * dt)
    assert close(segs[1].start_s, 2600, 5 * dt)
    assert close(segs[0].end_s, 2600, 5 * dt)


def test_stepped_block_is_one_varying_segment():
    rng = np.random.default_rng(5)
    dt = 5.0
    pieces = [(1000, 0), (1800, 500.0), (1800, 1500.0), (1800, 2500.0), (1500, 0), (2000, 1500.0), (1000, 0)]
    t, v, _ = build(pieces, dt, rng)
    segs = derive_segments(t, v)
    assert len(segs) == 2
    seg = segs[0]
    assert seg.kind == "varying" and seg.level is None
    assert len(seg.levels) == 3
    for got, want in zip(seg.levels, (500, 1500, 2500)):
        assert close(got, want, 0.01 * want)
    assert close(seg.start_s, 1000, 5 * dt)
    assert close(seg.on_end_s, 1000 + 3 * 1800, 5 * dt)
    assert segs[1].kind == "constant" and close(segs[1].level, 1500, 15)


def test_short_excursion_stays_in_its_level():
    rng = np.random.default_rng(6)
    dt = 5.0  # min_duration 250 s
    pieces = [(500, 0), (1800, 2000.0), (120, 3000.0), (1800, 2000.0), (600, 0)]
    t, v, _ = build(pieces, dt, rng)
    segs = derive_segments(t, v)
    assert len(segs) == 1
    assert segs[0].kind == "constant" and close(segs[0].level, 2000, 20)


@pytest.mark.parametrize("dwell_s", [1, 4])
def test_signed_velocity_is_one_constant_segment(dwell_s):
    rng = np.random.default_rng(7)
    dt = 1.0
    F = 2000.0
    stroke = [(12, F), (dwell_s, 0), (12, -F), (dwell_s, 0)]
    n_cycles = int(3600 // (24 + 2 * dwell_s))
    pieces = [(600, 0)] + stroke * n_cycles + [(1200, 0)]
    t, v, _ = build(pieces, dt, rng)
    on_end = 600 + n_cycles * (24 + 2 * dwell_s) - dwell_s  # the last dwell already rests
    segs = derive_segments(t, v)
    assert len(segs) == 1
    seg = segs[0]
    assert seg.kind == "constant"
    assert close(seg.level, F, 0.01 * F)
    assert close(seg.start_s, 600, 5 * dt)
    assert close(seg.on_end_s, on_end, 5 * dt)


def test_no_operation_gives_no_segments():
    t = np.arange(0.0, 1000.0, 1.0)
    assert derive_segments(t, np.zeros_like(t)) == []
    assert initial_rest(t, np.zeros_like(t)) == (0.0, 999.0)
    noise = np.random.default_rng(8).normal(0.0, 2.0, t.size)
    assert derive_segments(t, noise, stop_below=50.0) == []


def test_short_operation_at_the_end_is_not_a_segment_and_start_in_operation():
    rng = np.random.default_rng(9)
    dt = 1.0  # min_duration 50 s
    pieces = [(2000, 1200.0), (1000, 0), (20, 1200.0)]
    t, v, _ = build(pieces, dt, rng)
    segs = derive_segments(t, v)
    assert len(segs) == 1
    assert segs[0].start_s == 0.0  # the record starts while operating
    assert close(segs[0].on_end_s, 2000, 5 * dt)
    assert segs[0].end_s == t[-1]
    assert initial_rest(t, v) is None


def test_stop_below_and_window_parameters():
    rng = np.random.default_rng(10)
    dt = 1.0
    # an idling spindle at 150 rpm is "stopped" when stop_below says so
    pieces = [(600, 150.0), (2000, 5000.0), (1000, 150.0), (2000, 3000.0), (600, 150.0)]
    t, v, _ = build(pieces, dt, rng)
    (seg,) = derive_segments(t, v)  # default threshold 2 % of 5000 = 100 rpm: idling operates
    assert seg.kind == "varying" and seg.start_s == 0.0
    assert len(seg.levels) == 5 and close(seg.levels[1], 5000, 50) and close(seg.levels[2], 150, 5)
    segs = derive_segments(t, v, stop_below=500.0, window_s=11.0, min_duration_s=200.0)
    assert [s.kind for s in segs] == ["constant", "constant"]
    assert close(segs[0].start_s, 600, 11) and close(segs[1].start_s, 3600, 11)


def test_million_samples():  # its speed: benchmarks/bench_segments.py
    rng = np.random.default_rng(11)
    dt = 0.1
    pieces = [(5000, 0), (30000, 3000.0), (20000, 0), (30000, 6000.0), (15000, 0)]
    t, v, st = build(pieces, dt, rng)
    assert t.size == 1_000_000
    segs = derive_segments(t, v)
    assert len(segs) == 2
    assert close(segs[0].start_s, st[1], 0.5) and close(segs[1].on_end_s, st[4], 0.5)


def reference_periods(t, v, w, min_dur):
    """Steps 1-4 of the module docstring, written again the slow, literal way: the
    (start_s, on_end_s) of every operating period."""
    n = t.size
    dt = np.median(np.diff(t))
    mag = np.abs(v)
    vmax = np.percentile(mag, 99) or mag.max()
    thr = 0.02 * vmax
    h = w // 2
    around = np.clip(np.arange(n)[:, None] + np.arange(-h, h + 1), 0, n - 1)  # ends padded
    on = (np.median(mag[around], axis=1) > thr).tolist()
    runs = []  # [state, first, last]
    for i, o in enumerate(on):
        if runs and runs[-1][0] == o:
            runs[-1][2] = i
        else:
            runs.append([o, i, i])
    while True:
        last = len(runs) - 1
        cand = [
            (t[b] - t[a] + dt, a, k)
            for k, (o, a, b) in enumerate(runs)
            if t[b] - t[a] + dt < min_dur and (o or 0 < k < last)
        ]
        if not cand:
            break
        k = min(cand)[2]
        runs[k][0] = not runs[k][0]
        merged = []
        for r in runs:
            if merged and merged[-1][0] == r[0]:
                merged[-1][2] = r[2]
            else:
                merged.append(list(r))
        runs = merged
    return [(t[a], t[min(b + 1, n - 1)]) for o, a, b in runs if o]


@pytest.mark.parametrize("seed", range(4))
def test_periods_match_a_literal_reference(seed):
    rng = np.random.default_rng(200 + seed)
    for _ in range(40):
        n = int(rng.integers(3, 250))
        # even sampling (ties between run durations) or irregular sampling
        t = np.cumsum(rng.uniform(0.5, 1.5, n)) if rng.random() < 0.5 else np.arange(n) * 2.0
        # runs of random length, operating at random levels or stopped
        lengths = rng.geometric(rng.uniform(0.05, 0.5), n)
        state = np.repeat(np.arange(lengths.size) % 2 == rng.integers(0, 2), lengths)[:n]
        v = np.where(state, rng.uniform(500, 1000, n) * rng.choice([-1, 1], n), rng.uniform(0, 5, n))
        w = int(rng.choice([3, 5, 7]))
        min_dur = float(rng.uniform(0, 30))
        window_s = w * np.median(np.diff(t))
        got = [(g.start_s, g.on_end_s) for g in derive_segments(t, v, window_s=window_s, min_duration_s=min_dur)]
        assert got == reference_periods(t, v, w, min_dur)


# ------------------------------------------------------------- real data ---
@pytest.fixture(scope="module")
def fl_thermal():
    """Time and spindle speed of the real test. The first two columns only, read with
    openpyxl in read-only mode: a second faster than ``pandas.read_excel`` (which
    converts all 23 columns), same values."""
    wb = openpyxl.load_workbook(REAL, read_only=True, data_only=True)
    try:
        rows = list(wb.worksheets[0].iter_rows(max_col=2, values_only=True))
    finally:
        wb.close()
    header = [str(c).strip() for c in rows[0]]
    assert header == ["時間(s)", "spindle(RPM)"]  # the time header has a trailing space in the file
    data = np.asarray(rows[1:], dtype=float)
    assert data.shape == (11115, 2)  # README: 11 115 rows, every 15 s from 0 to 166 710 s
    return data[:, 0], data[:, 1]


def test_real_spindle_test_plan(fl_thermal):
    t, rpm = fl_thermal
    sample = 15.0
    # the test plan from the README (independent of the code)
    plan = [(465, 1250), (29265, 2500), (58065, 3750), (86865, 5000), (115665, 3500)]
    four_h = 14400.0
    tail_start, tail_levels, tail_stop, data_end = 144465, (500, 1500, 2500, 4500), 166065, 166710
    segs = derive_segments(t, rpm)
    assert len(segs) == 6
    for seg, (start, lvl) in zip(segs[:5], plan):
        assert seg.kind == "constant"
        assert close(seg.start_s, start, sample)
        assert close(seg.on_end_s, start + four_h, sample)
        assert close(seg.level, lvl, 0.01 * lvl)
    for seg, nxt in zip(segs[:5], [p[0] for p in plan[1:]] + [tail_start]):
        assert close(seg.end_s, nxt, sample)
    tail = segs[5]
    assert tail.kind == "varying" and tail.level is None
    assert close(tail.start_s, tail_start, sample)
    assert close(tail.on_end_s, tail_stop, sample)
    assert tail.end_s == data_end
    assert len(tail.levels) == len(tail_levels)
    for got, want in zip(tail.levels, tail_levels):
        assert close(got, want, 0.01 * want)
    rest = initial_rest(t, rpm)
    assert rest[0] == 0.0 and close(rest[1], 465, sample)
    names = [segment_name(s, "rpm") for s in segs]
    assert names == ["s01_1250rpm", "s02_2500rpm", "s03_3750rpm", "s04_5000rpm", "s05_3500rpm", "s06_varying"]


# ------------------------------------------------------------------ names ---
def test_segment_name():
    const = Segment(index=0, start_s=0.0, on_end_s=1.0, end_s=2.0, kind="constant", level=1249.6, levels=(1249.6,))
    vary = Segment(index=5, start_s=0.0, on_end_s=1.0, end_s=2.0, kind="varying", level=None, levels=(1.0, 2.0))
    assert segment_name(const, "rpm") == "s01_1250rpm"
    assert segment_name(vary, "rpm") == "s06_varying"
    assert segment_name(const, "mm/min") == "s01_1250mm_min"
    assert segment_name(const, "mm_min") == "s01_1250mm_min"
    assert segment_name(const, "") == "s01_1250"
    for unit in ("rpm", "mm/min", "µm/min", "1/min.", "x" * 200, " ", "../../etc"):
        name = segment_name(const, unit)
        assert RUN_ID.fullmatch(name) and len(name) <= 64, (unit, name)
    big = Segment(index=123, start_s=0.0, on_end_s=1.0, end_s=2.0, kind="constant", level=5e4, levels=(5e4,))
    assert segment_name(big, "rpm") == "s124_50000rpm"
    with pytest.raises(ValueError, match="kind"):
        segment_name(Segment(0, 0.0, 1.0, 2.0, "odd", 1.0, (1.0,)), "rpm")
    with pytest.raises(ValueError, match="level"):
        segment_name(Segment(0, 0.0, 1.0, 2.0, "constant", None, ()), "rpm")


# ----------------------------------------------------------- input errors ---
T = np.arange(10.0)
V = np.ones(10)


@pytest.mark.parametrize(
    "t, v, kwargs, match",
    [
        (T, V[:9], {}, "differ in length"),
        (T[:2], V[:2], {}, "at least 3 samples"),
        (T, np.r_[V[:4], np.nan, V[5:]], {}, "value holds 1 non-finite"),
        (np.r_[T[:9], np.inf], V, {}, "t_s holds 1 non-finite"),
        (np.r_[T[:5], T[4], T[6:]], V, {}, "strictly increasing"),
        (T[::-1], V, {}, "strictly increasing"),
        (T, V, {"window_s": -1.0}, "window_s must be positive"),
        (T, V, {"window_s": 0.0}, "window_s must be positive"),
        (T, V, {"min_duration_s": -5.0}, "min_duration_s must not be negative"),
        (T, V, {"stop_below": -1.0}, "stop_below must not be negative"),
        (T, V, {"rel_tol": -0.1}, "rel_tol must not be negative"),
        (T, V, {"window_s": float("nan")}, "window_s must be finite"),
        (T, V, {"min_duration_s": "long"}, "min_duration_s must be a number"),
        (T.reshape(2, 5), V.reshape(2, 5), {}, "one-dimensional"),
        (["a", "b", "c"], [1, 2, 3], {}, "t_s must be numeric"),
    ],
)
def test_input_errors(t, v, kwargs, match):
    with pytest.raises(ValueError, match=match):
        derive_segments(t, v, **kwargs)
    with pytest.raises(ValueError, match=match):
        initial_rest(t, v, **kwargs)
