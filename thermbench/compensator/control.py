"""One compensator cycle, without any I/O: readings in, compensation out.

:class:`CycleLogic` is what ``thermbench compensator`` does each control cycle between
reading the machine and writing to it, so every fault rule is testable without a
network:

* **Machine time** is the newest source timestamp of the inputs (``clock: source``, for a
  server that stamps every sample, as sim-cnc does), or the client's clock (``clock:
  client``, for a server that stamps a value only when it changes), in seconds since the
  first cycle. The exported model is stepped on its own sample grid (the dataset's
  process-log period, manifest ``sample_period_s``): when machine time passes a grid
  point, the runtime is stepped at that point with the latest values (zero-order hold),
  as the process log it was trained on was sampled.
* **Inputs**: a value that is missing, not finite, outside its configured range, or
  whose timestamp lags the axis by more than ``input_max_age_s`` is *held*: the last good
  value goes to the model and the cycle is flagged ``INPUT_HELD``.
* **Stale data**: machine time (or the optional ``heartbeat`` input's value) not advancing
  for ``stale_after_s`` of the client's clock, or a timestamp older than ``max_age_s``
  against the client's clock -> ``STALE``; timestamps going backwards -> ``CLOCK`` (a new
  timeline, model restarted, if it lasts ``stale_after_s`` or follows a reconnection). The
  compensation is then held at the value the controller has (``HELD``).
* **Outage**: longer than the runtime accepts between samples (``TB_MAX_GAP_S``) -> the
  model is restarted (``RESTARTED``) and the compensation held until it predicts again.
* **Sensor faults** (:mod:`thermbench.bench.faults`, the model's manifest ``faults``): every
  temperature of every model sample checked against the limits of the training runs (open circuit,
  out of range, a rate no training run shows, stuck, departing from the other sensors); a sensor
  judged faulty stays so until the model restarts, the model reads it as the other sensors predict
  it, and every cycle after is flagged ``SENSOR_FAULT`` (the cycle log's ``faulty`` names them).
  The compensation's magnitude never exceeds the manifest's bound (the largest thermal error of
  the training runs plus half of it; ``BOUNDED`` when it acts).
* **Rate limit**: the compensation never changes in time faster than ``rate_limit_um_s``
  per second of machine time, counted per cycle and at most one sample period per cycle
  (so no step after an outage or a freeze either; the role of SINUMERIK MD32760
  ``COMP_ADD_VELO_FACTOR``). It acts on the change in time at fixed positions: the change
  along the axis as it moves passes. For the value output the ramp keeps the lag between
  what is written and the model's value; after a hold it starts from the held value, at
  start-up from the controller's value (:meth:`CycleLogic.resume`). For the error line it
  acts at both ends of the travel.
The compensation is the value added to the axis position set point, ``-predicted
error`` (the C runtime's ``total_um``: geometric + thermal); ``convention: error`` in
the config writes the predicted error itself, for controllers that subtract it.
The error line's form: :mod:`.errorline`; the config keys: :mod:`.settings`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

import thermbench

from . import errorline
from .settings import config_error as _config_error

if TYPE_CHECKING:
    from .settings import Settings

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
    MACHINE_OFF = 512  # the controller dropped the compensation (LinuxCNC machine off): 0 written, ramps from 0 after
    RESUMED = 1024  # warm restart: the model state of the previous run re-stepped from its saved samples
    COLD = 2048  # the model started cold on a machine that may be warm (no usable saved state, or a gap longer
    # than the runtime bridges): its zero is the machine as it was then; set on every cycle after
    PROBE = 4096  # a probe reading (a new timestamp on the probe input) updated the correction this cycle
    EXTRAPOLATING = 8192  # the inputs are outside the envelope the model was fitted on (manifest 'envelope')
    SENSOR_FAULT = 16384  # a temperature sensor was judged faulty (manifest 'faults'): the model reads it reconstructed
    BOUNDED = 32768  # the compensation was held to the bound of its magnitude (bound_um, else manifest 'faults.bounds.max_um')


def flag_names(f: int) -> str:
    return "|".join(m.name for m in Flags if m.value and f & m.value) or "OK"


def inner_edge(total_um, interval: Mapping[str, Any], distance: float):
    """The inner edge of a prediction's interval (the ``limit`` policy): the prediction moved toward
    0 by its half-width ``q_um * (1 + kappa * distance)`` (manifest ``interval``), and 0 when the
    interval holds 0: compensate only what the model is sure of."""
    hw = float(interval["q_um"]) * (1.0 + float(interval.get("kappa", 1.0)) * float(distance))
    v = np.asarray(total_um, dtype=float)
    out = np.sign(v) * np.maximum(np.abs(v) - hw, 0.0)
    return out if np.ndim(total_um) else float(out)


@dataclass
class Reading:
    """One input as read: value, its source timestamp (s, any epoch; None: unknown) and
    whether the server called it good."""

    value: Any
    ts_s: float | None = None
    good: bool = True


@dataclass
class Cycle:
    """What one cycle decided (every field goes to the cycle log)."""

    t_s: float = math.nan  # machine time
    inputs: dict[str, float] = field(default_factory=dict)
    held: list[str] = field(default_factory=list)
    flags: int = 0
    value_um: float | None = None  # compensation at the current position (None: nothing to write yet)
    line: errorline.Line | None = None
    predicted_um: float = math.nan  # the runtime's total predicted error at the current position
    label: int = -1
    rc: int = 0
    correction_um: float = 0.0  # the probe filter's correction of the total at the current position
    probe_um: float | None = None  # the probe reading taken this cycle
    faulty: list[str] = field(default_factory=list)  # the temperature sensors judged faulty so far


class CycleLogic:
    """The compensator's per-cycle rules over a :class:`thermbench.export.native.LiveModel`."""

    def __init__(self, model, settings: Settings, output: str = "value", has_load: bool = False,
                 has_measuring: bool = False) -> None:  # fmt: skip
        self.model = model
        self.s = settings
        self.output = output
        if output in ("line", "both") and settings.line_travel_mm is None:
            raise _config_error("config key 'line.travel_mm': the error-line output needs the axis travel [start, end] "
                                "in mm")
        self.operating = list(getattr(model, "operating", []))  # e.g. spindle_rpm of a spindle's lumped network
        self.names = ["axis_mm", "feed_mm_min", *(["load_N"] if has_load else []),
                      *[f"{t}_C" for t in model.temperatures], *self.operating]  # fmt: skip
        self.has_measuring = has_measuring
        self.period_s = float(model.period_s)
        self.sign = -1.0 if settings.convention == "compensation" else 1.0
        self.t0_ts: float | None = None  # machine time origin (a timestamp)
        self.last_ts: float | None = None
        self.last_advance_wall: float | None = None
        self.heartbeat: Any = None
        self.back_since_wall: float | None = None
        self.k_last: int | None = None
        self.good: dict[str, float] = {}
        self.resync = False
        # what the controller holds (written or found there) and the ramp state
        self.value_um: float | None = None
        self.ends_um: tuple[float, float] | None = None
        self.t_prev: float | None = None  # machine time of the previous cycle (held or not)
        self.fresh_t_s: float | None = None  # time of the previous fresh value (None: the last cycle held)
        self.lag_um = 0.0  # written value minus the model's, at the current position
        self._saved: tuple = ()
        # what the model was stepped with since its last start: (k, axis, feed, load, measuring, temps...),
        # the state a warm restart re-steps (the C runtime's arena holds pointers: its bytes do not outlive us)
        self.stepped: list[tuple] = []
        self.keep_stepped = False  # recorded only for a state store (warm restarts): else it would only grow
        self.cold = False  # sticky: the model started cold on a possibly warm machine
        self.starts = 0  # model (re)starts: a state store rewrites its samples after one
        # inputs read from another server than the axis's (a station's separate logger): another clock, so
        # they neither set machine time nor are aged against it
        self.foreign: set[str] = set()
        # probe readings (thermbench/bench/adapt.py): the C runtime's filter on the model's total, from the
        # timeline's start; the last probe's timestamp (a reading is taken once per new timestamp)
        self.filter = None
        self.last_probe: tuple | None = None
        self.t_start: float | None = 0.0  # machine time of the model's (re)start: the filter's start
        env = (getattr(model, "manifest", None) or {}).get("envelope")
        if env is not None:
            from ..bench.intervals import Envelope, EnvelopeGuard

            self.guard = EnvelopeGuard(Envelope.from_dict(env), float(env.get("rate_tau_s", 600.0)))
        else:
            self.guard = None  # an export without an envelope (from before envelopes were exported): nothing to flag
        faults = (getattr(model, "manifest", None) or {}).get("faults")
        self.monitor, self.bound_um = None, math.inf
        if faults is not None:  # the sensor checks and the bound of the training runs (thermbench/bench/faults.py)
            from ..bench.faults import FaultMonitor, SensorLimits

            if faults.get("limits") is not None:  # None: the model reads no temperature
                limits = SensorLimits.from_dict(faults["limits"])
                if list(limits.sensors) != list(model.temperatures):
                    raise _config_error(f"the model's manifest 'faults' checks sensors {list(limits.sensors)}, the model "
                                        f"reads {list(model.temperatures)}: export it again")  # fmt: skip
                self.monitor = FaultMonitor(limits)
            bound = (faults.get("bounds") or {}).get("max_um")
            self.bound_um = math.inf if bound is None else float(bound)
        if self.s.bound_um is not None:  # the user's bound (config key bound_um) over the training runs'
            self.bound_um = float(self.s.bound_um)
        self.interval = (getattr(model, "manifest", None) or {}).get("interval")
        if self.s.extrapolation == "limit" and (self.guard is None or not self.interval):
            what = "no training envelope" if self.guard is None else "no interval"
            raise _config_error(f"config key 'extrapolation': limit needs the model's interval and envelope, and its "
                               f"manifest has {what} (export it with its dataset and export.interval_level=0.9)")  # fmt: skip

    def _restart(self) -> None:
        self.model.start()
        self.stepped = []
        self.starts += 1
        self.filter = None  # a new model state: the old correction is of another zero
        self.t_start = None  # set by the first sample after it
        if getattr(self, "guard", None) is not None:
            self.guard.reset()  # the rises count from the new first sample, as the model's
        if getattr(self, "monitor", None) is not None:
            self.monitor.reset()  # as the guard: a new first sample, and every sensor trusted again

    # ------------------------------------------------------------ warm restart ---
    STATE_COLUMNS = ("k", "axis_mm", "feed_mm_min", "load_N", "measuring")

    def state(self) -> dict:
        """What a later process needs to go on where this one stopped (with :attr:`stepped`)."""
        return {"t0_ts": self.t0_ts, "last_ts": self.last_ts, "k_last": self.k_last, "value_um": self.value_um,
                "ends_um": list(self.ends_um) if self.ends_um is not None else None, "period_s": self.period_s,
                "temperatures": list(self.model.temperatures), "cold": self.cold,
                "probe": self.filter.state() if self.filter is not None else None,
                "last_probe": list(self.last_probe) if self.last_probe is not None else None}  # fmt: skip

    def resume_decision(self, state: dict, rows, ts_now: float, inputs_now: Mapping[str, float],
                        max_gap_s: float = TB_MAX_GAP_S, agree_C: float = 2.0) -> tuple[bool, str]:  # fmt: skip
        """Warm (True) when the saved state is of this model's inputs, the gap in machine time is
        at most ``max_gap_s`` (what the runtime bridges) and every temperature now is within
        ``agree_C`` of the last saved sample's; else cold, and why."""
        if state.get("_problem"):
            return False, str(state["_problem"])
        if state.get("temperatures") != list(self.model.temperatures) or state.get("period_s") != self.period_s:
            return False, "the saved state is of another model"
        if not len(rows) or state.get("last_ts") is None:
            return False, "the saved state has no sample"
        gap = ts_now - float(state["last_ts"])
        if gap < 0:
            return False, f"machine time went back {-gap:.1f} s since the saved state (the server restarted its clock)"
        if gap > max_gap_s:
            return False, f"the saved state is {gap:.0f} s old, more than the {max_gap_s:.0f} s the runtime bridges"
        last = rows[-1]
        n0 = len(self.STATE_COLUMNS)
        for j, name in enumerate(self.model.temperatures):
            now = inputs_now.get(f"{name}_C")
            if now is None or not math.isfinite(now) or abs(now - last[n0 + j]) > agree_C:
                return False, f"{name} is {now} °C now, {last[n0 + j]:.2f} °C in the saved state (more than {agree_C} K apart)"
        return True, f"gap {gap:.1f} s, {len(rows)} samples re-stepped"

    def warm_start(self, state: dict, rows) -> None:
        """Re-step the saved samples into a fresh model state and go on from the saved clock and
        compensation (the controller still holds it: it ramps from there)."""
        self._restart()
        n0 = len(self.STATE_COLUMNS)
        for row in rows:
            k = int(row[0])
            nt = len(self.model.temperatures)
            rc = self.model.step(k * self.period_s, row[1], row[2], list(row[n0 : n0 + nt]), load_N=row[3],
                                 measuring=bool(row[4]), operating=list(row[n0 + nt :]))  # fmt: skip
            if rc >= 0:
                self.stepped.append(tuple(float(v) for v in row))
                if self.guard is not None:
                    self.guard.step(k * self.period_s, list(row[n0 : n0 + nt]), list(row[n0 + nt :]))
        self.t0_ts, self.last_ts = float(state["t0_ts"]), float(state["last_ts"])
        self.k_last = int(rows[-1][0])
        self.t_start = float(rows[0][0]) * self.period_s if len(rows) else 0.0
        if state.get("probe"):  # the correction the probes had made goes on (with its uncertainty)
            from ..export.native import LiveProbe

            self.filter = LiveProbe(self.s.probe, self.t_start)
            self.filter.restore(state["probe"])
        if state.get("last_probe") is not None:
            self.last_probe = tuple(state["last_probe"])
        self.value_um = state.get("value_um")
        self.ends_um = tuple(state["ends_um"]) if state.get("ends_um") else None
        self.cold = bool(state.get("cold"))
        self.fresh_t_s = None

    # ------------------------------------------------------------- controller ---
    def resume(self, value_um: float | None = None, line: "errorline.Line | None" = None) -> None:
        """Start from the compensation the controller holds already (read at connection), so
        the first values written ramp from it instead of stepping from zero."""
        if value_um is not None and math.isfinite(value_um):
            self.value_um = float(value_um)
        if line is not None and self.s.line_travel_mm is not None:
            a, b = self.s.line_travel_mm
            ends = (float(line.at(a)), float(line.at(b)))
            if all(math.isfinite(e) for e in ends):
                self.ends_um = ends

    def reconnected(self) -> None:
        """A new session: if the server's clock restarted (timestamps behind the last ones),
        the next cycle starts a new timeline (model restarted) instead of refusing it."""
        self.resync = True

    def undo(self) -> None:
        """The last cycle's values were not written (the write failed): forget them."""
        if self._saved:
            self.value_um, self.ends_um, self.t_prev, self.fresh_t_s, self.lag_um = self._saved

    # ------------------------------------------------------------------ inputs ---
    def _accept(self, name: str, r: Reading | None, ts_now: float) -> tuple[float | None, bool]:
        lo, hi = self.s.range_of(name)
        v = None if r is None else r.value
        ok = r is not None and r.good and isinstance(v, (int, float)) and not isinstance(v, bool)
        ok = ok and math.isfinite(float(v)) and lo <= float(v) <= hi
        if (ok and self.s.clock == "source" and r.ts_s is not None and name not in self.foreign
                and ts_now - r.ts_s > self.s.input_max_age_s):  # fmt: skip
            ok = False  # older than the newest input by more than the machine-time limit: stale
        if ok:
            self.good[name] = float(v)
            return float(v), False
        return self.good.get(name), True

    # ------------------------------------------------------------------- cycle ---
    def hold(self, flags: int, t_s: float = math.nan) -> Cycle:
        """A cycle that writes the value the controller holds (nothing before there is one)."""
        c = Cycle(t_s=t_s, flags=int(flags | Flags.HELD | (Flags.COLD if self.cold else 0)))
        c.value_um = self.value_um
        c.line = self._line_from_ends(self.ends_um) if self.ends_um is not None else None
        self.fresh_t_s = None  # the controller now holds one value at every position
        if math.isfinite(t_s):
            self.t_prev = t_s
        return c

    def _machine_ts(self, readings: Mapping[str, Reading], now_wall_s: float, now_epoch_s: float | None) -> float:
        now = now_epoch_s if now_epoch_s is not None else now_wall_s
        if self.s.clock == "client":
            return now
        stamps = [r.ts_s for n, r in readings.items()
                  if r is not None and r.ts_s is not None and n not in ("heartbeat", "probe") and n not in self.foreign]  # fmt: skip
        return max(stamps) if stamps else now

    def cycle(self, readings: Mapping[str, Reading], now_wall_s: float, now_epoch_s: float | None = None) -> Cycle:
        c = self._cycle(readings, now_wall_s, now_epoch_s)
        if self.cold:
            c.flags = int(c.flags | Flags.COLD)
        if self.monitor is not None and self.monitor.faulty:  # on every cycle until the model restarts
            c.flags = int(c.flags | Flags.SENSOR_FAULT)
            c.faulty = list(self.monitor.faulty)
        return c

    def _cycle(self, readings: Mapping[str, Reading], now_wall_s: float, now_epoch_s: float | None = None) -> Cycle:
        self._saved = (self.value_um, self.ends_um, self.t_prev, self.fresh_t_s, self.lag_um)
        ts = self._machine_ts(readings, now_wall_s, now_epoch_s)
        restarted = False
        back = self.last_ts is not None and ts < self.last_ts - 1e-9
        if back and self.back_since_wall is None:
            self.back_since_wall = now_wall_s
        if not back:
            self.back_since_wall = None
        if back and (self.resync or now_wall_s - self.back_since_wall > self.s.stale_after_s):
            # the server's clock restarted (after a reconnection, or for longer than a glitch): new timeline
            self._restart()
            self.cold = True
            self.t0_ts = self.last_ts = self.k_last = self.t_prev = self.fresh_t_s = None
            self.t_start = 0.0
            self.back_since_wall, back, restarted = None, False, True
        self.resync = False
        if back:
            return self.hold(Flags.CLOCK)
        hb = readings.get("heartbeat")
        advanced = (hb.value != self.heartbeat) if hb is not None else (self.last_ts is None or ts > self.last_ts)
        if hb is not None:
            self.heartbeat = hb.value
        if advanced or self.last_advance_wall is None:
            self.last_advance_wall = now_wall_s
        if self.last_ts is None or ts > self.last_ts:
            self.last_ts = ts
        if self.t0_ts is None:
            self.t0_ts = ts
        t = ts - self.t0_ts
        stale = now_wall_s - self.last_advance_wall > self.s.stale_after_s
        if self.s.max_age_s is not None and now_epoch_s is not None and self.s.clock == "source":
            stale = stale or now_epoch_s - ts > self.s.max_age_s
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
            return self._held_from(c, Flags.NOT_READY)
        meas = readings.get("measuring")
        measuring = bool(meas is not None and meas.good and meas.value)
        self._step(c, t, measuring)
        self._probe(c, readings.get("probe"), t)
        if self.guard is not None and self.guard.distance > 0:
            c.flags |= Flags.EXTRAPOLATING
            if self.s.extrapolation == "hold" and self.value_um is not None:
                return self._held_from(c, Flags.EXTRAPOLATING)
        return self._predict(c, t)

    # ------------------------------------------------------------------ probes ---
    def _probe(self, c: Cycle, r: Reading | None, t: float) -> None:
        """Take a probe reading (the measured error, µm, at the current axis position) once per new
        timestamp (per new value where the server gives none): the filter is updated with the
        model's total at the reading's machine time, which the runtime must still hold."""
        if r is None or not r.good or not isinstance(r.value, (int, float)) or isinstance(r.value, bool):
            return
        v = float(r.value)
        key = (r.ts_s,) if r.ts_s is not None else (None, v)
        if not math.isfinite(v) or key == self.last_probe:
            return
        first = self.last_probe is None
        self.last_probe = key
        if first and r.ts_s is not None and self.t0_ts is not None and r.ts_s < self.t0_ts:
            return  # a reading from before this timeline (the value the server held at start-up)
        t_p = t if r.ts_s is None or self.s.clock != "source" or self.t0_ts is None else min(r.ts_s - self.t0_ts, t)
        rc, _, total, _ = self.model.predict(t_p, c.inputs["axis_mm"])
        if rc < 0:
            return
        if self.filter is None:
            from ..export.native import LiveProbe

            self.filter = LiveProbe(self.s.probe, min(self.t_start if self.t_start is not None else t_p, t_p))
        if self.filter.probe(t_p, total, v)[0] == 0:
            c.flags |= Flags.PROBE
            c.probe_um = v

    def _corrected(self, t: float, total):
        """The model's total(s) at ``t`` corrected by the probe filter (as they are without one),
        then, outside the envelope with ``extrapolation: limit``, at the interval's inner edge."""
        if self.filter is not None:
            if np.ndim(total):
                total = np.array([self.filter.correct(t, float(v))[1] for v in np.asarray(total, dtype=float)])
            else:
                total = self.filter.correct(t, float(total))[1]
        if self.s.extrapolation == "limit" and self.guard is not None and self.guard.distance > 0:
            total = inner_edge(total, self.interval, self.guard.distance)
        return total

    def _step(self, c: Cycle, t: float, measuring: bool) -> None:
        k = math.floor(t / self.period_s + 1e-3)  # 0.1 % of a period: timestamps carry float rounding
        if self.k_last is not None and k <= self.k_last:
            return
        if self.k_last is not None and (k - self.k_last) * self.period_s > TB_MAX_GAP_S:
            self._restart()
            self.cold = True  # a gap the runtime does not bridge: the machine is warm, the model starts from it
            c.flags |= Flags.RESTARTED
            self.fresh_t_s = None  # a new model state: ramp from what the controller holds
        i = c.inputs
        temps = [i[f"{s}_C"] for s in self.model.temperatures]
        if self.monitor is not None:  # what the model reads: a faulty sensor as the others predict it
            temps = [float(v) for v in self.monitor.step(k * self.period_s, temps)]
        args = (k * self.period_s, i["axis_mm"], i["feed_mm_min"], temps)
        op = [i[n] for n in self.operating]
        kw = {"operating": op} if op else {}
        rc = self.model.step(*args, load_N=i.get("load_N", 0.0), measuring=measuring, **kw)
        if rc == TB_E_SAMPLING:
            self._restart()
            self.cold = True
            c.flags |= Flags.RESTARTED
            self.fresh_t_s = None
            rc = self.model.step(*args, load_N=i.get("load_N", 0.0), measuring=measuring, **kw)
        if self.t_start is None and rc >= 0:
            self.t_start = k * self.period_s
        if self.guard is not None and rc >= 0:
            self.guard.step(k * self.period_s, temps, op)
        if rc < 0:
            c.flags |= Flags.RUNTIME
            c.rc = rc
        elif self.keep_stepped:
            self.stepped.append((k, i["axis_mm"], i["feed_mm_min"], i.get("load_N", 0.0), float(measuring), *temps, *op))
        self.k_last = k

    def _predict(self, c: Cycle, t: float) -> Cycle:
        """The model's answer for the cycle's own time ``t`` (what ``thermbench replay`` answers
        there, tb_replay --live): with the samples up to t, never the model's last final time
        only (the screw physics' last macro step lagged it by up to a step)."""
        ready = self.model.ready_s
        if not ready > -1e29:  # the runtime says -1e30 (or NaN) before its first state
            return self._held_from(c, Flags.NOT_READY)
        x = c.inputs["axis_mm"]
        rc, _, total, label = self.model.predict(t, x)
        if rc < 0:
            c.rc = rc
            return self._held_from(c, Flags.NOT_READY if rc in (-14, -13) else Flags.RUNTIME)
        c.predicted_um, c.label = total, label
        total = self._corrected(t, total)
        if abs(total) > self.bound_um:
            total = math.copysign(self.bound_um, total)
            c.flags |= Flags.BOUNDED
        c.correction_um = total - c.predicted_um
        # the rate limit acts on the change in time (at fixed positions), per cycle of machine time
        # (at most one sample period per cycle: no step after an outage or a freeze)
        dt = 0.0 if self.t_prev is None else min(max(0.0, t - self.t_prev), self.period_s)
        step = self.s.rate_limit_um_s * dt
        limited = False
        if self.output in ("line", "both"):
            a, b = self.s.line_travel_mm
            xs = np.linspace(a, b, self.s.line_points)
            rcs, tot = self.model.predict_many(t, xs)
            if np.any(rcs < 0):
                c.rc = int(rcs[rcs < 0][0])
                return self._held_from(c, Flags.RUNTIME)
            tot = self._corrected(t, tot)
            if np.any(np.abs(tot) > self.bound_um):
                tot = np.clip(tot, -self.bound_um, self.bound_um)
                c.flags |= Flags.BOUNDED
            want_line = errorline.fit_line(xs, self.sign * tot, self._ref())
            want = (float(want_line.at(a)), float(want_line.at(b)))
            prev = self.ends_um or (0.0, 0.0)
            got = tuple(p + float(np.clip(w - p, -step, step)) for p, w in zip(prev, want))
            limited = max(abs(g - w) for g, w in zip(got, want)) > 1e-12
            self.ends_um = got
            c.line = self._line_from_ends(got)
        if self.output in ("value", "both"):
            want = self.sign * total
            base = None
            if self.fresh_t_s is not None:  # what the ramp would give here with the previous model state
                rc_p, _, tot_p, _ = self.model.predict(self.fresh_t_s, x)
                base = self.sign * self._corrected(self.fresh_t_s, tot_p) + self.lag_um if rc_p == 0 else None
            if base is None:  # start-up, or after a hold: the value the controller holds
                base = 0.0 if self.value_um is None else self.value_um
            got = base + float(np.clip(want - base, -step, step))
            limited = limited or abs(got - want) > 1e-12
            self.lag_um = got - want
            self.value_um = c.value_um = got
        if limited:
            c.flags |= Flags.RATE_LIMITED
        self.fresh_t_s = t
        self.t_prev = t
        return c

    def dropped(self, c: Cycle, flag: Flags) -> Cycle:
        """The controller holds no compensation any more (LinuxCNC drops external offsets at
        machine off): 0 is what it holds, and the next values ramp from 0 at the rate limit."""
        self.value_um, self.ends_um, self.fresh_t_s, self.lag_um = 0.0, None, None, 0.0
        c.value_um, c.line = 0.0, None
        c.flags = int(c.flags | flag | Flags.HELD)
        return c

    def _held_from(self, c: Cycle, flag: Flags) -> Cycle:
        h = self.hold(c.flags | flag, c.t_s)
        h.inputs, h.held, h.rc = c.inputs, c.held, c.rc
        return h

    def _ref(self) -> float:
        return self.s.line_ref_mm if self.s.line_ref_mm is not None else self.s.line_travel_mm[0]

    def _line_from_ends(self, ends: tuple[float, float]) -> errorline.Line:
        a, b = self.s.line_travel_mm
        slope_um_per_mm = (ends[1] - ends[0]) / (b - a)
        ref = self._ref()
        return errorline.Line(ends[0] + slope_um_per_mm * (ref - a), slope_um_per_mm * 1e3, ref)


__getattr__ = thermbench.moved_names(__name__)
