"""A read table's mapped columns as dataset columns: each source column found, its cells as
numbers (text codes mapped), its time column as seconds, its unit converted to the unit its
dataset column's name carries, its values checked against their plausible range; one table's
process, error and run columns, its run, and the tables of one file entry as one frame."""

from __future__ import annotations

import difflib
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from . import limits
from .errors import short_repr
from .import_mapping import ColumnMap, FileMap, Mapping, MappingError
from .schema import Metadata

# ------------------------------------------------------------------ units ---
# target suffix -> {source unit: (factor, offset)}: value_in_target = value * factor + offset
UNITS: dict[str, dict[str, tuple[float, float]]] = {
    "mm": {"mm": (1.0, 0.0), "m": (1e3, 0.0), "um": (1e-3, 0.0), "µm": (1e-3, 0.0), "in": (25.4, 0.0)},
    "um": {"um": (1.0, 0.0), "µm": (1.0, 0.0), "mm": (1e3, 0.0), "m": (1e6, 0.0), "nm": (1e-3, 0.0),
           "in": (25400.0, 0.0)},  # fmt: skip
    "mm_min": {"mm/min": (1.0, 0.0), "mm/s": (60.0, 0.0), "m/min": (1e3, 0.0), "m/s": (6e4, 0.0),
               "in/min": (25.4, 0.0)},  # fmt: skip
    "C": {"C": (1.0, 0.0), "°C": (1.0, 0.0), "K": (1.0, -273.15), "F": (5.0 / 9.0, -32.0 * 5.0 / 9.0),
          "°F": (5.0 / 9.0, -32.0 * 5.0 / 9.0)},  # fmt: skip
    "rpm": {"rpm": (1.0, 0.0), "1/min": (1.0, 0.0), "1/s": (60.0, 0.0), "Hz": (60.0, 0.0)},
    "N": {"N": (1.0, 0.0), "kN": (1e3, 0.0)},
    "s": {"s": (1.0, 0.0), "ms": (1e-3, 0.0), "min": (60.0, 0.0), "h": (3600.0, 0.0)},
    "urad": {"urad": (1.0, 0.0), "µrad": (1.0, 0.0), "mrad": (1e3, 0.0), "rad": (1e6, 0.0),
             "arcsec": (math.pi / 180 / 3600 * 1e6, 0.0), "um/m": (1.0, 0.0)},  # fmt: skip
}
ERROR_TARGETS = ("error_um", "target_mm", "direction")


def unit_of(name: str) -> str | None:
    """The unit a contract column's name carries (``feed_mm_min`` -> ``mm_min``)."""
    if name == "spindle_rpm":
        return "rpm"
    for suffix in sorted(UNITS, key=len, reverse=True):
        if name.endswith("_" + suffix):
            return suffix
    return None


