"""An exported model directory: compact model files, a JSON manifest, ONNX for the nets.

``export_model(model, out_dir, ...)`` writes, atomically (the directory appears
whole or not at all)::

    out_dir/manifest.json      inputs in order with units, preprocessing, training
                               dataset hash and runs, metrics, MLflow run id, files
                               (bytes, CRC-32, kind, dims), parity and footprint
    out_dir/model.tbm          one model (any family), or for a per-condition bank
    out_dir/classifier.tbm     seed 002 eq. 15-19 with the bank's motion window
    out_dir/member_NN.tbm      the condition models, in the classifier's class order
    out_dir/model.reduced.tbm  PSO-LSSVM with a reduced set of centres (when asked)
    out_dir/model.onnx         MLP/GRU thermal part, float32, checked with onnxruntime

and, when a dataset is given, checks before writing that the C runtime loads every
file and reproduces the Python model on the held-out runs within ``parity_tol_um``
(:mod:`.parity`), and that the files fit their target (:mod:`.budget`). Reading an export
directory back: :mod:`.directory`; the ONNX file: :mod:`.onnxfile`.
"""

from __future__ import annotations

import datetime as _dt
import json
import math
import sys
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

import thermbench

from .. import __version__
from ..outputs import output_dir
from ..data.reference import frame_text
from ..models.bank import ConditionBank
from ..models.base import ThermalErrorModel
from . import budget, directory, fileformat, onnxfile
from .budget import _check_target, _measure_on_target
from .encoding import Encoded, ExportError, encode, encode_classifier
from .parity import _verify
from .reduce import reduced_lssvm
from .samples import FILL_STEP_S, MAX_GAP_S, runtime_log


@dataclass
class ExportOptions:
    """What to write besides the model file. ``lssvm_reduced_size``: also write a reduced-set
    LSSVM with that many centres; ``verify``: run the C runtime (double and single precision) on
    the dataset's held-out runs and fail when the build ``target`` runs differs from Python by
    more than ``parity_tol_um``; ``onnx``: ONNX for the neural families; ``target``: the
    compensator the files are for (:data:`.budget.TARGETS`); ``interval_level``: the conformal interval of
    that level calibrated over the training runs (:func:`interval_calibration`; the compensator's
    ``extrapolation: limit`` needs it)."""

    lssvm_reduced_size: int | None = None
    seed: int = 0
    onnx: bool = True
    verify: bool = True
    parity_tol_um: float = 0.01
    target: str = "host"
    interval_level: float | None = None  # calibrate the model's conformal interval (manifest 'interval')
    interval_kappa: float = 1.0

    @property
    def precision(self) -> str:
        """The C runtime build of the target: "double", or "float" (``-DTB_SINGLE``)."""
        return budget.TARGETS[self.target]["precision"]


# ----------------------------------------------------------------- inputs ---
def model_inputs(model: ThermalErrorModel) -> list[str]:
    """The temperature sensors the exported files read, in channel order."""
    if isinstance(model, ConditionBank):
        out: list[str] = []
        for lab in [str(c) for c in model.classifier_.classes_]:
            out += [s for s in model.models_[lab].required_inputs().sensors if s not in out]
        return out
    return list(model.required_inputs().sensors)


#: the process columns tb_sample carries itself (tb_runtime.h)
SAMPLE_COLUMNS = ("t_s", "axis_mm", "feed_mm_min", "load_N")


def operating_inputs(model: ThermalErrorModel) -> list[str]:
    """The operating inputs the exported files read as input channels after the temperatures
    (``tb_sample.temps_C[len(temperatures) + i]``, manifest ``operating``): the process columns a
    model reads that tb_sample has no field for, e.g. the spindle_rpm of a lumped network."""
    return [c for c in model.required_inputs().operating if c not in SAMPLE_COLUMNS]


def sample_period_s(ds) -> float:
    """The process log's sample period (median step; the contract logs at >= 1 Hz)."""
    dt = ds.process.groupby("run_id", sort=False)["t_s"].diff().dropna()
    return float(np.median(dt)) if len(dt) else 1.0


def _filters_json(enc: Encoded, sensor: str) -> list[dict]:
    """The preprocessing chain of one sensor, from the encoded sensor block."""
    from .encoding import FSTEP_VALS, SENSOR_VALS

    i = enc.sensors.index(sensor)
    S = len(enc.sensors)
    at = 1 + S + SENSOR_VALS * i
    p = enc.payload
    out = []
    for k in range(int(p[at])):
        q = at + 1 + FSTEP_VALS * k
        typ, a, b = p[q], p[q + 1] + p[q + 2], p[q + 3] + p[q + 4]
        if typ == 1:
            out.append({"filter": "limit", "limit_C": a, "max_hold": int(b) or None, "ref": "seed 002 §2.3.1 eq. 1"})
        else:
            out.append({"filter": "kalman", "R": a, "Q": b, "ref": "seed 002 §2.3.1 eq. 2-3"})
    return out


