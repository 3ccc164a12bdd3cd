"""The robustness report's figures, matplotlib only: heatmaps of the train × test matrices, the
comparison of approaches, before / after curves, RMSE bars per channel and the probe curves. Each is a
module-level function of plain data and its path (so :class:`_Drawing` can draw them in other
processes); bare ``Figure`` objects, no pyplot state.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from ..bench.results import ALL_CHANNELS, CHANNEL
from .tables import _family_label, _unique
from .text import fmt_rate, fmt_um


RATE_CLIP = 1.0  # heatmap colours span [-100 %, 100 %]; the printed numbers are the true values


def _slug(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "-", str(s)).strip("-") or "x"


def _new_figure(width_in: float, height_in: float):
    # A bare Figure (no pyplot): nothing registered globally, so nothing to close,
    # and the caller's matplotlib backend is left alone; savefig renders with Agg.
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), layout="constrained")


def _save(fig, path: Path) -> Path:
    fig.savefig(path, format="png", dpi=110)
    fig.clear()
    return path


class _Drawing:
    """The report's figures, collected while its text is written and drawn at the end:
    in this process, or in ``n_jobs`` processes (joblib; each figure is a module-level
    function of plain data and its path, so it pickles). Rendering is most of a large
    report's time; the figures are independent."""

    def __init__(self) -> None:
        self.jobs: list[tuple[Callable[..., Path], tuple]] = []

    def __call__(self, fn: Callable[..., Path], *args) -> None:
        self.jobs.append((fn, args))

    def run(self, n_jobs: int = 1) -> list[Path]:
        if n_jobs == 1 or len(self.jobs) < 2:
            return [fn(*args) for fn, args in self.jobs]
        import joblib

        return joblib.Parallel(n_jobs=n_jobs)(joblib.delayed(fn)(*args) for fn, args in self.jobs)


def _rate_heatmap(fig, ax, rate: np.ndarray, texts: list[list[str]], rows: list[str], cols: list[str], outline=None):
    """Compensation-rate heatmap: diverging colours centred on 0 (no gain), clipped
    to ±RATE_CLIP so a model that makes things worse shows red; the text carries
    the true values."""
    from matplotlib import colormaps
    from matplotlib.colors import TwoSlopeNorm
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import PercentFormatter

    cmap = colormaps["RdBu"].with_extremes(bad="#d9d9d9")
    shown = np.ma.masked_invalid(np.clip(rate, -RATE_CLIP, RATE_CLIP))
    im = ax.imshow(shown, cmap=cmap, norm=TwoSlopeNorm(vmin=-RATE_CLIP, vcenter=0.0, vmax=RATE_CLIP), aspect="auto")
    for i in range(rate.shape[0]):
        for j in range(rate.shape[1]):
            v = rate[i, j]
            dark = not math.isnan(v) and abs(max(-RATE_CLIP, min(RATE_CLIP, v))) > 0.6
            ax.text(j, i, texts[i][j], ha="center", va="center", fontsize=7, color="white" if dark else "black")
            if outline is not None and outline[i][j]:
                ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, edgecolor="black", linewidth=1.6))
    tilt = len(cols) > 4
    ax.set_xticks(range(len(cols)), labels=cols, rotation=45 if tilt else 0, ha="right" if tilt else "center")
    ax.set_yticks(range(len(rows)), labels=rows)
    cb = fig.colorbar(im, ax=ax, shrink=0.85)
    cb.ax.yaxis.set_major_formatter(PercentFormatter(xmax=1.0))
    cb.set_label(f"compensation rate (colour clipped to ±{100 * RATE_CLIP:.0f} %)")
    return im


