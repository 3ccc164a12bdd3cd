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
file and reproduces the Python model on the held-out runs within ``parity_tol_um``.
"""

from __future__ import annotations

import datetime as _dt
import json
import sys
import warnings
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np
import pandas as pd

from .. import __version__
from ..outputs import output_dir
from ..models.motion_windows import measuring_intervals
from ..data.reference import frame_text
from ..models.bank import ConditionBank
from ..models.base import ThermalErrorModel
from . import fileformat, runtime
from .encoding import Encoded, ExportError, encode, encode_classifier
from .reduce import reduced_lssvm

MANIFEST = "manifest.json"
FORMAT = "thermbench-export/1"


class TargetRefused(ExportError):
    """The model does not meet its export target (:data:`TARGETS`): precision or budget."""


#: the compensators an export is for: the C runtime's precision there, and the budget it is refused
#: beyond (None: reported in the manifest's footprint only). cortex-m4f: seed 002's STM32F407
#: (Cortex-M4F, single-precision FPU, 1 MB flash, 128 KB main SRAM), thermbench.export.target
TARGETS = {
    "host": {"precision": "double", "budget": None},
    "cortex-m4f": {"precision": "float", "budget": {"ram_bytes": 16 * 1024, "file_bytes": 64 * 1024,
                                                     "cycle_insn": 100_000, "physics_update_insn": 50_000,
                                                     "prediction_insn": 200_000, "image_bytes": 64 * 1024}},
}


@dataclass
class ExportOptions:
    """What to write besides the model file. ``lssvm_reduced_size``: also write a reduced-set
    LSSVM with that many centres; ``verify``: run the C runtime (double and single precision) on
    the dataset's held-out runs and fail when the build ``target`` runs differs from Python by
    more than ``parity_tol_um``; ``onnx``: ONNX for the neural families; ``target``: the
    compensator the files are for (:data:`TARGETS`); ``interval_level``: the conformal interval of
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
        return TARGETS[self.target]["precision"]


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


def process_samples(ds, run: str) -> pd.DataFrame:
    """The run's process log with ``measuring`` (inside a measuring cycle: what the
    compensator knows and leaves out of the motion features)."""
    pr = ds.process_run(run).copy()
    t = pr["t_s"].to_numpy()
    meas = np.zeros(t.size, dtype=bool)
    for a, b in measuring_intervals(pr, ds.errors_run(run)):
        meas |= (t >= a) & (t <= b)
    pr["measuring"] = meas
    return pr


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


