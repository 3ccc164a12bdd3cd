"""Load, validate and write datasets in the thermbench contract (docs/dataset-format.md).

Every problem is reported as a :class:`DatasetError` whose message is one line naming
the file, the column (or the metadata key) and the row (1-based data row; for CSV also
the file line). Loading trusts nothing it reads: special files and oversized files are
refused before they are opened (:mod:`thermbench.data.files`), ``metadata.yaml`` is read
by a strict YAML loader (:mod:`thermbench.data.safe_yaml`), every value is checked
against its plausible range (:mod:`thermbench.data.limits`), and nothing is ever written.
Writing goes to a temporary directory that replaces the target only when
complete, so a failed write never leaves a half-written dataset.
"""

from __future__ import annotations

import codecs
import csv
import hashlib
import os
import re
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import yaml
from pydantic import ValidationError

from ..outputs import output_dir
from . import limits
from .errors import DatasetError, one_line, short_repr
from .files import find_case_variant, open_regular_file, read_capped
from .safe_yaml import YAMLInputError, dump_yaml, load_yaml
from .schema import FORMATS, Metadata, MetadataV1

PROCESS_REQUIRED = ("run_id", "t_s", "axis_mm", "feed_mm_min")
PROCESS_OPTIONAL_NUMERIC = ("load_N", "spindle_rpm")
ERRORS_REQUIRED = ("run_id", "t_s", "target_mm", "error_um")
MAX_SAMPLE_GAP_S = 1.0  # format 1: >= 1 sample per second
GAP_FACTOR = 5.0  # format 2 without sampling.max_gap_s: a step over 5 median steps is a gap
TEXT_COLUMNS = ("run_id", "channel")  # only the empty cell is missing here
TRAVEL_TOL_MM = 0.5
# what pandas reads as a missing value by default; run_id takes only the empty cell
# (a run may be called "NA" or "null")
try:
    from pandas._libs.parsers import STR_NA_VALUES as _PANDAS_NA
except ImportError:  # pragma: no cover - pandas moved it
    _PANDAS_NA = {"", "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN",
                  "<NA>", "N/A", "NA", "NULL", "NaN", "None", "n/a", "nan", "null"}  # fmt: skip
CSV_NA_VALUES = sorted(_PANDAS_NA)

__all__ = ["Dataset", "DatasetError", "DatasetWarning", "load_dataset", "load_metadata", "save_dataset"]


class DatasetWarning(UserWarning):
    """A dataset loads, but something in it is ignored (a sensor column that ``metadata.yaml``
    does not declare); the message (one line) names the file and the column."""


@dataclass
class Dataset:
    """A validated dataset: metadata plus the process stream and the measured errors."""

    metadata: Metadata
    process: pd.DataFrame
    errors: pd.DataFrame
    path: Path | None = None
    channel: str | None = None  # a view of one error channel (thermbench.data.views.channel_view)

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

    def channel_view(self, channel: str) -> "Dataset":
        """One error channel in the shape the model families use (:mod:`thermbench.data.views`)."""
        from .views import channel_view

        return channel_view(self, channel)

    def content_hash(self) -> str:
        """SHA-256 over the metadata and both tables (what tracking records)."""
        h = hashlib.sha256()
        h.update(yaml.safe_dump(self.metadata.model_dump(mode="json"), sort_keys=True).encode())
        for df in (self.process, self.errors):
            h.update(pd.util.hash_pandas_object(df, index=False).values.tobytes())
            h.update(",".join(df.columns).encode())
        return h.hexdigest()[:16]


def _some(items, n: int = 8) -> str:
    """A list for a message: at most ``n`` items, each repr cut short."""
    items = list(items)
    shown = ", ".join(short_repr(x, 40) for x in items[:n])
    return f"[{shown}{f', ... ({len(items)} in all)' if len(items) > n else ''}]"


# ------------------------------------------------------------ metadata ---
def _key_text(loc: tuple) -> str:
    return ".".join(str(p) for p in loc) or "(top level)"


