"""Adversarial datasets for ``thermbench validate``: bad input.

A small valid dataset is written by hand here (plain text, numpy and pandas: not with
thermbench's simulator nor ``save_dataset``), then each :class:`Case` applies one
mutation to a fresh copy of it. Every case says what must happen:

- ``valid``: ``thermbench validate`` exits 0;
- ``error``: exit 2 and exactly one line on stderr containing every one of ``needles``
  (the file name and the column / key / row, and what is wrong).

``resource`` cases (one each: alias bomb, huge file, FIFO, deep nesting, decompression bomb)
are also run in a subprocess under a time and memory limit.

    from tests.adversarial import CASES, build
    path = build(CASES["alias_bomb"], tmp_dir)
"""

from __future__ import annotations

import gzip
import hashlib
import os
import socket
import stat
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

# ------------------------------------------------------------ the base ---
META = """\
format: thermbench-dataset/1
machine: {name: test_vmc, axis: X}
screw:
  length_m: 1.0
  diameter_m: 0.04
  nut_length_m: 0.15
  fixed_bearing_length_m: 0.04
  mounting: fixed_supported
  fixed_end_axis_mm: -150.0
material:
  alpha_per_K: 1.17e-5
  density_kg_m3: 7800
  heat_capacity_J_kgK: 460
sensors:
  T_nut: nut_housing
  T_ambient: ambient
runs:
  c1:
    condition: {stroke_mm: 100, start_mm: 0, end_mm: 100, feed_mm_min: 600}
    notes: first run
  c2:
    condition: {stroke_mm: 50, start_mm: 25, end_mm: 75, feed_mm_min: 300}
"""
# line of each key in META (1-based), for the expected messages
LINE = {
    "format": 1, "machine": 2, "screw": 3, "length_m": 4, "diameter_m": 5, "nut_length_m": 6,
    "fixed_bearing_length_m": 7, "mounting": 8, "fixed_end_axis_mm": 9, "material": 10, "alpha_per_K": 11,
    "density_kg_m3": 12, "heat_capacity_J_kgK": 13, "sensors": 14, "runs": 17, "c1": 18, "c1.condition": 19,
    "c1.notes": 20, "c2": 21, "c2.condition": 22,
}  # fmt: skip

RUNS = {"c1": (0.0, 100.0, 0.02), "c2": (25.0, 75.0, 0.01)}  # start, end, nut warming °C/s
N_PER_RUN = 120  # 1 Hz process samples per run
PERIOD_S = 20  # one stroke there and back
CYCLES = 4  # measuring cycles per run, every 30 s
PROCESS_COLUMNS = ["run_id", "t_s", "axis_mm", "feed_mm_min", "T_nut_C", "T_ambient_C", "load_N", "spindle_rpm"]
ERRORS_COLUMNS = ["run_id", "t_s", "target_mm", "error_um"]


def _fmt(x: float) -> str:
    return repr(round(float(x), 6))


def base_process_rows() -> list[list[str]]:
    rows = []
    for run_id, (start, end, warm) in RUNS.items():
        t = np.arange(N_PER_RUN, dtype=float)
        phase = 1.0 - np.abs((t % PERIOD_S) / (PERIOD_S / 2) - 1.0)  # 0 -> 1 -> 0
        axis = start + (end - start) * phase
        feed = np.full_like(t, (end - start) / (PERIOD_S / 2) * 60.0)
        for k in range(N_PER_RUN):
            rows.append([run_id, _fmt(t[k]), _fmt(axis[k]), _fmt(feed[k]), _fmt(20.0 + warm * t[k]), "20.0", "0.0", "3000.0"])
    return rows


def base_errors_rows() -> list[list[str]]:
    rows = []
    for run_id, (start, end, _) in RUNS.items():
        targets = [start, (start + end) / 2, end]
        for k in range(CYCLES):
            for j, x in enumerate(targets):
                rows.append([run_id, _fmt(5 + 30 * k + 2 * j), _fmt(x), _fmt(1.0 + 0.01 * x + 0.1 * k)])
    return rows


def csv_text(columns: list[str], rows: list[list[str]], eol: str = "\n") -> str:
    return eol.join([",".join(columns)] + [",".join(r) for r in rows]) + eol


def base_frames() -> tuple[pd.DataFrame, pd.DataFrame]:
    """The base tables as typed frames (for the Parquet cases)."""
    p = pd.DataFrame(base_process_rows(), columns=PROCESS_COLUMNS)
    e = pd.DataFrame(base_errors_rows(), columns=ERRORS_COLUMNS)
    for df in (p, e):
        for c in df.columns[1:]:
            df[c] = df[c].astype(float)
    return p, e


def write_base(root: Path) -> Path:
    root.mkdir(parents=True)
    (root / "metadata.yaml").write_text(META, encoding="utf-8")
    (root / "process.csv").write_text(csv_text(PROCESS_COLUMNS, base_process_rows()), encoding="utf-8")
    (root / "errors.csv").write_text(csv_text(ERRORS_COLUMNS, base_errors_rows()), encoding="utf-8")
    return root


# ----------------------------------------------------------- mutations ---
Mutation = Callable[[Path], "Path | None"]


