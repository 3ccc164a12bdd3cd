"""The stack of every candidate family (thermbench/bench/stack.py): its weights, held-out and inner
scores against a hand computation with scipy's NNLS on planted out-of-run predictions, what it never
stacks, and the benchmark on a lab's files end to end (the stack scored, its deployed model exported
at parity)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from scipy.optimize import nnls

from tests.test_benchmark_own import lathe  # noqa: F401 (a fixture: the three-day lathe imported from a lab's files)
from thermbench.bench.plan import DEPLOY_FOLD
from thermbench.bench.stack import MAX_MEMBERS, STACK, fitted_weights, stack_task


def _w(P, y):
    w, _ = nnls(P, y)
    return w / w.sum()


def test_at_most_eight_members_the_smallest_leaving_and_the_rest_fitted_again():
    rng = np.random.default_rng(0)
    P = rng.standard_normal((400, 10))
    y = P @ np.linspace(1.0, 2.0, 10) + 0.01 * rng.standard_normal(400)  # every column earns a weight
    assert np.count_nonzero(_w(P, y)) == 10
    w, how = fitted_weights(P, y)
    assert how == "nnls" and np.count_nonzero(w) == MAX_MEMBERS == 8 and w.sum() == pytest.approx(1.0)
    kept = np.flatnonzero(w)
    assert set(range(10)) - set(kept) == {0, 1}  # the two of smallest weight (the planted 1.0 and 1.11)
    np.testing.assert_allclose(w[kept], _w(P[:, kept], y), atol=1e-12)


class _Fitted:
    """A fitted member as the stack reads it: what it trained on and the sensors it reads."""

    def __init__(self, sensors, runs):
        self.train_runs_ = list(runs)
        self.sensors = tuple(sensors)
        self.channel_ = None

    def required_inputs(self):
        from thermbench.models.base import Inputs

        return Inputs(sensors=self.sensors)

    def get_params(self, deep=False):
        return {}


def _task(family, preds_inner, preds_outer, runs, y_of, sensors=("T1",)):
    """A task output with planted predictions: inner (fold -> inner fold -> run -> array) and outer
    (fold -> run -> array), every run 4 readings."""
    inner = [pd.DataFrame({"fold": f, "inner_fold": g, "run_id": r, "row": np.arange(4), "y": y_of[r], "pred": p})
             for f, by_g in preds_inner.items() for g, by_r in by_g.items() for r, p in by_r.items()]  # fmt: skip
    outer = [pd.DataFrame({"fold": f, "run_id": r, "row": np.arange(4), "y": y_of[r], "pred": p})
             for f, by_r in preds_outer.items() for r, p in by_r.items()]  # fmt: skip
    results = pd.DataFrame(columns=["approach", "kind", "fold", "run_id"]) if not preds_outer else pd.DataFrame([{"dataset": "d", "channel": "all", "family": family, "approach": "global", "kind": "validation",
                             "fold": f, "run_id": r, "train": "all", "own": False, "rmse_um": 9.9,
                             "rms_error_um": float(np.sqrt(np.mean(y_of[r] ** 2))), "max_abs_error_um": 10.0,
                             "pv_error_um": 12.0, "max_abs_residual_um": 9.9, "compensation_rate": 0.01,
                             "sensors": " ".join(sensors), "coverage_80": 0.5}
                            for f, by_r in preds_outer.items() for r in by_r])  # fmt: skip
    return {"dataset": "d", "channel": "all", "family": family, "results": results,
            "models": {"global": _Fitted(sensors, runs)}, "stack_inner": pd.concat(inner, ignore_index=True),
            "stack_outer": pd.concat(outer, ignore_index=True) if outer else pd.DataFrame(), "dataset_hash": "h",
            "cv": "loro"}  # fmt: skip


@pytest.fixture
def any_kind(monkeypatch):
    """The planted members below are no models the C runtime encodes: taken as stackable."""
    import thermbench.bench.stack as stack_mod

    monkeypatch.setattr(stack_mod, "stackable", lambda model: True)


def test_only_the_kinds_that_answer_from_their_latest_samples_are_stacked(monkeypatch):
    """A physics, lumped or AR model steps on its own grid or window (its readiness lags the samples):
    the ENSEMBLE kind would refuse queries it answers alone, so it is not stacked; nor is what does not
    encode."""
    from types import SimpleNamespace

    import thermbench.export.encoding as enc
    from thermbench.bench.stack import stackable
    from thermbench.export.fileformat import Kind

    for kind, ok in [(Kind.THERMAL_LAG, True), (Kind.LINEAR_HISTORY, True), (Kind.GRU, True), (Kind.MLR_SEED001, True),
                     (Kind.PHYSICS, False), (Kind.LUMPED, False), (Kind.AR, False), (Kind.ENSEMBLE, False)]:  # fmt: skip
        monkeypatch.setattr(enc, "encode", lambda model, k=kind: SimpleNamespace(kind=k))
        assert stackable(object()) is ok, kind

    def refuse(model):
        raise enc.ExportError("no file encoding")

    monkeypatch.setattr(enc, "encode", refuse)
    assert stackable(object()) is False


def test_the_weights_the_held_out_and_the_inner_scores_by_hand(monkeypatch, any_kind):
    """Three runs, fold r3 holds r3 out (inner folds r1, r2), the deployed fold every run; two families
    with planted predictions: each figure recomputed here with scipy's NNLS."""
    import thermbench.bench.stack as stack_mod

    made = {}

    def of_fitted(names, fitted, weights, how, cv):  # what the deployed stack is built from
        made.update(names=list(names), weights=np.asarray(weights), how=how, cv=cv)
        return "stacked"

    monkeypatch.setattr(stack_mod.StackedEnsemble, "of_fitted", staticmethod(of_fitted))
    rng = np.random.default_rng(1)
    y = {r: rng.normal(5.0, 2.0, 4) for r in ("r1", "r2", "r3")}
    a = {r: y[r] + rng.normal(0, 0.5, 4) for r in y}  # family A: unbiased, noisy
    b = {r: 0.8 * y[r] + rng.normal(0, 0.2, 4) for r in y}  # family B: too small, quieter
    inner = lambda p: {"r3": {"r1": {"r1": p["r1"]}, "r2": {"r2": p["r2"]}},  # noqa: E731
                       DEPLOY_FOLD: {g: {g: p[g]} for g in ("r1", "r2", "r3")}}
    tasks = [_task("A", inner(a), {"r3": {"r3": a["r3"] + 0.1}}, ["r1", "r2", "r3"], y),
             _task("B", inner(b), {"r3": {"r3": b["r3"] - 0.1}}, ["r1", "r2", "r3"], y, sensors=("T2",)),
             _task("ensemble", inner(a), {"r3": {"r3": a["r3"]}}, ["r1", "r2", "r3"], y),  # never stacked
             _task("C", inner(b), {"r3": {"r3": b["r3"]}}, ["r1", "r2", "r3"], y)]  # not a candidate (below)
    (out,) = stack_task(tasks, never={("d", "C", "global")})
    assert out["family"] == STACK and out["models"] == {"global": "stacked"}
    # fold r3: weights on r1 and r2's out-of-run predictions
    P = np.column_stack([np.r_[a["r1"], a["r2"]], np.r_[b["r1"], b["r2"]]])
    w = _w(P, np.r_[y["r1"], y["r2"]])
    (row,) = out["results"].to_dict("records")
    held = w[0] * (a["r3"] + 0.1) + w[1] * (b["r3"] - 0.1)
    assert row["fold"] == "r3" and row["run_id"] == "r3" and row["family"] == STACK
    assert row["rmse_um"] == pytest.approx(np.sqrt(np.mean((y["r3"] - held) ** 2)), rel=1e-12)
    assert row["compensation_rate"] == pytest.approx(1 - np.max(np.abs(y["r3"] - held)) / 10.0, rel=1e-12)
    assert row["sensors"] == ("T1 T2" if w.min() > 0 else ("T1" if w[0] > 0 else "T2"))
    assert np.isnan(row["coverage_80"])  # a member's interval is not the stack's
    # its inner score on r1 of fold r3: weights from r2 alone
    inn = out["inner"].set_index(["fold", "inner_fold"])
    w2 = _w(np.column_stack([a["r2"], b["r2"]]), y["r2"])
    r1 = w2[0] * a["r1"] + w2[1] * b["r1"]
    assert inn.loc[("r3", "r1"), "rmse_um"] == pytest.approx(np.sqrt(np.mean((y["r1"] - r1) ** 2)), rel=1e-12)
    assert set(inn.index.get_level_values("fold")) == {"r3", DEPLOY_FOLD}
    # the deployed stack: the weights on every run's out-of-run predictions, members of weight above 0
    P3 = np.column_stack([np.r_[a["r1"], a["r2"], a["r3"]], np.r_[b["r1"], b["r2"], b["r3"]]])
    w3 = _w(P3, np.r_[y["r1"], y["r2"], y["r3"]])
    assert made["names"] == [n for n, wi in zip("AB", w3) if wi > 0]
    np.testing.assert_allclose(made["weights"], w3[w3 > 0], atol=1e-12)
    assert made["how"].startswith("nnls")


