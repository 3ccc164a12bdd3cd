"""From a (Hydra) simulate config to a dataset in the contract format.

``simulate_dataset(cfg)`` is the plain function behind ``thermbench simulate``:
machine + protocol + instruments (+ effects, numerics, seed) -> :class:`Dataset`.
"""

from __future__ import annotations

import copy
import math
from dataclasses import asdict, replace
from typing import Any, Sequence

import numpy as np
import pandas as pd
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from ..config import ConfigError
from ..data.dataset import Dataset
from ..data.schema import FORMAT, Metadata
from .duty import Measuring, Phase, Trajectory, build_run, random_phases
from .effects import Effect
from .history import ThermalHistory
from .instruments import FieldValueError, GeometricError, Interferometer, SensorSpec
from .model import ScrewThermalModel
from .parts import CoreParams, Material, Numerics, Screw, housings_from_config
from .registry import effects_from_config


def _plain(cfg: Any) -> Any:
    if isinstance(cfg, DictConfig):
        return OmegaConf.to_container(cfg, resolve=True)
    return copy.deepcopy(cfg)


def _targets(spec: Any) -> tuple[float, ...]:
    if isinstance(spec, dict):
        start, stop, step = float(spec["start"]), float(spec["stop"]), float(spec["step"])
        return tuple(float(x) for x in np.arange(start, stop + step / 2, step))
    return tuple(float(x) for x in spec)


def _build(spec: Any, cls: type, key: str) -> Any:
    """Instantiate from ``_target_`` when present, else from the fields; name the key on error."""
    try:
        if isinstance(spec, dict) and "_target_" in spec:
            return instantiate(spec, _convert_="all")
        return cls(**dict(spec or {}))
    except Exception as exc:
        why = exc.__cause__ if exc.__cause__ is not None else exc  # Hydra wraps the class's own message
        if isinstance(why, FieldValueError):  # the class names the field: name the whole key
            raise ConfigError(f"config key '{key}.{why.field}': {why.problem}") from None
        raise ConfigError(f"config key {key!r}: {why}") from None


def build_model(cfg: Any, extra_effects: Sequence[Effect] = ()) -> ScrewThermalModel:
    """The truth model of a simulate config: machine physics + enabled effects (+ ``extra_effects``:
    effect objects outside the canonical library, e.g. the discrepancy tests' out-of-library physics)."""
    c = _plain(cfg)
    m = c["machine"]
    clean = bool(c.get("clean", False))
    effects_cfg: dict = {}
    if not clean:
        effects_cfg.update(m.get("effects") or {})
        effects_cfg.update(c.get("effects") or {})
    return ScrewThermalModel(
        screw=_build(m["screw"], Screw, "machine.screw"),
        material=_build(m["material"], Material, "machine.material"),
        core=_build(m["core"], CoreParams, "machine.core"),
        effects=[*effects_from_config(effects_cfg), *([] if clean else extra_effects)],
        numerics=_build(c.get("numerics") or {}, Numerics, "numerics"),
        housings=housings_from_config(m.get("housings")),
    )


def _run_phases(run_id: str, run: dict) -> list[Phase]:
    cond = run.get("condition") or {}
    base = {k: cond[k] for k in ("start_mm", "end_mm", "feed_mm_min", "load_N") if k in cond}
    phases = []
    for i, ph in enumerate(run.get("phases") or []):
        spec = {**base, **ph}
        try:
            if spec.get("kind") == "stop":
                spec = {"kind": "stop", "duration_s": spec["duration_s"]}
            phases.append(Phase(**spec))
        except KeyError as exc:
            raise ConfigError(f"config key 'protocol.runs.{run_id}.phases[{i}]': a stop needs {exc}") from None
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"config key 'protocol.runs.{run_id}.phases[{i}]': {exc}") from None
    return phases


def _condition(phases: list[Phase], run: dict) -> dict:
    cond = dict(run.get("condition") or {})
    if not {"start_mm", "end_mm", "feed_mm_min"} <= set(cond):
        moves = [p for p in phases if p.kind == "move"]
        main = max(moves, key=lambda p: p.duration_s) if moves else None
        cond = {
            "start_mm": main.start_mm if main else 0.0,
            "end_mm": main.end_mm if main else 0.0,
            "feed_mm_min": main.feed_mm_min if main else 0.0,
        }
    cond.pop("load_N", None)
    lo, hi = sorted((float(cond["start_mm"]), float(cond["end_mm"])))
    return {"stroke_mm": hi - lo, "start_mm": lo, "end_mm": hi, "feed_mm_min": float(cond["feed_mm_min"])}


