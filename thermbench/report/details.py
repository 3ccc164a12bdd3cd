"""details.md's sections (:func:`thermbench.report.markdown.write_report` writes the file): how to
read it, the headline tables on unseen cycles, and per dataset the comparison of approaches, the
train × test matrices and the before / after curves (by channel for a dataset scored on several),
then the probe readings. Each section is a list of markdown lines; its figures are queued on the
report's :class:`~thermbench.report.figures._Drawing`.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from .figures import (
    _Drawing, _bars_figure, _best_curves_figure, _comparison_figure, _matrix_figure, _rmse_heatmap_figure,
    _rmse_norm, curves_figure, probe_figure,
)
from ..bench.results import ALL_CHANNELS, CHANNEL, RATE, RESIDUAL, RMSE
from .tables import (
    _case_label, _channels, _family_label, _matrix_models, _model_label,
    _runs, _test_matrix, _unique, approach_comparison, headline, best_by_channel, probe_curve, train_test_matrix,
    validation_by_channel,
)
from .text import _is_missing, fmt_rate, fmt_um, markdown_table, terminal_summary

#: the report's figures, a folder beside report.md and details.md
FIGURES_DIR = "figures"


HOW_TO_READ = (
    "**How to read this report.** The *compensation rate* of a run is 1 − max|residual| / max|thermal error| "
    "(seed 000 §5, seed 002 §3): 100 % means the model removed all the thermal error, 0 % that the compensated axis "
    "is no better than the uncompensated one, and a *negative* rate that compensation made the axis worse. "
    "*Max residual* is the largest |measured − predicted| thermal error left after compensation, in µm. "
    "*Unseen* runs are the runs a model was not trained on: the random validation duty cycles and, for a single-state "
    "model, the other modelling states (the off-diagonal cells of its train × test matrix). Approaches: "
    "*single* = one "
    "model trained on one loading state; *global* = one model trained on all modelling states; *bank* = one model per "
    "state plus a condition classifier that picks the model for the running duty (seed 002 §2.4); *bank_soft* = the "
    "same models blended by the classifier's probabilities. *Worst* is the "
    "lowest rate / the largest residual. In the heatmaps the colour is the compensation rate, blue = good, white = no "
    "gain, red = worse than not compensating, clipped to ±100 % so a model that fails badly still shows as deep red; "
    "the printed numbers are the true values, with the max residual in µm below the rate. Outlined cells are a "
    "model's own training state. In the before/after plots the black line is the uncompensated thermal error "
    "(max over the targets of each measuring cycle) and each coloured line the residual left by one model "
    "(colour = family, line style = approach: dotted single, solid global, dashed bank, dash-dotted bank_soft)."
)


HOW_TO_READ_CHANNELS = (
    "**Datasets with several error channels** (e.g. the five displacement sensors of a spindle test, ch1 … ch5) are "
    "scored per channel: each channel has its own models, trained and tested on that channel only. Their sections "
    "compare the *RMSE* of the residual (µm, lower is better) on the validation run(s): per channel, family and "
    "approach, where *single* is the mean over the single-state models (what training on one state gives on average; "
    "(k/N) when only k of the N states could be fitted). In their train × test heatmaps the colour is the RMSE on a "
    "log scale shared by every family of the dataset (light = small, dark red = large); outlined cells are runs the "
    "model was trained on."
)


HOW_TO_READ_BASELINES = (
    "**Baselines** (reference families: compared, never chosen for deployment) are marked *(baseline)* in the "
    "tables and figures, hatched grey in the bar charts and `*` in the summary."
)


_HEADLINE_HEADERS = {
    "family": "family",
    "approach": "approach",
    "n_models": "models",
    "own_rate_mean": "own runs mean",
    "val_rate_worst": "validation worst",
    "val_rate_mean": "validation mean",
    "val_worst_residual_um": "validation worst max µm",
    "states_rate_worst": "other states worst",
    "states_rate_mean": "other states mean",
    "states_worst_residual_um": "other states worst max µm",
}


def _headline_md(h: pd.DataFrame, runs: list[str], ref: frozenset[str] = frozenset()) -> str:
    """One dataset's headline rows: aggregates, then 'rate / max µm' per validation run."""
    drop = [lvl for lvl in ("dataset", CHANNEL) if lvl in h.index.names]
    t = h.reset_index(level=drop, drop=True).reset_index()
    t["family"] = [_family_label(f, ref) for f in t["family"]]
    fixed = [c for c in _HEADLINE_HEADERS if c in t.columns]
    show = t[fixed].copy()
    if show[["states_rate_worst", "states_rate_mean"]].isna().all().all():
        show = show.drop(columns=["states_rate_worst", "states_rate_mean", "states_worst_residual_um"])
    for run in runs:
        show[f"{run} rate / max µm"] = [
            "—" if _is_missing(a) else f"{fmt_rate(a)} / {fmt_um(b)}"
            for a, b in zip(t[f"{run}:rate"], t[f"{run}:residual_um"])
        ]
    return markdown_table(show, index=False, headers=_HEADLINE_HEADERS, formats={"n_models": str})


