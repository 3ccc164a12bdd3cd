"""The benchmark job (``thermbench benchmark``): every task run, the choice made, then the report,
MLflow (the parent run and one nested run per cell), the saved and registered models, and the
terminal, whose last lines are the answer.
"""

from __future__ import annotations

import os
import re
import time
from pathlib import Path

import pandas as pd
from omegaconf import DictConfig
from tqdm.auto import tqdm

from .. import __version__, tracking
from ..errors import ExperimentError
from ..experiment import JobResult, _finish, headline_metrics, plain, save_models
from ..report.answer import answer_metrics, answer_table, answer_text
from .choice import (
    _summary_text, _with_case, deployed_choice, flagged, held_out_flags, held_out_summary, held_out_table,
    nested_choice,
)
from .evidence import held_out_limits
from .plan import (
    _cv, _overrides, case_label, interval_settings, output_dirs, output_name, plain_value, reference_only, tasks,
)
from .run import _iterate
from .splits import load_split, outer_folds
from .stack import stack_task


def _blockers(done_tasks: list[dict], baselines) -> dict[tuple[str, str, str], str]:
    """(case, family, approach) -> why the C runtime cannot run that fitted model (never chosen), for
    every task that is not of a family in ``baselines``."""
    from ..export.encoding import export_blocker

    out = {}
    for o in done_tasks:
        if o["family"] in baselines:
            continue
        for a, m in o["models"].items():
            why = export_blocker(m)
            if why:
                out[(case_label(o["dataset"], o.get("channel", "all")), o["family"], a)] = why
    return out


def benchmark(cfg: DictConfig) -> JobResult:
    """Run every task, write ``report.md``, log it all to MLflow, save/register the chosen models.

    Not skipped by config hash like ``train``: a rerun takes every finished task from the
    on-disk cache (``cache_dir``), so it costs seconds and still rewrites the report."""
    import mlflow

    from ..report import DETAILS_NAME, FINDINGS_NAME, terminal_summary, write_report

    from ..outputs import check_library_dir, check_output_dir

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
    # one bar: the cells done of those to do, and tqdm's estimate of the time left
    bar = tqdm(total=len(todo), desc="benchmark cells", unit="cell", disable=None if cfg.get("progress", True) else True)
    try:
        for k, out in enumerate(_iterate(cfg, todo), 1):
            done_tasks.append(out)
            n_models = out["results"][["approach", "train"]].drop_duplicates().shape[0] if not out["results"].empty else 0
            where = out["dataset"] if out.get("channel", "all") == "all" else f"{out['dataset']} {out['channel']}"
            bar.write(f"[{k}/{len(todo)}] {where} x {out['family']}: {n_models} models in {out['seconds']:.1f} s"
                      + (f" ({len(out['errors'])} could not fit)" if out["errors"] else ""))
            bar.update(1)
    except KeyboardInterrupt:  # each finished cell is in the cache already (written whole by its worker)
        cache = cfg.get("cache_dir")
        bar.write(f"benchmark: {len(done_tasks)} of {len(todo)} cells done" + (
            f", kept in {Path(str(cache)).resolve()}: the same command resumes with the {len(todo) - len(done_tasks)} "
            "cells left" if cache else " (cache_dir is null: a re-run starts again)"))  # fmt: skip
        raise
    finally:
        bar.close()
    # the tasks come as they finish; results.csv, the report and the choice take them in the plan's order, so
    # the same configuration writes the same files whatever the workers' timing
    order = {(t["dataset_cfg"]["name"], t["channel"], t["family"]): i for i, t in enumerate(todo)}
    done_tasks.sort(key=lambda o: order[(o["dataset"], o.get("channel", "all"), o["family"])])
    baselines = sorted({t["family"] for t in todo if reference_only(t["family"])})
    blockers = _blockers(done_tasks, baselines)  # never chosen (nor stacked): what the C runtime cannot run
    if cfg.get("stack", True):  # the stack of every candidate family, one more family (bench/stack.py)
        flags = {k[:3] for o in done_tasks if not o["results"].empty for k in flagged(o["results"])}
        stacks = stack_task(done_tasks, set(blockers) | flags)
        blockers |= _blockers(stacks, baselines)
        done_tasks += stacks
    errors = [e for o in done_tasks for e in o["errors"]]
    parts = [o["results"] for o in done_tasks if not o["results"].empty]
    if not parts:
        raise ExperimentError("benchmark: no model could be fitted: " + "; ".join(errors))
    results = pd.concat(parts, ignore_index=True)
    parts = [o["curves"] for o in done_tasks if not o["curves"].empty]
    curves = pd.concat(parts, ignore_index=True) if parts else pd.DataFrame()
    wall_s = time.perf_counter() - t0
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
    case_data, case_folds, case_path = {}, {}, {}  # case (as the results name it) -> its dataset, each loaded once; its folds
    for dcfg, channel in case_cfg.values():
        sp = load_split(dcfg)
        case = case_label(sp.name, channel)
        case_data[case] = sp.dataset
        src = dict(dcfg.get("source") or {})
        if src.get("_target_") == "thermbench.data.io.load_dataset":  # a dataset directory: where thermbench export finds it
            case_path[case] = str(Path(str(src.get("path"))).resolve())
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
        extra[f"{c}__{f}__{a}"] = {"dataset": str(d), **({"dataset_path": case_path[c]} if c in case_path else {}),
                                   **({"channel": str(ch)} if ch != "all" else {}),
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