def _matrix_figure(rate: pd.DataFrame, resid: pd.DataFrame, dataset: str, family: str, path: Path) -> Path:
    n_r, n_c = rate.shape
    fig = _new_figure(max(4.5, 1.0 * n_c + 2.2), max(3.2, 0.62 * n_r + 1.6))
    ax = fig.add_subplot()
    texts = [
        [
            "n/a" if math.isnan(rate.iat[i, j]) else f"{fmt_rate(rate.iat[i, j])}\n{fmt_um(resid.iat[i, j])} µm"
            for j in range(n_c)
        ]
        for i in range(n_r)
    ]
    outline = [[rate.index[i] == rate.columns[j] for j in range(n_c)] for i in range(n_r)]
    _rate_heatmap(fig, ax, rate.to_numpy(float), texts, list(rate.index), list(rate.columns), outline)
    ax.set_xlabel("tested on (state)")
    ax.set_ylabel("trained on (state)")
    ax.set_title(
        f"{dataset} · {family} (single-state models)\nrate, max |residual| µm; outlined = own state", fontsize=9
    )
    return _save(fig, path)


def _comparison_figure(comp: pd.DataFrame, runs: list[str], dataset: str, path: Path) -> Path:
    cols = runs + ["mean_rate"]
    rate = comp[cols].to_numpy(float)
    labels = [f"{fam} · {model}" + (f" ({t})" if model in ("single best", "single worst") else "")
              for (fam, model), t in zip(comp.index, comp["trained_on"])]
    texts = [[fmt_rate(v) if not math.isnan(v) else "n/a" for v in row] for row in rate]
    fig = _new_figure(max(5.0, 0.95 * len(cols) + 3.8), max(3.0, 0.32 * len(comp) + 1.6))
    ax = fig.add_subplot()
    _rate_heatmap(fig, ax, rate, texts, labels, runs + ["mean"])
    ax.axvline(len(runs) - 0.5, color="black", linewidth=1.2)
    families = [fam for fam, _ in comp.index]
    for i in range(1, len(families)):
        if families[i] != families[i - 1]:
            ax.axhline(i - 0.5, color="black", linewidth=0.8)
    ax.set_xlabel("validation run")
    ax.set_title(f"{dataset}: compensation rate on the validation runs", fontsize=9)
    return _save(fig, path)


_LINESTYLES = {"single": ":", "global": "-", "bank": "--", "bank_soft": "-."}


def curves_figure(c: pd.DataFrame, runs: list[str], title: str, path: Path) -> Path:
    """Before/after compensation per measuring cycle, one subplot per run of ``runs``:
    black = uncompensated max |thermal error|, colour = family, line style = approach."""
    from matplotlib import colormaps

    n = len(runs)
    ncols = min(n, 3)
    nrows = math.ceil(n / ncols)
    fig = _new_figure(4.2 * ncols, 2.8 * nrows + 1.0)
    axes = fig.subplots(nrows, ncols, squeeze=False)
    has_train = "train" in c.columns
    families = _unique(c["family"])
    palette = colormaps["tab10" if len(families) <= 10 else "tab20"]
    colour = {f: palette(i % palette.N) for i, f in enumerate(families)}
    line_keys = ["family", "approach"] + (["train"] if has_train else [])
    handles: dict[str, object] = {}
    for k, run in enumerate(runs):
        ax = axes[k // ncols][k % ncols]
        cr = c[c["run_id"] == run]
        before = cr.groupby("t_s")["before_um"].max()
        (h0,) = ax.plot(before.index / 3600.0, before.to_numpy(), color="black", linewidth=2.2)
        handles.setdefault("uncompensated", h0)
        for key, g in cr.groupby(line_keys, sort=False):
            fam, app = key[0], key[1]
            label = f"{fam} · {app}" + (f" [{key[2]}]" if has_train and app == "single" else "")
            g = g.sort_values("t_s")
            (h,) = ax.plot(
                g["t_s"] / 3600.0,
                g["after_um"],
                color=colour[fam],
                linestyle=_LINESTYLES.get(app, "-."),
                linewidth=1.2,
                marker=".",
                markersize=3,
            )
            handles.setdefault(label, h)
        ax.set_title(run, fontsize=9)
        ax.set_xlabel("time (h)")
        ax.set_ylabel("max |error| in cycle (µm)")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
    for k in range(n, nrows * ncols):
        axes[k // ncols][k % ncols].set_visible(False)
    fig.legend(list(handles.values()), list(handles), loc="outside lower center", ncol=min(4, len(handles)), fontsize=7)
    fig.suptitle(f"{title}: before (black, uncompensated) and after compensation", fontsize=10)
    return _save(fig, path)


_APPROACH_COLOURS = {"single": "#6baed6", "global": "#fd8d3c", "bank": "#41ab5d", "bank_soft": "#9e9ac8"}


_BASELINE_FACE, _BASELINE_EDGE = "#cfcfcf", "#525252"


def _rmse_norm(values: np.ndarray):
    """One colour scale for every RMSE heatmap of a dataset: logarithmic (an own-state
    fit of 0.2 µm and a failed transfer of 40 µm both stay readable), from the 2nd to
    the 98th percentile so one wild value does not wash the rest out."""
    from matplotlib.colors import LogNorm

    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v) & (v > 0)]
    if v.size == 0:
        return LogNorm(vmin=0.1, vmax=10.0, clip=True)
    lo, hi = np.percentile(v, 2), np.percentile(v, 98)
    if not hi > lo * 1.05:
        lo, hi = lo / 2.0, hi * 2.0
    return LogNorm(vmin=lo, vmax=hi, clip=True)


