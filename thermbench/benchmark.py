"""The robustness comparison (the user's main question): how well does each model family
hold up in a loading state it was not trained on?

For each dataset (``conf/dataset``: its loading ``states`` and its ``validation`` runs) and
each family (``conf/model``), one task (:func:`run_task`) fits

* ``single``: one model per loading state, scored on every run — the train-state x
  test-state matrix (seed 001 §5: regression fails across moving states);
* ``global``: one model on all loading states;
* ``bank``: the single-state models behind a condition classifier (seed 002 §2.4,
  :class:`thermbench.models.bank.ConditionBank`), reusing the single fits;
* ``bank_soft``: the same members blended by the classifier's probabilities instead of
  switched by its label;

and scores them on the validation duty cycles (seed 001 Table 2, seed 002 Table 6,
seed 000's random cycle; the measured spindle test's stepped tail), the seeds' headline:
compensation rate and max residual on unseen cycles. A format 2 dataset with several error
channels (``channel: null`` in its option) is benchmarked on each channel: one task per
(dataset, channel, family); the results' ``channel`` column names it (``all`` for a format 1
dataset). Tasks run in parallel (joblib), each cached on disk by its arguments
(joblib.Memory), so an interrupted benchmark resumes where it stopped. Each of the ``n_jobs``
workers runs its fits on its share of the job's cores
(:func:`thermbench.parallel.worker_threads`), so parallel tasks never oversubscribe them.
"""

from __future__ import annotations

import os
import re
import sys
import time
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import joblib
import numpy as np
import pandas as pd
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from sklearn.base import clone
from tqdm.auto import tqdm

from . import __version__, tracking
from .config import group_option
from .adapt import ProbePlan
from .errors import ExperimentError
from .evidence import held_out_limits
from .experiment import JobResult, _finish, build_model, fit_evaluate, headline_metrics, model_flags, plain, save_models
from .parallel import hydra_runtime, run_workers
from .splits import dataset_option, load_source, load_split, outer_folds
from .report.answer import answer_metrics, answer_table, answer_text
from .data.reference import frame_text
from .metrics import evaluate as evaluate_runs
from .models.base import ModelError
from .models.gp import GaussianProcessLag


#: the fold name of the deployed model's choice: the inner folds over every run it is fitted on
DEPLOY_FOLD = "all runs"

#: what a cell (a family on a dataset: an approach, a fold) may fail with on its data: thermbench's own
#: ModelError, and scikit-learn's and numpy's refusals of the numbers they were given (no input left after a
#: selection, a singular matrix, non-finite values). Each is one line and a row of kind ``failed`` in
#: results.csv; the cell is no candidate of that fold and the benchmark goes on.
CELL_FAILURES = (ModelError, ValueError, np.linalg.LinAlgError, FloatingPointError)


def failure_text(exc: BaseException) -> str:
    """One line saying why a cell failed (a library's exception keeps its type name)."""
    text = " ".join(str(exc).split())
    return text if isinstance(exc, ModelError) else f"{type(exc).__name__}: {text}"


