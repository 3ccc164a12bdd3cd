"""What an outer fold's intervals and probe replays are made of: the inner folds' residuals and their
distance to the training envelope (:mod:`thermbench.bench.intervals`), the conformal interval of the
fold's held-out runs, and the probe approaches replayed on them (:mod:`thermbench.bench.adapt`).
"""

from __future__ import annotations

from typing import Any, Mapping

import numpy as np
import pandas as pd

from ..models.base import ModelError


def calibrate_fold(ds, fold, inner, fitted, X: pd.DataFrame, inner_residual_um: np.ndarray) -> dict[str, Any]:
    """What one outer fold's intervals and probe replays are made of. ``X``: the inner held-out
    readings as :func:`~thermbench.bench.splits.run_rows` gives them, ``inner_residual_um`` each one's
    residual from a fit without its run; ``fitted``: the fold's fit on all its training runs.
    Returns ``calibration``: per inner held-out run (t_s, residual_um, distance to the envelope
    of its inner fold's training runs), and ``held``: per run the fold holds out (t_s, measured,
    thermal, predicted by ``fitted``, distance to the envelope of the fold's training runs)."""
    from ..data.reference import thermal_errors
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
    """The conformal interval of one outer fold (:mod:`thermbench.bench.intervals`; ``cal`` from
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
    """The probe approaches of one outer fold (:func:`thermbench.bench.adapt.probe_replays`): each held-out
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
    """The GP-refit peer (:func:`thermbench.bench.adapt.gp_refit`) of one outer fold of the ``gp`` family:
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


def probe_approach(approach: str) -> bool:
    """True for an approach scored with probe readings of the run it scores (``adaptive-...``,
    ``naive_probe-...``): never compared with the open-loop approaches for a choice."""
    return str(approach).startswith(PROBE_PREFIXES)


#: the row names of the probe approaches begin so (thermbench.bench.adapt.probe_replays)
PROBE_PREFIXES = ("adaptive-", "naive_probe-", "gp_refit-")


def probe_rows(results: pd.DataFrame) -> pd.Series:
    """Which rows of ``results`` are of a :func:`probe_approach` (a boolean Series)."""
    return results["approach"].astype(str).str.startswith(PROBE_PREFIXES).astype(bool)