"""The linear families on lagged inputs: the thermal-lag family (:class:`thermbench.models.thermal_lag.ThermalLag`) as the C runtime's
``THERMAL_LAG`` kind (``embedded/src/tb_kind_thermal_lag.c``).

What the runtime does is what the model does: each input (a sensor's rise above the run's first
sample, or the operating input over its training scale) is filtered at each chosen time constant
from 0 at the run's first process sample, ``y_k = a y_{k-1} + (1 - a) u_k`` with
``a = exp(-(t_k - t_{k-1}) / tau)`` (:func:`~thermbench.models.thermal_lag.first_order_lag`); the
error at (t, x) is ``A(t) + x B(t)``, with the ridge's standardisation folded in here:

    A = a0 + sum wA_i y_i,  wA_i = coef_i / scale_i,  a0 = intercept - sum coef_i mean_i / scale_i
    B = b0 + sum wB_i y_i   (position terms: the x x lag columns and x itself; 0 at a fixed point)

and a query interpolates A and B linearly between samples (numpy.interp over the log).

Payload, after the sample period (0: any; the lags take each sample's own interval), the sensor block (the sensor inputs, no filters) and
the geometric block (0: the regression predicts the whole reading) of :mod:`.encoding`; every
real ``R`` a float32 (hi, lo) pair::

    u_source   0 feed_mm_min, 1 axis_mm, 2 load_N (tb_sample fields), 3 an input channel
    u_channel  that channel's index in tb_sample.temps_C (0 unless u_source 3)
    u_scale R  (1 without an operating input)
    tau        NT R (s; 0: the input itself)
    inputs     NI codes: a sensor's index in the block, S: the operating input, or S + 1 + k: the
               start state of sensor k (:func:`~thermbench.models.thermal_lag.start_state`; the
               machine's mean level, ``START_MEAN``, is the start states of its sensors, each with
               the mean's weights over their number: the lags are linear)
    a0 R, b0 R
    wA         NI x NT R (input-major, as the model's features; a start state's tau-0 weight 0)
    wB         NI x NT R (with position terms only)
    ref        the start state's reference: its sensor's index in the block, or S: the block's mean
               (layout version 2; version 1 ends at wB and has no start state)

dims ``[S, NI, NT, P, U]``. At most one operating input: a model that chose two is refused in one
line (the runtime carries one operating value per sample).

The linear-with-history family (:class:`thermbench.models.linear_history.LinearHistory`) is the
``LINEAR_HISTORY`` kind (``embedded/src/tb_kind_linear_history.c``): the same body with the delay line's
step ``h R`` after ``u_scale`` and delays (s; 0: the input now) in place of the time constants, each
input delayed by a delay line of step h (:func:`~thermbench.models.linear_history.delay_line`); dims
``[S, NI, ND, P, U, C]``, C the values one input's line holds (:func:`delay_line_length`).
"""

from __future__ import annotations

import numpy as np

from .encoding import Encoded, ExportError, _channels_for, geometric_block, sensor_block
from .fileformat import Kind
from .lumped_encoding import CHANNEL_SOURCE, MAX_CHANNEL, SAMPLE_SOURCES, _pair

#: tb_runtime.h TB_MAX_LAG_TAUS
MAX_TAUS = 8


def _linear_inputs(model, channels, where: str, kind: str):
    """What THERMAL_LAG and LINEAR_HISTORY share: the inputs (sensors, at most one operating input),
    their channels, the operating input's source, channel and scale, and the weights with the ridge's
    standardisation folded in: (sensors, ch, [source, channel, scale pair], codes, [a0, b0], wA, wB, U,
    operating, notes)."""
    if not hasattr(model, "coef_"):
        raise ExportError(f"{where}: the {kind} model is not fitted")
    is_start = getattr(model, "is_start_input", lambda name: False)  # a start state (thermal_lag only)
    inputs = list(model.inputs_)
    sensors = [i for i in inputs if i in model.sensor_names_]
    ops = [i for i in inputs if i not in model.sensor_names_ and not is_start(i)]
    missing = [k for i in inputs if is_start(i) for k in model.start_sensors(i) if k not in sensors]
    if missing:
        raise ExportError(f"{where}: the start state of sensors {missing} whose rises it does not read")
    if len(ops) > 1:
        raise ExportError(f"{where}: it chose {len(ops)} operating inputs {ops}; the C runtime carries one per "
                          "sample (fit it with operating=[one column])")  # fmt: skip
    S = len(sensors)
    ch = _channels_for(sensors, channels)
    source, channel, scale, operating = 0, 0, 1.0, []
    if ops:
        op = ops[0]
        scale = float(model.scale_of_[op])
        if op in SAMPLE_SOURCES:
            source = SAMPLE_SOURCES[op]
        else:
            source, operating = CHANNEL_SOURCE, [op]
            if channels is not None and op in channels:
                channel = int(channels[op])
            else:  # the operating inputs follow every exported channel
                channel = max([*ch.values(), -1]) + 1 if channels is not None else S
            if channel > MAX_CHANNEL:
                raise ExportError(f"{where}: operating input {op!r} at channel {channel}, beyond the C runtime's {MAX_CHANNEL}")
            if any(ch[s] == channel for s in sensors):
                raise ExportError(f"{where}: operating input {op!r} and a temperature share input channel {channel}")
    coef = np.asarray(model.coef_, dtype=float) / np.asarray(model.scale_, dtype=float)
    mean = np.asarray(model.mean_, dtype=float)
    a0 = float(model.intercept_) - float(coef @ mean)
    n = (coef.size - 1) // 2 if model.uses_position_ else coef.size
    if model.uses_position_:  # features [x, lags (n), x * lags (n)]
        b0, wA, wB = float(coef[0]), coef[1 : 1 + n], coef[1 + n : 1 + 2 * n]
    else:
        b0, wA, wB = 0.0, coef, np.zeros(0)
    if hasattr(model, "taus_s_"):  # the columns the model leaves out (a start state's tau 0) back, weight 0
        kept = model.kept_columns()
        full = np.zeros((2, kept.size))
        full[0, kept] = wA
        if wB.size:
            full[1, kept] = wB
        wA, wB = full[0], (full[1] if wB.size else wB)
    head = [float(source), float(channel), *_pair(scale)]
    codes, rows = [], []  # a start state of several sensors' mean: one input each, its weights over their number
    NT = wA.size // max(len(inputs), 1)
    for n, i in enumerate(inputs):
        if is_start(i):
            of = model.start_sensors(i)
            codes += [float(S + 1 + sensors.index(k)) for k in of]
            rows += [(n, 1.0 / len(of))] * len(of)  # the lags are linear: the mean's lag is the lags' mean
        else:
            codes.append(float(sensors.index(i)) if i in sensors else float(S))
            rows.append((n, 1.0))
    if len(rows) != len(inputs):
        def spread(w):
            return np.concatenate([w.reshape(len(inputs), NT)[n] * f for n, f in rows]) if w.size else w
        wA, wB = spread(wA), spread(wB)
    notes = {"operating_inputs": operating, "operating_channels": {operating[0]: channel} if operating else {}}
    return sensors, ch, head, codes, [*_pair(a0), *_pair(b0)], wA, wB, int(bool(ops)), ops, notes


