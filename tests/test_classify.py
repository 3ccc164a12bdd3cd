"""Motion-condition classification: seed 002 §2.4 eq. 15-19 (Tables 5-6) and the
online motion features a compensator computes from its own log."""

import sys

import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf
from sklearn.base import clone

from thermbench.models.classify import ClassifierError, ProximityNaiveBayes, learned_features
from thermbench.models.classify_one import classify_motion, format_classification
from thermbench.models.motion_windows import measuring_intervals, operating_window_features, window_features
from thermbench.config import config_dir

# seed 002 Table 6: (stroke A, P_start, P_end, feed C, the paper's class)
TABLE6 = [
    (100, 60, 160, 1250, "#2"),
    (30, 60, 90, 4000, "#2"),
    (320, 400, 720, 500, "#3"),
    (500, 0, 500, 500, "#3"),
    (20, 610, 630, 300, "#3"),
    (450, 110, 560, 4300, "#6"),
    (310, 330, 640, 3400, "#9"),
]
# what eq. 15-19 give (worked by hand, re-derived by _by_hand below); rows 2 and 5 differ from the paper
EQUATIONS = ["#2", "#7", "#3", "#3", "#7", "#6", "#9"]


def _by_hand(stroke, start, end, feed, feed_levels=(800, 2000, 4000)):
    """eq. 15-19 written out independently of thermbench, for Table 5 (#k: stroke level
    (k-1) % 3 of {50, 100, 300}; position and feed level (k-1) // 3 of {0, 650, 1300}
    and feed_levels)."""

    def normalised(v, levels):
        d = [abs(v - x) for x in levels]
        if 0 in d:
            return [1.0 if di == 0 else 0.0 for di in d]
        total = sum(1 / di for di in d)
        return [(1 / di) / total for di in d]

    pa = normalised(stroke, (50, 100, 300))
    pb = normalised(start + end, (0, 650, 1300))
    pc = normalised(feed, feed_levels)
    scores = {f"#{k}": pa[(k - 1) % 3] + pb[(k - 1) // 3] + pc[(k - 1) // 3] + 1 / 9 for k in range(1, 10)}
    return max(scores, key=scores.get), scores


def seed002_config():
    return OmegaConf.load(config_dir() / "classifier" / "seed002.yaml")


# ------------------------------------------------------------- Table 6 ---
def test_hand_derivation_of_table6():
    """The independent computation agrees with the expected labels written above."""
    assert [_by_hand(a, s, e, c)[0] for a, s, e, c, _ in TABLE6] == EQUATIONS


@pytest.mark.parametrize("row", range(7))
def test_table6_rows(row):
    """seed 002 Table 6 through the configured classifier (conf/classifier/seed002.yaml).

    Rows 1, 3, 4, 6, 7 come out as the paper prints them. Rows 2 and 5 do not, and no
    reading of eq. 15-19 can give the printed class:

    * row 2 (30 mm, 60-90 mm, 4000 mm/min; paper #2): the feed 4000 is the right-end
      level exactly, so P(feed level | C) is 1 for #7-#9 and 0 for #1-#6. Position B =
      150 is nearest the left end (P = 0.699 for #1-#3) and stroke 30 nearest 50 mm
      (P = (1/20)/(1/20 + 1/70 + 1/270) = 0.735 for #1, #4, #7; 0.210 for 100 mm).
      Scores: #7 = 0.735 + 0.091 + 1 + 1/9 = 1.938, #1 = 0.735 + 0.699 + 0 + 1/9 = 1.546,
      #2 = 0.210 + 0.699 + 0 + 1/9 = 1.020. #2 shares its position and feed levels
      with #1 but its stroke level (100) is farther from 30 than #1's (50), so any
      proximity that falls with distance ranks #1 above #2.
    * row 5 (20 mm, 610-630 mm, 300 mm/min; paper #3): B = 1240 is at the right end
      and feed 300 nearest 800 mm/min; #7 (50 mm, right, 4000) scores 1.750, #1 1.528,
      #3 only 0.814 + 1/9. #3 shares position and feed levels with #1 but stroke 300 is
      farther from 20 than 50 is: #3 can never beat #1.
    """
    stroke, start, end, feed, paper = TABLE6[row]
    label, table = classify_motion(stroke, start, end, feed)
    assert label == EQUATIONS[row]
    if row in (1, 4):
        assert label != paper
    else:
        assert label == paper
    _, scores = _by_hand(stroke, start, end, feed)
    np.testing.assert_allclose(table["score"].to_numpy(), [scores[f"#{k}"] for k in range(1, 10)], rtol=1e-12)
    assert table["probability"].sum() == pytest.approx(1.0)
    assert table["score"].idxmax() == label


def test_row2_level_probabilities_by_hand():
    """eq. 16 on Table 6 row 2, fractions worked out by hand."""
    _, table = classify_motion(30, 60, 90, 4000)
    p50 = (1 / 20) / (1 / 20 + 1 / 70 + 1 / 270)
    p_left = (1 / 150) / (1 / 150 + 1 / 500 + 1 / 1150)
    assert table.loc["#1", "stroke_p"] == pytest.approx(p50)
    assert table.loc["#4", "stroke_p"] == pytest.approx(p50)  # #4 is a 50 mm condition too
    assert table.loc["#2", "position_p"] == pytest.approx(p_left)
    # an exact match gives probability 1 to that level and 0 to the others
    assert table.loc["#7", "feed_p"] == 1.0 and table.loc["#1", "feed_p"] == 0.0
    assert table.loc["#1", "score"] == pytest.approx(p50 + p_left + 0 + 1 / 9)


def test_the_printed_40000_would_flip_row7_to_6():
    """The paper prints the last feed level as 40000; with it row 7 (3400 mm/min) is
    nearer the 2000 level and becomes #6, against the paper's own #9 - so 4000 (Table 5)."""
    assert _by_hand(310, 330, 640, 3400, feed_levels=(800, 2000, 40000))[0] == "#6"
    cfg = seed002_config()
    cfg.feed_levels_mm_min = [800.0, 2000.0, 40000.0]
    for k in ("#7", "#8", "#9"):
        cfg.conditions[k].feed_mm_min = 40000.0
    literal = instantiate(cfg, _convert_="all").fit()
    assert classify_motion(310, 330, 640, 3400, classifier=literal)[0] == "#6"
    assert classify_motion(310, 330, 640, 3400)[0] == "#9"


def test_exact_stroke_gives_probability_one():
    """seed 002 §2.4: "if A is 50, 100, and 300 ... the current stroke probability is 1"."""
    _, table = classify_motion(100, 60, 160, 1250)
    assert set(table.loc[["#2", "#5", "#8"], "stroke_p"]) == {1.0}
    assert set(table.loc[["#1", "#3", "#4", "#6", "#7", "#9"], "stroke_p"]) == {0.0}


def test_format_classification():
    label, table = classify_motion(100, 60, 160, 1250)
    text = format_classification(label, table)
    assert "class: #2" in text and "P_start + P_end = 220 mm" in text
    assert len([ln for ln in text.splitlines() if ln.startswith("#")]) == 9


@pytest.mark.parametrize(
    "args, match",
    [
        ((100, 60, 200, 1250), "within 1 mm"),
        ((100, 60, 160, -5), "feed_mm_min must be >= 0"),
        ((100, 60, float("nan"), 1250), "end_mm must be a finite number"),
    ],
)
def test_classify_motion_rejects_bad_motion(args, match):
    with pytest.raises(ValueError, match=match):
        classify_motion(*args)


# ------------------------------------------------------ the classifier ---
def test_works_from_config_alone_and_clones():
    clf = instantiate(seed002_config(), _convert_="all")
    assert isinstance(clf, ProximityNaiveBayes)
    assert clf.fit() is clf
    assert list(clf.classes_) == [f"#{k}" for k in range(1, 10)]
    c2 = clone(clf)
    assert not hasattr(c2, "classes_") and c2.get_params() == clf.get_params()


def test_predict_proba_is_the_normalised_score():
    clf = instantiate(seed002_config(), _convert_="all").fit()
    X = pd.DataFrame([r[:4] for r in TABLE6], columns=["stroke_mm", "start_mm", "end_mm", "feed_mm_min"])
    raw = clf.condition_scores(X)
    proba = clf.predict_proba(X)
    np.testing.assert_allclose(proba.sum(axis=1), 1.0)
    np.testing.assert_allclose(proba, raw / raw.sum(axis=1, keepdims=True))
    assert list(clf.predict(X)) == EQUATIONS
    # the same rows given as centre = (start + end) / 2 (what the bank feeds)
    assert list(clf.predict(learned_features(X))) == EQUATIONS


def test_fit_on_any_grid_uses_the_median_of_each_label():
    """seed 000's grid: one range, three feeds. Levels None: the distinct values."""
    rng = np.random.default_rng(0)
    rows, y = [], []
    for feed in (3000.0, 6000.0, 9000.0):
        for _ in range(20):
            rows.append((500 + rng.normal(0, 2), 0.0, 500.0, feed * (1 + rng.normal(0, 0.002))))
            y.append(f"f{int(feed)}")
    X = pd.DataFrame(rows, columns=["stroke_mm", "start_mm", "end_mm", "feed_mm_min"])
    clf = ProximityNaiveBayes().fit(X, y)
    assert list(clf.classes_) == ["f3000", "f6000", "f9000"]
    assert clf.levels_["stroke"].size == 1 and clf.levels_["position"].size == 1
    np.testing.assert_allclose(clf.levels_["feed"], [3000, 6000, 9000], rtol=2e-3)
    q = pd.DataFrame({"stroke_mm": [400, 500, 300], "start_mm": [0, 0, 100], "end_mm": [400, 500, 400],
                      "feed_mm_min": [4400, 5000, 12000]})  # fmt: skip
    # 4400: nearer 3000 (1400) than 6000 (1600); 5000: nearer 6000; 12000: nearer 9000
    assert list(clf.predict(q)) == ["f3000", "f6000", "f9000"]


def test_given_levels_map_each_condition_to_its_nearest_level():
    X = pd.DataFrame({"stroke_mm": [48.0, 96.0], "start_mm": [0.0, 0.0], "end_mm": [48.0, 96.0],
                      "feed_mm_min": [790.0, 810.0]})  # fmt: skip
    clf = ProximityNaiveBayes([50, 100, 300], [0, 650, 1300], [800, 2000, 4000]).fit(X, ["a", "b"])
    assert clf.condition_levels_.tolist() == [[0, 0, 0], [1, 0, 0]]


def test_conditions_on_the_same_levels_are_an_error_naming_them():
    X = pd.DataFrame({"stroke_mm": [40.0, 60.0, 300.0], "start_mm": [0.0, 0.0, 0.0],
                      "end_mm": [40.0, 60.0, 300.0], "feed_mm_min": [800.0, 800.0, 800.0]})  # fmt: skip
    with pytest.raises(ValueError, match=r"conditions \['a', 'b'\] map to the same levels"):
        ProximityNaiveBayes([50, 100, 300], [0, 650, 1300], [800, 2000, 4000]).fit(X, ["a", "b", "c"])


@pytest.mark.parametrize(
    "kwargs, fit_args, match",
    [
        ({}, (), "has no conditions"),
        ({"stroke_levels_mm": []}, (), "stroke_levels_mm must be a non-empty"),
        ({"conditions": {"#1": {"stroke_mm": 50, "feed_mm_min": 800}}}, (), r"conditions\['#1'\]: missing position_mm"),
        ({}, (pd.DataFrame({"stroke_mm": [1.0], "feed_mm_min": [2.0]}), ["a"]), "missing column"),
        ({}, (pd.DataFrame({"stroke_mm": [1.0], "centre_mm": [2.0], "feed_mm_min": [-2.0]}), ["a"]),
         "feed_mm_min must be >= 0"),
    ],
)  # fmt: skip
def test_bad_classifier_input(kwargs, fit_args, match):
    with pytest.raises(ValueError, match=match):
        ProximityNaiveBayes(**kwargs).fit(*fit_args)


# ------------------------------------------------------ motion features ---
def triangle(t, lo, hi, feed_mm_min, t0=0.0):
    """Position of an axis reciprocating lo -> hi -> lo at constant feed, starting at lo at t0."""
    s = hi - lo
    phase = np.mod((np.asarray(t, dtype=float) - t0) * feed_mm_min / 60.0, 2 * s)
    return lo + np.where(phase <= s, phase, 2 * s - phase)


def log(t, x, f):
    return pd.DataFrame({"t_s": np.asarray(t, dtype=float), "axis_mm": x, "feed_mm_min": f})


def test_window_features_of_a_steady_reciprocation():
    t = np.arange(0.0, 1800.0)
    pr = log(t, triangle(t, 100.0, 400.0, 2500.0), np.full(t.size, 2500.0))
    w = window_features(pr, [900.0, 1799.0])
    np.testing.assert_allclose(w[["start_mm", "end_mm", "stroke_mm", "feed_mm_min"]].to_numpy(),
                               [[100, 400, 300, 2500]] * 2, atol=1e-9)  # fmt: skip
    assert w["moving"].all()


def test_aliased_turning_points_are_recovered():
    """100 mm at 4000 mm/min (seed 002 #8) has a 3 s period: sampled at 1 Hz the axis
    shows 550, 616.7, 616.7 mm only; the path between the two 616.7 samples (66.7 mm)
    can only have turned at 650. 50 mm at 4000 mm/min turns twice between samples:
    ambiguous, so the range stays inside the true one (never beyond it)."""
    t = np.arange(0.0, 1200.0)
    x = triangle(t, 550.0, 650.0, 4000.0)
    assert np.unique(np.round(x, 6)).tolist() == [550.0, 616.666667]
    w = window_features(log(t, x, np.full(t.size, 4000.0)), [1199.0])
    assert (w.start_mm[0], w.end_mm[0]) == (pytest.approx(550.0), pytest.approx(650.0))
    x = triangle(t, 600.0, 650.0, 4000.0, t0=0.3)
    w = window_features(log(t, x, np.full(t.size, 4000.0)), [1199.0])
    assert 600.0 - 1e-9 <= w.start_mm[0] and w.end_mm[0] <= 650.0 + 1e-9
    assert w.stroke_mm[0] < 50.0  # aliased, as a 1 Hz log is


def test_dominant_feed_and_stops():
    """400 s at 2000 mm/min over 0-100 mm, then 150 s at 800 mm/min over 300-350, then a
    stop: the window ending at 600 s is dominated by 2000 mm/min; once the window holds
    less than min_moving_s of motion it is a stop (moving False, features NaN)."""
    t = np.arange(0.0, 2000.0)
    x = np.where(t < 400, triangle(t, 0.0, 100.0, 2000.0), triangle(t, 300.0, 350.0, 800.0, t0=400.0))
    f = np.where(t < 400, 2000.0, 800.0)
    x = np.where(t >= 550, x[550], x)
    f = np.where(t >= 550, 0.0, f)
    w = window_features(log(t, x, f), [599.0, 1200.0, 1900.0], window_s=600.0, min_moving_s=60.0)
    assert w.loc[0, "feed_mm_min"] == 2000.0
    assert (w.loc[0, "start_mm"], w.loc[0, "end_mm"]) == (0.0, 100.0)
    # at 1200 s the window (600, 1200] has no motion; nor at 1900 s
    assert list(w["moving"]) == [True, False, False]
    assert w.loc[1:, ["stroke_mm", "feed_mm_min"]].isna().all().all()


def _with_measuring_cycle(t_cycle=1000.0, work=(0.0, 50.0), feed=800.0):
    """A work reciprocation at the measuring feed (seed 002 #1) interrupted by a
    measuring cycle: approach to 0, 4 s dwell at each target 0..650 (every 50 mm),
    return to the work range - all at 800 mm/min, sampled at 1 Hz."""
    v = feed / 60.0
    # work until t_cycle, then the cycle, then work again
    tt = np.arange(0.0, t_cycle)
    x_work = triangle(tt, *work, feed)
    pos = x_work[-1]
    path_t, path_x = [t_cycle], [pos]
    readings = []
    for target in np.arange(0.0, 651.0, 50.0):
        path_t.append(path_t[-1] + abs(target - path_x[-1]) / v)
        path_x.append(target)
        readings.append((path_t[-1] + 2.0, target))
        path_t.append(path_t[-1] + 4.0)
        path_x.append(target)
    path_t.append(path_t[-1] + abs(650.0 - work[0]) / v)
    path_x.append(work[0])
    t_end_return = path_t[-1]
    t = np.arange(0.0, 3000.0)
    x = np.interp(t, path_t, path_x)
    x[t < t_cycle] = x_work
    after = t > t_end_return
    x[after] = triangle(t[after], *work, feed, t0=t_end_return)
    moving = np.r_[True, np.abs(np.diff(x)) > 1e-9] | (t < t_cycle) | after
    f = np.where(moving, feed, 0.0)
    er = pd.DataFrame(readings, columns=["t_s", "target_mm"])
    return log(t, x, f), er, t_end_return


def test_measuring_cycles_are_excluded():
    pr, er, t_ret = _with_measuring_cycle()
    ex = measuring_intervals(pr, er)
    assert ex.shape == (1, 2)
    t0, t1 = ex[0]
    assert t0 <= 1000.0 + 1 and t1 >= t_ret  # approach and return are inside
    assert t1 <= t_ret + 10.0  # and not much more
    without = window_features(pr, [t_ret + 300.0])
    with_ex = window_features(pr, [t_ret + 300.0], exclude=ex)
    assert without.end_mm[0] >= 650.0  # the measuring traverse looks like work
    assert (with_ex.start_mm[0], with_ex.end_mm[0]) == (pytest.approx(0.0), pytest.approx(50.0))


def _python_steps(fn):
    """``fn()`` and the number of Python calls and lines it executed (sys.settrace): its cost in
    interpreted steps, which does not depend on how fast the machine is."""
    n = 0

    def trace(frame, event, arg):
        nonlocal n
        n += 1
        return trace

    old = sys.gettrace()
    sys.settrace(trace)
    try:
        out = fn()
    finally:
        sys.settrace(old)
    return out, n


def test_window_features_are_fast():
    """A 4 h run at 1 Hz, evaluated every 60 s, is vectorised over the log: the same windows of a
    16 h log (43 200 more samples) cost no more interpreted steps. A Python loop over the samples
    would add at least one step per sample."""
    grid = np.arange(0.0, 4 * 3600.0 - 1.0, 60.0)
    w, steps = {}, {}
    for hours in (4, 16):
        t = np.arange(0.0, hours * 3600.0)
        pr = log(t, triangle(t, 0.0, 300.0, 2000.0), np.full(t.size, 2000.0))
        w[hours], steps[hours] = _python_steps(lambda: window_features(pr, grid))
    assert w[4]["moving"].sum() == (grid >= 60.0).sum()
    pd.testing.assert_frame_equal(w[16], w[4])  # the samples after the last window change nothing
    assert steps[16] - steps[4] < 0.01 * (16 - 4) * 3600, steps


def test_bad_log_is_named():
    with pytest.raises(ValueError, match="no column 'feed_mm_min'"):
        window_features(pd.DataFrame({"t_s": [0.0], "axis_mm": [0.0]}), [0.0])


# --------------------------------------------- seed 002 benchmark logs ---
@pytest.fixture(scope="module")
def seed002_windows():
    from thermbench.bench.datasets import load_benchmark

    ds = load_benchmark("seed002_vmc655h_x")
    out = {}
    for r in [f"c{k}" for k in range(1, 10)]:
        pr, er = ds.process_run(r), ds.errors_run(r)
        grid = np.arange(pr["t_s"].iloc[0], pr["t_s"].iloc[-1], 60.0)
        w = window_features(pr, grid, exclude=measuring_intervals(pr, er)).assign(t_s=grid)
        out[r] = (w[w["moving"]], ds.metadata.runs[r].condition)
    return out


def test_benchmark_windows_recover_table5_conditions(seed002_windows):
    """The declared conditions from the 1 Hz logs: exact, except #7 (50 mm at 4000 mm/min
    turns twice between samples: seen as 600-633 mm), and the seed 002 classifier labels
    every moving window of condition c_k as #k."""
    clf = instantiate(seed002_config(), _convert_="all").fit()
    for k in range(1, 10):
        w, c = seed002_windows[f"c{k}"]
        assert len(w) > 200
        if k != 7:
            assert np.allclose(w["start_mm"].median(), c.start_mm) and np.allclose(w["end_mm"].median(), c.end_mm)
        np.testing.assert_allclose(w["feed_mm_min"], c.feed_mm_min, rtol=1e-12)
        assert set(clf.predict(w)) == {f"#{k}"}


def test_learned_classifier_on_the_benchmark(seed002_windows):
    """GaussianNB (conf/classifier/learned.yaml) trained on the windows of the first half
    of each c1..c9 run labels the windows of the second half. The nine conditions differ
    by >= 50 mm of stroke or centre, or a factor >= 2 in feed, while a steady condition's
    window features repeat to within a sample step; only windows disturbed by a
    measuring cycle could be off, about 1 in 30 (one cycle per 30 min): we require
    >= 97 % (measured: 100 %)."""
    gnb = instantiate(OmegaConf.load(config_dir() / "classifier" / "learned.yaml"), _convert_="all")
    train, test = [], []
    for r, (w, _) in seed002_windows.items():
        half = w["t_s"] < w["t_s"].median()
        train.append(w[half].assign(y=r))
        test.append(w[~half].assign(y=r))
    train, test = pd.concat(train), pd.concat(test)
    gnb.fit(learned_features(train), train["y"])
    acc = float(np.mean(gnb.predict(learned_features(test)) == test["y"].to_numpy()))
    assert acc >= 0.97


# ----------------------- the learned classifier on unseen motion (classifier_eval) ---
# conditions far apart in feed (±15 % bands 425-575, 1700-2300, 5100-6900 mm/min never meet)
SEPARATED = {
    "A": {"start_mm": 0.0, "end_mm": 100.0, "feed_mm_min": 500.0},
    "B": {"start_mm": 250.0, "end_mm": 450.0, "feed_mm_min": 2000.0},
    "C": {"start_mm": 500.0, "end_mm": 620.0, "feed_mm_min": 6000.0},
}


class NearestFeed:
    """A classifier known to be right on SEPARATED by construction: the condition whose feed is
    nearest the window's feed (log scale); ``rename`` permutes its answers (a wrong classifier)."""

    def __init__(self, conditions, rename=None):
        self.feeds = {k: c["feed_mm_min"] for k, c in conditions.items()}
        self.rename = rename or {}
        self.classes_ = np.array(list(self.feeds), dtype=object)

    def predict(self, X):
        f = np.log(X["feed_mm_min"].to_numpy(dtype=float))[:, None]
        lab = self.classes_[np.argmin(np.abs(f - np.log([self.feeds[k] for k in self.classes_])), axis=1)]
        return np.array([self.rename.get(v, v) for v in lab], dtype=object)


@pytest.fixture(scope="module")
def seed002_learned():
    """GaussianNB (conf/classifier/learned.yaml) fitted as a ConditionBank fits it on c1..c9."""
    from thermbench.bench.classifier_eval import fit_condition_classifier, run_conditions
    from thermbench.bench.datasets import load_benchmark

    ds = load_benchmark("seed002_vmc655h_x")
    runs = [f"c{k}" for k in range(1, 10)]
    return fit_condition_classifier(ds, runs), run_conditions(ds, runs)


def test_eval_table6_is_the_papers_table():
    """The evaluation's Table 6 is the one transcribed above from the paper."""
    from thermbench.bench.classifier_eval import SEED002_TABLE6

    assert [tuple(r) for r in SEED002_TABLE6] == [tuple(float(v) for v in r[:4]) + (r[4],) for r in TABLE6]


def test_table6_through_the_window_features_with_eq19_as_the_classifier():
    """eq. 19 itself (conf/classifier/seed002.yaml, labels #1..#9) as the classifier: the window of
    each Table 6 motion, simulated at 1 Hz, shows the printed motion (except row 2: 30 mm at
    4000 mm/min is 66.7 mm of path per sample, aliased, seen shorter but inside the true range),
    so it gets the hand-derived eq. 19 class of every row; the paper column is the paper's."""
    from thermbench.bench.classifier_eval import table6_accuracy

    df = table6_accuracy(instantiate(seed002_config(), _convert_="all").fit())
    assert df["paper"].tolist() == [r[4] for r in TABLE6]
    assert df["eq19"].tolist() == EQUATIONS and df["learned"].tolist() == EQUATIONS
    assert (df["learned_share"] == 1.0).all() and (df["n_windows"] >= 20).all()
    assert df.attrs["agree_eq19"] == 7 and df.attrs["agree_paper"] == 5
    plain = df.drop(index=2)
    np.testing.assert_allclose(plain["seen_stroke_mm"], plain["stroke_mm"], atol=1.0)
    np.testing.assert_allclose(plain["seen_centre_mm"], (plain["start_mm"] + plain["end_mm"]) / 2, atol=1.0)
    np.testing.assert_allclose(df["seen_feed_mm_min"], df["feed_mm_min"], rtol=1e-9)
    assert df.loc[2, "seen_stroke_mm"] <= 30.0 + 1e-9


def test_table6_learned_gaussian_nb(seed002_learned):
    """GaussianNB on c1..c9. A steady condition's window features are constant (see
    test_benchmark_windows_recover_table5_conditions), so every class variance is GaussianNB's
    var_smoothing floor, the same for all three features: it labels a window with the nearest
    condition in raw (stroke_mm, centre_mm, feed_mm_min) units, where a feed difference of
    hundreds of mm/min outweighs any position. Derived here from the declared conditions and
    the printed motions: rows 1, 3, 4, 5, 7 as the paper prints them (row 5: feed 300 mm/min
    puts it among #1-#3 and its 620 mm centre is nearest #3's); row 2 (4000 mm/min, centre 75
    mm) and row 6 (4300 mm/min) among #7-#9, nearest #9; eq. 19 gives #7 and #6 there."""
    from thermbench.bench.classifier_eval import table5_label_map, table6_accuracy

    clf, cond = seed002_learned
    assert np.ptp(clf.var_) == 0.0
    means = np.array([[c["stroke_mm"], (c["start_mm"] + c["end_mm"]) / 2, c["feed_mm_min"]] for c in cond.values()])
    motion = np.array([[a, (s + e) / 2, f] for a, s, e, f, _ in TABLE6], dtype=float)
    nearest = [f"#{k + 1}" for k in np.argmin(np.linalg.norm(motion[:, None] - means[None], axis=2), axis=1)]
    assert table5_label_map(cond) == {f"c{k}": f"#{k}" for k in range(1, 10)}
    df = table6_accuracy(clf, table5_label_map(cond))
    assert df["learned"].tolist() == nearest
    assert (df["learned_share"] == 1.0).all()
    paper = [r[4] for r in TABLE6]
    assert df.attrs["agree_paper"] == sum(a == b for a, b in zip(nearest, paper))
    assert df.attrs["agree_eq19"] == sum(a == b for a, b in zip(nearest, EQUATIONS))


def test_duty_cycles_perfect_and_permuted_classifiers():
    """On SEPARATED a steady window (>= window_s after the axis reached the segment's stroke)
    holds one segment's feed only, so NearestFeed is right at every steady time (100 %) and the
    same with permuted labels is wrong at every one (0 %). After a switch the label changes
    once the new feed has more time in the window than the old one, about window_s / 2 after
    the switch without stops (the previous segment lasts >= 300 s): a lag share near 1/2."""
    from thermbench.bench.classifier_eval import duty_cycle_accuracy

    right = duty_cycle_accuracy(NearestFeed(SEPARATED), SEPARATED, seed=3, n_runs=6)
    assert right.accuracy == 1.0 and right.n_steady > 300 and right.n_lag > 300
    assert 0.0 < right.lag_share < 1.0
    assert (right.per_condition["accuracy"] == 1.0).all()
    conf = right.confusion.to_numpy()
    assert (conf == np.diag(np.diag(conf))).all() and conf.sum() == right.n_steady
    wrong = duty_cycle_accuracy(NearestFeed(SEPARATED, {"A": "B", "B": "C", "C": "A"}), SEPARATED, seed=3, n_runs=6)
    assert wrong.accuracy == 0.0 and wrong.n_steady == right.n_steady
    assert wrong.confusion.loc["A", "B"] == right.confusion.loc["A", "A"]
    no_stops = duty_cycle_accuracy(NearestFeed(SEPARATED), SEPARATED, seed=3, n_runs=6, p_stop=0.0)
    assert 0.35 < no_stops.lag_share < 0.65


def test_duty_cycles_are_reproducible_for_a_seed():
    from thermbench.bench.classifier_eval import duty_cycle_accuracy, random_duty_cycles

    assert random_duty_cycles(SEPARATED, 7, n_runs=2) == random_duty_cycles(SEPARATED, 7, n_runs=2)
    assert random_duty_cycles(SEPARATED, 7, n_runs=2) != random_duty_cycles(SEPARATED, 8, n_runs=2)
    a, b = (duty_cycle_accuracy(NearestFeed(SEPARATED), SEPARATED, seed=5, n_runs=3) for _ in range(2))
    pd.testing.assert_frame_equal(a.per_condition, b.per_condition)
    pd.testing.assert_frame_equal(a.confusion, b.confusion)
    assert (a.accuracy, a.lag_share, a.n_lag) == (b.accuracy, b.lag_share, b.n_lag)


def test_duty_cycle_draws_stay_near_their_condition():
    """Each move segment is its condition with stroke and feed within ±perturb, the centre within
    ±perturb x the stroke, inside the travel; consecutive segments differ in condition; the
    lengths are within move_s and stop_s (the simulator's random-run defaults)."""
    from thermbench.bench.classifier_eval import random_duty_cycles

    n = 0
    for run in random_duty_cycles(SEPARATED, 11, n_runs=4, perturb=0.15):
        moves = [(p, lab) for p, lab in run if lab is not None]
        assert all(a[1] != b[1] for a, b in zip(moves, moves[1:]))
        for p, lab in moves:
            c = SEPARATED[lab]
            stroke = c["end_mm"] - c["start_mm"]
            assert abs(p.end_mm - p.start_mm - stroke) <= 0.15 * stroke + 1e-9
            # (a longer stroke pushed back inside the travel moves by <= 7.5 % of the stroke)
            assert abs((p.start_mm + p.end_mm) / 2 - (c["start_mm"] + c["end_mm"]) / 2) <= 0.15 * stroke + 1e-9
            assert abs(p.feed_mm_min / c["feed_mm_min"] - 1) <= 0.15 + 1e-12
            assert 0.0 <= p.start_mm < p.end_mm <= 650.0 and 300.0 <= p.duration_s <= 1800.0
            n += 1
        assert all(300.0 <= p.duration_s <= 1200.0 for p, lab in run if lab is None)
    assert n == 4 * 12


def test_duty_cycles_learned_gaussian_nb_above_the_physics_floor(seed002_learned):
    """GaussianNB on random duty cycles of c1..c9 (stroke and feed ±15 %, centre ±15 % of the
    stroke). Floor from the features: a steady window is one segment's reciprocation, its feed
    exact and its range exact at 1 Hz (fast short strokes alias shorter, as in training). The
    ±15 % feed bands of 800, 2000 and 4000 mm/min (680-920, 1700-2300, 3400-4600) are >= 780
    mm/min apart, so the nearest condition (test_table6_learned_gaussian_nb) is in the right
    feed group; within it, conditions differ by >= 50 mm of stroke and a draw moves <= 15 % of
    its stroke: nearer its own. So every steady time should be right; allow for a window
    disturbed by a measuring cycle (one per 30 min, about 1 in 30): >= 97 % overall, >= 90 %
    per condition. Lag: a new label needs the new feed to dominate the window, about half of
    it after a switch without a stop (70 % of switches): lag share < 0.65. Into a 300 mm
    stroke (a third of the switches) the range seen once the new feed dominates, stroke plus
    the approach to it, is nearest that condition: lag share > 0.1 overall, > 0.4 for c3, c6, c9."""
    from thermbench.bench.classifier_eval import duty_cycle_accuracy

    clf, cond = seed002_learned
    r = duty_cycle_accuracy(clf, cond, seed=0)
    assert r.n_steady > 1000 and r.n_lag > 1000
    assert r.accuracy >= 0.97
    assert (r.per_condition["accuracy"] >= 0.90).all()
    assert 0.1 < r.lag_share < 0.65
    assert (r.per_condition.loc[["c3", "c6", "c9"], "lag_share"] > 0.4).all()
    assert list(r.confusion.index) == list(cond) and r.confusion.to_numpy().sum() == r.n_steady
    text = r.format()
    assert "per condition: c1" in text and "confusion" in text


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"seed": -1}, "seed must be an integer >= 0"),
        ({"seed": 1.5}, "seed must be an integer >= 0"),
        ({"perturb": 1.2}, r"perturb must be a fraction in \[0, 1\)"),
        ({"move_s": (600, 300)}, "move_s must be a .* 0 < min <= max"),
        ({"centre_scale": "centre"}, r"centre_scale must be one of \['stroke', 'travel'\]"),
        ({"conditions": {"A": SEPARATED["A"]}}, "at least two labels"),
        ({"conditions": {"A": {"start_mm": 0.0, "end_mm": 100.0}, "B": SEPARATED["B"]}},
         r"conditions\['A'\]: expected a motion condition with start_mm, end_mm \(mm\) and feed_mm_min"),
        ({"conditions": {**SEPARATED, "D": {"start_mm": 600.0, "end_mm": 700.0, "feed_mm_min": 1.0}}},
         "outside travel_mm 0-650 mm"),
    ],
)  # fmt: skip
def test_bad_duty_cycle_input_is_named(kwargs, match):
    from thermbench.bench.classifier_eval import random_duty_cycles

    args = {"conditions": SEPARATED, "seed": 0, "n_runs": 1} | kwargs
    with pytest.raises(ValueError, match=match):
        random_duty_cycles(**args)


