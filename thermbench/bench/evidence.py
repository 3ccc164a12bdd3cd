"""What limits a held-out score: per dataset and channel, thermbench's nested choice against the best
baseline (their ratio of median held-out RMSE), and the evidence the data hold of what keeps the
held-out error where it is:

* **outside the training range**: the share of a fold's held-out readings where some model input
  (a temperature rise above its run's first reading, or an operating signal such as spindle speed)
  lies outside the range it spans over the fold's training runs, and the input furthest out. A
  regression fitted there extrapolates; no family is promised to do that well.
* **the error's short-term scatter**: an upper estimate of the measurement noise of the held-out
  runs, from second differences of the error at each target in time order (robust: 1.4826 × the
  median absolute deviation, / √6, which is σ for white noise on a drift that is locally linear).
  No model's RMSE goes below the noise; when the best baseline is already within
  :data:`NOISE_MARGIN` of it, what is left is mostly measurement noise.
* **harder than the training runs are for each other**: the choice's median inner cross-validation
  RMSE (runs of the training set held out) against its held-out RMSE; a large gap says the
  held-out runs differ from the training runs more than those differ from each other.

Plain functions over the loaded datasets and the benchmark's tables; nothing here fits a model.
"""

from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np
import pandas as pd

#: the best baseline within this factor of the error's scatter: what is left is mostly noise
NOISE_MARGIN = 1.25
#: a gap between held-out and inner cross-validation RMSE above this factor is named
GAP_FACTOR = 1.5


def _inputs_by_run(ds, runs: Sequence[str]) -> dict[str, pd.DataFrame]:
    """Per run: its model inputs over the span it is scored on (its first to its last error
    reading; a run without readings: its whole log), the sensor rises above the first reading of
    its log (°C; a segment that keeps its history counts from the test's start, as the models
    do) and the operating signals the dataset declares (their own units)."""
    sensors = list(ds.sensor_columns)
    operating = [c for c in ds.metadata.operating_inputs() if c in ds.process.columns]
    out = {}
    for r in runs:
        pr = ds.process_run(r)
        temps = pr[sensors].astype(float)
        rises = temps - temps.iloc[0] if len(temps) else temps
        frame = pd.concat([rises.add_suffix(" rise"), pr[operating].astype(float)], axis=1)
        t_err = ds.errors.loc[ds.errors["run_id"] == r, "t_s"].to_numpy(dtype=float) if len(ds.errors) else []
        if len(t_err):
            t = pr["t_s"].to_numpy(dtype=float)
            frame = frame[(t >= t_err.min()) & (t <= t_err.max())]
        out[r] = frame
    return out


def outside_training_range(ds, train: Sequence[str], held_out: Sequence[str]) -> dict:
    """How far the held-out runs' inputs leave the range the training runs span: ``share`` of the
    held-out readings with some input outside it, and the input furthest out: ``input`` (its name,
    ``<sensor> rise`` or the operating column), ``excursion`` (how far beyond the range, in its own
    unit, signed: + above the largest training value, - below the smallest) and ``span`` (the
    training range's width)."""
    return _outside(_inputs_by_run(ds, [*train, *held_out]), train, held_out)


def _outside(frames: Mapping[str, pd.DataFrame], train: Sequence[str], held_out: Sequence[str]) -> dict:
    """:func:`outside_training_range` over the inputs of each run (:func:`_inputs_by_run`)."""
    tr = pd.concat([frames[r] for r in train], ignore_index=True)
    te = pd.concat([frames[r] for r in held_out], ignore_index=True)
    lo, hi = tr.min(), tr.max()
    above, below = (te - hi).clip(lower=0), (lo - te).clip(lower=0)
    out = (above > 0) | (below > 0)
    res = {"share": float(out.any(axis=1).mean()) if len(te) else 0.0, "input": "", "excursion": 0.0,
           "span": 0.0}  # fmt: skip
    if out.to_numpy().any():
        excess = np.maximum(above.max(), below.max())
        # how far out, in training spans (an input constant over the training runs: infinitely, when it moved)
        rel = (excess / (hi - lo).replace(0, np.nan)).where(excess > 0, 0.0).fillna(np.inf)
        name = str(rel.idxmax())
        up = float(above[name].max()) >= float(below[name].max())
        res |= {"input": name, "excursion": float(above[name].max()) if up else -float(below[name].max()),
                "span": float(hi[name] - lo[name])}  # fmt: skip
    return res