def run_task(
    dataset_cfg: Mapping,
    family: str,
    model_cfg: Mapping,
    approaches: Sequence[str],
    classifier_cfg: Mapping | None,
    seed: int,
    dataset_hash: str = "",
    code_version: str = __version__,
    verbose: bool = False,
    channel: str = "all",
    cv: str | None = None,
    cv_folds: int = 5,
    interval: Mapping | None = None,
    probe: Mapping | None = None,
) -> dict[str, Any]:
    """Fit and score one family on one dataset (see module docstring).

    ``dataset_hash`` (the data's content) and ``code_version`` (a hash of thermbench's
    source) are not used here: with the configs they are the key of the on-disk cache,
    so changed data or code is never served from it. ``verbose`` prints a line per fit.
    ``channel``: the error channel (``dataset_cfg`` names it) as the results label it.
    ``cv``: how ``global`` and the banks are scored (:mod:`thermbench.splits`): ``declared`` fits them
    on the loading states and scores them on every run; ``loro`` / ``group_kfold`` (``cv_folds``
    folds) fit them once per fold on its training runs and score them on its held-out runs
    (``kind`` validation, ``fold`` the held-out runs), then once more on every run: the model
    to deploy. Null: :func:`thermbench.splits.resolve_cv`. ``interval``: ``level`` and ``kappa`` of the
    prediction intervals of the global approach (:mod:`thermbench.intervals`), calibrated on each
    outer fold's inner folds: its rows get ``coverage_<level %>`` and ``half_width_um``. ``probe``: how
    approach ``adaptive`` probes each held-out run (:class:`thermbench.adapt.ProbePlan`): rows
    ``adaptive-<every>s``, ``naive_probe-<every>s`` (the peer) and ``adaptive-uncertainty``, scored
    without the probe readings (``probes``, ``probes_per_h``).

    Returns ``results`` (one row per fitted model x test run, the columns of
    :mod:`thermbench.report`), ``curves`` (per-cycle before/after on the validation runs
    for global and bank), ``models`` (fitted global/bank models), ``seconds`` and ``errors``.
    """
    from sklearn.model_selection import cross_val_predict

    from .splits import DatasetRef, Fold, RunsRegressor, inner_folds, run_rows

    t0 = time.perf_counter()
    split = load_split(dataset_cfg)
    ds = split.dataset
    model = build_model(model_cfg, seed=seed)
    rows, curves, models, errors = [], [], {}, []
    failed: list[dict] = []  # one row per cell that could not fit or predict (results.csv, kind "failed")
    cv, folds, outer = outer_folds(split, cv, cv_folds)  # outer: the folds a choice is made for
    inner_rows = []

    def tag(df: pd.DataFrame, approach: str, train: str, fitted=None, fold=None) -> pd.DataFrame:
        df = df.copy()
        df.insert(0, "approach", approach)
        df.insert(0, "family", family)
        df.insert(0, "channel", channel)
        df.insert(0, "dataset", split.name)
        df["train"] = train
        if fold is None:  # the declared split: the validation runs are each a fold of their own
            df["kind"] = [split.kind(r) for r in df["run_id"]]
            df["fold"] = ["+".join(split.validation) if k == "validation" else "" for k in df["kind"]]
        else:  # a fold's held-out runs
            df["kind"] = "validation"
            df["fold"] = fold
        if fitted is not None:  # the sensors it reads (e.g. those seed 002's selection chose)
            df["sensors"] = " ".join(fitted.required_inputs().sensors)
        return df

    where = split.name if channel == "all" else f"{split.name} {channel}"

    def fail(what: str, exc: BaseException, approach: str, fold: str = "", inner_fold: str = "") -> None:
        """A cell that could not fit or predict: one line, one row; never a candidate, the run goes on."""
        why = failure_text(exc)
        errors.append(f"{where}/{family}/{what}: {why}")
        failed.append({"dataset": split.name, "channel": channel, "family": family, "approach": approach, "fold": fold,
                       "inner_fold": inner_fold, "kind": "failed", "failure": why})  # fmt: skip

    def say(what: str, fit_s: float) -> None:
        if verbose:
            print(f"    {where} x {family}: {what} fitted in {fit_s:.1f} s", flush=True)

    singles, single_fit_s = {}, {}
    fold_models: dict[str, Any] = {}  # outer fold name -> its global fit (what the intervals are of)
    interval_cols: dict[tuple[str, str], tuple[float, float]] = {}  # (fold, run) -> (coverage, mean half-width)
    level, kappa = interval_settings(interval)
    plan = ProbePlan.from_config(probe) if "adaptive" in approaches else None
    banks = [a for a in approaches if a in BANKS]
    states = split.states if cv == "declared" else sorted({r for f in folds for r in f.held_out}, key=ds.run_ids.index)
    if "single" in approaches or banks:
        for state in states:
            try:
                fitted, res, _ = fit_evaluate(model, ds, [state])
            except CELL_FAILURES as exc:
                fail(f"single {state}", exc, "single")
                continue
            singles[state] = fitted
            single_fit_s[state] = float(res["fit_s"].iloc[0])
            say(f"single {state}", single_fit_s[state])
            if "single" in approaches:
                rows.append(tag(res, "single", state, fitted))
    if "global" in approaches and len(states) > 1 and cv == "declared":
        try:
            fitted, res, cur = fit_evaluate(model, ds, split.states, curves=True)
            fold_models["+".join(split.validation)] = fitted
            rows.append(tag(res, "global", "all", fitted))
            curves.append(tag(cur[cur["run_id"].isin(split.validation)], "global", "all"))
            models["global"] = fitted
            say("global", float(res["fit_s"].iloc[0]))
        except CELL_FAILURES as exc:
            fail("global", exc, "global", "+".join(split.validation))
    elif "global" in approaches:
        for fold in folds:  # one fit per fold, scored on the runs it holds out
            try:
                fitted, res, cur = fit_evaluate(model, ds, fold.train, fold.held_out, curves=True)
                if "rmse_um" in res and not np.isfinite(res["rmse_um"]).all():
                    raise FloatingPointError(f"non-finite predictions on {', '.join(fold.held_out)}")
                fold_models[fold.name] = fitted
                rows.append(tag(res, "global", "all", fitted, fold=fold.name))
                curves.append(tag(cur, "global", "all", fold=fold.name))
                say(f"global without {fold.name}", float(res["fit_s"].iloc[0]))
            except CELL_FAILURES as exc:
                fail(f"global fold {fold.name}", exc, "global", fold.name)
        try:  # the model to deploy: on every run
            models["global"] = clone(model).fit(ds, states)
        except CELL_FAILURES as exc:
            fail("global (the model to deploy)", exc, "global", "all runs")

    def new_bank(approach: str):
        from .models.bank import ConditionBank

        return ConditionBank(model=clone(model), classifier=instantiate(dict(classifier_cfg), _convert_="all"),
                             blend=BANKS[approach])  # fmt: skip

    for approach in banks if len(singles) > 1 and classifier_cfg is not None and cv != "declared" else []:
        for fold in folds:  # the members of the fold's training runs: none has seen a held-out run
            members = {s: m for s, m in singles.items() if s in fold.train}
            if len(members) < 2:
                errors.append(f"{where}/{family}/{approach} fold {fold.name}: fewer than 2 members to choose among")
                continue
            try:
                bank = new_bank(approach).fit_from_fitted(ds, members)
                res, cur = evaluate_runs(bank, ds, list(fold.held_out), curves=True)
                res.insert(1, "own", False)
                res["fit_s"] = sum(single_fit_s[s] for s in members)
                rows.append(tag(res, approach, "all", bank, fold=fold.name))
                curves.append(tag(cur, approach, "all", fold=fold.name))
            except CELL_FAILURES as exc:
                fail(f"{approach} fold {fold.name}", exc, approach, fold.name)
        try:
            models[approach] = new_bank(approach).fit_from_fitted(ds, singles)
            say(f"{approach} classifier", 0.0)
        except CELL_FAILURES as exc:
            fail(f"{approach} (the model to deploy)", exc, approach, "all runs")
    for approach in banks if len(singles) > 1 and classifier_cfg is not None and cv == "declared" else []:
        bank = new_bank(approach)
        try:
            t1 = time.perf_counter()
            bank.fit_from_fitted(ds, singles)
            fit_s = time.perf_counter() - t1 + sum(single_fit_s.values())
            res, cur = evaluate_runs(bank, ds, None, curves=True)
            res.insert(1, "own", res["run_id"].isin(list(singles)))
            res["fit_s"] = fit_s
            rows.append(tag(res, approach, "all", bank))
            curves.append(tag(cur[cur["run_id"].isin(split.validation)], approach, "all"))
            models[approach] = bank
            say(f"{approach} classifier", time.perf_counter() - t1)
        except CELL_FAILURES as exc:
            fail(approach, exc, approach, "+".join(split.validation))
    ref_only = reference_only_model(model)  # a baseline: inner folds for its intervals and probe peers only
    # the model to deploy is chosen as each outer fold's is, by the inner folds of its training runs: every run
    # (the states for declared); its fold is DEPLOY_FOLD (scored by no held-out run: the outer folds say how
    # well this procedure holds up). An outer fold with the same training runs serves as it is.
    same = [f for f in outer if set(f.train) == set(states)]
    deploy = [] if same or ref_only else [Fold(DEPLOY_FOLD, tuple(states), ())]
    if not ref_only or "global" in approaches:  # a candidate of the nested choice: scored by the inner folds
        ref = DatasetRef(ds)
        for f in outer + deploy:
            inner = inner_folds(f.train)
            if not inner:
                continue
            t1 = time.perf_counter()
            tag_inner = dict(dataset=split.name, channel=channel, family=family, fold=f.name)
            X, y, groups = run_rows(ds, f.train)
            fold_of = {r: g.name for g in inner for r in g.held_out}
            if "global" in approaches:  # scikit-learn drives the inner folds over whole runs (splits.RunsRegressor)
                cv_idx = [(np.flatnonzero(np.isin(groups, g.train)), np.flatnonzero(np.isin(groups, g.held_out)))
                          for g in inner]  # fmt: skip
                try:
                    pred = cross_val_predict(RunsRegressor(model, ref), X, y, groups=groups, cv=cv_idx)
                    if not np.isfinite(pred).all():
                        raise FloatingPointError("non-finite predictions on an inner fold's held-out runs")
                    if f.name in fold_models:  # intervals and probe replays of the fold's global fit
                        cal = calibrate_fold(ds, f, inner, fold_models[f.name], X, y - pred)
                        interval_cols.update(fold_intervals(cal, f.name, level, kappa))
                        for name, df in probe_results(cal, plan, level, kappa) if plan is not None else []:
                            rows.append(tag(df, name, "all", fold_models[f.name], fold=f.name))
                        if plan is not None and isinstance(fold_models[f.name], GaussianProcessLag):
                            for name, df in gp_refit_results(ds, cal, fold_models[f.name], plan):
                                rows.append(tag(df, name, "all", fold_models[f.name], fold=f.name))
                    sq = pd.Series((y - pred) ** 2).groupby(groups, sort=False).mean()
                    if not ref_only:  # never a candidate
                        inner_rows.append(pd.DataFrame({"run_id": sq.index, "rmse_um": np.sqrt(sq.to_numpy())})
                                          .assign(**tag_inner, approach="global", inner_fold=[fold_of[r] for r in sq.index]))  # fmt: skip
                except CELL_FAILURES as exc:
                    fail(f"global fold {f.name}, inner folds", exc, "global", f.name, "(inner folds)")
            for approach in [a for a in approaches if a in BANKS] if classifier_cfg is not None and not ref_only else []:
                for g in inner:  # the bank of the single models of the inner fold's training runs
                    members = {s: m for s, m in singles.items() if s in g.train}
                    if len(members) < 2:
                        continue
                    try:
                        res = evaluate_runs(new_bank(approach).fit_from_fitted(ds, members), ds, list(g.held_out))
                    except CELL_FAILURES as exc:
                        fail(f"{approach} fold {f.name}, inner fold {g.name}", exc, approach, f.name, g.name)
                        continue
                    inner_rows.append(res.assign(**tag_inner, approach=approach, inner_fold=g.name))
            say(f"the {len(inner)} inner folds of {f.name}", time.perf_counter() - t1)
        if same and inner_rows:  # the deployed model's choice: that outer fold's inner scores
            mine = [r[r["fold"] == same[0].name] for r in inner_rows]
            inner_rows += [r.assign(fold=DEPLOY_FOLD) for r in mine if len(r)]
    results = pd.concat(rows, ignore_index=True) if rows else pd.DataFrame()
    if len(results):
        cov = f"coverage_{round(100 * level)}"
        glob = (results["approach"] == "global") & (results["kind"] == "validation")
        got = [interval_cols.get((fo, r)) if g else None for fo, r, g in zip(results["fold"], results["run_id"], glob)]
        results[cov] = [v[0] if v else np.nan for v in got]
        results["half_width_um"] = [v[1] if v else np.nan for v in got]
        if "_coverage" in results:  # the adaptive approaches' own intervals
            has = results["_coverage"].notna()
            results.loc[has, cov] = results.loc[has, "_coverage"]
            results.loc[has, "half_width_um"] = results.loc[has, "_half_width"]
            results = results.drop(columns=["_coverage", "_half_width"])
    return {
        "dataset": split.name,
        "channel": channel,
        "family": family,
        "results": results,
        "curves": pd.concat(curves, ignore_index=True) if curves else pd.DataFrame(),
        "models": models,
        "dataset_hash": ds.content_hash(),
        "frame": frame_text(ds.metadata),  # what every score of this dataset is of (data.reference)
        "cv": cv,
        "inner": pd.concat(inner_rows, ignore_index=True) if inner_rows else pd.DataFrame(),
        "seconds": time.perf_counter() - t0,
        "errors": errors,
        "failed": failed,
    }


def interval_settings(interval: Mapping | None) -> tuple[float, float]:
    """(level, kappa) of config key ``interval``, checked."""
    cfg = dict(interval or {})
    unknown = sorted(set(cfg) - {"level", "kappa"})
    if unknown:
        raise ExperimentError(f"config key(s) {['interval.' + k for k in unknown]}: unknown; known: interval.level, interval.kappa")
    level, kappa = cfg.get("level", 0.9), cfg.get("kappa", 1.0)
    if isinstance(level, bool) or not isinstance(level, (int, float)) or not 0 < level < 1:
        raise ExperimentError(f"config key 'interval.level': expected a number between 0 and 1 (0.9: a 90 % interval), got {level!r}")
    if isinstance(kappa, bool) or not isinstance(kappa, (int, float)) or not (kappa >= 0 and np.isfinite(kappa)):
        raise ExperimentError(f"config key 'interval.kappa': expected a number >= 0, got {kappa!r}")
    return float(level), float(kappa)


