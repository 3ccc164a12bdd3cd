"""The envelope file (``envelope.tbm``): a model's training envelope for the C runtime's
extrapolation guard (``embedded/src/tb_guard.c``, ``tb_guard_open``), as
:class:`thermbench.bench.intervals.EnvelopeGuard` follows it in Python.

The model file's header and CRC (:mod:`.fileformat`), kind ``ENVELOPE_KIND``; dims
``[n_sensors, n_operating]``; payload ``[tau_s, lo[n], hi[n], width[n]]``, ``n = 2 n_sensors +
n_operating``, in the envelope's order (``rise:<sensor>``..., ``rate:<sensor>``...,
``op:<input>``...). The sensors and operating inputs are the model's, in its samples' order.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..bench.intervals import RATE_WINDOW_S, Envelope
from . import fileformat

ENVELOPE_FILE = "envelope.tbm"


def envelope_payload(env: Envelope, tau_s: float = RATE_WINDOW_S) -> tuple[list[int], np.ndarray]:
    return [len(env.sensors), len(env.operating)], np.concatenate([[float(tau_s)], env.lo, env.hi, env.width])


def write_envelope(path: Path, env: Envelope, tau_s: float = RATE_WINDOW_S) -> int:
    """Write ``env`` (float32, as every payload) atomically; returns the file's bytes."""
    dims, payload = envelope_payload(env, tau_s)
    return fileformat.write(Path(path), fileformat.ENVELOPE_KIND, dims, payload)


def read_envelope(path: Path, sensors=None, operating=None) -> tuple[Envelope, float]:
    """The envelope of a file as the C runtime reads it (float32 values) and its ``tau_s``;
    ``sensors`` / ``operating`` name its inputs (from the manifest), else ``s0``... / ``op0``..."""
    mf = fileformat.read(Path(path))
    if mf.kind != fileformat.ENVELOPE_KIND or len(mf.dims) != 2:
        raise fileformat.ModelFileError(f"{path}: not an envelope file (kind {int(mf.kind)})")
    ns, nop = mf.dims
    n = 2 * ns + nop
    if mf.payload.size != 1 + 3 * n:
        raise fileformat.ModelFileError(f"{path}: {mf.payload.size} values, an envelope of dims {mf.dims} has {1 + 3 * n}")
    p = mf.payload.astype(float)
    sensors = tuple(sensors) if sensors is not None else tuple(f"s{i}" for i in range(ns))
    operating = tuple(operating) if operating is not None else tuple(f"op{i}" for i in range(nop))
    names = [f"rise:{s}" for s in sensors] + [f"rate:{s}" for s in sensors] + [f"op:{c}" for c in operating]
    return Envelope(sensors, operating, names, p[1 : 1 + n], p[1 + n : 1 + 2 * n], p[1 + 2 * n :]), float(p[0])
