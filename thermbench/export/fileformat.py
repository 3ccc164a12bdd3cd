"""The compact model file (``.tbm``): what the embedded runtime (``embedded/``) loads.

Layout, little-endian (the C side: ``embedded/include/tb_runtime.h``)::

    0   char[4]  magic "TBMF"
    4   u16      format version (1)
    6   u16      model kind (:class:`Kind`)
    8   u16      number of dimensions used (<= 8)
    10  u16      flags (0)
    12  u32[8]   dimensions (unused ones 0)
    44  u32      n_payload
    48  f32[n]   payload
    48+4n u32    CRC-32 (zlib.crc32, IEEE 802.3) of every byte before it

The payload is float32 (integers in it are exact below 2**24). Each kind's
payload layout is documented with its encoder in :mod:`thermbench.export.encoding`.
"""

from __future__ import annotations

import enum
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from .._atomic import write_bytes_atomic

MAGIC = b"TBMF"
VERSION = 1
HEADER_BYTES = 48
MAX_DIMS = 8
_HEADER = struct.Struct("<4sHHHH8II")


class Kind(enum.IntEnum):
    """Model kinds of format version 1 (``TB_KIND_*`` in tb_runtime.h)."""

    MLR_CURVE = 1
    MLR_SEED001 = 2
    LSSVM = 3
    MLP = 4
    GRU = 5
    PHYSICS = 6
    AR = 7
    CLASSIFIER = 8
    LUMPED = 9  # lumped thermal network of a spindle (docs/concepts.md; :mod:`.lumped_encoding`)


class ModelFileError(ValueError):
    """A model file that cannot be read; the message names the file and what is wrong."""


@dataclass
class ModelFile:
    kind: Kind
    dims: tuple[int, ...]
    payload: np.ndarray  # float32

    @property
    def n_bytes(self) -> int:
        return HEADER_BYTES + 4 * self.payload.size + 4


def pack(kind: Kind, dims: Sequence[int], payload) -> bytes:
    """The bytes of a model file. ``payload`` is converted to float32; a value that is
    not finite in float32 (NaN, inf, or beyond float32's range) is an error."""
    dims = [int(d) for d in dims]
    if len(dims) > MAX_DIMS or any(d < 0 or d >= 2**32 for d in dims):
        raise ModelFileError(f"dims must be at most {MAX_DIMS} integers in [0, 2**32), got {dims}")
    p64 = np.asarray(payload, dtype=float).ravel()
    with np.errstate(over="ignore"):
        p = p64.astype("<f4")
    bad = np.flatnonzero(~np.isfinite(p))
    if bad.size:
        raise ModelFileError(
            f"{Kind(kind).name}: payload value #{bad[0]} = {p64[bad[0]]!r} is not a finite float32"
        )
    header = _HEADER.pack(MAGIC, VERSION, int(kind), len(dims), 0, *(dims + [0] * (MAX_DIMS - len(dims))), p.size)
    body = header + p.tobytes()
    return body + struct.pack("<I", zlib.crc32(body) & 0xFFFFFFFF)


def unpack(data: bytes, name: str = "model file") -> ModelFile:
    """Parse and check a model file's header, length and CRC (the payload layout is the
    C loader's job, and the parity tests')."""
    if len(data) < HEADER_BYTES + 4:
        raise ModelFileError(f"{name}: {len(data)} bytes, shorter than the {HEADER_BYTES + 4}-byte minimum")
    magic, version, kind, n_dims, flags, *rest = _HEADER.unpack_from(data)
    dims, n = rest[:MAX_DIMS], rest[MAX_DIMS]
    if magic != MAGIC:
        raise ModelFileError(f"{name}: not a thermbench model file (magic {magic!r}, expected {MAGIC!r})")
    if version != VERSION:
        raise ModelFileError(f"{name}: format version {version}, this thermbench reads {VERSION}")
    if len(data) != HEADER_BYTES + 4 * n + 4:
        raise ModelFileError(f"{name}: {len(data)} bytes, the header announces {HEADER_BYTES + 4 * n + 4}")
    (crc,) = struct.unpack_from("<I", data, len(data) - 4)
    if crc != zlib.crc32(data[:-4]) & 0xFFFFFFFF:
        raise ModelFileError(f"{name}: CRC-32 mismatch (the file is damaged)")
    try:
        kind = Kind(kind)
    except ValueError:
        raise ModelFileError(f"{name}: unknown model kind {kind}") from None
    payload = np.frombuffer(data, dtype="<f4", count=n, offset=HEADER_BYTES)
    return ModelFile(kind, tuple(dims[:n_dims]), payload.copy())


def write(path: Path, kind: Kind, dims: Sequence[int], payload) -> int:
    """Write a model file atomically; returns its size in bytes."""
    data = pack(kind, dims, payload)
    write_bytes_atomic(Path(path), data)
    return len(data)


def read(path: Path) -> ModelFile:
    path = Path(path)
    return unpack(path.read_bytes(), str(path))