def calibrate_fold(ds, fold, inner, fitted, X: pd.DataFrame, inner_residual_um: np.ndarray) -> dict[str, Any]:
    """What one outer fold's intervals and probe replays are made of. ``X``: the inner held-out
    readings as :func:`~thermbench.splits.run_rows` gives them, ``inner_residual_um`` each one's
    residual from a fit without its run; ``fitted``: the fold's fit on all its training runs.
    Returns ``calibration``: per inner held-out run (t_s, residual_um, distance to the envelope
    of its inner fold's training runs), and ``held``: per run the fold holds out (t_s, measured,
    thermal, predicted by ``fitted``, distance to the envelope of the fold's training runs)."""
    from .data.reference import thermal_errors
    from .intervals import Envelope

    inputs = fitted.required_inputs()
    sensors, operating = list(inputs.sensors), list(inputs.operating)
    te = thermal_errors(ds)
    by_run = {r: g for r, g in te.groupby("run_id", sort=False)}
    runs, rows = X["run_id"].to_numpy(), X["row"].to_numpy()
    calibration = []
    for g in inner:
        env = Envelope.fit(ds, g.train, sensors, operating)
        for r in g.held_out:
            idx = np.flatnonzero(runs == r)
            t = by_run[r]["t_s"].to_numpy(dtype=float)[rows[idx]]
            calibration.append((t, np.asarray(inner_residual_um, dtype=float)[idx],
                                env.distance(Envelope.features(ds, r, t, sensors, operating))))  # fmt: skip
    env = Envelope.fit(ds, fold.train, sensors, operating)
    held = {}
    for r in fold.held_out:
        g = by_run[r]
        t = g["t_s"].to_numpy(dtype=float)
        held[r] = (t, g["error_um"].to_numpy(dtype=float), g["thermal_um"].to_numpy(dtype=float),
                   np.asarray(fitted.predict(ds, r), dtype=float), env.distance(Envelope.features(ds, r, t, sensors, operating)))  # fmt: skip
    return {"calibration": calibration, "held": held}


def fold_intervals(cal: Mapping[str, Any], fold_name: str, level: float, kappa: float) -> dict[tuple[str, str], tuple[float, float]]:
    """The conformal interval of one outer fold (:mod:`thermbench.intervals`; ``cal`` from
    :func:`calibrate_fold`): scores of the inner residuals normalised by their distance to their
    inner envelope, applied to the fold's held-out runs. (fold, run) -> (coverage, mean half-width µm)."""
    from .intervals import conformal_quantile, half_widths, interval_scores

    scores = np.concatenate([interval_scores(d, dist, kappa) for _, d, dist in cal["calibration"]])
    q = conformal_quantile(scores, level)
    out = {}
    for r, (_, measured, _, pred, dist) in cal["held"].items():
        hw = half_widths(q, dist, kappa)
        out[(fold_name, r)] = (float(np.mean(np.abs(measured - pred) <= hw)), float(np.mean(hw)))
    return out


def probe_results(cal: Mapping[str, Any], plan, level: float, kappa: float) -> list[tuple[str, pd.DataFrame]]:
    """The probe approaches of one outer fold (:func:`thermbench.adapt.probe_replays`): each held-out
    run replayed with probes, scored on the readings that were not probes (``probes`` counts them).
    The filter's noise: ``plan.noise``, or estimated from the fold's calibration residuals at the
    first schedule's interval. An adaptive approach's interval is conformal too: the calibration
    runs replayed the same way, each residual normalised by the filter's standard deviation (the
    reading's scatter included) and the envelope distance. (approach, metrics rows) pairs."""
    import dataclasses

    from .adapt import estimate_noise, probe_replays, trigger_level
    from .intervals import conformal_quantile

    calib = cal["calibration"]  # (t_s, residual_um, distance) per inner held-out run
    params = plan.noise or estimate_noise([(t, d) for t, d, _ in calib], plan.every_s[0])
    if plan.trigger == "uncertainty" and plan.threshold_um is None:  # the fold's level, found once
        plan = dataclasses.replace(plan, threshold_um=trigger_level(calib, params, plan.every_s[0], kappa))
    scores: dict[str, list[np.ndarray]] = {}
    for t, d, dist in calib:  # the calibration runs as residuals (prediction 0, measured d)
        for name, c, var, probed in probe_replays(t, d, np.zeros_like(d), plan, params, calib, dist, kappa):
            if var is not None:
                s = np.abs(d - c) / (np.sqrt(var + params.r_um2) * (1.0 + kappa * dist))
                scores.setdefault(name, []).append(s[~probed])
    qs = {name: conformal_quantile(np.concatenate(v), level) for name, v in scores.items()}
    out: dict[str, list[dict]] = {}
    for r, (t, measured, thermal, pred, dist) in cal["held"].items():
        for name, c, var, probed in probe_replays(t, measured, pred, plan, params, calib, dist, kappa):
            row = _probe_row(r, t, measured, thermal, c, probed)
            keep = ~probed
            if var is not None:
                hw = qs[name] * np.sqrt(var + params.r_um2) * (1.0 + kappa * dist)
                row["_coverage"] = float(np.mean(np.abs(measured - c)[keep] <= hw[keep]))
                row["_half_width"] = float(np.mean(hw[keep]))
            out.setdefault(name, []).append(row)
    return [(name, pd.DataFrame(v)) for name, v in out.items()]


def _probe_row(run: str, t, measured, thermal, corrected, probed) -> dict:
    """A probe approach's metrics row of one held-out run: scored on the readings that were not probes."""
    from .metrics import residual_metrics

    keep = ~np.asarray(probed, dtype=bool)
    return {"run_id": run, "own": False, **residual_metrics(measured[keep], corrected[keep], thermal[keep]),
            "nonfinite_predictions": 0, "fit_s": 0.0, "probes": int((~keep).sum()),
            "probes_per_h": float((~keep).sum() / max((t[-1] - t[0]) / 3600.0, 1e-9))}  # fmt: skip


def gp_refit_results(ds, cal: Mapping[str, Any], fitted, plan) -> list[tuple[str, pd.DataFrame]]:
    """The GP-refit peer (:func:`thermbench.adapt.gp_refit`) of one outer fold of the ``gp`` family:
    ``gp_refit-<every>s`` per schedule of ``plan``, each held-out run scored on the readings that
    were not probes, as the adaptive approach is."""
    from .adapt import gp_refit, probe_schedule

    out = []
    for every in plan.every_s:
        rows = []
        for r, (t, measured, thermal, _, _) in cal["held"].items():
            er = ds.errors_run(r)
            if not np.array_equal(er["t_s"].to_numpy(dtype=float), t):
                raise ModelError(f"gp_refit: run {r!r}: the readings' order differs from the calibration's")
            sched = probe_schedule(t, every)
            c = gp_refit(fitted, ds, r, t, er["target_mm"].to_numpy(dtype=float), measured, sched)
            rows.append(_probe_row(r, t, measured, thermal, c, sched))
        out.append((f"gp_refit-{every:g}s", pd.DataFrame(rows)))
    return out


#: the bank approaches: name -> how the members are combined (ConditionBank ``blend``)
BANKS = {"bank": "hard", "bank_soft": "soft"}
APPROACHES = ("single", "global", *BANKS, "adaptive")


def probe_approach(approach: str) -> bool:
    """True for an approach scored with probe readings of the run it scores (``adaptive-...``,
    ``naive_probe-...``): never compared with the open-loop approaches for a choice."""
    return str(approach).startswith(PROBE_PREFIXES)


#: the row names of the probe approaches begin so (thermbench.adapt.probe_replays)
PROBE_PREFIXES = ("adaptive-", "naive_probe-", "gp_refit-")


def probe_rows(results: pd.DataFrame) -> pd.Series:
    """Which rows of ``results`` are of a :func:`probe_approach` (a boolean Series)."""
    return results["approach"].astype(str).str.startswith(PROBE_PREFIXES).astype(bool)


def families_by_dataset(cfg, datasets: Sequence[str]) -> dict[str, list[str]]:
    """The families to run per dataset: ``cfg.families`` for every dataset, or when it is null
    each dataset option's own ``benchmark_families`` (the shipped benchmark: the measured
    spindle test gets families the simulated axes do not)."""
    if cfg.get("families") is not None:
        fams = _names(cfg, "families", _options("model"))
        return {d: fams for d in datasets}
    out = {}
    for d in datasets:
        option, dcfg = dataset_option(d, "datasets")
        own = dcfg.get("benchmark_families")
        if own is None and option is not None and option != "path":
            raise ExperimentError(f"config key 'families': null, and conf/dataset/{d}.yaml has no benchmark_families; "
                                  f"give the families, e.g. families=[mlr_seed002]")  # fmt: skip
        if own is None:  # a dataset directory: every family (tasks() skips, in one line each, those it cannot serve)
            own = [f for f in _options("model") if not _is_bank_option(f)]
        out[d] = _names({"benchmark_families": own}, "benchmark_families", _options("model"))
    return out


