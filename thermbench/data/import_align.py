"""The mapped files on one clock: the process table (the alignment rule below) and the errors
table (docs/import.md "How the files are put on one clock").

Alignment (the documented rule): the process table takes the clock of one file (``align.base``,
default: the first file with process columns). Every other file's process columns are
brought onto those times:
- temperatures (``<sensor>_C``) by linear interpolation between the two neighbouring
  readings, and only where both lie within the file's ``max_gap_s`` of each other:
  never forward-filled over a long gap;
- every other column (operating inputs, positions) by the last reading at or before the
  time (``pandas.merge_asof``, direction backward, tolerance ``max_gap_s``): a CNC signal
  holds its value until it changes.
Process times outside the span that every process file covers are dropped (each file
must then overlap). Readings (errors) keep their own times, shifted by their file's offset.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from .import_columns import _filled
from .import_mapping import Mapping, MappingError
from .schema import Metadata


def _check_reading_times(frames: dict, process: pd.DataFrame) -> None:
    """Every reading within its run's process log: else one line naming the file's key
    (the usual cause is a clock offset)."""
    span = process.groupby("run_id")["t_s"].agg(["min", "max"])
    for fr in frames.values():
        if not (fr["wide"] or fr["long"]):
            continue
        for run in pd.unique(fr["run"]):
            if run not in span.index:
                raise MappingError(f"{fr['where']}: has readings of run {run!r}, which no process file has")
            sel = np.flatnonzero(fr["run"] == run)
            t = fr["t"][sel]
            lo, hi = span.loc[run, "min"], span.loc[run, "max"]
            out = (t < lo - 1e-9) | (t > hi + 1e-9)
            if out.any():
                i = int(np.flatnonzero(out)[0])
                raise MappingError(f"{fr['where']}: the reading of data row {sel[i] + 1} of {fr['path'].name} is at "
                                   f"{t[i]:g} s, outside the process log of run {run!r} ({lo:g}..{hi:g} s); check the "
                                   "files' offset_s and time columns")  # fmt: skip


def _file_gap(fr: dict) -> float:
    if fr["max_gap_s"] is not None:
        return float(fr["max_gap_s"])
    steps = np.diff(np.sort(fr["t"]))
    steps = steps[steps > 0]
    return 5.0 * float(np.median(steps)) if steps.size else np.inf


def _align_process(m: Mapping, frames: dict, meta: Metadata, path: Path) -> pd.DataFrame:
    with_proc = [n for n, fr in frames.items() if fr["proc"]]
    if not with_proc:
        raise MappingError(f"{path}: key 'files': no file maps a process column (temperatures, operating inputs, axis_mm)")
    base = m.align.base or with_proc[0]
    if base not in frames:
        raise MappingError(f"{path}: key 'align.base': {base!r} is not one of files ({sorted(frames)})")
    if base not in with_proc:
        raise MappingError(f"{path}: key 'align.base': file {base!r} maps no process column")
    seen: dict[str, str] = {}
    for n in with_proc:
        for col in frames[n]["proc"]:
            if col in seen:
                raise MappingError(f"{frames[n]['where']}.columns: {col!r} is mapped by files {seen[col]!r} and {n!r}; "
                                   "a dataset column comes from one file")  # fmt: skip
            seen[col] = n
    parts = []
    b = frames[base]
    present = dict.fromkeys(pd.unique(b["run"]))
    # the dataset's order (import_columns._run_order), not the rows'; a run the dataset does not declare
    # stays a run of its own (its rows are never taken for another's), and the validation names it
    runs = [r for r in meta.runs if r in present] + [r for r in present if r not in meta.runs]
    for run in runs:
        # (a one-run file in time order, a long log: its columns are taken as they are, not copied)
        sel = slice(None) if len(runs) == 1 else b["run"] == run
        t = b["t"][sel]
        order = slice(None) if np.all(np.diff(t) > 0) else np.argsort(t, kind="stable")
        t = t[order]
        if np.any(np.diff(t) <= 0):
            i = int(np.flatnonzero(np.diff(t) <= 0)[0])
            raise MappingError(f"{b['where']}.time.column: time {t[i]:g} s appears twice in run {run!r}")
        out = {"run_id": _filled(t.size, run), "t_s": t}
        for col, v in b["proc"].items():
            v = v[sel][order]
            if np.isnan(v).any():
                i = int(np.flatnonzero(np.isnan(v))[0])
                raise MappingError(f"{b['where']}.columns.{b['src'][col]!r}: empty at {t[i]:g} s of run {run!r}; the "
                                   "file whose clock the process table takes (align.base) needs every value")  # fmt: skip
            out[col] = v
        # first the span every process file covers: what lies outside is dropped, not filled in
        keep = np.ones(t.size, dtype=bool)
        others = {}
        for n in with_proc:
            if n == base:
                continue
            fr = frames[n]
            s = fr["run"] == run
            if not s.any():
                raise MappingError(f"{fr['where']}: has no rows of run {run!r}, which {base!r} has")
            o = np.argsort(fr["t"][s], kind="stable")
            ft = fr["t"][s][o]
            if np.any(np.diff(ft) <= 0):
                i = int(np.flatnonzero(np.diff(ft) <= 0)[0])
                raise MappingError(f"{fr['where']}.time.column: time {ft[i]:g} s appears twice in run {run!r}")
            keep &= (t >= ft[0]) & (t <= ft[-1])
            others[n] = (s, o, ft)
        for n, (s, o, ft_all) in others.items():
            fr = frames[n]
            gap = _file_gap(fr)
            for col, v_all in fr["proc"].items():
                v_all = v_all[s][o]
                ok = ~np.isnan(v_all)  # an empty cell is no reading: its neighbours are used
                ft, v = ft_all[ok], v_all[ok]
                if ft.size == 0:
                    raise MappingError(f"{fr['where']}.columns.{fr['src'][col]!r}: no value in run {run!r}")
                if col.endswith("_C"):
                    j = np.clip(np.searchsorted(ft, t, side="right"), 1, max(ft.size - 1, 1))
                    vals = np.interp(t, ft, v)
                    if ft.size > 1:
                        span = ft[j] - ft[j - 1]
                        near = (np.abs(t - ft[j - 1]) <= 1e-9) | (np.abs(t - ft[j]) <= 1e-9)
                        holes = keep & (span > gap * 1.01) & ~near
                    else:
                        holes = keep & (np.abs(t - ft[0]) > 1e-9)
                    if holes.any():
                        i = int(np.flatnonzero(holes)[0])
                        a, z = (ft[j[i] - 1], ft[j[i]]) if ft.size > 1 else (ft[0], ft[0])
                        raise MappingError(f"{fr['where']}: no {col} reading between {a:g} and {z:g} s of run {run!r} "
                                           f"({z - a:g} s apart, more than its max_gap_s {gap:g} s): it is not filled "
                                           "in over a long gap")  # fmt: skip
                else:
                    left = pd.DataFrame({"t_s": t})
                    right = pd.DataFrame({"t_s": ft, "v": v})
                    vals = pd.merge_asof(left, right, on="t_s", direction="backward", tolerance=gap)["v"].to_numpy()
                    miss = keep & np.isnan(vals)
                    if miss.any():
                        i = int(np.flatnonzero(miss)[0])
                        raise MappingError(f"{fr['where']}: no {col} reading within its max_gap_s {gap:g} s before "
                                           f"{t[i]:g} s of run {run!r}")  # fmt: skip
                out[col] = vals
        if not keep.any():
            spans = "; ".join(f"{n} {np.min(frames[n]['t'][frames[n]['run'] == run]):.6g}.."
                              f"{np.max(frames[n]['t'][frames[n]['run'] == run]):.6g} s" for n in with_proc)
            raise MappingError(f"{path}: key 'files': the process files of run {run!r} do not overlap in time ({spans}, "
                               "offsets applied); check each file's offset_s and time column (and its format)")  # fmt: skip
        part = pd.DataFrame(out, copy=False)
        parts.append(part if keep.all() else part[keep])
    return parts[0].reset_index(drop=True) if len(parts) == 1 else pd.concat(parts, ignore_index=True)


def _errors(frames: dict, channels: dict) -> pd.DataFrame:
    parts = []
    for fr in frames.values():
        for ch, v in fr["wide"].items():
            ok = ~np.isnan(v)  # an empty cell: no reading at that time
            parts.append(pd.DataFrame({"run_id": fr["run"][ok], "t_s": fr["t"][ok], "channel": ch, "error_um": v[ok]}))
        if fr["long"]:
            ch = fr["channel"] or next(iter(channels))
            d = {"run_id": fr["run"], "t_s": fr["t"], "channel": ch, **{k: v for k, v in fr["long"].items()}}
            parts.append(pd.DataFrame(d))
    if not parts:
        return pd.DataFrame()
    errors = pd.concat(parts, ignore_index=True)
    keys = ["run_id", "channel", "t_s"] + [c for c in ("target_mm", "direction") if c in errors.columns]
    errors = errors.sort_values(keys, kind="stable").reset_index(drop=True)  # whatever order the files' rows came in
    return errors
