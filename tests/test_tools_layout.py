"""The development tools (tools/: confref, nbrun) live outside the thermbench package: the package
neither holds nor imports them, and is installed without them."""

from __future__ import annotations

import json
import re
import subprocess
import sys
import tomllib
from pathlib import Path

import setuptools

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = ROOT / "thermbench"

# Imports thermbench and every module file below it (pkgutil.walk_packages would skip
# thermbench/models/, a namespace package without __init__.py; a __main__ (thermbench's, thermbench.cli's)
# runs the command line when imported and only imports thermbench.cli), then reports the tools modules loaded. A
# positive control follows: importing the tools must show up the same way.
PROBE = """
import importlib, json, sys
from pathlib import Path
import thermbench
root = Path(thermbench.__file__).parent
names = sorted({".".join(("thermbench", *p.relative_to(root).with_suffix("").parts)).removesuffix(".__init__")
                for p in root.rglob("*.py") if p.name != "__main__.py"} - {"thermbench"})
for name in names:
    importlib.import_module(name)
def loaded():
    return sorted(n for n in sys.modules if n == "tools" or n.startswith("tools."))
found = loaded()
import tools.nbrun, tools.confref
print(json.dumps({"file": thermbench.__file__, "modules": names, "tools": found, "control": loaded()}))
"""


def test_importing_every_thermbench_module_loads_no_tool():
    # a fresh interpreter in the source tree: the test process's own imports do not count
    proc = subprocess.run([sys.executable, "-c", PROBE], cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    got = json.loads(proc.stdout.strip().splitlines()[-1])
    assert Path(got["file"]).resolve() == PACKAGE / "__init__.py"
    assert len(got["modules"]) > 60 and {"thermbench.models.neural", "thermbench.export.native"} <= set(got["modules"])
    assert got["tools"] == []
    assert got["control"] == ["tools", "tools.confref", "tools.nbrun"]


def test_no_tool_in_the_package_and_no_import_of_one():
    assert not [p for p in PACKAGE.rglob("*.py") if p.name in ("confref.py", "nbrun.py")]
    importing = re.compile(r"^\s*(from\s+tools[\s.]|import\s+tools\b)", re.M)
    assert not [p for p in PACKAGE.rglob("*.py") if importing.search(p.read_text(encoding="utf-8"))]
    assert {p.name for p in (ROOT / "tools").glob("*.py")} >= {"__init__.py", "confref.py", "nbrun.py"}


def test_the_installed_packages_are_thermbench_only():
    find = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["tool"]["setuptools"]["packages"]["find"]
    packages = setuptools.find_packages(str(ROOT), include=find["include"])
    assert "thermbench" in packages and "thermbench.compensator" in packages
    assert not [p for p in packages if not p.startswith("thermbench")]
    assert "tools" in setuptools.find_packages(str(ROOT))  # without the include, tools/ would be found