def _line_of(lines: dict[tuple, int], loc: tuple) -> str:
    """`` (line N)`` for the deepest key of ``loc`` found in the YAML, else ''."""
    loc = tuple(loc)
    for k in range(len(loc), 0, -1):
        if loc[:k] in lines:
            return f" (line {lines[loc[:k]]})"
    return ""


def _check_run_ids(runs: dict, path: Path, lines: dict) -> None:
    """The run-id rule (:data:`~thermbench.data.limits.RUN_ID_PATTERN`) and no two ids
    that differ only by case."""
    seen: dict[str, str] = {}
    for run_id in runs:
        where = f"{path}: key {short_repr(_key_text(('runs', run_id)))}"
        at = _line_of(lines, ("runs", run_id))
        problem = limits.run_id_problem(run_id)
        if problem is not None:
            raise DatasetError(f"{where}: run id {short_repr(run_id)} {problem}; run ids are {limits.RUN_ID_RULE}{at}")
        other = seen.get(limits.run_id_key(run_id))
        if other is not None:
            raise DatasetError(
                f"{where}: run ids {run_id!r}{at} and {other!r}{_line_of(lines, ('runs', other))} differ only by "
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
        hint = (f" (it holds {_some(raw, 3)}: lab files come in through an import mapping, "
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
            f"{path}: key 'format': expected {expected}, got {short_repr(raw.get('format'))}{_line_of(lines, ('format',))}"
        )
    if isinstance(raw.get("runs"), dict):
        _check_run_ids(raw["runs"], path, lines)
    try:
        if raw["format"] == FORMATS[0]:
            MetadataV1.model_validate(raw)  # every format 1 key required, each message naming it
        return Metadata.model_validate(raw)
    except ValidationError as exc:
        raise DatasetError(_validation_message(exc, path, lines)) from None


def _validation_message(exc: ValidationError, path: Path, lines: dict) -> str:
    """One line for the first pydantic error: the key (and its line), what was wrong."""
    e = exc.errors()[0]
    loc = tuple(p for p in e["loc"] if p != "[key]")
    msg = str(e["msg"]).removeprefix("Value error, ")
    if e["type"] == "value_error" and not loc:  # a whole-file rule: the message starts with its key
        m = re.match(r"([A-Za-z0-9_.\-]+): (.*)$", msg)
        if m:
            loc, msg = tuple(m[1].split(".")), m[2]
    where = f"{path}: key {short_repr(_key_text(loc))}"
    at = _line_of(lines, loc)
    if e["type"] == "missing":
        return f"{where}: missing (required){at}"
    if e["type"] == "value_error":  # our own checks: the message names the value and unit
        return f"{where}: {msg}{at}"
    return f"{where}: {e['msg']} (got {short_repr(e.get('input'))}){at}"


# ---------------------------------------------------------------- tables ---
def _find_table(root: Path, stem: str) -> Path:
    for ext in (".parquet", ".csv"):
        p = root / f"{stem}{ext}"
        if os.path.lexists(p):
            return p
    found = find_case_variant(root, f"{stem}.csv") or find_case_variant(root, f"{stem}.parquet")
    hint = f" (found {found!r}: file names are case-sensitive)" if found else ""
    raise DatasetError(f"{root}: missing {stem}.csv or {stem}.parquet{hint}")


def _check_column_names(names: list, path: Path, contract: tuple[str, ...], where: str) -> None:
    """No duplicate names (pandas would silently rename the second ``x.1``) and no
    contract column hidden behind whitespace (`` t_s``)."""
    first: dict[str, int] = {}
    for i, name in enumerate(names):
        if name == "":
            continue
        if name in first:
            raise DatasetError(
                f"{path}: {where}column {name!r} appears twice (columns {first[name] + 1} and {i + 1}); "
                "every column name must be unique"
            )
        first[name] = i
    for i, name in enumerate(names):
        if name != name.strip() and name.strip() in contract:
            raise DatasetError(
                f"{path}: {where}column {short_repr(name)} (column {i + 1}) has whitespace around its name; "
                f"write {name.strip()!r}"
            )


def _scan_csv(fh, path: Path) -> tuple[str, int]:
    """One pass over a CSV file's bytes before pandas sees it: refuses binary data (NUL
    bytes), text that is not UTF-8 and a header line longer than
    :data:`~thermbench.data.limits.CSV_HEADER_MAX_BYTES`. Returns the header line and the
    number of data lines."""
    decoder = codecs.getincrementaldecoder("utf-8")("strict")
    newlines = 0  # line breaks: "\n", or "\r" alone (old Mac files)
    returns = 0
    head = b""
    offset = 0
    last = b""
    while True:
        chunk = fh.read(1 << 20)
        if not chunk:
            break
        nul = chunk.find(b"\0")
        if nul >= 0:
            line = newlines + chunk.count(b"\n", 0, nul) + 1
            raise DatasetError(
                f"{path}: line {line}: a NUL byte at offset {offset + nul}: binary data, not a CSV text file"
            )
        try:
            decoder.decode(chunk)
        except UnicodeDecodeError as exc:
            pos = max(exc.start - len(exc.object) + len(chunk), 0)  # in this chunk
            line = newlines + chunk.count(b"\n", 0, pos) + 1
            raise DatasetError(
                f"{path}: line {line}: not UTF-8 text (byte 0x{chunk[pos]:02x} at offset {offset + pos}); "
                "save the file as UTF-8"
            ) from None
        if len(head) <= limits.CSV_HEADER_MAX_BYTES and b"\n" not in head and b"\r" not in head:
            head += chunk[: limits.CSV_HEADER_MAX_BYTES + 1]
        newlines += chunk.count(b"\n")
        returns += chunk.count(b"\r")
        offset += len(chunk)
        last = chunk[-1:]
    try:
        decoder.decode(b"", final=True)
    except UnicodeDecodeError:
        raise DatasetError(f"{path}: line {newlines + 1}: not UTF-8 text (cut inside a character at the end)") from None
    if not head.strip():
        raise DatasetError(f"{path}: is empty; expected a header line such as run_id,t_s,...")
    breaks = [i for i in (head.find(b"\n"), head.find(b"\r")) if i >= 0]
    end = min(breaks) if breaks else -1
    if end < 0 and len(head) > limits.CSV_HEADER_MAX_BYTES:
        raise DatasetError(
            f"{path}: line 1: longer than {limits.CSV_HEADER_MAX_BYTES // 1024} KiB without a line break: "
            "not a CSV table with a header line"
        )
    header = (head if end < 0 else head[:end]).decode("utf-8-sig")
    if not header.strip():
        raise DatasetError(f"{path}: line 1: empty; the header line (run_id,t_s,...) must be the first line")
    lines = max(newlines, returns) + (1 if last not in (b"\n", b"\r", b"") else 0)
    return header, max(lines - 1, 0)


def _csv_parser_message(exc: Exception) -> str:
    text = one_line(str(exc)).replace("Error tokenizing data. C error: ", "")
    m = re.search(r"Expected (\d+) fields in line (\d+), saw (\d+)", text)
    if m:
        return f"line {m[2]}: {m[3]} fields, more than the {m[1]} columns of the header"
    return "not a readable CSV table: " + text.removesuffix("\\n").rstrip(". ")


def _check_row_lengths(fh, path: Path, n_columns: int) -> None:
    """No row with more fields than the header, except empty ones (a trailing comma)."""
    import io

    text = io.TextIOWrapper(fh, encoding="utf-8-sig", newline="")
    reader = csv.reader(text)
    try:
        for fields in reader:
            if len(fields) > n_columns and any(f.strip() for f in fields[n_columns:]):
                raise DatasetError(f"{path}: line {reader.line_num}: {len(fields)} fields, more than the "
                                   f"{n_columns} columns of the header")  # fmt: skip
    except csv.Error as exc:
        raise DatasetError(f"{path}: line {reader.line_num}: not a readable CSV table ({exc})") from None
    finally:
        text.detach()


def _check_blank_lines(fh, path: Path) -> None:
    """No empty (or whitespace-only) line inside a CSV table: pandas skips them, and every
    line number after one would be wrong. Empty lines at the end are harmless."""
    import io

    text = io.TextIOWrapper(fh, encoding="utf-8-sig", newline=None)
    try:
        blank = None
        for n, line in enumerate(text, 1):
            if not line.strip():
                blank = blank or n
            elif blank is not None:
                raise DatasetError(f"{path}: line {blank}: an empty line inside the table; remove it")
    finally:
        text.detach()


def _read_csv(path: Path, contract: tuple[str, ...]) -> pd.DataFrame:
    with open_regular_file(path, limits.TABLE_MAX_BYTES, "a table") as fh:
        header, rows = _scan_csv(fh, path)
        try:
            names = next(csv.reader([header]), [])
        except csv.Error as exc:
            raise DatasetError(f"{path}: line 1: not a readable CSV header ({exc})") from None
        if len(names) == 1:
            for sep, sep_name in ((";", "semicolon"), ("\t", "tab"), ("|", "bar")):
                if sep in names[0]:
                    raise DatasetError(
                        f"{path}: line 1: the header {short_repr(header)} is one column: the table looks "
                        f"{sep_name}-separated; write comma-separated CSV with '.' as the decimal point"
                    )
        _check_column_names(names, path, contract, "line 1: ")
        cells = rows * max(len(names), 1)
        if cells > limits.TABLE_MAX_CELLS:
            raise DatasetError(
                f"{path}: {cells} cells ({rows} rows x {len(names)} columns), more than a table may hold "
                f"({limits.TABLE_MAX_CELLS}; docs/dataset-format.md, Limits)"
            )
        fh.seek(0)
        # run_id: only the empty cell is missing; elsewhere pandas' usual missing-value words
        na = {i: ([""] if n in TEXT_COLUMNS else CSV_NA_VALUES) for i, n in enumerate(names)}
        try:
            # index_col=False: a row longer than the header never shifts the columns onto an
            # index; pandas then drops the extra field with a warning, turned into a check here
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", pd.errors.ParserWarning)
                df = pd.read_csv(fh, dtype=dict.fromkeys(TEXT_COLUMNS, str), keep_default_na=False, na_values=na,
                                 encoding="utf-8-sig", compression=None, engine="c", index_col=False)  # fmt: skip
            if any(issubclass(w.category, pd.errors.ParserWarning) for w in caught):
                fh.seek(0)
                _check_row_lengths(fh, path, len(names))
            if len(df) < rows:  # pandas skipped blank lines: inside the table, they shift the line numbers
                fh.seek(0)
                _check_blank_lines(fh, path)
            return df
        except DatasetError:
            raise
        except pd.errors.EmptyDataError:
            raise DatasetError(f"{path}: is empty; expected a header line such as run_id,t_s,...") from None
        except pd.errors.ParserError as exc:
            raise DatasetError(f"{path}: {_csv_parser_message(exc)}") from None
        except (ValueError, OverflowError, MemoryError) as exc:
            raise DatasetError(f"{path}: not a readable CSV table ({type(exc).__name__}: {short_repr(str(exc), 200)})") from None  # fmt: skip


def _read_parquet(path: Path, contract: tuple[str, ...]) -> pd.DataFrame:
    import pyarrow as pa
    import pyarrow.compute as pc
    import pyarrow.parquet as pq

    def unreadable(exc: Exception) -> DatasetError:
        return DatasetError(f"{path}: not a readable Parquet file ({type(exc).__name__}: {short_repr(str(exc), 200)})")

    with open_regular_file(path, limits.TABLE_MAX_BYTES, "a table") as fh:
        try:
            pf = pq.ParquetFile(fh)
            schema = pf.schema_arrow
            meta = pf.metadata
        except Exception as exc:  # any failure to read the footer: the user's file
            raise unreadable(exc) from None
        names = list(schema.names)
        _check_column_names(names, path, contract, "")
        try:  # values of every leaf column: a list column holds many per row
            values = sum(meta.row_group(g).column(c).num_values
                         for g in range(meta.num_row_groups) for c in range(meta.num_columns))  # fmt: skip
        except Exception as exc:
            raise unreadable(exc) from None
        cells = max(meta.num_rows * max(len(names), 1), values)
        if cells > limits.TABLE_MAX_CELLS:
            extra = ", list items included" if values > meta.num_rows * len(names) else ""
            raise DatasetError(
                f"{path}: {cells} cells ({meta.num_rows} rows x {len(names)} columns{extra}), more than a table "
                f"may hold ({limits.TABLE_MAX_CELLS}; docs/dataset-format.md, Limits)"
            )
        try:
            stored = sum(meta.row_group(g).column(c).total_uncompressed_size
                         for g in range(meta.num_row_groups) for c in range(meta.num_columns))  # fmt: skip
        except Exception as exc:
            raise unreadable(exc) from None
        if stored > limits.TABLE_MAX_DECODED_BYTES:
            raise DatasetError(f"{path}: {stored} bytes once decompressed, more than a table may hold "
                               f"({limits.TABLE_MAX_DECODED_BYTES}; docs/dataset-format.md, Limits)")  # fmt: skip
        for field in schema:
            t = field.type.value_type if pa.types.is_dictionary(field.type) else field.type
            if field.name in contract and pa.types.is_nested(t):
                raise DatasetError(f"{path}: column {field.name!r} holds {field.type}, not plain values")

        def is_text(t) -> bool:
            return any(f(t) for f in (pa.types.is_string, pa.types.is_large_string, pa.types.is_binary,
                                      pa.types.is_large_binary))  # fmt: skip

        # text columns stay dictionary-encoded until their decoded size is known: a few
        # bytes of repeated text must not expand to gigabytes
        text_cols = [f.name for f in schema if is_text(f.type)]
        try:
            fh.seek(0)
            table = pq.ParquetFile(fh, read_dictionary=text_cols).read()
        except Exception as exc:
            raise unreadable(exc) from None
        decoded = 0
        for col in table.columns:
            if not (pa.types.is_dictionary(col.type) and is_text(col.type.value_type)):
                continue
            for chunk in col.chunks:
                if len(chunk):
                    lengths = pc.binary_length(chunk.dictionary).take(chunk.indices)
                    decoded += int(pc.sum(lengths).as_py() or 0)
        if decoded > limits.TABLE_MAX_DECODED_BYTES:
            raise DatasetError(f"{path}: its text columns hold {decoded} bytes once decoded, more than a table may "
                               f"hold ({limits.TABLE_MAX_DECODED_BYTES}; docs/dataset-format.md, Limits)")  # fmt: skip
        for name in text_cols:
            i = table.schema.get_field_index(name)
            col = table.column(i)
            if pa.types.is_dictionary(col.type):
                table = table.set_column(i, name, pc.cast(col, col.type.value_type))
        try:
            df = table.to_pandas(split_blocks=True, self_destruct=True)  # frees each arrow column as it goes
            del table
        except Exception as exc:
            raise unreadable(exc) from None
    if not isinstance(df.index, pd.RangeIndex):  # an index stored by pandas: back to columns
        df = df.reset_index()
    return df


def _read_table(path: Path, contract: tuple[str, ...]) -> pd.DataFrame:
    """Read a table (.csv or .parquet) after the file checks; ``contract``: the column
    names the contract gives meaning to (for the checks on the header)."""
    if path.suffix == ".parquet":
        return _read_parquet(path, contract)
    return _read_csv(path, contract)


def _where(path: Path, idx: int) -> str:
    row = idx + 1
    return f"row {row} (line {row + 1})" if path.suffix == ".csv" else f"row {row}"


def _first(mask) -> int:
    return int(np.flatnonzero(np.asarray(mask))[0])


def _time_kind(s: pd.Series) -> str:
    if pd.api.types.is_timedelta64_dtype(s.dtype):
        return "duration"
    if pd.api.types.is_datetime64_any_dtype(s.dtype):
        return "date-time"
    return "number"


def _convert_times(process: pd.DataFrame, ppath: Path, errors: pd.DataFrame, epath: Path) -> None:
    """Parquet may store ``t_s`` as a duration or a date-time (docs/dataset-format.md):
    a duration becomes its seconds; date-times, which must then be in both tables, become
    seconds since the earliest ``t_s`` in ``process``: one zero for both files, so the
    two instruments stay on one clock."""
    kinds = {}
    for df, path in ((process, ppath), (errors, epath)):
        if "t_s" not in df.columns:
            return  # reported as a missing column
        kinds[path] = _time_kind(df["t_s"])
        if kinds[path] == "duration":
            df["t_s"] = df["t_s"].dt.total_seconds()
    pk, ek = kinds[ppath], kinds[epath]
    if "date-time" not in (pk, ek):
        return
    if pk != ek:
        dt_path, other = (ppath, epath) if pk == "date-time" else (epath, ppath)
        raise DatasetError(
            f"{dt_path}: column 't_s' holds date-times but {other.name} holds {kinds[other]}s: write both as "
            "date-times (one clock) or both as seconds"
        )
    p, e = process["t_s"], errors["t_s"]
    if (p.dt.tz is None) != (e.dt.tz is None):
        raise DatasetError(
            f"{epath}: column 't_s': date-times {'with' if e.dt.tz is not None else 'without'} a time zone, "
            f"but {ppath.name} has them {'with' if p.dt.tz is not None else 'without'}: use the same in both files"
        )
    if p.isna().all():
        return  # reported as missing values
    t0 = p.min()
    process["t_s"] = (p - t0).dt.total_seconds()
    errors["t_s"] = (e - t0).dt.total_seconds()


def _numeric(df: pd.DataFrame, col: str, path: Path) -> None:
    s = df[col]
    kind = _time_kind(s)
    if kind != "number":
        raise DatasetError(f"{path}: column {col!r} holds {kind}s ({s.dtype}); expected numbers")
    if pd.api.types.is_bool_dtype(s.dtype):
        raise DatasetError(f"{path}: column {col!r}, {_where(path, 0)}: expected a number, got {short_repr(s.iloc[0])} "
                           "(the column holds true/false values)")  # fmt: skip
    if s.dtype == object:
        is_bool = s.map(lambda v: isinstance(v, (bool, np.bool_))).to_numpy(dtype=bool)
        if is_bool.any():
            i = _first(is_bool)
            raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: expected a number, got {short_repr(s.iloc[i])}")
    if s.dtype == object or pd.api.types.is_string_dtype(s.dtype):
        conv = pd.to_numeric(s, errors="coerce")
        bad = conv.isna() & s.notna()
        if bad.any():
            i = _first(bad.to_numpy())
            hint = ""
            if col == "t_s" and not pd.isna(pd.to_datetime(s.iloc[i], errors="coerce")):
                hint = "; write seconds (date-times are read from Parquet only, docs/dataset-format.md)"
            raise DatasetError(
                f"{path}: column {col!r}, {_where(path, i)}: expected a number, got {short_repr(s.iloc[i])}{hint}"
            )
        df[col] = conv
    elif not pd.api.types.is_numeric_dtype(s.dtype):
        raise DatasetError(f"{path}: column {col!r} holds {s.dtype} values; expected numbers")
    df[col] = df[col].astype(float)
    nan = df[col].isna().to_numpy()
    if nan.any():
        i = _first(nan)
        raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: missing value (NaN)")
    inf = ~np.isfinite(df[col].to_numpy())
    if inf.any():
        i = _first(inf)
        raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: value must be finite, got {df[col].iloc[i]}")


def _check_range(df: pd.DataFrame, col: str, path: Path, q: limits.Quantity) -> None:
    """Every value of ``col`` (already finite numbers) plausible for ``q``."""
    v = df[col].to_numpy()
    bad = ~((v >= q.lo if q.lo_inclusive else v > q.lo) & (v <= q.hi))
    if bad.any():
        i = _first(bad)
        raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: {q.problem(float(v[i]))}")


def _unknown_run_message(value: str, runs: dict) -> str:
    near = [r for r in runs if limits.run_id_key(r) == limits.run_id_key(value)]
    if near:
        return f"unknown run_id {short_repr(value)}: it differs from the declared {near[0]!r} only by whitespace or case"
    return f"unknown run_id {short_repr(value)} (metadata.yaml declares {_some(sorted(runs))})"


def _check_table(df: pd.DataFrame, path: Path, required: tuple[str, ...], runs: dict) -> None:
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DatasetError(f"{path}: missing column(s) {missing}; found {_some(df.columns, 16)}")
    if df.empty:
        raise DatasetError(f"{path}: no rows (a header without data)")
    rid = df["run_id"]
    if rid.isna().any():
        i = _first(rid.isna().to_numpy())
        raise DatasetError(f"{path}: column 'run_id', {_where(path, i)}: missing value")
    df["run_id"] = rid.astype(str)
    unknown = ~df["run_id"].isin(list(runs))
    if unknown.any():
        i = _first(unknown.to_numpy())
        raise DatasetError(
            f"{path}: column 'run_id', {_where(path, i)}: {_unknown_run_message(df['run_id'].iloc[i], runs)}"
        )
    for col in required[1:]:
        _numeric(df, col, path)


def _run_codes(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """``run_id`` as integer codes and the run id of each code: every comparison below
    works on the codes (a text column turned into a numpy array of Python strings would
    take 60 bytes a row)."""
    codes, uniques = pd.factorize(df["run_id"])
    return np.asarray(codes), np.asarray(uniques, dtype=object)


def _check_increasing(df: pd.DataFrame, path: Path, codes: np.ndarray) -> None:
    t = df["t_s"].to_numpy()
    same = codes[1:] == codes[:-1]
    bad = same & (np.diff(t) <= 0)
    if bad.any():
        i = _first(bad) + 1
        raise DatasetError(
            f"{path}: column 't_s', {_where(path, i)}: time must increase within run "
            f"{df['run_id'].iloc[i]!r} ({t[i - 1]} then {t[i]}); rows of a run must be contiguous and in time order"
        )
    _check_contiguous(df, path, codes)


def _check_contiguous(df: pd.DataFrame, path: Path, codes: np.ndarray) -> None:
    """The rows of a run are one block."""
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
    seen = np.zeros(int(codes.max()) + 1 if len(codes) else 0, dtype=bool)
    for i in starts:  # one per block: as many as runs when contiguous
        if seen[codes[i]]:
            raise DatasetError(
                f"{path}: column 'run_id', {_where(path, int(i))}: rows of run {df['run_id'].iloc[int(i)]!r} "
                "are not contiguous"
            )
        seen[codes[i]] = True


def _check_increasing_errors(df: pd.DataFrame, path: Path, codes: np.ndarray) -> None:
    """Within a run, measurement times must not go backwards (equal times allowed
    only for distinct targets, e.g. an interferometer recording several at once)."""
    t = df["t_s"].to_numpy()
    same = codes[1:] == codes[:-1]
    bad = same & (np.diff(t) < 0)
    if bad.any():
        i = _first(bad) + 1
        raise DatasetError(
            f"{path}: column 't_s', {_where(path, i)}: time must not decrease within run "
            f"{df['run_id'].iloc[i]!r} ({t[i - 1]} then {t[i]})"
        )


def _check_duplicate_rows(df: pd.DataFrame, path: Path, cols: tuple[str, ...]) -> None:
    """No two rows equal in all of ``cols`` (a reading recorded twice)."""
    dup = df.duplicated(subset=list(cols), keep="first").to_numpy()
    if dup.any():
        i = _first(dup)
        same = np.ones(len(df), dtype=bool)
        for c in cols:
            same &= (df[c] == df[c].iloc[i]).to_numpy()
        j = _first(same)
        values = ", ".join(f"{c} {short_repr(df[c].iloc[i], 30)}" for c in cols)
        raise DatasetError(
            f"{path}: {_where(path, j)} and {_where(path, i)} are the same reading ({values}); remove the copy"
        )


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
        from .v2 import load_tables_v2

        process, errors = load_tables_v2(root, meta)
        notes += _undeclared_sensor_columns(process, meta, _find_table(root, "process"))
        return Dataset(meta, process, errors, root)
    ppath = _find_table(root, "process")
    epath = _find_table(root, "errors")
    sensor_cols = [meta.sensor_column(s) for s in meta.sensors]
    process = _read_table(ppath, PROCESS_REQUIRED + tuple(sensor_cols) + PROCESS_OPTIONAL_NUMERIC)
    errors = _read_table(epath, ERRORS_REQUIRED)
    _convert_times(process, ppath, errors, epath)

    _check_table(process, ppath, PROCESS_REQUIRED + tuple(sensor_cols), meta.runs)
    for col in PROCESS_OPTIONAL_NUMERIC:
        if col in process.columns:
            _numeric(process, col, ppath)
    p_codes, p_runs = _run_codes(process)
    _check_increasing(process, ppath, p_codes)
    neg = process["feed_mm_min"].to_numpy() < 0
    if neg.any():
        i = _first(neg)
        raise DatasetError(
            f"{ppath}: column 'feed_mm_min', {_where(ppath, i)}: feed must be >= 0 (speed magnitude), "
            f"got {process['feed_mm_min'].iloc[i]}"
        )
    _check_range(process, "feed_mm_min", ppath, limits.FEED_MM_MIN)
    _check_range(process, "axis_mm", ppath, limits.POSITION_MM)
    for col in sensor_cols:
        _check_range(process, col, ppath, limits.TEMPERATURE_C)
    if "spindle_rpm" in process.columns and (process["spindle_rpm"] < 0).any():
        i = _first(process["spindle_rpm"].to_numpy() < 0)
        raise DatasetError(f"{ppath}: column 'spindle_rpm', {_where(ppath, i)}: must be >= 0")
    t = process["t_s"].to_numpy()
    same = p_codes[1:] == p_codes[:-1]
    gap = same & (np.diff(t) > MAX_SAMPLE_GAP_S * 1.01)
    if gap.any():
        i = _first(gap) + 1
        raise DatasetError(
            f"{ppath}: column 't_s', {_where(ppath, i)}: gap of {t[i] - t[i - 1]:.3g} s; "
            f"the process stream needs >= 1 sample per second"
        )

    _check_table(errors, epath, ERRORS_REQUIRED, meta.runs)
    _check_range(errors, "target_mm", epath, limits.POSITION_MM)
    _check_range(errors, "error_um", epath, limits.ERROR_UM)
    e_codes, e_runs = _run_codes(errors)
    _check_increasing_errors(errors, epath, e_codes)
    _check_duplicate_rows(errors, epath, ERRORS_REQUIRED)
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
    _check_within(errors, epath, "target_mm", lo[k] - TRAVEL_TOL_MM, hi[k] + TRAVEL_TOL_MM,
                  lambda i: f"mm is outside the travel measured in {ppath.name} for run {errors['run_id'].iloc[i]!r} "
                  f"({lo[k[i]]:g}..{hi[k[i]]:g} mm)")  # fmt: skip
    _check_within(errors, epath, "t_s", t0[k], t1[k],
                  lambda i: f"s is outside the process log of run {errors['run_id'].iloc[i]!r} "
                  f"({t0[k[i]]:g}..{t1[k[i]]:g} s)")  # fmt: skip
    notes += _undeclared_sensor_columns(process, meta, ppath)
    return Dataset(meta, process.reset_index(drop=True), errors.reset_index(drop=True), root)


def _check_within(df: pd.DataFrame, path: Path, col: str, lo: np.ndarray, hi: np.ndarray, why) -> None:
    """Every value of ``col`` must lie in [lo, hi] (per row); ``why(i)`` explains row i."""
    v = df[col].to_numpy()
    out = (v < lo) | (v > hi)
    if out.any():
        i = _first(out)
        raise DatasetError(f"{path}: column {col!r}, {_where(path, i)}: {v[i]:g} {why(i)}")


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
