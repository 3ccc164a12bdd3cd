"""The diagnosis report: ``report.md``, residual maps, candidate scores, held-out error
per step, and the one-screen verdict printed at the end of ``thermbench diagnose``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from ..report.figures import _new_figure, _save
from ..report.text import markdown_table
from .localise import POSITION_WORDS
from .significance import display as _name  # a step's or candidate's name with its signal

FIGURES = ("residual_maps_before.png", "residual_maps_after.png", "heldout_by_step.png")


def _fixed_point(table: pd.DataFrame) -> bool:
    return table["target_mm"].nunique() <= 1  # a spindle's drift at one point: residual against time


def _scored(table: pd.DataFrame) -> pd.DataFrame:
    """The readings a score counts: after each target's cold reference, or all at a fixed point."""
    return table if _fixed_point(table) else table[table["cycle"] > 0]


def _maps(fig, table: pd.DataFrame, title: str, vmax: float) -> None:
    runs = list(dict.fromkeys(table["run_id"]))
    if _fixed_point(table):
        ax = fig.subplots()
        for run in runs:
            g = table[table["run_id"] == run]
            ax.plot(g["t_s"] / 3600.0, g["residual_um"], lw=0.8, label=str(run))
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel("time from the start of the test (h)")
        ax.set_ylabel("held-out residual (µm)")
        ax.legend(fontsize=7, ncol=min(len(runs), 6))
        fig.suptitle(title, fontsize=10)
        return
    axes = fig.subplots(1, len(runs), sharey=True, squeeze=False)[0]
    sc = None
    for ax, run in zip(axes, runs):
        g = table[(table["run_id"] == run) & (table["cycle"] > 0)]
        sc = ax.scatter(g["t_s"] / 3600.0, g["target_mm"], c=g["residual_um"], cmap="RdBu_r", vmin=-vmax, vmax=vmax,
                        marker="s", s=14)  # fmt: skip
        ax.set_title(str(run), fontsize=9)
        ax.set_xlabel("time (h)")
    axes[0].set_ylabel("target (mm)")
    fig.suptitle(title, fontsize=10)
    if sc is not None:
        fig.colorbar(sc, ax=list(axes), label="held-out residual (µm)")


def residual_maps(table: pd.DataFrame, title: str, path: Path, vmax: float) -> Path:
    n = table["run_id"].nunique()
    fig = _new_figure(min(2.6 * n + 1.5, 16), 3.4)
    _maps(fig, table, title, vmax)
    return _save(fig, path)


def candidates_figure(scan: dict, floor_um: float, threshold_x: float, path: Path) -> Path:
    c = [x for x in scan["candidates"] if not x.get("skipped")]
    fig = _new_figure(6.5, 0.45 * max(len(c), 2) + 1.4)
    ax = fig.subplots()
    names = [_name(x) for x in c]
    vals = [x["explained_um"] for x in c]
    colours = ["tab:green" if x["significant"] else "tab:grey" for x in c]
    ax.barh(names, vals, color=colours)
    ax.axvline(threshold_x * floor_um, color="k", ls="--", lw=1, label=f"{threshold_x:g} x noise floor")
    ax.set_xlabel("held-out error explained (µm)")
    ax.invert_yaxis()
    ax.legend(fontsize=8)
    ax.set_title(f"candidates on {_model_name(scan['effects'])}", fontsize=10)
    return _save(fig, path)


def heldout_figure(d: dict, path: Path) -> Path:
    labels = [_model_name(d["base_effects"])]
    vals = [d["final"]["heldout_rmse_base_um"]]
    for s in d["steps"]:
        if s["ambiguous_with"] or not s["confirmed"]:
            continue
        labels.append("+ " + _name(s))
        vals.append(s["heldout_rmse_after_um"])
    fig = _new_figure(6.5, 3.4)
    ax = fig.subplots()
    ax.plot(range(len(vals)), vals, "o-")
    ax.axhline(d["noise_floor_um"], color="k", ls="--", lw=1, label="noise floor")
    ax.set_xticks(range(len(vals)), labels, rotation=15, fontsize=8)
    ax.set_ylabel("held-out RMSE (µm)")
    ax.set_ylim(bottom=0)
    ax.legend(fontsize=8)
    return _save(fig, path)


