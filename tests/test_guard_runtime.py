"""The C runtime's extrapolation guard (embedded/src/tb_guard.c, ``tb_replay --guard``) against the
Python one (thermbench/intervals.py EnvelopeGuard) and a hand computation: the envelope file an
export writes, read back as the C runtime reads it (float32), followed over a run it was not
fitted on, in double precision (to rounding) and in single precision (the Cortex-M4F build)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd
import pytest

from thermbench.bench import datasets
from thermbench.export import read_manifest, runtime
from thermbench.export.directory import replay_dir, replay_inputs
from thermbench.export.samples import process_samples, readings_queries
from thermbench.export.fileformat import ModelFileError
from thermbench.export.guard import read_envelope, write_envelope
from thermbench.bench.intervals import Envelope, EnvelopeGuard


def _python_distances(env: Envelope, tau_s: float, samples: pd.DataFrame, sensors, operating, t_query) -> np.ndarray:
    """EnvelopeGuard over the samples; each query gets the distance at the last sample at or before it."""
    g = EnvelopeGuard(env, tau_s)
    d = np.array([g.step(t, row[: len(sensors)], row[len(sensors):]) for t, row in
                  zip(samples["t_s"], samples[[*sensors, *operating]].to_numpy(dtype=float))])  # fmt: skip
    i = np.searchsorted(samples["t_s"].to_numpy(), np.asarray(t_query, dtype=float), side="right") - 1
    return np.where(i >= 0, d[np.maximum(i, 0)], np.nan)


@pytest.mark.parametrize("flags, rtol", [((), 1e-9), (("-DTB_SINGLE",), 1e-3)])
def test_c_guard_equals_python_on_the_exported_envelope(seed001_exports, seed001_data_root, flags, rtol):
    """The export's envelope.tbm (fitted on the five loading states) over valid1."""
    ds = datasets.load_benchmark("seed001_vmc_x", seed001_data_root)
    model_dir = seed001_exports / "mlr"
    man = read_manifest(model_dir)
    assert man["envelope"]["file"] == "envelope.tbm" and man["envelope"]["bytes"] == (model_dir / "envelope.tbm").stat().st_size
    env, tau_s = read_envelope(model_dir / "envelope.tbm", man["envelope"]["sensors"], man["envelope"]["operating"])
    # the file holds the manifest's envelope, to float32
    for key in ("lo", "hi", "width"):
        np.testing.assert_allclose(getattr(env, key), man["envelope"][key], rtol=1e-6, atol=1e-6)
    assert tau_s == man["envelope"]["rate_tau_s"]
    q = readings_queries(ds, "valid1")
    c = replay_dir(model_dir, ds, "valid1", q, exe=runtime.build("tb_replay", list(flags)), live=True, guard=True)
    _, samples, temps, _ = replay_inputs(model_dir, ds, "valid1")
    want = _python_distances(env, tau_s, samples, temps, [], c["t_s"])
    np.testing.assert_allclose(c["distance"].to_numpy(), want, rtol=rtol, atol=rtol)


@pytest.mark.parametrize("flags, rtol", [((), 1e-9), (("-DTB_SINGLE",), 1e-3)])
def test_c_guard_equals_python_with_an_operating_input_and_excursions(seed001_exports, seed001_data_root, tmp_path, flags, rtol):
    """A narrow envelope (one loading state's, with the feed as an operating input): valid1 leaves it
    and comes back; C and Python agree at every query, and both say where it is outside."""
    ds = datasets.load_benchmark("seed001_vmc_x", seed001_data_root)
    model_dir = seed001_exports / "mlr"
    sensors = read_manifest(model_dir)["temperatures"]
    narrow = Envelope.fit(ds, ["state1"], sensors, ["feed_mm_min"])
    path = tmp_path / "narrow.tbm"
    write_envelope(path, narrow, 600.0)
    env, tau_s = read_envelope(path, sensors, ["feed_mm_min"])
    files, samples, temps, _ = replay_inputs(model_dir, ds, "valid1")
    q = process_samples(ds, "valid1")[["t_s", "axis_mm"]].iloc[::7].reset_index(drop=True)
    exe = runtime.build("tb_replay", list(flags))
    c = runtime.replay(files, samples, [*temps, "feed_mm_min"], q, exe=exe, live=True, guard=path)
    want = _python_distances(env, tau_s, samples, temps, ["feed_mm_min"], c["t_s"])
    outside = want > 0
    assert 0.05 < outside.mean() < 0.95  # both inside and outside happen on this run
    np.testing.assert_allclose(c["distance"].to_numpy(), want, rtol=rtol, atol=rtol)
    assert ((c["distance"].to_numpy() > 1e-6) == (want > 1e-6)).mean() > 0.99