def _fmt_short_um(v: float) -> str:
    if math.isnan(v):
        return "n/a"
    return f"{v:.2f}" if abs(v) < 1 else f"{v:.1f}" if abs(v) < 100 else f"{v:.0f}"


def _fixed_figure(width_in: float, height_in: float):
    """A bare Figure without a layout engine: the callers place their axes in inches,
    which is several times faster to save than a constrained layout of many panels."""
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in))


def _panel_grid(fig, n: int, ncols: int, panel_w: float, panel_h: float, left: float, top: float,
                below: float, gap_x: float) -> list:
    """``n`` axes of ``panel_w`` × ``panel_h`` inches in rows of ``ncols``, from ``left``
    / ``top`` inches; ``below`` inches under each row (tick labels) and 0.3 in above (title)."""
    w, h = fig.get_size_inches()
    axes = []
    for k in range(n):
        i, j = divmod(k, ncols)
        x0 = left + j * (panel_w + gap_x)
        y_top = top + 0.3 + i * (panel_h + below + 0.3)
        axes.append(fig.add_axes((x0 / w, 1 - (y_top + panel_h) / h, panel_w / w, panel_h / h)))
    return axes


def _rmse_heatmap_figure(panels: list[tuple[str, pd.DataFrame, pd.DataFrame]], n_states: int, norm,
                         title: str, path: Path) -> Path:
    """Train × test RMSE of one family, one panel per channel: rows = training state
    (single-state models) then global / bank / ...; columns = the modelling states then
    the validation runs; outlined = a run the model was trained on."""
    from matplotlib import colormaps
    from matplotlib.cm import ScalarMappable
    from matplotlib.patches import Rectangle
    from matplotlib.ticker import FuncFormatter, LogLocator

    cmap = colormaps["YlOrRd"].with_extremes(bad="#e0e0e0")
    n = len(panels)
    ncols = min(n, 3)
    nrows = math.ceil(n / ncols)
    rows, cols = list(panels[0][1].index), list(panels[0][1].columns)
    n_r, n_c = len(rows), len(cols)
    pw, ph = 0.46 * n_c + 0.1, 0.24 * n_r + 0.1
    left = 0.06 * max(map(len, rows)) + 0.55
    below = 0.045 * max(map(len, cols)) + 0.25
    gap_x, right = 0.2, 1.05
    fig = _fixed_figure(left + ncols * pw + (ncols - 1) * gap_x + right, 0.2 + nrows * (ph + below + 0.3) + 0.1)
    axes = _panel_grid(fig, n, ncols, pw, ph, left, 0.2, below, gap_x)
    n_single = sum(1 for x in rows if x in set(cols))
    for k, (channel, vals, own) in enumerate(panels):
        ax = axes[k]
        v = vals.to_numpy(float)
        shade = np.asarray(np.ma.filled(norm(np.ma.masked_invalid(v)), np.nan), dtype=float)
        ax.imshow(np.ma.masked_invalid(v), cmap=cmap, norm=norm, aspect="auto", interpolation="nearest")
        o = own.to_numpy(bool)
        for i in range(n_r):
            for j in range(n_c):
                dark = shade[i, j] > 0.62
                ax.text(j, i, _fmt_short_um(v[i, j]), ha="center", va="center", fontsize=6.5,
                        color="white" if dark else "black")  # fmt: skip
                if o[i, j]:
                    ax.add_patch(Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, edgecolor="black", linewidth=1.1))
        if 0 < n_states < n_c:
            ax.axvline(n_states - 0.5, color="black", linewidth=1.0)
        if 0 < n_single < n_r:
            ax.axhline(n_single - 0.5, color="black", linewidth=1.0)
        ax.set_xticks(range(n_c), labels=cols, rotation=45, ha="right", rotation_mode="anchor", fontsize=7)
        ax.set_yticks(range(n_r), labels=rows if k % ncols == 0 else [], fontsize=7)
        ax.tick_params(length=2, pad=2)
        ax.set_title(channel, fontsize=9, pad=3)
    w, h = fig.get_size_inches()
    cax = fig.add_axes(((w - right + 0.15) / w, 0.15, 0.14 / w, 0.7))
    cb = fig.colorbar(ScalarMappable(norm=norm, cmap=cmap), cax=cax)
    cb.ax.yaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
    cb.ax.yaxis.set_major_formatter(FuncFormatter(lambda x, _: f"{x:g}"))
    cb.ax.yaxis.set_minor_locator(LogLocator(subs="auto", numticks=0))
    cb.ax.tick_params(labelsize=7)
    cb.set_label("RMSE (µm), log colour scale", fontsize=8)
    fig.text(0.5, 1 - 0.06 / h, title, ha="center", va="top", fontsize=9)
    return _save(fig, path)


