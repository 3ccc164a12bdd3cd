"""Name the missing effect: the candidates and their scores, and the screw family they are fitted in.

Steps 1 and 3-5 of the discrepancy workflow. The current model is the seed 000
core (:class:`~thermbench.models.physics.PhysicsModel`: fixed-bearing heat, nut
heat, convection, constant ambient) plus the effects found so far. Each
canonical effect not yet in it is a candidate: added, re-identified from the
current parameters (warm start), scored by

* its *held-out* RMSE: the gains re-solved on the training runs of each fold
  with the nonlinear parameters of the fit on all training runs (a fast
  screening score; the named effect's proper score re-identifies every
  parameter per fold, warm-started only from that fold's own models), and
* BIC = n ln(SSE/n) + p ln n on the training runs (Schwarz 1978), n the
  readings after the cold reference; the gain is BIC(current) -
  BIC(candidate), > 0 favours the candidate. Residuals of a thermal model are
  autocorrelated in time, so BIC alone is lenient; the held-out criterion
  is the stricter half of the test.

The test and BIC are computed in :mod:`.significance`. :class:`ScrewFamily` is the screw's
physics model as the search grows it, with :func:`more_data`, what to measure next when the
runs cannot tell candidates apart.
"""

from __future__ import annotations

import itertools
import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Sequence

import numpy as np
import pandas as pd
from scipy.optimize import lsq_linear

import thermbench

from ..data.io import Dataset
from ..models.base import readings
from ..models.physics import CORE_GAINS, CORE_NONLINEAR, PhysicsModel
from ..models.physics_runs import FieldCache
from ..sim.effects import EFFECTS
from ..sim.open_terms import OPEN_TERMS
from ..sim.registry import effect_class, make_effect
from . import significance

if TYPE_CHECKING:  # pragma: no cover
    from .significance import SignificanceTest

#: the candidates, in the order they are tried: the canonical effect library, then the open terms
CANDIDATES = (*EFFECTS, *OPEN_TERMS)


def own_params(effect: str) -> tuple[str, ...]:
    """The nonlinear parameters identified by SQP together with ``effect`` (its heat gains are
    linear): what the effect class declares (``Effect.nonlinear``)."""
    return tuple(effect_class(effect).nonlinear)


def variants(effect: str, ds: Dataset) -> list[dict]:
    """The values of the effect's ``choice`` parameter that the dataset offers (the axis speed
    and every temperature sensor), one dict each; ``[{}]`` for an effect without a choice."""
    choice = effect_class(effect).choice
    if not choice:
        return [{}]
    return [{choice: "speed"}, *({choice: s} for s in ds.metadata.sensors)]


def context(ds: Dataset) -> dict:
    """What an open term needs to describe itself and find its canonical name."""
    targets = ds.errors["target_mm"]
    return {"length_m": ds.metadata.screw.length_m, "sensors": dict(ds.metadata.sensors),
            "travel_mm": (float(targets.min()), float(targets.max()))}  # fmt: skip


@dataclass
class Settings:
    """What the search needs besides the data (from ``conf/diagnose.yaml``)."""

    physics: dict = field(default_factory=dict)  # PhysicsModel numerics/solver options
    starts: dict = field(default_factory=dict)  # {effect: {param: [start values screened]}}
    test: SignificanceTest = field(default_factory=significance.SignificanceTest)
    candidates: Sequence[str] = CANDIDATES
    say: Callable[[str], None] = print
    refit: int = 3  # candidates re-identified with every parameter free after screening, per step
    family: Any = None  # what is confronted with the data (ScrewFamily, discrepancy.spindle.SpindleFamily); None: the screw

    def __post_init__(self):
        if self.family is None:
            self.family = ScrewFamily()


def ambient_sensor(ds: Dataset) -> str | None:
    return next((s for s, loc in ds.metadata.sensors.items() if loc == "ambient"), None)


#: why a dataset lacks what an effect ``needs`` (``Effect.needs``), by need
NEEDS = {
    "ambient_sensor": (lambda ds: ambient_sensor(ds) is not None,
                       "no ambient temperature sensor (no sensor at location 'ambient' in metadata.yaml)"),
    "load_N": (lambda ds: "load_N" in ds.process.columns, "no axial load in the process log (column load_N absent)"),
}  # fmt: skip


