"""The readers and checks both dataset formats share (docs/dataset-format.md): a table file
(CSV or Parquet) read after the file checks, and the checks on its columns and rows. Every
problem is a :class:`~thermbench.data.errors.DatasetError` whose message is one line naming the
file, the column and the row (1-based data row; for CSV also the file line). Format 1 is checked
in :mod:`thermbench.data.io`, format 2 in :mod:`thermbench.data.v2`; both call these."""

from __future__ import annotations

import codecs
import csv
import os
import re
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
from pydantic import ValidationError

from . import limits
from .errors import DatasetError, one_line, short_repr
from .files import find_case_variant, open_regular_file

TEXT_COLUMNS = ("run_id", "channel")  # only the empty cell is missing here
# what pandas reads as a missing value by default; run_id takes only the empty cell
# (a run may be called "NA" or "null")
try:
    from pandas._libs.parsers import STR_NA_VALUES as _PANDAS_NA
except ImportError:  # pragma: no cover - pandas moved it
    _PANDAS_NA = {"", "#N/A", "#N/A N/A", "#NA", "-1.#IND", "-1.#QNAN", "-NaN", "-nan", "1.#IND", "1.#QNAN",
                  "<NA>", "N/A", "NA", "NULL", "NaN", "None", "n/a", "nan", "null"}  # fmt: skip
CSV_NA_VALUES = sorted(_PANDAS_NA)
TRAVEL_TOL_MM = 0.5  # a reading's target may lie this far outside the travel the process log shows


def some(items, n: int = 8) -> str:
    """A list for a message: at most ``n`` items, each repr cut short."""
    items = list(items)
    shown = ", ".join(short_repr(x, 40) for x in items[:n])
    return f"[{shown}{f', ... ({len(items)} in all)' if len(items) > n else ''}]"



# ------------------------------------------------------------ messages ---
def key_text(loc: tuple) -> str:
    return ".".join(str(p) for p in loc) or "(top level)"


def line_of(lines: dict[tuple, int], loc: tuple) -> str:
    """`` (line N)`` for the deepest key of ``loc`` found in the YAML, else ''."""
    loc = tuple(loc)
    for k in range(len(loc), 0, -1):
        if loc[:k] in lines:
            return f" (line {lines[loc[:k]]})"
    return ""


def validation_message(exc: ValidationError, path: Path, lines: dict) -> str:
    """One line for the first pydantic error: the key (and its line), what was wrong."""
    e = exc.errors()[0]
    loc = tuple(p for p in e["loc"] if p != "[key]")
    msg = str(e["msg"]).removeprefix("Value error, ")
    if e["type"] == "value_error" and not loc:  # a whole-file rule: the message starts with its key
        m = re.match(r"([A-Za-z0-9_.\-]+): (.*)$", msg)
        if m:
            loc, msg = tuple(m[1].split(".")), m[2]
    where = f"{path}: key {short_repr(key_text(loc))}"
    at = line_of(lines, loc)
    if e["type"] == "missing":
        return f"{where}: missing (required){at}"
    if e["type"] == "value_error":  # our own checks: the message names the value and unit
        return f"{where}: {msg}{at}"
    return f"{where}: {e['msg']} (got {short_repr(e.get('input'))}){at}"


# ---------------------------------------------------------------- tables ---
def find_table(root: Path, stem: str) -> Path:
    for ext in (".parquet", ".csv"):
        p = root / f"{stem}{ext}"
        if os.path.lexists(p):
            return p
    found = find_case_variant(root, f"{stem}.csv") or find_case_variant(root, f"{stem}.parquet")
    hint = f" (found {found!r}: file names are case-sensitive)" if found else ""
    raise DatasetError(f"{root}: missing {stem}.csv or {stem}.parquet{hint}")


def check_column_names(names: list, path: Path, contract: tuple[str, ...], where: str) -> None:
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


def read_csv(path: Path, contract: tuple[str, ...]) -> pd.DataFrame:
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
        check_column_names(names, path, contract, "line 1: ")
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


def read_parquet(path: Path, contract: tuple[str, ...]) -> pd.DataFrame:
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
        check_column_names(names, path, contract, "")
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


def read_table(path: Path, contract: tuple[str, ...]) -> pd.DataFrame:
    """Read a table (.csv or .parquet) after the file checks; ``contract``: the column
    names the contract gives meaning to (for the checks on the header)."""
    if path.suffix == ".parquet":
        return read_parquet(path, contract)
    return read_csv(path, contract)


