"""``thermbench import MAPPING.yaml --out DIR``: a lab's own files to a format 2 dataset
(docs/import.md).

One YAML mapping file describes the user's files (CSV, Excel, Parquet), how to read
them (separator, decimal comma, encoding, preamble lines, sheet), their clocks (seconds
or timestamps, a clock offset each), and what each column is in the dataset contract,
with unit conversions. Nothing is written but the dataset, and only after it validates.

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

import difflib
import glob as globmod
import math
import os
import re
import time
import warnings
from pathlib import Path
from typing import Any, Literal, Optional, Union

import numpy as np
import pandas as pd
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..errors import UserError
from ..outputs import check_output_dir, output_dir
from . import limits
from .errors import DatasetError, short_repr
from .files import check_regular_file, open_regular_file
from .io import load_dataset
from .reference import run_summary
from .safe_yaml import YAMLInputError, dump_yaml, load_yaml
from .schema import FORMAT_V2, Metadata, RunMeta
from .tables import CSV_NA_VALUES, validation_message
from .views import split_segments

MAPPING_FORMAT = "thermbench-import/1"
MAPPING_MAX_BYTES = limits.METADATA_MAX_BYTES


class MappingError(UserError):
    """A mistake in an import mapping or in the files it names: one line naming the key."""


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
#: files from this size on are announced as they are read (a large import says what it is doing)
PROGRESS_MIN_BYTES = 32 * 1024 * 1024


def unit_of(name: str) -> str | None:
    """The unit a contract column's name carries (``feed_mm_min`` -> ``mm_min``)."""
    if name == "spindle_rpm":
        return "rpm"
    for suffix in sorted(UNITS, key=len, reverse=True):
        if name.endswith("_" + suffix):
            return suffix
    return None


# ---------------------------------------------------------------- mapping ---
class _M(BaseModel):
    model_config = ConfigDict(extra="forbid")


class ColumnMap(_M):
    """What one source column becomes."""

    to: Optional[str] = None  # a contract column: t1_C, spindle_rpm, axis_mm, error_um, ...
    channel: Optional[str] = None  # a wide error column: its readings belong to this channel
    unit: Optional[str] = None  # the source unit, converted to the unit of `to`'s name
    scale: float = 1.0  # then value * scale + offset (a sensor gain, a sign)
    offset: float = 0.0
    abs: bool = False  # signed velocity -> feed magnitude
    map: Optional[dict[Union[str, int, float], float]] = None  # text codes -> numbers (direction: fwd -> 1)


class TimeMap(_M):
    column: Optional[Union[str, list[str]]] = None  # a list: the cells joined with a space (a date and a time column)
    unit: Optional[str] = None  # numbers: s (default), ms, min, h
    format: Optional[str] = None  # timestamps: a strftime format, or "iso"
    dayfirst: bool = False
    step_s: Optional[float] = Field(None, gt=0)  # no time column: data row k of a run is at start_s + k * step_s
    start_s: float = 0.0


class ReadOptions(_M):
    sheet: Optional[Union[str, int]] = None  # Excel: the sheet name or 0-based index (default the first)
    sheets: Optional[Union[Literal["all"], list[str]]] = None  # Excel: several sheets, read one after another
    header: Optional[bool] = None  # False: no header row, columns named by 0-based position
    sep: Optional[str] = None  # CSV: the separator (default ",")
    decimal: str = "."
    thousands: Optional[str] = None
    encoding: str = "utf-8"
    skip_rows: int = Field(0, ge=0)  # preamble lines before the header
    skip_after_header: int = Field(0, ge=0)  # rows between the header and the data (a units row)


