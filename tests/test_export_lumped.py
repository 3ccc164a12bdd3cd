"""Export of the lumped thermal network of a spindle (``physics_spindle``, docs/concepts.md "A lumped
thermal network for a spindle") to the C runtime's ``LUMPED`` kind: the runtime, fed a synthetic
format 2 spindle test sample by sample, reproduces the Python model at every reading; a run whose
log starts long before its readings (the history) included; under ASan/UBSan; in-process
(:class:`~thermbench.export.native.LiveModel`); and one-line errors for what it cannot run.

The payload is float32, but every real of the body is a float32 (hi, lo) pair: the measured
parity is ~1e-12 um (1e-4 um asserted; 0.01 um required).
"""

from __future__ import annotations

import contextlib
import copy
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from tests.test_dataset_v2 import SPINDLE_META, write
from thermbench.data import load_dataset
from thermbench.data.views import channel_view
from thermbench.export import ExportError, ExportOptions, Kind, budget, bundle, directory, encoding, export_model
from thermbench.export import fileformat, runtime
from thermbench.export.directory import read_manifest
from thermbench.export.samples import process_samples, readings_queries
from thermbench.export.lumped_encoding import encode_lumped
from thermbench.models.lumped import LumpedThermalNetwork
from thermbench.preprocess.filters import KalmanFilter, LimitFilter

TOL_UM = 1e-4
LOG_S = 15.0
BLOCK_S = 5400.0  # 1.5 h per speed level
HISTORY_S = 15000.0  # run "h": readings only from here on, the log from 0


# --------------------------------------------- hooks others add (meanwhile) ---
SAMPLE_COLUMNS = ("t_s", "axis_mm", "feed_mm_min", "load_N")


def _export_encoding(self, channels, period_s, where):
    """What ``LumpedThermalNetwork.export_encoding`` is to be (the reply names the exact code)."""
    return encode_lumped(self, channels, period_s, where)


def _check_limits_with_lumped(original):
    def check_limits(enc, where):
        if enc.kind == Kind.LUMPED:  # encode_lumped checks the LUMPED limits itself
            return enc
        return original(enc, where)

    return check_limits


def _replay_dir_with_operating(model_dir, ds, run, queries, variant="model", sanitize=False, exe=None, manifest=None,
                               samples=None, lenient=False):  # fmt: skip
    """directory.replay_dir with the proposed change: the manifest's ``operating`` columns are input
    channels after the temperatures."""
    man = manifest if manifest is not None else read_manifest(Path(model_dir))
    temps = [ds.metadata.sensor_column(s) for s in man["temperatures"]]
    samples = process_samples(ds, run) if samples is None else samples
    for c in man.get("operating", []):
        if c not in samples.columns:
            raise ExportError(f"{model_dir}: the model reads the operating input {c!r}, which run {run!r} lacks")
        temps.append(c)
    f = man["files"][variant]
    return runtime.replay([Path(model_dir) / f["file"]], samples, temps, queries, sanitize=sanitize, exe=exe,
                          lenient=lenient)  # fmt: skip


@contextlib.contextmanager
def lumped_hooks(model):
    """The hooks lumped.py, encoding.py and bundle.py are to hold, patched in only while they lack them."""
    with pytest.MonkeyPatch.context() as mp:
        if not callable(getattr(LumpedThermalNetwork, "export_encoding", None)):
            mp.setattr(LumpedThermalNetwork, "export_encoding", _export_encoding, raising=False)
        try:
            encoding.check_limits(encoding.Encoded(Kind.LUMPED, [1, 0, 0, 0], []), "probe")
        except KeyError:
            mp.setattr(encoding, "check_limits", _check_limits_with_lumped(encoding.check_limits))
        if not hasattr(bundle, "operating_inputs"):
            ops = [c for c in model.required_inputs().operating if c not in SAMPLE_COLUMNS]
            footprint = budget.footprint

            def footprint_and_operating(model_dir, man):  # called before the parity check and the manifest
                man.setdefault("operating", ops)
                return footprint(model_dir, man)

            mp.setattr(budget, "footprint", footprint_and_operating)
            mp.setattr(directory, "replay_dir", _replay_dir_with_operating)
        yield


