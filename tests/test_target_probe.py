"""The probe filter (embedded/src/tb_probe.c) and the extrapolation guard (embedded/src/tb_guard.c) on
the target: the Cortex-M4F harness (embedded/target/tb_target_main.c) cross-compiled and run on QEMU's
mps2-an386 (thermbench.export.target), against the host's double tb_replay with the same options
(--probe, --live --guard), on an exported model of seed001_vmc_x over valid1.

Marker ``target``: ``make target-test`` runs these (``make test`` does not). Without the cross
compiler or QEMU they fail, naming the packages: ``make target-test`` installs them (tools/sysdeps.sh)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from tests.test_target import ds, queries  # noqa: F401  (the fixtures: seed001_vmc_x and valid1's readings)
from thermbench.bench.adapt import ProbeParams
from thermbench.export import directory, read_manifest, runtime, target
from thermbench.export.budget import TARGETS

pytestmark = pytest.mark.target

RUN = "valid1"
FLOAT_UM = 0.01  # single-precision parity
PARAMS = ProbeParams(q_bias_um2_per_h=1.5, q_gain_per_h=1e-3, r_um2=0.04, bias0_um=2.0, gain0=0.1)  # tests/test_probe_runtime.py's
BUDGET = TARGETS["cortex-m4f"]["budget"]


@pytest.fixture(scope="module")
def probes(ds):
    """About 8 probe readings over the run, at reading times (as tests/test_probe_runtime.py)."""
    er = ds.errors_run(RUN)
    every = er.groupby("t_s", sort=True).first().reset_index()
    every = every[np.isin(every["t_s"], every["t_s"].iloc[:: max(len(every) // 8, 1)])]
    return pd.DataFrame({"t_s": every["t_s"], "axis_mm": every["target_mm"], "measured_um": every["error_um"]}).reset_index(drop=True)


@pytest.mark.parametrize("precision", ["double", "float"])
def test_the_probe_filter_on_the_target_is_the_host_s(seed001_exports, ds, queries, probes, precision):
    """Every reading of valid1 answered on the emulated M4 with the probe readings among the queries
    (a query at a probe's time before it): the corrected prediction and its variance are the host
    double tb_replay --probe's, to 5e-10 in double, within 0.01 µm (µm²) in float. Every probe is
    taken (one tb_probe_update each), every answer corrected (one tb_probe_correct each), and the
    harness counts both and reports the filter state's size on the target."""
    model_dir = seed001_exports / "mlr"
    host = directory.replay_dir(model_dir, ds, RUN, queries, probes=probes, probe_params=PARAMS)
    files, samples, temps, _ = directory.replay_inputs(model_dir, ds, RUN)
    got, rep = target.replay(files, samples, temps, queries, precision=precision, probes=probes, probe_params=PARAMS)
    assert rep["rc"] == 0 and len(got) == len(host) == len(queries) and (got["rc"] == 0).all()
    np.testing.assert_array_equal(got[["t_s", "axis_mm"]].to_numpy(), host[["t_s", "axis_mm"]].to_numpy())
    tol = 5e-10 if precision == "double" else FLOAT_UM
    d_corr = np.abs(got["corrected_um"].to_numpy() - host["corrected_um"].to_numpy()).max()
    d_var = np.abs(got["var_um2"].to_numpy() - host["var_um2"].to_numpy()).max()
    print(f"target {precision} vs host double: corrected {d_corr:.2e} um, variance {d_var:.2e} um^2")
    assert d_corr <= tol and d_var <= tol
    # the probes did something (the comparison is not of uncorrected values): the correction moves the
    # answers by micrometres and the variance falls after the first probe
    assert np.abs(host["corrected_um"] - host["total_um"]).max() > 1.0
    first = probes["t_s"].iloc[0]
    assert host.loc[host["t_s"] > first, "var_um2"].iloc[0] < host.loc[host["t_s"] <= first, "var_um2"].iloc[-1]
    # what the harness counted: one update per probe, one correction per answer, one prediction per both
    assert rep["probes_taken"] == len(probes) and rep["probes_skipped"] == 0
    assert rep["probe_update_calls"] == len(probes) and rep["probe_correct_calls"] == len(queries)
    assert rep["predict_calls"] == len(queries) + len(probes) and rep["guard_step_calls"] == 0
    assert 0 < rep["probe_correct_insn_mean"] <= rep["probe_correct_insn_max"] < rep["probe_update_insn_max"]
    assert 0 < rep["probe_update_stack_bytes"] <= rep["stack_bytes"] < 8192
    # the state on the target (32-bit): five parameters, bias, gain, three covariances, its time (tb_real each), a count
    assert rep["sizeof_tb_real"] == (8 if precision == "double" else 4)
    assert rep["sizeof_tb_probe_state"] == 11 * rep["sizeof_tb_real"] + 4 + (4 if precision == "double" else 0)


def test_the_guard_and_the_probes_live_on_the_target_are_the_host_s(seed001_exports, ds, queries, probes, tmp_path):
    """A narrow envelope (loading state 2's, the feed an operating input: valid1 leaves it, by up to a
    fifth of a range, and comes back) linked into flash beside the model, answered live with the probes, in float on the emulated
    M4: the guard's distance at every query is the host double tb_replay --live --guard's within 1e-3
    (relative), inside and outside alike, and the corrected predictions within 0.01 µm. One
    tb_guard_step per sample; the model, its arena, the filter and the guard fit the 16 KB RAM budget."""
    from thermbench.export.guard import write_envelope
    from thermbench.bench.intervals import Envelope

    model_dir = seed001_exports / "mlr"
    sensors = read_manifest(model_dir)["temperatures"]
    path = tmp_path / "narrow.tbm"
    write_envelope(path, Envelope.fit(ds, ["state2"], sensors, ["feed_mm_min"]), 600.0)
    files, samples, temps, _ = directory.replay_inputs(model_dir, ds, RUN)
    cols = [*temps, "feed_mm_min"]
    host = runtime.replay(files, samples, cols, queries, live=True, probes=probes, probe_params=PARAMS, guard=path)
    got, rep = target.replay(files, samples, cols, queries, precision="float", live=True, probes=probes, probe_params=PARAMS,
                             guard=path)  # fmt: skip
    assert rep["rc"] == 0 and len(got) == len(host) == len(queries)
    assert got["rc"].tolist() == host["rc"].tolist() and (got["rc"] == 0).mean() > 0.99
    ok = (host["rc"] == 0).to_numpy()
    want = host["distance"].to_numpy()
    outside = want > 1e-6
    assert 0.05 < outside.mean() < 0.95 and (want > 0.1).any()  # both inside and outside happen on this run
    dist = got["distance"].to_numpy()
    far = want > 1e-2
    d_abs = np.nanmax(np.abs(dist - want))
    d_rel = (np.abs(dist[far] - want[far]) / want[far]).max()
    d_corr = np.abs(got["corrected_um"].to_numpy()[ok] - host["corrected_um"].to_numpy()[ok]).max()
    print(f"target float vs host double, live: corrected {d_corr:.2e} um, distance {d_rel:.2e} relative beyond 0.01, "
          f"{d_abs:.2e} absolute")
    # within 1e-3 relative; at the edge of a range (distances of 1e-4 widths) float32 resolves a
    # temperature near 20 degC to 2e-6 K, which is what is left there (atol)
    np.testing.assert_allclose(dist, want, rtol=1e-3, atol=1e-5)
    assert (dist[want == 0] == 0).all() and (dist[want > 1e-4] > 0).all()
    assert d_corr <= FLOAT_UM
    assert rep["guard_step_calls"] == len(samples) and rep["step_calls"] == len(samples)
    assert 0 < rep["guard_step_insn_mean"] <= rep["guard_step_insn_max"] and 0 < rep["guard_step_stack_bytes"] < 8192
    ram = rep["arena_bytes"] + rep["sizeof_tb_model"] + rep["sizeof_tb_probe_state"] + rep["sizeof_tb_guard"]
    assert rep["sizeof_tb_guard"] > 2 * 32 * 4 and ram <= BUDGET["ram_bytes"]  # its two per-sensor arrays (TB_MAX_SENSORS)
    assert rep["step_insn_max"] + rep["guard_step_insn_max"] <= BUDGET["cycle_insn"]


def test_the_guard_needs_live_answers():
    """As runtime.replay: a guard's distance is the last sample's before a query (live)."""
    with pytest.raises(ValueError, match="live"):
        target.replay([], pd.DataFrame(), [], pd.DataFrame(), guard="envelope.tbm")


def test_a_finer_instruction_count_agrees_with_the_default_one(seed001_exports, ds, queries, probes):
    """icount_shift=3: QEMU advances 8 ns per instruction and the harness counts 5 instructions per
    SysTick tick. The calibration loop of 100 000 instructions counts 100 000 within 2 ticks (10
    instructions); each operation's mean count agrees with the default build's (steps of 40) to within
    a tick of the coarse count."""
    files, samples, temps, _ = directory.replay_inputs(seed001_exports / "mlr", ds, RUN)
    kw = dict(precision="float", probes=probes, probe_params=PARAMS)
    _, coarse = target.replay(files, samples, temps, queries, **kw)
    _, fine = target.replay(files, samples, temps, queries, icount_shift=3, **kw)
    assert abs(fine["calibrate_insn_max"] - 100_000) <= 10
    for what in ("step", "predict", "probe_update", "probe_correct"):
        assert fine[f"{what}_calls"] == coarse[f"{what}_calls"] > 0
        assert abs(fine[f"{what}_insn_mean"] - coarse[f"{what}_insn_mean"]) <= 40, what
        assert fine[f"{what}_insn_max"] % 5 == 0
