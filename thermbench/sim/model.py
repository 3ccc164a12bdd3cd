"""The ball-screw thermal model: core seed 000 physics composed with effects.

``ScrewThermalModel(screw, material, core, effects, numerics).run(motion)``
integrates the temperature field (seed 000 §3.1) and returns a
:class:`ThermalHistory` that reads the positioning thermal error at any
(time, axis position) (seed 000 §3.2 and §2.2).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields, replace

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
    # heat inputs already made over this run, by k3, k4 and the heating effects' parameters (they
    # do not depend on k1, k2 or lambda: identification's steps in those reuse them); read-only
    heat: "Kept" = field(default_factory=lambda: Kept(), repr=False, compare=False)
    # anything else a caller derives from this run and its Pf alone (identification's read plans)
    derived: dict = field(default_factory=dict, repr=False, compare=False)


@dataclass(frozen=True)
class ReadPlan:
    """Where readings (t, Px) fall on a history's steps and screw nodes
    (:meth:`ThermalHistory.read_plan`): made once, it reads every field of a run that shares
    the steps and Pf (identification's basis)."""

    n_t: int  # steps of the history it was made on
    pf_m: float
    dx_m: float  # its grid
    n_nodes: int
    sign: float  # +1: Pf <= 0, the screw coordinate grows with Px; -1: the other way
    px_mm: np.ndarray
    k: np.ndarray  # per reading, the step before it ...
    w: np.ndarray  # ... and its weight towards the next
    rows: np.ndarray | None  # the steps whose elongation is needed (None: every step)
    rk: np.ndarray  # per reading, its row of the elongation at steps k ...
    rk1: np.ndarray  # ... and k + 1
    m: np.ndarray  # per reading, the node face before it ...
    f: np.ndarray  # ... and its fraction towards the next
    # per reading, its four corners (steps k, k + 1 x faces m, m + 1) in the faces of the rows,
    # flattened (4, readings), and their bilinear weights (4, readings)
    corners: np.ndarray = field(default_factory=lambda: np.zeros((4, 0), dtype=int))
    weights: np.ndarray = field(default_factory=lambda: np.zeros((4, 0)))


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
    # lagged signals already made, by (name, tau_s), read-only: histories of one run with the same
    # steps and signals may share one (identification's basis); None: none kept
    lagged: dict | None = field(default=None, repr=False, compare=False)

    def signal(self, name: str, tau_s: float = 0.0) -> np.ndarray:
        """Signal ``name`` through a first-order lag ``tau_s`` at the step boundaries:
        ``"speed"`` in m/min (exact for the step means: y[k+1] = a y[k] + (1 - a) v[k],
        a = exp(-dt/tau), y[0] = 0; with no lag y[k+1] = v[k]), a temperature rise in K."""
        if self.lagged is None:
            return self._signal(name, tau_s)
        key = (name, float(tau_s))
        y = self.lagged.get(key)
        if y is None:
            if len(self.lagged) >= 64:
                self.lagged.clear()
            y = self.lagged[key] = self._signal(name, tau_s)
            y.setflags(write=False)
        return y

    def _signal(self, name: str, tau_s: float) -> np.ndarray:
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
    def elongation_um(self, rows: np.ndarray | None = None) -> np.ndarray:
        """TEm at the node faces x = 0, dx, ..., N dx, shape (n_t, N + 1) in um (``rows``: at
        those steps only, (len(rows), N + 1)).

        E_n = alpha (T_n - Ta) dx, TEm(n dx) = sum_{i<=n} E_i, TEm(0) = 0
        (seed 000 §3.2), then the mounting/constraint effects.
        """
        sel = slice(None) if rows is None else rows
        u = _face_elongation_um(self.theta_C[sel], self.ambient_C[sel] - self.ta0_C, self.geom)
        for eff in self.effects:
            u = eff.adjust_elongation_um(u, self.geom)
        return u

    def offset_um(self) -> np.ndarray | None:
        """The effects' position-independent offsets at the steps, summed (None: no effect adds one)."""
        offs = [o for o in (eff.offset_um(self) for eff in self.effects) if o is not None]
        return np.sum(offs, axis=0) if offs else None

    def error_um(self, t_s, axis_mm, plan: "ReadPlan | None" = None) -> np.ndarray:
        """Thermal positioning error (measured - commanded, um) at pairs (t, Px).

        Linear in time between steps; within an element TEm is interpolated
        linearly (seed 000 §3.2). Pf < 0: TE = TEm(Px - Pf) + TEa; Pf > 0 the
        axis runs towards the fixed end and TE = -(TEm(Pf - Px) + TEa) (the
        signs are lost in the extracted text of seed 000 §3.2; these are the
        physically consistent ones). TEa = alpha dTa Px (seed 000 §2.2).

        ``plan``: :meth:`read_plan` of the same pairs on a history with this one's steps and
        Pf (identification reads several fields of a run at one set of readings).
        """
        if plan is None:
            plan = self.read_plan(t_s, axis_mm)
        return errors_um([self], plan)[0]

    def read_plan(self, t_s, axis_mm, rows: bool = True) -> "ReadPlan":
        """Where the pairs (t, Px) fall on this history's steps and nodes (see :meth:`error_um`);
        ``rows`` False: the plan reads an elongation given at every step."""
        t = np.atleast_1d(np.asarray(t_s, dtype=float))
        px_mm = np.broadcast_to(np.asarray(axis_mm, dtype=float), t.shape)
        k = np.clip(np.searchsorted(self.t_s, t, side="right") - 1, 0, len(self.t_s) - 2)
        w = np.clip((t - self.t_s[k]) / (self.t_s[k + 1] - self.t_s[k]), 0.0, 1.0)
        g = self.geom
        pf = self.core.pf_m
        sign = 1.0 if pf <= 0 else -1.0
        nodes = np.clip(sign * (px_mm / 1000.0 - pf), 0.0, g.screw.length_m) / g.numerics.dx_m
        m = np.clip(np.floor(nodes).astype(int), 0, g.n_nodes - 1)
        f = nodes - m
        if rows:
            sel = np.unique(np.concatenate([k, k + 1]))
            row_of = np.full(self.t_s.size, -1)
            row_of[sel] = np.arange(sel.size)
            rk, rk1 = row_of[k], row_of[k + 1]
        else:
            sel, rk, rk1 = None, k, k + 1
        nf = g.n_nodes + 1
        corners = np.stack([rk * nf + m, rk * nf + m + 1, rk1 * nf + m, rk1 * nf + m + 1])
        weights = np.stack([(1 - w) * (1 - f), (1 - w) * f, w * (1 - f), w * f])
        return ReadPlan(self.t_s.size, pf, g.numerics.dx_m, g.n_nodes, sign, px_mm, k, w, sel, rk, rk1, m, f,
                        corners, weights)  # fmt: skip

    def error_field_um(self, axis_mm) -> np.ndarray:
        """Error over an axis grid at every step, shape (n_t, n_x): the
        compensation table of seed 000 §4.3 (compensation = -error)."""
        axis_mm = np.asarray(axis_mm, dtype=float)
        tt = np.repeat(self.t_s, axis_mm.size)
        pp = np.tile(axis_mm, self.t_s.size)
        return errors_um([self], self.read_plan(tt, pp, rows=False))[0].reshape(self.t_s.size, axis_mm.size)


def _face_elongation_um(theta_C: np.ndarray, dta_C: np.ndarray, g: Geometry) -> np.ndarray:
    """TEm at the node faces from the field (..., n_t, N) and the ambient change (n_t,):
    E_n = alpha (T_n - Ta) dx, TEm(n dx) = sum_{i<=n} E_i, TEm(0) = 0 (seed 000 §3.2)."""
    e = g.material.alpha_per_K * (theta_C - dta_C[:, None]) * g.numerics.dx_m * 1e6
    u = np.zeros((*e.shape[:-1], e.shape[-1] + 1))
    np.cumsum(e, axis=-1, out=u[..., 1:])
    return u


def _adjusts_elongation(effect: Effect) -> bool:
    """Whether the effect's class changes the elongation at the faces (a mounting constraint)."""
    return type(effect).adjust_elongation_um is not Effect.adjust_elongation_um


def _adds_heat(effect: Effect) -> bool:
    """Whether the effect's class adds heat (overrides a heat hook of :class:`Effect`)."""
    cls = type(effect)
    return cls.nut_heat_W is not Effect.nut_heat_W or cls.sources is not Effect.sources


#: what a run keeps of the inputs it has made (:class:`Kept`), per kind, in bytes
KEEP_BYTES = 64_000_000


class Kept(dict):
    """Inputs kept with a run (tuples of arrays and numbers), read-only, within
    :data:`KEEP_BYTES` in all: past it, what was kept is dropped; a value larger than that
    alone is not kept. The bytes held are counted as values come and go (:meth:`keep`: the
    only way in)."""

    nbytes = 0

    def __init__(self) -> None:
        super().__init__()
        self.nbytes = 0

    @staticmethod
    def _size(value: tuple) -> int:
        return sum(a.nbytes for a in value if isinstance(a, np.ndarray))

    def keep(self, key, value: tuple) -> tuple:
        """Keep ``value`` under ``key``; returns it."""
        n = self._size(value)
        if n > KEEP_BYTES:
            return value
        if key in self:
            self.nbytes -= self._size(self[key])
        if self.nbytes + n > KEEP_BYTES:
            self.clear()
        for a in value:
            if isinstance(a, np.ndarray):
                a.setflags(write=False)
        super().__setitem__(key, value)
        self.nbytes += n
        return value

    def clear(self) -> None:
        super().clear()
        self.nbytes = 0


def errors_um(hists: Sequence[ThermalHistory], plan: ReadPlan) -> np.ndarray:
    """:meth:`ThermalHistory.error_um` of histories of one run at one read plan, shape
    (len(hists), n readings): histories with the same steps, ambient and Pf (identification's
    basis: a run's fields that differ in the heat gains and effects), read in one pass.

    TEm from the elongation at the node faces (seed 000 §3.2, :meth:`ThermalHistory.elongation_um`,
    then each history's mounting/constraint effects), interpolated linearly within an element
    and in time; Pf < 0: TE = TEm(Px - Pf) + TEa, Pf > 0: TE = -(TEm(Pf - Px) + TEa);
    TEa = alpha dTa Px (seed 000 §2.2); then each history's offsets and slopes."""
    h0 = hists[0]
    amb = h0.ambient_C
    g = h0.geom
    for h in hists:
        if h.t_s.size != plan.n_t or h.core.pf_m != plan.pf_m or (h.geom.numerics.dx_m, h.geom.n_nodes) != (plan.dx_m, plan.n_nodes):
            raise ValueError("error_um: the read plan was made for other steps, another Pf or another grid")
        if h.ambient_C is not amb and not np.array_equal(h.ambient_C, amb) or h.ta0_C != h0.ta0_C:
            raise ValueError("errors_um: the histories differ in their ambient")
        if h.geom is not g and h.geom != g:
            raise ValueError("errors_um: the histories differ in their screw, material or grid")
    k, w, m, f = plan.k, plan.w, plan.m, plan.f
    dta_r = (amb[k] * (1 - w) + amb[k + 1] * w) - h0.ta0_C
    sel = slice(None) if plan.rows is None else plan.rows
    tem = np.empty((len(hists), k.size))

    def read(u: np.ndarray) -> np.ndarray:  # faces (n, rows, N + 1) at the readings' corners
        return np.einsum("hjr,jr->hr", u.reshape(u.shape[0], -1)[:, plan.corners], plan.weights)

    # a field whose elongation no effect adjusts: its node sums at the readings (kernels.read_node_sums),
    # the ambient and the scale applied there (TEm = alpha dx 1e6 (sum theta - (m + f) dTa)); the others
    # (a constraint) adjust the elongation at every face of the rows, read at the corners
    adjusted = [i for i, h in enumerate(hists) if any(_adjusts_elongation(e) for e in h.effects)]
    plain = [i for i in range(len(hists)) if i not in adjusted]
    if plain:
        rows = np.arange(plan.n_t) if plan.rows is None else plan.rows
        scale = g.material.alpha_per_K * g.numerics.dx_m * 1e6
        for i in plain:
            sums = kernels.read_node_sums(np.ascontiguousarray(hists[i].theta_C), rows, plan.rk, plan.rk1, m, f, w)
            tem[i] = scale * (sums - (m + f) * dta_r)
    if adjusted:
        u = _face_elongation_um(np.stack([hists[i].theta_C[sel] for i in adjusted]), amb[sel] - h0.ta0_C, g)
        for j, i in enumerate(adjusted):
            for eff in hists[i].effects:
                u[j] = eff.adjust_elongation_um(u[j], g)
        tem[adjusted] = read(u)
    tea = g.material.alpha_per_K * dta_r * plan.px_mm * 1e-3 * 1e6
    out = plan.sign * (tem + tea)
    for i, h in enumerate(hists):
        off = h.offset_um()
        if off is not None:
            out[i] += off[k] * (1 - w) + off[k + 1] * w
        slope = h.slope_um_per_mm()
        if slope is not None:
            out[i] += (slope[k] * (1 - w) + slope[k + 1] * w) * plan.px_mm
    return out


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
            return replace(o, key=self.prepared_key(), drive=d, cover=cov[0], v_cover=cov[1], heat=Kept(), derived={})
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
        return ThermalHistory(
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
    shared: Kept = p.derived.setdefault("conductances", Kept())
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