def replace_text(name: str, old: str, new: str, count: int = 1) -> Mutation:
    def f(root: Path) -> None:
        p = root / name
        text = p.read_text(encoding="utf-8")
        assert text.count(old) >= count, (name, old)
        p.write_text(text.replace(old, new, count), encoding="utf-8")

    return f


def meta(old: str, new: str) -> Mutation:
    return replace_text("metadata.yaml", old, new)


def write_meta(text: str) -> Mutation:
    def f(root: Path) -> None:
        (root / "metadata.yaml").write_text(text, encoding="utf-8")

    return f


def set_cell(name: str, row: int, col: str, value: str) -> Mutation:
    """Data row ``row`` (1-based) of a base CSV table, column ``col``, as the text ``value``."""

    def f(root: Path) -> None:
        cols, rows = _table(name)
        rows[row - 1][cols.index(col)] = value
        (root / name).write_text(csv_text(cols, rows), encoding="utf-8")

    return f


def set_column(name: str, col: str, value: Callable[[int, str], str]) -> Mutation:
    def f(root: Path) -> None:
        cols, rows = _table(name)
        k = cols.index(col)
        for i, r in enumerate(rows):
            r[k] = value(i, r[k])
        (root / name).write_text(csv_text(cols, rows), encoding="utf-8")

    return f


def edit_rows(name: str, fn: Callable[[list[str], list[list[str]]], tuple[list[str], list[list[str]]]]) -> Mutation:
    def f(root: Path) -> None:
        cols, rows = fn(*_table(name))
        (root / name).write_text(csv_text(cols, rows), encoding="utf-8")

    return f


def _table(name: str) -> tuple[list[str], list[list[str]]]:
    if name == "process.csv":
        return list(PROCESS_COLUMNS), base_process_rows()
    return list(ERRORS_COLUMNS), base_errors_rows()


def write_bytes(name: str, data: bytes) -> Mutation:
    def f(root: Path) -> None:
        (root / name).write_bytes(data)

    return f


def write_text(name: str, text: str) -> Mutation:
    return write_bytes(name, text.encode("utf-8"))


def rename(name: str, new_name: str) -> Mutation:
    def f(root: Path) -> None:
        (root / name).rename(root / new_name)

    return f


def move_out_and_link(name: str) -> Mutation:
    """``name`` moved next to the dataset, a symbolic link to it left in its place."""

    def f(root: Path) -> None:
        outside = root.parent / f"{root.name}.{name}"
        os.replace(root / name, outside)
        os.symlink(outside, root / name)

    return f


def truncate_end(name: str, n_bytes: int) -> Mutation:
    def f(root: Path) -> None:
        data = (root / name).read_bytes()
        (root / name).write_bytes(data[:-n_bytes])

    return f


def remove(name: str) -> Mutation:
    def f(root: Path) -> None:
        (root / name).unlink()

    return f


def chain(*fs: Mutation) -> Mutation:
    def f(root: Path):
        out = None
        for g in fs:
            out = g(root) or out
        return out

    return f


def sparse(name: str, size: int) -> Mutation:
    """``name`` replaced by a sparse file of ``size`` zero bytes (truncate: nothing written)."""

    def f(root: Path) -> None:
        p = root / name
        p.unlink(missing_ok=True)
        with open(p, "wb") as fh:
            fh.truncate(size)

    return f


def fifo(name: str) -> Mutation:
    def f(root: Path) -> None:
        (root / name).unlink()
        os.mkfifo(root / name)

    return f


def symlink(name: str, target: str) -> Mutation:
    def f(root: Path) -> None:
        (root / name).unlink(missing_ok=True)
        os.symlink(target, root / name)

    return f


def unix_socket(name: str) -> Mutation:
    def f(root: Path) -> None:
        (root / name).unlink()
        cwd = os.getcwd()
        os.chdir(root)  # a relative name: socket paths are limited to ~100 characters
        try:
            s = socket.socket(socket.AF_UNIX, socket.SOCK_STREAM)
            s.bind(name)
            s.close()  # the socket file stays
        finally:
            os.chdir(cwd)

    return f


def as_directory(name: str) -> Mutation:
    def f(root: Path) -> None:
        (root / name).unlink()
        (root / name).mkdir()
        (root / name / "inside.txt").write_text("x")

    return f


def parquet(process: pd.DataFrame | None = None, errors: pd.DataFrame | None = None,
            both: bool = False) -> Mutation:  # fmt: skip
    """Replace the CSV table(s) by Parquet ones (the given frames, else the base)."""

    def f(root: Path) -> None:
        p, e = base_frames()
        if process is not None or both:
            (root / "process.csv").unlink()
            (process if process is not None else p).to_parquet(root / "process.parquet", index=False)
        if errors is not None or both:
            (root / "errors.csv").unlink()
            (errors if errors is not None else e).to_parquet(root / "errors.parquet", index=False)

    return f


def arrow_parquet(name: str, make_table: Callable[[], object], **options) -> Mutation:
    """Write a pyarrow table built by ``make_table`` as ``name`` (replacing the CSV of that
    stem), without the arrow schema: dictionary columns are read back as their values."""

    def f(root: Path) -> None:
        import pyarrow.parquet as pq

        (root / (name.split(".")[0] + ".csv")).unlink()
        pq.write_table(make_table(), root / name, store_schema=False, **options)

    return f


def other_target(fn: Callable[[Path], Path]) -> Mutation:
    """Validate another path than the dataset directory (``fn(root)`` returns it)."""
    return fn


