"""Exported models on the target: the Cortex-M4F (seed 002's STM32F407) emulated by QEMU.

For every export directory under EXPORTS (default ``exports/benchmark/``; run from the directory
the exports' dataset paths are relative to), in double and in float (``TB_REAL``): the firmware
image with the model in flash replays **every** parity run of the model (``manifest.json``) and
answers a query at every process sample on QEMU's mps2-an386 (``thermbench.export.target``).
Printed per model and precision, over all those runs:

* ``parity_um``: max |target − host| over every sample, the host being the x86-64 double runtime
  that the export's parity check tied to Python; for a bank, the samples whose condition label
  differs from the host's (``label_mismatches``: every classifier grid time is a sample);
* instructions per control cycle (``tb_*_step``) and per prediction, mean and worst (with the run
  of the worst cycle), and the end-of-stream ``tb_*_finish`` apart (not a control cycle), counted on
  the emulated M4 (``-icount shift=0``: the SysTick counts every 40 instructions, checked
  against a loop of known length in every run); at 168 MHz and an assumed 1.25 cycles per
  instruction, 100 000 instructions take 0.74 ms;
* the arena the models took on the target, the runtime's deepest stack (painted before each
  call), the flash of the whole test image (runtime with every kind, model, newlib stdio of the
  harness) and, for a single model, of the smallest one-kind image without stdio
  (``target.image``: what the 64 KB budget is about).

Budgets: float physics update <= 50 000 instructions, worst control cycle <= 100 000,
prediction <= 200 000, arena <= 16 KB, image <= 64 KB flash. Writes benchmarks/results/target.csv.

    .venv/bin/python benchmarks/bench_target.py [EXPORTS] [--only SUBSTRING] [--precision both|double|float]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from thermbench.outputs import write_text_atomic
from thermbench.data.io import load_dataset
from thermbench.export import read_manifest, runtime, target
from thermbench.export.budget import TARGETS
from thermbench.export.directory import replay_inputs
from thermbench.export.samples import readings_queries
from thermbench.export.replay import replay_view

KB = 1024
_B = TARGETS["cortex-m4f"]["budget"]  # the export's budget for the target (thermbench.export.budget)
CYCLE_BUDGET, PRED_BUDGET, ARENA_BUDGET, SRAM = _B["cycle_insn"], _B["prediction_insn"], _B["ram_bytes"], 128 * KB
PHYS_BUDGET, IMAGE_BUDGET = _B["physics_update_insn"], _B["image_bytes"]  # float: one physics update; one-kind firmware
MHZ, CPI = 168, 1.25  # seed 002's STM32F407; cycles per instruction assumed (not measured: QEMU counts instructions)


def over_budget(row: dict) -> list[str]:
    """The float build's figures of ``row`` beyond the budgets (empty: within)."""
    if row.get("note"):
        return [row["note"]]
    cyc = PHYS_BUDGET if row["kind"] == "PHYSICS" else CYCLE_BUDGET
    checks = [("cycle", row["cycle_insn_max"], cyc), ("prediction", row["pred_insn_max"], PRED_BUDGET),
              ("arena", row["arena_bytes"], ARENA_BUDGET), ("one-kind image", row.get("min_image_flash_bytes") or 0, IMAGE_BUDGET)]  # fmt: skip
    return [f"{what} {v} > {lim}" for what, v, lim in checks if v > lim]


def ms(insn: float) -> float:
    """Milliseconds at MHZ with CPI cycles per instruction."""
    return insn * CPI / (MHZ * 1e3)


