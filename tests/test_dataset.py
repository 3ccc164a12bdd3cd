"""Dataset contract: lossless round trip, and a clear error for each bad input."""

import re

import numpy as np
import pandas as pd
import pytest
import yaml

from thermbench.cli import main
from thermbench.data import DatasetError, load_dataset, save_dataset
from thermbench.sim.scenario import simulate_dataset


@pytest.fixture
def written(short_cfg, tmp_path):
    ds, _ = simulate_dataset(short_cfg)
    path = save_dataset(ds, tmp_path / "ds", file_format="csv")
    return ds, path


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_round_trip_is_lossless(short_cfg, tmp_path, fmt):
    ds, _ = simulate_dataset(short_cfg)
    ds.process["operator_note"] = "kept"  # unknown extra columns are kept
    path = save_dataset(ds, tmp_path / fmt, file_format=fmt)
    back = load_dataset(path)
    pd.testing.assert_frame_equal(back.process, ds.process, check_exact=True)
    pd.testing.assert_frame_equal(back.errors, ds.errors, check_exact=True)
    assert back.metadata.model_dump() == ds.metadata.model_dump()
    assert back.content_hash() == ds.content_hash()
    assert "operator_note" in back.process.columns


def _edit_csv(path, name, fn):
    df = pd.read_csv(path / name, dtype={"run_id": str})
    df = fn(df)
    df.to_csv(path / name, index=False)


def _set(col, row, value):
    def f(df):
        df[col] = df[col].astype(object) if isinstance(value, str) else df[col]
        df.loc[row, col] = value
        return df

    return f


