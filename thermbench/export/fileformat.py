"""The compact model file (``.tbm``): what the embedded runtime (``embedded/``) loads.

Layout, little-endian (the C side: ``embedded/include/tb_runtime.h``)::

    0   char[4]  magic "TBMF"
    4   u16      format version: the version of the kind's payload layout (:data:`KIND_VERSIONS`)
    6   u16      model kind (:class:`Kind`)
    8   u16      number of dimensions used (<= 8)
    10  u16      flags (0)
    12  u32[8]   dimensions (unused ones 0)
    44  u32      n_payload
    48  f32[n]   payload
    48+4n u32    CRC-32 (zlib.crc32, IEEE 802.3) of every byte before it

The payload is float32 (integers in it are exact below 2**24). Each kind's
payload layout is documented with its encoder in :mod:`thermbench.export.encoding`.

Versions: the header is the same for every version; the version number says which layout of
its kind's payload follows. Every kind has layout 1; :data:`KIND_VERSIONS` lists the kinds with
later ones (PHYSICS 2: the effects as sections ``(code, n_params, params...)`` instead of fixed
slots). The writer writes each kind's latest; the C runtime reads every version up to it (it
keeps a reader for PHYSICS 1), and refuses a version beyond what it knows with TB_E_VERSION.
"""

from __future__ import annotations

import enum
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

import numpy as np

from ..outputs import write_bytes_atomic

MAGIC = b"TBMF"
VERSION = 1  # the first version, every kind's (tb_runtime.h: TB_FORMAT_VERSION)
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
    THERMAL_LAG = 10  # first-order lags of the rises and an operating input (:mod:`.lag_encoding`)
    LINEAR_HISTORY = 12  # the rises now and delayed, from delay lines (:mod:`.lag_encoding`); 11 is ENVELOPE_KIND
    ENSEMBLE = 13  # a weighted sum of models of the other kinds, carried in the file (:func:`.encoding.encode_ensemble`)


#: not a model: a model's training envelope (``TB_KIND_ENVELOPE`` of tb_runtime.h, read by
#: ``tb_guard_open``; :mod:`thermbench.export.guard`), in the same file format
ENVELOPE_KIND = 11
#: not a model: the sensor checks and the correction's bounds (``TB_KIND_FAULTS``, read by
#: ``tb_faults_open``; :mod:`thermbench.export.faultfile`), a data kind above every model kind
FAULTS_KIND = 64
#: the kinds that are data for the runtime, not models
DATA_KINDS = {ENVELOPE_KIND: "ENVELOPE", FAULTS_KIND: "FAULTS"}


def kind_name(kind) -> str:
    return DATA_KINDS.get(int(kind)) or Kind(kind).name


#: kinds whose latest payload layout is beyond version 1 (tbi_kind.max_version in the C runtime)
KIND_VERSIONS: dict[Kind, int] = {Kind.PHYSICS: 2, Kind.THERMAL_LAG: 2}
MAX_VERSION = max(KIND_VERSIONS.values(), default=VERSION)


def kind_version(kind) -> int:
    """The latest payload version of ``kind`` (what :func:`pack` writes)."""
    return VERSION if int(kind) in DATA_KINDS else KIND_VERSIONS.get(Kind(kind), VERSION)


class ModelFileError(ValueError):
    """A model file that cannot be read; the message names the file and what is wrong."""


@dataclass
class ModelFile:
    kind: Kind  # or one of DATA_KINDS
    dims: tuple[int, ...]
    payload: np.ndarray  # float32
    version: int = VERSION  # of the kind's payload layout

    @property
    def n_bytes(self) -> int:
        return HEADER_BYTES + 4 * self.payload.size + 4


def pack(kind: Kind, dims: Sequence[int], payload, version: int | None = None) -> bytes:
    """The bytes of a model file. ``payload`` is converted to float32; a value that is
    not finite in float32 (NaN, inf, or beyond float32's range) is an error. ``version``:
    the payload layout ``payload`` follows, by default the kind's latest (:func:`kind_version`)."""
    latest = kind_version(kind)
    version = latest if version is None else int(version)
    if not 1 <= version <= latest:
        raise ModelFileError(f"{kind_name(kind)}: payload version {version}; this thermbench writes 1 to {latest}")
    dims = [int(d) for d in dims]
    if len(dims) > MAX_DIMS or any(d < 0 or d >= 2**32 for d in dims):
        raise ModelFileError(f"dims must be at most {MAX_DIMS} integers in [0, 2**32), got {dims}")
    p64 = np.asarray(payload, dtype=float).ravel()
    with np.errstate(over="ignore"):
        p = p64.astype("<f4")
    bad = np.flatnonzero(~np.isfinite(p))
    if bad.size:
        raise ModelFileError(
            f"{kind_name(kind)}: payload value #{bad[0]} = {p64[bad[0]]!r} is not a finite float32"
        )
    header = _HEADER.pack(MAGIC, version, int(kind), len(dims), 0, *(dims + [0] * (MAX_DIMS - len(dims))), p.size)
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
    if not VERSION <= version <= MAX_VERSION:
        raise ModelFileError(f"{name}: format version {version}, this thermbench reads {VERSION} to {MAX_VERSION}")
    if len(data) != HEADER_BYTES + 4 * n + 4:
        raise ModelFileError(f"{name}: {len(data)} bytes, the header announces {HEADER_BYTES + 4 * n + 4}")
    (crc,) = struct.unpack_from("<I", data, len(data) - 4)
    if crc != zlib.crc32(data[:-4]) & 0xFFFFFFFF:
        raise ModelFileError(f"{name}: CRC-32 mismatch (the file is damaged)")
    try:
        kind = kind if kind in DATA_KINDS else Kind(kind)
    except ValueError:
        raise ModelFileError(f"{name}: unknown model kind {kind}") from None
    if version > kind_version(kind):
        raise ModelFileError(f"{name}: format version {version} of kind {kind_name(kind)}, which has versions 1 to "
                             f"{kind_version(kind)}")  # fmt: skip
    payload = np.frombuffer(data, dtype="<f4", count=n, offset=HEADER_BYTES)
    return ModelFile(kind, tuple(dims[:n_dims]), payload.copy(), version)


def write(path: Path, kind: Kind, dims: Sequence[int], payload, version: int | None = None) -> int:
    """Write a model file atomically (:func:`pack`); returns its size in bytes."""
    data = pack(kind, dims, payload, version)
    write_bytes_atomic(Path(path), data)
    return len(data)


def read(path: Path) -> ModelFile:
    path = Path(path)
    return unpack(path.read_bytes(), str(path))
