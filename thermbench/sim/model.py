"""The ball-screw thermal model: core seed 000 physics composed with effects.

``ScrewThermalModel(screw, material, core, effects, numerics).run(motion)``
integrates the temperature field (seed 000 §3.1) and returns a
:class:`ThermalHistory` that reads the positioning thermal error at any
(time, axis position) (seed 000 §3.2 and §2.2).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from . import kernels
from .effects import AmbientDrift, Effect, FreeEndBearingHeat, first_order_lag
from .parts import CoreParams, Geometry, Housing, Material, Numerics, Screw, default_housings


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


@dataclass
class Drive:
    """The motion resampled on the model's fine time grid (seed 000 dt)."""

    t_s: np.ndarray
    dt_s: float
    axis_mm: np.ndarray
    x_screw_m: np.ndarray
    v_mm_min: np.ndarray
    load_N: np.ndarray | None


@dataclass
class Prepared:
    """What a run takes from the motion, the ambient series and the nut's path alone
    (:meth:`ScrewThermalModel.prepare`): the drive, the ambient on the fine and macro
    grids, and the step-averaged nut coverage of every node, plain and speed-weighted.

    Models that differ only in k1..k4, lambda, the housings or the effects' gains give
    the same ``Prepared``, so one serves them all (identification re-runs the model
    many times per run; :meth:`ScrewThermalModel.run_prepared`). ``key``: the screw,
    numerics and Pf it was made for; a model with others refuses it.
    """

    key: tuple
    drive: Drive
    t_b_s: np.ndarray  # macro-step boundaries
    ta0_C: float
    measured_f_C: np.ndarray | None  # the measured ambient on the fine grid (None: constant ta0)
    measured_b_C: np.ndarray | None  # ... on the macro grid
    cover: np.ndarray  # (n_steps, n_nodes) mean covered fraction
    v_cover: np.ndarray  # (n_steps, n_nodes) mean speed x covered fraction
    v_mean: np.ndarray  # (n_steps,) mean speed per step
    # measured signals (temperature rises above the first sample) at the macro-step boundaries
    signals_b: dict = field(default_factory=dict)


