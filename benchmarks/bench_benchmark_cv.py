"""Targets of ``thermbench benchmark`` with ``cv=loro`` and the default families on a dataset
of each of the two common lab shapes, at their real sizes, on this machine's cores:

* shape 1: 18 runs (one sheet per day), 6 temperature sensors, ~230 rows a run at 120 s, a
  displacement that starts each day at 40-55 µm (first_reading reference);
* shape 2: 5 runs (one header-less file each), 22 temperature rises, ~70 rows a run at 300 s.

The files are written (seeded) into a temporary directory, imported with the mappings of
docs/import.md (examples 3 and 4), then benchmarked in a child process each; prints the wall time
of each benchmark, its held-out summary (the nested choice vs the best baseline vs no
compensation) and its answer table (with the deployed model's interval: the share of held-out readings
it covered and its mean half-width). Target: at most 10 min each on 2 cores.

    .venv/bin/python benchmarks/bench_benchmark_cv.py [--families "[baseline_ols,lssvm]" --bank-families "[lssvm]"] [--keep DIR]
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import openpyxl

ROOT = Path(__file__).resolve().parents[1]


def _lag(u: np.ndarray, tau_rows: float) -> np.ndarray:
    """First-order response of ``u`` with a time constant of ``tau_rows`` rows."""
    out, a, y = np.empty_like(u), 1.0 / (1.0 + tau_rows), 0.0
    for k, v in enumerate(u):
        y += a * (v - y)
        out[k] = y
    return out


def shape1(root: Path, rng: np.random.Generator, days: int = 18) -> Path:
    wt, wd = openpyxl.Workbook(), openpyxl.Workbook()
    wt.remove(wt.active)
    wd.remove(wd.active)
    names = ["Ambient", "Ref Temp on Bed", "Spindle Rear", "Coolantwall", "Transfomerbed", "Spindle Front"]
    for d in range(days):
        n = int(rng.integers(200, 260))
        load = np.repeat(rng.uniform(0.2, 1.0, size=n // 30 + 1), 30)[:n]  # the day's hidden duty
        heat = _lag(load, 25.0)
        amb = 20.0 + 1.5 * np.sin(np.linspace(0, np.pi, n) + rng.uniform(0, 1)) + 0.05 * rng.standard_normal(n)
        temps = np.column_stack([amb, amb + 0.3 * heat, amb + 4 * heat, amb + 2 * _lag(heat, 20),
                                 amb + 1.0 * heat, amb + 6 * heat]) + 0.03 * rng.standard_normal((n, 6))  # fmt: skip
        disp = rng.uniform(40, 55) + 9 * _lag(heat, 15) + 2 * (amb - amb[0]) + 0.3 * rng.standard_normal(n)
        for wb, header, table in ((wt, names, temps), (wd, ["Dia Disp"], disp[:, None])):
            ws = wb.create_sheet(f"Day {d + 1:02d}")
            ws.append(header)
            for row in table:
                ws.append([float(v) for v in row])
    wt.save(root / "temperatures.xlsx")
    wd.save(root / "diameter.xlsx")
    (root / "mapping.yaml").write_text("""\
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
""")
    return root / "mapping.yaml"


def shape2(root: Path, rng: np.random.Generator, experiments: int = 5) -> Path:
    for e in range(experiments):
        n = int(rng.integers(56, 73))
        load = np.repeat(rng.uniform(0.3, 1.0, size=n // 12 + 1), 12)[:n]
        heat = _lag(load, 8.0)
        rises = np.column_stack([(0.5 + 0.15 * j) * _lag(heat, 1 + j % 5) for j in range(22)])
        rises += 0.02 * rng.standard_normal(rises.shape)
        elong = 5 * _lag(heat, 6) + 0.5 * rises[:, 3] + 0.15 * rng.standard_normal(n)
        table = np.column_stack([rises, elong])
        table[0] = 0.0
        wb = openpyxl.Workbook()
        for row in table:
            wb.active.append([float(v) for v in row])
        wb.save(root / f"exp{e + 1}.xlsx")
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
    return root / "mapping.yaml"


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default=None, help='e.g. "[baseline_ols,lssvm]"; default: every family')
    ap.add_argument("--bank-families", default="[]", help="with --families: the bank families, e.g. \"[lssvm]\"")
    ap.add_argument("--keep", default=None, help="write into this new directory and keep it")
    ap.add_argument("--seed", type=int, default=0)
    args = ap.parse_args()
    tb = str(Path(sys.executable).with_name("thermbench"))
    root = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="tb_cv_"))
    if args.keep:
        root.mkdir(parents=True)  # a new directory: nothing of the user's is written over
    rng = np.random.default_rng(args.seed)
    try:
        for name, make in (("shape1", shape1), ("shape2", shape2)):
            files = root / name
            files.mkdir()
            mapping = make(files, rng)
            subprocess.run([tb, "import", str(mapping), "--out", str(root / f"{name}_ds")], check=True,
                           stdout=subprocess.DEVNULL)  # fmt: skip
            cmd = [tb, "benchmark", f"datasets=[{root / f'{name}_ds'}]", "cv=loro", "cache_dir=null", "progress=false",
                   f"report_dir={root / f'{name}_report'}", f"export_dir={root / f'{name}_models'}"]  # fmt: skip
            if args.families:  # and the banks of those the default bank_families names
                cmd += [f"families={args.families}", f"bank_families={args.bank_families}"]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=root)  # MLflow's store and Hydra's outputs there
            wall = time.perf_counter() - t0
            if proc.returncode:
                print(proc.stderr[-3000:], file=sys.stderr)
                return proc.returncode
            lines = proc.stdout.splitlines()
            print(f"{name}: thermbench benchmark cv=loro, {wall:.0f} s wall")
            start = next((i for i, ln in enumerate(lines) if "held-out RMSE over the folds" in ln), None)
            if start is None:  # the summary's header changed: say so rather than print nothing
                print("  (no held-out summary found in the benchmark's output)")
            for ln in lines[start:] if start is not None else []:
                if "held-out RMSE over the folds" in ln or ln.startswith("flagged on held-out") or " folds; choice " in ln:
                    print("  " + ln)
            # the answer, the benchmark's last lines: the deployed model, its held-out RMSE and its interval's
            # coverage and mean half-width over the held-out runs
            answer = next((i for i, ln in enumerate(lines) if ln == "the model to deploy, and its RMSE on runs it never saw"), None)
            for ln in lines[answer:] if answer is not None else ["  (no answer table found in the benchmark's output)"]:
                if not ln.startswith("- "):
                    print("  " + ln)
    finally:
        if not args.keep:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
