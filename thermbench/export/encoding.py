"""Fitted thermbench models -> compact model files (the payload layouts of each kind).

Every payload starts with the sample period ``period_s`` (0: any sampling; the GRU
history and the classifier window need a uniformly sampled log), then, for models
that read temperatures, the **sensor block**::

    channel[S]                        index of each sensor in the exported input list
    per sensor: n_steps, (type, p1, p2) x 4   preprocessing chain (seed 002 §2.3.1):
                                      type 1 limit filter (limit_C, max_hold or 0),
                                      type 2 Kalman (R, Q); unused steps are zeros

then the **geometric block** (the geometric error the model separated)::

    gtype, n, off, scl, data..., m, origin, extra[m]
    gtype 0: none; 1: polynomial sum_i c_i (off + scl x)^i (numpy Polynomial with its
    domain map, n = degree + 1); 2: table x[n] (increasing), y[n], linear in between;
    plus sum_k extra_k (x - origin)^k (the AR model's cold-state curve)

then the kind's body (see each ``_encode_*``). Temperatures enter as rises dT above
the run's first filtered sample, as in the Python models.

Which encoder a fitted model gets: its class's own ``export_encoding`` if it has one, else the
built-in family registered for its class or a base class with :func:`family` (one decorator
line per family); :data:`KIND_LIMITS` holds each kind's limits (one line per kind).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from numpy.polynomial import Polynomial

from ..models.base import ModelError, ThermalErrorModel
from ..preprocess.filters import KalmanFilter, LimitFilter, resolve_steps
from .fileformat import Kind

MAX_FILTER_STEPS = 4
FSTEP_VALS = 5  # type, p1 (float32 hi, lo), p2 (hi, lo): the limit keeps its double value
SENSOR_VALS = 1 + FSTEP_VALS * MAX_FILTER_STEPS
#: the C runtime's limits (tb_runtime.h); a model beyond them is refused at export, not by the loader
LIMITS = {"sensors": 32, "poly": 16, "table": 4096, "support": 65536, "layers": 8, "width": 256, "gru_hidden": 128,
          "lags": 4096, "nodes": 4096, "ar_order": 64, "ar_terms": 8, "levels": 64, "conditions": 64,
          "window_samples": 20000, "lumped_nodes": 8, "effects": 8, "lag_taus": 8, "delay_line": 4096,
          "members": 8}  # fmt: skip
ACTIVATION_CODES = {"tanh": 1, "relu": 2, "gelu": 3, "silu": 4, "sigmoid": 5}


class ExportError(ValueError):
    """A model that cannot be exported as asked; the message says which part and why."""


@dataclass
class Encoded:
    """One model file's content and what its manifest says about it."""

    kind: Kind
    dims: list[int]
    payload: list[float]
    sensors: list[str] = field(default_factory=list)  # in channel order of this file
    needs_load: bool = False
    period_s: float = 0.0
    notes: dict = field(default_factory=dict)


# ------------------------------------------------------------------ blocks ---
def split_f32(values) -> list[float]:
    """``values`` as float32 hi parts then lo parts (hi + lo = the value to ~1e-14 relative):
    LSSVM weights are large and cancel, and float32 alone would move a prediction by
    ~1e-8 x sum|alpha| (0.006 um on the seed000_x bank); a filter threshold keeps its value."""
    v = np.atleast_1d(np.asarray(values, dtype=float))
    hi = v.astype(np.float32).astype(float)
    return [*hi, *(v - hi)]


#: per kind, the (limit, value) pairs of its dims that :func:`check_limits` compares with :data:`LIMITS`
KIND_LIMITS: dict[Kind, Callable[[list[int]], list[tuple[str, int]]]] = {
    Kind.MLR_CURVE: lambda d: [("sensors", d[0]), ("poly", d[1] + 1)],
    Kind.MLR_SEED001: lambda d: [("poly", d[1])],
    Kind.LSSVM: lambda d: [("sensors", d[0]), ("support", d[1])],
    Kind.MLP: lambda d: [("sensors", d[0]), ("layers", d[1])],
    Kind.GRU: lambda d: [("sensors", d[0]), ("gru_hidden", d[1]), ("poly", d[2] + 1), ("lags", d[3])],
    Kind.PHYSICS: lambda d: [("nodes", d[1])],
    Kind.AR: lambda d: [("poly", d[0] + 1), ("ar_order", d[1]), ("ar_order", d[2]), ("ar_terms", d[3])],
    Kind.CLASSIFIER: lambda d: [("conditions", d[0]), ("levels", max(d[1:4]))],
    Kind.LUMPED: lambda d: [("lumped_nodes", d[0]), ("sensors", d[1])],
    Kind.THERMAL_LAG: lambda d: [("sensors", d[0]), ("lag_taus", d[2])],
    Kind.LINEAR_HISTORY: lambda d: [("sensors", d[0]), ("lag_taus", d[2]), ("delay_line", d[5])],
    Kind.ENSEMBLE: lambda d: [("members", d[0])],
}


