"""Hyper-parameter checks of every model family (thermbench/models/params.py): one pydantic
model per family, validated at fit, a bad value a one-line ModelError naming
``<Family>.<param>``, what it expects and what it got."""

from __future__ import annotations

import math
from typing import Annotated, Literal, Optional

import numpy as np
import pytest
from annotated_types import Ge, Gt, Le, Lt
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.base import clone
from sklearn.linear_model import LinearRegression, LogisticRegression

from tests.synth import analytic_dataset, rise
from thermbench.config import config_dir
from thermbench.models.autoregressive import AutoRegressiveSeed003
from thermbench.models.bank import ConditionBank
from thermbench.models.base import ModelError, ThermalErrorModel
from thermbench.models.baseline import SensorRegressor
from thermbench.models.lssvm import LSSVMRegressor, PSOLSSVM
from thermbench.models.lumped import LumpedThermalNetwork
from thermbench.models.mlr import MLRSeed001, MLRSeed002, MLRSeed004
from thermbench.models.neural import GRUModel, MLPModel
from thermbench.models.params import Expect, Int, Number, Params, check_params, expected, validate
from thermbench.models.ensemble import StackedEnsemble
from thermbench.models.linear_history import LinearHistory
from thermbench.models.physics import PhysicsModel
from thermbench.models.thermal_lag import ThermalLag

#: every family, with what its constructor needs beyond the defaults to be valid
FAMILIES = {
    MLRSeed001: {},
    MLRSeed002: {},
    MLRSeed004: {},
    PSOLSSVM: {},
    MLPModel: {},
    GRUModel: {},
    ConditionBank: {"model": MLRSeed002()},
    SensorRegressor: {"estimator": LinearRegression()},
    LumpedThermalNetwork: {},
    AutoRegressiveSeed003: {},
    PhysicsModel: {},
    LinearHistory: {},
    ThermalLag: {},
    StackedEnsemble: {"members": [LinearHistory()]},
}


def make(cls, **params):
    return cls(**{**FAMILIES[cls], **params})


@pytest.fixture(scope="module")
def ds():
    """One hour, two sensors, three targets: enough for every family to reach its checks."""
    temps = {"r": {"T1": lambda t: 20.0 + rise(t, 3.0, 900.0), "T2": lambda t: 20.0 + rise(t, 1.0, 1800.0)}}
    return analytic_dataset(temps, lambda T, P, run: 0.01 * (T["T1"] - 20.0) * P, duration_s=3600,
                            targets_mm=(0, 100, 200, 300, 400, 500))  # fmt: skip


# --------------------------------------------------------------- coverage ---
@pytest.mark.parametrize("cls", list(FAMILIES), ids=lambda c: c.__name__)
def test_the_params_model_declares_every_constructor_parameter(cls):
    model = make(cls)
    assert issubclass(cls.params_model, Params)
    assert set(cls.params_model.model_fields) == set(model.get_params(deep=False))
    check_params(model, cls.params_model)  # the defaults are valid
    # the constructor only stores: a bad value is accepted there (clone works) and refused at fit
    assert clone(make(cls, **{next(iter(model.get_params(deep=False))): object()})) is not None


def test_the_regressor_params_model_declares_every_parameter():
    assert set(LSSVMRegressor.params_model.model_fields) == set(LSSVMRegressor().get_params())


CONFIGS = sorted(p.stem for p in (config_dir() / "model").glob("*.yaml"))


@pytest.mark.parametrize("name", CONFIGS)
@pytest.mark.parametrize("convert", [True, False], ids=["plain", "omegaconf"])
def test_every_model_config_is_valid(name, convert):
    """conf/model/*.yaml as thermbench builds them (plain lists/dicts) and as a bare hydra
    instantiate does (ListConfig/DictConfig values): every parameter passes its checks."""
    cfg = OmegaConf.load(config_dir() / "model" / f"{name}.yaml")
    model = instantiate(cfg, _convert_="all") if convert else instantiate(cfg, _convert_="none")
    assert isinstance(model, ThermalErrorModel)
    p = check_params(model, type(model).params_model)
    assert set(type(p).model_fields) == set(model.get_params(deep=False))


