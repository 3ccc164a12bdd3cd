"""Load, validate and write datasets in the thermbench contract (docs/dataset-format.md).

Every problem is reported as a :class:`DatasetError` whose message is one line naming
the file, the column (or the metadata key) and the row (1-based data row; for CSV also
the file line). The table readers and checks both formats share are in
:mod:`thermbench.data.tables`, the format 2 tables in :mod:`thermbench.data.v2`, the
:class:`Dataset` class in :mod:`thermbench.data.dataset`. Loading trusts nothing it reads: special files and oversized files are
refused before they are opened (:mod:`thermbench.data.files`), ``metadata.yaml`` is read
by a strict YAML loader (:mod:`thermbench.data.safe_yaml`), every value is checked
against its plausible range (:mod:`thermbench.data.limits`), and nothing is ever written.
Writing goes to a temporary directory that replaces the target only when
complete, so a failed write never leaves a half-written dataset.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from pydantic import ValidationError

from ..outputs import output_dir
from . import limits, tables
from .dataset import Dataset, DatasetWarning
from .errors import DatasetError, short_repr
from .files import find_case_variant, read_capped
from .safe_yaml import YAMLInputError, dump_yaml, load_yaml
from .schema import FORMATS, Metadata, MetadataV1
from .v2 import load_tables_v2

PROCESS_REQUIRED = ("run_id", "t_s", "axis_mm", "feed_mm_min")
PROCESS_OPTIONAL_NUMERIC = ("load_N", "spindle_rpm")
ERRORS_REQUIRED = ("run_id", "t_s", "target_mm", "error_um")
MAX_SAMPLE_GAP_S = 1.0  # format 1: >= 1 sample per second

__all__ = ["Dataset", "DatasetError", "DatasetWarning", "load_dataset", "load_metadata", "save_dataset"]


def _check_run_ids(runs: dict, path: Path, lines: dict) -> None:
    """The run-id rule (:data:`~thermbench.data.limits.RUN_ID_PATTERN`) and no two ids
    that differ only by case."""
    seen: dict[str, str] = {}
    for run_id in runs:
        where = f"{path}: key {short_repr(tables.key_text(('runs', run_id)))}"
        at = tables.line_of(lines, ("runs", run_id))
        problem = limits.run_id_problem(run_id)
        if problem is not None:
            raise DatasetError(f"{where}: run id {short_repr(run_id)} {problem}; run ids are {limits.RUN_ID_RULE}{at}")
        other = seen.get(limits.run_id_key(run_id))
        if other is not None:
            raise DatasetError(
                f"{where}: run ids {run_id!r}{at} and {other!r}{tables.line_of(lines, ('runs', other))} differ only by "
                "case; they would name the same file on Windows and macOS"
            )
        seen[limits.run_id_key(run_id)] = run_id


def load_metadata(root: Path) -> Metadata:
    """Read and validate ``root/metadata.yaml``; :class:`DatasetError` on any problem."""
    root = Path(root)
    path = root / "metadata.yaml"
    if not os.path.lexists(path):
        found = find_case_variant(root, "metadata.yaml")
        if found:
            raise DatasetError(f"{root}: missing metadata.yaml (found {found!r}: rename it)")
        try:
            raw = sorted(p.name for p in root.iterdir() if p.suffix.lower() in (".xlsx", ".xls", ".xlsm", ".csv", ".txt", ".tsv")
                         and p.stem not in ("process", "errors"))
        except OSError:
            raw = []
        hint = (f" (it holds {tables.some(raw, 3)}: lab files come in through an import mapping, "
                "thermbench import MAPPING.yaml --out DIR; docs/import.md)") if raw else ""  # fmt: skip
        raise DatasetError(f"{root}: missing metadata.yaml{hint}")
    data = read_capped(path, limits.METADATA_MAX_BYTES, "metadata.yaml")
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise DatasetError(
            f"{path}: line {line}: not UTF-8 text (byte 0x{data[exc.start]:02x} at offset {exc.start}); "
            "save the file as UTF-8"
        ) from None
    try:
        raw, lines = load_yaml(text)
    except YAMLInputError as exc:
        raise DatasetError(f"{path}: {exc}") from None
    if raw is None:
        raise DatasetError(f"{path}: is empty; expected the keys format, machine, screw, material, sensors, runs")
    if not isinstance(raw, dict):
        raise DatasetError(f"{path}: expected a mapping (key: value) at the top level, got a {type(raw).__name__}")
    if raw.get("format") not in FORMATS:
        expected = " or ".join(repr(f) for f in FORMATS)
        raise DatasetError(
            f"{path}: key 'format': expected {expected}, got {short_repr(raw.get('format'))}{tables.line_of(lines, ('format',))}"
        )
    if isinstance(raw.get("runs"), dict):
        _check_run_ids(raw["runs"], path, lines)
    try:
        if raw["format"] == FORMATS[0]:
            MetadataV1.model_validate(raw)  # every format 1 key required, each message naming it
        return Metadata.model_validate(raw)
    except ValidationError as exc:
        raise DatasetError(tables.validation_message(exc, path, lines)) from None


def load_dataset(path: str | Path) -> Dataset:
    """Read and validate a dataset directory; raise :class:`DatasetError` on any violation.
    Reads only: the dataset's files are never modified. What the dataset holds but does not
    declare (a sensor column missing from ``metadata.yaml``) is ignored with a
    :class:`DatasetWarning` naming the file and the column."""
    notes: list[str] = []
    with warnings.catch_warnings():  # a library's warning would be a second line on stderr
        warnings.simplefilter("ignore")
        try:
            ds = _load_dataset(Path(path), notes)
        except MemoryError:
            raise DatasetError(f"{path}: too large to load in this process's memory") from None
    for note in notes:  # ours, one line each, after the filter above
        warnings.warn(note, DatasetWarning, stacklevel=2)
    return ds


def _undeclared_sensor_columns(process: pd.DataFrame, meta: Metadata, ppath: Path) -> list[str]:
    """One note per temperature column (``<name>_C``) of the process table that
    ``metadata.yaml`` declares neither as a sensor nor as an operating input: nothing reads it."""
    declared = {meta.sensor_column(s) for s in meta.sensors} | set(meta.operating_inputs())
    return [f"{ppath}: column {short_repr(c)} is not declared in metadata.yaml; ignored (declare sensor "
            f"{short_repr(c[:-2])} under 'sensors' to use it)"
            for c in process.columns if isinstance(c, str) and c.endswith("_C") and c not in declared]  # fmt: skip


def _load_dataset(root: Path, notes: list[str] | None = None) -> Dataset:
    notes = [] if notes is None else notes
    if not root.is_dir():
        what = "does not exist" if not os.path.lexists(root) else "is not a directory"
        raise DatasetError(f"{root}: not a dataset directory ({what})")
    meta = load_metadata(root)
    if meta.version == 2:
        process, errors = load_tables_v2(root, meta)
        notes += _undeclared_sensor_columns(process, meta, tables.find_table(root, "process"))
        return Dataset(meta, process, errors, root)
    ppath = tables.find_table(root, "process")
    epath = tables.find_table(root, "errors")
    sensor_cols = [meta.sensor_column(s) for s in meta.sensors]
    process = tables.read_table(ppath, PROCESS_REQUIRED + tuple(sensor_cols) + PROCESS_OPTIONAL_NUMERIC)
    errors = tables.read_table(epath, ERRORS_REQUIRED)
    tables.convert_times(process, ppath, errors, epath)

    tables.check_table(process, ppath, PROCESS_REQUIRED + tuple(sensor_cols), meta.runs)
    for col in PROCESS_OPTIONAL_NUMERIC:
        if col in process.columns:
            tables.numeric(process, col, ppath)
    p_codes, p_runs = tables.run_codes(process)
    tables.check_increasing(process, ppath, p_codes)
    neg = process["feed_mm_min"].to_numpy() < 0
    if neg.any():
        i = tables.first_index(neg)
        raise DatasetError(
            f"{ppath}: column 'feed_mm_min', {tables.row_at(ppath, i)}: feed must be >= 0 (speed magnitude), "
            f"got {process['feed_mm_min'].iloc[i]}"
        )
    tables.check_range(process, "feed_mm_min", ppath, limits.FEED_MM_MIN)
    tables.check_range(process, "axis_mm", ppath, limits.POSITION_MM)
    for col in sensor_cols:
        tables.check_range(process, col, ppath, limits.TEMPERATURE_C)
    if "spindle_rpm" in process.columns and (process["spindle_rpm"] < 0).any():
        i = tables.first_index(process["spindle_rpm"].to_numpy() < 0)
        raise DatasetError(f"{ppath}: column 'spindle_rpm', {tables.row_at(ppath, i)}: must be >= 0")
    t = process["t_s"].to_numpy()
    same = p_codes[1:] == p_codes[:-1]
    gap = same & (np.diff(t) > MAX_SAMPLE_GAP_S * 1.01)
    if gap.any():
        i = tables.first_index(gap) + 1
        raise DatasetError(
            f"{ppath}: column 't_s', {tables.row_at(ppath, i)}: gap of {t[i] - t[i - 1]:.3g} s; "
            f"the process stream needs >= 1 sample per second"
        )

    tables.check_table(errors, epath, ERRORS_REQUIRED, meta.runs)
    tables.check_range(errors, "target_mm", epath, limits.POSITION_MM)
    tables.check_range(errors, "error_um", epath, limits.ERROR_UM)
    e_codes, e_runs = tables.run_codes(errors)
    tables.check_increasing_errors(errors, epath, e_codes)
    tables.check_duplicate_rows(errors, epath, ERRORS_REQUIRED)
    p_present, e_present = set(p_runs), set(e_runs)
    for run_id in meta.runs:
        if run_id not in p_present:
            raise DatasetError(f"{ppath}: run {run_id!r} (declared in metadata.yaml) has no rows")
        if run_id not in e_present:
            raise DatasetError(f"{epath}: run {run_id!r} (declared in metadata.yaml) has no rows")
    # each run is one block of process rows (checked above): its travel and time span
    starts = np.flatnonzero(np.r_[True, p_codes[1:] != p_codes[:-1]])
    ends = np.r_[starts[1:], len(p_codes)] - 1
    axis = process["axis_mm"].to_numpy()
    block = {p_runs[p_codes[s]]: k for k, s in enumerate(starts)}
    lo, hi = np.minimum.reduceat(axis, starts), np.maximum.reduceat(axis, starts)
    t0, t1 = t[starts], t[ends]
    k = np.array([block[r] for r in e_runs], dtype=int)[e_codes]  # the process block of each reading
    tables.check_within(errors, epath, "target_mm", lo[k] - tables.TRAVEL_TOL_MM, hi[k] + tables.TRAVEL_TOL_MM,
                  lambda i: f"mm is outside the travel measured in {ppath.name} for run {errors['run_id'].iloc[i]!r} "
                  f"({lo[k[i]]:g}..{hi[k[i]]:g} mm)")  # fmt: skip
    tables.check_within(errors, epath, "t_s", t0[k], t1[k],
                  lambda i: f"s is outside the process log of run {errors['run_id'].iloc[i]!r} "
                  f"({t0[k[i]]:g}..{t1[k[i]]:g} s)")  # fmt: skip
    notes += _undeclared_sensor_columns(process, meta, ppath)
    return Dataset(meta, process.reset_index(drop=True), errors.reset_index(drop=True), root)


# ---------------------------------------------------------------- writing ---
def save_dataset(ds: Dataset, path: str | Path, file_format: str = "csv", force: bool = False,
                 force_option: str = "force=true") -> Path:
    """Write ``ds`` as a dataset directory, atomically (staging directory, then rename): one
    output of kind ``dataset`` (:func:`thermbench.outputs.output_dir`), so only a dataset that
    thermbench wrote there before is replaced; a user's dataset or other files are refused."""
    if file_format not in ("csv", "parquet"):
        raise ValueError(f"file_format must be 'csv' or 'parquet', got {file_format!r}")
    target = Path(path)
    meta = ds.metadata.model_dump(mode="json", exclude_none=True)
    with output_dir(target, "dataset", force=force, force_option=force_option) as tmp:
        (tmp / "metadata.yaml").write_text(dump_yaml(meta, sort_keys=False), encoding="utf-8")
        for name, df in (("process", ds.process), ("errors", ds.errors)):
            if file_format == "parquet":
                df.to_parquet(tmp / f"{name}.parquet", index=False)
            else:
                df.to_csv(tmp / f"{name}.csv", index=False)
    return target
