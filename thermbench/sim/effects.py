"""Composable physical effects on top of the core seed 000 ball-screw model.

Each effect is a small class with named, unit-carrying parameters and one job.
They hook into the model through six methods; every hook defaults to "no
change", so an effect that is not in the model contributes exactly zero:

* ``nut_heat_W(drive)``: extra nut friction power added to QN;
* ``sources(geom, drive)``: extra heat sources, each (node weights, power per fine sample);
* ``ambient_C(t_s, measured_C, ta0_C)``: the varying ambient the screw exchanges
  heat with; :meth:`ScrewThermalModel.run` calls it only on the effect with id
  ``ambient_drift``, so it is not a general hook;
* ``adjust_elongation_um(u, geom)``: changes the growth read off the temperature field;
* ``offset_um(history)``: adds a position-independent offset;
* ``slope_um_per_mm(history)``: adds an error proportional to the axis position.

``history.signals`` holds the signals an offset or a slope may follow, per step:
``speed`` (mm/min) and, when the model is given them, measured temperature rises.

``heat_gains`` names an effect's heat-input gains: the error is affine in them,
and the identified physics model solves them by linear least squares. Other
parameters may be affine too (``origin_drift.beta_um_per_K``) without being
heat gains; those are searched by SLSQP when named in ``identify``.

The canonical ids (used by configs, the discrepancy workflow and export) are the
keys of :data:`EFFECTS`; :mod:`.registry` builds an effect or an open term by id, and the
effects of a config.

Each effect class describes itself, so that adding one touches this module (and, for the
C runtime, its encoder): besides ``heat_gains`` it declares

* ``nonlinear``: parameters the discrepancy search identifies by SQP when it tries the effect;
* ``bounds``: their search bounds; ``starts``: the start values the search screens;
* ``needs``: what a dataset must have for the effect to be tried (``load_N``: the process
  column; ``ambient_sensor``: a sensor at location ``ambient``);
* ``reference``, ``scaled``, ``caps``: how the discrepancy tests' hidden-data generator makes
  it (reference parameters, the ones a strength multiplies, their caps).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from numbers import Real
from typing import TYPE_CHECKING, ClassVar, Mapping

import numpy as np
from scipy.signal import lfilter

import thermbench

if TYPE_CHECKING:  # pragma: no cover
    from .history import ThermalHistory
    from .parts import Geometry
    from .prepared import Drive


def first_order_lag(u: np.ndarray, dt_s: float, tau_s: float, y0: float = 0.0) -> np.ndarray:
    """Exact zero-order-hold response of tau dy/dt = u - y, sampled at the input samples.

    ``y[k+1] = a y[k] + (1 - a) u[k]``, a = exp(-dt/tau); returns y at the same
    instants as u (y[0] = y0).
    """
    u = np.asarray(u, dtype=float)
    if tau_s <= 0:
        return u.copy()
    a = math.exp(-dt_s / tau_s)
    y, _ = lfilter([0.0, 1.0 - a], [1.0, -a], u, zi=[y0])
    return y


@dataclass
class Effect:
    """Base class: an effect that changes nothing."""

    id: ClassVar[str] = ""
    description: ClassVar[str] = ""
    # parameters that scale a heat input: the error is affine in them when every
    # other parameter is fixed (the identified physics model solves them linearly)
    heat_gains: ClassVar[tuple[str, ...]] = ()
    # self-description (module docstring): the search and the hidden-data generator read these
    nonlinear: ClassVar[tuple[str, ...]] = ()
    bounds: ClassVar[dict[str, tuple[float, float]]] = {}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {}
    needs: ClassVar[tuple[str, ...]] = ()
    reference: ClassVar[dict[str, float]] = {}
    scaled: ClassVar[tuple[str, ...]] = ()
    caps: ClassVar[dict[str, float]] = {}
    # gains that may take either sign (an offset, an expansion); heat gains are >= 0
    signed_gains: ClassVar[tuple[str, ...]] = ()
    # a parameter that names a driving signal (``"speed"`` or a temperature sensor), not a number
    choice: ClassVar[str | None] = None
    # the C runtime's implementation (embedded/src/tb_fx_<id>.c, docs/extending.md "The C side"): the code
    # of the effect's section in a physics model file; None: export refuses the effect. Export reads it
    # from the class itself only: a subclass that changes the physics is not silently its parent in C
    export_code: ClassVar[int | None] = None

    def nut_heat_W(self, drive: "Drive") -> np.ndarray | None:
        return None

    def sources(self, geom: "Geometry", drive: "Drive") -> list[tuple[np.ndarray, np.ndarray]]:
        return []

    def ambient_C(self, t_s: np.ndarray, measured_C: np.ndarray | None, ta0_C: float) -> np.ndarray | None:
        return None

    def adjust_elongation_um(self, u_um: np.ndarray, geom: "Geometry") -> np.ndarray:
        return u_um

    def offset_um(self, history: "ThermalHistory") -> np.ndarray | None:
        return None

    def slope_um_per_mm(self, history: "ThermalHistory") -> np.ndarray | None:
        """An error proportional to the axis position Px (per step: um per mm of Px), from
        a growth off the screw (a scale, the bed) about the axis origin."""
        return None

    def params(self) -> dict[str, float]:
        return asdict(self)

    def export_params(self, geom) -> list[float]:
        """The numbers of the effect's section in a physics model file, in the order its C file
        reads them; ``geom`` is the model's grid (:class:`thermbench.export.encoding.PhysicsGrid`:
        ``n_nodes``, ``n_bearing``, ``dx_m``, ``dt_s``, ``macro_dt_s``, ``housings``). A
        ValueError says why this effect's values cannot be exported."""
        raise ValueError(f"effect {self.id!r} has no C implementation")

    def describe(self, context: Mapping | None = None) -> str:
        """The identified effect in words and numbers (open terms say more)."""
        nums = ", ".join(f"{k} = {v:.4g}" for k, v in self.params().items() if isinstance(v, Real))
        return f"{self.id} ({nums})"

    def canonical(self, context: Mapping | None = None) -> str | None:
        """The canonical effect this identified effect is (``context``: what the data say
        about its signals, e.g. sensor locations); a canonical effect is itself."""
        return self.id if self.id in EFFECTS else None


