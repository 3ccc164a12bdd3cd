"""Intervals and probes on hand-made datasets of the two common shapes of a lab's files
(tests/test_import_shapes.py writes them by hand with openpyxl).

Shape 1: a lathe's spindle, one sheet per day (3 days, 25-30 readings at a constant step).
Shape 2: a mill's spindle, one headerless file per experiment (3 experiments, 20-26 readings).
Each is imported with its mapping file alone and benchmarked (thermbench benchmark, cross-validation
over runs: each run held out once, the families' interval calibrated on the inner folds), with
approaches global + adaptive and a probe every ``--every`` s. Printed per held-out run: the
global approach's RMSE, coverage of its 90 % interval and mean half-width, then the adaptive
approach's (scored on the readings that were not probes).

    python benchmarks/bench_intervals_shapes.py [--families baseline_ridge,thermal_lag] [--every 1800]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default="baseline_ridge,thermal_lag")
    ap.add_argument("--every", default="1800")
    a = ap.parse_args()

    from tests.test_import_shapes import shape1, shape2
    from thermbench import bench as bm
    from thermbench.config import load_config
    from thermbench.data.importer import import_dataset

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        tables = []
        for shape, writer in (("shape 1", shape1), ("shape 2", shape2)):
            mapping, _ = writer(tmp / shape.replace(" ", "") / "files")
            data = tmp / shape.replace(" ", "") / "data"
            import_dataset(mapping, data)
            out = tmp / shape.replace(" ", "") / "out"
            cfg = load_config("benchmark", [f"datasets=[{data}]", f"families=[{a.families}]", "bank_families=[]", "n_jobs=1",
                                            "progress=false", f"cache_dir={out}/cache", f"report_dir={out}/reports",
                                            f"export_dir={out}/models", f"tracking.uri=sqlite:///{out}/mlflow.db",
                                            f"tracking.artifact_root={out}/art", "approaches=[global,adaptive]",
                                            f"probe.every_s=[{a.every}]"])  # fmt: skip
            bm.benchmark(cfg)
            r = pd.read_csv(out / "reports" / "results.csv")
            keep = r["approach"].isin(["global", f"adaptive-{float(a.every):g}s"]) & ~r["own"].astype(bool)
            keep &= r["coverage_90"].notna()
            cols = ["family", "approach", "fold", "run_id", "rmse_um", "coverage_90", "half_width_um"]
            tables.append(r.loc[keep, [c for c in cols if c in r]].assign(shape=shape))
    t = pd.concat(tables, ignore_index=True)
    with pd.option_context("display.width", 200, "display.max_rows", 200, "display.float_format", "{:.2f}".format):
        print(t.to_string(index=False))
        print("\nper shape, family and approach: the worst held-out run's coverage and the mean half-width / RMSE")
        g = t.groupby(["shape", "family", "approach"])
        print(pd.DataFrame({"min_coverage_90": g["coverage_90"].min(), "mean_coverage_90": g["coverage_90"].mean(),
                            "half_width_over_rmse": g["half_width_um"].mean() / g["rmse_um"].mean()}).to_string())  # fmt: skip


if __name__ == "__main__":
    main()