# ----------------------------------------------------------------- export ---
def _file_entry(path: Path, enc: Encoded) -> dict:
    data = path.read_bytes()
    return {"file": path.name, "bytes": len(data), "crc32": f"{zlib.crc32(data[:-4]) & 0xFFFFFFFF:08x}",
            "kind": enc.kind.name, "dims": list(enc.dims)}  # fmt: skip


def export_model(model: ThermalErrorModel, out_dir: Path, name: str, ds=None, heldout: Sequence[str] = (),
                 source: dict | None = None, options: ExportOptions | None = None, force: bool = False) -> dict:  # fmt: skip
    """Write the export directory of one fitted model (see the module docstring); returns the manifest."""
    from ..models.lssvm import PSOLSSVM
    from ..models.physics import PhysicsModel

    neural = sys.modules.get("thermbench.models.neural")  # not imported: the model is not a neural one
    neural_classes = (neural.MLPModel, neural.GRUModel) if neural is not None else ()
    opts = options or ExportOptions()
    if not isinstance(model, ThermalErrorModel) or not hasattr(model, "train_runs_"):
        raise ExportError(f"{name}: expected a fitted thermbench model, got {type(model).__name__}")
    period = sample_period_s(ds) if ds is not None else 1.0
    temps = model_inputs(model)
    ops = operating_inputs(model)
    channels = {s: i for i, s in enumerate([*temps, *ops])}
    out_dir = Path(out_dir)
    source = dict(source or {})
    heldout = [r for r in heldout if ds is not None and r in ds.run_ids]
    period_note = "median step of the dataset's process log" if ds is not None else "assumed (no dataset given)"
    man: dict[str, Any] = {"format": directory.FORMAT, "name": name,
                           "family": f"{type(model).__module__}.{type(model).__name__}",
                           "thermbench_version": __version__,
                           "created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")}  # fmt: skip
    with output_dir(out_dir, "model-export", force=force) as tmp:
        encs: dict[str, Encoded] = {}
        models_py: dict[str, ThermalErrorModel] = {}
        if isinstance(model, ConditionBank):
            labels = [str(c) for c in model.classifier_.classes_]
            enc = encode_classifier(model, period, f"{name}: classifier")
            fileformat.write(tmp / "classifier.tbm", enc.kind, enc.dims, enc.payload)
            members = []
            for i, lab in enumerate(labels):
                e = encode(model.models_[lab], channels, period, f"{name}: condition {lab!r}")
                fname = f"member_{i:02d}.tbm"
                fileformat.write(tmp / fname, e.kind, e.dims, e.payload)
                encs[fname] = e
                members.append({"label": lab, "file": fname, "train_runs": list(model.models_[lab].train_runs_),
                                "family": type(model.models_[lab]).__name__, **_file_entry(tmp / fname, e)})  # fmt: skip
            man["kind"] = "bank"
            man["bank"] = {"classifier": "classifier.tbm", "classifier_file": _file_entry(tmp / "classifier.tbm", enc),
                           "window_s": float(model.window_s), "step_s": float(model.step_s),
                           "min_moving_s": float(model.min_moving_s), "members": members,
                           "ref": "seed 002 §2.4-2.5: the classifier picks the condition model at run time"}  # fmt: skip
            man["files"] = {}
            models_py["bank"] = model
        else:
            e = encode(model, channels, period, name)
            fileformat.write(tmp / "model.tbm", e.kind, e.dims, e.payload)
            encs["model"] = e
            man["kind"] = e.kind.name
            man["files"] = {"model": _file_entry(tmp / "model.tbm", e)}
            models_py["model"] = model
            if isinstance(model, PSOLSSVM) and opts.lssvm_reduced_size:
                red = reduced_lssvm(model, int(opts.lssvm_reduced_size), opts.seed)
                er = encode(red, channels, period, f"{name} (reduced)")
                fileformat.write(tmp / "model.reduced.tbm", er.kind, er.dims, er.payload)
                man["files"]["reduced"] = _file_entry(tmp / "model.reduced.tbm", er)
                man["files"]["reduced"]["support_vectors"] = int(red.n_support_)
                man["files"]["reduced"]["from_support_vectors"] = int(red.reduced_from_)
                models_py["reduced"] = red
            if isinstance(model, PhysicsModel):
                num = model.model_.numerics
                man["physics"] = {"dx_m": num.dx_m, "dt_s": num.dt_s, "macro_dt_s": num.macro_dt_s,
                                  "n_nodes": model.model_.geom.n_nodes, "effects": [e.id for e in model.model_.effects],
                                  "params": {k: float(v) for k, v in model.params_.items()},
                                  "ref": "seed 000 §3.1-3.2, §4.1; compensation table §4.3"}  # fmt: skip
            if opts.onnx and isinstance(model, neural_classes):
                man["onnx"] = onnxfile.write_onnx(model, tmp / "model.onnx", ds, heldout)
        man["needs_load"] = any(e.needs_load for e in encs.values())
        man["target"] = {"name": opts.target, **budget.TARGETS[opts.target]}  # what the export is for (checked below)
        man["sample_period_s"] = period
        man["sample_period_from"] = period_note
        man["temperatures"] = temps
        man["operating"] = ops
        man["inputs"] = _inputs_json(ds, temps, man["needs_load"], man["kind"] == "bank", ops)
        per_file = {f: {s: _filters_json(e, s) for s in e.sensors} for f, e in encs.items()}
        for f, e in list(encs.items()):  # an ensemble's members each read their sensors through their own filters
            for i, me in enumerate(e.notes.get("members", [])):
                per_file[f"{f} member {i}"] = {s: _filters_json(me, s) for s in me.sensors}
        man["preprocessing"] = {}
        for s in temps:
            chains = [pf[s] for pf in per_file.values() if s in pf]
            man["preprocessing"][s] = chains[0] if all(c == chains[0] for c in chains) else "per member (bank.members[].preprocessing)"
        if man["kind"] == "bank":
            for mem in man["bank"]["members"]:
                mem["preprocessing"] = per_file[mem["file"]]
        man["delta_T"] = "rise above the first filtered sample of the run (seed 002 eq. 10)"
        man["outputs"] = {"thermal_um": "thermal part of the positioning error", "total_um":
                          "geometric + thermal positioning error (measured - commanded); compensation = -total_um"}  # fmt: skip
        man["training"] = {"runs": list(model.train_runs_), **({"dataset": str(ds.path), "dataset_hash": ds.content_hash(),
                                                                "machine": ds.metadata.machine.model_dump(exclude_none=True),
                                                                "frame": frame_text(ds.metadata)}
                           if ds is not None else {}), **({"channel": ds.channel} if getattr(ds, "channel", None) else {}),
                           **source.pop("training", {})}  # fmt: skip
        if ds is not None:  # what the model was fitted on: the guard's envelope (thermbench/bench/intervals.py)
            from ..bench.intervals import RATE_WINDOW_S, Envelope

            from .guard import ENVELOPE_FILE, write_envelope

            env = Envelope.fit(ds, list(model.train_runs_), temps, ops)
            man["envelope"] = {**env.to_dict(), "rate_tau_s": RATE_WINDOW_S, "file": ENVELOPE_FILE,
                               "bytes": write_envelope(tmp / ENVELOPE_FILE, env, RATE_WINDOW_S),
                               "note": "rises above the run's first sample (K), high-pass rates (K/h), operating values; "
                                       "the file: the C runtime's guard (tb_guard_open)"}  # fmt: skip
            from ..bench.faults import Bounds, SensorLimits

            try:
                bounds = Bounds.fit(ds, list(model.train_runs_))
                bound = {"max_um": bounds.max_um, "rate_um_s": bounds.rate_um_s if math.isfinite(bounds.rate_um_s) else None}
            except ValueError:  # no thermal error in the training runs to bound a correction by
                bound = {"max_um": None, "rate_um_s": None}
            from .faultfile import FAULTS_FILE, write_faults

            limits = SensorLimits.fit(ds, list(model.train_runs_), temps) if temps else None
            man["faults"] = {"limits": limits.to_dict() if limits is not None else None, "bounds": bound,
                             "file": FAULTS_FILE,
                             "bytes": write_faults(tmp / FAULTS_FILE, limits, bounds if bound["max_um"] is not None else None),
                             "note": "each temperature checked per sample against the training runs (open, range, rate, "
                                     "stuck, the others' prediction: thermbench/bench/faults.py); |compensation| <= max_um, "
                                     "|its change| <= rate_um_s per second; the file: the C runtime's checks (tb_faults_open)"}  # fmt: skip
            if opts.interval_level is not None:
                man["interval"] = interval_calibration(model, ds, list(model.train_runs_), temps, ops, opts.interval_level,
                                                       opts.interval_kappa, name)  # fmt: skip
        man["metrics"] = source.pop("metrics", {})
        man["mlflow_run_id"] = source.pop("mlflow_run_id", None)
        man["source"] = source
        man["footprint"] = budget.footprint(tmp, man)
        if budget.TARGETS[opts.target]["budget"]:
            man["target"]["footprint"] = _check_target(tmp, man, opts.target, name)
        if opts.verify and ds is not None:
            # parity on held-out runs; when every run trained the model, on those (parity, not accuracy)
            runs = heldout or list(model.train_runs_)
            # a log sampled slower than the runtime takes (a lab's logger), filled in as the compensator would
            # sample it, for any sampling the files take (a period-bound kind keeps the log: refused in one line)
            log, widest = runtime_log(ds, runs) if all(e.period_s == 0 for e in encs.values()) else (ds, 0.0)
            man["parity"] = _verify(tmp, man, models_py, log, runs, opts.parity_tol_um, name, opts.precision)
            man["parity"]["runs_are_training_runs"] = not heldout
            if log is not ds:
                man["parity"]["log"] = (f"the runs' logs are up to {widest:g} s apart, over the C runtime's {MAX_GAP_S:g} s: "
                                        f"replayed with samples inserted at most {FILL_STEP_S:g} s apart (linear "
                                        "between the logged ones), through the Python model and the C runtime alike")  # fmt: skip
            if opts.target == "cortex-m4f":
                man["target"]["measured"] = _measure_on_target(tmp, man, log, runs, name)
        (tmp / directory.MANIFEST).write_text(json.dumps(man, indent=2, allow_nan=False) + "\n", encoding="utf-8")
    return man


