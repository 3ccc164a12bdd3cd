"""The lumped thermal network for a spindle (``physics_spindle``): identification checked
against responses computed here independently of the model's code (closed forms and
``scipy.integrate.solve_ivp`` of the documented ODE), the lead-in (history) case, the
scikit-learn conventions and one-line errors for bad parameters."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hydra.utils import instantiate
from omegaconf import OmegaConf
from scipy.integrate import solve_ivp
from sklearn.base import clone

from tests.synth import make_dataset
from thermbench.config import config_dir
from thermbench.data.dataset import Dataset
from thermbench.data.schema import Metadata
from thermbench.data.views import channel_view
from thermbench.models.base import ModelError
from thermbench.models.lumped import LumpedThermalNetwork

LOG_S = 15.0  # process log period, as the real spindle test
U_REF = 6000.0  # rpm
TRUTH2 = dict(tau_s=(900.0, 7200.0), gains_um=(-8.0, 25.0), exponent=1.5, offset_um=2.0)


def spindle_dataset(runs: dict[str, dict], sensors: dict[str, str] | None = None, operating=None) -> Dataset:
    """A format 2 spindle test (parts [spindle], one fixed-point channel Z) seen through
    its channel view. ``runs[id]`` = {"t_s", "spindle_rpm", "read_t_s", "error_um"} and
    optional ``<sensor>_C`` columns of the process log."""
    sensors = sensors or {"T_amb": "ambient"}
    procs, errs = [], []
    for run, r in runs.items():
        p = {"run_id": run, "t_s": r["t_s"], "spindle_rpm": r["spindle_rpm"]}
        for s in sensors:
            p[f"{s}_C"] = r.get(f"{s}_C", np.full(len(r["t_s"]), 20.0))
        procs.append(pd.DataFrame(p))
        errs.append(pd.DataFrame({"run_id": run, "t_s": r["read_t_s"], "channel": "Z", "error_um": r["error_um"]}))
    meta = {
        "format": "thermbench-dataset/2",
        "machine": {"name": "synthetic_spindle"},
        "parts": ["spindle"],
        "sensors": sensors,
        "channels": {"Z": {"kind": "fixed_point", "direction": "Z", "location": "test_mandrel"}},
        "reference": {"mode": "first_reading"},
        "runs": {run: {} for run in runs},
    }
    if operating is not None:
        meta["operating"] = operating
    ds = Dataset(Metadata.model_validate(meta), pd.concat(procs, ignore_index=True), pd.concat(errs, ignore_index=True))
    return channel_view(ds, "Z")


def profile(levels_rpm, block_s):
    """Piecewise-constant speed: (switching times, levels); level k holds over [k·block, (k+1)·block)."""
    levels = np.asarray(levels_rpm, dtype=float)
    return block_s * np.arange(levels.size), levels


def chain_by_ode(switch_s, levels_rpm, t_eval, tau_s, exponent, u_ref=U_REF):
    """The documented ODE dθ1/dt = (q − θ1)/τ1, dθi/dt = (θ_{i−1} − θi)/τi, q = (u/u_ref)^p,
    integrated by solve_ivp piece by piece (q constant between switches), from rest."""
    tau = np.asarray(tau_s, dtype=float)
    edges = np.r_[switch_s, np.inf]
    out = np.zeros((t_eval.size, tau.size))
    x = np.zeros(tau.size)
    for k, level in enumerate(levels_rpm):
        q = (level / u_ref) ** exponent
        t0, t1 = edges[k], min(edges[k + 1], t_eval.max())
        if t1 <= t0:
            break

        def rhs(_, th):
            up = np.r_[q, th[:-1]]
            return (up - th) / tau

        sol = solve_ivp(rhs, (t0, t1), x, method="LSODA", rtol=1e-10, atol=1e-12, dense_output=True)
        inside = (t_eval >= t0) & (t_eval <= t1)
        out[inside] = sol.sol(t_eval[inside]).T
        x = sol.y[:, -1]
    return out


def two_node_run(levels, block_s, noise_um=0.0, seed=0, first_read_s=0.0, read_s=60.0):
    switch, lv = profile(levels, block_s)
    end = switch[-1] + block_s
    t = np.arange(0.0, end + LOG_S / 2, LOG_S)
    rpm = lv[np.minimum((t // block_s).astype(int), lv.size - 1)]
    rt = np.arange(first_read_s + 7.0, end, read_s)  # readings off the simulation grid
    th = chain_by_ode(switch, lv, rt, TRUTH2["tau_s"], TRUTH2["exponent"])
    err = th @ np.asarray(TRUTH2["gains_um"]) + TRUTH2["offset_um"]
    noisy = err + noise_um * np.random.default_rng(seed).standard_normal(rt.size)
    return {"t_s": t, "spindle_rpm": rpm, "read_t_s": rt, "error_um": noisy, "truth_um": err}


# ---------------------------------------------------------------- recovery ---
def test_single_node_step_recovers_tau_and_gain():
    """One node, a speed step at 600 s: E = d + c·(1 − exp(−(t − 600)/τ)), written out here."""
    tau, c, d, t_on = 2400.0, 20.0, 1.5, 600.0
    t = np.arange(0.0, 6 * 3600.0 + 1.0, LOG_S)
    rpm = np.where(t >= t_on, 4000.0, 0.0)
    rt = np.arange(37.0, t[-1], 45.0)
    err = d + c * (1.0 - np.exp(-np.clip(rt - t_on, 0.0, None) / tau))
    ds = spindle_dataset({"r": {"t_s": t, "spindle_rpm": rpm, "read_t_s": rt, "error_um": err}})
    m = LumpedThermalNetwork(n_nodes=1, exponent=1.0).fit(ds)
    assert m.u_ref_ == 4000.0 and m.operating_ == "spindle_rpm"  # the dataset's operating input, its max
    assert m.tau_s_[0] == pytest.approx(tau, rel=0.02)
    assert m.gains_um_[0] == pytest.approx(c, rel=0.02)  # q = 1 at u = u_ref
    # scored and fitted on the drift from the run's first reading (reference first_reading): the
    # gauge's zero d is the first reading's, so no offset is left to fit
    assert m.offset_um_ == pytest.approx(0.0, abs=0.05)
    assert m.rmse_um_ < 0.02
    np.testing.assert_allclose(m.predict(ds, "r"), err - err[0], atol=0.05)
    np.testing.assert_array_equal(m.geometric_um([0.0]), [0.0])  # fixed point: the offset is thermal


@pytest.fixture(scope="module")
def two_node_data():
    noise = 0.3
    runs = {
        "a": two_node_run([6000, 6000, 3000, 0, 0, 4500, 1500, 0], 3600.0, noise, seed=1),
        "b": two_node_run([2000, 5000, 5000, 0, 3000, 3000, 0, 0], 2700.0, noise, seed=2),
        "held": two_node_run([4000, 1000, 6000, 0, 0, 2500, 2500, 5000, 0], 3000.0, noise, seed=3),
    }
    return spindle_dataset(runs), runs, noise


def test_two_nodes_predict_a_held_out_speed_profile(two_node_data):
    ds, runs, noise = two_node_data
    m = LumpedThermalNetwork(u_ref=U_REF).fit(ds, ["a", "b"])
    assert m.fit_s_ < 5.0
    np.testing.assert_allclose(m.tau_s_, TRUTH2["tau_s"], rtol=0.1)
    np.testing.assert_allclose(m.gains_um_, TRUTH2["gains_um"], rtol=0.1)
    assert m.exponent_ == pytest.approx(TRUTH2["exponent"], abs=0.1)
    assert m.rmse_um_ < 1.1 * noise
    held = runs["held"]
    pred = m.predict(ds, "held")
    # the drift from the held-out run's first reading (reference first_reading): that reading's
    # noise is in every drift of the run, so the truth is counted from it too
    drift = held["error_um"] - held["error_um"][0]
    np.testing.assert_allclose(ds.errors_run("held")["error_um"], drift, atol=1e-12)
    n0 = abs(held["error_um"][0] - held["truth_um"][0])  # the first reading's noise: in every drift, unpredictable
    assert np.sqrt(np.mean((pred - drift) ** 2)) < 1.5 * noise + n0
    assert np.sqrt(np.mean((pred - (held["truth_um"] - held["truth_um"][0])) ** 2)) < 0.5 * noise + n0
    # predict is geometric + thermal, and the compensation table interpolates it
    np.testing.assert_allclose(pred, m.predict_thermal_at(ds, "held", held["read_t_s"], 0.0))
    tab = m.compensation_table(ds, "held", step_s=60.0)
    assert tab.error_um.shape == (tab.t_s.size, 1)


def test_lead_in_history_is_simulated_and_only_readings_fitted():
    """A long history (12 h of speed steps) before the first reading: the network runs
    through it from rest and the parameters come out as if the whole run were read."""
    full = two_node_run([6000, 0, 3000, 5000, 0, 2000, 6000, 1000, 0, 4000, 0, 0], 3600.0)
    lead_s = 6 * 3600.0 + 1265.0
    keep = full["read_t_s"] >= lead_s
    late = {**full, "read_t_s": full["read_t_s"][keep], "error_um": full["error_um"][keep]}
    ds = spindle_dataset({"late": late})
    assert ds.errors_run("late")["t_s"].iloc[0] > lead_s and ds.process_run("late")["t_s"].iloc[0] == 0.0
    m = LumpedThermalNetwork(u_ref=U_REF).fit(ds)
    np.testing.assert_allclose(m.tau_s_, TRUTH2["tau_s"], rtol=0.02)
    np.testing.assert_allclose(m.gains_um_, TRUTH2["gains_um"], rtol=0.02)
    assert m.exponent_ == pytest.approx(TRUTH2["exponent"], abs=0.02)
    # fitted on the drift from the first (warm) reading: the offset is minus the network's state
    # there, which the history gives (not the cold start's 0)
    assert m.offset_um_ == pytest.approx(TRUTH2["offset_um"] - late["error_um"][0], abs=0.05)
    np.testing.assert_allclose(m.predict(ds, "late"), late["error_um"] - late["error_um"][0], atol=0.02)
    # the warm state at the first reading is the history's: not the cold start
    assert abs(late["error_um"][0] - TRUTH2["offset_um"]) > 1.0


def test_measured_ambient_drive_is_identified():
    """A slow ambient swing through its own lag τ_a adds c_a·θ_a; closed form for a ramp
    rise r(t) = β t: θ_a = β (t − τ_a (1 − exp(−t/τ_a)))."""
    tau, c, tau_a, c_a, beta = 1800.0, 12.0, 5400.0, 3.0, 1.0 / 3600.0  # 1 °C per hour
    t = np.arange(0.0, 8 * 3600.0 + 1.0, LOG_S)
    rpm = np.where((t >= 3600) & (t < 4 * 3600), 5000.0, 0.0)
    rt = np.arange(22.0, t[-1], 60.0)
    on = np.clip(rt - 3600.0, 0.0, None)
    off = np.clip(rt - 4 * 3600.0, 0.0, None)
    theta = (1 - np.exp(-on / tau)) - (1 - np.exp(-off / tau))
    theta_a = beta * (rt - tau_a * (1 - np.exp(-rt / tau_a)))
    err = c * theta + c_a * theta_a
    ds = spindle_dataset({"r": {"t_s": t, "spindle_rpm": rpm, "read_t_s": rt, "error_um": err, "T_amb_C": 21.0 + beta * t}})
    m = LumpedThermalNetwork(n_nodes=1, exponent=1.0, ambient_sensor="auto", preprocess=None).fit(ds)
    assert m.ambient_sensor_ == "T_amb"
    assert m.tau_s_[0] == pytest.approx(tau, rel=0.02) and m.gains_um_[0] == pytest.approx(c, rel=0.02)
    assert m.ambient_tau_s_ == pytest.approx(tau_a, rel=0.02)
    assert m.ambient_gain_um_per_C_ == pytest.approx(c_a, rel=0.02)
    inp = m.required_inputs()
    assert inp.sensors == ("T_amb",) and inp.ambient and inp.operating == ("spindle_rpm",) and not inp.motion


def test_along_axis_dataset_thermal_part_is_uniform():
    """On an axis (format 1, feed as operating input) the thermal part is one drift for
    every target, and the geometric polynomial is fitted with it."""
    tau, c = 1200.0, 6.0
    t = np.arange(0.0, 3 * 3600.0 + 1.0, 1.0)
    feed = np.where(t < 7200, 6000.0, 0.0)
    proc = pd.DataFrame({"run_id": "r", "t_s": t, "axis_mm": 250.0, "feed_mm_min": feed, "T_amb_C": 20.0})
    targets = np.arange(0.0, 501.0, 100.0)
    rt = np.repeat(np.arange(0.0, t[-1] - 60, 300.0), targets.size) + np.tile(np.arange(targets.size) * 4.0, 36)
    rx = np.tile(targets, 36)
    theta = (1 - np.exp(-rt / tau)) - (1 - np.exp(-np.clip(rt - 7200, 0, None) / tau))
    geo = 1e-5 * (rx - 250.0) ** 2 - 0.004 * rx
    err = c * theta + geo
    ds = make_dataset(proc, pd.DataFrame({"run_id": "r", "t_s": rt, "target_mm": rx, "error_um": err}), {"T_amb": "ambient"})
    m = LumpedThermalNetwork(n_nodes=1, exponent=1.0, geometric_degree=2).fit(ds)
    assert m.operating_ == "feed_mm_min" and m.required_inputs().motion
    assert m.tau_s_[0] == pytest.approx(tau, rel=0.02) and m.gains_um_[0] == pytest.approx(c, rel=0.02)
    pred = m.predict(ds, "r")
    np.testing.assert_allclose(pred, err, atol=0.05)
    np.testing.assert_allclose(pred, m.geometric_um(rx) + m.predict_thermal_at(ds, "r", rt, rx))
    a, b = m.predict_thermal_at(ds, "r", [5000.0, 5000.0], [0.0, 500.0])
    assert a == b


# ------------------------------------------------------------- conventions ---
def test_clone_get_params_and_hydra():
    m = LumpedThermalNetwork(n_nodes=3, operating="spindle_rpm", u_ref=5000.0, exponent=2, step_s=30.0, n_starts=2)
    assert vars(m) == m.get_params()  # the constructor stores the parameters and nothing else
    c = clone(m)
    assert c.get_params() == m.get_params() and not hasattr(c, "tau_s_")
    built = instantiate(OmegaConf.load(config_dir() / "model" / "physics_spindle.yaml"))
    assert type(built) is LumpedThermalNetwork
    assert built.get_params() == {**LumpedThermalNetwork().get_params(), "exponent_bounds": [0.5, 2.5],
                                  "tau_bounds_s": [60.0, 2.0e5]}  # fmt: skip


def test_fit_is_deterministic(two_node_data):
    ds, _, _ = two_node_data
    a = LumpedThermalNetwork(u_ref=U_REF, n_starts=1).fit(ds, ["a"])
    b = LumpedThermalNetwork(u_ref=U_REF, n_starts=1).fit(ds, ["a"])
    np.testing.assert_array_equal(a.tau_s_, b.tau_s_)
    np.testing.assert_array_equal(a.gains_um_, b.gains_um_)


@pytest.fixture(scope="module")
def small():
    t = np.arange(0.0, 7200.0, LOG_S)
    rpm = np.where(t >= 600, 3000.0, 0.0)
    rt = t[::4]
    return {"t_s": t, "spindle_rpm": rpm, "read_t_s": rt, "error_um": 5 * (1 - np.exp(-np.clip(rt - 600, 0, None) / 900))}


@pytest.mark.parametrize(
    "params, match",
    [
        (dict(n_nodes=0), r"^LumpedThermalNetwork\.n_nodes: expected an integer 1\.\.6 or a non-empty list of them, got 0$"),
        (dict(n_nodes=2.5), r"^LumpedThermalNetwork\.n_nodes: expected an integer"),
        (dict(n_nodes=True), r"^LumpedThermalNetwork\.n_nodes: expected an integer 1\.\.6 .*, got True$"),
        (dict(n_nodes=[2, 7]), r"^LumpedThermalNetwork\.n_nodes: expected .*, got \[2, 7\]$"),
        (dict(step_s=0.0), r"^LumpedThermalNetwork\.step_s: expected a finite number > 0, got 0\.0$"),
        (dict(step_s=-60), r"^LumpedThermalNetwork\.step_s: expected a finite number > 0, got -60$"),
        (dict(step_s=float("nan")), r"^LumpedThermalNetwork\.step_s: expected a finite number > 0, got nan$"),
        (dict(step_s="60"), r"^LumpedThermalNetwork\.step_s: expected a finite number > 0, got '60'$"),
        (dict(operating="coolant"), r"^operating: column 'coolant' is not in the process log of run 'r'; columns: \[.*'spindle_rpm'"),
        (dict(operating=["a", "b"]), r"^LumpedThermalNetwork\.operating: expected one process column name"),
        (dict(u_ref=-1.0), r"^LumpedThermalNetwork\.u_ref: expected None or a finite number > 0, got -1\.0$"),
        (dict(exponent=0), r"^LumpedThermalNetwork\.exponent: expected None or a finite number > 0, got 0$"),
        (dict(exponent_bounds=(2.0, 1.0)), r"^LumpedThermalNetwork\.exponent_bounds: expected None or a pair \(low, high\) of finite numbers with 0 < low < high, got \(2\.0, 1\.0\)$"),
        (dict(exponent_bounds=None), r"^LumpedThermalNetwork\.exponent_bounds: expected \(lo, hi\) with 0 < lo < hi to identify the exponent \(exponent is None\), got None$"),
        (dict(tau_bounds_s=(0.0, 1e4)), r"^LumpedThermalNetwork\.tau_bounds_s: expected a pair \(low, high\) .*0 < low < high"),
        (dict(tau_bounds_s=60.0), r"^LumpedThermalNetwork\.tau_bounds_s: expected a pair \(low, high\)"),
        (dict(n_starts=0), r"^LumpedThermalNetwork\.n_starts: expected an integer >= 1, got 0$"),
        (dict(geometric_degree=-1), r"^LumpedThermalNetwork\.geometric_degree: expected an integer >= 0, got -1$"),
        (dict(sensors="T_amb"), r"^LumpedThermalNetwork\.sensors: expected None, 'all', 'auto' or a non-empty list of sensor names, got 'T_amb'$"),
        (dict(max_sensors=False), r"^LumpedThermalNetwork\.max_sensors: expected an integer >= 1, got False$"),
        (dict(ambient_sensor="T_room"), r"^ambient_sensor: 'T_room' is not a sensor of the dataset .*\['T_amb'\]"),
    ],
)
def test_bad_parameters_name_the_key(small, params, match):
    ds = spindle_dataset({"r": small})
    with pytest.raises(ModelError, match=match) as exc:
        LumpedThermalNetwork(**params).fit(ds)
    assert "\n" not in str(exc.value)


def test_bad_data_is_one_line(small):
    neg = {**small, "spindle_rpm": small["spindle_rpm"] - 100.0}  # a negative operating value
    with pytest.raises(ModelError, match=r"^operating: column 'spindle_rpm' of run 'r' is negative \(min -100\).*exponent"):
        LumpedThermalNetwork().fit(spindle_dataset({"r": neg}))
    LumpedThermalNetwork(n_nodes=1, exponent=2, n_starts=1).fit(spindle_dataset({"r": neg}))  # an integer power is fine
    # a fixed exponent needs no bounds for it
    LumpedThermalNetwork(n_nodes=1, exponent=2, exponent_bounds=None, n_starts=1).fit(spindle_dataset({"r": neg}))
    idle = {**small, "spindle_rpm": np.zeros_like(small["spindle_rpm"])}
    with pytest.raises(ModelError, match=r"^operating: column 'spindle_rpm' is zero in every training run"):
        LumpedThermalNetwork().fit(spindle_dataset({"r": idle}))
    none = spindle_dataset({"r": small}, operating=[])
    with pytest.raises(ModelError, match=r"^LumpedThermalNetwork needs an operating input \(metadata 'operating'"):
        LumpedThermalNetwork().fit(none)
    # its own 'operating' parameter stands in for the dataset's declaration
    assert np.isfinite(LumpedThermalNetwork(n_nodes=1, n_starts=1, operating="spindle_rpm").fit(none).rmse_um_)
    with pytest.raises(ModelError, match="not fitted"):
        LumpedThermalNetwork().predict(spindle_dataset({"r": small}), "r")


# ------------------------------------------------- measured boundary temperatures ---
def boundary_runs():
    """Two runs: one node (τ 1800 s, gain 12 µm) heated by the speed, plus 4 µm/K of the
    measured structure temperature T_col, which drifts on its own (a slow sine); T_dummy is a
    second sensor that drifts too but does not act. Written out here in closed form."""
    tau, c, k_col = 1800.0, 12.0, 4.0
    runs = {}
    for i, (start, phase) in enumerate(((3600.0, 0.0), (7200.0, 1.3))):
        t = np.arange(0.0, 10 * 3600.0 + 1.0, LOG_S)
        rpm = np.where((t >= start) & (t < start + 3 * 3600), 5000.0, 0.0)
        rt = np.arange(11.0, t[-1], 60.0)
        on, off = np.clip(rt - start, 0, None), np.clip(rt - start - 3 * 3600, 0, None)
        theta = (1 - np.exp(-on / tau)) - (1 - np.exp(-off / tau))
        col = 20.0 + 1.5 * np.sin(2 * np.pi * t / 30000.0 + phase)
        dummy = 21.0 + 0.8 * np.cos(2 * np.pi * t / 17000.0 + phase)
        col_r = np.interp(rt, t, col) - col[0]
        runs[f"r{i}"] = {"t_s": t, "spindle_rpm": rpm, "read_t_s": rt, "error_um": 1.0 + c * theta + k_col * col_r,
                         "T_col_C": col, "T_dummy_C": dummy}  # fmt: skip
    return spindle_dataset(runs, sensors={"T_col": "structure", "T_dummy": "structure"}), (tau, c, k_col)


def test_boundary_temperatures_get_their_own_gains():
    ds, (tau, c, k_col) = boundary_runs()
    m = LumpedThermalNetwork(n_nodes=1, exponent=1.0, sensors=["T_col"], preprocess=None).fit(ds)
    assert m.sensors_ == ["T_col"]
    assert m.sensor_gains_um_per_C_[0] == pytest.approx(k_col, rel=0.01)
    assert m.tau_s_[0] == pytest.approx(tau, rel=0.02) and m.gains_um_[0] == pytest.approx(c, rel=0.02)
    np.testing.assert_allclose(m.predict(ds, "r1"), ds.errors_run("r1")["error_um"], atol=0.05)
    assert m.required_inputs().sensors == ("T_col",)
    with pytest.raises(ModelError, match=r"sensors: \['T_x'\] are not sensors of the dataset"):
        LumpedThermalNetwork(sensors=["T_x"]).fit(ds)


def test_auto_picks_the_sensor_that_acts_by_leave_one_run_out():
    ds, (_, _, k_col) = boundary_runs()
    m = LumpedThermalNetwork(n_nodes=1, exponent=1.0, sensors="auto", preprocess=None).fit(ds)
    assert m.sensors_ == ["T_col"]  # T_dummy does not lower the held-out error by 3 %
    assert [s for s, _ in m.sensor_selection_] == ["(operating input only)", "T_col"]
    # scored with the speed-only time constants, then identified again with the sensor
    assert m.sensor_selection_[1][1] < 0.5 * m.sensor_selection_[0][1]
    assert m.sensor_gains_um_per_C_[0] == pytest.approx(k_col, rel=0.01)


def test_node_count_chosen_by_leave_one_run_out(two_node_data):
    """Data of a two-node chain (solve_ivp): one node cannot follow it, two can; the held-out
    run picks two (three nodes contain two, so a held-out score cannot reject them reliably)."""
    ds, _, noise = two_node_data
    m = LumpedThermalNetwork(n_nodes=[1, 2], preprocess=None).fit(ds, ["a", "b"])
    scores = dict(m.node_selection_)
    assert m.n_nodes_ == 2 and set(scores) == {1, 2}
    assert scores[2] < 0.5 * scores[1]
    with pytest.raises(ModelError, match=r"n_nodes: expected an integer 1..6 or a non-empty list of them, got \[\]"):
        LumpedThermalNetwork(n_nodes=[]).fit(ds, ["a", "b"])
