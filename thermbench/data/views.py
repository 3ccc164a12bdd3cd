"""Views of a format 2 dataset that the model families work on (docs/dataset-format.md,
"Format 2: what the models see").

- :func:`channel_view`: one error channel as a dataset of the format 1 shape: readings at
  ``target_mm`` (a fixed-point channel: the one position 0.0), ``thermal_um`` computed
  with the dataset's reference rule and per direction of approach, and ``error_um`` what the
  models predict and every score compares: with ``cold_cycle`` the reading as read (``thermal_um``
  + the run's reference at that target averaged over the directions, so a bidirectional run's
  reversal value is in neither); with ``first_reading`` or ``time`` the drift ``thermal_um``
  itself (each run's zero is its own: a first reading of 40 µm is not an error to predict). A process log without ``axis_mm`` / ``feed_mm_min`` (a
  spindle test) gets them as zeros: the spindle does not move an axis.
- :func:`split_segments`: every run without a declared condition becomes one run per
  segment derived from its operating signal (:mod:`thermbench.data.segments`), named
  by ``runs.<id>.segments`` or ``s01_1250rpm``, ...; a constant segment's condition is its
  level. A segment is a run of its own: :func:`channel_view` of the split dataset counts its
  thermal error from the reference rule applied to the segment (as if a test started there).
  With ``history=True`` a segment keeps its past instead: its process log starts where its
  run starts (the lead-in), its readings are the segment's own, and a channel view split this
  way keeps the whole run's ``thermal_um`` (``dataset.history``: temperature rises and thermal
  errors count from the start of the test; a dynamic model runs through the lead-in, and
  only the segment's readings are fitted and scored).
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
import pandas as pd

from .errors import DatasetError
from .reference import block, run_rows, thermal_errors
from .schema import Condition, RunMeta
from .segments import derive_segments, segment_name

if TYPE_CHECKING:  # a view is a copy of the dataset (dataclasses.replace): the class is named in annotations only
    from .dataset import Dataset

__all__ = ["channel_view", "split_segments"]

UNIT_NAMES = {"spindle_rpm": "rpm", "feed_mm_min": "mm_min", "load_N": "N"}


def channel_view(ds: Dataset, channel: str) -> Dataset:
    """The dataset as seen through one error channel (module docstring)."""
    channels = ds.metadata.error_channels()
    if channel not in channels:
        raise DatasetError(f"{ds.path or ds.metadata.machine.name}: no error channel {channel!r}; "
                           f"channels: {sorted(channels)}")  # fmt: skip
    if ds.metadata.version == 1:
        return ds
    te = thermal_errors(ds)
    er = te[te["channel"] == channel].copy() if len(te) else te.copy()
    if channels[channel].kind == "fixed_point" or "target_mm" not in er.columns:
        er["target_mm"] = 0.0
    if ds.metadata.reference_mode().mode == "cold_cycle":
        # the reading as read: per run and target, the reference (the cold cycle: the geometric
        # error, seed 002 §3.1) averaged over the directions of approach (each counted once)
        keys = ["run_id", "target_mm"] + (["direction"] if "direction" in er.columns else [])
        per_direction = er.groupby(keys, sort=False)["reference_um"].first()
        base = per_direction.groupby(level=["run_id", "target_mm"]).mean()
        idx = pd.MultiIndex.from_arrays([er["run_id"], er["target_mm"]])
        er["error_um"] = er["thermal_um"].to_numpy() + base.reindex(idx).to_numpy()
    else:  # first_reading / time: each run's zero is its own (a gauge set anew): what is measured is the drift
        er["error_um"] = er["thermal_um"].to_numpy()
    er = er[["run_id", "t_s", "target_mm", "error_um", "thermal_um", "channel", "cycle"]].reset_index(drop=True)
    process = ds.process.copy()
    for col in ("axis_mm", "feed_mm_min"):
        if col not in process.columns:
            process[col] = 0.0
    meta = ds.metadata.model_copy(update={"channels": {channel: channels[channel]}})
    return dataclasses.replace(ds, metadata=meta, process=process, errors=er, channel=channel)


def split_segments(ds: Dataset, history: bool = False) -> Dataset:
    """Each format 2 run without a condition split into its derived segments (module
    docstring); runs with a condition, runs of a dataset with no operating input to segment
    by (each run is then its own state), and format 1 datasets are kept as they are.

    ``history``: each segment's process log starts at its run's first sample (the lead-in
    before the segment's first reading: what the machine went through before it), its
    errors are those inside the segment only."""
    meta = ds.metadata
    if meta.version == 1 or all(r.condition is not None for r in meta.runs.values()):
        return ds
    inputs = meta.operating_inputs()
    if not inputs:  # nothing to segment by: each run is one loading state of its own, as it is
        return ds
    op = inputs[0]
    runs: dict[str, RunMeta] = {}
    p_parts, e_parts = [], []
    spans: list[tuple[int, int] | None] = []  # the rows of ds.process each part is, while it is a block of them
    for run_id, run in meta.runs.items():
        pr = run_rows(ds.process, run_id)
        er = ds.errors_run(run_id)
        mask = (ds.process["run_id"] == run_id).to_numpy()
        at = block(mask) if mask.dtype == bool else None  # where pr starts in ds.process, when it is a slice of it
        if run.condition is not None:
            runs[run_id] = run
            p_parts.append(pr)
            spans.append(at)
            e_parts.append(er)
            continue
        t = pr["t_s"].to_numpy()
        segs = derive_segments(t, pr[op].to_numpy(), **(meta.segmentation.kwargs() if meta.segmentation else {}))
        if not segs and not run.segments:  # too short to derive a segment from: the run as it is
            runs[run_id] = run
            p_parts.append(pr)
            spans.append(at)
            e_parts.append(er)
            continue
        names = run.segments or [segment_name(s, UNIT_NAMES.get(op, op)) for s in segs]
        if len(names) != len(segs):
            found = ", ".join(f"{s.start_s:g} s ({s.kind}{'' if s.level is None else f' {s.level:g}'})" for s in segs)
            raise DatasetError(f"{ds.path}/metadata.yaml: key 'runs.{run_id}.segments': names {len(names)} segments, "
                               f"but {len(segs)} were derived from {op} (starting at {found or 'none'})")  # fmt: skip
        for k, (seg, name) in enumerate(zip(segs, names)):
            if name in meta.runs and name != run_id or name in runs:
                raise DatasetError(f"{ds.path}/metadata.yaml: key 'runs.{run_id}.segments': {name!r} is already a run id")
            last = k == len(segs) - 1
            pm = (t >= (t[0] if history else seg.start_s)) & ((t <= seg.end_s) if last else (t < seg.end_s))
            et = er["t_s"].to_numpy()
            em = (et >= seg.start_s) & ((et <= seg.end_s) if last else (et < seg.end_s))
            cond = Condition(**{op: float(seg.level)}) if seg.kind == "constant" else None
            levels = ", ".join(f"{v:g}" for v in seg.levels)
            note = f"segment {k + 1} of run {run_id}: {op} {levels} from {seg.start_s:g} s to {seg.end_s:g} s"
            if history:
                note += f" (its log from {t[0]:g} s: the history before it)"
            runs[name] = RunMeta(condition=cond, notes=note)
            rows = block(pm)  # pr[pm], as a slice of pr when it is one block (no copy of a long log)
            p_parts.append((pr[pm] if rows is None else pr.iloc[rows[0] : rows[1]]).assign(run_id=name))
            spans.append(None if rows is None or at is None else (at[0] + rows[0], at[0] + rows[1]))
            e_parts.append(er[em].assign(run_id=name))
    new_meta = meta.model_copy(update={"runs": runs})
    pr = er = None  # (the last run's rows: not held while the split table is built)
    process = _stacked(ds.process, p_parts, spans)
    errors = pd.concat(e_parts, ignore_index=True) if e_parts else ds.errors.iloc[:0]
    return dataclasses.replace(ds, metadata=new_meta, process=process, errors=errors)


def _stacked(process: pd.DataFrame, parts: list[pd.DataFrame], spans: list) -> pd.DataFrame:
    """``pd.concat(parts, ignore_index=True)`` of the split runs' rows, each a block of rows of
    ``process`` (``spans``: ``(first, last + 1)``, None when it is not one), with a run id of its own.
    When the blocks follow one another and pandas copies on write (a table shared by two frames is
    copied before either changes it): those rows of ``process`` as they are, not a copy of a long log,
    with the parts' run ids; the same table."""
    follow = all(s is not None for s in spans) and all(a < b for a, b in spans) and all(
        spans[k][1] == spans[k + 1][0] for k in range(len(spans) - 1))  # fmt: skip
    if not (parts and follow and _copy_on_write()):
        return pd.concat(parts, ignore_index=True)
    run_id = pd.concat([p["run_id"] for p in parts], ignore_index=True)
    return process.iloc[spans[0][0] : spans[-1][1]].reset_index(drop=True).assign(run_id=run_id)


def _copy_on_write() -> bool:
    """Whether pandas copies a table shared by two frames before either changes it (always from
    pandas 3, by its option in pandas 2)."""
    try:
        return int(pd.__version__.split(".")[0]) >= 3 or pd.get_option("mode.copy_on_write") is True
    except (ValueError, KeyError):
        return False


def has_readings(ds: Dataset, run: str) -> bool:
    return bool(np.any(ds.errors["run_id"].to_numpy() == run)) if len(ds.errors) else False