# -------------------------------------------------------------- cases ---
@dataclass(frozen=True)
class Case:
    name: str
    kind: str  # the class of bad input, for the report
    mutate: Mutation
    needles: tuple[str, ...] = ()
    valid: bool = False
    resource: bool = False

    @property
    def expect(self) -> str:
        return "valid" if self.valid else "error"


def build(case: Case, tmp: Path) -> Path:
    """A fresh copy of the base dataset under ``tmp`` with ``case``'s mutation: the path to validate."""
    root = write_base(tmp / case.name)
    return case.mutate(root) or root


def _p(row: int) -> tuple[str, str]:
    return f"row {row}", f"line {row + 1}"


CASES_LIST: list[Case] = []


def case(name: str, kind: str, mutate: Mutation, *needles: str, valid: bool = False, resource: bool = False) -> None:
    CASES_LIST.append(Case(name, kind, mutate, tuple(needles), valid, resource))


P, E, M = "process.csv", "errors.csv", "metadata.yaml"
C1_ROW = 1  # first process row of c1
C2_ROW = N_PER_RUN + 1  # first process row of c2
MiB = 1024 * 1024

# --- valid, if unusual
case("base", "valid", lambda root: None, valid=True)
case("parquet_tables", "valid", parquet(both=True), valid=True)
case("windows_line_endings", "valid", chain(
    write_bytes(P, csv_text(PROCESS_COLUMNS, base_process_rows(), "\r\n").encode()),
    write_bytes(E, csv_text(ERRORS_COLUMNS, base_errors_rows(), "\r\n").encode()),
    write_bytes(M, META.replace("\n", "\r\n").encode())), valid=True)  # fmt: skip
case("utf8_bom", "valid", chain(
    write_bytes(P, b"\xef\xbb\xbf" + csv_text(PROCESS_COLUMNS, base_process_rows()).encode()),
    write_bytes(M, b"\xef\xbb\xbf" + META.encode())), valid=True)  # fmt: skip
case("extra_columns", "valid", edit_rows(P, lambda c, r: (c + ["operator note"], [x + ["ok"] for x in r])), valid=True)
case("quoted_numbers", "valid", set_column(E, "error_um", lambda i, v: f'"{v}"'), valid=True)
case("columns_reordered", "valid", edit_rows(E, lambda c, r: (c[::-1], [x[::-1] for x in r])), valid=True)
case("trailing_commas", "valid", edit_rows(E, lambda c, r: (c, [x + [""] for x in r])), valid=True)
case("run_ids_na_words", "valid", chain(meta("  c1:", "  NA:"), meta("  c2:", "  'null':"),
                                        set_column(P, "run_id", lambda i, v: {"c1": "NA", "c2": "null"}[v]),
                                        set_column(E, "run_id", lambda i, v: {"c1": "NA", "c2": "null"}[v])),
     valid=True)  # fmt: skip
case("run_ids_dots_dashes", "valid", chain(meta("  c1:", "  Run-1.a_B:"),
                                           set_column(P, "run_id", lambda i, v: "Run-1.a_B" if v == "c1" else v),
                                           set_column(E, "run_id", lambda i, v: "Run-1.a_B" if v == "c1" else v)),
     valid=True)  # fmt: skip
case("yaml_comments_dates_extras", "valid", meta("machine: {name: test_vmc, axis: X}\n",
     "machine: {name: test_vmc, axis: X}  # the test machine\ncalibrated: 2024-03-04\nlab: {room: 3, ok: true}\n"),
     valid=True)  # fmt: skip
case("ds18b20_dropout_minus_127", "valid", set_cell(P, 30, "T_nut_C", "-127.0"), valid=True)
case("no_sensors", "valid", chain(meta("sensors:\n  T_nut: nut_housing\n  T_ambient: ambient\n", "sensors: {}\n"),
                                  edit_rows(P, lambda c, r: (c[:4] + c[6:], [x[:4] + x[6:] for x in r]))), valid=True)
case("symlinked_table", "valid", move_out_and_link(P), valid=True)


def _timedelta_frames():
    p, e = base_frames()
    return p.assign(t_s=pd.to_timedelta(p["t_s"], unit="s")), e.assign(t_s=pd.to_timedelta(e["t_s"], unit="s"))


def _datetime_frames(tz_p=None, tz_e=None):
    p, e = base_frames()
    t0 = pd.Timestamp("2024-03-04 07:00:00")
    pt = t0 + pd.to_timedelta(p["t_s"], unit="s")
    et = t0 + pd.to_timedelta(e["t_s"], unit="s")
    if tz_p:
        pt = pt.dt.tz_localize(tz_p)
    if tz_e:
        et = et.dt.tz_localize(tz_e)
    return p.assign(t_s=pt), e.assign(t_s=et)


case("parquet_timedelta_time", "valid", lambda root: parquet(*_timedelta_frames())(root), valid=True)
case("parquet_datetime_time", "valid", lambda root: parquet(*_datetime_frames())(root), valid=True)


def _pandas_index_parquet(root: Path) -> None:
    (root / P).unlink()
    base_frames()[0].set_index("run_id").to_parquet(root / "process.parquet")  # run_id stored as the index


case("parquet_pandas_index", "valid", _pandas_index_parquet, valid=True)

