"""Thermal error from interferometer data via the cold reference (seed 002 §3.1,
seed 004): the errors are not re-zeroed after the cold measurement, so the
thermal part at a target is the reading minus the mean of that target's
readings in the run's first measuring cycle(s) (the cold reference)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

if TYPE_CHECKING:  # the dataset is read here, never made: the class is named in annotations only
    from .dataset import Dataset


def measuring_cycles(t_s: np.ndarray, target_mm: np.ndarray, direction: np.ndarray | None = None) -> np.ndarray:
    """Cycle index of each reading of one run: a new cycle starts when a target
    (with ``direction``: a target in the same direction of approach, so that a forward
    and a backward pass make one cycle) repeats within the current cycle or after a
    pause longer than 2.5 times the median gap between readings."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(target_mm, dtype=float).tolist()
    d = [0.0] * len(x) if direction is None else np.asarray(direction, dtype=float).tolist()
    out = np.zeros(len(t), dtype=int)
    if len(t) < 2:
        return out
    typical = np.median(np.diff(t))
    seen: set[tuple[float, float]] = {(x[0], d[0])}
    c = 0
    for k in range(1, len(t)):
        key = (x[k], d[k])
        if key in seen or t[k] - t[k - 1] > 2.5 * typical:
            c += 1
            seen = set()
        seen.add(key)
        out[k] = c
    return out


def reading_cycles(er: pd.DataFrame) -> np.ndarray:
    """The measuring cycle of every reading of an errors table: :func:`measuring_cycles` per run
    (and channel), with the direction of approach when the table has one (a forward and a backward
    pass make one cycle). The one computation of cycles: :func:`thermal_errors` keeps it as the
    ``cycle`` column, and the reference, the models, the metrics and the reports read that."""
    out = np.zeros(len(er), dtype=int)
    if er.empty:
        return out
    keys = [c for c in ("run_id", "channel") if c in er.columns]
    t = er["t_s"].to_numpy(dtype=float)
    x = er["target_mm"].to_numpy(dtype=float) if "target_mm" in er.columns else np.zeros(len(er))
    d = er["direction"].fillna(0.0).to_numpy(dtype=float) if "direction" in er.columns else None
    groups = er.groupby(keys, sort=False).indices.values() if keys else [np.arange(len(er))]
    for idx in groups:
        out[idx] = measuring_cycles(t[idx], x[idx], None if d is None else d[idx])
    return out


def cold_reference(errors_run: pd.DataFrame) -> pd.Series:
    """Per target, the mean reading of the run's first measuring cycle (the cold
    reference, :func:`reading_cycles` cycle 0)."""
    cyc = reading_cycles(errors_run)
    return errors_run[cyc == 0].groupby("target_mm")["error_um"].mean()


def thermal_errors(ds: Dataset) -> pd.DataFrame:
    """The errors table with ``thermal_um`` = error - cold reference at the same target.

    Format 2 (:func:`thermal_errors_v2`): per channel, target and direction, with the
    dataset's reference rule. A channel view (:meth:`Dataset.channel_view`) carries its
    ``thermal_um`` already."""
    if "thermal_um" in ds.errors.columns:
        er = ds.errors.copy()
        return er if "cycle" in er.columns else er.assign(cycle=reading_cycles(er))
    if ds.metadata.version == 2:
        return thermal_errors_v2(ds)
    parts = []
    for run_id in ds.run_ids:
        er = ds.errors_run(run_id)
        cyc = reading_cycles(er)
        ref = er[cyc == 0].groupby("target_mm")["error_um"].mean()  # the cold reference (seed 002 §3.1)
        er = er.assign(thermal_um=er["error_um"] - er["target_mm"].map(ref).fillna(0.0).to_numpy(), cycle=cyc)
        parts.append(er)
    return pd.concat(parts, ignore_index=True)


def run_rows(df: pd.DataFrame, run_id: str) -> pd.DataFrame:
    """The rows of run ``run_id``, indexed from 0: :meth:`Dataset.process_run` of a process table,
    without a copy of them when they are one block (a long log of one run is not held twice)."""
    mask = (df["run_id"] == run_id).to_numpy()
    rows = block(mask) if mask.dtype == bool else None
    if rows is None:
        return df[df["run_id"] == run_id].reset_index(drop=True)
    return df.iloc[rows[0] : rows[1]].reset_index(drop=True)


def block(mask: np.ndarray) -> tuple[int, int] | None:
    """``(first, last + 1)`` of the rows a boolean ``mask`` selects when they are one block of at
    least one row; else None."""
    idx = np.flatnonzero(mask)
    if idx.size and idx[-1] - idx[0] + 1 == idx.size:
        return int(idx[0]), int(idx[-1]) + 1
    return None


def run_summary(ds: Dataset) -> pd.DataFrame:
    """One row per run: duration, condition, max |thermal error| measured (format 2:
    :func:`run_summary_v2`)."""
    if ds.metadata.version == 2:
        return run_summary_v2(ds)
    te = thermal_errors(ds)
    rows = []
    for run_id, run in ds.metadata.runs.items():
        pr = ds.process_run(run_id)
        tr = te[te["run_id"] == run_id]
        c = run.condition
        rows.append(
            {
                "run_id": run_id,
                "duration_h": float(pr["t_s"].iloc[-1] - pr["t_s"].iloc[0]) / 3600.0,
                "stroke_mm": c.stroke_mm,
                "start_mm": c.start_mm,
                "end_mm": c.end_mm,
                "feed_mm_min": c.feed_mm_min,
                "readings": len(tr),
                "max_thermal_error_um": float(tr["thermal_um"].abs().max()),
            }
        )
    return pd.DataFrame(rows)


