"""``thermbench import`` and dataset format 2 on data thermbench did not make: the measured
spindle test shipped in the package (checked against the workbook read cell by cell with
openpyxl and against the test plan in its SOURCE.md) and a lab's three files
(tests/labfiles.py, checked against the closed-form truth they were written from)."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import openpyxl
import pandas as pd
import pytest

from tests import labfiles
from thermbench.cli import main
from thermbench.data import load_dataset
from thermbench.data.import_mapping import MappingError
from thermbench.data.importer import import_dataset
from thermbench.data.reference import thermal_errors
from thermbench.data.views import split_segments

REALDATA = Path(__file__).resolve().parents[1] / "thermbench" / "realdata" / "fl_thermal"
MAPPING = REALDATA / "mapping.yaml"


@pytest.fixture(scope="module")
def workbook() -> pd.DataFrame:
    """The workbook's cells as openpyxl reads them (not through pandas or thermbench)."""
    wb = openpyxl.load_workbook(REALDATA / "data.xlsx", read_only=True, data_only=True)
    rows = list(wb.worksheets[0].iter_rows(values_only=True))
    wb.close()
    return pd.DataFrame(rows[1:], columns=[str(c) for c in rows[0]])


@pytest.fixture(scope="module")
def fl(tmp_path_factory):
    return import_dataset(MAPPING, tmp_path_factory.mktemp("fl") / "fl_thermal")


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    root = tmp_path_factory.mktemp("lab")
    mapping = labfiles.write_lab_files(root / "files")
    return import_dataset(mapping, root / "dataset", file_format="csv")


# ------------------------------------------------------------ the spindle test ---
def test_spindle_test_imports_every_cell(fl, workbook):
    ds = load_dataset(fl.path)  # what was written loads again
    assert ds.metadata.format == "thermbench-dataset/2" and ds.metadata.parts == ["spindle"]
    assert len(ds.process) == len(workbook) == 11115
    np.testing.assert_array_equal(ds.process["t_s"], workbook.iloc[:, 0].astype(float))
    np.testing.assert_array_equal(ds.process["spindle_rpm"], workbook["spindle(RPM)"].astype(float))
    for i in (1, 9, 16):
        np.testing.assert_array_equal(ds.process[f"t{i}_C"], workbook[f"t{i}(°C)"].astype(float))
    te = thermal_errors(ds)
    for ch in ("ch1", "ch3", "ch5"):
        raw = workbook[f"{ch}(um)"].astype(float).to_numpy()
        got = te[te["channel"] == ch].sort_values("t_s")
        np.testing.assert_allclose(got["error_um"], raw)
        # reference: first_reading -> the drift from the first sample
        np.testing.assert_allclose(got["thermal_um"], raw - raw[0], atol=1e-12)
    # the README's ranges: ch3 from -71 to 18 µm
    ch3 = te[te["channel"] == "ch3"]["error_um"]
    assert round(ch3.min()) == -71 and round(ch3.max()) == 18


def test_spindle_test_segments_are_its_test_plan(fl):
    seg = split_segments(fl)
    plan = {"rpm1250": (465, 1250), "rpm2500": (29265, 2500), "rpm3750": (58065, 3750), "rpm5000": (86865, 5000),
            "rpm3500": (115665, 3500)}  # fmt: skip  (SOURCE.md)
    assert list(seg.metadata.runs) == [*plan, "tail"]
    for name, (start, rpm) in plan.items():
        pr = seg.process_run(name)
        assert pr["t_s"].iloc[0] == start
        assert seg.metadata.runs[name].condition.levels() == {"spindle_rpm": rpm}
        # the 4 h heating and the 4 h stop after it
        assert pr["t_s"].iloc[-1] == start + 28800 - 15
    assert seg.metadata.runs["tail"].condition is None  # a duty cycle, not one level
    assert seg.process_run("tail")["t_s"].iloc[0] == 144465
    # every segment keeps the readings of its time span
    assert set(seg.errors["run_id"]) == set(seg.metadata.runs)