def test_a_fold_where_a_member_has_no_held_out_prediction_has_no_stack_score_at_all(any_kind):
    """A member whose fold fit failed: the stack is neither scored nor scored inside on that fold (a
    choice there would drop the fold from the held-out figures)."""
    rng = np.random.default_rng(3)
    y = {r: rng.normal(5.0, 2.0, 4) for r in ("r1", "r2", "r3")}
    inner = {"r3": {"r1": {"r1": y["r1"] + 0.1}, "r2": {"r2": y["r2"] - 0.1}}}
    tasks = [_task("A", inner, {"r3": {"r3": y["r3"]}}, ["r1", "r2", "r3"], y),
             _task("B", inner, {}, ["r1", "r2", "r3"], y)]  # B: no held-out prediction on fold r3
    (out,) = stack_task(tasks, never=set())
    assert out["results"].empty and out["inner"].empty and out["models"] == {}


def test_one_candidate_family_is_no_stack(any_kind):
    rng = np.random.default_rng(2)
    y = {r: rng.normal(size=4) for r in ("r1", "r2")}
    p = {DEPLOY_FOLD: {r: {r: y[r]} for r in y}}
    assert stack_task([_task("A", p, {}, ["r1", "r2"], y), _task("ensemble", p, {}, ["r1", "r2"], y)], never=set()) == []


