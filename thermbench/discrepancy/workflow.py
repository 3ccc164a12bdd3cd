"""``thermbench diagnose``: find where simulation and measurement disagree, name the
missing effect, add it, show the gap shrink (issue "Discrepancy workflow").

:func:`run_diagnosis` is the workflow on a loaded dataset (plain function, what
the tests call); :func:`diagnose` is the job behind the command: it reads the
dataset files, runs the workflow, writes ``diagnosis.json``, ``report.md`` and
the figures atomically into the output directory and logs them to MLflow.

1. Identify the current physics model (seed 000 core + ``base`` effects) with
   run-wise cross-validation (leave one run out, or a declared split).
2. Localise the held-out residual over (time, position) per run and condition
   against the noise floor estimated from the data (:mod:`.noise`, :mod:`.localise`).
3. Add each canonical effect not yet in the model, re-identify warm-started,
   score held-out error and BIC (:mod:`.search`).
4. Name the missing effect by the stated test, or report a tie, or none.
5. Add it, re-identify, report the held-out gap shrink; repeat up to ``max_effects``.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np
import pandas as pd

from ..outputs import check_output_dir, output_dir
from ..data.io import Dataset, load_dataset
from . import localise as loc
from .noise import estimate_noise_floor
from .search import (
    ScrewFamily,
    residual_table,
    Settings,
    SignificanceTest,
    decide,
    display,
    explained,
    fit_full,
    folds_for,
    heldout_loro,
    refit,
    score_candidates,
)


#: floor used when the data look noise-free (a zero floor would make every difference significant)
MIN_FLOOR_UM = 1e-3


class DiagnoseError(ValueError):
    """A user mistake in the diagnose command or its config; the message names the key."""


def _check_effects(names: Sequence[str], key: str, open_terms: bool = False, family=None) -> list[str]:
    """Effect ids of config key ``key``: the family's canonical effects, and its open terms where
    allowed (as candidates; a screw's base effect is a canonical one, a spindle's any term)."""
    family = family or ScrewFamily()
    out = [str(n).strip() for n in names if str(n).strip()]
    canonical = family.canonical if family.canonical else family.open
    known = {*canonical, *(family.open if open_terms else ())}
    bad = [n for n in out if n not in known]
    if bad:
        if not family.canonical:
            raise DiagnoseError(f"config key {key!r}: unknown term(s) {bad}; the {family.name} terms are {sorted(family.open)}")
        more = f", the open terms {sorted(family.open)}" if open_terms else ""
        raise DiagnoseError(f"config key {key!r}: unknown effect(s) {bad}; the canonical effects are {sorted(canonical)}{more}")
    if len(set(out)) != len(out):
        raise DiagnoseError(f"config key {key!r}: an effect is listed twice: {out}")
    return out


def physics_view(ds: Dataset) -> Dataset:
    """What the workflow confronts the screw physics model with: a format 1 dataset as it is; a
    format 2 one through its one along-axis channel, which needs a screw block. Anything else
    is one line saying what is missing (a spindle test has no screw to simulate)."""
    from ..models.base import NEEDS

    if ds.metadata.version == 1:
        return ds
    along = [c for c, m in ds.metadata.error_channels().items() if m.kind == "along_axis"]
    missing = ([NEEDS["screw"]] if ds.metadata.screw is None else []) + ([NEEDS["along_axis"]] if not along else [])
    if missing:
        raise DiagnoseError(f"{ds.path}: the discrepancy workflow confronts the screw physics model with the data; it "
                            f"needs {'; and '.join(missing)}, and this dataset (a test of: "
                            f"{', '.join(ds.metadata.parts or [])}) has none")  # fmt: skip
    if len(along) > 1:
        raise DiagnoseError(f"{ds.path}: {len(along)} along-axis channels {along}; the workflow takes one: "
                            "write a dataset with that channel only")  # fmt: skip
    return ds.channel_view(along[0])


def run_diagnosis(
    ds: Dataset,
    base: Sequence[str] = (),
    max_effects: int = 3,
    cv: Any = "loro",
    settings: Settings | None = None,
    noise_window_s: float = 60.0,
    noise_min_groups: int = 20,
    holdout: Sequence[str] = (),
) -> dict:
    """The discrepancy workflow on a dataset; returns the diagnosis (see module docstring).
    ``holdout``: runs kept out of the whole search (never fitted, scored or localised),
    scored once at the end with the base and with the final model."""
    from ..data.reference import frame_text

    settings = settings or Settings()
    fam = settings.family
    say = settings.say
    t_start = time.perf_counter()
    base = _check_effects(base, "base", family=fam)
    _check_effects(settings.candidates, "candidates", open_terms=True, family=fam)
    if int(max_effects) < 0:
        raise DiagnoseError(f"config key 'max_effects': expected an integer >= 0, got {max_effects}")
    notes = []
    base = fam.prepare_base(list(base), ds, notes)
    for e in base:
        if (why := fam.unavailable(e, ds)) is not None:
            raise DiagnoseError(f"config key 'base': effect {e!r} cannot be used on this dataset: {why}")
    holdout = [str(r) for r in holdout]
    if bad := [r for r in holdout if r not in ds.run_ids]:
        raise DiagnoseError(f"config key 'holdout': runs {bad} are not in the dataset; its runs: {list(ds.run_ids)}")
    runs = [r for r in ds.run_ids if r not in holdout]
    try:
        folds = folds_for(runs, cv)
    except ValueError as exc:
        raise DiagnoseError(str(exc)) from None
    # what the models are identified on: every run (leave-one-run-out) or the declared train runs
    fit_runs = runs if len(folds) > 1 else folds[0][0]
    skip = {e: why for e in settings.candidates if e not in base and (why := fam.unavailable(e, ds)) is not None}
    for e, why in skip.items():
        say(f"[diagnose] candidate {e} skipped: {why}")

    n_read = int(ds.errors["run_id"].isin(runs).sum())
    say(f"[diagnose] {len(runs)} runs, {n_read} readings{f' (held out of the search: {holdout})' if holdout else ''}; "
        f"base: {fam.base_words}{''.join(' + ' + e for e in base)}")  # fmt: skip
    current = fit_full(base, ds, fit_runs, folds, settings)
    path = [("base", current)]  # the model after each named step (the held-out runs are scored along it)
    say(f"[diagnose] base identified in {current.fit_s:.1f} s: train RMSE {np.sqrt(current.sse / current.n):.3f} um")
    before_um, table, fold_models = heldout_loro(base, ds, folds, settings)
    noise = _noise(fam, _in_sample_table(fam, current.model, ds, fit_runs), noise_window_s, noise_min_groups)
    floor = noise.noise_floor_um
    if floor < MIN_FLOOR_UM:
        notes.append(f"noise floor estimated at {floor:.2g} um (noise-free data?); {MIN_FLOOR_UM} um used")
        floor = MIN_FLOOR_UM
    say(f"[diagnose] noise floor {floor:.3f} um ({noise.method}); held-out RMSE of the base {before_um:.3f} um")
    loc_before = loc.localise(fam.annotate(table, ds, current.model, floor), floor, fam.driver)
    say(f"[diagnose] where: {loc_before['summary']}")

    steps, scans, missing, ambiguous = [], [], [], []
    tables = {"before": table}
    while len(missing) < int(max_effects):
        n_try = sum(1 for c in fam.candidates_for(settings.candidates, current.effects) if c not in skip)
        say(f"[diagnose] step {len(steps) + 1}: trying {n_try} candidate(s) on the base"
            f"{''.join(' + ' + e for e in current.effects)}")  # fmt: skip
        cands = score_candidates(current, ds, fit_runs, folds, settings, floor, skip)
        best, ties = decide(cands, floor, settings.test)
        while best is not None and not best["refit"]:  # named on its screening: re-identify it first
            i = next(i for i, c in enumerate(cands) if c.get("fitted") is best["fitted"])
            cands[i] = refit(cands[i], current, ds, fit_runs, folds, settings, floor)
            best, ties = decide(cands, floor, settings.test)
        scans.append({"effects": list(current.effects), "heldout_fast_um": current.heldout_fast_um, "noise_floor_um": floor,
                      "candidates": [_public(c) for c in cands], "named": best["effect"] if best else None,
                      "ambiguous_with": ties})  # fmt: skip
        if best is None:
            if settings.test.within_floor(before_um, floor):
                say(f"[diagnose] no candidate passes the test, and the held-out RMSE ({before_um:.3f} um) is within "
                    f"{settings.test.within_x_floor:g}x the noise floor: nothing (more) is missing that these data show")  # fmt: skip
            else:
                say(f"[diagnose] no candidate passes the test, but the held-out RMSE ({before_um:.3f} um) is still "
                    f"{before_um / floor:.1f}x the noise floor: something the candidates cannot describe is missing")  # fmt: skip
            break
        new = [*current.effects, best["effect"]]
        after_um, after_table, new_fold_models = heldout_loro(new, ds, folds, settings, fold_models, best["effect"],
                                                              best["variant"])  # fmt: skip
        step = {
            "effect": best["effect"],
            "variant": best["variant"],
            "label": best["label"],
            "canonical": best["label"] if best["label"] in fam.canonical else None,
            "description": best["description"],
            "signals_alike": best["alike"],
            "ambiguous_with": ties,
            "heldout_rmse_before_um": before_um,
            "heldout_rmse_after_um": after_um,
            "explained_um": explained(before_um, after_um),
            "bic_gain": best["bic_gain"],
            "identified": best["fitted"].identified,
            "confirmed": explained(before_um, after_um) >= settings.test.explained_x_floor * floor,
        }
        steps.append(step)
        if not step["confirmed"]:
            say(f"[diagnose] {best['effect']} passed the screening but not the held-out test with every parameter "
                f"re-identified per fold ({before_um:.3f} -> {after_um:.3f} um); stopping")  # fmt: skip
            break
        if ties:
            ambiguous.append([display(best), *ties])
            say(f"[diagnose] ambiguous: {' or '.join([display(best), *ties])} explain the data alike; not guessing")
            break
        if best["effect"] in fam.open:
            same = f" (= {best['label']})" if best["label"] != best["effect"] and best["label"] in {*fam.canonical, *fam.open} else ""
            say(f"[diagnose] described by {'an open term' if fam.canonical else 'a term'}{same}: {best['description']}")
            if best["alike"]:
                say(f"[diagnose] its driver is not told apart: {' or '.join([display(best), *best['alike']])} fit alike")
        say(f"[diagnose] missing effect: {display(best)}: held-out RMSE {before_um:.3f} -> {after_um:.3f} um "
            f"({1 - after_um / before_um:.0%} less)")  # fmt: skip
        missing.append(best["effect"])
        current, before_um, fold_models = best["fitted"], after_um, new_fold_models
        path.append(("+ " + display(best), current))
        tables[f"step{len(steps)}"] = after_table
        # the floor is a property of the data, best seen through the best model so far
        grown = _noise(fam, _in_sample_table(fam, current.model, ds, fit_runs), noise_window_s, noise_min_groups)
        if MIN_FLOOR_UM <= grown.noise_floor_um < floor:
            noise, floor = grown, grown.noise_floor_um
            say(f"[diagnose] noise floor re-estimated with the grown model: {floor:.3f} um")
    final_table = tables[list(tables)[-1]]
    loc_after = loc.localise(fam.annotate(final_table, ds, current.model, floor), floor, fam.driver)
    first = steps[0]["heldout_rmse_before_um"] if steps else before_um
    within = settings.test.within_floor(before_um, floor)
    if int(max_effects) == 0:
        notes.append("no search (max_effects = 0): the verdict judges the base model alone")
    if steps and not steps[-1]["confirmed"]:
        notes.append(f"{steps[-1]['effect']} passed the screening but not the held-out test with every parameter "
                     "re-identified per fold")  # fmt: skip
    if ambiguous:
        verdict = "ambiguous"
    elif missing:
        verdict = "found" if within else "found_partial"
    else:
        verdict = "none" if within else "unexplained"
    gap = _gap(before_um, floor, settings.test, loc_after, scans, ds, noise, current.effects, fam)
    validation = _validation(fam, ds, holdout, path, tables, floor) if holdout else None
    return {
        "family": fam.name,
        "base_words": fam.base_words,
        "validation": validation,
        "dataset": str(ds.path) if ds.path is not None else ds.metadata.machine.name,
        "frame": fam.frame(ds) if hasattr(fam, "frame") else frame_text(ds.metadata),  # the frame of every score
        "base_effects": list(base),
        "noise_floor_um": floor,
        "noise": noise.to_dict(),
        "missing_effects": missing,
        "ambiguous": ambiguous,
        "skipped": skip,
        "steps": steps,
        "scans": scans,
        "localisation": {"before": loc_before, "after": loc_after},
        "final": {
            "effects": list(current.effects),
            "heldout_rmse_um": before_um,
            "noise_floor_um": floor,
            "heldout_x_floor": before_um / floor,
            "within_floor": within,
            "heldout_rmse_base_um": first,
            "identified": current.identified,
        },
        "gap": gap,
        "cv": {"kind": "loro" if len(folds) > 1 else "split", "fit_runs": list(fit_runs),
               "folds": [{"train": a, "test": b} for a, b in folds]},  # fmt: skip
        "test": {"description": settings.test.describe(), **vars(settings.test)},
        "notes": notes,
        "verdict": verdict,
        "runtime_s": time.perf_counter() - t_start,
        "_tables": tables,
    }


def _gap(heldout_um: float, floor_um: float, test: SignificanceTest, where: dict, scans: list[dict], ds: Dataset,
         noise, in_model: Sequence[str] = (), family=None) -> dict:  # fmt: skip
    """What is left after the search: how far above the floor, where and when (the final
    model's localisation), what the best remaining candidate explains and what remains,
    and what data would tell more."""
    best = None
    if scans:
        tried = [c for c in scans[-1]["candidates"] if not c.get("skipped") and c.get("heldout_rmse_um") is not None
                 and c["effect"] not in in_model]  # the last scan's winner may have joined the model since
        if tried:
            c = min(tried, key=lambda c: c["heldout_rmse_um"])
            words = c.get("description") if c.get("label") != c["effect"] else None
            best = {"effect": display(c), "description": words, "explains_um": c["explained_um"], "heldout_rmse_um": c["heldout_rmse_um"],
                    "remains_x_floor": c["heldout_rmse_um"] / floor_um, "significant": bool(c.get("significant"))}  # fmt: skip
    return {
        "heldout_rmse_um": heldout_um,
        "noise_floor_um": floor_um,
        "x_floor": heldout_um / floor_um,
        "systematic_um": explained(heldout_um, floor_um),
        "within_floor": test.within_floor(heldout_um, floor_um),
        "where": where["where"],
        "phase": where["phase"],
        "driver": where["driver"],
        "driver_trend": where["driver_trend"],
        "load_trend": where["load_trend"],
        "best_candidate": best,
        "more_data": (family or ScrewFamily()).more_data(where, ds, noise) if not test.within_floor(heldout_um, floor_um) else [],
    }


def more_data(where: dict, ds: Dataset, noise) -> list[str]:
    """What measurements would tell more about a residual the search could not explain,
    from where and when it shows (:func:`.localise.localise` of the final model)."""
    from .search import ambient_sensor

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


def _in_sample_table(family, model, ds, runs):
    """Readings of ``runs`` with the in-sample residual of ``model`` (for the noise floor)."""
    return pd.concat([residual_table(family, model, ds, r) for r in runs], ignore_index=True)


def _noise(family, table, window_s, min_groups):
    est = getattr(family, "noise_floor", None)
    return est(table, window_s, min_groups) if est else estimate_noise_floor(table, window_s, min_groups)


def _validation(fam, ds, holdout, path, tables, floor_um) -> dict:
    """The runs held out of the search, scored once at its end: the base and the model after each
    named step (``path``: (name, Fitted) pairs), each fitted on every search run."""

    def scored(model) -> pd.DataFrame:
        t = pd.concat([residual_table(fam, model, ds, r) for r in holdout], ignore_index=True)
        return t[fam.scored(t)]

    rms = lambda t: float(np.sqrt(np.mean(t["residual_um"].to_numpy() ** 2)))  # noqa: E731
    steps = []
    for name, fitted in path:
        t = scored(fitted.model)
        steps.append({"model": name, "rmse_um": rms(t), "x_floor": rms(t) / floor_um,
                      "per_run": {r: rms(t[t["run_id"] == r]) for r in holdout}, "_table": t})  # fmt: skip
    tables["holdout_base"], tables["holdout_final"] = steps[0]["_table"], steps[-1]["_table"]
    for st in steps:
        del st["_table"]
    first, last = steps[0], steps[-1]
    return {"runs": list(holdout), "effects": list(path[-1][1].effects), "rmse_base_um": first["rmse_um"],
            "rmse_final_um": last["rmse_um"], "x_floor_base": first["x_floor"], "x_floor_final": last["x_floor"],
            "by_step": steps,
            "per_run": {r: {"rmse_base_um": first["per_run"][r], "rmse_final_um": last["per_run"][r]} for r in holdout}}  # fmt: skip


def _public(c: dict) -> dict:
    return {k: v for k, v in c.items() if k != "fitted"}


# ------------------------------------------------------------------ the job ---
def _number(value, key: str, kind=float, lo: float | None = None):
    """``value`` as ``kind``, finite (and >= ``lo`` when given), else a one-line error naming ``key``."""
    try:
        if isinstance(value, bool):
            raise ValueError
        out = kind(value)
    except (TypeError, ValueError, OverflowError):
        raise DiagnoseError(f"config key {key!r}: expected {'an integer' if kind is int else 'a number'}, got {value!r}") from None
    if not np.isfinite(out):
        raise DiagnoseError(f"config key {key!r}: expected a finite number, got {value!r}")
    if lo is not None and out < lo:
        raise DiagnoseError(f"config key {key!r}: expected a number >= {lo:g}, got {value!r}")
    return out


#: lowest allowed value of the numeric physics keys: (bound, strict: value > bound, else >=)
_PHYSICS_LOWEST = {"dx_m": (0, True), "dt_s": (0, True), "macro_dt_s": (0, True), "max_iter": (1, False),
                   "ftol": (0, True), "geometric_degree": (0, False)}  # fmt: skip


def _check_physics(physics: dict) -> None:
    """The identification model's numbers (``physics.*``) in range, before any data is read:
    steps and tolerances > 0, at least one iteration, ``macro_dt_s`` a whole multiple of
    ``dt_s`` (what :class:`thermbench.sim.parts.Numerics` requires)."""
    from ..sim.parts import Numerics

    for k, (lowest, strict) in _PHYSICS_LOWEST.items():
        if k in physics and (physics[k] <= lowest if strict else physics[k] < lowest):
            raise DiagnoseError(f"config key 'physics.{k}': must be {'>' if strict else '>='} {lowest}, got {physics[k]!r}")
    steps = {k: physics[k] for k in ("dx_m", "dt_s", "macro_dt_s") if k in physics}
    try:
        Numerics(**steps)
    except ValueError:
        dt_s, macro_dt_s = steps.get("dt_s", Numerics.dt_s), steps.get("macro_dt_s", Numerics.macro_dt_s)
        raise DiagnoseError(f"config key 'physics.macro_dt_s': must be a whole multiple of physics.dt_s "
                            f"(got macro_dt_s={macro_dt_s!r}, dt_s={dt_s!r})") from None  # fmt: skip


#: PhysicsModel options the diagnose config may set (the rest are the workflow's to choose)
PHYSICS_KEYS = {"dx_m": float, "dt_s": float, "macro_dt_s": float, "max_iter": int, "ftol": float,
                "geometric_degree": int, "preprocess": None, "bounds": None}  # fmt: skip


def settings_from_config(cfg, say: Callable[[str], None] = print, family=None) -> Settings:
    """:class:`Settings` from the composed ``conf/diagnose.yaml``, every key checked (the
    candidates and start grids against ``family``'s library; None: the screw's)."""
    from omegaconf import DictConfig, OmegaConf

    if isinstance(cfg, DictConfig):
        cfg = OmegaConf.to_container(cfg, resolve=True)
    test = dict(cfg.get("test") or {})
    known = {f.name for f in fields(SignificanceTest)}
    if bad := sorted(set(test) - known):
        raise DiagnoseError(f"config key 'test': unknown key(s) {bad}; known: {sorted(known)}")
    t = SignificanceTest(**{k: _number(v, f"test.{k}") for k, v in test.items()})
    if t.within_x_floor < 1.0:
        raise DiagnoseError(f"config key 'test.within_x_floor': expected a number >= 1 (a perfect model's held-out "
                            f"RMSE is the noise floor itself), got {t.within_x_floor:g}")  # fmt: skip
    physics = dict(cfg.get("physics") or {})
    if bad := sorted(set(physics) - set(PHYSICS_KEYS)):
        raise DiagnoseError(f"config key 'physics': unknown or reserved key(s) {bad}; allowed: {sorted(PHYSICS_KEYS)}")
    physics = {k: (_number(v, f"physics.{k}", PHYSICS_KEYS[k]) if PHYSICS_KEYS[k] else v) for k, v in physics.items()}
    _check_physics(physics)
    family = family or ScrewFamily()
    own_params = family.own_params
    starts = {}
    for eid, params in dict(cfg.get("starts") or {}).items():
        searched = sorted(e for e in (*family.canonical, *family.open) if own_params(e))
        if eid not in searched or not isinstance(params, dict):
            raise DiagnoseError(f"config key 'starts.{eid}': expected one of {searched} with "
                                f"{{param: [values]}}, e.g. +starts.motor_heat.tau_s=[600,1800]")  # fmt: skip
        for param, values in params.items():
            if param not in own_params(eid):
                raise DiagnoseError(f"config key 'starts.{eid}.{param}': {eid} has {list(own_params(eid))}")
            values = values if isinstance(values, (list, tuple)) else [values]
            starts.setdefault(eid, {})[param] = [_number(v, f"starts.{eid}.{param}") for v in values]
    return Settings(
        physics=physics,
        starts=starts,
        test=t,
        candidates=_check_effects(_as_list(cfg.get("candidates")) or list(family.candidates), "candidates", open_terms=True,
                                  family=family),  # fmt: skip
        say=say,
        refit=_refit(cfg.get("refit", 3)),
        family=family,
    )


def _refit(v) -> int:
    n = _number(v, "refit", int)
    if n < 1:
        raise DiagnoseError(f"config key 'refit': expected an integer >= 1 (candidates re-identified per step), got {v!r}")
    return n


def _as_list(v) -> list[str]:
    if v is None:
        return []
    if isinstance(v, str):
        return [s for s in v.split(",") if s.strip()]
    return [str(x) for x in v]


def check_out_dir(out_dir, data_dir, force: bool = False) -> Path:
    """The output directory, refused when writing there could lose anything
    (:func:`thermbench.outputs.check_output_dir`: it is, contains or lies in a dataset, or
    holds files that an earlier diagnosis did not write), or when it is not writable."""
    out = Path(out_dir).expanduser().resolve()
    data = Path(data_dir).expanduser().resolve()
    if out == data or data.is_relative_to(out) or out.is_relative_to(data):
        raise DiagnoseError(f"--out {out}: is, contains or lies inside the dataset directory {data}; choose another directory")
    check_output_dir(out, "diagnosis", force=force)
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not os.access(parent, os.W_OK):
        raise DiagnoseError(f"--out {out}: {parent} is not writable")
    return out


def load_for_diagnosis(conf: dict):
    """The dataset the workflow confronts, its family and the runs held out of the search.

    ``data_dir`` is a dataset directory or a ``conf/dataset`` option (``fl_thermal``). A screw
    axis (format 1, or an along-axis channel of a dataset with a screw) is confronted with the
    seed 000 physics model as it is; a fixed-point channel (a spindle test) with the lumped
    network (:mod:`.spindle`), through its segments (each with the test's log from its start,
    ``history``) and with the option's validation runs held out (``holdout`` overrides)."""
    from ..errors import ExperimentError
    from ..bench.splits import dataset_option, dataset_view, load_source
    from .spindle import NETWORK_KEYS, spindle_family

    entry, channel = str(conf["data_dir"]), conf.get("channel")
    holdout, history = conf.get("holdout"), conf.get("history")
    if history is not None and not isinstance(history, bool):
        raise DiagnoseError(f"config key 'history': expected true or false, got {history!r}")
    if (Path(entry) / "metadata.yaml").is_file():
        ds, validation = load_dataset(entry), []
    else:
        try:
            _, dcfg = dataset_option(entry, "data_dir")
            ds = load_source(dcfg)[0]
        except ExperimentError as exc:
            raise DiagnoseError(str(exc)) from None
        validation = list(dcfg.get("validation") or [])
        history = dcfg.get("history") if history is None else history
    channels = ds.metadata.error_channels() if ds.metadata.version == 2 else {}
    if channel is not None and channel not in channels:
        raise DiagnoseError(f"config key 'channel': {channel!r} is not an error channel of {ds.path}; "
                            f"its channels: {list(channels) or 'none (a format 1 dataset has one error)'}")  # fmt: skip
    if channel is None and len(channels) > 1 and not any(m.kind == "along_axis" for m in channels.values()):
        raise DiagnoseError(f"config key 'channel': {ds.path} has {len(channels)} error channels {list(channels)}; "
                            f"name one, e.g. --channel {next(iter(channels))}")  # fmt: skip
    kind = channels[channel].kind if channel is not None else (next(iter(channels.values())).kind if len(channels) == 1 else None)
    if kind != "fixed_point":
        if holdout:
            raise DiagnoseError("config key 'holdout': runs held out of the search are for a spindle test; on a screw "
                                "axis use cv: {train: [...], test: [...]}")  # fmt: skip
        return physics_view(ds.channel_view(channel) if channel is not None else ds), ScrewFamily(), []
    view = dataset_view(ds, channel or next(iter(channels)), segments=True, history=True if history is None else history)
    holdout = validation if holdout is None else _as_list(holdout)
    if bad := [r for r in holdout if r not in view.run_ids]:
        raise DiagnoseError(f"config key 'holdout': runs {bad} are not in the dataset; its runs: {list(view.run_ids)}")
    net = dict(conf.get("spindle") or {})
    if bad := sorted(set(net) - set(NETWORK_KEYS)):
        raise DiagnoseError(f"config key 'spindle': unknown or reserved key(s) {bad}; allowed: {sorted(NETWORK_KEYS)}")
    net = {k: (_number(v, f"spindle.{k}", NETWORK_KEYS[k], lo=1 if NETWORK_KEYS[k] is int else 0) if NETWORK_KEYS[k] else v)
           for k, v in net.items()}  # fmt: skip
    try:
        family = spindle_family(view, [r for r in view.run_ids if r not in holdout], net, history=history is not False)
    except ValueError as exc:
        raise DiagnoseError(str(exc)) from None
    return view, family, holdout


def diagnose(cfg, say: Callable[[str], None] | None = None) -> dict:
    """The ``thermbench diagnose`` job: ``cfg`` is ``conf/diagnose.yaml`` composed (a
    DictConfig or a plain mapping). Reads only the files of ``cfg.data_dir``."""
    from omegaconf import DictConfig, OmegaConf

    from .. import tracking
    from .report import terminal_verdict, write_figures, write_markdown

    conf = OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig) else dict(cfg)
    say = say or (lambda m: print(m, flush=True))
    for key in ("data_dir", "out_dir"):
        if not conf.get(key) or conf[key] == "???":
            raise DiagnoseError(f"config key {key!r}: required (thermbench diagnose DATA_DIR --out OUT_DIR)")
    # everything the user can get wrong is checked before anything is loaded or fitted: the numbers
    # first, then (the dataset says which library applies) the effects or terms named
    settings_from_config({**conf, "candidates": None, "starts": None, "base": None}, say)
    max_effects = _number(conf.get("max_effects", 3), "max_effects", int)
    noise = dict(conf.get("noise") or {})
    window_s = _number(noise.get("repeat_window_s", 60.0), "noise.repeat_window_s", lo=0.0)
    min_groups = _number(noise.get("min_groups", 20), "noise.min_groups", int)
    force = conf.get("force", False)
    if not isinstance(force, bool):
        raise DiagnoseError(f"config key 'force': expected true or false, got {force!r}")
    if Path(str(conf["data_dir"])).is_dir():
        check_out_dir(conf["out_dir"], conf["data_dir"], force)
    ds, family, holdout = load_for_diagnosis(conf)
    base = _check_effects(_as_list(conf.get("base")), "base", family=family)
    settings = settings_from_config(conf, say, family)
    out = check_out_dir(conf["out_dir"], ds.path if ds.path is not None else conf["data_dir"], force)
    track = bool(conf.get("track", True))
    exp_id = tracking.connect(conf["tracking"]) if track else None  # an unreachable server fails first
    d = run_diagnosis(ds, base=base, max_effects=max_effects, cv=conf.get("cv", "loro"), settings=settings,
                      noise_window_s=window_s, noise_min_groups=min_groups, holdout=holdout)  # fmt: skip
    tables = d.pop("_tables")
    d = _finite(d)
    with output_dir(out, "diagnosis", force=force) as tmp:
        (tmp / "diagnosis.json").write_text(json.dumps(d, indent=2, allow_nan=False, default=_json_default), encoding="utf-8")
        write_figures(d, tables, tmp, settings.test.explained_x_floor)
        write_markdown(d, tmp)
        pd.concat([t.assign(model=k) for k, t in tables.items()], ignore_index=True).to_csv(tmp / "heldout_residuals.csv", index=False)
    if track:
        import mlflow

        with mlflow.start_run(experiment_id=exp_id, run_name=f"diagnose | {ds.metadata.machine.name}") as run:
            mlflow.set_tags(tracking.standard_tags(ds.content_hash(), tracking.config_hash(conf), "diagnose")
                            | {"missing_effects": ",".join(d["missing_effects"]) or "none", "verdict": d["verdict"]})  # fmt: skip
            tracking.log_config(conf)
            tracking.log_dataset(ds, ds.metadata.machine.name, "evaluation", digest=ds.content_hash())
            mlflow.log_metrics({"noise_floor_um": d["noise_floor_um"], "heldout_rmse_base_um": d["final"]["heldout_rmse_base_um"],
                                "heldout_rmse_final_um": d["final"]["heldout_rmse_um"], "n_missing": len(d["missing_effects"]),
                                "runtime_s": d["runtime_s"]})  # fmt: skip
            mlflow.log_artifacts(str(out), artifact_path="diagnosis")
        d["mlflow_run_id"] = run.info.run_id
    say(terminal_verdict(d, out))
    return d


def _finite(o):
    """NaN and infinities -> None, so that diagnosis.json is strict JSON."""
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, (float, np.floating)) and not np.isfinite(o):
        return None
    return o


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")