def write_figures(d: dict, tables: dict, out: Path, threshold_x: float) -> list[str]:
    before = tables["before"]
    after = tables[list(tables)[-1]]
    vmax = float(np.quantile(np.abs(_scored(before)["residual_um"]), 0.98)) or 1.0
    names = [
        residual_maps(before, "held-out residual of the base model", out / FIGURES[0], vmax).name,
        residual_maps(after, "held-out residual of the final model (same colour scale)", out / FIGURES[1], vmax).name,
        heldout_figure(d, out / FIGURES[2]).name,
    ]
    for k, scan in enumerate(d["scans"], 1):
        names.append(candidates_figure(scan, scan["noise_floor_um"], threshold_x, out / f"candidates_step{k}.png").name)
    if "holdout_base" in tables:
        names.append(holdout_figure(tables["holdout_base"], tables["holdout_final"], d, out / "holdout.png").name)
    return names


def holdout_figure(base: pd.DataFrame, final: pd.DataFrame, d: dict, path: Path) -> Path:
    """The runs held out of the search: measured, the base's and the final model's predictions."""
    fig = _new_figure(8.0, 3.6)
    ax = fig.subplots()
    t = base["t_s"] / 3600.0
    ax.plot(t, base["thermal_um"], "k.", ms=1.5, label="measured")
    v = d["validation"]
    ax.plot(t, base["predicted_um"], lw=1, label=f"base (RMSE {v['rmse_base_um']:.2f} µm)")
    ax.plot(final["t_s"] / 3600.0, final["predicted_um"], lw=1,
            label=f"{_model_name(v['effects'])} (RMSE {v['rmse_final_um']:.2f} µm)")  # fmt: skip
    ax.set_xlabel("time from the start of the test (h)")
    ax.set_ylabel("error (µm)")
    ax.set_title(f"held out of the search: {', '.join(v['runs'])}", fontsize=10)
    ax.legend(fontsize=8)
    return _save(fig, path)


def _model_name(effects) -> str:
    return "base" + "".join(" + " + e for e in effects)


def described(s: dict) -> str:
    """An open term's identified form in words (and the canonical effect it is), else ''."""
    if not s.get("description") or s.get("label") == s["effect"]:
        return ""
    same = f" (= {s['canonical']})" if s.get("canonical") else ""
    alike = f"; driven alike by {', '.join(s['signals_alike'])}" if s.get("signals_alike") else ""
    return f"{s['description']}{same}{alike}"


def _um(x) -> str:
    return "" if x is None or (isinstance(x, float) and np.isnan(x)) else f"{x:.3f}"


def _loc_md(loc: dict) -> str:
    lines = [loc["summary"] + ".", ""]
    pos = pd.DataFrame(loc["by_position"]).T
    if len(pos):
        pos.index = [POSITION_WORDS.get(i, i) for i in pos.index]
        lines.append(markdown_table(pos.reset_index(names="position")[["position", "n", "mean_um", "rms_um", "rms_x_floor", "significant"]], index=False))
        lines.append("")
    run = pd.DataFrame(loc["by_run"]).T
    if len(run):
        cols = ["run_id", loc.get("driver", "feed_mm_min"), *(["load_N"] if "load_N" in run else []), "n", "rms_um", "rms_x_floor", "significant"]
        lines.append(markdown_table(run.reset_index(names="run_id")[cols], index=False))
    return "\n".join(lines)


