"""The C runtime's probe filter (embedded/src/tb_probe.c, ``tb_replay --probe``) against the Python
one (thermbench/adapt.py, itself checked against the joint estimate of the random walk in
tests/test_adapt.py): an exported model of seed001_vmc_x replayed over valid1 with a probe reading
every 10 min, in double precision (to rounding) and in single precision (the Cortex-M4F build,
within the required 0.01 µm)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from thermbench.bench import datasets
from thermbench.bench.adapt import ProbeFilter, ProbeParams
from thermbench.export import runtime
from thermbench.export.directory import replay_dir
from thermbench.export.samples import readings_queries


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


def test_replay_with_probes_is_the_python_filter_on_the_open_loop_replay(seed001_exports, seed001_data_root, tmp_path):
    """thermbench replay --probes: every reading's compensation is the open-loop replay's prediction
    corrected by the Python filter fed the probe readings in time order (each reading's correction
    the one before a probe at its own time); the readings that were probes are not scored; the
    probes bring the error down."""
    from thermbench.bench.adapt import ProbeFilter
    from thermbench.export.replay import read_probes, replay_run

    data = seed001_data_root / "seed001_vmc_x"
    open_loop = replay_run(seed001_exports / "mlr", data, "valid1")
    rd = open_loop["readings"]
    pick = rd.iloc[5 :: max(len(rd) // 6, 1)]  # after start-up (a probe before the model has a state is not taken)
    path = tmp_path / "probes.csv"
    pick.rename(columns={"target_mm": "axis_mm", "error_um": "measured_um"})[["t_s", "axis_mm", "measured_um"]].to_csv(path, index=False)
    probes = read_probes(path)
    closed = replay_run(seed001_exports / "mlr", data, "valid1", probes=probes)
    params = ProbeParams.from_config({})  # conf/compensator.yaml's probe block is the class defaults
    assert closed["figures"]["probe_params"] == params.as_dict()
    f = ProbeFilter(params, float(closed["compensation"]["t_s"].iloc[0]))
    pending = list(probes.itertuples(index=False))
    want = []
    for t, x, pred in zip(rd["t_s"], rd["target_mm"], rd["predicted_um"]):
        while pending and pending[0].t_s < t:
            p = pending.pop(0)
            f.probe(p.t_s, rd.loc[(rd["t_s"] == p.t_s) & (rd["target_mm"] == p.axis_mm), "predicted_um"].iloc[0], p.measured_um)
        want.append(f.correct(t, pred)[0])
    assert np.abs(np.array(want) - closed["readings"]["predicted_um"].to_numpy()).max() < 1e-9
    fig = closed["figures"]
    is_probe = rd["t_s"].isin(probes["t_s"])
    assert fig["n_probes"] == len(probes) and fig["n_readings_scored"] == int((~is_probe).sum())
    r_open = (rd["error_um"] - rd["predicted_um"])[~is_probe]
    assert fig["after_rmse_um"] < float(np.sqrt(np.mean(r_open**2)))


@pytest.mark.parametrize("text, message", [
    ("t_s,value\n0,1\n", "no column 'measured_um'; expected t_s, measured_um and optionally axis_mm, got ['t_s', 'value']"),
    ("t_s,measured_um\n0,1\n10,x\n", "column 'measured_um', row 3: expected a finite number, got 'x'"),
    ("t_s,measured_um\n10,1\n5,2\n", "column 't_s', row 3: times go back (5.0 after 10.0)"),
])
def test_bad_probe_files_are_one_line(tmp_path, text, message):
    from thermbench.export.encoding import ExportError
    from thermbench.export.replay import read_probes

    path = tmp_path / "p.csv"
    path.write_text(text)
    with pytest.raises(ExportError) as exc:
        read_probes(path)
    assert str(exc.value) == f"--probes {path}: {message}"
