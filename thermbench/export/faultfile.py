"""The faults file (``faults.tbm``): a model's sensor checks and the bounds of its correction for the
C runtime (``embedded/src/tb_faults.c``, ``tb_faults_open``), as
:class:`thermbench.bench.faults.FaultMonitor` and :class:`~thermbench.bench.faults.Bounds` follow
them in Python.

The model file's header and CRC (:mod:`.fileformat`), kind ``FAULTS_KIND``; dims ``[n]`` (the
sensors checked, the model's temperatures in its samples' order); payload: the rules' parameters
and the bounds (:data:`SCALARS`, in that order), then per sensor ``rise_lo_K``, ``rise_hi_K``,
``rate_max_K_h``, ``flat_s``, ``tol_K``, ``start_offset_K``, ``icpt``, ``rate_tol_K_h`` (n each),
then ``coef`` (n x n, row-major). An infinity of the Python side (a sensor that never moved:
``flat_s``; one no other predicts: ``tol_K``, ``rate_tol_K_h``; a bound that is not set) is written
as -1, which the C runtime reads so.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..bench import faults as F
from . import fileformat

FAULTS_FILE = "faults.tbm"

#: the payload's scalars: the rules' parameters (thermbench/bench/faults.py) and the bounds
SCALARS = ("tau_s", "plausible_lo_C", "plausible_hi_C", "unknown_start_C", "range_min_K", "rate_factor", "rate_min_K_h",
           "stuck_factor", "stuck_min_s", "stuck_move_K", "max_um", "rate_um_s")  # fmt: skip
#: the per-sensor arrays after them, in order (then coef)
ARRAYS = ("rise_lo_K", "rise_hi_K", "rate_max_K_h", "flat_s", "tol_K", "start_offset_K", "icpt", "rate_tol_K_h")


def _rules() -> dict[str, float]:
    """The rules' parameters this thermbench checks sensors with."""
    return {"plausible_lo_C": F.PLAUSIBLE_C[0], "plausible_hi_C": F.PLAUSIBLE_C[1], "unknown_start_C": F.UNKNOWN_START_C,
            "range_min_K": F.RANGE_MIN_K, "rate_factor": F.RATE_FACTOR, "rate_min_K_h": F.RATE_MIN_K_H,
            "stuck_factor": F.STUCK_FACTOR, "stuck_min_s": F.STUCK_MIN_S, "stuck_move_K": F.STUCK_MOVE_K}  # fmt: skip


def _neg_inf(v) -> np.ndarray:
    a = np.asarray(v, dtype=float).ravel()
    return np.where(np.isfinite(a), a, -1.0)


def faults_payload(limits: F.SensorLimits | None, bounds: F.Bounds | None) -> tuple[list[int], np.ndarray]:
    """The dims and payload of the faults file of ``limits`` (None: the model reads no temperature)
    and ``bounds`` (None, or a bound that is not finite: none)."""
    n = len(limits.sensors) if limits is not None else 0
    bound = [-1.0, -1.0] if bounds is None else [float(_neg_inf([bounds.max_um])[0]), float(_neg_inf([bounds.rate_um_s])[0])]
    rules = _rules()
    head = [limits.tau_s if limits is not None else F.RATE_WINDOW_S, *(rules[k] for k in SCALARS[1:-2]), *bound]
    if limits is None:
        return [0], np.asarray(head, dtype=float)
    offset = limits.start_offset_K if limits.start_offset_K is not None else np.zeros(n)
    if np.any(~np.isfinite(limits.tol_K) & np.isfinite(limits.rate_tol)):
        raise ValueError("sensor limits with a rate line where there is no rise line cannot be written")
    tols = np.concatenate([limits.tol_K, limits.rate_tol])
    if np.any(np.isfinite(limits.flat_s) & (limits.flat_s < 0)) or np.any(np.isfinite(tols) & (tols <= 0)):
        raise ValueError("sensor limits with a negative stuck time or a tolerance <= 0 cannot be written (-1 means none)")
    coef = np.asarray(limits.coef, dtype=float).copy()
    np.fill_diagonal(coef, 0.0)
    body = [limits.rise_lo_K, limits.rise_hi_K, limits.rate_max_K_h, _neg_inf(limits.flat_s), _neg_inf(limits.tol_K), offset,
            limits.icpt, _neg_inf(limits.rate_tol), coef.ravel()]  # fmt: skip
    return [n], np.concatenate([np.asarray(head, dtype=float), *[np.asarray(b, dtype=float).ravel() for b in body]])


def write_faults(path: Path, limits: F.SensorLimits | None, bounds: F.Bounds | None) -> int:
    """Write the faults file (float32, as every payload) atomically; returns the file's bytes."""
    dims, payload = faults_payload(limits, bounds)
    return fileformat.write(Path(path), fileformat.FAULTS_KIND, dims, payload)


def read_faults(path: Path, sensors=None) -> tuple[F.SensorLimits | None, F.Bounds]:
    """The limits and bounds of a faults file as the C runtime reads them (float32 values; -1 back to
    infinity), ``sensors`` naming its sensors (from the manifest), else ``s0``...; a file written with
    rule parameters other than this thermbench's is refused (its Python monitor would judge otherwise)."""
    path = Path(path)
    mf = fileformat.read(path)
    if mf.kind != fileformat.FAULTS_KIND or len(mf.dims) != 1:
        raise fileformat.ModelFileError(f"{path}: not a faults file (kind {int(mf.kind)})")
    (n,) = mf.dims
    want = len(SCALARS) + len(ARRAYS) * n + n * n
    if mf.payload.size != want:
        raise fileformat.ModelFileError(f"{path}: {mf.payload.size} values, a faults file of {n} sensors has {want}")
    p = mf.payload.astype(float)
    head = dict(zip(SCALARS, p[: len(SCALARS)]))
    for k, v in _rules().items():
        if float(np.float32(v)) != head[k]:
            raise fileformat.ModelFileError(f"{path}: rule parameter {k} = {head[k]:g}, this thermbench checks with {v:g}")
    inf = lambda v: math.inf if v < 0 else float(v)  # noqa: E731
    bounds = F.Bounds(inf(head["max_um"]), inf(head["rate_um_s"]))
    if n == 0:
        return None, bounds
    a = {k: p[len(SCALARS) + i * n : len(SCALARS) + (i + 1) * n] for i, k in enumerate(ARRAYS)}
    coef = p[len(SCALARS) + len(ARRAYS) * n :].reshape(n, n)
    sensors = tuple(sensors) if sensors is not None else tuple(f"s{i}" for i in range(n))
    if len(sensors) != n:
        raise ValueError(f"{path}: {n} sensors, {len(sensors)} names given")
    neg = lambda v: np.where(v < 0, np.inf, v)  # noqa: E731
    limits = F.SensorLimits(sensors, a["rise_lo_K"], a["rise_hi_K"], a["rate_max_K_h"], neg(a["flat_s"]), a["icpt"], coef,
                            neg(a["tol_K"]), a["start_offset_K"], float(head["tau_s"]), neg(a["rate_tol_K_h"]))  # fmt: skip
    return limits, bounds
