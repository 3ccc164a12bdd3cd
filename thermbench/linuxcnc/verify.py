"""Checks of a LinuxCNC closed-loop run (``thermbench linuxcnc sim``), from three records
made by three different programs:

* ``samples.txt``: LinuxCNC's own ``sampler``/``halsampler``, every servo period: the
  commanded position (``axis.x.pos-cmd``), the applied external offset (``axis.x.eoffset``)
  and the requested one (``axis.x.eoffset-request``), the actual position
  (``joint.0.motor-pos-fb``), the plant's machine time and the counts the component wrote;
* ``compensator_log.csv``: the component's per-cycle log;
* ``plant/``: the thermal plant's process log and dataset (the motion as the plant sampled it).

:func:`controller_figures`: does LinuxCNC's actual position equal the commanded position
plus the offset, and does the offset follow the request (counts x scale) within LinuxCNC's
own rate limit (``OFFSET_AV_RATIO`` x ``MAX_VELOCITY``)? :func:`replay_figures`: is the
compensation written what ``thermbench replay`` computes from the plant's logged motion?
:data:`SAMPLED` names the sampler's columns of ``samples.txt`` (the configuration :mod:`.sim` writes
wires them in this order).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Mapping

import numpy as np
import pandas as pd

SERVO_S = 0.001  # [EMCMOT]SERVO_PERIOD of the sim configuration
#: servo periods the external offset is given to reach a new request: LinuxCNC plans it within
#: OFFSET_AV_RATIO x the axis's velocity and acceleration (25 mm/s, 150 mm/s² here), so a step of a
#: few µm takes well under 10 ms; a step's size depends on how often the component got to write
#: (a loaded host writes less often, in bigger steps), the time to follow it does not
FOLLOW_PERIODS = 50

#: the sampler's columns: (name, cfg letter f=float s=s32, HAL signal, the pin that drives it when the
#: signal is made here; None: a signal the other nets already made)
SAMPLED = (("pos_cmd_mm", "f", "tb-pos-cmd", "axis.x.pos-cmd"), ("eoffset_mm", "f", "tb-eoffset", None),
           ("eoffset_request_mm", "f", "tb-eoffset-request", "axis.x.eoffset-request"),
           ("actual_mm", "f", "J0:pos-fb", None), ("machine_s", "f", "tb-time", None),
           ("counts", "s", "tb-counts", None), ("machine_on", "b", "sample:enable", None))  # fmt: skip


def read_samples(path: Path) -> pd.DataFrame:
    """halsampler's output (``-t``: the sample number first), one column per sampled pin."""
    names = ["sample", *(n for n, _, _, _ in SAMPLED)]
    df = pd.read_csv(path, sep=r"\s+", header=None, names=names, engine="python", on_bad_lines="skip")
    df = df.apply(pd.to_numeric, errors="coerce").dropna()  # the last line may be cut when halsampler is stopped
    return df.reset_index(drop=True)


def servo_delay(s: pd.DataFrame, max_periods: int = 5) -> tuple[int, np.ndarray]:
    """The simulated servo loop's delay in servo periods (the shift of the actual position behind
    commanded + offset that fits best; basic_sim's pass-through PID takes 2) and the residual
    actual - (commanded + offset) at that shift, in mm."""
    a, c = s["actual_mm"].to_numpy(), (s["pos_cmd_mm"] + s["eoffset_mm"]).to_numpy()
    res = [a[k:] - c[: c.size - k] for k in range(max_periods + 1)]
    k = int(np.argmin([np.max(np.abs(r)) for r in res]))
    return k, res[k]


def controller_figures(samples: pd.DataFrame, scale_mm: float, ratio: float, max_velocity_mm_s: float) -> dict:
    """What LinuxCNC did with the counts while the machine was on (all in mm unless named _um)."""
    gap = np.diff(samples["sample"].to_numpy())
    s = samples[samples["machine_on"] > 0].reset_index(drop=True)
    if len(s) < 10:
        raise ValueError(f"only {len(s)} servo samples with the machine on")
    delay, actual_vs = servo_delay(s)
    # the motion controller reads the counts at the start of its servo period, the sampler at the
    # end: a change written between the two shows one period later
    req = s["eoffset_request_mm"].to_numpy()
    cs = s["counts"].to_numpy() * scale_mm
    req_vs_counts = np.minimum(np.abs(req - cs), np.abs(req - np.concatenate([[cs[0]], cs[:-1]])))
    lag = s["eoffset_mm"] - s["eoffset_request_mm"]
    # the offset lies between the requests of the last FOLLOW_PERIODS servo periods (on its way from one
    # to the next), and equals the request wherever that has held for as long
    recent = s["eoffset_request_mm"].rolling(FOLLOW_PERIODS + 1, min_periods=1)
    lo, hi = recent.min().to_numpy(), recent.max().to_numpy()
    off = s["eoffset_mm"].to_numpy()
    outside = np.maximum(np.maximum(lo - off, off - hi), 0.0)
    held = (hi == lo) & (np.arange(len(s)) >= FOLLOW_PERIODS)
    rate = np.abs(np.diff(s["eoffset_mm"].to_numpy())) / SERVO_S
    return {
        "servo_samples": int(len(samples)), "servo_samples_machine_on": int(len(s)),
        "samples_lost": int(np.sum(gap[gap > 1] - 1)),
        "servo_delay_periods": delay,
        "actual_minus_commanded_plus_offset_max_abs_um": 1e3 * float(np.max(np.abs(actual_vs))),
        "request_minus_counts_x_scale_max_abs_um": 1e3 * float(np.max(np.abs(req_vs_counts))),
        "offset_minus_request_max_abs_um": 1e3 * float(np.max(np.abs(lag))),
        "offset_outside_recent_requests_max_um": 1e3 * float(np.max(outside)),
        "offset_minus_held_request_max_abs_um": 1e3 * float(np.max(np.abs(lag.to_numpy()[held]))) if held.any() else None,
        "request_held_samples": int(held.sum()),
        "offset_rate_max_mm_s": float(rate.max()) if rate.size else 0.0,
        "offset_rate_limit_mm_s": ratio * max_velocity_mm_s,
        "offset_max_abs_um": 1e3 * float(np.max(np.abs(s["eoffset_mm"]))),
        "counts_max_abs": int(np.max(np.abs(s["counts"]))),
    }  # fmt: skip


