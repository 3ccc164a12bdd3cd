"""The house's plan: no import circle across folders, and the modules that moved keep their old
names for one release (MOVED in thermbench/__init__.py, docs/architecture.md)."""

from __future__ import annotations

import subprocess
import sys
import textwrap
from pathlib import Path

from tools import importgraph

ROOT = Path(__file__).resolve().parents[1]


def _write(root: Path, files: dict[str, str]) -> None:
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(textwrap.dedent(text), encoding="utf-8")


def test_the_graph_of_a_hand_made_package_has_the_circles_drawn_by_hand(tmp_path):
    # pkg.a.x -> pkg.b.y (absolute) -> pkg.a.x (relative, inside a function): across folders a and b;
    # pkg.c.z <-> pkg.c.w (from . import w; from .z import f): inside c; pkg.b (no __init__: a namespace
    # folder) counts; pkg.d.u -> pkg.a.x only: no circle; "import numpy" names nothing of the package
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/a/__init__.py": "",
        "pkg/a/x.py": "from pkg.b.y import g\nimport numpy\n",
        "pkg/b/y.py": "def g():\n    from ..a import x\n",
        "pkg/c/__init__.py": "",
        "pkg/c/z.py": "from . import w\ndef f():\n    pass\n",
        "pkg/c/w.py": "from .z import f\n",
        "pkg/d/u.py": "from ..a.x import g\n",
        # typing only: pkg.e.t names pkg.e.s in annotations (never imported at run time), pkg.e.s imports pkg.e.t
        "pkg/e/__init__.py": "",
        "pkg/e/s.py": "from . import t\n",
        "pkg/e/t.py": "from typing import TYPE_CHECKING\nimport typing\nif TYPE_CHECKING:\n    from .s import S\n"
                      "if typing.TYPE_CHECKING:\n    import pkg.e.s\n",
    })  # fmt: skip
    files = importgraph.modules(tmp_path, "pkg")
    edges = importgraph.graph(tmp_path, "pkg")
    assert edges["pkg.a.x"] == {"pkg.b.y"} and edges["pkg.b.y"] == {"pkg.a.x"}
    assert edges["pkg.c.z"] == {"pkg.c.w"} and edges["pkg.c.w"] == {"pkg.c.z"} and edges["pkg.d.u"] == {"pkg.a.x"}
    assert edges["pkg.e.s"] == {"pkg.e.t"} and edges["pkg.e.t"] == set()
    found = importgraph.circles(edges)
    assert found == [["pkg.a.x", "pkg.b.y"], ["pkg.c.w", "pkg.c.z"]]
    assert [{importgraph.folder(m, files) for m in c} for c in found] == [{"pkg.a", "pkg.b"}, {"pkg.c"}]


def test_thermbench_has_no_import_circle_no_module_over_600_lines_and_ten_top_level_modules_at_most():
    files = importgraph.modules()
    assert importgraph.circles(importgraph.graph()) == []
    assert {m: n for m, n in importgraph.lines(files).items() if n > 600} == {}
    assert len(importgraph.top_level(files)) <= 10, importgraph.top_level(files)


def test_a_moved_module_keeps_its_old_name_with_a_warning_naming_the_new_place():
    """In a fresh interpreter (no module imported yet): each old name gives the very module at its
    new place, and says where that is, once."""
    from thermbench import MOVED

    code = textwrap.dedent(f"""
        import importlib, warnings
        for old, new in {MOVED!r}.items():
            with warnings.catch_warnings(record=True) as w:
                warnings.simplefilter("always")
                got = importlib.import_module(old)
            said = [str(x.message) for x in w if issubclass(x.category, DeprecationWarning)]
            assert got is importlib.import_module(new), old
            assert said == [f"{{old}} has moved to {{new}}: import it from there; the old name goes in the next release"], said
        from thermbench import benchmark
        assert benchmark.run_task.__module__ == "thermbench.bench.run"
        # a user's configuration naming an old place still builds its object (Hydra imports the old name)
        from hydra.utils import instantiate
        clf = instantiate({{"_target_": "thermbench.classify.ProximityNaiveBayes"}})
        assert type(clf).__module__ == "thermbench.models.classify"
        print("ok", len({MOVED!r}))
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ok", str(len(MOVED))]


def test_a_name_moved_out_of_a_split_module_keeps_its_old_place_with_a_warning():
    """In a fresh interpreter: every name of MOVED_NAMES is the very object at its new place, got
    from the old module with one warning naming the new place; a name that never was there is still
    an AttributeError."""
    from thermbench import MOVED_NAMES

    code = textwrap.dedent(f"""
        import importlib, warnings
        n = 0
        for old, names in {MOVED_NAMES!r}.items():
            module = importlib.import_module(old)
            for name, new in names.items():
                assert name not in vars(module), (old, name)  # else the old module would not warn
                with warnings.catch_warnings(record=True) as w:
                    warnings.simplefilter("always")
                    got = getattr(module, name)
                said = [str(x.message) for x in w if issubclass(x.category, DeprecationWarning)]
                assert got is getattr(importlib.import_module(new), name), (old, name)
                assert said == [f"{{old}}.{{name}} has moved to {{new}}: import it from there; the old name goes in "
                                "the next release"], said
                n += 1
            try:
                getattr(module, "no_such_name_here")
            except AttributeError:
                pass
            else:
                raise AssertionError(old)
        print("ok", n)
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ok", str(sum(map(len, MOVED_NAMES.values())))]


def test_moved_names_on_a_hand_made_split_module(tmp_path):
    """pkg.old was split: f went to pkg.new. pkg.old.f is pkg.new.f with one warning naming pkg.new;
    g, still in pkg.old, gives no warning; h was never anywhere and is an AttributeError."""
    _write(tmp_path, {
        "pkg/__init__.py": "",
        "pkg/new.py": "def f():\n    return 'f'\n",
        "pkg/old.py": "import thermbench\nthermbench.MOVED_NAMES[__name__] = {'f': 'pkg.new'}\n"
                      "__getattr__ = thermbench.moved_names(__name__)\ndef g():\n    return 'g'\n",
    })  # fmt: skip
    code = textwrap.dedent("""
        import warnings, pytest
        import pkg.new, pkg.old
        with warnings.catch_warnings(record=True) as w:
            warnings.simplefilter("always")
            assert pkg.old.f is pkg.new.f and pkg.old.g() == "g"
            from pkg.old import f
            assert f is pkg.new.f
        said = [str(x.message) for x in w if issubclass(x.category, DeprecationWarning)]
        assert said == ["pkg.old.f has moved to pkg.new: import it from there; the old name goes in the next release"] * 2, said
        with pytest.raises(AttributeError, match="'pkg.old' has no attribute 'h'"):
            pkg.old.h
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split() == ["ok"]


def test_docs_architecture_lists_every_moved_module_and_name():
    """docs/architecture.md names each old place and where it went (its tables are written by hand)."""
    from thermbench import MOVED, MOVED_NAMES

    doc = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    rows = [[c.strip() for c in ln.strip("|").split("|")] for ln in doc.splitlines() if ln.startswith("| `thermbench.")]
    listed = {(old.strip("`"), n.strip("` "), new.strip("`")) for old, names, new in (r for r in rows if len(r) == 3)
              for n in names.split(",")}  # fmt: skip
    missing = [(old, n, new) for old, names in MOVED_NAMES.items() for n, new in names.items() if (old, n, new) not in listed]
    assert missing == []
    old_modules = {m.split(".", 1)[1] for m in MOVED}
    assert all(f"`thermbench.{m}`" in doc or f"`.{m}`" in doc for m in old_modules), sorted(old_modules)
