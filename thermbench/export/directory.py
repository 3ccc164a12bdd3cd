"""An export directory read back: its ``manifest.json``, and the C runtime replaying it over a run
of a dataset (:func:`replay_dir`; :func:`replay_inputs`: the model files, process samples and input
columns it is fed)."""

from __future__ import annotations

import json
from pathlib import Path

import pandas as pd

from . import runtime
from .encoding import ExportError
from .samples import process_samples

MANIFEST = "manifest.json"
FORMAT = "thermbench-export/1"


def replay_dir(model_dir: Path, ds, run: str, queries: pd.DataFrame, variant: str = "model", sanitize: bool = False,
               exe: Path | None = None, manifest: dict | None = None, samples: pd.DataFrame | None = None,
               lenient: bool = False, live: bool = False, probes: pd.DataFrame | None = None,
               probe_params=None, guard: bool = False, faults: bool = False) -> pd.DataFrame:  # fmt: skip
    """The C runtime's predictions at ``queries`` over ``run`` of ``ds``, from an export directory
    (``live``: as the compensator answers; ``probes`` with ``probe_params``: corrected by probe
    readings; ``guard``: with the extrapolation guard's distance from the export's envelope file,
    ``faults``: with the sensor checks and bounds of the export's faults file, :func:`.runtime.replay`)."""
    files, samples, temps, bank = replay_inputs(model_dir, ds, run, variant, manifest, samples)
    env = checks = None
    man = manifest if manifest is not None else read_manifest(Path(model_dir))
    if faults:
        checks = Path(model_dir) / man.get("faults", {}).get("file", "")
        if not man.get("faults", {}).get("file") or not checks.is_file():
            raise ExportError(f"{model_dir}: no faults file (exported without its training data, or before thermbench "
                              "wrote one): the sensor checks need it")  # fmt: skip
    if guard:
        env = Path(model_dir) / man.get("envelope", {}).get("file", "")
        if not man.get("envelope", {}).get("file") or not env.is_file():
            raise ExportError(f"{model_dir}: no envelope file (exported without its training data, or before thermbench "
                              "wrote one): the guard needs it")  # fmt: skip
    return runtime.replay(files, samples, temps, queries, bank=bank, sanitize=sanitize, exe=exe, lenient=lenient,
                          live=live, probes=probes, probe_params=probe_params, guard=env, faults=checks)  # fmt: skip


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
