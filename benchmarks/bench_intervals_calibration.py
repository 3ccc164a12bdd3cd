"""Can an open-loop interval calibrated on the inner folds hold on the held-out run? fl_thermal's tail.

For each channel and the family given for it (default: the families `make demo` deploys), the
benchmark's own cell (:func:`thermbench.bench.run.run_task`, fold ``tail``) is run and the
calibration it builds is captured: per inner held-out block and for the tail, the residuals of a fit
without that run and their distance to the envelope of the runs that fit saw. Printed per run: its
readings, RMSE, mean residual (bias), the 90th percentile of |residual|, the share of readings outside
the envelope and the median distance; then the tail's coverage and mean half-width (as a multiple of
its RMSE) of the 90 % conformal interval ``q * (1 + kappa * distance)`` with ``kappa`` 0, 1 (the
shipped setting) and learnt from the inner folds (a 90 % quantile regression of |residual| on the
distance, scikit-learn's QuantileRegressor: ``kappa`` = slope / intercept). No number of the tail
enters any calibration.

    .venv/bin/python benchmarks/bench_intervals_calibration.py [--families ch1=physics_spindle_hybrid,...]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

DEPLOYED = "ch1=physics_spindle_hybrid,ch2=physics_spindle_hybrid,ch3=ridge_history,ch4=ridge_history,ch5=linear_history"


def _line(name: str, r: np.ndarray, d: np.ndarray) -> str:
    return (f"    {name:<8} n {len(r):5d}  RMSE {np.sqrt(np.mean(r ** 2)):5.2f}  bias {r.mean():+6.2f}  "
            f"q90|r| {np.quantile(np.abs(r), 0.9):5.2f}  outside {np.mean(d > 0):4.0%}  median distance {np.median(d):.2f}")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--families", default=DEPLOYED, help=f"channel=family, comma-separated (default {DEPLOYED})")
    args = ap.parse_args()
    from sklearn.linear_model import QuantileRegressor

    from thermbench import bench as bm
    from thermbench.config import load_config
    from thermbench.bench.intervals import conformal_quantile, half_widths, interval_scores

    want = dict(kv.split("=", 1) for kv in args.families.split(","))
    cfg = load_config("benchmark", ["datasets=[fl_thermal]", "bank_families=[]", "n_jobs=1", "progress=false",
                                    "approaches=[global]", "cache_dir=null"])  # fmt: skip
    captured = {}
    real = bm.run.fold_intervals  # where run_task looks it up

    def spy(cal, fold_name, level, kappa):
        captured[fold_name] = cal
        return real(cal, fold_name, level, kappa)

    bm.run.fold_intervals = spy
    for task in bm.tasks(cfg):
        if want.get(task["channel"]) != task["family"]:
            continue
        captured.clear()
        bm.run_task(**task)
        cal = captured["tail"]
        print(f"fl_thermal {task['channel']} x {task['family']}: fold tail, its inner folds hold out each block")
        for k, (_, r, d) in enumerate(cal["calibration"]):
            print(_line(f"block {k + 1}", r, d))
        (_, measured, _, pred, d_tail), = cal["held"].values()
        r_tail = measured - pred
        print(_line("tail", r_tail, d_tail))
        r = np.concatenate([c[1] for c in cal["calibration"]])
        d = np.concatenate([c[2] for c in cal["calibration"]])
        qr = QuantileRegressor(quantile=0.9, alpha=0.0, solver="highs").fit(d[:, None], np.abs(r))
        learnt = max(qr.coef_[0] / qr.intercept_, 0.0) if qr.intercept_ > 0 else 0.0
        rmse = np.sqrt(np.mean(r_tail ** 2))
        for name, kappa in (("kappa 0", 0.0), ("kappa 1", 1.0), (f"kappa {learnt:.2f} (learnt)", learnt)):
            hw = half_widths(conformal_quantile(interval_scores(r, d, kappa), 0.9), d_tail, kappa)
            print(f"    90 % interval, {name}: covers {np.mean(np.abs(r_tail) <= hw):.0%} of the tail, "
                  f"mean half-width {hw.mean():.2f} µm = {hw.mean() / rmse:.2f}x its RMSE")
    return 0


if __name__ == "__main__":
    sys.exit(main())
