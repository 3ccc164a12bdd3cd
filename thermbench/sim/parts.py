"""Parameter records of the ball-screw physics: geometry, material, core heat model, numerics.

Names carry units; ``v`` is the feed speed in mm/min, as in seed 000 §4.1.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

MOUNTINGS = ("fixed_free", "fixed_supported", "fixed_fixed")


@dataclass(frozen=True)
class Screw:
    """Ball-screw geometry (seed 000 Table 1; mounting from seed 004)."""

    length_m: float
    diameter_m: float
    nut_length_m: float
    fixed_bearing_length_m: float
    mounting: str = "fixed_free"

    def __post_init__(self) -> None:
        for name in ("length_m", "diameter_m", "nut_length_m"):
            if not 0 < getattr(self, name) < math.inf:
                raise ValueError(f"screw.{name} must be > 0, got {getattr(self, name)!r}")
        if self.fixed_bearing_length_m < 0:
            raise ValueError(f"screw.fixed_bearing_length_m must be >= 0, got {self.fixed_bearing_length_m!r}")
        if self.mounting not in MOUNTINGS:
            raise ValueError(f"screw.mounting must be one of {MOUNTINGS}, got {self.mounting!r}")

    @property
    def area_m2(self) -> float:
        """Cross-section A_s = pi D^2 / 4 (seed 000 §3.1)."""
        return math.pi * self.diameter_m**2 / 4.0


@dataclass(frozen=True)
class Material:
    """Screw material (seed 000 Table 1)."""

    alpha_per_K: float
    density_kg_m3: float
    heat_capacity_J_kgK: float


@dataclass
class CoreParams:
    """The six identified parameters of seed 000 §4.1-4.2 (Table 3).

    h = k1 v + k2, QB = k3 v, QN = k4 v with v in mm/min; lambda the thermal
    conductivity; Pf the axis coordinate at which the nut sits at the fixed end.
    """

    k1_W_m2K_per_mm_min: float = 0.911e-3
    k2_W_m2K: float = 26.034
    k3_W_per_mm_min: float = 0.904e-3
    k4_W_per_mm_min: float = 0.911e-3
    lambda_W_mK: float = 566.3
    pf_m: float = -0.141

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


@dataclass(frozen=True)
class Numerics:
    """Discretisation. ``dx_m`` and ``dt_s`` as in seed 000 Table 1; ``macro_dt_s``
    is the step of the fast integrator (a multiple of ``dt_s``)."""

    dx_m: float = 0.01
    dt_s: float = 0.1
    macro_dt_s: float = 10.0
    method: str = "macro"  # "macro" (fast, default) or "explicit" (seed 000 literal)

    def __post_init__(self) -> None:
        if self.method not in ("macro", "explicit"):
            raise ValueError(f"numerics.method must be 'macro' or 'explicit', got {self.method!r}")
        steps = (self.dx_m, self.dt_s, self.macro_dt_s)
        ok = all(isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v < math.inf for v in steps)
        ratio = self.macro_dt_s / self.dt_s if ok else math.nan
        if not ok or abs(ratio - round(ratio)) > 1e-9 or round(ratio) < 1:
            raise ValueError(
                f"numerics: dx_m, dt_s and macro_dt_s must be finite and > 0, macro_dt_s a whole multiple of dt_s "
                f"(got dx_m={self.dx_m}, dt_s={self.dt_s}, macro_dt_s={self.macro_dt_s})"
            )

    @property
    def per_step(self) -> int:
        return int(round(self.macro_dt_s / self.dt_s))


@dataclass(frozen=True)
class Housing:
    """A lumped housing node (nut, bearing, motor, bed housing) read by a sensor.

    T = Ta0 + lag_tau( gain_K_per_W * Q_source + gain_K_per_mm_min * v
                       + screw_coupling * theta_screw_local + (Ta - Ta0) )

    ``source`` names the heat that drives it: nut, fixed_bearing, free_bearing or
    none; ``screw_at`` where it touches the screw: nut, fixed_end, free_end or none.
    """

    tau_s: float
    gain_K_per_W: float = 0.0
    gain_K_per_mm_min: float = 0.0
    screw_coupling: float = 0.0
    source: str = "none"
    screw_at: str = "none"


def default_housings() -> dict[str, Housing]:
    """Housing nodes for the locations of the dataset contract."""
    return {
        "ambient": Housing(tau_s=1.0),
        "nut_housing": Housing(tau_s=600.0, gain_K_per_W=0.35, screw_coupling=0.5, source="nut", screw_at="nut"),
        "fixed_bearing_housing": Housing(
            tau_s=900.0, gain_K_per_W=0.45, screw_coupling=0.5, source="fixed_bearing", screw_at="fixed_end"
        ),
        "free_bearing_housing": Housing(
            tau_s=900.0, gain_K_per_W=0.45, screw_coupling=0.5, source="free_bearing", screw_at="free_end"
        ),
        "motor": Housing(tau_s=1500.0, gain_K_per_mm_min=6e-4),
        "bed": Housing(tau_s=7200.0),
    }


def housings_from_config(cfg: dict | None) -> dict[str, Housing]:
    out = default_housings()
    for name, spec in (cfg or {}).items():
        base = asdict(out.get(name, Housing(tau_s=600.0)))
        base.update(dict(spec))
        out[name] = Housing(**base)
    return out


@dataclass
class Geometry:
    """Derived grid quantities shared by the kernels."""

    screw: Screw
    material: Material
    numerics: Numerics = field(default_factory=Numerics)

    @property
    def n_nodes(self) -> int:
        return max(2, int(round(self.screw.length_m / self.numerics.dx_m)))

    @property
    def n_bearing(self) -> int:
        """Nodes n <= LB/dx are fixed-bearing nodes (seed 000 §3.1)."""
        return int(math.floor(self.screw.fixed_bearing_length_m / self.numerics.dx_m + 1e-9))

    @property
    def cap_J_K(self) -> float:
        m = self.material
        return m.density_kg_m3 * m.heat_capacity_J_kgK * self.screw.area_m2 * self.numerics.dx_m

    @property
    def side_area_m2(self) -> float:
        return math.pi * self.screw.diameter_m * self.numerics.dx_m

    @property
    def end_area_m2(self) -> float:
        return self.screw.area_m2
