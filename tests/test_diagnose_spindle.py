"""The discrepancy workflow on a spindle test.

The data are hand-made (:mod:`thermbench.discrepancy.hidden_spindle`): the truth is written as ODEs and
integrated by ``solve_ivp``, independently of the network's discretisation; each hidden term's
parameters are drawn at random from wide ranges (never the search's start grids) and its strength is
set by what the base network cannot absorb (4x and 8x the gauge noise). A clean negative control
must give ``none``, physics outside the library (a coolant cycle no sensor sees) never ``none``."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from thermbench.cli import main
from thermbench.discrepancy import hidden_spindle as hs
from thermbench.discrepancy.search import Settings
from thermbench.discrepancy.spindle import spindle_family
from thermbench.discrepancy.workflow import run_diagnosis
from thermbench.models.base import ModelError, readings
from thermbench.models.lumped import LumpedThermalNetwork
from thermbench.bench.splits import dataset_view

WORLD = hs.SpindleWorld()
SEEDS = {"second_heat_path": 2, "structure_growth": 3, "sensor_expansion": 2, "stop_drift": 3}


def view(hidden: hs.Hidden):
    return dataset_view(hs.dataset(WORLD, hidden), "Z", segments=True, history=True)


def diagnosis(hidden: hs.Hidden, **kw) -> dict:
    ds = view(hidden)
    fam = spindle_family(ds, [r for r in ds.run_ids if r != "tail"])
    return run_diagnosis(ds, settings=Settings(family=fam, candidates=fam.candidates, say=lambda m: None),
                         holdout=["tail"], **kw)  # fmt: skip


@pytest.mark.parametrize("x_noise", [4.0, 8.0])
@pytest.mark.parametrize("term", list(SEEDS))
def test_a_hidden_term_is_named_and_the_held_out_tail_shrinks(term, x_noise):
    h = hs.hidden_term(term, x_noise, np.random.default_rng(SEEDS[term]), WORLD)
    d = diagnosis(h)
    assert d["verdict"] in ("found", "found_partial"), (h, d["verdict"])
    first = d["steps"][0]
    assert first["confirmed"]
    assert first["effect"] == term  # no other term stands in for it
    if h.signal is not None:  # its driver too
        assert first["variant"]["signal"] == h.signal
    # the search never saw the tail: scored once, it shrinks toward the noise
    v = d["validation"]
    assert v["runs"] == ["tail"] and v["rmse_final_um"] < 0.8 * v["rmse_base_um"]
    # the step explains most of the systematic error the base left on held-out blocks
    systematic = np.sqrt(first["heldout_rmse_before_um"] ** 2 - d["noise_floor_um"] ** 2)
    assert first["explained_um"] >= 0.75 * systematic
    if d["verdict"] == "found":
        assert d["final"]["heldout_rmse_um"] <= 1.5 * d["noise_floor_um"]


def test_the_clean_negative_control_names_nothing():
    d = diagnosis(hs.Hidden())
    assert d["verdict"] == "none" and d["steps"] == [] and d["gap"]["more_data"] == []
    # the floor is the gauge noise the data were made with (0.1 um), estimated from the residual alone
    assert d["noise_floor_um"] == pytest.approx(WORLD.noise_um, rel=0.15)


def test_physics_outside_the_library_is_never_none():
    h = hs.hidden_term("chiller", 8.0, np.random.default_rng(1), WORLD)
    d = diagnosis(h)
    assert d["verdict"] in ("unexplained", "found_partial")
    assert d["gap"]["x_floor"] > 1.5 and d["gap"]["more_data"]


def test_folds_are_whole_blocks_and_the_holdout_is_never_fitted():
    d = diagnosis(hs.Hidden(), max_effects=0)
    blocks = [f"b{k}" for k in range(1, 6)]
    assert d["cv"]["fit_runs"] == blocks
    assert [f["test"] for f in d["cv"]["folds"]] == [[b] for b in blocks]
    assert all("tail" not in f["train"] + f["test"] for f in d["cv"]["folds"])


# ------------------------------------------------------------- the terms ---
def _stop_drift_by_ode(t_eval, tau_heat, tau_cool, exponent, u_ref):
    """θ' = (q − θ)/τ_heat while running, −θ/τ_cool while stopped, by solve_ivp between switches."""
    sw, levels = WORLD.schedule()
    edges = np.r_[sw, np.inf]
    out, x = np.zeros(t_eval.size), np.zeros(1)
    for k, u in enumerate(levels):
        t0, t1 = edges[k], min(edges[k + 1], t_eval.max())
        if t1 <= t0:
            break
        q = (u / u_ref) ** exponent

        def rhs(_, th, q=q, on=u > 0):
            return (q - th) / tau_heat if on else -th / tau_cool

        sol = solve_ivp(rhs, (t0, t1), x, rtol=1e-10, atol=1e-12, dense_output=True)
        inside = (t_eval >= t0) & (t_eval <= t1)
        if inside.any():
            out[inside] = sol.sol(t_eval[inside])[0]
        x = sol.y[:, -1]
    return out


