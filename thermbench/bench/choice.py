"""The one selection rule: among the candidates (global and bank models the C runtime can run, never a
baseline, never a flagged model), the simplest within one standard error of the lowest mean inner RMSE
over whole held-out runs (:func:`nested_choice`), per outer fold and for the model to deploy
(:func:`deployed_choice`); and what the held-out runs say of that choice (:func:`held_out_summary`,
:func:`held_out_table`, :func:`held_out_flags`).
"""

from __future__ import annotations

from typing import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..errors import ExperimentError
from ..experiment import model_flags
from .calibration import probe_rows
from .deployed import DEPLOYED_APPROACH
from .plan import DEPLOY_FOLD, case_label, family_class


#: a held-out RMSE beats another when lower by more than this fraction of it: two implementations of one
#: model (ridge_history and baseline_ridge) differ by rounding, 1e-12 µm, which is a tie, not a win
TIE_REL = 1e-6


def beats(a, b):
    """Where RMSE ``a`` is lower than ``b`` by more than :data:`TIE_REL` of ``b`` (elementwise)."""
    return np.asarray(a, dtype=float) < np.asarray(b, dtype=float) * (1.0 - TIE_REL)


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
    v = results[_held_out_rows(results)]
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
    from ..errors import MissingExtra
    from .stack import STACK

    if family == STACK:  # it needs every member's flexibility: as flexible as its most flexible, a network
        return 3
    try:
        base = int(getattr(family_class(family), "complexity", 3))
    except (MissingExtra, ExperimentError, KeyError):
        base = 3
    return base + (1 if str(approach).startswith("bank") else 0)


def nested_choice(inner: pd.DataFrame, blocked: Iterable[tuple[str, str, str]] = ()) -> pd.DataFrame:
    """Per dataset, channel and outer fold, the (family, approach) thermbench would deploy, chosen
    without seeing the fold's held-out runs, on the RMSE of each inner held-out run
    (:func:`thermbench.bench.splits.inner_folds`, on the fold's training runs only).

    The rule resists its own noise: with a few runs, the lowest of ten noisy inner scores
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


def _held_out_rows(r: pd.DataFrame) -> pd.Series:
    """The rows a model is compared and chosen on: validation rows of the approaches that fit a
    model (not ``single``, not the probe replays, not the fold fits scored as deployed: those are
    reported beside the model they replay)."""
    return (r["kind"] == "validation") & (r["approach"] != "single") & ~probe_rows(r) & (r["approach"] != DEPLOYED_APPROACH)


def _deployed_per_fold(r: pd.DataFrame) -> pd.DataFrame:
    """The fold fits scored as deployed (bench/deployed.py), per (case, family, fold): the mean RMSE over
    the fold's held-out runs, and the runs on which a sensor was judged faulty (``run: faults``)."""
    v = r[(r["kind"] == "validation") & (r["approach"] == DEPLOYED_APPROACH)]
    if v.empty:
        return pd.DataFrame(columns=["case", "family", "fold", "deployed_rmse_um", "faults"])
    faults = v["faults"].fillna("").astype(str) if "faults" in v else pd.Series("", index=v.index)
    v = v.assign(_f=[f"{run}: {f}" if f else "" for run, f in zip(v["run_id"], faults)])
    return v.groupby(["case", "family", "fold"], sort=False).agg(
        deployed_rmse_um=("rmse_um", "mean"), faults=("_f", lambda x: "; ".join(f for f in x if f))).reset_index()  # fmt: skip


def _held_out_per_fold(results: pd.DataFrame) -> tuple[pd.DataFrame, bool]:
    """The held-out scores per (case, family, approach, fold): the mean over the fold's held-out runs of
    ``rmse_um`` and ``rms_error_um``, and with intervals (a ``coverage_<level>`` column) of ``coverage`` and
    ``half_width_um``; and whether there are intervals. The rows :func:`held_out_summary` and
    :func:`held_out_table` are made of (validation rows, not ``single``, not the probe approaches)."""
    r = _with_case(results)
    v = r[_held_out_rows(r)]
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
    (``chosen_coverage``, ``chosen_half_width_um``; NaN where the chosen approach has no interval); and
    the choice as deployed, each fold's choice scored with the sensor checks, the reconstruction of
    a faulty sensor and the bounds of the compensator (``chosen_deployed_median_rmse_um``, ``chosen_deployed_worst_rmse_um``,
    ``chosen_faults``: the held-out runs on which a sensor was judged faulty; absent where a fold's
    choice has no such score, a bank)."""
    per_fold, interval = _held_out_per_fold(results)
    deployed = _deployed_per_fold(_with_case(results))
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
                    "beat_no_compensation": f"{int(beats(c, none.reindex(c.index)).sum())}/{len(c)}"}  # fmt: skip
            if interval:  # the choice's interval over its held-out runs: the mean of each fold's coverage and half-width
                row |= {"chosen_coverage": float(chosen["coverage"].mean()),
                        "chosen_half_width_um": float(chosen["half_width_um"].mean())}  # fmt: skip
            dep = deployed[deployed["case"] == case].merge(chosen.loc[chosen["approach"] == "global", ["fold", "family"]],
                                                          on=["fold", "family"])  # fmt: skip
            if len(dep) == len(chosen):  # every fold's choice scored as deployed
                d = dep.set_index("fold")["deployed_rmse_um"]
                row |= {"chosen_deployed_median_rmse_um": float(d.median(skipna=False)),  # a fold with no score: NaN
                        "chosen_deployed_worst_rmse_um": float(d.max(skipna=False)),
                        "chosen_faults": "; ".join(f for f in dep["faults"] if f)}  # fmt: skip
        if not base.empty:
            med = base.groupby(["family", "approach"])["rmse_um"].median().sort_values()
            fam, app = med.index[0]
            b = base[(base["family"] == fam) & (base["approach"] == app)].set_index("fold")["rmse_um"]
            row |= {"best_baseline": f"{fam} ({app})", "baseline_median_rmse_um": float(b.median()),
                    "baseline_worst_rmse_um": float(b.max())}  # fmt: skip
            if not chosen.empty:
                common = c.index.intersection(b.index)
                row["beat_best_baseline"] = f"{int(beats(c[common], b[common]).sum())}/{len(common)}"
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
                    "beat_no_compensation": f"{int(beats(scores, none.reindex(scores.index)).sum())}/{len(scores)}",
                    "beat_best_baseline": "-" if best is None or is_best else
                    f"{int(beats(scores[common], best[2][common]).sum())}/{len(common)}"} | means  # fmt: skip

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
    v = r[_held_out_rows(r)]
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