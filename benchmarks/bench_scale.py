"""The cost of ``thermbench benchmark "datasets=[DIR]" cv=group_kfold`` as a lab's season of runs grows,
and the overhead of running its cells on a Dask cluster.

The dataset has the shape of a CNC lathe's season (43 runs of 5-6 h, 24 temperatures, X and Z drift,
~700 rows a run at 28 s): seeded CSV files, one per run, imported with a mapping (as a lab would), each
run a hidden duty driving heat sources through first-order lags, 24 sensors mixing them, and the
two drifts lagging the heat, with a warm start and a slowly ramped ambient. For each run count of
``--runs`` (default 10, 20, 43, the first runs of the season) the benchmark runs in a child process on
this machine's cores (executor=local, n_jobs = the cores), and for ``--dask`` run counts again through a
LocalCluster of as many worker processes of one thread (executor=dask); each with an empty cell cache.
Prints the wall time of each (median of ``--repeats``), the cells, and the Dask overhead; checks that
the two results.csv agree in every column but fit_s.

    .venv/bin/python benchmarks/bench_scale.py [--runs 10 20 43] [--dask 43] [--repeats 1] [--families "[...]"]

Targets (2 cores): 43 runs within 10 min; Dask within 10 % of local at the same cores.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd
from bench_benchmark_cv import _lag  # a first-order response, row by row (this directory: run as a script)

ROOT = Path(__file__).resolve().parents[1]
SENSORS = [f"T{k:02d}" for k in range(1, 25)]
STEP_S = 28.0


def write_season(root: Path, n_runs: int, seed: int = 0) -> Path:
    """``n_runs`` CSV files (run_01.csv, ...) and mapping.yaml under ``root``; the runs are the first
    ``n_runs`` of one seeded season (the same first runs for every count)."""
    rng = np.random.default_rng(seed)
    mix = rng.uniform(0.0, 1.0, size=(24, 3))  # each sensor's share of the three heat sources
    mix[0] = 0.0  # T01 is the ambient
    for r in range(43):
        n = int(rng.integers(640, 780))
        duty = np.repeat(rng.uniform(0.1, 1.0, size=(n // 40 + 1, 2)), 40, axis=0)[:n]
        heat = np.column_stack([_lag(duty[:, 0], 60.0), _lag(duty[:, 1], 150.0), _lag(duty[:, 0] * duty[:, 1], 300.0)])
        warm = rng.uniform(0.0, 3.0)  # the start state: yesterday's heat, relaxing
        heat += warm * np.exp(-np.arange(n) / 200.0)[:, None]
        amb = rng.uniform(18.0, 24.0) + np.linspace(0.0, rng.uniform(-1.5, 1.5), n) + 0.05 * rng.standard_normal(n)
        temps = amb[:, None] + 6.0 * heat @ mix.T + 0.05 * rng.standard_normal((n, 24))
        x = 12.0 * _lag(heat[:, 0], 40.0) + 5.0 * heat[:, 2] + 1.5 * (amb - amb[0]) + 0.4 * rng.standard_normal(n)
        z = 25.0 * _lag(heat[:, 1], 80.0) + 8.0 * heat[:, 0] + 0.5 * rng.standard_normal(n)
        if r < n_runs:
            df = pd.DataFrame(temps, columns=[f"{s}(C)" for s in SENSORS])
            df.insert(0, "t(s)", np.arange(n) * STEP_S)
            df["X(um)"], df["Z(um)"] = x, z
            df.to_csv(root / f"run_{r + 1:02d}.csv", index=False, float_format="%.4f")
    sensors = ", ".join(f"{s}: {'ambient' if s == 'T01' else 'structure'}" for s in SENSORS)
    columns = ", ".join(f'"{s}(C)": {s}_C' for s in SENSORS)
    (root / "mapping.yaml").write_text(f"""\
format: thermbench-import/1
dataset:
  machine: {{name: lathe_season}}
  parts: [spindle]
  sensors: {{{sensors}}}
  channels: {{X: {{kind: fixed_point, direction: X, location: part}}, Z: {{kind: fixed_point, direction: Z, location: part}}}}
  reference: {{mode: first_reading}}