def replay_figures(model_dir: Path, plant_dir: Path, log: pd.DataFrame, run: str, probe_params=None) -> dict:
    """``thermbench replay`` of the plant's dataset against what the component wrote: at each
    of the plant's process samples (grid time t_k, its axis position), the component's value
    at its first cycle at or past t_k (the cycle that stepped the model with grid point k). The
    probe readings the component took (flag PROBE in its log) are replayed as ``--probes``, with
    the component's filter noise ``probe_params``."""
    from ..export.replay import replay_run
    from ..compensator.control import Flags

    took = log[(log["flags"].astype(int) & int(Flags.PROBE)) != 0] if "probe_um" in log else log.iloc[:0]
    probes = None
    if len(took):
        probes = pd.DataFrame({"t_s": took["t_s"].to_numpy(float), "axis_mm": took["axis_mm"].to_numpy(float),
                               "measured_um": took["probe_um"].to_numpy(float)})  # fmt: skip
    rep = replay_run(model_dir, plant_dir / "dataset", run, probes=probes, probe_params=probe_params)
    comp = rep["compensation"]
    ok = log[log["value_um"].notna() & ~log["flag_names"].astype(str).str.contains("HELD|NOT_READY")]
    t_log = ok["t_s"].to_numpy()
    idx = np.searchsorted(t_log, comp["t_s"].to_numpy() - 1e-9)
    has = idx < t_log.size
    written = ok["value_um"].to_numpy()[idx[has]]
    want = comp["compensation_um"].to_numpy()[has]
    x_log = ok["axis_mm"].to_numpy()[idx[has]]
    d = written - want
    f = rep["figures"]
    return {
        "compared_samples": int(has.sum()),
        "written_minus_replay_max_abs_um": float(np.max(np.abs(d))),
        "written_minus_replay_rms_um": float(np.sqrt(np.mean(d**2))),
        "position_difference_max_mm": float(np.max(np.abs(x_log - comp["axis_mm"].to_numpy()[has]))),
        "replay_before_max_abs_um": f.get("before_max_abs_um"), "replay_after_max_abs_um": f.get("after_max_abs_um"),
        "replay_readings": f.get("n_readings"), "probes": 0 if probes is None else len(probes),
    }  # fmt: skip


def check_run(stage: Path, cfg: Mapping[str, Any]) -> dict:
    """Every figure of a finished run directory (``thermbench linuxcnc sim``)."""
    stage = Path(stage)
    samples = read_samples(stage / "samples.txt")
    log = pd.read_csv(stage / "compensator_log.csv")
    plant = json.loads((stage / "plant" / "closed_loop.json").read_text())
    ctrl = controller_figures(samples, float(cfg["scale_per_count"]), float(cfg["offset_av_ratio"]),
                              float(cfg["max_velocity_mm_s"]))  # fmt: skip
    from ..bench.adapt import ProbeParams
    from ..config import with_defaults

    comp_cfg = with_defaults("linuxcnc_component", dict(cfg.get("component") or {}))
    rep = replay_figures(stage / "model", stage / "plant", log, "linuxcnc", ProbeParams.from_config(comp_cfg.get("probe")))
    summary = json.loads((stage / "compensator_log.summary.json").read_text())
    return {"ok": True, "time_scale": float(cfg["time_scale"]), "tool": plant, "controller": ctrl, "replay": rep,
            "component": {k: summary.get(k) for k in ("cycles", "cycle_ms", "flags", "ended")}}  # fmt: skip


def format_figures(f: Mapping[str, Any]) -> str:
    t, c, r = f["tool"], f["controller"], f["replay"]
    return "\n".join([
        f"linuxcnc sim: {t['machine_s'] / 3600:.2f} h of thermal time at {f['time_scale']:g}x, {t['samples']} process samples",
        f"  thermal error at the tool: before max {t['before_max_abs_um']:.2f} um (rms {t['before_rms_um']:.2f}), "
        f"after LinuxCNC's offset max {t['after_max_abs_um']:.2f} um (rms {t['after_rms_um']:.2f})",
        f"  LinuxCNC: actual - (commanded + offset) {c['servo_delay_periods']} servo periods before: max "
        f"{c['actual_minus_commanded_plus_offset_max_abs_um']:.4f} um; "
        f"request - counts x scale max {c['request_minus_counts_x_scale_max_abs_um']:.4f} um; offset - request max "
        f"{c['offset_minus_request_max_abs_um']:.3f} um; offset rate max {c['offset_rate_max_mm_s']:.3f} mm/s "
        f"(limit {c['offset_rate_limit_mm_s']:g})",
        f"  written vs thermbench replay of the plant's log: max {r['written_minus_replay_max_abs_um']:.3f} um "
        f"over {r['compared_samples']} samples; replay before {r['replay_before_max_abs_um']:.2f} um, after "
        f"{r['replay_after_max_abs_um']:.2f} um at {r['replay_readings']} readings",
    ])  # fmt: skip