# --- files
case("missing_metadata", "files", remove(M), "missing metadata.yaml")
case("metadata_yml_spelling", "files", rename(M, "metadata.yml"), "missing metadata.yaml", "metadata.yml")
case("missing_process", "files", remove(P), "missing process.csv or process.parquet")
case("missing_errors", "files", remove(E), "missing errors.csv or errors.parquet")
case("process_wrong_case", "files", rename(P, "Process.csv"), "missing process.csv", "Process.csv")
case("dataset_is_a_file", "files", other_target(lambda root: root / P), "process.csv", "not a dataset directory")
case("dataset_does_not_exist", "files", other_target(lambda root: root / "nope"), "nope", "does not exist")
case("metadata_is_a_directory", "files", as_directory(M), M, "is a directory")
case("process_is_a_directory", "files", as_directory(P), P, "is a directory")
case("process_fifo", "files", fifo(P), P, "named pipe", resource=True)
case("metadata_fifo", "files", fifo(M), M, "named pipe")
case("errors_dev_zero_symlink", "files", symlink(E, "/dev/zero"), E, "character device", "/dev/zero")
case("metadata_dev_zero_symlink", "files", symlink(M, "/dev/zero"), M, "character device")
case("process_dev_null_symlink", "files", symlink(P, "/dev/null"), P, "character device")
case("process_socket", "files", unix_socket(P), P, "socket")
case("process_broken_symlink", "files", symlink(P, "does-not-exist.csv"), P, "broken symbolic link")
case("process_huge_sparse_300MiB", "files", sparse(P, 300 * MiB), P, "too large", "256.0 MiB", resource=True)
case("errors_sparse_100MiB_zeros", "files", sparse(E, 100 * MiB), E, "line 1", "NUL byte")
case("metadata_huge_sparse_2MiB", "files", sparse(M, 2 * MiB), M, "too large", "1.0 MiB")
case("parquet_huge_sparse_1GiB", "files", chain(remove(P), sparse("process.parquet", 1024 * MiB)),
     "process.parquet", "too large")  # fmt: skip

# --- metadata.yaml: encoding and YAML
case("metadata_not_utf8", "yaml", write_bytes(M, META.replace("first run", "café").encode("latin-1")), M, "line 20",
     "not UTF-8")
case("metadata_empty", "yaml", write_meta(""), M, "is empty")
case("metadata_top_level_list", "yaml", write_meta("- format: thermbench-dataset/1\n"), M, "mapping")
case("yaml_syntax_error", "yaml", meta("machine: {name: test_vmc, axis: X}", "machine: {name: test_vmc, axis: X"),
     M, "line 3", "not valid YAML")
case("yaml_tab_indent", "yaml", meta("  length_m: 1.0", "\tlength_m: 1.0"), M, "line 4", "tab")
case("yaml_billion_laughs", "yaml", write_meta(
    'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n'
    + "".join(f"{chr(98 + i)}: &{chr(98 + i)} [{','.join(['*' + chr(97 + i)] * 9)}]\n" for i in range(8))
    + META), M, "line 1", "anchor &a", resource=True)  # fmt: skip
case("yaml_alias_reuse", "yaml", chain(meta("condition: {stroke_mm: 100", "condition: &cond {stroke_mm: 100"),
                                       meta("condition: {stroke_mm: 50, start_mm: 25, end_mm: 75, feed_mm_min: 300}",
                                            "condition: *cond")),
     M, f"line {LINE['c1.condition']}", "anchor &cond")  # fmt: skip
case("yaml_duplicate_run", "yaml", meta("  c2:\n", "  c1:\n"), M, f"line {LINE['c2']}", "duplicate key 'c1'",
     f"first at line {LINE['c1']}")
case("yaml_duplicate_runs_key", "yaml",
     write_meta(META + "runs:\n  c3:\n    condition: {stroke_mm: 0, start_mm: 0, end_mm: 0, feed_mm_min: 0}\n"),
     M, "line 23", "duplicate key 'runs'", f"first at line {LINE['runs']}")  # fmt: skip
case("yaml_duplicate_screw_key", "yaml", meta("  diameter_m: 0.04\n", "  diameter_m: 0.04\n  length_m: 2.0\n"),
     M, "line 6", "duplicate key 'length_m'")
case("yaml_python_object_tag", "yaml", meta("  notes: first run", "  notes: !!python/object/apply:os.system ['true']"),
     M, f"line {LINE['c1.notes']}", "!!python/object/apply:os.system")
case("yaml_custom_tag", "yaml", meta("  density_kg_m3: 7800", "  density_kg_m3: !steel 7800"), M,
     f"line {LINE['density_kg_m3']}", "'!steel'")
case("yaml_binary_tag", "yaml", meta("  notes: first run", "  notes: !!binary aGVsbG8="), M, "!!binary")
case("yaml_deep_flow_nesting", "yaml", meta("  notes: first run", "  notes: " + "[" * 50000 + "]" * 50000), M,
     f"line {LINE['c1.notes']}", "nested deeper than 32", resource=True)
case("yaml_deep_block_nesting", "yaml",
     write_meta(META + "deep:\n" + "".join("  " * (i + 1) + f"k{i}:\n" for i in range(100)) + "  " * 101 + "end: 1\n"),
     M, "line 55", "nested deeper than 32")  # fmt: skip
