"""``thermbench linuxcnc component MODEL_DIR``: thermal compensation as a userspace HAL component.

Started by LinuxCNC from the HAL file (``loadusr -Wn tbcomp thermbench linuxcnc component
MODEL_DIR ...``). Every ``period_s`` of the wall clock it

1. reads its input pins: the axis position (``axis-pos``, machine units: net
   ``joint.N.pos-fb``) and velocity (``axis-vel``, machine units per second: net
   ``joint.N.vel-cmd``), one ``temp.<sensor>`` pin per temperature the model needs (°C,
   wherever the user wires the sensors), ``machine-on`` (net ``motion.motion-enabled``) and,
   with ``time_source=pin``, ``time-s`` (machine time, e.g. a simulated plant's scaled clock);
2. decides the compensation with the OPC UA compensator's cycle rules
   (:class:`thermbench.compensator.control.CycleLogic`: the exported model stepped in the
   C runtime on its own sample grid, inputs held when implausible, the rate limit, a
   restart after a gap the runtime does not bridge), machine time stamping every input;
3. writes it to the axis's external offset: ``eoffset-counts`` = round(compensation /
   ``scale_per_count``), ``eoffset-scale`` = ``scale_per_count`` and ``eoffset-enable``,
   netted to ``axis.L.eoffset-counts``, ``-scale`` and ``-enable``. LinuxCNC then adds
   counts x scale to the axis, rate-limited by ``[AXIS_L]OFFSET_AV_RATIO``.

LinuxCNC adds the *changes* of the counts (x scale) to the offset, and drops the changes made
while the machine is off, not homed, or enable is false. So the offset is written only while
``machine-on`` (net ``motion.motion-enabled``) and ``all-homed`` (net ``motion.is-all-homed``) are
both true (``require_machine_on``): otherwise the model keeps stepping (the machine cools while
it is off), but the offset is dropped (enable false, counts 0, ``eoffset-clear`` true, flag
``MACHINE_OFF``), and on the way back the compensation ramps from zero at the rate limit.

Output pins for a GUI or halscope: ``comp-um`` (the compensation written, µm),
``predicted-um`` (the model's error at the axis position), ``flags`` (the cycle's
:class:`~thermbench.compensator.control.Flags`), ``ok`` and ``machine-time-s``.

Every cycle goes to the same CSV log as the OPC UA compensator's, its summary beside it. It
stops when LinuxCNC unloads it (SIGTERM, ``halcmd unload``), or after ``duration_s``.
"""

from __future__ import annotations

import importlib
import math
import signal
import sys
import time
from pathlib import Path
from typing import Any, Callable, Mapping

from ..compensator.cyclelog import CycleLog, Ring, cycle_stats, status_line
from ..compensator.control import Cycle, CycleLogic, Flags, Reading
from ..compensator.deadlines import Deadlines
from ..compensator.settings import Settings, config_error
from ..errors import UserError
from ..outputs import check_output_file, write_text

UNITS_MM = {"mm": 1.0, "inch": 25.4}
#: where Debian's and LinuxCNC's own builds put the Python modules hal and linuxcnc
LINUXCNC_PYTHON_DIRS = ("/usr/lib/python3/dist-packages", "/usr/lib/python3/site-packages", "/usr/local/lib/python3/dist-packages")
STATS_CYCLES = 1 << 20


class LinuxCncMissing(UserError, ImportError):
    """LinuxCNC's Python modules are not importable (LinuxCNC not installed)."""


def import_linuxcnc_module(name: str = "hal"):
    """LinuxCNC's Python module ``name`` (``hal`` or ``linuxcnc``): from this interpreter's path,
    else from the system's Python directory where the ``linuxcnc-uspace`` package puts it (a
    virtual environment does not see it). Only that module is taken from there: the directory
    is on ``sys.path`` while it is imported, and removed after."""
    try:
        return importlib.import_module(name)
    except ImportError:
        pass
    for d in LINUXCNC_PYTHON_DIRS:
        if (Path(d) / f"{name}.py").exists() or any(Path(d).glob(f"{name}.cpython-*.so")):
            sys.path.insert(0, d)
            try:
                return importlib.import_module(name)
            except ImportError:
                break
            finally:
                sys.path.remove(d)
    raise LinuxCncMissing(f"LinuxCNC's Python module {name!r} is not importable: install LinuxCNC (Debian: apt-get install "
                          "--no-install-recommends linuxcnc-uspace), or run this under the Python LinuxCNC was built for")  # fmt: skip


def _positive(cfg: Mapping[str, Any], key: str) -> float:
    v = cfg.get(key)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
        raise config_error(f"config key {key!r}: expected a number > 0, got {v!r}")
    return float(v)


