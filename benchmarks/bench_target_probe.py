"""The probe filter and the extrapolation guard on the target: the Cortex-M4F emulated by QEMU.

An MLR model of ``seed001_vmc_x`` (seed 002's, fitted on its five loading states and exported with
its training envelope, ``envelope.tbm``; or the export directory EXPORT) runs on the emulated M4
(``thermbench.export.target``, the harness ``embedded/target/tb_target_main.c``) over ``valid1``
as the compensator runs it: live, the envelope linked into flash beside the model and followed by
``tb_guard_step`` after every sample's ``tb_model_step``, a probe reading every EVERY seconds
(the first reading of each interval; ``tb_probe_update`` after a prediction at its time) and every
other reading answered and corrected (``tb_probe_correct`` after its prediction). Printed, per build:

* instructions per call of ``tb_probe_update``, ``tb_probe_correct`` and ``tb_guard_step`` (and of
  the model's step and prediction beside them), mean and worst, counted under ``-icount shift=3``:
  the SysTick ticks every 5 instructions (every 40 under the default shift=0 of bench_target.py),
  checked on a loop of 100 000 in every run; counts are deterministic, so the figures are the median
  of RUNS runs after a warm-up run and their spread (max - min) is printed, which should be 0;
* the deepest stack of each call as the harness measures it (the stack is painted before the call
  and read after it; the depth counts from the harness's frame and includes the few words of its
  own marker calls: an upper bound for a leaf function) and each function's own frame as gcc
  ``-fstack-usage`` reports it for the target;
* RAM: ``sizeof(tb_probe_state)`` and ``sizeof(tb_guard)`` on the target, and with the model's
  handle and arena against the 16 KB per-model budget (thermbench.export.budget.TARGETS); the control
  cycle (step + guard) against 100 000 instructions and a prediction + correction against 200 000;
* parity against the host's double ``tb_replay --live --probe --guard`` over the same stream:
  max |corrected|, |variance| and the guard's distance (relative beyond 0.01 of a range's width).

Each with the export's envelope (valid1 stays inside it) and with a narrow one (NARROW's loading
state alone, the feed an operating input: 5 inputs instead of 4, and valid1 leaves it).

Writes benchmarks/results/target_probe.csv.

    .venv/bin/python benchmarks/bench_target_probe.py [EXPORT] [--every 600] [--runs 5] [--precision float|double|both]
                                                      [--narrow state2]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pandas as pd

from thermbench.outputs import write_text_atomic
from thermbench.export import runtime, target
from thermbench.export.budget import TARGETS
from thermbench.export.directory import replay_inputs
from thermbench.export.samples import readings_queries

RUN = "valid1"
STATES = ["state1", "state2", "state3", "state4", "state5"]
OPS = ("step", "guard_step", "predict", "probe_update", "probe_correct")
FRAMES = ("tb_probe.c:tb_probe_update", "tb_probe.c:tb_probe_correct", "tb_guard.c:tb_guard_step")
_B = TARGETS["cortex-m4f"]["budget"]
MHZ, CPI = 168, 1.25  # seed 002's STM32F407; cycles per instruction assumed (QEMU counts instructions)


def export_dir(ds, out: Path) -> Path:
    """seed 002's MLR on the five loading states, exported (with its envelope) to ``out``."""
    from thermbench.export import export_model
    from thermbench.models.mlr import MLRSeed002

    export_model(MLRSeed002().fit(ds, STATES), out, "mlr", ds, [RUN])
    return out


def probe_readings(ds, every_s: float) -> tuple[pd.DataFrame, pd.DataFrame]:
    """(the queries: the readings that are not probes, the probes: the first reading of each
    ``every_s`` interval, its measured error the probe's reading)."""
    er = ds.errors_run(RUN).sort_values("t_s", kind="stable").reset_index(drop=True)
    slot = np.floor(er["t_s"].to_numpy(float) / every_s)
    first = np.r_[True, slot[1:] != slot[:-1]]
    probes = pd.DataFrame({"t_s": er["t_s"][first], "axis_mm": er["target_mm"][first], "measured_um": er["error_um"][first]})
    q = readings_queries(ds, RUN)
    q = q[~q["t_s"].isin(probes["t_s"])].reset_index(drop=True)
    return q, probes.reset_index(drop=True)