#: a run-metadata value longer than this is a bullet below the table, not a cell that widens every row


def _matrix_summary(rate: pd.DataFrame, resid: pd.DataFrame) -> str:
    diag, off = [], []
    for tr in rate.index:
        for te in rate.columns:
            (diag if tr == te else off).append((rate.at[tr, te], resid.at[tr, te], tr, te))
    parts = []
    d = [x for x in diag if not math.isnan(x[0])]
    if d:
        parts.append(f"own state mean {fmt_rate(np.mean([x[0] for x in d]))}")
    o = [x for x in off if not math.isnan(x[0])]
    if o:
        worst = min(o, key=lambda x: x[0])
        parts.append(
            f"unseen states mean {fmt_rate(np.mean([x[0] for x in o]))}, worst {fmt_rate(worst[0])} "
            f"(trained on {worst[2]}, tested on {worst[3]}), "
            f"worst max residual {fmt_um(np.nanmax([x[1] for x in o]))} µm"
        )
    return "; ".join(parts) + "." if parts else "No scored cells."


def _channel_table_md(t: pd.DataFrame, ref: frozenset[str], n_states: int, fmt: Callable,
                      lower_is_better: bool) -> str:
    """:func:`validation_by_channel` as markdown: a row per (family, approach), a column
    per channel, the best of each column in bold, (k/N) where single had k of N states."""
    counts = t.attrs.get("n_models")
    best = {}
    for ch in t.columns:
        col = t[ch].dropna()
        if len(col):
            best[ch] = col.idxmin() if lower_is_better else col.idxmax()
    rows = []
    for key in t.index:
        fam, app = key
        row = {"family": _family_label(fam, ref), "approach": "single (mean)" if app == "single" else app}
        for ch in t.columns:
            v = t.at[key, ch]
            text = fmt(v)
            if app == "single" and counts is not None and not _is_missing(v) and 0 < n_states:
                k = int(counts.at[key, ch])
                if k < n_states:
                    text += f" ({k}/{n_states})"
            row[ch] = f"**{text}**" if best.get(ch) == key else text
        rows.append(row)
    return markdown_table(pd.DataFrame(rows), index=False)


def _best_lines(t: pd.DataFrame, ref: frozenset[str]) -> list[str]:
    """Per channel: best thermbench family vs best baseline, RMSE in µm."""
    b = best_by_channel(t, ref)
    lines = []
    for ch, row in b.iterrows():
        if row["family"] is None and row["baseline"] is None:
            lines.append(f"- **{ch}**: nothing scored.")
        elif row["baseline"] is None:
            lines.append(f"- **{ch}**: best thermbench family {fmt_um(row['family_value'])} µm "
                         f"({_model_label(row['family'])}); no baseline family in the results.")  # fmt: skip
        elif row["family"] is None:
            lines.append(f"- **{ch}**: only baselines scored; best baseline {fmt_um(row['baseline_value'])} µm "
                         f"({_model_label(row['baseline'])}).")  # fmt: skip
        else:
            better = "better" if row["family_value"] < row["baseline_value"] else "NOT better"
            lines.append(
                f"- **{ch}**: best thermbench family vs best baseline: {fmt_um(row['family_value'])} µm vs "
                f"{fmt_um(row['baseline_value'])} µm ({_model_label(row['family'])} vs "
                f"{_model_label(row['baseline'])}; {better} than the baseline)."
            )
    return lines