files:
  runs:
    path: "run_*.csv"
    run: {{from: file}}
    time: {{column: "t(s)", unit: s}}
    columns: {{{columns}, "X(um)": {{channel: X, unit: um}}, "Z(um)": {{channel: Z, unit: um}}}}
""", encoding="utf-8")
    return root / "mapping.yaml"


def _thermbench(*args: str) -> None:
    subprocess.run([str(Path(sys.executable).parent / "thermbench"), *args], check=True, cwd=ROOT,
                   stdout=subprocess.DEVNULL)  # fmt: skip


def run_benchmark(data: Path, out: Path, executor: str, cores: int, families: str | None) -> float:
    """Wall seconds of one benchmark into ``out`` with an empty cache."""
    ex = ["executor=local", f"n_jobs={cores}"] if executor == "local" else [
        "executor=dask", f"executor.n_workers={cores}", "executor.threads_per_worker=1", "executor.threads_per_cell=1"]
    args = ["benchmark", f"datasets=[{data}]", "cv=group_kfold", *ex, f"cache_dir={out}/cache",
            f"report_dir={out}/reports", f"export_dir={out}/models", f"tracking.uri=sqlite:///{out}/mlflow.db",
            f"tracking.artifact_root={out}/art", "tracking.register=false", "progress=false",
            *([f"families={families}"] if families else [])]  # fmt: skip
    t0 = time.perf_counter()
    _thermbench(*args)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, nargs="+", default=[10, 20, 43])
    ap.add_argument("--dask", type=int, nargs="*", default=[43], help="run counts also timed through Dask")
    ap.add_argument("--repeats", type=int, default=1)
    ap.add_argument("--families", default=None, help='e.g. "[ridge_history,lag_bank]"; default: every family')
    ap.add_argument("--keep", type=Path, default=None, help="write here instead of a temporary directory")
    a = ap.parse_args(argv)
    cores = os.cpu_count() or 1
    base = a.keep or Path(tempfile.mkdtemp(prefix="bench_scale_"))
    print(f"{cores} cores; cv=group_kfold (5 folds); {a.repeats} timing(s) each, median; in {base}")
    print(f"{'runs':>5} {'rows':>7} {'cells':>6} {'local s':>9} {'dask s':>9} {'overhead':>9} {'results equal':>14}")
    for n in a.runs:
        src = base / f"files_{n}"
        src.mkdir(parents=True, exist_ok=True)
        write_season(src, n)
        data = base / f"data_{n}"
        _thermbench("import", str(src / "mapping.yaml"), "--out", str(data), "--force")
        rows = len(pd.read_parquet(data / "process.parquet"))
        times = {}
        for ex in ["local"] + (["dask"] if n in a.dask else []):
            ts = [run_benchmark(data, base / f"out_{n}_{ex}_{k}", ex, cores, a.families) for k in range(a.repeats)]
            times[ex] = statistics.median(ts)
        res = pd.read_csv(base / f"out_{n}_local_0" / "reports" / "results.csv")
        cells = res[["channel", "family"]].drop_duplicates().shape[0]
        same = "-"
        if "dask" in times:
            other = pd.read_csv(base / f"out_{n}_dask_0" / "reports" / "results.csv")
            try:
                pd.testing.assert_frame_equal(res.drop(columns="fit_s"), other.drop(columns="fit_s"), check_exact=False,
                                              rtol=1e-9, atol=1e-12)  # fmt: skip
                same = "yes"
            except AssertionError:
                same = "NO"
        d, loc = times.get("dask"), times["local"]
        dask_s = "-" if d is None else f"{d:.0f}"
        over = "-" if d is None else f"{100 * (d / loc - 1):+.0f} %"
        print(f"{n:>5} {rows:>7} {cells:>6} {loc:>9.0f} {dask_s:>9} {over:>9} {same:>14}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
