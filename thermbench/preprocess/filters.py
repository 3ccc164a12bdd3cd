"""Temperature preprocessing: limit filter then scalar Kalman filter (seed 002 §2.3.1 eq. 1-3).

The paper cleans each temperature channel in two steps: a limit filter that rejects
readings jumping by more than ``LimitTemp = 2 °C`` from the previous one (bus glitches,
dropouts), then a Kalman filter on a random-walk model of the temperature
(A = H = I, U = 0, R = 8.8706, Q = 1e-3) that smooths the remaining white noise.

Both filters are stateless between calls, keep their constructor arguments as
attributes (scikit-learn style: ``get_params``/``clone`` work) and validate them in
:meth:`transform`. :func:`filter_process` applies a chain of them to the temperature
columns of a process log, separately for each run.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from numbers import Integral, Real

import numpy as np
import pandas as pd
from sklearn.base import BaseEstimator

__all__ = ["KalmanFilter", "LimitFilter", "PreprocessError", "default_steps", "filter_process", "resolve_steps"]


START_SAMPLES = 5  # the limit filter checks the first reading against the median of the next 5


class PreprocessError(ValueError):
    """Bad input to preprocessing; the message names the column/parameter and what was expected."""


def _where(column: str) -> str:
    return f"column {column!r}" if column else "series"


def _positive(owner: str, name: str, value) -> float:
    if isinstance(value, bool) or not isinstance(value, Real) or not math.isfinite(value) or value <= 0:
        raise PreprocessError(f"{owner}: {name} must be a finite number > 0, got {value!r}")
    return float(value)


def _as_series(x, column: str) -> np.ndarray:
    """A 1-D float copy of ``x``; NaN/inf is an error naming the column and the first bad row."""
    try:
        arr = np.array(x, dtype=float)  # copy: the filters never modify their input
    except (TypeError, ValueError) as exc:
        raise PreprocessError(f"{_where(column)}: expected numeric temperatures, got {exc}") from None
    if arr.ndim != 1:
        raise PreprocessError(f"{_where(column)}: expected a 1-D series, got shape {arr.shape}")
    bad = ~np.isfinite(arr)
    if bad.any():
        i = int(np.argmax(bad))
        raise PreprocessError(
            f"{_where(column)}: row {i} is {arr[i]}; the filters need a complete series "
            "(fill or drop missing readings first)"
        )
    return arr


class LimitFilter(BaseEstimator):
    """Limit (spike) filter, seed 002 §2.3.1 eq. 1.

    ``y[0] = x[0]`` unless the first reading is itself a glitch (e.g. the 85 °C power-on
    value of a DS18B20): when it lies more than ``limit_C`` from the median of the next
    ``START_SAMPLES`` readings and those agree within ``limit_C``, the filter starts
    from that median. Then ``y[k] = y[k-1]`` if ``|x[k] - y[k-1]| > limit_C`` (hold the
    previous *accepted* value) else ``y[k] = x[k]``. The paper writes the comparison
    against ``Temp(t-1)``; comparing with the last accepted value is what makes a
    multi-sample dropout (e.g. 85.0 °C for 5 s) disappear completely rather than only
    its first sample. A difference exactly equal to the limit is accepted (the paper
    leaves equality open).

    The paper's rule never recovers from a genuine jump larger than the limit: the
    output would stay at the old level forever. ``max_hold`` (samples, default
    ``None`` = the paper's rule) bounds that: once ``max_hold`` consecutive readings
    have been rejected *and* they form a level of their own (each within ``limit_C`` of
    the previous rejected reading), the next such reading is accepted and the filter
    continues from it. A dropout shorter than or equal to ``max_hold`` samples is still
    removed entirely; rejected readings that scatter by more than ``limit_C`` among
    themselves (noise bursts, or a rise faster than ``limit_C`` per sample, which no
    real temperature does) restart the count.

    Parameters
    ----------
    limit_C : largest accepted change between consecutive accepted readings, °C (paper: 2).
    max_hold : ``None`` or an int >= 1, the most samples a persistent new level is held off.
    """

    def __init__(self, limit_C: float = 2.0, max_hold: int | None = None):
        self.limit_C = limit_C
        self.max_hold = max_hold

    def _check(self) -> tuple[float, int | None]:
        limit = _positive("LimitFilter", "limit_C", self.limit_C)
        mh = self.max_hold
        if mh is not None and (isinstance(mh, bool) or not isinstance(mh, Integral) or mh < 1):
            raise PreprocessError(f"LimitFilter: max_hold must be None or an int >= 1 (samples), got {mh!r}")
        return limit, (None if mh is None else int(mh))

    def transform(self, x: np.ndarray, column: str = "") -> np.ndarray:
        """Filter one channel; returns a new array (seed 002 §2.3.1 eq. 1)."""
        limit, max_hold = self._check()
        z = _as_series(x, column)
        if z.size < 2:
            return z
        y = z.copy()
        data = z.tolist()  # python floats: a scalar loop is ~10x faster on these than on numpy scalars
        prev = data[0]  # last accepted value
        nxt = z[1 : 1 + START_SAMPLES]
        if abs(prev - float(np.median(nxt))) > limit and np.ptp(nxt) <= limit:
            prev = y[0] = float(np.median(nxt))  # the first reading is a glitch the next ones agree on

        run = 0  # consecutive rejected readings forming one level
        last_rejected = 0.0
        for k in range(1, len(data)):
            v = data[k]
            if abs(v - prev) <= limit:
                prev = v
                run = 0
                continue
            if max_hold is not None:
                run = run + 1 if (run and abs(v - last_rejected) <= limit) else 1
                last_rejected = v
                if run > max_hold:
                    prev = v
                    run = 0
                    continue
            y[k] = prev
        return y


class KalmanFilter(BaseEstimator):
    """Scalar Kalman filter of one temperature channel, seed 002 §2.3.1 eq. 2-3.

    Model (eq. 2 with A = H = I, U = 0): ``T[k] = T[k-1] + w``, ``z[k] = T[k] + v``,
    ``var(w) = Q``, ``var(v) = R``; the paper uses R = 8.8706, Q = 1e-3.
    Recursion (eq. 3), run on each sample k >= 1::

        x⁻ = x;  P⁻ = P + Q                     (time update)
        K = P⁻ / (P⁻ + R)
        x = x⁻ + K (z[k] - x⁻);  P = (1 - K) P⁻  (measurement update)

    The output is the posterior estimate ``x`` at every sample.

    Initialisation: the paper takes the first measurement as the initial estimate,
    ``x[0] = z[0]``, and does not give P0. We use ``P0 = R``: the variance of an
    estimate made from one measurement of variance R, which is exactly what the
    update above yields from an uninformative prior (P⁻ → ∞ gives K → 1, x = z[0],
    P = R). The gain therefore starts near 1/2 and decays to the steady state
    ``K∞ = P∞⁻ / (P∞⁻ + R)`` with ``P∞⁻ = (Q + sqrt(Q² + 4QR)) / 2``.

    Q and R are per *sample*: with the defaults K∞ ≈ 0.0105, a smoothing time
    constant of about 95 samples, i.e. about 95 s on the contract's 1 Hz log but
    shorter on a faster log; scale Q with the sample period to keep it in seconds.

    Parameters
    ----------
    R : measurement-noise variance, °C².
    Q : process-noise variance per sample, °C².
    per_channel : optional ``{column: {"R": ..., "Q": ...}}`` overrides, used when
        :meth:`transform` is called with that ``column``; either key may be left out.
    """

    _OVERRIDE_KEYS = ("R", "Q")

    def __init__(self, R: float = 8.8706, Q: float = 1e-3, per_channel: dict[str, dict] | None = None):
        self.R = R
        self.Q = Q
        self.per_channel = per_channel

    def _check(self) -> dict[str, tuple[float, float]]:
        """Validated parameters: ``{"": (R, Q), column: (R, Q), ...}``."""
        R = _positive("KalmanFilter", "R", self.R)
        Q = _positive("KalmanFilter", "Q", self.Q)
        out = {"": (R, Q)}
        pc = self.per_channel
        if pc is None:
            return out
        if not isinstance(pc, Mapping):
            raise PreprocessError(
                f"KalmanFilter: per_channel must be a dict {{column: {{'R': ..., 'Q': ...}}}}, got {type(pc).__name__}"
            )
        for col, ov in pc.items():
            owner = f"KalmanFilter per_channel[{col!r}]"
            if not isinstance(col, str) or not col:
                raise PreprocessError(f"KalmanFilter: per_channel keys must be column names, got {col!r}")
            if not isinstance(ov, Mapping):
                raise PreprocessError(f"{owner}: expected a dict with keys 'R' and/or 'Q', got {ov!r}")
            unknown = [k for k in ov if k not in self._OVERRIDE_KEYS]
            if unknown:
                raise PreprocessError(f"{owner}: unknown key {unknown[0]!r}; expected 'R' and/or 'Q'")
            out[col] = (
                _positive(owner, "R", ov["R"]) if "R" in ov else R,
                _positive(owner, "Q", ov["Q"]) if "Q" in ov else Q,
            )
        return out

    def params_for(self, column: str = "") -> tuple[float, float]:
        """``(R, Q)`` used for ``column`` (its override if any, else the defaults)."""
        params = self._check()
        return params.get(column, params[""])

    def transform(self, x: np.ndarray, column: str = "") -> np.ndarray:
        """Filter one channel; returns the posterior estimates (seed 002 §2.3.1 eq. 3)."""
        R, Q = self.params_for(column)
        z = _as_series(x, column)
        if z.size == 0:
            return z
        data = z.tolist()
        out = [0.0] * len(data)
        est = data[0]  # initial estimate = first measurement (paper)
        P = R  # see class docstring
        out[0] = est
        for k in range(1, len(data)):
            P_prior = P + Q
            K = P_prior / (P_prior + R)
            est = est + K * (data[k] - est)
            P = (1.0 - K) * P_prior
            out[k] = est
        return np.asarray(out, dtype=float)


def _run_blocks(process: pd.DataFrame) -> list[tuple[str, int, int]]:
    """``(run_id, start, stop)`` positional slices of the contiguous runs."""
    rid = process["run_id"].to_numpy()
    n = rid.size
    if n == 0:
        return []
    change = np.flatnonzero(rid[1:] != rid[:-1]) + 1
    starts = np.r_[0, change]
    stops = np.r_[change, n]
    blocks, seen = [], set()
    for a, b in zip(starts, stops, strict=True):
        r = rid[a]
        if r in seen:
            raise PreprocessError(
                f"column 'run_id': rows of run {r!r} are not contiguous (it starts again at row {a}); "
                "sort the process log by run and time first"
            )
        seen.add(r)
        blocks.append((r, int(a), int(b)))
    return blocks


def filter_process(process: pd.DataFrame, columns: Sequence[str], steps: Sequence) -> pd.DataFrame:
    """Apply ``steps`` in order to each of ``columns``, separately for each run (seed 002 §2.3.1).

    ``process`` is a process log (docs/dataset-format.md): a ``run_id`` column whose
    rows are contiguous per run, in time order, and temperature columns ``<sensor>_C``.
    Each step is an object with ``transform(x, column)`` (:class:`LimitFilter`,
    :class:`KalmanFilter`, ...). Every run starts the filters afresh, so no state
    leaks from one run into the next. Returns a copy of ``process`` with the filtered
    columns replaced; other columns and the index are unchanged.
    """
    if not isinstance(process, pd.DataFrame):
        raise PreprocessError(f"process: expected a pandas DataFrame, got {type(process).__name__}")
    if isinstance(columns, str):
        raise PreprocessError(
            f"columns: expected a sequence of column names, got the string {columns!r}; use [{columns!r}]"
        )
    columns = list(columns)
    steps = list(steps)
    if "run_id" not in process.columns:
        raise PreprocessError("process: column 'run_id' is missing; it is needed to filter each run separately")
    temp_cols = [c for c in process.columns if isinstance(c, str) and c.endswith("_C")]
    for c in columns:
        if c not in process.columns:
            raise PreprocessError(
                f"column {c!r} is not in the process log; available temperature columns: {temp_cols or 'none'}"
            )
        if not pd.api.types.is_numeric_dtype(process[c]) or pd.api.types.is_bool_dtype(process[c]):
            raise PreprocessError(f"column {c!r}: expected numeric temperatures, got dtype {process[c].dtype}")
    if len(set(columns)) != len(columns):
        dup = next(c for c in columns if columns.count(c) > 1)
        raise PreprocessError(f"columns: {dup!r} is listed twice")
    for i, s in enumerate(steps):
        if not callable(getattr(s, "transform", None)):
            raise PreprocessError(f"steps[{i}]: expected a filter with transform(x, column), got {s!r}")

    blocks = _run_blocks(process)
    out = process.copy()
    for c in columns:
        values = process[c].to_numpy(dtype=float)
        bad = ~np.isfinite(values)
        if bad.any():
            i = int(np.argmax(bad))
            run = next(r for r, a, b in blocks if a <= i < b)
            raise PreprocessError(
                f"column {c!r}, run {run!r}, row {i} (index {process.index[i]!r}): value {values[i]}; "
                "the filters need a complete series (fill or drop missing readings first)"
            )
        result = values.copy()
        for run, a, b in blocks:
            seg = values[a:b]
            for s in steps:
                seg = np.asarray(s.transform(seg, column=c), dtype=float)
                if seg.shape != (b - a,):
                    raise PreprocessError(
                        f"column {c!r}, run {run!r}: step {type(s).__name__} returned shape {seg.shape}, "
                        f"expected ({b - a},)"
                    )
            if not np.isfinite(seg).all():
                j = int(np.argmax(~np.isfinite(seg)))
                raise PreprocessError(
                    f"column {c!r}, run {run!r}: filtering produced {seg[j]} at row {a + j} of the process log"
                )
            result[a:b] = seg
        out[c] = result
    return out


def default_steps() -> list:
    """The seed 002 §2.3.1 chain: limit filter (2 °C) then Kalman (R = 8.8706, Q = 1e-3)."""
    return [LimitFilter(), KalmanFilter()]


def resolve_steps(spec) -> list:
    """A model's ``preprocess`` parameter as a list of filters: ``"default"`` is
    :func:`default_steps`, ``None`` or ``[]`` no filtering, a list is taken as is."""
    if spec is None:
        return []
    if isinstance(spec, str):
        if spec != "default":
            raise PreprocessError(f"preprocess: expected 'default', None or a list of filters, got {spec!r}")
        return default_steps()
    return list(spec)
