"""The per-condition model bank (seed 002 §2.4-2.5) on small analytic datasets."""

import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.base import clone

from thermbench.models.classify import ProximityNaiveBayes
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
        (lambda ds: ConditionBank().fit(ds, ["a"]), r"^ConditionBank\.model: expected an unfitted thermbench model \(ThermalErrorModel\), got None$"),
        (lambda ds: ConditionBank(model="mlr").fit(ds, ["a"]), r"^ConditionBank\.model: expected an unfitted thermbench model .*, got 'mlr'$"),
        (lambda ds: ConditionBank(model=mlr(), step_s=0).fit(ds, ["a"]), r"^ConditionBank\.step_s: expected a finite number > 0, got 0$"),
        (lambda ds: ConditionBank(model=mlr(), window_s=True).fit(ds, ["a"]), r"^ConditionBank\.window_s: expected a finite number > 0, got True$"),
        (lambda ds: ConditionBank(model=mlr(), min_moving_s=-1.0).fit(ds, ["a"]), r"^ConditionBank\.min_moving_s: expected a finite number >= 0, got -1\.0$"),
        (lambda ds: ConditionBank(model=mlr(), classifier="bayes").fit(ds, ["a"]), r"^ConditionBank\.classifier: expected None or a scikit-learn classifier \(fit/predict/get_params\), got 'bayes'$"),
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


# ------------------------------------------- operating conditions (spindle) ---
# A spindle test: no axis motion, the condition is the spindle speed. Three constant-speed
# runs, one per known speed, whose error is a different known function of the one sensor's
# rise: GAIN[rpm] * (T1 - T1(0)) (MLR 002 recovers it exactly), and a run of unknown speeds.
LOG_S = 15.0  # the process log period of the real spindle test
GAIN_UM_PER_C = {1000.0: 1.0, 2000.0: 3.0, 4000.0: -2.0}
SPEEDS = {"r1000": 1000.0, "r2000": 2000.0, "r4000": 4000.0}
# the unknown run: (rpm, duration s): a known speed, one between two, one above all, a stop, one below all
MIXED = [(1000.0, 3600.0), (1600.0, 3600.0), (4500.0, 3600.0), (0.0, 1800.0), (500.0, 3600.0)]


def spindle_temperature_C(t):
    return 20.0 + 4.0 * (1 - np.exp(-np.asarray(t, dtype=float) / 2400.0))


def rise_C(t):
    return spindle_temperature_C(t) - spindle_temperature_C(0.0)


def spindle_dataset(runs: dict, declare: bool = True):
    """A format 2 spindle test seen through its fixed-point channel Z. ``runs[id] = (phases,
    gain)``: phases [(rpm, seconds)], readings every 900 s of gain * the rise of T1. A
    one-phase run declares its speed as its condition (``declare``)."""
    from thermbench.data.dataset import Dataset
    from thermbench.data.schema import Metadata
    from thermbench.data.views import channel_view

    procs, errs, meta_runs = [], [], {}
    for run, (phases, gain) in runs.items():
        t = np.arange(0.0, sum(d for _, d in phases), LOG_S)
        edges = np.cumsum([0.0] + [d for _, d in phases])
        rpm = np.array([phases[min(np.searchsorted(edges, x, side="right") - 1, len(phases) - 1)][0] for x in t])
        procs.append(pd.DataFrame({"run_id": run, "t_s": t, "spindle_rpm": rpm, "T1_C": spindle_temperature_C(t)}))
        rt = np.arange(0.0, t[-1], 900.0)
        errs.append(pd.DataFrame({"run_id": run, "t_s": rt, "channel": "Z", "error_um": gain * rise_C(rt)}))
        meta_runs[run] = {"condition": {"spindle_rpm": phases[0][0]}} if declare and len(phases) == 1 else {}
    meta = {"format": "thermbench-dataset/2", "machine": {"name": "synthetic_spindle"}, "parts": ["spindle"],
            "sensors": {"T1": "spindle_housing"}, "operating": ["spindle_rpm"], "runs": meta_runs,
            "channels": {"Z": {"kind": "fixed_point", "direction": "Z", "location": "test_mandrel"}},
            "reference": {"mode": "first_reading"}}  # fmt: skip
    ds = Dataset(Metadata.model_validate(meta), pd.concat(procs, ignore_index=True), pd.concat(errs, ignore_index=True))
    return channel_view(ds, "Z")