# ------------------------------------------------------------ bad values ---
NAN, INF = float("nan"), float("inf")
#: (family, parameter, a bad value): a wrong type or a value out of range of each kind of parameter
BAD = [
    (MLRSeed001, "degree", 0), (MLRSeed001, "degree", 5), (MLRSeed001, "degree", 2.5), (MLRSeed001, "degree", "4"),
    (MLRSeed001, "origin_mm", "zero"), (MLRSeed001, "origin_mm", NAN), (MLRSeed001, "nut_sensor", 3),
    (MLRSeed002, "geometric_degree", -1), (MLRSeed002, "origin_mm", INF), (MLRSeed002, "sensors", 5),
    (MLRSeed002, "selection", "gra"),
    (MLRSeed004, "geometric_degree", 1.5), (MLRSeed004, "mounting", 2), (MLRSeed004, "sensors", [1]),
    (PSOLSSVM, "sensors", 5), (PSOLSSVM, "gamma", 0.0), (PSOLSSVM, "sigma2", NAN), (PSOLSSVM, "gamma_bounds", (10.0, 1.0)),
    (PSOLSSVM, "gamma_bounds", (5.0, 5.0)), (PSOLSSVM, "sigma2_bounds", "ab"), (PSOLSSVM, "sigma2_bounds", (0.0, 1.0)),
    (PSOLSSVM, "n_particles", 0), (PSOLSSVM, "iters", 2.0), (PSOLSSVM, "val_fraction", 1.0),
    (PSOLSSVM, "val_fraction", "0.2"), (PSOLSSVM, "seed", -1), (PSOLSSVM, "seed", "0"), (PSOLSSVM, "max_samples", 9),
    (MLPModel, "hidden", []), (MLPModel, "hidden", "32"), (MLPModel, "hidden", [8, 0]), (MLPModel, "activation", "softsign"),
    (MLPModel, "lr", 0.0), (MLPModel, "weight_decay", -1e-3), (MLPModel, "patience", 0), (MLPModel, "min_epochs", -1),
    (MLPModel, "val_fraction", 1.0), (MLPModel, "batch_size", 0), (MLPModel, "max_samples", 5), (MLPModel, "sensors", "T1"),
    (GRUModel, "hidden_size", 0), (GRUModel, "window_s", -1.0), (GRUModel, "step_s", 0.0), (GRUModel, "position_degree", -1),
    (GRUModel, "lr", INF),
    (ConditionBank, "model", None), (ConditionBank, "model", "mlr"), (ConditionBank, "classifier", "bayes"),
    (ConditionBank, "window_s", 0.0), (ConditionBank, "min_moving_s", NAN), (ConditionBank, "blend", "mix"),
    (SensorRegressor, "estimator", None), (SensorRegressor, "estimator", LogisticRegression()),
    (SensorRegressor, "sensors", "T1"), (SensorRegressor, "sensors", []), (SensorRegressor, "interactions", 1),
    (SensorRegressor, "seed", -3),
    (LumpedThermalNetwork, "n_nodes", 7), (LumpedThermalNetwork, "n_nodes", [1, 7]), (LumpedThermalNetwork, "n_nodes", []),
    (LumpedThermalNetwork, "exponent_bounds", (1.0, 1.0)), (LumpedThermalNetwork, "u_ref", -1.0),
    (LumpedThermalNetwork, "operating", ["a", "b"]), (LumpedThermalNetwork, "sensors", "T1"),
    (LumpedThermalNetwork, "ambient_sensor", 1), (LumpedThermalNetwork, "max_sensors", 0),
    (AutoRegressiveSeed003, "na", -1), (AutoRegressiveSeed003, "nb", 0), (AutoRegressiveSeed003, "sample_s", "600"),
    (AutoRegressiveSeed003, "criterion", "free"), (AutoRegressiveSeed003, "origin_mm", None),
    (PhysicsModel, "dx_m", 0.0), (PhysicsModel, "dt_s", NAN), (PhysicsModel, "max_iter", 0), (PhysicsModel, "ftol", -1.0),
    (PhysicsModel, "geometric_degree", 1.5), (PhysicsModel, "initial", {"k2_W_m2K": "x"}),
    (PhysicsModel, "bounds", {"k2_W_m2K": 5.0}), (PhysicsModel, "identify", 3), (PhysicsModel, "effects", ["motor"]),
    (PhysicsModel, "polish_steps", -1), (PhysicsModel, "coarse_dt_s", 0.0), (PhysicsModel, "coarse_macro_dt_s", INF),
    (LinearHistory, "delays_s", [[-60.0]]), (LinearHistory, "delays_s", []), (LinearHistory, "delay_step_s", 0.0),
    (LinearHistory, "alphas", []), (LinearHistory, "sensors", "T1"), (LinearHistory, "estimator", "lasso"),
    (LinearHistory, "components", [0]), (LinearHistory, "components", [2.5]), (LinearHistory, "cv", "loo"),
    (ThermalLag, "select", "no"),
    (StackedEnsemble, "members", []), (StackedEnsemble, "members", ["linear_history"]),
    (StackedEnsemble, "stacking", "median"),
]  # fmt: skip