def _channels_headline_md(r: pd.DataFrame, ds: str, ref: frozenset[str]) -> list[str]:
    chans, runs, states = _channels(r, ds), _runs(r, ds, "validation"), _runs(r, ds, "state")
    md = [f"### {ds} ({len(chans)} error channels: {', '.join(chans)})", ""]
    if not runs:
        return md + ["_No validation runs for this dataset._", ""]
    t = validation_by_channel(r, ds, RMSE)
    md += [
        f"RMSE (µm) of the residual on the validation run(s) {', '.join(runs)}"
        + (" (mean over them)" if len(runs) > 1 else "")
        + ", per channel; single (mean) = mean over the single-state models; bold = best of the channel.",
        "",
        _channel_table_md(t, ref, len(states), fmt_um, lower_is_better=True),
        "",
        *_best_lines(t, ref),
        "",
    ]
    return md


def _channels_section(r: pd.DataFrame, c: pd.DataFrame | None, ds: str, ref: frozenset[str], fig_dir: Path,
                      fig_name: Callable[..., str], draw: "_Drawing") -> list[str]:
    """The section of a dataset scored on several error channels (see
    :func:`thermbench.report.markdown.write_report`)."""
    chans, runs, states = _channels(r, ds), _runs(r, ds, "validation"), _runs(r, ds, "state")
    d = r[r["dataset"] == ds]
    md = [f"## {ds}", ""]
    md += [
        f"Scored on {len(chans)} error channels ({', '.join(chans)}), each with its own models; modelling states "
        f"{', '.join(states) or '—'}; validation run(s) {', '.join(runs) or '—'}. The validation RMSE table is in "
        "the headline above.",
        "",
    ]
    rmse_t = validation_by_channel(r, ds, RMSE) if runs else None
    if runs:
        name = fig_name("rmse_bars", ds)
        draw(_bars_figure, rmse_t, ref, runs, ds, fig_dir / name)
        md += ["### Validation RMSE per channel", "", f"![{ds} validation RMSE per channel]({FIGURES_DIR}/{name})", ""]
        rate_t = validation_by_channel(r, ds, RATE)
        md += [
            "### Validation compensation rate per channel",
            "",
            "1 − max|residual| / max|thermal error| on the validation run(s); single (mean) = mean over the "
            "single-state models; bold = best of the channel.",
            "",
            _channel_table_md(rate_t, ref, len(states), fmt_rate, lower_is_better=False),
            "",
        ]
    else:
        md += ["_No validation runs for this dataset._", ""]

    md += [
        "### Train × test RMSE per family",
        "",
        "Rows: the state a single-state model was trained on, then the models trained on all states (global, bank); "
        "columns: the modelling states, then (right of the line) the validation run(s); one panel per channel; "
        "RMSE in µm, outlined = trained on that run; grey n/a = not fitted.",
        "",
    ]
    tests = states + runs
    panels_by_family, all_values = {}, []
    by_model = dict(list(d.groupby(["family", CHANNEL], sort=False)))
    for fam in _unique(d["family"]):
        models = _matrix_models(d[d["family"] == fam], states)
        panels = [(ch, *_test_matrix(by_model.get((fam, ch), d.iloc[:0]), RMSE, models, tests)) for ch in chans]
        panels_by_family[fam] = panels
        all_values += [p[1].to_numpy(float).ravel() for p in panels]
    norm = _rmse_norm(np.concatenate(all_values) if all_values else np.array([]))
    for fam, panels in panels_by_family.items():
        label = _family_label(fam, ref)
        name = fig_name("rmse_matrix", ds, fam)
        draw(_rmse_heatmap_figure, panels, len(states), norm, f"{ds} · {label}: RMSE (µm), trained on (rows) × tested "
             "on (columns), per channel", fig_dir / name)  # fmt: skip
        md += [f"#### {label}", "", _rmse_matrix_summary(panels, states), "",
               f"![{ds} {fam} RMSE matrix]({FIGURES_DIR}/{name})", ""]  # fmt: skip

    md += ["### Before / after compensation: best model per channel", ""]
    items, notes = [], []
    if rmse_t is not None and c is not None:
        cd = c[(c["dataset"] == ds) & c["run_id"].isin(runs)]
        have = set(zip(cd[CHANNEL], cd["family"], cd["approach"]))
        for ch in chans:
            col = rmse_t[ch].dropna()
            with_curves = [k for k in col.index if k[1] != "single" and (ch, *k) in have]
            fams = [k for k in with_curves if k[0] not in ref]
            bases = [k for k in with_curves if k[0] in ref]
            if not fams:
                notes.append(f"- **{ch}**: no curves of a thermbench family.")
                continue
            best = min(fams, key=lambda k: col[k])
            base = min(bases, key=lambda k: col[k]) if bases else None
            overall = col[[k for k in col.index if k[0] not in ref]]
            line = f"- **{ch}**: {_model_label(best)} ({fmt_um(col[best])} µm)"
            if base is not None:
                line += f" vs baseline {_model_label(base)} ({fmt_um(col[base])} µm)"
            if len(overall) and overall.idxmin() != best:
                k = overall.idxmin()
                line += (f"; the lowest thermbench RMSE, {_model_label(k)} ({fmt_um(col[k])} µm), has no curves "
                         "(single-state models are scored, not plotted)")  # fmt: skip
            notes.append(line + ".")
            for run in runs:
                sel = cd[(cd[CHANNEL] == ch) & (cd["run_id"] == run)]
                bc = sel[(sel["family"] == best[0]) & (sel["approach"] == best[1])]
                if bc.empty:
                    continue
                item = {"channel": ch, "run": run, "best": best, "best_value": float(col[best]), "best_curve": bc}
                if base is not None:
                    bb = sel[(sel["family"] == base[0]) & (sel["approach"] == base[1])]
                    if len(bb):
                        item |= {"base": base, "base_value": float(col[base]), "base_curve": bb}
                items.append(item)
    if items:
        name = fig_name("best_curves", ds)
        draw(_best_curves_figure, items, ds, fig_dir / name)
        md += ["The best thermbench model per channel that has before/after curves (lowest validation RMSE, "
               "baselines excluded), with the best baseline for comparison:", "", *notes, "",
               f"![{ds} before/after, best model per channel]({FIGURES_DIR}/{name})", ""]  # fmt: skip
    else:
        md += ["_No before/after curves for this dataset's validation runs._", *([""] + notes if notes else []), ""]
    return md


