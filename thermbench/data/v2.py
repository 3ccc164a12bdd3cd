"""The tables of a format 2 dataset (docs/dataset-format.md, "Format 2").

Format 2 admits what real thermal tests look like: a spindle test with displacement
channels at a fixed point and spindle speed as the operating input, any sample rate
(a largest gap per dataset, declared or inferred), feed derived from the axis position,
several error channels, bidirectional readings (a ``direction`` column) and runs
without readings (a production log to predict on). Every check reports one line naming
the file, the column and the row, as format 1 does, through the shared readers and checks
of :mod:`thermbench.data.tables`.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pandas as pd

from . import limits, tables
from .errors import DatasetError, short_repr
from .schema import Metadata

ERRORS_V2_REQUIRED = ("run_id", "t_s", "error_um")
OPTIONAL_NUMERIC = ("feed_mm_min", "spindle_rpm", "load_N")
GAP_FACTOR = 5.0  # without sampling.max_gap_s: a step over 5 median steps is a gap


def _errors_path(root: Path) -> Path | None:
    """The errors table, or None when the dataset has none (runs without readings)."""
    for ext in (".parquet", ".csv"):
        if os.path.lexists(root / f"errors{ext}"):
            return root / f"errors{ext}"
    return None


def _convert_process_times(process: pd.DataFrame, path: Path) -> None:
    """``t_s`` of a process table alone (no errors table): durations and date-times
    become seconds (date-times since the table's first one)."""
    if "t_s" not in process.columns:
        return
    kind = tables.time_kind(process["t_s"])
    if kind == "duration":
        process["t_s"] = process["t_s"].dt.total_seconds()
    elif kind == "date-time" and not process["t_s"].isna().all():
        process["t_s"] = (process["t_s"] - process["t_s"].min()).dt.total_seconds()


def max_gaps_s(meta: Metadata, t_s: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """The largest allowed step of each run's process log: ``sampling.max_gap_s`` when
    declared, else :data:`~thermbench.data.GAP_FACTOR` times the run's median step."""
    declared = meta.sampling.max_gap_s if meta.sampling is not None else None
    ends = np.r_[starts[1:], len(t_s)]
    out = np.empty(len(starts))
    for k, (a, b) in enumerate(zip(starts, ends)):
        if declared is not None:
            out[k] = declared
        else:
            steps = np.diff(t_s[a:b])
            out[k] = GAP_FACTOR * float(np.median(steps)) if steps.size else np.inf
    return out


def derive_feed(t_s: np.ndarray, axis_mm: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """``feed_mm_min`` from the axis position: the magnitude of the central difference
    (numpy.gradient) of each run's ``axis_mm`` over ``t_s``, × 60."""
    ends = np.r_[starts[1:], len(t_s)]
    feed = np.zeros(len(t_s))
    for a, b in zip(starts, ends):
        if b - a >= 2:
            feed[a:b] = np.abs(np.gradient(axis_mm[a:b], t_s[a:b])) * 60.0
    return feed


def load_tables_v2(root: Path, meta: Metadata) -> tuple[pd.DataFrame, pd.DataFrame]:
    """Read and check ``process`` and (when present) ``errors`` of a format 2 dataset."""
    sensor_cols = [meta.sensor_column(s) for s in meta.sensors]
    operating = meta.operating_inputs()
    ppath = tables.find_table(root, "process")
    epath = _errors_path(root)
    base = ["run_id", "t_s", *(["axis_mm"] if meta.has_axis else []), *sensor_cols]
    process = tables.read_table(ppath, tuple(base + operating) + OPTIONAL_NUMERIC)
    errors = None
    if epath is not None:
        errors = tables.read_table(epath, ERRORS_V2_REQUIRED + ("channel", "target_mm", "direction"))
        tables.convert_times(process, ppath, errors, epath)
    else:
        _convert_process_times(process, ppath)

    derive = "feed_mm_min" in operating and "feed_mm_min" not in process.columns and meta.has_axis
    required = base + [c for c in operating if not (c == "feed_mm_min" and derive)]
    tables.check_table(process, ppath, tuple(dict.fromkeys(required)), meta.runs)
    for col in dict.fromkeys([*OPTIONAL_NUMERIC, *operating]):
        if col in process.columns and col not in required:
            tables.numeric(process, col, ppath)
    codes, runs = tables.run_codes(process)
    tables.check_increasing(process, ppath, codes)
    if meta.has_axis:
        tables.check_range(process, "axis_mm", ppath, limits.POSITION_MM)
    for col in sensor_cols:
        tables.check_range(process, col, ppath, limits.TEMPERATURE_C)
    for col, q in (("feed_mm_min", limits.FEED_MM_MIN), ("spindle_rpm", limits.SPINDLE_RPM), ("load_N", limits.LOAD_N)):
        if col in process.columns:
            v = process[col].to_numpy()
            if q.lo == 0.0 and (v < 0).any():
                i = tables.first_index(v < 0)
                what = "speed magnitude" if col == "feed_mm_min" else "a speed"
                raise DatasetError(f"{ppath}: column {col!r}, {tables.row_at(ppath, i)}: must be >= 0 ({what}), got {v[i]:.6g}; "
                                   "a signed velocity is converted by thermbench import (abs: true)")  # fmt: skip
            tables.check_range(process, col, ppath, q)
    t = process["t_s"].to_numpy()
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
    gaps = max_gaps_s(meta, t, starts)
    block_of_row = np.repeat(np.arange(len(starts)), np.diff(np.r_[starts, len(t)]))
    step = np.diff(t)
    bad = (codes[1:] == codes[:-1]) & (step > gaps[block_of_row[1:]] * 1.01)
    if bad.any():
        i = tables.first_index(bad) + 1
        limit = gaps[block_of_row[i]]
        rule = ("sampling.max_gap_s in metadata.yaml" if meta.sampling is not None and meta.sampling.max_gap_s
                else f"{GAP_FACTOR:g} x the run's median step; declare sampling.max_gap_s to allow more")  # fmt: skip
        raise DatasetError(f"{ppath}: column 't_s', {tables.row_at(ppath, i)}: gap of {t[i] - t[i - 1]:.6g} s in run "
                           f"{process['run_id'].iloc[i]!r}, more than {limit:.6g} s ({rule})")  # fmt: skip
    if derive:
        process["feed_mm_min"] = derive_feed(t, process["axis_mm"].to_numpy(), starts)
    present = set(runs)
    for run_id in meta.runs:
        if run_id not in present:
            raise DatasetError(f"{ppath}: run {run_id!r} (declared in metadata.yaml) has no rows")

    channels = meta.error_channels()
    if errors is None:
        cols = ["run_id", "t_s", "channel", "error_um"] + (["target_mm"] if meta.has_axis else [])
        return process.reset_index(drop=True), pd.DataFrame({c: pd.Series(dtype=object if c in ("run_id", "channel") else float) for c in cols})
    if not channels:
        raise DatasetError(f"{root / 'metadata.yaml'}: key 'channels': missing; {epath.name} holds readings, so "
                           "metadata.yaml must declare the error channels they belong to")  # fmt: skip
    if "channel" not in errors.columns:
        if len(channels) > 1:
            raise DatasetError(f"{epath}: missing column 'channel'; metadata.yaml declares {len(channels)} channels "
                               f"({tables.some(channels)}), so each reading must name one")  # fmt: skip
        errors["channel"] = next(iter(channels))
    tables.check_table(errors, epath, ERRORS_V2_REQUIRED, meta.runs)
    ch = errors["channel"]
    if ch.isna().any():
        i = tables.first_index(ch.isna().to_numpy())
        raise DatasetError(f"{epath}: column 'channel', {tables.row_at(epath, i)}: missing value")
    errors["channel"] = ch.astype(str)
    unknown = ~errors["channel"].isin(list(channels))
    if unknown.any():
        i = tables.first_index(unknown.to_numpy())
        raise DatasetError(f"{epath}: column 'channel', {tables.row_at(epath, i)}: unknown channel "
                           f"{short_repr(errors['channel'].iloc[i])} (metadata.yaml declares {tables.some(channels)})")  # fmt: skip
    along = errors["channel"].map(lambda c: channels[c].kind == "along_axis").to_numpy(dtype=bool)
    tilt = errors["channel"].map(lambda c: channels[c].unit == "urad").to_numpy(dtype=bool)
    _optional_by_row(errors, epath, "target_mm", along, "along_axis", "its target position")
    _optional_by_row(errors, epath, "direction", along, "along_axis", "the direction of approach", required=False)
    if "direction" in errors.columns:
        d = errors["direction"].to_numpy()
        wrong = along & ~np.isnan(d) & ~np.isin(d, (-1.0, 1.0))
        if wrong.any():
            i = tables.first_index(wrong)
            raise DatasetError(f"{epath}: column 'direction', {tables.row_at(epath, i)}: must be 1 (approach in the "
                               f"positive direction) or -1 (negative), got {short_repr(errors['direction'].iloc[i])}")  # fmt: skip
        if along.any() and np.isnan(d[along]).any():
            i = tables.first_index(along & np.isnan(d))
            raise DatasetError(f"{epath}: column 'direction', {tables.row_at(epath, i)}: missing value; every reading of "
                               "an along_axis channel needs one when the column is given")  # fmt: skip
    for mask, q in ((~tilt, limits.ERROR_UM), (tilt, limits.TILT_URAD)):
        v = errors["error_um"].to_numpy()
        bad = mask & ~((v >= q.lo) & (v <= q.hi))
        if bad.any():
            i = tables.first_index(bad)
            raise DatasetError(f"{epath}: column 'error_um', {tables.row_at(epath, i)}: {q.problem(float(v[i]))}")
    if along.any():
        v = errors["target_mm"].to_numpy()
        bad = along & ~((v >= limits.POSITION_MM.lo) & (v <= limits.POSITION_MM.hi))
        if bad.any():
            i = tables.first_index(bad)
            raise DatasetError(f"{epath}: column 'target_mm', {tables.row_at(epath, i)}: {limits.POSITION_MM.problem(float(v[i]))}")
    # time order within each (run, channel); readings within the run's process log
    key = errors["run_id"] + "\0" + errors["channel"]
    kcodes = np.asarray(pd.factorize(key)[0])
    order_ok = np.ones(len(errors), dtype=bool)
    et = errors["t_s"].to_numpy()
    for k in np.unique(kcodes):
        idx = np.flatnonzero(kcodes == k)
        dec = np.flatnonzero(np.diff(et[idx]) < 0)
        if dec.size:
            order_ok[idx[dec[0] + 1]] = False
    if not order_ok.all():
        i = tables.first_index(~order_ok)
        raise DatasetError(f"{epath}: column 't_s', {tables.row_at(epath, i)}: time must not decrease within run "
                           f"{errors['run_id'].iloc[i]!r}, channel {errors['channel'].iloc[i]!r}")  # fmt: skip
    dup_cols = tuple(c for c in ("run_id", "channel", "t_s", "target_mm", "direction", "error_um") if c in errors.columns)
    tables.check_duplicate_rows(errors, epath, dup_cols)
    ends = np.r_[starts[1:], len(t)] - 1
    block = {runs[codes[s]]: k for k, s in enumerate(starts)}
    k = errors["run_id"].map(block).to_numpy(dtype=int)
    t0, t1 = t[starts], t[ends]
    tables.check_within(errors, epath, "t_s", t0[k], t1[k],
                     lambda i: f"s is outside the process log of run {errors['run_id'].iloc[i]!r} "
                     f"({t0[k[i]]:g}..{t1[k[i]]:g} s)")  # fmt: skip
    if along.any() and meta.has_axis:
        axis = process["axis_mm"].to_numpy()
        lo, hi = np.minimum.reduceat(axis, starts), np.maximum.reduceat(axis, starts)
        tol = tables.TRAVEL_TOL_MM
        v = errors["target_mm"].to_numpy()
        out = along & ((v < lo[k] - tol) | (v > hi[k] + tol))
        if out.any():
            i = tables.first_index(out)
            raise DatasetError(f"{epath}: column 'target_mm', {tables.row_at(epath, i)}: {v[i]:g} mm is outside the travel "
                               f"measured in {ppath.name} for run {errors['run_id'].iloc[i]!r} ({lo[k[i]]:g}..{hi[k[i]]:g} mm)")  # fmt: skip
    return process.reset_index(drop=True), errors.reset_index(drop=True)


def _optional_by_row(df: pd.DataFrame, path: Path, col: str, needed: np.ndarray, kind: str, what: str,
                     required: bool = True) -> None:
    """``col`` holds a number on the rows where ``needed`` and is empty elsewhere (a
    fixed-point reading has no target); the column may be absent when no row needs it."""
    if col not in df.columns:
        if needed.any() and required:
            i = tables.first_index(needed)
            raise DatasetError(f"{path}: missing column {col!r}; row {i + 1} is a reading of {kind} channel "
                               f"{df['channel'].iloc[i]!r}, which needs {what}")  # fmt: skip
        return
    s = df[col]
    if s.dtype == object or pd.api.types.is_string_dtype(s.dtype) or pd.api.types.is_bool_dtype(s.dtype):
        if pd.api.types.is_bool_dtype(s.dtype) or s.map(lambda v: isinstance(v, (bool, np.bool_))).any():
            raise DatasetError(f"{path}: column {col!r} holds true/false values; expected numbers")
        conv = pd.to_numeric(s, errors="coerce")
        bad = (conv.isna() & s.notna()).to_numpy()
        if bad.any():
            i = tables.first_index(bad)
            raise DatasetError(f"{path}: column {col!r}, {tables.row_at(path, i)}: expected a number, got {short_repr(s.iloc[i])}")
        s = conv
    v = s.astype(float).to_numpy()
    if required and (needed & np.isnan(v)).any():
        i = tables.first_index(needed & np.isnan(v))
        raise DatasetError(f"{path}: column {col!r}, {tables.row_at(path, i)}: missing value; a reading of {kind} channel "
                           f"{df['channel'].iloc[i]!r} needs {what}")  # fmt: skip
    if np.isinf(v).any():
        i = tables.first_index(np.isinf(v))
        raise DatasetError(f"{path}: column {col!r}, {tables.row_at(path, i)}: value must be finite, got {v[i]}")
    extra = ~needed & ~np.isnan(v)
    if extra.any():
        i = tables.first_index(extra)
        raise DatasetError(f"{path}: column {col!r}, {tables.row_at(path, i)}: channel {df['channel'].iloc[i]!r} is a "
                           f"fixed_point channel: leave {col} empty")  # fmt: skip
    df[col] = v
