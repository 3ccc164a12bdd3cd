"""The guided notebooks (notebooks/NN_*.py, jupytext percent format) run end to end.

Each is executed in a real Jupyter kernel with its small settings (``QUICK=True``), a scratch
``OUT_DIR`` and a benchmark root that holds seed001_vmc_x (prebuilt once per session). A notebook
fails the test when any cell raises, including the ``assert`` with which each notebook checks its
own claim, and when it shows no figure.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

from tools import nbrun

NOTEBOOKS = nbrun.notebook_paths()
EXPECTED = ["01_quickstart", "02_robustness", "03_discrepancy", "04_export_replay", "05_your_measurements"]


def test_the_five_guided_notebooks_are_there_as_jupytext_percent_files():
    assert [p.stem for p in NOTEBOOKS] == EXPECTED
    for p in NOTEBOOKS:
        ast.parse(p.read_text(encoding="utf-8"), p.name)  # a plain Python file too: every prose line commented
        nb = nbrun.read_notebook(p)
        assert nb.metadata["kernelspec"]["name"] == "python3", p.name
        assert nb.metadata["jupytext"]["formats"] == "py:percent", p.name
        assert sum(c.cell_type == "markdown" for c in nb.cells) >= 3, f"{p.name}: a guide needs prose"
    # output-free in the repository: no executed .ipynb beside the .py files
    assert not list(nbrun.notebooks_dir().glob("*.ipynb"))


@pytest.mark.parametrize("path", NOTEBOOKS, ids=[p.stem for p in NOTEBOOKS])
def test_notebook_runs_with_small_settings_and_shows_its_plots(path: Path, tmp_path, seed001_data_root, monkeypatch):
    # the kernel inherits the environment: no MLflow store or dataset may land in the repository
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    monkeypatch.setenv("MPLBACKEND", "Agg")  # as many CI machines set it: the figures must still show
    nb, _ = nbrun.run_notebook(
        path, {"QUICK": True, "OUT_DIR": str(tmp_path / "out"), "DATA_ROOT": str(seed001_data_root)}, cell_timeout_s=60
    )
    assert nbrun.images(nb) >= 2, f"{path.name} shows {nbrun.images(nb)} figure(s)"
    assert any("injected-parameters" in c.metadata.get("tags", []) for c in nb.cells)


def test_parameters_must_exist_in_the_parameters_cell(tmp_path):
    src = '# %% tags=["parameters"]\nQUICK = False\n\n# %%\nprint(QUICK)\n'
    p = tmp_path / "99_x.py"
    p.write_text(src)
    nb = nbrun.with_parameters(nbrun.read_notebook(p), {"QUICK": True})
    assert nb.cells[1].source.endswith("QUICK = True")
    with pytest.raises(nbrun.NotebookError, match="QUICKK"):
        nbrun.with_parameters(nbrun.read_notebook(p), {"QUICKK": True}, p.name)
    p.write_text("# %%\nprint(1)\n")
    with pytest.raises(nbrun.NotebookError, match="tagged 'parameters'"):
        nbrun.with_parameters(nbrun.read_notebook(p), {}, p.name)


def test_run_all_keeps_going_after_a_failing_notebook_and_saves_what_ran(tmp_path, capsys):
    head = '# %% tags=["parameters"]\nQUICK = False\n\n'
    (tmp_path / "nb").mkdir()
    (tmp_path / "nb" / "01_bad.py").write_text(head + "# %%\nprint('ran', QUICK)\n\n# %%\nraise ValueError('boom')\n")
    (tmp_path / "nb" / "02_good.py").write_text(head + "# %%\nprint('fine', QUICK)\n")
    rc = nbrun.main(["--notebooks", str(tmp_path / "nb"), "--out", str(tmp_path / "out"), "--quick"])
    assert rc == 1
    assert "01_bad.py: FAILED (CellExecutionError" in capsys.readouterr().out
    bad = nbrun.read_notebook(tmp_path / "out" / "01_bad.ipynb")
    printed = [o.get("text", "") for c in bad.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert "ran True\n" in printed  # the cells before the failure kept their outputs, with QUICK injected
    assert any(o.get("ename") == "ValueError" for c in bad.cells for o in c.get("outputs", []))
    good = nbrun.read_notebook(tmp_path / "out" / "02_good.ipynb")
    assert any("fine True" in o.get("text", "") for c in good.cells for o in c.get("outputs", []))
