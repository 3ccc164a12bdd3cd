"""The discrepancy workflow on physics outside its library: outcome per case x strength x seed.

    .venv/bin/python benchmarks/bench_out_of_library.py [--seeds 5] [--ratios 3,5,8] [--n-jobs 2] [--out FILE]

Each case of :data:`thermbench.discrepancy.hidden.OUT_OF_LIBRARY` (a support bearing
heating the screw mid-length, unsensed structure growth lagging the duty by hours, a scale
mount expanding about its own fixing point) gets its parameters drawn at random per seed
from wide physical ranges, its strength scaled so that the core model leaves ``ratio`` x the
noise floor on noise-free data; the noisy dataset is written, read back and diagnosed
(``conf/diagnose.yaml`` as shipped, up to ``--max-effects`` steps). Outcomes:

* ``described``: the final held-out RMSE is within 1.5x the noise floor, and the term named is the
  open term of the case's form (a heat source, an offset, an expansion: ``OutOfLibrary.term``);
* ``described_other``: within 1.5x the floor through another term (e.g. ``motor_heat`` for an offset
  lagging the speed: on these data they are alike);
* ``unexplained``: above it, and the verdict says so (unexplained, found_partial or ambiguous);
* ``wrong``: above it, yet the verdict is none or found (the tool calling an incomplete model complete).

Prints one line per diagnosis, then the outcome table; writes the rows to ``--out`` (CSV).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
os.environ.setdefault("OMP_NUM_THREADS", "1")

import pandas as pd  # noqa: E402
from joblib import Parallel, delayed  # noqa: E402

from thermbench.outputs import write_text_atomic  # noqa: E402
from thermbench.config import load_config  # noqa: E402
from thermbench.data.io import load_dataset  # noqa: E402
from thermbench.discrepancy import hidden  # noqa: E402
from thermbench.discrepancy.job import settings_from_config  # noqa: E402
from thermbench.discrepancy.workflow import run_diagnosis  # noqa: E402


def outcome(verdict: str, within: bool, named: list[str] = (), term: str = "") -> str:
    if within:
        return "described" if term in named else "described_other"
    return "unexplained" if verdict in ("unexplained", "found_partial", "ambiguous") else "wrong"


def task(name: str, seed: int, ratio: float, world: hidden.World, max_effects: int) -> dict:
    settings = settings_from_config(load_config("diagnose", ["data_dir=x", "out_dir=x"]), say=lambda m: None)
    row = {"case": name, "seed": seed, "ratio": ratio}
    try:
        params, resid = hidden.draw_out_of_library(name, seed, world, ratio=ratio, physics=settings.physics)
    except ValueError as exc:
        return row | {"outcome": "error", "error": str(exc)}
    with tempfile.TemporaryDirectory() as tmp:
        ds = load_dataset(hidden.make_out_of_library(Path(tmp) / "ds", name, params, seed, world))
        t0 = time.perf_counter()
        d = run_diagnosis(ds, max_effects=max_effects, settings=settings)
        dt = time.perf_counter() - t0
    f = d["final"]
    row |= {"params": str({k: float(f"{v:.4g}") for k, v in params.items()}),
            "core_residual_x_floor": resid / world.noise_floor_um, "verdict": d["verdict"],
            "named": "+".join(d["missing_effects"]), "ambiguous": ";".join("|".join(a) for a in d["ambiguous"]),
            "described_as": " | ".join(s["description"] for s in d["steps"] if s.get("description")),
            "heldout_x_floor": f["heldout_x_floor"],
            "outcome": outcome(d["verdict"], f["within_floor"], d["missing_effects"], hidden.OUT_OF_LIBRARY[name].term),
            "runtime_s": dt}  # fmt: skip
    print(f"{name:<22s} seed {seed} ratio {ratio:g}: {row['verdict']:<13s} {row['heldout_x_floor']:.2f}x floor, "
          f"named {row['named'] or '-'} -> {row['outcome']} ({dt:.0f} s) {row['described_as']}", flush=True)  # fmt: skip
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=",".join(hidden.OUT_OF_LIBRARY))
    ap.add_argument("--seeds", type=int, default=5)
    ap.add_argument("--ratios", default="3,5,8", help="core residual / noise floor the strengths are scaled to")
    ap.add_argument("--runs", type=int, default=3, help="runs per dataset")
    ap.add_argument("--hours", type=float, default=2.0, help="hours per run")
    ap.add_argument("--max-effects", type=int, default=2)
    ap.add_argument("--n-jobs", type=int, default=2, help="diagnoses in parallel (joblib)")
    ap.add_argument("--out", default="benchmarks/results/out_of_library.csv")
    args = ap.parse_args()
    world = hidden.World(n_runs=args.runs, run_h=args.hours)
    ratios = [float(r) for r in args.ratios.split(",")]
    jobs = [delayed(task)(c, s, r, world, args.max_effects)
            for c in args.cases.split(",") for r in ratios for s in range(args.seeds)]  # fmt: skip
    rows = Parallel(n_jobs=args.n_jobs)(jobs)
    df = pd.DataFrame(rows)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, df.to_csv(index=False))
    print("\noutcome per case and strength (count over seeds):")
    print(df.pivot_table(index=["case", "ratio"], columns="outcome", values="seed", aggfunc="count", fill_value=0).to_string())
    print(f"wrong (an incomplete model called complete): {(df['outcome'] == 'wrong').sum()} of {len(df)}")
    print(f"rows: {out}")


if __name__ == "__main__":
    main()