def check_limits(enc: "Encoded", where: str) -> "Encoded":
    """Refuse what the C runtime would refuse (:data:`LIMITS`), with the reason. A kind
    without an entry in :data:`KIND_LIMITS` is a KeyError (a registration missing)."""
    d, k = enc.dims, enc.kind
    checks = KIND_LIMITS[k](d)
    for name, value in checks:
        if value > LIMITS[name]:
            raise ExportError(f"{where}: {name} = {value} exceeds the C runtime's limit {LIMITS[name]} "
                              f"({k.name}); a smaller model is needed (e.g. export.lssvm_reduced_size for an LSSVM)")  # fmt: skip
    for name, value in enc.notes.get("limits", []):
        if value > LIMITS[name]:
            raise ExportError(f"{where}: {name} = {value} exceeds the C runtime's limit {LIMITS[name]} ({k.name})")
    return enc


def filter_chain(preprocess, column: str, where: str) -> list[float]:
    """The sensor block entries of one sensor: n_steps then 4 (type, p1, p2) triples."""
    try:
        steps = resolve_steps(preprocess)
    except ValueError as exc:
        raise ExportError(f"{where}: preprocess: {exc}") from None
    if len(steps) > MAX_FILTER_STEPS:
        raise ExportError(f"{where}: preprocess has {len(steps)} steps; the runtime runs at most {MAX_FILTER_STEPS}")
    out = [float(len(steps))]
    for s in steps:
        if type(s) is LimitFilter:
            limit, max_hold = s._check()
            out += [1.0, *split_f32(limit), *split_f32(float(max_hold or 0))]
        elif type(s) is KalmanFilter:
            R, Q = s.params_for(column)
            out += [2.0, *split_f32(R), *split_f32(Q)]
        else:
            raise ExportError(
                f"{where}: preprocess step {type(s).__name__} has no C implementation "
                "(the runtime runs LimitFilter and KalmanFilter, seed 002 §2.3.1)"
            )
    return out + [0.0] * (FSTEP_VALS * (MAX_FILTER_STEPS - len(steps)))


def sensor_block(sensors: Sequence[str], preprocess, channels: dict[str, int], where: str) -> list[float]:
    out = [float(channels[s]) for s in sensors]
    for s in sensors:
        out += filter_chain(preprocess, f"{s}_C", where)
    return out


def geometric_block(geom, where: str) -> list[float]:
    """The geometric block of a fitted geometric-error callable."""
    from ..models.autoregressive import _GeometricPlusCurve
    from ..models.separation import TargetTable

    extra: list[float] = [0.0, 0.0]
    if isinstance(geom, _GeometricPlusCurve):
        extra = [float(geom.coef.size), geom.origin_mm, *map(float, geom.coef)]
        geom = geom.base
    if geom is None:
        head = [0.0, 0.0, 0.0, 0.0]
    elif isinstance(geom, Polynomial):
        off, scl = geom.mapparms()
        head = [1.0, float(geom.coef.size), float(off), float(scl), *map(float, geom.coef)]
    elif isinstance(geom, TargetTable):
        head = [2.0, float(geom.axis_mm.size), 0.0, 0.0, *map(float, geom.axis_mm), *map(float, geom.error_um)]
    else:
        raise ExportError(f"{where}: geometric error of type {type(geom).__name__} has no file encoding")
    return head + extra


