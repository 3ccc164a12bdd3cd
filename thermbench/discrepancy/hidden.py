"""Datasets in which an effect is on and the base model lacks it: the test and
benchmark data of the discrepancy workflow.

The world differs from the identification model on purpose, so that a pass does
not rest on an identical world: a finer discretisation (dx 5 mm, dt 0.05 s,
macro step 5 s against the model's 10 mm / 0.1 s / 10 s), its own sensor model
(noise, 1/16 °C steps, spikes and 85 °C dropouts on the temperature channels;
0.25 um interferometer noise, a cubic + periodic pitch error), its own
measuring cycle (every 8 min, 3 s dwell), random duty cycles per seed (each
run alternates reciprocation at its own feed and load with stops) and a screw
that conducts like steel (lambda 60 W/mK; the model starts from seed 000's 566).

Strength. :func:`calibrate` chooses the effect's strength so that, after the
core model is re-identified *without* it on noise-free data of the same
duty, the residual RMS is ``ratio`` times the noise floor (>= 3 x): an effect
that re-identification absorbs is detectable by no one. The noise floor is
known here: sigma sqrt(2) (a thermal error is a reading minus one cold
reference reading).
"""

from __future__ import annotations

import copy
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from omegaconf import OmegaConf

from ..config import config_dir
from ..data.io import Dataset, save_dataset
from ..models.physics import PhysicsModel
from ..sim.scenario import simulate_dataset

#: reference parameters of each effect; ``SCALED`` names the ones a strength multiplies
REFERENCE = {
    "ambient_drift": {"amplitude_C": 1.0, "period_s": 86400.0, "phase_s": 0.0, "rate_C_per_h": 0.2},
    "free_end_bearing_heat": {"kF_W_per_mm_min": 0.5e-3},
    "motor_heat": {"k_motor_W_per_mm_min": 0.4e-3, "tau_s": 1800.0},
    "origin_drift": {"beta_um_per_K": 2.0},
    "fixed_fixed_constraint": {"kappa": 0.3},
    "quadratic_friction_heat": {"k5_W_per_mm_min2": 5e-8},
    "load_dependent_heat": {"k6_W_per_N_mm_min": 2e-7},
}
SCALED = {
    "ambient_drift": ("amplitude_C", "rate_C_per_h"),
    "free_end_bearing_heat": ("kF_W_per_mm_min",),
    "motor_heat": ("k_motor_W_per_mm_min",),
    "origin_drift": ("beta_um_per_K",),
    "fixed_fixed_constraint": ("kappa",),
    "quadratic_friction_heat": ("k5_W_per_mm_min2",),
    "load_dependent_heat": ("k6_W_per_N_mm_min",),
}
CAPS = {"fixed_fixed_constraint.kappa": 0.95}
IFM_NOISE_UM = 0.25
FEEDS_MM_MIN = (1500.0, 3500.0, 6000.0, 9000.0)
LOADS_N = (0.0, 1500.0, 3000.0, 4500.0)


@dataclass(frozen=True)
class World:
    """How the hidden-effect datasets are made (see module docstring)."""

    n_runs: int = 4
    run_h: float = 2.5
    travel_mm: tuple[float, float] = (0.0, 550.0)
    with_load: bool = True
    # load tied to feed (load_N = this x feed): load_dependent_heat then equals
    # quadratic_friction_heat on these data, a tie no method can break
    load_per_feed_N_min_per_mm: float | None = None
    ifm_noise_um: float = IFM_NOISE_UM
    numerics: dict = field(default_factory=lambda: {"dx_m": 0.005, "dt_s": 0.05, "macro_dt_s": 5.0})
    # the world's screw conducts like steel (~60 W/mK), not like seed 000's identified 566 W/mK
    # (which lumps axial transport): heat stays where it enters, so mounting and end effects show
    core: dict = field(default_factory=lambda: {"lambda_W_mK": 60.0})

    @property
    def noise_floor_um(self) -> float:
        return self.ifm_noise_um * math.sqrt(2.0)


def _machine(world: World) -> dict:
    m = OmegaConf.to_container(OmegaConf.load(config_dir() / "machine" / "seed000_x.yaml"), resolve=True)
    m["name"] = "hidden_effect_world"
    m["travel_mm"] = list(world.travel_mm)
    m["screw"]["mounting"] = "fixed_supported"
    m["core"].update(world.core)
    m["geometric"] = {"poly_um": [0.0, 0.01, -2e-5, 1.5e-8], "periodic_amp_um": 0.5, "periodic_period_mm": 10.0}
    return m


