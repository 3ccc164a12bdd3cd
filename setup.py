"""Packaging beyond pyproject.toml: the wheel carries the project's ``conf/`` and the C runtime's
``embedded/`` inside the package (``thermbench/conf``, ``thermbench/embedded``), so an installed
thermbench finds its Hydra configuration and runtime sources on its own (thermbench/_resources.py).
In the repository they stay at the top, where users edit them; an editable install reads them there."""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

HERE = Path(__file__).resolve().parent
# top-level directory -> what of it the wheel carries (patterns left out)
SHIPPED = {"conf": (), "embedded": ("fuzz",)}


class build_py_with_project_dirs(build_py):
    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):  # an editable install reads the checkout's own directories
            return
        for name, leave_out in SHIPPED.items():
            dest = Path(self.build_lib) / "thermbench" / name
            shutil.copytree(HERE / name, dest, dirs_exist_ok=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.pyc", *leave_out))


setup(cmdclass={"build_py": build_py_with_project_dirs})
