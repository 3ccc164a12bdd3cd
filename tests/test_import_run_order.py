"""The order of a dataset's runs comes from the lab's files, never from the order their rows come in
or from the names sorted as text: the same files with their rows shuffled import as the same dataset."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from thermbench.data.importer import import_dataset
from thermbench.data.io import load_dataset
from thermbench.data.limits import natural_key

MAPPING = """\
format: thermbench-import/1
dataset:
  machine: {name: order}
  parts: [spindle]
  sensors: {t1: structure}
  channels: {z: {kind: fixed_point, direction: Z, location: spindle}}
  reference: {mode: first_reading}
files:
  log:
    path: PATH
    TIME
    columns: COLUMNS
"""


def _write(d, frame: pd.DataFrame, time: str, columns: str, path: str = "log.csv", run: str = "") -> None:
    d.mkdir(parents=True, exist_ok=True)
    text = MAPPING.replace("PATH", path).replace("TIME", time).replace("COLUMNS", columns)
    if run:
        text = text.replace("    columns:", f"    run: {run}\n    columns:")
    (d / "mapping.yaml").write_text(text, encoding="utf-8")
    if frame is not None:
        frame.to_csv(d / path, index=False)


def _log(names, seconds_from=None):
    """One CSV table of three runs, 20 rows each (a row every 60 s), in a run column."""
    rows = []
    for k, name in enumerate(names):
        t = np.arange(20) * 60.0
        rows.append(pd.DataFrame({"run": name, "t": t if seconds_from is None else seconds_from[k] + t,
                                  "temp": 20.0 + 0.1 * k + 0.01 * t / 60.0, "z_um": (k + 1) * 0.2 * t / 60.0}))
    return pd.concat(rows, ignore_index=True)


def _same(a, b) -> None:
    assert a.run_ids == b.run_ids
    pd.testing.assert_frame_equal(a.process, b.process)
    pd.testing.assert_frame_equal(a.errors, b.errors)
    assert a.metadata == b.metadata


def test_natural_key_orders_names_as_a_person_reads_them():
    names = ["run10", "Run2", "run1", "2024-03-10", "2024-03-09", "Sheet 10", "sheet 9"]
    assert sorted(names, key=natural_key) == ["2024-03-09", "2024-03-10", "run1", "Run2", "run10", "sheet 9", "Sheet 10"]
    # a superscript is a digit to str.isdigit but not a decimal number: text, not a crash
    assert sorted(["Probe_1²", "Probe_1"], key=natural_key) == ["Probe_1", "Probe_1²"]


def test_a_run_the_dataset_does_not_declare_is_never_taken_for_another(tmp_path):
    d = tmp_path / "files"
    for k in (1, 2):
        d.mkdir(exist_ok=True)
        _log([f"exp{k}"]).drop(columns="run").to_csv(d / f"exp{k}.csv", index=False)
    _write(d, None, "time: {column: t, unit: s}", "{temp: t1_C, z_um: {channel: z, unit: um}}", path="exp*.csv",
           run="{from: file}")
    text = (d / "mapping.yaml").read_text().replace("  reference:", "  runs: {exp1: {}}\n  reference:")
    (d / "mapping.yaml").write_text(text)
    from thermbench.data.import_mapping import MappingError

    with pytest.raises(MappingError, match="exp2"):
        import_dataset(d / "mapping.yaml", tmp_path / "A")


def test_a_run_column_in_seconds_orders_the_runs_naturally_whatever_the_rows_order(tmp_path):
    columns = "{run: run_id, temp: t1_C, z_um: {channel: z, unit: um}}"
    log = _log(["run10", "run2", "run1"])
    _write(tmp_path / "a", log, "time: {column: t, unit: s}", columns)
    shuffled = log.iloc[np.random.default_rng(0).permutation(len(log))]
    _write(tmp_path / "b", shuffled, "time: {column: t, unit: s}", columns)
    import_dataset(tmp_path / "a" / "mapping.yaml", tmp_path / "A")
    import_dataset(tmp_path / "b" / "mapping.yaml", tmp_path / "B")
    a, b = load_dataset(tmp_path / "A"), load_dataset(tmp_path / "B")
    # every run starts at 0 s: the natural order of the names (the table's order of first rows is run10's)
    assert a.run_ids == ["run1", "run2", "run10"]
    assert list(pd.unique(a.process["run_id"])) == a.run_ids
    _same(a, b)


def test_runs_with_timestamps_come_in_the_order_they_started(tmp_path):
    columns = "{run: run_id, temp: t1_C, z_um: {channel: z, unit: um}}"
    start = pd.Timestamp("2026-03-04 08:00:00")
    log = _log(["b_first", "a_third", "c_second"], seconds_from=[0.0, 7200.0, 3600.0])
    log["t"] = [(start + pd.Timedelta(seconds=s)).strftime("%Y-%m-%d %H:%M:%S") for s in log["t"]]
    shuffled = log.iloc[np.random.default_rng(1).permutation(len(log))]
    _write(tmp_path / "a", shuffled, 'time: {column: t, format: "%Y-%m-%d %H:%M:%S"}', columns)
    import_dataset(tmp_path / "a" / "mapping.yaml", tmp_path / "A")
    assert load_dataset(tmp_path / "A").run_ids == ["b_first", "c_second", "a_third"]


@pytest.mark.parametrize("count", [3, 11])
def test_the_files_of_a_glob_are_runs_in_the_natural_order_of_their_names(tmp_path, count):
    d = tmp_path / "files"
    for k in range(1, count + 1):
        one = _log([f"exp{k}"]).drop(columns="run")
        d.mkdir(exist_ok=True)
        one.to_csv(d / f"exp{k}.csv", index=False)
    _write(d, None, "time: {column: t, unit: s}", "{temp: t1_C, z_um: {channel: z, unit: um}}", path="exp*.csv",
           run="{from: file}")
    import_dataset(d / "mapping.yaml", tmp_path / "A")
    assert load_dataset(tmp_path / "A").run_ids == [f"exp{k}" for k in range(1, count + 1)]
