"""A family or command whose extra is missing says in one line which extra to install
(thermbench.errors). The real core install is checked by ``make core-check`` in its own venv
(tests/core_check.py); here the optional modules are hidden from a subprocess by an
import hook, so the same messages are checked in the test suite."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

from thermbench.errors import UserError
from thermbench.errors import EXTRAS, MissingExtra, require

HIDE = textwrap.dedent("""
    import importlib.abc, sys
    HIDDEN = {hidden!r}
    class Hide(importlib.abc.MetaPathFinder):
        def find_spec(self, name, path=None, target=None):
            if name.split(".")[0] in HIDDEN:
                raise ModuleNotFoundError(f"No module named {{name!r}}", name=name)
    sys.meta_path.insert(0, Hide())
    from thermbench.cli import main
    sys.exit(main({argv!r}))
""")


def run_without(hidden: set[str], argv: list[str], cwd) -> subprocess.CompletedProcess:
    code = HIDE.format(hidden=sorted(hidden), argv=argv)
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)


def test_require_names_the_extra_and_is_a_user_error(monkeypatch):
    monkeypatch.setitem(EXTRAS, "tb_no_such_module", "neural")
    with pytest.raises(MissingExtra) as exc:
        require("tb_no_such_module", "the test family")
    msg = str(exc.value)
    assert "tb_no_such_module is not installed (needed by the test family)" in msg
    assert "'neural' extra" in msg and "pip install 'thermbench[neural]'" in msg and "\n" not in msg
    assert isinstance(exc.value, UserError) and isinstance(exc.value, ImportError)


def test_require_returns_the_module_and_leaves_other_import_errors_alone():
    import json

    assert require("json", "anyone") is json
    with pytest.raises(ModuleNotFoundError) as exc:  # not an optional module: a plain error, a bug to see
        require("tb_not_optional_at_all", "anyone")
    assert not isinstance(exc.value, MissingExtra)


def test_every_extra_named_is_an_extra_of_pyproject():
    import tomllib
    from pathlib import Path

    pyproject = tomllib.loads((Path(__file__).resolve().parents[1] / "pyproject.toml").read_text(encoding="utf-8"))
    extras = pyproject["project"]["optional-dependencies"]
    assert set(EXTRAS.values()) <= set(extras)
    core = " ".join(pyproject["project"]["dependencies"]).lower()
    for module in ("torch", "onnx", "asyncua", "submitit", "papermill", "psycopg"):
        assert module not in core, f"{module} is in the core dependencies"
    assert any(d.startswith("torch") for d in extras["neural"])
    named = extras["all"][0]
    assert len(extras["all"]) == 1 and named.startswith("thermbench[")
    assert {e for e in extras if e not in ("all", "dev")} == set(named.split("[", 1)[1].rstrip("]").split(","))


def test_a_neural_family_without_torch_is_one_line_naming_the_neural_extra(tmp_path, seed001_data_root, monkeypatch):
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    p = run_without({"torch"}, ["train", "model=gru", "train=state1", f"tracking.uri=sqlite:///{tmp_path}/m.db",
                                f"hydra.run.dir={tmp_path}/run"], tmp_path)  # fmt: skip
    assert p.returncode == 2, p.stderr[-3000:]
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Traceback" not in p.stderr
    assert lines[0].startswith("thermbench train: error: config key 'model._target_'")
    assert "torch is not installed" in lines[0] and "'neural' extra" in lines[0]


def test_the_benchmark_without_torch_skips_the_neural_families_in_one_line(tmp_path):
    code = HIDE.split("from thermbench.cli")[0].format(hidden=["torch"], argv=[]) + (
        "from thermbench.bench import family_lacks, reference_only\n"
        "print(family_lacks('gru', None)); print(family_lacks('bank_mlr_seed002', None)); print(reference_only('mlp'))\n")
    p = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert p.returncode == 0, p.stderr[-3000:]
    gru, bank, ref = p.stdout.splitlines()
    assert gru.startswith("torch is not installed (needed by the neural families MLP and GRU); the 'neural' extra")
    assert bank == "None" and ref == "False"  # a family that needs no extra lacks nothing here


def test_an_mlr_trains_without_torch(tmp_path, seed001_data_root, monkeypatch):
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    p = run_without({"torch", "onnx", "onnxruntime", "asyncua"},
                    ["train", "model=mlr_seed002", "train=state1", "eval=valid1", f"tracking.uri=sqlite:///{tmp_path}/m.db",
                     f"tracking.artifact_root={tmp_path}/art", f"hydra.run.dir={tmp_path}/run"], tmp_path)  # fmt: skip
    assert p.returncode == 0, p.stderr[-3000:]
    assert "registered: models:/" in p.stdout


@pytest.mark.parametrize("argv", [["sim-cnc"], ["certs", "x"]])
def test_an_opcua_command_without_asyncua_is_one_line_naming_the_opcua_extra(tmp_path, argv):
    p = run_without({"asyncua"}, argv, tmp_path)
    assert p.returncode == 2, p.stderr[-3000:]
    lines = [ln for ln in p.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "asyncua is not installed" in lines[0] and "'opcua' extra" in lines[0], p.stderr
    assert not (tmp_path / "x").exists()
