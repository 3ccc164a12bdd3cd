"""The optional parts of thermbench and the extra that installs each (``pyproject.toml``).

The core install (``pip install thermbench``) simulates, validates, imports lab files, trains
and benchmarks every family but the neural ones, tracks in MLflow and exports to the C
runtime. Heavier parts are extras:

=============  ===================================  =========================================
extra          installs                             needed by
=============  ===================================  =========================================
``neural``     torch (CPU build: see the README)    the MLP and GRU families
``onnx``       onnx, onnxruntime                    ONNX export of the neural families
``opcua``      asyncua                              ``thermbench compensator``, ``sim-cnc``, ``certs``
``cluster``    hydra-submitit-launcher (submitit)   ``hydra/launcher=submitit_local``/``cluster``
``postgres``   psycopg 3                            an MLflow tracking server on PostgreSQL
``notebooks``  jupyterlab, jupytext, papermill      the guided notebooks
``all``        every extra above
=============  ===================================  =========================================

:func:`require` imports an optional module and, when it is missing, raises
:class:`MissingExtra` (a :class:`~thermbench.errors.UserError`: one line, exit 2) naming the
extra to install. ``what`` names who needs it: ``require("torch", "the neural families MLP and GRU")``.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from .errors import UserError

__all__ = ["EXTRAS", "MissingExtra", "require"]

#: top-level module -> the extra that installs it
EXTRAS = {
    "torch": "neural",
    "onnx": "onnx",
    "onnxruntime": "onnx",
    "asyncua": "opcua",
    "cryptography": "opcua",
    "submitit": "cluster",
    "hydra_plugins.hydra_submitit_launcher": "cluster",
    "psycopg": "postgres",
    "papermill": "notebooks",
    "jupytext": "notebooks",
    "nbclient": "notebooks",
}


class MissingExtra(UserError, ImportError):
    """An optional dependency that is not installed: the message names the extra."""


def install_hint(extra: str) -> str:
    """The pip command that installs ``extra`` (editable checkout or installed package)."""
    return f"pip install 'thermbench[{extra}]' (from a checkout: pip install -e '.[{extra}]')"


def require(module: str, what: str) -> ModuleType:
    """``module`` imported, or :class:`MissingExtra` saying that ``what`` needs it and which
    extra installs it (``require("torch", "the MLP and GRU families")``)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as exc:
        top = module.split(".")[0]
        if exc.name is not None and not (exc.name == module or exc.name.split(".")[0] == top):
            raise  # the module is there but something it imports is not: a real error
        extra = EXTRAS.get(module) or EXTRAS.get(top)
        if extra is None:
            raise
        raise MissingExtra(f"{top} is not installed (needed by {what}); the '{extra}' extra installs it: "
                           f"{install_hint(extra)}") from None
