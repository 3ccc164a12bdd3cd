"""The C runtime's probe filter (embedded/src/tb_probe.c, ``tb_replay --probe``) against the Python
one (thermbench/adapt.py, itself checked against the joint estimate of the random walk in
tests/test_adapt.py): an exported model of seed001_vmc_x replayed over valid1 with a probe reading
every 10 min, in double precision (to rounding) and in single precision (the Cortex-M4F build,
within the issue's 0.01 µm)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from thermbench import datasets
from thermbench.adapt import ProbeFilter, ProbeParams
from thermbench.export import runtime
from thermbench.export.bundle import readings_queries, replay_dir


@pytest.mark.parametrize("flags, tol_um", [((), 1e-9), (("-DTB_SINGLE",), 0.01)])
def test_c_probe_filter_equals_python(seed001_exports, seed001_data_root, flags, tol_um):
    ds = datasets.load_benchmark("seed001_vmc_x", seed001_data_root)
    q = readings_queries(ds, "valid1")
    er = ds.errors_run("valid1")
    params = ProbeParams(q_bias_um2_per_h=1.5, q_gain_per_h=1e-3, r_um2=0.04, bias0_um=2.0, gain0=0.1)
    every = er.groupby("t_s", sort=True).first().reset_index()
    every = every[np.isin(every["t_s"], every["t_s"].iloc[:: max(len(every) // 8, 1)])]  # about 8 probes over the run
    probes = pd.DataFrame({"t_s": every["t_s"], "axis_mm": every["target_mm"], "measured_um": every["error_um"]})
    exe = runtime.build("tb_replay", list(flags))
    c = replay_dir(seed001_exports / "mlr", ds, "valid1", q, exe=exe, probes=probes, probe_params=params)
    assert len(probes) >= 5 and (c["rc"] == 0).all()
    # Python: the same filter over the C runtime's own uncorrected predictions, probes in time order,
    # a query at a probe's time answered before the probe
    f = ProbeFilter(params, float(min(q["t_s"].min(), probes["t_s"].min())))
    pending = list(probes.itertuples(index=False))
    corrected, var = [], []
    for t, x, total in zip(c["t_s"], c["axis_mm"], c["total_um"]):
        while pending and pending[0].t_s < t:
            p = pending.pop(0)
            pred = c.loc[(c["t_s"] == p.t_s) & (c["axis_mm"] == p.axis_mm), "total_um"].iloc[0]
            f.probe(p.t_s, pred, p.measured_um)
        v, s2 = f.correct(t, total)
        corrected.append(v)
        var.append(s2)
    assert f.n_probes == len(probes) - (1 if pending else 0)
    diff = np.abs(np.array(corrected) - c["corrected_um"].to_numpy()).max()
    print(f"max |C - Python| corrected {diff:.2e} um ({flags or 'double'})")
    assert diff <= tol_um
    assert np.abs(np.array(var) - c["var_um2"].to_numpy()).max() <= max(tol_um, 1e-9)
    # the probes did something: the corrected predictions are closer to the readings than the model's
    meas = er.set_index(["t_s", "target_mm"])["error_um"]
    m = meas.reindex(pd.MultiIndex.from_arrays([c["t_s"], c["axis_mm"]])).to_numpy()
    assert np.sqrt(np.mean((c["corrected_um"] - m) ** 2)) < np.sqrt(np.mean((c["total_um"] - m) ** 2))
