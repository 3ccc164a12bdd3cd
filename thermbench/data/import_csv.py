"""The lean CSV reader of the import: a long log read by Arrow block by block, each number
column straight into one numpy array (what ``pandas.read_csv(..., engine="pyarrow")`` reads, in
little more memory than the table it makes)."""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np
import pandas as pd

from . import limits
from .files import open_regular_file
from .tables import CSV_NA_VALUES

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