def _column(df: pd.DataFrame, name: str, where: str, path: Path) -> pd.Series:
    if name in df.columns:
        return df[name]
    near = difflib.get_close_matches(name, list(df.columns), n=1, cutoff=0.6)
    hint = f"; did you mean {near[0]!r}?" if near else ""
    if not near and sum(str(c).startswith("Unnamed: ") for c in df.columns) >= max(1, len(df.columns) // 2):
        hint = "; the header read looks like a preamble line: check read.skip_rows (the lines before the header)"
    sheets = df.attrs.get("sheets")
    if not near and sheets and len(sheets) > 1:
        hint += f"; the workbook has sheets {sheets}: choose one with read.sheet"
    shown = ", ".join(repr(c) for c in list(df.columns)[:12]) + (", ..." if len(df.columns) > 12 else "")
    raise MappingError(f"{where}: column {name!r} is not in {path.name} (columns: {shown}){hint}")


def _numbers(s: pd.Series, where: str, path: Path, codes: dict | None = None, decimal: str = ".") -> np.ndarray:
    if codes is not None:
        mapped = s.map(lambda v: codes.get(v, codes.get(str(v).strip(), np.nan)) if pd.notna(v) else np.nan)
        bad = mapped.isna() & s.notna()
        if bad.any():
            i = int(np.flatnonzero(bad.to_numpy())[0])
            raise MappingError(f"{where}.map: value {short_repr(s.iloc[i])} (data row {i + 1} of {path.name}) is not "
                               f"mapped; map has {sorted(map(str, codes))}")  # fmt: skip
        return mapped.to_numpy(dtype=float)
    if pd.api.types.is_bool_dtype(s.dtype):
        raise MappingError(f"{where}: column holds true/false values in {path.name}; expected numbers")
    if pd.api.types.is_float_dtype(s.dtype):  # read as numbers already: taken as it is (no copy of a long log)
        return s.to_numpy(dtype=float, copy=False)
    text = s
    if decimal != "." and (s.dtype == object or pd.api.types.is_string_dtype(s.dtype)):
        # a column pandas left as text (one bad cell in it): its numbers still have the declared decimal mark
        text = s.map(lambda v: v.strip().replace(decimal, ".") if isinstance(v, str) else v)
    conv = pd.to_numeric(text, errors="coerce")
    bad = conv.isna() & s.notna()
    if bad.any():
        i = int(np.flatnonzero(bad.to_numpy())[0])
        hint = ""
        if decimal == "." and isinstance(s.iloc[i], str) and re.fullmatch(r"\s*-?\d+,\d+\s*", s.iloc[i]):
            hint = "; it has a decimal comma: add read: {decimal: ','}"
        raise MappingError(f"{where}: data row {i + 1} of {path.name} holds {short_repr(s.iloc[i])}, not a number{hint}")
    return conv.to_numpy(dtype=float)


def _times(df: pd.DataFrame, f: FileMap, where: str, path: Path) -> tuple[np.ndarray, bool | str]:
    """The file's time column as seconds (timestamps: since the epoch, UTC when they carry a
    time zone) and its kind: False (numbers), "aware" or "naive" (timestamps). With no time
    column (``time.step_s``): data row k at ``start_s + k * step_s``."""
    tm = f.time
    if tm.step_s is not None:
        other = [k for k in ("column", "unit", "format") if getattr(tm, k) is not None]
        if other:
            raise MappingError(f"{where}.time: give either column (a time column) or step_s (a constant step, no "
                               f"time column), not both ({other[0]} and step_s)")  # fmt: skip
        return tm.start_s + df.index.to_numpy(dtype=float) * tm.step_s + f.offset_s, False
    if tm.column is None:
        raise MappingError(f"{where}.time: give column (the file's time column) or, with no time column, step_s "
                           "(rows step_s seconds apart)")  # fmt: skip
    cols = [f.time.column] if isinstance(f.time.column, str) else list(f.time.column)
    if not cols:
        raise MappingError(f"{where}.time.column: an empty list; name the time column (or a date and a time column)")
    parts = [_column(df, c, f"{where}.time.column", path) for c in cols]
    if len(parts) == 1:
        s = parts[0]
    else:
        if f.time.format is None:
            raise MappingError(f"{where}.time.format: the cells of {cols} are joined with a space into one "
                               "timestamp: give its format, e.g. \"%d.%m.%Y %H:%M:%S\"")  # fmt: skip
        s = parts[0].map(_cell_text)
        for extra in parts[1:]:
            s = s + " " + extra.map(_cell_text)
    if f.time.format is not None or pd.api.types.is_datetime64_any_dtype(s.dtype):
        if f.time.unit is not None:
            raise MappingError(f"{where}.time.unit: timestamps have no unit; give either unit (numbers) or format")
        if pd.api.types.is_datetime64_any_dtype(s.dtype):
            ts = s
        else:
            fmt = None if f.time.format in (None, "iso") else f.time.format
            ts = pd.to_datetime(s, format=fmt if fmt else "ISO8601", errors="coerce", dayfirst=f.time.dayfirst)
            bad = ts.isna() & s.notna()
            if bad.any():
                i = int(np.flatnonzero(bad.to_numpy())[0])
                raise MappingError(f"{where}.time.format: data row {i + 1} of {path.name}, {short_repr(s.iloc[i])}, "
                                   f"does not match {f.time.format!r}")  # fmt: skip
        aware = getattr(ts.dt, "tz", None) is not None
        if aware:
            ts = ts.dt.tz_convert("UTC").dt.tz_localize(None)
        ns = ts.to_numpy(dtype="datetime64[ns]").astype(np.int64).astype(float)
        if np.isnan(ts.to_numpy(dtype="datetime64[ns]").astype(float)).any() or ts.isna().any():
            i = int(np.flatnonzero(ts.isna().to_numpy())[0])
            raise MappingError(f"{where}.time.column: data row {i + 1} of {path.name} has no time")
        return ns / 1e9 + f.offset_s, "aware" if aware else "naive"
    factor, _ = UNITS["s"].get(f.time.unit or "s", (None, None))
    if factor is None:
        raise MappingError(f"{where}.time.unit: unknown unit {f.time.unit!r}; known: {', '.join(UNITS['s'])}")
    try:
        t = _numbers(s, f"{where}.time.column", path, decimal=f.read.decimal)
    except MappingError as exc:
        first = s.dropna().iloc[0] if s.notna().any() else None
        if isinstance(first, str) and not pd.isna(pd.to_datetime(first, errors="coerce", format="mixed")):
            raise MappingError(f"{exc}; it looks like a timestamp: give time.format (a strftime format, or iso)") from None
        raise
    if np.isnan(t).any():
        i = int(np.flatnonzero(np.isnan(t))[0])
        raise MappingError(f"{where}.time.column: data row {i + 1} of {path.name} has no time")
    return t * factor + f.offset_s, False


def _cell_text(v) -> str:
    """A cell as text for joining a date and a time column (an Excel date or time cell is a
    datetime / time object: written the ISO way, which the format must then match)."""
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return ""
    if isinstance(v, pd.Timestamp):
        return v.strftime("%Y-%m-%d") if v == v.normalize() else v.isoformat(sep=" ")
    return str(v).strip()


def _convert(values: np.ndarray, cm: ColumnMap, target: str, where: str) -> np.ndarray:
    if cm.unit is not None:
        unit = unit_of(target)
        if unit is None:
            raise MappingError(f"{where}.unit: {target!r} carries no unit to convert to; use scale/offset")
        table = UNITS[unit]
        if cm.unit not in table:
            raise MappingError(f"{where}.unit: cannot convert {cm.unit!r} to {unit.replace('_', '/')}; "
                               f"known: {', '.join(table)}")  # fmt: skip
        factor, off = table[cm.unit]
        if (factor, off) != (1.0, 0.0):
            values = values * factor + off
    if (cm.scale, cm.offset) != (1.0, 0.0):  # (an identity makes no copy: a long log's columns are large)
        values = values * cm.scale + cm.offset
    return np.abs(values) if cm.abs else values


RANGES = {"error_um": limits.ERROR_UM, "error_urad": limits.TILT_URAD, "target_mm": limits.POSITION_MM,
          "axis_mm": limits.POSITION_MM, "feed_mm_min": limits.FEED_MM_MIN, "spindle_rpm": limits.SPINDLE_RPM,
          "load_N": limits.LOAD_N}  # fmt: skip


def _check_range(values: np.ndarray, target: str, cm: ColumnMap, where: str, path: Path) -> None:
    """The converted values in the plausible range of ``target`` (a temperature: of °C); else one
    line naming the mapping key: the usual cause is a wrong or missing ``unit``."""
    q = limits.TEMPERATURE_C if target.endswith("_C") else RANGES.get(target)
    if q is None:
        return
    v = np.asarray(values, dtype=float)
    bad = ~np.isnan(v) & ~((v >= q.lo) & (v <= q.hi))
    if q.lo == 0.0 and target != "feed_mm_min":
        bad &= v < 0  # speeds: only negative values (the upper bound is checked at validation)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        given = f"unit: {cm.unit}" if cm.unit else "no unit (the column taken as already in the target's unit)"
        fix = ("a signed velocity needs abs: true" if v[i] < 0 and target in ("feed_mm_min", "spindle_rpm")
               else f"the mapping gives {given}: check the column's unit (and scale)")  # fmt: skip
        key = f"{where}.unit" if cm.unit and not (v[i] < 0 and target in ("feed_mm_min", "spindle_rpm")) else where
        raise MappingError(f"{key}: data row {i + 1} of {path.name} becomes {v[i]:.6g} {q.unit} as {target}, outside "
                           f"{q.range_text()}; {fix}")  # fmt: skip


def _target_ok(target: str, meta: Metadata, where: str) -> None:
    sensors = {meta.sensor_column(s) for s in meta.sensors}
    known = {"axis_mm", "run_id", *ERROR_TARGETS, *meta.operating_inputs(), "feed_mm_min", "spindle_rpm", "load_N"}
    if target == "axis_mm" and not meta.has_axis:
        raise MappingError(f"{where}: axis_mm is the position of a linear axis; dataset.parts {meta.parts} has none "
                           "(add axis to it, or leave the column out)")  # fmt: skip
    if target == "feed_mm_min" and not meta.has_axis and "feed_mm_min" not in meta.operating_inputs():
        raise MappingError(f"{where}: feed_mm_min is the feed of a linear axis; dataset.parts {meta.parts} has none "
                           "(add axis to parts, or feed_mm_min to dataset.operating)")  # fmt: skip
    if target in sensors or target in known:
        return
    if target.endswith("_C"):
        raise MappingError(f"{where}: {target!r} is a temperature column, but dataset.sensors declares no sensor "
                           f"{target[:-2]!r} (declared: {sorted(meta.sensors)})")  # fmt: skip
    near = difflib.get_close_matches(target, sorted(known | sensors), n=1)
    hint = f"; did you mean {near[0]!r}?" if near else ""
    raise MappingError(f"{where}: {target!r} is not a dataset column (a sensor <name>_C, an operating input of "
                       f"dataset.operating, axis_mm, error_um, target_mm, direction, run_id){hint}")  # fmt: skip


def _as_run_id(name: str, where: str, what: str) -> str:
    """A sheet name or file stem made a valid run id (characters outside the rule become _)."""
    rid = re.sub(r"[^A-Za-z0-9_.-]+", "_", name.strip()).strip("._-")[: limits.RUN_ID_MAX_LEN].rstrip(".")
    problem = limits.run_id_problem(rid)
    if problem is not None:
        raise MappingError(f"{where}.run: {what} {name!r} makes no valid run id ({rid!r} {problem}); name it with "
                           f"run: {{map: {{{name!r}: <run id>}}}}")  # fmt: skip
    return rid


def _piece_run(f: FileMap, path: Path, sheet: str | None, where: str) -> str | None:
    """The run every row of this file (sheet) belongs to, when the mapping says so."""
    if f.run is None:
        return None
    if isinstance(f.run, str):
        problem = limits.run_id_problem(f.run)
        if problem is not None:
            raise MappingError(f"{where}.run: run id {f.run!r} {problem}")
        return f.run
    if f.run.from_ == "sheet":
        if sheet is None:
            raise MappingError(f"{where}.run.from: sheet names runs after an Excel workbook's sheets; {path.name} "
                               "has none (one run per file: from: file)")  # fmt: skip
        name, what = sheet, "sheet"
    else:
        name, what = path.stem, "file"
    if f.run.map is not None:
        if name not in f.run.map:
            raise MappingError(f"{where}.run.map: has no entry for {what} {name!r} (it maps {sorted(f.run.map)})")
        rid = f.run.map[name]
        problem = limits.run_id_problem(rid)
        if problem is not None:
            raise MappingError(f"{where}.run.map.{name}: run id {rid!r} {problem}")
        return rid
    return _as_run_id(name, where, what)



def _piece_columns(df: pd.DataFrame, f: FileMap, src: Path, where: str, meta: Metadata, channels: dict, m: Mapping,
                   run: str | None, declared: bool) -> dict:  # fmt: skip
    """One table's mapped columns: process columns, wide and long error columns, its runs."""
    proc: dict[str, np.ndarray] = {}
    sources: dict[str, str] = {}  # dataset column -> the file's column (for messages)
    file_channel = f.channel or (next(iter(channels)) if len(channels) == 1 else None)
    if file_channel is not None and file_channel not in channels:
        raise MappingError(f"{where}.channel: {file_channel!r} is not declared in dataset.channels ({sorted(channels)})")
    wide: dict[str, np.ndarray] = {}
    long: dict[str, np.ndarray] = {}
    run_col = None
    for key, spec in f.columns.items():
        col = str(key)
        cw = f"{where}.columns.{col!r}"
        cm = ColumnMap(to=spec) if isinstance(spec, str) else spec
        if (cm.to is None) == (cm.channel is None):
            raise MappingError(f"{cw}: give either to: <dataset column> or channel: <error channel>")
        if isinstance(key, int) and f.read.header is not False:
            raise MappingError(f"{cw}: a column by position (a number) needs read: {{header: false}}; with a header "
                               "row, name the column (quote a numeric name: \"0\":)")  # fmt: skip
        s = _column(df, col, cw, src)
        if cm.to == "run_id":
            if run is not None:
                raise MappingError(f"{cw}: files.<name>.run already names this file's run; map no run_id column")
            run_col = s.astype(str).str.strip().to_numpy()
            unknown = [r for r in pd.unique(run_col) if r not in meta.runs] if declared else []
            if unknown:
                raise MappingError(f"{cw}: {src.name} holds run(s) {unknown[:5]} that "
                                   f"dataset.runs does not declare (it declares {sorted(meta.runs)})")  # fmt: skip
            bad = [(r, limits.run_id_problem(r)) for r in pd.unique(run_col) if limits.run_id_problem(r) is not None]
            if bad:
                raise MappingError(f"{cw}: {src.name} holds run id {bad[0][0]!r}, which {bad[0][1]}")
            continue
        values = _numbers(s, cw, src, None if cm.map is None else {k: float(v) for k, v in cm.map.items()}, f.read.decimal)
        if cm.channel is not None:
            if cm.channel not in channels:
                raise MappingError(f"{cw}: channel {cm.channel!r} is not declared in dataset.channels "
                                   f"({sorted(channels)})")  # fmt: skip
            if channels[cm.channel].kind != "fixed_point":
                raise MappingError(f"{cw}: channel {cm.channel!r} is along_axis: its readings need target_mm; "
                                   "map error_um, target_mm (and direction) columns and name the channel "
                                   f"with {where.split('key ')[-1]}.channel")  # fmt: skip
            unit = "urad" if channels[cm.channel].unit == "urad" else "um"
            wide[cm.channel] = _convert(values, cm, f"error_{unit}", cw)
            _check_range(wide[cm.channel], f"error_{unit}", cm, cw, src)
            continue
        _target_ok(cm.to, meta, cw)
        target = cm.to
        if cm.to == "error_um" and file_channel is not None and channels[file_channel].unit == "urad":
            target = "error_urad"  # a tilt channel's readings: converted to µrad, checked as tilts
        v = _convert(values, cm, target, cw)
        _check_range(v, target, cm, cw, src)
        (long if cm.to in ERROR_TARGETS else proc)[cm.to] = v
        sources[cm.to] = col
    if long and "error_um" not in long:
        raise MappingError(f"{where}.columns: maps {sorted(long)} but no column to error_um")
    if long:
        ch = f.channel or (next(iter(channels)) if len(channels) == 1 else None)
        if ch is None or ch not in channels:
            raise MappingError(f"{where}.channel: name the error channel of this file's readings "
                               f"(one of {sorted(channels)})")  # fmt: skip
        if channels[ch].kind == "along_axis" and "target_mm" not in long:
            raise MappingError(f"{where}.columns: channel {ch!r} is along_axis: map a column to target_mm")
    elif f.channel is not None:
        raise MappingError(f"{where}.channel: this file maps no error_um column")
    if run_col is None:
        if run is None and m.run is None and (len(meta.runs) > 1 or not declared):
            raise MappingError(f"{where}: name the run(s) of its rows: run: <run id> or run: {{from: sheet | file}} "
                               "(or a column mapped to run_id)")  # fmt: skip
        run_col = _filled(len(df), run or m.run or next(iter(meta.runs)))
    return {"run": run_col, "proc": proc, "wide": wide, "long": long, "src": sources}


def _filled(n: int, value) -> np.ndarray:
    """``n`` times ``value`` as an object array: the one object in every row (``np.full`` would
    make ``n`` copies of a text, some 70 bytes each: 180 MB for a month at 1 Hz)."""
    out = np.empty(n, dtype=object)
    out.fill(value)
    return out


def _run_order(pieces: list) -> list[str]:
    """The runs of one file entry in the order a person reads its tables: table by table (sheets in the
    workbook's order, the files of a glob in natural order), and within one table (a run column) by each
    run's first time, then by the natural order of the run ids (:func:`~thermbench.data.limits.natural_key`),
    never by the order its rows happen to come in."""
    order: dict[str, None] = {}
    for _src, _label, t, fr in pieces:
        runs = pd.unique(fr["run"])
        if len(runs) > 1:
            first = pd.Series(np.asarray(t, dtype=float)).groupby(pd.Series(fr["run"]), sort=False).min()
            runs = sorted(runs, key=lambda r: (float(first[r]), limits.natural_key(r)))
        order.update(dict.fromkeys(runs))
    return list(order)


def _merge_pieces(pieces: list, f: FileMap, where: str) -> dict:
    """The tables of one file entry (its files, its sheets), ``(path, label, t, columns)`` each, as
    one frame. Rows of one run from two tables counted from ``time.start_s`` each would be two
    logs on one clock: refused."""
    seen: dict[str, str] = {}
    for _src, label, _t, fr in pieces:
        for r in pd.unique(fr["run"]):
            if r in seen and seen[r] != label and f.time.step_s is not None:
                raise MappingError(f"{where}: run {r!r} comes from both {seen[r]} and {label}, each counted from "
                                   "time.start_s; one run per table: run: {from: sheet} or {from: file}")  # fmt: skip
            seen.setdefault(r, label)

    def cat(xs):  # (one table, a long log: its arrays as they are)
        return xs[0] if len(xs) == 1 else np.concatenate(xs) if xs else np.zeros(0)

    out = {"t": cat([p[2] for p in pieces]), "run": cat([p[3]["run"] for p in pieces]).astype(object, copy=False),
           "runs": _run_order(pieces)}
    for part in ("proc", "wide", "long"):
        cols = pieces[0][3][part].keys()
        out[part] = {c: cat([p[3][part][c] for p in pieces]) for c in cols}
    out.update({"channel": f.channel, "src": pieces[0][3]["src"], "where": where, "max_gap_s": f.max_gap_s,
                "path": pieces[0][0] if len(pieces) == 1 else Path(f.path)})  # fmt: skip
    return out