def _rmse_matrix_summary(panels, states: list[str]) -> str:
    """One line: per channel the mean RMSE of the single-state models on their own state
    and on the other states."""
    parts = []
    for ch, vals, own in panels:
        single = [i for i in vals.index if i in set(states)]
        if not single:
            continue
        v = vals.loc[single, states].to_numpy(float)
        o = own.loc[single, states].to_numpy(bool)
        mine, other = v[o & np.isfinite(v)], v[~o & np.isfinite(v)]
        if mine.size or other.size:
            parts.append(f"{ch} {fmt_um(mine.mean() if mine.size else np.nan)} / "
                         f"{fmt_um(other.mean() if other.size else np.nan)}")  # fmt: skip
    if not parts:
        return "No single-state models."
    return "Single-state models, mean RMSE on their own state / on the other states (µm): " + "; ".join(parts) + "."


PROBES_MD = (
    "## Probe readings: RMSE against probes per hour\n\n"
    "Each held-out run replayed with probe readings taken from its own measurements (approaches "
    "`adaptive-<every>s`, the bias + gain filter; `naive_probe-<every>s`, the last probe's residual added; "
    "`gp_refit-<every>s`, the GP refitted on all data so far; `adaptive-uncertainty`, probing when the filter's "
    "uncertainty exceeds its level), scored on the readings that were not probes, beside the same runs open "
    "loop. These rows never take part in choosing the model to deploy: they use the scored run's own readings."
)


def details_opening(r: pd.DataFrame, datasets: list[str], multi: list[str], ref: frozenset[str],
                    report_name: str) -> list[str]:
    """details.md's first sections: how to read it (the answer is in ``report_name``), the terminal
    summary at a glance, and the headline on unseen cycles of each dataset (by channel for those in
    ``multi``, scored on several)."""
    h = headline(r)
    details: list[str] = ["# Thermal-error robustness report: the details", "",
                          f"What the models were chosen on and scored by; the answer is in [{report_name}]({report_name}).",
                          "", HOW_TO_READ, ""]  # fmt: skip
    if multi:
        details += [HOW_TO_READ_CHANNELS, ""]
    if ref:
        details += [HOW_TO_READ_BASELINES, ""]
    details += ["## At a glance", "", "```text", terminal_summary(r, reference=ref), "```", ""]
    details += ["## Headline: unseen cycles", ""]
    details += [
        "Per dataset, family and approach: mean rate on the training runs (reference), worst and mean rate and worst "
        "max residual over the validation runs, the same over the other modelling states for single-state models, "
        "then rate / max residual per validation run (single: mean over the training states).",
        "",
    ]
    for ds in datasets:
        if ds in multi:
            details += _channels_headline_md(r, ds, ref)
            continue
        ch = _channels(r, ds)[0]
        rows = h.xs((ds, ch), level=("dataset", CHANNEL), drop_level=False) if CHANNEL in h.index.names else \
            h.xs(ds, level="dataset", drop_level=False)  # fmt: skip
        details += [f"### {_case_label(ds, ch)}", "", _headline_md(rows, _runs(r, ds, "validation"), ref), ""]
    return details


