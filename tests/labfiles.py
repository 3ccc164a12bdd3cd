"""A lab's three files, as real instruments write them, for ``thermbench import`` (docs/import.md).

A ball-screw X axis runs 2 h: a cold measuring cycle, then strokes over 0..400 mm at
6000 mm/min with a bidirectional measuring cycle every 20 min. Three instruments, three
clocks, three file styles:

- ``logger.csv``: a temperature logger every 10 s; ``;``-separated, decimal commas, one
  preamble line, cp1252 text (``°C``), timestamps ``04.03.2026 08:00:10``. Its clock is the
  reference.
- ``cnc_trace.csv``: the CNC trace at 4 Hz; ISO timestamps with milliseconds on a clock
  2.5 s ahead of the logger's; actual position (mm) and *signed* velocity (mm/s).
- ``interferometer.txt``: the laser's export, tab-separated, two preamble lines; a
  timestamp 1.2 s behind the logger's, the target (mm), the direction of approach as
  ``fwd`` / ``bwd`` and the deviation in **mm**.

Everything is computed from closed-form truth (the functions below), not from thermbench:
the thermal error at x is ``slope_um_per_m(t) * x / 1000``, the geometric error
``3 sin(2 pi x / 400)`` µm, and the reversal value ``B = 4`` µm (``+B/2`` approaching in the
positive direction, ``-B/2`` in the negative), so a test can check what the import and the
ISO evaluation recover against numbers that do not come from the code under test.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

START = pd.Timestamp("2026-03-04 08:00:00")
DURATION_S = 7200.0
COLD_END_S = 300.0  # the cold measuring cycle ends; strokes start
TARGETS_MM = np.arange(0.0, 401.0, 50.0)
CYCLE_EVERY_S = 1200.0
DWELL_S = 5.0
MOVE_S = 3.0  # between targets in a measuring cycle
FEED_MM_MIN = 6000.0
REVERSAL_UM = 4.0
CNC_AHEAD_S = 2.5  # the CNC clock reads 2.5 s more than the logger's
LASER_BEHIND_S = 1.2  # the interferometer's reads 1.2 s less
TAU_S = 2400.0


def on_s(t):
    return np.clip(np.asarray(t, dtype=float) - COLD_END_S, 0.0, None)


def slope_um_per_m(t):
    return 100.0 * (1.0 - np.exp(-on_s(t) / TAU_S))


def thermal_um(x_mm, t):
    return slope_um_per_m(t) * np.asarray(x_mm, dtype=float) / 1000.0


def geometric_um(x_mm):
    return 3.0 * np.sin(2.0 * np.pi * np.asarray(x_mm, dtype=float) / 400.0)


def t_nut_C(t):
    return 20.0 + 10.0 * (1.0 - np.exp(-on_s(t) / TAU_S))


def t_bed_C(t):
    return 20.0 + 1.0 * (1.0 - np.exp(-on_s(t) / (2 * TAU_S)))


def t_ambient_C(t):
    return 20.0 + 0.3 * np.sin(2.0 * np.pi * np.asarray(t, dtype=float) / 3600.0)


def _cycle_plan(t0: float) -> list[tuple[float, float, int]]:
    """(reading time, target, direction) of one bidirectional measuring cycle from t0: up
    through the targets, then down; each reading in the middle of a dwell."""
    plan, t = [], t0
    for x in TARGETS_MM:
        plan.append((t + DWELL_S / 2, x, 1))
        t += DWELL_S + MOVE_S
    for x in TARGETS_MM[::-1]:
        plan.append((t + DWELL_S / 2, x, -1))
        t += DWELL_S + MOVE_S
    return plan


CYCLE_S = len(TARGETS_MM) * 2 * (DWELL_S + MOVE_S)


def readings_truth() -> pd.DataFrame:
    """Every interferometer reading on the logger's clock, with its true parts."""
    rows = []
    starts = [0.0] + list(np.arange(COLD_END_S + CYCLE_EVERY_S, DURATION_S - CYCLE_S, CYCLE_EVERY_S))
    for c, t0 in enumerate(starts):
        for t, x, d in _cycle_plan(t0):
            rows.append({"cycle": c, "t_s": t, "target_mm": x, "direction": d})
    df = pd.DataFrame(rows)
    df["thermal_um"] = thermal_um(df["target_mm"], df["t_s"])
    df["error_um"] = geometric_um(df["target_mm"]) + df["thermal_um"] + df["direction"] * REVERSAL_UM / 2
    return df


