"""``thermbench iso230 DATA_DIR --out DIR``: what a machine-tool metrologist takes from a
thermal test, computed from any dataset (docs/iso230.md). The statistics are in
:mod:`thermbench.iso230`; this module picks them for each channel of a dataset and writes
``report.md``, ``figures.json`` and the figures.

- Every channel: the thermal drift (reading minus the dataset's reference,
  :func:`thermbench.data.reference.thermal_errors`) over time, its maximum, per
  heating/cooling block (the derived segments of a run without a declared condition,
  else whole runs): ISO 230-3 clause 6 style for a fixed point.
- Two fixed-point channels of one direction that declare ``position_mm``: their tilt.
- Along an axis: the error line (offset, slope) of every measuring cycle and its change
  with time (ISO 230-3 clause 7 style), and with a ``direction`` column the ISO 230-2
  figures (A, E, R, M, B) of every measuring cycle and of the whole run.
- A sensor at location ``ambient``: the environmental variation figures.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pandas as pd

from . import standards as iso230
from ..data.io import Dataset, load_dataset
from ..data.reference import thermal_errors
from ..outputs import check_output_dir, output_dir


def _segmented(ds: Dataset) -> Dataset | None:
    """The dataset split into its derived segments (format 2 runs without a condition), once."""
    from ..data.views import split_segments

    if ds.metadata.version == 1 or all(r.condition is not None for r in ds.metadata.runs.values()):
        return None
    return split_segments(ds)


def _blocks(seg: Dataset | None, run: str) -> list[tuple[str, float, float]]:
    """The heating/cooling blocks of a run: its derived segments in ``seg`` (:func:`_segmented`)."""
    if seg is None:
        return []
    out = []
    for name, r in seg.metadata.runs.items():
        if not r.notes or not (r.notes.startswith("segment ") and f" of run {run}:" in r.notes):
            continue  # a run kept as it is, or a segment of another run
        pr = seg.process_run(name)
        if not pr.empty:
            out.append((name, float(pr["t_s"].iloc[0]), float(pr["t_s"].iloc[-1])))
    return out


def _readings(ds: Dataset) -> pd.DataFrame:
    """The thermal errors of every reading, with a ``channel`` column (format 1: its one channel)."""
    te = thermal_errors(ds)
    if len(te) and "channel" not in te.columns:
        te = te.assign(channel=next(iter(ds.metadata.error_channels())))
    return te


def _from_reference(t: np.ndarray, thermal: np.ndarray, a: float, b: float) -> dict:
    """The largest |thermal error| in [a, b], counted from the dataset's reference (where the
    thermal error is 0), its sign and time."""
    m = (t >= a) & (t <= b)
    k = int(np.argmax(np.abs(thermal[m])))
    return {"max_from_reference_um": float(abs(thermal[m][k])), "max_from_reference_signed_um": float(thermal[m][k]),
            "t_max_from_reference_s": float(t[m][k])}  # fmt: skip


def _cycle_temperatures(ds: Dataset, pr: pd.DataFrame, t_s: np.ndarray, cyc: np.ndarray) -> pd.DataFrame:
    """Per measuring cycle, the mean of each sensor over the cycle's time span (``<sensor>_C``):
    how the figures drift with temperature."""
    t = pr["t_s"].to_numpy()
    rows = []
    for c in np.unique(cyc):
        a, b = t_s[cyc == c].min(), t_s[cyc == c].max()
        m = (t >= a) & (t <= b)
        row = {"cycle": int(c)}
        for col in ds.sensor_columns:
            v = pr[col].to_numpy()
            row[col] = float(v[m].mean()) if m.any() else float(np.interp(a, t, v))
        rows.append(row)
    return pd.DataFrame(rows)


def _clean(v):
    if isinstance(v, dict):
        return {str(k): _clean(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_clean(x) for x in v]
    if isinstance(v, (np.floating, float)):
        return None if not math.isfinite(float(v)) else round(float(v), 4)
    if isinstance(v, np.integer):
        return int(v)
    return v


def _table_md(df: pd.DataFrame, cols: list[str]) -> str:
    show = df[cols]
    head = "| " + " | ".join(cols) + " |\n| " + " | ".join("---" for _ in cols) + " |\n"
    rows = []
    for r in show.to_dict(orient="records"):  # per row: an int column stays int
        cells = []
        for c in cols:
            v = r[c]
            if c in ("cycle", "direction") and isinstance(v, (float, np.floating)) and math.isfinite(v):
                v = int(v)
            cells.append(f"{v:.2f}" if isinstance(v, (float, np.floating)) and math.isfinite(v) else
                         ("–" if isinstance(v, (float, np.floating)) else str(v)))  # fmt: skip
        rows.append("| " + " | ".join(cells) + " |")
    return head + "\n".join(rows) + "\n"


def compute(ds: Dataset, te: pd.DataFrame | None = None) -> dict:
    """All figures of the dataset, as plain data (what ``figures.json`` holds); ``te``: its
    :func:`_readings`, when already computed."""
    from ..data.reference import frame_text

    te = _readings(ds) if te is None else te
    meta = ds.metadata
    channels = meta.error_channels()
    ambient = next((s for s, loc in meta.sensors.items() if loc == "ambient"), None)
    out: dict = {"dataset": str(ds.path), "machine": meta.machine.name, "format": meta.format,
                 "reference": meta.reference_mode().mode if meta.version == 2 else "cold_cycle",
                 "frame": frame_text(meta), "runs": {}}  # fmt: skip
    if te.empty:
        out["note"] = "the dataset has no readings: nothing to evaluate"
        return out
    seg = _segmented(ds)
    for run in ds.run_ids:
        tr = te[te["run_id"] == run]
        if tr.empty:
            continue
        blocks = _blocks(seg, run)
        res: dict = {"blocks": [b[0] for b in blocks], "channels": {}}
        pr = ds.process_run(run)
        for ch, cm in channels.items():
            g = tr[tr["channel"] == ch].sort_values("t_s", kind="stable")
            if g.empty:
                continue
            unit = "urad" if cm.unit == "urad" else "um"
            entry: dict = {"kind": cm.kind, "direction": cm.direction, "unit": unit}
            if cm.kind == "fixed_point":
                t = g["t_s"].to_numpy()
                keep = np.r_[True, np.diff(t) > 0]
                th = g["thermal_um"].to_numpy()[keep]
                used = [b for b in blocks if ((t >= b[1]) & (t <= b[2])).sum() >= 1]
                d = iso230.drift_summary(t[keep], th, used)
                # from the dataset's reference (thermal_um is 0 there), whatever the reference mode
                ref_rows = [_from_reference(t[keep], th, a, b) for _, a, b in used] + [_from_reference(t[keep], th, -np.inf, np.inf)]
                d = pd.concat([d, pd.DataFrame(ref_rows)], axis=1)
                entry["drift"] = d.to_dict(orient="records")
                if ambient is not None:  # ISO 230-3 ETVE: the machine at rest, so over the stopped samples only
                    tk = t[keep]
                    ops = [c for c in meta.operating_inputs() if c in pr.columns]
                    rest = np.ones(tk.size, dtype=bool)
                    for c in ops:  # stopped: at or below the segmentation's stop threshold (data/segments.py)
                        v = np.abs(pr[c].to_numpy())
                        given = meta.segmentation.stop_below if meta.segmentation is not None else None
                        stop = given if given is not None else 0.02 * float(np.percentile(v, 99))
                        rest &= np.interp(tk, pr["t_s"].to_numpy(), v) <= stop
                    if rest.sum() >= 2:
                        amb = np.interp(tk[rest], pr["t_s"].to_numpy(), pr[meta.sensor_column(ambient)].to_numpy())
                        ev = iso230.environmental_variation_error(tk[rest], th[rest], amb)
                        entry["environmental"] = {**ev, "at_rest_s": float(np.sum(np.diff(tk)[rest[1:] & rest[:-1]]))}
            else:
                direction = g["direction"].to_numpy() if "direction" in g.columns else None
                cyc = g["cycle"].to_numpy()  # data.reference.reading_cycles (direction-aware)
                rd = pd.DataFrame({"target_mm": g["target_mm"].to_numpy(), "cycle": cyc, "t_s": g["t_s"].to_numpy(),
                                   "deviation_um": g["thermal_um"].to_numpy()})  # fmt: skip
                lines = iso230.error_lines(rd)
                temps = _cycle_temperatures(ds, pr, g["t_s"].to_numpy(), cyc)
                entry["error_lines"] = lines.merge(temps, on="cycle", how="left").to_dict(orient="records")
                entry["max_thermal_um"] = float(np.abs(g["thermal_um"]).max())
                last = cyc == cyc.max()
                per = pd.DataFrame({"target_mm": g["target_mm"].to_numpy(),
                                    "direction": direction if direction is not None else np.ones(len(g)),
                                    "abs_um": np.abs(g["thermal_um"].to_numpy()), "thermal_um": g["thermal_um"].to_numpy(),
                                    "last": last})  # fmt: skip
                tab = per.groupby(["target_mm", "direction"]).agg(max_abs_thermal_um=("abs_um", "max")).reset_index()
                fin = per[per["last"]].groupby(["target_mm", "direction"])["thermal_um"].mean().rename("last_cycle_thermal_um")
                entry["per_target"] = tab.merge(fin.reset_index(), on=["target_mm", "direction"], how="left").to_dict(orient="records")
                # ISO 230-2 figures: bidirectional with a direction column, else those of the one direction
                pos = pd.DataFrame({"target_mm": g["target_mm"].to_numpy(),
                                    "direction": (direction if direction is not None else np.ones(len(g))).astype(int),
                                    "cycle": cyc, "deviation_um": g["error_um"].to_numpy()})  # fmt: skip
                if not pos.duplicated(["target_mm", "direction", "cycle"]).any():
                    whole = iso230.positioning_statistics(pos)
                    entry["iso230_2_run"] = whole["axis"]
                    entry["iso230_2_per_target"] = whole["per_target"].to_dict(orient="records")
                    per = iso230.positioning_statistics_by(pos, "cycle")
                    t_mean = pd.Series(g["t_s"].to_numpy()).groupby(cyc).mean()
                    per.insert(1, "t_s", per["cycle"].map(t_mean))
                    entry["iso230_2_per_cycle"] = per.merge(temps, on="cycle", how="left").to_dict(orient="records")
            res["channels"][ch] = entry
        # tilt of two fixed-point channels of one direction with declared positions
        tilts = {}
        # ordered by position along the mandrel: the tilt is (far - near) / spacing, whatever the declaration order
        fixed = sorted(((c, m) for c, m in channels.items() if m.kind == "fixed_point" and m.position_mm is not None),
                       key=lambda cm: cm[1].position_mm)  # fmt: skip
        for i, (a, ma) in enumerate(fixed):
            for b, mb in fixed[i + 1:]:
                if ma.direction != mb.direction or ma.position_mm == mb.position_mm:
                    continue
                ga = tr[tr["channel"] == a].set_index("t_s")["thermal_um"]
                gb = tr[tr["channel"] == b].set_index("t_s")["thermal_um"]
                both = ga.index.intersection(gb.index)
                if len(both) == 0:
                    continue
                tl = iso230.tilt(ga.loc[both].to_numpy(), gb.loc[both].to_numpy(), abs(mb.position_mm - ma.position_mm))
                k = int(np.argmax(np.abs(tl)))
                tilts[f"{a}-{b}"] = {"max_abs_urad": float(abs(tl[k])), "signed_urad": float(tl[k]),
                                     "t_s": float(both[k]), "spacing_mm": abs(mb.position_mm - ma.position_mm)}  # fmt: skip
        if tilts:
            res["tilt"] = tilts
        out["runs"][run] = res
    return _clean(out)


def _figures(ds: Dataset, te: pd.DataFrame, figs: dict, out: Path) -> list[str]:
    from ..report.figures import _new_figure, _save

    if te.empty:
        return []
    names = []
    for run in figs["runs"]:
        tr = te[te["run_id"] == run]
        pr = ds.process_run(run)
        fig = _new_figure(9.0, 5.0)
        ax, ax2 = fig.subplots(2, 1, sharex=True, height_ratios=[3, 1])
        for ch, g in tr.groupby("channel", sort=False):
            if "direction" in g.columns and g["direction"].notna().any():
                for dval, gd in g.groupby("direction"):
                    ax.plot(gd["t_s"] / 3600.0, gd["thermal_um"], ".", ms=3, label=f"{ch} {'↑' if dval > 0 else '↓'}")
            else:
                ax.plot(g["t_s"] / 3600.0, g["thermal_um"], lw=1.0, label=str(ch))
        ax.set_ylabel("thermal drift from the reference, µm")
        ax.legend(fontsize=7, ncols=3)
        ax.set_title(f"{ds.metadata.machine.name} · run {run}\nscored on {figs['frame']}", fontsize=9)
        ops = [c for c in ds.metadata.operating_inputs() if c in pr.columns]
        for c in ops:
            ax2.plot(pr["t_s"] / 3600.0, pr[c], lw=0.8, label=c)
        if ops:
            ax2.legend(fontsize=7)
        ax2.set_xlabel("time, h")
        name = f"drift_{run}.png"
        _save(fig, out / name)
        names.append(name)
    return names


def _hottest(df: pd.DataFrame, n: int = 2) -> list[str]:
    """The ``n`` temperature columns that rise most over the cycles (what the table shows)."""
    cols = [c for c in df.columns if c.endswith("_C")]
    rise = {c: float(df[c].max() - df[c].min()) for c in cols if df[c].notna().any()}
    return sorted(rise, key=rise.get, reverse=True)[:n]


def _report_md(figs: dict, images: list[str]) -> str:
    lines = [f"# ISO 230 evaluation: {figs['machine']}", "",
             f"Dataset `{figs['dataset']}` ({figs['format']}); thermal error counted from: {figs['reference']}. "
             "Definitions and where they differ from the standards: docs/iso230.md.", ""]  # fmt: skip
    lines += [f"Scored on: {figs['frame']} — what a model of this dataset predicts and is scored on.", ""]
    if "note" in figs:
        lines.append(figs["note"])
    for run, res in figs["runs"].items():
        lines += [f"## Run {run}", ""]
        for ch, e in res["channels"].items():
            u = "µrad" if e["unit"] == "urad" else "µm"
            if e["kind"] == "fixed_point":
                d = pd.DataFrame(e["drift"])
                lines += [f"### {ch}: fixed point, {e['direction']} ({u})", "",
                          f"Drift from the reference ({figs['reference']}; `max_from_reference_um`) and within each "
                          "block (`max_drift_um`, from the block's first sample):", "",
                          _table_md(d, ["block", "start_s", "end_s", "max_from_reference_um",
                                        "max_from_reference_signed_um", "t_max_from_reference_s",
                                        "max_drift_um", "range_um"])]  # fmt: skip
                if "environmental" in e:
                    ev = e["environmental"]
                    lines += [f"Environmental variation, over the samples with the machine at rest "
                              f"({ev['at_rest_s'] / 3600:.1f} h; the heat of earlier operation still in it): {ev['etve_um']} µm "
                              f"over an ambient range of {ev['ambient_range_C']} °C ({ev['etve_um_per_C']} µm/°C).", ""]  # fmt: skip
            else:
                el = pd.DataFrame(e["error_lines"])
                tcols = _hottest(el)
                lines += [f"### {ch}: along the axis, {e['direction']} ({u})", "",
                          f"Max |thermal error| {e['max_thermal_um']} µm. Error line of each measuring cycle "
                          "(least squares over the targets; offset at 0 mm):", "",
                          _table_md(el, ["cycle", "t_s", "offset_um", "slope_um_per_m", "offset_change_um",
                                         "slope_change_um_per_m", *tcols]),
                          "The thermal error at each target (direction 1: approached in the positive direction):", "",
                          _table_md(pd.DataFrame(e["per_target"]), ["target_mm", "direction", "max_abs_thermal_um",
                                                                     "last_cycle_thermal_um"])]  # fmt: skip
                if "iso230_2_run" in e:
                    a = e["iso230_2_run"]
                    lines += ["ISO 230-2 figures over the whole run (every cycle a repetition; thermal drift "
                              "between cycles inflates R and A; B and M need both directions):", "",
                              "| A | E | R | M | B | B mean |", "| --- | --- | --- | --- | --- | --- |",
                              f"| {a['A_um']} | {a['E_um']} | {a['R_um']} | {a['M_um']} | {a['B_um']} | {a['B_mean_um']} |",
                              "", "Per measuring cycle (one repetition: s, R and A undefined):", "",
                              _table_md(pd.DataFrame(e["iso230_2_per_cycle"]), ["cycle", "t_s", "E_um", "M_um", "B_um",
                                                                                "B_mean_um", *tcols])]  # fmt: skip
        for pair, tl in res.get("tilt", {}).items():
            lines.append(f"Tilt {pair}: max |{tl['max_abs_urad']}| µrad at {tl['t_s']} s "
                         f"(sensors {tl['spacing_mm']} mm apart).")  # fmt: skip
        lines.append("")
    lines += [f"![{img}]({img})" for img in images]
    return "\n".join(lines) + "\n"


def iso230_report(data_dir: str | Path, out_dir: str | Path, force: bool = False) -> dict:
    """Evaluate ``data_dir`` and write ``out_dir`` (``report.md``, ``figures.json``, one
    figure per run): one output of kind ``iso230`` (:mod:`thermbench.outputs`)."""
    out = Path(out_dir)
    check_output_dir(out, "iso230", force=force)
    ds = load_dataset(data_dir)
    te = _readings(ds)
    figs = compute(ds, te)
    with output_dir(out, "iso230", force=force) as tmp:
        images = _figures(ds, te, figs, tmp)
        (tmp / "figures.json").write_text(json.dumps(figs, indent=1, ensure_ascii=False), encoding="utf-8")
        (tmp / "report.md").write_text(_report_md(figs, images), encoding="utf-8")
    return figs