def _bars_figure(table: pd.DataFrame, ref: frozenset[str], runs: list[str], title: str, path: Path) -> Path:
    """Validation RMSE per channel (one panel each), a horizontal bar per (family,
    approach): colour = approach, hatched grey = baseline; single = mean over the
    training states with a whisker from the best to the worst state. A bar beyond the
    axis (3 × the panel's median) is cut and its value printed."""
    from matplotlib.patches import Patch

    low, high = table.attrs.get("low"), table.attrs.get("high")
    labels = [
        f"{_family_label(fam, ref)} · {app}" + (" (mean)" if app == "single" else "") for fam, app in table.index
    ]
    n_rows, channels = len(table), list(table.columns)
    n = len(channels)
    ncols = min(n, 5)
    nrows = math.ceil(n / ncols)
    pw, ph = 2.1, 0.16 * n_rows + 0.15
    left = min(3.6, 0.062 * max(map(len, labels)) + 0.3)
    below, gap_x = 0.45, 0.3
    fig = _fixed_figure(left + ncols * pw + (ncols - 1) * gap_x + 0.3, 0.2 + nrows * (ph + below + 0.3) + 0.25)
    axes = _panel_grid(fig, n, ncols, pw, ph, left, 0.2, below, gap_x)
    y = np.arange(n_rows)
    is_ref = np.array([fam in ref for fam, _ in table.index], dtype=bool)
    face = [_BASELINE_FACE if base else _APPROACH_COLOURS.get(app, "#bcbddc")
            for base, (_, app) in zip(is_ref, table.index)]
    for k, ch in enumerate(channels):
        ax = axes[k]
        vals = table[ch].to_numpy(float)
        ok = np.isfinite(vals)
        finite = vals[ok]
        cap = float(np.max(finite)) if finite.size else 1.0
        if finite.size and np.max(finite) > 3 * np.median(finite):
            cap = 3 * float(np.median(finite))
        shown = np.where(ok, np.minimum(vals, cap), 0.0)
        for mask, kw in ((~is_ref, {}), (is_ref, {"edgecolor": _BASELINE_EDGE, "hatch": "////", "linewidth": 0.6})):
            sel = mask & ok
            if sel.any():
                ax.barh(y[sel], shown[sel], height=0.72, color=[face[i] for i in np.flatnonzero(sel)], **kw)
        text_at = shown.copy()
        if low is not None and high is not None:
            lo, hi = low[ch].to_numpy(float), high[ch].to_numpy(float)
            spread = np.isfinite(lo) & np.isfinite(hi) & (hi > lo)
            if spread.any():
                ax.hlines(y[spread], lo[spread], np.minimum(hi[spread], cap), color="black", linewidth=0.8)
                text_at[spread] = np.maximum(shown[spread], np.minimum(hi[spread], cap))
        best = int(np.nanargmin(vals)) if finite.size else -1
        for i in range(n_rows):
            if not ok[i]:
                ax.text(0, i, " n/a", va="center", ha="left", fontsize=6, color="#777777")
                continue
            txt = f" {vals[i]:.1f}" + (" ▸" if vals[i] > cap else "")
            ax.text(text_at[i], i, txt, va="center", ha="left", fontsize=6,
                    fontweight="bold" if i == best else "normal")
        ax.set_xlim(0, cap * 1.25)
        ax.set_ylim(n_rows - 0.5, -0.5)
        ax.set_yticks(y, labels=labels if k % ncols == 0 else [], fontsize=7)
        ax.tick_params(axis="x", labelsize=7)
        ax.tick_params(axis="y", length=0)
        ax.grid(axis="x", alpha=0.3)
        ax.set_axisbelow(True)
        ax.set_title(ch, fontsize=9, pad=3)
        ax.set_xlabel("RMSE (µm)", fontsize=7, labelpad=1)
    apps = _unique(app for _, app in table.index)
    handles = [Patch(facecolor=_APPROACH_COLOURS.get(a, "#bcbddc"), label=a) for a in apps]
    if is_ref.any():
        handles.append(Patch(facecolor=_BASELINE_FACE, edgecolor=_BASELINE_EDGE, hatch="////", label="baseline"))
    w, h = fig.get_size_inches()
    fig.legend(handles=handles, loc="lower center", bbox_to_anchor=(0.5, 0.0), ncol=len(handles), fontsize=7,
               frameon=False)  # fmt: skip
    fig.text(0.5, 1 - 0.06 / h, f"{title}: RMSE on the validation run(s) {', '.join(runs)}, lower is better; "
             "bold = best of the channel; single: mean over the training states, line = best to worst state; "
             "▸ = cut", ha="center", va="top", fontsize=8)  # fmt: skip
    return _save(fig, path)


