"""Every family's held-out RMSE beside the ridge baseline's, from the results.csv of `thermbench benchmark`.

Per dataset and channel of each results.csv: for every family fitted on all training runs of a fold
(approach ``global``) and for thermbench's choice (the ``chosen`` rows), the median and worst held-out
RMSE over the folds; against ``baseline_ridge``, fold by fold, the mean paired difference (family minus
ridge, µm) and its standard error over the folds: a family is *worse than the ridge* when the mean
difference exceeds its own standard error (and 0.01 µm) (``worse`` column), and ``max |d|`` is the largest per-fold
difference (``ridge_history`` is the ridge made deployable: it should be ~0).
Given two files (``--before``), the table shows both.

    .venv/bin/python benchmarks/families_vs_ridge.py reports/ace/results.csv [--before OLD/results.csv]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

REFERENCE = "baseline_ridge"
#: a mean difference below this is a tie (the digits a report prints)
TIE_UM = 0.01


def table(path: str) -> pd.DataFrame:
    d = pd.read_csv(path, keep_default_na=False, na_values=[""])
    held = d[(d["kind"] == "validation")]
    rows = []
    for (dataset, channel), g in held.groupby(["dataset", "channel"], sort=False):
        ref = g[(g["family"] == REFERENCE) & (g["approach"] == "global")].set_index("fold")["rmse_um"]
        parts = {f: x.set_index("fold")["rmse_um"] for f, x in g[g["approach"] == "global"].groupby("family")}
        chosen = g[g["chosen"].astype(str) == "True"].groupby("fold")["rmse_um"].first()
        parts["(thermbench's choice)"] = chosen
        for fam, s in parts.items():
            both = pd.concat([s, ref], axis=1, keys=["f", "r"]).dropna()
            diff = (both["f"] - both["r"]).to_numpy()
            se = float(np.std(diff, ddof=1) / np.sqrt(diff.size)) if diff.size > 1 else float("nan")
            rows.append({"dataset": f"{dataset}-{channel}", "family": fam, "folds": int(s.size),
                         "median_um": float(s.median()), "worst_um": float(s.max()),
                         "mean_d_um": float(diff.mean()) if diff.size else float("nan"), "se_d_um": se,
                         "max_abs_d_um": float(np.max(np.abs(diff))) if diff.size else float("nan"),
                         "worse": bool(diff.size > 1 and diff.mean() > max(se, TIE_UM))})  # fmt: skip
    return pd.DataFrame(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("results", help="results.csv of a benchmark")
    ap.add_argument("--before", help="results.csv of the same benchmark at an earlier commit")
    a = ap.parse_args(argv)
    for path in (a.results, a.before):
        if path is not None and not Path(path).is_file():
            ap.error(f"{path}: no such file (the results.csv a `thermbench benchmark` wrote into its report_dir)")
    now = table(a.results)
    if a.before:
        old = table(a.before)[["dataset", "family", "median_um", "worst_um"]]
        now = now.merge(old, on=["dataset", "family"], how="left", suffixes=("", "_before"))
        cols = ["dataset", "family", "folds", "median_um_before", "worst_um_before", "median_um", "worst_um",
                "mean_d_um", "se_d_um", "max_abs_d_um", "worse"]  # fmt: skip
        now = now[cols]
    print(now.to_markdown(index=False, floatfmt=".3f"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
