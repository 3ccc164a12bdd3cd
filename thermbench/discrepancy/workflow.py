"""``thermbench diagnose``: find where simulation and measurement disagree, name the
missing effect, add it, show the gap shrink.

:func:`run_diagnosis` is the workflow on a loaded dataset (plain function, what
the tests call); :func:`thermbench.discrepancy.job.diagnose` is the job behind the
command (:mod:`.job`).

1. Identify the current physics model (seed 000 core + ``base`` effects) with
   run-wise cross-validation (leave one run out, or a declared split).
2. Localise the held-out residual over (time, position) per run and condition
   against the noise floor estimated from the data (:mod:`.noise`, :mod:`.localise`).
3. Add each canonical effect not yet in the model, re-identify warm-started,
   score held-out error and BIC (:mod:`.search`).
4. Name the missing effect by the stated test (:mod:`.significance`), or report a tie, or none.
5. Add it, re-identify, report the held-out gap shrink; repeat up to ``max_effects``.
"""

from __future__ import annotations

import time
from typing import Any, Sequence

import numpy as np
import pandas as pd

import thermbench

from ..data.io import Dataset
from . import localise as loc
from .noise import estimate_noise_floor
from .search import (
    ScrewFamily,
    residual_table,
    Settings,
    fit_full,
    folds_for,
    heldout_loro,
    refit,
    score_candidates,
)
from .significance import SignificanceTest, decide, display, explained


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


__getattr__ = thermbench.moved_names(__name__)
