"""Install size and time of thermbench: a fresh venv per install, as `make` does it.

    python benchmarks/bench_install.py                       # the core of this checkout
    python benchmarks/bench_install.py --extras neural,onnx  # what make demo installs
    python benchmarks/bench_install.py --ref 6a5da5a         # the core of an older commit (git worktree)
    python benchmarks/bench_install.py --repeat 3            # median of 3 installs

Each install: ``python -m venv``, then ``pip install -c constraints.txt -e .[extras]`` from the
checkout (the same pip configuration and package indexes as `make`), timed by wall clock; then
the venv's size on disk (du) and its number of installed distributions, and whether torch is
among them. Installs are minutes long and use the network or the local wheel cache, so the figure
depends on the machine: compare two revisions on the same machine, one after the other.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def du_mb(path: Path) -> float:
    total = 0
    for dirpath, _, files in os.walk(path):
        for f in files:
            p = Path(dirpath) / f
            if not p.is_symlink():
                total += p.stat().st_blocks * 512
    return total / 1e6


def install_once(src: Path, extras: str) -> dict:
    with tempfile.TemporaryDirectory(prefix="tb-install-") as tmp:
        venv = Path(tmp) / "venv"
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
        py = venv / "bin" / "python"
        spec = f".[{extras}]" if extras else "."
        env = {**os.environ, "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
        subprocess.run([str(py), "-m", "pip", "install", "-q", "-c", "constraints.txt", "-e", spec], cwd=src, env=env,
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
        took = time.perf_counter() - t0
        dists = subprocess.run([str(py), "-m", "pip", "list", "--format=freeze"], capture_output=True, text=True,
                               env=env, check=True).stdout.split()  # fmt: skip
        return {"s": took, "mb": du_mb(venv), "n": len(dists),
                "torch": any(d.lower().startswith("torch==") for d in dists)}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--extras", default="", help="comma-separated extras, e.g. neural,onnx (default: the core)")
    ap.add_argument("--ref", default=None, help="a git revision to install instead of the working tree")
    ap.add_argument("--repeat", type=int, default=1)
    a = ap.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="tb-ref-") as tmp:
        src = ROOT
        if a.ref:
            src = Path(tmp) / "src"
            subprocess.run(["git", "-C", str(ROOT), "worktree", "add", "--detach", "-q", str(src), a.ref], check=True)
        try:
            runs = [install_once(src, a.extras) for _ in range(a.repeat)]
        finally:
            if a.ref:
                subprocess.run(["git", "-C", str(ROOT), "worktree", "remove", "--force", str(src)], check=False)
    what = f"{a.ref or 'working tree'} [{a.extras or 'core'}]"
    each = ", ".join(f"{r['s']:.0f}" for r in runs)
    print(f"install {what}: {statistics.median(r['s'] for r in runs):.0f} s (median of {len(runs)}; {each}), "
          f"{statistics.median(r['mb'] for r in runs):.0f} MB in the venv, "
          f"{runs[0]['n']} distributions, torch {'installed' if runs[0]['torch'] else 'not installed'}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