def unavailable(effect: str, ds: Dataset) -> str | None:
    """Why ``effect`` cannot be tried on this dataset (None: it can): the first of its
    ``needs`` the dataset lacks."""
    for need in effect_class(effect).needs:
        has, why = NEEDS[need]
        if not has(ds):
            return why
    return None


def n_params(effects: Sequence[str]) -> int:
    """Identified parameters of core + effects (the ambient series adds none)."""
    p = len(CORE_GAINS) + len(CORE_NONLINEAR)
    for e in effects:
        p += len(make_effect(e).heat_gains) + len(own_params(e))
    return p


def make_model(
    effects: Sequence[str], ds: Dataset, settings: Settings, warm: PhysicsModel | None = None, start: dict | None = None,
    cache: FieldCache | None = None,
) -> PhysicsModel:
    """The physics model with ``effects`` on the core, warm-started from ``warm``'s parameters.

    ``ambient_drift`` is the measured ambient series as the model's ambient
    (without it the ambient is constant, as in the seed 000 core). ``cache``: simulated
    fields shared with other fits of the same search step."""
    eff, identify = {}, list(CORE_NONLINEAR)
    for e in effects:
        if e == "ambient_drift":
            continue
        params = dict(warm.effects_.get(e, {})) if warm is not None else {}
        params.update((start or {}).get(e, {}))
        eff[e] = params
        identify += [f"{e}.{p}" for p in own_params(e)]
    initial = {k: warm.params_[k] for k in CORE_NONLINEAR} if warm is not None else None
    amb = ambient_sensor(ds) if "ambient_drift" in effects else None
    m = PhysicsModel(effects=eff, identify=identify, initial=initial, ambient_sensor=amb, **settings.physics)
    if cache is not None:
        m.field_cache = cache
    return m


@dataclass
class Fitted:
    """A fitted model of the search with its scores."""

    effects: tuple[str, ...]
    model: PhysicsModel
    sse: float
    n: int
    bic: float
    heldout_fast_um: float
    fit_s: float

    @property
    def identified(self) -> dict:
        return {k: (v if isinstance(v, str) else float(v)) for k, v in self.model.params_.items()}


def folds_for(runs: Sequence[str], cv) -> list[tuple[list[str], list[str]]]:
    """Leave-one-run-out folds (:func:`thermbench.bench.splits.folds`, the benchmark's), or the declared
    split ``{train: [...], test: [...]}``, as (train runs, held-out runs) pairs."""
    from ..bench.splits import folds

    runs = list(runs)
    if cv in (None, "loro"):
        return [(list(f.train), list(f.held_out)) for f in folds(runs, [], "loro")]
    if isinstance(cv, dict) and {"train", "test"} <= set(cv):
        train, test = [str(r) for r in cv["train"]], [str(r) for r in cv["test"]]
        bad = [r for r in train + test if r not in runs]
        if bad or not train or not test or set(train) & set(test):
            raise ValueError(
                f"config key 'cv': train and test must be disjoint, non-empty lists of runs of the dataset "
                f"{runs}; got train={train}, test={test}"
            )
        return [(train, test)]
    raise ValueError(f"config key 'cv': expected 'loro' or {{train: [...], test: [...]}}, got {cv!r}")


def heldout_fast(model, ds: Dataset, folds, family=None) -> float:
    """Held-out RMSE with the gains re-solved per fold at the model's nonlinear parameters
    (a screening score: those parameters come from the fit on all training runs), within the
    gains' bounds as the full fit has them (heat gains >= 0, signed ones free)."""
    family = family or ScrewFamily()
    runs = list(dict.fromkeys(r for tr, te in folds for r in (*tr, *te)))
    lb, per_run = family.gain_basis(model, ds, runs)
    rd = readings(ds, runs)
    index = {r: i for i, r in enumerate(runs)}
    mask = [family.scored(rd[rd["run_id"] == r]) for r in runs]
    sq, n = 0.0, 0
    for train, test in folds:
        tr = [index[r] for r in train]
        a = np.concatenate([per_run[i][1] for i in tr])
        b = np.concatenate([per_run[i][2] - per_run[i][0] for i in tr])
        g = lsq_linear(a, b, bounds=(lb, np.inf), method="bvls").x if a.shape[1] else np.zeros(0)
        for r in test:
            e0, a_t, y = per_run[index[r]]
            res = (y - e0 - a_t @ g)[mask[index[r]]]
            sq += float(res @ res)
            n += res.size
    return float(np.sqrt(sq / max(n, 1)))