def test_shipped_dataset_loads_by_name_and_is_cached(tmp_path):
    from thermbench.bench import datasets

    ds = datasets.load_benchmark("fl_thermal", root=tmp_path)
    assert ds.metadata.machine.name == "fl_thermal" and len(ds.process) == 11115
    meta = tmp_path / "fl_thermal" / "metadata.yaml"
    before = meta.stat().st_mtime_ns
    datasets.load_benchmark("fl_thermal", root=tmp_path)
    assert meta.stat().st_mtime_ns == before  # from the cache, not imported again


# ------------------------------------------------------------- the lab's files ---
def test_lab_files_temperatures_interpolated_on_the_cnc_clock(lab):
    pr = lab.process
    assert len(pr) == 28801  # the 4 Hz CNC trace is the process clock (align.base: cnc)
    t = pr["t_s"].to_numpy()
    assert np.allclose(np.diff(t), 0.25)
    # the logger's 10 s readings (3 decimals) interpolated linearly onto the CNC times
    assert np.max(np.abs(pr["T_nut_C"] - labfiles.t_nut_C(t))) < 0.01
    assert np.max(np.abs(pr["T_amb_C"] - labfiles.t_ambient_C(t))) < 0.01


def test_lab_files_feed_from_signed_velocity(lab):
    pr = lab.process
    _, v = labfiles.axis_at(pr["t_s"].to_numpy())
    np.testing.assert_allclose(pr["feed_mm_min"], np.abs(v) * 60.0, atol=1e-6)
    assert (pr["feed_mm_min"] >= 0).all() and pr["feed_mm_min"].max() == pytest.approx(labfiles.FEED_MM_MIN)


def test_lab_files_clock_offsets_put_readings_at_their_true_times(lab):
    truth = labfiles.readings_truth()
    er = lab.errors.sort_values("t_s").reset_index(drop=True)
    np.testing.assert_allclose(er["t_s"], truth["t_s"], atol=1e-6)
    np.testing.assert_allclose(er["target_mm"], truth["target_mm"])
    np.testing.assert_array_equal(er["direction"], truth["direction"])
    np.testing.assert_allclose(er["error_um"], truth["error_um"], atol=1e-3)  # mm with 7 decimals -> 0.1 nm


def test_bidirectional_thermal_error_excludes_the_reversal(lab):
    te = thermal_errors(lab).sort_values("t_s").reset_index(drop=True)
    truth = labfiles.readings_truth()
    # each direction is referenced to its own cold pass: the thermal part alone remains
    np.testing.assert_allclose(te["thermal_um"], truth["thermal_um"], atol=1e-3)
    view = lab.channel_view("X")
    assert np.abs(view.errors["thermal_um"]).max() == pytest.approx(truth["thermal_um"].abs().max(), abs=1e-3)


def test_iso230_on_the_lab_files(lab, tmp_path):
    from thermbench.iso230.report import iso230_report

    figs = iso230_report(lab.path, tmp_path / "iso")
    e = figs["runs"]["warmup_6000"]["channels"]["X"]
    assert e["iso230_2_run"]["B_um"] == pytest.approx(labfiles.REVERSAL_UM, abs=1e-3)
    cold = e["iso230_2_per_cycle"][0]
    # by hand, cold cycle: deviations 3 sin(2 pi x / 400) +/- 2 over x = 0..400 step 50:
    # E = (3 + 2) - (-3 - 2) = 10, M = 3 - (-3) = 6
    assert cold["E_um"] == pytest.approx(10.0, abs=2e-3) and cold["M_um"] == pytest.approx(6.0, abs=2e-3)
    last = e["error_lines"][-1]
    assert last["slope_um_per_m"] == pytest.approx(float(labfiles.slope_um_per_m(last["t_s"])), rel=0.01)
    assert (tmp_path / "iso" / "report.md").is_file() and (tmp_path / "iso" / "drift_warmup_6000.png").is_file()
    # the lab declares cold_cycle: the frame named is the error as read, its cold cycle the geometric error
    assert "cold measuring cycle" in figs["frame"] and "first reading" not in figs["frame"]
    assert f"Scored on: {figs['frame']} — " in (tmp_path / "iso" / "report.md").read_text(encoding="utf-8")


