"""Two common shapes of a lab's files, imported with a mapping file alone, and the
mapping mistakes around them: each one line naming the key, and nothing written.

Shape 1: one workbook per instrument (temperatures in one, a measured displacement in the other),
one sheet per day, no time column (one row per sample at a constant interval), a block of empty
rows at the end of one sheet, each day's first displacement reading 40-55 µm.
Shape 2: one file per experiment, no header row, a first row of zeros, no time column.

The fixtures are written here by hand with openpyxl; every expected value is computed from the
numbers written, not by thermbench.
"""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import openpyxl
import pandas as pd
import pytest

from thermbench.data.import_mapping import MappingError
from thermbench.data.importer import import_dataset
from thermbench.data.views import channel_view
from thermbench.bench.metrics import evaluate

TEMPS1 = ["Ambient", "Ref Temp on Bed", "Spindle Rear", "Coolantwall", "Transfomerbed", "Spindle Front"]
SENSORS1 = ["amb", "bed", "sp_rear", "coolant", "trafo", "sp_front"]
DAYS = {"Day 1": (30, 40.0), "Day 2": (25, 47.5), "Day 3": (28, 55.0)}  # rows, first displacement reading (µm)
EMPTY_TAIL = 6  # fully empty rows at the end of "Day 2" ('' and ' ' cells, as a spreadsheet leaves them)


def _day(k: int, n: int, zero_um: float) -> tuple[np.ndarray, np.ndarray]:
    """Temperatures (n x 6, °C) and the displacement (n, µm) of day k: the front heats by 3 K."""
    s = np.arange(n) / max(n - 1, 1)
    temps = np.column_stack([20.0 + 0.2 * k + 0.1 * j + (j + 1) * 0.5 * s for j in range(6)])
    disp = zero_um + 4.0 * (temps[:, 5] - temps[0, 5]) + 0.3 * np.sin(7.0 * s + k)
    return temps, disp


def _sheet(ws, header, rows, empty_tail=0):
    ws.append(header)
    for r in rows:
        ws.append([float(v) for v in r])
    for i in range(empty_tail):
        for c in range(1, len(header) + 1):
            ws.cell(row=len(rows) + 2 + i, column=c).value = "" if i == 2 else " "


def shape1(root):
    root.mkdir(parents=True, exist_ok=True)
    wt, wd = openpyxl.Workbook(), openpyxl.Workbook()
    wt.remove(wt.active)
    wd.remove(wd.active)
    truth = {}
    for k, (day, (n, zero)) in enumerate(DAYS.items()):
        temps, disp = _day(k, n, zero)
        tail = EMPTY_TAIL if day == "Day 2" else 0
        _sheet(wt.create_sheet(day), TEMPS1, temps, tail)
        _sheet(wd.create_sheet(day), ["Dia Disp"], disp[:, None], tail)
        truth[day.replace(" ", "_")] = (temps, disp)
    wt.save(root / "temperatures.xlsx")
    wd.save(root / "diameter.xlsx")
    (root / "mapping.yaml").write_text(MAPPING1)
    return root / "mapping.yaml", truth


MAPPING1 = """\
format: thermbench-import/1
dataset:
  machine: {name: lathe_d}
  parts: [spindle]
  sensors: {amb: ambient, bed: bed, sp_rear: spindle, coolant: structure, trafo: structure, sp_front: spindle}
  channels: {dia: {kind: fixed_point, direction: X, location: part}}
  reference: {mode: first_reading}
files:
  temps:
    path: temperatures.xlsx
    read: {sheets: all}
    run: {from: sheet}
    time: {step_s: 120}
    columns: {Ambient: amb_C, "Ref Temp on Bed": bed_C, "Spindle Rear": sp_rear_C, Coolantwall: coolant_C, Transfomerbed: trafo_C, "Spindle Front": sp_front_C}
  diameter:
    path: diameter.xlsx
    read: {sheets: all}
    run: {from: sheet}
    time: {step_s: 120}
    columns: {"Dia Disp": {channel: dia, unit: um}}
"""

N_EXP = {"exp1": 20, "exp2": 26, "exp3": 23}  # data rows after the zero row


def shape2(root):
    """Files exp1..3.xlsx: no header; row 0 all zeros; 22 temperature rises then the elongation."""
    root.mkdir(parents=True, exist_ok=True)
    truth = {}
    for k, (name, n) in enumerate(N_EXP.items()):
        s = np.arange(n + 1) / n
        rises = np.column_stack([(0.5 + 0.1 * j + 0.2 * k) * s**0.7 for j in range(22)])
        elong = 6.0 * rises[:, 0] + 2.0 * rises[:, 21] + 0.1 * k * s
        table = np.column_stack([rises, elong])
        table[0] = 0.0  # the first row of zeros
        wb = openpyxl.Workbook()
        for r in table:
            wb.active.append([float(v) for v in r])
        wb.save(root / f"{name}.xlsx")
        truth[name] = table
    sensors = ", ".join(f"T{j:02d}: structure" for j in range(1, 23))
    cols = ", ".join(f"{j}: T{j + 1:02d}_C" for j in range(22))
    (root / "mapping.yaml").write_text(f"""\
format: thermbench-import/1
dataset:
  machine: {{name: mill_g}}
  parts: [spindle]
  sensors: {{{sensors}}}
  channels: {{elong: {{kind: fixed_point, direction: Z, location: spindle}}}}
  reference: {{mode: first_reading}}
files:
  tests:
    path: "exp*.xlsx"
    run: {{from: file}}
    read: {{header: false}}
    time: {{step_s: 300}}
    columns: {{{cols}, 22: {{channel: elong, unit: um}}}}
""")
    return root / "mapping.yaml", truth