def _group_keys(er: pd.DataFrame) -> pd.Series:
    """A reading's reference group: its target (fixed point: one group) and direction."""
    target = er["target_mm"] if "target_mm" in er.columns else pd.Series(0.0, index=er.index)
    key = target.fillna(0.0).astype(float).map(repr)
    if "direction" in er.columns:
        key = key + "/" + er["direction"].fillna(0.0).astype(float).map(repr)
    return key


def reference_values(er: pd.DataFrame, mode: str, t_ref_s: float | None, along_axis: bool,
                     cycles: np.ndarray | None = None) -> pd.Series:  # fmt: skip
    """The reference of each reading of one run and channel (format 2, docs/dataset-format.md
    "Reference"): per target and direction, the mean of the first measuring cycle
    (``cold_cycle``; a fixed-point channel's cycle is one reading), the first reading
    (``first_reading``) or the readings interpolated at ``t_ref_s`` (``time``; before
    the first reading its value, after the last the last)."""
    keys = _group_keys(er)
    ref = pd.Series(np.nan, index=er.index)
    if mode == "cold_cycle" and along_axis:
        cyc = reading_cycles(er) if cycles is None else cycles
        first = er[cyc == 0].groupby(keys[cyc == 0])["error_um"].mean()
        return keys.map(first)
    for _, idx in er.groupby(keys, sort=False).groups.items():
        g = er.loc[idx]
        if mode == "time":
            value = float(np.interp(t_ref_s, g["t_s"].to_numpy(), g["error_um"].to_numpy()))
        else:
            value = float(g["error_um"].iloc[0])
        ref.loc[idx] = value
    return ref


def thermal_errors_v2(ds: Dataset) -> pd.DataFrame:
    """Format 2: ``thermal_um`` = reading - reference (:func:`reference_values`) per run,
    channel, target and direction; ``reference_um`` is the reference itself. With a
    ``direction`` column each direction has its own reference, so the reversal value
    never enters the thermal error (it is reported by ``thermbench iso230``)."""
    er = ds.errors
    if er.empty:
        return er.assign(thermal_um=pd.Series(dtype=float), reference_um=pd.Series(dtype=float),
                         cycle=pd.Series(dtype=int))  # fmt: skip
    ref_meta = ds.metadata.reference_mode()
    channels = ds.metadata.error_channels()
    cycles = pd.Series(reading_cycles(er), index=er.index)
    ref = pd.Series(np.nan, index=er.index)
    for (_, ch), g in er.groupby(["run_id", "channel"], sort=False):
        ref.loc[g.index] = reference_values(g, ref_meta.mode, ref_meta.t_s, channels[ch].kind == "along_axis",
                                            cycles.loc[g.index].to_numpy())  # fmt: skip
    ref = ref.fillna(er["error_um"] * 0.0)  # a target missing from the cold cycle: the raw reading (format 1's rule)
    return er.assign(thermal_um=er["error_um"] - ref, reference_um=ref, cycle=cycles.to_numpy())


def run_summary_v2(ds: Dataset) -> pd.DataFrame:
    """Format 2: one row per run: duration, samples, median sample step, condition (or
    ``derived``), readings, and the max |thermal error| of each channel."""
    te = thermal_errors(ds)
    channels = ds.metadata.error_channels()
    rows = []
    for run_id, run in ds.metadata.runs.items():
        t = run_rows(ds.process, run_id)["t_s"].to_numpy()
        cond = run.condition.levels() if run.condition is not None else None
        row = {
            "run_id": run_id,
            "duration_h": float(t[-1] - t[0]) / 3600.0,
            "samples": len(t),
            "step_s": float(np.median(np.diff(t))) if len(t) > 1 else float("nan"),
            # no condition: derived from the operating signal's segments, or (none to segment by) its own state
            "condition": (", ".join(f"{k} {v:g}" for k, v in cond.items()) if cond
                          else "derived" if ds.metadata.operating_inputs() else "own state"),
            "readings": int((te["run_id"] == run_id).sum()) if len(te) else 0,
        }
        for ch, meta in channels.items():
            tr = te[(te["run_id"] == run_id) & (te["channel"] == ch)] if len(te) else te
            unit = "urad" if meta.unit == "urad" else "um"
            row[f"max_{ch}_{unit}"] = float(tr["thermal_um"].abs().max()) if len(tr) else float("nan")
        rows.append(row)
    return pd.DataFrame(rows)


def frame_text(meta) -> str:
    """The frame every score of a dataset is in (docs/dataset-format.md "Reference"): what a
    model predicts and a residual is measured against."""
    ref = meta.reference_mode()
    if meta.version == 1 or ref.mode == "cold_cycle":
        return "the error as read (each run's cold measuring cycle is the geometric error, seed 002 §3.1)"
    if ref.mode == "first_reading":
        return "each run's drift from its own first reading (per channel, target and direction)"
    return f"each run's drift from its readings at {ref.t_s:g} s"