# ------------------------------------------------------------------- onnx ---
def write_onnx(model, path: Path, ds=None, runs: Sequence[str] = ()) -> dict:
    """The net's thermal part as ONNX (float32, inputs in raw units, standardisation inside),
    run by onnxruntime against the Python model; returns the check's figures."""
    import io

    from ..errors import require
    from ..models.neural import GRUModel, torch

    nn = torch.nn
    ort = require("onnxruntime", "the ONNX export of a neural model (or set export.onnx=false)")
    require("onnx", "the ONNX export of a neural model (or set export.onnx=false)")

    gru = isinstance(model, GRUModel)
    means = [torch.tensor(np.asarray(m, dtype=np.float32)) for m in model.input_mean_]
    scales = [torch.tensor(np.asarray(s, dtype=np.float32)) for s in model.input_scale_]
    net = _float32_copy(model.net_)
    ym, ys = float(model.y_mean_um_), float(model.y_scale_um_)

    class Wrap(nn.Module):
        def forward(self, *xs):
            z = [(x - m) / s for x, m, s in zip(xs, means, scales)]
            return net(*z) * ys + ym

    S = len(model.sensors_)
    if gru:
        example = (torch.zeros(2, model.n_lags_ + 1, S), torch.zeros(2, 1))
        names = ["dT_history_C", "axis_mm"]
        axes = {"dT_history_C": {0: "n"}, "axis_mm": {0: "n"}, "thermal_um": {0: "n"}}
    else:
        example = (torch.zeros(2, S + 1),)
        names = ["dT_C_and_axis_mm"]
        axes = {"dT_C_and_axis_mm": {0: "n"}, "thermal_um": {0: "n"}}
    buf = io.BytesIO()
    with torch.no_grad(), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # tracer notes on the GRU's shape checks; the result is checked below
        torch.onnx.export(Wrap().eval(), example, buf, dynamo=False, input_names=names, output_names=["thermal_um"],
                          dynamic_axes=axes, opset_version=17)  # fmt: skip
    data = buf.getvalue()
    path.write_bytes(data)
    # check: onnxruntime against the Python model on held-out readings (or the training scale)
    if ds is not None and runs:
        from ..models.base import readings

        rd = readings(ds, list(runs))
        feats = [model._inputs(ds, r, g["t_s"].to_numpy(), g["target_mm"].to_numpy()) for r, g in rd.groupby("run_id", sort=False)]
        inputs = [np.concatenate([f[i] for f in feats]) for i in range(len(feats[0]))]
        with torch.no_grad():
            ref = model._forward(inputs).numpy() * ys + ym
    else:
        rng = np.random.default_rng(0)
        inputs = [m + s * rng.standard_normal((64, *np.shape(m))) for m, s in zip(model.input_mean_, model.input_scale_)]
        if gru:
            inputs[0] = np.repeat(inputs[0][:, None, :], model.n_lags_ + 1, axis=1)
        with torch.no_grad():
            ref = model._forward(inputs).numpy() * ys + ym
    sess = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    got = sess.run(None, {n: np.asarray(a, dtype=np.float32) for n, a in zip(names, inputs)})[0]
    return {"file": path.name, "bytes": len(data), "inputs": names, "output": "thermal_um",
            "onnxruntime_max_abs_diff_um": float(np.max(np.abs(got - ref))), "n_checked": int(ref.size),
            "note": "thermal part only, float32; the geometric part is in the .tbm file"}  # fmt: skip


def _float32_copy(net):
    import copy

    out = copy.deepcopy(net).float().eval()
    for p in out.parameters():
        p.requires_grad_(False)
    return out


# ----------------------------------------------------------------- parity ---
def python_predictions(model, ds, run: str, q: pd.DataFrame) -> np.ndarray:
    return model.predict_at(ds, run, q["t_s"].to_numpy(), q["axis_mm"].to_numpy())


def readings_queries(ds, run: str) -> pd.DataFrame:
    er = ds.errors_run(run)
    return pd.DataFrame({"t_s": er["t_s"].to_numpy(), "axis_mm": er["target_mm"].to_numpy(), "error_um": er["error_um"].to_numpy()})


def replay_dir(model_dir: Path, ds, run: str, queries: pd.DataFrame, variant: str = "model", sanitize: bool = False,
               exe: Path | None = None, manifest: dict | None = None, samples: pd.DataFrame | None = None,
               lenient: bool = False, live: bool = False, probes: pd.DataFrame | None = None,
               probe_params=None, guard: bool = False) -> pd.DataFrame:  # fmt: skip
    """The C runtime's predictions at ``queries`` over ``run`` of ``ds``, from an export directory
    (``live``: as the compensator answers; ``probes`` with ``probe_params``: corrected by probe
    readings; ``guard``: with the extrapolation guard's distance from the export's envelope file,
    :func:`.runtime.replay`)."""
    files, samples, temps, bank = replay_inputs(model_dir, ds, run, variant, manifest, samples)
    env = None
    if guard:
        man = manifest if manifest is not None else read_manifest(Path(model_dir))
        env = Path(model_dir) / man.get("envelope", {}).get("file", "")
        if not man.get("envelope", {}).get("file") or not env.is_file():
            raise ExportError(f"{model_dir}: no envelope file (exported without its training data, or before thermbench "
                              "wrote one): the guard needs it")  # fmt: skip
    return runtime.replay(files, samples, temps, queries, bank=bank, sanitize=sanitize, exe=exe, lenient=lenient,
                          live=live, probes=probes, probe_params=probe_params, guard=env)  # fmt: skip


