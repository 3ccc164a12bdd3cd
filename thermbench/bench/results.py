"""The benchmark's results and curves frames: their columns, and their checks. One row of results per
(fitted model, test run): the frame the benchmark's cells make (:mod:`.run`), the choice reads
(:mod:`.choice`) and results.csv is written from (:func:`thermbench.report.results_table`, the columns of
:data:`CSV_COLUMNS` first). One row of curves per reading of a before/after curve.
"""

from __future__ import annotations

from typing import Sequence

import pandas as pd


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


#: the leading columns of results.csv, in this order (``test`` = the run scored)
CSV_COLUMNS = ("dataset", "family", "approach", "train", "test", "channel", RMSE, RESIDUAL, RATE)


_KEYS = ("dataset", "channel", "family", "approach", "train", "run_id")


_STR_COLUMNS = ("dataset", "family", "approach", "train", "run_id", "kind")


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
