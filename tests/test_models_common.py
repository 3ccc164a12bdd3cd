"""The one interface, checked on every model family built from its conf/model config."""

import numpy as np
import pytest
from omegaconf import OmegaConf

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
    # the compensation table (seed 000 §4.3), given an unsorted grid, is sorted, and
    # between its nodes the compensator interpolates bilinearly from the four corners
    tab = model.compensation_table(two_runs, "b", axis_mm=[500.0, 0.0, 250.0], step_s=600.0)
    assert list(tab.axis_mm) == [0.0, 250.0, 500.0] and tab.error_um.shape == (tab.t_s.size, 3)
    t0, t1 = tab.t_s[2], tab.t_s[3]
    corners = model.predict_at(two_runs, "b", [t0, t0, t1, t1], [250.0, 500.0, 250.0, 500.0])
    by_hand = 0.75 * (0.5 * corners[0] + 0.5 * corners[1]) + 0.25 * (0.5 * corners[2] + 0.5 * corners[3])
    assert tab.at(t0 + 0.25 * (t1 - t0), 375.0)[0] == pytest.approx(by_hand, abs=1e-9)
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


@pytest.mark.parametrize("name", FAMILIES)
def test_prediction_does_not_use_the_predicted_runs_measurements(name, two_runs):
    """A model fitted on run a predicts run b from b's process log only: changing b's
    interferometer readings must not change the prediction."""
    model = model_from_config(name).set_params(**FAST.get(name, {})).fit(two_runs, ["a"])
    before = model.predict(two_runs, "b")
    errors = two_runs.errors.copy()
    errors.loc[errors["run_id"] == "b", "error_um"] += 1000.0
    tampered = type(two_runs)(two_runs.metadata, two_runs.process, errors)
    np.testing.assert_array_equal(model.predict(tampered, "b"), before)


def test_a_failed_refit_leaves_an_unfitted_model(two_runs):
    model = model_from_config("mlr_seed002").fit(two_runs, ["a"])
    with pytest.raises(ModelError, match="sensors"):
        model.set_params(sensors=["T_missing"]).fit(two_runs, ["a"])
    with pytest.raises(ModelError, match="not fitted"):
        model.predict(two_runs, "b")
    assert not [a for a in vars(model) if a.endswith("_")]
