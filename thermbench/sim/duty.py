"""Duty cycles: what the axis does during a run, as a piecewise-linear trajectory.

A run is a list of phases (reciprocate over [start, end] at a feed, or stop),
interrupted by interferometer measuring cycles (seed 000 §5.1, seed 001 §2
steps 2-5, seed 002 §3.1): every ``every_s`` of phase time the axis leaves its
duty, visits the targets at the measuring feed with a dwell at each, and the
duty resumes from there. Phase durations count duty time only; measuring
cycles add to the run's length. The cold reference measurement (repeated
``reference_repeats`` times, seed 002 §3.1) opens every run and a last
measuring cycle closes it.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .model import Motion


@dataclass(frozen=True)
class Phase:
    kind: str  # "move" (reciprocate) or "stop"
    duration_s: float
    start_mm: float = 0.0
    end_mm: float = 0.0
    feed_mm_min: float = 0.0
    load_N: float = 0.0

    def __post_init__(self) -> None:
        if self.kind not in ("move", "stop"):
            raise ValueError(f"phase kind must be 'move' or 'stop', got {self.kind!r}")
        if self.duration_s < 0:
            raise ValueError(f"phase duration_s must be >= 0, got {self.duration_s}")
        if self.kind == "move" and (self.feed_mm_min <= 0 or self.end_mm == self.start_mm):
            raise ValueError(
                f"a move phase needs feed_mm_min > 0 and end_mm != start_mm "
                f"(got feed {self.feed_mm_min}, {self.start_mm}..{self.end_mm} mm)"
            )


@dataclass(frozen=True)
class Measuring:
    """Interferometer measuring-cycle settings (one reading per target, taken at mid-dwell)."""

    targets_mm: tuple[float, ...]
    every_s: float = 600.0
    dwell_s: float = 4.0
    feed_mm_min: float = 800.0
    reference_repeats: int = 1

    def __post_init__(self) -> None:
        if len(self.targets_mm) < 2:
            raise ValueError("measuring.targets_mm needs at least two targets")
        if self.every_s <= 0 or self.dwell_s <= 0 or self.feed_mm_min <= 0:
            raise ValueError("measuring: every_s, dwell_s and feed_mm_min must be > 0")


@dataclass
class Trajectory:
    """Waypoints (t, x) joined by straight lines; speed constant on each segment."""

    t_s: list[float] = field(default_factory=lambda: [0.0])
    x_mm: list[float] = field(default_factory=list)
    load_N: list[float] = field(default_factory=lambda: [0.0])
    readings: list[tuple[float, float]] = field(default_factory=list)  # (t_s, target_mm)
    # (phase index, wall-clock start, end) of each stretch of a phase between measuring cycles
    spans: list[tuple[int, float, float]] = field(default_factory=list)

    @property
    def now(self) -> float:
        return self.t_s[-1]

    @property
    def at(self) -> float:
        return self.x_mm[-1]

    def go(self, x_mm: float, feed_mm_min: float, load_N: float = 0.0) -> None:
        dist = abs(x_mm - self.at)
        if dist <= 0:
            return
        self._add(self.now + dist / (feed_mm_min / 60.0), x_mm, load_N)

    def wait(self, duration_s: float) -> None:
        if duration_s > 0:
            self._add(self.now + duration_s, self.at, 0.0)

    def _add(self, t: float, x: float, load: float) -> None:
        self.t_s.append(t)
        self.x_mm.append(x)
        self.load_N.append(load)

    def sample(self, t_s: np.ndarray) -> Motion:
        """Position, speed and load at ``t_s`` (speed of the segment in force)."""
        t = np.asarray(self.t_s)
        x = np.asarray(self.x_mm)
        seg_v = np.abs(np.diff(x)) / np.diff(t) * 60.0
        seg_load = np.asarray(self.load_N[1:])
        idx = np.clip(np.searchsorted(t, t_s, side="right") - 1, 0, len(seg_v) - 1)
        return Motion(t_s=t_s, axis_mm=np.interp(t_s, t, x), feed_mm_min=seg_v[idx], load_N=seg_load[idx])


def _reciprocate(tr: Trajectory, ph: Phase, duration_s: float, state: dict) -> None:
    """Spend ``duration_s`` of duty time on phase ``ph`` from the current position."""
    end_t = tr.now + duration_s
    if ph.kind == "stop" or duration_s <= 0:
        tr.wait(duration_s)
        return
    v = ph.feed_mm_min / 60.0
    lo, hi = sorted((ph.start_mm, ph.end_mm))
    # resume heading where the phase left off; first reach the stroke
    target = state.get("heading", ph.end_mm)
    if not (lo <= tr.at <= hi):
        target = ph.start_mm if abs(tr.at - ph.start_mm) <= abs(tr.at - ph.end_mm) else ph.end_mm
    while tr.now < end_t - 1e-9:
        dist = abs(target - tr.at)
        if dist <= 1e-12:
            target = hi if target == lo else lo
            continue
        dt = dist / v
        if tr.now + dt > end_t:
            frac = (end_t - tr.now) / dt
            tr._add(end_t, tr.at + frac * (target - tr.at), ph.load_N)
            break
        tr._add(tr.now + dt, target, ph.load_N)
        target = hi if target == lo else lo
    state["heading"] = target


def _measure(tr: Trajectory, meas: Measuring) -> None:
    for tgt in meas.targets_mm:
        tr.go(tgt, meas.feed_mm_min)
        tr.readings.append((tr.now + meas.dwell_s / 2.0, float(tgt)))
        tr.wait(meas.dwell_s)


def build_run(phases: list[Phase], meas: Measuring, start_mm: float | None = None) -> Trajectory:
    """The trajectory of a run: reference measurement, phases with measuring
    cycles every ``meas.every_s`` of duty time, closing measurement. ``spans`` records
    when each phase ran (wall-clock stretches between measuring cycles)."""
    tr = Trajectory()
    tr.x_mm.append(float(meas.targets_mm[0] if start_mm is None else start_mm))
    for _ in range(max(1, meas.reference_repeats)):
        _measure(tr, meas)
    duty_clock = 0.0
    next_meas = meas.every_s
    measured_last = True
    for index, ph in enumerate(phases):
        left = ph.duration_s
        state: dict = {}
        while left > 1e-9:
            chunk = min(left, next_meas - duty_clock)
            t0 = tr.now
            _reciprocate(tr, ph, chunk, state)
            tr.spans.append((index, t0, tr.now))
            measured_last = False
            duty_clock += chunk
            left -= chunk
            if duty_clock >= next_meas - 1e-9:
                _measure(tr, meas)
                measured_last = True
                next_meas += meas.every_s
    if not measured_last:
        _measure(tr, meas)
    return tr


def random_phases(
    rng: np.random.Generator,
    n_phases: int,
    travel_mm: tuple[float, float],
    feed_mm_min: tuple[float, float],
    stroke_mm: tuple[float, float],
    move_s: tuple[float, float],
    stop_s: tuple[float, float],
    p_stop: float = 0.3,
) -> list[Phase]:
    """A random duty sequence in the style of seed 001 Table 2 / seed 002 Table 6."""
    lo, hi = travel_mm
    out: list[Phase] = []
    for _ in range(n_phases):
        if rng.random() < p_stop:
            out.append(Phase("stop", float(rng.uniform(*stop_s))))
            continue
        stroke = float(min(rng.uniform(*stroke_mm), hi - lo))
        start = float(rng.uniform(lo, hi - stroke))
        feed = float(np.round(rng.uniform(*feed_mm_min), -1))
        out.append(Phase("move", float(rng.uniform(*move_s)), start, start + stroke, feed))
    return out
