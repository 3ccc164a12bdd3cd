"""Hand-made spindle tests with a known hidden term, for checking the spindle workflow
(its tests and the recovery table).

A test as fl_thermal is run: five constant-speed blocks, each heating ``on_s`` then stopped
``off_s``, then a stepped tail, one run whose segments are the blocks and the tail. The truth is
written here as ordinary differential equations and integrated by :func:`scipy.integrate.solve_ivp`
(tight tolerances, piece by piece between speed changes), independently of the network's code
(:mod:`thermbench.models.lumped` discretises exactly on a grid with :func:`scipy.signal.lfilter`):

* the base: heat q = (u/u_ref)^p through two first-order nodes, the drift c1 θ1 + c2 θ2 + d;
* the sensors: ``T_amb`` (ambient: a daily swing and a slow rise), ``T_bed`` (bed: the ambient
  lagged by 3 h, and the spindle's heat lagged by 4 h), ``T_head`` (headstock: the spindle's
  heat through two nodes, and half the ambient's swing), logged with small white noise;
* the hidden term, each as its documented physics (:mod:`thermbench.models.spindle_terms`), or
  physics outside the library (``chiller``: a coolant cycle of about 90 min that no sensor sees).

The drift is read every ``read_s`` with white gauge noise ``noise_um``. Nothing is random
except through ``seed``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.integrate import solve_ivp

#: what each hidden term may be, drawn at random from wide ranges (none is a start of the search's grid
#: but by chance of measure zero): ``{term: {parameter: (lo, hi, log)}}``; ``gain_um`` scales the term
RANGES = {
    "second_heat_path": {"tau_s": (600.0, 20000.0, True), "exponent": (0.6, 2.8, False)},
    "structure_growth": {"tau_s": (1200.0, 20000.0, True)},
    "sensor_expansion": {},
    "stop_drift": {"tau_heat_s": (900.0, 4000.0, True), "tau_cool_s": (8000.0, 30000.0, True)},
    "chiller": {"period_s": (3600.0, 7200.0, False)},
}
#: the signal of a signal-driven hidden term (the sensor it follows, or the speed)
SIGNALS = {"structure_growth": ("T_head", "T_bed", "speed"), "sensor_expansion": ("T_amb",)}
SENSORS = {"T_amb": "ambient", "T_bed": "bed", "T_head": "structure"}
U_REF = 6000.0


@dataclass
class SpindleWorld:
    """The test's schedule and the machine's base behaviour (module docstring)."""

    levels_rpm: tuple = (1250.0, 2500.0, 3750.0, 5000.0, 3500.0)
    tail_rpm: tuple = (500.0, 1500.0, 2500.0, 4500.0)
    on_s: float = 10800.0
    off_s: float = 10800.0
    tail_step_s: float = 5400.0
    log_s: float = 60.0
    read_s: float = 60.0
    noise_um: float = 0.1
    sensor_noise_C: float = 0.01
    tau_s: tuple = (1500.0, 9000.0)
    gains_um: tuple = (6.0, 14.0)
    exponent: float = 1.4
    offset_um: float = 0.5
    seed: int = 0

    def schedule(self) -> tuple[np.ndarray, np.ndarray]:
        """(switch times, speeds): each block on then off, then the tail's steps; the last held."""
        t, u = [], []
        now = 0.0
        for lv in self.levels_rpm:
            t += [now, now + self.on_s]
            u += [lv, 0.0]
            now += self.on_s + self.off_s
        for lv in self.tail_rpm:
            t.append(now)
            u.append(lv)
            now += self.tail_step_s
        return np.array(t), np.array(u)

    @property
    def end_s(self) -> float:
        return len(self.levels_rpm) * (self.on_s + self.off_s) + len(self.tail_rpm) * self.tail_step_s


@dataclass
class Hidden:
    """A hidden term: its kind, parameters, signal and gain (µm per unit of its state)."""

    term: str | None = None
    params: dict = field(default_factory=dict)
    signal: str | None = None
    gain_um: float = 0.0


def ambient_C(t):
    return 20.0 + 0.8 * np.sin(2 * np.pi * t / 86400.0 + 0.7) + 0.03 * t / 3600.0


