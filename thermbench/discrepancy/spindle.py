"""The discrepancy workflow on a spindle test.

What the search confronts with the data is the lumped network of ``physics_spindle``
(:class:`~thermbench.models.lumped.LumpedThermalNetwork`: heat q = (u/u_ref)^p of the spindle
speed through a chain of first-order thermal nodes, the drift a linear combination of the node
rises plus an offset); the candidates are the physical terms of
:mod:`thermbench.models.spindle_terms` (a second heat path, structure growth with a measured
temperature or the speed, expansion with the ambient or bed, a stop drift), each identified
with the network (variable projection: its gains linear, its time constants and exponent
searched). :class:`SpindleFamily` answers what the search asks of a family
(:class:`~thermbench.discrepancy.search.ScrewFamily` is the screw's); the search, the test,
the verdicts and the report are the screw workflow's own.

The runs are the test's heating/cooling blocks (segments, each with the test's log from its
start: the drift counts from the test's first reading), folds leave one block out, and the
runs held out of the whole search (fl_thermal's stepped tail) are scored once at the end.
Every reading is scored: the error of a fixed-point channel is not referenced to a cold
reading of its own run (its offset is the network's ``d``).
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

from ..data.io import Dataset
from ..models.base import readings
from ..models.lumped import LumpedThermalNetwork
from ..models.spindle_terms import REFERENCE_LOCATIONS, SPINDLE_TERMS, base_id, term_class
from .noise import NoiseFloor, high_frequency_scatter

#: what the diagnose config may set of the base network (``spindle.*``); the rest is the workflow's
NETWORK_KEYS = {"n_nodes": int, "step_s": float, "n_starts": int, "exponent": None, "exponent_bounds": None,
                "tau_bounds_s": None, "preprocess": None}  # fmt: skip
#: the base network: physics_spindle with two nodes, no sensors (conf/model/physics_spindle.yaml); the terms read
#: the sensors as logged (a filter's lag, e.g. the default Kalman of seed 002, would be physics of its own)
BASE_NETWORK = {"n_nodes": 2, "sensors": None, "preprocess": None}
#: instances of one signal-driven term a model may hold (structure growth with up to four temperatures)
MAX_REPEATS = 4
#: the running share of a block's own readings above which the block counts as running at its speed
RUNNING = 0.5

NEEDS = {
    "reference_sensor": (lambda ds: any(loc in REFERENCE_LOCATIONS for loc in ds.metadata.sensors.values()),
                         f"no sensor at location {' or '.join(REFERENCE_LOCATIONS)} in metadata.yaml (the "
                         "dataset's sensors are at: {locations})"),
}  # fmt: skip


class _Terms(dict):
    """The term library, holding every instance name (``structure_growth@2``) of its terms."""

    def __contains__(self, key) -> bool:
        return dict.__contains__(self, base_id(str(key)))


class SpindleFamily:
    """A spindle test's thermal drift at a fixed point: the lumped network and its terms."""

    name = "spindle"
    canonical: dict = {}  # no canonical library: every term is screened, the most promising refitted
    driver = "spindle_rpm"

    def __init__(self, network: dict | None = None, operating: str = "spindle_rpm", u_ref: float | None = None,
                 history: bool = True):  # fmt: skip
        self.network = {**BASE_NETWORK, **dict(network or {})}
        self.operating = operating
        self.u_ref = u_ref
        self.driver = operating
        self.history = history

    def frame(self, ds: Dataset) -> str:
        """What every score is of: with history, the drift from the test's first reading."""
        from ..data.reference import frame_text

        if self.history:
            return ("the drift from the first reading of the whole test: each segment keeps the test's log and drift "
                    "from its start (history)")  # fmt: skip
        return frame_text(ds.metadata)

    @property
    def base_words(self) -> str:
        n = self.network["n_nodes"]
        return (f"the lumped network of physics_spindle (heat (u/u_ref)^p of {self.operating} through a chain of {n} "
                f"thermal node(s), an offset)")  # fmt: skip

    @property
    def candidates(self) -> tuple[str, ...]:
        return tuple(SPINDLE_TERMS)

    @property
    def open(self):
        return _Terms(SPINDLE_TERMS)

    def cls(self, eid: str):
        return term_class(eid)

    def own_params(self, eid: str) -> tuple[str, ...]:
        return tuple(term_class(eid).nonlinear)

    def variants(self, eid: str, ds: Dataset, model=None) -> list[dict]:
        """The values of the term's signal the dataset offers: the speed (where the term takes it)
        and every sensor, or only sensors at a reference location (``sensor_expansion``); not a
        signal another instance of the term in ``model`` already has."""
        cls = term_class(eid)
        if not cls.choice:
            return [{}]
        used = {t.params.get(cls.choice) for t in getattr(model, "terms_", []) if base_id(t.key) == base_id(eid)}
        if "reference_sensor" in cls.needs:
            offered = [s for s, loc in ds.metadata.sensors.items() if loc in REFERENCE_LOCATIONS]
        else:
            offered = (["speed"] if cls.defaults.get(cls.choice) == "speed" else []) + list(ds.metadata.sensors)
        return [{cls.choice: s} for s in offered if s not in used]

    def candidates_for(self, candidates, effects) -> list[str]:
        """The candidates of a step: each term not in the model yet, and a term driven by a signal
        once more (``<term>@<k>``, on another signal: a second structure temperature) while it has
        signals left and fewer than ``MAX_REPEATS`` instances."""
        out = []
        for c in candidates:
            k = sum(1 for e in effects if base_id(e) == c)
            if k == 0:
                out.append(c)
            elif term_class(c).choice and k < MAX_REPEATS:
                out.append(f"{c}@{k + 1}")
        return out

    def context(self, ds: Dataset) -> dict:
        return {"sensors": dict(ds.metadata.sensors)}

    def unavailable(self, eid: str, ds: Dataset) -> str | None:
        for need in term_class(eid).needs:
            has, why = NEEDS[need]
            if not has(ds):
                return why.format(locations=sorted(set(ds.metadata.sensors.values())) or "none")
        return None

    def n_params(self, effects: Sequence[str]) -> int:
        """Identified numbers: per node a time constant and a gain, the exponent (when searched), the
        offset; per term its gains and its nonlinear parameters."""
        n = int(self.network["n_nodes"])
        p = 2 * n + (self.network.get("exponent") is None) + 1
        for e in effects:
            cls = term_class(e)
            p += len(cls.gains) + len(cls.nonlinear)
        return p

    def make_model(self, effects, ds, settings, warm=None, start=None, cache=None) -> LumpedThermalNetwork:
        """The network with ``effects`` as terms, warm-started from ``warm``'s parameters (the base
        and the terms it has) and ``start`` (a new term's values: its signal and start values)."""
        terms = {}
        for e in effects:
            params = self.effect_params(warm, e) if warm is not None and e in warm.term_gains_ else {}
            params.update((start or {}).get(e, {}))
            terms[e] = params
        initial = None
        if warm is not None:
            initial = {k: v for k, v in warm.params_.items() if "." not in k}
        return LumpedThermalNetwork(**self.network, operating=self.operating, u_ref=self.u_ref, terms=terms or None,
                                    initial=initial)  # fmt: skip

    def hold(self, model: LumpedThermalNetwork, free: Sequence[str]) -> LumpedThermalNetwork:
        model.set_params(identify=list(free))
        return model

    def effect_params(self, model: LumpedThermalNetwork, eid: str) -> dict:
        term = next((t for t in model.terms_ if t.key == eid), None)
        return dict(term.params) if term is not None else {}

    def gain_basis(self, model, ds, runs):
        names, per_run = model.gain_basis(ds, runs)
        return np.full(len(names), -np.inf), per_run  # every gain of the network takes either sign

    def table(self, model, ds, run) -> tuple[pd.DataFrame, np.ndarray]:
        """The run's readings (``thermal_um`` = the drift the network fits, ``error_um``) and the
        model's prediction at them."""
        rd = readings(ds, [run]).reset_index(drop=True)
        rd = rd.assign(thermal_um=rd["error_um"].to_numpy(dtype=float))
        pred = model.predict_at(ds, run, rd["t_s"].to_numpy(dtype=float), rd["target_mm"].to_numpy(dtype=float))
        return rd, pred

    def scored(self, rd: pd.DataFrame) -> np.ndarray:
        return np.ones(len(rd), dtype=bool)  # no cold reference reading per run: every reading counts

    def train_rmse(self, model) -> float:
        return float(model.rmse_um_)

    def train_sse(self, model, ds, runs) -> tuple[float, int]:
        n = len(readings(ds, runs))
        return float(model.rmse_um_) ** 2 * n, n

    def cache(self):
        return None

    def label(self, eid: str, model, ctx: dict) -> tuple[str, str]:
        term = next(t for t in model.terms_ if t.key == eid)
        own = f"{eid}[{term.params[term.choice]}]" if term.choice else eid
        return term.canonical(ctx) or own, term.describe(ctx)

    # ------------------------------------------------------------- workflow ---
    def prepare_base(self, base: list[str], ds: Dataset, notes: list[str]) -> list[str]:
        return base

    def noise_floor(self, table: pd.DataFrame, window_s: float, min_groups: int) -> NoiseFloor:
        """The reading scatter from the second time difference of the in-sample residual (a drift
        read every few seconds has no repeats); the error is not referenced per run, so the floor
        is the scatter itself."""
        t = table.assign(cycle=1)  # every reading (high_frequency_scatter drops cycle 0)
        sigma, n = high_frequency_scatter(t)
        if not n:
            raise ValueError("cannot estimate the noise floor: no run has 3 readings")
        return NoiseFloor(float(sigma), float(sigma), "high_frequency", 0.0, {"high_frequency": (float(sigma), n)})

    def annotate(self, table: pd.DataFrame, ds: Dataset, model, floor_um: float) -> pd.DataFrame:
        """``position`` (always the fixed point), ``phase`` (the spindle running or stopped at
        the reading) and the block's speed (the mean operating value over its own readings while
        running) for :func:`thermbench.discrepancy.localise.localise`."""
        t = table.copy()
        t["position"] = "fixed_point"
        phase = np.empty(len(t), dtype=object)
        speed = {}
        for run, g in t.groupby("run_id", sort=False):
            pr = ds.process_run(run)
            tp = pr["t_s"].to_numpy(dtype=float)
            u = pd.to_numeric(pr[self.operating], errors="coerce").to_numpy(dtype=float)
            k = np.clip(np.searchsorted(tp, g["t_s"].to_numpy(dtype=float), side="right") - 1, 0, tp.size - 1)
            on = u[k] > 0
            phase[t.index.get_indexer(g.index)] = np.where(on, "running", "stopped")
            speed[run] = float(u[k][on].mean()) if on.any() else 0.0
        t["phase"] = phase
        t[self.driver] = t["run_id"].map(speed)
        return t

    def more_data(self, where: dict, ds: Dataset, noise) -> list[str]:
        """What measurements would tell more about a residual no term could explain."""
        hints = []
        if where["phase"] == "stopped":
            hints.append("it shows mostly while the spindle stands: longer stops, and a temperature at the spindle "
                         "nose and the headstock during them, would separate slow cooling paths")  # fmt: skip
        elif where["phase"] == "running":
            hints.append("it shows mostly while the spindle runs: blocks at more speeds, and temperatures at the "
                         "front bearing and the motor, would show how each heat path scales")  # fmt: skip
        locs = set(ds.metadata.sensors.values())
        if not locs & set(REFERENCE_LOCATIONS):
            hints.append("add an ambient temperature sensor (location 'ambient') and one on the bed: expansion with "
                         "them cannot be tried without")  # fmt: skip
        if locs <= {"structure"}:
            hints.append("declare where each sensor is (metadata.yaml sensors: bearing, motor, headstock, column, "
                         "bed, coolant): the terms then name the physics, not a channel")  # fmt: skip
        hints.append("a repeat of the test would give a model-free noise floor (the floor here is the residual's "
                     "high-frequency scatter)")  # fmt: skip
        return hints


def spindle_family(ds: Dataset, runs: Sequence[str], network: dict | None = None, history: bool = True) -> SpindleFamily:
    """The family for a spindle dataset: the operating column the dataset declares (first), the
    speed scale the largest |speed| over ``runs`` (fixed across folds, so their gains compare)."""
    from ..models.base import ModelError

    inputs = ds.metadata.operating_inputs()
    if not inputs:
        raise ModelError(f"{ds.path}: the spindle workflow drives the network by an operating input; the dataset "
                         "declares none (metadata 'operating', e.g. spindle_rpm)")  # fmt: skip
    col = str(inputs[0])
    u = max(float(np.max(np.abs(pd.to_numeric(ds.process_run(r)[col], errors="coerce").to_numpy(dtype=float)))) for r in runs)
    return SpindleFamily(network, operating=col, u_ref=u if u > 0 else None, history=history)