def test_bad_table6_input_is_named():
    from thermbench.bench.classifier_eval import table6_accuracy

    eq19 = instantiate(seed002_config(), _convert_="all").fit()
    with pytest.raises(ValueError, match=r"label_map has no Table 5 class for the classifier's label '#2'"):
        table6_accuracy(eq19, label_map={"c1": "#1"})
    with pytest.raises(ValueError, match=r"Table 6 row 1 .*stroke_mm 100 must equal \|end_mm - start_mm\|"):
        table6_accuracy(eq19, rows=[(100, 60, 200, 1250, "#2")])
    with pytest.raises(ValueError, match=r"Table 6 row 1: expected \(stroke_mm, start_mm, end_mm, feed_mm_min"):
        table6_accuracy(eq19, rows=[(100, 60, 160)])
    with pytest.raises(ValueError, match="duration_s must be a number >= window_s"):
        table6_accuracy(eq19, duration_s=300.0)
    with pytest.raises(ValueError, match="classifier must be a fitted classifier with predict"):
        table6_accuracy(object())


def test_cli_classify_prints_the_class_and_the_probabilities(capsys):
    """`thermbench classify` on Table 6 row 1: class #2; the printed scores are eq. 19's
    (stroke 100 matches #2/#5/#8 exactly; position 220 and feed 1250 from the hand
    computation in test_table6_rows: P_B(left) = 0.583, P_C(800) = 0.567) plus the prior 1/9."""
    from thermbench.cli import main

    assert main(["classify", "--stroke", "100", "--start", "60", "--end", "160", "--feed", "1250"]) == 0
    out = capsys.readouterr().out
    assert "class: #2" in out
    row2 = next(ln for ln in out.splitlines() if ln.startswith("#2"))
    score = float(row2.split()[4])
    assert score == pytest.approx(1.0 + (1 / 220) / (1 / 220 + 1 / 430 + 1 / 1080)
                                  + (1 / 450) / (1 / 450 + 1 / 750 + 1 / 2750) + 1 / 9, abs=2e-3)


