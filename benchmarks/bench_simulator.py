"""Speed of the ball-screw simulator (8 h of the seed 000 X axis at 80 nodes).

Simulates 8 h of machine time for the seed 000 X axis (Table 1 geometry, Table 3
parameters, dx = 0.01 m -> 80 nodes) under the Table 2 loading repeated (warm 84
min, cool 42 min, warm 42 min at 9000 mm/min, 10-min measuring cycles), with

* the fast integrator (heat inputs averaged exactly over 10-s steps, SDIRK2), and
* the dt = 0.1 s explicit scheme of seed 000 §3.1 (the reference),

and prints the median wall time of 5 runs after a warm-up for each, their ratio,
and the largest difference of the error field (all 11 targets, every 10 s).
Single core: numba kernels are serial; BLAS/OpenMP threads are pinned to 1.

    python benchmarks/bench_simulator.py [--repeats 5] [--feed 9000]
"""

from __future__ import annotations

import argparse
import os

for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(var, "1")

import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from thermbench.sim.duty import Measuring, Phase, build_run  # noqa: E402
from thermbench.sim.model import ScrewThermalModel  # noqa: E402
from thermbench.sim.parts import CoreParams, Material, Numerics, Screw  # noqa: E402


def eight_hour_motion(feed_mm_min: float, dt_s: float):
    meas = Measuring(targets_mm=tuple(float(x) for x in range(0, 501, 50)), every_s=600, dwell_s=4, feed_mm_min=3000)
    cycle = [Phase("move", 5040, 0, 500, feed_mm_min), Phase("stop", 2520), Phase("move", 2520, 0, 500, feed_mm_min)]
    phases = []
    while sum(p.duration_s for p in phases) < 8 * 3600 - 1:
        phases.extend(cycle)
    tr = build_run(phases, meas)
    t_end = 8 * 3600.0
    return tr.sample(np.arange(0.0, t_end, dt_s)), t_end


def timed(fn, repeats: int) -> tuple[float, object]:
    out = fn()  # warm-up (JIT compile / caches)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--feed", type=float, default=9000.0)
    args = ap.parse_args()
    screw = Screw(0.8, 0.034, 0.212, 0.03)
    material = Material(11.7e-6, 7800.0, 448.0)
    numerics = Numerics(dx_m=0.01, dt_s=0.1, macro_dt_s=10.0)
    model = ScrewThermalModel(screw, material, CoreParams(), [], numerics)
    motion, t_end = eight_hour_motion(args.feed, numerics.dt_s)
    grid = np.arange(0.0, 501.0, 50.0)

    fast_s, fast = timed(lambda: model.run(motion, duration_s=t_end, method="macro"), args.repeats)
    expl_s, expl = timed(lambda: model.run(motion, duration_s=t_end, method="explicit"), args.repeats)
    f_fast = fast.error_field_um(grid)
    f_expl = expl.error_field_um(grid)
    dev = float(np.max(np.abs(f_fast - f_expl)))
    read_s, _ = timed(lambda: fast.error_field_um(grid), args.repeats)
    # convergence: halve dx and dt (fast integrator, same 10-s steps)
    fine_model = ScrewThermalModel(screw, material, CoreParams(), [], Numerics(dx_m=0.005, dt_s=0.05, macro_dt_s=10.0))
    fine_motion, _ = eight_hour_motion(args.feed, 0.05)
    conv = float(np.max(np.abs(fine_model.run(fine_motion, duration_s=t_end).error_field_um(grid) - f_fast)))

    print(f"seed 000 X axis, {model.geom.n_nodes} nodes, 8 h at {args.feed:.0f} mm/min, median of {args.repeats} after warm-up")
    print(f"  fast integrator (10 s steps, exact step averages): {fast_s * 1e3:8.1f} ms")
    print(f"  explicit scheme dt = 0.1 s (seed 000 §3.1):       {expl_s * 1e3:8.1f} ms")
    print(f"  speed-up explicit / fast:                          {expl_s / fast_s:8.1f} x")
    print(f"  max |error field difference| (11 targets, 10 s):   {dev:8.4f} um  (max error {f_expl.max():.1f} um)")
    print(f"  halving dx and dt changes the error field by:      {conv:8.4f} um")
    print(f"  reading the error field (2881 x 11):               {read_s * 1e3:8.2f} ms")
    ok = fast_s <= 0.05 and dev <= 0.1 and conv <= 0.1
    print(f"  targets: fast <= 50 ms, deviation <= 0.1 um, convergence <= 0.1 um -> {'PASS' if ok else 'FAIL'}")


if __name__ == "__main__":
    main()
