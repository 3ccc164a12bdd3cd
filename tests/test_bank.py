"""The per-condition model bank (seed 002 §2.4-2.5) on small analytic datasets."""

import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.base import clone

from thermbench.classify import ProximityNaiveBayes
from thermbench.config import config_dir
from thermbench.experiment import model_from_config
from thermbench.models.bank import ConditionBank
from thermbench.models.base import ModelError
from thermbench.models.mlr import MLRSeed002

from .synth import make_dataset

TARGETS = np.arange(0.0, 501.0, 100.0)
MEAS_FEED = 3000.0
A = (0.0, 100.0, 3000.0)  # condition A: 0-100 mm at 3000 mm/min, the measuring feed (as seed 002 #1)
B = (300.0, 500.0, 4000.0)  # condition B: 300-500 mm at 4000 mm/min
K_UM_PER_C_MM = {"A": 0.01, "B": -0.02}  # thermal error slope per °C in each condition


def geometric_um(x):
    return 2.0 - 0.01 * x + 3e-5 * x**2 - 2e-8 * x**3  # a cubic (seed 002 eq. 7)


def temperature_C(t):
    return 20.0 + 6.0 * (1 - np.exp(-t / 2400.0))


def build_path(plan, every_s=600.0, dwell_s=4.0):
    """Waypoints (t, x, feed of the move ending there) of a run made of work phases
    ("A", "B": reciprocation; "stop") and a measuring cycle every ``every_s``
    (approach to each target at MEAS_FEED, ``dwell_s`` there, back to the work)."""
    pts = [(0.0, 0.0, 0.0)]
    readings = []
    conds = {"A": A, "B": B}

    def move(x, feed):
        t0, x0, _ = pts[-1]
        if abs(x - x0) > 0:
            pts.append((t0 + abs(x - x0) / (feed / 60.0), x, feed))

    def wait(s):
        t0, x0, _ = pts[-1]
        pts.append((t0 + s, x0, 0.0))

    def measure(label):
        for target in TARGETS:
            move(target, MEAS_FEED)
            readings.append((pts[-1][0] + dwell_s / 2, target, label))
            wait(dwell_s)

    next_cycle = 0.0
    for kind, duration in plan:
        end = pts[-1][0] + duration
        label = kind
        while pts[-1][0] < end:
            if pts[-1][0] >= next_cycle:
                measure(label)
                next_cycle += every_s
            if kind == "stop":
                wait(min(end, next_cycle) - pts[-1][0])
                continue
            lo, hi, feed = conds[kind]
            move(lo, feed)
            while pts[-1][0] < min(end, next_cycle):
                move(hi, feed)
                move(lo, feed)
    return np.array(pts), readings


def run_tables(run_id, plan):
    pts, readings = build_path(plan)
    t = np.arange(0.0, np.floor(pts[-1, 0]))
    x = np.interp(t, pts[:, 0], pts[:, 1])
    seg = np.clip(np.searchsorted(pts[:, 0], t, side="right"), 1, len(pts) - 1)
    f = pts[seg, 2]
    process = pd.DataFrame({"run_id": run_id, "t_s": t, "axis_mm": x, "feed_mm_min": f, "T1_C": temperature_C(t)})
    rt = np.array([r[0] for r in readings])
    rx = np.array([r[1] for r in readings])
    keep = rt <= t[-1]
    rt, rx = rt[keep], rx[keep]
    kinds = [k for k, _ in plan if k != "stop"]
    k = K_UM_PER_C_MM[kinds[0] if kinds else "A"]
    err = geometric_um(rx) + k * (temperature_C(rt) - temperature_C(0.0)) * rx
    errors = pd.DataFrame({"run_id": run_id, "t_s": rt, "target_mm": rx, "error_um": err})
    return process, errors


def dataset(plans: dict):
    parts = [run_tables(r, p) for r, p in plans.items()]
    ds = make_dataset(pd.concat([p for p, _ in parts]), pd.concat([e for _, e in parts]), {"T1": "nut_housing"})
    # declare each run's condition as the protocol would (make_dataset takes the log's range)
    for r, plan in plans.items():
        kind = next((k for k, _ in plan if k != "stop"), None)
        lo, hi, feed = {"A": A, "B": B}.get(kind, (0.0, 0.0, 0.0))
        c = ds.metadata.runs[r].condition
        c.start_mm, c.end_mm, c.stroke_mm, c.feed_mm_min = lo, hi, hi - lo, feed
    return ds


@pytest.fixture(scope="module")
def ds():
    return dataset(
        {
            "a": [("A", 7200)],
            "b": [("B", 7200)],
            "a2": [("A", 3600)],
            "switch": [("A", 3600), ("B", 3600)],
            "stops": [("A", 2400), ("stop", 3000), ("B", 2400)],
            "late": [("stop", 1800), ("B", 3600)],
            "idle": [("stop", 3600)],
        }
    )


