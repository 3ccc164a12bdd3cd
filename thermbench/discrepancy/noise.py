"""The noise floor of a dataset, estimated from the data alone (the discrepancy workflow, step 2).

Two estimators of the interferometer's per-reading scatter sigma:

* ``repeat``: readings of the same target of a run within ``window_s`` of each
  other (several readings per dwell, repeated targets): the pooled standard
  deviation within such groups. Model-free; used when there are enough groups.
* ``high_frequency``: the second difference in time of the residual of a
  physics model at each (run, target), d_k = r_{k+1} - 2 r_k + r_{k-1}, whose
  variance is 6 sigma^2 for white reading noise; the smooth model error hardly
  enters it. Robust: sigma = 1.4826 MAD(d) / sqrt(6).

The *noise floor* is the RMSE a perfect model would have on the thermal errors:
a thermal error is a reading minus the cold reference at its target (one
reading, or the mean of ``n_ref``), so it carries sigma^2 (1 + 1/n_ref).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import pandas as pd


@dataclass(frozen=True)
class NoiseFloor:
    noise_floor_um: float  # RMSE of a perfect model on the thermal errors
    reading_sigma_um: float  # scatter of a single reading
    method: str  # "repeat" or "high_frequency"
    n_ref: float  # readings per target in the cold reference
    estimates: dict  # every estimator that had data: {name: (sigma_um, n)}

    def to_dict(self) -> dict:
        return asdict(self)


def repeat_scatter(rd: pd.DataFrame, window_s: float) -> tuple[float, int, int]:
    """Pooled SD of readings of one target of a run taken within ``window_s`` of the
    group's first reading; returns (sigma, degrees of freedom, groups), (nan, 0, 0)
    when no target is read twice that quickly."""
    ss, dof, groups = 0.0, 0, 0
    for _, g in rd.sort_values("t_s").groupby(["run_id", "target_mm"], sort=False):
        t = g["t_s"].to_numpy()
        y = g["error_um"].to_numpy()
        start = 0
        for k in range(1, t.size + 1):
            if k == t.size or t[k] - t[start] > window_s:  # close the group [start, k)
                v = y[start:k]
                if v.size > 1:
                    ss += float(np.sum((v - v.mean()) ** 2))
                    dof += v.size - 1
                    groups += 1
                start = k
    return (float(np.sqrt(ss / dof)), dof, groups) if dof else (float("nan"), 0, 0)


def high_frequency_scatter(rd: pd.DataFrame, residual_col: str = "residual_um") -> tuple[float, int]:
    """Robust sigma from the second time difference of the residual at each (run, target)."""
    d = []
    for _, g in rd[rd["cycle"] > 0].sort_values("t_s").groupby(["run_id", "target_mm"], sort=False):
        r = g[residual_col].to_numpy()
        if r.size >= 3:
            d.append(r[2:] - 2 * r[1:-1] + r[:-2])
    if not d:
        return float("nan"), 0
    d = np.concatenate(d)
    mad = float(np.median(np.abs(d - np.median(d))))
    return 1.4826 * mad / np.sqrt(6.0), int(d.size)


def estimate_noise_floor(rd: pd.DataFrame, window_s: float = 60.0, min_groups: int = 20) -> NoiseFloor:
    """Noise floor of readings ``rd`` (columns run_id, t_s, target_mm, error_um, cycle and
    the residual of a physics model ``residual_um``); see the module docstring."""
    rep, n_rep, groups = repeat_scatter(rd[rd["cycle"] > 0], window_s)
    hf, n_hf = high_frequency_scatter(rd)
    estimates = {}
    if n_rep:
        estimates["repeat"] = (rep, n_rep)
    if n_hf:
        estimates["high_frequency"] = (hf, n_hf)
    if groups >= min_groups:
        sigma, method = rep, "repeat"
    elif n_hf:
        sigma, method = hf, "high_frequency"
    else:
        raise ValueError(
            "cannot estimate the noise floor: no target is read repeatedly within "
            f"{window_s} s and no target has 3 readings after the cold reference"
        )
    ref = rd[rd["cycle"] == 0]
    n_ref = float(ref.groupby(["run_id", "target_mm"]).size().mean()) if len(ref) else 1.0
    floor = sigma * np.sqrt(1.0 + 1.0 / n_ref)
    return NoiseFloor(float(floor), float(sigma), method, n_ref, estimates)