def test_a_terms_columns_match_its_ode():
    """The network's stop-drift column, simulated on its 60 s grid, against the documented ODE."""
    ds = view(hs.Hidden())
    m = LumpedThermalNetwork(operating="spindle_rpm", u_ref=5000.0, exponent=1.3, preprocess=None,
                             terms={"stop_drift": {"tau_heat_s": 2500.0, "tau_cool_s": 15000.0}},
                             initial={"tau1": 1500.0, "tau2": 9000.0}, identify=[])  # fmt: skip
    m.fit(ds, ["b1", "b2"])
    t = readings(ds, ["b3"])["t_s"].to_numpy()
    col = m.simulate(ds, "b3", t)[:, 2]
    ode = _stop_drift_by_ode(t, 2500.0, 15000.0, 1.3, 5000.0)
    assert np.max(np.abs(col - ode)) < 2e-3 * np.max(np.abs(ode))
    assert m.params_["stop_drift.tau_cool_s"] == pytest.approx(15000.0, rel=1e-12)  # held (searched in log)


def test_a_network_with_terms_is_not_exported_and_bad_terms_are_one_line():
    ds = view(hs.Hidden())
    m = LumpedThermalNetwork(operating="spindle_rpm", preprocess=None, terms={"second_heat_path": {}}).fit(ds, ["b1", "b2"])
    with pytest.raises(ModelError, match="no terms beyond the node chain.*second_heat_path"):
        m.export_encoding(["Z"], 1.0, None)
    with pytest.raises(ModelError, match="terms: unknown term 'nut_magic'"):
        LumpedThermalNetwork(operating="spindle_rpm", terms={"nut_magic": {}}).fit(ds, ["b1"])
    with pytest.raises(ModelError, match=r"terms.structure_growth.signal: 'T_nope' is not one of \['speed', 'T_amb'"):
        LumpedThermalNetwork(operating="spindle_rpm", terms={"structure_growth": {"signal": "T_nope"}}).fit(ds, ["b1"])


def test_a_term_describes_itself_in_one_place(monkeypatch):
    """Adding a term is its class: the family's candidates, own parameters, variants and
    parameter count come from it (registered in SPINDLE_TERMS)."""
    from thermbench.models.spindle_terms import SPINDLE_TERMS, SpindleTerm, lag

    class BedLag(SpindleTerm):
        id = "bed_lag"
        nonlinear = ("tau_s",)
        log_params = ("tau_s",)
        bounds = {"tau_s": (60.0, 1e5)}
        starts = {"tau_s": (3000.0,)}
        defaults = {"tau_s": 3000.0, "signal": "T_bed"}
        choice = "signal"

        def columns(self, dr, u_ref, p):
            return lag(dr.signals[self.signal], self.tau_s, dr.h)[:, None]

    monkeypatch.setitem(SPINDLE_TERMS, BedLag.id, BedLag)
    ds = view(hs.Hidden())
    fam = spindle_family(ds, ["b1", "b2"])
    assert "bed_lag" in fam.candidates and fam.own_params("bed_lag") == ("tau_s",)
    assert fam.variants("bed_lag", ds) == [{"signal": s} for s in hs.SENSORS]
    assert fam.n_params(["bed_lag"]) == fam.n_params([]) + 2
    m = fam.make_model(["bed_lag"], ds, Settings(family=fam), start={"bed_lag": {"signal": "T_bed"}}).fit(ds, ["b1", "b2"])
    assert set(m.term_gains_) == {"bed_lag"} and "bed_lag.tau_s" in m.params_


# ------------------------------------------------------------- the command ---
def test_the_command_on_a_spindle_directory(tmp_path):
    h = hs.hidden_term("structure_growth", 8.0, np.random.default_rng(SEEDS["structure_growth"]), WORLD)
    data = hs.make(WORLD, h, tmp_path / "data")
    out = tmp_path / "diag"
    assert main(["diagnose", str(data), "--out", str(out), "holdout=[tail]", "max_effects=1", "track=false"]) == 0
    d = json.loads((out / "diagnosis.json").read_text())
    assert d["family"] == "spindle" and d["steps"][0]["label"] == f"structure_growth[{h.signal}]"
    report = (out / "report.md").read_text()
    assert "## Held out of the search" in report and "lumped network" in report and (out / "holdout.png").is_file()
    assert [s["model"] for s in d["validation"]["by_step"]] == ["base", f"+ structure_growth[{h.signal}]"]


def test_spindle_mistakes_are_one_line_exit_2(tmp_path, capsys):
    data = hs.make(WORLD, hs.Hidden(), tmp_path / "data")
    cases = [
        (["--channel", "X"], "config key 'channel': 'X' is not an error channel"),
        (["holdout=[nope]"], "config key 'holdout': runs ['nope'] are not in the dataset"),
        (["--base", "nut_magic"], "config key 'base': unknown term(s) ['nut_magic']; the spindle terms are"),
        (["spindle.n_nodes=0"], "config key 'spindle.n_nodes': expected a number >= 1"),
        (["+spindle.sensors=all"], "config key 'spindle': unknown or reserved key(s) ['sensors']"),
    ]
    for args, expected in cases:
        assert main(["diagnose", str(data), "--out", str(tmp_path / "o"), *args, "track=false"]) == 2
        err = capsys.readouterr().err
        assert expected in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert main(["diagnose", "fl_thermal", "--out", str(tmp_path / "o"), "track=false"]) == 2
    assert "config key 'channel': " in capsys.readouterr().err
