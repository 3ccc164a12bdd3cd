"""Bringing real measurements in: how long the shipped 46-hour spindle test takes to import
(Excel workbook -> dataset, ``thermbench import``), to load once imported (``load_dataset``,
Parquet and CSV), and how fast the segmentation of an operating signal runs (1 M samples).

Prints the median of ``--repeats`` runs after one warm-up run, per step.

    python benchmarks/bench_import.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from thermbench.data import load_dataset
from thermbench.data.importer import import_dataset
from thermbench.data.segments import derive_segments

MAPPING = Path(__file__).resolve().parents[1] / "thermbench/realdata/fl_thermal/mapping.yaml"


def timed(fn, repeats: int) -> float:
    fn()  # warm-up
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return statistics.median(out)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        n = [0]

        def imp(fmt: str):
            n[0] += 1
            return import_dataset(MAPPING, tmp / f"imp{n[0]}", file_format=fmt)

        t_imp = timed(lambda: imp("parquet"), args.repeats)
        import_dataset(MAPPING, tmp / "pq", file_format="parquet")
        import_dataset(MAPPING, tmp / "csv", file_format="csv")
        t_pq = timed(lambda: load_dataset(tmp / "pq"), args.repeats)
        t_csv = timed(lambda: load_dataset(tmp / "csv"), args.repeats)
        ds = load_dataset(tmp / "pq")
    rng = np.random.default_rng(0)
    t = np.arange(1_000_000) * 0.1
    v = np.where((t // 3600) % 2 == 1, 3000.0, 0.0) + rng.normal(0, 5, t.size)
    t_seg = timed(lambda: derive_segments(t, v), args.repeats)
    print(f"fl_thermal: {len(ds.process)} process rows x {ds.process.shape[1]} columns, {len(ds.errors)} readings")
    print(f"import (Excel -> Parquet dataset, validated): median {t_imp:.2f} s over {args.repeats} runs")
    print(f"load_dataset, Parquet: median {t_pq:.3f} s")
    print(f"load_dataset, CSV:     median {t_csv:.3f} s")
    print(f"derive_segments, 1 000 000 samples: median {t_seg:.3f} s")


if __name__ == "__main__":
    main()
