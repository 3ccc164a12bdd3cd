"""``thermbench import MAPPING.yaml --out DIR``: a lab's own files to a format 2 dataset
(docs/import.md).

One YAML mapping file describes the user's files (CSV, Excel, Parquet), how to read
them (separator, decimal comma, encoding, preamble lines, sheet), their clocks (seconds
or timestamps, a clock offset each), and what each column is in the dataset contract,
with unit conversions. Nothing is written but the dataset, and only after it validates.

Alignment (the documented rule) is :mod:`thermbench.data.import_align`'s. The mapping is read
by :mod:`thermbench.data.import_mapping`, its files by :mod:`thermbench.data.import_sources`, their
columns made dataset columns by :mod:`thermbench.data.import_columns`; here they become the
dataset, written only after it validates.
"""

from __future__ import annotations

import os
import time
from pathlib import Path

import numpy as np
import pandas as pd
from pydantic import ValidationError

import thermbench

from ..outputs import check_output_dir, output_dir
from . import import_mapping, limits
from .errors import DatasetError
from .import_align import _align_process, _check_reading_times, _errors
from .import_columns import _merge_pieces, _piece_columns, _piece_run, _times
from .import_sources import _read_source, _source_paths
from .io import load_dataset
from .reference import run_summary
from .safe_yaml import dump_yaml
from .schema import FORMAT_V2, Metadata, RunMeta
from .tables import validation_message
from .views import split_segments

#: files from this size on are announced as they are read (a large import says what it is doing)
PROGRESS_MIN_BYTES = 32 * 1024 * 1024


# ----------------------------------------------------------------- import ---
def _metadata(m: import_mapping.Mapping, path: Path, lines: dict) -> Metadata:
    raw = {"format": FORMAT_V2, **m.dataset}
    if "format" in m.dataset:
        raise import_mapping.MappingError(f"{path}: key 'dataset.format': leave it out; import writes {FORMAT_V2}")
    if "runs" not in m.dataset:  # the runs the files name (run: from sheet / file, a run_id column, run:)
        raw["runs"] = {_UNDECLARED: {}}
    sub = {tuple(k[1:]): v for k, v in lines.items() if k and k[0] == "dataset"}
    try:
        meta = Metadata.model_validate(raw)
    except ValidationError as exc:
        msg = validation_message(exc, path, sub)
        raise import_mapping.MappingError(msg.replace(f"{path}: key '", f"{path}: key 'dataset.", 1)) from None
    if m.run is not None and m.run not in meta.runs and _UNDECLARED not in meta.runs:
        raise import_mapping.MappingError(f"{path}: key 'run': {m.run!r} is not a run of dataset.runs "
                                          f"({sorted(meta.runs)})")  # fmt: skip
    return meta


#: the placeholder run of a mapping whose dataset declares no runs (they come from the files)
_UNDECLARED = "undeclared-runs"