# ------------------------------------------------------------------ shape 1 ---
def test_shape1_one_run_per_sheet_constant_step_and_empty_rows_skipped(tmp_path):
    mapping, truth = shape1(tmp_path / "files")
    ds = import_dataset(mapping, tmp_path / "out")
    assert ds.run_ids == ["Day_1", "Day_2", "Day_3"]  # the sheet names made run ids, in workbook order
    assert ds.import_notes[:2] == [f"files.temps: temperatures.xlsx sheet 'Day 2': {EMPTY_TAIL} fully empty row(s) skipped",
                                   f"files.diameter: diameter.xlsx sheet 'Day 2': {EMPTY_TAIL} fully empty row(s) skipped"]  # fmt: skip
    assert ds.metadata.operating == [] and "operating: []" in ds.import_notes[2]  # the files have no speed signal
    for run, (temps, disp) in truth.items():
        pr, er = ds.process_run(run), ds.errors_run(run)
        np.testing.assert_array_equal(pr["t_s"].to_numpy(), 120.0 * np.arange(len(temps)))  # row k at k x 120 s
        for j, s in enumerate(SENSORS1):
            np.testing.assert_allclose(pr[f"{s}_C"].to_numpy(), temps[:, j])
        np.testing.assert_allclose(er["error_um"].to_numpy(), disp)
    assert not (tmp_path / "out" / "metadata.yaml").read_text().count("condition")  # no condition needed


def test_shape1_scores_are_each_runs_drift_from_its_first_reading(tmp_path):
    """Runs whose first readings are 40, 47.5 and 55 µm: with reference first_reading every score
    is of the drift from each run's own first reading. A model that predicts a constant 1 µm is
    scored here against the hand computation from the numbers written into the workbook."""
    mapping, truth = shape1(tmp_path / "files")
    view = channel_view(import_dataset(mapping, tmp_path / "out"), "dia")

    class Constant:
        def predict(self, ds, run):
            return np.full(len(ds.errors_run(run)), 1.0)

    rows = evaluate(Constant(), view).set_index("run_id")
    for run, (_, disp) in truth.items():
        drift = disp - disp[0]
        res = drift - 1.0
        r = rows.loc[run]
        assert r["rmse_um"] == pytest.approx(np.sqrt(np.mean(res**2)), rel=1e-12)
        assert r["max_abs_residual_um"] == pytest.approx(np.max(np.abs(res)), rel=1e-12)
        assert r["max_abs_error_um"] == pytest.approx(np.max(np.abs(drift)), rel=1e-12)
        assert r["pv_error_um"] == pytest.approx(np.ptp(drift), rel=1e-12)
        assert r["compensation_rate"] == pytest.approx(1 - np.max(np.abs(res)) / np.max(np.abs(drift)), rel=1e-12)
    # the raw frame would have scored the 40-55 µm first readings as error: at least 39 µm RMS
    assert rows["rmse_um"].max() < 20.0


