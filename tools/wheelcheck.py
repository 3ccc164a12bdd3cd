"""The wheel, installed as a user installing a release would (``make core-check``; tests/test_wheel.py).

Builds thermbench's wheel from a copy of the tracked source (so nothing is written into the
checkout), creates a fresh venv outside the repository, installs the wheel with the core
dependencies only (no extras), and runs tests/core_check.py with that venv's Python from an empty
directory: ``simulate``, ``validate``, an MLR ``train`` and ``export`` (``--quick``), and in full the
extras' one-line messages and a small benchmark too. The installed package must be the wheel's,
not the checkout's: it finds ``conf/`` and ``embedded/`` inside itself.

    python -m tools.wheelcheck --venv .venv-core [--quick] [--keep]
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
# what a wheel is built from (setup.py copies conf/ and embedded/ into the package)
SOURCE = ("pyproject.toml", "setup.py", "MANIFEST.in", "README.md", "thermbench", "conf", "embedded")


def _run(cmd: list[str], **kw) -> None:
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, **kw)
    print(f"wheelcheck: {' '.join(str(c) for c in cmd[:4])} ... in {time.perf_counter() - t0:.1f} s", flush=True)


def build_wheel(out_dir: Path) -> Path:
    """The wheel, built from a copy of the source tree in a scratch directory."""
    with tempfile.TemporaryDirectory(prefix="tb-wheel-src-") as tmp:
        src = Path(tmp) / "thermbench-src"
        src.mkdir()
        for name in SOURCE:
            p = ROOT / name
            if p.is_dir():
                shutil.copytree(p, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info"))
            else:
                shutil.copy2(p, src / name)
        _run([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "-w", str(out_dir), str(src)])
    wheels = sorted(out_dir.glob("thermbench-*.whl"))
    if len(wheels) != 1:
        sys.exit(f"wheelcheck: expected one wheel in {out_dir}, found {[w.name for w in wheels]}")
    return wheels[0]


MARK = ".thermbench-wheelcheck"  # a venv this command made, and may make anew


def _check_venv_dir(venv: Path) -> None:
    if venv.exists() and not (venv / MARK).exists():
        sys.exit(f"wheelcheck: {venv} exists and was not made by this command; name a new directory (one an older "
                 "`make core-check` made with pip install -e: remove it yourself)")


def install(wheel: Path, venv: Path) -> Path:
    """A fresh venv at ``venv`` with the wheel and its core dependencies; its Python. A venv this
    command made before is made anew; any other existing directory is refused, never removed."""
    _check_venv_dir(venv)
    if venv.exists():
        shutil.rmtree(venv)
    _run([sys.executable, "-m", "venv", str(venv)])
    (venv / MARK).write_text("made by tools/wheelcheck.py\n", encoding="utf-8")
    py = venv / "bin" / "python"
    env = {**os.environ, "PIP_CONSTRAINT": str(ROOT / "constraints.txt"), "PIP_DISABLE_PIP_VERSION_CHECK": "1"}
    _run([str(py), "-m", "pip", "install", "-q", "--no-compile", str(wheel)], env=env)
    return py


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--venv", type=Path, required=True, help="where the fresh venv goes (a new directory, or one this command made)")
    ap.add_argument("--quick", action="store_true", help="simulate, validate, train, export only")
    args = ap.parse_args(argv)
    venv = args.venv.resolve()
    _check_venv_dir(venv)
    with tempfile.TemporaryDirectory(prefix="tb-wheel-") as tmp:
        wheel = build_wheel(Path(tmp))
        py = install(wheel, venv)
    with tempfile.TemporaryDirectory(prefix="tb-wheel-run-") as empty:
        env = {k: v for k, v in os.environ.items() if k not in ("THERMBENCH_CONFIG_DIR", "THERMBENCH_EMBEDDED_DIR", "PYTHONPATH")}
        cmd = [str(py), str(ROOT / "tests" / "core_check.py"), "--installed"] + (["--quick"] if args.quick else [])
        return subprocess.run(cmd, cwd=empty, env=env).returncode


if __name__ == "__main__":
    raise SystemExit(main())
