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
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from .._atomic import atomic_dir
from ..data.io import Dataset, load_dataset
from ..sim.effects import EFFECTS
from . import localise as loc
from .noise import estimate_noise_floor
from .search import (
    CANDIDATES,
    Settings,
    SignificanceTest,
    decide,
    explained,
    fit_full,
    folds_for,
    heldout_loro,
    score_candidates,
    unavailable,
)


class DiagnoseError(ValueError):
    """A user mistake in the diagnose command or its config; the message names the key."""


def _check_effects(names: Sequence[str], key: str) -> list[str]:
    out = [str(n).strip() for n in names if str(n).strip()]
    bad = [n for n in out if n not in EFFECTS]
    if bad:
        raise DiagnoseError(f"config key {key!r}: unknown effect(s) {bad}; the canonical effects are {sorted(EFFECTS)}")
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
) -> dict:
    """The discrepancy workflow on a dataset; returns the diagnosis (see module docstring)."""
    settings = settings or Settings()
    say = settings.say
    t_start = time.perf_counter()
    base = _check_effects(base, "base")
    _check_effects(settings.candidates, "candidates")
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
    skip = {e: why for e in settings.candidates if e not in base and (why := unavailable(e, ds)) is not None}
    for e, why in skip.items():
        say(f"[diagnose] candidate {e} skipped: {why}")

    say(f"[diagnose] {len(runs)} runs, {len(ds.errors)} readings; base: core{''.join(' + ' + e for e in base)}")
    current = fit_full(base, ds, runs, folds, settings)
    say(f"[diagnose] base identified in {current.fit_s:.1f} s: train RMSE {np.sqrt(current.sse / current.n):.3f} um")
    before_um, table = heldout_loro(base, ds, runs, folds, settings, current.model)
    noise = estimate_noise_floor(_in_sample_table(current.model, ds, runs), noise_window_s, noise_min_groups)
    floor = noise.noise_floor_um
    say(f"[diagnose] noise floor {floor:.3f} um ({noise.method}); held-out RMSE of the base {before_um:.3f} um")
    pf_mm = lambda m: m.params_["pf_m"] * 1000.0  # noqa: E731
    loc_before = loc.localise(loc.annotate(table, ds, pf_mm(current.model), floor), floor)
    say(f"[diagnose] where: {loc_before['summary']}")

    steps, scans, missing, ambiguous = [], [], [], []
    tables = {"before": table}
    while len(missing) < int(max_effects):
        say(f"[diagnose] step {len(steps) + 1}: trying {len(settings.candidates) - len(current.effects)} candidate(s) "
            f"on core{''.join(' + ' + e for e in current.effects)}")  # fmt: skip
        cands = score_candidates(current, ds, runs, folds, settings, floor, skip)
        best, ties = decide(cands, floor, settings.test)
        scans.append({"effects": list(current.effects), "heldout_fast_um": current.heldout_fast_um,
                      "candidates": [_public(c) for c in cands], "named": best["effect"] if best else None,
                      "ambiguous_with": ties})  # fmt: skip
        if best is None:
            say("[diagnose] no candidate passes the test: nothing (more) is missing that these data can show")
            break
        new = [*current.effects, best["effect"]]
        after_um, after_table = heldout_loro(new, ds, runs, folds, settings, best["fitted"].model)
        step = {
            "effect": best["effect"],
            "ambiguous_with": ties,
            "heldout_rmse_before_um": before_um,
            "heldout_rmse_after_um": after_um,
            "explained_um": explained(before_um, after_um),
            "bic_gain": best["bic_gain"],
            "identified": best["fitted"].identified,
        }
        ok = step["explained_um"] >= settings.test.explained_x_floor * floor
        step["confirmed"] = bool(ok)
        steps.append(step)
        if ties:
            ambiguous.append([best["effect"], *ties])
            say(f"[diagnose] ambiguous: {' or '.join([best['effect'], *ties])} explain the data alike; not guessing")
            break
        if not ok:
            say(f"[diagnose] {best['effect']} not confirmed by leave-one-run-out "
                f"({before_um:.3f} -> {after_um:.3f} um); stopping")  # fmt: skip
            break
        say(f"[diagnose] missing effect: {best['effect']}: held-out RMSE {before_um:.3f} -> {after_um:.3f} um "
            f"({1 - after_um / before_um:.0%} less)")  # fmt: skip
        missing.append(best["effect"])
        current, before_um = best["fitted"], after_um
        tables[f"step{len(steps)}"] = after_table
        # the floor is a property of the data, best seen through the best model so far
        noise = estimate_noise_floor(_in_sample_table(current.model, ds, runs), noise_window_s, noise_min_groups)
        if noise.noise_floor_um < floor:
            floor = noise.noise_floor_um
            say(f"[diagnose] noise floor re-estimated with the grown model: {floor:.3f} um")
    final_table = tables[list(tables)[-1]]
    loc_after = loc.localise(loc.annotate(final_table, ds, pf_mm(current.model), floor), floor)
    first = steps[0]["heldout_rmse_before_um"] if steps else before_um
    return {
        "dataset": str(ds.path) if ds.path is not None else ds.metadata.machine.name,
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
            "heldout_rmse_base_um": first,
            "identified": current.identified,
        },
        "cv": {"kind": "loro" if cv in (None, "loro") else "split", "folds": [{"train": a, "test": b} for a, b in folds]},
        "test": {"description": settings.test.describe(), **vars(settings.test)},
        "notes": notes,
        "verdict": "ambiguous" if ambiguous else "found" if missing else "none",
        "runtime_s": time.perf_counter() - t_start,
        "_tables": tables,
    }