def test_iso230_on_the_spindle_test(fl, workbook, tmp_path, capsys):
    assert main(["iso230", str(fl.path), "--out", str(tmp_path / "iso")]) == 0
    import json

    figs = json.loads((tmp_path / "iso" / "figures.json").read_text(encoding="utf-8"))
    # the spindle test declares first_reading: its drift is each run's from its first reading, not a cold cycle's
    assert figs["frame"].startswith("each run's drift from its own first reading") and "cold" not in figs["frame"]
    md = (tmp_path / "iso" / "report.md").read_text(encoding="utf-8")
    assert f"Scored on: {figs['frame']} — " in md and "cold measuring cycle" not in md
    ch3 = workbook["ch3(um)"].astype(float).to_numpy()
    drift = next(r for r in figs["runs"]["test"]["channels"]["ch3"]["drift"] if r["block"] == "all")
    assert drift["max_from_reference_um"] == pytest.approx(np.max(np.abs(ch3 - ch3[0])), abs=1e-3)
    blocks = [r["block"] for r in figs["runs"]["test"]["channels"]["ch3"]["drift"]]
    assert blocks == ["rpm1250", "rpm2500", "rpm3750", "rpm5000", "rpm3500", "tail", "all"]


# ---------------------------------------------------------- mapping mistakes ---
def _lab_copy(tmp_path: Path) -> Path:
    return labfiles.write_lab_files(tmp_path / "files")


