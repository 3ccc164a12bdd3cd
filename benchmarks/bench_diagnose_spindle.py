"""The spindle workflow's recovery table on hand-made tests (thermbench/discrepancy/hidden_spindle.py):
each term hidden at each strength (x the gauge noise left after the base absorbs what it can) with
parameters drawn from wide ranges per seed, a clean control and physics outside the library.

    .venv/bin/python benchmarks/bench_diagnose_spindle.py [--seeds 1,2] [--strengths 4,8] [--jobs 2]

Prints per case: the verdict, the first named term (and signal), whether it is the hidden one,
the held-out block RMSE before and after it, and the tail's RMSE (never seen by the search)."""

from __future__ import annotations

import argparse

import numpy as np
import pandas as pd
from joblib import Parallel, delayed

from thermbench.discrepancy import hidden_spindle as hs
from thermbench.discrepancy.search import Settings
from thermbench.discrepancy.spindle import spindle_family
from thermbench.discrepancy.workflow import run_diagnosis
from thermbench.bench.splits import dataset_view

TERMS = ("second_heat_path", "structure_growth", "sensor_expansion", "stop_drift")


def case(term, x, seed) -> dict:
    world = hs.SpindleWorld()
    h = hs.hidden_term(term, x, np.random.default_rng(seed), world)
    ds = dataset_view(hs.dataset(world, h), "Z", segments=True, history=True)
    fam = spindle_family(ds, [r for r in ds.run_ids if r != "tail"])
    d = run_diagnosis(ds, settings=Settings(family=fam, candidates=fam.candidates, say=lambda m: None), holdout=["tail"])
    s = d["steps"][0] if d["steps"] else None
    named = None if s is None else s["label"]
    hidden = None if term is None else term + (f"[{h.signal}]" if h.signal else "")
    right = (named is None) if term is None else (term == "chiller" and d["verdict"] not in ("none", "found")) or named == hidden
    return {"hidden": hidden or "none", "x_noise": x, "seed": seed, "verdict": d["verdict"], "named": named or "-",
            "right": right, "heldout_before_um": d["final"]["heldout_rmse_base_um"], "heldout_after_um": d["final"]["heldout_rmse_um"],
            "floor_um": d["noise_floor_um"], "tail_base_um": d["validation"]["rmse_base_um"],
            "tail_final_um": d["validation"]["rmse_final_um"], "runtime_s": d["runtime_s"]}  # fmt: skip


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", default="1,2")
    ap.add_argument("--strengths", default="4,8")
    ap.add_argument("--jobs", type=int, default=2)
    a = ap.parse_args()
    seeds = [int(s) for s in a.seeds.split(",")]
    xs = [float(x) for x in a.strengths.split(",")]
    cases = [(t, x, s) for t in (*TERMS, "chiller") for x in xs for s in seeds] + [(None, 0.0, s) for s in seeds]
    rows = Parallel(n_jobs=a.jobs)(delayed(case)(*c) for c in cases)
    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 220, "display.max_rows", 200, "display.float_format", "{:.3f}".format):
        print(df.to_string(index=False))
    print(f"\nright: {int(df['right'].sum())}/{len(df)}")


if __name__ == "__main__":
    main()
