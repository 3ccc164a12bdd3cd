"""A spindle thermal test as a lab writes it, for the family contract suite (tests/test_family_contract.py).

Five runs of 3 h, one sheet each in two workbooks, as the 18-day lathe test of ``../shared/realdata/ace/``
comes: ``logger.xlsx`` (the temperature logger and the spindle speed, one row a minute, a time column in
seconds) and ``gauge.xlsx`` (the dial gauge at the test mandrel, one reading a minute). Every number comes
from the closed-form truth below, not from thermbench:

- the spindle runs at one speed for 2 h, then stands for 1 h (run 5 steps 1500 / 4500 / 3000 rpm);
  its heat is ``q = (rpm / 6000) ** 1.5``;
- each temperature is the ambient plus a first-order lag of ``q`` (time constant 900, 2400, 5400 s);
  the ambient drifts by ±0.4 °C over 6 h, each run at its own phase;
- ``zmotor`` is the drive's temperature read as a whole number of °C, as a CNC reports it: in the first
  run (the slowest) it never moves from 22 °C;
- the drift (µm) is ``2.0 ΔT_front + 1.2 ΔT_rear + 6 lag(q, 3000 s)`` plus 0.05 µm of seeded noise.

What the suite varies, each a way a lab's files differ and none a change of the test: the runs' names
(:data:`NAMES`: a name in natural order that sorts otherwise as text, a sheet name with a space, non-ASCII
letters, a date), the rows of each sheet shuffled (a time column orders them), and one run's logger with
an irregular step (it logged every third minute for half an hour, and one sample late).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

STEP_S = 60.0
DURATION_S = 3 * 3600.0
RUN_S = 2 * 3600.0  # the spindle runs, then stands
SPEEDS_RPM = (1500.0, 6000.0, 3000.0, 4500.0, None)  # None: the stepped run
TAUS_S = {"front": 900.0, "rear": 2400.0, "housing": 5400.0}
RISE_C = {"front": 8.0, "rear": 5.0, "housing": 3.0}
NOISE_UM = 0.05
#: the runs as the base files name their sheets (in the workbooks' order)
BASE = ("run1", "run2", "run3", "run4", "run5")
#: the same sheets named as labs name them; the run ids thermbench makes of them sort as text in
#: another order than the workbook's (2024-03-01, Prüfung_3 -> Pr_fung_3, Sheet_1, run10, run2)
NAMES = ("run2", "run10", "Sheet 1", "Prüfung 3", "2024-03-01")
RUN_IDS = ("run2", "run10", "Sheet_1", "Pr_fung_3", "2024-03-01")
SENSORS = {"amb": "ambient", "front": "spindle", "rear": "spindle", "housing": "structure", "zmotor": "motor"}


def speed_rpm(k: int, t: np.ndarray) -> np.ndarray:
    """Run ``k``'s (0-based) spindle speed at ``t``."""
    on = t < RUN_S
    if SPEEDS_RPM[k] is not None:
        return np.where(on, SPEEDS_RPM[k], 0.0)
    steps = np.select([t < 2400.0, t < 4800.0], [1500.0, 4500.0], 3000.0)
    return np.where(on, steps, 0.0)


def lag(t: np.ndarray, q: np.ndarray, tau_s: float) -> np.ndarray:
    """The first-order lag of ``q`` (held between the samples ``t``) with time constant ``tau_s``, exact per step."""
    out = np.zeros(t.size)
    for i in range(1, t.size):
        a = np.exp(-(t[i] - t[i - 1]) / tau_s)
        out[i] = a * out[i - 1] + (1 - a) * q[i - 1]
    return out


