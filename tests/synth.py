"""Analytic datasets whose truth is known exactly, for model-recovery tests."""

from __future__ import annotations

from typing import Callable

import numpy as np
import pandas as pd

from thermbench.data.dataset import Dataset
from thermbench.data.schema import FORMAT, Metadata


def make_dataset(process: pd.DataFrame, errors: pd.DataFrame, sensors: dict[str, str], mounting: str = "fixed_free"):
    """A validated-shape Dataset from a process table and an errors table."""
    runs = {}
    for rid, g in process.groupby("run_id", sort=False):
        lo, hi = float(g["axis_mm"].min()), float(g["axis_mm"].max())
        runs[str(rid)] = {"condition": {"stroke_mm": hi - lo, "start_mm": lo, "end_mm": hi,
                                        "feed_mm_min": float(g["feed_mm_min"].max())}}  # fmt: skip
    meta = Metadata.model_validate(
        {
            "format": FORMAT,
            "machine": {"name": "synthetic", "axis": "X"},
            "screw": {"length_m": 0.8, "diameter_m": 0.034, "nut_length_m": 0.2,
                      "fixed_bearing_length_m": 0.03, "mounting": mounting},  # fmt: skip
            "material": {"alpha_per_K": 11.7e-6, "density_kg_m3": 7800.0, "heat_capacity_J_kgK": 448.0},
            "sensors": sensors,
            "runs": runs,
        }
    )
    return Dataset(meta, process.reset_index(drop=True), errors.reset_index(drop=True))


def rise(t_s, amp_C, tau_s, t_on_s=0.0, t_off_s=None):
    """First-order rise from t_on (and decay after t_off) of amplitude amp_C."""
    t = np.asarray(t_s, dtype=float)
    up = amp_C * (1 - np.exp(-np.clip(t - t_on_s, 0, None) / tau_s))
    if t_off_s is None:
        return up
    at_off = amp_C * (1 - np.exp(-(t_off_s - t_on_s) / tau_s))
    return np.where(t < t_off_s, up, at_off * np.exp(-np.clip(t - t_off_s, 0, None) / tau_s))


def analytic_dataset(
    temps: dict[str, dict[str, Callable]],
    error_fn: Callable[[dict, np.ndarray, str], np.ndarray],
    duration_s: float = 4 * 3600,
    targets_mm=tuple(range(0, 501, 50)),
    every_s: float = 600.0,
    read_gap_s: float = 8.0,
    feed_mm_min: dict[str, float] | None = None,
    mounting: str = "fixed_free",
    noise_um: float = 0.0,
    seed: int = 0,
) -> Dataset:
    """Runs with 1 Hz temperatures ``temps[run][sensor](t)`` (°C) and readings every
    ``every_s`` over ``targets_mm``; the reading is ``error_fn(T_at_reading, P, run)``
    (+ Gaussian noise), where ``T_at_reading`` maps sensor -> temperatures."""
    rng = np.random.default_rng(seed)
    sensors = {s: "nut_housing" for s in next(iter(temps.values()))}
    pframes, eframes = [], []
    targets = np.asarray(targets_mm, dtype=float)
    for run, fns in temps.items():
        t = np.arange(0.0, duration_s + 1.0, 1.0)
        feed = (feed_mm_min or {}).get(run, 3000.0)
        axis = targets[0] + (targets[-1] - targets[0]) * 0.5 * (1 - np.cos(2 * np.pi * t / 20.0))
        pdf = {"run_id": run, "t_s": t, "axis_mm": axis, "feed_mm_min": np.full(t.size, feed)}
        for s, fn in fns.items():
            pdf[f"{s}_C"] = fn(t)
        pframes.append(pd.DataFrame(pdf))
        starts = np.arange(0.0, duration_s - targets.size * read_gap_s, every_s)
        rt = (starts[:, None] + read_gap_s * np.arange(targets.size)[None, :]).ravel()
        rx = np.tile(targets, starts.size)
        T = {s: fn(rt) for s, fn in fns.items()}
        err = error_fn(T, rx, run) + noise_um * rng.standard_normal(rt.size)
        eframes.append(pd.DataFrame({"run_id": run, "t_s": rt, "target_mm": rx, "error_um": err}))
    return make_dataset(pd.concat(pframes), pd.concat(eframes), sensors, mounting)
