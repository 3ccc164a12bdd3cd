"""Planted sensor faults on a dataset's held-out runs: detected when, and the correction as deployed against the raw model's.

Each run is held out in turn; a family is fitted on the others, with the sensor limits and the
correction bounds of those runs (thermbench/bench/faults.py). Into the held-out run, one fault at a
time is planted in one sensor from ``--onset`` of the run's duration on: a 30 K jump, a 10 K/h drift,
the reading stuck, the reading open-circuit (850 °C); in every sensor the model reads in turn. Printed per fault:
how many cases (run x sensor), detected in how many and how long after the first sample that carries
the fault (median, worst),
the held-out RMSE raw / as deployed / with no compensation (median, worst over the cases), and on
how many cases as deployed is worse than no compensation (and how many of those on runs where the
model as deployed, without the fault, beats no compensation). And the clean runs: the largest change of
the held-out RMSE as deployed against the raw model's.

``--off-after S [S ...]`` asks what detection delay a slow fault leaves room for: for the drifts and the
stuck readings on runs where the clean model as deployed beats no compensation, the raw model's
correction with the fault up to ``S`` seconds after the onset and no correction from then on (as
bounded), and the share of those cases no worse than no compensation, per delay; beside it, per
sensor, the largest departure of its rise (K) and of its rate (K/h) from the others' prediction on
a training run held out of the lines (the tolerance over ``OTHERS_FACTOR``: what a clean run
shows), smallest / largest over the folds.

    .venv/bin/python benchmarks/bench_faults.py DATASET_DIR [--family ridge_history] [--channel C] [--onset 0.33]
        [--off-after 0 300 600 1200 1800 3600]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("dataset", help="a dataset directory (thermbench import ... --out DIR)")
    ap.add_argument("--family", default="ridge_history", help="a conf/model option (default ridge_history)")
    ap.add_argument("--channel", default=None, help="the error channel (default: the only one)")
    ap.add_argument("--fallback", choices=["refit", "reconstruct"], default="reconstruct",
                    help="reconstruct (what the export runs, in Python and in the C runtime): the faulty sensor read as "
                         "the others predict it; refit (measured, not exported): switch to the family fitted without "
                         "the faulty sensor where it can drop one (else the readings reconstructed)")
    ap.add_argument("--onset", type=float, default=1 / 3, help="the fault's onset, as a fraction of the run (default 1/3)")
    ap.add_argument("--off-after", type=float, nargs="+", default=None, metavar="S",
                    help="delays (s): the drifts and stuck readings with no correction from S after the onset on")
    a = ap.parse_args(argv)
    if a.off_after is not None and any(d < 0 for d in a.off_after):
        ap.error("--off-after: delays are seconds after the onset, >= 0")
    if not Path(a.dataset).is_dir():
        ap.error(f"{a.dataset}: no such dataset directory")
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from thermbench.bench.deployed import FAULT_KINDS, deployed_predictions, plant_fault, without_sensors
    from thermbench.bench.faults import OTHERS_FACTOR, Bounds, SensorLimits, fault_summary
    from thermbench.bench.metrics import residual_metrics
    from thermbench.config import config_dir
    from thermbench.data.io import load_dataset
    from thermbench.data.reference import thermal_errors

    warnings.filterwarnings("ignore")
    ds = load_dataset(a.dataset)
    chans = sorted(ds.metadata.error_channels()) if ds.metadata.version != 1 else ["all"]
    channel = a.channel or (chans[0] if len(chans) == 1 else None)
    if channel is None:
        ap.error(f"--channel: the dataset has channels {chans}; name one")
    v = ds if channel == "all" else ds.channel_view(channel)
    option = Path(config_dir()) / "model" / f"{a.family}.yaml"
    if not option.is_file():
        ap.error(f"--family {a.family}: no conf/model/{a.family}.yaml")
    cfg = OmegaConf.load(option)
    sensors = list(v.metadata.sensors)
    te = thermal_errors(v)

    def rmse(run, pred):
        tr = te[te["run_id"] == run]
        return residual_metrics(tr["error_um"], pred, tr["thermal_um"])["rmse_um"]

    cases, clean, offs, noise = [], [], [], []
    t0 = time.perf_counter()
    for run in v.run_ids:
        train = [r for r in v.run_ids if r != run]
        model = instantiate(cfg).fit(v, train)
        limits = SensorLimits.fit(v, train, [s for s in sensors if s in set(model.required_inputs().sensors)])
        bounds = Bounds.fit(v, train)
        noise.append(pd.DataFrame({"sensor": limits.sensors, "rise_K": limits.tol_K / OTHERS_FACTOR,
                                   "rate_K_h": limits.rate_tol / OTHERS_FACTOR}))  # fmt: skip
        cache = {}

        def fallback(faulty, model=model, train=train, cache=cache):
            if a.fallback != "refit":
                return None
            if faulty not in cache:
                cache[faulty] = without_sensors(model, v, train, faulty)
            return cache[faulty]

        tr = te[te["run_id"] == run]
        none = float(np.sqrt(np.mean(tr["error_um"].to_numpy() ** 2)))
        raw = rmse(run, model.predict(v, run))
        dep, mon, acted = deployed_predictions(model, v, run, limits, bounds, fallback, te)
        clean.append({"run": run, "raw": raw, "deployed": rmse(run, dep), "none": none, "false_faults": mon.faulty, "judged": fault_summary(mon),
                      "bounded": float(acted.mean())})  # fmt: skip
        t = v.process_run(run)["t_s"].to_numpy(dtype=float)
        onset = float(t[0] + a.onset * (t[-1] - t[0]))
        first = float(t[t >= onset][0])  # the first sample that carries the fault
        for kind in FAULT_KINDS:
            for s in limits.sensors:  # the sensors the model reads
                bad = plant_fault(v, run, s, kind, onset)
                with np.errstate(all="ignore"):
                    p_raw = np.asarray(model.predict(bad, run), dtype=float)
                r_raw = rmse(run, p_raw) if np.isfinite(p_raw).all() else float("inf")
                dep, mon, _ = deployed_predictions(model, bad, run, limits, bounds, fallback, te)  # a planted fault leaves the errors as they are
                if a.off_after is not None and kind in ("drift", "stuck") and clean[-1]["deployed"] < none:
                    t_read = tr["t_s"].to_numpy(dtype=float)
                    offs.append({"fault": kind, **{f"{d:g} s": rmse(run, bounds.apply(t_read, np.where(t_read >= first + d, 0.0, p_raw))[0]) <= none
                                                   for d in a.off_after}})  # fmt: skip
                i = list(limits.sensors).index(s)
                cases.append({"fault": kind, "run": run, "sensor": s, "raw": r_raw, "deployed": rmse(run, dep), "none": none,
                              "clean": clean[-1]["deployed"],
                              "detected_after_s": mon.onset_s[i] - first if mon.fault[i] else np.nan, "rule": mon.fault[i],
                              "others": [x for x in mon.faulty if x != s]})  # fmt: skip
    c = pd.DataFrame(cases)
    rows = []
    for kind, g in c.groupby("fault", sort=False):
        det = g["detected_after_s"].dropna()
        rows.append({"fault": kind, "cases": len(g), "detected": f"{len(det)}/{len(g)}",
                     "after s (median / worst)": f"{det.median():.0f} / {det.max():.0f}" if len(det) else "-",
                     "rules": ", ".join(f"{k} {n}" for k, n in g["rule"].value_counts().items()),
                     "raw µm (median / worst)": f"{g['raw'].median():.2f} / {g['raw'].max():.2f}",
                     "deployed µm": f"{g['deployed'].median():.2f} / {g['deployed'].max():.2f}",
                     "none µm": f"{g['none'].median():.2f} / {g['none'].max():.2f}",
                     "deployed worse than none": int((g["deployed"] > g["none"]).sum()),
                     "of them on runs the clean model beats none": int(((g["deployed"] > g["none"])
                                                                        & (g["clean"] < g["none"])).sum()),
                     "raw worse than none": int((g["raw"] > g["none"]).sum())})  # fmt: skip
    cl = pd.DataFrame(clean)
    change = (cl["deployed"] / cl["raw"] - 1.0).abs()
    print(f"{Path(a.dataset).name} {channel}: {a.family}, {len(v.run_ids)} runs held out in turn, {len(sensors)} sensors, "
          f"onset at {a.onset:.2f} of each run ({time.perf_counter() - t0:.0f} s)")  # fmt: skip
    print(pd.DataFrame(rows).to_markdown(index=False))
    print(f"clean runs: as deployed vs raw, largest change {100 * change.max():.2f} % (run {cl['run'][change.idxmax()]}); "
          f"a sensor judged faulty on {int((cl['false_faults'].str.len() > 0).sum())} of {len(cl)} clean runs "
          f"{sorted({s for x in cl['false_faults'] for s in x})}; a bound acted on {100 * cl['bounded'].mean():.2f} % of the readings")  # fmt: skip
    print(cl.drop(columns=["false_faults"]).round(3).to_markdown(index=False))
    if a.off_after is not None:
        o = pd.DataFrame(offs)
        print("drifts and stuck readings on runs the clean model beats none: the share no worse than none with no correction "
              "from the delay after the onset on (s):")  # fmt: skip
        print(o.groupby("fault").agg(["mean"]).droplevel(1, axis=1).assign(cases=o.groupby("fault").size()).round(3).to_markdown())
        nz = pd.concat(noise).groupby("sensor", sort=False).agg(["min", "max"]).round(2)
        nz.columns = [f"{k} {m}" for k, m in nz.columns]
        print("the largest departure of a clean held-out training run from the others' prediction, over the folds:")
        print(nz.to_markdown())
    worst = c.loc[(c["deployed"] > c["none"]) & (c["clean"] < c["none"])]
    if len(worst):
        print("as deployed worse than no compensation, on runs where the clean model as deployed beats it:")
        print(worst.to_markdown(index=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
