"""What the identification of :class:`~thermbench.models.physics.PhysicsModel` keeps of each run:
its data prepared once (:class:`_RunData`: drive, readings, cold-reference indices, measured
signals), the runs prepared for the simulator at the last Pf values (:func:`_prepared_at`) and the
last simulated temperature fields (:class:`FieldCache`), so that the evaluations of a search share them."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ..sim.model import Motion, ScrewThermalModel

__all__ = ["PREPARED_PER_RUN", "FieldCache"]


@dataclass
class _RunData:
    """What identification needs from one run, prepared once."""

    run: str
    motion: Motion
    duration_s: float
    ambient_C: np.ndarray | float
    ambient_t_s: np.ndarray | None
    t_s: np.ndarray  # reading times
    x_mm: np.ndarray  # reading targets
    ref_idx: np.ndarray  # per reading, the index of its target's cold reference reading(s)
    thermal_um: np.ndarray  # measured thermal error
    signals: dict  # measured signals the effects follow: {sensor: (t_s, filtered series)}


def _signals_at(rd: _RunData, p) -> tuple[dict, dict]:
    """The run's measured signals as rises above their first sample, at the steps of the
    prepared run ``p``, and a dict for their lagged forms (:attr:`thermbench.sim.history.ThermalHistory.lagged`):
    kept with ``p`` for these signals, read-only."""
    kept = p.derived.get("signals_at")
    if kept is not None and kept[0] is rd.signals:
        return kept[1], kept[2]
    out = {n: np.interp(p.t_b_s, st, sv - sv[0]) for n, (st, sv) in rd.signals.items()}
    for a in out.values():
        a.setflags(write=False)
    p.derived["signals_at"] = (rd.signals, out, {})
    return out, p.derived["signals_at"][2]


#: prepared runs kept per run and numerics, at as many Pf values (:func:`_prepared_at`)
PREPARED_PER_RUN = 2


def _prepared_at(prepared: dict, rd: _RunData, model: ScrewThermalModel, source):
    """The run prepared for ``model``'s Pf with the ambient ``source`` (sensor and filters; None:
    constant): one of the last used for the run, or one made from the latest (only the nut's
    path anew, :meth:`ScrewThermalModel.prepare`); the least recently used past
    :data:`PREPARED_PER_RUN` is dropped, with its caches (cached histories keep it alive: their
    housings read it)."""
    kept = prepared.setdefault((rd.run, model.numerics, source), [])
    key = model.prepared_key()
    p = next((q for q in kept if q.key == key), None)
    if p is not None:  # the most recently used first
        kept.remove(p)
        kept.insert(0, p)
    else:
        p = model.prepare(rd.motion, ambient_C=rd.ambient_C, ambient_t_s=rd.ambient_t_s, duration_s=rd.duration_s,
                          at_other_pf=kept[0] if kept else None)  # fmt: skip
        kept.insert(0, p)
        for old in kept[PREPARED_PER_RUN:]:
            old.heat.clear()
            old.derived.clear()
        del kept[PREPARED_PER_RUN:]
    return p


class FieldCache:
    """The last ``size`` simulated temperature fields of an identification, by run, active
    gain and every parameter the field depends on (:meth:`.physics.PhysicsModel._basis`). The
    discrepancy search hands one to the fits of a step (``field_cache``), so candidates that
    only add offsets or slopes re-read the current model's fields instead of re-simulating."""

    def __init__(self, size: int = 64) -> None:
        self.size = size
        self._d: OrderedDict = OrderedDict()
        self.prepared: dict = {}  # (run id, numerics, ambient source) -> the last Prepared runs (at a Pf each)

    def get(self, key):
        hit = self._d.get(key)
        if hit is not None:
            self._d.move_to_end(key)
        return hit

    def put(self, key, value):
        self._d[key] = value
        self._d.move_to_end(key)
        while len(self._d) > self.size:
            self._d.popitem(last=False)
        return value
