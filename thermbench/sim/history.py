"""The temperature field of a run and the thermal error read off it (seed 000 §3.2 and §2.2).

:class:`ThermalHistory` holds the field at the macro-step boundaries and reads the positioning
thermal error at any (time, axis position); :class:`ReadPlan` is where readings fall on its steps
and nodes; :func:`errors_um` reads several histories of one run at one plan in one pass.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import lfilter

from . import kernels
from .effects import Effect
from .parts import CoreParams, Geometry


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
