"""The guided notebooks (notebooks/NN_*.py, jupytext percent format) run end to end.

Each is executed in a real Jupyter kernel with its small settings (``QUICK=True``), a scratch
``OUT_DIR`` and a benchmark root that holds seed001_vmc_x (prebuilt once per session). A notebook
fails the test when any cell raises, including the ``assert`` with which each notebook checks its
own claim, and when it shows no figure.
"""

from __future__ import annotations

import ast
import os
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
    tags = [c.metadata.get("tags", []) for c in nb.cells]
    assert tags[tags.index(["parameters"]) + 1] == [nbrun.INJECTED_TAG]  # papermill's cell, right after
    assert (tmp_path / "out").is_dir()  # the injected OUT_DIR took effect (the default is under outputs/)


def test_papermill_injects_the_parameters_after_the_parameters_cell(tmp_path, monkeypatch):
    (tmp_path / "nb").mkdir()
    p = tmp_path / "nb" / "99_x.py"
    p.write_text('# %%\nimport os\n\n# %% tags=["parameters"]\nQUICK = False  # small settings\nNAME = "default"\n\n'
                 "# %%\nprint('got', QUICK, NAME)\nprint('cwd', os.getcwd())\nprint('backend', os.environ['MPLBACKEND'])\n")
    monkeypatch.setenv("MPLBACKEND", "Agg")
    nb, elapsed = nbrun.run_notebook(p, {"QUICK": True, "NAME": "it's"})
    assert elapsed > 0
    tags = [c.metadata.get("tags", []) for c in nb.cells]
    assert tags[1] == ["parameters"] and tags[2] == [nbrun.INJECTED_TAG]
    assert nb.cells[2].source == "# Parameters\nQUICK = True\nNAME = \"it's\"\n"  # papermill's cell
    assert nb.metadata.papermill.parameters == {"QUICK": True, "NAME": "it's"}
    assert nb.metadata.papermill.input_path == str(p)  # not papermill's copy of the whole input notebook
    printed = "".join(o.get("text", "") for o in nb.cells[3].outputs)
    assert f"got True it's\ncwd {p.parent}\nbackend {nbrun.INLINE_BACKEND}\n" == printed
    assert os.environ["MPLBACKEND"] == "Agg"  # the caller's environment is back
    nb, _ = nbrun.run_notebook(p, {})  # nothing to inject: the defaults run
    assert [c.metadata.get("tags", []) for c in nb.cells][2] == []
    assert "got False default\n" in "".join(o.get("text", "") for o in nb.cells[2].outputs)


def test_parameters_must_exist_in_the_parameters_cell(tmp_path):
    src = '# %% tags=["parameters"]\nQUICK = False\nSEED: int = 0  # annotated\n\n# %%\nOTHER = 1\nprint(QUICK)\n'
    p = tmp_path / "99_x.py"
    p.write_text(src)
    nbrun.check_parameters(nbrun.read_notebook(p), {"QUICK": True, "SEED": 1}, p.name)
    for typo in ("QUICKK", "OTHER"):  # OTHER is assigned, but not in the parameters cell
        with pytest.raises(nbrun.NotebookError, match=rf"99_x.py: parameters \['{typo}'\] are not set"):
            nbrun.check_parameters(nbrun.read_notebook(p), {"QUICK": True, typo: True}, p.name)
    # run_notebook refuses before a kernel starts: the cell that would leave a file never runs
    p.write_text('# %% tags=["parameters"]\nQUICK = False\n\n# %%\nopen("ran", "w").close()\n')
    with pytest.raises(nbrun.NotebookError, match=r"99_x.py: parameters \['QUICKK'\]"):
        nbrun.run_notebook(p, {"QUICKK": True})
    assert not (tmp_path / "ran").exists()
    p.write_text("# %%\nprint(1)\n")
    with pytest.raises(nbrun.NotebookError, match="99_x.py: expected exactly one code cell tagged 'parameters', found 0"):
        nbrun.check_parameters(nbrun.read_notebook(p), {}, p.name)
    p.write_text('# %% tags=["parameters"]\nA = 1\n\n# %% tags=["parameters"]\nB = 2\n')
    with pytest.raises(nbrun.NotebookError, match="99_x.py: expected exactly one .*, found 2"):
        nbrun.run_notebook(p, {})


def test_run_all_keeps_going_after_a_failing_notebook_and_saves_what_ran(tmp_path, capsys):
    head = '# %% tags=["parameters"]\nQUICK = False\n\n'
    (tmp_path / "nb").mkdir()
    (tmp_path / "nb" / "01_bad.py").write_text(head + "# %%\nprint('ran', QUICK)\n\n# %%\nraise ValueError('boom')\n")
    (tmp_path / "nb" / "02_good.py").write_text(head + "# %%\nprint('fine', QUICK)\n")
    (tmp_path / "nb" / "03_typo.py").write_text('# %% tags=["parameters"]\nQUIK = False\n')
    rc = nbrun.main(["--notebooks", str(tmp_path / "nb"), "--out", str(tmp_path / "out"), "--quick"])
    assert rc == 1
    out, err = capsys.readouterr()
    assert "01_bad.py: FAILED (PapermillExecutionError: ValueError: boom), 0 figures" in out
    assert "03_typo.py: FAILED (NotebookError: 03_typo.py: parameters ['QUICK'] are not set in its parameters cell:)" in out
    assert err.splitlines()[-1] == "failed: 01_bad.py, 03_typo.py"
    bad = nbrun.read_notebook(tmp_path / "out" / "01_bad.ipynb")
    printed = [o.get("text", "") for c in bad.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert "ran True\n" in printed  # the cells before the failure kept their outputs, with QUICK injected
    assert any(o.get("ename") == "ValueError" for c in bad.cells for o in c.get("outputs", []))
    good = nbrun.read_notebook(tmp_path / "out" / "02_good.ipynb")
    assert any("fine True" in o.get("text", "") for c in good.cells for o in c.get("outputs", []))


def test_a_cell_timeout_stops_the_run_and_keeps_the_cells_that_ran(tmp_path):
    p = tmp_path / "99_slow.py"
    p.write_text('# %% tags=["parameters"]\nQUICK = False\n\n# %%\nprint("before", QUICK)\n\n# %%\nimport time\ntime.sleep(30)\n')
    with pytest.raises(nbrun.NotebookFailed, match="99_slow.py") as info:
        nbrun.run_notebook(p, {"QUICK": True}, cell_timeout_s=1)
    assert type(info.value.__cause__).__name__ == "CellTimeoutError"
    assert 1 <= info.value.elapsed_s < 25
    outputs = [o.get("text", "") for c in info.value.nb.cells if c.cell_type == "code" for o in c.get("outputs", [])]
    assert "before True\n" in outputs