def _scored(effects, model, ds, runs, folds, fit_s: float, family) -> Fitted:
    sse, n = family.train_sse(model, ds, runs)
    return Fitted(tuple(effects), model, sse, n, significance.bic(sse, n, family.n_params(effects)),
                  heldout_fast(model, ds, folds, family), fit_s)  # fmt: skip


def fit_full(effects, ds, runs, folds, settings, warm=None, start=None, cache=None) -> Fitted:
    """Identify ``effects`` on ``runs`` (the training runs: all of them for leave-one-run-out,
    the declared train runs for a split) and score it. ``cache``: fields shared with the
    other fits of the search step."""
    t0 = time.perf_counter()
    model = settings.family.make_model(effects, ds, settings, warm, start, cache).fit(ds, runs)
    return _scored(effects, model, ds, runs, folds, time.perf_counter() - t0, settings.family)


def held_fit(effects, ds, runs, settings, warm, start: dict | None, cache=None):
    """``effects`` fitted with only the last one's own nonlinear parameters identified (with
    every gain): the rest held at ``warm``'s values."""
    fam = settings.family
    model = fam.make_model(effects, ds, settings, warm, start, cache)
    fam.hold(model, [f"{effects[-1]}.{p}" for p in fam.own_params(effects[-1])])
    return model.fit(ds, runs)


def fit_screen(effect: str, current: Fitted, ds, runs, folds, settings, start: dict, cache: FieldCache) -> Fitted:
    """The screening fit of a candidate: the current model's nonlinear parameters held, the
    candidate's own identified with every gain (a lower bound on what the candidate can do)."""
    t0 = time.perf_counter()
    effects = [*current.effects, effect]
    model = held_fit(effects, ds, runs, settings, current.model, start, cache)
    return _scored(effects, model, ds, runs, folds, time.perf_counter() - t0, settings.family)


def heldout_loro(effects, ds, folds, settings, warms=None, new_effect: str | None = None, variant: dict | None = None):
    """Proper held-out score: every parameter re-identified on each fold's training runs,
    warm-started from that fold's own current model (``warms``, one per fold; None: cold),
    never from a fit that saw the held-out run. The new effect's own nonlinear parameters
    start from the grid value that suits the fold's training runs, then are identified with
    the fold's other parameters held, then everything is identified (as on all runs). A choice
    term keeps the signal chosen on all runs (``variant``).

    Returns the pooled RMSE over readings after the cold reference, the table of held-out
    predictions and the fold models (the warm starts of the next step)."""
    fam = settings.family
    parts, models = [], []
    cache = fam.cache()  # the folds share their runs' fields
    for k, (train, test) in enumerate(folds):
        warm = warms[k] if warms is not None else None
        start = None
        if new_effect:
            start = (screen_start(new_effect, effects[:-1], warm, ds, train, settings, variant, cache)
                     or {new_effect: dict(variant or {})})  # fmt: skip
        if new_effect in fam.open:  # as on all runs: then its own parameters with the rest held
            start = {new_effect: fam.effect_params(held_fit(effects, ds, train, settings, warm, start, cache), new_effect)}
        m = fam.make_model(effects, ds, settings, warm, start, cache).fit(ds, train)
        models.append(m)
        for run in test:
            parts.append(residual_table(fam, m, ds, run))
    table = pd.concat(parts, ignore_index=True)
    r = table.loc[fam.scored(table), "residual_um"].to_numpy()
    return float(np.sqrt(np.mean(r**2))), table, models