def narrow_envelope(ds, model_dir: Path, state: str, out: Path) -> Path:
    """The envelope of loading state ``state`` alone over the model's sensors, the feed an operating
    input (tests/test_target_probe.py's): valid1 leaves it and comes back."""
    from thermbench.export import read_manifest
    from thermbench.export.guard import write_envelope
    from thermbench.bench.intervals import Envelope

    write_envelope(out, Envelope.fit(ds, [state], read_manifest(model_dir)["temperatures"], ["feed_mm_min"]), 600.0)
    return out


def one(model_dir: Path, ds, precision: str, every_s: float, n_runs: int, guard: Path, operating=(), label="") -> dict:
    from thermbench.bench.adapt import ProbeParams

    params = ProbeParams()  # the compensator's defaults (conf/compensator.yaml's probe block)
    files, samples, temps, bank = replay_inputs(model_dir, ds, RUN)
    temps = [*temps, *operating]
    q, probes = probe_readings(ds, every_s)
    kw = dict(live=True, probes=probes, probe_params=params, guard=guard)
    host = runtime.replay(files, samples, temps, q, bank=bank, **kw)
    reps, walls = [], []
    for i in range(n_runs + 1):  # the first: the warm-up (builds and caches the image)
        t0 = time.perf_counter()
        got, rep = target.replay(files, samples, temps, q, precision=precision, icount_shift=3, **kw)
        if rep["rc"] != 0:
            raise SystemExit(f"the firmware stopped: {rep['end']}")
        if i:
            reps.append(rep)
            walls.append(time.perf_counter() - t0)
    ok = (host["rc"] == 0).to_numpy() & (got["rc"] == 0).to_numpy()
    want, dist = host["distance"].to_numpy(), got["distance"].to_numpy()
    far = ok & (want > 1e-2)
    row = {"precision": precision, "envelope": label, "queries": len(q), "probes": len(probes), "samples": len(samples),
           "probes_taken": reps[0]["probes_taken"], "outside_share": float((want[ok] > 0).mean()),
           "parity_corrected_um": float(np.abs(got["corrected_um"] - host["corrected_um"])[ok].max()),
           "parity_var_um2": float(np.abs(got["var_um2"] - host["var_um2"])[ok].max()),
           "parity_distance_abs": float(np.abs(dist - want)[ok].max()),
           "parity_distance_rel": float((np.abs(dist[far] - want[far]) / want[far]).max()) if far.any() else float("nan"),
           "calibration_insn": statistics.median(r["calibrate_insn_max"] for r in reps),
           "wall_s_per_run": statistics.median(walls)}  # fmt: skip
    for op in OPS:
        for what in ("calls", "insn_mean", "insn_max", "stack_bytes"):
            vals = [r[f"{op}_{what}"] for r in reps]
            row[f"{op}_{what}"] = statistics.median(vals)
            row[f"{op}_{what}_spread"] = max(vals) - min(vals)
    for k in ("sizeof_tb_model", "sizeof_tb_probe_state", "sizeof_tb_guard", "arena_bytes", "stack_bytes"):
        row[k] = reps[0][k]
    frames = target.stack_frames(precision)
    for f in FRAMES:
        row[f"frame_{f.split(':')[1]}"] = frames.get(f)
    row["ram_bytes"] = row["arena_bytes"] + row["sizeof_tb_model"] + row["sizeof_tb_probe_state"] + row["sizeof_tb_guard"]
    row["cycle_insn_max"] = row["step_insn_max"] + row["guard_step_insn_max"]
    row["answer_insn_max"] = row["predict_insn_max"] + row["probe_correct_insn_max"]
    return row