def _channels_for(sensors: Sequence[str], channels: dict[str, int] | None) -> dict[str, int]:
    if channels is None:
        return {s: i for i, s in enumerate(sensors)}
    missing = [s for s in sensors if s not in channels]
    if missing:
        raise ExportError(f"sensors {missing} are not among the exported inputs {list(channels)}")
    return channels


# ------------------------------------------------------------------ families ---
#: the built-in families: fitted class ``"module:QualName"`` (its subclasses included) -> its encoder
#: ``(model, channels, period_s, where, **options) -> Encoded``; filled by :func:`family`
FAMILIES: dict[str, Callable[..., "Encoded"]] = {}


def family(model_class: str):
    """Register the decorated function as the encoder of ``model_class`` (``"module:QualName"``)
    and its subclasses. The class is named, not imported: ``encode`` resolves it along the
    fitted model's MRO (the nearest registered class wins), so families that import torch
    load only when used."""

    def register(fn: Callable[..., "Encoded"]) -> Callable[..., "Encoded"]:
        FAMILIES[model_class] = fn
        return fn

    return register


def family_encoder(cls: type) -> Callable[..., "Encoded"] | None:
    """The registered encoder of ``cls`` or of its nearest registered base class."""
    for klass in cls.__mro__:
        fn = FAMILIES.get(f"{klass.__module__}:{klass.__qualname__}")
        if fn is not None:
            return fn
    return None


# ------------------------------------------------------------------ kinds ---
def encode_mlr_curve(m, channels=None, where: str = "model") -> Encoded:
    """The ``MLR_CURVE`` kind: seed 002 eq. 6-11 / seed 004. Body: origin, coef[(D+1) x (1+S)]
    (row i: k_i0, k_i1..). Any fitted model with ``sensors_``, ``preprocess``, ``geometric_``,
    ``origin_``, ``shape_degree_`` and ``curve_coef_`` of that form can use it from its
    ``export_encoding`` (docs/extending.md)."""
    S, D = len(m.sensors_), int(m.shape_degree_)
    ch = _channels_for(m.sensors_, channels)
    payload = [0.0, *sensor_block(m.sensors_, m.preprocess, ch, where), *geometric_block(m.geometric_, where)]
    payload += [float(m.origin_), *np.asarray(m.curve_coef_, dtype=float).ravel()]
    return Encoded(Kind.MLR_CURVE, [S, D], payload, list(m.sensors_))


@family("thermbench.models.mlr:_CurveRegression")
def _encode_curve_regression(m, channels, period_s, where, **_) -> Encoded:
    """MLRSeed002 and MLRSeed004: :func:`encode_mlr_curve`."""
    return encode_mlr_curve(m, channels, where)


@family("thermbench.models.mlr:MLRSeed001")
def _encode_mlr001(m, channels, period_s, where, **_) -> Encoded:
    """seed 001 eq. 12. Body: origin, a1..am, b1, c."""
    ch = _channels_for(m.sensors_, channels)
    payload = [0.0, *sensor_block(m.sensors_, m.preprocess, ch, where), *geometric_block(m.geometric_, where)]
    payload += [float(m.origin_), *np.asarray(m._coef_vector_, dtype=float)]
    return Encoded(Kind.MLR_SEED001, [2, int(m.degree_)], payload, list(m.sensors_))


@family("thermbench.models.lssvm:PSOLSSVM")
def _encode_lssvm(m, channels, period_s, where, lssvm_reduced: dict | None = None, **_) -> Encoded:
    """seed 002 eq. 12-14. Body: mean[d], scale[d], sigma2, b (hi, lo), alpha hi[N], lo[N],
    sv[N x d] (d = S + 1,
    features [dT..., position]); ``lssvm_reduced``: a reduced-set expansion (:mod:`.reduce`)."""
    reduced = lssvm_reduced
    r = m.regressor_
    S = len(m.sensors_)
    ch = _channels_for(m.sensors_, channels)
    alpha, sv, b = (r.alpha_, r.X_fit_, r.b_) if reduced is None else (reduced["alpha"], reduced["sv"], reduced["b"])
    payload = [0.0, *sensor_block(m.sensors_, m.preprocess, ch, where), *geometric_block(m.geometric_, where)]
    payload += [*map(float, r.mean_), *map(float, r.scale_), float(r.sigma2_), *split_f32(b)]
    payload += [*split_f32(alpha), *np.asarray(sv, dtype=float).ravel()]
    return Encoded(Kind.LSSVM, [S, int(np.asarray(alpha).size)], payload, list(m.sensors_))