case("yaml_merge_key", "yaml", meta("  c2:\n    condition:", "  c2:\n    <<: {notes: x}\n    condition:"), M,
     "line 22", "merge key")
case("yaml_nul_byte", "yaml", meta("first run", "first\x00run"), M, f"line {LINE['c1.notes']}", "not valid YAML")
case("yaml_two_documents", "yaml", write_meta(META + "---\nformat: x\n"), M, "single document")
case("yaml_huge_integer", "yaml", meta("  density_kg_m3: 7800", "  density_kg_m3: " + "7" * 5000), M,
     f"line {LINE['density_kg_m3']}", "not an integer")
case("format_wrong", "yaml", meta("thermbench-dataset/1", "thermbench-dataset/9"), M, "key 'format'",
     "thermbench-dataset/1", "line 1")
case("format_missing", "yaml", meta("format: thermbench-dataset/1\n", ""), M, "key 'format'", "None")

# --- run ids
RID = "c2 (6000 mm/min) #2"
case("run_id_spaces_parens_hash", "run ids", chain(meta("  c2:", f'  "{RID}":'),
                                                   set_column(P, "run_id", lambda i, v: RID if v == "c2" else v),
                                                   set_column(E, "run_id", lambda i, v: RID if v == "c2" else v)),
     M, f"runs.{RID}", f"line {LINE['c2']}", "not allowed", "A-Z a-z 0-9 _ . -")  # fmt: skip
case("run_id_slash", "run ids", meta("  c2:", "  a/b:"), M, "'a/b'", "'/'", f"line {LINE['c2']}")
case("run_id_leading_space", "run ids", meta("  c1:", '  " c1":'), M, "' c1'", "whitespace", f"line {LINE['c1']}")
case("run_id_case_collision", "run ids", meta("  c2:", "  C1:"), M, "'C1'", "'c1'", "differ only by case",
     f"line {LINE['c2']}")
case("run_id_unquoted_number", "run ids", meta("  c2:", "  2:"), M, "runs.2", "not text", "quote it",
     f"line {LINE['c2']}")
case("run_id_yaml_boolean", "run ids", meta("  c2:", "  on:"), M, "runs.True", "not text", f"line {LINE['c2']}")
case("run_id_dot_dot", "run ids", meta("  c2:", '  "..":'), M, "'..'", "start with a letter or digit")
case("run_id_too_long", "run ids", meta("  c2:", "  " + "r" * 65 + ":"), M, "65 characters")
case("run_id_windows_device", "run ids", meta("  c2:", "  CON:"), M, "'CON'", "Windows")
case("run_id_non_ascii", "run ids", meta("  c2:", "  ré2:"), M, "'ré2'", "'é'")
case("table_run_id_whitespace", "run ids", set_cell(E, 1, "run_id", " c1"), E, "column 'run_id'", *_p(1), "' c1'",
     "only by whitespace or case")
case("table_run_id_case", "run ids", set_cell(P, 5, "run_id", "C1"), P, "column 'run_id'", *_p(5), "'C1'",
     "only by whitespace or case")
case("table_unknown_run_id", "run ids", set_cell(E, 4, "run_id", "zz"), E, "column 'run_id'", *_p(4), "'zz'")
case("table_missing_run_id", "run ids", set_cell(P, 7, "run_id", ""), P, "column 'run_id'", *_p(7), "missing")
case("declared_run_without_rows", "run ids",
     write_meta(META + "  c3:\n    condition: {stroke_mm: 0, start_mm: 0, end_mm: 0, feed_mm_min: 0}\n"),
     P, "'c3'", "no rows")  # fmt: skip

# --- metadata values
case("alpha_in_um_per_m_K", "metadata values", meta("alpha_per_K: 1.17e-5", "alpha_per_K: 11.7"), M,
     "material.alpha_per_K", f"line {LINE['alpha_per_K']}", "1/K", "11.7 looks like µm/(m·K)", "write 1.17e-05")
case("alpha_negative", "metadata values", meta("alpha_per_K: 1.17e-5", "alpha_per_K: -1.17e-5"), M,
     "material.alpha_per_K", "1/K", "-1.17e-05")
case("alpha_inf", "metadata values", meta("alpha_per_K: 1.17e-5", "alpha_per_K: .inf"), M, "material.alpha_per_K",
     "finite")
case("alpha_nan", "metadata values", meta("alpha_per_K: 1.17e-5", "alpha_per_K: .nan"), M, "material.alpha_per_K",
     "finite")
case("alpha_text", "metadata values", meta("alpha_per_K: 1.17e-5", "alpha_per_K: steel"), M, "material.alpha_per_K",
     "expected a number of 1/K", "'steel'")
case("alpha_boolean", "metadata values", meta("alpha_per_K: 1.17e-5", "alpha_per_K: true"), M,
     "material.alpha_per_K", "True")
case("density_in_g_cm3", "metadata values", meta("density_kg_m3: 7800", "density_kg_m3: 7.8"), M,
     "material.density_kg_m3", "kg/m³", "g/cm³", "write 7800")
case("heat_capacity_in_kJ", "metadata values", meta("heat_capacity_J_kgK: 460", "heat_capacity_J_kgK: 0.46"), M,
     "material.heat_capacity_J_kgK", "J/(kg·K)", "write 460")