def _in_sample_table(model, ds, runs):
    """Readings of ``runs`` with the in-sample residual of ``model`` (for the noise floor)."""
    import pandas as pd

    parts = [rd.assign(residual_um=rd["thermal_um"].to_numpy() - pred)
             for rd, pred in (model.referenced_thermal_um(ds, r) for r in runs)]  # fmt: skip
    return pd.concat(parts, ignore_index=True)


def _public(c: dict) -> dict:
    return {k: v for k, v in c.items() if k != "fitted"}


# ------------------------------------------------------------------ the job ---
def settings_from_config(cfg, say: Callable[[str], None] = print) -> Settings:
    test = dict(cfg.get("test") or {})
    try:
        t = SignificanceTest(**{k: float(v) for k, v in test.items()})
    except TypeError as exc:
        raise DiagnoseError(f"config key 'test': {exc}; known: explained_x_floor, bic_min, tie_x_floor") from None
    return Settings(
        physics=dict(cfg.get("physics") or {}),
        starts={str(k): list(v) for k, v in dict(cfg.get("starts") or {}).items()},
        test=t,
        candidates=list(cfg.get("candidates") or CANDIDATES),
        say=say,
    )


def _as_list(v) -> list[str]:
    if v is None:
        return []
    if isinstance(v, str):
        return [s for s in v.split(",") if s.strip()]
    return [str(x) for x in v]


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
    _check_effects(_as_list(conf.get("base")), "base")  # before anything is opened or loaded
    track = bool(conf.get("track", True))
    exp_id = tracking.connect(conf["tracking"]) if track else None  # an unreachable server fails first
    ds = load_dataset(conf["data_dir"])
    noise = dict(conf.get("noise") or {})
    d = run_diagnosis(
        ds,
        base=_as_list(conf.get("base")),
        max_effects=int(conf.get("max_effects", 3)),
        cv=conf.get("cv", "loro"),
        settings=settings_from_config(conf, say),
        noise_window_s=float(noise.get("repeat_window_s", 60.0)),
        noise_min_groups=int(noise.get("min_groups", 20)),
    )
    tables = d.pop("_tables")
    out = Path(conf["out_dir"])
    with atomic_dir(out) as tmp:
        (tmp / "diagnosis.json").write_text(json.dumps(d, indent=2, default=_json_default), encoding="utf-8")
        figures = write_figures(d, tables, tmp, settings_from_config(conf).test.explained_x_floor)
        write_markdown(d, figures, tmp)
        import pandas as pd

        pd.concat([t.assign(model=k) for k, t in tables.items()], ignore_index=True).to_csv(tmp / "heldout_residuals.csv", index=False)
    if track:
        import mlflow

        with mlflow.start_run(experiment_id=exp_id, run_name=f"diagnose | {ds.metadata.machine.name}") as run:
            mlflow.set_tags(tracking.standard_tags(ds.content_hash(), tracking.config_hash(conf), "diagnose")
                            | {"missing_effects": ",".join(d["missing_effects"]) or "none", "verdict": d["verdict"]})  # fmt: skip
            tracking.log_config(conf)
            mlflow.log_metrics({"noise_floor_um": d["noise_floor_um"], "heldout_rmse_base_um": d["final"]["heldout_rmse_base_um"],
                                "heldout_rmse_final_um": d["final"]["heldout_rmse_um"], "n_missing": len(d["missing_effects"]),
                                "runtime_s": d["runtime_s"]})  # fmt: skip
            mlflow.log_artifacts(str(out), artifact_path="diagnosis")
        d["mlflow_run_id"] = run.info.run_id
    say(terminal_verdict(d, out))
    return d


def _json_default(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.bool_):
        return bool(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o)}")