def residual_table(family, model, ds, run: str) -> pd.DataFrame:
    """The run's readings with the model's prediction and residual (``thermal_um`` − predicted)."""
    rd, pred = family.table(model, ds, run)
    return rd.assign(predicted_um=pred, residual_um=rd["thermal_um"].to_numpy() - pred)


def screen_start(effect: str, current_effects, warm, ds, runs, settings, variant: dict | None = None, cache=None) -> dict:
    """Start values of the candidate's own nonlinear parameters: the best of the
    configured grid with every other nonlinear parameter held (gains solved).
    ``variant``: the candidate's choice (its driving signal), kept in the start."""
    fam = settings.family
    variant = dict(variant or {})
    own = {**fam.cls(effect).starts, **settings.starts.get(effect, {})}  # the effect's grid, or the config's
    grid = {p: list(own.get(p) or []) for p in fam.own_params(effect)}
    grid = {p: v for p, v in grid.items() if v}
    if not grid:
        return {effect: variant} if variant else {}
    best, best_rmse = {}, np.inf
    if getattr(fam.cls(effect), "joint_starts", False):  # the grid's product: parameters that trade off
        points = [dict(zip(grid, c)) for c in itertools.product(*grid.values())]
    else:  # one parameter at a time, the others at the effect's own values
        points = [{p: v} for p, values in grid.items() for v in values]
    for point in points:
        start = {effect: {**variant, **{p: float(v) for p, v in point.items()}}}
        m = fam.make_model([*current_effects, effect], ds, settings, warm, start, cache)
        fam.hold(m, [])
        m.fit(ds, runs)
        if fam.train_rmse(m) < best_rmse:
            best, best_rmse = start, fam.train_rmse(m)
    return best


def label(effect: str, model: PhysicsModel, ctx: dict) -> tuple[str, str]:
    """(label, description) of a fitted candidate: the canonical effect an open term's
    identified form is (within tolerance), else the term and its signal; its form in words."""
    eff = make_effect(effect, **model.effects_.get(effect, {})) if effect != "ambient_drift" else make_effect(effect)
    if effect not in OPEN_TERMS:
        return effect, eff.description
    choice = effect_class(effect).choice
    own = f"{effect}[{getattr(eff, choice)}]" if choice else effect
    return eff.canonical(ctx) or own, eff.describe(ctx)


def _record(eid, variant, f: Fitted, current: Fitted, floor_um, settings, ctx, refit: bool) -> dict:
    lab, words = settings.family.label(eid, f.model, ctx)
    rec = {
        "effect": eid,
        "variant": dict(variant),
        "label": lab,
        "description": words,
        "skipped": None,
        "refit": refit,
        "n_params": settings.family.n_params(f.effects),
        "heldout_rmse_um": f.heldout_fast_um,
        "explained_um": significance.explained(current.heldout_fast_um, f.heldout_fast_um),
        "bic_gain": current.bic - f.bic,
        "train_rmse_um": float(np.sqrt(f.sse / f.n)),
        "fit_s": f.fit_s,
        "fitted": f,
    }
    t = settings.test
    rec["significant"] = bool(rec["explained_um"] >= t.explained_x_floor * floor_um and rec["bic_gain"] > t.bic_min)
    return rec