def test_cli_classify_rejects_inconsistent_stroke_and_learned_classifier(capsys):
    from thermbench.cli import main

    assert main(["classify", "--stroke", "100", "--start", "60", "--end", "100", "--feed", "1250"]) == 2
    assert "stroke" in capsys.readouterr().err
    assert main(["classify", "--stroke", "40", "--start", "60", "--end", "100", "--feed", "1250",
                 "--classifier", "learned"]) == 2
    assert "--classifier learned" in capsys.readouterr().err


# ------------------------------------------- operating factors (spindle speed) ---
def speed_rows(rpms, label_of):
    return pd.DataFrame({"spindle_rpm": rpms}), [label_of[r] for r in rpms]


def test_one_factor_proximity_by_hand():
    """seed 002 eq. 15-19 with the spindle speed as the one factor, levels 1000, 2000 and
    4000 rpm. At 1600 rpm, eq. 15: 1/600, 1/400, 1/2400; eq. 16 normalises them to
    4/11, 6/11, 1/11 (x 2400: 4, 6, 1); eq. 19 adds the prior 1/3: the class is 2000
    and the normalised scores are (4/11 + 1/3) / 2, ... (they sum to 1 + 1)."""
    X, y = speed_rows([1000.0] * 3 + [2000.0] * 3 + [4000.0] * 3, {1000.0: "a", 2000.0: "b", 4000.0: "c"})
    q = pd.DataFrame({"spindle_rpm": [1600.0]})
    p16 = np.array([4 / 11, 6 / 11, 1 / 11])
    clf = ProximityNaiveBayes(factors=["spindle_rpm"]).fit(X, y)
    assert clf.factors_ == ("spindle_rpm",) and list(clf.classes_) == ["a", "b", "c"]
    np.testing.assert_allclose(clf.level_probabilities(q)["spindle_rpm"], [p16])
    np.testing.assert_allclose(clf.condition_scores(q), [p16 + 1 / 3])
    np.testing.assert_allclose(clf.predict_proba(q), [(p16 + 1 / 3) / 2])
    assert list(clf.predict(q)) == ["b"]
    prox = clone(clf).set_params(probability="proximity").fit(X, y)
    np.testing.assert_allclose(prox.predict_proba(q), [p16])
    lin = clone(clf).set_params(probability="linear").fit(X, y)
    np.testing.assert_allclose(lin.predict_proba(q), [[0.4, 0.6, 0.0]])  # (2000-1600)/1000, (1600-1000)/1000
    # the proximity rule beyond the known speeds: 500 -> 1000, 4500 -> 4000; an exact level has probability 1
    out = pd.DataFrame({"spindle_rpm": [500.0, 4500.0, 2000.0]})
    assert list(clf.predict(out)) == ["a", "c", "b"]
    np.testing.assert_allclose(prox.predict_proba(out)[0], [21 / 31, 7 / 31, 3 / 31])  # 1/500 : 1/1500 : 1/3500
    np.testing.assert_allclose(prox.predict_proba(out)[2], [0.0, 1.0, 0.0])
    np.testing.assert_allclose(lin.predict_proba(out)[:2], [[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])


def test_operating_levels_from_the_conditions_keep_close_speeds_apart():
    """fl_thermal's speeds: 3500 and 3750 rpm differ by 250 rpm = 5 % of the largest (5000),
    which merges motion levels; operating levels merge within 5 % of the larger neighbour."""
    rpms = [1250.0, 2500.0, 3500.0, 3750.0, 5000.0]
    X, y = speed_rows(rpms, {r: f"rpm{int(r)}" for r in rpms})
    clf = ProximityNaiveBayes(factors=["spindle_rpm"]).fit(X, y)
    np.testing.assert_allclose(clf.levels_["spindle_rpm"], rpms)
    with pytest.raises(ValueError, match=r"conditions \['rpm3500', 'rpm3750'\] map to the same levels"):
        ProximityNaiveBayes(factors=["spindle_rpm"], level_tolerance=0.1).fit(X, y)
    given = ProximityNaiveBayes(factors=["spindle_rpm"], levels={"spindle_rpm": [1000, 2500, 3600, 5000]})
    with pytest.raises(ValueError, match=r"config key 'classifier.levels.spindle_rpm'"):
        given.fit(X, y)  # 3500 and 3750 both nearest 3600


def test_preset_operating_conditions_need_no_data():
    clf = ProximityNaiveBayes(factors=["spindle_rpm"], conditions={"slow": {"spindle_rpm": 1000},
                                                                   "fast": {"spindle_rpm": 4000}}).fit()  # fmt: skip
    assert list(clf.predict(pd.DataFrame({"spindle_rpm": [2400.0, 2600.0]}))) == ["slow", "fast"]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"factors": "spindle_rpm"}, "config key 'classifier.factors': factors must be null"),
        ({"factors": ["spindle_rpm", "spindle_rpm"]}, "names a column twice"),
        ({"factors": ["spindle_rpm"], "stroke_levels_mm": [50.0]}, "'classifier.stroke_levels_mm'.*motion level"),
        ({"levels": {"spindle_rpm": [1000.0]}}, "'classifier.levels'.*set factors"),
        ({"factors": ["spindle_rpm"], "levels": {"load_N": [1.0]}}, r"levels names \['load_N'\]"),
        ({"factors": ["spindle_rpm"], "probability": "soft"}, r"'classifier.probability'.*\['score', 'proximity'"),
        ({"factors": ["spindle_rpm"], "conditions": {"a": {"rpm": 1.0}}},
         r"conditions\['a'\]: missing \['spindle_rpm'\]"),
    ],
)  # fmt: skip
def test_bad_operating_classifier_config(kwargs, match):
    X, y = speed_rows([1000.0, 2000.0], {1000.0: "a", 2000.0: "b"})
    with pytest.raises(ValueError, match=match):
        ProximityNaiveBayes(**kwargs).fit(X, y)


