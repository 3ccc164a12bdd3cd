"""The benchmark's answer in one screen: per dataset and error channel, the model to deploy, its error
on runs it never saw, the best baseline's, no compensation's, and how often its prediction interval
held.

One frame (:func:`answer_table`, plain pandas) is rendered four ways, so the report, the terminal and
MLflow say the same thing: the first table of ``report.md`` (:func:`answer_markdown`), the
benchmark's last lines on the terminal (:func:`answer_text`), the parent MLflow run's metrics, one
name per case and figure (:func:`answer_metrics`: comparable across runs in the MLflow UI), and one
figure (:func:`answer_figure`, matplotlib only).

The figures are those of the benchmark's nested choice: in each fold of the cross-validation over
whole runs the model is chosen on that fold's training runs alone and scored on its held-out runs;
the model to deploy is chosen by the same rule on every run (:func:`thermbench.bench.choice.deployed_choice`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Mapping

import numpy as np
import pandas as pd

__all__ = ["answer_table", "answer_markdown", "answer_text", "answer_metrics", "answer_figure", "ANSWER_HEADERS"]

#: the answer's columns as the report and the terminal head them (one short value per cell)
ANSWER_HEADERS = {
    "case": "dataset, channel",
    "deploy": "deploy",
    "median_um": "held out µm",
    "worst_um": "worst µm",
    "deployed_um": "as deployed µm",
    "baseline_um": "baseline µm",
    "ratio": "vs baseline",
    "none_um": "uncompensated µm",
    "coverage": "interval covers",
    "half_width_um": "± µm",
}


def _model(family, approach) -> str:
    """A model as a cell: the family, and its approach when that is not one model on every run."""
    if not isinstance(family, str):
        return "-"
    return family if approach in (None, "global") or not isinstance(approach, str) else f"{family} ({approach})"


def answer_table(held: pd.DataFrame, chosen: pd.DataFrame) -> pd.DataFrame:
    """One row per case: ``held``, :func:`thermbench.bench.choice.held_out_summary` (the nested choice's
    held-out RMSE median / worst over the folds, the best baseline's median, no compensation's
    median, the choice's interval coverage and mean half-width); ``chosen``, the deployed
    (family, approach) per case (:func:`thermbench.bench.choice.deployed_choice`). Columns: ``case``,
    ``deploy``, ``folds``, ``median_um``, ``worst_um``, ``deployed_um`` (the choice as deployed, its median),
    ``faults`` (the held-out runs on which a sensor was judged faulty), ``baseline`` (the best baseline family),
    ``baseline_um``, ``ratio`` (the choice's median over the best baseline's), ``none_um``,
    ``coverage`` (a fraction) and ``half_width_um``; NaN where a case has no such figure."""
    deploy = {r.case: _model(r.family, r.approach) for r in chosen.itertuples()} if len(chosen) else {}
    rows = []
    for s in held.to_dict("records"):
        get = lambda k: float(s[k]) if k in s and s[k] is not None and not pd.isna(s[k]) else np.nan  # noqa: E731
        base = s.get("best_baseline")
        rows.append({"case": s["case"], "deploy": deploy.get(s["case"], "-"), "folds": int(s["folds"]),
                     "median_um": get("chosen_median_rmse_um"), "worst_um": get("chosen_worst_rmse_um"),
                     "deployed_um": get("chosen_deployed_median_rmse_um"),
                     "faults": s.get("chosen_faults") if isinstance(s.get("chosen_faults"), str) else "",
                     "baseline": base.split(" (")[0] if isinstance(base, str) else "-",
                     "baseline_um": get("baseline_median_rmse_um"),
                     "ratio": get("chosen_median_rmse_um") / get("baseline_median_rmse_um"),
                     "none_um": get("none_median_rmse_um"), "coverage": get("chosen_coverage"),
                     "half_width_um": get("chosen_half_width_um")})  # fmt: skip
    return pd.DataFrame(rows, columns=["case", "deploy", "folds", "median_um", "worst_um", "deployed_um", "faults",
                                       "baseline", "baseline_um", "ratio", "none_um", "coverage", "half_width_um"])  # fmt: skip


def _shown(answer: pd.DataFrame) -> pd.DataFrame:
    """The answer as strings, in :data:`ANSWER_HEADERS`' order and names."""
    um = lambda v: "-" if pd.isna(v) else f"{v:.2f}"  # noqa: E731
    out = pd.DataFrame({
        "case": answer["case"], "deploy": answer["deploy"], "median_um": answer["median_um"].map(um),
        "worst_um": answer["worst_um"].map(um), "deployed_um": answer["deployed_um"].map(um), "baseline_um": answer["baseline_um"].map(um),
        "ratio": answer["ratio"].map(lambda v: "-" if pd.isna(v) else f"{v:.2f}×"), "none_um": answer["none_um"].map(um),
        "coverage": answer["coverage"].map(lambda v: "-" if pd.isna(v) else f"{100 * v:.0f} %"),
        "half_width_um": answer["half_width_um"].map(um),
    })  # fmt: skip
    return out.rename(columns=ANSWER_HEADERS)


def _notes(answer: pd.DataFrame, level: float) -> list[str]:
    """What the columns mean, and the lists a cell does not hold, as bullets."""
    folds = sorted(set(answer["folds"]))
    bases = sorted(set(answer["baseline"]) - {"-"})
    return [
        "- **deploy**: the model `thermbench export` ships for that channel, chosen by cross-validation over whole "
        "runs (the simplest candidate within one standard error of the best).",
        f"- **held out / worst**: its RMSE on runs it was never fitted on, median and worst over "
        f"{' or '.join(map(str, folds))} fold{'s' if folds != [1] else ''}; each fold's model chosen without "
        "that fold's runs.",
        "- **as deployed**: the same median with each fold's model run as the compensator runs it: every sensor "
        "checked at every sample, a faulty one replaced, the correction bounded in value and rate "
        "(thermbench/bench/faults.py; '-' where a fold's choice has no such score: a bank, the stack (no fit of "
        "its own to run), or a fit that could not be scored so, listed in findings.md).",
        *[f"- {r['case']} as deployed: a sensor judged faulty on held-out {r['faults']}" for r in answer.to_dict("records")
          if isinstance(r.get("faults"), str) and r["faults"]],
        f"- **baseline**: the best baseline's median ({', '.join(bases) or 'none run'}); **vs baseline**: "
        "held out ÷ baseline, below 1 is better.",
        f"- **interval covers / ±**: the share of held-out readings inside the model's {100 * level:.0f} % "
        "prediction interval, and its mean half-width.",
    ]


def answer_markdown(answer: pd.DataFrame, level: float, figure: str | None = None) -> list[str]:
    """The report's first screen: the table, the figure (``figure``: its path relative to the report)
    and what the columns mean."""
    md = [_shown(answer).to_markdown(index=False, tablefmt="pipe", disable_numparse=True), ""]
    if figure:
        md += [f"![held-out RMSE per dataset and channel]({figure})", ""]
    return md + _notes(answer, level) + [""]


def answer_text(answer: pd.DataFrame, level: float) -> str:
    """The benchmark's last lines on the terminal: the same table as plain text, and its notes."""
    table = _shown(answer).to_markdown(index=False, tablefmt="simple", disable_numparse=True)
    notes = [n.replace("**", "") for n in _notes(answer, level)]
    return "\n".join(["the model to deploy, and its RMSE on runs it never saw", table, *notes])


def answer_metrics(answer: pd.DataFrame, level: float) -> dict[str, float]:
    """The answer as MLflow metrics of the parent run, ``<case>/<figure>``: ``held_out_median_rmse_um``,
    ``held_out_worst_rmse_um``, ``as_deployed_median_rmse_um``, ``best_baseline_median_rmse_um``, ``ratio_to_best_baseline``,
    ``uncompensated_median_rmse_um``, ``interval_coverage_<level %>`` and ``interval_half_width_um``
    (finite figures only)."""
    names = {"median_um": "held_out_median_rmse_um", "worst_um": "held_out_worst_rmse_um",
             "deployed_um": "as_deployed_median_rmse_um",
             "baseline_um": "best_baseline_median_rmse_um", "ratio": "ratio_to_best_baseline",
             "none_um": "uncompensated_median_rmse_um", "coverage": f"interval_coverage_{round(100 * level)}",
             "half_width_um": "interval_half_width_um"}  # fmt: skip
    out = {}
    for r in answer.to_dict("records"):
        for col, name in names.items():
            if np.isfinite(r[col]):
                out[f"{r['case']}/{name}"] = float(r[col])
    return out


def answer_figure(answer: pd.DataFrame, path: Path) -> Path:
    """One horizontal bar group per case, on a log scale of µm: uncompensated, the best baseline and
    the model to deploy (its median held-out RMSE, a line to its worst)."""
    from matplotlib.figure import Figure

    n = len(answer)
    fig = Figure(figsize=(7.5, 0.9 + 0.55 * max(n, 1)), layout="constrained")
    ax = fig.add_subplot()
    y = np.arange(n)[::-1].astype(float)
    h = 0.26
    bars: Mapping[str, tuple] = {"uncompensated": ("none_um", "#bbbbbb", h),
                                 "best baseline": ("baseline_um", "#666666", 0.0),
                                 "model to deploy": ("median_um", "#1f77b4", -h)}  # fmt: skip
    for label, (col, color, dy) in bars.items():
        v = answer[col].to_numpy(dtype=float)
        ax.barh(y + dy, np.where(np.isfinite(v), v, np.nan), height=h, color=color, label=label)
    worst = answer["worst_um"].to_numpy(dtype=float)
    med = answer["median_um"].to_numpy(dtype=float)
    ax.hlines(y - h, med, worst, color="black", linewidth=1.2, label="worst fold")
    ax.set_xscale("log")
    ax.set_yticks(y, [f"{c}: {d}" for c, d in zip(answer["case"], answer["deploy"])])
    ax.set_xlabel("RMSE on runs never trained on (µm, log scale)")
    ax.legend(loc="lower right", fontsize="small")
    ax.grid(axis="x", which="both", alpha=0.3)
    fig.savefig(path, format="png", dpi=110)
    return path
