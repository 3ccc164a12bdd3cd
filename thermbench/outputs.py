"""Where thermbench writes, and what it refuses: no command ever deletes or overwrites a file
it did not write.

Every command that writes output goes through :func:`output_dir` (a directory of files: a
dataset, a report, a model directory, an export, a replay, a diagnosis, ...) or
:func:`output_file` (one file in a directory that also holds other things: a rewritten part
program, ``nodes.yaml``, a notebook). Both keep a small record, ``.thermbench-output.json``,
in the directory they write to, listing each file they wrote with its SHA-256. The rules:

* a new directory is written whole into a staging directory next to it and renamed into
  place: a reader sees no output or all of it;
* an existing directory is written to only when it is empty, or when its record says it
  holds an earlier output of the same kind and every file in it is on that record,
  unchanged. The files on the new list then replace the old ones one by one (each with a
  rename), the old files no longer produced are removed (they are on the record, unchanged:
  thermbench wrote them), and anything else is refused before any work starts;
* ``force=True`` (``--force`` on the command line) also writes into a directory holding
  other files, beside them: they are left alone, and a file of the same name as one of them
  is still refused;
* a directory that is a dataset, contains one, or lies inside one (any directory with
  ``metadata.yaml`` that this very output did not write) is always refused, ``force`` or not;
* a file edited since thermbench wrote it counts as the user's file.

A refusal is an :class:`OutputRefused` (a ``FileExistsError``): one line that names the path
and what to do.

Under both, one file is never half-written: :func:`atomic_path` (a temporary file beside the
target, renamed onto it on success), :func:`write_text_atomic`, :func:`write_bytes_atomic`.
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

RECORD = ".thermbench-output.json"
RECORD_FORMAT = "thermbench-output/1"
DATASET_MARK = "metadata.yaml"
_WHOLE = "."  # the record's set name for a whole-directory output
STREAMING = "being written"  # a file thermbench writes as it goes (a log): its content is not fixed yet


class OutputRefused(FileExistsError):
    """thermbench will not write there: the message names the path and what to do."""


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ------------------------------------------------ one file, never half-written ---
@contextmanager
def atomic_path(target: str | os.PathLike, mode: int | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``target``; rename it onto ``target`` on success.

    On any exception the temporary file is removed and ``target`` is untouched.
    ``mode``: the file's permissions from the start (e.g. 0o600 for a private key);
    default the usual mode under the umask.
    """
    target = Path(target)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    if mode is None:
        os.chmod(tmp_path, 0o666 & ~_umask())  # mkstemp makes 0600; the file gets the usual mode
    else:
        os.chmod(tmp_path, mode)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text_atomic(target: str | os.PathLike, text: str) -> None:
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def write_bytes_atomic(target: str | os.PathLike, data: bytes, mode: int | None = None) -> None:
    with atomic_path(target, mode) as tmp:
        tmp.write_bytes(data)


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def _files_below(root: Path) -> list[str]:
    """Every non-directory entry below ``root`` (links not followed), as relative POSIX paths."""
    out = []
    for dirpath, dirnames, filenames in os.walk(root, followlinks=False):
        base = Path(dirpath)
        for name in filenames + [d for d in dirnames if (base / d).is_symlink()]:
            out.append((base / name).relative_to(root).as_posix())
    return sorted(out)


