"""thermbench's import graph: its modules, their sizes, and the import circles among them.

Every ``import`` and ``from … import`` of every module under ``thermbench/`` (those inside functions
too: a deferred import still ties two modules together; not those under ``if TYPE_CHECKING:``, which
never run: a class named in annotations only ties nothing at run time, as grimp's
``exclude_type_checking_imports``), resolved to the thermbench module it names
(``from .x import y`` names module ``x.y`` when that is a module, else ``x``). The circles are the
strongly connected components of that graph with more than one module (scipy's
``connected_components``), each said to sit *inside* one folder or to go *across* folders. Folders
without an ``__init__.py`` (namespace packages) count as folders too, which grimp leaves out.

    python -m tools.importgraph            # the circles, then the top level and the modules over 600 lines
    python -m tools.importgraph --edges    # and every import, one per line
"""

from __future__ import annotations

import argparse
import ast
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = "thermbench"


def modules(root: Path = ROOT, package: str = PACKAGE) -> dict[str, Path]:
    """Dotted name -> file of every module of ``root/package`` (a package is its ``__init__``)."""
    out = {}
    for p in sorted((root / package).rglob("*.py")):
        parts = list(p.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = p
    return out


def typing_only(tree: ast.AST) -> set[int]:
    """The ids of the nodes under an ``if TYPE_CHECKING:`` (or ``typing.TYPE_CHECKING``) of ``tree``."""
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and (
            (isinstance(node.test, ast.Name) and node.test.id == "TYPE_CHECKING")
            or (isinstance(node.test, ast.Attribute) and node.test.attr == "TYPE_CHECKING")
        ):
            out |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return out


def imports(name: str, path: Path, files: dict[str, Path]) -> set[str]:
    """The thermbench modules module ``name`` (file ``path``) imports (at run time)."""
    here = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out = set()
    tree = ast.parse(path.read_text(encoding="utf-8"))
    skip = typing_only(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                up = here.split(".")[: len(here.split(".")) - (node.level - 1)]
                base = ".".join(up + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in files else base for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in files and "." in t:  # e.g. thermbench.x.function -> thermbench.x
                t = t.rpartition(".")[0]
            if t in files and t != name:
                out.add(t)
    return out


def graph(root: Path = ROOT, package: str = PACKAGE) -> dict[str, set[str]]:
    """Module -> the package's modules it imports."""
    files = modules(root, package)
    return {m: imports(m, p, files) for m, p in files.items()}


def circles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module, each sorted, in name order."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import connected_components

    names = sorted(edges)
    idx = {m: i for i, m in enumerate(names)}
    pairs = [(idx[a], idx[b]) for a, bs in edges.items() for b in bs]
    rows, cols = zip(*pairs) if pairs else ((), ())
    matrix = csr_matrix((np.ones(len(pairs)), (rows, cols)), shape=(len(names), len(names)))
    _, label = connected_components(matrix, directed=True, connection="strong")
    groups = [[names[i] for i in np.flatnonzero(label == k)] for k in np.unique(label)]
    return sorted(g for g in groups if len(g) > 1)


def folder(name: str, files: dict[str, Path]) -> str:
    """The folder a module sits in (a package's ``__init__`` sits in its own folder)."""
    return name if files[name].name == "__init__.py" else name.rpartition(".")[0]


def top_level(files: dict[str, Path]) -> list[str]:
    """The modules of the package's flat top level (not its sub-packages)."""
    return [m for m in files if m.count(".") == 1 and files[m].name != "__init__.py"]


def lines(files: dict[str, Path]) -> dict[str, int]:
    """Each module's number of lines."""
    return {m: len(p.read_text(encoding="utf-8").splitlines()) for m, p in files.items()}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--edges", action="store_true", help="print every import too")
    args = ap.parse_args(argv)
    files = modules()
    edges = graph()
    found = circles(edges)
    across = [c for c in found if len({folder(m, files) for m in c}) > 1]
    print(f"{len(files)} modules, {sum(map(len, edges.values()))} imports, {len(found)} circles "
          f"({len(across)} across folders)")
    for c in found:
        where = "across folders" if c in across else f"inside {folder(c[0], files)}"
        print(f"  circle {where}: {' <-> '.join(c)}")
    top = top_level(files)
    print(f"top level: {len(top)} modules: {', '.join(m.split('.', 1)[1] for m in top)}")
    big = sorted(((n, m) for m, n in lines(files).items()), reverse=True)
    print("over 600 lines: " + (", ".join(f"{m} ({n})" for n, m in big if n > 600) or "none"))
    if args.edges:
        for a in sorted(edges):
            for b in sorted(edges[a]):
                print(f"{a} -> {b}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
