"""Open a dataset's files without trusting them: a named pipe, a device, a socket or a
directory where a file is expected, and a file larger than its cap, are refused from
``os.stat`` alone, before anything is opened or read (a FIFO is never opened: opening
one blocks until a writer comes)."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import BinaryIO

from . import limits
from .errors import DatasetError


def _size_text(n: int) -> str:
    for unit, scale in (("GiB", 1 << 30), ("MiB", 1 << 20), ("KiB", 1 << 10)):
        if n >= scale:
            return f"{n / scale:.1f} {unit}"
    return f"{n} bytes"


def _kind(mode: int) -> str | None:
    """What a non-regular file is, or None for a regular file."""
    if stat.S_ISREG(mode):
        return None
    if stat.S_ISDIR(mode):
        return "a directory"
    if stat.S_ISFIFO(mode):
        return "a named pipe (FIFO)"
    if stat.S_ISCHR(mode):
        return "a character device"
    if stat.S_ISBLK(mode):
        return "a block device"
    if stat.S_ISSOCK(mode):
        return "a socket"
    return "not a regular file"


def check_regular_file(path: Path, max_bytes: int, what: str) -> os.stat_result:
    """``os.stat(path)`` (following symbolic links) when it is a regular file of at most
    ``max_bytes``; else :class:`DatasetError`. ``what`` names the file's role in messages."""
    try:
        st = os.stat(path)
    except FileNotFoundError:
        if os.path.islink(path):
            raise DatasetError(f"{path}: broken symbolic link (to {os.readlink(path)!r})") from None
        raise DatasetError(f"{path}: missing") from None
    except OSError as exc:
        raise DatasetError(f"{path}: cannot read it ({exc.strerror or exc})") from None
    kind = _kind(st.st_mode)
    if kind is not None:
        target = f" (a link to {os.path.realpath(path)!r})" if os.path.islink(path) else ""
        raise DatasetError(f"{path}: is {kind}{target}, not a regular file; refused without reading it")
    if st.st_size > max_bytes:
        more = f"; ${limits.TABLE_CAP_ENV} sets another cap in MiB" if what == "a table" else ""
        raise DatasetError(
            f"{path}: {_size_text(st.st_size)} is too large for {what} (at most {_size_text(max_bytes)}, "
            f"docs/dataset-format.md, Limits{more})"
        )
    return st


def open_regular_file(path: Path, max_bytes: int, what: str) -> BinaryIO:
    """Open ``path`` for binary reading after :func:`check_regular_file`. The open is
    non-blocking and re-checked on the descriptor, so a file swapped for a FIFO or a
    device between the check and the open is refused too, never waited on."""
    st = check_regular_file(path, max_bytes, what)
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_NOCTTY", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        raise DatasetError(f"{path}: cannot open it ({exc.strerror or exc})") from None
    try:
        st2 = os.fstat(fd)
        if _kind(st2.st_mode) is not None or (st2.st_dev, st2.st_ino) != (st.st_dev, st.st_ino) or st2.st_size > max_bytes:
            raise DatasetError(f"{path}: changed while being opened; refused")
        if hasattr(os, "set_blocking"):
            os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


def read_capped(path: Path, max_bytes: int, what: str) -> bytes:
    """The whole content of a regular file of at most ``max_bytes`` (checked before reading,
    and again while reading, should the file grow)."""
    with open_regular_file(path, max_bytes, what) as fh:
        data = fh.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise DatasetError(f"{path}: grew beyond {_size_text(max_bytes)} while being read; refused")
    return data


def find_case_variant(root: Path, name: str) -> str | None:
    """A directory entry of ``root`` that differs from ``name`` only by case or by the
    usual variant (metadata.yml): what the user probably meant."""
    wanted = {name.casefold()}
    stem, _, ext = name.rpartition(".")
    if ext == "yaml":
        wanted.add(f"{stem}.yml".casefold())
    try:
        with os.scandir(root) as it:
            for entry in it:
                if entry.name != name and entry.name.casefold() in wanted:
                    return entry.name
    except OSError:
        return None
    return None