@pytest.fixture(scope="module")
def sds():
    runs = {r: ([(rpm, 3 * 3600.0)], GAIN_UM_PER_C[rpm]) for r, rpm in SPEEDS.items()}
    return spindle_dataset({**runs, "mixed": (MIXED, 0.5)})


@pytest.fixture(scope="module")
def srefs(sds):
    return {r: mlr().fit(sds, [r]) for r in SPEEDS}


def eq16_by_hand(rpm):
    """seed 002 eq. 15-16 for one factor with levels 1000, 2000, 4000 rpm, as exact fractions."""
    return {1000.0: [1.0, 0.0, 0.0], 500.0: [21 / 31, 7 / 31, 3 / 31],  # 1/500 : 1/1500 : 1/3500
            1600.0: [4 / 11, 6 / 11, 1 / 11],  # 1/600 : 1/400 : 1/2400
            4500.0: [5 / 47, 7 / 47, 35 / 47]}[rpm]  # 1/3500 : 1/2500 : 1/500  # fmt: skip


def pure_times(phase: int, margin_s: float = 660.0) -> np.ndarray:
    """Query times of MIXED's phase whose last grid point's window lies wholly in it, on
    the log's samples (between samples a model interpolates the temperature)."""
    start = sum(d for _, d in MIXED[:phase])
    end = start + MIXED[phase][1]
    return np.arange(start + margin_s, end - 1.0, 5 * LOG_S)


def test_the_members_are_the_known_functions(sds, srefs):
    t = np.arange(0.0, 10000.0, 33 * LOG_S)  # on the log's samples
    for r, rpm in SPEEDS.items():
        np.testing.assert_allclose(srefs[r].predict_at(sds, "mixed", t, 0.0), GAIN_UM_PER_C[rpm] * rise_C(t), atol=1e-9)


def test_the_hard_bank_picks_the_nearest_speed(sds, srefs):
    bank = ConditionBank(model=mlr()).fit(sds, list(SPEEDS))
    assert bank.condition_inputs_ == ("spindle_rpm",) and bank.labels_ == list(SPEEDS)
    assert bank.classifier_.factors_ == ("spindle_rpm",)
    np.testing.assert_allclose(bank.classifier_.levels_["spindle_rpm"], [1000, 2000, 4000])
    inp = bank.required_inputs()
    assert inp.operating == ("spindle_rpm",) and not inp.motion and inp.sensors == ("T1",)
    # each phase of the unknown run: the nearest known speed (1600 -> 2000, 4500 -> 4000, 500 -> 1000)
    for phase, want in [(0, "r1000"), (1, "r2000"), (2, "r4000"), (4, "r1000")]:
        t = pure_times(phase)
        assert set(bank.conditions_at(sds, "mixed", t)) == {want}, phase
        np.testing.assert_allclose(bank.predict_at(sds, "mixed", t, 0.0),
                                   GAIN_UM_PER_C[SPEEDS[want]] * rise_C(t), atol=1e-9)  # fmt: skip
    # the stop holds the last class; the window features are the running speed (not diluted by the stop)
    track = bank.condition_track(sds, "mixed")
    stop = (track["t_s"] >= 10800 + 600) & (track["t_s"] < 12600)
    assert not track.loc[stop, "moving"].any() and set(track.loc[stop, "label"]) == {"r4000"}
    late = track[(track["t_s"] > 10800) & track["moving"]]
    assert np.allclose(late.loc[late["t_s"] < 12000, "spindle_rpm"], 4500.0)
    # before the first classified window (60 s: four 15 s samples), no thermal error
    assert bank.predict_thermal_at(sds, "mixed", [0.0, 59.0], [0.0, 0.0]).tolist() == [0.0, 0.0]