def _linear_layers(net) -> tuple[list, str | None]:
    from torch import nn

    from ..models.neural import ACTIVATIONS

    layers, act = [], None
    for mod in net.body:
        if isinstance(mod, nn.Linear):
            layers.append(mod)
        else:
            name = next((k for k, v in ACTIVATIONS.items() if isinstance(mod, v)), None)
            if name is None:
                raise ExportError(f"MLP layer {type(mod).__name__} has no C implementation")
            act = name
    return layers, act


@family("thermbench.models.neural:MLPModel")
def _encode_mlp(m, channels, period_s, where, **_) -> Encoded:
    """Body: in_mean[d], in_scale[d], y_mean, y_scale, widths[L], then per layer W (out x in), b."""
    S = len(m.sensors_)
    ch = _channels_for(m.sensors_, channels)
    layers, act = _linear_layers(m.net_)
    act = act or m.activation
    payload = [0.0, *sensor_block(m.sensors_, m.preprocess, ch, where), *geometric_block(m.geometric_, where)]
    payload += [*map(float, m.input_mean_[0]), *map(float, m.input_scale_[0]), m.y_mean_um_, m.y_scale_um_]
    payload += [float(l.out_features) for l in layers]
    for l in layers:
        payload += [*l.weight.detach().double().numpy().ravel(), *l.bias.detach().double().numpy()]
    return Encoded(Kind.MLP, [S, len(layers), ACTIVATION_CODES[act]], payload, list(m.sensors_),
                   notes={"limits": [("width", max(l.out_features for l in layers))]})


@family("thermbench.models.neural:GRUModel")
def _encode_gru(m, channels, period_s: float, where, **_) -> Encoded:
    """Body: step_s, seq_mean[S], seq_scale[S], p_mean, p_scale, y_mean, y_scale, W_ih (3H x S),
    W_hh (3H x H), b_ih, b_hh (PyTorch gate order r, z, n), head W ((D+1) x H), head b."""
    if not period_s > 0:
        raise ExportError(f"{where}: the GRU history needs the log's sample period (got {period_s})")
    S = len(m.sensors_)
    ch = _channels_for(m.sensors_, channels)
    g, head = m.net_.gru, m.net_.head
    H = int(g.hidden_size)
    D = int(m.net_.degree)
    t = lambda x: x.detach().double().numpy().ravel()  # noqa: E731
    payload = [period_s, *sensor_block(m.sensors_, m.preprocess, ch, where), *geometric_block(m.geometric_, where)]
    payload += [float(m.step_s), *map(float, m.input_mean_[0]), *map(float, m.input_scale_[0])]
    payload += [float(m.input_mean_[1][0]), float(m.input_scale_[1][0]), m.y_mean_um_, m.y_scale_um_]
    payload += [*t(g.weight_ih_l0), *t(g.weight_hh_l0), *t(g.bias_ih_l0), *t(g.bias_hh_l0), *t(head.weight), *t(head.bias)]
    return Encoded(Kind.GRU, [S, H, D, int(m.n_lags_)], payload, list(m.sensors_), period_s=period_s,
                   notes={"limits": [("window_samples", int(math.ceil(m.n_lags_ * float(m.step_s) / period_s)))]})


#: the physics payload's core block, after the sensor and geometric blocks (tb_kind_physics.c: P_*)
PHYSICS_CORE = (
    "dx_m dt_s per_step macro_dt_s n_nodes n_bearing nut_length_m fixed_bearing_length_m length_m cap_J_K "
    "cond_W_K side_area_m2 end_area_m2 alpha_per_K k1 k2 k3 k4 pf_m"
).split()


@dataclass(frozen=True)
class PhysicsGrid:
    """What an effect's ``export_params(geom)`` may read besides its own parameters: the
    physics model's grid and housings (``thermbench.sim.parts``)."""

    n_nodes: int
    n_bearing: int
    dx_m: float
    dt_s: float
    macro_dt_s: float
    housings: Mapping[str, Any]