def simulate(world: SpindleWorld, hidden: Hidden, t_eval: np.ndarray) -> dict[str, np.ndarray]:
    """The noise-free truth at ``t_eval``: the drift (µm), the base part and each sensor (°C)."""
    sw, levels = world.schedule()
    edges = np.r_[sw, np.inf]
    a0 = ambient_C(0.0)
    h = hidden
    n = 7  # b1, b2, head1, head2, bed_amb, bed_heat, term state

    def rhs(t, x, u):
        q = (u / U_REF) ** world.exponent
        amb = ambient_C(t) - a0
        b1, b2, h1, h2, ba, bq, s = x
        head = 1.5 * h2 + 0.5 * amb
        bed = ba + 0.3 * bq
        dx = [(q - b1) / world.tau_s[0], (b1 - b2) / world.tau_s[1], (q - h1) / 900.0, (h1 - h2) / 2400.0,
              (amb - ba) / 10800.0, (q - bq) / 14400.0, 0.0]  # fmt: skip
        if h.term == "second_heat_path":
            dx[6] = ((u / U_REF) ** h.params["exponent"] - s) / h.params["tau_s"]
        elif h.term == "structure_growth":
            drive = {"speed": u / U_REF, "T_head": head, "T_bed": bed}[h.signal]
            dx[6] = (drive - s) / h.params["tau_s"]
        elif h.term == "stop_drift":
            dx[6] = (q - s) / h.params["tau_heat_s"] if u > 0 else -s / h.params["tau_cool_s"]
        return dx

    out = np.zeros((t_eval.size, n))
    x = np.zeros(n)
    for k, u in enumerate(levels):
        t0, t1 = edges[k], min(edges[k + 1], world.end_s)
        if t1 <= t0:
            break
        sol = solve_ivp(rhs, (t0, t1), x, args=(float(u),), method="LSODA", rtol=1e-9, atol=1e-11, dense_output=True,
                        max_step=600.0)  # fmt: skip
        inside = (t_eval >= t0) & (t_eval <= t1)
        out[inside] = sol.sol(t_eval[inside]).T
        x = sol.y[:, -1]
    amb = ambient_C(t_eval) - a0
    base = world.gains_um[0] * out[:, 0] + world.gains_um[1] * out[:, 1] + world.offset_um
    if h.term in ("second_heat_path", "structure_growth", "stop_drift"):
        term = out[:, 6]
    elif h.term == "sensor_expansion":
        term = amb
    elif h.term == "chiller":
        term = np.sin(2 * np.pi * t_eval / h.params["period_s"])
    else:
        term = np.zeros(t_eval.size)
    return {
        "error_um": base + h.gain_um * term,
        "base_um": base,
        "term": term,
        "T_amb": a0 + amb,
        "T_head": a0 + 1.5 * out[:, 3] + 0.5 * amb,
        "T_bed": a0 + out[:, 4] + 0.3 * out[:, 5],
    }


def draw(term: str | None, strength_um: float, rng: np.random.Generator, world: SpindleWorld) -> Hidden:
    """A hidden term of kind ``term`` with parameters drawn from :data:`RANGES`, its gain set so that
    its contribution (its state minus its mean) has an RMS of ``strength_um`` over the test."""
    if term is None:
        return Hidden()
    params = {}
    for p, (lo, hi, log) in RANGES[term].items():
        params[p] = float(np.exp(rng.uniform(math.log(lo), math.log(hi)))) if log else float(rng.uniform(lo, hi))
    signals = SIGNALS.get(term)
    signal = str(signals[rng.integers(len(signals))]) if signals else None
    h = Hidden(term, params, signal, 1.0)
    t = np.arange(0.0, world.end_s, 300.0)
    s = simulate(world, h, t)["term"]
    h.gain_um = float(strength_um / max(np.std(s), 1e-12)) * (1 if rng.uniform() < 0.5 else -1)
    return h


