"""The sensor checks and bounds (embedded/src/tb_faults.c) on the target: the Cortex-M4F harness
(embedded/target/tb_target_main.c) cross-compiled and run on QEMU's mps2-an386
(thermbench.export.target), against the host's tb_replay --live --faults, over the shipped real
spindle test's stepped tail with each of the four faults planted into it, in both precisions.

Marker ``target``: ``make target-test`` runs these (``make test`` does not)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from tests.test_faults_runtime import fl_export  # noqa: F401  (the fixture: ch5 of fl_thermal exported)
from thermbench.bench.deployed import FAULT_KINDS, plant_fault
from thermbench.export import runtime, target
from thermbench.export.budget import TARGETS
from thermbench.export.directory import replay_inputs
from thermbench.export.faultfile import FAULTS_FILE

pytestmark = pytest.mark.target

BUDGET = TARGETS["cortex-m4f"]["budget"]


@pytest.mark.parametrize("precision", ["double", "float"])
@pytest.mark.parametrize("kind", FAULT_KINDS)
def test_the_checks_and_bounds_on_the_target_are_the_host_s(fl_export, kind, precision):  # noqa: F811
    """A fault planted into t2 an hour into the tail; the queries every fourth sample. On the emulated
    M4 each query's rules are the host build's of the same precision (the same rule at the same
    sample), the bounded correction and whether a bound acted too (to rounding in double, 0.01 µm in
    float); one tb_faults_step per sample, one tb_faults_bound per answer, and the checks' state (and,
    in float, the target's precision, their worst cycle) fit the target's budget beside the model."""
    ds, tail, out, man = fl_export
    onset = float(ds.errors_run(tail)["t_s"].min()) + 3600.0
    d = plant_fault(ds, tail, "t2", kind, onset)
    files, samples, temps, _ = replay_inputs(out, d, tail)
    q = pd.DataFrame({"t_s": samples["t_s"].to_numpy(float)[::4], "axis_mm": 0.0})
    flags = [] if precision == "double" else ["-DTB_SINGLE"]
    host = runtime.replay(files, samples, temps, q, exe=runtime.build("tb_replay", flags), live=True, faults=out / FAULTS_FILE)
    got, rep = target.replay(files, samples, temps, q, precision=precision, live=True, faults=out / FAULTS_FILE)
    assert rep["rc"] == 0 and len(got) == len(host) == len(q)
    assert got["rules"].tolist() == host["rules"].tolist()
    i = list(man["temperatures"]).index("t2")
    assert host["rules"].iloc[-1][i] != "0"  # the fault was judged
    tol = 1e-9 if precision == "double" else 0.01
    np.testing.assert_allclose(got["bounded_um"].to_numpy(float), host["bounded_um"].to_numpy(float), rtol=0, atol=tol)
    assert (got["bounded"] == host["bounded"]).mean() >= (1.0 if precision == "double" else 0.999)
    assert rep["faults_step_calls"] == len(samples) and rep["faults_bound_calls"] == len(q)
    assert 0 < rep["faults_step_insn_mean"] <= rep["faults_step_insn_max"] and 0 < rep["faults_step_stack_bytes"] < 8192
    ram = rep["arena_bytes"] + rep["sizeof_tb_model"] + rep["sizeof_tb_faults"]
    assert ram <= BUDGET["ram_bytes"]
    if precision == "float":  # the M4F's precision (its budget's): double is software arithmetic there
        assert rep["step_insn_max"] + rep["faults_step_insn_max"] + rep["faults_bound_insn_max"] <= BUDGET["cycle_insn"]
    print(f"{kind} {precision}: faults_step mean {rep['faults_step_insn_mean']:.0f} max {rep['faults_step_insn_max']} insn, "
          f"state {rep['sizeof_tb_faults']} B, stack {rep['faults_step_stack_bytes']} B")


def test_the_faults_file_needs_live_answers():
    with pytest.raises(ValueError, match="live"):
        target.replay([], pd.DataFrame(), [], pd.DataFrame(), faults="faults.tbm")
