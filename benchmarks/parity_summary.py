"""The export parity of every model under EXPORTS (default ``exports/benchmark/``), per family.

Read from each ``manifest.json`` (written by ``thermbench export``'s parity check, which runs the
C runtime over every parity run of the model): per family and file variant, over all its exports,

* ``double_vs_python_um``: max |host double build - Python| at the interferometer readings of the
  parity runs (the export tolerance is 0.01 um);
* ``float_vs_python_um``: the same for the single-precision build;
* ``float_vs_double_um``: max |float - double| at **every process sample** of every parity run
  (classifier grid times, macro-step boundaries, the streams' ends among them), and the number of
  samples compared.

The emulated Cortex-M4F's own figures (float against the host's double at every sample, bank labels,
instructions) are ``bench_target.py``'s.

    .venv/bin/python benchmarks/parity_summary.py [EXPORTS]
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import pandas as pd


def rows(exports: Path) -> pd.DataFrame:
    out = []
    for path in sorted(exports.glob("*/manifest.json")):
        man = json.loads(path.read_text())
        family = man["name"].split("__")[1] if "__" in man["name"] else man["name"]
        family += " bank" if man["kind"] == "bank" else ""
        for variant, p in man.get("parity", {}).items():
            if not isinstance(p, dict) or "max_abs_diff_um" not in p:
                continue
            out.append({"family": family if variant == "model" else f"{family} ({variant})", "export": man["name"],
                        "double_vs_python_um": p["max_abs_diff_um"], "float_vs_python_um": p.get("float_max_abs_diff_um"),
                        "float_vs_double_um": p.get("float_vs_double_every_sample_max_abs_um"),
                        "samples": p.get("n_samples", 0), "readings": p.get("n_readings", 0)})  # fmt: skip
    return pd.DataFrame(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("exports", nargs="?", default="exports/benchmark")
    args = ap.parse_args(argv)
    df = rows(Path(args.exports))
    if df.empty:
        print(f"no export manifests under {args.exports}: run `thermbench export` first", file=sys.stderr)
        return 2
    agg = df.groupby("family").agg(exports=("export", "size"), double_vs_python_um=("double_vs_python_um", "max"),
                                   float_vs_python_um=("float_vs_python_um", "max"),
                                   float_vs_double_um=("float_vs_double_um", "max"), samples=("samples", "sum"),
                                   readings=("readings", "sum"))  # fmt: skip
    with pd.option_context("display.width", 200, "display.float_format", "{:.2g}".format):
        print(agg.to_string())
    return 0


if __name__ == "__main__":
    sys.exit(main())
