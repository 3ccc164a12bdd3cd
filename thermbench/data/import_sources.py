"""The files an import mapping names, read: the paths its globs match, each CSV, Excel or
Parquet file's tables (one per sheet read) as the mapping's read options say, and their data rows
(fully empty rows left out)."""

from __future__ import annotations

import difflib
import glob as globmod
import os
import warnings
from pathlib import Path

import numpy as np
import pandas as pd

from . import limits
from .errors import DatasetError, short_repr
from .files import check_regular_file, open_regular_file
from .import_csv import _read_csv_arrow
from .import_mapping import FileMap, MappingError


# ------------------------------------------------------------------ files ---
def _source_paths(f: FileMap, base_dir: Path, where: str) -> list[Path]:
    """The file ``path`` names, or every file its glob matches (in the natural order of their names:
    ``exp2`` before ``exp10``, :func:`~thermbench.data.limits.natural_key`)."""
    raw = os.path.expanduser(f.path)
    if not any(c in raw for c in "*?["):
        p = Path(raw)
        return [p if p.is_absolute() else base_dir / p]
    pattern = raw if os.path.isabs(raw) else str(base_dir / raw)
    found = sorted((Path(p) for p in globmod.glob(pattern) if os.path.isfile(p)), key=lambda p: limits.natural_key(p.name))
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
