"""The lumped thermal network of a spindle (``physics_spindle``, docs/concepts.md "A lumped
thermal network for a spindle", :class:`thermbench.models.lumped.LumpedThermalNetwork`) as the
C runtime's ``LUMPED`` kind.

What the runtime does with it (``embedded/src/tb_kind_lumped.c``) is what
:meth:`LumpedThermalNetwork.simulate` and ``_predict_thermal`` do: the heat
``q = (u/u_ref)^p`` of each process sample is held to the next sample and averaged exactly
over the intervals of a grid of ``step_s`` from the run's first process sample; the chain
advances over each interval with the exact discretisation ``(A_d, B_d)`` of
:func:`~thermbench.models.lumped.chain_matrices`, computed here (the C does no matrix
exponential), the lagged ambient rise with ``a = exp(-step_s / tau_a)``; a query interpolates
the grid states linearly in time, and adds the unlagged sensors' rises at its time (the same
limit + Kalman preprocessing as the MLR kinds, in C).

Payload, after the sample period (0 without unlagged sensors: they need it for their
history), the sensor block (the ambient sensor first, then the other ``sensors_``, as
``required_inputs().sensors``) and the geometric block of :mod:`.encoding`. Every real is a
float32 pair ``R`` = (hi, lo), hi + lo = the double value (a float32 ``A_d`` entry moves a
node's rise by ~6e-8 / (1 - a) of itself: 2e-4 relative for tau = 2e5 s at a 60-s step)::

    u_source   0 feed_mm_min, 1 axis_mm, 2 load_N (tb_sample fields), 3 an input channel
    u_channel  that channel's index in tb_sample.temps_C (0 unless u_source 3)
    u_nonneg   1: u < 0 is refused (a fractional power; thermbench raises there too)
    step_s R, u_ref R, exponent R
    A_d        lower triangle row by row, n (n + 1) / 2 R
    B_d        n R
    gains      n R (um per unit node rise)
    ambient    (dims[3] = 1) sensor index in the block, a R, gain R (um/degC)
    sensors    K sensor indices in the block, then K gains R (um/degC)
    offset     R (um)

dims ``[n, S, K, A]``: nodes, sensors in the block, unlagged sensor terms, lagged ambient (0/1).

The operating input (e.g. ``spindle_rpm``) has no field in ``tb_sample``: it is an input
channel after the temperatures, ``channels[operating]`` when the exporter lists it, else the
next channel after every channel in ``channels`` (the manifest's ``operating`` inputs follow
its ``temperatures``).
"""

from __future__ import annotations

import math

import numpy as np

from .encoding import Encoded, ExportError, _channels_for, geometric_block, sensor_block
from .fileformat import Kind

#: tb_runtime.h: TB_MAX_LUMPED_NODES, TB_MIN_LUMPED_STEP_S, TB_MAX_SENSORS, TB_MAX_WINDOW, TB_MAX_GAP_S
MAX_NODES = 8
MIN_STEP_S = 1.0
MAX_STEP_S = 1e6
MAX_SENSORS = 16
MAX_CHANNEL = 128  # TB_MAX_SENSORS * 4: the largest input channel index
MAX_HISTORY_SAMPLES = 20000
MAX_GAP_S = 60.0
MAX_EXPONENT = 16.0
#: operating columns the runtime reads from tb_sample itself (u_source codes)
SAMPLE_SOURCES = {"feed_mm_min": 0, "axis_mm": 1, "load_N": 2}
CHANNEL_SOURCE = 3


def _pair(v: float) -> list[float]:
    """``v`` as a float32 (hi, lo) pair: hi + lo = v to ~4e-15 relative."""
    hi = float(np.float32(v))
    return [hi, float(v) - hi]


def history_samples(step_s: float, period_s: float) -> int:
    """Samples of the unlagged sensor terms the runtime keeps (``lump_hist_samples``)."""
    g_cap = math.ceil(MAX_GAP_S / step_s - 1e-9) + 3
    return math.ceil(g_cap * step_s / period_s) + 3


