"""Open-ended terms: generic parametric forms for physics the canonical library lacks.

The canonical effects (:data:`thermbench.sim.effects.EFFECTS`) name what seed 000
leaves out and the simulator can make. Real machines miss more (intermediate support
bearings, coolant in hollow screws, column and saddle growth, scale mounts, preload
loss), so the discrepancy search also fits these generic terms, each a small
:class:`~thermbench.sim.effects.Effect` that describes its identified form in words
and numbers (:meth:`describe`) and says which canonical effect it is when it falls
within tolerance of one (:meth:`canonical`):

* :class:`HeatSource`: a heat source at an unknown place s on the screw, power
  q (v / 6000 mm/min)^p, lagging the speed by tau (the free-end bearing, the motor
  coupling and mid-length supports are special cases);
* :class:`NutHeatPower`: extra nut friction heat q (v / 6000 mm/min)^p with a fitted
  exponent (p = 2: the viscous ``quadratic_friction_heat``);
* :class:`DrivenOffset`: a position-independent offset g lag_tau(s(t)) driven by the
  axis speed or by any measured temperature channel (structure growth, origin drift);
* :class:`ReferencedExpansion`: a position-proportional expansion
  a lag_tau(s(t)) (Px - P0) with a free reference point P0, driven the same way
  (ambient, bed or scale expansion referenced elsewhere than the axis origin).

The signal ``s`` is ``"speed"`` (the axis speed, m/min) or the name of a temperature
sensor (its filtered rise above the run's first sample, K); the model feeds both
through ``ThermalHistory.signals``. Offsets and expansions do not touch the
temperature field (``field_free``): their gains and lag cost no simulation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Mapping

import numpy as np

from .effects import Effect, first_order_lag

#: open-ended terms (:mod:`thermbench.sim.open_terms`): generic parametric forms that the
#: discrepancy search fits beside the canonical effects and describes in words and numbers
OPEN_TERMS: dict[str, type[Effect]] = {}

#: the speed the heat terms' power is quoted at (mm/min)
V_REF_MM_MIN = 6000.0
#: lags shorter than this are described as "no lag" (s)
NO_LAG_S = 120.0


def _lag_words(tau_s: float) -> str:
    if tau_s < NO_LAG_S:
        return "no lag"
    return f"lagging by {tau_s / 3600:.1f} h" if tau_s >= 5400 else f"lagging by {tau_s / 60:.0f} min"


def _signal_words(signal: str, context: Mapping | None) -> tuple[str, str]:
    """(what the signal is, its unit) in words."""
    if signal == "speed":
        return "the axis speed", "m/min"
    where = dict((context or {}).get("sensors", {})).get(signal)
    return (f"{signal} ({where})" if where else signal), "K"


def _node_weights(n: int, dx_m: float, centre_m: float, length_m: float) -> np.ndarray:
    """Weights (sum 1) of the nodes under an interval of ``length_m`` centred at ``centre_m``,
    by overlap, so that they move continuously with the centre; clipped to the screw."""
    half = max(length_m, dx_m) / 2.0
    lo = min(max(centre_m - half, 0.0), n * dx_m - 2 * half)
    hi = lo + 2 * half
    edges = np.arange(n + 1) * dx_m
    w = np.clip(np.minimum(edges[1:], hi) - np.maximum(edges[:-1], lo), 0.0, None)
    return w / w.sum()


def _register(cls):
    OPEN_TERMS[cls.id] = cls
    return cls


@_register
@dataclass
class HeatSource(Effect):
    """A heat source on the screw at ``at_frac`` of its length from the fixed end, spread
    over ``length_m``: Q = q (v / 6000 mm/min)^p through a first-order lag ``tau_s``."""

    id: ClassVar[str] = "heat_source"
    description: ClassVar[str] = "a heat source at an unknown place on the screw, q*(v/6000)^p, lagging by tau"
    heat_gains: ClassVar[tuple[str, ...]] = ("q_W",)
    nonlinear: ClassVar[tuple[str, ...]] = ("at_frac", "p", "tau_s")
    bounds: ClassVar[dict[str, tuple[float, float]]] = {"at_frac": (0.0, 1.0), "p": (0.25, 3.0), "tau_s": (0.0, 2e4)}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {"at_frac": (0.1, 0.3, 0.55, 0.8, 0.97)}
    q_W: float = 1.0
    at_frac: float = 0.5
    p: float = 1.0
    tau_s: float = 0.0
    length_m: float = 0.03

    def power_W(self, v_mm_min: np.ndarray, dt_s: float) -> np.ndarray:
        u = self.q_W * (np.abs(v_mm_min) / V_REF_MM_MIN) ** self.p
        return first_order_lag(u, dt_s, self.tau_s)

    def sources(self, geom, drive):
        n, dx = geom.n_nodes, geom.numerics.dx_m
        w = _node_weights(n, dx, self.at_frac * n * dx, self.length_m)
        return [(w, self.power_W(drive.v_mm_min, drive.dt_s))]

    def describe(self, context: Mapping | None = None) -> str:
        L = (context or {}).get("length_m")
        where = f"near {self.at_frac * L:.2f} m along the screw" if L else "along the screw"
        return (f"a heat source {where} ({self.at_frac:.0%} of its length from the fixed end), ∝ v^{self.p:.1f}, "
                f"{_lag_words(self.tau_s)}, {self.q_W:.2g} W at {V_REF_MM_MIN:.0f} mm/min")  # fmt: skip

    def canonical(self, context: Mapping | None = None) -> str | None:
        linear = abs(self.p - 1.0) <= 0.35
        if linear and self.at_frac >= 0.85 and self.tau_s <= 600.0:
            return "free_end_bearing_heat"
        if linear and self.at_frac <= 0.1 and self.tau_s >= 300.0:
            return "motor_heat"
        return None


@_register
@dataclass
class NutHeatPower(Effect):
    """More nut friction heat with a fitted speed exponent: dQN = q (v / 6000 mm/min)^p."""

    id: ClassVar[str] = "nut_heat_power"
    description: ClassVar[str] = "extra nut friction heat q*(v/6000)^p with a fitted exponent"
    heat_gains: ClassVar[tuple[str, ...]] = ("q_W",)
    nonlinear: ClassVar[tuple[str, ...]] = ("p",)
    bounds: ClassVar[dict[str, tuple[float, float]]] = {"p": (0.25, 4.0)}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {"p": (0.6, 1.6, 2.7)}
    q_W: float = 1.0
    p: float = 1.5

    def nut_heat_W(self, drive):
        return self.q_W * (np.abs(drive.v_mm_min) / V_REF_MM_MIN) ** self.p

    def describe(self, context: Mapping | None = None) -> str:
        return (f"more nut friction heat ∝ v^{self.p:.1f}, {self.q_W:.2g} W at {V_REF_MM_MIN:.0f} mm/min "
                "(beyond the core's k4·v)")  # fmt: skip

    def canonical(self, context: Mapping | None = None) -> str | None:
        return "quadratic_friction_heat" if abs(self.p - 2.0) <= 0.3 else None


class _Driven(Effect):
    """What the signal-driven terms share: a signal, its lag and the words for them."""

    choice: ClassVar[str | None] = "signal"
    field_free: ClassVar[bool] = True
    nonlinear: ClassVar[tuple[str, ...]] = ("tau_s",)
    bounds: ClassVar[dict[str, tuple[float, float]]] = {"tau_s": (0.0, 5e4)}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {"tau_s": (0.0, 2400.0, 9000.0, 20000.0)}

    def driver(self, history) -> np.ndarray:
        """The signal through the lag, at the history's steps."""
        return history.signal(self.signal, self.tau_s)