def exportable_effects() -> list[str]:
    """The ids of the registered effects (canonical and open terms) the C runtime implements."""
    from ..sim.effects import EFFECTS
    from ..sim.open_terms import OPEN_TERMS

    return sorted(i for i, cls in {**OPEN_TERMS, **EFFECTS}.items() if vars(cls).get("export_code") is not None)


def effect_sections(effects, geom: PhysicsGrid, where: str) -> list[float]:
    """The effect list of a physics payload (v2): n_effects, then per effect in increasing
    ``export_code`` order its section ``(code, n_params, params...)`` with the numbers of its
    ``export_params(geom)``. An effect whose class declares no ``export_code`` (an open term, a
    new effect without its C file) is an ExportError naming it."""
    missing = [e.id for e in effects if vars(type(e)).get("export_code") is None]
    if missing:
        what = f"effect {missing[0]!r} has" if len(missing) == 1 else f"effects {', '.join(map(repr, missing))} have"
        raise ExportError(f"{where}: {what} no C implementation; the runtime implements {exportable_effects()} "
                          "(docs/extending.md, 'The C side')")  # fmt: skip
    sections = []
    for e in effects:
        try:
            params = [float(v) for v in e.export_params(geom)]
        except ValueError as exc:
            raise ExportError(f"{where}: effect {e.id!r}: {exc}") from None
        sections.append((int(vars(type(e))["export_code"]), e.id, params))
    sections.sort(key=lambda c: c[0])
    for a, b in zip(sections, sections[1:]):
        if a[0] == b[0]:
            raise ExportError(f"{where}: effects {a[1]!r} and {b[1]!r} share the export code {a[0]}")
    out = [float(len(sections))]
    for code, _, params in sections:
        out += [float(code), float(len(params)), *params]
    return out


@family("thermbench.models.physics:PhysicsModel")
def _encode_physics(m, channels, period_s, where, **_) -> Encoded:
    """seed 000 §3.1-3.2 + effects (payload v2). Body: the core (:data:`PHYSICS_CORE`), then the
    effects as sections (:func:`effect_sections`); a measured ambient is the sensor block's one
    sensor (dims[0] = 1), else ``ambient_drift`` (if present) simulates it."""
    sm = m.model_
    g, core, num = sm.geom, sm.core, sm.numerics
    sensors = [m.ambient_name_] if m.ambient_name_ else []
    ch = _channels_for(sensors, channels)
    n = g.n_nodes
    vals = {
        "dx_m": num.dx_m, "dt_s": num.dt_s, "per_step": num.per_step, "macro_dt_s": num.macro_dt_s, "n_nodes": n,
        "n_bearing": g.n_bearing, "nut_length_m": sm.screw.nut_length_m,
        "fixed_bearing_length_m": sm.screw.fixed_bearing_length_m, "length_m": sm.screw.length_m,
        "cap_J_K": g.cap_J_K, "cond_W_K": sm.material_conductance(core.lambda_W_mK), "side_area_m2": g.side_area_m2,
        "end_area_m2": g.end_area_m2, "alpha_per_K": sm.material.alpha_per_K, "k1": core.k1_W_m2K_per_mm_min,
        "k2": core.k2_W_m2K, "k3": core.k3_W_per_mm_min, "k4": core.k4_W_per_mm_min, "pf_m": core.pf_m,
    }  # fmt: skip
    grid = PhysicsGrid(n, g.n_bearing, num.dx_m, num.dt_s, num.macro_dt_s, sm.housings)
    payload = [0.0, *sensor_block(sensors, m.preprocess, ch, where), *geometric_block(m.geometric_, where)]
    payload += [float(vals[k]) for k in PHYSICS_CORE]
    payload += effect_sections(sm.effects, grid, where)
    return Encoded(Kind.PHYSICS, [len(sensors), n], payload, sensors,
                   needs_load=any("load_N" in type(e).needs for e in sm.effects),
                   notes={"limits": [("effects", len(sm.effects))]})  # fmt: skip