def report(r: dict) -> None:
    ms = lambda insn: insn * CPI / (MHZ * 1e3)  # noqa: E731
    print(f"\n{r['precision']} build, {r['envelope']}: {r['samples']} samples, {r['queries']} queries, {r['probes']} probes "
          f"({r['probes_taken']} taken), {100 * r['outside_share']:.0f} % of the answers outside the envelope; "
          f"calibration loop {r['calibration_insn']:.0f} / 100000 instructions; {r['wall_s_per_run']:.2f} s per QEMU run")  # fmt: skip
    print(f"  {'call':<14s} {'calls':>6s} {'insn mean':>10s} {'insn max':>9s} {'max ms':>7s} {'stack B':>8s} {'frame B':>8s} spread")
    for op in OPS:
        frame = r.get(f"frame_tb_{op}")  # gcc's own frame: the probe and guard calls
        spread = max(r[f"{op}_{w}_spread"] for w in ("calls", "insn_mean", "insn_max", "stack_bytes"))
        print(f"  {op:<14s} {r[f'{op}_calls']:>6.0f} {r[f'{op}_insn_mean']:>10.1f} {r[f'{op}_insn_max']:>9.0f} "
              f"{ms(r[f'{op}_insn_max']):>7.4f} {r[f'{op}_stack_bytes']:>8.0f} {'' if frame is None else frame:>8} {spread:g}")  # fmt: skip
    print(f"  RAM on the target: tb_probe_state {r['sizeof_tb_probe_state']} B, tb_guard {r['sizeof_tb_guard']} B; with the "
          f"model (tb_model {r['sizeof_tb_model']} B, arena {r['arena_bytes']} B) {r['ram_bytes']} B of {_B['ram_bytes']} B")  # fmt: skip
    print(f"  control cycle (step + guard) worst {r['cycle_insn_max']:.0f} of {_B['cycle_insn']} instructions; "
          f"prediction + correction worst {r['answer_insn_max']:.0f} of {_B['prediction_insn']}; deepest stack of any "
          f"call {r['stack_bytes']} B of the 8 KB")  # fmt: skip
    far = "all inside" if np.isnan(r["parity_distance_rel"]) else f"{r['parity_distance_rel']:.2e} relative beyond 0.01 /"
    print(f"  vs the host's double build: corrected {r['parity_corrected_um']:.2e} um, variance {r['parity_var_um2']:.2e} um^2, "
          f"distance {far} {r['parity_distance_abs']:.2e} absolute")  # fmt: skip
    over = [w for w, v, lim in (("RAM", r["ram_bytes"], _B["ram_bytes"]), ("cycle", r["cycle_insn_max"], _B["cycle_insn"]),
                                ("prediction", r["answer_insn_max"], _B["prediction_insn"])) if v > lim]  # fmt: skip
    if r["precision"] == "float":
        print("  within the cortex-m4f budgets" if not over else f"  OVER the budget: {', '.join(over)}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("export", nargs="?", default=None, help="an export directory of seed001_vmc_x (default: fit and export one)")
    ap.add_argument("--data", default=None, help="the benchmark datasets' root (default: thermbench's)")
    ap.add_argument("--every", type=float, default=600.0, help="seconds between probe readings")
    ap.add_argument("--runs", type=int, default=5, help="measured runs after the warm-up")
    ap.add_argument("--precision", choices=("float", "double", "both"), default="float")
    ap.add_argument("--narrow", default="state2", help="also a narrow envelope: this loading state's alone, the feed as an "
                                                      "operating input ('' for none)")  # fmt: skip
    args = ap.parse_args(argv)
    try:
        target.toolchain()
    except runtime.RuntimeUnavailable as exc:
        print(exc, file=sys.stderr)
        return 2
    from thermbench.bench.datasets import load_benchmark

    ds = load_benchmark("seed001_vmc_x", args.data)
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_target_probe_") as tmp:
        model_dir = Path(args.export) if args.export else export_dir(ds, Path(tmp) / "mlr")
        guards = [(model_dir / "envelope.tbm", (), "the export's envelope")]
        if args.narrow:
            guards.append((narrow_envelope(ds, model_dir, args.narrow, Path(tmp) / "narrow.tbm"), ("feed_mm_min",),
                           f"{args.narrow}'s envelope with the feed"))  # fmt: skip
        for precision in ("float", "double") if args.precision == "both" else (args.precision,):
            for guard, operating, label in guards:
                rows.append(one(model_dir, ds, precision, args.every, args.runs, guard, operating, label))
                report(rows[-1])
    out = Path(__file__).parent / "results" / "target_probe.csv"
    write_text_atomic(out, pd.DataFrame(rows).to_csv(index=False))
    print(f"\nmedian of {args.runs} runs after a warm-up; milliseconds at {MHZ} MHz assuming {CPI} cycles per instruction -> {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
