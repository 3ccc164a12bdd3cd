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


def rms(v) -> float:
    return float(np.sqrt(np.mean(np.square(np.asarray(v, dtype=float)))))


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
    # a prediction is a function of its own (t, x): the readings asked for in reverse order, or
    # every other one, give the same values at the same points, in the order asked
    t, x = er["t_s"].to_numpy(), er["target_mm"].to_numpy()
    np.testing.assert_allclose(model.predict_at(two_runs, "b", t[::-1], x[::-1]), pred[::-1], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(model.predict_at(two_runs, "b", t[1::2], x[1::2]), pred[1::2], rtol=1e-9, atol=1e-9)
    # and they are predictions of the measured error: on its own run the residual is a fraction
    # of the error (22 µm RMS there), on the unseen run it is smaller than the error (14 µm RMS)
    own = two_runs.errors_run("a")
    assert rms(own["error_um"] - model.predict(two_runs, "a")) < 0.3 * rms(own["error_um"])
    assert rms(er["error_um"] - pred) < 0.8 * rms(er["error_um"])
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
    assert inp.sensors or inp.motion or inp.operating  # something must drive the thermal part


def test_mlr_predicts_the_least_squares_solution_computed_here(two_runs):
    """Seed 001 eq. 11-12 solved here from the dataset's own tables (numpy.linalg.lstsq, no
    thermbench code): the geometric error is the quartic through run a's first measuring pass,
    the thermal error (a1 ΔTn + ... + a4 ΔTn^4 + b1 ΔTb + c)·P fitted to what is left; the
    model's prediction on run b is that solution's, the geometric and thermal parts included."""
    from thermbench.models.mlr import MLRSeed001

    model = MLRSeed001(degree=4, nut_sensor="T_nut", bed_sensor="T_bed", origin_mm=0.0, preprocess=None)
    model.fit(two_runs, ["a"])

    def rises(run, t):  # the rise of each sensor above the run's first sample, interpolated at t
        log = two_runs.process_run(run)
        cols = [np.interp(t, log["t_s"], log[c]) - log[c].iloc[0] for c in ("T_nut_C", "T_bed_C")]
        return np.column_stack(cols)

    def design(dT, p):
        n = dT[:, 0]
        return np.column_stack([n, n**2, n**3, n**4, dT[:, 1], np.ones(len(p))]) * p[:, None]

    er = two_runs.errors_run("a")
    t, p, e = er["t_s"].to_numpy(), er["target_mm"].to_numpy(), er["error_um"].to_numpy()
    first = 0  # the first measuring pass: the readings before a target is measured again
    while first < len(p) and p[first] not in p[:first]:
        first += 1
    assert first == np.unique(p).size and first < len(p)
    geometric = np.polyfit(p[:first], e[:first], 4)
    coef, *_ = np.linalg.lstsq(design(rises("a", t), p), e - np.polyval(geometric, p), rcond=None)

    eb = two_runs.errors_run("b")
    tb, pb = eb["t_s"].to_numpy(), eb["target_mm"].to_numpy()
    by_hand = np.polyval(geometric, pb) + design(rises("b", tb), pb) @ coef
    pred = model.predict(two_runs, "b")
    assert np.ptp(by_hand) > 10.0  # a real drift is compared, not a constant
    np.testing.assert_allclose(pred, by_hand, rtol=0, atol=1e-6)
    np.testing.assert_allclose(model.geometric_um(pb), np.polyval(geometric, pb), rtol=0, atol=1e-6)
    np.testing.assert_allclose(list(model.coef_.values()), coef, rtol=1e-6, atol=0)


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
