"""Physical terms a spindle's lumped network may miss: the discrepancy workflow's candidates on a
spindle test, each a small class with one job.

The base is :class:`~thermbench.models.lumped.LumpedThermalNetwork`: heat q = (u/u_ref)^p of the
operating signal (the spindle speed) through a chain of first-order nodes, the displacement a
linear combination of the node rises plus an offset. A machine's drift holds more than that
one path, and the literature on spindle thermal error names the usual suspects (Mayr et al.,
"Thermal issues in machine tools", CIRP Annals 61 (2012) §3; seed 003's spindle, whose
temperatures at bearings, housing and bed all enter the error):

* :class:`SecondHeatPath`: a second heat source with a time constant and a speed exponent of its
  own (the motor's heat vs the bearings', which scale with speed differently);
* :class:`StructureGrowth`: a structure that grows with a measured temperature (which sensor:
  chosen) through a lag, or, unsensed, lagging the speed by hours (the column, the headstock);
* :class:`SensorExpansion`: expansion with the ambient or the bed temperature, unlagged, relative
  to its value at the start of the log (a constant reference folds into the offset);
* :class:`StopDrift`: a node that heats with one time constant and cools with another during
  stops (convection while the spindle turns, none while it stands).

Each term adds one column per gain to the network's design, computed on the simulation grid
(:meth:`SpindleTerm.columns`) from what the drive offers: the heat of the operating signal at
any exponent, the fraction of each step the spindle runs, and each sensor's rise above its
first sample, all averaged over the grid's steps. A term describes itself: its linear
``gains``, its ``nonlinear`` parameters (identified by the network's search, in log where
``log_params`` says so, within ``bounds``, screened from ``starts``), its ``choice`` (a driving
signal), what it ``needs`` of the dataset, and its identified form in words (:meth:`describe`).
Adding a term is one class here, registered by ``@_register``: the network, the search, the
config checks and the report read only these attributes (as :mod:`thermbench.sim.open_terms`).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, ClassVar, Mapping

import numpy as np
from scipy.signal import lfilter

if TYPE_CHECKING:  # pragma: no cover
    from .lumped_drive import _Drive

#: the registered terms by id, in the order the search tries them
SPINDLE_TERMS: dict[str, type["SpindleTerm"]] = {}
#: lags shorter than this are described as "no lag" (s): ten simulation steps of the default 60 s, short
#: against the hours a spindle's structure takes (an unlagged expansion identifies a lag of a few minutes in noise)
NO_LAG_S = 600.0
#: sensor locations whose temperature expands the machine relative to a reference (SensorExpansion)
REFERENCE_LOCATIONS = ("ambient", "bed")


def _register(cls):
    SPINDLE_TERMS[cls.id] = cls
    return cls


def lag(x: np.ndarray, tau_s: float, h_s: float) -> np.ndarray:
    """First-order lag ``dθ/dt = (x − θ)/τ`` from rest, exact for ``x`` constant over each step
    of ``h_s``: ``x`` per step (n), θ at the grid times (n + 1)."""
    a = math.exp(-h_s / tau_s)
    out = np.zeros(x.size + 1)
    out[1:] = lfilter([1.0 - a], [1.0, -a], x)
    return out


def _lag_words(tau_s: float) -> str:
    if tau_s < NO_LAG_S:
        return "no lag"
    return f"a lag of {tau_s / 3600:.1f} h" if tau_s >= 5400 else f"a lag of {tau_s / 60:.0f} min"


def _where(signal: str, context: Mapping | None) -> str:
    loc = dict((context or {}).get("sensors", {})).get(signal)
    return f"{signal} ({loc})" if loc else signal


class SpindleTerm:
    """Base class: a term's self-description (module docstring) and its parameter values."""

    id: ClassVar[str] = ""
    description: ClassVar[str] = ""
    gains: ClassVar[tuple[str, ...]] = ("gain",)  # one design column each, solved linearly (any sign)
    nonlinear: ClassVar[tuple[str, ...]] = ()
    log_params: ClassVar[tuple[str, ...]] = ()  # nonlinear parameters searched in log (time constants)
    bounds: ClassVar[dict[str, tuple[float, float]]] = {}
    starts: ClassVar[dict[str, tuple[float, ...]]] = {}
    defaults: ClassVar[dict[str, float | str]] = {}
    choice: ClassVar[str | None] = None  # a parameter naming a driving signal ("speed" or a sensor)
    needs: ClassVar[tuple[str, ...]] = ()
    joint_starts: ClassVar[bool] = False  # screen the product of the start grids (parameters that trade off)

    def __init__(self, key: str | None = None, **params):
        self.key = key or self.id  # the instance's name in a network: the id, or ``<id>@<k>`` for a repeat
        known = {*self.nonlinear, *((self.choice,) if self.choice else ())}
        if bad := sorted(set(params) - known):
            raise ValueError(f"term {self.id!r}: unknown parameter(s) {bad}; it has {sorted(known)}")
        self.params = {**self.defaults, **params}
        for p in self.nonlinear:
            v = self.params[p]
            lo, hi = self.bounds[p]
            if not (isinstance(v, (int, float)) and lo <= float(v) <= hi):
                raise ValueError(f"term {self.id!r}: {p} = {v!r} is outside its bounds [{lo:g}, {hi:g}]")
            self.params[p] = float(v)

    def __getattr__(self, name):
        try:
            return self.__dict__["params"][name]
        except KeyError:
            raise AttributeError(name) from None

    def with_params(self, own: Mapping) -> "SpindleTerm":
        """A copy with nonlinear parameters ``own`` (the search's values: within bounds, unchecked)."""
        t = object.__new__(type(self))
        t.key, t.params = self.key, {**self.params, **own}
        return t

    def signals(self) -> tuple[str, ...]:
        """The temperature sensors the term reads (their rises come with the drive)."""
        s = self.params.get(self.choice) if self.choice else None
        return (s,) if s and s != "speed" else ()

    def columns(self, dr: "_Drive", u_ref: float, p: float) -> np.ndarray:
        """The term's design columns at the grid times, (n_steps + 1, len(gains)); ``p`` is the
        network's own heat exponent."""
        raise NotImplementedError

    def describe(self, context: Mapping | None = None) -> str:
        return self.description

    def canonical(self, context: Mapping | None = None) -> str | None:
        """The other term this identified one is (within tolerance), or None."""
        return None


