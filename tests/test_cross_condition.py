"""Seed 001's finding, reproduced: regression fits its own moving state but fails
on others, while the heat-transfer (physics) model holds on all of them."""

import pytest

from thermbench.config import load_config
from thermbench.experiment import cross_condition, model_from_config
from thermbench.models.mlr import MLRSeed001
from thermbench.models.physics import PhysicsModel
from thermbench.sim.scenario import simulate_dataset

STATES = ["state1", "state2", "state3", "state4", "state5"]  # seed 001 Table 1


@pytest.fixture(scope="module")
def seed001():
    """The seed 001 VMC X axis under the five Table 1 moving states, realistic
    sensors and interferometer (the core physics, no extra effects)."""
    cfg = load_config("simulate", ["machine=seed001_vmc_x", "protocol=seed001_states", "seed=11"])
    ds, _ = simulate_dataset(cfg)
    return ds


def _frac(res, run):
    return float(res.loc[res["run_id"] == run, "residual_fraction_of_pv"].iloc[0])


def test_mlr_trained_on_state1_degrades_on_other_states(seed001):
    """seed 001 §5.1 (M1): eq. 12 with Px from the fixed end fits state 1, but on
    the other moving states the residual grows to a large part of the P-V."""
    mlr = MLRSeed001(degree=4)  # Px from the declared fixed end, limit + Kalman filtered temperatures
    res = cross_condition(mlr, seed001, ["state1"], STATES)
    own = _frac(res, "state1")
    worst_other = max(_frac(res, r) for r in STATES[1:])
    assert own < 0.15
    assert worst_other > 0.3 and worst_other > 2.5 * own, res


def test_physics_trained_on_state1_holds_on_all_five(seed001):
    """seed 001 §5.1.2 / seed 000's criterion: the physics model identified on state 1
    keeps the residual within 15 % of the measured P-V on every state."""
    res = cross_condition(PhysicsModel(), seed001, ["state1"], STATES)
    for run in STATES:
        assert _frac(res, run) < 0.15, res
    assert res["max_abs_error_um"].min() > 20.0


def test_models_build_from_their_configs():
    for name, cls in [("physics", PhysicsModel), ("mlr_seed001", MLRSeed001)]:
        assert isinstance(model_from_config(name), cls)
    with pytest.raises(ValueError, match="model 'nope'.*known models"):
        model_from_config("nope")
