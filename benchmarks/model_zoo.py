"""The model-zoo table: every family x training condition on the benchmark datasets.

    .venv/bin/python benchmarks/model_zoo.py                 # all families, all datasets
    .venv/bin/python benchmarks/model_zoo.py --models physics mlr_seed001 --datasets seed001_vmc_x

Each family (conf/model/<name>.yaml) is trained on one condition run and scored on
every run of the dataset (thermbench.bench.metrics): RMSE, max |residual|, compensation
rate and max |residual| / P-V, on its own condition and on the others (worst case).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import pandas as pd

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from thermbench.bench.datasets import load_benchmark  # noqa: E402
from thermbench.experiment import cross_condition, model_from_config  # noqa: E402
from thermbench.models.base import ModelError  # noqa: E402

FAMILIES = ["mlr_seed001", "mlr_seed002", "mlr_seed004", "lssvm", "mlp", "gru", "ar_seed003", "physics"]
TRAIN = {
    "seed000_x": ["cond1_3000", "cond3_9000"],
    "seed001_vmc_x": ["state1", "state5"],  # seed 001 §5.1: models M1 and M5
    "seed002_vmc655h_x": ["c2", "c5"],
    "seed004_ff_x": ["warmup_6000"],
}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="+", default=FAMILIES)
    ap.add_argument("--datasets", nargs="+", default=list(TRAIN))
    ap.add_argument("--csv", type=Path, default=None, help="also write every row to this CSV")
    args = ap.parse_args()
    rows = []
    for name in args.datasets:
        ds = load_benchmark(name)
        for fam in args.models:
            for train in TRAIN[name]:
                try:
                    res = cross_condition(model_from_config(fam), ds, [train])
                except ModelError as exc:
                    print(f"{name:18s} {fam:12s} train={train:12s} cannot fit: {exc}", flush=True)
                    continue
                res.insert(0, "family", fam)
                res.insert(0, "dataset", name)
                rows.append(res)
                own = res[res["own"]].iloc[0]
                other = res[~res["own"]]
                print(
                    f"{name:18s} {fam:12s} train={train:12s} fit {own['fit_s']:6.1f} s | own: rmse {own['rmse_um']:5.2f} "
                    f"max {own['max_abs_residual_um']:5.2f} um rate {own['compensation_rate']:5.1%} | others: "
                    f"rmse {other['rmse_um'].mean():5.2f} (mean) max {other['max_abs_residual_um'].max():6.2f} um "
                    f"rate {other['compensation_rate'].min():6.1%} (worst) res/PV {other['residual_fraction_of_pv'].max():5.1%}",
                    flush=True,
                )
    table = pd.concat(rows, ignore_index=True)
    if args.csv:
        table.to_csv(args.csv, index=False)


if __name__ == "__main__":
    main()
