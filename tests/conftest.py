import os

# every test runs with the documented 256 MiB table cap, whatever the machine's memory (the default
# is a quarter of it): the size guards are tested at a fixed size (tests/test_dataset.py checks the
# default's scaling apart); set before thermbench is imported, and inherited by every subprocess
os.environ["THERMBENCH_MAX_TABLE_MIB"] = "256"

import numpy as np
import pytest
from omegaconf import OmegaConf

from thermbench.config import load_config
from thermbench.sim.duty import Measuring, Phase, build_run
from thermbench.sim.parts import Material, Screw

# seed 000 Table 1 (X axis)
SEED000_SCREW = Screw(length_m=0.8, diameter_m=0.034, nut_length_m=0.212, fixed_bearing_length_m=0.03)
SEED000_MATERIAL = Material(alpha_per_K=11.7e-6, density_kg_m3=7800.0, heat_capacity_J_kgK=448.0)


def seed000_motion(feed_mm_min, warm_s=5040, cool_s=2520, warm2_s=2520, dt_s=0.1, load_N=0.0):
    """seed 000 Table 2 loading over 0-500 mm with 10-min measuring cycles."""
    meas = Measuring(targets_mm=tuple(float(x) for x in range(0, 501, 50)), every_s=600, dwell_s=4, feed_mm_min=3000)
    phases = [Phase("move", warm_s, 0, 500, feed_mm_min, load_N)]
    if cool_s:
        phases.append(Phase("stop", cool_s))
    if warm2_s:
        phases.append(Phase("move", warm2_s, 0, 500, feed_mm_min, load_N))
    tr = build_run(phases, meas)
    return tr, tr.sample(np.arange(0.0, tr.now, dt_s))


@pytest.fixture
def short_cfg():
    """A seed 000 simulate config with two short runs (fast to simulate)."""
    cfg = load_config("simulate", ["seed=7"])
    OmegaConf.set_struct(cfg, False)
    cfg.protocol.runs = {
        "a": {
            "condition": {"start_mm": 0.0, "end_mm": 500.0, "feed_mm_min": 6000.0},
            "phases": [{"kind": "move", "duration_s": 1800}, {"kind": "stop", "duration_s": 600}],
        },
        "b": {
            "condition": {"start_mm": 100.0, "end_mm": 300.0, "feed_mm_min": 3000.0},
            "phases": [{"kind": "move", "duration_s": 1200}],
        },
    }
    cfg.protocol.random_runs = {"count": 0}
    return cfg


@pytest.fixture(scope="session")
def seed001_data_root(tmp_path_factory):
    """A benchmark root holding ``seed001_vmc_x`` only, built once per test session (per
    xdist worker; a few seconds), so tests that load it through ``THERMBENCH_DATA`` never
    depend on a prebuilt ``data/benchmark`` nor write into the repository."""
    from thermbench.bench import datasets

    root = tmp_path_factory.mktemp("benchmark")
    datasets.build("seed001_vmc_x", root)
    return root


@pytest.fixture(scope="session")
def seed001_exports(seed001_data_root, tmp_path_factory):
    """Two exported models of ``seed001_vmc_x`` (fitted on its five loading states, parity-checked
    on valid1): ``mlr`` (seed 002 MLR) and ``bank`` (seed 002 §2.4-2.5 per-condition bank of
    seed 001 MLR), the cheapest families: for the live runtime and the compensator."""
    from thermbench.bench import datasets
    from thermbench.export import export_model
    from thermbench.models.bank import ConditionBank
    from thermbench.models.mlr import MLRSeed001, MLRSeed002

    ds = datasets.load_benchmark("seed001_vmc_x", seed001_data_root)
    root = tmp_path_factory.mktemp("exports")
    states = ["state1", "state2", "state3", "state4", "state5"]
    for name, model in {"mlr": MLRSeed002(), "bank": ConditionBank(MLRSeed001())}.items():
        export_model(model.fit(ds, states), root / name, name, ds, ["valid1"])
    return root