def row_at(path: Path, idx: int) -> str:
    row = idx + 1
    return f"row {row} (line {row + 1})" if path.suffix == ".csv" else f"row {row}"


def first_index(mask) -> int:
    return int(np.flatnonzero(np.asarray(mask))[0])


def time_kind(s: pd.Series) -> str:
    if pd.api.types.is_timedelta64_dtype(s.dtype):
        return "duration"
    if pd.api.types.is_datetime64_any_dtype(s.dtype):
        return "date-time"
    return "number"


def convert_times(process: pd.DataFrame, ppath: Path, errors: pd.DataFrame, epath: Path) -> None:
    """Parquet may store ``t_s`` as a duration or a date-time (docs/dataset-format.md):
    a duration becomes its seconds; date-times, which must then be in both tables, become
    seconds since the earliest ``t_s`` in ``process``: one zero for both files, so the
    two instruments stay on one clock."""
    kinds = {}
    for df, path in ((process, ppath), (errors, epath)):
        if "t_s" not in df.columns:
            return  # reported as a missing column
        kinds[path] = time_kind(df["t_s"])
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


def numeric(df: pd.DataFrame, col: str, path: Path) -> None:
    s = df[col]
    kind = time_kind(s)
    if kind != "number":
        raise DatasetError(f"{path}: column {col!r} holds {kind}s ({s.dtype}); expected numbers")
    if pd.api.types.is_bool_dtype(s.dtype):
        raise DatasetError(f"{path}: column {col!r}, {row_at(path, 0)}: expected a number, got {short_repr(s.iloc[0])} "
                           "(the column holds true/false values)")  # fmt: skip
    if s.dtype == object:
        is_bool = s.map(lambda v: isinstance(v, (bool, np.bool_))).to_numpy(dtype=bool)
        if is_bool.any():
            i = first_index(is_bool)
            raise DatasetError(f"{path}: column {col!r}, {row_at(path, i)}: expected a number, got {short_repr(s.iloc[i])}")
    if s.dtype == object or pd.api.types.is_string_dtype(s.dtype):
        conv = pd.to_numeric(s, errors="coerce")
        bad = conv.isna() & s.notna()
        if bad.any():
            i = first_index(bad.to_numpy())
            hint = ""
            if col == "t_s" and not pd.isna(pd.to_datetime(s.iloc[i], errors="coerce")):
                hint = "; write seconds (date-times are read from Parquet only, docs/dataset-format.md)"
            raise DatasetError(
                f"{path}: column {col!r}, {row_at(path, i)}: expected a number, got {short_repr(s.iloc[i])}{hint}"
            )
        df[col] = conv
    elif not pd.api.types.is_numeric_dtype(s.dtype):
        raise DatasetError(f"{path}: column {col!r} holds {s.dtype} values; expected numbers")
    df[col] = df[col].astype(float)
    nan = df[col].isna().to_numpy()
    if nan.any():
        i = first_index(nan)
        raise DatasetError(f"{path}: column {col!r}, {row_at(path, i)}: missing value (NaN)")
    inf = ~np.isfinite(df[col].to_numpy())
    if inf.any():
        i = first_index(inf)
        raise DatasetError(f"{path}: column {col!r}, {row_at(path, i)}: value must be finite, got {df[col].iloc[i]}")


def check_range(df: pd.DataFrame, col: str, path: Path, q: limits.Quantity) -> None:
    """Every value of ``col`` (already finite numbers) plausible for ``q``."""
    v = df[col].to_numpy()
    bad = ~((v >= q.lo if q.lo_inclusive else v > q.lo) & (v <= q.hi))
    if bad.any():
        i = first_index(bad)
        raise DatasetError(f"{path}: column {col!r}, {row_at(path, i)}: {q.problem(float(v[i]))}")


def _unknown_run_message(value: str, runs: dict) -> str:
    near = [r for r in runs if limits.run_id_key(r) == limits.run_id_key(value)]
    if near:
        return f"unknown run_id {short_repr(value)}: it differs from the declared {near[0]!r} only by whitespace or case"
    return f"unknown run_id {short_repr(value)} (metadata.yaml declares {some(sorted(runs))})"


