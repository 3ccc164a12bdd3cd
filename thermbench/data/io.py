"""Load, validate and write datasets in the thermbench contract (docs/dataset-format.md).

Every problem is reported as a :class:`DatasetError` whose message names the
file, the column and the row (1-based data row; for CSV also the file line).
Writing goes to a temporary directory that replaces the target only when
complete, so a failed write never leaves a half-written dataset.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from pydantic import ValidationError

from .._atomic import atomic_dir
from .schema import FORMAT, Metadata

PROCESS_REQUIRED = ("run_id", "t_s", "axis_mm", "feed_mm_min")
PROCESS_OPTIONAL_NUMERIC = ("load_N", "spindle_rpm")
ERRORS_REQUIRED = ("run_id", "t_s", "target_mm", "error_um")
MAX_SAMPLE_GAP_S = 1.0  # the contract: >= 1 sample per second
TRAVEL_TOL_MM = 0.5


class DatasetError(ValueError):
    """A dataset does not meet the contract; the message says where and why."""


@dataclass
class Dataset:
    """A validated dataset: metadata plus the process stream and the measured errors."""

    metadata: Metadata
    process: pd.DataFrame
    errors: pd.DataFrame
    path: Path | None = None

    @property
    def run_ids(self) -> list[str]:
        return list(self.metadata.runs)

    @property
    def sensor_columns(self) -> list[str]:
        return [self.metadata.sensor_column(s) for s in self.metadata.sensors]

    def process_run(self, run_id: str) -> pd.DataFrame:
        return self.process[self.process["run_id"] == run_id].reset_index(drop=True)

    def errors_run(self, run_id: str) -> pd.DataFrame:
        return self.errors[self.errors["run_id"] == run_id].reset_index(drop=True)

    def content_hash(self) -> str:
        """SHA-256 over the metadata and both tables (what tracking records)."""
        h = hashlib.sha256()
        h.update(yaml.safe_dump(self.metadata.model_dump(mode="json"), sort_keys=True).encode())
        for df in (self.process, self.errors):
            h.update(pd.util.hash_pandas_object(df, index=False).values.tobytes())
            h.update(",".join(df.columns).encode())
        return h.hexdigest()[:16]


# ---------------------------------------------------------------- reading ---
def _find_table(root: Path, stem: str) -> Path:
    for ext in (".parquet", ".csv"):
        p = root / f"{stem}{ext}"
        if p.exists():
            return p
    raise DatasetError(f"{root}: missing {stem}.csv or {stem}.parquet")


def _read_table(path: Path) -> pd.DataFrame:
    try:
        if path.suffix == ".parquet":
            return pd.read_parquet(path)
        return pd.read_csv(path, dtype={"run_id": str}, keep_default_na=True)
    except Exception as exc:  # any parser/IO failure is the user's file
        raise DatasetError(f"{path}: unreadable ({type(exc).__name__}: {exc})") from None


def _where(path: Path, idx: int) -> str:
    row = idx + 1
    return f"row {row} (line {row + 1})" if path.suffix == ".csv" else f"row {row}"


def _numeric(df: pd.DataFrame, col: str, path: Path) -> None:
    s = df[col]
    if s.dtype == object or pd.api.types.is_string_dtype(s):
        conv = pd.to_numeric(s, errors="coerce")
        bad = conv.isna() & s.notna()
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: expected a number, got {s.iloc[i]!r}")
        df[col] = conv
    df[col] = df[col].astype(float)
    nan = df[col].isna().to_numpy()
    if nan.any():
        i = int(np.flatnonzero(nan)[0])
        raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: missing value (NaN)")
    inf = ~np.isfinite(df[col].to_numpy())
    if inf.any():
        i = int(np.flatnonzero(inf)[0])
        raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: value must be finite")


def _check_table(df: pd.DataFrame, path: Path, required: tuple[str, ...], runs: dict) -> None:
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DatasetError(f"{path}: missing column(s) {missing}; found {list(df.columns)}")
    if df.empty:
        raise DatasetError(f"{path}: no rows")
    rid = df["run_id"]
    if rid.isna().any():
        i = int(np.flatnonzero(rid.isna().to_numpy())[0])
        raise DatasetError(f"{path}: column 'run_id', {_where(path, i)}: missing value")
    df["run_id"] = rid.astype(str)
    unknown = ~df["run_id"].isin(list(runs))
    if unknown.any():
        i = int(np.flatnonzero(unknown.to_numpy())[0])
        raise DatasetError(
            f"{path}: column 'run_id', {_where(path, i)}: unknown run_id {df['run_id'].iloc[i]!r} "
            f"(metadata.yaml declares {sorted(runs)})"
        )
    for col in required[1:]:
        _numeric(df, col, path)


def _check_increasing(df: pd.DataFrame, path: Path) -> None:
    t = df["t_s"].to_numpy()
    same = df["run_id"].to_numpy()[1:] == df["run_id"].to_numpy()[:-1]
    bad = same & (np.diff(t) <= 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0]) + 1
        raise DatasetError(
            f"{path}: column 't_s', {_where(path, i)}: time must increase within run "
            f"{df['run_id'].iloc[i]!r} ({t[i - 1]} then {t[i]}); rows of a run must be contiguous and in time order"
        )
    # a run's rows must be contiguous
    starts = df["run_id"].to_numpy()[np.r_[True, ~same]]
    if len(starts) != len(set(starts)):
        dup = pd.Series(starts)[pd.Series(starts).duplicated()].iloc[0]
        raise DatasetError(f"{path}: column 'run_id': rows of run {dup!r} are not contiguous")


def load_metadata(root: Path) -> Metadata:
    path = root / "metadata.yaml"
    if not path.exists():
        raise DatasetError(f"{root}: missing metadata.yaml")
    try:
        raw = yaml.safe_load(path.read_text(encoding="utf-8"))
    except Exception as exc:
        raise DatasetError(f"{path}: unreadable YAML ({exc})") from None
    if not isinstance(raw, dict):
        raise DatasetError(f"{path}: expected a mapping at the top level")
    if raw.get("format") != FORMAT:
        raise DatasetError(f"{path}: key 'format': expected {FORMAT!r}, got {raw.get('format')!r}")
    try:
        return Metadata.model_validate(raw)
    except ValidationError as exc:
        e = exc.errors()[0]
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        raise DatasetError(f"{path}: key {loc!r}: {e['msg']} (got {e.get('input')!r})") from None


def load_dataset(path: str | Path) -> Dataset:
    """Read and validate a dataset directory; raise :class:`DatasetError` on any violation."""
    root = Path(path)
    if not root.is_dir():
        raise DatasetError(f"{root}: not a dataset directory")
    meta = load_metadata(root)
    ppath = _find_table(root, "process")
    epath = _find_table(root, "errors")
    process = _read_table(ppath)
    errors = _read_table(epath)

    sensor_cols = [meta.sensor_column(s) for s in meta.sensors]
    _check_table(process, ppath, PROCESS_REQUIRED + tuple(sensor_cols), meta.runs)
    for col in PROCESS_OPTIONAL_NUMERIC:
        if col in process.columns:
            _numeric(process, col, ppath)
    _check_increasing(process, ppath)
    neg = process["feed_mm_min"].to_numpy() < 0
    if neg.any():
        i = int(np.flatnonzero(neg)[0])
        raise DatasetError(
            f"{ppath}: column 'feed_mm_min', {_where(ppath, i)}: feed must be >= 0 (speed magnitude), "
            f"got {process['feed_mm_min'].iloc[i]}"
        )
    if "spindle_rpm" in process.columns and (process["spindle_rpm"] < 0).any():
        i = int(np.flatnonzero(process["spindle_rpm"].to_numpy() < 0)[0])
        raise DatasetError(f"{ppath}: column 'spindle_rpm', {_where(ppath, i)}: must be >= 0")
    t = process["t_s"].to_numpy()
    same = process["run_id"].to_numpy()[1:] == process["run_id"].to_numpy()[:-1]
    gap = same & (np.diff(t) > MAX_SAMPLE_GAP_S * 1.01)
    if gap.any():
        i = int(np.flatnonzero(gap)[0]) + 1
        raise DatasetError(
            f"{ppath}: column 't_s', {_where(ppath, i)}: gap of {t[i] - t[i - 1]:.3g} s; "
            f"the process stream needs >= 1 sample per second"
        )

    _check_table(errors, epath, ERRORS_REQUIRED, meta.runs)
    _check_increasing_errors(errors, epath)
    for run_id in meta.runs:
        pr = process[process["run_id"] == run_id]
        if pr.empty:
            raise DatasetError(f"{ppath}: run {run_id!r} (declared in metadata.yaml) has no rows")
        er_mask = (errors["run_id"] == run_id).to_numpy()
        if not er_mask.any():
            raise DatasetError(f"{epath}: run {run_id!r} (declared in metadata.yaml) has no rows")
        lo, hi = pr["axis_mm"].min(), pr["axis_mm"].max()
        _check_within(errors, epath, er_mask, "target_mm", lo - TRAVEL_TOL_MM, hi + TRAVEL_TOL_MM,
                      f"mm is outside the travel measured in {ppath.name} for run {run_id!r} ({lo:g}..{hi:g} mm)")
        tp0, tp1 = pr["t_s"].iloc[0], pr["t_s"].iloc[-1]
        _check_within(errors, epath, er_mask, "t_s", tp0, tp1,
                      f"s is outside the process log of run {run_id!r} ({tp0:g}..{tp1:g} s)")  # fmt: skip
    return Dataset(meta, process.reset_index(drop=True), errors.reset_index(drop=True), root)


def _check_within(df: pd.DataFrame, path: Path, rows: np.ndarray, col: str, lo: float, hi: float, why: str) -> None:
    """Among ``rows``, every value of ``col`` must lie in [lo, hi]."""
    v = df[col].to_numpy()
    out = rows & ((v < lo) | (v > hi))
    if out.any():
        i = int(np.flatnonzero(out)[0])
        raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: {v[i]:g} {why}")


def _check_increasing_errors(df: pd.DataFrame, path: Path) -> None:
    """Within a run, measurement times must not go backwards (equal times allowed
    only for distinct targets, e.g. an interferometer recording several at once)."""
    t = df["t_s"].to_numpy()
    same = df["run_id"].to_numpy()[1:] == df["run_id"].to_numpy()[:-1]
    bad = same & (np.diff(t) < 0)
    if bad.any():
        i = int(np.flatnonzero(bad)[0]) + 1
        raise DatasetError(
            f"{path}: column 't_s', {_where(path, i)}: time must not decrease within run "
            f"{df['run_id'].iloc[i]!r} ({t[i - 1]} then {t[i]})"
        )


# ---------------------------------------------------------------- writing ---
def save_dataset(ds: Dataset, path: str | Path, file_format: str = "csv") -> Path:
    """Write ``ds`` as a dataset directory, atomically (temporary dir, then rename)."""
    if file_format not in ("csv", "parquet"):
        raise ValueError(f"file_format must be 'csv' or 'parquet', got {file_format!r}")
    target = Path(path)
    meta = ds.metadata.model_dump(mode="json", exclude_none=True)
    with atomic_dir(target) as tmp:
        (tmp / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
        for name, df in (("process", ds.process), ("errors", ds.errors)):
            if file_format == "parquet":
                df.to_parquet(tmp / f"{name}.parquet", index=False)
            else:
                df.to_csv(tmp / f"{name}.csv", index=False)
    return target
