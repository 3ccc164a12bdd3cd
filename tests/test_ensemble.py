"""The stacked ensemble (thermbench/models/ensemble.py) and its C kind ENSEMBLE.

Checked against what is known independently: the weights against a target built as a known
non-negative mix; the fitted weights against non-negative least squares on out-of-run predictions
made here by a plain loop over the runs (not scikit-learn's cross_val_predict, which the family uses);
the C runtime (each member run by its own kind, then summed) against Python at every reading in both
precisions and on the emulated Cortex-M4F."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import nnls
from sklearn.base import clone

from tests.test_linear_history import SENSORS, SPECS, _runs
from tests.test_lumped import spindle_dataset
from thermbench.bench.metrics import evaluate
from thermbench.models.base import ModelError, readings
from thermbench.models.ensemble import StackedEnsemble, stack_weights
from thermbench.models.linear_history import LinearHistory
from thermbench.models.thermal_lag import ThermalLag

TRAIN = ["r0", "r1", "r2", "r3"]


def test_stack_weights_recover_a_known_mix_and_fall_back_to_the_mean():
    rng = np.random.default_rng(0)
    a, b, c = rng.standard_normal((3, 200))
    w, how = stack_weights(np.column_stack([a, b, c]), 0.3 * a + 0.7 * b)
    np.testing.assert_allclose(w, [0.3, 0.7, 0.0], atol=1e-12)
    assert how == "nnls"
    # a mix whose least-squares weights sum to 0.8 (0.4 and 0.4): scaled to a weighted average, 0.5 and 0.5
    w, how = stack_weights(np.column_stack([a, b, c]), 0.4 * a + 0.4 * b)
    np.testing.assert_allclose(w, [0.5, 0.5, 0.0], atol=1e-12)
    w, how = stack_weights(np.column_stack([a, b]), -a - b)  # no non-negative mix helps: the plain mean
    assert list(w) == [0.5, 0.5] and how.startswith("mean")


@pytest.fixture(scope="module")
def planted():
    return spindle_dataset(_runs(SPECS), sensors=SENSORS, operating=["spindle_rpm"])


def _members():
    return [LinearHistory(delays_s=[[0.0]], operating=["spindle_rpm"]), ThermalLag(max_inputs=2),
            LinearHistory(delays_s=[[0.0, 900.0, 1800.0, 3600.0]])]  # fmt: skip


def test_the_weights_are_non_negative_least_squares_on_out_of_run_predictions(planted):
    m = StackedEnsemble(members=_members()).fit(planted, TRAIN)
    # by hand: each training run predicted by every member fitted on the other three
    rd = readings(planted, TRAIN)
    P = np.zeros((len(rd), 3))
    for run in TRAIN:
        rows = (rd["run_id"] == run).to_numpy()
        for i, member in enumerate(_members()):
            fitted = member.fit(planted, [r for r in TRAIN if r != run])
            P[rows, i] = fitted.predict_at(planted, run, rd.loc[rows, "t_s"].to_numpy(), rd.loc[rows, "target_mm"].to_numpy())
    w, _ = nnls(P, rd["error_um"].to_numpy())
    np.testing.assert_allclose(m.weights_, w / w.sum(), rtol=1e-6, atol=1e-9)  # a weighted average of the members
    assert m.stacking_ == "nnls" and m.member_names_ == [  # each named by what it sets away from its defaults
        "LinearHistory(delays_s=[[0]], operating=['spindle_rpm'])", "ThermalLag(max_inputs=2)",
        "LinearHistory(delays_s=[[0, 900, 1800, 3600]])"]  # fmt: skip
    # the planted error needs the rise 30 min earlier: the member that has it carries the weight, and the
    # ensemble holds up on the held-out run as that member does, far better than the rises now alone
    assert m.weights_[2] > 0.9
    rmse = {k: evaluate(x, planted, ["r4"])["rmse_um"].iloc[0] for k, x in
            (("ensemble", m), ("now", m.members_[0]), ("delays", m.members_[2]))}  # fmt: skip
    assert rmse["ensemble"] < 1.1 * rmse["delays"] < rmse["now"] / 5, rmse
    assert m.fit_summary().startswith("weights LinearHistory(delays_s=[[0]], operating=['spindle_rpm']) 0.000, ThermalLag(")


def test_the_plain_mean_on_one_run_or_when_asked(planted):
    one = StackedEnsemble(members=_members()[:2]).fit(planted, ["r0"])
    assert list(one.weights_) == [0.5, 0.5] and one.stacking_ == "mean (one training run: no run to hold out)"
    asked = StackedEnsemble(members=_members()[:2], stacking="mean").fit(planted, TRAIN)
    assert list(asked.weights_) == [0.5, 0.5]
    t = np.linspace(0, 20000, 50)
    x = np.zeros_like(t)
    both = [mm.predict_at(planted, "r4", t, x) for mm in asked.members_]
    np.testing.assert_allclose(asked.predict_at(planted, "r4", t, x), 0.5 * both[0] + 0.5 * both[1], atol=1e-12)


def test_it_is_a_scikit_learn_estimator_and_names_a_bad_member(planted):
    m = StackedEnsemble(members=_members(), stacking="mean")
    assert clone(m).get_params()["stacking"] == "mean" and len(clone(m).get_params()["members"]) == 3
    with pytest.raises(ModelError, match=r"StackedEnsemble.members"):
        StackedEnsemble(members=["linear_history"]).fit(planted, TRAIN)
    with pytest.raises(ModelError, match=r"StackedEnsemble.stacking"):
        StackedEnsemble(members=_members(), stacking="median").fit(planted, TRAIN)


@pytest.fixture(scope="module")
def ensemble_export(planted, tmp_path_factory):
    from thermbench.export import export_model

    # the plain mean: every member in the file (the least squares give one of these members weight 0, and
    # a member of weight 0 is left out of it: test_a_member_of_weight_zero_is_left_out_of_the_file...)
    m = StackedEnsemble(members=_members(), stacking="mean").fit(planted, TRAIN)
    out = tmp_path_factory.mktemp("ensemble") / "en"
    man = export_model(m, out, "en", ds=planted, heldout=["r4"])
    return m, out, man


def test_the_c_runtime_kind_reproduces_python_in_both_precisions(planted, ensemble_export):
    """ENSEMBLE (embedded/src/tb_kind_ensemble.c): the members' files inside one, each run by its own kind
    (LINEAR_HISTORY, THERMAL_LAG), the weighted sum; double to 1e-9 µm, float within 0.01 µm at every reading."""
    m, _, man = ensemble_export
    p = man["parity"]["model"]
    # dims: three members, of the kinds THERMAL_LAG (10) and LINEAR_HISTORY (12)
    assert man["kind"] == "ENSEMBLE" and man["files"]["model"]["dims"] == [3, 2**10 + 2**12] and p["n_readings"] > 1000
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01
    assert p["heldout_rmse_um_c"] == pytest.approx(evaluate(m, planted, ["r4"])["rmse_um"].iloc[0], abs=1e-9)
    assert man["operating"] == ["spindle_rpm"] and man["temperatures"] == ["T_a", "T_b", "T_c"]


def test_a_member_of_weight_zero_is_left_out_of_the_file_and_the_sum_is_the_same(planted, ensemble_export, tmp_path):
    """A member the stack gives weight 0 adds nothing: the file carries the others (its state would
    cost the M4F's RAM) and answers as the Python model, which sums every member, at every reading."""
    import copy

    from thermbench.export import export_model

    m, _, full = ensemble_export
    zeroed = copy.deepcopy(m)
    w = np.asarray(m.weights_, dtype=float).copy()
    w[1] = 0.0
    zeroed.weights_ = w / w.sum()
    man = export_model(zeroed, tmp_path / "z", "en", ds=planted, heldout=["r4"])
    p = man["parity"]["model"]
    assert man["files"]["model"]["dims"][0] == 2 and full["files"]["model"]["dims"][0] == 3
    assert man["files"]["model"]["bytes"] < full["files"]["model"]["bytes"]
    assert p["max_abs_diff_um"] < 1e-9 and p["float_max_abs_diff_um"] < 0.01
    assert p["heldout_rmse_um_c"] == pytest.approx(evaluate(zeroed, planted, ["r4"])["rmse_um"].iloc[0], abs=1e-9)


@pytest.mark.target
@pytest.mark.parametrize("precision", ["double", "float"])
def test_the_ensemble_kind_runs_on_the_target(planted, ensemble_export, precision):
    from tests.test_target import _host_and_target_agree

    _, out, _ = ensemble_export
    _host_and_target_agree(planted, out, "r4", precision, min_readings=1000)


@pytest.mark.target
def test_an_ensemble_export_for_the_cortex_m4f_is_within_its_budget(planted, ensemble_export, tmp_path):
    from thermbench.export import ExportOptions, export_model

    m, _, _ = ensemble_export
    man = export_model(m, tmp_path / "m4", "en", ds=planted, heldout=["r4"],
                       options=ExportOptions(target="cortex-m4f", onnx=False))  # fmt: skip
    assert man["footprint"]["within_budget"] and man["parity"]["model"]["max_abs_diff_um"] <= 0.01


def test_two_members_alike_are_told_apart_by_number(planted):
    m = StackedEnsemble(members=[LinearHistory(delays_s=[[0.0]]), LinearHistory(delays_s=[[0.0]]), LinearHistory()])
    m.fit(planted, TRAIN[:2])
    assert m.member_names_ == ["LinearHistory(delays_s=[[0]])", "LinearHistory(delays_s=[[0]])#2", "LinearHistory"]
    assert m.fit_summary().startswith("weights LinearHistory(delays_s=[[0]]) ")


def test_a_member_the_runtime_cannot_run_is_refused_with_its_reason(planted):
    from thermbench.export.encoding import ExportError, encode
    from thermbench.models.gp import GaussianProcessLag

    m = StackedEnsemble(members=[LinearHistory(delays_s=[[0.0]]), GaussianProcessLag(max_samples=100)]).fit(planted, TRAIN)
    with pytest.raises(ExportError, match=r"^model: member GaussianProcessLag\(max_samples=100\): the C runtime has no Gaussian-process kind"):
        encode(m)


def test_the_loader_refuses_a_header_that_misnames_the_kinds_inside_or_a_nested_ensemble(ensemble_export, tmp_path):
    import ctypes

    from numpy.polynomial import Polynomial

    from thermbench.export import fileformat, native
    from thermbench.export.encoding import geometric_block
    from thermbench.export.fileformat import Kind

    _, out, _ = ensemble_export
    mf = fileformat.read(out / "model.tbm")
    lib = native.library()

    def rc_of(dims, payload) -> int:
        path = tmp_path / "x.tbm"
        fileformat.write(path, Kind.ENSEMBLE, dims, payload)
        data = path.read_bytes()
        buf = (ctypes.c_uint8 * len(data)).from_buffer_copy(data)
        return lib.tb_model_open(ctypes.byref(native.tb_model()), buf, len(data))

    payload = [float(v) for v in mf.payload]
    assert rc_of(list(mf.dims), payload) == native.TB_OK
    assert rc_of([3, 2**12], payload) == native.TB_E_DIMS  # THERMAL_LAG (10) is inside but not named
    first = 1 + len(geometric_block(Polynomial([0.0]), "")) + 2 * 3  # period, geometric block, 3 weights as pairs
    assert payload[first] == float(Kind.LINEAR_HISTORY)  # the first member's record starts with its kind
    nested = payload.copy()
    nested[first] = float(Kind.ENSEMBLE)
    assert rc_of([3, 2**10 + 2**12 + 2**13], nested) == native.TB_E_PAYLOAD


def test_the_default_ensemble_of_conf_fits_the_cortex_m4f_arena_with_sixteen_sensors(tmp_path):
    """conf/model/ensemble.yaml's four linear-with-history members, each with its own delay line or lags,
    on 16 sensors (fl_thermal's count) with an hour of history: the single-precision state arena stays
    within the Cortex-M4F budget of 16 KB (seed 002's compensator), so the export for that target is not
    refused."""
    from hydra.utils import instantiate
    from omegaconf import OmegaConf

    from thermbench.export import ExportOptions, export_model
    from thermbench.export.budget import BUDGET
    from tests.test_linear_history import _runs as lh_runs

    rng = np.random.default_rng(3)
    runs = lh_runs(SPECS[:3])
    names = {f"T{k:02d}": "structure" for k in range(16)}
    for r in runs.values():
        base = [r["T_a_C"], r["T_b_C"], r["T_c_C"]]
        for k in range(16):
            r[f"T{k:02d}_C"] = base[k % 3] + 0.1 * k + 0.01 * rng.standard_normal(r["t_s"].size)
        for s in ("T_a_C", "T_b_C", "T_c_C"):
            del r[s]
    ds = spindle_dataset(runs, sensors=names, operating=[])
    m = instantiate(OmegaConf.load("conf/model/ensemble.yaml"))
    for member in m.members:  # the worst case the config allows: each member's longest history chosen
        if isinstance(member, LinearHistory):
            member.set_params(delays_s=[max(member.delays_s, key=max)])
    m.fit(ds, ["r0", "r1", "r2"])
    longest = [max(mm.delays_s_) for mm in m.members_ if hasattr(mm, "delays_s_")]
    assert len(m.members_) == 4 and longest == [1800.0, 3600.0, 3600.0]
    man = export_model(m, tmp_path / "m4", "en", ds=ds,
                       options=ExportOptions(target="cortex-m4f", verify=False, onnx=False))  # fmt: skip
    assert man["temperatures"] == list(names) and man["target"]["footprint"]["arena_bytes"] <= BUDGET["ram_bytes"]
