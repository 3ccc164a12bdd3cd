"""The ball-screw thermal model: core seed 000 physics composed with effects.

``ScrewThermalModel(screw, material, core, effects, numerics).run(motion)``
integrates the temperature field (seed 000 §3.1) and returns a
:class:`~thermbench.sim.history.ThermalHistory` that reads the positioning thermal
error at any (time, axis position) (seed 000 §3.2 and §2.2). The run's prepared
inputs are in :mod:`.prepared`, the read-out in :mod:`.history`, the integrators in
:mod:`.kernels`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import TYPE_CHECKING

import numpy as np

import thermbench

from . import history, kernels, prepared
from .effects import AmbientDrift, Effect, FreeEndBearingHeat, first_order_lag
from .parts import CoreParams, Geometry, Housing, Material, Numerics, Screw, default_housings

if TYPE_CHECKING:  # pragma: no cover
    from .history import ThermalHistory
    from .prepared import Drive, Kept, Prepared


@dataclass
class Motion:
    """What the axis did: samples of time, axis position, speed and axial load.

    Any sampling works; the model resamples linearly to its fine step.
    """

    t_s: np.ndarray
    axis_mm: np.ndarray
    feed_mm_min: np.ndarray
    load_N: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.t_s = np.asarray(self.t_s, dtype=float)
        self.axis_mm = np.asarray(self.axis_mm, dtype=float)
        self.feed_mm_min = np.asarray(self.feed_mm_min, dtype=float)
        if self.load_N is not None:
            self.load_N = np.asarray(self.load_N, dtype=float)
        n = self.t_s.shape[0]
        if n < 2 or self.axis_mm.shape[0] != n or self.feed_mm_min.shape[0] != n:
            raise ValueError("Motion needs at least two samples and equal-length t_s, axis_mm, feed_mm_min")
        if np.any(np.diff(self.t_s) <= 0):
            raise ValueError("Motion.t_s must be strictly increasing")


def _adds_heat(effect: Effect) -> bool:
    """Whether the effect's class adds heat (overrides a heat hook of :class:`Effect`)."""
    cls = type(effect)
    return cls.nut_heat_W is not Effect.nut_heat_W or cls.sources is not Effect.sources


