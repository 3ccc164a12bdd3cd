"""The wheel works on its own: built from the source, installed with the core dependencies only into a
fresh venv outside the repository, and run from an empty directory (``simulate``, ``validate``, an MLR
``train``, ``export`` with the C runtime). Before, a non-editable install looked for ``conf/`` next to
site-packages and every command stopped at once. ``make core-check`` runs the same script in full."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_the_wheel_runs_simulate_validate_train_export_from_an_empty_directory(tmp_path):
    venv = tmp_path / "venv"
    p = subprocess.run([sys.executable, "-m", "tools.wheelcheck", "--venv", str(venv), "--quick"], cwd=ROOT,
                       capture_output=True, text=True, timeout=900)
    out = p.stdout + p.stderr
    assert p.returncode == 0, out[-4000:]
    site = next((venv / "lib").glob("python3*/site-packages"))
    # the package the commands ran is the wheel's, with its configuration and runtime sources inside it
    assert f"thermbench installed at {site / 'thermbench'}, with its conf/ and embedded/" in out
    assert (site / "thermbench" / "conf" / "simulate.yaml").is_file()
    assert (site / "thermbench" / "embedded" / "src" / "tb_runtime.c").is_file()
    assert not list(site.glob("__editable__*thermbench*")), "installed editable, not from the wheel"
    # a user's own copy of conf/ (THERMBENCH_CONFIG_DIR) with a machine option of theirs: refused without it, run with it
    assert "core-check: thermbench simulate machine=my_axis out_dir=mine: exit 2" in out
    assert "core-check: thermbench simulate machine=my_axis out_dir=mine: exit 0" in out
    assert "core-check: passed (quick)" in out
    # no extra came with the core
    assert not (site / "torch").exists() and not (site / "asyncua").exists()


def test_a_second_run_refuses_a_directory_it_did_not_make(tmp_path):
    mine = tmp_path / "venv"
    mine.mkdir()
    (mine / "keep.txt").write_text("a user's file")
    p = subprocess.run([sys.executable, "-m", "tools.wheelcheck", "--venv", str(mine), "--quick"], cwd=ROOT,
                       capture_output=True, text=True, timeout=300)
    assert p.returncode != 0 and "was not made by this command" in p.stderr
    assert (mine / "keep.txt").read_text() == "a user's file"