def test_operating_features_missing_column_is_named():
    clf = ProximityNaiveBayes(factors=["spindle_rpm"]).fit(*speed_rows([1000.0, 2000.0], {1000.0: "a", 2000.0: "b"}))
    with pytest.raises(ValueError, match=r"missing column\(s\) \['spindle_rpm'\]"):
        clf.predict(pd.DataFrame({"feed_mm_min": [1.0]}))
    with pytest.raises(ClassifierError, match="classifies axis motion"):
        classify_motion(100, 60, 160, 1250, classifier=clf)


def test_operating_window_features_by_hand():
    """A 10 s log: 1000 rpm until 300 s, stopped until 400 s, 3000 rpm until 1000 s, then
    stopped. The window (90, 690] holds 20 samples at 1000, 10 stopped, 30 at 3000: the
    running mean is (20 x 1000 + 30 x 3000) / 50 = 2200 rpm (the stop does not dilute it);
    (990, 1590] has one running sample (10 s < min_moving_s 60): a stop; (1040, 1640] none."""
    t = np.arange(0.0, 2000.0, 10.0)
    rpm = np.where(t < 300, 1000.0, np.where(t < 400, 0.0, np.where(t < 1000, 3000.0, 0.0)))
    w = operating_window_features(pd.DataFrame({"t_s": t, "spindle_rpm": rpm}), [690.0, 1590.0, 1640.0],
                                  ["spindle_rpm"], window_s=600.0, min_moving_s=60.0)  # fmt: skip
    assert w.loc[0, "spindle_rpm"] == pytest.approx(2200.0, rel=1e-12) and w.loc[0, "moving"]
    assert list(w["moving"]) == [True, False, False] and w.loc[1:, "spindle_rpm"].isna().all()
    with pytest.raises(ValueError, match=r"no column\(s\) \['spindle_rpm'\]"):
        operating_window_features(pd.DataFrame({"t_s": t}), [690.0], ["spindle_rpm"])
