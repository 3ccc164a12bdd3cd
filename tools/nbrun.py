"""Run the guided notebooks in ``notebooks/`` headless: read, parameterise, execute.

The notebooks are jupytext percent-format ``.py`` files (``notebooks/NN_name.py``). Each has one
code cell tagged ``parameters`` (the papermill convention) that sets its defaults, ``QUICK =
False`` among them; ``run_notebook`` inserts a cell right after it with the caller's values, so
the test suite runs every notebook with ``QUICK=True`` (small settings) and a scratch ``OUT_DIR``.

    python -m tools.nbrun                 # all notebooks, full settings -> outputs/notebooks/*.ipynb
    python -m tools.nbrun --quick 01 03   # two of them, small settings

Needs the ``dev`` (or ``notebooks``) extras: jupytext, nbclient, ipykernel.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import Mapping

from thermbench.outputs import OutputRefused, check_output_file, output_file

PARAMETERS_TAG = "parameters"


class NotebookError(ValueError):
    """A notebook that cannot be parameterised (names the file and what is missing)."""


def notebooks_dir() -> Path:
    """``notebooks/`` of the source tree that holds ``tools/``."""
    return Path(__file__).resolve().parent.parent / "notebooks"


def notebook_paths(root: str | Path | None = None) -> list[Path]:
    """The guided notebooks, in order (``NN_*.py``)."""
    return sorted(Path(root or notebooks_dir()).glob("[0-9][0-9]_*.py"))


def _libs():
    try:
        import jupytext
        import nbformat
        from nbclient import NotebookClient
    except ImportError as exc:  # pragma: no cover - message for a user without the extras
        raise SystemExit(f"running notebooks needs jupytext, nbclient and ipykernel: pip install -e '.[dev]' ({exc})")
    return jupytext, nbformat, NotebookClient


def read_notebook(path: str | Path):
    """The notebook of a jupytext ``.py`` file, or of an executed ``.ipynb`` with its outputs, as an
    nbformat v4 node."""
    jupytext, _, _ = _libs()
    return jupytext.read(Path(path))


def with_parameters(nb, params: Mapping[str, object], name: str = "notebook"):
    """``nb`` with a cell assigning ``params`` inserted after its ``parameters``-tagged cell.

    Only names the parameters cell already assigns may be overridden, so a typo fails here
    instead of being silently ignored by the notebook.
    """
    _, nbformat, _ = _libs()
    idx = [i for i, c in enumerate(nb.cells) if PARAMETERS_TAG in c.get("metadata", {}).get("tags", [])]
    if len(idx) != 1:
        raise NotebookError(f"{name}: expected exactly one code cell tagged {PARAMETERS_TAG!r}, found {len(idx)}")
    src = nb.cells[idx[0]].source
    unknown = [k for k in params if not any(line.split("=")[0].strip() == k for line in src.splitlines() if "=" in line)]
    if unknown:
        raise NotebookError(f"{name}: parameters {unknown} are not set in its parameters cell:\n{src}")
    if params:
        lines = [f"{k} = {v!r}" for k, v in params.items()]
        cell = nbformat.v4.new_code_cell("# injected parameters\n" + "\n".join(lines))
        cell.metadata["tags"] = ["injected-parameters"]
        nb.cells.insert(idx[0] + 1, cell)
    return nb


INLINE_BACKEND = "module://matplotlib_inline.backend_inline"


def run_notebook(path: str | Path, params: Mapping[str, object] | None = None, cell_timeout_s: float | None = 120.0,
                 nb=None):  # fmt: skip
    """Execute the notebook at ``path`` (working directory: its folder) with ``params``.

    ``cell_timeout_s`` None: no limit per cell. The kernel draws inline whatever ``MPLBACKEND``
    the caller has set (ipykernel keeps a backend it finds there, and the figures would be lost).
    ``nb``: execute this already-read notebook instead (it is filled in place, so a caller keeps
    the cells that ran when one fails). Returns ``(executed notebook, elapsed_s)``; a failing
    cell raises nbclient's ``CellExecutionError`` with the cell's traceback.
    """
    _, _, NotebookClient = _libs()
    path = Path(path)
    nb = with_parameters(nb if nb is not None else read_notebook(path), dict(params or {}), path.name)
    client = NotebookClient(nb, timeout=None if cell_timeout_s is None else int(cell_timeout_s), kernel_name="python3",
                            resources={"metadata": {"path": str(path.parent)}})  # fmt: skip
    t0 = time.perf_counter()
    client.execute(env={**os.environ, "MPLBACKEND": INLINE_BACKEND})
    return nb, time.perf_counter() - t0


def images(nb) -> int:
    """How many PNG figures the executed notebook shows."""
    return sum("image/png" in out.get("data", {}) for c in nb.cells if c.cell_type == "code" for out in c.get("outputs", []))


def save_executed(nb, out: Path) -> Path:
    _, nbformat, _ = _libs()
    with output_file(out, "notebook") as tmp:  # never over a notebook thermbench did not write
        tmp.write_bytes(nbformat.writes(nb).encode("utf-8"))
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m tools.nbrun", description=__doc__.split("\n\n")[0])
    ap.add_argument("names", nargs="*", help="notebook numbers or names (default: all)")
    ap.add_argument("--quick", action="store_true", help="small settings (QUICK=True), as the test suite runs them")
    ap.add_argument("--out", default=None, help="where the executed .ipynb go (default: outputs/notebooks/ beside notebooks/)")
    ap.add_argument("--timeout", type=float, default=None, help="seconds per cell (default: none)")
    ap.add_argument("--notebooks", default=None, help="the folder of NN_*.py notebooks (default: the source tree's notebooks/)")
    a = ap.parse_args(argv)
    folder = Path(a.notebooks) if a.notebooks else notebooks_dir()
    every = notebook_paths(folder)
    if not every:
        print(f"no NN_*.py notebooks in {folder} (give the folder with --notebooks)", file=sys.stderr)
        return 2
    wanted = [n.removesuffix(".py") for n in a.names]
    paths = [p for p in every if not wanted or any(p.stem.startswith(n) for n in wanted)]
    if not paths:
        print(f"no notebook matches {a.names}; have {[p.stem for p in every]}", file=sys.stderr)
        return 2
    out = Path(a.out).resolve() if a.out else folder.resolve().parent / "outputs" / "notebooks"
    try:  # a notebook file thermbench did not write is refused before any notebook runs
        for p in paths:
            check_output_file(out / f"{p.stem}.ipynb", "notebook")
    except OutputRefused as exc:
        print(f"python -m tools.nbrun: error: {exc}", file=sys.stderr)
        return 2
    failed = []
    for p in paths:
        nb = read_notebook(p)
        try:
            _, dt = run_notebook(p, {"QUICK": True} if a.quick else {}, a.timeout, nb=nb)
            status = f"{dt:6.1f} s"
        except Exception as exc:  # a failing cell (or a timeout): keep what ran, go on with the others
            failed.append(p.name)
            status = f"FAILED ({type(exc).__name__}: {str(exc).strip().splitlines()[-1][:200] if str(exc).strip() else ''})"
        saved = save_executed(nb, out / f"{p.stem}.ipynb")
        print(f"{p.name}: {status}, {images(nb)} figures -> {saved}", flush=True)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