def _is_bank_option(family: str) -> bool:
    """A model option that is a bank of another family (``bank_mlr_seed002``): the benchmark's
    ``bank`` approaches build banks of every family, so it is not a family of its own there."""
    return str(group_option("model", family).get("_target_", "")).endswith("ConditionBank")


def channels_of(ds, dcfg: Mapping) -> list[str]:
    """The error channels a benchmark scores ``ds`` on: the option's ``channel`` when it names
    one, every channel of a format 2 dataset when it is null, ``all`` for format 1."""
    if ds.metadata.version == 1:
        return ["all"]
    if dcfg.get("channel") is not None:
        return [str(dcfg["channel"])]
    return sorted(ds.metadata.error_channels())


def case_label(dataset: str, channel: str) -> str:
    """How a (dataset, channel) pair is named in model keys, registry names and the report:
    the dataset's name, with ``-<channel>`` for one channel of a format 2 dataset."""
    return str(dataset) if channel == "all" else f"{dataset}-{channel}"


def tasks(cfg: DictConfig, skipped: list[str] | None = None) -> list[dict]:
    """One task per (dataset, channel, family) of ``cfg.datasets`` x their error channels x ``cfg.families``.

    Each dataset is loaded (built on first use) here, once, before any task runs, so
    parallel workers never build the same dataset at the same time; its content hash
    and the code version join the task's cache key. What a dataset cannot serve (a family
    whose needs it lacks, the bank approaches when it has nothing to classify) is said in one
    line each on stderr, and appended to ``skipped``."""
    from .models.bank import condition_inputs

    def skip(line: str) -> None:
        print(f"[benchmark] skipped {line}", file=sys.stderr, flush=True)
        if skipped is not None:
            skipped.append(line)

    interval_settings(plain_value(cfg.get("interval")))  # one line before any worker starts
    approaches = _names(cfg, "approaches", list(APPROACHES))
    if "adaptive" in approaches:
        ProbePlan.from_config(plain_value(cfg.get("probe")))
        if "global" not in approaches:
            raise ExperimentError("config key 'approaches': adaptive replays the global fits with probes; add global")
    if not approaches:
        raise ExperimentError(f"config key 'approaches': empty; choose among {', '.join(APPROACHES)}")
    datasets = _dataset_entries(cfg)
    per_dataset = families_by_dataset(cfg, datasets)
    families = list(dict.fromkeys(f for fams in per_dataset.values() for f in fams))
    # with each dataset's own families (families: null), bank families a dataset does not run are ignored there
    bank_families = _names(cfg, "bank_families", families if cfg.get("families") is not None else _options("model"),
                           required=False)  # fmt: skip
    for key, lo in (("seed", 0), ("n_jobs", -1)):
        v = cfg.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < lo or (key == "n_jobs" and v == 0):
            raise ExperimentError(f"config key '{key}': expected an integer >= {lo}{' other than 0' if key == 'n_jobs' else ''}"
                                  f", got {v!r}")  # fmt: skip
    stray = sorted(set(bank_families) - set(families))
    if stray and cfg.get("families") is not None:
        raise ExperimentError(f"config key 'bank_families': {stray} are not in 'families' {families}")
    classifier = OmegaConf.to_container(cfg.classifier, resolve=True) if cfg.get("classifier") else None
    version = tracking.code_version()
    out = []
    for dname in datasets:
        option, dcfg = dataset_option(dname, "datasets")
        if option is None:  # a dataset directory: the benchmark's own settings of the costly families
            dcfg = {**dcfg, "benchmark_models": plain_value(cfg.get("benchmark_models"))}
        raw = load_source(dcfg)[0]
        for channel in channels_of(raw, dcfg):
            ccfg = dcfg if channel == "all" else {**dcfg, "channel": channel}
            split = load_split(ccfg)
            ccfg = {**ccfg, "name": split.name}  # a dataset directory: named by its machine
            ds, first = split.dataset, channel == channels_of(raw, dcfg)[0]
            data_hash = ds.content_hash()
            if first:  # cv and cv_folds checked here, in one line, before any worker starts
                outer_folds(split, _cv(cfg), cfg.get("cv_folds", 5))
            banked = [a for a in approaches if a in BANKS]
            try:
                if banked:
                    condition_inputs(ds, list(ds.run_ids), require=False)
            except ModelError as exc:  # e.g. runs without conditions and no operating input: nothing to classify
                if first:
                    skip(f"{', '.join(banked)} on {dname}: {exc}")
                banked = []
            for fam in per_dataset[str(dname)]:
                lacks = family_lacks(fam, ds)
                if lacks:  # e.g. the screw physics model on a spindle test: skipped there, and said so
                    if first:
                        skip(f"{fam} on {dname}: {lacks}")
                    continue
                out.append(
                    dict(
                        dataset_cfg=ccfg,
                        family=fam,
                        model_cfg=model_config(fam, dcfg, str(dname) if option else None),
                        approaches=[a for a in approaches if a not in BANKS or (fam in bank_families and a in banked)],
                        classifier_cfg=classifier,
                        seed=int(cfg.seed),
                        dataset_hash=data_hash,
                        code_version=version,
                        verbose=bool(cfg.get("progress", True)),
                        channel=channel,
                        cv=_cv(cfg),
                        cv_folds=cfg.get("cv_folds", 5),
                        interval=plain_value(cfg.get("interval")),
                        probe=plain_value(cfg.get("probe")),
                    )
                )
    return out


def _dataset_entries(cfg) -> list[str]:
    """``cfg.datasets``: dataset options by name or dataset directories (each checked here, one line)."""
    value = cfg.get("datasets")
    if isinstance(value, str) or not OmegaConf.is_list(value) and not isinstance(value, (list, tuple)):
        raise ExperimentError(f"config key 'datasets': expected a list, e.g. datasets=[{value}], got {value!r}")
    if not value:
        raise ExperimentError("config key 'datasets': empty; give dataset options or directories, e.g. datasets=[fl_thermal]")
    entries = [str(v) for v in value]
    for e in entries:
        dataset_option(e, "datasets")
    return entries


def model_config(family: str, dcfg: Mapping, dname: str | None) -> dict:
    """The model option ``family`` with the settings the benchmark gives it on this dataset
    (``benchmark_models.<family>``: in ``conf/dataset/<dname>.yaml`` for a dataset option, e.g.
    fewer epochs or a smaller LSSVM subsample on a 46 h log; the benchmark's own key for a
    dataset directory, ``dname`` None). An unknown family or parameter names the key."""
    import difflib

    where = f"conf/dataset/{dname}.yaml: key 'benchmark_models" if dname else "config key 'benchmark_models"
    base = dict(group_option("model", family))
    extra = dcfg.get("benchmark_models") or {}
    if not isinstance(extra, Mapping):
        raise ExperimentError(f"{where}': expected a mapping family -> settings, got {extra!r}")
    known = _options("model")
    for fam in extra:
        if fam not in known:
            near = difflib.get_close_matches(str(fam), known, n=1)
            raise ExperimentError(f"{where}.{fam}': no model option {fam!r}{f'; did you mean {near[0]!r}?' if near else ''}")
    settings = extra.get(family) or {}
    if not isinstance(settings, Mapping):
        raise ExperimentError(f"{where}.{family}': expected a mapping parameter -> value, got {settings!r}")
    for k, v in dict(settings).items():
        if k not in base:
            raise ExperimentError(f"{where}.{family}.{k}': conf/model/{family}.yaml has no parameter {k!r}; "
                                  f"it has {sorted(base)}")  # fmt: skip
        base[k] = OmegaConf.to_container(v, resolve=True) if OmegaConf.is_config(v) else v
    return base


def plain_value(value):
    """A config node as plain data (a container resolved), anything else as it is."""
    return OmegaConf.to_container(value, resolve=True) if OmegaConf.is_config(value) else value


def family_class(family: str):
    """The model class of option ``family`` (``conf/model/<family>.yaml``); for a bank option,
    the class of the models inside it. None when the option names no ``_target_``. A family
    whose optional dependency is missing raises :class:`~thermbench.extras.MissingExtra`."""
    from hydra._internal.utils import _locate

    from .extras import MissingExtra

    opt = group_option("model", family)
    target = opt.get("_target_")
    if target is None:
        return None
    if str(target).endswith("ConditionBank") and opt.get("model", {}).get("_target_"):
        target = opt["model"]["_target_"]
    try:
        return _locate(str(target))
    except ImportError as exc:  # Hydra wraps the module's own error
        if isinstance(exc.__cause__, MissingExtra):
            raise exc.__cause__ from None
        raise


def family_lacks(family: str, ds) -> str | None:
    """What dataset ``ds`` lacks that model family ``family`` needs (its class's ``needs``,
    :func:`thermbench.models.base.missing_needs`), as text; None when it has everything."""
    from .extras import MissingExtra
    from .models.base import missing_needs, needs_text

    try:
        cls = family_class(family)
    except MissingExtra as exc:  # e.g. gru on the core install: the other families still run
        return str(exc)
    params = dict(group_option("model", family))
    if str(params.get("_target_", "")).endswith("ConditionBank"):  # a bank option: its members' parameters
        params = dict(params.get("model") or {})
    missing = missing_needs(cls, ds, params) if cls is not None else []
    return "needs " + needs_text(cls, missing) if missing else None


