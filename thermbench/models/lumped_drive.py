"""A run prepared for the lumped network's simulation (:class:`~thermbench.models.lumped.LumpedThermalNetwork`):
the operating log and the sensors' rises held from one sample to the next (zero-order hold) and averaged
over the intervals of a uniform grid, and where the requested times fall on that grid. The network's
terms (:mod:`thermbench.models.spindle_terms`) read their inputs from it."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import sparse


def _zoh_average(t: np.ndarray, v: np.ndarray, gidx: np.ndarray, gfrac: np.ndarray, h: float) -> np.ndarray:
    """Interval averages over a uniform grid of a signal held from each sample to the next
    (the last sample held on): ``gidx``/``gfrac`` locate each grid time in ``t``."""
    cum = np.concatenate([[0.0], np.cumsum(v[:-1] * np.diff(t))])
    f = cum[gidx] + v[gidx] * gfrac
    return np.diff(f) / h



@dataclass
class _Drive:
    """One run prepared for simulation: the grid, the operating samples, the ambient
    rise averaged over the grid, and where the requested times fall on the grid."""

    run: str
    h: float
    t_proc: np.ndarray
    u: np.ndarray
    gidx: np.ndarray
    gfrac: np.ndarray
    rise_avg: np.ndarray | None  # ambient/structure rise averaged per grid interval (°C)
    interp: sparse.csr_matrix  # linear interpolation from the grid to the requested times
    signals: dict | None = None  # rises of the sensors the terms read, averaged per grid interval (°C)
    running: np.ndarray | None = None  # fraction of each grid interval with the operating signal > 0
    _heat: dict | None = None  # {(u_ref, p): q} of the exponents asked for

    @property
    def n_steps(self) -> int:
        return self.gidx.size - 1

    def heat(self, u_ref: float, p: float) -> np.ndarray:
        """q per grid interval: (u/u_ref)^p held between samples, averaged over the interval."""
        if self._heat is None or len(self._heat) > 8:  # the exponents of one search: a few at a time
            self._heat = {}
        key = (u_ref, p)
        if key not in self._heat:
            self._heat[key] = _zoh_average(self.t_proc, (self.u / u_ref) ** p, self.gidx, self.gfrac, self.h)
        return self._heat[key]

    def at(self, states: np.ndarray) -> np.ndarray:
        """Grid states (n_steps + 1, m) interpolated to the requested times."""
        return self.interp @ states
