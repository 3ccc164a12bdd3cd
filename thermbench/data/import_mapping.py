"""The import mapping file (docs/import.md): its keys (what each file is, how to read it, its
clock, what each column becomes) and reading it, validated, with :class:`MappingError` naming the
key of any mistake."""

from __future__ import annotations

import difflib
import os
from pathlib import Path
from typing import Any, Literal, Optional, Union

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator

from ..errors import UserError
from . import limits
from .errors import DatasetError, short_repr
from .files import check_regular_file, open_regular_file
from .safe_yaml import YAMLInputError, load_yaml

MAPPING_FORMAT = "thermbench-import/1"
MAPPING_MAX_BYTES = limits.METADATA_MAX_BYTES


class MappingError(UserError):
    """A mistake in an import mapping or in the files it names: one line naming the key."""


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
