"""Figures of the machine-tool acceptance standards ISO 230-2 and ISO 230-3, computed from tables.

Pure functions (numpy and pandas only, no I/O) that turn measured deviations into the figures a
machine-tool metrologist reports:

* ISO 230-2:2014 (accuracy and repeatability of positioning of numerically controlled axes):
  :func:`positioning_statistics` (per target and per axis: mean unidirectional and bidirectional
  positional deviations, estimators of the unidirectional standard uncertainty, repeatability,
  reversal value, systematic positional deviation, mean bidirectional positional deviation range,
  accuracy) and :func:`positioning_statistics_by` (the same per group, e.g. per measuring block or
  per hour of a warm-up, to follow the drift of the figures with temperature / time).
* ISO 230-3:2020 (determination of thermal effects): :func:`drift_summary` (a fixed-point
  displacement channel, e.g. X1/X2/Y1/Y2/Z at a test mandrel, clauses 5 and 6), :func:`tilt`
  (angular drift from two paired sensors, clause 6), :func:`error_line` / :func:`error_lines`
  (offset and slope of the positioning error line per measuring cycle, the along-axis drift of
  clause 7, thermal distortion caused by moving linear axes) and
  :func:`environmental_variation_error` (the ETVE figure of clause 5).

Units are in the names: ``_um`` micrometres, ``_mm`` millimetres, ``_s`` seconds, ``_C`` degrees
Celsius, ``_um_per_m`` micrometres per metre (= microradians for an angle).

These functions compute the standards' *figures* from whatever data they are given; they do not
check that the data were taken by the standards' *procedures* (number of cycles and targets,
feed, dwell, warm-up, test duration, environment, measurement uncertainty per ISO/TR 230-9).
Each docstring says where the computation is simpler than the standard.

Every function validates its inputs and raises :class:`ValueError` naming the argument or column
and what was expected.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import pandas as pd

__all__ = [
    "POSITIONING_COLUMNS",
    "drift_summary",
    "environmental_variation_error",
    "error_line",
    "error_lines",
    "positioning_statistics",
    "positioning_statistics_by",
    "tilt",
]

#: the columns :func:`positioning_statistics` reads
POSITIONING_COLUMNS = ("target_mm", "direction", "cycle", "deviation_um")

#: the per-target columns of :func:`positioning_statistics`, in order
PER_TARGET_COLUMNS = (
    "target_mm", "n_up", "n_down",
    "mean_up_um", "mean_down_um", "s_up_um", "s_down_um", "R_up_um", "R_down_um",
    "B_um", "mean_bidir_um", "R_bidir_um",
)

#: the axis figures of :func:`positioning_statistics`, in order
AXIS_KEYS = (
    "A_up_um", "A_down_um", "A_um", "E_up_um", "E_down_um", "E_um", "M_um",
    "R_up_um", "R_down_um", "R_um", "B_um", "B_signed_um", "B_target_mm", "B_mean_um",
    "n_cycles", "n_targets",
)

_NAN = float("nan")


# ------------------------------------------------------------------ validation helpers ---
def _check_frame(df, name: str, columns: Iterable[str]) -> None:
    if not isinstance(df, pd.DataFrame):
        raise ValueError(f"{name}: expected a pandas DataFrame, got {type(df).__name__}")  # noqa: TRY004 (one error type for every bad input)
    missing = [c for c in columns if c not in df.columns]
    if missing:
        raise ValueError(
            f"{name}: missing column(s) {', '.join(repr(c) for c in missing)} "
            f"(expected columns {', '.join(repr(c) for c in columns)}; has {list(map(str, df.columns))})"
        )
    if len(df) == 0:
        raise ValueError(f"{name}: empty table (expected at least one row)")


def _numeric_column(df: pd.DataFrame, col: str, name: str) -> np.ndarray:
    s = df[col]
    if pd.api.types.is_bool_dtype(s):
        raise ValueError(f"{name}: column {col!r} must be numeric, got booleans")
    try:
        values = pd.to_numeric(s, errors="raise").to_numpy(dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: column {col!r} must be numeric ({exc})") from None
    bad = ~np.isfinite(values)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{name}: column {col!r} must be finite; {int(bad.sum())} non-finite value(s), "
            f"first at row {df.index[i]!r} ({s.iloc[i]!r})"
        )
    return values


def _array_1d(x, name: str) -> np.ndarray:
    if isinstance(x, (str, bytes)):
        raise ValueError(f"{name}: expected a 1-D sequence of numbers, got a string")  # noqa: TRY004 (one error type for every bad input)
    try:
        a = np.asarray(x, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a 1-D sequence of numbers ({exc})") from None
    if a.ndim != 1:
        raise ValueError(f"{name}: expected a 1-D sequence of numbers, got an array of shape {a.shape}")
    if a.size == 0:
        raise ValueError(f"{name}: empty (expected at least one sample)")
    bad = ~np.isfinite(a)
    if bad.any():
        raise ValueError(
            f"{name}: must be finite; {int(bad.sum())} non-finite value(s), "
            f"first at index {int(np.flatnonzero(bad)[0])}"
        )
    return a


def _same_length(**arrays: np.ndarray) -> None:
    lengths = {k: len(v) for k, v in arrays.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(
            "mismatched lengths: " + ", ".join(f"{k} has {n}" for k, n in lengths.items())
            + " (expected the same number of samples)"
        )


def _strictly_increasing(t: np.ndarray, name: str) -> None:
    if t.size > 1:
        steps = np.diff(t)
        if (steps <= 0).any():
            i = int(np.flatnonzero(steps <= 0)[0])
            raise ValueError(
                f"{name}: must be strictly increasing; {name}[{i + 1}]={t[i + 1]!r} <= {name}[{i}]={t[i]!r}"
            )


def _finite_scalar(x, name: str) -> float:
    try:
        v = float(x)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number, got {x!r}") from None
    if not math.isfinite(v):
        raise ValueError(f"{name}: expected a finite number, got {x!r}")
    return v


def _nan_if_any_nan_max(values: np.ndarray) -> float:
    """max of ``values``; NaN if empty or if any value is NaN (an incomplete set is not a maximum)."""
    if values.size == 0 or np.isnan(values).any():
        return _NAN
    return float(values.max())


def _nan_if_any_nan_min(values: np.ndarray) -> float:
    if values.size == 0 or np.isnan(values).any():
        return _NAN
    return float(values.min())


# ------------------------------------------------------------------------- ISO 230-2 ---
def _validated_readings(readings, name: str = "readings") -> pd.DataFrame:
    _check_frame(readings, name, POSITIONING_COLUMNS)
    target = _numeric_column(readings, "target_mm", name)
    direction = _numeric_column(readings, "direction", name)
    cycle = _numeric_column(readings, "cycle", name)
    deviation = _numeric_column(readings, "deviation_um", name)
    bad = ~np.isin(direction, (1.0, -1.0))
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{name}: column 'direction' must be +1 (positive approach) or -1 (negative approach); "
            f"got {readings['direction'].iloc[i]!r} at row {readings.index[i]!r}"
        )
    bad = cycle != np.round(cycle)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise ValueError(
            f"{name}: column 'cycle' must hold integers (the measuring cycle j); "
            f"got {readings['cycle'].iloc[i]!r} at row {readings.index[i]!r}"
        )
    df = pd.DataFrame({
        "target_mm": target,
        "direction": direction.astype(int),
        "cycle": cycle.astype(np.int64),
        "deviation_um": deviation,
    })
    dup = df.duplicated(["target_mm", "direction", "cycle"], keep=False)
    if dup.any():
        first = df[dup].iloc[0]
        key = (float(first["target_mm"]), int(first["direction"]), int(first["cycle"]))
        raise ValueError(
            f"{name}: duplicated (target_mm, direction, cycle) = {key}: each target, direction and "
            f"cycle must be measured at most once ({int(dup.sum())} rows are duplicates)"
        )
    return df


def _per_direction(df: pd.DataFrame, sign: int) -> pd.DataFrame:
    sub = df[df["direction"] == sign]
    g = sub.groupby("target_mm")["deviation_um"]
    return pd.DataFrame({"n": g.size(), "mean": g.mean(), "s": g.std(ddof=1)})


def positioning_statistics(readings: pd.DataFrame, coverage: float = 2.0) -> dict:
    """ISO 230-2:2014 positioning figures of one axis from bidirectional (or unidirectional) readings.

    ``readings`` columns (other columns are ignored):

    * ``target_mm``: target position P_i (each distinct value is one target);
    * ``direction``: +1 for an approach in the positive direction (↑), -1 negative (↓);
    * ``cycle``: measuring cycle j (integer; the repetition of the test cycle);
    * ``deviation_um``: positional deviation x_ij = actual position reached minus target, µm.

    Each (target, direction, cycle) must occur at most once (ValueError naming the duplicate).

    Per target i and direction (ISO 230-2:2014 clause 3, terms and definitions), with n the
    number of cycles at that target and direction and k = ``coverage`` (the standard's k = 2):

    * mean unidirectional positional deviation x̄_i↑ = (1/n) Σ_j x_ij↑ (``mean_up_um``; ↓ likewise);
    * estimator of the unidirectional standard uncertainty of positioning
      s_i↑ = sqrt(Σ_j (x_ij↑ − x̄_i↑)² / (n − 1)) (``s_up_um``; NaN if n < 2);
    * unidirectional repeatability R_i↑ = 2 k s_i↑ (= 4 s_i↑) (``R_up_um``);
    * reversal value B_i = x̄_i↑ − x̄_i↓ (``B_um``);
    * mean bidirectional positional deviation x̄_i = (x̄_i↑ + x̄_i↓) / 2 (``mean_bidir_um``);
    * bidirectional repeatability R_i = max(k s_i↑ + k s_i↓ + |B_i|; R_i↑; R_i↓) (``R_bidir_um``).

    Axis figures (``axis``), over the targets:

    * ``B_um`` reversal value of the axis B = max_i |B_i|, with ``B_signed_um`` the signed B_i and
      ``B_target_mm`` the target where it occurs (first target on a tie); ``B_mean_um`` mean
      reversal value B̄ = (1/m) Σ_i B_i;
    * ``R_up_um`` / ``R_down_um`` unidirectional repeatability R↑ = max_i R_i↑ (R↓ likewise),
      ``R_um`` bidirectional repeatability R = max_i R_i;
    * ``E_up_um`` / ``E_down_um`` unidirectional systematic positional deviation
      E↑ = max_i x̄_i↑ − min_i x̄_i↑; ``E_um`` bidirectional systematic positional deviation
      E = max(x̄_i↑, x̄_i↓) − min(x̄_i↑, x̄_i↓) over all targets and both directions;
    * ``M_um`` mean bidirectional positional deviation range M = max_i x̄_i − min_i x̄_i;
    * ``A_up_um`` / ``A_down_um`` unidirectional accuracy A↑ = max_i (x̄_i↑ + k s_i↑) − min_i (x̄_i↑ − k s_i↑);
      ``A_um`` bidirectional accuracy A = max over i and both directions of (x̄ + k s) − min over i
      and both directions of (x̄ − k s);
    * ``n_cycles`` (distinct cycle labels) and ``n_targets`` (distinct targets), as floats like
      the rest.

    Returns ``{"per_target": DataFrame, "axis": dict}``: one row per target, sorted by target,
    with the columns ``target_mm, n_up, n_down, mean_up_um, mean_down_um, s_up_um, s_down_um,
    R_up_um, R_down_um, B_um, mean_bidir_um, R_bidir_um``; the axis dict with the keys above, all
    floats, NaN where undefined.

    Differences from the standard's full procedure:

    * The standard test cycle (ISO 230-2 test program) takes at least 5 cycles (n = 5) in each
      direction at at least 5 target positions per metre of travel (and at least 5 overall), with
      randomly spaced targets. These functions compute for any n ≥ 1 and any targets and do not
      check the test program; with few cycles s is a poor estimate.
    * n = 1 (or any target/direction with a single reading): s is undefined (NaN), so R_i and the
      figures built from s (R↑, R↓, R, A↑, A↓, A) are NaN as well: a repeatability or accuracy
      is never reported on s = 0. An axis maximum is NaN as soon as one of the values it is
      taken over is NaN (a maximum over an incomplete set would understate the figure). E, M and
      B do not use s and stay defined.
    * Targets with one direction only (outside the standard): their unidirectional figures are
      computed for that direction; B_i, x̄_i and R_i are NaN and those targets are excluded from
      B, B̄, M and R. E and A use every mean (and s) that exists, so a fully unidirectional run
      has B, B̄, M, R NaN, E = E↑ (or E↓) and A = A↑ (or A↓) of the direction present; the
      unidirectional figures of the absent direction are NaN.
    * Targets are grouped by their exact ``target_mm`` value (round the column first if the
      targets carry measurement noise); the cycles need not be the same at every target (n is
      counted per target and direction).
    * ``coverage`` replaces the factor 2 of the standard wherever it multiplies s (R_i↑ = 2 k s_i↑,
      R_i, A); the measurement uncertainty of ISO 230-2 Annex A / ISO/TR 230-9 is not estimated.
    """
    k = _finite_scalar(coverage, "coverage")
    if k <= 0:
        raise ValueError(f"coverage: expected a positive coverage factor (the standard's is 2), got {coverage!r}")
    df = _validated_readings(readings)

    targets = np.sort(df["target_mm"].unique())
    up = _per_direction(df, +1).reindex(targets)
    down = _per_direction(df, -1).reindex(targets)

    per = pd.DataFrame({"target_mm": targets})
    per["n_up"] = up["n"].fillna(0).to_numpy(dtype=int)
    per["n_down"] = down["n"].fillna(0).to_numpy(dtype=int)
    per["mean_up_um"] = up["mean"].to_numpy(dtype=float)
    per["mean_down_um"] = down["mean"].to_numpy(dtype=float)
    per["s_up_um"] = up["s"].to_numpy(dtype=float)        # NaN for n < 2 (pandas std, ddof=1)
    per["s_down_um"] = down["s"].to_numpy(dtype=float)
    per["R_up_um"] = 2.0 * k * per["s_up_um"]
    per["R_down_um"] = 2.0 * k * per["s_down_um"]
    both = (per["n_up"] > 0) & (per["n_down"] > 0)
    per["B_um"] = np.where(both, per["mean_up_um"] - per["mean_down_um"], np.nan)
    per["mean_bidir_um"] = np.where(both, (per["mean_up_um"] + per["mean_down_um"]) / 2.0, np.nan)
    spread = k * per["s_up_um"] + k * per["s_down_um"] + per["B_um"].abs()
    r_bidir = np.column_stack([spread, per["R_up_um"], per["R_down_um"]]).max(axis=1)  # NaN if any is NaN
    per["R_bidir_um"] = np.where(both, r_bidir, np.nan)
    per = per[list(PER_TARGET_COLUMNS)]

    has_up = per["n_up"].to_numpy() > 0
    has_down = per["n_down"].to_numpy() > 0
    bidir = both.to_numpy()
    mean_up = per["mean_up_um"].to_numpy()[has_up]
    mean_down = per["mean_down_um"].to_numpy()[has_down]
    s_up = per["s_up_um"].to_numpy()[has_up]
    s_down = per["s_down_um"].to_numpy()[has_down]

    def _range(values: np.ndarray) -> float:
        return _NAN if values.size == 0 else float(values.max() - values.min())

    def _accuracy(means: np.ndarray, s: np.ndarray) -> float:
        hi = _nan_if_any_nan_max(means + k * s)
        lo = _nan_if_any_nan_min(means - k * s)
        return hi - lo

    axis: dict[str, float] = {}
    axis["A_up_um"] = _accuracy(mean_up, s_up)
    axis["A_down_um"] = _accuracy(mean_down, s_down)
    axis["A_um"] = _accuracy(np.concatenate([mean_up, mean_down]), np.concatenate([s_up, s_down]))
    axis["E_up_um"] = _range(mean_up)
    axis["E_down_um"] = _range(mean_down)
    axis["E_um"] = _range(np.concatenate([mean_up, mean_down]))
    axis["M_um"] = _range(per["mean_bidir_um"].to_numpy()[bidir])
    axis["R_up_um"] = _nan_if_any_nan_max(per["R_up_um"].to_numpy()[has_up])
    axis["R_down_um"] = _nan_if_any_nan_max(per["R_down_um"].to_numpy()[has_down])
    axis["R_um"] = _nan_if_any_nan_max(per["R_bidir_um"].to_numpy()[bidir])
    b = per["B_um"].to_numpy()[bidir]
    if b.size:
        i = int(np.argmax(np.abs(b)))                   # first target on a tie
        axis["B_um"] = float(abs(b[i]))
        axis["B_signed_um"] = float(b[i])
        axis["B_target_mm"] = float(per["target_mm"].to_numpy()[bidir][i])
        axis["B_mean_um"] = float(b.mean())
    else:
        axis["B_um"] = axis["B_signed_um"] = axis["B_target_mm"] = axis["B_mean_um"] = _NAN
    axis["n_cycles"] = float(df["cycle"].nunique())
    axis["n_targets"] = float(len(targets))
    return {"per_target": per, "axis": {key: float(axis[key]) for key in AXIS_KEYS}}


def positioning_statistics_by(readings: pd.DataFrame, by: str, coverage: float = 2.0) -> pd.DataFrame:
    """:func:`positioning_statistics` per group of the column ``by`` (e.g. a measuring block, an hour).

    Returns a DataFrame with one row per group (sorted by the group value), the group value in
    column ``by`` first, then the axis figures of :func:`positioning_statistics` (``A_up_um`` ...
    ``n_targets``) computed on that group's rows alone. Shows how the ISO 230-2 figures drift
    while the machine warms up or cools down (ISO 230-3 clause 7 uses repeated positioning
    measurements in the same way); each group is evaluated as an independent ISO 230-2 test, so
    the cycle labels may repeat across groups, and the same (target, direction, cycle) must not
    repeat within a group.

    ``by`` must name a column of ``readings`` without missing values; it may be one of the
    ISO 230-2 columns (``by="cycle"`` gives a single-cycle evaluation per cycle: s, R and A NaN).
    """
    if not isinstance(by, str):
        raise ValueError(f"by: expected a column name (str), got {by!r}")  # noqa: TRY004 (one error type for every bad input)
    _check_frame(readings, "readings", (*POSITIONING_COLUMNS, by))
    if readings[by].isna().any():
        i = int(np.flatnonzero(readings[by].isna().to_numpy())[0])
        raise ValueError(f"readings: column {by!r} (by) has missing values, first at row {readings.index[i]!r}")
    rows = []
    for key, group in readings.groupby(by, sort=True):
        try:
            axis = positioning_statistics(group, coverage=coverage)["axis"]
        except ValueError as exc:
            raise ValueError(f"{by}={key!r}: {exc}") from None
        rows.append({by: key, **axis})
    return pd.DataFrame(rows, columns=[by, *AXIS_KEYS])


# ------------------------------------------------------------------------- ISO 230-3 ---
def _drift_figures(t: np.ndarray, x: np.ndarray, ref: float) -> tuple[float, float, float, float]:
    """(max |x − ref|, signed x − ref there, its time, final x − ref)."""
    d = x - ref
    i = int(np.argmax(np.abs(d)))                        # first sample on a tie
    return float(abs(d[i])), float(d[i]), float(t[i]), float(d[-1])


DRIFT_COLUMNS = (
    "block", "start_s", "end_s", "n_samples",
    "max_drift_um", "max_drift_signed_um", "t_max_drift_s", "range_um", "final_drift_um",
    "max_drift_from_start_um", "max_drift_from_start_signed_um", "t_max_drift_from_start_s",
    "final_drift_from_start_um",
)


def drift_summary(t_s, value_um, blocks: Sequence[tuple[str, float, float]] | None = None) -> pd.DataFrame:
    """Thermal drift of one fixed-point displacement channel (ISO 230-3:2020 clauses 5 and 6).

    ``t_s`` (strictly increasing, s) and ``value_um`` (µm, same length): one channel, e.g. the
    X1, X2, Y1, Y2 or Z displacement measured at a test mandrel in the spindle (clause 6, thermal
    distortion caused by rotating spindles) or between tool side and workpiece side at rest
    (clause 5, ETVE). Drift is the change relative to a reference sample:

    * ``max_drift_um``: max |x − x0| (x0 the reference), ``max_drift_signed_um`` the signed
      x − x0 at that sample (the first one on a tie) and ``t_max_drift_s`` its time;
    * ``range_um``: max x − min x (the same for any reference);
    * ``final_drift_um``: x(last sample) − x0.

    ``blocks``: optional list of ``(name, start_s, end_s)`` (e.g. ``("spindle on", 0, 14400)``,
    ``("spindle off", 14400, 28800)``). Each block takes the samples with start_s ≤ t ≤ end_s
    (closed interval: a sample on a shared boundary belongs to both blocks, so the second block
    starts from the state the first one ended in). For a block, the columns above are relative
    to the block's first sample; the ``*_from_start_*`` columns are the same figures relative to
    the first sample of the whole run.

    Returns a DataFrame with the columns ``block, start_s, end_s, n_samples, max_drift_um,
    max_drift_signed_um, t_max_drift_s, range_um, final_drift_um, max_drift_from_start_um,
    max_drift_from_start_signed_um, t_max_drift_from_start_s, final_drift_from_start_um``: one
    row per block in the given order, then the row ``"all"`` (the whole run; start_s and end_s
    the first and last sample times; its two references coincide).

    Simplification: the standard reports the drift of each channel over the test (and, for
    clause 6, the tilt from paired channels, see :func:`tilt`) with the measurement setup,
    spindle speed programme and durations it prescribes; this function only summarises the
    series it is given, sampled as it is (no interpolation between samples).
    """
    t = _array_1d(t_s, "t_s")
    x = _array_1d(value_um, "value_um")
    _same_length(t_s=t, value_um=x)
    _strictly_increasing(t, "t_s")

    specs: list[tuple[str, float, float]] = []
    if blocks is not None:
        if isinstance(blocks, (str, bytes)) or not isinstance(blocks, Iterable):
            raise ValueError(f"blocks: expected a list of (name, start_s, end_s), got {blocks!r}")
        seen: set[str] = set()
        for j, spec in enumerate(blocks):
            if isinstance(spec, (str, bytes)) or not hasattr(spec, "__len__") or len(spec) != 3:
                raise ValueError(f"blocks[{j}]: expected (name, start_s, end_s), got {spec!r}")
            name, start, end = spec
            if not isinstance(name, str) or not name:
                raise ValueError(f"blocks[{j}]: the name must be a non-empty string, got {name!r}")
            if name == "all":
                raise ValueError(f"blocks[{j}]: the name 'all' is reserved for the whole-run row")
            if name in seen:
                raise ValueError(f"blocks[{j}]: duplicated block name {name!r}")
            seen.add(name)
            start = _finite_scalar(start, f"blocks[{j}] ({name!r}) start_s")
            end = _finite_scalar(end, f"blocks[{j}] ({name!r}) end_s")
            if end < start:
                raise ValueError(f"blocks[{j}] ({name!r}): end_s={end!r} is before start_s={start!r}")
            inside = (t >= start) & (t <= end)
            if not inside.any():
                raise ValueError(
                    f"blocks[{j}] ({name!r}): no sample of t_s in [{start!r}, {end!r}] "
                    f"(t_s runs from {t[0]!r} to {t[-1]!r})"
                )
            specs.append((name, start, end))

    x0_run = float(x[0])
    rows = []
    for name, start, end in specs + [("all", float(t[0]), float(t[-1]))]:
        inside = (t >= start) & (t <= end)
        tb, xb = t[inside], x[inside]
        own = _drift_figures(tb, xb, float(xb[0]))
        run = _drift_figures(tb, xb, x0_run)
        rows.append((name, start, end, int(tb.size), own[0], own[1], own[2],
                     float(xb.max() - xb.min()), own[3], *run))
    return pd.DataFrame(rows, columns=list(DRIFT_COLUMNS))


def tilt(a_um, b_um, spacing_mm: float) -> np.ndarray:
    """Tilt in µrad (= µm/m) from two paired displacement sensors (ISO 230-3:2020 clause 6).

    ``a_um``: the sensor nearer the reference (e.g. X1, near the spindle nose), ``b_um``: the
    paired sensor (X2, farther along the test mandrel), both in µm, ``spacing_mm`` apart along the
    mandrel. tilt = (b − a) / spacing_mm × 1000: µm per mm × 1000 = µm/m = µrad (small angles).
    Positive when b moved more (in the sensors' positive sense) than a.

    ``a_um`` and ``b_um``: scalars or arrays of the same shape, finite; ``spacing_mm`` finite and
    > 0. Returns a float ndarray of that shape (0-d for scalars). The standard reports the tilt
    drift (the change relative to the start of the test); subtract the first value for that.
    """
    spacing = _finite_scalar(spacing_mm, "spacing_mm")
    if spacing <= 0:
        raise ValueError(f"spacing_mm: expected the sensors' spacing in mm, > 0; got {spacing_mm!r}")
    arrays = []
    for name, v in (("a_um", a_um), ("b_um", b_um)):
        if isinstance(v, (str, bytes)):
            raise ValueError(f"{name}: expected numbers, got a string")  # noqa: TRY004 (one error type for every bad input)
        try:
            arr = np.asarray(v, dtype=float)
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{name}: expected numbers ({exc})") from None
        if arr.size == 0:
            raise ValueError(f"{name}: empty (expected at least one value)")
        if not np.isfinite(arr).all():
            raise ValueError(f"{name}: must be finite; {int((~np.isfinite(arr)).sum())} non-finite value(s)")
        arrays.append(arr)
    a, b = arrays
    if a.shape != b.shape:
        raise ValueError(f"mismatched shapes: a_um has shape {a.shape}, b_um has shape {b.shape} (expected the same)")
    return (b - a) / spacing * 1000.0


def error_line(target_mm, deviation_um) -> tuple[float, float]:
    """Least-squares straight line through the positioning deviations of one measuring cycle.

    deviation ≈ offset_um + slope × target. Returns ``(offset_um, slope_um_per_m)``: the offset is
    the line's value at target 0 mm (the axis coordinate origin, not the mean target), the slope
    is in µm per metre of travel (a linear thermal expansion of the axis shows as a slope:
    11.7 µm/m per K for steel).

    ISO 230-3:2020 clause 7 (thermal distortion caused by moving linear axes) follows the
    positioning deviations at targets along the axis over time; the change of this line's offset
    and slope from cycle to cycle (:func:`error_lines`) is the thermal drift of the axis's
    positioning. The standard evaluates the drift of the deviations at its prescribed positions;
    the straight-line fit is a summary of those, not a clause of the standard.

    ``target_mm`` and ``deviation_um``: 1-D, same length, finite, at least two distinct targets.
    """
    p = _array_1d(target_mm, "target_mm")
    d = _array_1d(deviation_um, "deviation_um")
    _same_length(target_mm=p, deviation_um=d)
    if np.unique(p).size < 2:
        raise ValueError(f"target_mm: expected at least two distinct targets for a line, got {np.unique(p).tolist()}")
    pm = p.mean()
    dp = p - pm
    slope_per_mm = float(np.dot(dp, d - d.mean()) / np.dot(dp, dp))
    offset = float(d.mean() - slope_per_mm * pm)
    return offset, slope_per_mm * 1000.0


ERROR_LINE_COLUMNS = ("cycle", "t_s", "n_points", "offset_um", "slope_um_per_m",
                      "offset_change_um", "slope_change_um_per_m")


def error_lines(readings: pd.DataFrame) -> pd.DataFrame:
    """:func:`error_line` per measuring cycle (ISO 230-3:2020 clause 7 style along-axis drift).

    ``readings`` columns: ``target_mm``, ``cycle``, ``t_s`` (time of each reading, s) and
    ``deviation_um``. Every reading of a cycle enters its fit (both approach directions, if the
    table has them, weigh equally; filter first to fit one direction).

    Returns a DataFrame, one row per cycle sorted by cycle: ``cycle``, ``t_s`` (mean time of the
    cycle's readings), ``n_points``, ``offset_um``, ``slope_um_per_m`` and the change relative to
    the first cycle in that order, ``offset_change_um`` and ``slope_change_um_per_m``.
    A cycle with fewer than two distinct targets raises ValueError naming it.
    """
    cols = ("target_mm", "cycle", "t_s", "deviation_um")
    _check_frame(readings, "readings", cols)
    df = pd.DataFrame({c: _numeric_column(readings, c, "readings") for c in cols})
    rows = []
    for cyc, g in df.groupby("cycle", sort=True):
        try:
            offset, slope = error_line(g["target_mm"].to_numpy(), g["deviation_um"].to_numpy())
        except ValueError as exc:
            raise ValueError(f"readings: cycle {cyc!r}: {exc}") from None
        label = int(cyc) if float(cyc).is_integer() else float(cyc)
        rows.append((label, float(g["t_s"].mean()), len(g), offset, slope))
    out = pd.DataFrame(rows, columns=list(ERROR_LINE_COLUMNS[:5]))
    out["offset_change_um"] = out["offset_um"] - out["offset_um"].iloc[0]
    out["slope_change_um_per_m"] = out["slope_um_per_m"] - out["slope_um_per_m"].iloc[0]
    return out


def environmental_variation_error(t_s, value_um, ambient_C) -> dict:
    """ETVE-style figure of one displacement channel (ISO 230-3:2020 clause 5).

    Returns a dict of floats:

    * ``etve_um``: the range of the displacement over the data given, max − min (µm);
    * ``ambient_range_C``: the range of the ambient temperature over the same samples (°C);
    * ``etve_um_per_C``: their ratio (µm/°C), NaN if the ambient range is 0;
    * ``duration_s``: last − first time; ``n_samples``.

    ``t_s`` strictly increasing, ``value_um`` and ``ambient_C`` the same length, all finite.

    The standard's ETVE test runs the machine at rest (axes and spindle stopped, in its normal
    environment) for a long period, typically 12 h or more and including a night/day change,
    reading each direction's relative displacement between tool side and workpiece side; ETVE is
    the largest range observed in each direction. This function computes the figures from
    whatever data it is given and does not check the duration or the machine's state. The ratio
    is a plain range/range quotient, not a sensitivity: it ignores the time lag between the air
    temperature and the structure's response.
    """
    t = _array_1d(t_s, "t_s")
    x = _array_1d(value_um, "value_um")
    a = _array_1d(ambient_C, "ambient_C")
    _same_length(t_s=t, value_um=x, ambient_C=a)
    _strictly_increasing(t, "t_s")
    rng = float(x.max() - x.min())
    amb = float(a.max() - a.min())
    return {
        "etve_um": rng,
        "ambient_range_C": amb,
        "etve_um_per_C": rng / amb if amb > 0 else _NAN,
        "duration_s": float(t[-1] - t[0]),
        "n_samples": float(t.size),
    }