def interval_calibration(model: ThermalErrorModel, ds, runs: Sequence[str], sensors: Sequence[str],
                         operating: Sequence[str], level: float, kappa: float, name: str = "model") -> dict:
    """The split-conformal interval of a model (:mod:`thermbench.bench.intervals`) from its training runs,
    each left out once: a clone fitted on the others predicts it, and its residuals, normalised
    by their distance to the others' envelope, are the calibration scores. ``q_um``: the interval's
    half-width inside the envelope (``q * (1 + kappa * distance)`` outside)."""
    from sklearn.base import clone

    from ..bench.intervals import Envelope, conformal_quantile, interval_scores

    runs = list(runs)
    if len(runs) < 2:
        raise ExportError(f"{name}: export.interval_level needs a model fitted on >= 2 runs (each left out once); "
                          f"it was fitted on {runs}")  # fmt: skip
    scores = []
    for r in runs:
        others = [o for o in runs if o != r]
        er = ds.errors_run(r)
        residual = er["error_um"].to_numpy(dtype=float) - clone(model).fit(ds, others).predict(ds, r)
        env = Envelope.fit(ds, others, sensors, operating)
        scores.append(interval_scores(residual, env.distance(Envelope.features(ds, r, er["t_s"], sensors, operating)), kappa))
    s = np.concatenate(scores)
    q = conformal_quantile(s, level)
    if not np.isfinite(q):
        raise ExportError(f"{name}: export.interval_level={level}: {s.size} calibration readings are too few for it")
    return {"level": float(level), "kappa": float(kappa), "q_um": float(q), "n_runs": len(runs), "n_readings": int(s.size),
            "calibration": "each training run left out once (a clone fitted on the others); scores |residual| / "
                           "(1 + kappa * distance to the others' envelope); half-width = q_um * (1 + kappa * distance)"}  # fmt: skip


def _inputs_json(ds, temps: list[str], needs_load: bool, bank: bool, operating: Sequence[str] = ()) -> list[dict]:
    out = [{"name": "t_s", "unit": "s", "what": "time of the process sample (uniform period)"},
           {"name": "axis_mm", "unit": "mm", "what": "axis position"},
           {"name": "feed_mm_min", "unit": "mm/min", "what": "feed"}]  # fmt: skip
    if needs_load:
        out.append({"name": "load_N", "unit": "N", "what": "axial load"})
    if bank:
        out.append({"name": "measuring", "unit": "flag", "what": "1 inside a measuring cycle (left out of the motion window)"})
    for i, s in enumerate(temps):
        loc = ds.metadata.sensors.get(s) if ds is not None else None
        out.append({"name": f"{s}_C", "unit": "°C", "sensor": s, "location": loc, "channel": i})
    for i, c in enumerate(operating):
        out.append({"name": c, "unit": c.rsplit("_", 1)[-1] if "_" in c else "", "channel": len(temps) + i,
                    "what": "operating input (process column), in temps_C after the temperatures"})  # fmt: skip
    return out


__getattr__ = thermbench.moved_names(__name__)