@_register
@dataclass
class DrivenOffset(_Driven):
    """A position-independent offset ``g lag_tau(s(t))``: a growth off the screw (column,
    saddle) or a drift of the origin that follows the speed or a measured temperature."""

    id: ClassVar[str] = "driven_offset"
    description: ClassVar[str] = "a position-independent offset g*lag_tau(signal)"
    heat_gains: ClassVar[tuple[str, ...]] = ("g_um_per_unit",)
    signed_gains: ClassVar[tuple[str, ...]] = ("g_um_per_unit",)
    g_um_per_unit: float = 1.0
    tau_s: float = 0.0
    signal: str = "speed"

    def offset_um(self, history):
        return self.g_um_per_unit * self.driver(history)

    def describe(self, context: Mapping | None = None) -> str:
        what, unit = _signal_words(self.signal, context)
        return f"a position-independent offset of {self.g_um_per_unit:.2g} µm per {unit} of {what}, {_lag_words(self.tau_s)}"

    def canonical(self, context: Mapping | None = None) -> str | None:
        where = dict((context or {}).get("sensors", {})).get(self.signal)
        if where == "fixed_bearing_housing" and self.tau_s <= 600.0:
            return "origin_drift"
        return None


@_register
@dataclass
class ReferencedExpansion(_Driven):
    """A position-proportional expansion ``lag_tau(s(t)) (a Px/1000 - b)`` = ``a lag_tau(s)
    (Px - P0)/1000`` with P0 = 1000 b / a: a scale, bed or ambient expansion referenced at
    a point other than the axis origin. a and b are both gains (the error is affine in
    them), so P0 costs no search."""

    id: ClassVar[str] = "referenced_expansion"
    description: ClassVar[str] = "a position-proportional expansion a*lag_tau(signal)*(Px - P0)"
    heat_gains: ClassVar[tuple[str, ...]] = ("a_um_per_m_unit", "b_um_per_unit")
    signed_gains: ClassVar[tuple[str, ...]] = ("a_um_per_m_unit", "b_um_per_unit")
    a_um_per_m_unit: float = 1.0
    b_um_per_unit: float = 1.0
    tau_s: float = 0.0
    signal: str = "speed"

    def offset_um(self, history):
        return -self.b_um_per_unit * self.driver(history)

    def slope_um_per_mm(self, history):
        return self.a_um_per_m_unit / 1000.0 * self.driver(history)

    @property
    def p0_mm(self) -> float:
        return 1000.0 * self.b_um_per_unit / self.a_um_per_m_unit if self.a_um_per_m_unit else math.nan

    def describe(self, context: Mapping | None = None) -> str:
        what, unit = _signal_words(self.signal, context)
        p0 = f"about P0 = {self.p0_mm:.0f} mm" if math.isfinite(self.p0_mm) else "with no slope"
        return (f"a position-proportional expansion of {self.a_um_per_m_unit:.2g} µm per m of travel per {unit} of "
                f"{what} {p0}, {_lag_words(self.tau_s)}")  # fmt: skip

    def canonical(self, context: Mapping | None = None) -> str | None:
        ctx = dict(context or {})
        where = dict(ctx.get("sensors", {})).get(self.signal)
        travel = ctx.get("travel_mm")
        if where == "ambient" and self.tau_s <= 600.0 and travel and abs(self.p0_mm) <= 0.1 * (travel[1] - travel[0]):
            return "ambient_drift"
        return None
