"""tools/stress.sh (make stress): runs the real-time tests N times beside K busy loops and prints
how many runs each test passed; checked here on stand-in tests whose outcomes are known."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

STAND_IN = '''
import os, pathlib, pytest


@pytest.mark.timing
def test_always():
    pass


@pytest.mark.timing
def test_every_other_run():  # fails on runs 1 and 3 of 3
    n = pathlib.Path(os.environ["COUNTER"])
    k = int(n.read_text()) if n.exists() else 0
    n.write_text(str(k + 1))
    assert k % 2 == 1, f"run {k + 1} fails"


@pytest.mark.realtime
def test_realtime_marker_counts_too():
    pass


@pytest.mark.slow
def test_not_real_time():  # deselected: not a real-time test
    raise AssertionError("not to be run")
'''


def test_stress_counts_passes_per_test_and_fails_when_one_did_not_pass_every_run(tmp_path):
    (tmp_path / "test_standin.py").write_text(STAND_IN)
    env = {"COUNTER": str(tmp_path / "counter"), "STRESS_OUT": str(tmp_path / "out"), "PYTHON": sys.executable,
           "PATH": "/usr/bin:/bin"}  # fmt: skip
    p = subprocess.run(["bash", str(ROOT / "tools" / "stress.sh"), "3", "1", str(tmp_path / "test_standin.py")],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert p.returncode == 1, p.stdout + p.stderr  # one test did not pass every run
    rows = {ln.split()[0]: ln.split()[1:] for ln in p.stdout.splitlines() if "::test_" in ln}
    assert rows == {"test_standin::test_always": ["3", "/", "3"], "test_standin::test_every_other_run": ["1", "/", "3"],
                    "test_standin::test_realtime_marker_counts_too": ["3", "/", "3"]}, p.stdout  # fmt: skip
    assert p.stdout.count("run 1 fails") == 1 and p.stdout.count("run 3 fails") == 1  # each failure's first line
    assert len(list((tmp_path / "out").glob("*/run*.xml"))) == 3
    # all passing: exit 0
    (tmp_path / "test_standin.py").write_text(STAND_IN.replace("assert k % 2 == 1", "assert k >= 0"))
    p = subprocess.run(["bash", str(ROOT / "tools" / "stress.sh"), "2", "1", str(tmp_path / "test_standin.py")],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=300)  # fmt: skip
    assert p.returncode == 0 and "2 / 2" in p.stdout, p.stdout + p.stderr
    p = subprocess.run(["bash", str(ROOT / "tools" / "stress.sh"), "x"], cwd=ROOT, env=env, capture_output=True, text=True)
    assert p.returncode == 2 and "N and K are whole numbers" in p.stderr