case("length_inf", "metadata values", meta("length_m: 1.0", "length_m: .inf"), M, "screw.length_m", "finite",
     f"line {LINE['length_m']}")
case("length_overflowing_float", "metadata values", meta("length_m: 1.0", "length_m: 1.0e400"), M, "screw.length_m",
     "finite")
case("length_zero", "metadata values", meta("length_m: 1.0", "length_m: 0"), M, "screw.length_m", "> 0")
case("length_in_mm", "metadata values", meta("length_m: 1.0", "length_m: 1000"), M, "screw.length_m",
     "looks like mm", "write 1")
case("nut_longer_than_screw", "metadata values", meta("nut_length_m: 0.15", "nut_length_m: 1.2"), M,
     "screw.nut_length_m", "shorter than the screw", f"line {LINE['nut_length_m']}")
case("diameter_negative", "metadata values", meta("diameter_m: 0.04", "diameter_m: -0.04"), M, "screw.diameter_m",
     " m,")
case("fixed_end_nan", "metadata values", meta("fixed_end_axis_mm: -150.0", "fixed_end_axis_mm: .nan"), M,
     "screw.fixed_end_axis_mm", "finite", "mm")
case("condition_feed_inf", "metadata values", meta("feed_mm_min: 600", "feed_mm_min: .inf"), M,
     "runs.c1.condition.feed_mm_min", "finite", "mm/min")
case("condition_start_text", "metadata values", meta("start_mm: 25", "start_mm: left"), M,
     "runs.c2.condition.start_mm", "'left'")
case("mounting_missing", "metadata values", meta("  mounting: fixed_supported\n", ""), M, "screw.mounting", "missing")
case("mounting_unknown", "metadata values", meta("mounting: fixed_supported", "mounting: glued"), M, "screw.mounting",
     "'glued'")
case("runs_empty", "metadata values", write_meta(META.split("runs:")[0] + "runs: {}\n"), M, "runs", "at least one run")

# --- tables: structure
case("duplicate_column_csv", "table structure", edit_rows(P, lambda c, r: (c + ["axis_mm"], [x + [x[2]] for x in r])),
     P, "line 1", "'axis_mm' appears twice", "columns 3 and 9")


def _dup_parquet():
    import pyarrow as pa

    p, _ = base_frames()
    arrays = [pa.array(p[c]) for c in p.columns] + [pa.array(p["t_s"])]
    return pa.Table.from_arrays(arrays, names=list(p.columns) + ["t_s"])


case("duplicate_column_parquet", "table structure", arrow_parquet("process.parquet", _dup_parquet),
     "process.parquet", "'t_s' appears twice")
case("header_whitespace", "table structure", edit_rows(P, lambda c, r: ([c[0], " t_s"] + c[2:], r)), P, "' t_s'",
     "whitespace", "write 't_s'")
case("missing_column", "table structure", edit_rows(P, lambda c, r: (c[:2] + c[3:], [x[:2] + x[3:] for x in r])), P,
     "missing column", "axis_mm")
case("missing_sensor_column", "table structure",
     edit_rows(P, lambda c, r: (c[:4] + ["T_nut"] + c[5:], r)), P, "missing column", "T_nut_C")
case("semicolon_delimiter", "table structure",
     write_text(P, csv_text(PROCESS_COLUMNS, base_process_rows()).replace(",", ";")), P, "line 1", "semicolon")
case("tab_delimiter", "table structure",
     write_text(E, csv_text(ERRORS_COLUMNS, base_errors_rows()).replace(",", "\t")), E, "line 1", "tab-separated")
case("empty_table", "table structure", write_bytes(P, b""), P, "is empty")
case("blank_table", "table structure", write_bytes(E, b"\n\n  \n"), E, "is empty")
case("blank_line_inside", "table structure", edit_rows(P, lambda c, r: (c, r[:9] + [[""]] + r[9:])), P, "line 11",
     "empty line")
case("blank_first_line", "table structure", write_text(E, "\n" + csv_text(ERRORS_COLUMNS, base_errors_rows())), E,
     "line 1", "header")
case("old_mac_line_endings", "valid", write_bytes(E, csv_text(ERRORS_COLUMNS, base_errors_rows(), "\r").encode()),
     valid=True)
case("blank_lines_at_end", "valid", write_text(E, csv_text(ERRORS_COLUMNS, base_errors_rows()) + "\n\n  \n"),
     valid=True)
case("header_only", "table structure", write_bytes(E, b"run_id,t_s,target_mm,error_um\n"), E, "no rows")
case("binary_garbage", "table structure",
     write_bytes(P, np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes()), P, "NUL byte")
case("binary_no_nul_not_utf8", "table structure", write_bytes(E, bytes(range(1, 256)) * 4), E, "not UTF-8")
def _latin1_table(root: Path) -> None:
    rows = [x + ["ok"] for x in base_process_rows()]
    rows[9][-1] = "café"
    (root / P).write_bytes(csv_text(PROCESS_COLUMNS + ["note"], rows).encode("latin-1"))


case("latin1_in_table", "table structure", _latin1_table, P, "line 11", "not UTF-8", "0xe9")
case("gzip_as_csv", "table structure",
     write_bytes(P, gzip.compress(csv_text(PROCESS_COLUMNS, base_process_rows()).encode(), mtime=0)), P, "NUL byte")