@pytest.mark.parametrize("probability", ["score", "proximity", "linear"])
def test_the_soft_bank_blends_by_the_hand_computed_probabilities(sds, srefs, probability):
    """prediction(t) = Σ_k P_k(t) model_k(t); P by hand: eq. 16 over 1000/2000/4000 rpm;
    ``score`` = (eq. 16 + 1/3) / 2 (eq. 19 with one factor, normalised), ``proximity`` =
    eq. 16, ``linear`` = between the bracketing levels (1600: 0.4 / 0.6; beyond: the end)."""
    soft = ConditionBank(classifier=ProximityNaiveBayes(probability=probability), blend="soft")
    soft.fit_from_fitted(sds, srefs)
    linear = {1000.0: [1, 0, 0], 1600.0: [0.4, 0.6, 0], 4500.0: [0, 0, 1], 500.0: [1, 0, 0]}
    gains = np.array([GAIN_UM_PER_C[SPEEDS[r]] for r in soft.labels_])
    for phase in (0, 1, 2, 4):
        rpm = MIXED[phase][0]
        p16 = np.array(eq16_by_hand(rpm))
        P = {"score": (p16 + 1 / 3) / 2, "proximity": p16, "linear": np.array(linear[rpm], dtype=float)}[probability]
        t = pure_times(phase)
        np.testing.assert_allclose(soft.probabilities_at(sds, "mixed", t), np.tile(P, (t.size, 1)), atol=1e-12)
        want = sum(P[k] * srefs[r].predict_at(sds, "mixed", t, 0.0) for k, r in enumerate(soft.labels_))
        np.testing.assert_allclose(soft.predict_at(sds, "mixed", t, 0.0), want, atol=1e-9)
        np.testing.assert_allclose(soft.predict_at(sds, "mixed", t, 0.0), (P @ gains) * rise_C(t), atol=1e-9)
    # the stop holds the 4500 rpm probabilities; before the first window: no thermal error
    t_stop = np.arange(11400.0, 12600.0, 100.0)
    np.testing.assert_allclose(soft.probabilities_at(sds, "mixed", t_stop),
                               soft.probabilities_at(sds, "mixed", np.full(t_stop.size, 10000.0)))  # fmt: skip
    assert soft.predict_thermal_at(sds, "mixed", [0.0, 45.0], [0.0, 0.0]).tolist() == [0.0, 0.0]
    # the hard bank on the same fits is the argmax
    hard = ConditionBank().fit_from_fitted(sds, srefs)
    assert all(hard.models_[k] is soft.models_[k] is srefs[k] for k in srefs)
    t = pure_times(1)
    np.testing.assert_allclose(hard.predict_at(sds, "mixed", t, 0.0), 3.0 * rise_C(t), atol=1e-9)


def test_the_learned_classifier_works_on_the_speed(sds, srefs):
    gnb = instantiate(OmegaConf.load(config_dir() / "classifier" / "learned.yaml"), _convert_="all")
    b = ConditionBank(classifier=gnb).fit_from_fitted(sds, srefs)
    ref = ConditionBank().fit_from_fitted(sds, srefs)
    t = np.arange(0.0, 16000.0, 60.0)
    np.testing.assert_array_equal(b.conditions_at(sds, "mixed", t), ref.conditions_at(sds, "mixed", t))
    np.testing.assert_allclose(b.classifier_.theta_.ravel(), [1000.0, 2000.0, 4000.0])