def truth(k: int, t: np.ndarray, seed: int = 0) -> dict[str, np.ndarray]:
    """Run ``k``'s signals at ``t`` (s, from 0): rpm, the temperatures (°C) and the drift (µm)."""
    fine = np.arange(0.0, DURATION_S + 1.0, 10.0)
    q = (speed_rpm(k, fine) / 6000.0) ** 1.5
    amb = 20.0 + 0.4 * np.sin(2 * np.pi * fine / 21600.0 + 1.3 * k)
    out = {"rpm": speed_rpm(k, t), "amb": np.interp(t, fine, amb)}
    for s, tau in TAUS_S.items():
        out[s] = np.interp(t, fine, amb + RISE_C[s] * lag(fine, q, tau))
    motor = np.round(22.0 + (0.0 if k == 0 else 4.0) * np.interp(t, fine, lag(fine, q, 1200.0)))
    out["zmotor"] = motor
    drift = (2.0 * (out["front"] - out["front"][0]) + 1.2 * (out["rear"] - out["rear"][0])
             + 6.0 * np.interp(t, fine, lag(fine, q, 3000.0)))  # fmt: skip
    rng = np.random.default_rng(seed + 17 * k)
    out["drift"] = drift + NOISE_UM * rng.standard_normal(t.size)
    return out


def logger_times(k: int, irregular: bool) -> np.ndarray:
    t = np.arange(0.0, DURATION_S + 1.0, STEP_S)
    if irregular and k == 2:  # every third minute from 1 h to 1.5 h, and one sample 7 s late
        gap = (t > 3600.0) & (t < 5400.0) & (np.round(t / STEP_S) % 3 != 0)
        t = t[~gap]
        t[np.searchsorted(t, 6000.0)] += 7.0
    return t


def write_files(out: Path, names=BASE, shuffle: bool = False, irregular: bool = False, seed: int = 0) -> Path:
    """The two workbooks and their import mapping in ``out``; returns the mapping's path."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    with pd.ExcelWriter(out / "logger.xlsx") as lw, pd.ExcelWriter(out / "gauge.xlsx") as gw:
        for k, name in enumerate(names):
            t_log = logger_times(k, irregular)
            s = truth(k, t_log, seed)
            log = pd.DataFrame({"Zeit [s]": t_log, "Drehzahl": s["rpm"], "Umgebung": s["amb"], "Lager vorn": s["front"],
                                "Lager hinten": s["rear"], "Gehaeuse": s["housing"], "Motor": s["zmotor"]})  # fmt: skip
            t_g = np.arange(0.0, DURATION_S + 1.0, STEP_S)
            gauge = pd.DataFrame({"Zeit [s]": t_g, "Verlagerung": truth(k, t_g, seed)["drift"]})
            if shuffle:
                log = log.iloc[rng.permutation(len(log))]
                gauge = gauge.iloc[rng.permutation(len(gauge))]
            log.to_excel(lw, sheet_name=name, index=False)
            gauge.to_excel(gw, sheet_name=name, index=False)
    mapping = out / "mapping.yaml"
    ids = RUN_IDS if tuple(names) == NAMES else tuple(names)
    runs = "".join(f"\n    {r!r}: {{condition: {{spindle_rpm: {SPEEDS_RPM[k] or 3000.0:g}}}}}" for k, r in enumerate(ids))
    mapping.write_text(MAPPING.replace("RUNS", runs), encoding="utf-8")
    return mapping


MAPPING = """\
format: thermbench-import/1
dataset:
  machine: {name: contract_spindle}
  parts: [spindle]
  sensors: {amb: ambient, front: spindle, rear: spindle, housing: structure, zmotor: motor}
  operating: [spindle_rpm]
  channels: {drift: {kind: fixed_point, direction: Z, location: spindle}}
  runs:RUNS
  reference: {mode: first_reading}
files:
  logger:
    path: logger.xlsx
    read: {sheets: all}
    run: {from: sheet}
    time: {column: "Zeit [s]", unit: s}
    columns: {Drehzahl: spindle_rpm, Umgebung: amb_C, "Lager vorn": front_C, "Lager hinten": rear_C,
              Gehaeuse: housing_C, Motor: zmotor_C}
  gauge:
    path: gauge.xlsx
    read: {sheets: all}
    run: {from: sheet}
    time: {column: "Zeit [s]", unit: s}
    columns: {Verlagerung: {channel: drift, unit: um}}
"""
