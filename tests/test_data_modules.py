"""The dataset package's modules import one another one way only: the class, the
shared readers and checks, format 1, format 2, the views and the reference each in a module
that imports none of the modules built on it."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import thermbench.data
from tools import importgraph

DATA = Path(thermbench.data.__file__).parent


def _imports(path: Path) -> list[tuple[str, bool]]:
    """The sibling modules ``path`` imports at run time (not under ``if TYPE_CHECKING:``: a class
    named in annotations only), each with whether the import is at module level."""
    tree = ast.parse(path.read_text())
    top = {id(n) for n in tree.body}
    skip = importgraph.typing_only(tree)
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.level == 1 and id(node) not in skip:
            names = [node.module] if node.module else [a.name for a in node.names]
            out += [(n.split(".")[0], id(node) in top) for n in names]
    return out


def test_no_module_of_the_data_package_imports_one_that_imports_it_back():
    graph = {p.stem: _imports(p) for p in DATA.glob("*.py") if p.stem != "__init__"}
    # the one import inside a function: Dataset.channel_view, a convenience over the views module
    lazy = {(m, dep) for m, deps in graph.items() for dep, at_top in deps if not at_top}
    assert lazy == {("dataset", "views")}
    edges = {m: {dep for dep, _ in deps} for m, deps in graph.items()}  # the deferred one too
    assert {"tables", "dataset"} <= edges["io"] and "v2" in edges["io"]  # io builds on the shared parts
    assert "io" not in edges["v2"] and "io" not in edges["views"] and "io" not in edges["reference"]

    def cycle_from(start: str, node: str, seen: tuple[str, ...]) -> tuple[str, ...] | None:
        for dep in edges.get(node, ()):
            if dep == start:
                return seen + (dep,)
            if dep not in seen:
                found = cycle_from(start, dep, seen + (dep,))
                if found:
                    return found
        return None

    for m in edges:
        assert cycle_from(m, m, (m,)) is None, f"import cycle {cycle_from(m, m, (m,))}"


def test_each_module_imports_on_its_own():
    """Any of them first, in a fresh interpreter: no order of imports is needed."""
    for m in sorted(p.stem for p in DATA.glob("*.py")):
        subprocess.run([sys.executable, "-c", f"import thermbench.data.{m}"], check=True)


def _thermbench_imports(path: Path) -> set[str]:
    """The thermbench modules ``path`` imports, anywhere in it (functions too), as dotted names."""
    pkg = path.relative_to(DATA.parent.parent).with_suffix("").parts[:-1]  # ("thermbench", "export")
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.level:
            base = list(pkg[: len(pkg) - node.level + 1])
            out.add(".".join(base + ([node.module] if node.module else [])))
        elif isinstance(node, ast.ImportFrom) and (node.module or "").startswith("thermbench"):
            out.add(node.module)
    return out


def test_splits_and_views_are_shared_from_one_module_below_the_jobs():
    """The runs and views the jobs fit on (thermbench.bench.splits), the workers
    (thermbench.bench.parallel): the benchmark, the export and the replay take them from there; none of
    those, nor splits, imports the Hydra-job module thermbench.experiment back (no import circle)."""
    root = DATA.parent
    for mod in ("bench/splits.py", "bench/parallel.py", "config.py", "export/job.py", "export/replay.py"):
        assert "thermbench.experiment" not in _thermbench_imports(root / mod), mod
    assert "thermbench.bench.splits" in _thermbench_imports(root / "export/job.py")
    assert "thermbench.bench.splits" in _thermbench_imports(root / "export/replay.py")
    assert "thermbench.bench.splits" in _thermbench_imports(root / "bench/run.py")
    for m in ("bench.splits", "bench.parallel", "export.job", "export.replay"):
        subprocess.run([sys.executable, "-c", f"import thermbench.{m}"], check=True)