@dataclass
class AmbientDrift(Effect):
    """Ambient temperature varies over the day (seed 000 §2.2, seed 001 eq. 2).

    The screw convects to the current ambient Ta(t) and the axis grows by
    TEa = alpha (Ta(t) - Ta(t0)) Px. With a measured ambient series the model
    uses it; otherwise (in the simulator) Ta(t) = Ta0 + amplitude sin(2 pi (t +
    phase)/period) - amplitude sin(2 pi phase/period) + rate t.
    """

    id: ClassVar[str] = "ambient_drift"
    description: ClassVar[str] = "ambient temperature varies; screw follows it and the axis grows alpha*dTa*x"
    needs: ClassVar[tuple[str, ...]] = ("ambient_sensor",)
    reference: ClassVar[dict[str, float]] = {"amplitude_C": 1.0, "period_s": 86400.0, "phase_s": 0.0, "rate_C_per_h": 0.2}
    scaled: ClassVar[tuple[str, ...]] = ("amplitude_C", "rate_C_per_h")
    export_code: ClassVar[int | None] = 1
    amplitude_C: float = 1.5
    period_s: float = 86400.0
    phase_s: float = 0.0
    rate_C_per_h: float = 0.0

    def export_params(self, geom):
        return [self.amplitude_C, self.period_s, self.phase_s, self.rate_C_per_h]

    def ambient_C(self, t_s, measured_C, ta0_C):
        if measured_C is not None:
            return np.asarray(measured_C, dtype=float)
        w = 2.0 * math.pi / self.period_s
        t = np.asarray(t_s, dtype=float) - float(np.asarray(t_s)[0])
        return (
            ta0_C
            + self.amplitude_C * (np.sin(w * (t + self.phase_s)) - math.sin(w * self.phase_s))
            + self.rate_C_per_h * t / 3600.0
        )


