"""Run the guided notebooks in ``notebooks/`` headless with papermill: read, parameterise, execute.

The notebooks are jupytext percent-format ``.py`` files (``notebooks/NN_name.py``), read with
jupytext. Each has one code cell tagged ``parameters`` (papermill's convention) that sets its
defaults, ``QUICK = False`` among them; papermill inserts a cell tagged ``injected-parameters``
right after it with the caller's values and executes the notebook, so the test suite runs every
notebook with ``QUICK=True`` (small settings) and a scratch ``OUT_DIR``.

    python -m tools.nbrun                 # all notebooks, full settings -> outputs/notebooks/*.ipynb
    python -m tools.nbrun --quick 01 03   # two of them, small settings

Run from the project root. Needs the ``dev`` extras: papermill, jupytext, ipykernel.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator, Mapping

from thermbench.outputs import OutputRefused, check_output_file, output_file

PARAMETERS_TAG = "parameters"
INJECTED_TAG = "injected-parameters"  # the tag of the cell papermill inserts
KERNEL = "python3"
KERNELSPEC = {"name": KERNEL, "language": "python", "display_name": "Python 3"}  # for inspecting a cell
INLINE_BACKEND = "module://matplotlib_inline.backend_inline"


class NotebookError(ValueError):
    """A notebook that cannot be parameterised (names the file and what is missing)."""


class NotebookFailed(RuntimeError):
    """A run that stopped (a failing cell, a cell timeout, a dead kernel); the cause is chained.

    ``nb`` is the notebook as far as it ran (papermill marks the failing cell), ``elapsed_s``
    the time until it stopped.
    """

    def __init__(self, message: str, nb, elapsed_s: float):
        super().__init__(message)
        self.nb = nb
        self.elapsed_s = elapsed_s


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
        import papermill
    except ImportError as exc:  # pragma: no cover - message for a user without the extras
        raise SystemExit(f"running notebooks needs papermill, jupytext and ipykernel: pip install -e '.[dev]' ({exc})")
    return jupytext, nbformat, papermill


def read_notebook(path: str | Path):
    """The notebook of a jupytext ``.py`` file, or of an executed ``.ipynb`` with its outputs, as an
    nbformat v4 node."""
    jupytext, _, _ = _libs()
    return jupytext.read(Path(path))


def check_parameters(nb, params: Mapping[str, object], name: str = "notebook") -> None:
    """Raise :class:`NotebookError` unless ``nb`` has exactly one cell tagged ``parameters`` and
    papermill finds every name of ``params`` assigned in it (papermill itself only logs a warning
    for an unknown name and runs on, so a typo would be silently ignored)."""
    _, nbformat, papermill = _libs()
    cells = [c for c in nb.cells if PARAMETERS_TAG in c.get("metadata", {}).get("tags", [])]
    if len(cells) != 1:
        raise NotebookError(f"{name}: expected exactly one code cell tagged {PARAMETERS_TAG!r}, found {len(cells)}")
    probe = nbformat.v4.new_notebook(cells=cells, metadata={"kernelspec": KERNELSPEC})
    known = papermill.inspect_notebook(probe)  # the names papermill's Python translator reads off the cell
    unknown = [k for k in params if k not in known]
    if unknown:
        raise NotebookError(f"{name}: parameters {unknown} are not set in its parameters cell:\n{cells[0].source}")


@contextmanager
def _environ(**values: str) -> Iterator[None]:
    """``os.environ`` with ``values`` for a while: papermill passes no environment to the kernel,
    which inherits this process's."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def _provenance(nb, path: Path):
    """``nb`` with papermill's ``input_path`` naming the ``.py`` file (papermill stores an input
    notebook node there whole)."""
    if "papermill" in nb.metadata:
        nb.metadata.papermill["input_path"] = str(path)
        nb.metadata.papermill["output_path"] = None
    return nb


def run_notebook(path: str | Path, params: Mapping[str, object] | None = None, cell_timeout_s: float | None = 120.0):
    """Execute the notebook at ``path`` with papermill (working directory: its folder), ``params``
    injected after its ``parameters`` cell (checked first by :func:`check_parameters`).

    ``cell_timeout_s`` None: no limit per cell. The kernel draws inline whatever ``MPLBACKEND``
    the caller has set (ipykernel keeps a backend it finds there, and the figures would be lost).
    Returns ``(executed notebook, elapsed_s)``. A run that stops raises :class:`NotebookFailed`
    with the cells that ran, chained to papermill's ``PapermillExecutionError`` (the failing
    cell's traceback) or nbclient's ``CellTimeoutError``.
    """
    _, nbformat, papermill = _libs()
    path = Path(path)
    params = dict(params or {})
    nb = read_notebook(path)
    check_parameters(nb, params, path.name)
    timeout = None if cell_timeout_s is None else max(1, math.ceil(cell_timeout_s))
    with tempfile.TemporaryDirectory(prefix="nbrun-") as tmp, _environ(MPLBACKEND=INLINE_BACKEND):
        scratch = Path(tmp) / f"{path.stem}.ipynb"  # papermill saves the notebook there after each cell
        t0 = time.perf_counter()
        try:
            nb = papermill.execute_notebook(nb, str(scratch), parameters=params, kernel_name=KERNEL, language="python",
                                            progress_bar=False, cwd=str(path.parent), execution_timeout=timeout)  # fmt: skip
        except Exception as exc:
            elapsed = time.perf_counter() - t0
            ran = nbformat.read(scratch, as_version=4) if scratch.exists() else nb
            raise NotebookFailed(f"{path.name}: {exc}", _provenance(ran, path), elapsed) from exc
        return _provenance(nb, path), time.perf_counter() - t0


def images(nb) -> int:
    """How many PNG figures the executed notebook shows."""
    return sum("image/png" in out.get("data", {}) for c in nb.cells if c.cell_type == "code" for out in c.get("outputs", []))


def save_executed(nb, out: Path) -> Path:
    """Write ``nb`` to ``out`` atomically, never over a notebook thermbench did not write."""
    _, nbformat, _ = _libs()
    if "papermill" in nb.metadata:
        nb.metadata.papermill["output_path"] = str(out)
    with output_file(out, "notebook") as tmp:
        tmp.write_bytes(nbformat.writes(nb).encode("utf-8"))
    return out


def _summary(exc: BaseException) -> str:
    """One line of ``exc``: a traceback's last line, a :class:`NotebookError`'s first."""
    lines = str(exc).strip().splitlines() or [""]
    return lines[0 if isinstance(exc, NotebookError) else -1][:200]


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
        try:
            nb, dt = run_notebook(p, {"QUICK": True} if a.quick else {}, a.timeout)
            status = f"{dt:6.1f} s"
        except Exception as exc:  # a failing cell, a timeout, a bad parameters cell: keep what ran, go on
            failed.append(p.name)
            nb = exc.nb if isinstance(exc, NotebookFailed) else read_notebook(p)
            cause = exc.__cause__ if isinstance(exc, NotebookFailed) and exc.__cause__ is not None else exc
            status = f"FAILED ({type(cause).__name__}: {_summary(cause)})"
        saved = save_executed(nb, out / f"{p.stem}.ipynb")
        print(f"{p.name}: {status}, {images(nb)} figures -> {saved}", flush=True)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":  # pragma: no cover
    raise SystemExit(main())
