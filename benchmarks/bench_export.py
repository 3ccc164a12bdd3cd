"""Footprint of exported models in the C runtime, against seed 002's STM32F407 budget.

For every export directory under EXPORTS (default ``exports/benchmark/``, written by
``thermbench export``): file bytes, RAM for the running state (the arena the
runtime asks for, plus the ``tb_model`` handle per file) and instructions per
control cycle / per prediction / per physics update, counted by
``valgrind --tool=callgrind`` (instruction counts are repeatable: each figure is
measured twice and must agree). The stream is the model's dataset's first
held-out run (``manifest.json`` parity runs), first ``--seconds`` of it.

Budget (seed 002: 1 MB flash, 192 KB RAM, 168 MHz): every model <= 64 KB file and
<= 16 KB RAM; MLR and the classifier <= 1 KB file; one physics update <= 50 000
instructions. Prints a table and writes benchmarks/results/export_footprint.csv.

    .venv/bin/python benchmarks/bench_export.py [EXPORTS] [--seconds 1800] [--target]

``--target`` adds the float build's figures on the emulated Cortex-M4F (``m4f_*``: parity against
the host, worst instructions per cycle and per prediction, arena, stack; bench_target.py).
"""

from __future__ import annotations

import argparse
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import pandas as pd

from thermbench.outputs import write_text_atomic
from thermbench.data.io import load_dataset
from thermbench.export import read_manifest
from thermbench.export.samples import process_samples
from thermbench.export.replay import replay_view
from thermbench.export.runtime import build, info, stream_text

KB = 1024
FILE_BUDGET, RAM_BUDGET, SMALL_BUDGET, PHYS_BUDGET = 64 * KB, 16 * KB, 1 * KB, 50_000