def _dataset_section(r: pd.DataFrame, c: pd.DataFrame | None, ds: str, ref: frozenset[str], fig_dir: Path,
                     fig_name: Callable, draw: _Drawing) -> list[str]:
    """details.md's section of a dataset scored on one channel: single vs global vs bank on its validation
    runs (table + figure), the train × test matrix of each family, the before / after curves."""
    details: list[str] = []
    ch = _channels(r, ds)[0]
    label = _case_label(ds, ch)
    parts = (ds,) if ch == ALL_CHANNELS else (ds, ch)
    details += [f"## {label}", ""]
    runs = _runs(r, ds, "validation")
    details += ["### Single vs global vs bank on the validation runs", ""]
    if runs:
        comp = approach_comparison(r, ds, channel=ch)
        if ref:
            comp.index = pd.MultiIndex.from_tuples([(_family_label(f, ref), m) for f, m in comp.index],
                                                   names=comp.index.names)  # fmt: skip
        name = fig_name("compare", *parts)
        draw(_comparison_figure, comp, runs, label, fig_dir / name)
        details += [
            "Compensation rate per validation run; single best / worst = the training state with the highest "
            "/ lowest mean rate over these runs.",
            "",
            markdown_table(
                comp,
                formats={"trained_on": str, **{run: fmt_rate for run in runs}},
                headers={"mean_rate": "mean", "worst_rate": "worst", "worst_residual_um": "worst max µm"},
            ),
            "",
            f"![{label} comparison]({FIGURES_DIR}/{name})",
            "",
        ]
    else:
        details += ["_No validation runs for this dataset._", ""]

    details += ["### Train × test matrices (single-state models)", ""]
    single = r[(r["dataset"] == ds) & (r["approach"] == "single") & (r["kind"] == "state")]
    fams = _unique(single["family"])
    if not fams:
        details += ["_No single-state models for this dataset._", ""]
    for fam in fams:
        rate = train_test_matrix(r, ds, fam, RATE, channel=ch)
        resid = train_test_matrix(r, ds, fam, RESIDUAL, channel=ch)
        name = fig_name("matrix", *parts, fam)
        draw(_matrix_figure, rate, resid, label, _family_label(fam, ref), fig_dir / name)
        details += [f"#### {_family_label(fam, ref)}", "", _matrix_summary(rate, resid), ""]
        details += [f"![{label} {fam} matrix]({FIGURES_DIR}/{name})", ""]

    details += ["### Before / after compensation (validation runs)", ""]
    cd = None if c is None else \
        c[(c["dataset"] == ds) & c[CHANNEL].isin([ch, ALL_CHANNELS]) & c["run_id"].isin(runs)]
    plotted = [run for run in runs if cd is not None and (cd["run_id"] == run).any()]
    if plotted:
        name = fig_name("curves", *parts)
        draw(curves_figure, cd, plotted, f"{label}, validation runs", fig_dir / name)
        details += [f"![{label} before/after]({FIGURES_DIR}/{name})", ""]
        missing = [run for run in runs if run not in plotted]
        if missing:
            details += [f"_No curves for validation run(s) {', '.join(missing)}._", ""]
    else:
        details += ["_No before/after curves for this dataset's validation runs._", ""]
    return details


def _probe_section(r: pd.DataFrame, fig_dir: Path, fig_name: Callable, draw: _Drawing,
                   ref: frozenset[str]) -> list[str]:
    """details.md's section of the probe readings (:func:`probe_curve`): none without probe rows."""
    details: list[str] = []
    curve = probe_curve(r)
    if len(curve):
        details += [PROBES_MD, ""]
        for ds in _unique(curve["dataset"]):
            cd = curve[curve["dataset"] == ds]
            name = fig_name("probes", ds)
            draw(probe_figure, cd, str(ds), fig_dir / name, 4, ref)
            details += [f"### {ds}", "", f"![{ds} probes]({FIGURES_DIR}/{name})", "",
                        markdown_table(cd.drop(columns="dataset").round(3), index=False), ""]  # fmt: skip
    return details
