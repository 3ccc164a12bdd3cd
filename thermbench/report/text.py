"""The robustness report's text: number formats, markdown tables (:func:`markdown_table`) and the
one-screen terminal summary (:func:`terminal_summary`).
"""

from __future__ import annotations

import math
from typing import Callable, Mapping, Sequence

import numpy as np
import pandas as pd

from ..bench.results import ALL_CHANNELS, CHANNEL, _check_results
from .tables import _approach_rank, _case_label, _has_channels, _reference_set, _unique, headline


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