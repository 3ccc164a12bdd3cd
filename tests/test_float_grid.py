"""Single precision at the classifier's grid times: the float runtime answered a query
exactly at a grid time with the previous condition's member, because its readiness said "ready
until 1e-6 s before the next grid time" and in float that margin vanishes (at 840 s floats are
6.1e-5 apart). The seed 002 MLR bank (9 members) on table6_1 changes condition at 840 s; the float
build was 0.71 um off there. Queried at every process sample (grid times included) the float and
double builds must pick the same member as the Python bank and agree to rounding, also with the
run moved to t = 2^22 s."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from thermbench.data.dataset import Dataset
from thermbench.bench.datasets import load_benchmark
from thermbench.export import export_model, replay_dir, runtime, unpack
from thermbench.export.budget import SINGLE_FLAGS
from thermbench.export.bundle import ExportOptions
from thermbench.export.samples import process_samples
from thermbench.models.bank import ConditionBank
from thermbench.models.mlr import MLRSeed002

from .families import shifted_run

TRAIN = [f"c{k}" for k in range(1, 10)]


@pytest.fixture(scope="module")
def seed002_bank(tmp_path_factory):
    ds = load_benchmark("seed002_vmc655h_x")
    bank = ConditionBank(MLRSeed002()).fit(ds, TRAIN)
    out = tmp_path_factory.mktemp("bank") / "bank"
    export_model(bank, out, "bank", ds, ["table6_1"], options=ExportOptions(verify=False))
    return ds, bank, out


@pytest.mark.parametrize("shift_s", [0.0, 2.0**22])
def test_every_sample_in_float_takes_the_member_python_takes(seed002_bank, shift_s):
    ds, bank, out = seed002_bank
    run = "table6_1"
    data = shifted_run(ds, run, shift_s) if shift_s else ds
    s = process_samples(data, run)
    q = pd.DataFrame({"t_s": s["t_s"].to_numpy(), "axis_mm": s["axis_mm"].to_numpy()})
    py = [str(c) for c in bank.conditions_at(data, run, q["t_s"].to_numpy())]
    t_rel = q["t_s"].to_numpy() - shift_s
    i840 = int(np.flatnonzero(t_rel == 840.0)[0])
    assert py[i840] != py[i840 - 1]  # the condition changes at the grid time 840 s: the case is exercised
    res = {}
    for prec, flags in (("double", ()), ("float", SINGLE_FLAGS)):
        c = replay_dir(out, data, run, q, exe=runtime.build("tb_replay", flags))
        labels = [str(bank.classifier_.classes_[i]) if i >= 0 else "None" for i in c["label"]]
        wrong = [float(t) for t, a, b in zip(t_rel, labels, py) if a != b]
        assert wrong == [], f"{prec}: another member than Python's at t = {wrong[:5]} s"
        res[prec] = c["total_um"].to_numpy()
    # the same member everywhere: float and double differ by rounding alone (it was 0.71 um at 840 s)
    assert np.max(np.abs(res["float"] - res["double"])) < 1e-3


def test_the_exports_parity_compares_float_and_double_at_every_sample(seed002_bank, tmp_path):
    ds, bank, _ = seed002_bank
    man = export_model(bank, tmp_path / "bank", "bank", ds, ["table6_1", "table6_2"])
    par = man["parity"]["model"]
    assert par["n_samples"] == len(ds.process_run("table6_1")) + len(ds.process_run("table6_2"))
    assert par["n_samples"] > 50 * par["n_readings"]  # every sample, not the readings
    assert par["float_vs_double_every_sample_max_abs_um"] < 1e-3


def test_a_float_build_off_at_one_sample_is_refused_for_a_float_target(seed002_bank, tmp_path, monkeypatch):
    """The check itself: the float build made 0.5 um wrong at one process sample (a grid time) between
    the readings; the parity at the readings cannot see it, the every-sample comparison names it."""
    from thermbench.export import parity
    from thermbench.export.budget import TargetRefused
    from thermbench.export.directory import read_manifest
    from thermbench.export.samples import readings_queries

    ds, bank, out = seed002_bank
    real = runtime.replay_text
    float_exe = runtime.build("tb_replay", SINGLE_FLAGS)

    def off_at_840(exe, files, text, *a, **k):  # each answer carries its query's time
        c = real(exe, files, text, *a, **k)
        if exe == float_exe:
            c.loc[c["t_s"].to_numpy() == 840.0, "total_um"] += 0.5
        return c

    monkeypatch.setattr(runtime, "replay_text", off_at_840)
    man = read_manifest(out)
    assert not (readings_queries(ds, "table6_1")["t_s"] == 840.0).any()  # no reading at the grid time
    with pytest.raises(TargetRefused, match=r"differs from the double build by 0\.5 um at t = 840 s of run 'table6_1' "
                                            r"\(every process sample of \['table6_1'\] compared\)"):
        parity._verify(out, man, {"bank": bank}, ds, ["table6_1"], 0.01, "bank", "float")
    parity._verify(out, man, {"bank": bank}, ds, ["table6_1"], 0.01, "bank", "double")  # a double target: reported only


def test_a_float_clock_with_a_tenth_of_a_second_period_is_on_its_grid_days_later(tmp_path):
    """A logger sampling every 0.1 s, 1.5 days into its run (t = 2^17 s, where floats are 1/64 s
    apart): each time the float runtime receives is the nearest float to t_first + k * 0.1, up to
    0.008 s off the exact grid. The sampling check accepts a time on the grid to the precision of
    the build (it refused them as off the grid, TB_E_SAMPLING), the GRU counts its lags back from
    the newest sample (it counted from the oldest, its rounding growing with the clock), and the
    float and double builds agree at every sample at both clocks."""
    from thermbench.bench.datasets import load_benchmark as load
    from thermbench.models.neural import GRUModel

    base = load("seed001_vmc_x")

    def every_tenth_s(shift_s: float) -> Dataset:  # seed001 (logged every 1 s) interpolated to 0.1 s
        runs = []
        for run, p in base.process.groupby("run_id", sort=False):
            t = np.round(np.arange(0, 10 * (len(p) - 1) + 1) * 0.1 + p["t_s"].iloc[0], 10)
            cols = {c: np.interp(t, p["t_s"], p[c]) for c in p.columns if c not in ("run_id", "t_s")}
            runs.append(pd.DataFrame({"run_id": run, "t_s": t + shift_s, **cols}))
        er = base.errors.assign(t_s=lambda d: d["t_s"] + shift_s)
        return Dataset(base.metadata, pd.concat(runs, ignore_index=True), er, path=base.path)

    ds = every_tenth_s(0.0)
    model = GRUModel(hidden_size=4, window_s=600.0, step_s=60.0, max_epochs=5, min_epochs=2, patience=5, seed=0)
    man = export_model(model.fit(ds, ["state1", "state2", "state3"]), tmp_path / "m", "m", ds, ["valid1"],
                       options=ExportOptions(verify=False))  # fmt: skip
    assert man["files"]["model"]["kind"] == "GRU"
    assert unpack((tmp_path / "m" / "model.tbm").read_bytes()).payload[0] == np.float32(0.1)  # its sample period
    exes = [runtime.build("tb_replay", f) for f in ((), SINGLE_FLAGS)]
    gap = {}
    for shift_s in (0.0, 2.0**17):
        data = every_tenth_s(shift_s)
        s = process_samples(data, "valid1")
        t = s["t_s"].to_numpy()
        q = pd.DataFrame({"t_s": t, "axis_mm": s["axis_mm"].to_numpy()})
        double, single = (replay_dir(tmp_path / "m", data, "valid1", q, exe=e)["total_um"].to_numpy() for e in exes)
        assert len(single) == len(double) == len(t)  # every sample answered (it was TB_E_SAMPLING, TB_E_LATE)
        gap[shift_s] = float(np.max(np.abs(single - double)))
    assert np.max(np.abs(t.astype(np.float32).astype(float) - t)) > 1e-3  # the float clock was off the grid
    # float arithmetic alone (the export's parity tolerance), and the clock adds nothing to it
    # (before, 0.26 um at 1.5 days: lags counted from rounded times fell between samples)
    assert gap[0.0] < 0.01 and gap[2.0**17] <= gap[0.0] + 1e-4, gap