@pytest.mark.parametrize("cls, key, value", BAD, ids=lambda v: v.__name__ if isinstance(v, type) else repr(v))
def test_a_bad_parameter_is_one_line_naming_it(ds, cls, key, value):
    with pytest.raises(ModelError) as exc:
        make(cls, **{key: value}).fit(ds)
    msg = str(exc.value)
    # the key, then what it expects, then the value given; the wording of "expected ..." is held to
    # hand-written texts in test_the_messages_say_what_is_expected
    assert msg.startswith(f"{cls.__name__}.{key}: expected ") and ", got " in msg, msg
    assert len(msg.split(": expected ", 1)[1].split(", got ")[0]) > 5, msg
    assert "\n" not in msg


#: every integer parameter of every family: a bool is not an integer
INTS = {
    MLRSeed001: ["degree"], MLRSeed002: ["geometric_degree"], MLRSeed004: ["geometric_degree"],
    PSOLSSVM: ["n_particles", "iters", "seed", "geometric_degree", "max_samples"],
    MLPModel: ["max_epochs", "patience", "min_epochs", "batch_size", "seed", "geometric_degree", "max_samples", "hidden"],
    GRUModel: ["hidden_size", "position_degree", "max_epochs", "patience", "min_epochs", "batch_size", "seed"],
    SensorRegressor: ["seed"], LumpedThermalNetwork: ["n_nodes", "n_starts", "geometric_degree", "max_sensors"],
    AutoRegressiveSeed003: ["na", "nb", "geometric_degree"], PhysicsModel: ["geometric_degree", "max_iter", "polish_steps"],
}  # fmt: skip
#: every number parameter: a bool is not a number either
NUMBERS = {
    MLRSeed001: ["origin_mm"], MLRSeed002: ["origin_mm"], MLRSeed004: ["origin_mm"],
    PSOLSSVM: ["gamma", "sigma2", "val_fraction"], MLPModel: ["lr", "weight_decay", "val_fraction"],
    GRUModel: ["window_s", "step_s", "lr"], ConditionBank: ["window_s", "step_s", "min_moving_s"],
    LumpedThermalNetwork: ["u_ref", "exponent", "step_s"], AutoRegressiveSeed003: ["sample_s", "origin_mm"],
    PhysicsModel: ["dx_m", "dt_s", "macro_dt_s", "ftol", "coarse_dt_s", "coarse_macro_dt_s"],
}  # fmt: skip


@pytest.mark.parametrize("cls, key", [(c, k) for d in (INTS, NUMBERS) for c, ks in d.items() for k in ks],
                         ids=lambda v: v.__name__ if isinstance(v, type) else v)  # fmt: skip
def test_a_bool_is_refused_where_a_number_is_expected(ds, cls, key):
    value = [8, True] if key == "hidden" else True  # hidden: a list of widths
    with pytest.raises(ModelError, match=rf"^{cls.__name__}\.{key}: expected .*, got (True|\[8, True\])$"):
        make(cls, **{key: value}).fit(ds)


def test_the_messages_say_what_is_expected(ds):
    cases = [
        (MLRSeed001(degree=True), "MLRSeed001.degree: expected an integer 1..4, got True"),
        (PSOLSSVM(n_particles=0), "PSOLSSVM.n_particles: expected an integer >= 1, got 0"),
        (PSOLSSVM(val_fraction=NAN), "PSOLSSVM.val_fraction: expected a finite number in (0, 1), got nan"),
        (PSOLSSVM(gamma_bounds=[10.0, 1.0]),
         "PSOLSSVM.gamma_bounds: expected a pair (low, high) of finite numbers with 0 < low < high, got [10.0, 1.0]"),
        (MLPModel(val_fraction=1.0), "MLPModel.val_fraction: expected a finite number in [0, 1), got 1.0"),
        (MLPModel(activation="softsign"),
         "MLPModel.activation: expected one of ['tanh', 'relu', 'gelu', 'silu', 'sigmoid'], got 'softsign'"),
        (GRUModel(batch_size=0), "GRUModel.batch_size: expected None or an integer >= 1, got 0"),
        (SensorRegressor(estimator=LogisticRegression()),
         "SensorRegressor.estimator: expected a scikit-learn regressor (or a pipeline ending in one), got a LogisticRegression"),
        (PhysicsModel(dt_s=0.3, macro_dt_s=10.0),
         "PhysicsModel: macro_dt_s must be a whole multiple of dt_s, got macro_dt_s=10, dt_s=0.3"),
        (PhysicsModel(coarse_dt_s=None),
         "PhysicsModel: coarse_dt_s and coarse_macro_dt_s: give both (a coarse first stage) or neither, got "
         "coarse_dt_s=None, coarse_macro_dt_s=60.0"),
        (PhysicsModel(coarse_dt_s=0.7),
         "PhysicsModel: coarse_macro_dt_s must be a whole multiple of coarse_dt_s, got 60 and 0.7"),
    ]  # fmt: skip
    for model, message in cases:
        with pytest.raises(ModelError) as exc:
            model.fit(ds)
        assert str(exc.value) == message


