"""The robustness report: how well each thermal-error model family holds up when
the machine runs in a loading state it was not trained on.

Seed 001 §5 found that a regression model fitted on one moving state fails on
the others while the heat-transfer model holds; seed 002 §3.1.2/§3.2 answers the
same weakness with a bank of per-condition models and a condition classifier
(§2.4), reporting the gain as a compensation rate (88.69 % own condition,
70.67 % PSO-LSSVM, 53.11 % with classification). This module turns the
benchmark's long results table into those numbers, per dataset, error channel,
family and approach, on the runs each model has *not* seen.

Inputs (built by the benchmark; checked here, a missing column is a ValueError
naming it and the frame):

``results``
    One row per (fitted model, test run): ``dataset``, ``family``, ``approach``
    (``single`` = trained on one loading state, ``global`` = one model on all
    states, ``bank`` / ``bank_soft`` = per-state models + condition classifier,
    switched / blended), ``train`` (the training run for ``single``, ``all``
    otherwise), ``run_id``, ``kind`` (``state`` = modelling state, ``validation``
    = validation duty cycle), ``own`` (the test run was in the training set) and
    the metrics of :func:`thermbench.metrics.residual_metrics`
    (``compensation_rate`` is a fraction, 1 − max|residual| / max|thermal error|,
    seed 000 §5, seed 002 §3; ``rmse_um`` is needed for a dataset with several
    channels). Optional ``channel``: the error channel the model was fitted to
    (``ch1`` … of a format 2 dataset; ``all`` for a format 1 dataset; a missing
    column or value means ``all``). A fitted model is one (dataset, channel,
    family, approach, train); each is scored once per test run.
``curves``
    Before/after compensation per measuring cycle: ``dataset``, ``family``,
    ``approach``, ``run_id``, ``t_s``, ``before_um`` (max |thermal error| of the
    cycle, uncompensated), ``after_um`` (max |residual| after compensation);
    optionally ``train`` to tell several single-state models apart and
    ``channel`` (missing = ``all``).

"Unseen" runs are the rows with ``own`` false: the validation cycles for every
approach and, for single-state models, the other modelling states (the
off-diagonal cells of the train × test matrix).

Report directory (:func:`write_report`): ``report.md`` (the answer: the model to deploy per
dataset and channel and its held-out error), ``details.md`` (the tables and figures behind it),
``findings.md`` (the run's lists of findings, e.g. the flagged models), ``figures/*.png`` and
``results.csv``, one row per (fitted model, test run), columns in this order:

``dataset, family, approach, train, test, channel, rmse_um, max_abs_residual_um,
compensation_rate, kind, own, reference``, then the other columns of ``results``
in their order (e.g. ``pv_residual_um, max_abs_error_um, pv_error_um,
residual_fraction_of_pv, nonfinite_predictions, fit_s``). ``test`` is the run
scored (``run_id``: a loading state or a validation run such as ``tail``),
``channel`` the error channel (``all`` for a format 1 dataset), ``reference``
true for a baseline family (compared, never chosen); ``rmse_um`` is empty when
``results`` has no such column. Rows are in report order (dataset, channel,
family, approach single/global/bank/bank_soft, then as given).

A dataset scored on several channels gets its own layout (:func:`write_report`):
validation RMSE per channel (table with the best per channel and the best
thermbench family vs the best baseline), a bar chart of it, one train × test
RMSE heatmap per family (a panel per channel) and the before/after curves of
the best model per channel. Format 1 and single-channel datasets keep the
compensation-rate layout.

Public API: :func:`train_test_matrix`, :func:`headline`,
:func:`approach_comparison`, :func:`validation_by_channel`,
:func:`best_by_channel`, :func:`terminal_summary`, :func:`write_report`,
:func:`results_table` (the rows of results.csv), :func:`figure_paths`,
:func:`markdown_table`.
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
APPROACH_ORDER = ("single", "global", "bank", "bank_soft")
RATE = "compensation_rate"
RESIDUAL = "max_abs_residual_um"
RMSE = "rmse_um"
CHANNEL = "channel"
ALL_CHANNELS = "all"  # the channel of a format 1 dataset (and of results without a channel column)
CSV_NAME = "results.csv"
#: the leading columns of results.csv, in this order (``test`` = the run scored)
CSV_COLUMNS = ("dataset", "family", "approach", "train", "test", "channel", RMSE, RESIDUAL, RATE)
RATE_CLIP = 1.0  # heatmap colours span [-100 %, 100 %]; the printed numbers are the true values
FIGURES_DIR = "figures"
REPORT_NAME = "report.md"
#: the report's linked files: everything behind its tables, and the run's lists of findings
DETAILS_NAME = "details.md"
FINDINGS_NAME = "findings.md"

_KEYS = ("dataset", "channel", "family", "approach", "train", "run_id")
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
    r = results.reset_index(drop=True)  # a copy; positions as labels (concatenated frames repeat labels)
    if CHANNEL not in r.columns:  # an old caller or a format 1 dataset: one channel, "all"
        r[CHANNEL] = ALL_CHANNELS
    r[CHANNEL] = r[CHANNEL].astype(object).where(r[CHANNEL].notna(), ALL_CHANNELS).astype(str)
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
    for col in (RATE, RESIDUAL) + ((RMSE,) if RMSE in r.columns else ()) + tuple(extra):
        try:
            r[col] = pd.to_numeric(r[col]).astype(float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"results column {col!r} must be numeric: {exc}") from exc
    dup = r.duplicated(list(_KEYS), keep=False)
    if dup.any():
        first = r.loc[dup, list(_KEYS)].drop_duplicates().head(3).to_dict("records")
        raise ValueError(
            f"results has {int(dup.sum())} rows sharing (dataset, family, approach, train, run_id) and channel, "
            f"e.g. {first}; each fitted model must be scored once per test run"
        )
    return r


def _check_curves(curves) -> pd.DataFrame:
    _require_columns(curves, CURVE_COLUMNS, "curves")
    c = curves.copy()
    if CHANNEL not in c.columns:
        c[CHANNEL] = ALL_CHANNELS
    c[CHANNEL] = c[CHANNEL].astype(object).where(c[CHANNEL].notna(), ALL_CHANNELS)
    for col in ("dataset", CHANNEL, "family", "approach", "run_id") + (("train",) if "train" in c.columns else ()):
        c[col] = c[col].astype(str)
    for col in ("t_s", "before_um", "after_um"):
        try:
            c[col] = pd.to_numeric(c[col]).astype(float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"curves column {col!r} must be numeric: {exc}") from exc
    keys = ["dataset", CHANNEL, "family", "approach"] + (["train"] if "train" in c.columns else []) + ["run_id", "t_s"]
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


def _case_label(dataset: str, channel: str) -> str:
    """How a (dataset, channel) pair is named in the report: the dataset, with the
    channel after a space for a named channel (``fl_thermal ch3``)."""
    return str(dataset) if channel == ALL_CHANNELS else f"{dataset} {channel}"


def _channels(r: pd.DataFrame, dataset: str) -> list[str]:
    return _unique(r.loc[r["dataset"] == dataset, CHANNEL])


def _has_channels(r: pd.DataFrame) -> bool:
    return bool((r[CHANNEL] != ALL_CHANNELS).any())


def _groups(r: pd.DataFrame):
    """(dataset, channel, family, approach, rows) in report order: datasets,
    channels and families as they first appear, approaches single, global, bank,
    bank_soft, then others."""
    keys = ["dataset", CHANNEL, "family", "approach"]
    first = {}
    for n in (1, 2, 3):
        sub = r[keys[:n]].drop_duplicates()
        first[n] = {tuple(k): i for i, k in enumerate(sub.itertuples(index=False, name=None))}
    groups = list(r.groupby(keys, sort=False))
    groups.sort(key=lambda kg: (first[1][kg[0][:1]], first[2][kg[0][:2]], first[3][kg[0][:3]],
                                _approach_rank(kg[0][3])))  # fmt: skip
    for (ds, ch, fam, app), g in groups:
        yield ds, ch, fam, app, g


def _runs(r: pd.DataFrame, dataset: str, kind: str) -> list[str]:
    d = r[(r["dataset"] == dataset) & (r["kind"] == kind)]
    return _unique(d["run_id"])


def _one_channel(r: pd.DataFrame, dataset: str, channel: str | None) -> pd.DataFrame:
    """``r`` restricted to one channel of ``dataset`` (other datasets' rows kept);
    ``channel=None`` is fine when the dataset has only one."""
    chans = _channels(r, dataset)
    if channel is None:
        if len(chans) > 1:
            raise ValueError(f"dataset {dataset!r} is scored on several channels {chans}; pass channel=")
        return r
    channel = str(channel)
    if chans and channel not in chans:
        raise ValueError(f"dataset {dataset!r} has no channel {channel!r}; its channels: {chans}")
    return r[(r["dataset"] != dataset) | (r[CHANNEL] == channel)]


def _reference_set(reference) -> frozenset[str]:
    if reference is None:
        return frozenset()
    if isinstance(reference, str):
        return frozenset([reference])
    return frozenset(str(f) for f in reference)


def _family_label(family: str, ref: frozenset[str]) -> str:
    return f"{family} (baseline)" if family in ref else str(family)


# --------------------------------------------------------------------------- tables


def train_test_matrix(results: pd.DataFrame, dataset: str, family: str, metric: str = RATE,
                      channel: str | None = None) -> pd.DataFrame:
    """Single-state models of one family on one dataset: rows = training state,
    columns = test state (modelling states only, ``approach == "single"``,
    ``kind == "state"``), values = ``metric``. The diagonal is each model on its
    own state; the off-diagonal cells are the unseen states (seed 001 §5.1 does this for M1 and M5).
    States keep the order in which they appear in ``results``. ``channel``: which
    error channel, needed when the dataset is scored on several."""
    r = _one_channel(_check_results(results, extra=(metric,)), dataset, channel)
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
    """The headline numbers on unseen cycles, one row per (dataset, family, approach),
    or per (dataset, channel, family, approach) when ``results`` names channels
    (some ``channel`` other than ``all``; the index then has a ``channel`` level
    after ``dataset``).

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
    keys = ["dataset", CHANNEL, "family", "approach"]
    order = [(ds, ch, fam, app) for ds, ch, fam, app, _ in _groups(r)]
    index = pd.MultiIndex.from_tuples(order, names=keys)
    is_val = r["kind"] == "validation"
    is_state = r["kind"] == "state"
    val, own, states = r[is_val], r[is_state & r["own"]], r[is_state & ~r["own"]]
    per_run = val.groupby(keys + ["run_id"], sort=False)[[RATE, RESIDUAL]].mean()
    out = pd.DataFrame(
        {
            "n_models": r.groupby(keys, sort=False)["train"].nunique(),
            "own_rate_mean": own.groupby(keys, sort=False)[RATE].mean(),
            "val_rate_worst": val.groupby(keys, sort=False)[RATE].min(),
            "val_rate_mean": per_run[RATE].groupby(level=keys, sort=False).mean(),
            "val_worst_residual_um": val.groupby(keys, sort=False)[RESIDUAL].max(),
            "states_rate_worst": states.groupby(keys, sort=False)[RATE].min(),
            "states_rate_mean": states.groupby(keys, sort=False)[RATE].mean(),
            "states_worst_residual_um": states.groupby(keys, sort=False)[RESIDUAL].max(),
        }
    ).reindex(index)
    runs = _unique(run for ds in _unique(r["dataset"]) for run in _runs(r, ds, "validation"))
    for run in runs:
        cell = per_run.xs(run, level="run_id") if run in set(val["run_id"]) else per_run.iloc[:0].droplevel("run_id")
        out[f"{run}:rate"] = cell[RATE].reindex(index)
        out[f"{run}:residual_um"] = cell[RESIDUAL].reindex(index)
    out["n_models"] = out["n_models"].astype(int)
    if not _has_channels(r):
        out = out.droplevel(CHANNEL)
    return out.astype({c: float for c in out.columns if c != "n_models"})


def approach_comparison(results: pd.DataFrame, dataset: str, channel: str | None = None) -> pd.DataFrame:
    """Single vs global vs bank (vs the physics family) on one dataset's validation runs.

    Index (family, model). For ``single`` three rows: ``single best`` and
    ``single worst`` are the training states with the highest / lowest mean rate
    over the validation runs (named in ``trained_on``), ``single mean`` the mean
    over all training states per run. Other approaches: one row per fitted model.
    Columns: ``trained_on``, the compensation rate on each validation run (column
    = run id), then ``mean_rate``, ``worst_rate`` and ``worst_residual_um`` over
    that row's runs. ``channel``: which error channel, needed when the dataset is
    scored on several.
    """
    r = _one_channel(_check_results(results), dataset, channel)
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

    for _, _, fam, app, g in _groups(d):
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


def validation_by_channel(results: pd.DataFrame, dataset: str, metric: str = RMSE) -> pd.DataFrame:
    """One dataset's score on its validation runs per error channel: index (family,
    approach) in report order, one column per channel (order of appearance), value =
    ``metric`` averaged over the validation runs (each run weighs the same); for
    ``single`` then averaged over the training states, i.e. what training on one state
    gives on average (no state is picked by its validation score). NaN where nothing
    was scored. The number of fitted models behind each cell and the best / worst
    single-state model are in ``.attrs["n_models"]``, ``.attrs["low"]`` and
    ``.attrs["high"]`` (frames of the same shape: min / max over the models)."""
    r = _check_results(results, extra=(metric,))
    v = r[(r["dataset"] == dataset) & (r["kind"] == "validation")]
    if v.empty:
        raise ValueError(
            f"dataset {dataset!r} has no validation runs (kind == 'validation') in results; "
            f"datasets with validation runs: {_unique(r.loc[r['kind'] == 'validation', 'dataset'])}"
        )
    channels = _channels(r, dataset)
    per_model = v.groupby(["family", "approach", "train", CHANNEL], sort=False)[metric].mean().reset_index()
    rows = [(fam, app) for fam in _unique(v["family"])
            for app in sorted(_unique(v.loc[v["family"] == fam, "approach"]), key=_approach_rank)]  # fmt: skip
    index = pd.MultiIndex.from_tuples(rows, names=["family", "approach"])
    g = per_model.groupby(["family", "approach", CHANNEL], sort=False)[metric]

    def table(agg) -> pd.DataFrame:
        t = agg.unstack(CHANNEL) if len(agg) else pd.DataFrame(index=index)
        return t.reindex(index=index, columns=channels).astype(float).rename_axis(columns=CHANNEL)

    out = table(g.mean())
    out.attrs["n_models"] = table(g.count())
    out.attrs["low"] = table(g.min())
    out.attrs["high"] = table(g.max())
    out.attrs["metric"] = metric
    return out


def best_by_channel(table: pd.DataFrame, reference: Sequence[str] = (), lower_is_better: bool = True) -> pd.DataFrame:
    """Per channel (column of :func:`validation_by_channel`), the best row overall, the
    best thermbench row (not a ``reference`` family) and the best baseline row: index =
    channel, columns ``best``, ``best_value``, ``family``, ``family_value``, ``baseline``,
    ``baseline_value``; each row label is a (family, approach) tuple, None when there is
    no candidate."""
    ref = _reference_set(reference)
    out = {}
    for ch in table.columns:
        col = table[ch].dropna()
        if not lower_is_better:
            col = -col

        def pick(mask) -> tuple:
            c = col[mask]
            if c.empty:
                return None, np.nan
            key = c.idxmin()
            return key, float(table.at[key, ch])

        is_ref = np.array([fam in ref for fam, _ in col.index], dtype=bool)
        best, best_v = pick(np.ones(len(col), dtype=bool))
        fam, fam_v = pick(~is_ref)
        base, base_v = pick(is_ref)
        out[ch] = {"best": best, "best_value": best_v, "family": fam, "family_value": fam_v,
                   "baseline": base, "baseline_value": base_v}  # fmt: skip
    return pd.DataFrame.from_dict(out, orient="index").rename_axis(CHANNEL)


def _matrix_models(d: pd.DataFrame, states: list[str]) -> list[tuple[str, str, str]]:
    """The rows of a family's train × test matrices, as (label, approach, train): its
    single-state models in the order of ``states``, then its other models (global, bank,
    ...), over all channels of ``d`` (the family's rows on one dataset)."""
    single = set(d.loc[d["approach"] == "single", "train"])
    out = [(s, "single", s) for s in states if s in single] + [(s, "single", s) for s in sorted(single - set(states))]
    others = d[d["approach"] != "single"]
    for app in sorted(_unique(others["approach"]), key=_approach_rank):
        trains = _unique(others.loc[others["approach"] == app, "train"])
        out += [(app if len(trains) == 1 else f"{app} [{tr}]", app, tr) for tr in trains]
    return out


def _test_matrix(g: pd.DataFrame, metric: str, models: list[tuple[str, str, str]],
                 tests: list[str]) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The rows ``g`` of one family on one channel of one dataset as a matrix: a row per
    model of ``models`` (:func:`_matrix_models`), columns ``tests``; the metric and
    whether the cell is one of the model's training runs (``own``). NaN / False where
    the model was not fitted or not scored."""
    by_model = {key: s.set_index("run_id") for key, s in g.groupby(["approach", "train"], sort=False)}
    vals, owns = [], []
    for _, app, train in models:
        s = by_model.get((app, train))
        if s is None:
            vals.append(np.full(len(tests), np.nan))
            owns.append(np.zeros(len(tests), dtype=bool))
        else:
            vals.append(s[metric].reindex(tests).to_numpy(float))
            owns.append(s["own"].reindex(tests, fill_value=False).to_numpy(bool))
    rows = [label for label, _, _ in models]
    return pd.DataFrame(vals, index=rows, columns=tests), pd.DataFrame(owns, index=rows, columns=tests)


# --------------------------------------------------------------------------- formatting


def _is_missing(x) -> bool:
    return x is None or (isinstance(x, (float, np.floating)) and math.isnan(x))


def fmt_rate(x) -> str:
    """A rate fraction as a percentage with one decimal (0.853 -> '85.3%'); '—' if missing."""
    return "—" if _is_missing(x) else f"{100.0 * float(x):.1f}%"


def _percent(x) -> str:
    """A fraction as a whole percentage; an em dash when missing (as fmt_um)."""
    return "—" if _is_missing(x) else f"{100 * float(x):.0f} %"


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
    """``df`` as a GitHub markdown table (``DataFrame.to_markdown``, tabulate's ``pipe`` format).

    ``formats`` maps a column to a value -> str callable; by default columns
    ending in ``_um`` get two decimals, columns containing ``rate`` a percentage
    with one decimal. ``headers`` renames columns for display. Index levels
    become leading columns. Numeric columns are right-aligned. Cells are shown as
    formatted (tabulate's number parsing is off); a ``|`` in a cell is escaped."""
    formats = dict(formats or {})
    headers = dict(headers or {})
    frame = df.reset_index() if index else df
    cols = list(frame.columns)
    fns = [formats.get(c, _passing_strings(_default_format(c))) for c in cols]
    cells = [[_md_escape(f(v)) for v in frame.iloc[:, i]] for i, f in enumerate(fns)]
    shown = pd.DataFrame(dict(enumerate(cells)), columns=range(len(cols)), dtype=object)
    right = [pd.api.types.is_numeric_dtype(frame.iloc[:, i]) and frame.iloc[:, i].dtype != bool for i in range(len(cols))]
    return shown.to_markdown(index=False, tablefmt="pipe", disable_numparse=True,
                             headers=[_md_escape(headers.get(c, c)) for c in cols],
                             colalign=["right" if r else "left" for r in right])  # fmt: skip


# --------------------------------------------------------------------------- terminal

TERMINAL_WIDTH = 120


def _cell(worst, mean, residual, decimals: int = 1) -> str:
    if _is_missing(worst) and _is_missing(mean):
        return "-"
    w = "nan" if _is_missing(worst) else f"{100 * worst:.{decimals}f}"
    m = "nan" if _is_missing(mean) else f"{100 * mean:.{decimals}f}"
    res = "—" if _is_missing(residual) else f"{float(residual):.{decimals + 1}f}"
    return f"{w}/{m} {res}"


def terminal_summary(results: pd.DataFrame, reference: Sequence[str] = ()) -> str:
    """One screen: per dataset (and channel: ``fl_thermal ch3``) and family (rows), per
    approach (columns) the worst/mean compensation rate (%) and the worst max |residual|
    (µm) on unseen runs. ``<approach>:val`` cells are over the validation runs
    (comparable across approaches); ``single:states`` over the other modelling states
    (the off-diagonal of the train × test matrix). ``reference`` families (baselines)
    are marked ``*``. Lines are at most 120 characters: if the table is wider, the rates
    lose their decimal, then the columns are split into blocks. The four benchmark
    datasets with eight families fit in 40 lines."""
    r = _check_results(results)
    h = headline(r)
    ref = _reference_set(reference) & set(r["family"])
    if not _has_channels(r):  # the same rows, one index shape
        h = pd.concat({ALL_CHANNELS: h}, names=[CHANNEL]).reorder_levels(["dataset", CHANNEL, "family", "approach"])
    values: dict[tuple[str, str], dict[str, tuple]] = {}
    for (ds, ch, fam, app), row in h.iterrows():
        key = (_case_label(ds, ch), f"{fam}*" if fam in ref else fam)
        cells = values.setdefault(key, {})
        if not (_is_missing(row["val_rate_worst"]) and _is_missing(row["val_rate_mean"])):
            cells[f"{app}:val"] = (row["val_rate_worst"], row["val_rate_mean"], row["val_worst_residual_um"])
        if not (_is_missing(row["states_rate_worst"]) and _is_missing(row["states_rate_mean"])):
            cells[f"{app}:states"] = (row["states_rate_worst"], row["states_rate_mean"],
                                      row["states_worst_residual_um"])
    present = _unique(c for cells in values.values() for c in cells)

    def col_rank(c):
        app, part = c.rsplit(":", 1)
        return (_approach_rank(app), part != "val")

    order = sorted(present, key=col_rank)

    def render(columns: list[str], decimals: int) -> str:
        table = pd.DataFrame.from_dict(
            {k: {c: _cell(*v, decimals=decimals) for c, v in cells.items()} for k, cells in values.items()},
            orient="index",
        ).reindex(columns=columns).fillna("-")
        table.index = pd.MultiIndex.from_tuples(list(values), names=["dataset", "family"])
        return table.to_string(index_names=False, max_colwidth=60)

    def width(text: str) -> int:
        return max(map(len, text.splitlines()))

    if not order:
        body = "(no unseen runs in results)"
    else:
        for decimals in (1, 0):
            body = render(order, decimals)
            if width(body) <= TERMINAL_WIDTH:
                break
        else:  # still too wide: blocks of columns, each with the row labels
            blocks, cur = [], []
            for c in order:
                if cur and width(render(cur + [c], 0)) > TERMINAL_WIDTH:
                    blocks.append(cur)
                    cur = []
                cur.append(c)
            blocks.append(cur)
            body = "\n\n".join(render(b, 0) for b in blocks)
    legend = [
        "Compensation on runs each model was NOT trained on (thermbench robustness benchmark)",
        "cell = worst/mean compensation rate (%), worst max|residual| (um); "
        "val = validation runs, states = other states",
    ]
    if ref:
        legend.append("* = baseline family (for comparison, never chosen)")
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
    "state plus a condition classifier that picks the model for the running duty (seed 002 §2.4); *bank_soft* = the "
    "same models blended by the classifier's probabilities. *Worst* is the "
    "lowest rate / the largest residual. In the heatmaps the colour is the compensation rate, blue = good, white = no "
    "gain, red = worse than not compensating, clipped to ±100 % so a model that fails badly still shows as deep red; "
    "the printed numbers are the true values, with the max residual in µm below the rate. Outlined cells are a "
    "model's own training state. In the before/after plots the black line is the uncompensated thermal error "
    "(max over the targets of each measuring cycle) and each coloured line the residual left by one model "
    "(colour = family, line style = approach: dotted single, solid global, dashed bank, dash-dotted bank_soft)."
)

HOW_TO_READ_CHANNELS = (
    "**Datasets with several error channels** (e.g. the five displacement sensors of a spindle test, ch1 … ch5) are "
    "scored per channel: each channel has its own models, trained and tested on that channel only. Their sections "
    "compare the *RMSE* of the residual (µm, lower is better) on the validation run(s): per channel, family and "
    "approach, where *single* is the mean over the single-state models (what training on one state gives on average; "
    "(k/N) when only k of the N states could be fitted). In their train × test heatmaps the colour is the RMSE on a "
    "log scale shared by every family of the dataset (light = small, dark red = large); outlined cells are runs the "
    "model was trained on."
)
HOW_TO_READ_BASELINES = (
    "**Baselines** (reference families: compared, never chosen for deployment) are marked *(baseline)* in the "
    "tables and figures, hatched grey in the bar charts and `*` in the summary."
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


def _headline_md(h: pd.DataFrame, runs: list[str], ref: frozenset[str] = frozenset()) -> str:
    """One dataset's headline rows: aggregates, then 'rate / max µm' per validation run."""
    drop = [lvl for lvl in ("dataset", CHANNEL) if lvl in h.index.names]
    t = h.reset_index(level=drop, drop=True).reset_index()
    t["family"] = [_family_label(f, ref) for f in t["family"]]
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


#: a run-metadata value longer than this is a bullet below the table, not a cell that widens every row
META_CELL_CHARS = 100


def _meta_md(meta: Mapping | None, lists_file: str | None = None) -> str:
    """The run's metadata (``meta``: name -> value) as a table of short values. A longer value is a
    bullet below the table (``- **name**: value``), so one long entry does not widen every row. A list of
    findings is one bullet each: below the table, or with ``lists_file`` (a file name, see
    :func:`_lists_md`) in that file, and its row links there."""
    if not meta:
        return "_No run metadata was given._"
    rows, long, lists = [], [], []
    for k, v in meta.items():
        if isinstance(v, Mapping):
            v = ", ".join(f"{a}={b}" for a, b in v.items())
        if isinstance(v, (list, tuple)):
            lists.append((str(k), v))
            v = f"{len(v)}, in [{lists_file}]({lists_file})" if lists_file else f"{len(v)}, listed below"
        elif len(str(v)) > META_CELL_CHARS:
            long.append(f"- **{k}**: " + (f"`{v}`" if k == "command" else str(v)))
            continue
        rows.append({"": str(k), "value": f"`{v}`" if k == "command" else str(v)})
    parts = [markdown_table(pd.DataFrame(rows), index=False)] if rows else []
    if long:
        parts += ["", *long]
    if not lists_file:
        for k, items in lists:
            parts += ["", f"**{k}**", "", *(f"- {x}" for x in items)]
    return "\n".join(parts)


def _lists_md(meta: Mapping | None) -> str | None:
    """The list-valued entries of the run's metadata (findings such as the flagged models), a section
    each with one bullet per finding; None when there are none."""
    lists = [(str(k), v) for k, v in (meta or {}).items() if isinstance(v, (list, tuple))]
    if not lists:
        return None
    md = ["# Findings of the run", "", f"Back to [the report]({REPORT_NAME}).", ""]
    for k, items in lists:
        md += [f"## {k} ({len(items)})", "", *(f"- {x}" for x in items), ""]
    return "\n".join(md).rstrip() + "\n"


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


def _model_label(key, single_mean: bool = True) -> str:
    fam, app = key
    return f"{fam} · {app}" + (" mean" if app == "single" and single_mean else "")


def _channel_table_md(t: pd.DataFrame, ref: frozenset[str], n_states: int, fmt: Callable,
                      lower_is_better: bool) -> str:
    """:func:`validation_by_channel` as markdown: a row per (family, approach), a column
    per channel, the best of each column in bold, (k/N) where single had k of N states."""
    counts = t.attrs.get("n_models")
    best = {}
    for ch in t.columns:
        col = t[ch].dropna()
        if len(col):
            best[ch] = col.idxmin() if lower_is_better else col.idxmax()
    rows = []
    for key in t.index:
        fam, app = key
        row = {"family": _family_label(fam, ref), "approach": "single (mean)" if app == "single" else app}
        for ch in t.columns:
            v = t.at[key, ch]
            text = fmt(v)
            if app == "single" and counts is not None and not _is_missing(v) and 0 < n_states:
                k = int(counts.at[key, ch])
                if k < n_states:
                    text += f" ({k}/{n_states})"
            row[ch] = f"**{text}**" if best.get(ch) == key else text
        rows.append(row)
    return markdown_table(pd.DataFrame(rows), index=False)


def _best_lines(t: pd.DataFrame, ref: frozenset[str]) -> list[str]:
    """Per channel: best thermbench family vs best baseline, RMSE in µm."""
    b = best_by_channel(t, ref)
    lines = []
    for ch, row in b.iterrows():
        if row["family"] is None and row["baseline"] is None:
            lines.append(f"- **{ch}**: nothing scored.")
        elif row["baseline"] is None:
            lines.append(f"- **{ch}**: best thermbench family {fmt_um(row['family_value'])} µm "
                         f"({_model_label(row['family'])}); no baseline family in the results.")  # fmt: skip
        elif row["family"] is None:
            lines.append(f"- **{ch}**: only baselines scored; best baseline {fmt_um(row['baseline_value'])} µm "
                         f"({_model_label(row['baseline'])}).")  # fmt: skip
        else:
            better = "better" if row["family_value"] < row["baseline_value"] else "NOT better"
            lines.append(
                f"- **{ch}**: best thermbench family vs best baseline: {fmt_um(row['family_value'])} µm vs "
                f"{fmt_um(row['baseline_value'])} µm ({_model_label(row['family'])} vs "
                f"{_model_label(row['baseline'])}; {better} than the baseline)."
            )
    return lines


def _channels_headline_md(r: pd.DataFrame, ds: str, ref: frozenset[str]) -> list[str]:
    chans, runs, states = _channels(r, ds), _runs(r, ds, "validation"), _runs(r, ds, "state")
    md = [f"### {ds} ({len(chans)} error channels: {', '.join(chans)})", ""]
    if not runs:
        return md + ["_No validation runs for this dataset._", ""]
    t = validation_by_channel(r, ds, RMSE)
    md += [
        f"RMSE (µm) of the residual on the validation run(s) {', '.join(runs)}"
        + (" (mean over them)" if len(runs) > 1 else "")
        + ", per channel; single (mean) = mean over the single-state models; bold = best of the channel.",
        "",
        _channel_table_md(t, ref, len(states), fmt_um, lower_is_better=True),
        "",
        *_best_lines(t, ref),
        "",
    ]
    return md


def _channels_section(r: pd.DataFrame, c: pd.DataFrame | None, ds: str, ref: frozenset[str], fig_dir: Path,
                      fig_name: Callable[..., str], draw: "_Drawing") -> list[str]:
    """The section of a dataset scored on several error channels (see :func:`write_report`)."""
    chans, runs, states = _channels(r, ds), _runs(r, ds, "validation"), _runs(r, ds, "state")
    d = r[r["dataset"] == ds]
    md = [f"## {ds}", ""]
    md += [
        f"Scored on {len(chans)} error channels ({', '.join(chans)}), each with its own models; modelling states "
        f"{', '.join(states) or '—'}; validation run(s) {', '.join(runs) or '—'}. The validation RMSE table is in "
        "the headline above.",
        "",
    ]
    rmse_t = validation_by_channel(r, ds, RMSE) if runs else None
    if runs:
        name = fig_name("rmse_bars", ds)
        draw(_bars_figure, rmse_t, ref, runs, ds, fig_dir / name)
        md += ["### Validation RMSE per channel", "", f"![{ds} validation RMSE per channel]({FIGURES_DIR}/{name})", ""]
        rate_t = validation_by_channel(r, ds, RATE)
        md += [
            "### Validation compensation rate per channel",
            "",
            "1 − max|residual| / max|thermal error| on the validation run(s); single (mean) = mean over the "
            "single-state models; bold = best of the channel.",
            "",
            _channel_table_md(rate_t, ref, len(states), fmt_rate, lower_is_better=False),
            "",
        ]
    else:
        md += ["_No validation runs for this dataset._", ""]

    md += [
        "### Train × test RMSE per family",
        "",
        "Rows: the state a single-state model was trained on, then the models trained on all states (global, bank); "
        "columns: the modelling states, then (right of the line) the validation run(s); one panel per channel; "
        "RMSE in µm, outlined = trained on that run; grey n/a = not fitted.",
        "",
    ]
    tests = states + runs
    panels_by_family, all_values = {}, []
    by_model = dict(list(d.groupby(["family", CHANNEL], sort=False)))
    for fam in _unique(d["family"]):
        models = _matrix_models(d[d["family"] == fam], states)
        panels = [(ch, *_test_matrix(by_model.get((fam, ch), d.iloc[:0]), RMSE, models, tests)) for ch in chans]
        panels_by_family[fam] = panels
        all_values += [p[1].to_numpy(float).ravel() for p in panels]
    norm = _rmse_norm(np.concatenate(all_values) if all_values else np.array([]))
    for fam, panels in panels_by_family.items():
        label = _family_label(fam, ref)
        name = fig_name("rmse_matrix", ds, fam)
        draw(_rmse_heatmap_figure, panels, len(states), norm, f"{ds} · {label}: RMSE (µm), trained on (rows) × tested "
             "on (columns), per channel", fig_dir / name)  # fmt: skip
        md += [f"#### {label}", "", _rmse_matrix_summary(panels, states), "",
               f"![{ds} {fam} RMSE matrix]({FIGURES_DIR}/{name})", ""]  # fmt: skip

    md += ["### Before / after compensation: best model per channel", ""]
    items, notes = [], []
    if rmse_t is not None and c is not None:
        cd = c[(c["dataset"] == ds) & c["run_id"].isin(runs)]
        have = set(zip(cd[CHANNEL], cd["family"], cd["approach"]))
        for ch in chans:
            col = rmse_t[ch].dropna()
            with_curves = [k for k in col.index if k[1] != "single" and (ch, *k) in have]
            fams = [k for k in with_curves if k[0] not in ref]
            bases = [k for k in with_curves if k[0] in ref]
            if not fams:
                notes.append(f"- **{ch}**: no curves of a thermbench family.")
                continue
            best = min(fams, key=lambda k: col[k])
            base = min(bases, key=lambda k: col[k]) if bases else None
            overall = col[[k for k in col.index if k[0] not in ref]]
            line = f"- **{ch}**: {_model_label(best)} ({fmt_um(col[best])} µm)"
            if base is not None:
                line += f" vs baseline {_model_label(base)} ({fmt_um(col[base])} µm)"
            if len(overall) and overall.idxmin() != best:
                k = overall.idxmin()
                line += (f"; the lowest thermbench RMSE, {_model_label(k)} ({fmt_um(col[k])} µm), has no curves "
                         "(single-state models are scored, not plotted)")  # fmt: skip
            notes.append(line + ".")
            for run in runs:
                sel = cd[(cd[CHANNEL] == ch) & (cd["run_id"] == run)]
                bc = sel[(sel["family"] == best[0]) & (sel["approach"] == best[1])]
                if bc.empty:
                    continue
                item = {"channel": ch, "run": run, "best": best, "best_value": float(col[best]), "best_curve": bc}
                if base is not None:
                    bb = sel[(sel["family"] == base[0]) & (sel["approach"] == base[1])]
                    if len(bb):
                        item |= {"base": base, "base_value": float(col[base]), "base_curve": bb}
                items.append(item)
    if items:
        name = fig_name("best_curves", ds)
        draw(_best_curves_figure, items, ds, fig_dir / name)
        md += ["The best thermbench model per channel that has before/after curves (lowest validation RMSE, "
               "baselines excluded), with the best baseline for comparison:", "", *notes, "",
               f"![{ds} before/after, best model per channel]({FIGURES_DIR}/{name})", ""]  # fmt: skip
    else:
        md += ["_No before/after curves for this dataset's validation runs._", *([""] + notes if notes else []), ""]
    return md


def _rmse_matrix_summary(panels, states: list[str]) -> str:
    """One line: per channel the mean RMSE of the single-state models on their own state
    and on the other states."""
    parts = []
    for ch, vals, own in panels:
        single = [i for i in vals.index if i in set(states)]
        if not single:
            continue
        v = vals.loc[single, states].to_numpy(float)
        o = own.loc[single, states].to_numpy(bool)
        mine, other = v[o & np.isfinite(v)], v[~o & np.isfinite(v)]
        if mine.size or other.size:
            parts.append(f"{ch} {fmt_um(mine.mean() if mine.size else np.nan)} / "
                         f"{fmt_um(other.mean() if other.size else np.nan)}")  # fmt: skip
    if not parts:
        return "No single-state models."
    return "Single-state models, mean RMSE on their own state / on the other states (µm): " + "; ".join(parts) + "."


def figure_paths(out_dir) -> list[Path]:
    """The PNGs of the report in ``out_dir`` (``out_dir/figures/*.png``, sorted),
    e.g. to log them as MLflow artifacts."""
    return sorted((Path(out_dir) / FIGURES_DIR).glob("*.png"))


def results_table(results: pd.DataFrame, reference: Sequence[str] = ()) -> pd.DataFrame:
    """``results`` as written to ``results.csv``: the columns of :data:`CSV_COLUMNS`
    (``run_id`` renamed ``test``, ``channel`` filled with ``all`` where missing, ``rmse_um``
    NaN when absent), then ``kind``, ``own``, ``reference`` (the family is a baseline),
    then the other columns as given; rows in report order."""
    r = _check_results(results)
    ref = _reference_set(reference)
    if RMSE not in r.columns:
        r[RMSE] = np.nan
    r["reference"] = r["family"].isin(ref)
    order = [i for *_, g in _groups(r) for i in g.index]
    r = r.loc[order].rename(columns={"run_id": "test"}).reset_index(drop=True)
    lead = list(CSV_COLUMNS) + ["kind", "own", "reference"]
    return r[lead + [col for col in r.columns if col not in lead]]


HELD_OUT_MD = (
    "## Held out: every score on runs the model never saw\n\n"
    "Per dataset and channel, over the folds of the cross-validation (`cv`): the held-out RMSE (µm) of each family "
    "and approach fitted without the fold's runs, and of *thermbench's choice*, the family and approach picked in "
    "each fold by an inner cross-validation on that fold's training runs only (nested: the choice never sees the "
    "runs it is scored on; `chosen` in results.csv). *Beat*: on how many folds its RMSE was below no compensation's "
    "(the RMS of the error itself) and below the best baseline's (the baseline of smallest median). *Interval "
    "covers* / *±*: the share of held-out readings inside the model's prediction interval and its mean half-width "
    "(one model on every training run, `global`: the approaches with an interval)."
)
HELD_OUT_COLUMNS = {"model": "model", "folds": "folds", "median_rmse_um": "median RMSE µm",
                    "worst_rmse_um": "worst RMSE µm", "beat_no_compensation": "beat no compensation",
                    "beat_best_baseline": "beat the best baseline", "coverage": "interval covers",
                    "half_width_um": "± µm"}  # fmt: skip

LIMITS_MD = (
    "### What limits the held-out error\n\n"
    "Per dataset and channel: thermbench's choice against the best baseline (the ratio of their median held-out RMSE, "
    "below 1 the choice is better), and the evidence the data hold (thermbench/evidence.py): the share of a fold's "
    "held-out readings with some input (a temperature rise, an operating signal) outside the range of its training "
    "runs, and the input furthest out; the error's short-term scatter (second differences at each measuring "
    "position, an upper estimate of the measurement noise); the choice's inner cross-validation RMSE (training runs "
    "held out from each other) against its held-out RMSE."
)
LIMITS_COLUMNS = {"choice_median_um": "choice median µm", "baseline_median_um": "best baseline µm", "ratio": "ratio",
                  "outside_range_median": "held-out readings outside the training range (median fold)",
                  "outside_range_worst": "(worst fold)", "worst_fold": "worst fold", "furthest_input": "input furthest out",
                  "excursion": "by (its unit)", "scatter_um": "error scatter µm",
                  "inner_cv_median_um": "choice's inner CV median µm"}  # fmt: skip


#: the probe approaches' strategies (thermbench.adapt.probe_replays, benchmark.gp_refit_results)
PROBE_STRATEGIES = {"adaptive": "adaptive (bias + gain filter)", "naive_probe": "naive (last residual added)",
                    "gp_refit": "GP refit on all data so far", "open_loop": "open loop (no probes)"}  # fmt: skip


def probe_curve(r: pd.DataFrame) -> pd.DataFrame:
    """RMSE against probes per hour: per (dataset, channel, family, strategy, schedule) the mean
    over the held-out runs of the RMSE (on the readings that were not probes), the probes per
    hour, the coverage and half-width of the 90 % interval, beside the same runs' open-loop
    (global) scores at 0 probes. Empty without probe rows."""
    cov = next((c for c in r.columns if str(c).startswith("coverage_")), None)
    is_probe = r["approach"].astype(str).str.match(r"^(adaptive|naive_probe|gp_refit)-")
    if "probes_per_h" not in r.columns or not is_probe.any():
        return pd.DataFrame()
    pr = r[is_probe].copy()
    pr["strategy"] = pr["approach"].str.split("-", n=1).str[0]
    pr["schedule"] = pr["approach"].str.split("-", n=1).str[1]
    ch = CHANNEL if CHANNEL in r.columns else None
    keys = ["dataset", *([ch] if ch else []), "family", "fold", "run_id"]
    held = pr[keys].drop_duplicates()
    gl = r[(r["approach"] == "global")].merge(held, on=keys)
    gl = gl.assign(strategy="open_loop", schedule="none", probes_per_h=0.0)
    both = pd.concat([pr, gl], ignore_index=True)
    agg = {"rmse_um": ("rmse_um", "mean"), "probes_per_h": ("probes_per_h", "mean"), "runs": ("run_id", "count")}
    if cov:
        agg.update(coverage=(cov, "mean"), half_width_um=("half_width_um", "mean"))
    out = both.groupby(["dataset", *([ch] if ch else []), "family", "strategy", "schedule"], sort=False).agg(**agg)
    return out.reset_index().sort_values(["dataset", *([ch] if ch else []), "family", "strategy", "probes_per_h"])


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


PROBES_MD = (
    "## Probe readings: RMSE against probes per hour\n\n"
    "Each held-out run replayed with probe readings taken from its own measurements (approaches "
    "`adaptive-<every>s`, the bias + gain filter; `naive_probe-<every>s`, the last probe's residual added; "
    "`gp_refit-<every>s`, the GP refitted on all data so far; `adaptive-uncertainty`, probing when the filter's "
    "uncertainty exceeds its level), scored on the readings that were not probes, beside the same runs open "
    "loop. These rows never take part in choosing the model to deploy: they use the scored run's own readings."
)


def write_report(results: pd.DataFrame, curves: pd.DataFrame | None, out_dir, meta: Mapping | None = None,
                 force: bool = False, reference: Sequence[str] = (), n_jobs: int = 1,
                 held_out: pd.DataFrame | None = None, limits: pd.DataFrame | None = None,
                 failed: pd.DataFrame | None = None, answer: pd.DataFrame | None = None, level: float = 0.9) -> Path:
    """Write ``out_dir/report.md`` (the answer), ``out_dir/details.md`` (everything behind it), their
    figures ``out_dir/figures/*.png``, ``out_dir/results.csv`` (:func:`results_table`) and, when ``meta``
    holds lists of findings, ``out_dir/findings.md``; return the path of report.md.

    ``reference``: the baseline families (compared, never chosen): marked in the tables
    and figures, ``reference`` true in results.csv. ``n_jobs``: processes that draw the
    figures (:class:`_Drawing`). ``answer``: the benchmark's answer
    (:func:`thermbench.summary.answer_table`), report.md's first screen: its table, its figure
    (``figures/summary.png``) and what the columns mean (``level``: the intervals' level).
    ``held_out``: the benchmark's held-out table (:func:`thermbench.benchmark.held_out_table`), one
    table per case; ``limits``: per case the choice against the best baseline and what limits it
    (:func:`thermbench.evidence.held_out_limits`). ``failed``: the cells that could not fit or predict
    (dataset, channel, family, approach, fold, inner_fold, failure), appended to results.csv as rows of
    kind ``failed`` with their one-line reason in ``failure``.

    report.md: the answer, the held-out tables, what limits the held-out error, then the run
    (``meta``, :func:`_meta_md`: short values in a table, longer ones as bullets, lists of findings in
    findings.md, linked) and the links to details.md and results.csv. details.md: how to read, the
    terminal summary, the headline tables (:func:`headline`, one per dataset), then per dataset: single
    vs global vs bank on the validation runs (:func:`approach_comparison`, table + heatmap), the
    train × test heatmap per family (:func:`train_test_matrix` of the compensation rate, max residual
    annotated) and the before/after compensation curves of the validation runs (``curves``; None or an
    empty frame means no curves, the report says so), then the probe readings.

    A dataset scored on several error channels is laid out by channel instead: its
    headline is the validation RMSE per channel (:func:`validation_by_channel`; rows =
    family × approach, best per channel in bold, then per channel the best thermbench
    family vs the best baseline, :func:`best_by_channel`); its section has the bar chart
    of that RMSE (a panel per channel, baselines hatched grey), the validation
    compensation rate per channel, one train × test RMSE heatmap per family (a panel per
    channel; rows = training state, then global / bank / bank_soft; columns = the states,
    then the validation runs) and the before/after curves of the best thermbench model
    per channel that has curves (with the best baseline). It needs ``rmse_um``.

    Written as one output of kind ``report`` (:func:`thermbench.outputs.output_dir`): the
    figures, results.csv and report.md are rendered into a staging directory and replace
    the previous report's files only when all are done, so any failure leaves the previous
    report untouched; a directory holding anything else is refused (``force``: written
    beside it). List the PNGs with :func:`figure_paths`.
    """
    r = _check_results(results)
    ref = _reference_set(reference) & set(r["family"])
    no_curves = curves is None or (isinstance(curves, pd.DataFrame) and curves.empty)
    c = None if no_curves else _check_curves(curves)
    datasets = _unique(r["dataset"])
    multi = [ds for ds in datasets if len(_channels(r, ds)) > 1]
    if multi and RMSE not in r.columns:
        raise ValueError(f"results has no column {RMSE!r}, needed for dataset(s) {multi} scored on several channels")
    table = results_table(r, ref)
    if failed is not None and len(failed):
        table = pd.concat([table, failed.assign(reference=failed["family"].isin(ref))], ignore_index=True)
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

    md: list[str] = ["# Thermal-error robustness report", ""]  # report.md: the answer and the held-out evidence
    answer_fig = None
    if answer is not None and len(answer):
        from .summary import answer_figure, answer_markdown

        answer_fig = fig_name("summary")
        md += answer_markdown(answer, level, f"{FIGURES_DIR}/{answer_fig}")
    if held_out is not None and not held_out.empty:
        md += [HELD_OUT_MD, ""]
        for case, g in held_out.groupby("case", sort=False):
            md += [f"### {case}", "", markdown_table(g.drop(columns="case"), index=False, headers=HELD_OUT_COLUMNS,
                                                           formats={"coverage": _percent}), ""]
    if limits is not None and not limits.empty:
        md += [LIMITS_MD, ""]
        md += [f"- **{r['case']}**: {r['verdict']}" for r in limits.to_dict("records")] + [""]
        md += [markdown_table(limits.drop(columns="verdict"), index=False, headers=LIMITS_COLUMNS,
                                 formats={"ratio": lambda v: f"{v:.2f}×"}), ""]
    findings = _lists_md(meta)
    md += ["## The run", "", _meta_md(meta, FINDINGS_NAME if findings else None), ""]
    md += [f"Everything behind these tables is in [{DETAILS_NAME}]({DETAILS_NAME}): how to read it, the terminal summary, "
           "the headline tables on unseen cycles and, per dataset, the comparison of approaches, the train × test "
           f"matrices and the before / after curves. The scores, one row per (fitted model, test run), are in "
           f"[{CSV_NAME}]({CSV_NAME}).", ""]  # fmt: skip
    details: list[str] = ["# Thermal-error robustness report: the details", "",
                          f"What the models were chosen on and scored by; the answer is in [{REPORT_NAME}]({REPORT_NAME}).",
                          "", HOW_TO_READ, ""]  # fmt: skip
    if multi:
        details += [HOW_TO_READ_CHANNELS, ""]
    if ref:
        details += [HOW_TO_READ_BASELINES, ""]
    details += ["## At a glance", "", "```text", terminal_summary(r, reference=ref), "```", ""]
    details += ["## Headline: unseen cycles", ""]
    details += [
        "Per dataset, family and approach: mean rate on the training runs (reference), worst and mean rate and worst "
        "max residual over the validation runs, the same over the other modelling states for single-state models, "
        "then rate / max residual per validation run (single: mean over the training states).",
        "",
    ]
    for ds in datasets:
        if ds in multi:
            details += _channels_headline_md(r, ds, ref)
            continue
        ch = _channels(r, ds)[0]
        rows = h.xs((ds, ch), level=("dataset", CHANNEL), drop_level=False) if CHANNEL in h.index.names else \
            h.xs(ds, level="dataset", drop_level=False)  # fmt: skip
        details += [f"### {_case_label(ds, ch)}", "", _headline_md(rows, _runs(r, ds, "validation"), ref), ""]

    with output_dir(out_dir, "report", force=force) as stage:
        fig_dir = stage / FIGURES_DIR
        fig_dir.mkdir()
        draw = _Drawing()
        if answer_fig:
            draw(answer_figure, answer, fig_dir / answer_fig)
        table.to_csv(stage / CSV_NAME, index=False, lineterminator="\n")
        for ds in datasets:
            if ds in multi:
                details += _channels_section(r, c, ds, ref, fig_dir, fig_name, draw)
                continue
            ch = _channels(r, ds)[0]
            label = _case_label(ds, ch)
            parts = (ds,) if ch == ALL_CHANNELS else (ds, ch)
            details += [f"## {label}", ""]
            runs = _runs(r, ds, "validation")
            details += ["### Single vs global vs bank on the validation runs", ""]
            if runs:
                comp = approach_comparison(r, ds, channel=ch)
                if ref:
                    comp.index = pd.MultiIndex.from_tuples([(_family_label(f, ref), m) for f, m in comp.index],
                                                           names=comp.index.names)  # fmt: skip
                name = fig_name("compare", *parts)
                draw(_comparison_figure, comp, runs, label, fig_dir / name)
                details += [
                    "Compensation rate per validation run; single best / worst = the training state with the highest "
                    "/ lowest mean rate over these runs.",
                    "",
                    markdown_table(
                        comp,
                        formats={"trained_on": str, **{run: fmt_rate for run in runs}},
                        headers={"mean_rate": "mean", "worst_rate": "worst", "worst_residual_um": "worst max µm"},
                    ),
                    "",
                    f"![{label} comparison]({FIGURES_DIR}/{name})",
                    "",
                ]
            else:
                details += ["_No validation runs for this dataset._", ""]

            details += ["### Train × test matrices (single-state models)", ""]
            single = r[(r["dataset"] == ds) & (r["approach"] == "single") & (r["kind"] == "state")]
            fams = _unique(single["family"])
            if not fams:
                details += ["_No single-state models for this dataset._", ""]
            for fam in fams:
                rate = train_test_matrix(r, ds, fam, RATE, channel=ch)
                resid = train_test_matrix(r, ds, fam, RESIDUAL, channel=ch)
                name = fig_name("matrix", *parts, fam)
                draw(_matrix_figure, rate, resid, label, _family_label(fam, ref), fig_dir / name)
                details += [f"#### {_family_label(fam, ref)}", "", _matrix_summary(rate, resid), ""]
                details += [f"![{label} {fam} matrix]({FIGURES_DIR}/{name})", ""]

            details += ["### Before / after compensation (validation runs)", ""]
            cd = None if c is None else \
                c[(c["dataset"] == ds) & c[CHANNEL].isin([ch, ALL_CHANNELS]) & c["run_id"].isin(runs)]
            plotted = [run for run in runs if cd is not None and (cd["run_id"] == run).any()]
            if plotted:
                name = fig_name("curves", *parts)
                draw(curves_figure, cd, plotted, f"{label}, validation runs", fig_dir / name)
                details += [f"![{label} before/after]({FIGURES_DIR}/{name})", ""]
                missing = [run for run in runs if run not in plotted]
                if missing:
                    details += [f"_No curves for validation run(s) {', '.join(missing)}._", ""]
            else:
                details += ["_No before/after curves for this dataset's validation runs._", ""]
        curve = probe_curve(r)
        if len(curve):
            details += [PROBES_MD, ""]
            for ds in _unique(curve["dataset"]):
                cd = curve[curve["dataset"] == ds]
                name = fig_name("probes", ds)
                draw(probe_figure, cd, str(ds), fig_dir / name, 4, ref)
                details += [f"### {ds}", "", f"![{ds} probes]({FIGURES_DIR}/{name})", "",
                            markdown_table(cd.drop(columns="dataset").round(3), index=False), ""]  # fmt: skip
        draw.run(n_jobs)
        for name, lines in ((REPORT_NAME, md), (DETAILS_NAME, details)):
            (stage / name).write_text("\n".join(lines).rstrip() + "\n", encoding="utf-8")
        if findings:
            (stage / FINDINGS_NAME).write_text(findings, encoding="utf-8")
    return out_dir / REPORT_NAME
