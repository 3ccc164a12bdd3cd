"""The robustness report: how well each thermal-error model family holds up when
the machine runs in a loading state it was not trained on.

Seed 001 §5 found that a regression model fitted on one moving state fails on
the others while the heat-transfer model holds; seed 002 §3.1.2/§3.2 answers the
same weakness with a bank of per-condition models and a condition classifier
(§2.4), reporting the gain as a compensation rate (88.69 % own condition,
70.67 % PSO-LSSVM, 53.11 % with classification). This module turns the
benchmark's long results table into those numbers, per dataset, family and
approach, on the runs each model has *not* seen.

Inputs (built by the benchmark; checked here, a missing column is a ValueError
naming it and the frame):

``results``
    One row per (fitted model, test run): ``dataset``, ``family``, ``approach``
    (``single`` = trained on one loading state, ``global`` = one model on all
    states, ``bank`` = per-state models + condition classifier), ``train``
    (the training run for ``single``, ``all`` otherwise), ``run_id``, ``kind``
    (``state`` = modelling state, ``validation`` = random validation duty
    cycle), ``own`` (the test run was in the training set) and the metrics of
    :func:`thermbench.metrics.residual_metrics` (``compensation_rate`` is a
    fraction, 1 − max|residual| / max|thermal error|, seed 000 §5, seed 002 §3).
``curves``
    Before/after compensation per measuring cycle: ``dataset``, ``family``,
    ``approach``, ``run_id``, ``t_s``, ``before_um`` (max |thermal error| of the
    cycle, uncompensated), ``after_um`` (max |residual| after compensation);
    optionally ``train`` to tell several single-state models apart.

"Unseen" runs are the rows with ``own`` false: the validation cycles for every
approach and, for single-state models, the other modelling states (the
off-diagonal cells of the train × test matrix).

Public API: :func:`train_test_matrix`, :func:`headline`,
:func:`approach_comparison`, :func:`terminal_summary`, :func:`write_report`,
:func:`figure_paths`, :func:`markdown_table`.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from .outputs import output_dir

RESULT_COLUMNS = (
    "dataset",
    "family",
    "approach",
    "train",
    "run_id",
    "kind",
    "own",
    "compensation_rate",
    "max_abs_residual_um",
)
CURVE_COLUMNS = ("dataset", "family", "approach", "run_id", "t_s", "before_um", "after_um")
KINDS = ("state", "validation")
APPROACH_ORDER = ("single", "global", "bank")
RATE = "compensation_rate"
RESIDUAL = "max_abs_residual_um"
RATE_CLIP = 1.0  # heatmap colours span [-100 %, 100 %]; the printed numbers are the true values
FIGURES_DIR = "figures"
REPORT_NAME = "report.md"

_KEYS = ("dataset", "family", "approach", "train", "run_id")
_STR_COLUMNS = ("dataset", "family", "approach", "train", "run_id", "kind")


# --------------------------------------------------------------------------- input checks


def _require_columns(frame, required: Sequence[str], name: str) -> None:
    if not isinstance(frame, pd.DataFrame):
        raise ValueError(f"{name} must be a pandas DataFrame, got {type(frame).__name__}")
    missing = [c for c in required if c not in frame.columns]
    if missing:
        raise ValueError(
            f"{name} is missing column(s) {missing}; expected at least {list(required)}, got {list(frame.columns)}"
        )


def _check_results(results, extra: Sequence[str] = ()) -> pd.DataFrame:
    """A normalised copy of ``results`` (key columns as str, ``own`` as bool), or a
    ValueError saying what is wrong."""
    _require_columns(results, RESULT_COLUMNS, "results")
    for col in extra:
        if col not in results.columns:
            metrics = [c for c in results.columns if c not in _STR_COLUMNS and c != "own"]
            raise ValueError(f"results has no column {col!r}; numeric columns: {metrics}")
    if results.empty:
        raise ValueError("results is empty: no (fitted model, test run) rows to report")
    r = results.copy()
    for col in _STR_COLUMNS + ("own",):
        n_missing = int(r[col].isna().sum())
        if n_missing:
            raise ValueError(f"results column {col!r} has {n_missing} missing value(s)")
    for col in _STR_COLUMNS:
        r[col] = r[col].astype(str)
    bad_kind = sorted(set(r["kind"]) - set(KINDS))
    if bad_kind:
        raise ValueError(f"results column 'kind' has unexpected value(s) {bad_kind}; expected one of {list(KINDS)}")
    own_values = set(r["own"].tolist())
    if not own_values <= {True, False}:
        bad = sorted(map(repr, own_values - {True, False}))[:5]
        raise ValueError(f"results column 'own' must be boolean, found value(s) {bad}")
    r["own"] = r["own"].astype(bool)
    for col in (RATE, RESIDUAL) + tuple(extra):
        try:
            r[col] = pd.to_numeric(r[col]).astype(float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"results column {col!r} must be numeric: {exc}") from exc
    dup = r.duplicated(list(_KEYS), keep=False)
    if dup.any():
        first = r.loc[dup, list(_KEYS)].drop_duplicates().head(3).to_dict("records")
        raise ValueError(
            f"results has {int(dup.sum())} rows sharing (dataset, family, approach, train, run_id), e.g. {first}; "
            "each fitted model must be scored once per test run"
        )
    return r


def _check_curves(curves) -> pd.DataFrame:
    _require_columns(curves, CURVE_COLUMNS, "curves")
    c = curves.copy()
    for col in ("dataset", "family", "approach", "run_id") + (("train",) if "train" in c.columns else ()):
        c[col] = c[col].astype(str)
    for col in ("t_s", "before_um", "after_um"):
        try:
            c[col] = pd.to_numeric(c[col]).astype(float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"curves column {col!r} must be numeric: {exc}") from exc
    keys = ["dataset", "family", "approach"] + (["train"] if "train" in c.columns else []) + ["run_id", "t_s"]
    dup = c.duplicated(keys, keep=False)
    if dup.any():
        first = c.loc[dup, keys].head(1).to_dict("records")
        raise ValueError(
            f"curves has {int(dup.sum())} rows sharing {tuple(keys)}, e.g. {first}; "
            "pass one model per family/approach or add a 'train' column to tell them apart"
        )
    return c


# --------------------------------------------------------------------------- ordering helpers


def _unique(values) -> list:
    """Unique values in order of first appearance."""
    return list(dict.fromkeys(values))


def _approach_rank(approach: str) -> tuple[int, str]:
    return (APPROACH_ORDER.index(approach), "") if approach in APPROACH_ORDER else (len(APPROACH_ORDER), approach)


def _groups(r: pd.DataFrame):
    """(dataset, family, approach, rows) in report order: datasets and families
    as they first appear, approaches single, global, bank, then others."""
    for ds in _unique(r["dataset"]):
        d = r[r["dataset"] == ds]
        for fam in _unique(d["family"]):
            f = d[d["family"] == fam]
            for app in sorted(_unique(f["approach"]), key=_approach_rank):
                yield ds, fam, app, f[f["approach"] == app]


def _runs(r: pd.DataFrame, dataset: str, kind: str) -> list[str]:
    d = r[(r["dataset"] == dataset) & (r["kind"] == kind)]
    return _unique(d["run_id"])


# --------------------------------------------------------------------------- tables


def train_test_matrix(results: pd.DataFrame, dataset: str, family: str, metric: str = RATE) -> pd.DataFrame:
    """Single-state models of one family on one dataset: rows = training state,
    columns = test state (modelling states only, ``approach == "single"``,
    ``kind == "state"``), values = ``metric``. The diagonal is each model on its
    own state; the off-diagonal cells are the unseen states (seed 001 §5.1 does this for M1 and M5).
    States keep the order in which they appear in ``results``."""
    r = _check_results(results, extra=(metric,))
    sel = r[
        (r["dataset"] == dataset) & (r["family"] == family) & (r["approach"] == "single") & (r["kind"] == "state")
    ]
    if sel.empty:
        datasets = _unique(r["dataset"])
        fams = _unique(r.loc[(r["dataset"] == dataset) & (r["approach"] == "single"), "family"])
        raise ValueError(
            f"no single-state results for dataset {dataset!r}, family {family!r}; "
            f"datasets: {datasets}; families with single models on {dataset!r}: {fams}"
        )
    tests = _unique(sel["run_id"])
    trains = [s for s in tests if s in set(sel["train"])] + [t for t in _unique(sel["train"]) if t not in set(tests)]
    m = sel.pivot(index="train", columns="run_id", values=metric).reindex(index=trains, columns=tests).astype(float)
    m.index.name = "train"
    m.columns.name = "test"
    return m


def headline(results: pd.DataFrame) -> pd.DataFrame:
    """The headline numbers on unseen cycles, one row per (dataset, family, approach).

    Columns, left to right (rates are fractions, residuals µm; "worst" is the
    lowest rate / the largest residual):

    * ``n_models`` — fitted models behind the row (one per training state for ``single``);
    * ``own_rate_mean`` — mean rate on the runs the models were trained on (reference);
    * ``val_rate_worst``, ``val_rate_mean``, ``val_worst_residual_um`` — over the
      validation runs (``kind == "validation"``); for ``single`` the worst is over
      every (training state, validation run) pair, i.e. the worst single model;
    * ``states_rate_worst``, ``states_rate_mean``, ``states_worst_residual_um`` —
      over the unseen modelling states (``kind == "state"`` and not ``own``): the
      off-diagonal of :func:`train_test_matrix` for ``single``, NaN otherwise;
    * ``<run>:rate``, ``<run>:residual_um`` per validation run (NaN for other
      datasets' runs); for ``single`` the mean over the training states.

    ``val_rate_mean`` is the mean over validation runs of the per-run column
    (each run weighs the same), so for a complete single-state design it equals
    the mean over all (training state, validation run) pairs.
    """
    r = _check_results(results)
    rows = []
    for ds, fam, app, g in _groups(r):
        val = g[g["kind"] == "validation"]
        states = g[(g["kind"] == "state") & ~g["own"]]
        own = g[(g["kind"] == "state") & g["own"]]
        per_run = val.groupby("run_id", sort=False)[[RATE, RESIDUAL]].mean()
        row = {
            "dataset": ds,
            "family": fam,
            "approach": app,
            "n_models": int(g["train"].nunique()),
            "own_rate_mean": own[RATE].mean(),
            "val_rate_worst": val[RATE].min(),
            "val_rate_mean": per_run[RATE].mean(),
            "val_worst_residual_um": val[RESIDUAL].max(),
            "states_rate_worst": states[RATE].min(),
            "states_rate_mean": states[RATE].mean(),
            "states_worst_residual_um": states[RESIDUAL].max(),
        }
        for run in _runs(r, ds, "validation"):
            row[f"{run}:rate"] = per_run[RATE].get(run, np.nan)
            row[f"{run}:residual_um"] = per_run[RESIDUAL].get(run, np.nan)
        rows.append(row)
    out = pd.DataFrame(rows).set_index(["dataset", "family", "approach"])
    return out.astype({c: float for c in out.columns if c != "n_models"})


def approach_comparison(results: pd.DataFrame, dataset: str) -> pd.DataFrame:
    """Single vs global vs bank (vs the physics family) on one dataset's validation runs.

    Index (family, model). For ``single`` three rows: ``single best`` and
    ``single worst`` are the training states with the highest / lowest mean rate
    over the validation runs (named in ``trained_on``), ``single mean`` the mean
    over all training states per run. Other approaches: one row per fitted model.
    Columns: ``trained_on``, the compensation rate on each validation run (column
    = run id), then ``mean_rate``, ``worst_rate`` and ``worst_residual_um`` over
    that row's runs.
    """
    r = _check_results(results)
    runs = _runs(r, dataset, "validation")
    if not runs:
        raise ValueError(
            f"dataset {dataset!r} has no validation runs (kind == 'validation') in results; "
            f"datasets with validation runs: {_unique(r.loc[r['kind'] == 'validation', 'dataset'])}"
        )
    d = r[(r["dataset"] == dataset) & (r["kind"] == "validation")]
    rows, index = [], []

    def add(fam, label, trained_on, rate: pd.Series, res: pd.Series):
        rate, res = rate.reindex(runs), res.reindex(runs)
        index.append((fam, label))
        rows.append(
            {
                "trained_on": trained_on,
                **rate.to_dict(),
                "mean_rate": rate.mean(),
                "worst_rate": rate.min(),
                "worst_residual_um": res.max(),
            }
        )

    for _, fam, app, g in _groups(d):
        rate = g.pivot(index="train", columns="run_id", values=RATE).reindex(columns=runs)
        res = g.pivot(index="train", columns="run_id", values=RESIDUAL).reindex(columns=runs)
        if app == "single":
            score = rate.mean(axis=1).fillna(-np.inf)
            best, worst = score.idxmax(), score.idxmin()
            add(fam, "single best", best, rate.loc[best], res.loc[best])
            add(fam, "single mean", f"mean of {len(rate)}", rate.mean(axis=0), res.mean(axis=0))
            add(fam, "single worst", worst, rate.loc[worst], res.loc[worst])
        else:
            for train in rate.index:
                label = app if len(rate) == 1 else f"{app} [{train}]"
                add(fam, label, train, rate.loc[train], res.loc[train])
    out = pd.DataFrame(rows, index=pd.MultiIndex.from_tuples(index, names=["family", "model"]))
    return out.astype({c: float for c in out.columns if c != "trained_on"})


# --------------------------------------------------------------------------- formatting


def _is_missing(x) -> bool:
    return x is None or (isinstance(x, (float, np.floating)) and math.isnan(x))


def fmt_rate(x) -> str:
    """A rate fraction as a percentage with one decimal (0.853 -> '85.3%'); '—' if missing."""
    return "—" if _is_missing(x) else f"{100.0 * float(x):.1f}%"


def fmt_um(x) -> str:
    """A length in µm with two decimals; '—' if missing."""
    return "—" if _is_missing(x) else f"{float(x):.2f}"


def _default_format(col: str) -> Callable:
    name = str(col)
    if name.endswith("_um"):
        return fmt_um
    if "rate" in name:
        return fmt_rate
    return lambda x: "—" if _is_missing(x) else (f"{x:.4g}" if isinstance(x, (float, np.floating)) else str(x))


def _passing_strings(fn: Callable) -> Callable:
    return lambda x: x if isinstance(x, str) else fn(x)


def _md_escape(s) -> str:
    return str(s).replace("|", "\\|").replace("\n", " ")


def markdown_table(
    df: pd.DataFrame,
    formats: Mapping[str, Callable] | None = None,
    index: bool = True,
    headers: Mapping[str, str] | None = None,
) -> str:
    """``df`` as a GitHub markdown table (``DataFrame.to_markdown`` needs tabulate).

    ``formats`` maps a column to a value -> str callable; by default columns
    ending in ``_um`` get two decimals, columns containing ``rate`` a percentage
    with one decimal. ``headers`` renames columns for display. Index levels
    become leading columns. Numeric columns are right-aligned."""
    formats = dict(formats or {})
    headers = dict(headers or {})
    frame = df.reset_index() if index else df
    cols = list(frame.columns)
    head = [_md_escape(headers.get(c, c)) for c in cols]
    align = ["---:" if pd.api.types.is_numeric_dtype(frame[c]) and frame[c].dtype != bool else "---" for c in cols]
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join(align) + " |"]
    fns = [formats.get(c, _passing_strings(_default_format(c))) for c in cols]
    for values in frame.itertuples(index=False, name=None):
        lines.append("| " + " | ".join(_md_escape(f(v)) for f, v in zip(fns, values)) + " |")
    return "\n".join(lines)


# --------------------------------------------------------------------------- terminal


def _cell(worst, mean, residual) -> str:
    if _is_missing(worst) and _is_missing(mean):
        return "-"
    w = "nan" if _is_missing(worst) else f"{100 * worst:.1f}"
    m = "nan" if _is_missing(mean) else f"{100 * mean:.1f}"
    return f"{w}/{m} {fmt_um(residual)}"


def terminal_summary(results: pd.DataFrame) -> str:
    """One screen: per dataset and family (rows), per approach (columns) the
    worst/mean compensation rate (%) and the worst max |residual| (µm) on unseen
    runs. ``<approach>:val`` cells are over the validation runs (comparable across
    approaches); ``single:states`` over the other modelling states (the
    off-diagonal of the train × test matrix). The four benchmark datasets with
    eight families fit in 40 lines of at most 120 characters."""
    h = headline(results)
    cols: dict[tuple[str, str], dict[str, str]] = {}
    for (ds, fam, app), row in h.iterrows():
        key = (ds, fam)
        cells = cols.setdefault(key, {})
        if not (_is_missing(row["val_rate_worst"]) and _is_missing(row["val_rate_mean"])):
            cells[f"{app}:val"] = _cell(row["val_rate_worst"], row["val_rate_mean"], row["val_worst_residual_um"])
        if not (_is_missing(row["states_rate_worst"]) and _is_missing(row["states_rate_mean"])):
            cells[f"{app}:states"] = _cell(
                row["states_rate_worst"], row["states_rate_mean"], row["states_worst_residual_um"]
            )
    present = _unique(c for cells in cols.values() for c in cells)

    def col_rank(c):
        app, part = c.rsplit(":", 1)
        return (_approach_rank(app), part != "val")

    order = sorted(present, key=col_rank)
    table = pd.DataFrame.from_dict(cols, orient="index").reindex(columns=order).fillna("-")
    table.index = pd.MultiIndex.from_tuples(list(cols), names=["dataset", "family"])
    body = table.to_string(index_names=False, max_colwidth=60) if order else "(no unseen runs in results)"
    legend = [
        "Compensation on runs each model was NOT trained on (thermbench robustness benchmark)",
        "cell = worst/mean compensation rate (%), worst max|residual| (um); "
        "val = validation runs, states = other states",
    ]
    return "\n".join(legend + [body])


# --------------------------------------------------------------------------- figures


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


_LINESTYLES = {"single": ":", "global": "-", "bank": "--"}


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


# --------------------------------------------------------------------------- report


HOW_TO_READ = (
    "**How to read this report.** The *compensation rate* of a run is 1 − max|residual| / max|thermal error| "
    "(seed 000 §5, seed 002 §3): 100 % means the model removed all the thermal error, 0 % that the compensated axis "
    "is no better than the uncompensated one, and a *negative* rate that compensation made the axis worse. "
    "*Max residual* is the largest |measured − predicted| thermal error left after compensation, in µm. "
    "*Unseen* runs are the runs a model was not trained on: the random validation duty cycles and, for a single-state "
    "model, the other modelling states (the off-diagonal cells of its train × test matrix). Approaches: "
    "*single* = one "
    "model trained on one loading state; *global* = one model trained on all modelling states; *bank* = one model per "
    "state plus a condition classifier that picks the model for the running duty (seed 002 §2.4). *Worst* is the "
    "lowest rate / the largest residual. In the heatmaps the colour is the compensation rate, blue = good, white = no "
    "gain, red = worse than not compensating, clipped to ±100 % so a model that fails badly still shows as deep red; "
    "the printed numbers are the true values, with the max residual in µm below the rate. Outlined cells are a "
    "model's own training state. In the before/after plots the black line is the uncompensated thermal error "
    "(max over the targets of each measuring cycle) and each coloured line the residual left by one model "
    "(colour = family, line style = approach: dotted single, solid global, dashed bank)."
)

_HEADLINE_HEADERS = {
    "family": "family",
    "approach": "approach",
    "n_models": "models",
    "own_rate_mean": "own runs mean",
    "val_rate_worst": "validation worst",
    "val_rate_mean": "validation mean",
    "val_worst_residual_um": "validation worst max µm",
    "states_rate_worst": "other states worst",
    "states_rate_mean": "other states mean",
    "states_worst_residual_um": "other states worst max µm",
}


def _headline_md(h: pd.DataFrame, runs: list[str]) -> str:
    """One dataset's headline rows: aggregates, then 'rate / max µm' per validation run."""
    t = h.reset_index(level="dataset", drop=True).reset_index()
    fixed = [c for c in _HEADLINE_HEADERS if c in t.columns]
    show = t[fixed].copy()
    if show[["states_rate_worst", "states_rate_mean"]].isna().all().all():
        show = show.drop(columns=["states_rate_worst", "states_rate_mean", "states_worst_residual_um"])
    for run in runs:
        show[f"{run} rate / max µm"] = [
            "—" if _is_missing(a) else f"{fmt_rate(a)} / {fmt_um(b)}"
            for a, b in zip(t[f"{run}:rate"], t[f"{run}:residual_um"])
        ]
    return markdown_table(show, index=False, headers=_HEADLINE_HEADERS, formats={"n_models": str})


def _meta_md(meta: Mapping | None) -> str:
    if not meta:
        return "_No run metadata was given._"
    rows = []
    for k, v in meta.items():
        if isinstance(v, Mapping):
            v = ", ".join(f"{a}={b}" for a, b in v.items())
        rows.append({"": str(k), "value": f"`{v}`" if k == "command" else str(v)})
    return markdown_table(pd.DataFrame(rows), index=False)


def _matrix_summary(rate: pd.DataFrame, resid: pd.DataFrame) -> str:
    diag, off = [], []
    for tr in rate.index:
        for te in rate.columns:
            (diag if tr == te else off).append((rate.at[tr, te], resid.at[tr, te], tr, te))
    parts = []
    d = [x for x in diag if not math.isnan(x[0])]
    if d:
        parts.append(f"own state mean {fmt_rate(np.mean([x[0] for x in d]))}")
    o = [x for x in off if not math.isnan(x[0])]
    if o:
        worst = min(o, key=lambda x: x[0])
        parts.append(
            f"unseen states mean {fmt_rate(np.mean([x[0] for x in o]))}, worst {fmt_rate(worst[0])} "
            f"(trained on {worst[2]}, tested on {worst[3]}), "
            f"worst max residual {fmt_um(np.nanmax([x[1] for x in o]))} µm"
        )
    return "; ".join(parts) + "." if parts else "No scored cells."


def figure_paths(out_dir) -> list[Path]:
    """The PNGs of the report in ``out_dir`` (``out_dir/figures/*.png``, sorted),
    e.g. to log them as MLflow artifacts."""
    return sorted((Path(out_dir) / FIGURES_DIR).glob("*.png"))


def write_report(results: pd.DataFrame, curves: pd.DataFrame | None, out_dir, meta: Mapping | None = None,
                 force: bool = False) -> Path:
    """Write ``out_dir/report.md`` and its figures ``out_dir/figures/*.png``; return the report path.

    Layout: header (``meta``), how to read, the terminal summary, the headline
    tables (:func:`headline`, one per dataset), then per dataset: single vs
    global vs bank on the validation runs (:func:`approach_comparison`, table +
    heatmap), the train × test heatmap per family (:func:`train_test_matrix` of
    the compensation rate, max residual annotated) and the before/after
    compensation curves of the validation runs (``curves``; None or an empty
    frame means no curves, the report says so).

    Written as one output of kind ``report`` (:func:`thermbench.outputs.output_dir`): the
    figures and report.md are rendered into a staging directory and replace the previous
    report's files only when all are done, so any failure leaves the previous report
    untouched; a directory holding anything else is refused (``force``: written beside it).
    List the PNGs with :func:`figure_paths`.
    """
    r = _check_results(results)
    no_curves = curves is None or (isinstance(curves, pd.DataFrame) and curves.empty)
    c = None if no_curves else _check_curves(curves)
    out_dir = Path(out_dir)
    h = headline(r)
    used: set[str] = set()

    def fig_name(*parts: str) -> str:
        base = "__".join(_slug(p) for p in parts)
        name, k = f"{base}.png", 1
        while name in used:
            k += 1
            name = f"{base}-{k}.png"
        used.add(name)
        return name

    md: list[str] = ["# Thermal-error robustness report", "", _meta_md(meta), "", HOW_TO_READ, ""]
    md += ["## At a glance", "", "```text", terminal_summary(r), "```", ""]
    md += ["## Headline: unseen cycles", ""]
    md += [
        "Per dataset, family and approach: mean rate on the training runs (reference), worst and mean rate and worst "
        "max residual over the validation runs, the same over the other modelling states for single-state models, "
        "then rate / max residual per validation run (single: mean over the training states).",
        "",
    ]
    datasets = _unique(r["dataset"])
    for ds in datasets:
        rows = h.xs(ds, level="dataset", drop_level=False)
        md += [f"### {ds}", "", _headline_md(rows, _runs(r, ds, "validation")), ""]

    with output_dir(out_dir, "report", force=force) as stage:
        fig_dir = stage / FIGURES_DIR
        fig_dir.mkdir()
        for ds in datasets:
            md += [f"## {ds}", ""]
            runs = _runs(r, ds, "validation")
            md += ["### Single vs global vs bank on the validation runs", ""]
            if runs:
                comp = approach_comparison(r, ds)
                name = fig_name("compare", ds)
                _comparison_figure(comp, runs, ds, fig_dir / name)
                md += [
                    "Compensation rate per validation run; single best / worst = the training state with the highest "
                    "/ lowest mean rate over these runs.",
                    "",
                    markdown_table(
                        comp,
                        formats={"trained_on": str, **{run: fmt_rate for run in runs}},
                        headers={"mean_rate": "mean", "worst_rate": "worst", "worst_residual_um": "worst max µm"},
                    ),
                    "",
                    f"![{ds} comparison]({FIGURES_DIR}/{name})",
                    "",
                ]
            else:
                md += ["_No validation runs for this dataset._", ""]

            md += ["### Train × test matrices (single-state models)", ""]
            single = r[(r["dataset"] == ds) & (r["approach"] == "single") & (r["kind"] == "state")]
            fams = _unique(single["family"])
            if not fams:
                md += ["_No single-state models for this dataset._", ""]
            for fam in fams:
                rate = train_test_matrix(r, ds, fam, RATE)
                resid = train_test_matrix(r, ds, fam, RESIDUAL)
                name = fig_name("matrix", ds, fam)
                _matrix_figure(rate, resid, ds, fam, fig_dir / name)
                md += [f"#### {fam}", "", _matrix_summary(rate, resid), ""]
                md += [f"![{ds} {fam} matrix]({FIGURES_DIR}/{name})", ""]

            md += ["### Before / after compensation (validation runs)", ""]
            cd = None if c is None else c[(c["dataset"] == ds) & c["run_id"].isin(runs)]
            plotted = [run for run in runs if cd is not None and (cd["run_id"] == run).any()]
            if plotted:
                name = fig_name("curves", ds)
                curves_figure(cd, plotted, f"{ds}, validation runs", fig_dir / name)
                md += [f"![{ds} before/after]({FIGURES_DIR}/{name})", ""]
                missing = [run for run in runs if run not in plotted]
                if missing:
                    md += [f"_No curves for validation run(s) {', '.join(missing)}._", ""]
            else:
                md += ["_No before/after curves for this dataset's validation runs._", ""]
        text = "\n".join(md).rstrip() + "\n"
        (stage / REPORT_NAME).write_text(text, encoding="utf-8")
    return out_dir / REPORT_NAME