def test_numpy_scalars_count_as_the_numbers_they_hold(ds):
    p = check_params(PSOLSSVM(n_particles=np.int64(4), val_fraction=np.float32(0.5), seed=np.uint32(3)),
                     PSOLSSVM.params_model)  # fmt: skip
    assert (p.n_particles, p.val_fraction, p.seed) == (4, 0.5, 3) and type(p.n_particles) is int
    m = MLRSeed001(degree=np.int64(1), origin_mm=np.float64(0.0), nut_sensor="T1", bed_sensor="T2", preprocess=None).fit(ds)
    assert m.degree_ == 1 and type(m.degree_) is int
    with pytest.raises(ModelError, match=r"^MLRSeed001\.degree: expected an integer 1\.\.4, got True$"):
        MLRSeed001(degree=np.bool_(True)).fit(ds)


def test_a_checked_refit_starts_from_nothing(ds):
    """A bad parameter set after a fit is refused at the next fit, and the model is unfitted."""
    m = MLRSeed001(degree=1, nut_sensor="T1", bed_sensor="T2", preprocess=None).fit(ds)
    with pytest.raises(ModelError, match=r"^MLRSeed001\.degree"):
        m.set_params(degree=9).fit(ds)
    with pytest.raises(ModelError, match="not fitted"):
        m.predict(ds, "r")


# ------------------------------------------------------------ the helper ---
class Demo(Params):
    count: Annotated[Int, Ge(1)]
    width: Annotated[Int, Ge(1), Le(6)]
    share: Annotated[Number, Gt(0), Lt(1)]
    level: Optional[Annotated[Number, Ge(0)]]
    mode: Literal["a", "b"]
    pair: Annotated[tuple[Number, Number], Expect("two numbers")]


@pytest.mark.parametrize(
    "key, words",
    [("count", "an integer >= 1"), ("width", "an integer 1..6"), ("share", "a finite number in (0, 1)"),
     ("level", "None or a finite number >= 0"), ("mode", "one of ['a', 'b']"), ("pair", "two numbers")],
)  # fmt: skip
def test_expected_derives_the_words_from_the_type(key, words):
    assert expected(Demo, key) == words


def test_validate_names_the_first_bad_key_in_field_order():
    good = dict(count=1, width=2, share=0.5, level=None, mode="a", pair=(1, 2))
    assert validate(Demo, good, "Demo").pair == (1.0, 2.0)
    with pytest.raises(ModelError, match=r"^Demo\.share: expected a finite number in \(0, 1\), got inf$"):
        validate(Demo, {**good, "share": math.inf, "mode": "c"}, "Demo")
    with pytest.raises(ModelError, match=r"^Demo\.count: expected an integer >= 1, got '1'$"):
        validate(Demo, {**good, "count": "1"}, "Demo")
    with pytest.raises(ModelError, match=r"^Demo\.pair: expected two numbers, got \[1, 2, 3\]$"):
        validate(Demo, {**good, "pair": OmegaConf.create([1, 2, 3])}, "Demo")


def test_physics_bounds_may_be_infinite_but_not_nan(ds):
    ok = check_params(PhysicsModel(bounds={"k2_W_m2K": [0.0, math.inf]}), PhysicsModel.params_model)
    assert ok.bounds["k2_W_m2K"] == (0.0, math.inf)
    with pytest.raises(ModelError, match=r"^PhysicsModel\.bounds: expected .*, got \{'k2_W_m2K': \[0\.0, nan\]\}$"):
        PhysicsModel(bounds={"k2_W_m2K": [0.0, NAN]}).fit(ds)
