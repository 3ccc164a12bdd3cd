"""Setting up :class:`~thermbench.models.physics.PhysicsModel` (a base class of it): the ambient
sensor, each run's drive and measured signals, the effects and start values checked, the
seed 000 model built for given parameters, the coarse stage's numerics, and each run's data
prepared once for identification (:class:`~thermbench.models.physics_runs._RunData`)."""

from __future__ import annotations

import math

import numpy as np

from ..data.dataset import Dataset
from ..sim.effects import AmbientDrift
from ..sim.model import Motion, ScrewThermalModel
from ..sim.parts import CoreParams, Material, Numerics, Screw
from ..sim.registry import effect_class, make_effect
from .base import ModelError, derived, fallback, require, sensor_series
from .physics_runs import _RunData


class _PhysicsSetup:
    """The set-up of :class:`~thermbench.models.physics.PhysicsModel` (module docstring): these
    methods read its parameters and fitted attributes."""

    # ------------------------------------------------------------ set-up ---
    def _ambient_name(self, ds: Dataset) -> str | None:
        if self.ambient_sensor is None:
            return None
        if self.ambient_sensor == "auto":
            name = next((s for s, loc in ds.metadata.sensors.items() if loc == "ambient"), None)
            if name is None:
                fallback("ambient_sensor auto: the dataset has no sensor at location 'ambient', so the ambient "
                         "is taken as constant (20 °C)")  # fmt: skip
            return name
        if self.ambient_sensor not in ds.metadata.sensors:
            raise ModelError(
                f"ambient_sensor: {self.ambient_sensor!r} is not a sensor of the dataset; "
                f"sensors: {list(ds.metadata.sensors)}"
            )
        return self.ambient_sensor

    def _drive(self, ds: Dataset, run: str, name: str | None):
        """(motion, duration, ambient series, its times) of a run from its process log,
        with the ambient of sensor ``name`` (None: constant)."""
        pr = ds.process_run(run)
        t = pr["t_s"].to_numpy()
        load = pr["load_N"].to_numpy() if "load_N" in pr else None
        mot = Motion(t, pr["axis_mm"].to_numpy(), pr["feed_mm_min"].to_numpy(), load)
        if name is None:
            return mot, float(t[-1] - t[0]), 20.0, None
        s = sensor_series(ds, run, [name], self.preprocess)
        return mot, float(t[-1] - t[0]), s[ds.metadata.sensor_column(name)].to_numpy(), s["t_s"].to_numpy()

    @staticmethod
    def _signal_names(specs: dict) -> list[str]:
        """The temperature sensors the effects follow (an effect's ``choice`` parameter)."""
        return sorted({str(p[cls.choice]) for eid, p in specs.items()
                       if (cls := effect_class(eid)).choice and p.get(cls.choice, "speed") != "speed"})  # fmt: skip

    def _signals(self, ds: Dataset, run: str, specs: dict) -> dict:
        """The measured temperature channels the effects follow, filtered like the ambient:
        {sensor: (t_s, series)}."""
        names = self._signal_names(specs)
        if not names:
            return {}
        missing = [n for n in names if n not in ds.metadata.sensors]
        if missing:
            raise ModelError(f"effects: signal(s) {missing} are not sensors of the dataset; sensors: "
                             f"{list(ds.metadata.sensors)} (or 'speed')")  # fmt: skip
        s = sensor_series(ds, run, names, self.preprocess)
        return {n: (s["t_s"].to_numpy(), s[ds.metadata.sensor_column(n)].to_numpy()) for n in names}

    def _effect_specs(self) -> dict[str, dict]:
        specs = {str(k): dict(v or {}) for k, v in dict(self.effects or {}).items()}
        for eid, params in specs.items():
            try:
                make_effect(eid, **params)  # validates ids and parameter names
            except ValueError as exc:
                raise ModelError(f"effects: {exc}") from None
        return specs

    def _start(self, ds: Dataset) -> dict[str, float]:
        start = CoreParams().as_dict()
        if ds.metadata.screw.fixed_end_axis_mm is not None:
            start["pf_m"] = ds.metadata.screw.fixed_end_axis_mm / 1000.0
        for k, v in dict(self.initial or {}).items():
            if k not in start:
                raise ModelError(f"initial: unknown core parameter {k!r}; known: {sorted(start)}")
            start[k] = float(v)
        return start

    def _build(self, ds: Dataset, core: dict, effect_specs: dict, ambient: bool,
               numerics: Numerics | None = None) -> ScrewThermalModel:  # fmt: skip
        sm = ds.metadata.screw
        screw = Screw(sm.length_m, sm.diameter_m, sm.nut_length_m, sm.fixed_bearing_length_m, sm.mounting)
        mm = ds.metadata.material
        material = Material(mm.alpha_per_K, mm.density_kg_m3, mm.heat_capacity_J_kgK)
        effects = [make_effect(eid, **p) for eid, p in effect_specs.items()]
        if ambient and AmbientDrift.id not in effect_specs:
            effects.append(AmbientDrift())  # measured series: the screw follows it (seed 000 §2.2)
        numerics = numerics or Numerics(dx_m=self.dx_m, dt_s=self.dt_s, macro_dt_s=self.macro_dt_s)
        return ScrewThermalModel(screw, material, CoreParams(**core), effects, numerics)

    def _coarse_numerics(self) -> Numerics | None:
        """The first stage's numerics: the coarse steps where they are coarser than the
        model's own (else no first stage)."""
        if self.coarse_macro_dt_s is None or (self.coarse_macro_dt_s <= self.macro_dt_s and self.coarse_dt_s <= self.dt_s):
            return None
        dt = max(self.coarse_dt_s, self.dt_s)
        # a whole number of fine steps per macro step (Numerics), at least the coarse macro step
        macro = float(f"{dt * math.ceil(max(self.coarse_macro_dt_s, self.macro_dt_s) / dt - 1e-9):.12g}")
        return Numerics(dx_m=self.dx_m, dt_s=dt, macro_dt_s=macro)

    # ---------------------------------------------------------- run data ---
    def _ambient_source(self) -> tuple:
        """What the measured ambient the fields are driven by is made from: its sensor and filters."""
        return (self.ambient_name_, repr(self.preprocess))

    def _run_data(self, ds: Dataset, runs: list[str], rd_all, specs: dict) -> list[_RunData]:
        """Per run: its drive and readings, each reading with the index of its target's
        cold reference reading; made once per dataset, run, ambient sensor, filters and
        signals (:func:`~thermbench.models.base.derived`) and shared by every fit."""
        names = tuple(self._signal_names(specs))
        shared = self.preprocess is None or isinstance(self.preprocess, str)
        out = []
        for run in runs:
            make = lambda run=run: self._one_run(ds, run, rd_all, specs)  # noqa: E731
            key = ("physics_run", run, self.ambient_name_, self.preprocess, names)
            out.append(derived(ds, key, make, copy=False) if shared else make())
        return out

    def _one_run(self, ds: Dataset, run: str, rd_all, specs: dict) -> _RunData:
        g = rd_all[rd_all["run_id"] == run].reset_index(drop=True)
        require(int((g["cycle"] > 0).sum()), 1, f"readings after the cold reference in run {run!r}")
        ref = g[g["cycle"] == 0]
        first = {x: i for i, x in reversed(list(zip(ref.index, ref["target_mm"])))}
        ref_idx = np.array([first.get(x, i) for i, x in enumerate(g["target_mm"])])
        mot, dur, amb, amb_t = self._drive(ds, run, self.ambient_name_)
        return _RunData(run, mot, dur, amb, amb_t, g["t_s"].to_numpy(), g["target_mm"].to_numpy(), ref_idx,
                        g["thermal_um"].to_numpy(), self._signals(ds, run, specs))  # fmt: skip
