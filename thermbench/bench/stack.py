"""The stack of every family: a weighted sum of the benchmark's candidates, the weights fitted on
their out-of-run predictions, scored and chosen as one more family (``stack``).

The benchmark already predicts each training run of every outer fold from fits that never saw it
(the inner folds of the nested choice) and each held-out run from the fold's fit. So the stack
costs no fit of its own (the SuperLearner of van der Laan, Polley and Hubbard 2007, *Super
Learner*, with the benchmark's folds):

* **members**: the families that are candidates of the choice on that dataset and channel (not a
  baseline, not one the C runtime cannot run, not one worse than no compensation on its own training
  runs, not the stacked ensemble itself: the runtime does not nest ensembles) whose C kind answers
  from its latest samples (:data:`STACKABLE_KINDS`: not the physics models, not AR), the neural ones
  and the lag bank among them;
* **weights, per outer fold**: non-negative least squares of the measured error on the members'
  inner out-of-run predictions over the fold's training runs, scaled to sum to one
  (:func:`thermbench.models.ensemble.stack_weights`), at most :data:`MAX_MEMBERS` members of weight
  above 0 (the ENSEMBLE kind's limit: the smallest left out and the rest fitted again);
* **held-out score**: that weighted sum of the fold fits' predictions on the fold's held-out runs;
* **inner score**, for the nested choice: each inner held-out run predicted by weights fitted on
  the other inner runs' out-of-run predictions (the members' predictions there come from fits
  without it, so neither level saw the run it is scored on);
* **the model to deploy**: the weights of the inner folds over every run, on the members fitted on
  every run, as a :class:`~thermbench.models.ensemble.StackedEnsemble` (exported as ``ENSEMBLE``).

Its complexity is 3 (:func:`thermbench.bench.choice.model_complexity`): a weighted sum needs every
member's flexibility, and among every family the most flexible is a network (3); so the choice takes
it only where it is better than every simpler candidate by more than the scatter of its score. (The
stacked ensemble of four linear models keeps 0: its members are linear.)
"""

from __future__ import annotations

from typing import Iterable

import numpy as np
import pandas as pd

from ..export.fileformat import Kind
from ..models.ensemble import StackedEnsemble, stack_weights
from .plan import DEPLOY_FOLD, case_label

__all__ = ["MAX_MEMBERS", "STACK", "STACKABLE_KINDS", "fitted_weights", "stack_task", "stackable"]

#: the family name of the stack in results.csv, the report and the choice
STACK = "stack"
#: the most members of weight above 0 (StackedEnsemble's, and the ENSEMBLE file's, limit)
MAX_MEMBERS = 8
#: a family never stacked: the stacked ensemble (an ensemble inside an ensemble does not export)
NOT_STACKED = ("ensemble",)
#: the C runtime's kinds a stack carries: those that answer from their latest samples, as the ENSEMBLE
#: kind asks its members at once. A screw or lumped physics model steps on its own grid, an AR model on its
#: window, a bank's classifier on its windows: their readiness lags the samples, and the ensemble would
#: refuse queries each member answers alone
STACKABLE_KINDS = frozenset({Kind.MLR_CURVE, Kind.MLR_SEED001, Kind.LSSVM, Kind.MLP, Kind.GRU, Kind.THERMAL_LAG,
                             Kind.LINEAR_HISTORY})  # fmt: skip


def stackable(model) -> bool:
    """Whether the fitted ``model`` encodes to one of :data:`STACKABLE_KINDS`."""
    from ..export.encoding import ExportError, encode

    try:
        return encode(model).kind in STACKABLE_KINDS
    except ExportError:
        return False

_KEYS = ["run_id", "row"]


def fitted_weights(P: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, str]:
    """Non-negative weights of the columns of ``P`` summing to one (:func:`stack_weights`), with at
    most :data:`MAX_MEMBERS` above 0: while more are, the column of smallest weight leaves and the
    rest are fitted again."""
    cols = np.arange(P.shape[1])
    while True:
        w, how = stack_weights(P[:, cols], y)
        if np.count_nonzero(w) <= MAX_MEMBERS:
            out = np.zeros(P.shape[1])
            out[cols] = w
            return out, how
        cols = np.delete(cols, int(np.argmin(np.where(w > 0, w, np.inf))))


def _aligned(frames: dict[str, pd.DataFrame], extra: Iterable[str] = ()) -> tuple[pd.DataFrame, np.ndarray]:
    """The rows every family predicted (merged on run and reading) and the families' predictions
    there, one column each in the order of ``frames``."""
    names = list(frames)
    keep = [*_KEYS, "y", *extra]
    base = frames[names[0]][keep].reset_index(drop=True)
    merged = base
    for i, n in enumerate(names):
        merged = merged.merge(frames[n][_KEYS + ["pred"]].rename(columns={"pred": f"_p{i}"}), on=_KEYS, how="inner")
    return merged[keep], merged[[f"_p{i}" for i in range(len(names))]].to_numpy(dtype=float)