def export(model, out: Path, ds, heldout, **opts) -> dict:
    with lumped_hooks(model):
        return export_model(model, out, out.name, ds, heldout, options=ExportOptions(**opts))


# ------------------------------------------------------------------ data ---
def _run(run_id: str, levels_rpm, rng, first_read_s: float = 0.0):
    """A stepped speed profile (15-s log), a ground truth of two lags of (u/6000)^1.5 with a front
    bearing and an ambient temperature in it; readings every 60 s from ``first_read_s``."""
    t = np.arange(0.0, len(levels_rpm) * BLOCK_S, LOG_S)
    rpm = np.asarray(levels_rpm, dtype=float)[(t // BLOCK_S).astype(int)]
    q = (rpm / 6000.0) ** 1.5
    a1, a2 = np.exp(-LOG_S / 900.0), np.exp(-LOG_S / 7200.0)
    th1, th2 = np.zeros(t.size), np.zeros(t.size)
    for i in range(1, t.size):
        th1[i] = a1 * th1[i - 1] + (1 - a1) * q[i - 1]
        th2[i] = a2 * th2[i - 1] + (1 - a2) * th1[i - 1]
    amb = 20.0 + 1.5 * np.sin(2 * np.pi * t / 30000.0) + 0.05 * rng.standard_normal(t.size)
    front = 22.0 + 8.0 * th1 + 0.5 * (amb - 20.0) + 0.05 * rng.standard_normal(t.size)
    front[40] = 85.0  # a power-on glitch: the limit filter runs in C too
    err = -8.0 * th1 + 25.0 * th2 + 1.2 * (front - front[0]) - 2.0 * (amb - amb[0]) + 0.2 * rng.standard_normal(t.size)
    proc = pd.DataFrame({"run_id": run_id, "t_s": t, "spindle_rpm": rpm, "T_front_C": front, "T_amb_C": amb})
    keep = (t >= first_read_s) & (np.arange(t.size) % 4 == 1)  # every 60 s, off the 60-s grid
    return proc, pd.DataFrame({"run_id": run_id, "t_s": t[keep], "channel": "Z", "error_um": err[keep]})


@pytest.fixture(scope="module")
def spindle(tmp_path_factory):
    """Format 2, a fixed-point channel Z: run "a" (training) and run "h", whose log starts
    HISTORY_S before its first reading (a segment with its history)."""
    rng = np.random.default_rng(0)
    pa, ea = _run("a", [0, 3000, 6000, 1500, 0, 4500, 2000], rng)
    ph, eh = _run("h", [4000, 0, 6000, 3000, 5000], rng, first_read_s=HISTORY_S)
    meta = {**SPINDLE_META, "runs": {"a": {}, "h": {}}}
    root = write(tmp_path_factory.mktemp("spindle") / "ds", meta, pd.concat([pa, ph]), pd.concat([ea, eh]))
    return channel_view(load_dataset(root), "Z")


CONFIGS = {
    "speed_1node": dict(n_nodes=1),
    "speed_2nodes": dict(n_nodes=2),
    "ambient": dict(n_nodes=2, ambient_sensor="T_amb"),
    "sensors": dict(n_nodes=2, sensors=["T_front", "T_amb"]),
    "ambient_and_sensors": dict(n_nodes=2, ambient_sensor="T_amb", sensors=["T_front", "T_amb"]),
}


@pytest.fixture(scope="module")
def exported(spindle, tmp_path_factory):
    root = tmp_path_factory.mktemp("lumped")
    out = {}
    for name, kw in CONFIGS.items():
        m = LumpedThermalNetwork(n_starts=1, **kw).fit(spindle, ["a"])
        out[name] = (m, root / name, export(m, root / name, spindle, ["h"]))
    return out


def c_vs_python(model, model_dir, ds, run, sanitize=False) -> tuple[float, int]:
    q = readings_queries(ds, run)
    with lumped_hooks(model):
        c = directory.replay_dir(model_dir, ds, run, q, sanitize=sanitize)
    py = model.predict_at(ds, run, q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
    return float(np.max(np.abs(c["total_um"].to_numpy() - py))), len(q)


# ---------------------------------------------------------------- parity ---
@pytest.mark.parametrize("name", list(CONFIGS))
def test_c_runtime_reproduces_the_lumped_network(exported, spindle, name):
    """Speed only (1 and 2 nodes), a lagged ambient drive, two unlagged sensors, both: the C runtime
    within 1e-4 um of Python on the training run and on the run with a long history."""
    model, model_dir, man = exported[name]
    assert man["kind"] == "LUMPED" and man["files"]["model"]["dims"][0] == model.n_nodes_
    assert man["operating"] == ["spindle_rpm"] and man["temperatures"] == list(model.required_inputs().sensors)
    assert man["parity"]["model"]["max_abs_diff_um"] < TOL_UM and man["parity"]["runs"] == ["h"]
    for run in ("a", "h"):
        worst, n = c_vs_python(model, model_dir, spindle, run)
        assert n >= 190
        assert worst < TOL_UM, f"{name} on {run}: max |C - Python| = {worst} um"
    fp = man["footprint"]
    assert fp["within_budget"] and fp["file_bytes"] < 1024 and fp["ram_bytes"] < 4096


def test_history_run_is_simulated_from_its_first_process_sample(exported, spindle):
    """Run "h": readings from 15 000 s on, the network heated from the log's start at 0 s; a log
    cut at the first reading gives a visibly different answer (the history matters)."""
    model, model_dir, _ = exported["speed_2nodes"]
    q = readings_queries(spindle, "h")
    assert q["t_s"].min() >= HISTORY_S and spindle.process_run("h")["t_s"].min() == 0.0
    worst, _ = c_vs_python(model, model_dir, spindle, "h")
    assert worst < TOL_UM
    cut = process_samples(spindle, "h")
    cut = cut[cut["t_s"] >= HISTORY_S].reset_index(drop=True)
    with lumped_hooks(model):
        c = directory.replay_dir(model_dir, spindle, "h", q, samples=cut)
    py = model.predict_at(spindle, "h", q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
    assert np.max(np.abs(c["total_um"].to_numpy() - py)) > 1.0


def test_sanitizers_find_nothing(exported, spindle):
    model, model_dir, _ = exported["ambient_and_sensors"]
    worst, _ = c_vs_python(model, model_dir, spindle, "h", sanitize=True)
    assert worst < TOL_UM


def test_live_model_steps_the_spindle_speed_as_an_input_channel(exported, spindle):
    """In-process, one control cycle at a time: the speed goes after the temperatures
    (LiveModel.operating); every value answered once final equals Python's."""
    from thermbench.export.native import LiveModel

    model, model_dir, _ = exported["sensors"]
    live = LiveModel(model_dir)
    assert live.operating == ["spindle_rpm"]
    pr = process_samples(spindle, "h")
    cols = [spindle.metadata.sensor_column(s) for s in live.temperatures]
    q = readings_queries(spindle, "h")
    tq, got, k = q["t_s"].to_numpy(), [], 0
    for row in pr.itertuples(index=False):
        r = row._asdict()
        assert live.step(r["t_s"], r["axis_mm"], r["feed_mm_min"], [r[c] for c in cols], operating=[r["spindle_rpm"]]) == 0
        while k < tq.size and tq[k] <= live.ready_s:
            rc, _, total, _ = live.predict(tq[k], 0.0)
            assert rc == 0
            got.append(total)
            k += 1
    assert k > 190
    py = model.predict_at(spindle, "h", tq[:k], np.zeros(k))
    assert np.max(np.abs(np.asarray(got) - py)) < TOL_UM
    # the current compensation (before the grid interval closes) is an estimate, never refused
    rc, _, now, _ = live.predict(float(pr["t_s"].iloc[-1]), 0.0)
    assert rc == 0 and np.isfinite(now)


def test_a_bad_spindle_speed_is_refused_like_a_bad_temperature(exported, spindle):
    """A NaN or negative speed (a fractional power) is TB_E_INPUT (-11); --lenient skips it."""
    model, model_dir, _ = exported["speed_2nodes"]
    q = readings_queries(spindle, "h")
    for bad in (np.nan, -100.0):
        pr = process_samples(spindle, "h")
        pr.loc[500, "spindle_rpm"] = bad
        with lumped_hooks(model), pytest.raises(runtime.RuntimeFailed, match="error -11"):
            directory.replay_dir(model_dir, spindle, "h", q, samples=pr)
        with lumped_hooks(model):
            assert len(directory.replay_dir(model_dir, spindle, "h", q, samples=pr, lenient=True)) == len(q)


# ---------------------------------------------------------------- errors ---
class _MedianFilter(KalmanFilter):
    """A filter the C runtime does not run."""


def test_unsupported_options_are_one_line_export_errors(exported):
    model = exported["sensors"][0]
    odd = copy.copy(model)
    odd.preprocess = [LimitFilter(), _MedianFilter()]
    with pytest.raises(ExportError, match=r"^m: preprocess step _MedianFilter has no C implementation") as exc:
        encode_lumped(odd, None, LOG_S, "m")
    assert "\n" not in str(exc.value)
    with pytest.raises(ExportError, match=r"^m: the sensors' rises at the query time need the log's sample period"):
        encode_lumped(model, None, 0.0, "m")


def test_bad_lumped_files_are_refused_with_their_code(exported, tmp_path):
    """A spindle speed channel that is a temperature channel, a grid step below 1 s, an A_d
    diagonal above 1: each is TB_E_PAYLOAD (-8) at open, never a run."""
    import subprocess

    model = exported["ambient_and_sensors"][0]
    enc = encode_lumped(model, None, LOG_S, "m")
    body = _body_offset(enc)
    exe = runtime.build("tb_replay", sanitize=True)
    for at, value in ((body + 1, 0.0), (body + 3, 0.5), (body + 9, 1.5)):  # u_channel, step_s hi, A_d[0][0] hi
        p = list(enc.payload)
        if at == body + 1:
            p[body + 1] = 0.0  # the channel of the first temperature
        else:
            p[at], p[at + 1] = value, 0.0
        f = tmp_path / "bad.tbm"
        fileformat.write(f, enc.kind, enc.dims, p)
        res = subprocess.run([str(exe), "--info", str(f)], capture_output=True, text=True)
        assert res.returncode == 3 and "error -8:" in res.stderr, res.stderr
    fileformat.write(tmp_path / "good.tbm", enc.kind, enc.dims, enc.payload)
    assert runtime.info([tmp_path / "good.tbm"])["kind"].tolist() == [Kind.LUMPED]


def _body_offset(enc) -> int:
    """Where the LUMPED body starts in an encoded payload (after the period, sensors and geometry)."""
    S = enc.dims[1]
    at = 1 + S + S * encoding.SENSOR_VALS
    gtype, n = int(enc.payload[at]), int(enc.payload[at + 1])
    at += 4 + (2 * n if gtype == 2 else n)
    return at + 2 + int(enc.payload[at])


@pytest.mark.parametrize("name", ["speed_2nodes", "ambient_and_sensors"])
def test_float_and_double_agree_at_every_sample_also_at_t_2_22(exported, spindle, name):
    """Every process sample of run "h" (its 15-s log, readings off the grid, the stream's
    end) in the single- and the double-precision build, the run as recorded and moved to
    t = 2^22 s (floats 0.5 s apart there): the float build's times step the network as the
    double build's do, so the answers agree to rounding at both clocks."""
    from tests.families import double_and_float_at_every_sample

    model, model_dir, man = exported[name]
    assert man["parity"]["model"]["float_vs_double_every_sample_max_abs_um"] < 1e-3  # the export's own check
    for shift_s in (0.0, 2.0**22):
        with lumped_hooks(model):
            double, single = double_and_float_at_every_sample(
                spindle, "h", shift_s, lambda data, q, exe: directory.replay_dir(model_dir, data, "h", q, exe=exe))
        assert len(double) == len(spindle.process_run("h")) and np.max(np.abs(single - double)) < 1e-3, shift_s