def one(model_dir: Path, precision: str) -> dict:
    """One export in one precision over every parity run of its manifest, a query at every process
    sample: parity against the host's double build, the worst cycle and prediction of all runs (the
    mean over all cycles), the finish call apart, arena, stack, flash."""
    man = read_manifest(model_dir)
    full = load_dataset(man["training"]["dataset"])
    runs = man.get("parity", {}).get("runs", [full.run_ids[-1]])
    row = {"model": man["name"], "kind": man["kind"], "precision": precision, "runs": " ".join(runs)}
    acc = {"parity_um": 0.0, "cycle_insn_max": 0, "pred_insn_max": 0, "finish_insn": 0, "arena_bytes": 0,
           "stack_bytes": 0, "n_samples": 0, "cycle_worst": ""}  # fmt: skip
    sums = {"step": [0.0, 0], "predict": [0.0, 0]}
    for run in runs:
        ds = replay_view(full, man, run, None, Path(man["training"]["dataset"])) if full.metadata.version == 2 else full
        files, samples, temps, bank = replay_inputs(model_dir, ds, run, manifest=man)
        q = pd.DataFrame({"t_s": samples["t_s"].to_numpy(), "axis_mm": samples["axis_mm"].to_numpy()})
        host_state = int(runtime.info(files)["state_bytes"].sum())  # x86-64: >= the 32-bit target's
        arena = max(ARENA_BUDGET, host_state + 8 * len(files))
        if arena > SRAM - 24 * KB:
            return row | {"note": f"arena {host_state} B (host) does not fit the 128 KB SRAM"}
        ref = runtime.replay(files, samples, temps, q, bank=bank)
        got, rep = target.replay(files, samples, temps, q, precision=precision, arena_bytes=arena)
        if rep["rc"] != 0:
            return row | {"note": f"run {run}: {rep['end']}"}
        acc["parity_um"] = max(acc["parity_um"], float(np.max(np.abs(got["total_um"].to_numpy() - ref["total_um"].to_numpy()))))
        if bank:  # the condition in force at every sample (every classifier grid time among them)
            acc["label_mismatches"] = acc.get("label_mismatches", 0) + int((got["label"].to_numpy() != ref["label"].to_numpy()).sum())
        if rep["step_insn_max"] > acc["cycle_insn_max"]:
            acc["cycle_insn_max"], acc["cycle_worst"] = rep["step_insn_max"], run
        acc["pred_insn_max"] = max(acc["pred_insn_max"], rep["predict_insn_max"])
        acc["finish_insn"] = max(acc["finish_insn"], rep["finish_insn_max"])  # tb_*_finish at a stream's end: not a cycle
        acc["arena_bytes"], acc["stack_bytes"] = max(acc["arena_bytes"], rep["arena_bytes"]), max(acc["stack_bytes"], rep["stack_bytes"])
        acc["n_samples"] += len(samples)
        for what in sums:
            sums[what][0] += rep[f"{what}_insn_mean"] * rep[f"{what}_calls"]
            sums[what][1] += rep[f"{what}_calls"]
    return row | acc | {
        "cycle_insn_mean": sums["step"][0] / max(sums["step"][1], 1),
        "pred_insn_mean": sums["predict"][0] / max(sums["predict"][1], 1),
        "image_flash_bytes": rep["flash_bytes"], "calibration_insn": rep["calibrate_insn_max"],
        # the smallest one-kind firmware for a single model (no stdio): the 64 KB flash budget
        "min_image_flash_bytes": None if bank else target.image(files[0], precision).flash_bytes,
    }  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("exports", nargs="?", default="exports/benchmark")
    ap.add_argument("--only", default="", help="only export directories whose name contains this")
    ap.add_argument("--precision", choices=("both", "double", "float"), default="both",
                    help="the builds to run (double is informative and slow: software double on the M4)")
    args = ap.parse_args(argv)
    try:
        target.toolchain()
    except runtime.RuntimeUnavailable as exc:
        print(exc, file=sys.stderr)
        return 2
    dirs = sorted(p.parent for p in Path(args.exports).glob("*/manifest.json") if args.only in p.parent.name)
    if not dirs:
        print(f"no export directories under {args.exports}: run `thermbench export` first", file=sys.stderr)
        return 2
    rows = []
    for d in dirs:
        for precision in ("double", "float") if args.precision == "both" else (args.precision,):
            rows.append(one(d, precision))
            r = rows[-1]
            if precision == "float":
                r["over_budget"] = "; ".join(over_budget(r))
            print(f"{r['model']:<48s} {r['kind']:<12s} {precision:<6s} "
                  + (r.get("note") or f"{r['n_samples']} samples of {r['runs']}: parity {r['parity_um']:.2g} um, cycle "
                     f"{r['cycle_insn_mean']:.0f}/{r['cycle_insn_max']} insn (worst on {r['cycle_worst']}) "
                     f"({ms(r['cycle_insn_max']):.2f} ms), prediction {r['pred_insn_mean']:.0f}/{r['pred_insn_max']} "
                     f"({ms(r['pred_insn_max']):.2f} ms), finish {r['finish_insn']} insn, arena {r['arena_bytes']} B, "
                     f"stack {r['stack_bytes']} B, "
                     f"min image {r['min_image_flash_bytes']} B"
                     + (f", labels differing from the host's double {r['label_mismatches']}" if "label_mismatches" in r else ""))
                  + (f"  OVER: {r['over_budget']}" if r.get("over_budget") else ""), flush=True)  # fmt: skip
    df = pd.DataFrame(rows)
    part = "".join(f"-{v}" for v in (args.only, "" if args.precision == "both" else args.precision) if v)
    out = Path(__file__).parent / "results" / f"target{part}.csv"  # a subset: its own file
    write_text_atomic(out, df.to_csv(index=False))
    fl = df[df["precision"] == "float"] if "precision" in df else df.iloc[:0]
    if fl.empty:  # double only: the budgets are the float build's
        print(f"\n-> {out}")
        return 0
    print(f"\nbudgets (float): cycle <= {CYCLE_BUDGET} (physics update <= {PHYS_BUDGET}), prediction <= {PRED_BUDGET} "
          f"instructions, arena <= {ARENA_BUDGET} B, one-kind image <= {IMAGE_BUDGET} B; {int((fl['over_budget'] == '').sum())}"
          f"/{len(fl)} within. Milliseconds at {MHZ} MHz assuming {CPI} cycles per instruction -> {out}")  # fmt: skip
    return 0


if __name__ == "__main__":
    sys.exit(main())