def mlr():
    return MLRSeed002(sensors=["T1"], preprocess=None)


@pytest.fixture(scope="module")
def refs(ds):
    return {"a": mlr().fit(ds, ["a"]), "b": mlr().fit(ds, ["b"])}


@pytest.fixture(scope="module")
def bank(ds):
    return ConditionBank(model=mlr(), classifier=ProximityNaiveBayes()).fit(ds, ["a", "b"])


# ------------------------------------------------------------------ tests ---
def test_the_synthetic_conditions_need_different_models(ds, refs):
    er = ds.errors_run("b")
    measured = er["error_um"].to_numpy()
    # MLR 002 fits B well (not exactly: it takes each cycle's temperature at the cycle's mean time)
    assert np.max(np.abs(refs["b"].predict(ds, "b") - measured)) < 0.5
    assert np.max(np.abs(refs["a"].predict(ds, "b") - measured)) > 20.0  # and A's model is far off


def test_each_training_run_is_predicted_by_its_own_model(ds, refs, bank):
    assert bank.labels_ == ["a", "b"]
    for r in ("a", "b"):
        er = ds.errors_run(r)
        t, x = er["t_s"].to_numpy(), er["target_mm"].to_numpy()
        track = bank.condition_track(ds, r)
        first = track.loc[track["raw_label"].notna(), "t_s"].min()  # the first classified window
        assert first <= 600.0
        known = t >= first
        pred = bank.predict(ds, r)
        np.testing.assert_allclose(pred[known], refs[r].predict(ds, r)[known], atol=1e-9)
        # before it the bank does not guess the class: a cold axis, the geometric part only
        np.testing.assert_allclose(pred[~known], bank.geometric_um(x[~known]), atol=1e-9)
        tp = ds.process_run(r)["t_s"].to_numpy()
        assert set(bank.conditions_at(ds, r, tp[tp >= first])) == {r}
    # geometric part: the mean of the two models'; geometric + thermal is the chosen model
    x = np.array([0.0, 250.0, 500.0])
    np.testing.assert_allclose(bank.geometric_um(x), (refs["a"].geometric_um(x) + refs["b"].geometric_um(x)) / 2)
    t = np.full(3, 3000.0)
    np.testing.assert_allclose(bank.predict_thermal_at(ds, "a", t, x) + bank.geometric_um(x),
                               refs["a"].predict_at(ds, "a", t, x))  # fmt: skip
    inp = bank.required_inputs()
    assert inp.sensors == ("T1",) and inp.motion


def test_measuring_cycles_are_left_out_of_the_windows(ds, bank):
    """A works at the measuring feed: only leaving the cycles out shows its 0-100 mm."""
    track = bank.condition_track(ds, "a")
    mv = track[track["moving"]]
    assert len(mv) > 100
    np.testing.assert_allclose(mv[["start_mm", "end_mm", "feed_mm_min"]].to_numpy(), [[0.0, 100.0, 3000.0]] * len(mv))


def test_runs_with_one_condition_share_one_model(ds, refs):
    bank = ConditionBank(model=mlr()).fit(ds, ["a", "b", "a2"])
    assert bank.labels_ == ["a+a2", "b"]
    assert bank.models_["a+a2"].train_runs_ == ["a", "a2"]
    assert bank.train_runs_ == ["a", "b", "a2"]