def error_scatter_um(ds, runs: Sequence[str]) -> float:
    """The median over ``runs`` of the error's short-term scatter (µm, see the module docstring):
    at each target (and direction), the readings in time order, their second differences,
    1.4826 × their median absolute deviation / √6. NaN when no target has three readings."""
    from ..data.reference import thermal_errors

    te = thermal_errors(ds)
    te = te[te["run_id"].isin(list(runs))]
    keys = ["run_id", *[c for c in ("target_mm", "direction") if c in te.columns]]
    per_run = {}
    for key, g in te.sort_values("t_s", kind="stable").groupby(keys, sort=False):
        d2 = np.diff(g["thermal_um"].to_numpy(dtype=float), 2)
        if d2.size:
            per_run.setdefault(key[0] if isinstance(key, tuple) else key, []).append(d2)
    if not per_run:
        return float("nan")
    scatter = [1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(6.0)
               for d in (np.concatenate(v) for v in per_run.values())]  # fmt: skip
    return float(np.median(scatter))


def held_out_limits(summary: pd.DataFrame, cases: Mapping[str, tuple], nested: pd.DataFrame) -> pd.DataFrame:
    """One row per case of ``summary`` (:func:`thermbench.bench.choice.held_out_summary`) that has a
    choice and a best baseline: the choice's median held-out RMSE, its ratio to the best baseline's,
    and the evidence of the module docstring. ``cases``: case -> (the dataset as the models saw it, its
    outer folds, :func:`thermbench.bench.splits.outer_folds`); ``nested``: the nested choice per fold with
    its ``inner_median_rmse_um``. ``verdict``: one line a reader can act on."""
    rows = []
    for s in summary.to_dict("records"):
        case = s["case"]
        if case not in cases or pd.isna(s.get("chosen_median_rmse_um")) or pd.isna(s.get("baseline_median_rmse_um")):
            continue
        ds, folds = cases[case]
        choice, base = float(s["chosen_median_rmse_um"]), float(s["baseline_median_rmse_um"])
        frames = _inputs_by_run(ds, list(dict.fromkeys(r for f in folds for r in (*f.train, *f.held_out))))  # once a case
        ranges = {f.name: _outside(frames, f.train, f.held_out) for f in folds if f.train and f.held_out}
        scatter = error_scatter_um(ds, sorted({r for f in folds for r in f.held_out}))
        inner = nested.loc[nested["case"] == case, "inner_median_rmse_um"] if len(nested) else pd.Series(dtype=float)
        inner_um = float(inner.median()) if len(inner) else float("nan")
        worst = max(ranges.items(), key=lambda kv: kv[1]["share"]) if ranges else None
        row = {"case": case, "choice_median_um": choice, "baseline_median_um": base, "ratio": choice / base,
               "outside_range_median": float(np.median([v["share"] for v in ranges.values()])) if ranges else 0.0,
               "outside_range_worst": worst[1]["share"] if worst else 0.0, "worst_fold": worst[0] if worst else "",
               "furthest_input": worst[1]["input"] if worst else "", "excursion": worst[1]["excursion"] if worst else 0.0,
               "scatter_um": scatter, "inner_cv_median_um": inner_um}  # fmt: skip
        row["verdict"] = _verdict(row, base)
        rows.append(row)
    return pd.DataFrame(rows)


def _verdict(row: Mapping, base_um: float) -> str:
    """The line the report and the terminal give for one case: the choice against the best baseline,
    then what limits it."""
    head = (f"choice {row['choice_median_um']:.2f} µm, {row['ratio']:.2f}× the best baseline's {base_um:.2f} µm")
    why = []
    if np.isfinite(row["scatter_um"]) and base_um <= NOISE_MARGIN * row["scatter_um"]:
        why.append(f"the best baseline is within {NOISE_MARGIN:g}× the error's short-term scatter "
                   f"({row['scatter_um']:.3g} µm): what is left is mostly measurement noise")  # fmt: skip
    if row["outside_range_worst"] > 0:
        unit = "" if not row["furthest_input"].endswith(" rise") else " °C"
        side = "above" if row["excursion"] > 0 else "below"
        why.append(f"{row['outside_range_worst']:.0%} of the readings of held-out fold {row['worst_fold']} lie outside "
                   f"the training runs' range (furthest: {row['furthest_input']}, {abs(row['excursion']):.3g}{unit} "
                   f"{side} it): the models extrapolate there")  # fmt: skip
    if np.isfinite(row["inner_cv_median_um"]) and row["choice_median_um"] > GAP_FACTOR * row["inner_cv_median_um"]:
        why.append(f"the held-out runs are harder than the training runs are for each other (inner cross-validation "
                   f"median {row['inner_cv_median_um']:.2f} µm, held out {row['choice_median_um']:.2f} µm)")  # fmt: skip
    if not why and row["ratio"] > 1:
        why.append(f"no limit found in the data (the error's scatter {row['scatter_um']:.3g} µm is far below the "
                   "baseline, the held-out inputs lie within the training range): the families fall short")  # fmt: skip
    return "; ".join([head, *why])
