"""One compensator cycle, without any I/O: readings in, compensation out.

:class:`CycleLogic` is what ``thermbench compensator`` does each control cycle between
reading the machine and writing to it, so every fault rule is testable without a
network:

* **Machine time** is the source timestamp of the axis position (seconds since the
  first one). The exported model is stepped on its own sample grid (the dataset's
  process-log period, manifest ``sample_period_s``): when the machine time passes a grid
  point, the runtime is stepped at that point with the latest values (zero-order hold),
  as the process log it was trained on was sampled.
* **Inputs**: a value that is missing, not finite, outside its configured range, or
  whose timestamp lags the axis by more than ``input_max_age_s`` is *held*: the last good
  value goes to the model and the cycle is flagged ``INPUT_HELD``.
* **Stale data**: no new axis timestamp for ``stale_after_s`` of the client's clock (or
  a timestamp older than ``max_age_s`` when the server's clock is the wall clock) ->
  ``STALE``; a timestamp going backwards -> ``CLOCK``. The compensation is then held at
  its last good value (``HELD``).
* **Outage**: longer than the runtime accepts between samples (``TB_MAX_GAP_S``) -> the
  model is restarted (``RESTARTED``) and the compensation held until it predicts again.
* **Rate limit**: the written compensation never changes faster than
  ``rate_limit_um_s`` of machine time (the role of SINUMERIK MD32760
  ``COMP_ADD_VELO_FACTOR``); for the error line, at both ends of the travel.

The compensation is the value added to the axis position set point, ``-predicted
error`` (the C runtime's ``total_um``: geometric + thermal); ``convention: error`` in
the config writes the predicted error itself, for controllers that subtract it.

The error line (SINUMERIK 840D SD43900 / SD43910 / SD43920, Beckhoff TwinCAT CNC
P-AXIS-00273 / 00274 / 00272) is the least-squares straight line through the
compensation predicted at ``n_points`` positions over the travel:
``comp(x) = offset + slope * (x - ref)``.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

TB_E_SAMPLING = -12
TB_MAX_GAP_S = 60.0  # embedded/include/tb_runtime.h


class Flags(enum.IntFlag):
    OK = 0
    INPUT_HELD = 1  # an input was bad, out of range or stale: its last good value used
    STALE = 2  # no new data: compensation held
    CLOCK = 4  # timestamp went backwards: sample ignored, compensation held
    DISCONNECTED = 8  # no connection to the server: compensation held (nothing written)
    NOT_READY = 16  # the model has no prediction yet (start-up, after a restart)
    RUNTIME = 32  # the C runtime refused a sample or a query
    RATE_LIMITED = 64  # the compensation was limited to the configured rate
    RESTARTED = 128  # the model was restarted after an outage longer than it bridges
    HELD = 256  # the written compensation is the last good value, not a new prediction


def flag_names(f: int) -> str:
    return "|".join(m.name for m in Flags if m.value and f & m.value) or "OK"


@dataclass
class Settings:
    """The ``conf/compensator.yaml`` keys the cycle logic uses (see there)."""

    rate_limit_um_s: float = 20.0
    stale_after_s: float = 2.0
    max_age_s: float | None = None
    input_max_age_s: float = 10.0
    convention: str = "compensation"
    line_travel_mm: tuple[float, float] | None = None
    line_points: int = 21
    line_ref_mm: float | None = None
    ranges: dict[str, tuple[float, float]] = field(default_factory=dict)

    @classmethod
    def from_config(cls, cfg: Mapping[str, Any]) -> "Settings":
        line = cfg.get("line") or {}
        travel = line.get("travel_mm")
        s = cls(rate_limit_um_s=float(cfg.get("rate_limit_um_s", 20.0)), stale_after_s=float(cfg.get("stale_after_s", 2.0)),
                max_age_s=None if cfg.get("max_age_s") is None else float(cfg["max_age_s"]),
                input_max_age_s=float(cfg.get("input_max_age_s", 10.0)), convention=str(cfg.get("convention", "compensation")),
                line_travel_mm=None if travel is None else (float(travel[0]), float(travel[1])),
                line_points=int(line.get("n_points", 21)),
                line_ref_mm=None if line.get("ref_mm") is None else float(line["ref_mm"]),
                ranges={k: (float(v[0]), float(v[1])) for k, v in (cfg.get("ranges") or {}).items()})  # fmt: skip
        if s.convention not in ("compensation", "error"):
            raise ValueError(f"config key 'convention': expected compensation or error, got {s.convention!r}")
        if not s.rate_limit_um_s > 0:
            raise ValueError(f"config key 'rate_limit_um_s': must be > 0 µm/s, got {s.rate_limit_um_s}")
        if s.line_travel_mm is not None and not s.line_travel_mm[1] > s.line_travel_mm[0]:
            raise ValueError(f"config key 'line.travel_mm': expected [start, end] with end > start, got {list(s.line_travel_mm)}")
        if s.line_points < 2:
            raise ValueError(f"config key 'line.n_points': at least 2, got {s.line_points}")
        for k, (lo, hi) in s.ranges.items():
            if not hi > lo:
                raise ValueError(f"config key 'ranges.{k}': expected [min, max] with max > min, got [{lo}, {hi}]")
        return s

    def range_of(self, name: str) -> tuple[float, float]:
        key = "temperature_C" if name.endswith("_C") else name
        return self.ranges.get(key, (-math.inf, math.inf))


@dataclass
class Reading:
    """One input as read: value, its source timestamp (s, any epoch; None: unknown) and
    whether the server called it good."""

    value: Any
    ts_s: float | None = None
    good: bool = True


@dataclass
class Line:
    offset_um: float  # compensation at ref_mm
    slope_um_per_m: float
    ref_mm: float

    def at(self, x_mm) -> np.ndarray:
        return self.offset_um + self.slope_um_per_m * 1e-3 * (np.asarray(x_mm, dtype=float) - self.ref_mm)


@dataclass
class Cycle:
    """What one cycle decided (every field goes to the cycle log)."""

    t_s: float = math.nan  # machine time
    inputs: dict[str, float] = field(default_factory=dict)
    held: list[str] = field(default_factory=list)
    flags: int = 0
    value_um: float | None = None  # compensation at the current position (None: nothing to write yet)
    line: Line | None = None
    predicted_um: float = math.nan  # the runtime's total predicted error at the current position
    label: int = -1
    rc: int = 0


def fit_line(x_mm: np.ndarray, comp_um: np.ndarray, ref_mm: float) -> Line:
    """Least-squares line ``comp = offset + slope (x - ref)`` (numpy.polyfit, degree 1)."""
    slope_um_per_mm, offset_um = np.polyfit(np.asarray(x_mm, dtype=float) - ref_mm, np.asarray(comp_um, dtype=float), 1)
    return Line(float(offset_um), float(slope_um_per_mm) * 1e3, float(ref_mm))


class CycleLogic:
    """The compensator's per-cycle rules over a :class:`thermbench.export.native.LiveModel`."""

    def __init__(self, model, settings: Settings, output: str = "value", has_load: bool = False,
                 has_measuring: bool = False) -> None:  # fmt: skip
        self.model = model
        self.s = settings
        self.output = output
        if output in ("line", "both") and settings.line_travel_mm is None:
            raise ValueError("config key 'line.travel_mm': the error-line output needs the axis travel [start, end] in mm")
        self.names = ["axis_mm", "feed_mm_min", *(["load_N"] if has_load else []),
                      *[f"{t}_C" for t in model.temperatures]]  # fmt: skip
        self.has_measuring = has_measuring
        self.period_s = float(model.period_s)
        self.t0_ts: float | None = None
        self.last_ts: float | None = None
        self.last_advance_wall: float | None = None
        self.k_last: int | None = None
        self.good: dict[str, float] = {}
        self.value_um: float | None = None  # last written (rate-limited) compensation
        self.ends_um: tuple[float, float] | None = None  # last written line at the travel ends
        self.t_out: float | None = None
        self.resync = False

    # ------------------------------------------------------------------ inputs ---
    def _accept(self, name: str, r: Reading | None, ts_axis: float) -> tuple[float | None, bool]:
        lo, hi = self.s.range_of(name)
        v = None if r is None else r.value
        ok = r is not None and r.good and isinstance(v, (int, float)) and not isinstance(v, bool)
        ok = ok and math.isfinite(float(v)) and lo <= float(v) <= hi
        if ok and r.ts_s is not None and name != "axis_mm" and ts_axis - r.ts_s > self.s.input_max_age_s:
            ok = False  # older than the axis by more than the machine-time limit: stale
        if ok:
            self.good[name] = float(v)
            return float(v), False
        return self.good.get(name), True

    # ------------------------------------------------------------------- cycle ---
    def hold(self, flags: int, t_s: float = math.nan) -> Cycle:
        """A cycle that writes the last good compensation (or nothing before the first)."""
        c = Cycle(t_s=t_s, flags=int(flags | Flags.HELD))
        c.value_um = self.value_um
        c.line = self._line_from_ends(self.ends_um) if self.ends_um is not None else None
        return c

    def reconnected(self) -> None:
        """A new session: if the server's clock restarted (timestamps behind the last ones),
        the next cycle starts a new timeline (model restarted) instead of refusing it."""
        self.resync = True

    def cycle(self, readings: Mapping[str, Reading], now_wall_s: float, now_epoch_s: float | None = None) -> Cycle:
        ax = readings.get("axis_mm")
        ts = None if ax is None else ax.ts_s
        if ts is None:
            ts = now_epoch_s if now_epoch_s is not None else now_wall_s
        restarted = False
        if self.resync and self.last_ts is not None and ts < self.last_ts - 1e-9:
            self.model.start()
            self.t0_ts = self.last_ts = self.k_last = self.t_out = None
            restarted = True
        self.resync = False
        if self.last_ts is not None and ts < self.last_ts - 1e-9:
            return self.hold(Flags.CLOCK, self._t(self.last_ts))
        if self.last_ts is None or ts > self.last_ts:
            self.last_advance_wall = now_wall_s
            self.last_ts = ts
        if self.t0_ts is None:
            self.t0_ts = ts
        t = self._t(ts)
        stale = now_wall_s - self.last_advance_wall > self.s.stale_after_s
        if self.s.max_age_s is not None and now_epoch_s is not None and now_epoch_s - ts > self.s.max_age_s:
            stale = True
        if stale:
            return self.hold(Flags.STALE, t)
        c = Cycle(t_s=t, flags=int(Flags.RESTARTED) if restarted else 0)
        for name in self.names:
            v, held = self._accept(name, readings.get(name), ts)
            if held:
                c.held.append(name)
            if v is not None:
                c.inputs[name] = v
        if c.held:
            c.flags |= Flags.INPUT_HELD
        if len(c.inputs) < len(self.names):  # an input never seen good: no sample to give the model
            out = self.hold(c.flags | Flags.NOT_READY, t)
            out.inputs, out.held = c.inputs, c.held
            return out
        meas = readings.get("measuring")
        measuring = bool(meas is not None and meas.good and meas.value)
        self._step(c, t, measuring)
        return self._predict(c, t)

    def _t(self, ts: float) -> float:
        return ts - (self.t0_ts if self.t0_ts is not None else ts)

    def _step(self, c: Cycle, t: float, measuring: bool) -> None:
        k = math.floor(t / self.period_s + 1e-6)
        if self.k_last is not None and k <= self.k_last:
            return
        if self.k_last is not None and (k - self.k_last) * self.period_s > TB_MAX_GAP_S:
            self.model.start()
            c.flags |= Flags.RESTARTED
        i = c.inputs
        temps = [i[f"{s}_C"] for s in self.model.temperatures]
        rc = self.model.step(k * self.period_s, i["axis_mm"], i["feed_mm_min"], temps, load_N=i.get("load_N", 0.0),
                             measuring=measuring)  # fmt: skip
        if rc == TB_E_SAMPLING:
            self.model.start()
            c.flags |= Flags.RESTARTED
            rc = self.model.step(k * self.period_s, i["axis_mm"], i["feed_mm_min"], temps, load_N=i.get("load_N", 0.0),
                                 measuring=measuring)  # fmt: skip
        if rc < 0:
            c.flags |= Flags.RUNTIME
            c.rc = rc
        self.k_last = k

    def _predict(self, c: Cycle, t: float) -> Cycle:
        ready = self.model.ready_s
        if not ready > -1e299:  # the runtime says -1e300 (or NaN) before its first state
            return self._held_from(c, Flags.NOT_READY)
        sign = -1.0 if self.s.convention == "compensation" else 1.0
        rc, _, total, label = self.model.predict(ready, c.inputs["axis_mm"])
        if rc < 0:
            c.rc = rc
            return self._held_from(c, Flags.NOT_READY if rc in (-14, -13) else Flags.RUNTIME)
        c.predicted_um, c.label = total, label
        dt = 0.0 if self.t_out is None else max(0.0, t - self.t_out)
        step = self.s.rate_limit_um_s * dt
        if self.output in ("value", "both"):
            want = sign * total
            prev = 0.0 if self.value_um is None else self.value_um
            got = prev + float(np.clip(want - prev, -step, step))
            if abs(got - want) > 1e-12:
                c.flags |= Flags.RATE_LIMITED
            self.value_um = c.value_um = got
        if self.output in ("line", "both"):
            a, b = self.s.line_travel_mm
            xs = np.linspace(a, b, self.s.line_points)
            rcs, tot = self.model.predict_many(ready, xs)
            if np.any(rcs < 0):
                c.rc = int(rcs[rcs < 0][0])
                return self._held_from(c, Flags.RUNTIME)
            want_line = fit_line(xs, sign * tot, self._ref())
            want = (float(want_line.at(a)), float(want_line.at(b)))
            prev = self.ends_um or (0.0, 0.0)
            got = tuple(p + float(np.clip(w - p, -step, step)) for p, w in zip(prev, want))
            if max(abs(g - w) for g, w in zip(got, want)) > 1e-12:
                c.flags |= Flags.RATE_LIMITED
            self.ends_um = got
            c.line = self._line_from_ends(got)
        self.t_out = t
        return c

    def _held_from(self, c: Cycle, flag: Flags) -> Cycle:
        h = self.hold(c.flags | flag, c.t_s)
        h.inputs, h.held, h.rc = c.inputs, c.held, c.rc
        return h

    def _ref(self) -> float:
        return self.s.line_ref_mm if self.s.line_ref_mm is not None else self.s.line_travel_mm[0]

    def _line_from_ends(self, ends: tuple[float, float]) -> Line:
        a, b = self.s.line_travel_mm
        slope_um_per_mm = (ends[1] - ends[0]) / (b - a)
        ref = self._ref()
        return Line(ends[0] + slope_um_per_mm * (ref - a), slope_um_per_mm * 1e3, ref)
