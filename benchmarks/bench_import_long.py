"""A long monitoring log in: ``thermbench import`` of a logger's CSV at 1 Hz over DAYS days,
16 temperatures and the spindle speed, plus a file of drift readings every 10 minutes.

Writes the CSV (2.6 M rows, about 312 MiB for 30 days) into a temporary directory, then runs the
import ``--repeats`` times as a separate process each (after one warm-up), and prints per run the
wall time and the peak resident memory of the importing process (``getrusage`` of the child), the
median of each, the CSV's size and the size of the process table the import builds (its rows x 19
columns of 8 bytes: time, speed and the 16 temperatures as float64, and the run id's reference;
MB here are 2**20 bytes). The table cap is the machine's default (a quarter of its memory) unless
``THERMBENCH_MAX_TABLE_MIB`` is set.

    .venv/bin/python benchmarks/bench_import_long.py [--days 30] [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

N_TEMPS = 16


def write_log(root: Path, days: float, seed: int = 0) -> Path:
    rng = np.random.default_rng(seed)
    n = int(days * 86400)
    t = np.arange(n, dtype=float)
    rpm = np.repeat(rng.choice([0.0, 1500.0, 3000.0, 6000.0], size=n // 1800 + 1), 1800)[:n]
    heat = np.convolve(rpm / 6000.0, np.exp(-np.arange(3600) / 900.0) / 900.0)[:n]
    cols = {"time_s": t, "speed_rpm": rpm}
    for j in range(N_TEMPS):
        cols[f"T{j + 1:02d}"] = np.round(20.0 + (1.0 + 0.3 * j) * heat + 0.02 * rng.standard_normal(n), 3)
    with open(root / "logger.csv", "w") as fh:  # pandas' writer, in blocks (its memory stays small)
        for k in range(0, n, 200_000):
            pd.DataFrame({c: v[k:k + 200_000] for c, v in cols.items()}).to_csv(fh, header=k == 0, index=False)
    read = t[::600]
    drift = 8.0 * heat[::600] + 0.1 * rng.standard_normal(read.size)
    pd.DataFrame({"time_s": read, "z_um": drift}).to_csv(root / "probe.csv", index=False)
    sensors = ", ".join(f"T{j + 1:02d}: spindle" for j in range(N_TEMPS))
    temps = ", ".join(f"T{j + 1:02d}: T{j + 1:02d}_C" for j in range(N_TEMPS))
    (root / "mapping.yaml").write_text(f"""\
format: thermbench-import/1
dataset:
  machine: {{name: logger_month}}
  parts: [spindle]
  sensors: {{{sensors}}}
  channels: {{z: {{kind: fixed_point, direction: Z, location: spindle}}}}
  reference: {{mode: first_reading}}
  runs: {{month: {{}}}}
run: month
files:
  logger:
    path: logger.csv
    time: {{column: time_s}}
    columns: {{speed_rpm: spindle_rpm, {temps}}}
  probe:
    path: probe.csv
    time: {{column: time_s}}
    columns: {{z_um: {{channel: z, unit: um}}}}
""")
    return root / "mapping.yaml"


def one_import(mapping: Path, out: Path) -> tuple[float, float]:
    """Wall seconds and peak RSS (MB) of ``thermbench import`` in a child process."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "thermbench.cli", "import", str(mapping), "--out", str(out)],
                          capture_output=True, text=True)  # fmt: skip
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        raise SystemExit(f"import failed ({proc.returncode}): {proc.stderr.strip()}")
    peak = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss  # kB on Linux: the largest child so far
    return wall, max(peak, before) / 1024.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--days", type=float, default=30.0)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    root = Path(tempfile.mkdtemp(prefix="tb_long_"))
    try:
        t0 = time.perf_counter()
        mapping = write_log(root, args.days)
        size_mib = os.path.getsize(root / "logger.csv") / 2**20
        table_mb = int(args.days * 86400) * (N_TEMPS + 3) * 8 / 2**20  # the process table in memory
        print(f"logger.csv: {args.days:g} days at 1 Hz, {N_TEMPS} temperatures + speed, {size_mib:.1f} MiB "
              f"(written in {time.perf_counter() - t0:.0f} s)")  # fmt: skip
        runs = []
        for k in range(args.repeats + 1):  # the first is the warm-up
            out = root / f"out{k}"
            wall, peak_mb = one_import(mapping, out)
            shutil.rmtree(out)
            print(f"  {'warm-up' if k == 0 else f'run {k}'}: {wall:.1f} s, peak resident memory so far {peak_mb:.0f} MB")
            if k:
                runs.append(wall)
        print(f"median import time {statistics.median(runs):.1f} s over {len(runs)} runs; peak resident memory of "
              f"the largest import {peak_mb:.0f} MB ({peak_mb / size_mib:.2f} x the CSV's size, {peak_mb / table_mb:.1f} x "
              f"the process table it builds, {table_mb:.0f} MB)")  # fmt: skip
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