def encode_lumped(model, channels: dict[str, int] | None = None, period_s: float = 0.0, where: str = "model") -> Encoded:
    """The ``LUMPED`` model file of a fitted :class:`~thermbench.models.lumped.LumpedThermalNetwork`
    (module docstring); an :class:`ExportError` of one line for what the runtime cannot run."""
    if not hasattr(model, "_z_"):
        raise ExportError(f"{where}: the lumped network is not fitted")
    tau, p, tau_a, _ = model._unpack(model._z_)  # what simulate() runs (no terms: refused above)
    tau = np.asarray(tau, dtype=float)
    n, h = int(tau.size), float(model.step_)
    if n > MAX_NODES:
        raise ExportError(f"{where}: n_nodes = {n} exceeds the C runtime's limit {MAX_NODES} (LUMPED)")
    if not MIN_STEP_S <= h <= MAX_STEP_S:
        raise ExportError(f"{where}: step_s = {h:g} s: the C runtime runs a lumped network on a grid of "
                          f"{MIN_STEP_S:g} to {MAX_STEP_S:g} s")  # fmt: skip
    if not 0.0 < float(p) <= MAX_EXPONENT:
        raise ExportError(f"{where}: exponent {p:g} is outside the C runtime's (0, {MAX_EXPONENT:g}]")
    u_ref = float(model.u_ref_)
    if not 0.0 < u_ref <= 1e30:
        raise ExportError(f"{where}: u_ref {u_ref:g} is outside the C runtime's (0, 1e30]")

    amb = model.ambient_sensor_
    sensors = list(model.sensors_)
    block = ([amb] if amb else []) + [s for s in sensors if s != amb]
    S, K, A = len(block), len(sensors), int(amb is not None)
    if S > MAX_SENSORS:
        raise ExportError(f"{where}: {S} sensors exceed the C runtime's limit {MAX_SENSORS} (LUMPED)")
    if K and not period_s > 0:
        raise ExportError(f"{where}: the sensors' rises at the query time need the log's sample period (got {period_s})")
    if K and history_samples(h, period_s) > MAX_HISTORY_SAMPLES:
        raise ExportError(f"{where}: step_s {h:g} s at a {period_s:g}-s log keeps {history_samples(h, period_s)} "
                          f"samples of sensor history, beyond the C runtime's {MAX_HISTORY_SAMPLES}")  # fmt: skip
    ch = _channels_for(block, channels)

    op = model.operating_
    if op in SAMPLE_SOURCES:
        source, channel = SAMPLE_SOURCES[op], 0
        operating: list[str] = []
    else:
        source, operating = CHANNEL_SOURCE, [op]
        if channels is not None and op in channels:
            channel = int(channels[op])
        else:  # the operating inputs follow every exported channel
            channel = max([*ch.values(), -1]) + 1 if channels is not None else S
        if channel > MAX_CHANNEL:
            raise ExportError(f"{where}: operating input {op!r} at channel {channel}, beyond the C runtime's {MAX_CHANNEL}")
        if any(ch[s] == channel for s in block):
            raise ExportError(f"{where}: operating input {op!r} and a temperature share input channel {channel}")

    ad, bd = model.chain_matrices(tau, h)  # the network's own discretisation (models -> export, one way)
    coef = np.asarray(model._coef_, dtype=float)
    na = int(model._n_states_)
    if na != n + A or coef.size != na + K + 1:
        raise ExportError(f"{where}: the fitted gains ({coef.size}) do not match {n} nodes, {A} ambient lag, {K} sensors")
    body = [float(source), float(channel), float(bool(model.fractional_))]
    body += [*_pair(h), *_pair(u_ref), *_pair(float(p))]
    for i in range(n):
        for j in range(i + 1):
            body += _pair(ad[i, j])
    for i in range(n):
        body += _pair(bd[i])
    for i in range(n):
        body += _pair(coef[i])
    if A:
        body += [float(block.index(amb)), *_pair(math.exp(-h / float(tau_a))), *_pair(coef[n])]
    body += [float(block.index(s)) for s in sensors]
    for k in range(K):
        body += _pair(coef[na + k])
    body += _pair(coef[-1])

    period = float(period_s) if K else 0.0
    payload = [period, *sensor_block(block, model.preprocess, ch, where), *geometric_block(model.geometric_, where), *body]
    return Encoded(Kind.LUMPED, [n, S, K, A], payload, block, needs_load=op == "load_N", period_s=period,
                   notes={"operating_inputs": operating, "operating_channels": {op: channel} if operating else {}})
