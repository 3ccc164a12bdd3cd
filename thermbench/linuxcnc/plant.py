"""``thermbench linuxcnc plant``: a simulated thermal plant for a LinuxCNC sim configuration.

A LinuxCNC simulator moves its axis for real (trajectory planner, servo loop, external
offsets) but has no heat. This userspace HAL component supplies it: the ball-screw
simulator of a benchmark machine (seed 000 §3, :func:`thermbench.sim.scenario.build_model`
with the benchmark's truth) driven by the axis's actual motion, read from HAL.

**The scaled clock.** Machine (thermal) time starts when the machine is first on (``machine-on``,
net ``motion.motion-enabled``) and runs ``time_scale`` times faster than the wall clock: with 120, one minute of LinuxCNC's motion is two hours of thermal history. The
motion is stretched in time: where the nut is, and for what fraction of the time, are the
axis's; the friction heat uses the axis's real speed (mm/min as LinuxCNC moves it). So a
program that reciprocates for a minute heats the screw as that duty cycle would for two
hours. The clock is published on ``time-s``; the compensator takes its machine time from
it (``time_source=pin``), as an OPC UA compensator takes it from source timestamps.

Each cycle (``period_s`` of the wall clock) the plant reads ``axis-pos`` and ``axis-vel``
(net ``joint.N.pos-fb`` and ``joint.N.vel-cmd``) and ``eoffset`` (``axis.L.eoffset``, the
offset LinuxCNC applies, for the scoring), appends them to the motion history, and every
``update_every_s`` of machine time re-runs the simulator over the whole history (causal:
the past does not change) and publishes the sensor temperatures (``temp.<sensor>``, the
machine's sensor names) at the newest step.

It logs, in ``out_dir``: ``process.csv``, the process log on the ``sample_s`` grid (the first
cycle past each grid point: axis, feed, the published temperatures, the applied offset), and
at the end, with the history complete, ``dataset/``: the run in the contract format, with a
virtual measuring cycle every ``reading_every_s`` (the thermal error of the screw at every
measuring target of the benchmark's protocol, a cold reference at 0 s), and
``closed_loop.json``: the thermal error at the tool (the axis position of each process
sample) before and after the offset LinuxCNC applied (:func:`tool_errors`).
"""

from __future__ import annotations

import json
import math
import signal
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd

from ..compensator.deadlines import Deadlines
from ..outputs import check_output_dir, output_dir
from .component import UNITS_MM, _choice, _positive, import_linuxcnc_module, temp_pin


_WORKER: dict = {}


def _worker_init(key: str) -> None:
    """The simulator's process (the plant's loop never waits for a re-run, nor for numba's compile)."""
    from ..bench import datasets
    from ..sim.scenario import _plain, build_model

    bcfg = _plain(datasets.benchmark_config(key))
    _WORKER["model"] = build_model(bcfg)
    _WORKER["ambient_C"] = float(bcfg["machine"].get("ambient_C", 20.0))
    _WORKER["sensors"] = dict(bcfg["machine"].get("sensors") or {})


def _worker_temps(motion: np.ndarray, probe: bool = False) -> dict[str, float]:
    """The sensor temperatures at the newest step of a run over ``motion`` (t, axis, feed rows);
    ``probe``: also the thermal error there (key ``PROBE_KEY``), what a probe would measure."""
    from ..sim.model import Motion

    hist = _WORKER["model"].run(Motion(motion[:, 0], motion[:, 1], motion[:, 2]), ambient_C=_WORKER["ambient_C"])
    return _readout(hist, _WORKER["sensors"], motion, probe)


#: the key of the probe's reading in a re-run's result
PROBE_KEY = "_probe_um"


def _readout(hist, sensors: Mapping[str, str], motion: np.ndarray, probe: bool) -> dict[str, float]:
    out = {s: float(hist.housing_C[loc][-1]) for s, loc in sensors.items()}
    if probe:  # the thermal error at the newest time, where the axis is then (the dataset's sign)
        out[PROBE_KEY] = float(np.asarray(hist.error_um(np.array([motion[-1, 0]]), np.array([motion[-1, 1]])))[0])
    return out