def replay_inputs(model_dir: Path, ds, run: str, variant: str = "model", manifest: dict | None = None,
                  samples: pd.DataFrame | None = None) -> tuple[list[Path], pd.DataFrame, list[str], bool]:  # fmt: skip
    """What a replay of an export directory over ``run`` of ``ds`` feeds the runtime: the model
    files (a bank: the classifier, then the members in class order), the process samples, the
    columns after the motion (temperatures, then operating inputs) and whether it is a bank."""
    model_dir = Path(model_dir)
    man = manifest if manifest is not None else read_manifest(model_dir)
    temps = []
    for s in man["temperatures"]:
        col = ds.metadata.sensor_column(s) if s in ds.metadata.sensors else None
        if col is None or col not in ds.process.columns:
            raise ExportError(f"{model_dir}: the model reads sensor {s!r}, which dataset {ds.path} lacks; "
                              f"it has {list(ds.metadata.sensors)}")  # fmt: skip
        temps.append(col)
    samples = process_samples(ds, run) if samples is None else samples
    for c in man.get("operating", []):  # input channels after the temperatures
        if c not in samples.columns:
            raise ExportError(f"{model_dir}: the model reads the operating input {c!r}, which run {run!r} of {ds.path} "
                              f"lacks; its process columns: {list(samples.columns)}")  # fmt: skip
        temps.append(c)
    if man.get("needs_load") and "load_N" not in samples:
        raise ExportError(f"{model_dir}: the model reads load_N, which run {run!r} of {ds.path} lacks")
    if man["kind"] == "bank":
        files = [model_dir / man["bank"]["classifier"], *[model_dir / m["file"] for m in man["bank"]["members"]]]
        return files, samples, temps, True
    f = man["files"].get(variant)
    if f is None:
        raise ExportError(f"{model_dir}: no file variant {variant!r}; it has {sorted(man['files'])}")
    return [model_dir / f["file"]], samples, temps, False