def dataset(world: SpindleWorld, hidden: Hidden, noise: bool = True):
    """The test as a format 2 dataset (one run ``test``, segments b1..b5 and ``tail``), in memory."""
    from ..data.dataset import Dataset
    from ..data.schema import Metadata

    rng = np.random.default_rng(world.seed)
    t_log = np.arange(0.0, world.end_s + 1e-9, world.log_s)
    t_read = np.arange(world.read_s / 2, world.end_s, world.read_s)
    sw, levels = world.schedule()
    rpm = levels[np.clip(np.searchsorted(sw, t_log, side="right") - 1, 0, levels.size - 1)]
    log = simulate(world, hidden, t_log)
    proc = pd.DataFrame({"run_id": "test", "t_s": t_log, "spindle_rpm": rpm})
    for s in SENSORS:
        proc[f"{s}_C"] = np.round(log[s] + noise * world.sensor_noise_C * rng.standard_normal(t_log.size), 4)
    truth = simulate(world, hidden, t_read)
    err = truth["error_um"] + noise * world.noise_um * rng.standard_normal(t_read.size)
    errors = pd.DataFrame({"run_id": "test", "t_s": t_read, "channel": "Z", "error_um": err - err[0]})
    meta = {
        "format": "thermbench-dataset/2",
        "machine": {"name": "hidden_spindle"},
        "parts": ["spindle"],
        "operating": ["spindle_rpm"],
        "sensors": dict(SENSORS),
        "channels": {"Z": {"kind": "fixed_point", "direction": "Z", "location": "test_mandrel", "unit": "um"}},
        "reference": {"mode": "first_reading"},
        "runs": {"test": {"notes": f"hidden: {hidden.term} {hidden.params} {hidden.signal} gain {hidden.gain_um:.4g}",
                          "segments": [f"b{k + 1}" for k in range(len(world.levels_rpm))] + ["tail"]}},
    }  # fmt: skip
    return Dataset(Metadata.model_validate(meta), proc, errors)


def make(world: SpindleWorld, hidden: Hidden, out: Path) -> Path:
    """Write the test as a dataset directory (:func:`dataset`)."""
    from ..data.io import save_dataset

    save_dataset(dataset(world, hidden), out)
    return out


#: a hidden term may be at most this many times the machine's own drift (RMS): a term the base absorbs
#: all but a sliver of needs an absurd gain to show, and is redrawn (:func:`hidden_term`)
MAX_TERM_X_BASE = 3.0


def hidden_term(term: str | None, x_noise: float, rng: np.random.Generator, world: SpindleWorld,
                tries: int = 50) -> Hidden:  # fmt: skip
    """A hidden term drawn (:func:`draw`) and calibrated (:func:`calibrate`) to leave ``x_noise``
    times the gauge noise, redrawn while it would have to dwarf the machine's own drift to show."""
    t = np.arange(0.0, world.end_s, 300.0)
    base = np.std(simulate(world, Hidden(), t)["base_um"])
    for _ in range(tries):
        h = calibrate(world, draw(term, 1.0, rng, world), x_noise)
        if h.term is None or abs(h.gain_um) * np.std(simulate(world, h, t)["term"]) <= MAX_TERM_X_BASE * base:
            return h
    raise RuntimeError(f"no {term} in {tries} draws shows at {x_noise}x the noise without dwarfing the base drift")


def calibrate(world: SpindleWorld, hidden: Hidden, x_noise: float = 4.0, rounds: int = 3) -> Hidden:
    """``hidden`` with its gain scaled so that the base network, identified on the noise-free test's
    blocks without the term, leaves an RMSE of ``x_noise`` times the gauge noise (the strength a
    search sees: what the base cannot absorb; as :func:`thermbench.discrepancy.hidden.calibrate`)."""
    from ..models.lumped import LumpedThermalNetwork
    from ..bench.splits import dataset_view

    if hidden.term is None:
        return hidden
    target = x_noise * world.noise_um
    h = Hidden(hidden.term, dict(hidden.params), hidden.signal, hidden.gain_um)
    for _ in range(rounds):
        ds = dataset_view(dataset(world, h, noise=False), "Z", segments=True, history=True)
        blocks = [r for r in ds.run_ids if r != "tail"]
        m = LumpedThermalNetwork(n_nodes=2, operating="spindle_rpm", preprocess=None).fit(ds, blocks)
        left = m.rmse_um_
        if left <= 0:
            break
        h.gain_um *= target / left
    return h
