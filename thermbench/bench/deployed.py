"""A fitted model as the compensator runs it, scored so; and the faults planted to test it.

:func:`deployed_predictions`: the process log through the sensor checks of
:mod:`thermbench.bench.faults` (a faulty sensor read as the other sensors predict it, or the family
refitted without it, :func:`without_sensors`), the model on that log, its answer bounded in value
and rate. :func:`deployed_rows` scores a benchmark fold's fit so, beside its raw score
(approach :data:`DEPLOYED_APPROACH`), as the export runs it: a faulty sensor read as the others
predict it (the refit without it, ``fallback``, is measured by ``benchmarks/bench_faults.py
--fallback refit``, not exported). :func:`plant_fault` puts one of four faults into one sensor
of one run (a jump, a drift, a stuck reading, an open circuit).
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from .faults import Bounds, FaultMonitor, SensorLimits, fault_summary

__all__ = ["DEPLOYED_APPROACH", "FAULT_KINDS", "deployed_predictions", "deployed_rows", "plant_fault", "without_sensors"]

#: the benchmark's approach of a family's fold fit scored as deployed (:func:`deployed_rows`)
DEPLOYED_APPROACH = "as_deployed"
#: the faults :func:`plant_fault` plants
FAULT_KINDS = ("jump", "drift", "stuck", "open")


def deployed_predictions(model, ds, run: str, limits: SensorLimits | None, bounds: Bounds | None, fallback=None,
                         errors=None):  # fmt: skip
    """A fitted ``model``'s predictions on ``run`` as the compensator makes them: the process log
    through a :class:`FaultMonitor` (a faulty sensor replaced from the sample it is judged faulty),
    the model on that log, the answer bounded by ``bounds``. ``fallback(faulty)`` (optional): the
    model to switch to once the sensors ``faulty`` (a tuple) are judged faulty, fitted without them
    (:func:`without_sensors`), or None where there is none: then the model reads the replaced
    readings. ``errors``: the dataset's :func:`~thermbench.data.reference.thermal_errors`, when the
    caller has them already (else computed here). Returns (predictions at the run's readings, the
    monitor after the run, per reading whether a bound acted)."""
    from ..data.reference import thermal_errors

    monitor = None
    view = ds
    te = thermal_errors(ds) if errors is None else errors
    tr = te[te["run_id"] == run].reset_index(drop=True)
    if limits is not None and limits.sensors:
        pr = ds.process_run(run)
        cols = [ds.metadata.sensor_column(s) for s in limits.sensors]
        used, monitor = FaultMonitor.run(limits, pr["t_s"].to_numpy(dtype=float), pr[cols].to_numpy(dtype=float))
        if monitor.faulty:
            process = ds.process.copy()
            rows = (process["run_id"] == run).to_numpy()
            process.loc[rows, cols] = used
            view = replace(ds, process=process)
    pred = np.asarray(model.predict(view, run), dtype=float)
    if monitor is not None and monitor.faulty and fallback is not None:
        # from each onset on, the model fitted without every sensor judged faulty by then
        t_read = tr["t_s"].to_numpy(dtype=float)
        onsets = sorted({float(o) for o in monitor.onset_s if np.isfinite(o)})
        for k, onset in enumerate(onsets):
            faulty = tuple(s for s, o in zip(limits.sensors, monitor.onset_s) if np.isfinite(o) and o <= onset)
            alt = fallback(faulty)
            if alt is None:
                continue
            end = onsets[k + 1] if k + 1 < len(onsets) else np.inf
            span = (t_read >= onset) & (t_read < end)
            if span.any():
                pred[span] = np.asarray(alt.predict(view, run), dtype=float)[span]
    acted = np.zeros(pred.size, dtype=bool)
    if bounds is not None:  # in time, per measuring position (the value at one target follows its previous one)
        keys = [c for c in ("channel", "target_mm", "direction") if c in tr.columns]
        groups = tr.groupby(keys, sort=False, dropna=False).indices.values() if keys else [np.arange(len(tr))]
        t = tr["t_s"].to_numpy(dtype=float)
        for idx in groups:
            idx = np.asarray(idx)[np.argsort(t[idx], kind="stable")]
            pred[idx], acted[idx] = bounds.apply(t[idx], pred[idx])
    return pred, monitor, acted


def without_sensors(model, ds, runs: Sequence[str], drop: Sequence[str]):
    """``model``'s family fitted on ``runs`` without the sensors ``drop``: a clone whose ``sensors``
    are those the fitted model reads (or its own list) but ``drop``; None when the family has no list
    of ``sensors`` to set (none, or a rule such as ``auto``), when it reads none of ``drop``, or when
    nothing is left."""
    from sklearn.base import clone

    mine = model.get_params(deep=False).get("sensors", "absent")
    if not (mine is None or isinstance(mine, (list, tuple))):  # no such parameter, or a rule ('auto', 'all')
        return None
    reads = list(model.required_inputs().sensors)  # what the fitted model reads, whatever None means to it
    keep = [s for s in (reads if mine is None else list(mine)) if s not in set(drop)]
    if not keep or keep == reads:
        return None
    return clone(model).set_params(sensors=keep).fit(ds, list(runs))


def plant_fault(ds, run: str, sensor: str, kind: str, onset_s: float, *, jump_K: float = 30.0,
                drift_K_h: float = 10.0, open_C: float = 850.0):  # fmt: skip
    """A copy of ``ds`` with one fault in sensor ``sensor`` of run ``run`` from ``onset_s`` on (the
    other runs and sensors as they are): ``jump`` (+``jump_K``), ``drift`` (+``drift_K_h`` per hour
    since the onset), ``stuck`` (the reading at the onset held) or ``open`` (``open_C``, a PT100
    transmitter's over-range)."""
    if kind not in FAULT_KINDS:
        raise ValueError(f"fault kind {kind!r}: expected one of {list(FAULT_KINDS)}")
    if sensor not in ds.metadata.sensors:
        raise ValueError(f"sensor {sensor!r} is not a sensor of the dataset; it has {list(ds.metadata.sensors)}")
    col = ds.metadata.sensor_column(sensor)
    process = ds.process.copy()
    process[col] = process[col].astype(float)
    rows = (process["run_id"] == run).to_numpy()
    if not rows.any():
        raise ValueError(f"run {run!r} has no process log; runs: {list(ds.run_ids)}")
    t = process.loc[rows, "t_s"].to_numpy(dtype=float)
    v = process.loc[rows, col].to_numpy(dtype=float)
    after = t >= onset_s
    if not after.any():
        raise ValueError(f"onset {onset_s} s is after the last sample of run {run!r} ({t[-1]} s)")
    if kind == "jump":
        v = np.where(after, v + jump_K, v)
    elif kind == "drift":
        v = np.where(after, v + drift_K_h * (t - onset_s) / 3600.0, v)
    elif kind == "stuck":
        v = np.where(after, v[np.argmax(after)], v)
    else:
        v = np.where(after, open_C, v)
    process.loc[rows, col] = v
    return replace(ds, process=process)


def deployed_rows(model, ds, train: Sequence[str], held_out: Sequence[str]):
    """A fitted ``model`` (fitted on ``train``) scored on each run of ``held_out`` as the exported
    compensator runs it (:func:`deployed_predictions`, as the C runtime's tb_faults and the OPC UA /
    LinuxCNC loops do): the sensor limits over the sensors the model reads and the bounds from
    ``train``; a sensor judged faulty read as the other sensors predict it. One row per run:
    ``run_id``, the :func:`~thermbench.bench.metrics.residual_metrics`, ``faults`` (each sensor
    judged faulty, its rule and time; '' for none) and ``bounded_share`` (the share of readings
    where a bound acted)."""
    import pandas as pd

    from ..data.reference import thermal_errors
    from .metrics import residual_metrics

    reads = [s for s in ds.metadata.sensors if s in set(model.required_inputs().sensors)]
    limits = SensorLimits.fit(ds, list(train), reads) if reads else None
    bounds = Bounds.fit(ds, list(train))
    te = thermal_errors(ds)
    rows = []
    for run in held_out:
        pred, monitor, acted = deployed_predictions(model, ds, run, limits, bounds, None, te)
        tr = te[te["run_id"] == run]
        bad = int(np.sum(~np.isfinite(pred)))
        metrics = (residual_metrics(tr["error_um"], pred, tr["thermal_um"]) if not bad else
                   dict.fromkeys(residual_metrics(tr["error_um"], np.zeros(len(tr)), tr["thermal_um"]), float("nan")))  # fmt: skip
        rows.append({"run_id": run, **metrics, "nonfinite_predictions": bad, "faults": fault_summary(monitor),
                     "bounded_share": float(acted.mean()) if acted.size else 0.0})  # fmt: skip
    return pd.DataFrame(rows)