def _best_curves_figure(items: list[dict], title: str, path: Path) -> Path:
    """Before/after compensation of the best model per channel, one panel per (channel,
    validation run): black = uncompensated max |thermal error| per cycle, colour = the
    best thermbench model, grey = the best baseline."""
    n = len(items)
    ncols = min(n, 3)
    nrows = math.ceil(n / ncols)
    pw, ph, left, below, gap_x = 3.4, 1.9, 0.5, 0.45, 0.55
    fig = _fixed_figure(left + ncols * pw + (ncols - 1) * gap_x + 0.2, 0.2 + nrows * (ph + below + 0.3) + 0.05)
    axes = _panel_grid(fig, n, ncols, pw, ph, left, 0.2, below, gap_x)
    for k, it in enumerate(items):
        ax = axes[k]
        best = it["best_curve"].sort_values("t_s")
        t0 = float(best["t_s"].min())
        before = best.groupby("t_s")["before_um"].max()
        ax.plot((before.index - t0) / 3600.0, before.to_numpy(), color="black", linewidth=1.4, label="uncompensated")
        if it.get("base_curve") is not None:
            base = it["base_curve"].sort_values("t_s")
            ax.plot((base["t_s"] - t0) / 3600.0, base["after_um"], color="#8c8c8c", linewidth=0.8, alpha=0.9,
                    label=f"baseline {it['base'][0]} · {it['base'][1]} ({it['base_value']:.2f} µm)")  # fmt: skip
        ax.plot((best["t_s"] - t0) / 3600.0, best["after_um"], color="tab:blue", linewidth=0.9,
                label=f"{it['best'][0]} · {it['best'][1]} ({it['best_value']:.2f} µm)")  # fmt: skip
        ax.set_title(f"{it['channel']} · {it['run']}", fontsize=9, pad=3)
        ax.set_xlabel("time in run (h)", fontsize=7, labelpad=1)
        ax.set_ylabel("|error| (µm)", fontsize=7, labelpad=1)
        ax.tick_params(labelsize=7)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, loc="upper left", framealpha=0.8)
    h = fig.get_size_inches()[1]
    fig.text(0.5, 1 - 0.06 / h, f"{title}: before (black) and after compensation, best thermbench model per "
             "channel (blue) and best baseline (grey); validation RMSE in the legend",
             ha="center", va="top", fontsize=9)
    return _save(fig, path)