class ScrewThermalModel:
    """Seed 000 §3.1-3.2 finite-difference model composed with effects (pysindy-style).

    Heat parameterisation (seed 000 §4.1): h = k1 v + k2, QB = k3 v, QN = k4 v
    (+ the effects' nut heat). Mounting from seed 004: ``fixed_fixed`` screws need
    the ``fixed_fixed_constraint`` effect (the simulator adds it from config).
    """

    def __init__(
        self,
        screw: Screw,
        material: Material,
        core: CoreParams | None = None,
        effects: list[Effect] | tuple = (),
        numerics: Numerics | None = None,
        housings: dict[str, Housing] | None = None,
    ) -> None:
        self.screw = screw
        self.material = material
        self.core = core or CoreParams()
        self.effects = list(effects)
        self.numerics = numerics or Numerics()
        self.housings = housings or default_housings()
        ids = [e.id for e in self.effects]
        dup = {i for i in ids if ids.count(i) > 1}
        if dup:
            raise ValueError(f"effect(s) listed twice: {sorted(dup)}")

    @property
    def geom(self) -> Geometry:
        return Geometry(self.screw, self.material, self.numerics)

    def effect(self, effect_id: str) -> Effect | None:
        return next((e for e in self.effects if e.id == effect_id), None)

    # -------------------------------------------------------------------
    def drive(self, motion: Motion, duration_s: float | None = None) -> Drive:
        num = self.numerics
        t0 = float(motion.t_s[0])
        span = float(duration_s if duration_s is not None else motion.t_s[-1] - t0)
        n_steps = max(1, int(math.ceil(span / num.macro_dt_s - 1e-9)))
        n_fine = n_steps * num.per_step
        t = t0 + np.arange(n_fine) * num.dt_s
        axis = np.interp(t, motion.t_s, motion.axis_mm)
        v = np.abs(np.interp(t, motion.t_s, motion.feed_mm_min))
        load = None if motion.load_N is None else np.interp(t, motion.t_s, motion.load_N)
        pf = self.core.pf_m
        sign = 1.0 if pf <= 0 else -1.0
        x = np.clip(sign * (axis / 1000.0 - pf), 0.0, self.screw.length_m)
        return prepared.Drive(t_s=t, dt_s=num.dt_s, axis_mm=axis, x_screw_m=x, v_mm_min=v, load_N=load)

    def prepared_key(self) -> tuple:
        return (self.screw, self.numerics.dx_m, self.numerics.dt_s, self.numerics.macro_dt_s, float(self.core.pf_m))

    def prepare(
        self,
        motion: Motion,
        ambient_C: np.ndarray | float | None = None,
        ambient_t_s: np.ndarray | None = None,
        duration_s: float | None = None,
        signals: dict | None = None,
        at_other_pf: Prepared | None = None,
    ) -> Prepared:
        """The part of :meth:`run` that depends on the motion, the ambient series, the
        screw, the numerics and Pf only (see :class:`Prepared`). ``signals``: measured
        series ``{name: (t_s, values)}`` that offsets and slopes may follow (as rises above
        their first value). ``at_other_pf``: this run prepared by a model that differs in Pf
        only (the same motion, ambient and signals; identification's steps in Pf): its
        resampled series are reused, only the nut's path on the screw is made anew."""
        g = self.geom
        num = self.numerics
        if at_other_pf is not None and at_other_pf.key[:-1] == self.prepared_key()[:-1]:
            o = at_other_pf
            sign = 1.0 if self.core.pf_m <= 0 else -1.0
            x = np.clip(sign * (o.drive.axis_mm / 1000.0 - self.core.pf_m), 0.0, self.screw.length_m)
            d = replace(o.drive, x_screw_m=x)
            m = num.per_step
            n_steps = d.t_s.size // m
            cov = kernels.accumulate_cover(
                d.x_screw_m, d.v_mm_min[None, :], m, n_steps, g.n_nodes, num.dx_m, self.screw.nut_length_m / 2.0, g.n_bearing
            )
            return replace(o, key=self.prepared_key(), drive=d, cover=cov[0], v_cover=cov[1], heat=prepared.Kept(),
                           derived={})
        d = self.drive(motion, duration_s)
        m = num.per_step
        n_steps = d.t_s.size // m
        t_b = d.t_s[0] + np.arange(n_steps + 1) * num.macro_dt_s
        if ambient_C is None:
            ambient_C = 20.0
        amb_in = np.asarray(ambient_C, dtype=float)
        if amb_in.ndim == 0:
            ta0 = float(amb_in)
            measured_f = measured_b = None
        else:
            src_t = motion.t_s if ambient_t_s is None else np.asarray(ambient_t_s, dtype=float)
            ta0 = float(amb_in[0])
            measured_f = np.interp(d.t_s, src_t, amb_in)
            measured_b = np.interp(t_b, src_t, amb_in)
        cov = kernels.accumulate_cover(
            d.x_screw_m, d.v_mm_min[None, :], m, n_steps, g.n_nodes, num.dx_m, self.screw.nut_length_m / 2.0, g.n_bearing
        )
        v_mean = d.v_mm_min.reshape(n_steps, m).mean(axis=1)
        sig = {}
        for name, (st, sv) in dict(signals or {}).items():
            sv = np.asarray(sv, dtype=float)
            sig[name] = np.interp(t_b, np.asarray(st, dtype=float), sv - sv[0])
        return prepared.Prepared(self.prepared_key(), d, t_b, ta0, measured_f, measured_b, cov[0], cov[1], v_mean, sig)

    def run(
        self,
        motion: Motion,
        ambient_C: np.ndarray | float | None = None,
        ambient_t_s: np.ndarray | None = None,
        theta0_C: np.ndarray | None = None,
        duration_s: float | None = None,
        method: str | None = None,
        signals: dict | None = None,
    ) -> ThermalHistory:
        """Integrate the temperature field over the motion.

        ``ambient_C``: a constant, or a measured series at ``ambient_t_s`` (default
        the motion's times). Without the ``ambient_drift`` effect the screw sees a
        constant ambient Ta0 = the first value (seed 000 §3.1, T_n(0) = Ta).
        """
        return self.run_prepared(self.prepare(motion, ambient_C, ambient_t_s, duration_s, signals), theta0_C, method)

    def run_prepared(self, p: Prepared, theta0_C: np.ndarray | None = None, method: str | None = None) -> ThermalHistory:
        """:meth:`run` from a :meth:`prepare` result (of this model or of one with the same
        screw, numerics and Pf)."""
        return run_prepared_many(p, [self], theta0_C, method)[0]

    def _grid(self, p: Prepared) -> tuple:
        """(geometry, numerics, drive, nodes, fine samples per step, steps) of a run over ``p``."""
        g, num = self.geom, self.numerics
        return g, num, p.drive, g.n_nodes, num.per_step, p.drive.t_s.size // num.per_step

    def _inputs(self, p: Prepared, theta0_C, shared: dict | None = None) -> "_Inputs":
        """The heat inputs, conductances and ambient of a run over ``p`` (seed 000 §4.1 + effects).
        ``shared``: the conductance and ambient parts already made for models with the same
        k1, k2, lambda and ambient drift (:func:`run_prepared_many`: models that differ in heat
        gains only share them, the same arrays)."""
        if p.key != self.prepared_key():
            raise ValueError("run_prepared: prepared for another screw, numerics or Pf; call prepare() with this model")
        g, num, d, n, m, n_steps = self._grid(p)
        t_b, ta0 = p.t_b_s, p.ta0_C

        # ambient and conductances (shared by models that differ in heat gains only) ---------
        c = self.core
        drift = self.effect(AmbientDrift.id)
        key = (c.k1_W_m2K_per_mm_min, c.k2_W_m2K, c.lambda_W_mK,
               None if drift is None else tuple(getattr(drift, f.name) for f in fields(drift)))
        cached = None if shared is None else shared.get(key)
        if cached is None:
            if drift is not None:
                amb_f = drift.ambient_C(d.t_s, p.measured_f_C, ta0)
                amb_b = drift.ambient_C(t_b, p.measured_b_C, ta0)
                dta_f = amb_f - ta0
                dta_step = dta_f.reshape(n_steps, m).mean(axis=1)
            else:
                amb_b = np.full(t_b.size, ta0)
                # no ambient change: one zero series per run (the fine grid is long), read-only
                dta_f = p.derived.get("zero_fine")
                if dta_f is None:
                    dta_f = p.derived["zero_fine"] = np.zeros(d.t_s.size)
                    dta_f.setflags(write=False)
                dta_step = np.zeros(n_steps)
            nb = g.n_bearing
            h_cov = c.k1_W_m2K_per_mm_min * p.v_cover + c.k2_W_m2K * p.cover
            area = np.full(n, g.side_area_m2)
            area[-1] += g.end_area_m2
            area[:nb] = 0.0
            h_mean = c.k1_W_m2K_per_mm_min * p.v_mean + c.k2_W_m2K
            gk = (h_mean[:, None] - h_cov) * area[None, :]
            cached = (amb_b, dta_f, dta_step, gk, self.material_conductance(c.lambda_W_mK))
            if shared is not None:
                cached = shared.keep(key, cached)  # kept with the run (run_prepared_many)
        amb_b, dta_f, dta_step, gk, cond = cached

        th0 = np.zeros(n) if theta0_C is None else np.asarray(theta0_C, dtype=float).copy()
        # the effects that add heat (an effect whose heat gains are all zero adds none: the basis runs)
        heating = [e for e in self.effects if _adds_heat(e) and not (e.heat_gains and all(getattr(e, k) == 0 for k in e.heat_gains))]
        hkey = (c.k3_W_per_mm_min, c.k4_W_per_mm_min, *((e.id, *(getattr(e, f.name) for f in fields(e))) for e in heating))
        heat = p.heat.get(hkey)
        if heat is None:
            heat = p.heat.keep(hkey, self._heat(p, heating))
        q, extra, sw, sp, qn_mean, qb_mean = heat
        return _Inputs(
            th0=th0, q=q, gk=gk, dta_f=dta_f, dta_step=dta_step, amb_b=amb_b, extra=extra, sw=sw, sp=sp,
            qn_mean=qn_mean, qb_mean=qb_mean, cond=cond,
        )  # fmt: skip

    def _heat(self, p: Prepared, heating: list) -> tuple:
        """The step-mean heat per node and what the explicit scheme and the housings need, from
        k3, k4 and the ``heating`` effects (see :meth:`_inputs`)."""
        g, num, d, n, m, n_steps = self._grid(p)
        c = self.core
        # heat (seed 000 §4.1 + effects) -------------------------------------
        # h = k1 v + k2, QB = k3 v, QN = k4 v (+ the effects' nut heat): their step means are
        # affine in the mean speed; the fine series only for the explicit scheme. An effect whose
        # heat gains are all zero adds no heat (identification's basis runs): it is skipped
        v_mean = p.v_mean
        extras = [x for x in (eff.nut_heat_W(d) for eff in heating) if x is not None]
        extra = np.sum(extras, axis=0) if extras else None
        qb_mean = c.k3_W_per_mm_min * v_mean
        qn_mean = c.k4_W_per_mm_min * v_mean
        if extra is not None:
            qn_mean = qn_mean + extra.reshape(n_steps, m).mean(axis=1)
        srcs = [s for eff in heating for s in eff.sources(g, d)]
        if srcs:
            sw = np.stack([s[0] for s in srcs]).astype(float)
            sp = np.stack([np.broadcast_to(s[1], d.t_s.shape) for s in srcs]).astype(float)
        else:
            sw = np.zeros((0, n))
            sp = np.zeros((0, d.t_s.size))

        half = self.screw.nut_length_m / 2.0
        nb = g.n_bearing
        # step means of (nut heat per node) and (h x covered fraction), both affine in the
        # speed-weighted coverage (Prepared); the effects' extra nut heat takes one more pass
        per_node = num.dx_m / self.screw.nut_length_m
        q_nut = (c.k4_W_per_mm_min * per_node) * p.v_cover
        if extra is not None:
            extra_cov = kernels.accumulate_cover(d.x_screw_m, extra[None, :], m, n_steps, n, num.dx_m, half, nb)[1]
            q_nut = q_nut + per_node * extra_cov
        q = q_nut  # a new array: the bearing heat is added in place
        if nb > 0:
            q[:, :nb] += (qb_mean * num.dx_m / self.screw.fixed_bearing_length_m)[:, None]
        if srcs:
            q = q + (sp.reshape(len(srcs), n_steps, m).mean(axis=2).T @ sw)
        return q, extra, sw, sp, qn_mean, qb_mean

    def _explicit(self, p: Prepared, x: "_Inputs") -> np.ndarray:
        """The seed 000 §3.1 iteration at the fine step (:func:`kernels.explicit_run`)."""
        g, num, d, c = self.geom, self.numerics, p.drive, self.core
        v = d.v_mm_min
        h = c.k1_W_m2K_per_mm_min * v + c.k2_W_m2K
        qb = c.k3_W_per_mm_min * v
        qn = c.k4_W_per_mm_min * v + (0.0 if x.extra is None else x.extra)
        return kernels.explicit_run(
            x.th0, d.x_screw_m, qn, qb, h, x.dta_f, x.sw, x.sp, num.dt_s, num.per_step, num.dx_m,
            self.screw.nut_length_m / 2.0, self.screw.nut_length_m, g.n_bearing, self.screw.fixed_bearing_length_m,
            g.cap_J_K, x.cond, g.side_area_m2, g.end_area_m2,
        )  # fmt: skip

    def _history(self, p: Prepared, x: "_Inputs", theta: np.ndarray, conv_J: np.ndarray) -> ThermalHistory:
        num = self.numerics
        n_steps = p.drive.t_s.size // num.per_step
        housing = _Housings(self, p, theta, x.amb_b, n_steps, x.qn_mean, x.qb_mean)
        return history.ThermalHistory(
            t_s=p.t_b_s, theta_C=theta, ambient_C=x.amb_b, ta0_C=p.ta0_C, housing_C=housing, geom=self.geom,
            core=self.core, effects=self.effects, heat_in_J=x.q.sum(axis=1) * num.macro_dt_s, convected_J=conv_J,
            signals={"speed": p.v_mean, **p.signals_b},
        )  # fmt: skip

    def material_conductance(self, lambda_W_mK: float) -> float:
        """lambda A_s / dx: the conductance between neighbouring nodes."""
        return lambda_W_mK * self.screw.area_m2 / self.numerics.dx_m