case("row_with_extra_field", "table structure", edit_rows(E, lambda c, r: (c, r[:5] + [r[5] + ["99"]] + r[6:])), E,
     "line 7", "5 fields, more than the 4 columns")
case("first_row_with_extra_field", "table structure", edit_rows(E, lambda c, r: (c, [r[0] + ["99"]] + r[1:])), E,
     "line 2", "5 fields, more than the 4 columns")
case("row_with_two_extra_fields", "table structure",
     edit_rows(E, lambda c, r: (c, r[:5] + [r[5] + ["99", "98"]] + r[6:])), E, "line 7", "6 fields")
case("unterminated_quote", "table structure", set_cell(E, 6, "error_um", '"1.5'), E, "not a readable CSV")
case("first_line_without_break", "table structure", write_bytes(P, b"run_id," + b"x" * (70 * 1024)), P, "line 1",
     "64 KiB")
case("parquet_truncated", "table structure", chain(parquet(both=True), truncate_end("process.parquet", 100)),
     "process.parquet", "not a readable Parquet")
case("parquet_is_text", "table structure", chain(remove(E), write_bytes("errors.parquet", b"run_id,t_s\nc1,1\n")),
     "errors.parquet", "not a readable Parquet")
case("parquet_nested_column", "table structure",
     lambda root: parquet(process=base_frames()[0].assign(axis_mm=[[1.0, 2.0]] * (2 * N_PER_RUN)))(root),
     "process.parquet", "'axis_mm'", "list")  # fmt: skip


def _parquet_cell_bomb():
    import pyarrow as pa

    n = 17_000_000  # 2 columns: 34 M cells, a few hundred kB on disk
    idx = pa.array(np.zeros(n, dtype=np.int8))
    return pa.table({"run_id": pa.DictionaryArray.from_arrays(idx, pa.array(["c1"])),
                     "t_s": pa.DictionaryArray.from_arrays(idx, pa.array([0.0]))})  # fmt: skip


def _parquet_text_bomb():
    import pyarrow as pa

    p, _ = base_frames()
    t = pa.Table.from_pandas(p, preserve_index=False)
    big = "x" * (4 * MiB)  # one 4 MiB text, repeated in every row: 960 MiB decoded
    note = pa.DictionaryArray.from_arrays(pa.array(np.zeros(len(p), dtype=np.int8)), pa.array([big]))
    return t.append_column("note", note)  # written without the arrow schema: read back as plain text


def _parquet_list_bomb():
    import pyarrow as pa

    p, _ = base_frames()
    t = pa.Table.from_pandas(p, preserve_index=False)
    per_row = 140_000  # 240 rows x 140 000 list items: 33.6 M values in an extra column
    items = pa.ListArray.from_arrays(pa.array(np.arange(len(p) + 1, dtype=np.int32) * per_row),
                                     pa.array(np.zeros(len(p) * per_row, dtype=np.int8)))  # fmt: skip
    return t.append_column("samples", items)


case("parquet_list_bomb", "table structure", arrow_parquet("process.parquet", _parquet_list_bomb, compression="zstd",
                                                          use_dictionary=False),
     "process.parquet",
     "cells", "list items included")
case("parquet_cell_bomb", "table structure", arrow_parquet("process.parquet", _parquet_cell_bomb), "process.parquet",
     "34000000 cells")
case("parquet_text_bomb", "table structure", arrow_parquet("process.parquet", _parquet_text_bomb), "process.parquet",
     "once decoded", resource=True)

# --- tables: values
NUMERIC_P = ["t_s", "axis_mm", "feed_mm_min", "T_nut_C", "T_ambient_C", "load_N", "spindle_rpm"]
NUMERIC_E = ["t_s", "target_mm", "error_um"]
for k, col in enumerate(NUMERIC_P):
    row = 10 + 7 * k
    case(f"nan_process_{col}", "values: NaN/inf", set_cell(P, row, col, ["", "nan", "NaN", "NA"][k % 4]), P,
         f"'{col}'", *_p(row), "missing value")
    case(f"inf_process_{col}", "values: NaN/inf", set_cell(P, row + 1, col, ["inf", "-inf", "Infinity"][k % 3]), P,
         f"'{col}'", *_p(row + 1), "finite")
for k, col in enumerate(NUMERIC_E):
    row = 3 + k
    case(f"nan_errors_{col}", "values: NaN/inf", set_cell(E, row, col, ""), E, f"'{col}'", *_p(row), "missing value")
    case(f"inf_errors_{col}", "values: NaN/inf", set_cell(E, row + 1, col, "inf"), E, f"'{col}'", *_p(row + 1),
         "finite")
case("text_in_temperature", "values: types", set_cell(P, 40, "T_nut_C", "ERR"), P, "'T_nut_C'", *_p(40), "'ERR'")
case("text_in_error", "values: types", set_cell(E, 6, "error_um", "abc"), E, "'error_um'", *_p(6), "'abc'")
case("comma_decimal", "values: types", set_cell(E, 2, "error_um", '"1,5"'), E, "'error_um'", *_p(2), "'1,5'")
case("datetime_text_in_csv_time", "values: types", set_cell(E, 1, "t_s", "2024-03-04 07:00:05"), E, "'t_s'", *_p(1),
     "write seconds")
case("booleans_in_feed", "values: types", set_column(P, "feed_mm_min", lambda i, v: "True" if i % 2 else "False"), P,
     "'feed_mm_min'", *_p(1), "true/false")