def write_markdown(d: dict, out: Path) -> Path:
    md = [f"# Diagnosis of `{d['dataset']}`", "", f"**{verdict_line(d)}**", ""]
    if d.get("frame"):
        md.append(f"- scored on: {d['frame']}")
    md += [f"- base model: {d['base_words']}{''.join(' + ' + e for e in d['base_effects'])}",
           f"- noise floor: {d['noise_floor_um']:.3f} um ({d['noise']['method']}; per-reading scatter "
           f"{d['noise']['reading_sigma_um']:.3f} um; estimates: "
           + ", ".join(f"{k} {v[0]:.3f} um from {v[1]}" for k, v in d["noise"]["estimates"].items()) + ")",
           f"- cross-validation: {d['cv']['kind']} ({len(d['cv']['folds'])} fold(s))",
           f"- test: {d['test']['description']}", f"- runtime: {d['runtime_s']:.0f} s"]
    for note in d["notes"]:
        md.append(f"- note: {note}")
    for e, why in d["skipped"].items():
        md.append(f"- skipped `{e}`: {why}")
    md += ["", "## Where the base model disagrees (held-out)", "", _loc_md(d["localisation"]["before"]), "",
           "![](residual_maps_before.png)", ""]  # fmt: skip
    md += ["## Steps", ""]
    if d["steps"]:
        rows = pd.DataFrame([{"effect": _name(s), **{k: s[k] for k in ("heldout_rmse_before_um", "heldout_rmse_after_um", "bic_gain")},
                              "ambiguous_with": ", ".join(s["ambiguous_with"]), "confirmed": s["confirmed"],
                              "identified form": described(s)}
                             for s in d["steps"]])  # fmt: skip
        md += [markdown_table(rows, index=False), "", "![](heldout_by_step.png)", ""]
    else:
        md += ["No candidate passed the test.", ""]
    for k, scan in enumerate(d["scans"], 1):
        md += [f"### Candidates, scan {k}: {_model_name(scan['effects'])}", ""]
        rows = pd.DataFrame([{"effect": _name(c), "heldout_rmse_um": c.get("heldout_rmse_um"),
                              "explained_um": c.get("explained_um"), "bic_gain": c.get("bic_gain"),
                              "significant": c.get("significant"),
                              "fit": "" if c.get("skipped") else ("all parameters" if c.get("refit") else "screened"),
                              "identified form": "" if c.get("skipped") else described({**c, "canonical": None}),
                              "skipped": c.get("skipped") or ""}
                             for c in scan["candidates"]])  # fmt: skip
        md += [markdown_table(rows, index=False), "",
               "Screened: the current model's parameters held and the candidate's own identified (a lower bound on "
               "what it explains); all parameters: re-identified with every parameter free.", "",
               f"![](candidates_step{k}.png)", ""]  # fmt: skip
    md += ["## Final model", "", f"model: {_model_name(d['final']['effects'])}; "
           f"held-out RMSE {d['final']['heldout_rmse_um']:.3f} um ({d['final']['heldout_x_floor']:.1f}x the noise "
           f"floor {d['final']['noise_floor_um']:.3f} um)", ""]  # fmt: skip
    md += [markdown_table(pd.DataFrame({"parameter": list(d["final"]["identified"]),
                                        "value": [v if isinstance(v, str) else f"{v:.6g}"
                                                  for v in d["final"]["identified"].values()]})), ""]  # fmt: skip
    md += ["## Where the final model disagrees (held-out)", "", _loc_md(d["localisation"]["after"]), "",
           "![](residual_maps_after.png)", ""]  # fmt: skip
    if d.get("validation"):
        md += validation_md(d)
    md += ["## What is left", "", *gap_md(d)]
    path = out / "report.md"
    path.write_text("\n".join(md), encoding="utf-8")
    return path


def verdict_line(d: dict) -> str:
    """One line: the verdict (``none``, ``found``, ``found_partial``, ``ambiguous``,
    ``unexplained``) with the final held-out RMSE against the noise floor."""
    f = d["final"]
    vs = f"held-out RMSE {f['heldout_rmse_um']:.3f} um, {f['heldout_x_floor']:.1f}x the noise floor {f['noise_floor_um']:.3f} um"
    found = ", ".join(_name(s) + (f" ({w})" if (w := described(s)) else "")
                      for s in d["steps"] if s["confirmed"] and not s["ambiguous_with"]) or ", ".join(d["missing_effects"])
    if d["verdict"] == "ambiguous":
        amb = "; ".join(" or ".join(a) for a in d["ambiguous"])
        return f"{'missing: ' + found + '; then ' if found else ''}ambiguous: {amb} (the data cannot tell them apart; {vs})"
    if d["verdict"] == "found":
        return f"missing effect(s), in the order found: {found}; with them the model explains the data ({vs})"
    if d["verdict"] == "found_partial":
        return (f"{found} explain(s) part of the gap, not all of it: the {vs}; something else is missing "
                "(see 'What is left')")  # fmt: skip
    if d["verdict"] == "unexplained":
        tried = any(not c.get("skipped") for scan in d["scans"] for c in scan["candidates"])
        why = ("no candidate was tried" if not tried else
               f"{d['steps'][-1]['effect']} passed the screening but not the per-fold test" if d["steps"] else
               "no candidate accounts for the residual")  # fmt: skip
        return f"unexplained: {why}; {vs} (see 'What is left')"
    return f"no missing effect: the base model explains the data ({vs})"