def axis_at(t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(position mm, signed velocity mm/s) at times t: at the targets during measuring cycles,
    a triangle wave over 0..400 mm at the feed otherwise."""
    rd = readings_truth()
    x = np.empty(t.size)
    v = np.empty(t.size)
    speed = FEED_MM_MIN / 60.0
    period = 2 * 400.0 / speed
    in_cycle = np.zeros(t.size, dtype=bool)
    for _, g in rd.groupby("cycle"):
        a, b = g["t_s"].min() - DWELL_S / 2, g["t_s"].max() + DWELL_S / 2
        m = (t >= a) & (t <= b)
        in_cycle |= m
        # the axis sits at the target of the reading nearest in time
        idx = np.abs(t[m][:, None] - g["t_s"].to_numpy()[None, :]).argmin(axis=1)
        x[m] = g["target_mm"].to_numpy()[idx]
        v[m] = 0.0
    free = ~in_cycle
    phase = np.mod(t[free], period)
    up = phase < period / 2
    x[free] = np.where(up, phase * speed, 400.0 - (phase - period / 2) * speed)
    v[free] = np.where(up, speed, -speed)
    x[free & (t < COLD_END_S)] = 0.0
    v[free & (t < COLD_END_S)] = 0.0
    return x, v


def _stamp(t_s: np.ndarray, fmt: str) -> list[str]:
    ts = START + pd.to_timedelta(t_s, unit="s")
    if fmt == "iso":
        return [s.isoformat(timespec="milliseconds") for s in ts]
    return [s.strftime(fmt) for s in ts]


MAPPING = """# The lab's three files (tests/labfiles.py) -> one dataset; docs/import.md explains each key.
format: thermbench-import/1
dataset:
  machine: {name: lab_x, axis: X}
  parts: [axis]
  sensors: {T_nut: nut_housing, T_bed: bed, T_amb: ambient}
  channels:
    X: {kind: along_axis, direction: X, location: table}
  reference: {mode: cold_cycle}
  runs:
    warmup_6000:
      condition: {stroke_mm: 400, start_mm: 0, end_mm: 400, feed_mm_min: 6000}
run: warmup_6000
align: {base: cnc}
files:
  logger:
    path: logger.csv
    read: {sep: ";", decimal: ",", encoding: cp1252, skip_rows: 1}
    time: {column: Zeit, format: "%d.%m.%Y %H:%M:%S"}
    columns:
      "Temp. Mutter [°C]": T_nut_C
      "Temp. Bett [°C]": T_bed_C
      "Umgebung [°C]": T_amb_C
  cnc:
    path: cnc_trace.csv
    time: {column: Timestamp, format: iso}
    offset_s: -2.5            # the CNC clock is 2.5 s ahead of the logger's
    columns:
      X_act_mm: axis_mm
      X_vel: {to: feed_mm_min, unit: mm/s, abs: true}   # signed velocity -> feed magnitude
  laser:
    path: interferometer.txt
    read: {sep: "\\t", skip_rows: 2}
    time: {column: Date/Time, format: "%Y-%m-%d %H:%M:%S.%f"}
    offset_s: 1.2             # the interferometer's clock is 1.2 s behind
    channel: X
    columns:
      "Target (mm)": target_mm
      "Deviation (mm)": {to: error_um, unit: mm}
      Direction: {to: direction, map: {fwd: 1, bwd: -1}}
"""


def write_lab_files(out: Path) -> Path:
    """Write the three files and ``mapping.yaml`` into ``out``; return the mapping's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    # temperature logger: 10 s, ; and decimal commas, preamble, cp1252
    t_log = np.arange(0.0, DURATION_S + 10.0, 10.0)
    lines = ["Logger TL-4 S/N 1187 export", "Zeit;Temp. Mutter [°C];Temp. Bett [°C];Umgebung [°C]"]
    for stamp, a, b, c in zip(_stamp(t_log, "%d.%m.%Y %H:%M:%S"), t_nut_C(t_log), t_bed_C(t_log), t_ambient_C(t_log)):
        lines.append(";".join([stamp] + [f"{v:.3f}".replace(".", ",") for v in (a, b, c)]))
    (out / "logger.csv").write_bytes(("\r\n".join(lines) + "\r\n").encode("cp1252"))
    # CNC trace: 4 Hz, its clock 2.5 s ahead
    t_cnc = np.arange(0.0, DURATION_S + 0.125, 0.25)
    x, v = axis_at(t_cnc)
    pd.DataFrame({"Timestamp": _stamp(t_cnc + CNC_AHEAD_S, "iso"), "X_act_mm": np.round(x, 4),
                  "X_vel": np.round(v, 4)}).to_csv(out / "cnc_trace.csv", index=False)  # fmt: skip
    # interferometer: tab-separated, 2 preamble lines, deviation in mm, its clock 1.2 s behind
    rd = readings_truth()
    rows = ["XL-80 linear measurement", "Axis X  Targets 0-400 mm  Bidirectional",
            "Date/Time\tTarget (mm)\tRun\tDirection\tDeviation (mm)"]  # fmt: skip
    for stamp, r in zip(_stamp(rd["t_s"].to_numpy() - LASER_BEHIND_S, "%Y-%m-%d %H:%M:%S.%f"), rd.itertuples()):
        rows.append(f"{stamp}\t{r.target_mm:.1f}\t{r.cycle + 1}\t{'fwd' if r.direction > 0 else 'bwd'}\t{r.error_um / 1000:.7f}")
    (out / "interferometer.txt").write_text("\n".join(rows) + "\n", encoding="utf-8")
    (out / "mapping.yaml").write_text(MAPPING, encoding="utf-8")
    return out / "mapping.yaml"


if __name__ == "__main__":  # python -m tests.labfiles OUT_DIR: the files docs/import.md walks through
    import sys

    print(write_lab_files(Path(sys.argv[1] if len(sys.argv) > 1 else "lab_files")))