def test_guard_by_hand(seed001_exports, tmp_path):
    """One sensor, one operating input, three samples a second apart; the distances computed by
    hand, from the C runtime (stepping a model alongside, as a compensator does) and from Python."""
    tau = 600.0
    env = Envelope(("s",), ("rpm",), ["rise:s", "rate:s", "op:rpm"], np.array([0.0, -1.0, 0.0]), np.array([1.0, 1.0, 1000.0]),
                   np.array([1.0, 2.0, 1000.0]))  # fmt: skip
    path = tmp_path / "env.tbm"
    write_envelope(path, env, tau)
    T, rpm = [20.0, 20.5, 22.0], [500.0, 1500.0, 900.0]
    e1 = 20.0 + (1 - math.exp(-1 / tau)) * 0.5
    e2 = e1 + (1 - math.exp(-1 / tau)) * (22.0 - e1)
    want = [0.0,
            max(((20.5 - e1) * 3600 / tau - 1.0) / 2.0, (1500.0 - 1000.0) / 1000.0),  # the rate and the speed beyond
            max((2.0 - 1.0) / 1.0, ((22.0 - e2) * 3600 / tau - 1.0) / 2.0)]  # the rise and the rate beyond  # fmt: skip
    assert want[1] == pytest.approx(0.998, abs=0.001) and want[2] == pytest.approx(5.49, abs=0.01)
    g = EnvelopeGuard(read_envelope(path)[0], tau)
    np.testing.assert_allclose([g.step(t, [a], [b]) for t, a, b in zip([0.0, 1.0, 2.0], T, rpm)], want, rtol=1e-6)
    # the C guard: the seed001 model reads two sensors; the guard its first column and the second as rpm
    samples = pd.DataFrame({"t_s": [0.0, 1.0, 2.0], "axis_mm": 0.0, "feed_mm_min": 0.0, "T_nut_C": T, "T_bed_C": rpm})
    c = runtime.replay([seed001_exports / "mlr" / "model.tbm"], samples, ["T_nut_C", "T_bed_C"],
                       pd.DataFrame({"t_s": [0.0, 1.0, 2.0], "axis_mm": 0.0}), live=True, guard=path)  # fmt: skip
    np.testing.assert_allclose(c["distance"].to_numpy(), want, rtol=1e-6)


def test_a_damaged_envelope_file_is_refused(seed001_exports, tmp_path):
    data = bytearray((seed001_exports / "mlr" / "envelope.tbm").read_bytes())
    data[60] ^= 0xFF
    bad = tmp_path / "envelope.tbm"
    bad.write_bytes(bytes(data))
    with pytest.raises(ModelFileError, match="CRC"):
        read_envelope(bad)
    with pytest.raises(runtime.RuntimeFailed, match="CRC|error -5"):
        runtime.replay([seed001_exports / "mlr" / "model.tbm"], pd.DataFrame({"t_s": [0.0, 1.0], "axis_mm": 0.0,
                       "feed_mm_min": 0.0, "T_nut_C": 20.0, "T_bed_C": 20.0}), ["T_nut_C", "T_bed_C"],
                       pd.DataFrame({"t_s": [1.0], "axis_mm": [0.0]}), live=True, guard=bad)  # fmt: skip