def flagged(results: pd.DataFrame) -> dict[tuple[str, str, str, str], list[str]]:
    """(case, family, approach, train) -> what disqualifies that fitted model
    (:func:`thermbench.experiment.model_flags`); models with no flag are left out. The case
    is :func:`case_label` of the dataset and channel."""
    out = {}
    results = _with_case(results)
    by = [c for c in ("case", "family", "approach", "train") if c in results]
    for key, g in results.groupby(by, sort=False):
        flags = model_flags(g)
        if flags:
            out[tuple(str(k) for k in key) + ("",) * (4 - len(by))] = flags
    return out


def _with_case(results: pd.DataFrame) -> pd.DataFrame:
    """``results`` with a ``case`` column: :func:`case_label` of each row's dataset and channel."""
    channel = results["channel"] if "channel" in results else pd.Series("all", index=results.index)
    return results.assign(case=[case_label(d, c) for d, c in zip(results["dataset"], channel)])


def reference_only_model(model) -> bool:
    """True for a baseline model (``reference_only`` on its class, or on a bank's members)."""
    inner = getattr(model, "model", None)
    return bool(getattr(model, "reference_only", False) or getattr(inner, "reference_only", False))


def reference_only(family: str) -> bool:
    """True for a baseline family (``reference_only`` on its class): in the tables for
    comparison, never chosen for deployment."""
    from .extras import MissingExtra

    try:
        return bool(getattr(family_class(family), "reference_only", False))
    except MissingExtra:  # not installed, so not in the results: not a baseline either
        return False


def _options(group: str) -> list[str]:
    from .config import config_dir

    return sorted(p.stem for p in (config_dir() / group).glob("*.yaml"))


def _names(cfg, key: str, known: Sequence[str], required: bool = True) -> list[str]:
    """``cfg[key]`` as a list of names, each one of ``known`` (a mistake names the key, with a did-you-mean)."""
    import difflib

    value = cfg.get(key)
    if value is None and not required:
        return []
    if isinstance(value, str) or not OmegaConf.is_list(value) and not isinstance(value, (list, tuple)):
        raise ExperimentError(f"config key '{key}': expected a list, e.g. {key}=[{value}], got {value!r}")
    names = [str(v) for v in value]
    for n in names:
        if n not in known:
            close = difflib.get_close_matches(n, known, n=1)
            hint = f"did you mean {close[0]!r}? " if close else ""
            raise ExperimentError(f"config key '{key}': unknown {n!r}; {hint}known: {', '.join(known)}")
    return names


def choose(results: pd.DataFrame, exclude: Sequence[str] = (), blocked: Iterable[tuple[str, str, str]] = ()) -> pd.DataFrame:
    """Per dataset and channel, the (family, approach) to deploy: the best worst-case
    compensation rate on the validation runs (ties: the smaller max residual). Single-state
    models are not candidates: which state would you train on? Nor is a family in ``exclude``
    (the baselines), a (case, family, approach) in ``blocked`` (one the C runtime cannot run:
    the chosen model is the one to deploy), a model with a non-finite score on any run, or one that makes the error
    worse than no compensation on its own training runs (:func:`flagged`). Note that the
    choice is made on the same validation runs the headline reports, so the chosen model's
    figures are not an independent estimate (the report says so). Columns: ``dataset``,
    ``channel``, ``case`` (:func:`case_label`), ``family``, ``approach``, ``worst_rate``,
    ``max_residual_um``."""
    results = _with_case(results)
    bad = {k[:3] for k in flagged(results)} | set(blocked)
    keep = [(d, f, a) not in bad and f not in exclude
            for d, f, a in zip(results["case"], results["family"], results["approach"])]  # fmt: skip
    results = results[keep]
    v = results[(results["kind"] == "validation") & (results["approach"] != "single")
                & ~probe_rows(results)]  # fmt: skip
    cols = ["dataset", "channel", "case", "family", "approach"]
    if v.empty:
        return pd.DataFrame(columns=cols)
    agg = v.assign(channel=v["channel"] if "channel" in v else "all").groupby(cols).agg(
        worst_rate=("compensation_rate", "min"), max_residual_um=("max_abs_residual_um", "max")
    )
    agg = agg.reset_index().sort_values(["case", "worst_rate", "max_residual_um"], ascending=[True, False, True])
    return agg.groupby("case").head(1).reset_index(drop=True)


def model_complexity(family: str, approach: str) -> int:
    """How flexible a (family, approach) is, for :func:`nested_choice`: the family's
    :attr:`~thermbench.models.base.ThermalErrorModel.complexity` (0 the stacked ensemble and the ridge
    baseline made deployable, ``ridge_history``; 1 linear, 2 a physical model with a
    few nonlinear parameters, 3 a kernel machine or network; 3 when unknown), one more for a bank (a
    model per condition and a classifier)."""
    from .extras import MissingExtra

    try:
        base = int(getattr(family_class(family), "complexity", 3))
    except (MissingExtra, ExperimentError, KeyError):
        base = 3
    return base + (1 if str(approach).startswith("bank") else 0)


def nested_choice(inner: pd.DataFrame, blocked: Iterable[tuple[str, str, str]] = ()) -> pd.DataFrame:
    """Per dataset, channel and outer fold, the (family, approach) thermbench would deploy, chosen
    without seeing the fold's held-out runs, on the RMSE of each inner held-out run
    (:func:`thermbench.splits.inner_folds`, on the fold's training runs only).

    The rule resists its own noise (issue 54): with a few runs, the lowest of ten noisy inner scores
    is often a flexible family that fitted those runs. So the candidate of lowest mean inner RMSE
    (ties: the smaller worst) sets a bar, its mean plus the standard error of that mean over the inner
    held-out runs; of the candidates at or under the bar, the simplest (:func:`model_complexity`) is
    chosen, and of equally simple ones the lowest mean. This is the one-standard-error rule of Hastie,
    Tibshirani and Friedman (*The Elements of Statistical Learning*, §7.10) applied across families:
    a more flexible candidate is chosen only when it is better by more than the scatter of the score
    that ranks it.

    Candidates: the non-baseline families (only they have inner scores) with a score on every inner
    held-out run of the fold and none non-finite, and not in ``blocked`` (the C runtime cannot run
    it). Columns: ``dataset``, ``channel``, ``case``, ``fold``, ``family``, ``approach``,
    ``inner_median_rmse_um``, ``inner_mean_rmse_um``, ``inner_se_um`` (the chosen one's), ``bar_um``
    (the bar), ``best_family``, ``best_approach`` (the lowest mean's)."""
    cols = ["dataset", "channel", "case", "fold", "family", "approach", "inner_median_rmse_um", "inner_mean_rmse_um",
            "inner_se_um", "bar_um", "best_family", "best_approach"]  # fmt: skip
    if inner.empty:
        return pd.DataFrame(columns=cols)
    inner = _with_case(inner)
    blocked = set(blocked)
    keys = ["dataset", "channel", "case", "fold"]
    out = []
    for key, g in inner.groupby(keys, sort=False):
        need = g[["inner_fold", "run_id"]].drop_duplicates().shape[0]  # every inner held-out run of the fold
        cands = []
        for (fam, app), c in g.groupby(["family", "approach"], sort=False):
            r = c["rmse_um"].to_numpy(dtype=float)
            if (key[2], fam, app) in blocked or len(r) < need or not np.isfinite(r).all():
                continue
            se = float(np.std(r, ddof=1) / np.sqrt(r.size)) if r.size > 1 else 0.0
            cands.append({"family": fam, "approach": app, "inner_median_rmse_um": float(np.median(r)),
                          "inner_mean_rmse_um": float(r.mean()), "inner_se_um": se, "worst": float(r.max()),
                          "complexity": model_complexity(fam, app)})  # fmt: skip
        if not cands:
            continue
        best = min(cands, key=lambda c: (c["inner_mean_rmse_um"], c["worst"]))
        bar = best["inner_mean_rmse_um"] + best["inner_se_um"]
        pick = min((c for c in cands if c["inner_mean_rmse_um"] <= bar),
                   key=lambda c: (c["complexity"], c["inner_mean_rmse_um"], c["worst"]))  # fmt: skip
        out.append(dict(zip(keys, key)) | {k: pick[k] for k in cols if k in pick}
                   | {"bar_um": bar, "best_family": best["family"], "best_approach": best["approach"]})  # fmt: skip
    return pd.DataFrame(out, columns=cols)


