"""Which exceptions are the user's mistakes, and how the command line reports them.

A *user error* is a validated input mistake (a config key, a dataset, a file, a model
directory, the machine's endpoint...): the command prints one line, ``thermbench: error:
...``, and exits with code 2. Every other exception is a programming error and keeps its
traceback (a ``KeyError`` or ``ValueError`` raised inside model code is a bug to report,
not something to hide behind a one-line message).

New user-input errors derive from :class:`UserError`; the older per-module classes are
listed in ``_MODULE_ERRORS`` (they could later derive from :class:`UserError` instead).
:func:`user_errors` is the one tuple both :mod:`thermbench.cli` and :mod:`thermbench.app`
catch. A ``ValueError`` raised for a user's input anywhere else is reported as a bug, with
its traceback: raise one of these instead.

Exit codes: 2 a user mistake, 1 a bug (traceback), 130 interrupted, 141 stdout closed by
its reader (``thermbench ... | head``).

**A missing optional part** is a user error too. The optional parts of thermbench and the extra that installs each (``pyproject.toml``).

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
import os
import sys
from types import ModuleType

#: exit code of a user mistake (argparse uses 2 for its own usage errors too)
USER_ERROR_EXIT = 2
#: exit code when the reader of stdout went away (``thermbench ... | head``): 128 + SIGPIPE,
#: what a shell reports for a tool stopped by a closed pipe
BROKEN_PIPE_EXIT = 141


class UserError(ValueError):
    """A validated user-input mistake: reported in one line (exit 2), no traceback.

    The message names what is wrong (file, column, config key, run id...) and, where it
    can, what to do instead."""


class ExperimentError(UserError):
    """A user mistake in an experiment config (a job's, the benchmark's); the message names the key."""


class StdoutClosed(SystemExit):
    """Standard output was closed by its reader (``thermbench ... | head``).

    A ``SystemExit`` (code 141), so nothing that catches ``Exception`` (Hydra's job runner,
    logging handlers, a sweep's per-job error handling) swallows it, and the process ends
    quietly if nobody catches it."""

    def __init__(self) -> None:
        super().__init__(BROKEN_PIPE_EXIT)


#: the user-input error classes of the older modules: (module under thermbench, class name)
_MODULE_ERRORS = (
    ("config", "ConfigError"),
    ("data.io", "DatasetError"),
    ("data.errors", "DatasetError"),
    ("models.base", "ModelError"),
    ("preprocess.filters", "PreprocessError"),  # a filter parameter or input series, named
    ("tracking", "TrackingError"),
    ("export.encoding", "ExportError"),
    ("export.fileformat", "ModelFileError"),
    ("export.runtime", "RuntimeUnavailable"),
    ("export.runtime", "RuntimeFailed"),
    ("discrepancy.workflow", "DiagnoseError"),
    ("precompensate", "PrecompError"),
    ("compensator.errors", "CompensatorError"),
    ("bench.adapt", "ProbeParamsError"),
    ("compensator.nodes", "NodesError"),
    ("compensator.simcnc", "SimCncError"),
)

#: the user's files and folders: a path that is missing, in the way, not a directory, not ours
_OS_ERRORS = (FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError, PermissionError)


def user_errors() -> tuple[type[BaseException], ...]:
    """The exceptions that are user mistakes: reported in one line, no traceback.

    :class:`UserError` and its subclasses, the per-module classes listed in
    ``_MODULE_ERRORS``, and the OS errors about the user's paths. Nothing else: a plain
    ``ValueError``/``KeyError`` is a bug. Only modules already imported are looked at (an
    exception of a class whose module was never imported cannot have been raised), so
    catching these costs no import of pandas, MLflow or asyncua."""
    found: list[type[BaseException]] = [UserError]
    for module, name in _MODULE_ERRORS:
        cls = getattr(sys.modules.get(f"{__package__}.{module}"), name, None)
        if isinstance(cls, type) and issubclass(cls, BaseException) and cls not in found:
            found.append(cls)
    return (*found, *_OS_ERRORS)


def one_line(message: object) -> str:
    """``message`` on one line: its non-empty lines joined with '; '."""
    lines = [ln.strip() for ln in str(message).splitlines() if ln.strip()]
    return "; ".join(lines) if lines else type(message).__name__


def report(prefix: str, exc: BaseException) -> int:
    """Print a user error as ``<prefix>: error: <message>`` (one line on stderr); return 2."""
    print(f"{prefix}: error: {one_line(exc)}", file=sys.stderr, flush=True)
    return USER_ERROR_EXIT


class GuardedStdout:
    """``sys.stdout`` whose writes raise :class:`StdoutClosed` once the reader is gone.

    The standard recipe (Python docs, "Note on SIGPIPE"): on ``BrokenPipeError`` point the
    stdout file descriptor at ``/dev/null`` (so the interpreter's final flush cannot fail
    again) and exit quietly."""

    def __init__(self, stream) -> None:
        self._stream = stream

    def write(self, s: str) -> int:
        try:
            return self._stream.write(s)
        except BrokenPipeError:
            raise stdout_closed(self._stream) from None

    def flush(self) -> None:
        try:
            self._stream.flush()
        except BrokenPipeError:
            raise stdout_closed(self._stream) from None

    def writelines(self, lines) -> None:
        for line in lines:
            self.write(line)

    def __getattr__(self, name: str):
        return getattr(self._stream, name)


def stdout_closed(stream=None) -> StdoutClosed:
    """Silence ``stream`` (default ``sys.stdout``) for good: ``/dev/null`` on its file
    descriptor; return the exit to raise."""
    stream = sys.stdout if stream is None else stream
    try:
        fd = stream.fileno()
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, fd)
        finally:
            os.close(devnull)
    except (OSError, ValueError, AttributeError):  # no real stdout (captured in tests): nothing to redirect
        pass
    return StdoutClosed()


# --------------------------------------------- the optional parts (extras) ---
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