CASES = {
    "missing column": ("process.csv", lambda df: df.drop(columns=["axis_mm"]), ["process.csv", "axis_mm"]),
    "NaN": ("process.csv", _set("T_nut_C", 40, np.nan), ["process.csv", "T_nut_C", "row 41", "line 42", "NaN"]),
    "non-increasing time": ("process.csv", _set("t_s", 12, 5.0), ["process.csv", "t_s", "row 13", "increase"]),
    "negative feed": ("process.csv", _set("feed_mm_min", 30, -5.0), ["process.csv", "feed_mm_min", "row 31", ">= 0"]),
    "unknown run_id": ("errors.csv", _set("run_id", 3, "zz"), ["errors.csv", "run_id", "row 4", "'zz'"]),
    "target outside travel": ("errors.csv", _set("target_mm", 2, 900.0), ["errors.csv", "target_mm", "row 3", "900"]),
    "not a number": ("errors.csv", _set("error_um", 5, "abc"), ["errors.csv", "error_um", "row 6", "'abc'"]),
    "sampling gap": ("process.csv", lambda df: df.drop(index=[100, 101, 102]), ["process.csv", "t_s", "gap"]),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input_names_file_column_and_row(written, case):
    _, path = written
    name, fn, needles = CASES[case]
    _edit_csv(path, name, fn)
    with pytest.raises(DatasetError) as err:
        load_dataset(path)
    msg = str(err.value)
    for n in needles:
        assert n in msg, (n, msg)


def test_wrong_format_version(written):
    _, path = written
    meta = yaml.safe_load((path / "metadata.yaml").read_text())
    meta["format"] = "thermbench-dataset/9"
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(DatasetError, match=r"metadata.yaml: key 'format': expected 'thermbench-dataset/1'"):
        load_dataset(path)


def test_bad_metadata_value_names_the_key(written):
    _, path = written
    meta = yaml.safe_load((path / "metadata.yaml").read_text())
    meta["screw"]["mounting"] = "glued"
    (path / "metadata.yaml").write_text(yaml.safe_dump(meta))
    with pytest.raises(DatasetError, match=r"key 'screw.mounting'"):
        load_dataset(path)


def test_unreadable_file(written):
    _, path = written
    (path / "errors.csv").write_bytes(b"\x00\x01\x02 not,a\ncsv\x00,,,\n\"unterminated")
    with pytest.raises(DatasetError, match=r"errors.csv"):
        load_dataset(path)
    (path / "errors.csv").unlink()
    with pytest.raises(DatasetError, match=r"missing errors.csv or errors.parquet"):
        load_dataset(path)


def test_cli_validate_reports_without_traceback(written, capsys):
    _, path = written
    assert main(["validate", str(path)]) == 0
    assert "valid thermbench-dataset/1" in capsys.readouterr().out
    _edit_csv(path, "process.csv", _set("feed_mm_min", 7, -1.0))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err
    assert "feed_mm_min" in err and "Traceback" not in err


def test_failed_write_leaves_nothing_half_written(written, tmp_path, monkeypatch):
    ds, path = written
    before = sorted(p.name for p in path.iterdir())
    content = (path / "process.csv").read_bytes()

    def boom(self, *a, **k):
        raise OSError("disk full")

    monkeypatch.setattr(pd.DataFrame, "to_csv", boom)
    with pytest.raises(OSError):
        save_dataset(ds, path)
    with pytest.raises(OSError):
        save_dataset(ds, tmp_path / "fresh")
    assert sorted(p.name for p in path.iterdir()) == before
    assert (path / "process.csv").read_bytes() == content
    assert not (tmp_path / "fresh").exists()
    assert [p for p in path.parent.iterdir() if p.name.startswith(".")] == []


def test_atomic_writes_get_the_usual_file_mode(tmp_path):
    """mkstemp/mkdtemp create private files (0600/0700); written files must not stay private."""
    import os

    from thermbench.outputs import write_text_atomic
    from thermbench.outputs import output_dir

    mask = os.umask(0o022)
    try:
        write_text_atomic(tmp_path / "a.txt", "x")
        with output_dir(tmp_path / "d", "test") as d:
            (d / "f").write_text("y")
    finally:
        os.umask(mask)
    assert (tmp_path / "a.txt").stat().st_mode & 0o777 == 0o644
    assert (tmp_path / "d").stat().st_mode & 0o777 == 0o755


# ---------------------------------------------------------------- hostile input ---
# (the adversarial set is tests/adversarial.py, run by tests/test_adversarial.py)


@pytest.mark.parametrize("fmt", ["csv", "parquet"])
def test_a_table_over_the_cell_cap_is_refused_before_it_is_read(written, monkeypatch, fmt):
    from thermbench.data import limits

    ds, path = written
    if fmt == "parquet":
        for name in ("process", "errors"):
            pd.read_csv(path / f"{name}.csv", dtype={"run_id": str}).to_parquet(path / f"{name}.parquet", index=False)
    rows, cols = ds.process.shape
    monkeypatch.setattr(limits, "TABLE_MAX_CELLS", rows * cols - 1)
    with pytest.raises(DatasetError, match=rf"process.{fmt}: {rows * cols} cells \({rows} rows x {cols} columns\)"):
        load_dataset(path)
    monkeypatch.setattr(limits, "TABLE_MAX_CELLS", rows * cols)
    load_dataset(path)


def test_messages_are_one_line_even_for_a_path_with_a_line_break(written, tmp_path):
    _, path = written
    odd = tmp_path / "two\nlines"
    path.rename(odd)
    (odd / "metadata.yaml").write_text("format: thermbench-dataset/1\nruns: {a: 1, a: 2}\n")
    with pytest.raises(DatasetError) as err:
        load_dataset(odd)
    msg = str(err.value)
    assert "\n" not in msg and "two\\nlines" in msg and "line 2" in msg and "duplicate key 'a'" in msg


def test_strict_yaml_loader():
    from thermbench.data.safe_yaml import YAMLInputError, load_yaml

    data, lines = load_yaml("a: 1e-5\nb:\n  when: 2024-03-04\n  n: [1, 2]\n")
    assert data == {"a": 1e-5, "b": {"when": "2024-03-04", "n": [1, 2]}}  # YAML 1.2 float; dates stay text
    assert lines == {("a",): 1, ("b",): 2, ("b", "when"): 3, ("b", "n"): 4}
    for text, needle in [("a: &x 1\nb: *x\n", "line 1: anchor &x"), ("a: *x\n", "line 1: alias *x"),
                         ("a: 1\na: 2\n", "line 2: duplicate key 'a' (first at line 1)"),
                         ("a: !!python/name:os.system\n", "'!!python/name:os.system'"),
                         ("a: " + "[" * 40 + "]" * 40, "nested deeper than 32"),
                         ("a: [" + "1," * 100_001 + "1]", "more than 100000 values")]:  # fmt: skip
        with pytest.raises(YAMLInputError, match=re.escape(needle)):
            load_yaml(text)


def test_parquet_time_as_duration_or_datetime_becomes_seconds(written, tmp_path):
    ds, path = written
    p = pd.read_csv(path / "process.csv", dtype={"run_id": str})
    e = pd.read_csv(path / "errors.csv", dtype={"run_id": str})
    (path / "process.csv").unlink()
    (path / "errors.csv").unlink()
    t0 = pd.Timestamp("2024-03-04 07:00:00", tz="Europe/Berlin")
    p.assign(t_s=t0 + pd.to_timedelta(p["t_s"] + 5.0, unit="s")).to_parquet(path / "process.parquet")
    e.assign(t_s=t0 + pd.to_timedelta(e["t_s"] + 5.0, unit="s")).to_parquet(path / "errors.parquet")
    back = load_dataset(path)  # date-times: seconds since the earliest process time, in both files
    np.testing.assert_allclose(back.process["t_s"], p["t_s"] - p["t_s"].min(), atol=1e-6)
    np.testing.assert_allclose(back.errors["t_s"], e["t_s"] - p["t_s"].min(), atol=1e-6)
    p.assign(t_s=pd.to_timedelta(p["t_s"], unit="s")).to_parquet(path / "process.parquet")
    e.assign(t_s=pd.to_timedelta(e["t_s"], unit="s")).to_parquet(path / "errors.parquet")
    back = load_dataset(path)  # durations: their seconds
    np.testing.assert_allclose(back.process["t_s"], p["t_s"], atol=1e-6)


def test_metadata_ranges_apply_to_programmatic_metadata_too():
    from pydantic import ValidationError

    from thermbench.data.schema import MaterialMeta, ScrewMeta

    with pytest.raises(ValidationError, match=r"11.7 looks like µm/\(m·K\).*write 1.17e-05"):
        MaterialMeta(alpha_per_K=11.7, density_kg_m3=7800, heat_capacity_J_kgK=460)
    with pytest.raises(ValidationError, match="finite"):
        ScrewMeta(length_m=float("inf"), diameter_m=0.04, nut_length_m=0.1, fixed_bearing_length_m=0.0,
                  mounting="fixed_free")  # fmt: skip
    with pytest.raises(ValidationError, match="shorter than the screw"):
        ScrewMeta(length_m=1.0, diameter_m=0.04, nut_length_m=1.0, fixed_bearing_length_m=0.0, mounting="fixed_free")


def test_the_table_cap_scales_with_the_machine_and_is_a_setting(monkeypatch):
    """The guard against absurd tables (docs/dataset-format.md, Limits): a quarter of the machine's
    memory and at least 256 MiB by default; $THERMBENCH_MAX_TABLE_MIB sets it; a bad setting is one
    line naming the variable."""
    from thermbench.data import limits

    MiB = limits.MiB
    monkeypatch.delenv(limits.TABLE_CAP_ENV, raising=False)
    monkeypatch.setattr(limits, "machine_memory_bytes", lambda: 64 * 1024 * MiB)
    assert limits.table_cap_bytes() == 16 * 1024 * MiB
    monkeypatch.setattr(limits, "machine_memory_bytes", lambda: 512 * MiB)
    assert limits.table_cap_bytes() == 256 * MiB  # never below 256 MiB
    monkeypatch.setenv(limits.TABLE_CAP_ENV, "1024")
    assert limits.table_cap_bytes() == 1024 * MiB
    assert limits.table_cap_bytes(mib=10) == 10 * MiB
    for bad in ("lots", "-5", "0", "nan"):
        monkeypatch.setenv(limits.TABLE_CAP_ENV, bad)
        with pytest.raises(DatasetError, match=rf"^\$THERMBENCH_MAX_TABLE_MIB='{bad}': expected a size in MiB, > 0$"):
            limits.table_cap_bytes()