def protocol_runs(cfg: Any, rng: np.random.Generator) -> dict[str, dict]:
    """Expand the protocol into runs: id -> {phases, condition, notes}."""
    c = _plain(cfg)
    proto = c["protocol"]
    travel = tuple(float(x) for x in c["machine"]["travel_mm"])
    runs: dict[str, dict] = {}
    for run_id, run in (proto.get("runs") or {}).items():
        phases = _run_phases(str(run_id), run)
        runs[str(run_id)] = {
            "phases": phases,
            "condition": _condition(phases, run),
            "notes": run.get("notes"),
            "measure_every_s": run.get("measure_every_s"),
        }
    rnd = proto.get("random_runs") or {}
    for i in range(int(rnd.get("count", 0))):
        phases = random_phases(
            rng,
            n_phases=int(rnd.get("n_phases", 10)),
            travel_mm=travel,
            feed_mm_min=tuple(rnd.get("feed_mm_min", (500, 6000))),
            stroke_mm=tuple(rnd.get("stroke_mm", (20, travel[1] - travel[0]))),
            move_s=tuple(rnd.get("move_s", (300, 1800))),
            stop_s=tuple(rnd.get("stop_s", (300, 1200))),
            p_stop=float(rnd.get("p_stop", 0.3)),
        )
        runs[f"random_{i + 1:02d}"] = {
            "phases": phases,
            "condition": _condition(phases, {}),
            "notes": "random duty sequence (condition = its longest move phase)",
        }
    if not runs:
        raise ConfigError("config key 'protocol.runs': the protocol defines no runs")
    return runs


def simulate_run(model: ScrewThermalModel, traj: Trajectory, ambient_C: float) -> ThermalHistory:
    """Integrate the model over a run's trajectory at the model's fine step."""
    t = np.arange(0.0, traj.now, model.numerics.dt_s)
    return model.run(traj.sample(t), ambient_C=ambient_C, duration_s=traj.now)