@dataclass
class _Record:
    """The parsed ``.thermbench-output.json`` of one directory."""

    path: Path
    sets: dict[str, dict] = field(default_factory=dict)
    copied: bool = False  # the record was copied here with the files (cp -r): they are not thermbench's here

    @classmethod
    def read(cls, directory: Path) -> "_Record":
        path = directory / RECORD
        if not path.is_file():
            return cls(path)
        try:
            raw = json.loads(path.read_text(encoding="utf-8"))
            sets = raw["sets"] if raw.get("format") == RECORD_FORMAT else None
            if not isinstance(sets, dict):
                raise ValueError("no sets")
        except (ValueError, KeyError, TypeError, OSError, UnicodeDecodeError):
            raise OutputRefused(f"{path}: not a record thermbench wrote (unreadable); choose a new directory") from None
        if raw.get("dir") != _dir_id(directory):  # a record is valid only in the directory it was written in
            return cls(path, {}, copied=True)
        return cls(path, sets)

    def owner(self, rel: str) -> str | None:
        """The set whose list has ``rel``."""
        for name, s in self.sets.items():
            if rel in s.get("files", {}):
                return name
        return None

    def unchanged(self, directory: Path, rel: str) -> bool:
        """``rel`` is on the record and its content is one thermbench wrote."""
        name = self.owner(rel)
        if name is None:
            return False
        want = self.sets[name]["files"][rel]
        p = directory / rel
        if p.is_symlink() or not p.is_file():
            return False
        return want == STREAMING or sha256_file(p) in (want if isinstance(want, list) else [want])

    def write(self) -> None:
        body = {"format": RECORD_FORMAT, "dir": _dir_id(self.path.parent), "sets": self.sets}
        if not self.sets:
            self.path.unlink(missing_ok=True)
            return
        fd, tmp = tempfile.mkstemp(prefix=f".{RECORD}.", suffix=".tmp", dir=self.path.parent)
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            json.dump(body, fh, indent=1, sort_keys=True)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, self.path)


def _dir_id(directory: Path) -> str:
    """The directory's identity (device and inode): kept by a rename, new for a copy."""
    st = os.stat(directory)
    return f"{st.st_dev}:{st.st_ino}"


def _real(target: str | os.PathLike) -> Path:
    """``target`` with symbolic links resolved (``link/..`` is where the file system goes), and
    refused when an existing part of its path is a file, not a directory."""
    path = Path(os.path.realpath(target))
    for anc in path.parents:
        if anc.exists():
            if not anc.is_dir():
                raise _refuse(Path(target), f"{anc} is a file, not a directory", "choose a new directory")
            break
    return path


def _is_dataset(d: Path) -> bool:
    return (d / DATASET_MARK).exists() or (d / DATASET_MARK).is_symlink()


def _refuse(path: Path, why: str, what: str = "choose a new directory") -> OutputRefused:
    return OutputRefused(f"{path}: {why}; {what}")


def _dataset_guard(target: Path, ours: set[str], option: str) -> None:
    """Refuse a target that is, contains or lies inside a dataset (other than one listed in ``ours``)."""
    target = Path(os.path.abspath(target))
    for anc in [target, *target.parents]:
        if anc.is_dir() and _is_dataset(anc) and not (anc == target and DATASET_MARK in ours):
            where = "is a dataset" if anc == target else f"lies inside the dataset {anc}"
            raise _refuse(target, f"{where} (it has {DATASET_MARK}): thermbench never writes into a dataset"
                          + (f" ({option} does not change that)" if option else ""))  # fmt: skip
    if target.is_dir():
        for rel in _files_below(target):
            p = Path(rel)
            if p.name == DATASET_MARK and rel not in ours:
                raise _refuse(target, f"contains the dataset {target / p.parent}: thermbench never writes over a dataset")


def _force_hint(force_option: str) -> str:
    return f"choose a new directory (or {force_option} to write beside them)" if force_option else "choose a new directory"


def check_output_dir(target: str | os.PathLike, kind: str, force: bool = False, force_option: str = "--force") -> None:
    """Raise :class:`OutputRefused` unless :func:`output_dir` may write ``kind`` to ``target``.

    Call it before any long work, so that a refusal costs nothing; :func:`output_dir` checks
    again when it writes."""
    _check_dir(_real(target), kind, force, force_option)