@dataclass
class _Inputs:
    """A run's heat inputs, conductances and ambient (:meth:`ScrewThermalModel._inputs`)."""

    th0: np.ndarray
    q: np.ndarray  # (n_steps, n_nodes) step-mean heat per node, W
    gk: np.ndarray  # (n_steps, n_nodes) step-mean convective conductance, W/K
    dta_f: np.ndarray  # ambient change on the fine grid
    dta_step: np.ndarray  # ... its step means
    amb_b: np.ndarray  # the ambient at the step boundaries
    extra: np.ndarray | None  # the effects' extra nut heat on the fine grid
    sw: np.ndarray  # the effects' heat sources: node weights (n_src, n_nodes) ...
    sp: np.ndarray  # ... and powers on the fine grid (n_src, n_fine)
    qn_mean: np.ndarray
    qb_mean: np.ndarray
    cond: float


def run_prepared_many(
    p: Prepared, models: list[ScrewThermalModel], theta0_C: np.ndarray | None = None, method: str | None = None,
    energy: bool = True,
) -> list[ThermalHistory]:
    """:meth:`ScrewThermalModel.run_prepared` for several models over one run: those with the
    same conductances, ambient and material (models that differ in heat gains only, as
    identification's basis runs do) share one integration, each step's matrix factorised once
    (:func:`kernels.macro_run`). The same numbers as one by one. ``energy`` False: the convected
    heat is not accumulated (``convected_J`` empty; identification reads the field only)."""
    out: list[ThermalHistory | None] = [None] * len(models)
    groups: list[list[int]] = []
    xs: list[_Inputs] = []
    # conductances and ambient by (k1, k2, lambda, drift), kept with the run: made once for the models that
    # share them, here and in later calls (identification's steps in a gain effect's own parameters)
    shared: Kept = p.derived.setdefault("conductances", prepared.Kept())
    for i, model in enumerate(models):
        how = method or model.numerics.method
        x = model._inputs(p, theta0_C, shared if model.geom == models[0].geom else None)
        xs.append(x)
        if how == "explicit":
            out[i] = model._history(p, x, model._explicit(p, x), np.zeros(x.q.shape[0]))
            continue
        if not (x.q.any() or x.th0.any() or x.dta_step.any()):
            # no heat, no initial rise, no ambient change: the field stays at zero (the linear
            # scheme maps zero to zero; identification's basis run with every gain at zero)
            n_steps = x.q.shape[0]
            out[i] = model._history(p, x, np.zeros((n_steps + 1, x.th0.size)), np.zeros(n_steps if energy else 0))
            continue
        for idx in groups:
            m0, x0 = models[idx[0]], xs[idx[0]]
            if (m0.geom == model.geom and x0.cond == x.cond and (x0.gk is x.gk or np.array_equal(x0.gk, x.gk))
                    and (x0.dta_step is x.dta_step or np.array_equal(x0.dta_step, x.dta_step))):  # fmt: skip
                idx.append(i)
                break
        else:
            groups.append([i])
    for idx in groups:
        m0, x0 = models[idx[0]], xs[idx[0]]
        g = m0.geom
        theta, conv_J = kernels.macro_run(
            np.stack([xs[i].th0 for i in idx]), np.stack([xs[i].q for i in idx]), x0.gk, x0.dta_step,
            m0.numerics.macro_dt_s, g.cap_J_K, x0.cond, energy,
        )  # fmt: skip
        for r, i in enumerate(idx):
            out[i] = models[i]._history(p, xs[i], theta[r], conv_J[r])
    return out