def test_the_benchmark_scores_the_stack_and_its_deployed_model_exports_at_parity(lathe, tmp_path):  # noqa: F811
    """Three days held out once each: the stack's rows beside its members', its inner scores in the
    choice, its deployed model an ENSEMBLE of the members of weight above 0 that the C runtime answers
    as Python does (the lathe's 120 s log filled in for the replay)."""
    import json

    import yaml

    from tests.test_benchmark import _cfg
    from thermbench import bench as bm
    from thermbench.config import load_config
    from thermbench.export.job import run_export
    from thermbench.models.ensemble import StackedEnsemble

    cfg = _cfg(tmp_path, f"datasets=[{lathe}]", "families=[ridge_history,thermal_lag,linear_history,baseline_ridge]",
               "bank_families=[]", "approaches=[global]")  # fmt: skip
    bm.benchmark(cfg)
    res = pd.read_csv(tmp_path / "reports" / "results.csv")
    st = res[(res["family"] == STACK) & (res["kind"] == "validation")]
    assert sorted(st["test"]) == ["Day_1", "Day_2", "Day_3"] and np.isfinite(st["rmse_um"]).all()
    assert set(res["family"]) >= {STACK, "ridge_history", "thermal_lag", "linear_history"}
    man = yaml.safe_load((tmp_path / "models" / "manifest.yaml").read_text())
    key = next(k for k in man if f"__{STACK}__" in k)
    import joblib

    model = joblib.load(tmp_path / "models" / man[key]["file"])
    assert isinstance(model, StackedEnsemble) and 1 <= len(model.members_) <= 3
    assert np.all(np.asarray(model.weights_) > 0) and sum(model.weights_) == pytest.approx(1.0)
    assert set(model.member_names_) <= {"ridge_history", "thermal_lag", "linear_history"}
    e = load_config("export", [f"export.source={tmp_path / 'models'}", f"export.select=[{key}]",
                               f"export.out_dir={tmp_path / 'x'}", "export.n_jobs=1", "export.onnx=false",
                               f"tracking.uri=sqlite:///{tmp_path}/other.db", f"tracking.artifact_root={tmp_path}/oa"])  # fmt: skip
    run_export(e)
    m = json.loads((tmp_path / "x" / key / "manifest.json").read_text())
    assert m["kind"] == "ENSEMBLE" and m["files"]["model"]["dims"][0] == len(model.members_)
    assert m["parity"]["model"]["max_abs_diff_um"] < 1e-9 and m["parity"]["model"]["float_max_abs_diff_um"] < 0.01
