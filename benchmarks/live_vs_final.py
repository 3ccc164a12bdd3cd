"""What the live compensator writes against the model's final values, per export.

For every export directory under EXPORTS whose name contains ``--only`` (default: the physics
models), over every parity run of its manifest, at every process sample, in the C runtime:

* ``final``: each query answered once its value is final (tb_replay; what the export's parity
  check compares with Python and what the benchmark scores);
* ``live``: each query answered with the log up to its own time (tb_replay --live; what the
  compensator writes, cycle by cycle, and what ``thermbench replay`` scores);
* ``hold``: the final value at the last macro-step boundary at or before t (what earlier
  versions of the compensator wrote, asking for the model's last final time).

Printed: max and RMS of |live - final| and |hold - final| over all samples.

    .venv/bin/python benchmarks/live_vs_final.py [EXPORTS] [--only physics]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
import pandas as pd

from thermbench.data.io import load_dataset
from thermbench.export import read_manifest
from thermbench.export.directory import replay_dir
from thermbench.export.samples import process_samples
from thermbench.export.replay import replay_view


def one(model_dir: Path) -> dict:
    man = read_manifest(model_dir)
    full = load_dataset(man["training"]["dataset"])
    live_d, hold_d = [], []
    for run in man["parity"]["runs"]:
        ds = replay_view(full, man, run, None, Path(man["training"]["dataset"])) if full.metadata.version == 2 else full
        s = process_samples(ds, run)
        q = pd.DataFrame({"t_s": s["t_s"].to_numpy(), "axis_mm": s["axis_mm"].to_numpy()})
        final = replay_dir(model_dir, ds, run, q)["total_um"].to_numpy()
        live = replay_dir(model_dir, ds, run, q, live=True)
        ok = (live["rc"] == 0).to_numpy()
        live_d.append(np.abs(live["total_um"].to_numpy()[ok] - final[ok]))
        if man["kind"] == "PHYSICS":
            macro_s = float(man.get("physics", {}).get("macro_dt_s", 10.0))
            t0 = q["t_s"].iloc[0]
            at = t0 + np.floor((q["t_s"] - t0) / macro_s + 1e-9) * macro_s
            hold = replay_dir(model_dir, ds, run, q.assign(t_s=at))["total_um"].to_numpy()
            hold_d.append(np.abs(hold[ok] - final[ok]))
    out = {"model": man["name"], "kind": man["kind"], "samples": int(sum(d.size for d in live_d))}
    for name, parts in (("live", live_d), ("hold", hold_d)):
        if parts:
            d = np.concatenate(parts)
            out[f"{name}_max_um"], out[f"{name}_rms_um"] = float(d.max()), float(np.sqrt(np.mean(d**2)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("exports", nargs="?", default="exports/benchmark")
    ap.add_argument("--only", default="physics", help="only export directories whose name contains this")
    args = ap.parse_args(argv)
    dirs = sorted(p.parent for p in Path(args.exports).glob("*/manifest.json") if args.only in p.parent.name)
    if not dirs:
        print(f"no export directories matching {args.only!r} under {args.exports}", file=sys.stderr)
        return 2
    rows = [one(d) for d in dirs]
    with pd.option_context("display.width", 200, "display.float_format", "{:.3g}".format):
        print(pd.DataFrame(rows).to_string(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