def test_shape1_validate_says_valid_and_the_frame(tmp_path):
    mapping, _ = shape1(tmp_path / "files")
    proc = subprocess.run([sys.executable, "-m", "thermbench.cli", "import", str(mapping), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    assert "6 fully empty row(s) skipped" in proc.stdout
    val = subprocess.run([sys.executable, "-m", "thermbench.cli", "validate", str(tmp_path / "out")], capture_output=True,
                         text=True)  # fmt: skip
    assert val.returncode == 0, val.stderr
    assert "valid thermbench-dataset/2 dataset" in val.stdout
    assert "models are scored on each run's drift from its own first reading" in val.stdout
    for run in ("Day_1", "Day_2", "Day_3"):
        assert run in val.stdout


# ------------------------------------------------------------------ shape 2 ---
def test_shape2_headerless_files_one_run_each_keep_their_first_row(tmp_path):
    mapping, truth = shape2(tmp_path / "files")
    ds = import_dataset(mapping, tmp_path / "out")
    assert ds.run_ids == list(N_EXP)
    for run, table in truth.items():
        pr, er = ds.process_run(run), ds.errors_run(run)
        assert len(pr) == len(table)  # the row of zeros is data, not a header
        np.testing.assert_array_equal(pr["t_s"].to_numpy(), 300.0 * np.arange(len(table)))
        np.testing.assert_allclose(pr[[f"T{j:02d}_C" for j in range(1, 23)]].to_numpy(), table[:, :22])
        np.testing.assert_allclose(er["error_um"].to_numpy(), table[:, 22])
        assert er["t_s"].iloc[0] == 0.0 and er["error_um"].iloc[0] == 0.0


def test_a_headerless_file_read_with_a_header_is_refused_not_shortened(tmp_path):
    mapping, _ = shape2(tmp_path / "files")
    mapping.write_text(mapping.read_text().replace("    read: {header: false}\n", ""))
    with pytest.raises(MappingError) as exc:
        import_dataset(mapping, tmp_path / "out")
    msg = str(exc.value)
    assert "\n" not in msg and "key files.tests.read.header: the first row of exp1.xlsx reads as data" in msg
    assert "read: {header: false}" in msg
    assert not (tmp_path / "out").exists()


# --------------------------------------------------------------- mistakes ---
@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda t: t.replace("read: {sheets: all}\n    run: {from: sheet}\n    time: {step_s: 120}\n    columns: {Ambient",
                             "read: {sheet: [Day 1, Day 2]}\n    run: {from: sheet}\n    time: {step_s: 120}\n    columns: {Ambient"),
         "key 'files.temps.read.sheet': expected one sheet, by name or 0-based index (several sheets: read: {sheets: all} "
         "or sheets: [names]), got ['Day 1', 'Day 2']"),
        (lambda t: t.replace("    time: {step_s: 120}\n    columns: {\"Dia", "    columns: {\"Dia"),
         "key 'files.diameter.time': missing: give time: {column: NAME} (the file's time column) or, with no time "
         "column, time: {step_s: S} (rows S seconds apart)"),
        (lambda t: t.replace("time: {step_s: 120}\n    columns: {\"Dia", "time: {step_s: 120, column: t}\n    columns: {\"Dia"),
         "key files.diameter.time: give either column (a time column) or step_s (a constant step, no time column), "
         "not both (column and step_s)"),
        (lambda t: t + "  again:\n    path: temperatures.xlsx\n    read: {sheets: all}\n    run: {from: sheet}\n"
                       "    time: {step_s: 120}\n    columns: {Ambient: amb_C}\n",
         "key files.again.columns: 'amb_C' is mapped by files 'temps' and 'again'; a dataset column comes from one file"),
        (lambda t: t.replace("read: {sheets: all}\n    run: {from: sheet}\n    time: {step_s: 120}\n    columns: {\"Dia",
                             "read: {sheets: all}\n    run: {from: sheets}\n    time: {step_s: 120}\n    columns: {\"Dia"),
         "key 'files.diameter.run': expected a run id, or {from: sheet} / {from: file}"),
        (lambda t: t.replace("read: {sheets: all}\n    run: {from: sheet}\n    time: {step_s: 120}\n    columns: {\"Dia",
                             "read: {sheets: all, sheet: Day 1}\n    run: {from: sheet}\n    time: {step_s: 120}\n    columns: {\"Dia"),
         "key files.diameter.read: give sheet (one sheet) or sheets (several), not both"),
        (lambda t: t.replace("columns: {\"Dia Disp\": {channel: dia, unit: um}}", "columns: {0: {channel: dia, unit: um}}"),
         "key files.diameter.columns.'0': a column by position (a number) needs read: {header: false}"),
    ],
)
def test_each_mapping_mistake_is_one_line_and_writes_nothing(tmp_path, edit, message):
    mapping, _ = shape1(tmp_path / "files")
    mapping.write_text(edit(mapping.read_text()))
    proc = subprocess.run([sys.executable, "-m", "thermbench.cli", "import", str(mapping), "--out", str(tmp_path / "out")],
                          capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and message in lines[0], proc.stderr
    assert "Input should be" not in proc.stderr and "Traceback" not in proc.stderr
    assert not (tmp_path / "out").exists()


def test_a_dataset_refused_after_its_tables_are_built_leaves_no_output(tmp_path):
    """A failure found only once the tables exist (a run's segment names against what its speed
    signal derives): the import stops with one line and the output directory never appears."""
    root = tmp_path / "files"
    root.mkdir()
    t = np.arange(0.0, 4000.0, 10.0)
    rpm = np.where((t >= 500) & (t < 2000), 3000.0, 0.0)
    pd.DataFrame({"t": t, "rpm": rpm, "T": 20.0 + 0.001 * t, "z": 0.01 * t}).to_csv(root / "log.csv", index=False)
    (root / "mapping.yaml").write_text("""\
format: thermbench-import/1
dataset:
  machine: {name: m}
  parts: [spindle]
  operating: [spindle_rpm]
  sensors: {front: spindle}
  channels: {z: {kind: fixed_point, direction: Z, location: spindle}}
  runs: {r1: {segments: [a, b, c, d, e, f, g]}}
files:
  log:
    path: log.csv
    time: {column: t}
    columns: {rpm: spindle_rpm, T: front_C, z: {channel: z, unit: um}}
""")
    proc = subprocess.run([sys.executable, "-m", "thermbench.cli", "import", str(root / "mapping.yaml"), "--out",
                           str(tmp_path / "out")], capture_output=True, text=True)  # fmt: skip
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "segments" in lines[0] and "Traceback" not in proc.stderr, proc.stderr
    assert "imported" not in proc.stdout and "valid" not in proc.stdout
    assert not (tmp_path / "out").exists()