def simulate_dataset(cfg: Any, runs_only: Sequence[str] | None = None,
                     extra_effects: Sequence[Effect] = ()) -> tuple[Dataset, dict]:  # fmt: skip
    """Simulate every run of the protocol on the machine; return the dataset and a summary.

    ``runs_only``: simulate just these runs (the same numbers as in the full dataset: each
    run draws from its own seeded stream); the summary then also holds each run's
    :class:`ThermalHistory` under ``histories`` and the geometric error under ``geometric``
    (what ``thermbench sim-cnc`` needs for the error at any position and time)."""
    c = _plain(cfg)
    clean = bool(c.get("clean", False))
    seed = c.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:  # numpy's rngs take seeds >= 0
        raise ConfigError(f"config key 'seed': expected an integer >= 0, got {seed!r}")
    seed = int(seed)
    m = c["machine"]
    model = build_model(c, extra_effects)
    inst = c.get("instruments") or {}
    sensor = SensorSpec(noise_C=0, quantum_C=0) if clean else _build(inst.get("sensor"), SensorSpec, "instruments.sensor")
    geometric = GeometricError() if clean else _build(m.get("geometric"), GeometricError, "machine.geometric")
    ifm_spec = dict(inst.get("interferometer") or {})
    ifm_spec.pop("_target_", None)
    try:
        ifm = Interferometer(noise_um=0.0 if clean else ifm_spec.get("noise_um", 0.2), geometric=geometric)
    except FieldValueError as exc:
        raise ConfigError(f"config key 'instruments.interferometer.{exc.field}': {exc.problem}") from None
    rate_hz = inst.get("process_rate_hz", 1.0)
    if isinstance(rate_hz, bool) or not isinstance(rate_hz, (int, float)) or not 1.0 <= rate_hz < math.inf:
        raise ConfigError(f"config key 'instruments.process_rate_hz': must be >= 1 (contract), got {rate_hz!r}")
    rate_hz = float(rate_hz)
    meas_cfg = dict(c["protocol"]["measuring"])
    meas_cfg["targets_mm"] = _targets(meas_cfg["targets_mm"])
    meas = _build(meas_cfg, Measuring, "protocol.measuring")
    sensors: dict[str, str] = dict(m.get("sensors") or {})
    known_locations = sorted({*model.housings, "ambient"})  # what ThermalHistory.housing_C will hold
    for name, loc in sensors.items():  # checked before any run is simulated
        if loc not in known_locations:
            raise ConfigError(f"config key 'machine.sensors.{name}': unknown location {loc!r}; known: {known_locations}")
    ambient0 = float(m.get("ambient_C", 20.0))

    root_rng = np.random.default_rng(seed)
    runs = protocol_runs(c, root_rng)
    if runs_only is not None:
        unknown = sorted(set(runs_only) - set(runs))
        if unknown:
            raise ConfigError(f"config key 'run': run(s) {unknown} are not in protocol {c['protocol'].get('name')!r}; "
                              f"its runs: {list(runs)}")  # fmt: skip
    uses_load = any(p.load_N for r in runs.values() for p in r["phases"]) or model.effect("load_dependent_heat")
    process_frames, error_frames, summary_runs, histories = [], [], {}, {}
    for index, (run_id, run) in enumerate(runs.items()):
        if runs_only is not None and run_id not in runs_only:
            continue
        rng = np.random.default_rng([seed, index + 1])
        run_meas = replace(meas, every_s=float(run["measure_every_s"])) if run.get("measure_every_s") else meas
        traj = build_run(run["phases"], run_meas, start_mm=meas.targets_mm[0])
        hist = simulate_run(model, traj, ambient0)
        tp = np.arange(0.0, traj.now + 1e-9, 1.0 / rate_hz)
        mot = traj.sample(tp)
        pdf = {"run_id": run_id, "t_s": tp, "axis_mm": mot.axis_mm, "feed_mm_min": mot.feed_mm_min}
        for name, loc in sensors.items():
            true_C = np.interp(tp, hist.t_s, hist.housing_C[loc])
            pdf[f"{name}_C"] = sensor.read(true_C, tp, rng)
        if uses_load:
            pdf["load_N"] = mot.load_N
        process_frames.append(pd.DataFrame(pdf))
        rt = np.array([r[0] for r in traj.readings])
        rx = np.array([r[1] for r in traj.readings])
        thermal = hist.error_um(rt, rx)
        error_frames.append(
            pd.DataFrame({"run_id": run_id, "t_s": rt, "target_mm": rx, "error_um": ifm.read(thermal, rx, rng)})
        )
        histories[run_id] = hist
        summary_runs[run_id] = {
            "duration_h": traj.now / 3600.0,
            "max_thermal_error_um": float(np.max(np.abs(hist.error_field_um(np.asarray(meas.targets_mm))))),
            "condition": run["condition"],
        }

    screw = asdict(model.screw)
    if m.get("declare_fixed_end", True):
        screw["fixed_end_axis_mm"] = model.core.pf_m * 1000.0
    meta = Metadata.model_validate(
        {
            "format": FORMAT,
            "machine": {"name": m["name"], "axis": m.get("axis", "X")},
            "screw": screw,
            "material": asdict(model.material),
            "sensors": sensors,
            "runs": {
                rid: {"condition": r["condition"], **({"notes": r["notes"]} if r["notes"] else {})}
                for rid, r in runs.items()
                if runs_only is None or rid in runs_only
            },
            "simulation": {
                "seed": seed,
                "clean": clean,
                # the canonical effects only: an extra effect object is no config a reader could rebuild
                "effects": {e.id: e.params() for e in model.effects if not any(e is x for x in extra_effects)},
                "core": model.core.as_dict(),
                "numerics": asdict(model.numerics),
                "protocol": c["protocol"].get("name"),
            },
        }
    )
    ds = Dataset(meta, pd.concat(process_frames, ignore_index=True), pd.concat(error_frames, ignore_index=True))
    summary = {"machine": m["name"], "runs": summary_runs}
    if runs_only is not None:
        summary.update(histories=histories, geometric=geometric)
    return ds, summary