def score_candidates(current: Fitted, ds, runs, folds, settings, floor_um: float, skip: dict) -> list[dict]:
    """Try every candidate not in the current model; one record per candidate.

    Every candidate is first *screened* (:func:`fit_screen`: the current model's nonlinear
    parameters held; a choice term with each signal the data offer, the best kept), then the
    ``refit`` most promising are re-identified with every parameter free (:func:`fit_full`).
    A candidate named on its screening alone is re-identified before it is named."""
    fam = settings.family
    cache, ctx = fam.cache(), fam.context(ds)
    out, screened = [], []
    for eid in fam.candidates_for(settings.candidates, current.effects):
        if eid in skip:
            out.append({"effect": eid, "skipped": skip[eid]})
            continue
        fits = []
        for var in fam.variants(eid, ds, current.model):
            start = screen_start(eid, current.effects, current.model, ds, runs, settings, var, cache)
            if eid not in fam.open:  # re-identified in full below, from the grid's start
                fits.append((eid, var, _Start(start)))
                continue
            fits.append((eid, var, fit_screen(eid, current, ds, runs, folds, settings, start or {eid: var}, cache)))
        best = min(fits, key=lambda x: x[2].sse) if len(fits) > 1 else fits[0]
        screened.append(best)
        if best[1] and best[1] != fits[0][1]:
            screened.append(fits[0])  # the speed variant too (see below)
    # re-identified with every parameter free: every canonical effect (the held core may have
    # absorbed what one explains, and then its screening says nothing), the most promising open
    # terms by screening, and every speed-driven choice term: the core's own heat inputs follow
    # the speed, so the held core has absorbed most of what such a term explains
    promising = sorted((x for x in screened
                        if x[0] in fam.open and significance.explained(current.heldout_fast_um, x[2].heldout_fast_um) > 0),
                       key=lambda x: x[2].heldout_fast_um)[: settings.refit]  # fmt: skip
    chosen = ({id(x) for x in promising} | {id(x) for x in screened if x[0] not in fam.open}
              | {id(x) for x in screened if x[1] and next(iter(x[1].values())) == "speed"})  # fmt: skip
    for x in screened:
        eid, var, fs = x
        if isinstance(fs, _Start):
            f = fit_full([*current.effects, eid], ds, runs, folds, settings, current.model, fs.start, cache)
            rec = _record(eid, var, f, current, floor_um, settings, ctx, refit=True)
        else:
            rec = _record(eid, var, fs, current, floor_um, settings, ctx, refit=False)
            if id(x) in chosen:
                rec = refit(rec, current, ds, runs, folds, settings, floor_um, cache)
        out.append(rec)
        say_record(rec, settings)
    return out


@dataclass
class _Start:
    """A canonical candidate's start (no screening fit: it is re-identified in full)."""

    start: dict


def refit(rec: dict, current: Fitted, ds, runs, folds, settings, floor_um: float, cache=None) -> dict:
    """A screened candidate re-identified with every parameter free, from its screening fit."""
    eid = rec["effect"]
    start = {eid: settings.family.effect_params(rec["fitted"].model, eid)}
    f = fit_full([*current.effects, eid], ds, runs, folds, settings, current.model, start, cache)
    f.fit_s += rec["fit_s"]
    return _record(eid, rec["variant"], f, current, floor_um, settings, settings.family.context(ds), refit=True)


def say_record(rec: dict, settings) -> None:
    settings.say(
        f"[diagnose]   {significance.display(rec):<32s} held-out {rec['heldout_rmse_um']:7.3f} um  explains {rec['explained_um']:6.3f} um  "
        f"BIC gain {rec['bic_gain']:9.1f}  {'significant' if rec['significant'] else '-':11s} "
        f"({'refit' if rec['refit'] else 'screened'}, {rec['fit_s']:.1f} s)"
    )


def more_data(where: dict, ds: Dataset, noise) -> list[str]:
    """What measurements would tell more about a residual the search could not explain,
    from where and when it shows (:func:`.localise.localise` of the final model)."""
    hints = []
    targets = ds.errors["target_mm"]
    w = where["where"]
    if w == "far_end":
        hints.append(f"the residual is largest near the far end of the measured travel: measure beyond "
                     f"{targets.max():.0f} mm if the axis allows, and add a temperature sensor near the free end")  # fmt: skip
    elif w == "fixed_end":
        hints.append("the residual is largest near the fixed end: add a temperature sensor at the fixed bearing and "
                     "the motor flange")  # fmt: skip
    elif w == "middle":
        hints.append("the residual is largest mid-travel: a heat source along the screw (a support bearing, coolant) "
                     "would show on a temperature sensor mid-screw")  # fmt: skip
    elif w == "everywhere":
        hints.append("the residual is alike over the whole travel (an offset or a growth off the screw): log the "
                     "structure's temperatures (column, saddle, bed, scale mount)")  # fmt: skip
    if where["phase"] == "cooling":
        hints.append("it shows mostly while cooling: longer cool-downs would separate slow sources")
    elif where["phase"] == "heating":
        hints.append("it shows mostly while heating: heating ramps at more feeds would show how it scales")
    feeds = {ds.metadata.runs[r].condition.feed_mm_min for r in ds.run_ids}
    if len(feeds) < 3:
        hints.append(f"the runs cover {len(feeds)} feed(s): runs at three or more would show its speed dependence")
    if "load_N" not in ds.process.columns:
        hints.append("log the axial load (load_N): load-dependent heat cannot be tried without it")
    if ambient_sensor(ds) is None:
        hints.append("add an ambient temperature sensor (location 'ambient')")
    if noise.method != "repeat":
        hints.append("repeat readings of a target within a minute would give a model-free noise floor")
    return hints