def deployed_choice(nested: pd.DataFrame, results: pd.DataFrame, baselines: Sequence[str],
                    blocked: Iterable[tuple[str, str, str]] = ()) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The model to deploy per dataset and channel, and the nested choice without it. One rule makes
    both: :func:`nested_choice`, here on the inner folds over every run the deployed model is fitted on
    (fold :data:`DEPLOY_FOLD`); so the held-out figures of the nested choice are the figures of the
    procedure that picked what is exported. Only a case with no inner folds (fewer than two training
    runs: nothing to cross-validate on) falls back to :func:`choose`, and its ``rule`` says so.
    Returns (``chosen``: ``dataset``, ``channel``, ``case``, ``family``, ``approach``, ``rule``, ``best_family``,
    ``best_approach`` (the lowest mean inner RMSE; None for the fallback);
    ``nested`` without the deploy rows)."""
    deploy = nested["fold"] == DEPLOY_FOLD
    cols = ["dataset", "channel", "case", "family", "approach"]
    chosen = nested.loc[deploy, cols + [c for c in ("best_family", "best_approach") if c in nested]].assign(rule="nested")
    r = _with_case(results)
    missing = sorted(set(r["case"]) - set(chosen["case"]))
    if missing:
        fb = choose(r[r["case"].isin(missing)], exclude=baselines, blocked=blocked)
        chosen = pd.concat([chosen, fb[cols].assign(rule="the best worst-case rate on the validation runs (fewer "
                                                          "than two training runs: no inner folds)")])  # fmt: skip
    for c in ("best_family", "best_approach"):  # the lowest mean inner RMSE (the pick unless a simpler one was as good)
        chosen[c] = chosen[c] if c in chosen else None
    return chosen.reset_index(drop=True), nested[~deploy].reset_index(drop=True)


def _held_out_per_fold(results: pd.DataFrame) -> tuple[pd.DataFrame, bool]:
    """The held-out scores per (case, family, approach, fold): the mean over the fold's held-out runs of
    ``rmse_um`` and ``rms_error_um``, and with intervals (a ``coverage_<level>`` column) of ``coverage`` and
    ``half_width_um``; and whether there are intervals. The rows :func:`held_out_summary` and
    :func:`held_out_table` are made of (validation rows, not ``single``, not the probe approaches)."""
    r = _with_case(results)
    v = r[(r["kind"] == "validation") & (r["approach"] != "single") & ~probe_rows(r)]
    cov = next((c for c in v.columns if str(c).startswith("coverage_")), None)  # the interval's level, e.g. coverage_90
    extra = {"coverage": (cov, "mean"), "half_width_um": ("half_width_um", "mean")} if cov and "half_width_um" in v else {}
    per_fold = v.groupby(["case", "family", "approach", "fold"], sort=False).agg(
        rmse_um=("rmse_um", "mean"), rms_error_um=("rms_error_um", "mean"), **extra).reset_index()  # fmt: skip
    return per_fold, bool(extra)


def held_out_summary(results: pd.DataFrame, choice: pd.DataFrame, baselines: Sequence[str]) -> pd.DataFrame:
    """Per dataset and channel, over the folds: thermbench's nested choice (the held-out RMSE of the
    model chosen in each fold), the best baseline (the baseline family and approach of smallest
    median held-out RMSE over the folds) and no compensation; median and worst over the folds, and
    on how many folds the choice beat the best baseline and beat no compensation (a fold's RMSE:
    the root of the mean square over its held-out runs' readings, approximated by the mean of the
    runs' RMSE when a fold holds out several runs); with intervals (a ``coverage_<level>`` column),
    the choice's coverage and half-width, means over its folds of each fold's mean over its runs
    (``chosen_coverage``, ``chosen_half_width_um``; NaN where the chosen approach has no interval)."""
    per_fold, interval = _held_out_per_fold(results)
    out = []
    for case, g in per_fold.groupby("case", sort=False):
        ch = choice[choice["case"] == case]
        chosen = g.merge(ch[["fold", "family", "approach"]], on=["fold", "family", "approach"])
        base = g[g["family"].isin(list(baselines))]
        row = {"case": case, "folds": int(g["fold"].nunique())}
        none = g.groupby("fold")["rms_error_um"].first()
        row |= {"none_median_rmse_um": float(none.median()), "none_worst_rmse_um": float(none.max())}
        if not chosen.empty:
            c = chosen.set_index("fold")["rmse_um"]
            row |= {"chosen_median_rmse_um": float(c.median()), "chosen_worst_rmse_um": float(c.max()),
                    "chosen": "; ".join(f"{f}: {a} {b}" for f, a, b in chosen[["fold", "family", "approach"]].itertuples(index=False)),
                    "beat_no_compensation": f"{int((c < none.reindex(c.index)).sum())}/{len(c)}"}  # fmt: skip
            if interval:  # the choice's interval over its held-out runs: the mean of each fold's coverage and half-width
                row |= {"chosen_coverage": float(chosen["coverage"].mean()),
                        "chosen_half_width_um": float(chosen["half_width_um"].mean())}  # fmt: skip
        if not base.empty:
            med = base.groupby(["family", "approach"])["rmse_um"].median().sort_values()
            fam, app = med.index[0]
            b = base[(base["family"] == fam) & (base["approach"] == app)].set_index("fold")["rmse_um"]
            row |= {"best_baseline": f"{fam} ({app})", "baseline_median_rmse_um": float(b.median()),
                    "baseline_worst_rmse_um": float(b.max())}  # fmt: skip
            if not chosen.empty:
                common = c.index.intersection(b.index)
                row["beat_best_baseline"] = f"{int((c[common] < b[common]).sum())}/{len(common)}"
        out.append(row)
    return pd.DataFrame(out)


def held_out_table(results: pd.DataFrame, choice: pd.DataFrame, baselines: Sequence[str]) -> pd.DataFrame:
    """The report's held-out table: per case (dataset and channel), a row for thermbench's nested
    choice, one per family and approach (not ``single``) and one for no compensation; columns the
    folds scored, the median and worst held-out RMSE over them (a fold's RMSE as in
    :func:`held_out_summary`), and on how many folds it beat no compensation and the best
    baseline (the best baseline's own row: '-'); with intervals, ``coverage`` and ``half_width_um``:
    the means over the folds of each fold's mean over its held-out runs (NaN for an approach without
    an interval and for no compensation)."""
    per_fold, interval = _held_out_per_fold(results)
    if per_fold.empty:
        return pd.DataFrame()
    out = []
    for case, g in per_fold.groupby("case", sort=False):
        none = g.groupby("fold", sort=False)["rms_error_um"].first()
        base = g[g["family"].isin(list(baselines))]
        best = None
        if not base.empty:
            fam, app = base.groupby(["family", "approach"])["rmse_um"].median().sort_values().index[0]
            best = (fam, app, base[(base["family"] == fam) & (base["approach"] == app)].set_index("fold")["rmse_um"])
        ch = choice[choice["case"] == case] if not choice.empty else choice
        chosen = g.merge(ch[["fold", "family", "approach"]], on=["fold", "family", "approach"]) if len(ch) else g.iloc[:0]

        def row(label: str, scores: pd.Series, is_best: bool = False, cells: pd.DataFrame | None = None) -> dict:
            common = scores.index.intersection(best[2].index) if best is not None else []
            means = {k: float(cells[k].mean()) if cells is not None else np.nan
                     for k in ("coverage", "half_width_um")} if interval else {}  # fmt: skip
            return {"case": case, "model": label, "folds": len(scores), "median_rmse_um": float(scores.median()),
                    "worst_rmse_um": float(scores.max()),
                    "beat_no_compensation": f"{int((scores < none.reindex(scores.index)).sum())}/{len(scores)}",
                    "beat_best_baseline": "-" if best is None or is_best else
                    f"{int((scores[common] < best[2][common]).sum())}/{len(common)}"} | means  # fmt: skip

        if not chosen.empty:
            out.append(row("thermbench's choice (nested)", chosen.set_index("fold")["rmse_um"], cells=chosen))
        for (fam, app), m in g.groupby(["family", "approach"], sort=False):
            label = f"{fam} ({app})" + (" (baseline)" if fam in baselines else "")
            is_best = best is not None and (fam, app) == best[:2]
            out.append(row(label + (", the best baseline" if is_best else ""), m.set_index("fold")["rmse_um"], is_best, m))
        out.append({**row("no compensation", none), "beat_no_compensation": "-"})
    return pd.DataFrame(out)


def held_out_flags(results: pd.DataFrame, baselines: Sequence[str]) -> list[str]:
    """What the held-out scores say against a family, never hidden: per dataset, channel, family
    and approach (not ``single``), the held-out runs where it made the error worse than no
    compensation (its RMSE above the run's ``rms_error_um``), and a median held-out RMSE over the
    folds above the best baseline's (:func:`held_out_summary`'s best baseline). One line each."""
    r = _with_case(results)
    v = r[(r["kind"] == "validation") & (r["approach"] != "single") & ~probe_rows(r)]
    if v.empty or "rms_error_um" not in v:
        return []
    per_fold = v.groupby(["case", "family", "approach", "fold"], sort=False)["rmse_um"].mean()
    lines = []
    for case, g in v.groupby("case", sort=False):
        med = per_fold.loc[case].groupby(level=["family", "approach"], sort=False).median()
        base = med[[f in baselines for f, _ in med.index]].sort_values()
        best = (base.index[0], float(base.iloc[0])) if len(base) else None
        for (fam, app), c in g.groupby(["family", "approach"], sort=False):
            worse = c.loc[c["rmse_um"] > c["rms_error_um"], "run_id"].tolist()
            if worse:
                lines.append(f"{case}/{fam}/{app}: worse than no compensation on held-out run(s) {worse}")
            if best is not None and fam not in baselines and float(med[(fam, app)]) > best[1]:
                lines.append(f"{case}/{fam}/{app}: median held-out RMSE {float(med[(fam, app)]):.2f} µm, worse than the "
                             f"best baseline {best[0][0]} ({best[0][1]}) {best[1]:.2f} µm")  # fmt: skip
    return lines


def _summary_text(row: Mapping, deployed: str | None = None) -> str:
    """One line of :func:`held_out_summary`, led by the model deployed (``deployed``) when given."""

    def pair(prefix: str) -> str:
        med, worst = row.get(f"{prefix}_median_rmse_um"), row.get(f"{prefix}_worst_rmse_um")
        return "-" if med is None or pd.isna(med) else f"{med:.2f} / {worst:.2f}"

    parts = [f"deployed {deployed}"] if deployed else []
    parts += [f"{row['folds']} fold{'s' if row['folds'] != 1 else ''}", f"choice {pair('chosen')}"]
    if isinstance(row.get("best_baseline"), str):
        parts.append(f"best baseline {row['best_baseline']} {pair('baseline')}")
    parts.append(f"no compensation {pair('none')}")
    if isinstance(row.get("beat_best_baseline"), str):
        parts.append(f"choice beat the best baseline on {row['beat_best_baseline']} folds")
    if isinstance(row.get("beat_no_compensation"), str):
        parts.append(f"no compensation on {row['beat_no_compensation']}")
    return "; ".join(parts)


def _cv(cfg) -> str | None:
    """The config's ``cv`` (null: :func:`thermbench.splits.resolve_cv` decides per dataset)."""
    return None if cfg.get("cv") is None else str(cfg.get("cv"))


def _iterate(cfg: DictConfig, todo: list[dict]) -> Iterable[dict]:
    cache = cfg.get("cache_dir")
    fn = joblib.Memory(str(cache), verbose=0).cache(run_task, ignore=["verbose"]) if cache else run_task
    # each worker on its share of the job's cores (parallel.worker_threads); results as they finish
    return run_workers(fn, [((), t) for t in todo], int(cfg.get("n_jobs", 1)), ordered=False)


def _overrides() -> list[str]:
    hc = hydra_runtime()
    return list(hc.overrides.task) if hc is not None else []


#: the keys that do not change what a benchmark computes (left out of its name)
_NOT_SETTINGS = (*tracking.NON_RESULT_KEYS, "name", "force")


def output_name(cfg: DictConfig | Mapping) -> str:
    """The name of a benchmark's output set: ``cfg.name`` when given, else ``benchmark`` for
    the settings of ``conf/benchmark.yaml`` as shipped and ``benchmark-<hash>`` of the settings
    for any other (so a benchmark with other settings never replaces the demo's outputs)."""
    from .config import ConfigError, load_config

    if cfg.get("name"):
        name = str(cfg.get("name"))
        if not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]{0,63}", name):
            raise ConfigError(f"config key 'name': {name!r} is not a usable directory name "
                              "(letters, digits, '_', '.', '-'; at most 64)")  # fmt: skip
        return name

    def settings(c) -> str:
        return tracking.config_hash({k: v for k, v in plain(c).items() if k not in _NOT_SETTINGS})

    mine = settings(cfg)
    return "benchmark" if mine == settings(load_config("benchmark")) else f"benchmark-{mine[:8]}"