def gap_md(d: dict) -> list[str]:
    """The 'What is left' section: how far above the floor, where, when, the best candidate
    and what data would tell more (``d['gap']``)."""
    g = d["gap"]
    if g["within_floor"]:
        return [f"The final model's held-out RMSE ({g['heldout_rmse_um']:.3f} um) is within "
                f"{d['test']['within_x_floor']:g}x the noise floor ({g['noise_floor_um']:.3f} um).", ""]  # fmt: skip
    lines = [f"- the final model's held-out RMSE is {g['heldout_rmse_um']:.3f} um, {g['x_floor']:.1f}x the noise floor "
             f"({g['noise_floor_um']:.3f} um): a systematic part of about {g['systematic_um']:.3f} um is left",
             f"- where and when: {d['localisation']['after']['summary']}"]  # fmt: skip
    b = g["best_candidate"]
    if b is not None:
        lines.append(f"- the best remaining candidate, {b['effect']}{' (' + b['description'] + ')' if b.get('description') else ''}, explains {b['explains_um']:.3f} um and leaves "
                     f"{b['heldout_rmse_um']:.3f} um ({b['remains_x_floor']:.1f}x the floor)"
                     + ("" if b["significant"] else "; it does not pass the test"))  # fmt: skip
    for h in g["more_data"]:
        lines.append(f"- to tell more: {h}")
    return lines + [""]


def validation_md(d: dict) -> list[str]:
    """The runs held out of the whole search, scored once at its end."""
    v = d["validation"]
    rows = pd.DataFrame([{"model": st["model"], "RMSE (um)": f"{st['rmse_um']:.3f}", "x floor": f"{st['x_floor']:.1f}",
                          **{f"{r} (um)": f"{x:.3f}" for r, x in st["per_run"].items()}}
                         for st in v["by_step"]])  # fmt: skip
    return ["## Held out of the search", "",
            f"Never fitted, scored or localised during the search; scored once here, by the base and by the model "
            f"after each named term, each fitted on every search run: RMSE {v['rmse_base_um']:.3f} -> {v['rmse_final_um']:.3f} um "
            f"({v['x_floor_base']:.1f}x -> {v['x_floor_final']:.1f}x the noise floor).", "",
            markdown_table(rows, index=False), "", "![](holdout.png)", ""]  # fmt: skip


def terminal_verdict(d: dict, out: Path | None = None) -> str:
    lines = ["", f"== diagnosis: {d['dataset']} ==", verdict_line(d)]
    if d.get("frame"):
        lines.append(f"scored on {d['frame']}")
    lines.append(f"noise floor {d['noise_floor_um']:.3f} um ({d['noise']['method']}); "
                 f"base: {d['base_words']}{''.join(' + ' + e for e in d['base_effects'])}")  # fmt: skip
    if v := d.get("validation"):
        lines.append(f"held out of the search ({', '.join(v['runs'])}): RMSE {v['rmse_base_um']:.3f} um (base) -> "
                     f"{v['rmse_final_um']:.3f} um ({_model_name(v['effects'])})")  # fmt: skip
    for k, s in enumerate(d["steps"], 1):
        tag = " (ambiguous with " + ", ".join(s["ambiguous_with"]) + ")" if s["ambiguous_with"] else ""
        tag += "" if s["confirmed"] else " (not confirmed)"
        shrink = 1 - s["heldout_rmse_after_um"] / s["heldout_rmse_before_um"]
        if w := described(s):
            tag += f": {w}"
        lines.append(f"  step {k}: {_name(s)}{tag}: held-out RMSE {s['heldout_rmse_before_um']:.3f} -> "
                     f"{s['heldout_rmse_after_um']:.3f} um ({shrink:.0%} less), BIC gain {s['bic_gain']:.1f}")  # fmt: skip
    lines.append(f"where (before): {d['localisation']['before']['summary']}")
    lines.append(f"where (after):  {d['localisation']['after']['summary']}")
    if not d["gap"]["within_floor"]:
        b = d["gap"]["best_candidate"]
        if b is not None:
            lines.append(f"best remaining candidate: {b['effect']} explains {b['explains_um']:.3f} um, leaves "
                         f"{b['remains_x_floor']:.1f}x the floor")  # fmt: skip
        for h in d["gap"]["more_data"]:
            lines.append(f"to tell more: {h}")
    for e, why in d["skipped"].items():
        lines.append(f"skipped {e}: {why}")
    if out is not None:
        lines.append(f"report: {out / 'report.md'}  ({d['runtime_s']:.0f} s)")
    return "\n".join(lines)