class RunFrom(_M):
    """Runs named after the workbook's sheets or the files a glob matched (one run each)."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)
    from_: Literal["sheet", "file"] = Field(alias="from")
    map: Optional[dict[str, str]] = None  # sheet name / file stem -> run id (default: the name made a valid run id)


class FileMap(_M):
    path: str  # a glob (*, ?, [...]) names several files, read in name order
    format: Optional[Literal["csv", "excel", "parquet"]] = None  # default: from the suffix
    read: ReadOptions = ReadOptions()
    time: TimeMap
    run: Optional[Union[str, RunFrom]] = None  # the run of every row, or one run per sheet / file
    offset_s: float = 0.0  # added to this file's clock: what makes it agree with the others
    max_gap_s: Optional[float] = Field(None, gt=0)  # default: 5 x the file's median step
    channel: Optional[str] = None  # a long errors file (error_um, target_mm): its channel
    columns: dict[Union[int, str], Union[str, ColumnMap]]  # a column by its header, or by 0-based position

    @field_validator("columns")
    @classmethod
    def _nonempty(cls, v):
        if not v:
            raise ValueError("maps no column")
        return v


class AlignMap(_M):
    base: Optional[str] = None


class Mapping(_M):
    format: str
    dataset: dict[str, Any]
    run: Optional[str] = None
    files: dict[str, FileMap]
    align: AlignMap = AlignMap()


def _key(loc) -> str:
    return ".".join(str(p) for p in loc if p != "[key]")


def read_mapping(path: Path) -> tuple[Mapping, dict]:
    """The mapping file, validated; :class:`MappingError` naming the key on any mistake."""
    if not os.path.lexists(path):
        raise MappingError(f"{path}: no such mapping file (relative paths start from the current directory, "
                           f"{Path.cwd()})")  # fmt: skip
    try:
        check_regular_file(path, MAPPING_MAX_BYTES, "a mapping file")
        with open_regular_file(path, MAPPING_MAX_BYTES, "a mapping file") as fh:
            text = fh.read().decode("utf-8-sig")
        raw, lines = load_yaml(text)
    except (DatasetError, YAMLInputError) as exc:
        raise MappingError(str(exc) if str(exc).startswith(str(path)) else f"{path}: {exc}") from None
    except UnicodeDecodeError:
        raise MappingError(f"{path}: not UTF-8 text; save the mapping file as UTF-8") from None
    if not isinstance(raw, dict):
        raise MappingError(f"{path}: expected a mapping with keys format, dataset, files")
    if raw.get("format") != MAPPING_FORMAT:
        raise MappingError(f"{path}: key 'format': expected {MAPPING_FORMAT!r}, got {short_repr(raw.get('format'))}")
    try:
        m = Mapping.model_validate(raw)
    except ValidationError as exc:
        errs = exc.errors()
        # a misspelt key is also a missing one: name the misspelling (with its suggestion)
        e = next((x for x in errs if x["type"] == "extra_forbidden"), errs[0])
        loc = tuple(p for p in e["loc"] if p != "[key]")
        # a union's error location names the branch tried (str, ColumnMap, ...): drop it
        loc = tuple(p for p in loc if not _is_branch(p))
        at = _line(lines, loc)
        msg = str(e["msg"]).removeprefix("Value error, ")
        expected = _EXPECTED.get(str(loc[-1]) if loc else "", _EXPECTED.get(str(loc[-2]) if len(loc) > 1 and loc[-2] == "columns" else "", None))
        if e["type"] == "missing" and loc and loc[-1] == "time":
            raise MappingError(f"{path}: key {_key(loc)!r}: missing: give time: {{column: NAME}} (the file's time "
                               f"column) or, with no time column, time: {{step_s: S}} (rows S seconds apart){at}") from None  # fmt: skip
        if expected is not None and e["type"] not in ("missing", "extra_forbidden"):
            raise MappingError(f"{path}: key {_key(loc)!r}: expected {expected}, got {short_repr(e.get('input'))}{at}") from None
        if e["type"] == "extra_forbidden":
            known = _known_keys(loc[:-1])
            near = difflib.get_close_matches(str(loc[-1]), known, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else (f"; known keys: {', '.join(known)}" if known else "")
            raise MappingError(f"{path}: key {_key(loc)!r}: unknown key{hint}{at}") from None
        if e["type"] == "missing":
            raise MappingError(f"{path}: key {_key(loc)!r}: missing (required){at}") from None
        raise MappingError(f"{path}: key {_key(loc)!r}: {msg} (got {short_repr(e.get('input'))}){at}") from None
    return m, lines


#: what a key takes, said instead of pydantic's text when its value has the wrong type
_EXPECTED = {
    "sheet": "one sheet, by name or 0-based index (several sheets: read: {sheets: all} or sheets: [names])",
    "sheets": "all, or a list of sheet names",
    "header": "true or false (false: no header row; columns by 0-based position)",
    "run": "a run id, or {from: sheet} / {from: file} (one run per sheet or file; map: renames them)",
    "from": "sheet or file",
    "step_s": "a time step in seconds, > 0",
    "columns": "a dataset column (t1_C, axis_mm, ...) or {to: ..., unit: ...} / {channel: ..., unit: ...}",
}


def _is_branch(p) -> bool:
    """A part of a pydantic error location that names a union branch or a validator, not a key."""
    return isinstance(p, str) and (p in ("str", "int", "float", "ColumnMap", "RunFrom") or p.startswith(("function-", "literal[", "list[", "dict[")))


def _known_keys(loc: tuple) -> list[str]:
    """The keys allowed where ``loc`` points (for the did-you-mean of an unknown key)."""
    if not loc:
        return list(Mapping.model_fields)
    if loc[0] == "files" and len(loc) == 2:
        return list(FileMap.model_fields)
    if loc[0] == "files" and len(loc) >= 3 and loc[2] in ("read", "time"):
        return list((ReadOptions if loc[2] == "read" else TimeMap).model_fields)
    if loc[0] == "files" and len(loc) >= 3 and loc[2] == "run":
        return ["from", "map"]
    if loc[0] == "files" and len(loc) >= 4 and loc[2] == "columns":
        return list(ColumnMap.model_fields)
    if loc[0] == "align":
        return list(AlignMap.model_fields)
    return []


def _line(lines: dict, loc: tuple) -> str:
    for k in range(len(loc), 0, -1):
        if tuple(loc[:k]) in lines:
            return f" (line {lines[tuple(loc[:k])]})"
    return ""


# ------------------------------------------------------------------ files ---
def _source_paths(f: FileMap, base_dir: Path, where: str) -> list[Path]:
    """The file ``path`` names, or every file its glob matches (in name order)."""
    raw = os.path.expanduser(f.path)
    if not any(c in raw for c in "*?["):
        p = Path(raw)
        return [p if p.is_absolute() else base_dir / p]
    pattern = raw if os.path.isabs(raw) else str(base_dir / raw)
    found = sorted(Path(p) for p in globmod.glob(pattern) if os.path.isfile(p))
    if not found:
        raise MappingError(f"{where}.path: no file matches {f.path!r} (in {Path(pattern).parent})")
    return found


def _read_source(f: FileMap, path: Path, where: str) -> list[tuple[str | None, pd.DataFrame, int]]:
    """The data of one file: ``(sheet, table, fully empty rows skipped)`` per sheet read (one, with
    sheet None, for a CSV or Parquet file). Each table's index is its data rows' 0-based positions
    (what ``time.step_s`` counts), fully empty rows left out."""
    if path.suffix.lower() == ".xls":
        raise MappingError(f"{where}.path: {path.name} is an Excel 97-2003 workbook (.xls), which openpyxl cannot "
                           "read; save it as .xlsx or CSV")  # fmt: skip
    fmt = f.format or {".csv": "csv", ".txt": "csv", ".tsv": "csv", ".xlsx": "excel", ".xlsm": "excel",
                       ".parquet": "parquet"}.get(path.suffix.lower())  # fmt: skip
    if fmt is None:
        raise MappingError(f"{where}.path: cannot tell the format of {path.name!r} from its suffix; "
                           "add format: csv, excel or parquet")  # fmt: skip
    if not os.path.lexists(path):
        raise MappingError(f"{where}.path: no such file {path} (a relative path starts from the mapping file's directory)")
    try:
        check_regular_file(path, limits.TABLE_MAX_BYTES, "a table")
    except DatasetError as exc:
        raise MappingError(f"{where}.path: {exc}") from None
    r = f.read
    if r.sheet is not None and r.sheets is not None:
        raise MappingError(f"{where}.read: give sheet (one sheet) or sheets (several), not both")
    if fmt != "excel" and (r.sheet is not None or r.sheets is not None):
        raise MappingError(f"{where}.read.{'sheet' if r.sheet is not None else 'sheets'}: a {fmt} file has no sheets")
    header = None if r.header is False else 0
    out: list[tuple[str | None, pd.DataFrame]] = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        try:
            if fmt == "csv":
                # Arrow's reader (columns built without Python objects: a 1-Hz month of 16
                # temperatures reads in seconds, in little more memory than its table, through
                # _read_csv_arrow) where the options allow it; else pandas' own
                arrow = r.decimal == "." and r.thousands is None and len(r.sep or ",") == 1
                engine = "pyarrow" if arrow else ("python" if r.sep and len(r.sep) > 1 else "c")
                kw = {} if arrow else {"decimal": r.decimal, "thousands": r.thousands}
                with open_regular_file(path, limits.TABLE_MAX_BYTES, "a table") as fh:
                    df = _read_csv_arrow(path, r.sep or ",", header, r.encoding, r.skip_rows) if arrow else None
                    if df is None:  # pandas' reader: any file the lean one above does not take, as it is
                        df = pd.read_csv(fh, sep=r.sep or ",", header=header, encoding=r.encoding, skiprows=r.skip_rows,
                                         skip_blank_lines=False, engine=engine, **kw)  # fmt: skip
                out.append((None, df))
            elif fmt == "excel":
                with pd.ExcelFile(path, engine="openpyxl") as book:
                    sheets = list(book.sheet_names)
                    if isinstance(r.sheet, int) and not 0 <= r.sheet < len(sheets):
                        raise MappingError(f"{where}.read.sheet: {path.name} has {len(sheets)} sheet(s) {sheets}; "
                                           f"index {r.sheet} is out of range (0-based)")  # fmt: skip
                    if r.sheets is not None:
                        key, chosen = "sheets", sheets if r.sheets == "all" else list(r.sheets)
                    else:
                        key, chosen = "sheet", [sheets[r.sheet] if isinstance(r.sheet, int) else (r.sheet or sheets[0])]
                    for name in chosen:
                        if name not in sheets:
                            near = difflib.get_close_matches(name, sheets, n=1)
                            raise MappingError(f"{where}.read.{key}: {path.name} has no sheet {name!r}; its sheets: "
                                               f"{sheets}" + (f"; did you mean {near[0]!r}?" if near else ""))  # fmt: skip
                    for name in chosen:
                        df = book.parse(sheet_name=name, skiprows=r.skip_rows, header=header)
                        df.attrs["sheets"] = sheets if r.sheets is None else None
                        out.append((name, df))
            else:
                out.append((None, pd.read_parquet(path)))
        except MappingError:
            raise
        except UnicodeDecodeError as exc:
            raise MappingError(f"{where}.read.encoding: {path.name} is not {r.encoding} text "
                               f"(byte 0x{exc.object[exc.start]:02x}); set the file's encoding, e.g. cp1252") from None  # fmt: skip
        except LookupError:
            raise MappingError(f"{where}.read.encoding: unknown encoding {r.encoding!r}") from None
        except ValueError as exc:
            if "Worksheet" in str(exc) or "sheet" in str(exc).lower():
                raise MappingError(f"{where}.read.sheet: {str(exc).strip()}") from None
            raise MappingError(f"{where}.path: cannot read {path.name} as {fmt}: {short_repr(str(exc), 200)}") from None
        except Exception as exc:  # a corrupt file: the user's
            raise MappingError(f"{where}.path: cannot read {path.name} as {fmt} ({type(exc).__name__}: "
                               f"{short_repr(str(exc), 200)})") from None  # fmt: skip
    return [_data_rows(df, sheet, f, path, where, fmt) for sheet, df in out]


#: the lean CSV reader takes its columns' types from this much of the file's start (pandas' Arrow
#: engine reads in blocks of 1 MiB); a file no longer is read from it alone
ARROW_PROBE_BYTES = 1 << 20
#: columns whose type the lean CSV reader corrects (a later value that does not fit the start's
#: type) before it reads the file the way pandas' engine does (every type over the whole file)
ARROW_RETYPES = 3


def _read_csv_arrow(path: Path, sep: str, header: int | None, encoding: str, skip_rows: int) -> pd.DataFrame | None:
    """The CSV file as ``pandas.read_csv(..., engine="pyarrow")`` reads it with these options (the
    same Arrow options, column names, types and values), in little more memory than the table it
    makes; None when this reader does not take the file, which pandas then reads (as before, with
    its messages).

    pandas' Arrow engine infers each column's type over the whole file, and Arrow holds every block
    it parsed until the end to do so (about twice the file's size), before pandas copies the table
    into its own blocks. Here the types come from the file's first MiB (a column empty there is
    read as numbers), the file is read block by block (Arrow's streaming reader), and each number
    column goes straight into one numpy array. A type under which every value of a column converts
    is the type Arrow's inference gives that column (it takes the first kind of null, integer,
    boolean, real, date, time, timestamp, text under which every value converts), and a column
    empty at the start that holds numbers later is one of numbers and empty cells for pandas too
    (float64, NaN where empty). A later value that does not convert (text after numbers): that
    column's type inferred over the whole file (Arrow reading it alone), and the file read again;
    after :data:`ARROW_RETYPES` such columns, every type inferred over the whole file (the read
    pandas' engine makes) and its blocks taken one by one. A parse error, an empty or repeated
    header name, no data row: None."""
    try:
        import pyarrow as pa
        import pyarrow.csv as pacsv
    except ImportError:  # pragma: no cover - a core dependency
        return None

    def options(types=None, only=None):
        return (pacsv.ReadOptions(autogenerate_column_names=header is None, skip_rows=skip_rows, encoding=encoding),
                pacsv.ParseOptions(delimiter=sep, quote_char='"', ignore_empty_lines=False),
                pacsv.ConvertOptions(null_values=CSV_NA_VALUES, strings_can_be_null=True, decimal_point=".",
                                     column_types=types or {}, include_columns=only or []))  # fmt: skip

    def opened():  # a handle per read: Arrow's streaming reader reads ahead in a thread of its own
        return open_regular_file(path, limits.TABLE_MAX_BYTES, "a table")

    def numbers_first(table):  # pandas reads a column of no value as float64 (all NaN)
        types = {n: pa.float64() if pa.types.is_null(t) else t for n, t in zip(table.column_names, table.schema.types)}
        return types, table.cast(pa.schema(list(types.items())))

    def take(batches, est: int):
        """The batches' number columns into numpy arrays (segments of ``est`` rows, one more when
        it is short), the other columns' Arrow arrays as they are."""
        floats = [i for i, n in enumerate(names) if types[n] == pa.float64()]
        segments: list[list] = []  # [rows filled, an array per number column]
        others: dict[int, list] = {i: [] for i in range(len(names)) if i not in floats}
        cap = n = 0
        for batch in batches:
            m = batch.num_rows
            if not segments or segments[-1][0] + m > cap:
                cap = max(m, est - n if not segments else n // 2)
                if cap >= 1 << 20:  # beyond malloc's largest heap block (32 MiB): mapped, and given back when freed
                    cap = max(cap, ((32 << 20) + (64 << 10)) // 8)
                segments.append([0, [np.empty(cap) for _ in floats]])
            seg = segments[-1]
            for a, i in zip(seg[1], floats):
                a[seg[0] : seg[0] + m] = batch.column(i).to_numpy(zero_copy_only=False)
            for i, chunks in others.items():
                chunks.append(batch.column(i))
            seg[0] += m
            n += m
            del batch
        return n, floats, segments, others

    def drain(batches: list):  # each let go once taken (and what Arrow's pool kept of them given back)
        while batches:
            yield batches.pop(0)
            if len(batches) % 64 == 0:
                pa.default_memory_pool().release_unused()

    try:
        with opened() as fh:
            size = os.fstat(fh.fileno()).st_size
            head = fh.read(ARROW_PROBE_BYTES + 1)
        whole = len(head) <= ARROW_PROBE_BYTES
        if not whole:  # the complete lines of the start (Arrow's blocks end at a line break too)
            head = head[: head.rfind(b"\n") + 1]
            if not head:
                return None
        probe = pacsv.read_csv(pa.BufferReader(head), *options())
        names = probe.column_names
        if not names or (header is not None and ("" in names or len(set(names)) != len(names))):
            return None  # pandas names them (Unnamed: i, x.1)
        types, probe = numbers_first(probe)
        if whole:
            n, floats, segments, others = take(drain(probe.to_batches()), probe.num_rows)
        else:
            est = int(probe.num_rows * size / len(head) * 1.05) + 1024  # the rows the file holds, from its start
            del probe
            segments, retyped = None, 0
            while segments is None:
                with opened() as fh:
                    try:
                        n, floats, segments, others = take(pacsv.open_csv(fh, *options(types)), est)
                        break
                    except pa.ArrowInvalid as exc:  # a value after the first MiB does not fit its column's type
                        failed = re.match(r"In CSV column #(\d+): CSV conversion error", str(exc))
                        if failed is None:
                            raise  # a parse error: pandas says which
                # (what was read went with the exception) that column's type over the whole file
                if retyped == ARROW_RETYPES or int(failed[1]) >= len(names):
                    break
                retyped += 1
                col = names[int(failed[1])]
                with opened() as fh:
                    inferred = pacsv.read_csv(fh, *options(only=[col])).schema.types[0]
                pa.default_memory_pool().release_unused()  # the blocks Arrow held to infer it
                types[col] = pa.float64() if pa.types.is_null(inferred) else inferred
            if segments is None:  # every type over the whole file: the table pandas' engine reads
                with opened() as fh:
                    table = pacsv.read_csv(fh, *options())
                pa.default_memory_pool().release_unused()  # the blocks Arrow held to infer the types
                if table.column_names != names:
                    return None
                types, table = numbers_first(table)
                rows, batches = table.num_rows, table.to_batches()
                del table
                n, floats, segments, others = take(drain(batches), rows)
        if n == 0:
            return None
        data: dict = {}
        for j, i in enumerate(floats):
            parts = [(seg[1][j], seg[0]) for seg in segments if seg[0]]
            if len(parts) == 1:
                a, k = parts[0]
                if k < len(a):
                    a.resize(k, refcheck=False)  # in place: the unused end is given back
            else:
                a = np.concatenate([p[:k] for p, k in parts])
            del parts
            for seg in segments:
                seg[1][j] = None
            data[i] = a
        if others:
            from pandas.io._util import arrow_table_to_pandas  # pandas' own conversion (ImportError: pandas reads)

            for i, chunks in others.items():
                col = pa.chunked_array(chunks, type=types[names[i]])
                others[i] = None
                data[i] = arrow_table_to_pandas(pa.table({names[i]: col}), null_to_int64=True).iloc[:, 0]
                del col, chunks
        labels = range(len(names)) if header is None else names
        return pd.DataFrame({labels[i]: data.pop(i) for i in range(len(names))}, copy=False)
    except (pa.ArrowException, ImportError):  # what Arrow refuses (a parse error, a bad value): pandas reads it
        return None
    finally:
        pa.default_memory_pool().release_unused()  # what Arrow's pool kept of the blocks read: back to the system


def _data_rows(df: pd.DataFrame, sheet: str | None, f: FileMap, path: Path, where: str, fmt: str):
    r = f.read
    name = path.name + (f", sheet {sheet!r}" if sheet is not None and f.read.sheets is not None else "")
    if df.shape[0] * max(df.shape[1], 1) > limits.TABLE_MAX_CELLS:
        raise MappingError(f"{where}.path: {name} holds more than {limits.TABLE_MAX_CELLS} cells")
    sheets = df.attrs.get("sheets")
    df.columns = [str(c) for c in df.columns]
    if r.header is None and len(df.columns) and all(_looks_numeric(c) for c in df.columns):
        raise MappingError(f"{where}.read.header: the first row of {name} reads as data (its {len(df.columns)} cells "
                           "are all numbers), not as column names: add read: {header: false} (columns are then named "
                           "by 0-based position), or header: true if those are its names")  # fmt: skip
    if r.skip_after_header:
        df = df.iloc[r.skip_after_header:]
    df = df.reset_index(drop=True)
    empty = np.ones(len(df), dtype=bool)
    for k, dtype in enumerate(df.dtypes):  # column by column: no copy of a long table
        s = df.iloc[:, k]
        blank = s.isna().to_numpy()
        if dtype == object:  # a cell of spaces is empty too
            blank = blank | s.map(lambda v: isinstance(v, str) and not v.strip()).to_numpy(dtype=bool)
        empty &= blank
    if empty.any():
        df = df[~empty]
    if df.empty:
        raise MappingError(f"{where}.path: {name} has no data rows")
    if len(df.columns) == 1 and fmt == "csv":
        for sep, sname in ((";", "semicolon"), ("\t", "tab"), (",", "comma")):
            if sep in df.columns[0] and sep != (r.sep or ","):
                raise MappingError(f"{where}.read.sep: the header of {path.name} is one column "
                                   f"{short_repr(df.columns[0])}: it looks {sname}-separated; set sep: {sep!r}")  # fmt: skip
    df.attrs["sheets"] = sheets
    return sheet, df, int(empty.sum())


def _looks_numeric(name: str) -> bool:
    try:
        float(name)
    except ValueError:
        return False
    return True


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


# ----------------------------------------------------------------- import ---
def _metadata(m: Mapping, path: Path, lines: dict) -> Metadata:
    raw = {"format": FORMAT_V2, **m.dataset}
    if "format" in m.dataset:
        raise MappingError(f"{path}: key 'dataset.format': leave it out; import writes {FORMAT_V2}")
    if "runs" not in m.dataset:  # the runs the files name (run: from sheet / file, a run_id column, run:)
        raw["runs"] = {_UNDECLARED: {}}
    sub = {tuple(k[1:]): v for k, v in lines.items() if k and k[0] == "dataset"}
    try:
        meta = Metadata.model_validate(raw)
    except ValidationError as exc:
        msg = validation_message(exc, path, sub)
        raise MappingError(msg.replace(f"{path}: key '", f"{path}: key 'dataset.", 1)) from None
    if m.run is not None and m.run not in meta.runs and _UNDECLARED not in meta.runs:
        raise MappingError(f"{path}: key 'run': {m.run!r} is not a run of dataset.runs ({sorted(meta.runs)})")
    return meta


#: the placeholder run of a mapping whose dataset declares no runs (they come from the files)
_UNDECLARED = "undeclared-runs"


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

    out = {"t": cat([p[2] for p in pieces]), "run": cat([p[3]["run"] for p in pieces]).astype(object, copy=False)}
    for part in ("proc", "wide", "long"):
        cols = pieces[0][3][part].keys()
        out[part] = {c: cat([p[3][part][c] for p in pieces]) for c in cols}
    out.update({"channel": f.channel, "src": pieces[0][3]["src"], "where": where, "max_gap_s": f.max_gap_s,
                "path": pieces[0][0] if len(pieces) == 1 else Path(f.path)})  # fmt: skip
    return out


def build_tables(mapping_path: str | Path, progress=None) -> tuple[Metadata, pd.DataFrame, pd.DataFrame, list[str]]:
    """Read the mapping and its files; return the dataset's metadata and tables (not yet
    written), and notes on what was left out (fully empty rows, per file). :class:`MappingError`
    names the mapping key of any mistake."""
    path = Path(mapping_path)
    m, lines = read_mapping(path)
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
    if not declared:  # the runs are those the files name, in the order met
        order = list(dict.fromkeys(r for fr in frames.values() for r in fr["run"]))
        meta = meta.model_copy(update={"runs": {r: RunMeta() for r in order}})
    mapped = {c for fr in frames.values() for c in fr["proc"]}
    if "operating" not in m.dataset and meta.operating_inputs() and not mapped & set(meta.operating_inputs()):
        # no operating signal in the files (a test logged temperatures and a drift only): none is
        # expected, and each run is one state of its own
        notes.append(f"no file maps an operating input ({', '.join(meta.operating_inputs())}): the dataset has none "
                     "(operating: []), each run is a state of its own")  # fmt: skip
        meta = meta.model_copy(update={"operating": []})
    if False in kinds and len(kinds) > 1:
        raise MappingError(f"{path}: key 'files': some files have timestamps and some seconds; a common clock needs "
                           "the same kind in every file (give each file's time the same way)")  # fmt: skip
    if kinds == {"aware", "naive"}:
        raise MappingError(f"{path}: key 'files': some files' timestamps carry a time zone and some do not; a "
                           "timestamp without one could be any zone: write the zone into the files, or read all "
                           "without it and align them with offset_s")  # fmt: skip
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
    runs = pd.unique(b["run"])
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
    errors = errors.sort_values(["run_id", "channel", "t_s"], kind="stable").reset_index(drop=True)
    return errors


def import_dataset(mapping_path: str | Path, out: str | Path, file_format: str = "parquet", force: bool = False,
                   extra: dict | None = None, progress=None):
    """Build the dataset the mapping describes and write it to ``out`` (one output of kind
    ``dataset``, :mod:`thermbench.outputs`), validated before it is moved into place.
    ``progress``: called with one line at each long step (large files, a long alignment)."""
    if file_format not in ("csv", "parquet"):
        raise MappingError(f"--format: expected csv or parquet, got {file_format!r}")
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
            raise MappingError(f"{mapping_path}: the imported dataset is not valid: {msg}") from None
    ds.path = out
    ds.import_notes = notes  # what the import left out, for the command to say
    return ds