def callgrind_ir(exe: Path, args: list[str], stdin: str, function: str) -> int:
    """Instructions executed inside ``function`` (inclusive) over one run of ``exe``."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "cg.out"
        cmd = ["valgrind", "--tool=callgrind", f"--callgrind-out-file={out}", "--collect-atstart=no",
               f"--toggle-collect={function}", str(exe), *args]  # fmt: skip
        res = subprocess.run(cmd, input=stdin, capture_output=True, text=True)
        if res.returncode != 0:
            raise RuntimeError(f"callgrind failed: {res.stderr[-1500:]}")
        m = re.search(r"^(?:summary|totals):\s+(\d+)", out.read_text(), re.M)
        return int(m.group(1)) if m else 0


def measure(exe: Path, args: list[str], stdin: str, function: str) -> int:
    a = callgrind_ir(exe, args, stdin, function)
    b = callgrind_ir(exe, args, stdin, function)
    if a != b:
        raise RuntimeError(f"callgrind counts differ between two runs ({a} vs {b}): not repeatable")
    return a


def one(model_dir: Path, seconds: float, exe: Path) -> dict:
    man = read_manifest(model_dir)
    ds = load_dataset(man["training"]["dataset"])
    run = man.get("parity", {}).get("runs", [ds.run_ids[-1]])[0]
    if ds.metadata.version == 2:  # the error channel and segments the model was trained on
        ds = replay_view(ds, man, run, None, Path(man["training"]["dataset"]))
    bank = man["kind"] == "bank"
    files = ([model_dir / man["bank"]["classifier"], *[model_dir / m["file"] for m in man["bank"]["members"]]]
             if bank else [model_dir / man["files"]["model"]["file"]])  # fmt: skip
    inf = info(files)
    temps = [ds.metadata.sensor_column(s) for s in man["temperatures"]] + list(man.get("operating", []))
    pr = process_samples(ds, run)
    pr = pr[pr["t_s"] <= pr["t_s"].iloc[0] + seconds].reset_index(drop=True)
    q = pd.DataFrame({"t_s": pr["t_s"], "axis_mm": pr["axis_mm"]})
    args = (["--bank"] if bank else []) + [str(f) for f in files]
    step_fn, pred_fn = ("tb_bank_step", "tb_bank_predict") if bank else ("tb_model_step", "tb_model_predict")
    no_q = stream_text(pr, temps, q.iloc[:0])
    with_q = stream_text(pr, temps, q)
    row = {
        "model": man["name"], "kind": man["kind"], "files": len(files),
        "file_bytes": int(inf["file_bytes"].sum()), "largest_file_bytes": int(inf["file_bytes"].max()),
        "ram_bytes": int(inf["state_bytes"].sum() + inf["model_bytes"].sum()),
        "instr_per_cycle": measure(exe, args, no_q, step_fn) / len(pr),
        "instr_per_prediction": measure(exe, args, with_q, pred_fn) / len(q),
    }  # fmt: skip
    if man["kind"] == "PHYSICS":  # one update of the error array (seed 000 §4.3): a sample per macro step
        macro = float(man["physics"]["macro_dt_s"])
        sub = pr.iloc[:: int(round(macro / man["sample_period_s"]))].reset_index(drop=True)
        row["instr_per_physics_update"] = measure(exe, [str(files[0])], stream_text(sub, temps, sub.iloc[:0]), step_fn) / len(sub)
    small = man["kind"] in ("MLR_CURVE", "MLR_SEED001")
    limit_file = SMALL_BUDGET if small else FILE_BUDGET
    ok = row["largest_file_bytes"] <= limit_file and row["ram_bytes"] <= RAM_BUDGET
    if bank:
        ok = ok and inf["file_bytes"].iloc[0] <= SMALL_BUDGET  # the classifier
        if all(m["kind"] in ("MLR_CURVE", "MLR_SEED001") for m in man["bank"]["members"]):
            ok = ok and row["largest_file_bytes"] <= SMALL_BUDGET
    if "instr_per_physics_update" in row:
        ok = ok and row["instr_per_physics_update"] <= PHYS_BUDGET
    row["within_budget"] = bool(ok)
    for variant in ("reduced",):
        if variant in man["files"]:
            r = info([model_dir / man["files"][variant]["file"]])
            row["reduced_file_bytes"] = int(r["file_bytes"].iloc[0])
            row["reduced_instr_per_prediction"] = measure(exe, [str(model_dir / man["files"][variant]["file"])], with_q, pred_fn) / len(q)
            par = man.get("parity", {})
            row["reduced_cost_rmse_um"] = par.get("reduced_cost_um")
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("exports", nargs="?", default="exports/benchmark")
    ap.add_argument("--seconds", type=float, default=1800.0, help="length of the replayed stream")
    ap.add_argument("--target", action="store_true",
                    help="also the Cortex-M4F figures in float under QEMU (benchmarks/bench_target.py)")
    args = ap.parse_args(argv)
    if shutil.which("valgrind") is None:
        print("valgrind is needed (apt install valgrind)", file=sys.stderr)
        return 2
    dirs = sorted(p.parent for p in Path(args.exports).glob("*/manifest.json"))
    if not dirs:
        print(f"no export directories under {args.exports}: run `thermbench export` first", file=sys.stderr)
        return 2
    exe = build("tb_replay", extra_flags=["-g"])
    rows = [one(d, args.seconds, exe) for d in dirs]
    if args.target:  # beside the host figures: the same stream on the emulated M4, float build
        import bench_target

        for row, d in zip(rows, dirs):
            t = bench_target.one(d, args.seconds, "float")
            row.update({f"m4f_{k}": t.get(k) for k in ("parity_um", "cycle_insn_max", "pred_insn_max", "arena_bytes",
                                                         "stack_bytes", "min_image_flash_bytes", "note")})  # fmt: skip
            row["m4f_over_budget"] = "; ".join(bench_target.over_budget(t))
    df = pd.DataFrame(rows)
    with pd.option_context("display.width", 200, "display.max_columns", 30, "display.float_format", "{:.0f}".format):
        print(df.to_string(index=False))
    print(f"\nbudget: file <= {FILE_BUDGET} B (MLR, classifier <= {SMALL_BUDGET} B), RAM <= {RAM_BUDGET} B, "
          f"physics update <= {PHYS_BUDGET} instructions; {int(df['within_budget'].sum())}/{len(df)} within")  # fmt: skip
    if args.target:
        print(f"m4f_*: the float build (-DTB_SINGLE) on the emulated Cortex-M4F, instructions counted by QEMU; budgets "
              f"cycle <= {bench_target.CYCLE_BUDGET} (physics update <= {bench_target.PHYS_BUDGET}), prediction <= "
              f"{bench_target.PRED_BUDGET}; at {bench_target.MHZ} MHz and an assumed {bench_target.CPI} cycles per "
              f"instruction, 100 000 instructions take {bench_target.ms(100_000):.2f} ms; "
              f"{int((df['m4f_over_budget'] == '').sum())}/{len(df)} within")  # fmt: skip
    out = Path(__file__).parent / "results" / "export_footprint.csv"
    write_text_atomic(out, df.to_csv(index=False))
    print(f"-> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
