"""Where the project's own directories are: ``conf/`` (Hydra configuration) and ``embedded/`` (the C
runtime's sources). A source checkout (or an editable install) has them at the top of the repository;
a wheel carries them inside the package (setup.py copies them in). An environment variable points at
a user's own copy instead."""

from __future__ import annotations

import os
from pathlib import Path

_PACKAGE = Path(__file__).resolve().parent


def project_dir(name: str, env: str, marker: str) -> tuple[Path, list[Path]]:
    """``$env`` when set; else the first of the package's own copy (a wheel) and the checkout's
    top-level ``name/`` that holds ``marker``. Returns the directory and the places looked at
    (the caller names them when none fits)."""
    if os.environ.get(env):
        return Path(os.environ[env]), [Path(os.environ[env])]
    tried = [_PACKAGE / name, _PACKAGE.parent / name]
    for cand in tried:
        if (cand / marker).exists():
            return cand, tried
    return tried[-1], tried