def build_tables(mapping_path: str | Path, progress=None) -> tuple[Metadata, pd.DataFrame, pd.DataFrame, list[str]]:
    """Read the mapping and its files; return the dataset's metadata and tables (not yet
    written), and notes on what was left out (fully empty rows, per file). :class:`.import_mapping.MappingError`
    names the mapping key of any mistake."""
    path = Path(mapping_path)
    m, lines = import_mapping.read_mapping(path)
    meta = _metadata(m, path, lines)
    base_dir = path.parent
    frames: dict[str, dict] = {}
    channels = meta.error_channels()
    kinds = set()
    declared = _UNDECLARED not in meta.runs
    notes: list[str] = []
    say = progress or (lambda _msg: None)
    for name, f in m.files.items():
        where = f"{path}: key files.{name}"
        pieces = []
        for src in _source_paths(f, base_dir, where):
            size = os.path.getsize(src) if os.path.isfile(src) else 0
            t_read = time.perf_counter()
            if size >= PROGRESS_MIN_BYTES:
                say(f"files.{name}: reading {src.name} ({size / limits.MiB:.1f} MiB)")
            read = _read_source(f, src, where)
            if size >= PROGRESS_MIN_BYTES:
                rows = sum(len(df) for _, df, _ in read)
                say(f"files.{name}: {src.name}: {rows} rows in {time.perf_counter() - t_read:.1f} s")
            for sheet, df, dropped in read:
                label = src.name + (f" sheet {sheet!r}" if sheet is not None and f.read.sheets is not None else "")
                if dropped:
                    notes.append(f"files.{name}: {label}: {dropped} fully empty row(s) skipped")
                t, kind = _times(df, f, where, src)
                kinds.add(kind)
                run = _piece_run(f, src, sheet, where)
                pieces.append((src, label, t, _piece_columns(df, f, src, where, meta, channels, m, run, declared)))
            del read, df  # the tables read: only the mapped columns go on (a large log is not held twice)
        frames[name] = _merge_pieces(pieces, f, where)
        del pieces
    if not declared:  # the runs are those the files name, file entry by file entry (import_columns._run_order)
        order = list(dict.fromkeys(r for fr in frames.values() for r in fr["runs"]))
        meta = meta.model_copy(update={"runs": {r: RunMeta() for r in order}})
    mapped = {c for fr in frames.values() for c in fr["proc"]}
    if "operating" not in m.dataset and meta.operating_inputs() and not mapped & set(meta.operating_inputs()):
        # no operating signal in the files (a test logged temperatures and a drift only): none is
        # expected, and each run is one state of its own
        notes.append(f"no file maps an operating input ({', '.join(meta.operating_inputs())}): the dataset has none "
                     "(operating: []), each run is a state of its own")  # fmt: skip
        meta = meta.model_copy(update={"operating": []})
    if False in kinds and len(kinds) > 1:
        raise import_mapping.MappingError(f"{path}: key 'files': some files have timestamps and some seconds; a "
                                          "common clock needs the same kind in every file (give each file's time the "
                                          "same way)")  # fmt: skip
    if kinds == {"aware", "naive"}:
        raise import_mapping.MappingError(f"{path}: key 'files': some files' timestamps carry a time zone and some "
                                          "do not; a timestamp without one could be any zone: write the zone into the "
                                          "files, or read all without it and align them with offset_s")  # fmt: skip
    epoch = 0.0
    if False not in kinds:  # timestamps: seconds since the earliest one of the process files
        with_proc = [fr for fr in frames.values() if fr["proc"] or fr["wide"]] or list(frames.values())
        epoch = min(float(np.min(fr["t"])) for fr in with_proc)
        for fr in frames.values():
            fr["t"] = fr["t"] - epoch
    t_align = time.perf_counter()
    process = _align_process(m, frames, meta, path)
    if time.perf_counter() - t_align > 2.0:
        say(f"the files put on one clock: {len(process)} process rows in {time.perf_counter() - t_align:.1f} s")
    errors = _errors(frames, channels)
    _check_reading_times(frames, process)
    if False not in kinds and len(process):  # timestamps: each run's clock starts at its first process sample
        zero = process.groupby("run_id")["t_s"].min()
        process["t_s"] = process["t_s"] - process["run_id"].map(zero).to_numpy()
        if len(errors):
            errors["t_s"] = errors["t_s"] - errors["run_id"].map(zero).to_numpy()
        zone = "+00:00" if kinds == {"aware"} else ""
        for run, z in zero.items():  # when t_s = 0 was, on the files' clock (the base file's, offsets applied)
            stamp = pd.Timestamp(round((epoch + float(z)) * 1e6), unit="us").isoformat()
            meta.runs[run].started = stamp + zone  # an extra key of the run (pydantic extra="allow")
    return meta, process, errors, notes


def import_dataset(mapping_path: str | Path, out: str | Path, file_format: str = "parquet", force: bool = False,
                   extra: dict | None = None, progress=None):
    """Build the dataset the mapping describes and write it to ``out`` (one output of kind
    ``dataset``, :mod:`thermbench.outputs`), validated before it is moved into place.
    ``progress``: called with one line at each long step (large files, a long alignment)."""
    if file_format not in ("csv", "parquet"):
        raise import_mapping.MappingError(f"--format: expected csv or parquet, got {file_format!r}")
    out = Path(out)
    check_output_dir(out, "dataset", force=force)
    meta, process, errors, notes = build_tables(mapping_path, progress)
    if progress is not None and len(process) >= 1_000_000:
        progress(f"writing and checking the dataset: {len(process)} process rows, {len(errors)} readings")
    with output_dir(out, "dataset", force=force) as tmp:
        doc = meta.model_dump(mode="json", exclude_none=True) | dict(extra or {})
        (tmp / "metadata.yaml").write_text(dump_yaml(doc, sort_keys=False, allow_unicode=True), encoding="utf-8")
        pieces = [("process", process)] + ([("errors", errors)] if len(errors) else [])
        del process, errors  # written, then read back to be checked: not held twice
        while pieces:
            name, df = pieces.pop(0)
            if file_format == "parquet":
                df.to_parquet(tmp / f"{name}.parquet", index=False)
            else:
                df.to_csv(tmp / f"{name}.csv", index=False)
            del df
        try:
            ds = load_dataset(tmp)
            # what validate and every command derive from it, before anything is moved into place
            split_segments(ds)
            run_summary(ds)
        except DatasetError as exc:
            msg = str(exc)
            for name in ("process", "errors"):
                msg = msg.replace(f"{tmp / name}.{file_format}", f"the imported {name} table")
            msg = msg.replace(str(tmp / "metadata.yaml"), "dataset").replace(str(tmp), str(out))
            raise import_mapping.MappingError(f"{mapping_path}: the imported dataset is not valid: {msg}") from None
    ds.path = out
    ds.import_notes = notes  # what the import left out, for the command to say
    return ds


__getattr__ = thermbench.moved_names(__name__)  # the names moved out (MOVED_NAMES): for one release