def test_history_segments_train_only_inside_their_readings():
    """One test of three 2 h blocks (1000, 2000, 4000 rpm), each with 1 h stopped after it,
    split with its history: a segment's log starts at 0 s (earlier speeds), its readings at
    its own start. The classifier is trained on the windows from the first reading on only:
    GaussianNB's class means are exactly the segment speeds, and each class has the windows
    of its block alone: grid points (every 60 s) from 60 s after the block start (4 samples of
    15 s) until the last 600 s window holding 4 running samples (block end + 540 s - 60 s),
    (7200 + 480 - 60) / 60 + 1 = 128 per block - the same as the split without history."""
    from thermbench.data.views import split_segments

    phases = [(1000.0, 7200.0), (0.0, 3600.0), (2000.0, 7200.0), (0.0, 3600.0), (4000.0, 7200.0), (0.0, 3600.0)]
    ds = spindle_dataset({"test": (phases, 1.0)})
    gnb = instantiate(OmegaConf.load(config_dir() / "classifier" / "learned.yaml"), _convert_="all")
    banks = {}
    for history in (True, False):
        seg = split_segments(ds, history=history)
        runs = seg.run_ids
        assert [seg.metadata.runs[r].condition.levels() for r in runs] == [{"spindle_rpm": v} for v in (1e3, 2e3, 4e3)]
        if history:
            assert all(seg.process_run(r)["t_s"].iloc[0] == 0.0 for r in runs)  # the lead-in is there
        banks[history] = b = ConditionBank(model=mlr(), classifier=clone(gnb)).fit(seg, runs)
        np.testing.assert_array_equal(b.classifier_.theta_.ravel(), [1000.0, 2000.0, 4000.0])
        assert b.classifier_.class_count_.tolist() == [128.0, 128.0, 128.0]
    # at prediction the live track runs from the process start (no look-ahead): at the 2000 rpm
    # segment's start the machine has seen 1000 rpm, then a stop; that class is held
    seg = split_segments(ds, history=True)
    assert banks[True].conditions_at(seg, "s02_2000rpm", [10800.0]).tolist() == ["s01_1000rpm"]
    assert banks[True].conditions_at(seg, "s02_2000rpm", [10800.0 + 660.0]).tolist() == ["s02_2000rpm"]


@pytest.fixture(scope="module")
def fl_views():
    from thermbench.bench.datasets import load_benchmark
    from thermbench.experiment import dataset_view

    raw = load_benchmark("fl_thermal")
    return {h: dataset_view(raw, "ch5", True, h) for h in (False, True)}


@pytest.mark.parametrize("history", [False, True])
def test_fl_thermal_tail_speeds_go_to_the_nearest_state(fl_views, history):
    """The real 46 h spindle test: the five constant-speed blocks train the classifier; the
    stepped tail (500, 1500, 2500, 4500 rpm; no declared condition) is classified on its
    live speed window: 500 -> 1250, 1500 -> 1250, 2500 -> 2500, 4500 -> 5000 (nearest)."""
    ds = fl_views[history]
    states = [r for r in ds.run_ids if ds.metadata.runs[r].condition is not None]
    tail = [r for r in ds.run_ids if ds.metadata.runs[r].condition is None]
    assert len(states) == 5 and len(tail) == 1
    fits = {r: MLRSeed002(sensors=["t1"], preprocess=None).fit(ds, [r]) for r in states}
    by_rpm = {ds.metadata.runs[r].condition.levels()["spindle_rpm"]: r for r in states}
    assert sorted(by_rpm) == [1250.0, 2500.0, 3500.0, 3750.0, 5000.0]
    bank = ConditionBank(blend="soft").fit_from_fitted(ds, fits)
    track = bank.condition_track(ds, tail[0])
    track = track[(track["t_s"] >= ds.errors_run(tail[0])["t_s"].min()) & track["moving"]]
    pure = track[np.isin(track["spindle_rpm"], [500.0, 1500.0, 2500.0, 4500.0])]
    got = pure.groupby("spindle_rpm")["raw_label"].agg(set).to_dict()
    assert got == {500.0: {by_rpm[1250.0]}, 1500.0: {by_rpm[1250.0]}, 2500.0: {by_rpm[2500.0]},
                   4500.0: {by_rpm[5000.0]}}  # fmt: skip
    pred = bank.predict(ds, tail[0])
    assert pred.shape == (len(ds.errors_run(tail[0])),) and np.all(np.isfinite(pred))


