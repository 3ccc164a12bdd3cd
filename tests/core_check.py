"""The core install, checked from its own venv (``make core-check``, through tools/wheelcheck.py, which
builds the wheel and installs it without extras into a fresh venv; the test suite runs the ``--quick``
part the same way in tests/test_wheel.py and checks the extras' messages with the optional modules
hidden: tests/test_extras.py).

Run by the Python of a venv holding thermbench's core and nothing else; ``--installed``: the wheel,
not a checkout (the package must find its configuration and C runtime inside itself). It checks that the
extras' packages are absent (torch above all), then runs what a core user runs, as a new user
would, in a scratch directory: ``thermbench simulate``, ``validate``, an MLR ``train`` (tracked
in the embedded MLflow store), ``export`` of the registered model for the C runtime and a small
``benchmark`` (which skips the neural family, saying which extra it needs). A
family or command that needs a missing extra must fail in one line, exit 2, naming the extra.
Prints one line per step with its wall time; exits 1 on the first failure.
"""

from __future__ import annotations

import importlib.util
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

BIN = Path(sys.executable).parent
ABSENT = {"torch": "neural", "onnx": "onnx", "onnxruntime": "onnx", "asyncua": "opcua", "submitit": "cluster",
          "papermill": "notebooks", "psycopg": "postgres"}  # fmt: skip


def run(args: list[str], cwd: Path, expect: int = 0, env: dict | None = None) -> str:
    t0 = time.perf_counter()
    p = subprocess.run([str(BIN / "thermbench"), *args], cwd=cwd, capture_output=True, text=True,
                       env=None if env is None else {**os.environ, **env})  # fmt: skip
    took = time.perf_counter() - t0
    if p.returncode != expect:
        sys.exit(f"core-check: `thermbench {' '.join(args)}` exited {p.returncode}, expected {expect}:\n"
                 f"{p.stdout[-3000:]}\n{p.stderr[-3000:]}")  # fmt: skip
    print(f"core-check: thermbench {' '.join(args)}: exit {p.returncode} in {took:.1f} s", flush=True)
    return p.stdout + p.stderr


def missing_extra(args: list[str], cwd: Path, extra: str) -> None:
    out = run(args, cwd, expect=2)
    lines = [ln for ln in out.splitlines() if ln.strip()]
    if len(lines) != 1 or f"'{extra}' extra" not in lines[0] or "Traceback" in out:
        sys.exit(f"core-check: `thermbench {' '.join(args)}` should say in one line to install the "
                 f"'{extra}' extra, got:\n{out}")  # fmt: skip
    print(f"core-check:   {lines[0]}")


def main(argv: list[str]) -> int:
    if "--installed" in argv:
        import thermbench
        from thermbench.config import config_dir
        from thermbench.export.runtime import embedded_dir

        pkg = Path(thermbench.__file__).resolve().parent
        for what, d in (("conf", config_dir()), ("embedded", embedded_dir())):
            if d.resolve() != pkg / what:
                sys.exit(f"core-check: the installed package should use its own {what}/ ({pkg / what}), uses {d}")
        print(f"core-check: thermbench installed at {pkg}, with its conf/ and embedded/")
    present = [m for m in ABSENT if importlib.util.find_spec(m) is not None]
    if present:
        sys.exit(f"core-check: the core install pulled in {present} (extras: {sorted({ABSENT[m] for m in present})})")
    print(f"core-check: none of {', '.join(ABSENT)} is installed")
    with tempfile.TemporaryDirectory(prefix="tb-core-") as tmp:
        cwd = Path(tmp)
        run(["simulate", "out_dir=ds"], cwd)
        run(["validate", "ds"], cwd)
        out = run(["train", "dataset=path", "dataset.source.path=ds", "train=cond1_3000", "model=mlr_seed002"], cwd)
        uri = re.search(r"registered: (models:/\S+)", out)
        if uri is None:
            sys.exit(f"core-check: train printed no registered model:\n{out}")
        run(["export", f"export.model_uri={uri.group(1)}", "export.out_dir=exp"], cwd)
        tbm = list((cwd / "exp").glob("*/model.tbm"))
        if len(tbm) != 1:
            sys.exit(f"core-check: export wrote {len(tbm)} model files under exp/")
        if "--installed" in argv:  # a user's own copy of conf/ with an option of theirs, by THERMBENCH_CONFIG_DIR
            import shutil

            from thermbench.config import config_dir

            mine = cwd / "myconf"
            shutil.copytree(config_dir(), mine)
            (mine / "machine" / "my_axis.yaml").write_text((mine / "machine" / "seed000_x.yaml").read_text())
            missing = run(["simulate", "machine=my_axis", "out_dir=mine"], cwd, expect=2)
            if "my_axis" not in missing:
                sys.exit(f"core-check: machine=my_axis should be unknown to the packaged conf/:\n{missing}")
            run(["simulate", "machine=my_axis", "out_dir=mine"], cwd,
                env={"THERMBENCH_CONFIG_DIR": str(mine)})  # fmt: skip
        if "--quick" in argv:
            print("core-check: passed (quick)")
            return 0
        missing_extra(["train", "dataset=path", "dataset.source.path=ds", "train=cond1_3000", "model=gru"], cwd, "neural")
        out = run(["benchmark", "name=core", "datasets=[seed001_vmc_x]", "families=[mlr_seed002,gru]",
                   "bank_families=[mlr_seed002]", "n_jobs=1"], cwd)  # fmt: skip
        skipped = [ln for ln in out.splitlines() if ln.startswith("[benchmark] skipped gru")]
        if len(skipped) != 1 or "'neural' extra" not in skipped[0] or not (cwd / "reports/core/report.md").is_file():
            sys.exit(f"core-check: the benchmark should skip gru in one line naming the 'neural' extra:\n{out[-3000:]}")
        print(f"core-check:   {skipped[0]}")
        missing_extra(["sim-cnc", "run=cond1_3000"], cwd, "opcua")
        missing_extra(["train", "-m", "hydra/launcher=submitit_local", "dataset=path", "dataset.source.path=ds",
                       "model=mlr_seed002", "train=cond1_3000,cond2_6000"], cwd, "cluster")  # fmt: skip
    print("core-check: passed")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
