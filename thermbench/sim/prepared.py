"""What a run of the model is driven by, made once: the motion resampled on the model's fine
time grid (:class:`Drive`), what a run takes from the motion, the ambient series and the nut's
path alone (:class:`Prepared`: one serves every model that differs only in its gains), and the
inputs a run keeps (:class:`Kept`, within :data:`KEEP_BYTES`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class Drive:
    """The motion resampled on the model's fine time grid (seed 000 dt)."""

    t_s: np.ndarray
    dt_s: float
    axis_mm: np.ndarray
    x_screw_m: np.ndarray
    v_mm_min: np.ndarray
    load_N: np.ndarray | None


@dataclass
class Prepared:
    """What a run takes from the motion, the ambient series and the nut's path alone
    (:meth:`.model.ScrewThermalModel.prepare`): the drive, the ambient on the fine and macro
    grids, and the step-averaged nut coverage of every node, plain and speed-weighted.

    Models that differ only in k1..k4, lambda, the housings or the effects' gains give
    the same ``Prepared``, so one serves them all (identification re-runs the model
    many times per run; :meth:`.model.ScrewThermalModel.run_prepared`). ``key``: the screw,
    numerics and Pf it was made for; a model with others refuses it.
    """

    key: tuple
    drive: Drive
    t_b_s: np.ndarray  # macro-step boundaries
    ta0_C: float
    measured_f_C: np.ndarray | None  # the measured ambient on the fine grid (None: constant ta0)
    measured_b_C: np.ndarray | None  # ... on the macro grid
    cover: np.ndarray  # (n_steps, n_nodes) mean covered fraction
    v_cover: np.ndarray  # (n_steps, n_nodes) mean speed x covered fraction
    v_mean: np.ndarray  # (n_steps,) mean speed per step
    # measured signals (temperature rises above the first sample) at the macro-step boundaries
    signals_b: dict = field(default_factory=dict)
    # heat inputs already made over this run, by k3, k4 and the heating effects' parameters (they
    # do not depend on k1, k2 or lambda: identification's steps in those reuse them); read-only
    heat: "Kept" = field(default_factory=lambda: Kept(), repr=False, compare=False)
    # anything else a caller derives from this run and its Pf alone (identification's read plans)
    derived: dict = field(default_factory=dict, repr=False, compare=False)


#: what a run keeps of the inputs it has made (:class:`Kept`), per kind, in bytes
KEEP_BYTES = 64_000_000


class Kept(dict):
    """Inputs kept with a run (tuples of arrays and numbers), read-only, within
    :data:`KEEP_BYTES` in all: past it, what was kept is dropped; a value larger than that
    alone is not kept. The bytes held are counted as values come and go (:meth:`keep`: the
    only way in)."""

    nbytes = 0

    def __init__(self) -> None:
        super().__init__()
        self.nbytes = 0

    @staticmethod
    def _size(value: tuple) -> int:
        return sum(a.nbytes for a in value if isinstance(a, np.ndarray))

    def keep(self, key, value: tuple) -> tuple:
        """Keep ``value`` under ``key``; returns it."""
        n = self._size(value)
        if n > KEEP_BYTES:
            return value
        if key in self:
            self.nbytes -= self._size(self[key])
        if self.nbytes + n > KEEP_BYTES:
            self.clear()
        for a in value:
            if isinstance(a, np.ndarray):
                a.setflags(write=False)
        super().__setitem__(key, value)
        self.nbytes += n
        return value

    def clear(self) -> None:
        super().clear()
        self.nbytes = 0