def _check_dir(target: Path, kind: str, force: bool, force_option: str) -> _Record:
    if target.exists() or target.is_symlink():
        if target.is_symlink() or not target.is_dir():
            raise _refuse(target, "exists and is not a directory", "choose a new directory")
        rec = _Record.read(target)
        mine = rec.sets.get(_WHOLE)
        ours = {rel for rel in (mine or {}).get("files", {}) if rec.unchanged(target, rel)}
        _dataset_guard(target, ours, force_option if force else "")
        if rec.sets and (mine is None or mine.get("kind") != kind):
            other = f"{mine.get('kind')} output" if mine else "other thermbench output"
            raise _refuse(target, f"holds {other}, not {kind} output", "choose a new directory")
        foreign = [rel for rel in _files_below(target) if (rel != RECORD or rec.copied) and rel not in ours]
        if foreign and not force:
            changed = [rel for rel in foreign if rec.owner(rel)]
            why = (f"holds {len(foreign)} file(s) thermbench did not write there (e.g. {foreign[0]!r}"
                   + (f"; {changed[0]!r} was changed since thermbench wrote it" if changed else "")
                   + ("; its thermbench record was copied from another directory" if rec.copied else "") + ")")
            raise _refuse(target, why, _force_hint(force_option))
        return rec
    _dataset_guard(target, set(), force_option if force else "")
    return _Record(target / RECORD)


def _command() -> str:
    return " ".join(["thermbench" if i == 0 else a for i, a in enumerate(sys.argv)])[:500]


def _stage_hashes(stage: Path) -> dict[str, str]:
    files = _files_below(stage)
    links = [f for f in files if (stage / f).is_symlink()]
    if links:  # thermbench writes plain files only
        raise RuntimeError(f"output staging wrote symbolic link(s) {links}")
    return {rel: sha256_file(stage / rel) for rel in files if rel != RECORD}


