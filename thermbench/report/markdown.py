"""The robustness report's files (:func:`write_report`): ``report.md`` (the answer and its held-out
evidence, the run), ``details.md`` (the tables and figures behind it, per dataset), ``findings.md``
(the run's lists of findings), ``figures/`` and ``results.csv``, written as one output.
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping, Sequence

import pandas as pd

import thermbench

from ..outputs import output_dir
from .details import FIGURES_DIR, _channels_section, _dataset_section, _probe_section, details_opening
from .figures import _Drawing, _slug
from ..bench.results import RMSE, _check_curves, _check_results
from .tables import _channels, _reference_set, _unique, results_table
from .text import _percent, markdown_table


CSV_NAME = "results.csv"


REPORT_NAME = "report.md"


#: the report's linked files: everything behind its tables, and the run's lists of findings
DETAILS_NAME = "details.md"


FINDINGS_NAME = "findings.md"


META_CELL_CHARS = 100


def _meta_md(meta: Mapping | None, lists_file: str | None = None) -> str:
    """The run's metadata (``meta``: name -> value) as a table of short values. A longer value is a
    bullet below the table (``- **name**: value``), so one long entry does not widen every row. A list of
    findings is one bullet each: below the table, or with ``lists_file`` (a file name, see
    :func:`_lists_md`) in that file, and its row links there."""
    if not meta:
        return "_No run metadata was given._"
    rows, long, lists = [], [], []
    for k, v in meta.items():
        if isinstance(v, Mapping):
            v = ", ".join(f"{a}={b}" for a, b in v.items())
        if isinstance(v, (list, tuple)):
            lists.append((str(k), v))
            v = f"{len(v)}, in [{lists_file}]({lists_file})" if lists_file else f"{len(v)}, listed below"
        elif len(str(v)) > META_CELL_CHARS:
            long.append(f"- **{k}**: " + (f"`{v}`" if k == "command" else str(v)))
            continue
        rows.append({"": str(k), "value": f"`{v}`" if k == "command" else str(v)})
    parts = [markdown_table(pd.DataFrame(rows), index=False)] if rows else []
    if long:
        parts += ["", *long]
    if not lists_file:
        for k, items in lists:
            parts += ["", f"**{k}**", "", *(f"- {x}" for x in items)]
    return "\n".join(parts)


def _lists_md(meta: Mapping | None) -> str | None:
    """The list-valued entries of the run's metadata (findings such as the flagged models), a section
    each with one bullet per finding; None when there are none."""
    lists = [(str(k), v) for k, v in (meta or {}).items() if isinstance(v, (list, tuple))]
    if not lists:
        return None
    md = ["# Findings of the run", "", f"Back to [the report]({REPORT_NAME}).", ""]
    for k, items in lists:
        md += [f"## {k} ({len(items)})", "", *(f"- {x}" for x in items), ""]
    return "\n".join(md).rstrip() + "\n"


def figure_paths(out_dir) -> list[Path]:
    """The PNGs of the report in ``out_dir`` (``out_dir/figures/*.png``, sorted),
    e.g. to log them as MLflow artifacts."""
    return sorted((Path(out_dir) / FIGURES_DIR).glob("*.png"))


HELD_OUT_MD = (
    "## Held out: every score on runs the model never saw\n\n"
    "Per dataset and channel, over the folds of the cross-validation (`cv`): the held-out RMSE (µm) of each family "
    "and approach fitted without the fold's runs, and of *thermbench's choice*, the family and approach picked in "
    "each fold by an inner cross-validation on that fold's training runs only (nested: the choice never sees the "
    "runs it is scored on; `chosen` in results.csv). *Beat*: on how many folds its RMSE was below no compensation's "
    "(the RMS of the error itself) and below the best baseline's (the baseline of smallest median). *Interval "
    "covers* / *±*: the share of held-out readings inside the model's prediction interval and its mean half-width "
    "(one model on every training run, `global`: the approaches with an interval)."
)


HELD_OUT_COLUMNS = {"model": "model", "folds": "folds", "median_rmse_um": "median RMSE µm",
                    "worst_rmse_um": "worst RMSE µm", "beat_no_compensation": "beat no compensation",
                    "beat_best_baseline": "beat the best baseline", "coverage": "interval covers",
                    "half_width_um": "± µm"}  # fmt: skip


LIMITS_MD = (
    "### What limits the held-out error\n\n"
    "Per dataset and channel: thermbench's choice against the best baseline (the ratio of their median held-out RMSE, "
    "below 1 the choice is better), and the evidence the data hold (thermbench/bench/evidence.py): the share of a fold's "
    "held-out readings with some input (a temperature rise, an operating signal) outside the range of its training "
    "runs, and the input furthest out; the error's short-term scatter (second differences at each measuring "
    "position, an upper estimate of the measurement noise); the choice's inner cross-validation RMSE (training runs "
    "held out from each other) against its held-out RMSE."
)


LIMITS_COLUMNS = {"choice_median_um": "choice median µm", "baseline_median_um": "best baseline µm", "ratio": "ratio",
                  "outside_range_median": "held-out readings outside the training range (median fold)",
                  "outside_range_worst": "(worst fold)", "worst_fold": "worst fold", "furthest_input": "input furthest out",
                  "excursion": "by (its unit)", "scatter_um": "error scatter µm",
                  "inner_cv_median_um": "choice's inner CV median µm"}  # fmt: skip


def folds_md(results: pd.DataFrame) -> list[str]:
    """The runs of each fold that holds out several (``fold 3 of 5`` in the tables), listed once per dataset
    and channel; none when every fold holds out one run (named by it)."""
    if not {"fold", "kind", "run_id"} <= set(results.columns):
        return []
    val = results[(results["kind"] == "validation") & results["fold"].fillna("").astype(str).str.startswith("fold ")]
    if val.empty:
        return []
    md = ["## Folds", "", "The runs each fold holds out (it trains on the others).", ""]
    keys = ["dataset", *(["channel"] if "channel" in val and (val["channel"] != "all").any() else [])]
    for case, g in val.groupby(keys, sort=False):
        case = " ".join(map(str, case)) if isinstance(case, tuple) else str(case)
        md += [f"- **{case}**: " + "; ".join(f"{fold}: {', '.join(dict.fromkeys(h['run_id'].astype(str)))}"
                                           for fold, h in g.groupby("fold", sort=False))]  # fmt: skip
    return md + [""]


def write_report(results: pd.DataFrame, curves: pd.DataFrame | None, out_dir, meta: Mapping | None = None,
                 force: bool = False, reference: Sequence[str] = (), n_jobs: int = 1,
                 held_out: pd.DataFrame | None = None, limits: pd.DataFrame | None = None,
                 failed: pd.DataFrame | None = None, answer: pd.DataFrame | None = None, level: float = 0.9) -> Path:
    """Write ``out_dir/report.md`` (the answer), ``out_dir/details.md`` (everything behind it), their
    figures ``out_dir/figures/*.png``, ``out_dir/results.csv`` (:func:`results_table`) and, when ``meta``
    holds lists of findings, ``out_dir/findings.md``; return the path of report.md.

    ``reference``: the baseline families (compared, never chosen): marked in the tables
    and figures, ``reference`` true in results.csv. ``n_jobs``: processes that draw the
    figures (:class:`_Drawing`). ``answer``: the benchmark's answer
    (:func:`thermbench.report.answer.answer_table`), report.md's first screen: its table, its figure
    (``figures/summary.png``) and what the columns mean (``level``: the intervals' level).
    ``held_out``: the benchmark's held-out table (:func:`thermbench.bench.choice.held_out_table`), one
    table per case; ``limits``: per case the choice against the best baseline and what limits it
    (:func:`thermbench.bench.evidence.held_out_limits`). ``failed``: the cells that could not fit or predict
    (dataset, channel, family, approach, fold, inner_fold, failure), appended to results.csv as rows of
    kind ``failed`` with their one-line reason in ``failure``.

    report.md: the answer, the held-out tables, what limits the held-out error, then the run
    (``meta``, :func:`_meta_md`: short values in a table, longer ones as bullets, lists of findings in
    findings.md, linked) and the links to details.md and results.csv. details.md: how to read, the
    terminal summary, the headline tables (:func:`.tables.headline`, one per dataset), then per dataset: single
    vs global vs bank on the validation runs (:func:`.tables.approach_comparison`, table + heatmap), the
    train × test heatmap per family (:func:`.tables.train_test_matrix` of the compensation rate, max residual
    annotated) and the before/after compensation curves of the validation runs (``curves``; None or an
    empty frame means no curves, the report says so), then the probe readings.

    A dataset scored on several error channels is laid out by channel instead: its
    headline is the validation RMSE per channel (:func:`.tables.validation_by_channel`; rows =
    family × approach, best per channel in bold, then per channel the best thermbench
    family vs the best baseline, :func:`.tables.best_by_channel`); its section has the bar chart
    of that RMSE (a panel per channel, baselines hatched grey), the validation
    compensation rate per channel, one train × test RMSE heatmap per family (a panel per
    channel; rows = training state, then global / bank / bank_soft; columns = the states,
    then the validation runs) and the before/after curves of the best thermbench model
    per channel that has curves (with the best baseline). It needs ``rmse_um``.

    Written as one output of kind ``report`` (:func:`thermbench.outputs.output_dir`): the
    figures, results.csv and report.md are rendered into a staging directory and replace
    the previous report's files only when all are done, so any failure leaves the previous
    report untouched; a directory holding anything else is refused (``force``: written
    beside it). List the PNGs with :func:`figure_paths`.
    """
    r = _check_results(results)
    ref = _reference_set(reference) & set(r["family"])
    no_curves = curves is None or (isinstance(curves, pd.DataFrame) and curves.empty)
    c = None if no_curves else _check_curves(curves)
    datasets = _unique(r["dataset"])
    multi = [ds for ds in datasets if len(_channels(r, ds)) > 1]
    if multi and RMSE not in r.columns:
        raise ValueError(f"results has no column {RMSE!r}, needed for dataset(s) {multi} scored on several channels")
    table = results_table(r, ref)
    if failed is not None and len(failed):
        table = pd.concat([table, failed.assign(reference=failed["family"].isin(ref))], ignore_index=True)
    out_dir = Path(out_dir)
    used: set[str] = set()

    def fig_name(*parts: str) -> str:
        base = "__".join(_slug(p) for p in parts)
        name, k = f"{base}.png", 1
        while name in used:
            k += 1
            name = f"{base}-{k}.png"
        used.add(name)
        return name

    md: list[str] = ["# Thermal-error robustness report", ""]  # report.md: the answer and the held-out evidence
    answer_fig = None
    if answer is not None and len(answer):
        from .answer import answer_figure, answer_markdown

        answer_fig = fig_name("summary")
        md += answer_markdown(answer, level, f"{FIGURES_DIR}/{answer_fig}")
    if held_out is not None and not held_out.empty:
        md += [HELD_OUT_MD, ""]
        for case, g in held_out.groupby("case", sort=False):
            md += [f"### {case}", "", markdown_table(g.drop(columns="case"), index=False, headers=HELD_OUT_COLUMNS,
                                                           formats={"coverage": _percent}), ""]
    if limits is not None and not limits.empty:
        md += [LIMITS_MD, ""]
        md += [f"- **{r['case']}**: {r['verdict']}" for r in limits.to_dict("records")] + [""]
        md += [markdown_table(limits.drop(columns="verdict"), index=False, headers=LIMITS_COLUMNS,
                                 formats={"ratio": lambda v: f"{v:.2f}×"}), ""]
    md += folds_md(r)
    findings = _lists_md(meta)
    md += ["## The run", "", _meta_md(meta, FINDINGS_NAME if findings else None), ""]
    md += [f"Everything behind these tables is in [{DETAILS_NAME}]({DETAILS_NAME}): how to read it, the terminal summary, "
           "the headline tables on unseen cycles and, per dataset, the comparison of approaches, the train × test "
           f"matrices and the before / after curves. The scores, one row per (fitted model, test run), are in "
           f"[{CSV_NAME}]({CSV_NAME}).", ""]  # fmt: skip
    details = details_opening(r, datasets, multi, ref, REPORT_NAME)

    with output_dir(out_dir, "report", force=force) as stage:
        fig_dir = stage / FIGURES_DIR
        fig_dir.mkdir()
        draw = _Drawing()
        if answer_fig:
            draw(answer_figure, answer, fig_dir / answer_fig)
        table.to_csv(stage / CSV_NAME, index=False, lineterminator="\n")
        for ds in datasets:
            details += (_channels_section(r, c, ds, ref, fig_dir, fig_name, draw) if ds in multi
                        else _dataset_section(r, c, ds, ref, fig_dir, fig_name, draw))
        details += _probe_section(r, fig_dir, fig_name, draw, ref)
        draw.run(n_jobs)
        for name, lines in ((REPORT_NAME, md), (DETAILS_NAME, details)):
            (stage / name).write_text("\n".join(lines).rstrip() + "\n", encoding="utf-8")
        if findings:
            (stage / FINDINGS_NAME).write_text(findings, encoding="utf-8")
    return out_dir / REPORT_NAME


__getattr__ = thermbench.moved_names(__name__)  # details.md's sections moved to report/details.py