def probe_figure(curve: pd.DataFrame, title: str, path: Path, top: int = 4, ref: frozenset[str] = frozenset()) -> Path:
    """One panel per channel: RMSE against probes per hour, the ``top`` thermbench families by
    their adaptive RMSE (solid: adaptive, dashed: the naive peer, from their open-loop point), the
    GP-refit peer (black) and the best baseline's naive peer (grey, dashed: what a user gets from a
    baseline fit and the last probe's residual)."""
    chans = _unique(curve[CHANNEL]) if CHANNEL in curve.columns else [ALL_CHANNELS]
    fig = _new_figure(max(3.0 * len(chans) + 0.6, 6.0), 4.2)
    axes = fig.subplots(1, len(chans), squeeze=False)[0]
    for ax, chan in zip(axes, chans):
        c = curve[curve[CHANNEL] == chan] if CHANNEL in curve.columns else curve
        ad = c[(c["strategy"] == "adaptive") & ~c["family"].isin(list(ref))].groupby("family")["rmse_um"].mean().sort_values()
        nb = c[(c["strategy"] == "naive_probe") & c["family"].isin(list(ref))].groupby("family")["rmse_um"].mean().sort_values()
        for fam in nb.index[:1]:
            f = c[c["family"] == fam]
            g = pd.concat([f[f["strategy"] == "open_loop"], f[f["strategy"] == "naive_probe"]]).sort_values("probes_per_h")
            ax.plot(g["probes_per_h"], g["rmse_um"], "--", color="0.5", linewidth=1.2,
                    label=f"{fam} naive (baseline)" if chan == chans[0] else None)  # fmt: skip
        for i, fam in enumerate(ad.index[:top]):
            f = c[c["family"] == fam]
            base = f[f["strategy"] == "open_loop"]
            for strat, style in (("adaptive", "-o"), ("naive_probe", "--s")):
                g = pd.concat([base, f[(f["strategy"] == strat) & (f["schedule"] != "uncertainty")]]).sort_values("probes_per_h")
                ax.plot(g["probes_per_h"], g["rmse_um"], style, color=f"C{i}", markersize=3, linewidth=1.2,
                        label=f"{fam} {strat.replace('_probe', '')}" if chan == chans[0] else None)  # fmt: skip
            trig = f[(f["strategy"] == "adaptive") & (f["schedule"] == "uncertainty")]
            ax.plot(trig["probes_per_h"], trig["rmse_um"], "*", color=f"C{i}", markersize=9)
        gp = c[c["strategy"] == "gp_refit"].sort_values("probes_per_h")
        if len(gp):
            ax.plot(gp["probes_per_h"], gp["rmse_um"], "-^", color="black", markersize=3, linewidth=1.0,
                    label="gp refit" if chan == chans[0] else None)  # fmt: skip
        ax.set_title(str(chan), fontsize=9)
        ax.set_xlabel("probes per hour")
        ax.grid(alpha=0.3)
    axes[0].set_ylabel("RMSE on the readings not probed (µm)")
    fig.legend(loc="outside lower center", fontsize=7, ncol=4)
    fig.suptitle(f"{title}: RMSE against probes per hour\n(star: adaptive, probing triggered by uncertainty)", fontsize=9)
    return _save(fig, path)