"""What every front end of the cycle logic keeps of a run (the OPC UA compensator and
station, the LinuxCNC component): the per-cycle CSV log, a fixed-size ring of recent values,
the cycle-time statistics of the summary, and the periodic status line."""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import Sequence

import numpy as np

from ..outputs import OutputStream
from .control import Cycle, Flags, flag_names

STATS_CYCLES = 100_000  # the run's summary covers the last this many cycles


class CycleLog:
    """The per-cycle CSV log (one line per cycle, flushed each time)."""

    def __init__(self, path: Path, inputs: list[str]) -> None:
        self.path = Path(path)
        self.inputs = inputs
        self.out = OutputStream(self.path, "compensator-log")  # never over a file thermbench did not write
        self.fh = self.out.fh
        self.w = csv.writer(self.fh)
        self.w.writerow(["wall_s", "cycle", "t_s", "late_ms", "cycle_ms", *inputs, "held", "value_um", "offset_um",
                         "slope_um_per_m", "ref_mm", "predicted_um", "label", "rc", "flags", "flag_names", "correction_um", "probe_um",
                         "faulty"])  # fmt: skip

    def write(self, wall_s: float, k: int, c: Cycle, late_ms: float, cycle_ms: float) -> None:
        ln = c.line
        self.w.writerow([f"{wall_s:.6f}", k, _f(c.t_s), f"{late_ms:.3f}", f"{cycle_ms:.3f}",
                         *[_f(c.inputs.get(n)) for n in self.inputs], ";".join(c.held), _f(c.value_um),
                         _f(ln.offset_um if ln else None), _f(ln.slope_um_per_m if ln else None), _f(ln.ref_mm if ln else None),
                         _f(c.predicted_um), c.label, c.rc, c.flags, flag_names(c.flags), _f(c.correction_um),
                         _f(c.probe_um), ";".join(c.faulty)])  # fmt: skip

    def close(self) -> None:
        self.out.close()


def _f(v) -> str:
    return "" if v is None or (isinstance(v, float) and math.isnan(v)) else repr(float(v))


def cycle_stats(durations_ms, late_ms, index, starts_s, period_s: float) -> dict:
    """Cycle-time distribution and schedule drift of a run of cycles: ``index`` is each
    cycle's deadline number (deadline = start + index * period), so the mean period is the
    slope of start time over it and the drift the trend of the start lateness over the run."""
    d = np.asarray(durations_ms, dtype=float)
    lt = np.asarray(late_ms, dtype=float)
    st = np.asarray(starts_s, dtype=float)
    k = np.asarray(index, dtype=float)
    if d.size == 0:
        return {"cycles": 0}
    q = np.percentile(d, [50, 90, 99])
    lq = np.percentile(lt, [50, 99])
    fit = d.size > 2 and k[-1] > k[0]
    slope = float(np.polyfit(k, st - st[0], 1)[0]) if fit else float("nan")
    trend = float(np.polyfit(k, lt, 1)[0]) * (k[-1] - k[0]) if fit else float("nan")
    return {"cycles": int(d.size), "cycle_ms": {"p50": q[0], "p90": q[1], "p99": q[2], "max": float(d.max()),
                                                "mean": float(d.mean())},
            "late_ms": {"p50": lq[0], "p99": lq[1], "max": float(lt.max())},
            "over_period": int(np.sum(d > 1e3 * period_s)),
            "mean_period_ms": 1e3 * slope, "drift_ms": trend}  # fmt: skip


class Ring:
    """The last ``n`` values of a float series in a buffer allocated once (the loop's
    statistics take no memory per cycle, however long it runs)."""

    def __init__(self, n: int) -> None:
        self.buf = np.full(n, np.nan)  # written now: the pages are resident from the start, not one by one
        self.n = 0

    def append(self, v: float) -> None:
        self.buf[self.n % self.buf.size] = v
        self.n += 1

    def values(self) -> np.ndarray:
        if self.n <= self.buf.size:
            return self.buf[: self.n].copy()
        i = self.n % self.buf.size
        return np.concatenate([self.buf[i:], self.buf[:i]])

    def __len__(self) -> int:
        return self.n


def status_line(k: int, c, cycle_ms: Sequence[float]) -> str:
    """One line of the running loop: cycles so far, the cycle times since the last line (mean,
    max), machine time, the compensation written and the flags of the latest cycle."""
    names = "|".join(f.name for f in Flags if f.value and c.flags & f.value) or "OK"
    value = "-" if c.value_um is None or not math.isfinite(c.value_um) else f"{c.value_um:+.2f} um"
    ms = np.asarray(cycle_ms, dtype=float)
    t = "-" if c.t_s is None or not math.isfinite(c.t_s) else f"{c.t_s:.0f} s"
    return (f"cycle {k + 1}: {ms.mean():.2f} ms mean, {ms.max():.2f} ms max over {ms.size} cycles; machine time {t}; "
            f"compensation {value}; {names}")  # fmt: skip