class _Housings(Mapping):
    """Lumped housing temperatures at the step boundaries (see :class:`Housing`), each
    computed when first read (most runs read none of them: identification's do not unless an
    effect follows a housing)."""

    def __init__(self, model: ScrewThermalModel, p: Prepared, theta, amb_b, n_steps, qn_mean, qb_mean) -> None:
        self._model, self._p, self._theta, self._amb_b = model, p, theta, amb_b
        self._n_steps, self._qn, self._qb = n_steps, qn_mean, qb_mean
        self._names = [*model.housings, "ambient"]
        self._done: dict[str, np.ndarray] = {}
        for name, hs in model.housings.items():
            if hs.source not in _SOURCES or hs.screw_at not in _SCREW_AT:
                raise ValueError(f"housing {name!r}: source must be one of {sorted(_SOURCES)} and screw_at one of "
                                 f"{sorted(_SCREW_AT)}")  # fmt: skip

    def __iter__(self):
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def __getitem__(self, name: str) -> np.ndarray:
        if name not in self._done:
            if name not in self._names:
                raise KeyError(name)
            self._done[name] = self._amb_b.copy() if name == "ambient" else self._one(name)
        return self._done[name]

    def _one(self, name: str) -> np.ndarray:
        """``qn_mean``, ``qb_mean``, the speed: step means (seed 000 §4.1)."""
        model, p, n_steps = self._model, self._p, self._n_steps
        hs = model.housings[name]
        m = model.numerics.per_step
        ta0, th = p.ta0_C, self._theta[:-1]
        if hs.source == "free_bearing":
            fb = model.effect(FreeEndBearingHeat.id)
            q = fb.heat_W(p.drive.v_mm_min).reshape(n_steps, m).mean(axis=1) if fb is not None else np.zeros(n_steps)
        else:
            q = {"nut": self._qn, "fixed_bearing": self._qb, "none": np.zeros(n_steps)}[hs.source]
        if hs.screw_at == "nut":
            cov = p.cover
            covsum = cov.sum(axis=1)
            local = np.where(covsum > 0, (th * cov).sum(axis=1) / np.maximum(covsum, 1e-12), th.mean(axis=1))
        else:
            local = {"fixed_end": lambda: th[:, : max(1, model.geom.n_bearing)].mean(axis=1),
                     "free_end": lambda: th[:, -3:].mean(axis=1),
                     "none": lambda: np.zeros(n_steps)}[hs.screw_at]()  # fmt: skip
        u = hs.gain_K_per_W * q + hs.gain_K_per_mm_min * p.v_mean
        u = u + hs.screw_coupling * local + (self._amb_b[:-1] - ta0)
        return ta0 + first_order_lag(np.append(u, u[-1]), model.numerics.macro_dt_s, hs.tau_s)


_SOURCES = ("nut", "fixed_bearing", "free_bearing", "none")
_SCREW_AT = ("nut", "fixed_end", "free_end", "none")


__getattr__ = thermbench.moved_names(__name__)