@_register
class SecondHeatPath(SpindleTerm):
    id = "second_heat_path"
    description = "a second heat path: q2 = (u/u_ref)^p2 through its own lag tau (motor vs bearing heat)"
    nonlinear = ("tau_s", "exponent")
    log_params = ("tau_s",)
    bounds = {"tau_s": (60.0, 2.0e5), "exponent": (0.3, 3.0)}
    starts = {"tau_s": (900.0, 3600.0, 14400.0), "exponent": (1.0, 2.0)}
    defaults = {"tau_s": 3600.0, "exponent": 1.0}
    joint_starts = True

    def columns(self, dr, u_ref, p):
        return lag(dr.heat(u_ref, self.exponent), self.tau_s, dr.h)[:, None]

    def describe(self, context=None):
        return (f"a second heat path: heat growing with speed^{self.exponent:.2f}, through "
                f"{_lag_words(self.tau_s)} (tau {self.tau_s:.0f} s)")  # fmt: skip


@_register
class StructureGrowth(SpindleTerm):
    id = "structure_growth"
    description = "structure growth: a measured temperature's rise (or the speed) through a lag"
    nonlinear = ("tau_s",)
    log_params = ("tau_s",)
    bounds = {"tau_s": (30.0, 3.0e5)}
    starts = {"tau_s": (1800.0, 7200.0, 21600.0)}
    defaults = {"tau_s": 3600.0, "signal": "speed"}
    choice = "signal"

    def columns(self, dr, u_ref, p):
        x = dr.heat(u_ref, 1.0) if self.signal == "speed" else dr.signals[self.signal]
        return lag(x, self.tau_s, dr.h)[:, None]

    def describe(self, context=None):
        what = "the speed (unsensed)" if self.signal == "speed" else f"the rise of {_where(self.signal, context)}"
        return f"structure growth with {what}, through {_lag_words(self.tau_s)} (tau {self.tau_s:.0f} s)"

    def canonical(self, context=None):
        loc = dict((context or {}).get("sensors", {})).get(self.signal)
        # the same physics as the unlagged expansion on that sensor: the same label, so the search names the simpler
        return f"{SensorExpansion.id}[{self.signal}]" if self.tau_s < NO_LAG_S and loc in REFERENCE_LOCATIONS else None