@dataclass
class FreeEndBearingHeat(Effect):
    """The support/free-end bearing adds friction heat QF = kF v over its length
    at the far end of the screw (seed 000 §2.1 assumes it is zero)."""

    id: ClassVar[str] = "free_end_bearing_heat"
    description: ClassVar[str] = "free/support-end bearing friction heat kF*v at the far end"
    heat_gains: ClassVar[tuple[str, ...]] = ("kF_W_per_mm_min",)
    reference: ClassVar[dict[str, float]] = {"kF_W_per_mm_min": 0.5e-3}
    scaled: ClassVar[tuple[str, ...]] = ("kF_W_per_mm_min",)
    export_code: ClassVar[int | None] = 5
    kF_W_per_mm_min: float = 0.5e-3
    length_m: float = 0.03

    def export_params(self, geom):
        k = max(1, int(math.ceil(self.length_m / geom.dx_m - 1e-9)))  # the slices sources() heats
        if k > geom.n_nodes:
            raise ValueError(f"length_m = {self.length_m} m covers {k} slices, more than the screw's {geom.n_nodes}")
        return [self.kF_W_per_mm_min, float(k)]

    def sources(self, geom, drive):
        n = geom.n_nodes
        k = max(1, int(math.ceil(self.length_m / geom.numerics.dx_m - 1e-9)))
        w = np.zeros(n)
        w[n - k :] = 1.0 / k
        return [(w, self.kF_W_per_mm_min * drive.v_mm_min)]

    def heat_W(self, v_mm_min):
        return self.kF_W_per_mm_min * np.asarray(v_mm_min)


@dataclass
class MotorHeat(Effect):
    """Servo-motor heat enters the fixed end through the coupling (seed 000 §2.1
    takes the coupling as adiabatic). Q_M = k_motor * lag_tau(v): the motor's
    over-temperature follows the speed with a first-order lag of tens of minutes,
    so heat keeps flowing after the axis stops."""

    id: ClassVar[str] = "motor_heat"
    description: ClassVar[str] = "motor heat through the coupling into the fixed end, lagging the speed"
    heat_gains: ClassVar[tuple[str, ...]] = ("k_motor_W_per_mm_min",)
    nonlinear: ClassVar[tuple[str, ...]] = ("tau_s",)
    bounds: ClassVar[dict[str, tuple[float, float]]] = {"tau_s": (1.0, 1e5)}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {"tau_s": (600.0, 1800.0, 5400.0)}
    reference: ClassVar[dict[str, float]] = {"k_motor_W_per_mm_min": 0.4e-3, "tau_s": 1800.0}
    scaled: ClassVar[tuple[str, ...]] = ("k_motor_W_per_mm_min",)
    export_code: ClassVar[int | None] = 4
    k_motor_W_per_mm_min: float = 0.4e-3
    tau_s: float = 1800.0

    def export_params(self, geom):
        return [self.k_motor_W_per_mm_min, self.tau_s]

    def sources(self, geom, drive):
        w = np.zeros(geom.n_nodes)
        w[0] = 1.0
        lagged = first_order_lag(drive.v_mm_min, drive.dt_s, self.tau_s)
        return [(w, self.k_motor_W_per_mm_min * lagged)]


@dataclass
class OriginDrift(Effect):
    """The fixed-bearing housing grows and shifts the screw's fixed point: a
    position-independent offset beta (T_fixed_bearing_housing(t) - T0)
    (the intercept term of seed 002 eq. 6, regressed in eq. 9)."""

    id: ClassVar[str] = "origin_drift"
    description: ClassVar[str] = "fixed-point shift beta*(T_fixed_bearing_housing - T0), position-independent"
    nonlinear: ClassVar[tuple[str, ...]] = ("beta_um_per_K",)
    bounds: ClassVar[dict[str, tuple[float, float]]] = {"beta_um_per_K": (0.0, np.inf)}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {"beta_um_per_K": (1.0,)}
    reference: ClassVar[dict[str, float]] = {"beta_um_per_K": 2.0}
    scaled: ClassVar[tuple[str, ...]] = ("beta_um_per_K",)
    export_code: ClassVar[int | None] = 7
    beta_um_per_K: float = 2.0

    def export_params(self, geom):
        h = geom.housings.get("fixed_bearing_housing")
        if h is None or h.source != "fixed_bearing" or h.screw_at != "fixed_end":
            raise ValueError("the runtime models the fixed-bearing housing driven by the fixed bearing at the "
                             f"fixed end; this model's housing is {h}")  # fmt: skip
        return [self.beta_um_per_K, h.tau_s, h.gain_K_per_W, h.gain_K_per_mm_min, h.screw_coupling]

    def offset_um(self, history):
        th = history.housing_C["fixed_bearing_housing"]
        return self.beta_um_per_K * (th - th[0])


