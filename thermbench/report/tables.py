"""The robustness report's tables, pure pandas: what the report shows, computed from the results and
curves frames (their schema and checks: :mod:`thermbench.bench.results`): the train × test matrix of a
family, the headline on unseen cycles, the comparison of approaches, the validation RMSE per channel
and the best per channel, the probe curve, and the rows of results.csv (:func:`results_table`). No
text, no figures.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import pandas as pd

import thermbench

from ..bench.results import ALL_CHANNELS, APPROACH_ORDER, CHANNEL, CSV_COLUMNS, RATE, RESIDUAL, RMSE, _check_results


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


def _model_label(key, single_mean: bool = True) -> str:
    fam, app = key
    return f"{fam} · {app}" + (" mean" if app == "single" and single_mean else "")


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


#: the probe approaches' strategies (thermbench.bench.adapt.probe_replays, benchmark.gp_refit_results)
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


__getattr__ = thermbench.moved_names(__name__)  # the results' schema moved to bench/results.py