@dataclass
class ThermalHistory:
    """Temperature field and derived displacement at the macro-step boundaries."""

    t_s: np.ndarray  # (n_t,)
    theta_C: np.ndarray  # (n_t, n_nodes) screw temperature rise above Ta0
    ambient_C: np.ndarray  # (n_t,) ambient the screw exchanges heat with
    ta0_C: float
    housing_C: dict[str, np.ndarray]
    geom: Geometry
    core: CoreParams
    effects: list[Effect]
    heat_in_J: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per step
    convected_J: np.ndarray = field(default_factory=lambda: np.zeros(0))  # per step (macro only)
    # what offsets and slopes may follow: "speed" (mm/min, step means, n_t - 1) and measured
    # temperature rises (K, at the step boundaries, n_t)
    signals: dict = field(default_factory=dict)

    def signal(self, name: str, tau_s: float = 0.0) -> np.ndarray:
        """Signal ``name`` through a first-order lag ``tau_s`` at the step boundaries:
        ``"speed"`` in m/min (exact for the step means: y[k+1] = a y[k] + (1 - a) v[k],
        a = exp(-dt/tau), y[0] = 0; with no lag y[k+1] = v[k]), a temperature rise in K."""
        if name not in self.signals:
            raise KeyError(f"signal {name!r} is not available to the model; it has {sorted(self.signals)}")
        dt = float(self.t_s[1] - self.t_s[0]) if self.t_s.size > 1 else 1.0
        a = math.exp(-dt / tau_s) if tau_s > 0 else 0.0
        if name == "speed":
            v = np.asarray(self.signals[name], dtype=float) / 1000.0
            y = lfilter([0.0, 1.0 - a], [1.0, -a], np.append(v, v[-1:]))
            return y
        r = np.asarray(self.signals[name], dtype=float)
        y, _ = lfilter([1.0 - a], [1.0, -a], r, zi=[a * r[0]])
        return y

    def slope_um_per_mm(self) -> np.ndarray | None:
        out = None
        for eff in self.effects:
            s = eff.slope_um_per_mm(self)
            if s is not None:
                out = s if out is None else out + s
        return out

    # -- seed 000 §3.2 ------------------------------------------------------
    def elongation_um(self) -> np.ndarray:
        """TEm at the node faces x = 0, dx, ..., N dx, shape (n_t, N + 1) in um.

        E_n = alpha (T_n - Ta) dx, TEm(n dx) = sum_{i<=n} E_i, TEm(0) = 0
        (seed 000 §3.2), then the mounting/constraint effects.
        """
        g = self.geom
        dta = (self.ambient_C - self.ta0_C)[:, None]
        e = g.material.alpha_per_K * (self.theta_C - dta) * g.numerics.dx_m * 1e6
        u = np.concatenate([np.zeros((e.shape[0], 1)), np.cumsum(e, axis=1)], axis=1)
        for eff in self.effects:
            u = eff.adjust_elongation_um(u, g)
        return u

    def offset_um(self) -> np.ndarray:
        off = np.zeros_like(self.t_s)
        for eff in self.effects:
            o = eff.offset_um(self)
            if o is not None:
                off = off + o
        return off

    def error_um(self, t_s, axis_mm) -> np.ndarray:
        """Thermal positioning error (measured - commanded, um) at pairs (t, Px).

        Linear in time between steps; within an element TEm is interpolated
        linearly (seed 000 §3.2). Pf < 0: TE = TEm(Px - Pf) + TEa; Pf > 0 the
        axis runs towards the fixed end and TE = -(TEm(Pf - Px) + TEa) (the
        signs are lost in the extracted text of seed 000 §3.2; these are the
        physically consistent ones). TEa = alpha dTa Px (seed 000 §2.2).
        """
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        px_mm = np.broadcast_to(np.asarray(axis_mm, dtype=float), t.shape)
        u = self.elongation_um()
        return self._read(u, self.offset_um(), self.ambient_C, t, px_mm)

    def _read(self, u, off, amb, t, px_mm):
        slope = self.slope_um_per_mm()
        out = self._read_screw(u, off, amb, t, px_mm)
        if slope is None:
            return out
        k = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, len(self.t_s) - 2)
        w = np.clip((t - self.t_s[k]) / (self.t_s[k + 1] - self.t_s[k]), 0.0, 1.0)
        return out + (slope[k] * (1 - w) + slope[k + 1] * w) * px_mm

    def _read_screw(self, u, off, amb, t, px_mm):
        g = self.geom
        k = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, len(self.t_s) - 2)
        w = np.clip((t - self.t_s[k]) / (self.t_s[k + 1] - self.t_s[k]), 0.0, 1.0)
        pf = self.core.pf_m
        sign = 1.0 if pf <= 0 else -1.0
        x = np.clip(sign * (px_mm / 1000.0 - pf), 0.0, g.screw.length_m)
        nodes = x / g.numerics.dx_m
        m = np.clip(np.floor(nodes).astype(int), 0, u.shape[1] - 2)
        f = nodes - m
        u_k = u[k, m] * (1 - f) + u[k, m + 1] * f
        u_k1 = u[k + 1, m] * (1 - f) + u[k + 1, m + 1] * f
        tem = u_k * (1 - w) + u_k1 * w
        dta = (amb[k] * (1 - w) + amb[k + 1] * w) - self.ta0_C
        tea = g.material.alpha_per_K * dta * px_mm * 1e-3 * 1e6
        return sign * (tem + tea) + off[k] * (1 - w) + off[k + 1] * w

    def error_field_um(self, axis_mm) -> np.ndarray:
        """Error over an axis grid at every step, shape (n_t, n_x): the
        compensation table of seed 000 §4.3 (compensation = -error)."""
        axis_mm = np.asarray(axis_mm, dtype=float)
        tt = np.repeat(self.t_s, axis_mm.size)
        pp = np.tile(axis_mm, self.t_s.size)
        u = self.elongation_um()
        return self._read(u, self.offset_um(), self.ambient_C, tt, pp).reshape(self.t_s.size, axis_mm.size)


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
        return Drive(t_s=t, dt_s=num.dt_s, axis_mm=axis, x_screw_m=x, v_mm_min=v, load_N=load)

    def prepared_key(self) -> tuple:
        return (self.screw, self.numerics.dx_m, self.numerics.dt_s, self.numerics.macro_dt_s, float(self.core.pf_m))

    def prepare(
        self,
        motion: Motion,
        ambient_C: np.ndarray | float | None = None,
        ambient_t_s: np.ndarray | None = None,
        duration_s: float | None = None,
        signals: dict | None = None,
    ) -> Prepared:
        """The part of :meth:`run` that depends on the motion, the ambient series, the
        screw, the numerics and Pf only (see :class:`Prepared`). ``signals``: measured
        series ``{name: (t_s, values)}`` that offsets and slopes may follow (as rises above
        their first value)."""
        g = self.geom
        num = self.numerics
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
        return Prepared(self.prepared_key(), d, t_b, ta0, measured_f, measured_b, cov[0], cov[1], v_mean, sig)

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
        if p.key != self.prepared_key():
            raise ValueError("run_prepared: prepared for another screw, numerics or Pf; call prepare() with this model")
        g = self.geom
        num = self.numerics
        method = method or num.method
        d = p.drive
        n = g.n_nodes
        m = num.per_step
        n_steps = d.t_s.size // m
        t_b, ta0 = p.t_b_s, p.ta0_C

        # ambient -----------------------------------------------------------
        drift = self.effect(AmbientDrift.id)
        if drift is not None:
            amb_f = drift.ambient_C(d.t_s, p.measured_f_C, ta0)
            amb_b = drift.ambient_C(t_b, p.measured_b_C, ta0)
        else:
            amb_f = np.full(d.t_s.size, ta0)
            amb_b = np.full(t_b.size, ta0)
        dta_f = amb_f - ta0

        # heat (seed 000 §4.1 + effects) -------------------------------------
        # h = k1 v + k2, QB = k3 v, QN = k4 v (+ the effects' nut heat): their step means are
        # affine in the mean speed; the fine series only for the explicit scheme
        c = self.core
        v_mean = p.v_mean
        extras = [x for x in (eff.nut_heat_W(d) for eff in self.effects) if x is not None]
        extra = np.sum(extras, axis=0) if extras else None
        qb_mean = c.k3_W_per_mm_min * v_mean
        qn_mean = c.k4_W_per_mm_min * v_mean
        if extra is not None:
            qn_mean = qn_mean + extra.reshape(n_steps, m).mean(axis=1)
        srcs = [s for eff in self.effects for s in eff.sources(g, d)]
        if srcs:
            sw = np.stack([s[0] for s in srcs]).astype(float)
            sp = np.stack([np.broadcast_to(s[1], d.t_s.shape) for s in srcs]).astype(float)
        else:
            sw = np.zeros((0, n))
            sp = np.zeros((0, d.t_s.size))

        cond = self.material_conductance(c.lambda_W_mK)
        th0 = np.zeros(n) if theta0_C is None else np.asarray(theta0_C, dtype=float).copy()
        half = self.screw.nut_length_m / 2.0
        nb = g.n_bearing
        # step means of (nut heat per node) and (h x covered fraction), both affine in the
        # speed-weighted coverage (Prepared); the effects' extra nut heat takes one more pass
        per_node = num.dx_m / self.screw.nut_length_m
        q_nut = (c.k4_W_per_mm_min * per_node) * p.v_cover
        if extra is not None:
            extra_cov = kernels.accumulate_cover(d.x_screw_m, extra[None, :], m, n_steps, n, num.dx_m, half, nb)[1]
            q_nut = q_nut + per_node * extra_cov
        h_cov = c.k1_W_m2K_per_mm_min * p.v_cover + c.k2_W_m2K * p.cover
        cov = p.cover
        q = q_nut
        if nb > 0:
            q = q.copy()
            q[:, :nb] += (qb_mean * num.dx_m / self.screw.fixed_bearing_length_m)[:, None]
        if srcs:
            q = q + (sp.reshape(len(srcs), n_steps, m).mean(axis=2).T @ sw)
        heat_in = q.sum(axis=1) * num.macro_dt_s
        conv_J = np.zeros(n_steps)

        if method == "explicit":
            v = d.v_mm_min
            h = c.k1_W_m2K_per_mm_min * v + c.k2_W_m2K
            qb = c.k3_W_per_mm_min * v
            qn = c.k4_W_per_mm_min * v + (0.0 if extra is None else extra)
            theta = kernels.explicit_run(
                th0, d.x_screw_m, qn, qb, h, dta_f, sw, sp, num.dt_s, m, num.dx_m, half,
                self.screw.nut_length_m, nb, self.screw.fixed_bearing_length_m,
                g.cap_J_K, cond, g.side_area_m2, g.end_area_m2,
            )  # fmt: skip
        else:
            area = np.full(n, g.side_area_m2)
            area[-1] += g.end_area_m2
            area[:nb] = 0.0
            h_mean = c.k1_W_m2K_per_mm_min * v_mean + c.k2_W_m2K
            gk = (h_mean[:, None] - h_cov) * area[None, :]
            dta_step = dta_f.reshape(n_steps, m).mean(axis=1)
            theta, conv_J = kernels.macro_run(th0, q, gk, dta_step, num.macro_dt_s, g.cap_J_K, cond)

        housing = self._housings(d, theta, cov, amb_b, ta0, n_steps, m, qn_mean, qb_mean, v_mean)
        return ThermalHistory(
            t_s=t_b, theta_C=theta, ambient_C=amb_b, ta0_C=ta0, housing_C=housing, geom=g,
            core=self.core, effects=self.effects, heat_in_J=heat_in, convected_J=conv_J,
            signals={"speed": v_mean, **p.signals_b},
        )  # fmt: skip

    def material_conductance(self, lambda_W_mK: float) -> float:
        """lambda A_s / dx: the conductance between neighbouring nodes."""
        return lambda_W_mK * self.screw.area_m2 / self.numerics.dx_m

    def _housings(self, d, theta, cov, amb_b, ta0, n_steps, m, qn_mean, qb_mean, v_step) -> dict[str, np.ndarray]:
        """Lumped housing temperatures at the step boundaries (see :class:`Housing`);
        ``qn_mean``, ``qb_mean``, ``v_step``: the nut and bearing heat and the speed, step means."""
        fb = self.effect(FreeEndBearingHeat.id)
        mean = lambda a: np.asarray(a).reshape(n_steps, m).mean(axis=1)  # noqa: E731
        q_src = {
            "nut": qn_mean,
            "fixed_bearing": qb_mean,
            "free_bearing": mean(fb.heat_W(d.v_mm_min)) if fb is not None else np.zeros(n_steps),
            "none": np.zeros(n_steps),
        }
        th = theta[:-1]
        covsum = cov.sum(axis=1)
        nut_local = np.where(covsum > 0, (th * cov).sum(axis=1) / np.maximum(covsum, 1e-12), th.mean(axis=1))
        local = {
            "nut": nut_local,
            "fixed_end": th[:, : max(1, self.geom.n_bearing)].mean(axis=1),
            "free_end": th[:, -3:].mean(axis=1),
            "none": np.zeros(n_steps),
        }
        out: dict[str, np.ndarray] = {}
        for name, hs in self.housings.items():
            if hs.source not in q_src or hs.screw_at not in local:
                raise ValueError(
                    f"housing {name!r}: source must be one of {sorted(q_src)} and screw_at one of {sorted(local)}"
                )
            u = hs.gain_K_per_W * q_src[hs.source] + hs.gain_K_per_mm_min * v_step
            u = u + hs.screw_coupling * local[hs.screw_at] + (amb_b[:-1] - ta0)
            y = first_order_lag(np.append(u, u[-1]), self.numerics.macro_dt_s, hs.tau_s)
            out[name] = ta0 + y
        out["ambient"] = amb_b.copy()
        return out