@_register
class SensorExpansion(SpindleTerm):
    id = "sensor_expansion"
    description = "expansion with the ambient or bed temperature, unlagged, relative to its value at the start"
    defaults = {"signal": ""}
    choice = "signal"
    needs = ("reference_sensor",)

    def columns(self, dr, u_ref, p):
        x = dr.signals[self.signal]
        # the rise at the grid times from its step averages: the value held at each step's end
        return np.r_[0.0, x][:, None]

    def describe(self, context=None):
        return f"expansion with {_where(self.signal, context)}, unlagged, relative to its value at the start of the log"


@_register
class StopDrift(SpindleTerm):
    id = "stop_drift"
    description = "a node heating with one time constant while the spindle runs and cooling with another while it stands"
    nonlinear = ("tau_heat_s", "tau_cool_s")
    log_params = ("tau_heat_s", "tau_cool_s")
    bounds = {"tau_heat_s": (60.0, 2.0e5), "tau_cool_s": (60.0, 2.0e5)}
    starts = {"tau_heat_s": (1800.0, 7200.0), "tau_cool_s": (900.0, 3600.0, 14400.0)}
    defaults = {"tau_heat_s": 3600.0, "tau_cool_s": 3600.0}
    joint_starts = True

    def columns(self, dr, u_ref, p):
        """θ' = (q − θ)/τ_heat while running (more than half the step), −θ/τ_cool while stopped
        (q is 0 then), exact per step; one first-order section per stretch of one mode."""
        q = dr.heat(u_ref, p)
        run = dr.running >= 0.5
        out = np.zeros(q.size + 1)
        edges = np.flatnonzero(np.diff(run.astype(np.int8))) + 1
        theta = 0.0
        for a_i, b_i in zip(np.r_[0, edges], np.r_[edges, q.size]):
            tau = self.tau_heat_s if run[a_i] else self.tau_cool_s
            a = math.exp(-dr.h / tau)
            y, _ = lfilter([1.0 - a], [1.0, -a], q[a_i:b_i], zi=[a * theta])
            out[a_i + 1 : b_i + 1] = y
            theta = float(y[-1])
        return out[:, None]

    def describe(self, context=None):
        return (f"a node heating through {_lag_words(self.tau_heat_s)} while the spindle runs and cooling through "
                f"{_lag_words(self.tau_cool_s)} while it stands (tau {self.tau_heat_s:.0f} / {self.tau_cool_s:.0f} s)")  # fmt: skip


def base_id(key: str) -> str:
    """The term id of an instance name: ``structure_growth@2`` (a second structure growth, on
    another signal) is a ``structure_growth``."""
    return str(key).split("@", 1)[0]


def term_class(key: str) -> type[SpindleTerm]:
    try:
        return SPINDLE_TERMS[base_id(key)]
    except KeyError:
        raise ValueError(f"unknown spindle term {key!r}; known: {sorted(SPINDLE_TERMS)} (a repeat: <term>@2)") from None


def make_term(key: str, **params) -> SpindleTerm:
    return term_class(key)(key=key, **params)