# ----------------------------------------------------------------- export ---
def test_speed_and_soft_banks_are_refused_by_the_c_export(ds, sds, srefs):
    from thermbench.export import ExportError, encode_classifier

    speed = ConditionBank().fit_from_fitted(sds, srefs)
    with pytest.raises(ExportError, match=r"on the operating input\(s\) \['spindle_rpm'\] cannot be exported"):
        encode_classifier(speed, 15.0, "bank")
    soft = ConditionBank(model=mlr(), blend="soft").fit(ds, ["a", "b"])
    with pytest.raises(ExportError, match=r"a soft bank \(blend 'soft'\) cannot be exported to the C runtime yet"):
        encode_classifier(soft, 1.0, "bank")
    hard = ConditionBank(model=mlr()).fit(ds, ["a", "b"])
    assert encode_classifier(hard, 1.0, "bank").dims[0] == 2  # the motion bank exports as before


def test_soft_motion_bank_and_same_fits(ds, refs, bank):
    """fit_from_fitted builds both kinds from the same fits; on pure windows of one known
    condition eq. 16 is 1 for it on each of the three factors, so the eq. 19 scores are
    3 + 1/2 and 0 + 1/2: the soft blend with ``score`` weights 7/8 and 1/8 mixes the other
    model in; with ``proximity`` (product of eq. 16) it is the hard switch."""
    soft = ConditionBank(classifier=ProximityNaiveBayes(probability="proximity"), blend="soft")
    soft.fit_from_fitted(ds, refs)
    hard = ConditionBank(classifier=ProximityNaiveBayes()).fit_from_fitted(ds, refs)
    for r in ("switch", "stops", "late"):
        np.testing.assert_allclose(hard.predict(ds, r), bank.predict(ds, r), atol=1e-9)
    # A and B differ on every factor: eq. 16 is exact (1/0) on a pure window, so the
    # proximity blend is the hard switch there
    t = np.arange(700.0, 3500.0, 50.0)
    x = np.full(t.size, 300.0)
    np.testing.assert_allclose(soft.predict_at(ds, "switch", t, x), hard.predict_at(ds, "switch", t, x), atol=1e-9)
    score = ConditionBank(blend="soft").fit_from_fitted(ds, refs)
    P = score.probabilities_at(ds, "switch", t)
    np.testing.assert_allclose(P, np.tile([7 / 8, 1 / 8], (t.size, 1)))
    np.testing.assert_allclose(score.predict_at(ds, "switch", t, x),
                               7 / 8 * refs["a"].predict_at(ds, "switch", t, x)
                               + 1 / 8 * refs["b"].predict_at(ds, "switch", t, x), atol=1e-9)  # fmt: skip


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda s: ConditionBank(blend="mix").fit_from_fitted(*s), r"^ConditionBank\.blend: expected one of \['hard', 'soft'\], got 'mix'$"),
        (lambda s: ConditionBank(blend="soft", classifier=__import__("sklearn.linear_model").linear_model
                                 .RidgeClassifier()).fit_from_fitted(*s), "^ConditionBank: blend 'soft' needs a classifier with "
                                                                          "predict_proba"),
        (lambda s: ConditionBank(classifier=ProximityNaiveBayes(factors=["feed_mm_min"])).fit_from_fitted(*s),
         r"'classifier.factors': \['feed_mm_min'\], but the bank's conditions are levels of \['spindle_rpm'\]"),
        (lambda s: ConditionBank(classifier=instantiate(OmegaConf.load(config_dir() / "classifier" / "seed002.yaml"),
                                                        _convert_="all")).fit_from_fitted(*s),
         r"'classifier.stroke_levels_mm': set for axis-motion conditions"),
        (lambda s: ConditionBank(model=mlr()).fit(s[0], ["r1000", "mixed"]), r"run 'mixed' declares no condition"),
    ],
)  # fmt: skip
def test_bad_spindle_bank_input_is_named(sds, srefs, make, match):
    with pytest.raises(ModelError, match=match):
        make((sds, srefs))


def test_a_motion_classifier_on_operating_factors_is_named(ds, refs):
    with pytest.raises(ModelError, match=r"'classifier.factors': \['spindle_rpm'\] are operating inputs"):
        ConditionBank(classifier=ProximityNaiveBayes(factors=["spindle_rpm"])).fit_from_fitted(ds, refs)