def output_dirs(cfg: DictConfig | Mapping) -> tuple[Path, Path]:
    """The report and model directories of a benchmark: ``report_dir`` / ``export_dir`` when
    set, else ``reports/<name>`` and ``models/<name>`` (:func:`output_name`)."""
    name = None if cfg.get("report_dir") and cfg.get("export_dir") else output_name(cfg)
    report = Path(str(cfg.get("report_dir") or f"reports/{name}"))
    models = Path(str(cfg.get("export_dir") or f"models/{name}"))
    return report, models


def benchmark(cfg: DictConfig) -> JobResult:
    """Run every task, write ``report.md``, log it all to MLflow, save/register the chosen models.

    Not skipped by config hash like ``train``: a rerun takes every finished task from the
    on-disk cache (``cache_dir``), so it costs seconds and still rewrites the report."""
    import mlflow

    from .report import DETAILS_NAME, FINDINGS_NAME, terminal_summary, write_report

    from .outputs import check_library_dir, check_output_dir

    report_dir, model_dir = output_dirs(cfg)
    force = bool(cfg.get("force", False))
    r, m = Path(os.path.realpath(report_dir)), Path(os.path.realpath(model_dir))
    if r == m or r.is_relative_to(m) or m.is_relative_to(r):
        raise ExperimentError(f"config keys 'report_dir' and 'export_dir': {report_dir} and {model_dir} must be separate directories")
    for d, kind in ((report_dir, "report"), (model_dir, "models")):  # refused now, not after the fits
        check_output_dir(d, kind, force=force, force_option="force=true")
    if cfg.get("cache_dir"):  # joblib.Memory writes joblib/ (and a .gitignore) there
        check_library_dir(Path(str(cfg.cache_dir)), {"joblib", ".gitignore"}, "cache_dir")
    name = output_name(cfg)
    alias = "champion" if name == "benchmark" else re.sub(r"[^A-Za-z0-9_-]", "_", name)
    exp_id = tracking.connect(cfg.tracking)
    conf = plain(cfg)
    skipped: list[str] = []
    todo = tasks(cfg, skipped)
    if not todo:
        raise ExperimentError("config keys 'datasets' and 'families': nothing to run")
    data_hashes = sorted({f"{case_label(t['dataset_cfg'].get('name'), t['channel'])}={t['dataset_hash']}" for t in todo})
    case_cfg = {case_label(t["dataset_cfg"].get("name"), t["channel"]): (t["dataset_cfg"], t["channel"]) for t in todo}
    h = tracking.config_hash(conf | {"dataset_content": data_hashes})
    t0 = time.perf_counter()
    done_tasks = []
    bar = tqdm(total=len(todo), desc="benchmark", unit="task", disable=None if cfg.get("progress", True) else True)
    for k, out in enumerate(_iterate(cfg, todo), 1):
        done_tasks.append(out)
        n_models = out["results"][["approach", "train"]].drop_duplicates().shape[0] if not out["results"].empty else 0
        where = out["dataset"] if out.get("channel", "all") == "all" else f"{out['dataset']} {out['channel']}"
        bar.write(f"[{k}/{len(todo)}] {where} x {out['family']}: {n_models} models in {out['seconds']:.1f} s"
                  + (f" ({len(out['errors'])} could not fit)" if out["errors"] else ""))
        bar.update(1)
    bar.close()
    errors = [e for o in done_tasks for e in o["errors"]]
    parts = [o["results"] for o in done_tasks if not o["results"].empty]
    if not parts:
        raise ExperimentError("benchmark: no model could be fitted: " + "; ".join(errors))
    results = pd.concat(parts, ignore_index=True)
    parts = [o["curves"] for o in done_tasks if not o["curves"].empty]
    curves = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
    wall_s = time.perf_counter() - t0
    baselines = sorted({t["family"] for t in todo if reference_only(t["family"])})
    from .export.encoding import export_blocker

    blockers = {}  # (case, family, approach) -> why the C runtime cannot run it: never chosen
    for o in done_tasks:
        if o["family"] in baselines:
            continue
        for a, m in o["models"].items():
            why = export_blocker(m)
            if why:
                blockers[(case_label(o["dataset"], o.get("channel", "all")), o["family"], a)] = why
    parts = [o["inner"] for o in done_tasks if not o.get("inner", pd.DataFrame()).empty]
    # never a candidate: one the C runtime cannot run, one worse than no compensation on its own training runs
    never = set(blockers) | {k[:3] for k in flagged(results)}
    nested = nested_choice(pd.concat(parts, ignore_index=True) if parts else pd.DataFrame(), blocked=never)
    chosen, nested = deployed_choice(nested, results, baselines, blockers)
    deployed = {r.case: f"{r.family} ({r.approach})" + (
        f", the simplest within one standard error of {r.best_family} ({r.best_approach})"
        if isinstance(r.best_family, str) and (r.best_family, r.best_approach) != (r.family, r.approach) else "")
        for r in chosen.itertuples()}  # fmt: skip
    key = _with_case(results)
    mark = set(zip(nested["case"], nested["fold"], nested["family"], nested["approach"]))
    results["chosen"] = [(c, fo, f, a) in mark and k == "validation" for c, fo, f, a, k in
                         zip(key["case"], results["fold"], results["family"], results["approach"], results["kind"])]  # fmt: skip
    summary = held_out_summary(results, nested, baselines)
    answer = answer_table(summary, chosen)  # the first screen: the report's, the terminal's last lines, MLflow's
    level = interval_settings(plain_value(cfg.get("interval")))[0]
    case_data, case_folds = {}, {}  # case (as the results name it) -> its dataset, each loaded once; its folds
    for dcfg, channel in case_cfg.values():
        sp = load_split(dcfg)
        case = case_label(sp.name, channel)
        case_data[case] = sp.dataset
        case_folds[case] = (sp.dataset, outer_folds(sp, _cv(cfg), cfg.get("cv_folds", 5))[2])
    limits = held_out_limits(summary, case_folds, nested)  # the target and, when missed, the evidence why
    flags = flagged(results)
    meta = {
        "command": "thermbench benchmark " + " ".join(_overrides()),
        "datasets": ", ".join(map(str, cfg.datasets)),
        "families": "; ".join(f"{d}: {', '.join(dict.fromkeys(t['family'] for t in todo if t['dataset_cfg']['name'] == d))}"
                              for d in dict.fromkeys(t["dataset_cfg"]["name"] for t in todo)),  # fmt: skip
        "approaches": ", ".join(map(str, cfg.approaches)),
        "thermbench version": __version__,
        "git commit": tracking.git_commit(),
        "dataset hashes": ", ".join(data_hashes),
        "wall time": f"{wall_s:.0f} s",
        "chosen models": "; ".join(f"{r.case}: {r.family} ({r.approach})" for r in chosen.itertuples())
        + " (deployed; chosen by " + ("the inner cross-validation over every run: the simplest within one standard error of the "
                                      "lowest mean inner RMSE, the rule the held-out figures score"
                                      if (chosen["rule"] == "nested").all() else "; ".join(sorted(set(chosen["rule"]))))
        + (f"; baselines {', '.join(baselines)} are for comparison, never chosen)" if baselines else ")"),
    }
    if skipped:
        meta["skipped"] = "; ".join(skipped)
    frames = sorted({f"{o['dataset']}: {o['frame']}" for o in done_tasks if o.get("frame")})
    if frames:
        meta["scored on"] = "; ".join(frames)
    for row in summary.to_dict("records"):  # the nested choice against the best baseline and no compensation
        meta[f"held out, {row['case']}"] = _summary_text(row, deployed.get(row["case"]))
    models = {f"{case_label(o['dataset'], o.get('channel', 'all'))}__{o['family']}__{a}": m
              for o in done_tasks for a, m in o["models"].items()}  # fmt: skip
    for r in chosen.itertuples():  # what the deployed model is made of (an ensemble: its members' weights)
        m = models.get(f"{r.case}__{r.family}__{r.approach}")
        line = m.fit_summary() if m is not None else None
        if line:
            meta[f"deployed model, {r.case}"] = f"{r.family} ({r.approach}): {line}"
    held_flags = held_out_flags(results, baselines)
    if held_flags:
        meta["flagged on held-out runs"] = held_flags
    if errors:
        meta["could not fit (never a candidate there)"] = errors
    flag_lines = [f"{d}/{f}/{a} ({t}): {'; '.join(why)}" for (d, f, a, t), why in flags.items()]
    if flag_lines:
        meta["flagged (never chosen)"] = flag_lines
    if blockers:
        meta["not exportable to the C runtime (never chosen)"] = [f"{c}/{f}/{a}: {why}" for (c, f, a), why in blockers.items()]
    unchosen = sorted(set(_with_case(results)["case"]) - set(chosen["case"]))
    if unchosen:
        meta["no model chosen"] = ", ".join(unchosen) + " (every candidate is flagged)"
    report = write_report(results, curves, report_dir, meta=meta, force=force, reference=baselines,
                          n_jobs=int(cfg.n_jobs), held_out=held_out_table(results, nested, baselines), limits=limits,
                          failed=pd.DataFrame([f for o in done_tasks for f in o.get("failed", [])]),
                          answer=answer, level=level)  # with results.csv
    chosen_keys = [f"{r.case}__{r.family}__{r.approach}" for r in chosen.itertuples()]
    extra = {}
    cased = _with_case(results)
    for (c, d, ch, f, a), g in cased.groupby(["case", "dataset", "channel", "family", "approach"], sort=False):
        cell = headline_metrics(g, list(g.loc[g["kind"] == "validation", "run_id"].unique()))
        extra[f"{c}__{f}__{a}"] = {"dataset": str(d), **({"channel": str(ch)} if ch != "all" else {}),
                                   "metrics": {k: float(v) for k, v in cell.items()}}  # fmt: skip
    logged = {}
    inputs = {c: tracking.dataset_input(ds, c) for c, ds in case_data.items()}  # MLflow's dataset inputs, named by case
    with mlflow.start_run(experiment_id=exp_id, run_name="benchmark") as run:
        for v in extra.values():
            v["mlflow_run_id"] = run.info.run_id  # the run that holds these models (thermbench export reads it)
        save_models(models, model_dir, chosen=chosen_keys, extra=extra, force=force)
        mlflow.set_tags(tracking.standard_tags(";".join(data_hashes), h, "benchmark"))
        tracking.log_config(conf)
        # every dataset it fitted on (MLflow asks for the three lists, of one length)
        mlflow.log_inputs(list(inputs.values()), contexts=["training"] * len(inputs), tags_list=[None] * len(inputs))
        metrics = {}
        for (c, d, ch, f, a), g in cased.groupby(["case", "dataset", "channel", "family", "approach"], sort=False):
            cell = extra[f"{c}__{f}__{a}"]["metrics"]
            for k in ("validation_worst_compensation_rate", "validation_max_abs_residual_um"):
                if k in cell:
                    metrics[f"{c}/{f}/{a}/{k}"] = cell[k]
            # one nested run per (dataset, channel, family, approach): the MLflow UI lists and compares them
            with mlflow.start_run(experiment_id=exp_id, run_name=f"{f} | {a} | {c}", nested=True):
                mlflow.set_tags({"dataset": d, "channel": ch, "model": f, "approach": a,
                                 "thermbench.job": "benchmark-cell"})  # fmt: skip
                mlflow.log_params({"dataset": d, "channel": ch, "family": f, "approach": a,
                                   "n_models": int(g["train"].nunique())})  # fmt: skip
                mlflow.log_input(inputs[c], context="training")
                mlflow.log_metrics(cell)
                mlflow.log_text(g.to_csv(index=False), "results.csv")
        mlflow.log_metrics(metrics | answer_metrics(answer, level) | {"wall_s": wall_s})
        mlflow.log_artifacts(str(report_dir), "report")
        mlflow.log_artifacts(str(model_dir), "models")  # every fitted global/bank model + manifest.yaml
        mlflow.log_text(results.to_csv(index=False), "results.csv")
        for r in chosen.itertuples():
            key = f"{r.case}__{r.family}__{r.approach}"
            logged[r.case] = tracking.log_model(models[key], case_data[r.case], name=key.replace("__", "-"))
    registered = {}
    if cfg.tracking.get("register", True):  # after the run has finished: no version of an unfinished run
        for d, info in logged.items():
            name = f"thermbench-{d}"
            version = tracking.register(info.model_uri, name)
            tracking.set_alias(name, alias, version)  # 'champion' only for the shipped settings
            registered[d] = f"models:/{name}@{alias}"
    # the terminal: the details first, then the files and runs, and last the answer (the report's first screen)
    print(terminal_summary(results, reference=baselines))
    if not summary.empty:
        print("\nthe model deployed, and held-out RMSE over the folds, median / worst (µm): thermbench's choice made "
              "without the held-out run (nested, the rule that picked the deployed model), the best baseline, no "
              "compensation")
        for row in summary.to_dict("records"):
            print(f"  {row['case']}: {_summary_text(row, deployed.get(row['case']))}")
    for row in limits.to_dict("records"):
        print(f"  {row['case']}: {row['verdict']}")
    findings = report.parent / FINDINGS_NAME
    for what, lines in (("flagged on held-out runs", held_flags), ("flagged (never chosen)", flag_lines)):
        if lines:  # often dozens of models: counted here, listed in findings.md
            print(f"{what}: {len(lines)} models, listed in {findings.resolve()}")
    for line in errors:
        print(f"could not fit (never a candidate there): {line}")
    for d in unchosen:
        print(f"no model chosen for {d}: every candidate is flagged")
    print(f"\nreport: {report.resolve()} (details: {(report.parent / DETAILS_NAME).resolve()})\n"
          f"models: {model_dir.resolve()} (manifest.yaml marks the chosen ones)\nmlflow run: {run.info.run_id}")
    for d, uri in registered.items():
        print(f"registered: {uri}")
    if len(answer):
        print("\n" + answer_text(answer, level))
    table = chosen.rename(columns={"worst_rate": "validation_worst_compensation_rate"})
    return _finish(JobResult("benchmark", table, metrics, mlflow_run_id=run.info.run_id,
                             outputs={"report": str(report), "models": str(model_dir), **registered}))
