"""Identification time of the physics model (target: <= 1 s on one core for the
three seed 000 loading conditions)
and the PSO-LSSVM's size.

    .venv/bin/python benchmarks/bench_identification.py [--repeats 3]

Pins the process to one core, fits once to warm up (numba compilation, caches),
then reports the median of ``--repeats`` fits of PhysicsModel on the benchmark
dataset seed000_x runs cond1_3000, cond2_6000, cond3_9000 (coarse to fine, the default),
and the same fit in one stage on the model's own numerics with SLSQP converged tightly
(ftol 1e-12, the reference): parameters and held-out RMSE side by side.
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from thermbench.bench.datasets import load_benchmark  # noqa: E402
from thermbench.experiment import model_from_config  # noqa: E402
from thermbench.bench.metrics import evaluate  # noqa: E402

RUNS = ["cond1_3000", "cond2_6000", "cond3_9000"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        os.sched_setaffinity(0, {sorted(os.sched_getaffinity(0))[0]})
    ds = load_benchmark("seed000_x")
    model_from_config("physics").set_params(max_iter=2).fit(ds, RUNS[:1])  # warm-up
    times, model = [], None
    for _ in range(args.repeats):
        model = model_from_config("physics")
        t0 = time.perf_counter()
        model.fit(ds, RUNS)
        times.append(time.perf_counter() - t0)
    print(f"physics identification, seed000_x {'+'.join(RUNS)}, one core: median {statistics.median(times):.2f} s "
          f"over {args.repeats} fits (min {min(times):.2f}, max {max(times):.2f}; target <= 1 s); "
          f"{model.n_model_evaluations_} objective evaluations: {model.coarse_iterations_} least-squares evaluations on "
          f"the coarse steps, {model.polish_steps} Gauss-Newton step(s) on the model's own")  # fmt: skip
    ref = model_from_config("physics").set_params(coarse_dt_s=None, coarse_macro_dt_s=None, ftol=1e-12)
    t0 = time.perf_counter()
    ref.fit(ds, RUNS)
    ref_s = time.perf_counter() - t0
    print(f"reference, one stage, ftol 1e-12: {ref_s:.2f} s, {ref.n_model_evaluations_} objective evaluations")
    print(f"train RMSE: {model.train_rmse_um_:.5f} um (reference {ref.train_rmse_um_:.5f})")
    print("identified:", {k: float(f"{v:.4g}") for k, v in model.params_.items()})
    print("reference: ", {k: float(f"{v:.4g}") for k, v in ref.params_.items()})
    cols = ["run_id", "rmse_um", "max_abs_residual_um", "compensation_rate"]
    res = evaluate(model, ds)[cols].merge(evaluate(ref, ds)[cols[:2]], on="run_id", suffixes=("", "_reference"))
    print(res.to_string(index=False))

    lssvm = model_from_config("lssvm").fit(ds, ["cond2_6000"])
    print(f"PSO-LSSVM on cond2_6000: {lssvm.n_support_} support vectors, {lssvm.memory_bytes_} bytes, "
          f"gamma {lssvm.gamma_:.4g}, sigma2 {lssvm.sigma2_:.4g}")


if __name__ == "__main__":
    main()