@family("thermbench.models.autoregressive:AutoRegressiveSeed003")
def _encode_ar(m, channels, period_s, where, **_) -> Encoded:
    """seed 003 (our reading). Body: origin, sample_s, nu x (column code 0 feed / 1 load, power),
    ar[(D+1) x na], input[(D+1) x nb x nu], offset[D+1]."""
    codes = {"feed_mm_min": 0, "load_N": 1}
    terms = []
    for col, power in m.operating_:
        if col not in codes:
            raise ExportError(f"{where}: operating column {col!r}: the runtime reads feed_mm_min and load_N only")
        terms += [float(codes[col]), float(power)]
    D = int(m.shape_degree_)
    payload = [0.0, *geometric_block(m.geometric_, where), float(m.origin_), float(m.sample_), *terms]
    payload += [*np.asarray(m.ar_coef_, dtype=float).ravel(), *np.asarray(m.input_coef_, dtype=float).ravel()]
    payload += [*np.asarray(m.offset_, dtype=float)]
    return Encoded(Kind.AR, [D, int(m.na_), int(m.nb_), len(m.operating_)], payload,
                   needs_load=any(c == "load_N" for c, _ in m.operating_))  # fmt: skip


def _check_c_bank(bank, where: str) -> None:
    """What the C runtime's bank does: a hard switch (seed 002 §2.5) on the axis motion of
    the sample (tb_sample: axis_mm, feed_mm_min); a bank classified on an operating input
    (a spindle speed: tb_sample has no such field) or blending its members is refused."""
    inputs = tuple(getattr(bank, "condition_inputs_", ()))
    if inputs:
        raise ExportError(f"{where}: a bank classified on the operating input(s) {list(inputs)} cannot be exported "
                          "to the C runtime yet (it classifies the axis motion only)")  # fmt: skip
    if getattr(bank, "blend", "hard") != "hard":
        raise ExportError(f"{where}: a soft bank (blend {bank.blend!r}) cannot be exported to the C runtime yet "
                          "(it switches to one member: blend 'hard')")  # fmt: skip


def encode_classifier(bank, period_s: float, where: str = "classifier") -> Encoded:
    """seed 002 eq. 15-19 with the bank's window. Body: window_s, step_s, min_moving_s,
    levels A[nA] (stroke), B[nB] (start + end), C[nC] (feed), then per condition its
    three level indices (conditions in the classifier's class order). A bank classified
    on an operating input, or a soft bank, is an ExportError (:func:`_check_c_bank`)."""
    from ..models.classify import FACTORS, ProximityNaiveBayes

    _check_c_bank(bank, where)
    clf = bank.classifier_
    if type(clf) is not ProximityNaiveBayes:
        raise ExportError(f"{where}: classifier {type(clf).__name__} has no C implementation (ProximityNaiveBayes has)")
    if not period_s > 0:
        raise ExportError(f"{where}: the motion window needs the log's sample period (got {period_s})")
    lv = [np.asarray(clf.levels_[f], dtype=float) for f in FACTORS]
    payload = [period_s, float(bank.window_s), float(bank.step_s), float(bank.min_moving_s)]
    payload += [*lv[0], *lv[1], *lv[2], *np.asarray(clf.condition_levels_, dtype=float).ravel()]
    enc = Encoded(Kind.CLASSIFIER, [len(clf.classes_), lv[0].size, lv[1].size, lv[2].size], payload, period_s=period_s,
                  notes={"limits": [("window_samples", int(math.ceil(float(bank.window_s) / period_s)))]})
    if float(bank.step_s) < period_s:
        raise ExportError(f"{where}: step_s {bank.step_s} s is shorter than the log's sample period {period_s} s")
    return check_limits(enc, where)


def encode(model: ThermalErrorModel, channels: dict[str, int] | None = None, period_s: float = 1.0,
           where: str = "model", lssvm_reduced: dict | None = None) -> Encoded:  # fmt: skip
    """The file content of one fitted model of any family but the bank (see :func:`thermbench.export.bundle`).

    A family of its own exports when its class defines ``export_encoding(channels, period_s,
    where) -> Encoded`` for a kind the C runtime evaluates, e.g. with :func:`encode_mlr_curve`;
    the built-in families are registered with :func:`family`."""
    if not hasattr(model, "train_runs_"):
        raise ExportError(f"{where}: the model is not fitted")
    try:
        if callable(getattr(type(model), "export_encoding", None)):  # a family of its own
            enc = model.export_encoding(channels, period_s, where)
            if not isinstance(enc, Encoded):
                raise ExportError(f"{where}: {type(model).__name__}.export_encoding returned {type(enc).__name__}, not Encoded")
        else:
            fn = family_encoder(type(model))
            if fn is None:
                raise ExportError(f"{where}: no file encoding for {type(model).__name__}")
            enc = fn(model, channels, period_s, where, lssvm_reduced=lssvm_reduced)
    except ModelError as exc:
        raise ExportError(f"{where}: {exc}") from None
    return check_limits(enc, where)