def _choice(cfg: Mapping[str, Any], key: str, options) -> str:
    v = cfg.get(key)
    if v not in options:
        raise config_error(f"config key {key!r}: expected one of {', '.join(options)}, got {v!r}")
    return str(v)


def temp_pin(sensor: str) -> str:
    return f"temp.{sensor}"


class HalCompensator:
    """The component: :meth:`pins` declares what it reads and writes, :meth:`step` is one cycle
    over anything that maps pin names to values (a ``hal.component``, or a dict in a test),
    :meth:`run` the loop."""

    def __init__(self, model_dir: str | Path, cfg: Mapping[str, Any] | None = None,
                 say: Callable[[str], None] | None = None) -> None:  # fmt: skip
        from ..config import with_defaults
        from ..export.native import LiveModel

        cfg = with_defaults("linuxcnc_component", cfg or {})
        self.cfg = cfg
        self.name = str(cfg["name"])
        self.period_s = _positive(cfg, "period_s")
        self.time_source = _choice(cfg, "time_source", ("wall", "pin"))
        self.time_scale = _positive(cfg, "time_scale")
        self.unit_mm = UNITS_MM[_choice(cfg, "units", tuple(UNITS_MM))]
        self.scale = _positive(cfg, "scale_per_count")
        self.require_on = bool(cfg["require_machine_on"])
        self.status_every_s = _positive(cfg, "status_every_s")
        self.duration_s = None if cfg.get("duration_s") is None else _positive(cfg, "duration_s")
        self.log_path = Path(str(cfg["log"]))
        check_output_file(self.log_path, "compensator-log")  # refused before LinuxCNC waits on us
        check_output_file(self.log_path.with_suffix(".summary.json"), "compensator-summary")
        self.model = LiveModel(model_dir)
        settings = Settings.from_config({**cfg, "clock": "source"})  # machine time stamps every reading here
        self.logic = CycleLogic(self.model, settings, "value", has_load=self.model.needs_load)
        if self.time_source == "pin":  # the pin's clock is the machine's: its zero, not our first cycle, is time 0
            self.logic.t0_ts = 0.0
        self.say = say
        self.stop_requested = False
        self.t0_wall: float | None = None
        self.was_on = False
        self.probe_was_valid = False

    # ------------------------------------------------------------------ pins ---
    def pins(self) -> list[tuple[str, str, str]]:
        """(name, type, direction) of every pin: type float|s32|bit, direction in|out."""
        ins = [("axis-pos", "float"), ("axis-vel", "float"), ("machine-on", "bit"), ("all-homed", "bit")]
        ins += [(temp_pin(s), "float") for s in self.model.temperatures]
        if self.model.needs_load:
            ins.append(("load-N", "float"))
        if self.time_source == "pin":
            ins.append(("time-s", "float"))
        ins += [("probe-um", "float"), ("probe-valid", "bit")]  # a probe reading, taken when probe-valid rises
        outs = [("eoffset-counts", "s32"), ("eoffset-scale", "float"), ("eoffset-enable", "bit"), ("eoffset-clear", "bit"),
                ("comp-um", "float"), ("predicted-um", "float"), ("flags", "s32"), ("ok", "bit"),
                ("machine-time-s", "float")]  # fmt: skip
        return [(n, t, "in") for n, t in ins] + [(n, t, "out") for n, t in outs]

    def component(self):
        """The HAL component with its pins, marked ready (``loadusr -W`` waits for that)."""
        hal = import_linuxcnc_module("hal")
        h = hal.component(self.name)
        types = {"float": hal.HAL_FLOAT, "s32": hal.HAL_S32, "bit": hal.HAL_BIT}
        dirs = {"in": hal.HAL_IN, "out": hal.HAL_OUT}
        for name, typ, d in self.pins():
            h.newpin(name, types[typ], dirs[d])
        h.ready()
        return h

    # ----------------------------------------------------------------- cycle ---
    def machine_time(self, h, now_wall_s: float) -> float:
        if self.time_source == "pin":
            return float(h["time-s"])
        if self.t0_wall is None:
            self.t0_wall = now_wall_s
        return self.time_scale * (now_wall_s - self.t0_wall)

    def readings(self, h, ts: float) -> dict[str, Reading]:
        r = {"axis_mm": Reading(float(h["axis-pos"]) * self.unit_mm, ts),
             "feed_mm_min": Reading(abs(float(h["axis-vel"])) * self.unit_mm * 60.0, ts)}  # fmt: skip
        for s in self.model.temperatures:
            r[f"{s}_C"] = Reading(float(h[temp_pin(s)]), ts)
        if self.model.needs_load:
            r["load_N"] = Reading(float(h["load-N"]), ts)
        valid = bool(h["probe-valid"])
        if valid and not self.probe_was_valid:  # a new probe reading: measured error (µm), taken now, once
            r["probe"] = Reading(float(h["probe-um"]), ts)
        self.probe_was_valid = valid
        return r

    def counts(self, value_um: float | None) -> int:
        """The s32 count for a compensation (µm), in the machine's units."""
        if value_um is None or not math.isfinite(value_um):
            return 0
        return int(round(value_um * 1e-3 / self.unit_mm / self.scale))

    def step(self, h, now_wall_s: float) -> Cycle:
        """One cycle: read ``h``'s input pins, decide, write its output pins."""
        ts = self.machine_time(h, now_wall_s)
        c = self.logic.cycle(self.readings(h, ts), now_wall_s)
        # LinuxCNC adds count *changes* x scale to the offset, and drops the changes made while the
        # machine is off, not homed, or enable is false: the offset can only follow the counts while
        # both pins say so, and it starts from 0 (counts 0, clear) every time they do
        on = not self.require_on or (bool(h["machine-on"]) and bool(h["all-homed"]))
        if not on:
            c = self.logic.dropped(c, Flags.MACHINE_OFF)
        h["eoffset-scale"] = self.scale
        h["eoffset-clear"] = not on
        h["eoffset-enable"] = on
        h["eoffset-counts"] = self.counts(c.value_um) if on else 0
        h["comp-um"] = c.value_um if c.value_um is not None else 0.0
        h["predicted-um"] = c.predicted_um if math.isfinite(c.predicted_um) else 0.0
        h["flags"] = int(c.flags)
        h["ok"] = on and not c.flags & (Flags.HELD | Flags.NOT_READY)
        h["machine-time-s"] = c.t_s if math.isfinite(c.t_s) else 0.0
        self.was_on = on
        return c

    # ------------------------------------------------------------------ loop ---
    def stop(self, *_: Any) -> None:
        self.stop_requested = True

    def run(self, h=None) -> dict:
        """Cycle on absolute deadlines until stopped (SIGTERM from ``halcmd unload``, Ctrl-C) or
        ``duration_s``; the summary is written beside the log however the loop ends."""
        h = self.component() if h is None else h
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self.stop)
        log = CycleLog(self.log_path, self.logic.names)
        durations, lates, starts, index = (Ring(STATS_CYCLES) for _ in range(4))
        counts: dict[str, int] = {}
        window: list[float] = []
        sched = Deadlines(self.period_s, time.monotonic(), duration_s=self.duration_s)
        next_status = time.monotonic() + self.status_every_s
        self._say(f"{self.name}: running {self.model.manifest.get('name')} every {1e3 * self.period_s:g} ms; "
                  f"pins {self.name}.*")  # fmt: skip
        ended = "unloaded"
        try:
            while not self.stop_requested:
                k, deadline = sched.k, sched.deadline
                time.sleep(sched.wait_s(time.monotonic()))
                begin = time.monotonic()
                c = self.step(h, begin)
                end = time.monotonic()
                cyc_ms, late_ms = 1e3 * (end - begin), 1e3 * (begin - deadline)
                for ring, v in zip((durations, lates, starts, index), (cyc_ms, late_ms, begin, k)):
                    ring.append(v)
                for f in Flags:
                    if f.value and c.flags & f.value:
                        counts[f.name] = counts.get(f.name, 0) + 1
                log.write(time.time(), k, c, late_ms, cyc_ms)
                window.append(cyc_ms)
                if end >= next_status:
                    self._say(status_line(k, c, window) + f"; counts {self.counts(c.value_um)}")
                    window.clear()
                    next_status = end + self.status_every_s
                over = sched.next(end)
                if over:
                    ended = over
                    break
        except KeyboardInterrupt:  # hal raises it when the component is asked to exit
            ended = "unloaded"
        finally:
            log.close()
            if sched.skipped:
                counts["skipped_deadlines"] = sched.skipped
            summary = {"component": self.name, "model": self.model.manifest.get("name"), "period_s": self.period_s,
                       "log": str(self.log_path), "ended": ended, "flags": counts,
                       **cycle_stats(durations.values(), lates.values(), index.values(), starts.values(), self.period_s)}  # fmt: skip
            write_text(self.log_path.with_suffix(".summary.json"), _json(summary), "compensator-summary")
            self._say(f"{self.name}: {summary.get('cycles', 0)} cycles, ended: {ended}")
        return summary

    def _say(self, line: str) -> None:
        if self.say is not None:
            self.say(line)


def _json(d: dict) -> str:
    import json

    return json.dumps(d, indent=2, default=float) + "\n"