@contextmanager
def output_dir(target: str | os.PathLike, kind: str, force: bool = False, force_option: str = "--force") -> Iterator[Path]:
    """Yield an empty staging directory; fill it; on success its files become ``target``'s
    output of ``kind`` under the rules of this module. On an exception nothing changes."""
    target = _real(target)
    _check_dir(target, kind, force, force_option)
    target.parent.mkdir(parents=True, exist_ok=True)
    stage = Path(tempfile.mkdtemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent))
    os.chmod(stage, 0o777 & ~_umask())  # mkdtemp makes 0700; the directory gets the usual mode
    try:
        yield stage
        new = _stage_hashes(stage)
        rec = _check_dir(target, kind, force, force_option)  # again: things may have changed meanwhile
        entry = {"kind": kind, "command": _command(), "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                 "files": new}  # fmt: skip
        if not target.exists():
            rec = _Record(stage / RECORD, {_WHOLE: entry})
            rec.write()
            os.rename(stage, target)  # fails if target appeared meanwhile: nothing lost
            return
        _replace_files(target, stage, rec, _WHOLE, entry)
    finally:
        if stage.exists():
            shutil.rmtree(stage)


def _replace_files(directory: Path, stage: Path, rec: _Record, set_name: str, entry: dict) -> None:
    """Move the staged files of ``entry`` into ``directory``, remove the files of the set's
    earlier output that are no longer produced, and update the record. The record lists old
    and new content while files move, so an interruption leaves nothing unaccounted for."""
    old = dict(rec.sets.get(set_name, {}).get("files", {}))
    new = entry["files"]
    for rel in new:
        dest = directory / rel
        if (dest.exists() or dest.is_symlink()) and not (rec.owner(rel) == set_name and rec.unchanged(directory, rel)):
            raise _refuse(dest, "exists and thermbench did not write it (or it was changed since)",
                          "move it away or choose a new directory")  # fmt: skip
    transit = {rel: sorted({*_as_list(old.get(rel)), *_as_list(new.get(rel))}) for rel in {*old, *new}}
    rec.sets[set_name] = {**entry, "files": transit}
    rec.write()
    for rel in new:
        dest = directory / rel
        dest.parent.mkdir(parents=True, exist_ok=True)
        os.replace(stage / rel, dest)
    for rel in sorted(set(old) - set(new)):
        p = directory / rel
        if rec.unchanged(directory, rel):
            p.unlink()
            for parent in p.parents:
                if parent == directory:
                    break
                try:
                    parent.rmdir()  # only when empty: a user's file keeps its folder
                except OSError:
                    break
    rec.sets[set_name] = entry
    rec.write()


def _as_list(v) -> list[str]:
    return [] if v is None else list(v) if isinstance(v, list) else [v]


def check_output_file(target: str | os.PathLike, kind: str) -> None:
    """Raise :class:`OutputRefused` unless :func:`output_file` may write ``target``."""
    _check_file(_real(target), kind)


def _check_file(target: Path, kind: str) -> _Record:
    directory = target.parent
    if target.is_dir():
        raise _refuse(target, "is a directory; a file name is expected", "give a file name")
    rec = _Record.read(directory) if directory.is_dir() else _Record(directory / RECORD)
    whole = rec.sets.get(_WHOLE)
    if whole is not None:
        raise _refuse(target, f"lies in a directory that holds a {whole.get('kind')} output", "choose another directory")
    name = target.name
    _dataset_guard(target, set(), "")
    if target.exists() or target.is_symlink():
        s = rec.sets.get(name)
        if s is None or not rec.unchanged(directory, name):
            raise _refuse(target, "exists and thermbench did not write it (or it was changed since)",
                          "choose a new file name or move it away")  # fmt: skip
        if s.get("kind") != kind:
            raise _refuse(target, f"holds {s.get('kind')} output, not {kind}", "choose a new file name")
    return rec


@contextmanager
def output_file(target: str | os.PathLike, kind: str, mode: int | None = None) -> Iterator[Path]:
    """Yield a temporary path next to ``target``; on success it becomes ``target`` (one file
    among others of its directory; the directory's record lists it). ``target`` may exist only
    as an unchanged earlier output of the same kind. ``mode``: the file's permissions from the
    start (e.g. 0o600 for a private key)."""
    target = _real(target)
    _check_file(target, kind)
    target.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
    os.close(fd)
    tmp_path = Path(tmp)
    os.chmod(tmp_path, (0o666 & ~_umask()) if mode is None else mode)
    try:
        yield tmp_path
        rec = _check_file(target, kind)
        name = target.name
        entry = {"kind": kind, "command": _command(), "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
                 "files": {name: sha256_file(tmp_path)}}  # fmt: skip
        old = rec.sets.get(name, {}).get("files", {}).get(name)
        rec.sets[name] = {**entry, "files": {name: sorted({*_as_list(old), entry["files"][name]})}}
        rec.write()
        os.replace(tmp_path, target)
        rec.sets[name] = entry
        rec.write()
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text(target: str | os.PathLike, text: str, kind: str) -> Path:
    """:func:`output_file` for a text file."""
    with output_file(target, kind) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(target)


class OutputStream:
    """A file thermbench writes line by line while it runs (e.g. the compensator's cycle log),
    readable as it grows. Like :func:`output_file` it may replace only an unchanged earlier
    output of the same kind; the record marks it as being written until :meth:`close`
    stores its final SHA-256 (a log cut short by a crash still counts as thermbench's)."""

    def __init__(self, target: str | os.PathLike, kind: str) -> None:
        self.path = _real(target)
        self.kind = kind
        _check_file(self.path, kind)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        rec = _Record.read(self.path.parent)
        rec.sets[self.path.name] = {"kind": kind, "command": _command(), "files": {self.path.name: STREAMING},
                                    "written_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}  # fmt: skip
        rec.write()
        self.fh = open(self.path, "w", newline="", encoding="utf-8", buffering=1)

    def close(self) -> None:
        if self.fh.closed:
            return
        self.fh.close()
        rec = _Record.read(self.path.parent)
        entry = rec.sets.get(self.path.name)
        if entry is not None:
            entry["files"] = {self.path.name: sha256_file(self.path)}
            rec.write()


#: what Hydra and a thermbench job leave in a run directory, and in a sweep directory
_HYDRA_RUN = r"\.hydra/(?:config|hydra|overrides)\.yaml|[A-Za-z0-9_.-]+\.log|result\.json"
#: ... and the submitit launcher's job files (hydra.launcher.submitit_folder, ${hydra.sweep.dir}/.submitit/%j):
#: per job id (local: a pid; SLURM: 123 or 123_4 for an array task) the pickled job, its result, its
#: task logs, on SLURM the submission script, and a pickle being written (.save_tmp, renamed when done);
#: on SLURM also, directly in .submitit/, the link to each submission script and the pickles of jobs
#: being submitted (submitit's Executor._submit_command)
_SUBMITIT = (r"\.submitit/(?:[0-9_]+/[0-9_]+_(?:submitted\.pkl|submission\.sh|\d+_log\.(?:out|err)|\d+_result\.pkl)"
             r"(?:\.save_tmp)?|\.submission_file_[0-9a-f]{32}\.sh|[0-9a-f]{32}\.pkl)")
_HYDRA_FILES = {"hydra.run.dir": re.compile(_HYDRA_RUN),
                "hydra.sweep.dir": re.compile(rf"multirun\.yaml|sweep_size\.txt|\d+/(?:{_HYDRA_RUN})|{_SUBMITIT}")}  # fmt: skip
_HYDRA_PROOF = {"hydra.run.dir": ".hydra/hydra.yaml", "hydra.sweep.dir": "multirun.yaml"}


def _foreign_dir(path: str | os.PathLike, key: str) -> Path:
    """The real path of a directory another program writes into (config key ``key``), refused
    when it is, contains or lies inside a dataset."""
    try:
        real = _real(path)
        _dataset_guard(real, set(), "")
    except OutputRefused as exc:
        raise OutputRefused(f"config key '{key}': {exc}") from None
    return real


def check_hydra_dir(path: str | os.PathLike, key: str = "hydra.run.dir") -> None:
    """Refuse a Hydra run (``key='hydra.run.dir'``) or sweep (``'hydra.sweep.dir'``) directory
    that is, contains or lies inside a dataset, or that already holds files unless it is an
    earlier Hydra job's directory (it has Hydra's own ``.hydra/hydra.yaml``, resp.
    ``multirun.yaml``) holding only what Hydra and thermbench write there."""
    real = _foreign_dir(path, key)
    if real.is_dir():
        files = [rel for rel in _files_below(real) if rel != RECORD]
        if files and not (real / _HYDRA_PROOF[key]).is_file():
            raise _refuse(Path(path), f"holds {len(files)} file(s) and is not an earlier Hydra job's directory "
                          f"(e.g. {files[0]!r})", f"choose another {key}")  # fmt: skip
        foreign = [rel for rel in files if not _HYDRA_FILES[key].fullmatch(rel)]
        if foreign:
            raise _refuse(Path(path), f"holds {len(foreign)} file(s) that are not an earlier Hydra job's "
                          f"(e.g. {foreign[0]!r})", f"choose another {key}")  # fmt: skip


def check_library_dir(path: str | os.PathLike, names: set[str], key: str) -> None:
    """A directory another library writes into (e.g. joblib's cache, under config key ``key``):
    refused when it is, contains or lies inside a dataset, or holds entries other than ``names``."""
    real = _foreign_dir(path, key)
    if real.is_dir():
        other = sorted(p.name for p in real.iterdir() if p.name not in names)
        if other:
            raise _refuse(Path(path), f"holds {other[:3]}, not only what it is for ({', '.join(sorted(names))})",
                          f"choose another {key}")  # fmt: skip
