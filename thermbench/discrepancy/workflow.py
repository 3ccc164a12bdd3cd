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
from ..sim.effects import EFFECTS, OPEN_TERMS
from . import localise as loc
from .noise import estimate_noise_floor
from .search import (
    CANDIDATES,
    own_params,
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
    unavailable,
)


#: floor used when the data look noise-free (a zero floor would make every difference significant)
MIN_FLOOR_UM = 1e-3


class DiagnoseError(ValueError):
    """A user mistake in the diagnose command or its config; the message names the key."""


def _check_effects(names: Sequence[str], key: str, open_terms: bool = False) -> list[str]:
    """Effect ids of config key ``key``: canonical effects, and the open terms where allowed
    (as candidates; a base effect is a canonical one)."""
    out = [str(n).strip() for n in names if str(n).strip()]
    known = {*EFFECTS, *(OPEN_TERMS if open_terms else ())}
    bad = [n for n in out if n not in known]
    if bad:
        more = f", the open terms {sorted(OPEN_TERMS)}" if open_terms else ""
        raise DiagnoseError(f"config key {key!r}: unknown effect(s) {bad}; the canonical effects are {sorted(EFFECTS)}{more}")
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
) -> dict:
    """The discrepancy workflow on a dataset; returns the diagnosis (see module docstring)."""
    from ..data.reference import frame_text

    settings = settings or Settings()
    say = settings.say
    t_start = time.perf_counter()
    base = _check_effects(base, "base")
    _check_effects(settings.candidates, "candidates", open_terms=True)
    if int(max_effects) < 0:
        raise DiagnoseError(f"config key 'max_effects': expected an integer >= 0, got {max_effects}")
    notes = []
    if ds.metadata.screw.mounting == "fixed_fixed" and "fixed_fixed_constraint" not in base:
        base.append("fixed_fixed_constraint")
        notes.append("fixed_fixed_constraint added to the base: metadata.yaml declares mounting fixed_fixed")
    for e in base:
        if (why := unavailable(e, ds)) is not None:
            raise DiagnoseError(f"config key 'base': effect {e!r} cannot be used on this dataset: {why}")
    runs = ds.run_ids
    try:
        folds = folds_for(runs, cv)
    except ValueError as exc:
        raise DiagnoseError(str(exc)) from None
    # what the models are identified on: every run (leave-one-run-out) or the declared train runs
    fit_runs = runs if len(folds) > 1 else folds[0][0]
    skip = {e: why for e in settings.candidates if e not in base and (why := unavailable(e, ds)) is not None}
    for e, why in skip.items():
        say(f"[diagnose] candidate {e} skipped: {why}")

    say(f"[diagnose] {len(runs)} runs, {len(ds.errors)} readings; base: core{''.join(' + ' + e for e in base)}")
    current = fit_full(base, ds, fit_runs, folds, settings)
    say(f"[diagnose] base identified in {current.fit_s:.1f} s: train RMSE {np.sqrt(current.sse / current.n):.3f} um")
    before_um, table, fold_models = heldout_loro(base, ds, folds, settings)
    noise = estimate_noise_floor(_in_sample_table(current.model, ds, fit_runs), noise_window_s, noise_min_groups)
    floor = noise.noise_floor_um
    if floor < MIN_FLOOR_UM:
        notes.append(f"noise floor estimated at {floor:.2g} um (noise-free data?); {MIN_FLOOR_UM} um used")
        floor = MIN_FLOOR_UM
    say(f"[diagnose] noise floor {floor:.3f} um ({noise.method}); held-out RMSE of the base {before_um:.3f} um")
    pf_mm = lambda m: m.params_["pf_m"] * 1000.0  # noqa: E731
    loc_before = loc.localise(loc.annotate(table, ds, pf_mm(current.model), floor), floor)
    say(f"[diagnose] where: {loc_before['summary']}")

    steps, scans, missing, ambiguous = [], [], [], []
    tables = {"before": table}
    while len(missing) < int(max_effects):
        n_try = sum(1 for c in settings.candidates if c not in current.effects and c not in skip)
        say(f"[diagnose] step {len(steps) + 1}: trying {n_try} candidate(s) on core"
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
            "canonical": best["label"] if best["label"] in EFFECTS else None,
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
        if best["effect"] in OPEN_TERMS:
            same = f" (= {best['label']})" if best["label"] in EFFECTS else ""
            say(f"[diagnose] described by an open term{same}: {best['description']}")
            if best["alike"]:
                say(f"[diagnose] its driver is not told apart: {' or '.join([display(best), *best['alike']])} fit alike")
        say(f"[diagnose] missing effect: {display(best)}: held-out RMSE {before_um:.3f} -> {after_um:.3f} um "
            f"({1 - after_um / before_um:.0%} less)")  # fmt: skip
        missing.append(best["effect"])
        current, before_um, fold_models = best["fitted"], after_um, new_fold_models
        tables[f"step{len(steps)}"] = after_table
        # the floor is a property of the data, best seen through the best model so far
        grown = estimate_noise_floor(_in_sample_table(current.model, ds, fit_runs), noise_window_s, noise_min_groups)
        if MIN_FLOOR_UM <= grown.noise_floor_um < floor:
            noise, floor = grown, grown.noise_floor_um
            say(f"[diagnose] noise floor re-estimated with the grown model: {floor:.3f} um")
    final_table = tables[list(tables)[-1]]
    loc_after = loc.localise(loc.annotate(final_table, ds, pf_mm(current.model), floor), floor)
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
    gap = _gap(before_um, floor, settings.test, loc_after, scans, ds, noise, current.effects)
    return {
        "dataset": str(ds.path) if ds.path is not None else ds.metadata.machine.name,
        "frame": frame_text(ds.metadata),  # the frame of every score (data.reference.frame_text)
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
         noise, in_model: Sequence[str] = ()) -> dict:  # fmt: skip
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
        "feed_trend": where["feed_trend"],
        "load_trend": where["load_trend"],
        "best_candidate": best,
        "more_data": more_data(where, ds, noise) if not test.within_floor(heldout_um, floor_um) else [],
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


def _in_sample_table(model, ds, runs):
    """Readings of ``runs`` with the in-sample residual of ``model`` (for the noise floor)."""
    parts = [rd.assign(residual_um=rd["thermal_um"].to_numpy() - pred)
             for rd, pred in (model.referenced_thermal_um(ds, r) for r in runs)]  # fmt: skip
    return pd.concat(parts, ignore_index=True)


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


def settings_from_config(cfg, say: Callable[[str], None] = print) -> Settings:
    """:class:`Settings` from the composed ``conf/diagnose.yaml``, every key checked."""
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
    starts = {}
    for eid, params in dict(cfg.get("starts") or {}).items():
        searched = sorted(e for e in (*EFFECTS, *OPEN_TERMS) if own_params(e))
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
        candidates=_check_effects(_as_list(cfg.get("candidates")) or list(CANDIDATES), "candidates", open_terms=True),
        say=say,
        refit=_refit(cfg.get("refit", 3)),
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
    # everything the user can get wrong is checked before anything is loaded or fitted
    base = _check_effects(_as_list(conf.get("base")), "base")
    settings = settings_from_config(conf, say)
    max_effects = _number(conf.get("max_effects", 3), "max_effects", int)
    noise = dict(conf.get("noise") or {})
    window_s = _number(noise.get("repeat_window_s", 60.0), "noise.repeat_window_s", lo=0.0)
    min_groups = _number(noise.get("min_groups", 20), "noise.min_groups", int)
    force = conf.get("force", False)
    if not isinstance(force, bool):
        raise DiagnoseError(f"config key 'force': expected true or false, got {force!r}")
    out = check_out_dir(conf["out_dir"], conf["data_dir"], force)
    track = bool(conf.get("track", True))
    exp_id = tracking.connect(conf["tracking"]) if track else None  # an unreachable server fails first
    ds = physics_view(load_dataset(conf["data_dir"]))
    d = run_diagnosis(ds, base=base, max_effects=max_effects, cv=conf.get("cv", "loro"), settings=settings,
                      noise_window_s=window_s, noise_min_groups=min_groups)  # fmt: skip
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
