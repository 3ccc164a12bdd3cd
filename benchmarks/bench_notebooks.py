"""Wall time of each guided notebook (kernel start included), as the test suite runs them.

Each notebook runs once as a warm-up (datasets built, C runtime compiled, caches filled), then
``--repeat`` times; the median is printed against the budget of 60 s per notebook.

    .venv/bin/python benchmarks/bench_notebooks.py              # QUICK=True (the test settings)
    .venv/bin/python benchmarks/bench_notebooks.py --full 01    # full settings, one notebook
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tools/ lives in the source tree, not installed

from thermbench.bench import datasets  # noqa: E402
from tools import nbrun  # noqa: E402

BUDGET_S = 60.0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("names", nargs="*", help="notebook numbers (default: all)")
    ap.add_argument("--full", action="store_true", help="full settings instead of QUICK=True")
    ap.add_argument("--repeat", type=int, default=3)
    a = ap.parse_args(argv)
    paths = [p for p in nbrun.notebook_paths() if not a.names or any(p.stem.startswith(n) for n in a.names)]
    if not paths:
        print(f"no notebook matches {a.names}", file=sys.stderr)
        return 2
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "benchmark"
        datasets.build("seed001_vmc_x", root)  # as the tests' session fixture does
        print(f"{'notebook':<28} {'median_s':>9} {'min_s':>7} {'max_s':>7} figures  budget {BUDGET_S:.0f} s")
        for p in paths:
            params = {"OUT_DIR": str(Path(tmp) / p.stem), "DATA_ROOT": str(root)}
            if not a.full:
                params["QUICK"] = True
            timeout_s = None if a.full else 120.0
            nb, _ = nbrun.run_notebook(p, params, timeout_s)  # warm-up
            times = [nbrun.run_notebook(p, params, timeout_s)[1] for _ in range(a.repeat)]
            med = statistics.median(times)
            flag = "" if med < BUDGET_S else "  OVER BUDGET"
            print(f"{p.stem:<28} {med:9.1f} {min(times):7.1f} {max(times):7.1f} {nbrun.images(nb):7d}{flag}", flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