case("boolean_in_error", "values: types", set_cell(E, 5, "error_um", "True"), E, "'error_um'", *_p(5), "'True'")
case("parquet_boolean_temperature", "values: types",
     lambda root: parquet(process=base_frames()[0].assign(T_nut_C=True))(root), "process.parquet", "'T_nut_C'",
     "row 1", "true/false")  # fmt: skip
case("parquet_datetime_axis", "values: types",
     lambda root: parquet(process=base_frames()[0].assign(axis_mm=pd.Timestamp("2024-01-01")))(root),
     "process.parquet", "'axis_mm'", "date-time")  # fmt: skip
case("parquet_datetime_process_only", "values: types", lambda root: parquet(process=_datetime_frames()[0])(root),
     "process.parquet", "'t_s'", "date-times", "errors.csv")
case("parquet_datetime_tz_mismatch", "values: types",
     lambda root: parquet(*_datetime_frames(tz_p="UTC"))(root), "errors.parquet", "'t_s'", "time zone")
case("temperature_in_kelvin", "values: ranges", set_column(P, "T_ambient_C", lambda i, v: "293.15"), P,
     "'T_ambient_C'", *_p(1), "°C", "looks like kelvin")
case("temperature_missing_code", "values: ranges", set_cell(P, 50, "T_nut_C", "-999"), P, "'T_nut_C'", *_p(50),
     "°C")
case("error_in_nm", "values: ranges", set_cell(E, 8, "error_um", "12000"), E, "'error_um'", *_p(8), "µm",
     "looks like nm")
case("feed_absurd", "values: ranges", set_cell(P, 3, "feed_mm_min", "600000"), P, "'feed_mm_min'", *_p(3), "mm/min")
case("axis_in_um", "values: ranges", set_column(P, "axis_mm", lambda i, v: _fmt(float(v) * 1000 + 1e6)), P,
     "'axis_mm'", *_p(1), "looks like µm")
case("feed_negative", "values: ranges", set_cell(P, 31, "feed_mm_min", "-5.0"), P, "'feed_mm_min'", *_p(31), ">= 0")
case("spindle_negative", "values: ranges", set_cell(P, 12, "spindle_rpm", "-1"), P, "'spindle_rpm'", *_p(12), ">= 0")
case("time_goes_back", "values: time", set_cell(P, 13, "t_s", "5.0"), P, "'t_s'", *_p(13), "increase")
case("time_repeats", "values: time", set_cell(P, 13, "t_s", "11.0"), P, "'t_s'", *_p(13), "increase")
case("errors_time_goes_back", "values: time", set_cell(E, 5, "t_s", "1.0"), E, "'t_s'", *_p(5), "decrease")
case("sample_gap", "values: time", edit_rows(P, lambda c, r: (c, r[:20] + r[23:])), P, "'t_s'", *_p(21), "gap")
case("run_not_contiguous", "values: time", edit_rows(P, lambda c, r: (c, r[:N_PER_RUN - 1] + r[N_PER_RUN:] + [r[N_PER_RUN - 1]])),
     P, "'run_id'", "'c1'", "not contiguous")  # fmt: skip
case("target_outside_travel", "values: travel", set_cell(E, 3, "target_mm", "900.0"), E, "'target_mm'", *_p(3),
     "outside the travel")
case("reading_outside_process_log", "values: travel", set_cell(E, 24, "t_s", "500.0"), E, "'t_s'", *_p(24),
     "outside the process log")
case("duplicate_error_row", "values: duplicates", edit_rows(E, lambda c, r: (c, r[:3] + [list(r[2])] + r[3:])), E,
     "row 3 (line 4)", "row 4 (line 5)", "same reading")


CASES: dict[str, Case] = {c.name: c for c in CASES_LIST}
assert len(CASES) == len(CASES_LIST), "case names must be unique"


# ------------------------------------------------------------ hashing ---
HASH_MAX_BYTES = 16 * MiB


def snapshot(path: Path) -> dict[str, tuple]:
    """What every entry under ``path`` is (type, and content hash or link target), read
    without opening anything but regular files. A file over 16 MiB (the sparse ones) is
    recorded by size, modification and change times instead of read whole: any write
    changes its ctime, which no program can set back."""
    out: dict[str, tuple] = {}

    def one(p: Path, rel: str) -> None:
        st = os.lstat(p)
        if stat.S_ISLNK(st.st_mode):
            out[rel] = ("link", os.readlink(p))
        elif stat.S_ISDIR(st.st_mode):
            out[rel] = ("dir",)
            for child in sorted(os.listdir(p)):
                one(p / child, f"{rel}/{child}")
        elif stat.S_ISREG(st.st_mode) and st.st_size > HASH_MAX_BYTES:
            out[rel] = ("big file", st.st_size, st.st_mtime_ns, st.st_ctime_ns)
        elif stat.S_ISREG(st.st_mode):
            h = hashlib.sha256()
            with open(p, "rb") as fh:
                for chunk in iter(lambda: fh.read(1 << 22), b""):
                    h.update(chunk)
            out[rel] = ("file", st.st_size, h.hexdigest())
        else:
            out[rel] = ("special", stat.S_IFMT(st.st_mode))

    if os.path.lexists(path):
        one(path, ".")
    return out