def check_table(df: pd.DataFrame, path: Path, required: tuple[str, ...], runs: dict) -> None:
    missing = [c for c in required if c not in df.columns]
    if missing:
        raise DatasetError(f"{path}: missing column(s) {missing}; found {some(df.columns, 16)}")
    if df.empty:
        raise DatasetError(f"{path}: no rows (a header without data)")
    rid = df["run_id"]
    if rid.isna().any():
        i = first_index(rid.isna().to_numpy())
        raise DatasetError(f"{path}: column 'run_id', {row_at(path, i)}: missing value")
    df["run_id"] = rid.astype(str)
    unknown = ~df["run_id"].isin(list(runs))
    if unknown.any():
        i = first_index(unknown.to_numpy())
        raise DatasetError(
            f"{path}: column 'run_id', {row_at(path, i)}: {_unknown_run_message(df['run_id'].iloc[i], runs)}"
        )
    for col in required[1:]:
        numeric(df, col, path)


def run_codes(df: pd.DataFrame) -> tuple[np.ndarray, np.ndarray]:
    """``run_id`` as integer codes and the run id of each code: every comparison below
    works on the codes (a text column turned into a numpy array of Python strings would
    take 60 bytes a row)."""
    codes, uniques = pd.factorize(df["run_id"])
    return np.asarray(codes), np.asarray(uniques, dtype=object)


def check_increasing(df: pd.DataFrame, path: Path, codes: np.ndarray) -> None:
    t = df["t_s"].to_numpy()
    same = codes[1:] == codes[:-1]
    bad = same & (np.diff(t) <= 0)
    if bad.any():
        i = first_index(bad) + 1
        raise DatasetError(
            f"{path}: column 't_s', {row_at(path, i)}: time must increase within run "
            f"{df['run_id'].iloc[i]!r} ({t[i - 1]} then {t[i]}); rows of a run must be contiguous and in time order"
        )
    check_contiguous(df, path, codes)


def check_contiguous(df: pd.DataFrame, path: Path, codes: np.ndarray) -> None:
    """The rows of a run are one block."""
    starts = np.flatnonzero(np.r_[True, codes[1:] != codes[:-1]])
    seen = np.zeros(int(codes.max()) + 1 if len(codes) else 0, dtype=bool)
    for i in starts:  # one per block: as many as runs when contiguous
        if seen[codes[i]]:
            raise DatasetError(
                f"{path}: column 'run_id', {row_at(path, int(i))}: rows of run {df['run_id'].iloc[int(i)]!r} "
                "are not contiguous"
            )
        seen[codes[i]] = True


def check_increasing_errors(df: pd.DataFrame, path: Path, codes: np.ndarray) -> None:
    """Within a run, measurement times must not go backwards (equal times allowed
    only for distinct targets, e.g. an interferometer recording several at once)."""
    t = df["t_s"].to_numpy()
    same = codes[1:] == codes[:-1]
    bad = same & (np.diff(t) < 0)
    if bad.any():
        i = first_index(bad) + 1
        raise DatasetError(
            f"{path}: column 't_s', {row_at(path, i)}: time must not decrease within run "
            f"{df['run_id'].iloc[i]!r} ({t[i - 1]} then {t[i]})"
        )


def check_duplicate_rows(df: pd.DataFrame, path: Path, cols: tuple[str, ...]) -> None:
    """No two rows equal in all of ``cols`` (a reading recorded twice)."""
    dup = df.duplicated(subset=list(cols), keep="first").to_numpy()
    if dup.any():
        i = first_index(dup)
        same = np.ones(len(df), dtype=bool)
        for c in cols:
            same &= (df[c] == df[c].iloc[i]).to_numpy()
        j = first_index(same)
        values = ", ".join(f"{c} {short_repr(df[c].iloc[i], 30)}" for c in cols)
        raise DatasetError(
            f"{path}: {row_at(path, j)} and {row_at(path, i)} are the same reading ({values}); remove the copy"
        )


def check_within(df: pd.DataFrame, path: Path, col: str, lo: np.ndarray, hi: np.ndarray, why) -> None:
    """Every value of ``col`` must lie in [lo, hi] (per row); ``why(i)`` explains row i."""
    v = df[col].to_numpy()
    out = (v < lo) | (v > hi)
    if out.any():
        i = first_index(out)
        raise DatasetError(f"{path}: column {col!r}, {row_at(path, i)}: {v[i]:g} {why(i)}")
