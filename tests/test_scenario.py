"""Configs, duty cycles, instruments, the simulate command and the benchmark datasets."""

import numpy as np
import pandas as pd
import pytest
from omegaconf import OmegaConf

from thermbench.bench import datasets
from thermbench.cli import main
from thermbench.config import ConfigError, config_dir, load_config
from thermbench.data import load_dataset
from thermbench.data.reference import run_summary, thermal_errors
from thermbench.sim.duty import Measuring, Phase, build_run
from thermbench.sim.instruments import GeometricError, SensorSpec
from thermbench.sim.model import ScrewThermalModel
from thermbench.sim.scenario import build_model, simulate_dataset

MACHINES = sorted(p.stem for p in (config_dir() / "machine").glob("*.yaml"))
PROTOCOLS = sorted(p.stem for p in (config_dir() / "protocol").glob("*.yaml"))


@pytest.mark.parametrize("machine", MACHINES)
@pytest.mark.parametrize("truth", ["none", "benchmark"])
def test_every_machine_config_builds_a_model(machine, truth):
    cfg = load_config("simulate", [f"machine={machine}", f"truth={truth}"])
    model = build_model(cfg)
    assert model.screw.mounting in ("fixed_free", "fixed_supported", "fixed_fixed")
    if truth == "benchmark":
        assert {e.id for e in model.effects} >= {"ambient_drift", "motor_heat", "origin_drift"}
        assert model.numerics.dx_m == 0.005


def test_bad_override_names_the_key():
    with pytest.raises(ConfigError, match="machine"):
        load_config("simulate", ["machine=no_such_machine"])
    cfg = load_config("simulate", ["+effects.spindle_heat.k=1"])
    with pytest.raises(ValueError, match="spindle_heat"):
        build_model(cfg)
    cfg = load_config("simulate", ["numerics.macro_dt_s=0.25"])
    with pytest.raises(ValueError, match="numerics"):
        build_model(cfg)


def test_protocol_tables_match_the_seeds():
    c2 = load_config("simulate", ["protocol=seed002_conditions"]).protocol
    runs = c2.runs
    assert [r for r in runs if r.startswith("c")] == [f"c{i}" for i in range(1, 10)]
    # seed 002 Table 5: #1-#3 left at 800, #4-#6 middle at 2000, #7-#9 right at 4000; strokes 50/100/300
    strokes = [runs[f"c{i}"].condition.end_mm - runs[f"c{i}"].condition.start_mm for i in range(1, 10)]
    assert strokes == [50, 100, 300] * 3
    assert [runs[f"c{i}"].condition.feed_mm_min for i in (1, 4, 7)] == [800, 2000, 4000]
    assert runs.c1.condition.start_mm == 0 and runs.c9.condition.end_mm == 650
    assert len([r for r in runs if r.startswith("table6_")]) == 7
    assert len(np.arange(0, 651, 50)) == 14 and c2.measuring.every_s == 1800 and c2.measuring.reference_repeats == 5
    c0 = load_config("simulate", ["protocol=seed000_table2"]).protocol
    for rid, feed in (("cond1_3000", 3000), ("cond2_6000", 6000), ("cond3_9000", 9000)):
        r = c0.runs[rid]
        assert r.condition.feed_mm_min == feed
        assert [p.duration_s for p in r.phases] == [84 * 60, 42 * 60, 42 * 60]  # seed 000 Table 2
    c1 = load_config("simulate", ["protocol=seed001_states"]).protocol
    t1 = [(c1.runs[f"state{i}"].condition.feed_mm_min, c1.runs[f"state{i}"].condition.start_mm,
           c1.runs[f"state{i}"].condition.end_mm) for i in range(1, 6)]  # fmt: skip
    assert t1 == [(8000, 210, 490), (6500, 210, 490), (15000, 210, 490), (8000, 0, 210), (8000, 0, 700)]


def test_duty_cycle_reciprocates_and_measures():
    meas = Measuring(targets_mm=(0.0, 100.0, 200.0), every_s=600.0, dwell_s=4.0, feed_mm_min=1200.0, reference_repeats=2)
    tr = build_run([Phase("move", 1800.0, 50.0, 150.0, 3000.0), Phase("stop", 600.0)], meas)
    t = np.arange(0.0, tr.now, 0.05)
    m = tr.sample(t)
    moving = (m.feed_mm_min == 3000.0)
    # the duty time at 3000 mm/min adds up to the move phase (less the walk into the stroke)
    assert abs(moving.sum() * 0.05 - 1800.0) < 10.0
    # apart from the walk from the last target into the stroke, the nut stays on [50, 150]
    inside = (m.axis_mm[moving] >= 50.0 - 1e-9) & (m.axis_mm[moving] <= 150.0 + 1e-9)
    assert inside.mean() > 0.99 and m.axis_mm[moving].min() >= 50.0 - 1e-9
    # 2 reference cycles + one per 600 s of duty (1800 + 600 s) = 6 cycles of 3 targets
    assert len(tr.readings) == 3 * (2 + 4)
    for t_read, target in tr.readings:
        assert abs(np.interp(t_read, tr.t_s, tr.x_mm) - target) < 1e-9  # dwelling on the target