def read_manifest(model_dir: Path) -> dict:
    p = Path(model_dir) / MANIFEST
    if not p.exists():
        raise ExportError(f"{model_dir}: no {MANIFEST}; export a model there with `thermbench export`")
    try:
        man = json.loads(p.read_text(encoding="utf-8"))
    except json.JSONDecodeError as exc:
        raise ExportError(f"{p}: not valid JSON ({exc})") from None
    if man.get("format") != FORMAT:
        raise ExportError(f"{p}: format {man.get('format')!r}, expected {FORMAT!r}")
    return man


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
    man: dict[str, Any] = {"format": FORMAT, "name": name, "family": f"{type(model).__module__}.{type(model).__name__}",
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
                man["onnx"] = write_onnx(model, tmp / "model.onnx", ds, heldout)
        man["needs_load"] = any(e.needs_load for e in encs.values())
        man["target"] = {"name": opts.target, **TARGETS[opts.target]}  # what the export is for (checked below)
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
            if opts.interval_level is not None:
                man["interval"] = interval_calibration(model, ds, list(model.train_runs_), temps, ops, opts.interval_level,
                                                       opts.interval_kappa, name)  # fmt: skip
        man["metrics"] = source.pop("metrics", {})
        man["mlflow_run_id"] = source.pop("mlflow_run_id", None)
        man["source"] = source
        man["footprint"] = footprint(tmp, man)
        if TARGETS[opts.target]["budget"]:
            man["target"]["footprint"] = _check_target(tmp, man, opts.target, name)
        if opts.verify and ds is not None:
            # parity on held-out runs; when every run trained the model, on those (parity, not accuracy)
            runs = heldout or list(model.train_runs_)
            man["parity"] = _verify(tmp, man, models_py, ds, runs, opts.parity_tol_um, name, opts.precision)
            man["parity"]["runs_are_training_runs"] = not heldout
            if opts.target == "cortex-m4f":
                man["target"]["measured"] = _measure_on_target(tmp, man, ds, runs, name)
        (tmp / MANIFEST).write_text(json.dumps(man, indent=2, allow_nan=False) + "\n", encoding="utf-8")
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


#: seed 002's compensator, an STM32F407 (1 MB flash, 192 KB RAM, 168 MHz): the issue's budget per model
BUDGET = {"file_bytes": 64 * 1024, "ram_bytes": 16 * 1024, "small_file_bytes": 1024}
SMALL_KINDS = ("MLR_CURVE", "MLR_SEED001", "CLASSIFIER")


def footprint(model_dir: Path, man: dict) -> dict:
    """File bytes and RAM (state arena + model handles) as the C runtime reports them, against
    :data:`BUDGET` (MLR files and the classifier <= 1 KB). Instruction counts: benchmarks/bench_export.py."""
    if man["kind"] == "bank":
        entries = [man["bank"]["classifier_file"], *man["bank"]["members"]]
        names = [man["bank"]["classifier"], *[m["file"] for m in man["bank"]["members"]]]
    else:
        entries = [man["files"]["model"]]
        names = [man["files"]["model"]["file"]]
    try:
        inf = runtime.info([Path(model_dir) / n for n in names])
    except runtime.RuntimeUnavailable as exc:  # export.verify=false works without gcc; RAM is then unknown
        return {"file_bytes": int(sum(e["bytes"] for e in entries)), "ram_bytes": None, "budget": BUDGET,
                "within_budget": None, "over_budget": [], "note": f"RAM not measured: {exc}"}  # fmt: skip
    ram = int(inf["state_bytes"].sum() + inf["model_bytes"].sum())
    over = [f"{n}: {e['bytes']} B file" for n, e in zip(names, entries)
            if e["bytes"] > (BUDGET["small_file_bytes"] if e["kind"] in SMALL_KINDS else BUDGET["file_bytes"])]  # fmt: skip
    if ram > BUDGET["ram_bytes"]:
        over.append(f"{ram} B RAM")
    return {"file_bytes": int(inf["file_bytes"].sum()), "ram_bytes": ram, "budget": BUDGET,
            "within_budget": not over, "over_budget": over}  # fmt: skip


def _check_target(model_dir: Path, man: dict, target: str, name: str) -> dict:
    """The export's files and state arenas in the target's build (the host's 64-bit pointers make
    the arenas a little larger than on a 32-bit target), refused beyond the target's budget."""
    budget = TARGETS[target]["budget"]
    files = ([man["bank"]["classifier"], *[m["file"] for m in man["bank"]["members"]]] if man["kind"] == "bank"
             else [f["file"] for f in man["files"].values()])  # fmt: skip
    inf = runtime.info([Path(model_dir) / f for f in files], SINGLE_FLAGS if TARGETS[target]["precision"] == "float" else ())
    arena = int(inf["state_bytes"].sum()) if man["kind"] == "bank" else int(inf["state_bytes"].max())
    over = [f"{f}: {b} B file" for f, b in zip(files, inf["file_bytes"]) if b > budget["file_bytes"]]
    if arena > budget["ram_bytes"]:
        why = (f"the bank's {len(files) - 1} members each keep their own state ({', '.join(map(str, inf['state_bytes'][1:]))} B)"
               if man["kind"] == "bank" else f"its state arena")  # fmt: skip
        over.append(f"{arena} B of state arena, above the target's {budget['ram_bytes']} B ({why})")
    if over:
        raise TargetRefused(f"{name}: does not fit the {target} target: {'; '.join(over)}. Export a smaller model "
                          f"(a global model instead of a bank, a shorter window_s for a GRU) or for export.target=host")  # fmt: skip
    return {"arena_bytes": arena, "file_bytes": [int(b) for b in inf["file_bytes"]], "budget": budget}


def _measure_on_target(model_dir: Path, man: dict, ds, runs: Sequence[str], name: str) -> dict:
    """Each file variant in single precision on the emulated Cortex-M4F (:mod:`.target`, QEMU) over
    **every** parity run, answering a query at every process sample: its worst instructions per
    control cycle and per prediction over all runs (with the run and the time of the worst cycle),
    the end-of-stream finish call on its own, arena, stack and the one-kind image's flash, refused
    beyond the budget (one physics update: ``physics_update_insn``); and its answers against the
    host's double build at every sample (``parity_vs_host_double_um``)."""
    from . import target as tgt

    budget = TARGETS["cortex-m4f"]["budget"]
    try:
        tgt.toolchain()
    except runtime.RuntimeUnavailable as exc:
        raise ExportError(f"{name}: export.target=cortex-m4f measures the model on the emulated M4: {exc}") from None
    out: dict[str, Any] = {"runs": list(runs), "queries": "every process sample"}
    over = []
    host = runtime.build("tb_replay")
    for variant in (["model"] if man["kind"] == "bank" else list(man["files"])):
        kind = man["kind"] if man["kind"] == "bank" else man["files"][variant]["kind"]
        m: dict[str, Any] = {"cycle_insn_max": 0, "prediction_insn_max": 0, "finish_insn_max": 0, "arena_bytes": 0,
                             "stack_bytes": 0, "parity_vs_host_double_um": 0.0, "n_samples": 0}  # fmt: skip
        for run in runs:
            files, samples, temps, bank = replay_inputs(model_dir, ds, run, variant, man)
            q = pd.DataFrame({"t_s": samples["t_s"].to_numpy(), "axis_mm": samples["axis_mm"].to_numpy()})
            got, rep = tgt.replay(files, samples, temps, q, precision="float", arena_bytes=budget["ram_bytes"])
            if rep["rc"] != 0:
                over.append(f"{variant}: the firmware stopped on run {run!r} ({rep['end']})")
                break
            ref = runtime.replay(files, samples, temps, q, bank=bank, exe=host)
            m["parity_vs_host_double_um"] = max(m["parity_vs_host_double_um"],
                                                float(np.max(np.abs(got["total_um"].to_numpy() - ref["total_um"].to_numpy()))))  # fmt: skip
            if rep.get("step_insn_max", 0) > m["cycle_insn_max"]:
                m["cycle_insn_max"], m["cycle_worst_run"] = rep["step_insn_max"], run
            for key, what in (("prediction_insn_max", "predict_insn_max"), ("finish_insn_max", "finish_insn_max"),
                              ("arena_bytes", "arena_bytes"), ("stack_bytes", "stack_bytes")):  # fmt: skip
                m[key] = max(m[key], int(rep.get(what, 0)))
            m["n_samples"] += len(samples)
        m["image_bytes"] = None if man["kind"] == "bank" else tgt.image(files[0], "float").flash_bytes
        out[variant] = m
        cyc = budget["physics_update_insn"] if kind == "PHYSICS" else budget["cycle_insn"]
        for what, v, lim in (("control cycle", m["cycle_insn_max"], cyc), ("prediction", m["prediction_insn_max"],
                             budget["prediction_insn"]), ("one-kind image", m["image_bytes"] or 0, budget["image_bytes"])):  # fmt: skip
            if v > lim:
                at = f" (worst on run {m['cycle_worst_run']!r})" if what == "control cycle" else ""
                over.append(f"{variant}: {what} {v} {'B' if what.endswith('image') else 'instructions'} > {lim}{at}")
    if over:
        hint = (" (a GRU's prediction runs window_s / step_s + 1 lags of 3 x hidden x (hidden + sensors) "
                "multiply-adds: fewer lags or hidden units)" if '"GRU"' in json.dumps([man.get("files"), man.get("bank")]) else "")  # fmt: skip
        raise TargetRefused(f"{name}: over the cortex-m4f budget, measured on the emulated M4 in float over every sample "
                            f"of {list(runs)}: {'; '.join(over)}{hint}")  # fmt: skip
    return out


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


#: the C runtime in single precision (tb_runtime.h), as the Cortex-M4F target builds it
SINGLE_FLAGS = ("-DTB_SINGLE",)


def _float_hint(model) -> str:
    """Why single precision may not be enough for ``model``, and what to do instead."""
    from ..models.lssvm import PSOLSSVM

    lssvms = [model] if isinstance(model, PSOLSSVM) else [m for m in getattr(model, "models_", {}).values()
                                                           if isinstance(m, PSOLSSVM)]  # fmt: skip
    if lssvms:
        return (": an LSSVM's kernel weights are large and cancel, and float32 keeps 7 digits of each term; for a "
                "float target fit it on fewer samples (max_samples: fewer support vectors) or with a smaller penalty "
                "(gamma), or choose another family, or run the runtime in double (export.target=host)")  # fmt: skip
    return ": run this model on a double-precision build (export.target=host)"


def _verify(tmp: Path, man: dict, models_py: dict, ds, runs: Sequence[str], tol_um: float, name: str,
            precision: str = "double") -> dict:  # fmt: skip
    """C runtime vs the Python model at every reading of ``runs`` (parity), per file variant, in
    double and in single precision (``-DTB_SINGLE``); the build of ``precision`` must be within ``tol_um``.
    And the single-precision build vs the double one at **every process sample** of every run (grid
    times of a bank's classifier, stream ends: where a time comparison that holds in double can fail
    in float; readings alone never fall on a grid time): within ``tol_um`` too when the target is float."""
    out: dict[str, Any] = {"runs": list(runs), "tolerance_um": tol_um, "precision": precision}
    exes = {"double": runtime.build("tb_replay"), "float": runtime.build("tb_replay", SINGLE_FLAGS)}
    for variant, model in models_py.items():
        file_variant = "model" if variant == "bank" else variant
        worst, n, err_c, err_py = {"double": 0.0, "float": 0.0}, 0, [], []
        every, n_samples, where = 0.0, 0, None  # float vs double at every process sample
        for run in runs:
            q = readings_queries(ds, run)
            py = python_predictions(model, ds, run, q)
            s = process_samples(ds, run)
            # one replay per precision answers the readings and every process sample: the two query
            # sets merged in time order (tb_replay takes nondecreasing times), answers split back
            qs = pd.DataFrame({"t_s": s["t_s"].to_numpy(dtype=float), "axis_mm": s["axis_mm"].to_numpy(dtype=float)})
            merged = pd.concat([q[["t_s", "axis_mm"]].astype(float), qs], ignore_index=True)
            order = np.argsort(merged["t_s"].to_numpy(), kind="stable")  # stable: each set keeps its own order
            is_reading = order < len(q)
            files, s, cols, bank = replay_inputs(tmp, ds, run, file_variant, man, s)
            text = runtime.stream_text(s, cols, merged.iloc[order])  # one input, both builds
            total = {}
            for prec, exe in exes.items():
                total[prec] = runtime.replay_text(exe, files, text, bank=bank)["total_um"].to_numpy()
                at_readings = total[prec][is_reading]
                worst[prec] = max(worst[prec], float(np.max(np.abs(at_readings - py))))
                if prec == precision:
                    err_c.append(q["error_um"].to_numpy() - at_readings)
            n += len(q)
            err_py.append(q["error_um"].to_numpy() - py)
            d = np.abs(total["float"][~is_reading] - total["double"][~is_reading])
            if d.size and float(d.max()) > every:
                every, where = float(d.max()), (run, float(qs["t_s"].iloc[int(np.argmax(d))]))
            n_samples += len(qs)
        key = file_variant
        out[key] = {"max_abs_diff_um": worst["double"], "float_max_abs_diff_um": worst["float"], "n_readings": n,
                    "float_vs_double_every_sample_max_abs_um": every, "n_samples": n_samples,
                    "heldout_rmse_um_c": float(np.sqrt(np.mean(np.concatenate(err_c) ** 2))),
                    "heldout_rmse_um_python": float(np.sqrt(np.mean(np.concatenate(err_py) ** 2)))}  # fmt: skip
        if worst[precision] > tol_um:
            build, err = ("", ExportError) if precision == "double" else (" in single precision (-DTB_SINGLE)", TargetRefused)
            raise err(f"{name} ({variant}): the C runtime{build} differs from the Python model by {worst[precision]:.4g} um "
                      f"on held-out runs {list(runs)}, above parity_tol_um={tol_um}"
                      f"{_float_hint(model) if precision == 'float' else ''}")  # fmt: skip
        if precision == "float" and every > tol_um:
            raise TargetRefused(f"{name} ({variant}): the C runtime in single precision (-DTB_SINGLE) differs from the "
                                f"double build by {every:.4g} um at t = {where[1]:g} s of run {where[0]!r} (every process "
                                f"sample of {list(runs)} compared), above parity_tol_um={tol_um}{_float_hint(model)}")  # fmt: skip
    if "reduced" in out:
        out["reduced_cost_um"] = out["reduced"]["heldout_rmse_um_python"] - out["model"]["heldout_rmse_um_python"]
    return out