class ThermalPlant:
    """The plant; :meth:`step` is one cycle over a pin mapping, :meth:`finish` writes the results."""

    def __init__(self, cfg: Mapping[str, Any] | None = None) -> None:
        from ..bench import datasets
        from ..config import with_defaults
        from ..sim.scenario import _plain, _targets, build_model

        cfg = with_defaults("linuxcnc_plant", cfg or {})
        self.cfg = cfg
        self.name = str(cfg["name"])
        key = str(cfg["benchmark"])
        if key not in datasets.names():
            from ..compensator.settings import config_error

            raise config_error(f"config key 'benchmark': {key!r} is not a benchmark dataset; known: {datasets.names()}")
        bcfg = _plain(datasets.benchmark_config(key))
        self.machine_cfg = bcfg["machine"]
        self.model = build_model(bcfg)
        self.sensors: dict[str, str] = dict(self.machine_cfg.get("sensors") or {})
        self.ambient0_C = float(self.machine_cfg.get("ambient_C", 20.0))
        self.targets_mm = np.asarray(_targets(bcfg["protocol"]["measuring"]["targets_mm"]), dtype=float)
        self.time_scale = _positive(cfg, "time_scale")
        self.period_s = _positive(cfg, "period_s")
        self.sample_s = _positive(cfg, "sample_s")
        self.update_every_s = _positive(cfg, "update_every_s")
        self.reading_every_s = _positive(cfg, "reading_every_s")
        self.probe_every_s = None if cfg.get("probe_every_s") is None else _positive(cfg, "probe_every_s")
        self.next_probe = self.probe_every_s
        self.probe_high_until: float | None = None  # wall clock: probe-valid is held high a while (the reader polls)
        self.probes: list[tuple[float, float, float]] = []  # (machine s, axis mm, measured µm)
        self.unit_mm = UNITS_MM[_choice(cfg, "units", tuple(UNITS_MM))]
        self.run_id = str(cfg["run"])
        self.out_dir = Path(str(cfg["out_dir"]))
        self.force = bool(cfg["force"])
        check_output_dir(self.out_dir, "linuxcnc-plant", force=self.force, force_option="force=true")
        self.t0_wall: float | None = None
        self.motion: list[tuple[float, float, float]] = []  # (machine s, axis mm, |speed| mm/min), every cycle
        self.rows: list[dict] = []  # the process log on the sample grid
        self.temps_C = {s: self.ambient0_C for s in self.sensors}
        self.next_sample = 0.0
        self.next_update = self.update_every_s
        self.stop_requested = False
        self.pending = None  # the re-run under way in the simulator's process
        self.pending_at = None  # the newest (t, axis, feed) of its motion
        self.reruns = 0
        self.pool = None

    def start_worker(self) -> None:
        """The simulator's own process, warmed up (numba compiled) before the pins are ready."""
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        self.pool = ProcessPoolExecutor(1, mp_context=multiprocessing.get_context("fork"), initializer=_worker_init,
                                        initargs=(str(self.cfg["benchmark"]),))  # fmt: skip
        warm = np.array([[0.0, 0.0, 0.0], [3 * self.model.numerics.macro_dt_s, 1.0, 100.0]])
        self.pool.submit(_worker_temps, warm).result()

    # ------------------------------------------------------------------ pins ---
    def pins(self) -> list[tuple[str, str, str]]:
        ins = [("axis-pos", "float", "in"), ("axis-vel", "float", "in"), ("eoffset", "float", "in"), ("machine-on", "bit", "in"),
               ("finish", "bit", "in")]  # finish: write the results now (the sim's display sets it before LinuxCNC stops)
        outs = [("time-s", "float", "out"), *((temp_pin(s), "float", "out") for s in self.sensors)]
        if self.probe_every_s is not None:  # a simulated touch probe: the thermal error at the axis, every probe_every_s
            outs += [("probe-um", "float", "out"), ("probe-valid", "bit", "out")]
        return ins + outs

    def component(self):
        hal = import_linuxcnc_module("hal")
        if self.pool is None:
            self.start_worker()
        h = hal.component(self.name)
        for name, typ, d in self.pins():
            h.newpin(name, {"float": hal.HAL_FLOAT, "bit": hal.HAL_BIT}[typ], hal.HAL_IN if d == "in" else hal.HAL_OUT)
        for s, v in self.temps_C.items():
            h[temp_pin(s)] = v
        h.ready()
        return h

    # ----------------------------------------------------------------- cycle ---
    def history(self, upto: int | None = None):
        """The simulator run over the motion so far (seed 000 §3.1)."""
        from ..sim.model import Motion

        m = np.asarray(self.motion[:upto] if upto else self.motion, dtype=float)
        return self.model.run(Motion(m[:, 0], m[:, 1], m[:, 2]), ambient_C=self.ambient0_C)

    def step(self, h, now_wall_s: float) -> float:
        if self.t0_wall is None:  # the clock starts when the machine is first on: the compensator is loaded by
            if not h["machine-on"]:  # then, so its first sample is the run's first, as in the dataset written at the end
                h["time-s"] = 0.0
                return 0.0
            self.t0_wall = now_wall_s
        t = self.time_scale * (now_wall_s - self.t0_wall)
        x = float(h["axis-pos"]) * self.unit_mm
        feed = abs(float(h["axis-vel"])) * self.unit_mm * 60.0
        if not self.motion or t > self.motion[-1][0]:
            self.motion.append((t, x, feed))
        if self.pending is not None and self.pending.done():
            self._took(self.pending.result(), h, now_wall_s)
            self.pending = None
        if self.probe_high_until is not None and now_wall_s >= self.probe_high_until:
            h["probe-valid"] = False
            self.probe_high_until = None
        if t >= self.next_update and len(self.motion) > 1 and self.pending is None:
            probe = self.next_probe is not None and t >= self.next_probe
            motion = np.asarray(self.motion, dtype=float)
            if self.pool is None:  # no worker (a test stepping the plant by hand): re-run here
                self._took(_readout(self.history(), self.sensors, motion, probe), h, now_wall_s, motion[-1])
            else:
                self.pending = self.pool.submit(_worker_temps, motion, probe)
                self.pending_at = motion[-1]
            if probe:
                self.next_probe += self.probe_every_s * max(1, math.floor((t - self.next_probe) / self.probe_every_s) + 1)
            self.next_update += self.update_every_s * max(1, math.floor((t - self.next_update) / self.update_every_s) + 1)
        for s, v in self.temps_C.items():
            h[temp_pin(s)] = v
        h["time-s"] = t
        if t >= self.next_sample:
            # every grid point passed since the last cycle gets this cycle's values (zero-order hold:
            # a cycle late by more than a sample period leaves no hole in the process log)
            k0 = round(self.next_sample / self.sample_s)
            k = math.floor(t / self.sample_s + 1e-9)
            row = {"axis_mm": x, "feed_mm_min": feed, **{f"{s}_C": v for s, v in self.temps_C.items()},
                   "eoffset_um": float(h["eoffset"]) * self.unit_mm * 1e3}  # fmt: skip
            self.rows += [{"t_s": j * self.sample_s, **row} for j in range(k0 if self.rows else k, k + 1)]
            self.next_sample = (k + 1) * self.sample_s
        return t

    def _took(self, result: dict, h, now_wall_s: float, at=None) -> None:
        """A re-run's result: the temperatures, and a probe's reading (held on probe-um, probe-valid
        high for 0.1 s of wall clock: a new reading per rising edge)."""
        at = self.pending_at if at is None else at
        probe = result.pop(PROBE_KEY, None)
        self.temps_C = result
        self.reruns += 1
        if probe is not None:
            self.probes.append((float(at[0]), float(at[1]), probe))
            h["probe-um"] = probe
            h["probe-valid"] = True
            self.probe_high_until = now_wall_s + 0.1

    def stop(self, *_: Any) -> None:
        self.stop_requested = True

    def run(self, h=None) -> dict:
        """The loop, until stopped (SIGTERM, SIGINT) or asked to finish (pin ``finish``): then the
        results. LinuxCNC's shutdown gives a component 2 s after SIGTERM, too little for the
        results of a long run: the sim's display sets ``finish`` first and waits for them."""
        h = self.component() if h is None else h
        for sig in (signal.SIGTERM, signal.SIGINT):
            signal.signal(sig, self.stop)
        sched = Deadlines(self.period_s, time.monotonic())
        try:
            while not self.stop_requested and not h["finish"]:
                time.sleep(sched.wait_s(time.monotonic()))
                self.step(h, time.monotonic())
                sched.next(time.monotonic())
        except KeyboardInterrupt:
            pass
        finally:
            if self.pool is not None:
                self.pool.shutdown(wait=False, cancel_futures=True)
        figures = self.finish()
        while not self.stop_requested:  # finished on request: a HAL component stays until LinuxCNC unloads it
            time.sleep(0.05)
        return figures

    # ---------------------------------------------------------------- results ---
    def finish(self) -> dict:
        """The dataset, the process log and the closed-loop figures, written atomically."""
        from ..data.io import Dataset, save_dataset
        from ..data.schema import FORMAT, Metadata

        if len(self.rows) < 2:
            return {"samples": len(self.rows)}
        hist = self.history()
        proc = pd.DataFrame(self.rows)
        t_end = float(self.motion[-1][0])
        t_read = np.arange(0.0, t_end - self.sample_s + 1e-9, self.reading_every_s)
        xs = proc["axis_mm"].to_numpy()
        tg = self.targets_mm[(self.targets_mm >= xs.min()) & (self.targets_mm <= xs.max())]  # the travel the run used
        errs = [pd.DataFrame({"run_id": self.run_id, "t_s": tr + 1e-6 * np.arange(tg.size), "target_mm": tg,
                              "error_um": hist.error_um(np.full(tg.size, tr), tg)})
                for tr in t_read]  # fmt: skip
        errors = pd.concat(errs, ignore_index=True)
        m = np.asarray(self.motion)
        moving = m[:, 2] > 0
        cond = {"start_mm": float(m[moving, 1].min() if moving.any() else m[:, 1].min()),
                "end_mm": float(m[moving, 1].max() if moving.any() else m[:, 1].max()),
                "feed_mm_min": float(np.percentile(m[moving, 2], 90)) if moving.any() else 0.0}  # fmt: skip
        cond["stroke_mm"] = cond["end_mm"] - cond["start_mm"]
        screw = asdict(self.model.screw)
        if self.machine_cfg.get("declare_fixed_end", True):
            screw["fixed_end_axis_mm"] = self.model.core.pf_m * 1000.0
        meta = Metadata.model_validate({
            "format": FORMAT, "machine": {"name": self.machine_cfg["name"], "axis": self.machine_cfg.get("axis", "X")},
            "screw": screw, "material": asdict(self.model.material), "sensors": self.sensors,
            "runs": {self.run_id: {"condition": cond, "notes": f"LinuxCNC run on a {self.time_scale:g}x thermal clock"}}})  # fmt: skip
        process = proc.drop(columns=["eoffset_um"]).assign(run_id=self.run_id)
        process = process[["run_id", "t_s", "axis_mm", "feed_mm_min", *[f"{s}_C" for s in self.sensors]]]
        ds = Dataset(meta, process, errors)
        figures = tool_errors(proc, hist)
        figures.update(time_scale=self.time_scale, machine_s=t_end, samples=len(proc), readings=len(t_read),
                       probes=len(self.probes))  # fmt: skip
        with output_dir(self.out_dir, "linuxcnc-plant", force=self.force, force_option="force=true") as stage:
            proc.assign(thermal_um=figures.pop("thermal_um"), after_um=figures.pop("after_um")).to_csv(stage / "process.csv", index=False)
            save_dataset(ds, stage / "dataset")
            (stage / "closed_loop.json").write_text(json.dumps(figures, indent=2) + "\n")
            if self.probes:  # what the simulated probe read (the thermal error, the model's sign)
                pd.DataFrame(self.probes, columns=["t_s", "axis_mm", "measured_um"]).to_csv(stage / "probes.csv", index=False)
        return figures


def tool_errors(proc: pd.DataFrame, hist) -> dict:
    """The screw's thermal error at the tool (each process sample's time and axis position)
    before compensation, and after it: thermal error + the offset LinuxCNC applied (an
    external offset moves the axis by its value, so it adds to the positioning error)."""
    thermal = np.asarray(hist.error_um(proc["t_s"].to_numpy(), proc["axis_mm"].to_numpy()), dtype=float)
    after = thermal + proc["eoffset_um"].to_numpy()
    return {"before_max_abs_um": float(np.max(np.abs(thermal))), "after_max_abs_um": float(np.max(np.abs(after))),
            "before_rms_um": float(np.sqrt(np.mean(thermal**2))), "after_rms_um": float(np.sqrt(np.mean(after**2))),
            "thermal_um": thermal, "after_um": after}  # fmt: skip