@pytest.mark.parametrize(
    "edit, expected",
    [
        (("files:", "filez:"), "key 'filez': unknown key; did you mean 'files'?"),
        (("offset_s: -2.5", "ofset_s: -2.5"), "key 'files.cnc.ofset_s': unknown key; did you mean 'offset_s'?"),
        (("Temp. Bett [°C]\": T_bed_C", "Temp. Bet [°C]\": T_bed_C"), "column 'Temp. Bet [°C]' is not in logger.csv"),
        (('read: {sep: ";", decimal: ",", encoding: cp1252, skip_rows: 1}', 'read: {sep: ";", encoding: cp1252, skip_rows: 1}'),
         "it has a decimal comma: add read: {decimal: ','}"),
        (('encoding: cp1252, ', ''), "key files.logger.read.encoding: logger.csv is not utf-8 text"),
        (("unit: mm/s", "unit: mm/h"), "key files.cnc.columns.'X_vel'.unit: cannot convert 'mm/h' to mm/min"),
        (('"Umgebung [°C]": T_amb_C', '"Umgebung [°C]": T_room_C'), "'T_room_C' is a temperature column, but dataset.sensors declares no sensor 'T_room'"),
        (("offset_s: 1.2", "offset_s: -30"), "outside the process log of run 'warmup_6000'"),
        (("align: {base: cnc}", "align: {base: plc}"), "key 'align.base': 'plc' is not one of files"),
        (("channel: X\n", "channel: Y\n"), "key files.laser.channel: 'Y' is not declared in dataset.channels (['X'])"),
        (("{fwd: 1, bwd: -1}", "{fwd: 1}"), "value 'bwd' (data row 10 of interferometer.txt) is not mapped"),
        (("kind: along_axis", "kind: alongaxis"), "key 'dataset.channels.X.kind'"),
    ],
)
def test_mapping_mistake_is_one_line_naming_the_key(tmp_path, capsys, edit, expected):
    mapping = _lab_copy(tmp_path)
    text = mapping.read_text(encoding="utf-8")
    assert edit[0] in text
    mapping.write_text(text.replace(edit[0], edit[1], 1), encoding="utf-8")
    assert main(["import", str(mapping), "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("thermbench: error: ") and str(mapping) in err, err
    assert expected in err, err
    assert not (tmp_path / "ds").exists()  # nothing half-written


def test_a_long_logger_gap_is_not_filled_in(tmp_path, capsys):
    mapping = _lab_copy(tmp_path)
    log = mapping.parent / "logger.csv"
    lines = log.read_bytes().split(b"\r\n")
    del lines[200:215]  # 150 s of the 10 s logger missing (its default max_gap_s: 5 x 10 s)
    log.write_bytes(b"\r\n".join(lines))
    assert main(["import", str(mapping), "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert "key files.logger: no T_nut_C reading between" in err and "not filled in over a long gap" in err, err


def test_import_never_overwrites_a_users_directory(tmp_path, capsys):
    mapping = _lab_copy(tmp_path)
    out = tmp_path / "mine"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["import", str(mapping), "--out", str(out)]) == 2
    assert (out / "notes.txt").read_text() == "mine" and sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    assert main(["import", str(mapping), "--out", str(out), "--force"]) == 0  # beside, never over
    assert (out / "notes.txt").read_text() == "mine" and (out / "metadata.yaml").is_file()
    capsys.readouterr()


def test_excel_and_parquet_sources(tmp_path):
    """The same logger as an Excel workbook and as Parquet gives the same dataset."""
    mapping = _lab_copy(tmp_path)
    files = mapping.parent
    raw = pd.read_csv(files / "logger.csv", sep=";", decimal=",", encoding="cp1252", skiprows=1)
    raw.to_excel(files / "logger.xlsx", index=False, sheet_name="Daten")
    raw.to_parquet(files / "logger.parquet", index=False)
    text = mapping.read_text(encoding="utf-8")
    old = 'path: logger.csv\n    read: {sep: ";", decimal: ",", encoding: cp1252, skip_rows: 1}'
    assert old in text
    base = import_dataset(mapping, tmp_path / "csv")
    for name, read in (("logger.xlsx", "read: {sheet: Daten}"), ("logger.parquet", "read: {}")):
        mapping.write_text(text.replace(old, f"path: {name}\n    {read}"), encoding="utf-8")
        ds = import_dataset(mapping, tmp_path / name)
        pd.testing.assert_frame_equal(ds.process, base.process)
    mapping.write_text(text.replace(old, "path: logger.xlsx\n    read: {sheet: Data}"), encoding="utf-8")
    with pytest.raises(MappingError, match=r"files.logger.read.sheet: .*Data"):
        import_dataset(mapping, tmp_path / "bad")
    shutil.rmtree(tmp_path / "csv")


def test_several_runs_in_one_file_by_a_run_column(tmp_path):
    """A logger file holding two tests, told apart by a column mapped to run_id; times in ms."""
    t = np.arange(0, 600_000, 15_000)  # ms
    rows = []
    for run, rpm, k in (("A", 1000.0, 0.01), ("B", 3000.0, 0.03)):
        rows += [{"Test": run, "Time [ms]": ti, "Speed": rpm, "T front": 20 + k * ti / 1000, "Z [mm]": k * ti / 1e6}
                 for ti in t]  # fmt: skip
    pd.DataFrame(rows).to_csv(tmp_path / "log.csv", index=False)
    (tmp_path / "mapping.yaml").write_text(
        """format: thermbench-import/1
dataset:
  machine: {name: two_tests}
  parts: [spindle]
  sensors: {T_front: spindle_front_bearing}
  channels: {Z: {kind: fixed_point, direction: Z, location: spindle_nose}}
  reference: {mode: first_reading}
  runs:
    A: {condition: {spindle_rpm: 1000}}
    B: {condition: {spindle_rpm: 3000}}
files:
  log:
    path: log.csv
    time: {column: "Time [ms]", unit: ms}
    columns:
      Test: run_id
      Speed: spindle_rpm
      T front: T_front_C
      "Z [mm]": {channel: Z, unit: mm}
""", encoding="utf-8")
    ds = import_dataset(tmp_path / "mapping.yaml", tmp_path / "ds")
    assert ds.run_ids == ["A", "B"]
    for run, k in (("A", 0.01), ("B", 0.03)):
        pr = ds.process_run(run)
        np.testing.assert_allclose(pr["t_s"], t / 1000.0)
        np.testing.assert_allclose(pr["T_front_C"], 20 + k * t / 1000.0)
        er = thermal_errors(ds)
        er = er[er["run_id"] == run]
        np.testing.assert_allclose(er["thermal_um"], k * t / 1000.0, atol=1e-9)  # mm -> µm: k t/1e6 mm = k t/1e3 µm


def test_time_zone_aware_timestamps_are_one_clock(tmp_path):
    """A logger writing UTC and a CNC writing local time (+01:00) give one clock."""
    base = pd.Timestamp("2026-03-04 07:00:00", tz="UTC")
    t = np.arange(0, 3600, 10.0)
    utc = [(base + pd.Timedelta(seconds=s)).isoformat() for s in t]
    local = [(base + pd.Timedelta(seconds=s)).tz_convert("Europe/Berlin").isoformat() for s in t]
    pd.DataFrame({"when": utc, "T": 20 + t / 3600}).to_csv(tmp_path / "logger.csv", index=False)
    pd.DataFrame({"when": local, "rpm": np.where(t > 600, 2000.0, 0.0), "dz": t / 1000.0}).to_csv(tmp_path / "cnc.csv", index=False)
    (tmp_path / "mapping.yaml").write_text(
        """format: thermbench-import/1
dataset:
  machine: {name: tz}
  parts: [spindle]
  sensors: {T: structure}
  channels: {Z: {kind: fixed_point, direction: Z, location: spindle_nose}}
  reference: {mode: first_reading}
  runs: {r: {}}
run: r
files:
  logger: {path: logger.csv, time: {column: when, format: iso}, columns: {T: T_C}}
  cnc: {path: cnc.csv, time: {column: when, format: iso}, columns: {rpm: spindle_rpm, dz: {channel: Z}}}
""", encoding="utf-8")
    ds = import_dataset(tmp_path / "mapping.yaml", tmp_path / "ds")
    np.testing.assert_allclose(ds.process["t_s"], t)  # the same instants, so no shift
    np.testing.assert_allclose(ds.process["T_C"], 20 + t / 3600)
    np.testing.assert_allclose(ds.process["spindle_rpm"], np.where(t > 600, 2000.0, 0.0))


def test_a_text_cell_among_decimal_commas_is_named(tmp_path, capsys):
    mapping = _lab_copy(tmp_path)
    log = mapping.parent / "logger.csv"
    lines = log.read_bytes().split(b"\r\n")
    fields = lines[12].split(b";")
    fields[2] = b"ERR"  # the logger's text for an open thermocouple, in 'Temp. Bett'
    lines[12] = b";".join(fields)
    log.write_bytes(b"\r\n".join(lines))
    assert main(["import", str(mapping), "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert "key files.logger.columns.'Temp. Bett [°C]': data row 11 of logger.csv holds 'ERR', not a number" in err, err
    assert "decimal comma" not in err


def test_runs_not_declared_are_named_at_the_mapping(tmp_path, capsys):
    pd.DataFrame({"Test": ["A", "A", "B", "B"], "t": [0.0, 1.0, 0.0, 1.0], "rpm": 1000.0, "z": 0.0}).to_csv(
        tmp_path / "log.csv", index=False)
    (tmp_path / "mapping.yaml").write_text(
        """format: thermbench-import/1
dataset:
  machine: {name: m}
  parts: [spindle]
  sensors: {}
  channels: {Z: {kind: fixed_point, direction: Z, location: nose}}
  runs: {A: {}}
files:
  log: {path: log.csv, time: {column: t}, columns: {Test: run_id, rpm: spindle_rpm, z: {channel: Z}}}
""", encoding="utf-8")
    assert main(["import", str(tmp_path / "mapping.yaml"), "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert "key files.log.columns.'Test': log.csv holds run(s) ['B'] that dataset.runs does not declare" in err, err


def _spindle_mapping(tmp_path: Path, files: str, extra_dataset: str = "") -> Path:
    text = f"""format: thermbench-import/1
dataset:
  machine: {{name: m}}
  parts: [spindle]
  sensors: {{T: structure}}
  channels: {{Z: {{kind: fixed_point, direction: Z, location: nose}}}}
  reference: {{mode: first_reading}}
  runs: {{r: {{}}}}{extra_dataset}
run: r
files:
{files}"""
    (tmp_path / "mapping.yaml").write_text(text, encoding="utf-8")
    return tmp_path / "mapping.yaml"


def test_a_date_and_a_time_column_and_a_units_row(tmp_path):
    """An Excel-style German logger: date and time in two columns, a units row under the header."""
    t = np.arange(0, 1800, 10.0)
    stamps = pd.Timestamp("2026-03-12 07:30:00") + pd.to_timedelta(t, unit="s")
    lines = ["Datum;Uhrzeit;Temp;Drehzahl;Z", "TT.MM.JJJJ;hh:mm:ss;°C;1/min;µm"]
    for k, s in enumerate(stamps):
        temp, z = f"{20 + k / 100:.2f}".replace(".", ","), f"{k / 10:.1f}".replace(".", ",")
        lines.append(f"{s:%d.%m.%Y};{s:%H:%M:%S};{temp};1000;{z}")
    (tmp_path / "log.csv").write_bytes(("\r\n".join(lines) + "\r\n").encode("cp1252"))
    files = """  log:
    path: log.csv
    read: {sep: ";", decimal: ",", encoding: cp1252, skip_after_header: 1}
    time: {column: [Datum, Uhrzeit], format: "%d.%m.%Y %H:%M:%S"}
    columns: {Temp: T_C, Drehzahl: spindle_rpm, Z: {channel: Z}}
"""
    ds = import_dataset(_spindle_mapping(tmp_path, files), tmp_path / "ds")
    np.testing.assert_allclose(ds.process["t_s"], t)
    np.testing.assert_allclose(ds.process["T_C"], 20 + np.arange(t.size) / 100)
    assert ds.metadata.runs["r"].model_extra["started"] == "2026-03-12T07:30:00"


@pytest.mark.parametrize(
    "files, expected",
    [
        ("  x: {path: book.xlsx, read: {sheet: Messwert}, time: {column: t}, columns: {T: T_C}}\n",
         "key files.x.read.sheet: book.xlsx has no sheet 'Messwert'; its sheets: ['Info', 'Messwerte']; did you mean 'Messwerte'?"),
        ("  x: {path: book.xlsx, time: {column: t}, columns: {T: T_C}}\n",
         "the workbook has sheets ['Info', 'Messwerte']: choose one with read.sheet"),
        ("  x: {path: book.xlsx, read: {sheet: Messwerte}, time: {column: t}, columns: {T: T_C, rpm: spindle_rpm, Z: {channel: Z, unit: mm}}}\n",
         "key files.x.columns.'Z'.unit: data row 1 of book.xlsx becomes 50000 µm as error_um"),
        ("  x: {path: book.xlsx, read: {sheet: Messwerte}, time: {column: t}, columns: {T: T_C, rpm: axis_mm}}\n",
         "axis_mm is the position of a linear axis; dataset.parts ['spindle'] has none"),
        ("  x: {path: missing.yaml.csv, time: {column: t}, columns: {T: T_C}}\n", "key files.x.path: "),
    ],
)
def test_workbook_mistakes(tmp_path, capsys, files, expected):
    with pd.ExcelWriter(tmp_path / "book.xlsx") as xw:
        pd.DataFrame({"Feld": ["Maschine"], "Wert": ["VMC 1"]}).to_excel(xw, sheet_name="Info", index=False)
        pd.DataFrame({"t": [0.0, 1.0, 2.0], "T": 20.0, "rpm": 1000.0, "Z": 50.0}).to_excel(xw, sheet_name="Messwerte", index=False)
    assert main(["import", str(_spindle_mapping(tmp_path, files)), "--out", str(tmp_path / "ds")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and expected in err, err


def test_a_mapping_file_that_does_not_exist(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(["import", "thermbench/realdata/fl_thermal/mapping.yaml", "--out", "ds"]) == 2
    err = capsys.readouterr().err
    assert "no such mapping file (relative paths start from the current directory" in err, err


def test_iso230_never_overwrites_a_users_directory(lab, tmp_path, capsys):
    out = tmp_path / "mine"
    out.mkdir()
    (out / "report.md").write_text("my own report")
    assert main(["iso230", str(lab.path), "--out", str(out)]) == 2
    assert "thermbench did not write there" in capsys.readouterr().err
    assert (out / "report.md").read_text() == "my own report" and sorted(p.name for p in out.iterdir()) == ["report.md"]
    assert main(["iso230", str(lab.path), "--out", str(tmp_path / "new")]) == 0
    assert main(["iso230", str(lab.path), "--out", str(tmp_path / "new")]) == 0  # its own earlier report: replaced
    capsys.readouterr()


def _three_files(tmp_path: Path, order: tuple[str, ...], hole_in_b: bool = True) -> Path:
    ta = np.arange(0.0, 101.0)
    pd.DataFrame({"t": ta, "rpm": 1000.0}).to_csv(tmp_path / "a.csv", index=False)
    tb = np.r_[0.0, np.arange(50.0, 101.0)] if hole_in_b else ta
    tb_T = 20 + tb / 100
    pd.DataFrame({"t": tb, "T1": tb_T}).to_csv(tmp_path / "b.csv", index=False)
    tc = np.arange(60.0, 101.0)
    pd.DataFrame({"t": tc, "T2": 30 + tc / 100, "z": tc / 100}).to_csv(tmp_path / "c.csv", index=False)
    specs = {"a": "  a: {path: a.csv, time: {column: t}, columns: {rpm: spindle_rpm}}\n",
             "b": "  b: {path: b.csv, time: {column: t}, max_gap_s: 5, columns: {T1: T1_C}}\n",
             "c": "  c: {path: c.csv, time: {column: t}, max_gap_s: 5, columns: {T2: T2_C, z: {channel: Z}}}\n"}  # fmt: skip
    text = f"""format: thermbench-import/1
dataset:
  machine: {{name: m}}
  parts: [spindle]
  sensors: {{T1: structure, T2: structure}}
  channels: {{Z: {{kind: fixed_point, direction: Z, location: nose}}}}
  reference: {{mode: first_reading}}
  runs: {{r: {{}}}}
run: r
align: {{base: a}}
files:
{''.join(specs[k] for k in order)}"""
    (tmp_path / f"mapping_{''.join(order)}.yaml").write_text(text, encoding="utf-8")
    return tmp_path / f"mapping_{''.join(order)}.yaml"


def test_the_common_span_does_not_depend_on_the_order_of_the_files(tmp_path):
    """b has a hole from 0 to 50 s, but c starts at 60 s: the process keeps 60..100 s, whatever
    the order in which the mapping lists the files."""
    for order in (("a", "b", "c"), ("a", "c", "b")):
        ds = import_dataset(_three_files(tmp_path, order), tmp_path / f"ds_{''.join(order)}")
        np.testing.assert_allclose(ds.process["t_s"], np.arange(60.0, 101.0))
        np.testing.assert_allclose(ds.process["T1_C"], 20 + np.arange(60.0, 101.0) / 100)


def test_an_empty_temperature_cell_is_interpolated_from_its_neighbours(tmp_path):
    mapping = _three_files(tmp_path, ("a", "b", "c"), hole_in_b=False)
    b = pd.read_csv(tmp_path / "b.csv")
    b.loc[b["t"] == 80.0, "T1"] = np.nan  # an empty cell: no reading at 80 s
    b.to_csv(tmp_path / "b.csv", index=False)
    ds = import_dataset(mapping, tmp_path / "ds")
    at80 = ds.process.loc[ds.process["t_s"] == 80.0, "T1_C"].iloc[0]
    assert at80 == pytest.approx(20.80)  # between 20.79 at 79 s and 20.81 at 81 s, linear


def test_a_tilt_channel_in_long_form_takes_a_tilt_unit(tmp_path):
    t = np.arange(0.0, 61.0)
    pd.DataFrame({"t": t, "rpm": 1000.0}).to_csv(tmp_path / "a.csv", index=False)
    pd.DataFrame({"t": t, "tilt": t / 1000}).to_csv(tmp_path / "e.csv", index=False)  # mrad
    (tmp_path / "mapping.yaml").write_text("""format: thermbench-import/1
dataset:
  machine: {name: m}
  parts: [spindle]
  sensors: {}
  channels: {B: {kind: fixed_point, direction: B, location: spindle, unit: urad}}
  reference: {mode: first_reading}
  runs: {r: {}}
run: r
files:
  a: {path: a.csv, time: {column: t}, columns: {rpm: spindle_rpm}}
  e: {path: e.csv, time: {column: t}, channel: B, columns: {tilt: {to: error_um, unit: mrad}}}
""", encoding="utf-8")
    ds = import_dataset(tmp_path / "mapping.yaml", tmp_path / "ds")
    np.testing.assert_allclose(ds.errors["error_um"], t)  # t/1000 mrad = t µrad (the column holds µrad for a tilt)


def test_one_measuring_cycle_for_the_reference_the_models_and_the_metrics(lab):
    """A forward and a backward pass over the targets are one measuring cycle (the lab files'
    truth says which cycle each reading belongs to). The cycle is computed once
    (data.reference.reading_cycles, the ``cycle`` column of the thermal errors) and the models'
    readings, the channel view and the metrics' per-cycle curves all take that one."""
    from thermbench.bench.metrics import cycle_curves
    from thermbench.models.base import readings

    truth = labfiles.readings_truth().sort_values("t_s").reset_index(drop=True)
    te = thermal_errors(lab).sort_values("t_s").reset_index(drop=True)
    np.testing.assert_array_equal(te["cycle"].to_numpy(), truth["cycle"].to_numpy())
    view = lab.channel_view("X")
    rd = readings(view, view.run_ids).sort_values("t_s").reset_index(drop=True)
    np.testing.assert_array_equal(rd["cycle"].to_numpy(), truth["cycle"].to_numpy())
    curves = cycle_curves(rd, np.zeros(len(rd)))
    assert list(curves["cycle"]) == sorted(truth["cycle"].unique())


@pytest.mark.parametrize("header, retyped", [(0, 2), (None, 2), (0, 5)])  # 5 > ARROW_RETYPES: one full read
def test_the_lean_csv_reader_reads_what_pandas_reads_when_types_change_after_its_probe(tmp_path, header, retyped):
    """The long-log reader (import_csv._read_csv_arrow) takes its types from the file's first MiB;
    a file whose columns change after that (numbers then text, empty then numbers, integers then
    reals, a missing-value word late) must read as pandas' own Arrow engine reads it: with a few
    such columns (each retyped) and with more than the reader retypes one by one."""
    from thermbench.data import import_csv

    n = 80_000  # about 2.5 MiB: most rows after the first MiB
    rng = np.random.default_rng(3)
    t = np.arange(n, dtype=float)
    late = n - 5
    df = pd.DataFrame({
        "t_s": t,
        "T1": np.round(20 + rng.standard_normal(n), 3),
        "empty_then_numbers": [""] * late + ["1.5"] * (n - late),
        "numbers_then_text": [f"{v:.2f}" for v in rng.standard_normal(late)] + ["sensor off"] * (n - late),
        "ints_then_reals": [str(k) for k in range(late)] + ["0.25"] * (n - late),
        "na_late": ["2.0"] * late + ["NA"] * (n - late),
    })
    for k in range(retyped - 2):
        df[f"text_late_{k}"] = ["1.0"] * late + [f"x{k}"] * (n - late)
    path = tmp_path / "log.csv"
    df.to_csv(path, index=False, header=header is not None)
    assert path.stat().st_size > 2 * import_csv.ARROW_PROBE_BYTES
    lean = import_csv._read_csv_arrow(path, ",", header, "utf-8", 0)
    ref = pd.read_csv(path, header=header, engine="pyarrow")
    assert lean is not None  # taken by the lean reader, not handed back
    pd.testing.assert_frame_equal(lean, ref)