def test_a_switch_of_condition_switches_the_model(ds, refs, bank):
    """A for 1 h then B: before the switch A's model; once the 600 s window has moved
    past the switch (plus one 60 s classification step), B's."""
    t = np.arange(0.0, 7000.0, 37.0)
    start = bank.condition_track(ds, "switch")
    first = start.loc[start["raw_label"].notna(), "t_s"].min()  # the first classified window
    assert first <= 600.0
    t = t[t >= first]  # before it: no condition (tested elsewhere)
    labels = bank.conditions_at(ds, "switch", t)
    assert set(labels[t < 3600]) == {"a"}
    assert set(labels[t >= 3600 + 600 + 60]) == {"b"}
    first_b = t[np.argmax(labels == "b")]
    assert 3600 < first_b <= 3600 + 660
    x = np.tile([0.0, 200.0, 500.0], t.size // 3 + 1)[: t.size]
    pred = bank.predict_at(ds, "switch", t, x)
    early, late = t < 3600, t >= 3600 + 660
    np.testing.assert_allclose(pred[early], refs["a"].predict_at(ds, "switch", t[early], x[early]))
    np.testing.assert_allclose(pred[late], refs["b"].predict_at(ds, "switch", t[late], x[late]))


def test_stops_hold_the_last_class_and_the_start_does_not_look_ahead(ds, bank):
    track = bank.condition_track(ds, "stops")
    in_stop = (track["t_s"] >= 2400 + 600 + 60) & (track["t_s"] < 5400)
    assert in_stop.sum() > 30
    assert not track.loc[in_stop, "moving"].any()  # the windows see no motion ...
    assert set(track.loc[in_stop, "label"]) == {"a"}  # ... and A is held
    assert set(track.loc[track["t_s"] >= 5400 + 660, "label"]) == {"b"}
    late = bank.condition_track(ds, "late")
    first_motion = late.loc[late["moving"], "t_s"].min()
    assert first_motion > 1800  # the run starts with a 30 min stop, then runs condition B
    # a live compensator cannot know the coming class: until the first window is
    # classified there is no condition (not the later B)
    assert late.loc[late["t_s"] < first_motion, "label"].isna().all()
    assert set(late.loc[late["t_s"] >= first_motion + 660, "label"]) == {"b"}


def test_clone_and_params(bank):
    c = clone(bank)
    assert not hasattr(c, "models_")
    p = c.get_params(deep=True)
    assert p["model__sensors"] == ["T1"] and p["window_s"] == 600.0 and p["classifier__level_tolerance"] == 0.05
    c.set_params(model__sensors=["T2"], step_s=30.0)
    assert c.model.sensors == ["T2"] and c.step_s == 30.0
    assert bank.model.sensors == ["T1"]  # the original is untouched


def test_fit_from_fitted_is_fit(ds, refs, bank):
    b2 = ConditionBank(classifier=ProximityNaiveBayes()).fit_from_fitted(ds, refs)
    for r in ("switch", "stops", "late"):
        np.testing.assert_allclose(b2.predict(ds, r), bank.predict(ds, r), atol=1e-9)
    assert b2.models_["a"] is refs["a"]  # not refitted
    assert b2.train_runs_ == ["a", "b"]


def test_learned_classifier_in_the_bank(ds, bank):
    gnb = instantiate(OmegaConf.load(config_dir() / "classifier" / "learned.yaml"), _convert_="all")
    b2 = ConditionBank(model=mlr(), classifier=gnb).fit(ds, ["a", "b"])
    t = np.arange(0.0, 7000.0, 60.0)
    np.testing.assert_array_equal(b2.conditions_at(ds, "switch", t), bank.conditions_at(ds, "switch", t))


def test_bank_yaml_builds_and_runs(ds):
    bank = model_from_config("bank_mlr_seed002")
    assert isinstance(bank, ConditionBank) and isinstance(bank.model, MLRSeed002)
    assert isinstance(bank.classifier, ProximityNaiveBayes)
    # the nested model is conf/model/mlr_seed002.yaml
    nested = OmegaConf.to_container(OmegaConf.load(config_dir() / "model" / "bank_mlr_seed002.yaml"))["model"]
    assert nested == OmegaConf.to_container(OmegaConf.load(config_dir() / "model" / "mlr_seed002.yaml"))
    bank.set_params(model__sensors=["T1"]).fit(ds, ["a", "b"])
    pred = bank.predict(ds, "switch")
    assert pred.shape == (len(ds.errors_run("switch")),) and np.all(np.isfinite(pred))


# ---------------------------------------------------------------- errors ---
def test_classifier_with_other_labels_is_an_error(ds):
    seed002 = instantiate(OmegaConf.load(config_dir() / "classifier" / "seed002.yaml"), _convert_="all")
    with pytest.raises(ModelError, match=r"labels \['#1'.*not conditions of the bank \['a', 'b'\]"):
        ConditionBank(model=mlr(), classifier=seed002).fit(ds, ["a", "b"])


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda ds: ConditionBank(model=mlr()).fit(ds, []), "no runs given"),
        (lambda ds: ConditionBank(model=mlr()).fit(ds, ["a", "nope"]), r"run\(s\) \['nope'\] not in dataset"),
        (lambda ds: ConditionBank().fit(ds, ["a"]), "model must be an unfitted thermbench model"),
        (lambda ds: ConditionBank(model=mlr(), step_s=0).fit(ds, ["a"]), "step_s must be a number > 0"),
        (lambda ds: ConditionBank(model=mlr(), classifier="bayes").fit(ds, ["a"]), "classifier must be a scikit-learn"),
        (lambda ds: ConditionBank().fit_from_fitted(ds, {}), "non-empty mapping"),
        (lambda ds: ConditionBank().fit_from_fitted(ds, {"a": mlr()}), "'a' is not fitted"),
        (lambda ds: ConditionBank(model=mlr()).fit(ds, ["a", "idle"]), r"condition 'idle'.*no motion windows"),
    ],
)  # fmt: skip
def test_bad_input_is_named(ds, make, match):
    with pytest.raises(ModelError, match=match):
        make(ds)


def test_predicting_a_run_without_motion_is_an_error(ds, bank):
    with pytest.raises(ModelError, match="run 'idle' has no motion"):
        bank.predict(ds, "idle")