def test_sensor_artefacts():
    rng = np.random.default_rng(0)
    t = np.arange(0.0, 36000.0, 1.0)
    spec = SensorSpec(noise_C=0.05, quantum_C=0.0625, spike_rate_per_h=1.0, dropout_rate_per_h=1.0)
    y = spec.read(np.full(t.size, 21.3), t, rng)
    q = y / 0.0625
    assert np.allclose(q, np.round(q))  # DS18B20 steps (spikes of 6.0 K and 85.0 are multiples too)
    assert (y == 85.0).sum() >= 5  # dropouts read the power-on value
    assert ((np.abs(y - 21.3) > 3) & (y != 85.0)).sum() >= 1  # spikes
    assert abs(np.median(y) - 21.3) < 0.07
    g = GeometricError(poly_um=(-3.0184, 0.0374, -8.8847e-5, 5.2357e-8))
    assert abs(g([0.0])[0] + 3.0184) < 1e-12  # seed 002 eq. 7 at P = 0


def test_same_config_same_numbers_and_seed_changes_them(short_cfg):
    a, _ = simulate_dataset(short_cfg)
    b, _ = simulate_dataset(short_cfg)
    pd.testing.assert_frame_equal(a.process, b.process, check_exact=True)
    pd.testing.assert_frame_equal(a.errors, b.errors, check_exact=True)
    short_cfg.seed = 8
    c, _ = simulate_dataset(short_cfg)
    assert not np.array_equal(a.errors["error_um"].to_numpy(), c.errors["error_um"].to_numpy())
    np.testing.assert_array_equal(a.process["axis_mm"].to_numpy(), c.process["axis_mm"].to_numpy())


def test_clean_switch_gives_the_bare_seed000_model(short_cfg):
    short_cfg.clean = True
    OmegaConf.set_struct(short_cfg, False)
    short_cfg.effects = {"motor_heat": {"k_motor_W_per_mm_min": 1e-3}}  # ignored when clean
    ds, _ = simulate_dataset(short_cfg)
    model = build_model(short_cfg)
    assert model.effects == []
    bare = ScrewThermalModel(model.screw, model.material, model.core, [], model.numerics)
    from thermbench.sim.scenario import protocol_runs, _targets
    from thermbench.sim.duty import Measuring as M

    meas_cfg = dict(OmegaConf.to_container(short_cfg.protocol.measuring))
    meas_cfg["targets_mm"] = _targets(meas_cfg["targets_mm"])
    meas = M(**meas_cfg)
    for run_id, run in protocol_runs(short_cfg, np.random.default_rng(0)).items():
        tr = build_run(run["phases"], meas)
        hist = bare.run(tr.sample(np.arange(0.0, tr.now, model.numerics.dt_s)), ambient_C=20.0, duration_s=tr.now)
        er = ds.errors_run(run_id)
        np.testing.assert_allclose(er["error_um"], hist.error_um(er["t_s"], er["target_mm"]), atol=1e-12)
    # no noise, no artefacts: the ambient sensor reads the constant ambient
    assert np.all(ds.process["T_ambient_C"] == 20.0)
    # the first reading of the cold reference is (almost) zero: no geometric error,
    # and the screw has only warmed by the measuring move to the first target
    assert np.all(ds.errors.groupby("run_id")["error_um"].first().abs() < 0.01)


def test_geometric_error_is_not_rezeroed(short_cfg):
    """The interferometer keeps the cold pitch error; the thermal part is the reading
    minus the cold reference at the same target (seed 002 §3.1)."""
    short_cfg.instruments.interferometer.noise_um = 0.0
    ds, _ = simulate_dataset(short_cfg)
    geo = GeometricError(**{k: v for k, v in OmegaConf.to_container(short_cfg.machine.geometric).items() if k != "_target_"})
    first = ds.errors.groupby("run_id").head(11)  # the cold reference cycle
    # the reference readings are the pitch error plus the little heat of the measuring moves
    np.testing.assert_allclose(first["error_um"], geo(first["target_mm"]), atol=0.5)
    assert np.ptp(geo(first["target_mm"])) > 2.0
    te = thermal_errors(ds)
    assert te.groupby("run_id")["thermal_um"].max().min() > 5.0


def test_cli_simulate_writes_a_valid_dataset(tmp_path, capsys):
    out = tmp_path / "sim"
    rc = main(["simulate", "protocol=seed004_warmup", "machine=seed004_ff_x", f"out_dir={out}", "file_format=parquet"])
    assert rc == 0
    ds = load_dataset(out)
    assert ds.metadata.screw.mounting == "fixed_fixed"
    assert (out / "process.parquet").exists()
    text = capsys.readouterr().out
    assert "warmup_6000" in text and str(out) in text and "max_thermal_error_um" in text
    assert main(["simulate", "machine=nope"]) == 2
    assert "machine" in capsys.readouterr().err


def test_benchmark_datasets_build_deterministically_and_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("THERMBENCH_DATA", str(tmp_path))
    assert datasets.names() == ["seed000_x", "seed001_vmc_x", "seed002_vmc655h_x", "seed004_ff_x"]
    path, summary = datasets.build("seed000_x")
    assert summary is not None
    path2, summary2 = datasets.build("seed000_x")
    assert path2 == path and summary2 is None  # cached: the config hash matches
    ds = datasets.load_benchmark("seed000_x")
    sim = ds.metadata.model_extra["simulation"]
    assert set(sim["effects"]) >= {"ambient_drift", "motor_heat", "origin_drift", "quadratic_friction_heat"}
    assert sim["numerics"]["dx_m"] == 0.005  # finer than any model's grid
    table = run_summary(ds)
    assert list(table["run_id"]) == ["cond1_3000", "cond2_6000", "cond3_9000", "random_01"]
    peaks = table.set_index("run_id")["max_thermal_error_um"]
    assert peaks["cond1_3000"] < peaks["cond2_6000"] < peaks["cond3_9000"]
    rebuilt, _ = datasets.build("seed000_x", root=tmp_path / "again", force=True)
    again = load_dataset(rebuilt)
    pd.testing.assert_frame_equal(again.errors, ds.errors, check_exact=True)