def _run_row(template: pd.DataFrame, y: np.ndarray, p: np.ndarray) -> dict:
    """A held-out run's row of results.csv for the stack: a member's row of that fold and run with the
    stack's residual metrics (the measured error's own figures are the member's)."""
    row = template.iloc[0].to_dict()
    r = y - p
    max_err, pv_err = float(row["max_abs_error_um"]), float(row["pv_error_um"])
    max_res = float(np.max(np.abs(r)))
    row.update({"rmse_um": float(np.sqrt(np.mean(r**2))), "max_abs_residual_um": max_res, "pv_residual_um": float(np.ptp(r)),
                "compensation_rate": 1.0 - max_res / max_err if max_err > 0 else np.nan,
                "residual_fraction_of_pv": max_res / pv_err if pv_err > 0 else np.nan, "nonfinite_predictions": 0,
                "fit_s": 0.0, "family": STACK})  # fmt: skip
    for c in [k for k in row if str(k).startswith("coverage_")] + ["half_width_um", "faults", "bounded_share"]:
        if c in row:  # a member's interval and as-deployed figures: not the stack's
            row[c] = np.nan
    return row


def _held_out_rows(members: list[dict], outer: dict[str, pd.DataFrame], fold: str, w: np.ndarray) -> list[dict] | None:
    """The stack's rows of results.csv on the held-out runs of ``fold`` (weights ``w``), or None when a
    member has no prediction there (its fold fit failed) or a held-out run has no member row."""
    if any(df.empty or not (df["fold"] == fold).any() for df in outer.values()):
        return None
    held_rows, Q = _aligned({n: df[df["fold"] == fold] for n, df in outer.items()})
    p = Q @ w
    res = members[0]["results"]
    rows = []
    for run, idx in held_rows.groupby("run_id", sort=False).indices.items():
        template = res[(res["approach"] == "global") & (res["kind"] == "validation") & (res["fold"] == fold)
                       & (res["run_id"] == run)]  # fmt: skip
        if template.empty:
            return None
        mine = [m["results"] for m, wi in zip(members, w) if wi > 0]  # what the weighted members' fold fits read
        sensors = [s for r in mine for v in r.loc[(r["fold"] == fold) & (r["run_id"] == run) & (r["approach"] == "global")
                                                   & (r["kind"] == "validation"), "sensors"].astype(str).head(1)
                   for s in v.split()] if all("sensors" in r for r in mine) else []  # fmt: skip
        rows.append(_run_row(template, held_rows["y"].to_numpy()[idx], p[idx]) | {"sensors": " ".join(dict.fromkeys(sensors))})
    return rows


def stack_task(tasks: list[dict], never: set[tuple[str, str, str]]) -> list[dict]:
    """Per dataset and channel with two candidate families or more, the stack as one more task output
    of :func:`thermbench.bench.run.run_task` (``results``, ``inner``, ``models``: what the choice, the
    report and the export read of any family). ``never``: (case, family, approach) that are no
    candidate (the C runtime cannot run them, or flagged)."""
    out = []
    cases: dict[tuple[str, str], list[dict]] = {}
    for o in tasks:
        cases.setdefault((o["dataset"], o.get("channel", "all")), []).append(o)
    for (dataset, channel), group in cases.items():
        case = case_label(dataset, channel)
        members = [o for o in group if o["family"] not in NOT_STACKED and "global" in o["models"]
                   and not o.get("stack_inner", pd.DataFrame()).empty and (case, o["family"], "global") not in never
                   and stackable(o["models"]["global"])]  # fmt: skip
        if len(members) < 2:
            continue
        names = [o["family"] for o in members]
        inner = {o["family"]: o["stack_inner"] for o in members}
        outer = {o["family"]: o.get("stack_outer", pd.DataFrame()) for o in members}
        folds = sorted(set.intersection(*[set(df["fold"]) for df in inner.values()]))
        rows, inner_rows, deploy = [], [], None
        for fold in folds:
            rows_f, P = _aligned({n: df[df["fold"] == fold] for n, df in inner.items()}, extra=["inner_fold"])
            y = rows_f["y"].to_numpy()
            w, how = fitted_weights(P, y)
            if fold == DEPLOY_FOLD:
                deploy = (w, how, float(np.sqrt(np.mean((y - P @ w) ** 2))))
            else:  # a held-out score on every held-out run of the fold, or none (and no inner score: never chosen there)
                held = _held_out_rows(members, outer, fold, w)
                if held is None:
                    continue
                rows += held
            for g in rows_f["inner_fold"].unique():  # each inner held-out run by weights of the others
                on = (rows_f["inner_fold"] == g).to_numpy()
                wg, _ = fitted_weights(P[~on], y[~on])
                sq = pd.Series((y[on] - P[on] @ wg) ** 2).groupby(rows_f.loc[on, "run_id"].to_numpy(), sort=False).mean()
                inner_rows.append(pd.DataFrame({"run_id": sq.index, "rmse_um": np.sqrt(sq.to_numpy())}).assign(
                    dataset=dataset, channel=channel, family=STACK, fold=fold, approach="global", inner_fold=g))  # fmt: skip
        models = {}
        if deploy is not None:
            w, how, cv = deploy
            keep = [i for i in range(len(names)) if w[i] > 0]
            models["global"] = StackedEnsemble.of_fitted([names[i] for i in keep], [members[i]["models"]["global"] for i in keep],
                                                         w[keep], f"{how} on the benchmark's out-of-run predictions", cv)  # fmt: skip
        out.append({"dataset": dataset, "channel": channel, "family": STACK,
                    "results": pd.DataFrame(rows), "curves": pd.DataFrame(), "models": models,
                    "dataset_hash": group[0].get("dataset_hash"), "frame": group[0].get("frame"), "cv": group[0].get("cv"),
                    "inner": pd.concat(inner_rows, ignore_index=True) if inner_rows else pd.DataFrame(),
                    "seconds": 0.0, "errors": [], "failed": []})  # fmt: skip
    return out
