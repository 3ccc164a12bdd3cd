"""One benchmark task (:func:`run_task`): a family fitted and scored on one dataset and channel, every
approach, every outer fold and its inner folds; and the tasks run in parallel (:func:`_iterate`).
"""

from __future__ import annotations

import os
import time
from typing import Any, Iterable, Mapping, Sequence

import joblib
import numpy as np
import pandas as pd
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from sklearn.base import clone

from .. import __version__
from ..data.reference import frame_text
from ..experiment import build_model, fit_evaluate
from .metrics import evaluate as evaluate_runs
from ..errors import ExperimentError
from ..models.base import ModelError
from ..models.gp import GaussianProcessLag
from .adapt import ProbePlan
from .calibration import calibrate_fold, fold_intervals, gp_refit_results, probe_results
from .deployed import DEPLOYED_APPROACH, deployed_rows
from .parallel import run_workers
from .plan import BANKS, CELL_FAILURES, DEPLOY_FOLD, interval_settings, reference_only_model
from .splits import load_split, outer_folds


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
    ``cv``: how ``global`` and the banks are scored (:mod:`thermbench.bench.splits`): ``declared`` fits them
    on the loading states and scores them on every run; ``loro`` / ``group_kfold`` (``cv_folds``
    folds) fit them once per fold on its training runs and score them on its held-out runs
    (``kind`` validation, ``fold`` the held-out runs), then once more on every run: the model
    to deploy. Null: :func:`thermbench.bench.splits.resolve_cv`. ``interval``: ``level`` and ``kappa`` of the
    prediction intervals of the global approach (:mod:`thermbench.bench.intervals`), calibrated on each
    outer fold's inner folds: its rows get ``coverage_<level %>`` and ``half_width_um``. ``probe``: how
    approach ``adaptive`` probes each held-out run (:class:`thermbench.bench.adapt.ProbePlan`): rows
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
    # each fit's predictions per reading, for the stack of every family (bench/stack.py): on the outer folds'
    # held-out runs, and on each outer fold's inner held-out runs (out of run)
    stack_outer, stack_inner = [], []
    candidate = not reference_only_model(model)

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
            try:  # scored on every run for the train x test matrix; a bank's member only on its own run
                fitted, res, _ = fit_evaluate(model, ds, [state], None if "single" in approaches else [state])
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
            if candidate:
                stack_outer.append(held_out_predictions(fitted, ds, split.validation, "+".join(split.validation)))
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
                if candidate:
                    stack_outer.append(held_out_predictions(fitted, ds, fold.held_out, fold.name))
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
        from ..models.bank import ConditionBank

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
    if "global" in approaches and not ref_only:  # each fold's fit as the compensator runs it (bench/deployed.py)
        by_name = {f.name: f for f in folds}
        for name, fitted in fold_models.items():
            train, held = (split.states, split.validation) if cv == "declared" else (by_name[name].train,
                                                                                      by_name[name].held_out)  # fmt: skip
            try:
                res = deployed_rows(fitted, ds, train, held)
            except CELL_FAILURES as exc:
                fail(f"{DEPLOYED_APPROACH} fold {name}", exc, DEPLOYED_APPROACH, name)
                continue
            res.insert(1, "own", False)
            res["fit_s"] = 0.0
            rows.append(tag(res, DEPLOYED_APPROACH, "all", fitted, fold=None if cv == "declared" else name))
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
                        stack_inner.append(pd.DataFrame({"fold": f.name, "inner_fold": [fold_of[r] for r in groups],
                                                         "run_id": groups, "row": X["row"].to_numpy(), "y": y, "pred": pred}))  # fmt: skip
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
            stack_inner += [r.assign(fold=DEPLOY_FOLD) for r in stack_inner if len(r) and r["fold"].iloc[0] == same[0].name]
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
        "stack_inner": pd.concat(stack_inner, ignore_index=True) if stack_inner else pd.DataFrame(),
        "stack_outer": pd.concat(stack_outer, ignore_index=True) if stack_outer else pd.DataFrame(),
        "seconds": time.perf_counter() - t0,
        "errors": errors,
        "failed": failed,
    }


def held_out_predictions(fitted, ds, runs, fold: str) -> pd.DataFrame:
    """A fit's predictions at every reading of ``runs`` (the rows of :func:`~thermbench.bench.splits.run_rows`):
    ``fold``, ``run_id``, ``row``, ``y`` (the measured error), ``pred``."""
    from .splits import run_rows

    X, y, groups = run_rows(ds, list(runs))
    pred = np.empty(len(X))
    rows = X["row"].to_numpy()
    for run, idx in X.groupby("run_id", sort=False).indices.items():
        pred[idx] = np.asarray(fitted.predict(ds, run), dtype=float)[rows[idx]]
    return pd.DataFrame({"fold": fold, "run_id": groups, "row": rows, "y": y, "pred": pred})


def executor_of(cfg: DictConfig):
    """The job's executor (``executor``: conf/executor, :mod:`thermbench.bench.parallel`); none set: local."""
    from .parallel import LocalExecutor

    ex = cfg.get("executor")
    if ex is None:
        return LocalExecutor()
    if not OmegaConf.is_dict(ex) or "_target_" not in ex:
        raise ExperimentError(f"config key 'executor': expected an option of conf/executor (local, dask, slurm), got {ex!r}")
    return instantiate(ex, _convert_="all")


def absolute_paths(task: Mapping) -> dict:
    """``task`` with its dataset's paths absolute (a dataset directory, the benchmark datasets' root), as
    workers elsewhere with another working directory find them (on a filesystem they share)."""
    from .datasets import default_root

    dcfg = dict(task["dataset_cfg"])
    src = dict(dcfg.get("source") or {})
    if src.get("_target_") == "thermbench.data.io.load_dataset" and src.get("path") is not None:
        src["path"] = os.path.abspath(str(src["path"]))
    elif src.get("_target_") == "thermbench.bench.datasets.load_benchmark":
        src["root"] = os.path.abspath(str(src.get("root") or default_root()))
    return {**task, "dataset_cfg": {**dcfg, "source": src}}


def _iterate(cfg: DictConfig, todo: list[dict]) -> Iterable[dict]:
    """Every task's output as it finishes, on the job's executor (local joblib workers or a Dask cluster)."""
    executor = executor_of(cfg)
    cache = cfg.get("cache_dir")
    fn = joblib.Memory(os.path.abspath(str(cache)), verbose=0).cache(run_task, ignore=["verbose"]) if cache else run_task
    calls = [((), absolute_paths(t)) for t in todo]  # one cache key wherever the cell runs
    # each worker on its share of the job's cores (parallel.worker_threads); results as they finish
    with executor.session(int(cfg.get("n_jobs", 1))) as (n_jobs, threads):
        yield from run_workers(fn, calls, n_jobs, ordered=False, threads=threads)