def _pairs(values) -> list[float]:
    return [v for w in values for v in _pair(float(w))]


def encode_thermal_lag(model, channels: dict[str, int] | None = None, period_s: float = 0.0,
                       where: str = "model") -> Encoded:  # fmt: skip
    """The ``THERMAL_LAG`` model file of a fitted thermal-lag model (module docstring)."""
    sensors, ch, head, codes, ab, wA, wB, U, ops, notes = _linear_inputs(model, channels, where, "thermal-lag")
    taus = [float(t) for t in model.taus_s_]
    if len(taus) > MAX_TAUS:
        raise ExportError(f"{where}: {len(taus)} time constants exceed the C runtime's {MAX_TAUS} (THERMAL_LAG)")
    ref = getattr(model, "start_reference_", None)
    if ref is not None and ref not in sensors:
        raise ExportError(f"{where}: the start state's reference sensor {ref!r} is not among the sensors it reads")
    body = [*head, *_pairs(taus), *codes, *ab, *_pairs(wA), *_pairs(wB), float(sensors.index(ref) if ref is not None else len(sensors))]
    payload = [0.0, *sensor_block(sensors, None, ch, where), *geometric_block(model.geometric_, where), *body]
    dims = [len(sensors), len(codes), len(taus), int(bool(model.uses_position_)), U]
    return Encoded(Kind.THERMAL_LAG, dims, payload, sensors, needs_load=bool(ops) and ops[0] == "load_N", notes=notes)


def delay_line_length(delays_s, step_s: float) -> int:
    """The values one input's delay line holds (``C`` of ``LINEAR_HISTORY``): the longest delay's steps
    and three more (the two values around the delayed time, and the one being filled)."""
    return int(np.floor(max(delays_s) / step_s)) + 3


def encode_linear_history(model, channels: dict[str, int] | None = None, period_s: float = 0.0,
                          where: str = "model") -> Encoded:  # fmt: skip
    """The ``LINEAR_HISTORY`` model file of a fitted linear-with-history model
    (:class:`thermbench.models.linear_history.LinearHistory`; ``embedded/src/tb_kind_linear_history.c``):
    the body of THERMAL_LAG with the delay line's step before the delays in place of the time constants,
    dims ``[S, NI, ND, P, U, C]`` (``C``: :func:`delay_line_length`)."""
    sensors, ch, head, codes, ab, wA, wB, U, ops, notes = _linear_inputs(model, channels, where, "linear-history")
    delays, step = [float(d) for d in model.delays_s_], float(model.step_s_)
    if len(delays) > MAX_TAUS:
        raise ExportError(f"{where}: {len(delays)} delays exceed the C runtime's {MAX_TAUS} (LINEAR_HISTORY)")
    C = delay_line_length(delays, step)
    body = [*head, *_pair(step), *_pairs(delays), *codes, *ab, *_pairs(wA), *_pairs(wB)]
    payload = [0.0, *sensor_block(sensors, None, ch, where), *geometric_block(model.geometric_, where), *body]
    dims = [len(sensors), len(codes), len(delays), int(bool(model.uses_position_)), U, C]
    return Encoded(Kind.LINEAR_HISTORY, dims, payload, sensors, needs_load=bool(ops) and ops[0] == "load_N",
                   notes=notes | {"limits": [("delay_line", C)]})