@dataclass
class FixedFixedConstraint(Effect):
    """Both ends held (seed 004, fixed-fixed): a fraction kappa of the free
    elongation is suppressed by a uniform compressive strain, so
    u(x) = u_free(x) - kappa (x / L) u_free(L); with non-uniform heating the
    error over the travel becomes the seed 004 parabola."""

    id: ClassVar[str] = "fixed_fixed_constraint"
    description: ClassVar[str] = "fixed-fixed mounting suppresses a fraction kappa of the free elongation"
    nonlinear: ClassVar[tuple[str, ...]] = ("kappa",)
    bounds: ClassVar[dict[str, tuple[float, float]]] = {"kappa": (0.0, 1.0)}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {"kappa": (0.3, 0.8)}
    reference: ClassVar[dict[str, float]] = {"kappa": 0.3}
    scaled: ClassVar[tuple[str, ...]] = ("kappa",)
    caps: ClassVar[dict[str, float]] = {"kappa": 0.95}
    export_code: ClassVar[int | None] = 6
    kappa: float = 0.8

    def export_params(self, geom):
        return [self.kappa]

    def adjust_elongation_um(self, u_um, geom):
        n = u_um.shape[-1]
        frac = np.linspace(0.0, 1.0, n)
        return u_um - self.kappa * u_um[..., -1:] * frac


@dataclass
class QuadraticFrictionHeat(Effect):
    """The nut's friction heat has a viscous part: QN = k4 v + k5 v^2."""

    id: ClassVar[str] = "quadratic_friction_heat"
    description: ClassVar[str] = "viscous nut friction: QN = k4*v + k5*v^2"
    heat_gains: ClassVar[tuple[str, ...]] = ("k5_W_per_mm_min2",)
    reference: ClassVar[dict[str, float]] = {"k5_W_per_mm_min2": 5e-8}
    scaled: ClassVar[tuple[str, ...]] = ("k5_W_per_mm_min2",)
    export_code: ClassVar[int | None] = 2
    k5_W_per_mm_min2: float = 5e-8

    def export_params(self, geom):
        return [self.k5_W_per_mm_min2]

    def nut_heat_W(self, drive):
        return self.k5_W_per_mm_min2 * drive.v_mm_min**2


@dataclass
class LoadDependentHeat(Effect):
    """The nut's friction heat grows with axial load: QN = (k4 + k6 F) v, F from load_N."""

    id: ClassVar[str] = "load_dependent_heat"
    description: ClassVar[str] = "nut friction grows with axial load: QN = (k4 + k6*F)*v"
    heat_gains: ClassVar[tuple[str, ...]] = ("k6_W_per_N_mm_min",)
    needs: ClassVar[tuple[str, ...]] = ("load_N",)
    reference: ClassVar[dict[str, float]] = {"k6_W_per_N_mm_min": 2e-7}
    scaled: ClassVar[tuple[str, ...]] = ("k6_W_per_N_mm_min",)
    export_code: ClassVar[int | None] = 3
    k6_W_per_N_mm_min: float = 2e-7

    def export_params(self, geom):
        return [self.k6_W_per_N_mm_min]

    def nut_heat_W(self, drive):
        if drive.load_N is None:
            raise ValueError("effect 'load_dependent_heat' needs the axial load (column load_N)")
        return self.k6_W_per_N_mm_min * drive.load_N * drive.v_mm_min


EFFECTS: dict[str, type[Effect]] = {
    cls.id: cls
    for cls in (
        AmbientDrift,
        FreeEndBearingHeat,
        MotorHeat,
        OriginDrift,
        FixedFixedConstraint,
        QuadraticFrictionHeat,
        LoadDependentHeat,
    )
}


__getattr__ = thermbench.moved_names(__name__)
