"""Where simulation and measurement disagree (the discrepancy workflow, step 2).

Input: one row per interferometer reading with the measured thermal error and
a model's (held-out) prediction. Each reading is placed along the screw (its
distance from the fixed end, from the identified Pf), in a thermal phase
(heating or cooling: whether the measured error at that target is growing or
shrinking in magnitude) and in its run's loading condition. A block of readings
disagrees *significantly* when sum(r^2) / floor^2 exceeds the 99.9 % quantile of
chi^2 with n degrees of freedom (under "the model is right" the residuals are
noise of RMS ``floor``) and its RMS is at least ``MATERIAL_X`` times the floor
(with hundreds of readings the chi^2 test alone flags discrepancies too small to matter).
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.stats import chi2, spearmanr

from ..data.io import Dataset

ALPHA = 1e-3  # significance level of the chi^2 test of a block
MATERIAL_X = 1.5  # and the block's RMS must reach this multiple of the floor
POSITION_BINS = ("fixed_end", "middle", "far_end")
POSITION_WORDS = {"fixed_end": "near the fixed end", "middle": "mid-travel", "far_end": "near the far end",
                  "fixed_point": "at the measured point"}  # fmt: skip
#: the driver of a run's heat in words (the per-run trend of the residual)
DRIVER_WORDS = {"feed_mm_min": "feed", "spindle_rpm": "spindle speed"}


def annotate(table: pd.DataFrame, ds: Dataset, pf_mm: float, floor_um: float) -> pd.DataFrame:
    """Add ``dist_fixed_mm``, ``position`` (third of the measured travel, from the fixed
    end), ``phase`` (heating / cooling / steady), ``feed_mm_min`` and ``load_N`` (the
    run's condition feed, mean logged load) to a residual table."""
    t = table.copy()
    t["dist_fixed_mm"] = np.abs(t["target_mm"].to_numpy() - pf_mm)
    lo, hi = t["dist_fixed_mm"].min(), t["dist_fixed_mm"].max()
    edges = np.linspace(lo, hi, 4)
    t["position"] = np.array(POSITION_BINS)[np.clip(np.searchsorted(edges, t["dist_fixed_mm"], side="right") - 1, 0, 2)]
    phase = np.full(len(t), "steady", dtype=object)
    for _, g in t.sort_values("t_s").groupby(["run_id", "target_mm"], sort=False):
        if len(g) < 2:
            continue
        sign = np.sign(g["thermal_um"].mean()) or 1.0
        mag = sign * g["thermal_um"].to_numpy()
        slope = np.gradient(mag, g["t_s"].to_numpy())  # um/s
        step_um = slope * np.median(np.diff(g["t_s"].to_numpy()))
        ph = np.where(step_um > floor_um / 2, "heating", np.where(step_um < -floor_um / 2, "cooling", "steady"))
        phase[t.index.get_indexer(g.index)] = ph
    t["phase"] = phase
    feed = {r: ds.metadata.runs[r].condition.feed_mm_min for r in t["run_id"].unique()}
    t["feed_mm_min"] = t["run_id"].map(feed)
    if "load_N" in ds.process.columns:
        load = ds.process.groupby("run_id")["load_N"].mean()
        t["load_N"] = t["run_id"].map(load)
    return t


def block_stats(t: pd.DataFrame, by: list[str], floor_um: float) -> pd.DataFrame:
    """Per block: readings, mean and RMS residual, RMS / floor and the chi^2 verdict."""
    rows = []
    for key, g in t.groupby(by, sort=True):
        r = g["residual_um"].to_numpy()
        n = r.size
        stat = float(np.sum(r**2) / floor_um**2)
        rows.append(
            {
                **dict(zip(by, key if isinstance(key, tuple) else (key,))),
                "n": n,
                "mean_um": float(r.mean()),
                "rms_um": float(np.sqrt(np.mean(r**2))),
                "rms_x_floor": float(np.sqrt(np.mean(r**2)) / floor_um),
                "significant": bool(stat > chi2.ppf(1 - ALPHA, n) and np.sqrt(np.mean(r**2)) >= MATERIAL_X * floor_um),
            }
        )
    return pd.DataFrame(rows)


def _trend(x: pd.Series, y: pd.Series) -> str | None:
    if x.nunique() < 3:
        return None
    rho = float(spearmanr(x, y).statistic)
    return "grows" if rho > 0.7 else "falls" if rho < -0.7 else "no clear trend"


def localise(t: pd.DataFrame, floor_um: float, driver: str = "feed_mm_min") -> dict:
    """Summary of where the residual of an annotated table exceeds the noise floor; ``driver``:
    the column of each run's heat driver (its feed, a spindle block's speed)."""
    t = t[t["cycle"] > 0] if "position" in t and not (t["position"] == "fixed_point").all() else t
    blocks = block_stats(t, ["run_id", "position", "phase"], floor_um)
    by_pos = block_stats(t, ["position"], floor_um).set_index("position")
    by_pos = by_pos.reindex([p for p in (*POSITION_BINS, "fixed_point") if p in by_pos.index])
    by_phase = block_stats(t[t["phase"] != "steady"], ["phase"], floor_um)
    by_phase = by_phase.set_index("phase") if len(by_phase) else by_phase
    by_run = block_stats(t, ["run_id"], floor_um).set_index("run_id")
    by_run[driver] = t.groupby("run_id")[driver].first()
    if "load_N" in t:
        by_run["load_N"] = t.groupby("run_id")["load_N"].first()
    rms_all = float(np.sqrt(np.mean(t["residual_um"] ** 2)))
    sig = blocks["significant"].to_numpy()
    frac = float(np.average(sig, weights=blocks["n"])) if len(blocks) else 0.0

    if not by_pos["significant"].any():
        where = "nowhere"
    else:
        rms = by_pos["rms_um"]
        where = str(rms.index[0]) if len(rms) == 1 else "everywhere" if rms.max() < 1.5 * rms.min() else str(rms.idxmax())
    phase = "none"
    if len(by_phase) and by_phase["significant"].any():
        rms = by_phase["rms_um"]
        phase = "both" if len(rms) == 2 and rms.max() < 1.5 * rms.min() else str(rms.idxmax())
    feeds = _trend(by_run[driver], by_run["rms_um"])
    dword = DRIVER_WORDS.get(driver, driver)
    loads = _trend(by_run["load_N"], by_run["rms_um"]) if "load_N" in by_run else None

    if where == "nowhere":
        text = f"the residual (RMS {rms_all:.2f} um) stays within the noise floor ({floor_um:.2f} um) everywhere"
    else:
        place = "over the whole travel" if where == "everywhere" else POSITION_WORDS[where]
        text = (f"the residual (RMS {rms_all:.2f} um, {rms_all / floor_um:.1f}x the noise floor) exceeds the noise "
                f"floor in {frac:.0%} of the readings, largest {place}")  # fmt: skip
        if phase != "none":
            text += ", " + (f"while {' and '.join(by_phase.index)} alike" if phase == "both" else f"mostly while {phase}")
        if feeds:
            text += f"; per-run residual {feeds} with {dword}" if feeds != "no clear trend" else f"; no clear trend with {dword}"
        if loads and loads != "no clear trend":
            text += f" and {loads} with load"
    return {
        "summary": text,
        "where": where,
        "phase": phase,
        "driver": driver,
        "driver_trend": feeds,
        "load_trend": loads,
        "rms_um": rms_all,
        "significant_fraction": frac,
        "by_position": _records(by_pos),
        "by_phase": _records(by_phase),
        "by_run": _records(by_run),
    }


def _records(df: pd.DataFrame) -> dict:
    if not len(df):
        return {}
    return {str(k): {c: (v.item() if hasattr(v, "item") else v) for c, v in row.items()} for k, row in df.iterrows()}
