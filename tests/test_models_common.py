"""The one interface, checked on every model family built from its conf/model config."""

import numpy as np
import pytest
from omegaconf import OmegaConf
from sklearn.base import clone

from thermbench.config import config_dir, load_config
from thermbench.experiment import model_from_config
from thermbench.models.base import ModelError, ThermalErrorModel
from thermbench.preprocess.filters import PreprocessError
from thermbench.sim.scenario import simulate_dataset

FAMILIES = sorted(p.stem for p in (config_dir() / "model").glob("*.yaml"))
# keep the test fast: fewer epochs / particles; one AR lag on a one-hour run
FAST = {"mlp": dict(max_epochs=200), "gru": dict(max_epochs=100), "lssvm": dict(iters=5, n_particles=8),
        "ar_seed003": dict(na=1, nb=1)}  # fmt: skip


@pytest.fixture(scope="module")
def two_runs():
    """Seed 000 X axis with realistic sensors: a 6000 mm/min run with cooling and a 3000 mm/min run."""
    cfg = load_config("simulate", ["seed=7", "protocol.random_runs.count=0"])
    OmegaConf.set_struct(cfg, False)
    cfg.protocol.runs = {
        "a": {"condition": {"start_mm": 0.0, "end_mm": 500.0, "feed_mm_min": 6000.0},
              "phases": [{"kind": "move", "duration_s": 3600}, {"kind": "stop", "duration_s": 1200}]},
        "b": {"condition": {"start_mm": 100.0, "end_mm": 300.0, "feed_mm_min": 3000.0},
              "phases": [{"kind": "move", "duration_s": 3600}]},
    }  # fmt: skip
    return simulate_dataset(cfg)[0]


def test_every_family_has_a_config():
    assert set(FAMILIES) >= {"mlr_seed001", "mlr_seed002", "mlr_seed004", "lssvm", "mlp", "gru", "ar_seed003", "physics"}


@pytest.mark.parametrize("name", FAMILIES)
def test_family_implements_the_interface(name, two_runs):
    model = model_from_config(name).set_params(**FAST.get(name, {}))
    assert isinstance(model, ThermalErrorModel)
    assert clone(model).get_params() == model.get_params()
    with pytest.raises(ModelError, match="not fitted"):
        model.predict(two_runs, "b")
    assert model.fit(two_runs, ["a"]) is model
    er = two_runs.errors_run("b")
    pred = model.predict(two_runs, "b")  # a run it was not trained on
    assert pred.shape == (len(er),) and np.all(np.isfinite(pred))
    # predict is predict_at at the readings, and the total error is geometric + thermal
    t, x = er["t_s"].to_numpy(), er["target_mm"].to_numpy()
    np.testing.assert_allclose(pred, model.predict_at(two_runs, "b", t, x))
    np.testing.assert_allclose(pred, model.predict_thermal_at(two_runs, "b", t, x) + model.geometric_um(x))
    # the compensation table holds the same numbers at its grid points
    tab = model.compensation_table(two_runs, "b", axis_mm=[0.0, 250.0, 500.0], step_s=600.0)
    assert tab.error_um.shape == (tab.t_s.size, 3)
    np.testing.assert_allclose(tab.error_um[:, 1], model.predict_at(two_runs, "b", tab.t_s, 250.0), atol=1e-9)
    # it declares inputs the dataset has
    inp = model.required_inputs()
    assert set(inp.sensors) <= set(two_runs.metadata.sensors)
    assert inp.sensors or inp.motion  # something must drive the thermal part


@pytest.mark.parametrize("name", ["mlr_seed002", "lssvm", "mlp"])
def test_nan_left_in_a_temperature_is_named(name, two_runs):
    ds = type(two_runs)(two_runs.metadata, two_runs.process.copy(), two_runs.errors)
    ds.process.loc[ds.process.index[50], "T_nut_C"] = np.nan
    model = model_from_config(name).set_params(sensors=["T_nut", "T_bed"], **FAST.get(name, {}))
    with pytest.raises(PreprocessError, match="T_nut_C.*run 'a'"):
        model.fit(ds, ["a"])
