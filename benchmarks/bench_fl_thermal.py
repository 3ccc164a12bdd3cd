"""The first real-data benchmark, measured: every family against the baselines on the measured
spindle test ``fl_thermal`` (thermbench/realdata/fl_thermal/SOURCE.md), with its targets.

1. Runs ``thermbench benchmark datasets=[fl_thermal]`` (the shipped model settings, a fresh
   task cache, its own output and tracking directories) ``--repeats`` times after a warm-up
   that imports the dataset, and prints the median wall time (target: <= 300 s on 2 cores).
2. From its ``results.csv``: the tail RMSE per channel for every family x approach (baselines
   marked), and per channel the best thermbench family against the best baseline (target:
   below it on every channel; the aim is half of it).
3. Exports the chosen model of every channel to the C runtime (``thermbench export``) and
   prints its parity on the tail (target: <= 0.01 µm), then replays the tail through the C
   runtime (``thermbench replay``) and prints before/after.

    python benchmarks/bench_fl_thermal.py [--repeats 1] [--out DIR] [--keep]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pandas as pd

TAIL = "tail"
CHANNELS = ["ch1", "ch2", "ch3", "ch4", "ch5"]


def run(cmd: list[str], cwd: Path) -> str:
    p = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if p.returncode != 0:
        sys.exit(f"failed ({p.returncode}): {' '.join(cmd)}\n{p.stdout[-3000:]}\n{p.stderr[-3000:]}")
    return p.stdout


def benchmark(work: Path, k: int) -> tuple[float, Path, Path]:
    report, models = work / f"report{k}", work / f"models{k}"
    cmd = [sys.executable, "-m", "thermbench", "benchmark", "datasets=[fl_thermal]", f"report_dir={report}",
           f"export_dir={models}", f"cache_dir={work / f'cache{k}'}", f"tracking.uri=sqlite:///{work}/mlflow{k}.db",
           f"hydra.run.dir={work}/hydra{k}", "progress=false"]  # fmt: skip
    t0 = time.perf_counter()
    run(cmd, work)
    return time.perf_counter() - t0, report, models


def tail_table(results: pd.DataFrame) -> pd.DataFrame:
    tail = results[results["test"] == TAIL]
    tail = tail.assign(label=[f"{f} ({a}{', ' + t if a == 'single' else ''})"
                              for f, a, t in zip(tail["family"], tail["approach"], tail["train"])])  # fmt: skip
    return tail.pivot_table(index=["reference", "label"], columns="channel", values="rmse_um", aggfunc="first")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=1, help="benchmark runs timed (median), after a warm-up import")
    ap.add_argument("--out", default=None, help="working directory (default: a temporary one)")
    ap.add_argument("--keep", action="store_true", help="keep the working directory")
    ap.add_argument("--reuse", action="store_true",
                    help="take the benchmark already in --out (report0/, models0/) instead of running it")
    args = ap.parse_args()
    work = Path(args.out or tempfile.mkdtemp(prefix="bench_fl_"))
    work.mkdir(parents=True, exist_ok=True)
    os.environ.setdefault("THERMBENCH_DATA", str(Path("data/benchmark").resolve()))
    from thermbench.bench.datasets import load_benchmark

    load_benchmark("fl_thermal")  # warm-up: the import (cached by the shipped files' hash)
    walls, report, models = [], work / "report0", work / "models0"
    for k in range(0 if args.reuse else args.repeats):
        wall, report, models = benchmark(work, k)
        walls.append(wall)
        print(f"run {k + 1}: thermbench benchmark datasets=[fl_thermal]: {wall:.0f} s", flush=True)
    if walls:
        print(f"\nwall time, median of {len(walls)}: {statistics.median(walls):.0f} s (target <= 300 s on 2 cores)")

    results = pd.read_csv(report / "results.csv")
    table = tail_table(results)
    with pd.option_context("display.width", 200, "display.max_rows", 200, "display.float_format", "{:.2f}".format):
        print("\nTail RMSE (µm) per channel, every family x approach (reference=True: baseline)\n")
        print(table.to_string())
    tail = results[(results["test"] == TAIL) & (results["approach"] != "single")]
    print("\nBest thermbench family vs best baseline on the tail (global/bank approaches):")
    ok = True
    for ch in CHANNELS:
        c = tail[tail["channel"] == ch]
        mine, base = c[~c["reference"]], c[c["reference"]]
        if mine.empty or base.empty:
            print(f"  {ch}: missing rows")
            ok = False
            continue
        a, b = mine.loc[mine["rmse_um"].idxmin()], base.loc[base["rmse_um"].idxmin()]
        ratio = a["rmse_um"] / b["rmse_um"]
        ok &= ratio < 1
        print(f"  {ch}: {a['family']} ({a['approach']}) {a['rmse_um']:.2f} µm vs {b['family']} ({b['approach']}) "
              f"{b['rmse_um']:.2f} µm: {ratio:.2f}x {'beats' if ratio < 1 else 'does NOT beat'}"
              f"{' (half or better)' if ratio <= 0.5 else ''}")  # fmt: skip
    print(f"target 'beats the best baseline on every channel': {'met' if ok else 'NOT met'}")

    exports = Path(tempfile.mkdtemp(prefix="exports-", dir=work))  # new and empty: nothing of anyone's replaced
    run([sys.executable, "-m", "thermbench", "export", f"export.source={models}", "export.select=chosen",
         f"export.out_dir={exports}",
         f"hydra.run.dir={work}/hydra-export", f"tracking.uri=sqlite:///{work}/mlflow0.db"], work)  # fmt: skip
    print("\nChosen models exported to the C runtime; parity and replay of the tail:")
    data = Path(os.environ["THERMBENCH_DATA"]) / "fl_thermal"
    for d in sorted(p for p in exports.iterdir() if (p / "manifest.json").is_file()):
        man = json.loads((d / "manifest.json").read_text())
        par = man.get("parity", {}).get("model", {})
        out = Path(tempfile.mkdtemp(prefix=f"replay-{d.name}-", dir=work))
        run([sys.executable, "-m", "thermbench", "replay", str(d), str(data), "--run", TAIL, "--out", str(out)], work)
        fig = json.loads((out / "replay.json").read_text())
        before, after = fig.get("before_rms_um"), fig.get("after_rmse_um")
        print(f"  {d.name}: {man['kind']}, parity max |C - Python| {par.get('max_abs_diff_um', float('nan')):.2e} µm "
              f"(target <= 0.01), tail RMS before {before:.2f} µm, after {after:.2f} µm")  # fmt: skip
    if not args.keep and args.out is None:
        shutil.rmtree(work, ignore_errors=True)
    else:
        print(f"\nworking directory: {work}")


if __name__ == "__main__":
    main()