#: tb_kind_ensemble.c: a member's record before its payload: kind, layout version, n_dims, dims[8], n_payload
MAX_DIMS = 8


def encode_ensemble(model, channels: dict[str, int] | None = None, period_s: float = 1.0,
                    where: str = "model") -> Encoded:  # fmt: skip
    """The ``ENSEMBLE`` model file of a fitted stacked ensemble
    (:class:`thermbench.models.ensemble.StackedEnsemble`; ``embedded/src/tb_kind_ensemble.c``): the
    period (0), no sensors, a zero geometric block, the weights as (hi, lo) pairs, then each member's
    record (kind, layout version, n_dims, dims padded to 8, n_payload) and its payload as in its own
    file, every member of weight above 0 (one of weight 0 adds nothing to the sum) encoded on the same input channels (``channels``; None: the ensemble's sensors
    then its operating inputs, in order). dims ``[N, K]``, K the set of the members' kinds (bit k for
    kind k: what a firmware image must carry, read from the header). A member the runtime cannot run is refused
    with its reason."""
    from .fileformat import kind_version

    # the fitted ensemble's weights and members, read without importing its class (the model calls this
    # encoder through its export_encoding hook: models -> export, one way)
    if not all(hasattr(model, a) for a in ("weights_", "members_", "member_names_")):
        raise ExportError(f"{where}: the ensemble is not fitted")
    ins = model.required_inputs()
    if channels is None:
        channels = {s: i for i, s in enumerate([*ins.sensors, *ins.operating])}
    body, members = [], []
    # a member of weight 0 adds nothing to the sum: it is left out of the file (its state would cost RAM)
    keep = [i for i, w in enumerate(model.weights_) if float(w) != 0.0]
    for i in keep:  # (hi, lo) pairs
        hi = float(np.float32(model.weights_[i]))
        body += [hi, float(model.weights_[i]) - hi]
    for name, m in [(model.member_names_[i], model.members_[i]) for i in keep]:
        e = encode(m, channels, period_s, f"{where}: member {name}")
        if e.kind == Kind.ENSEMBLE:
            raise ExportError(f"{where}: member {name} is an ensemble itself; the C runtime does not nest them")
        if len(e.dims) > MAX_DIMS:
            raise ExportError(f"{where}: member {name} has {len(e.dims)} dims, beyond the file's {MAX_DIMS}")
        body += [float(int(e.kind)), float(kind_version(e.kind)), float(len(e.dims)),
                 *[float(d) for d in [*e.dims, *[0] * (MAX_DIMS - len(e.dims))]], float(len(e.payload)), *e.payload]
        members.append(e)
    payload = [0.0, *sensor_block([], None, {}, where), *geometric_block(Polynomial([0.0]), where), *body]
    notes = {"operating_inputs": list(dict.fromkeys(c for e in members for c in e.notes.get("operating_inputs", []))),
             "operating_channels": {k: v for e in members for k, v in e.notes.get("operating_channels", {}).items()},
             "members": members, "limits": [n for e in members for n in e.notes.get("limits", [])]}  # fmt: skip
    kinds = sum(1 << int(k) for k in {e.kind for e in members})  # the kinds inside, for a firmware image's table
    return Encoded(Kind.ENSEMBLE, [len(members), kinds], payload, [], needs_load=any(e.needs_load for e in members),
                   notes=notes)


def export_blocker(model) -> str | None:
    """Why ``model`` cannot go to the C runtime, in one line, or None when it can: what
    ``thermbench benchmark`` checks before choosing a model to deploy. Encodes the model (and
    a bank's classifier and members) without writing anything."""
    from ..models.bank import ConditionBank

    try:
        if isinstance(model, ConditionBank):
            encode_classifier(model, period_s=1.0, where="the bank's classifier")
            for label, member in model.models_.items():
                encode(member, where=f"the bank's member {label!r}")
        else:
            encode(model)
    except ExportError as exc:
        return str(exc)
    return None
