"""What a reduced-set LSSVM export costs in accuracy, per number of centres.

For each benchmark PSO-LSSVM (models/benchmark/<dataset>__lssvm__global.joblib, written by
``thermbench benchmark``): the held-out RMSE of measured minus predicted positioning error on
the dataset's validation runs, full model vs reduced sets of m centres
(:func:`thermbench.export.reduce.reduced_lssvm`), and the file size of each export.

    .venv/bin/python benchmarks/bench_lssvm_reduced.py [--sizes 5 10 20 50 100 200]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import joblib
import numpy as np
import pandas as pd

from thermbench.outputs import write_text_atomic
from thermbench.experiment import group_option, load_split
from thermbench.export.encoding import encode
from thermbench.export.fileformat import pack
from thermbench.export.reduce import reduced_lssvm


def heldout_rmse(model, ds, runs) -> float:
    err = [ds.errors_run(r)["error_um"].to_numpy() - model.predict(ds, r) for r in runs]
    return float(np.sqrt(np.mean(np.concatenate(err) ** 2)))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", default="models/benchmark")
    ap.add_argument("--sizes", type=int, nargs="+", default=[5, 10, 20, 50, 100, 200])
    args = ap.parse_args(argv)
    files = sorted(Path(args.models).glob("*__lssvm__global.joblib"))
    if not files:
        print(f"no *__lssvm__global.joblib under {args.models}: run `thermbench benchmark` first", file=sys.stderr)
        return 2
    rows = []
    for f in files:
        dname = f.name.split("__")[0]
        sp = load_split(group_option("dataset", dname))
        m = joblib.load(f)
        full = heldout_rmse(m, sp.dataset, sp.validation)
        enc = encode(m)
        rows.append({"dataset": dname, "centres": m.n_support_, "file_bytes": len(pack(enc.kind, enc.dims, enc.payload)),
                     "heldout_rmse_um": full, "cost_um": 0.0})  # fmt: skip
        for size in args.sizes:
            r = reduced_lssvm(m, size, seed=0)
            enc = encode(r)
            rmse = heldout_rmse(r, sp.dataset, sp.validation)
            rows.append({"dataset": dname, "centres": size, "file_bytes": len(pack(enc.kind, enc.dims, enc.payload)),
                         "heldout_rmse_um": rmse, "cost_um": rmse - full})  # fmt: skip
    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 140, "display.float_format", "{:.4f}".format):
        print(df.to_string(index=False))
    out = Path(__file__).parent / "results" / "lssvm_reduced.csv"
    write_text_atomic(out, df.to_csv(index=False))
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