class ScrewFamily:
    """The ball screw: the seed 000 core (:class:`PhysicsModel`) and its effect library
    (canonical effects, then the open terms). What the search asks of a family, answered for the
    screw; :class:`thermbench.discrepancy.spindle.SpindleFamily` answers it for a spindle."""

    name = "screw"
    base_words = "the seed 000 core (fixed-bearing heat, nut heat, convection, constant ambient)"
    driver = "feed_mm_min"  # what the per-run residual is set against (the run's condition)

    @property
    def candidates(self) -> tuple[str, ...]:
        return (*EFFECTS, *OPEN_TERMS)

    @property
    def canonical(self):
        return EFFECTS

    @property
    def open(self):
        return OPEN_TERMS

    def cls(self, eid: str):
        return effect_class(eid)

    def own_params(self, eid: str) -> tuple[str, ...]:
        return own_params(eid)

    def variants(self, eid: str, ds: Dataset, model=None) -> list[dict]:
        return variants(eid, ds)

    def candidates_for(self, candidates, effects) -> list[str]:
        """The candidates of a step: those not in the model yet."""
        return [c for c in candidates if c not in effects]

    def context(self, ds: Dataset) -> dict:
        return context(ds)

    def unavailable(self, eid: str, ds: Dataset) -> str | None:
        return unavailable(eid, ds)

    def n_params(self, effects) -> int:
        return n_params(effects)

    def make_model(self, effects, ds, settings, warm=None, start=None, cache=None):
        return make_model(effects, ds, settings, warm, start, cache)

    def hold(self, model, free: Sequence[str]):
        """Identify only ``free`` of the model's nonlinear parameters at its next fit."""
        model.set_params(identify=list(free))
        return model

    def effect_params(self, model, eid: str) -> dict:
        return dict(model.effects_.get(eid, {}))

    def gain_basis(self, model, ds, runs):
        units, per_run = model.gain_basis(ds, runs)
        return model.gain_lower_bounds(units), per_run

    def table(self, model, ds, run):
        return model.referenced_thermal_um(ds, run)

    def scored(self, rd: pd.DataFrame) -> np.ndarray:
        """Readings that carry information: the cold reference readings have residual 0."""
        return (rd["cycle"] > 0).to_numpy()

    def train_rmse(self, model) -> float:
        return model.train_rmse_um_

    def train_sse(self, model, ds, runs) -> tuple[float, int]:
        rd = readings(ds, runs)
        sse = model.train_rmse_um_**2 * len(rd)  # the cold-reference readings have residual 0 ...
        return sse, int((rd["cycle"] > 0).sum())  # ... and carry no information: n counts the others

    def cache(self):
        return FieldCache(size=256)

    def label(self, eid, model, ctx):
        return label(eid, model, ctx)

    # ------------------------------------------------------------- workflow ---
    def prepare_base(self, base: list[str], ds: Dataset, notes: list[str]) -> list[str]:
        """Seed 004: a screw held at both ends has the fixed-fixed constraint in its base."""
        if ds.metadata.screw.mounting == "fixed_fixed" and "fixed_fixed_constraint" not in base:
            base.append("fixed_fixed_constraint")
            notes.append("fixed_fixed_constraint added to the base: metadata.yaml declares mounting fixed_fixed")
        return base

    def annotate(self, table, ds, model, floor_um):
        from .localise import annotate

        return annotate(table, ds, model.params_["pf_m"] * 1000.0, floor_um)

    def more_data(self, where, ds, noise):
        return more_data(where, ds, noise)


__getattr__ = thermbench.moved_names(__name__)