def duty(world: World, seed: int) -> dict:
    """Random runs: per run a feed level and a load level (each run its own), phases
    of reciprocation over random strokes at +-20 % of the level, with stops."""
    rng = np.random.default_rng([seed, 7])
    lo, hi = world.travel_mm
    feeds = rng.permutation(np.resize(FEEDS_MM_MIN, world.n_runs))
    loads = rng.permutation(np.resize(LOADS_N, world.n_runs))
    runs = {}
    for i in range(world.n_runs):
        total, phases = world.run_h * 3600.0, []
        while total > 0:
            if phases and phases[-1]["kind"] == "move" and rng.random() < 0.45:
                d = float(min(total, rng.uniform(600, 1500)))
                phases.append({"kind": "stop", "duration_s": d})
            else:
                stroke = float(rng.uniform(0.1, 1.0) * (hi - lo))
                a = float(rng.uniform(lo, hi - stroke))
                d = float(min(total, rng.uniform(1200, 2700)))
                feed = float(np.round(feeds[i] * rng.uniform(0.8, 1.2), -1))
                load = float(loads[i] * rng.uniform(0.7, 1.3)) if world.with_load else 0.0
                if world.with_load and world.load_per_feed_N_min_per_mm is not None:
                    load = world.load_per_feed_N_min_per_mm * feed
                phases.append({"kind": "move", "duration_s": d, "start_mm": round(a, 1), "end_mm": round(a + stroke, 1),
                               "feed_mm_min": feed, "load_N": load})  # fmt: skip
            total -= d
        runs[f"run{i + 1}"] = {"phases": phases, "notes": f"random duty, feed level {feeds[i]:.0f} mm/min"}
    return runs


def _config(world: World, effects: dict, seed: int, clean: bool) -> dict:
    lo, hi = world.travel_mm
    sensor = {"noise_C": 0.05, "quantum_C": 0.0625, "spike_rate_per_h": 0.3, "spike_C": 5.0,
              "dropout_rate_per_h": 0.1, "dropout_len_s": 4.0}  # fmt: skip
    return {
        "machine": _machine(world),
        "protocol": {
            "name": "hidden_effect_duty",
            "measuring": {"targets_mm": {"start": lo, "stop": hi, "step": 50.0}, "every_s": 480.0, "dwell_s": 3.0,
                          "feed_mm_min": 2500.0, "reference_repeats": 1},  # fmt: skip
            "runs": duty(world, seed),
        },
        "instruments": {
            "process_rate_hz": 1.0,
            "sensor": {"noise_C": 0.0, "quantum_C": 0.0} if clean else sensor,
            "interferometer": {"noise_um": 0.0 if clean else world.ifm_noise_um},
        },
        "effects": copy.deepcopy(effects),
        "numerics": dict(world.numerics),
        "seed": int(seed),
    }


def simulate(world: World, effects: dict, seed: int, clean: bool = False) -> Dataset:
    """The world with ``effects`` ({id: params}) on; ``clean``: no measurement noise
    and no pitch error (for calibration)."""
    cfg = _config(world, effects, seed, clean)
    if clean:
        cfg["machine"]["geometric"] = {"poly_um": []}
    ds, _ = simulate_dataset(cfg)
    return ds


def core_residual_um(ds: Dataset, physics: dict | None = None) -> float:
    """RMS residual (readings after the cold reference) of the core model re-identified
    on ``ds`` with a constant ambient: what an effect leaves that the core cannot absorb."""
    m = PhysicsModel(ambient_sensor=None, **(physics or {})).fit(ds)
    parts = [m.referenced_thermal_um(ds, r) for r in ds.run_ids]
    r = np.concatenate([(rd["thermal_um"].to_numpy() - p)[rd["cycle"].to_numpy() > 0] for rd, p in parts])
    return float(np.sqrt(np.mean(r**2)))


def scaled(effect: str, factor: float) -> dict:
    p = dict(REFERENCE[effect])
    for k in SCALED[effect]:
        p[k] = p[k] * factor
        cap = CAPS.get(f"{effect}.{k}")
        if cap is not None:
            p[k] = min(p[k], cap)
    return p


def calibrate(effect: str, world: World, seed: int, ratio: float = 4.0, minimum: float = 3.0,
              physics: dict | None = None, max_rounds: int = 4) -> tuple[dict, float]:
    """Parameters of ``effect`` leaving a core residual of about ``ratio`` x the noise floor
    (at least ``minimum`` x); returns (params, residual_um). Raises when the effect stays
    undetectable at its largest allowed strength."""
    floor = world.noise_floor_um
    factor, r = 1.0, 0.0
    for _ in range(max_rounds):
        params = scaled(effect, factor)
        r = core_residual_um(simulate(world, {effect: params}, seed, clean=True), physics)
        if r >= minimum * floor and (r <= 2.0 * ratio * floor or _at_cap(effect, params)):
            return params, r
        if _at_cap(effect, params) and r < minimum * floor:
            break
        factor *= ratio * floor / max(r, 1e-6)
    if r >= minimum * floor:
        return params, r
    raise ValueError(f"{effect}: residual {r:.3f} um < {minimum} x floor {floor:.3f} um at its largest strength {params}")


def _at_cap(effect: str, params: dict) -> bool:
    return any(params[k] >= CAPS.get(f"{effect}.{k}", math.inf) for k in SCALED[effect])


def make(out_dir: str | Path, effects: dict, seed: int, world: World | None = None) -> Path:
    """Write the noisy dataset with ``effects`` on to ``out_dir`` (contract format)."""
    world = world or World()
    return save_dataset(simulate(world, effects, seed), Path(out_dir))
