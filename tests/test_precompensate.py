"""Pre-compensation of a part program (seed 003 §1: revise the NC program before
machining, from the planned operation only): reading, timing, rewriting, the
prediction wiring for the motion-only models, verification in the simulator, and
the messages for bad input."""

from pathlib import Path

import joblib
import numpy as np
import pandas as pd
import pytest
import yaml
from numpy.polynomial import Polynomial

from tests.synth import make_dataset
from thermbench.data.io import load_dataset, save_dataset
from thermbench.data.schema import FORMAT, Metadata
from thermbench.models.autoregressive import AutoRegressiveSeed003
from thermbench.models.base import Inputs, ThermalErrorModel
from thermbench.models.physics import PhysicsModel
from thermbench.precompensate import (
    PrecompError,
    ProgramError,
    format_summary,
    parse_program,
    plan_motion,
    planned_dataset,
    precompensate,
    run_precompensate,
    simulate_true_errors,
    truth_from_metadata,
    verify_in_simulator,
)
from thermbench.sim.model import ScrewThermalModel
from thermbench.sim.parts import CoreParams, Material, Numerics, Screw

SAMPLE = Path(__file__).parent / "data" / "sample_program.nc"
# seed 000 Table 1 X axis, coarse numerics so that a 45-min program runs in well under a second
SCREW = Screw(length_m=0.8, diameter_m=0.034, nut_length_m=0.212, fixed_bearing_length_m=0.03)
MATERIAL = Material(alpha_per_K=11.7e-6, density_kg_m3=7800.0, heat_capacity_J_kgK=448.0)
NUMERICS = Numerics(dx_m=0.02, dt_s=0.5, macro_dt_s=10.0)


def seed000_metadata(simulation: dict | None = None) -> Metadata:
    body = {
        "format": FORMAT,
        "machine": {"name": "seed000_test", "axis": "X"},
        "screw": {"length_m": SCREW.length_m, "diameter_m": SCREW.diameter_m, "nut_length_m": SCREW.nut_length_m,
                  "fixed_bearing_length_m": SCREW.fixed_bearing_length_m, "mounting": SCREW.mounting},  # fmt: skip
        "material": {"alpha_per_K": MATERIAL.alpha_per_K, "density_kg_m3": MATERIAL.density_kg_m3,
                     "heat_capacity_J_kgK": MATERIAL.heat_capacity_J_kgK},  # fmt: skip
        "sensors": {"T_ambient": "ambient", "T_nut": "nut_housing"},
        "runs": {"train": {"condition": {"stroke_mm": 500.0, "start_mm": 0.0, "end_mm": 500.0, "feed_mm_min": 3000.0}}},
    }
    if simulation is not None:
        body["simulation"] = simulation
    return Metadata.model_validate(body)


def truth_model(core: CoreParams | None = None) -> ScrewThermalModel:
    return ScrewThermalModel(SCREW, MATERIAL, core or CoreParams(), [], NUMERICS)


def oracle(core: CoreParams | None = None, ambient_sensor: str | None = None) -> PhysicsModel:
    """A PhysicsModel 'fitted' to exactly the truth's parameters (same numerics)."""
    m = PhysicsModel(dx_m=NUMERICS.dx_m, dt_s=NUMERICS.dt_s, macro_dt_s=NUMERICS.macro_dt_s, ambient_sensor=ambient_sensor)
    m.train_runs_ = ["train"]
    m.ambient_name_ = ambient_sensor
    m.core_ = core or CoreParams()
    m.effects_ = {}
    m.geometric_ = Polynomial([0.0])
    return m


class Stub(ThermalErrorModel):
    """A known error e = 2 + 0.01·t + 0.02·x µm (t in s, x the axis position in mm)."""

    def __init__(self, sensors=(), operating=()):
        self.sensors = sensors
        self.operating = operating

    def _fit(self, ds, runs):
        self.geometric_ = Polynomial([0.0])

    def _predict_thermal(self, ds, run, t_s, axis_mm):
        assert list(ds.metadata.runs) == [run]  # the planned program is the dataset's one run
        return 2.0 + 0.01 * t_s + 0.02 * axis_mm

    def _model_inputs(self):
        return Inputs(sensors=tuple(self.sensors), motion=True, operating=tuple(self.operating))


def stub(**kw) -> Stub:
    m = Stub(**kw)
    m.train_runs_ = ["train"]
    m.geometric_ = Polynomial([0.0])
    return m


def stub_error(t_s, x_mm):
    return 2.0 + 0.01 * np.asarray(t_s) + 0.02 * np.asarray(x_mm)


# --------------------------------------------------------------- reading ---
def test_timing_of_a_hand_computed_program():
    """100 mm at F1000 = 6 s; G4 P2 = 2 s; G0 100 mm at the rapid feed 10000 = 0.6 s;
    nothing after M30 is read."""
    text = "G21 G90\nN10 G1 X0 F1000\nN20 G1 X100 (cut)\nG4 P2\nG0 X0\nM30\nG1 X999\n"
    prog = parse_program(text, start_mm=0.0)
    moves, log = plan_motion(prog)
    assert moves["kind"].tolist() == ["G1", "G1", "G4", "G0"]
    assert moves["line"].tolist() == [2, 3, 4, 5]
    np.testing.assert_allclose(moves["t_end_s"], [0.0, 6.0, 8.0, 8.6])
    np.testing.assert_allclose(moves["target_mm"], [0.0, 100.0, 100.0, 0.0])
    assert moves["compensate"].tolist() == [True, True, False, True]
    np.testing.assert_allclose(log["t_s"], [0, 1, 2, 3, 4, 5, 6, 7, 8, 8.6])
    np.testing.assert_allclose(log["axis_mm"], [0, 100 / 6, 200 / 6, 50, 400 / 6, 500 / 6, 100, 100, 100, 0])
    np.testing.assert_allclose(log["feed_mm_min"], [1000] * 6 + [0, 0, 10000, 0])

    # options: the rapid feed, the clock start, the sampling step
    moves2, log2 = plan_motion(prog, rapid_mm_min=5000.0, sample_s=0.5, start_s=100.0)
    np.testing.assert_allclose(moves2["t_end_s"], [100.0, 106.0, 108.0, 109.2])
    assert np.diff(log2["t_s"]).max() == pytest.approx(0.5)
    assert log2["t_s"].iloc[-1] == pytest.approx(109.2)
    # a feed above the rapid (LinuxCNC's 3D_Chips.ngc programs F4500000) runs at the machine's top speed:
    # 100 mm at the rapid 5000 mm/min = 1.2 s, not 100 / 4.5e6 min
    fast = parse_program("G21 G90\nG1 X0 F4500000\nG1 X100\n", start_mm=0.0)
    moves3, log3 = plan_motion(fast, rapid_mm_min=5000.0)
    np.testing.assert_allclose(moves3["duration_s"], [0.0, 1.2])
    assert log3["feed_mm_min"].max() == 5000.0


def test_incremental_blocks_and_their_rewrite():
    """G91 moves are relative to the current position; their rewritten increments put
    the axis on the compensated absolute points (re-read from the output)."""
    text = "G90 G1 X10 F600\nG91 X5\nX-20.5\nG90 X0\n"
    prog = parse_program(text, source="inc.nc")
    moves, _ = plan_motion(prog)
    np.testing.assert_allclose(moves["target_mm"], [10.0, 15.0, -5.5, 0.0])
    np.testing.assert_allclose(moves["duration_s"], [0.0, 0.5, 2.05, 0.55])  # starts at the first target

    res = precompensate(text, stub(), seed000_metadata(), source="inc.nc")
    e = stub_error(moves["t_end_s"], moves["target_mm"])  # the stub's error, independently
    want = moves["target_mm"].to_numpy() - e / 1000.0
    again = parse_program(res.text)
    np.testing.assert_allclose([b.target_mm for b in again.blocks], want, atol=0.6e-4)
    lines = res.text.splitlines()
    assert lines[0] == f"G90 G1 X{want[0]:.4f} F600"  # 10 - 2.2 µm = 9.9978
    assert lines[0] == "G90 G1 X9.9978 F600"
    assert lines[1] == f"G91 X{round(want[1], 4) - round(want[0], 4):.4f}"
    assert again.blocks[1].incremental and again.blocks[2].incremental and not again.blocks[3].incremental


def test_unsupported_lines_pass_through_and_are_listed():
    text = (
        "%\n"
        "O100 (header)\n"
        "N5 G21 G17 G54\n"
        "N10 T2 M6 ; tool change\n"
        "#100 = 5\n"
        "N20 g1 x50.5 y3 Z-1. F1200 (finish (pass)\n"
        "N30 G2 X60. Y10. R5.\n"
        "N40 G1 Y20 ; other axis only\n"
        "N50 G1 X70\n"
        "M30\n"
        "%\n"
    )
    res = precompensate(text, stub(), seed000_metadata(), source="p.nc")
    out, src = res.text.splitlines(), text.splitlines()
    assert len(out) == len(src)
    for i in (0, 1, 2, 3, 4, 6, 7, 9, 10):  # no X move compensated there: untouched
        assert out[i] == src[i]
    comp = res.moves[res.moves["compensate"]]
    assert comp["line"].tolist() == [6, 9]
    # only the number of the X word changed; case, other words and comments stay
    x6 = comp["new_target_mm"].iloc[0]
    assert out[5] == f"N20 g1 x{x6:.4f} y3 Z-1. F1200 (finish (pass)"
    assert out[8] == f"N50 G1 X{comp['new_target_mm'].iloc[1]:.4f}"
    listed = {u.line: u.reason for u in res.unsupported}
    assert set(listed) == {3, 4, 5, 7}
    assert "G17" in listed[3] and "G54" in listed[3]
    assert "M6" in listed[4] and "T2" in listed[4]
    assert "(parameters #)" in listed[5]
    assert "G2" in listed[7] and "not compensated" in listed[7]
    # the arc is followed to X60 and timed on its X distance at F1200; Y-only blocks take no time
    arc = res.moves[res.moves["kind"] == "G2"].iloc[0]
    assert arc["target_mm"] == 60.0 and arc["duration_s"] == pytest.approx(9.5 / 1200 * 60)
    assert comp["t_end_s"].iloc[1] - arc["t_end_s"] == pytest.approx(10.0 / 1200 * 60)
    assert "line 7" in format_summary(res)


def test_line_endings_and_dwell_units():
    """CRLF endings survive the rewrite; a G4 P without a decimal point of 100 or more
    is read as seconds and flagged (Fanuc-style controls read it in ms)."""
    text = "G0 X0\r\nG1 X100 F6000\r\nG4 P1000\r\nG4 P1.5\r\n"
    res = precompensate(text, stub(), seed000_metadata())
    assert res.text.count("\r\n") == 4 and res.text.splitlines()[2:] == ["G4 P1000", "G4 P1.5"]
    assert [u.line for u in res.unsupported] == [3] and "ms" in res.unsupported[0].reason
    assert res.moves["t_end_s"].iloc[-1] == pytest.approx(1.0 + 1000.0 + 1.5)


# ------------------------------------------------------------ prediction ---
def test_rewritten_targets_are_target_minus_prediction():
    """Each G0/G1 target moves by -e/1000 mm, e the model's thermal error at the move end
    (checked against the model called directly on the planned dataset); a physics model
    with an ambient sensor sees it held constant, which changes nothing."""
    text = SAMPLE.read_text()
    meta = seed000_metadata()
    plain = precompensate(text, oracle(), meta)
    amb = precompensate(text, oracle(ambient_sensor="T_ambient"), meta, ambient_C=23.0)
    comp = plain.moves[plain.moves["compensate"]]
    ds = planned_dataset(meta, plain.process)
    direct = oracle().predict_thermal_at(ds, "program", comp["t_end_s"], comp["axis_target_mm"])
    np.testing.assert_allclose(comp["predicted_error_um"], direct, atol=1e-9)
    np.testing.assert_allclose(comp["new_target_mm"], comp["target_mm"] - direct / 1000.0, atol=0.5e-4 + 1e-12)
    np.testing.assert_allclose(amb.moves["predicted_error_um"], plain.moves["predicted_error_um"], atol=1e-6)
    assert amb.text == plain.text
    assert direct.max() > 15.0  # the sample program heats the screw


def _in_inches(text: str) -> str:
    """``text`` (a G21 program) by hand in inches: G20 for G21, every X and F word divided by
    25.4 and written with 6 decimals (1e-6 in = 25 nm, below the 0.1 um of the mm program)."""
    import re

    def inch(m):
        return f"{m.group(1)}{float(m.group(2)) / 25.4:.6f}"

    out = []
    for line in text.splitlines(keepends=True):
        code, paren, comment = line.partition("(")
        code = re.sub(r"\b([XF])(-?\d+\.?\d*)", inch, code.replace("G21", "G20"))
        out.append(code + paren + comment)
    return "".join(out)


def test_an_inch_program_is_the_mm_program_and_is_written_back_in_inches():
    """G20: the sample program converted by hand to inches plans and compensates as the mm program
    (same moves, times and predicted errors), and its revised X words are in inches: x 25.4 they
    are the mm program's revised targets (to the rounding of both: 1e-5 in and 1e-4 mm)."""
    mm_text = SAMPLE.read_text()
    inch_text = _in_inches(mm_text)
    assert "G20" in inch_text and "X18.897638" in inch_text  # 480 mm
    meta = seed000_metadata()
    mm, inch = precompensate(mm_text, oracle(), meta), precompensate(inch_text, oracle(), meta)
    a, b = mm.moves, inch.moves
    assert len(a) == len(b) and (a["compensate"] == b["compensate"]).all()
    np.testing.assert_allclose(b["target_mm"], a["target_mm"], atol=25.4 * 0.5e-6)
    np.testing.assert_allclose(b["t_end_s"], a["t_end_s"], atol=1e-4)
    # the inch words' rounding (< 1e-6 in) shifts move ends by < 3e-5 s, which moves some across the
    # planned log's sample grid: the predicted errors differ by up to a few hundredths of a um
    np.testing.assert_allclose(b["predicted_error_um"], a["predicted_error_um"], atol=0.05, equal_nan=True)
    comp = a["compensate"].to_numpy()
    np.testing.assert_allclose(b.loc[comp, "new_target_mm"], a.loc[comp, "new_target_mm"],
                               atol=25.4 * 0.5e-5 + 0.5e-4 + 0.05e-3)  # fmt: skip
    blocks = parse_program(inch_text).blocks
    assert len(blocks) == len(b) and all(blk.mm_per_unit == 25.4 for blk in blocks if blk.span is not None)
    absolute = comp & ~np.array([blk.incremental for blk in blocks])  # G91 blocks write the increment
    np.testing.assert_allclose(b.loc[absolute, "written_value"] * 25.4, b.loc[absolute, "new_target_mm"], atol=1e-9)
    # the written numbers have 5 decimals (the sample's inch words have 6: kept), and the text is inches
    first = b.index[comp][0]
    line = inch.text.splitlines()[int(b.loc[first, "line"]) - 1]
    assert f"X{b.loc[first, 'written_value']:.6f}" in line


def test_work_offset_moves_the_axis_not_the_program():
    text = "G90 G0 X0\nG1 X100 F6000\n"
    res = precompensate(text, stub(), seed000_metadata(), work_offset_mm=50.0)
    last = res.moves.iloc[-1]
    assert last["axis_target_mm"] == 150.0
    e = stub_error(1.0, 150.0)  # 100 mm at 6000 mm/min = 1 s; the axis is at 150 mm
    assert last["predicted_error_um"] == pytest.approx(e)
    assert res.text.splitlines()[1] == f"G1 X{100 - e / 1000:.4f} F6000"


def test_planned_dataset_meets_the_contract(tmp_path):
    meta = seed000_metadata()
    _, log = plan_motion(parse_program("G0 X0\nG1 X100 F1000\nG4 P3.5\nG0 X20\n"))
    ds = planned_dataset(meta, log, {"T_ambient": 21.5})
    back = load_dataset(save_dataset(ds, tmp_path / "planned"))  # validates everything
    assert back.run_ids == ["program"]
    assert dict(back.metadata.sensors) == {"T_ambient": "ambient"}
    assert (back.process["T_ambient_C"] == 21.5).all()
    np.testing.assert_allclose(back.process["axis_mm"], log["axis_mm"])
    assert back.metadata.screw == meta.screw and back.metadata.material == meta.material


def ar_truth(u, a, b):
    """c(k) = a c(k-1) + b u(k), at rest before k = 1."""
    c = [0.0]
    for uk in u:
        c.append(a * c[-1] + b * uk)
    return np.array(c)


def test_autoregressive_seed003_model_predicts_the_planned_feed():
    """Seed 003's model: an ARX fitted on feed-driven data (error uniform over the
    travel, c(k) = 0.6 c(k-1) + 2e-3·u(k)) predicts at move ends on its 600-s grid the
    values of the recursion driven by the program's feed."""
    a, b = 0.6, 2.0e-3
    targets = np.arange(0.0, 501.0, 100.0)
    pframes, eframes = [], []
    for run, levels in {"r1": [3000, 0, 6000, 1500, 0, 4500, 3000, 0], "r2": [6000, 6000, 0, 1500, 3000, 0, 0, 4500]}.items():
        u = np.array(levels, dtype=float)
        t = np.arange(0.0, u.size * 600.0 + 1.0)
        feed = np.where(t < u.size * 600, u[np.minimum((t // 600).astype(int), u.size - 1)], 0.0)
        pframes.append(pd.DataFrame({"run_id": run, "t_s": t, "axis_mm": 250 + 250 * np.sin(t / 7.0), "feed_mm_min": feed}))
        c = ar_truth(u, a, b)
        tk = np.repeat(600.0 * np.arange(u.size + 1), targets.size)
        eframes.append(pd.DataFrame({"run_id": run, "t_s": tk, "target_mm": np.tile(targets, u.size + 1),
                                     "error_um": np.repeat(c, targets.size)}))  # fmt: skip
    ds = make_dataset(pd.concat(pframes), pd.concat(eframes), {})
    model = AutoRegressiveSeed003(na=1, nb=1).fit(ds)

    # 120 strokes of 500 mm at F3000 (10 s each): 1200 s of feed 3000, then rest
    text = "G90 G0 X0\nF3000\n" + "G1 X500\nG1 X0\n" * 60 + "G4 P600\nG0 X250\n"
    res = precompensate(text, model, ds)
    comp = res.moves[res.moves["compensate"]]
    c = ar_truth(np.array([3000.0, 3000.0, 0.0]), a, b)
    at = {600.0: c[1], 1200.0: c[2]}
    for t_end, want in at.items():
        row = comp[np.isclose(comp["t_end_s"], t_end)].iloc[0]
        assert row["predicted_error_um"] == pytest.approx(want, rel=1e-6, abs=1e-6)
        assert row["new_target_mm"] == pytest.approx(row["target_mm"] - want / 1000.0, abs=0.6e-4)


# ---------------------------------------------------------- verification ---
def test_with_the_truth_as_model_the_residual_vanishes():
    """Replaying the original motion in the simulator: a model equal to the truth
    leaves < 0.1 µm at the move ends where the uncompensated program is 10-25 µm off."""
    truth = truth_model()
    text = SAMPLE.read_text()
    # sampled at the truth's own step and written with 5 decimals: only the method remains
    fine = precompensate(text, oracle(), seed000_metadata(), sample_s=NUMERICS.dt_s, decimals=5)
    v = verify_in_simulator(fine, truth)
    assert v["moves"] == int(fine.moves["compensate"].sum()) > 300
    assert v["max_abs_before_um"] > 10.0 and v["rms_before_um"] > 5.0
    assert v["max_abs_after_um"] < 0.1
    assert v["reduction_rms_pct"] > 99.0
    # the defaults (1 Hz planned log, 4 decimals): sub-second rapids blur a little
    default = verify_in_simulator(precompensate(text, oracle(), seed000_metadata()), truth)
    assert default["max_abs_after_um"] < 0.3 and default["reduction_max_abs_pct"] > 98.0

    tab = simulate_true_errors(fine, truth)
    # before: the error at the commanded target; after: the compensated position's error
    np.testing.assert_allclose(tab["error_before_um"], tab["predicted_error_um"], atol=0.1)


def test_a_wrong_model_is_shown_by_the_verification():
    """A model with half the truth's heat leaves about half of the error."""
    half = CoreParams(k3_W_per_mm_min=CoreParams().k3_W_per_mm_min / 2, k4_W_per_mm_min=CoreParams().k4_W_per_mm_min / 2)
    res = precompensate(SAMPLE.read_text(), oracle(half), seed000_metadata())
    v = verify_in_simulator(res, truth_model())
    assert 0.3 < v["rms_after_um"] / v["rms_before_um"] < 0.7


def test_run_precompensate_from_files(tmp_path):
    sim = {"core": CoreParams().as_dict(), "effects": {}, "numerics": {"dx_m": 0.02, "dt_s": 0.5, "macro_dt_s": 10.0}}
    data = tmp_path / "data"
    data.mkdir()
    import yaml

    (data / "metadata.yaml").write_text(yaml.safe_dump(seed000_metadata(sim).model_dump(mode="json", exclude_none=True)))
    model_path = tmp_path / "physics.joblib"
    joblib.dump(oracle(), model_path)
    prog = tmp_path / "part.nc"
    prog.write_text(SAMPLE.read_text())
    out = tmp_path / "out" / "part_comp.nc"

    res = run_precompensate(prog, model_path, out, dataset=data, truth="auto")
    assert out.read_text() == res.text
    assert prog.read_text() == SAMPLE.read_text()  # the input is untouched
    assert res.verification["max_abs_after_um"] < 0.3
    assert truth_from_metadata(seed000_metadata(sim)).core == CoreParams()
    summary = format_summary(res)
    assert str(out) in summary and "reduction" in summary and "G2" in summary


# ------------------------------------------------------------ bad input ---
@pytest.mark.parametrize(
    "text, line, expected",
    [
        ("G90\nG1 X10\n", 2, "F<mm/min>"),
        ("G1 X10 F-100\n", 1, "feed > 0"),
        ("G0 X0\nG4\n", 2, "P<seconds>"),
        ("G0 X0\nG4 X2\n", 2, "P<seconds>"),
        ("G91 G1 X10 F100\n", 1, "incremental"),
        ("G1 X#1 F100\n", 1, "(a word whose value is a parameter or an expression)"),
        ("X10\n", 1, "no motion mode"),
        ("G0 X0\nG28 X0\n", 2, "G28"),
        ("G0 X0\nG53 G0 X0\n", 2, "G53"),  # no work offset given: the machine position is not a program one
        ("G1 X1 X2 F100\n", 1, "at most one"),
        ("G0 X0 (open\n", 1, "unclosed"),
        ("G1 G95 X1 F0.1\n", 1, "G94"),
        ("G0 X0\nG33 X10 F1.5\n", 2, "G0/G1"),
        ("G0 X0\nG0 G1 X10 F100\n", 2, "expected one"),
    ],
)
def test_program_errors_name_file_line_and_expectation(text, line, expected):
    with pytest.raises(ProgramError) as exc:
        parse_program(text, source="part.nc")
    assert f"part.nc:{line}:" in str(exc.value) and expected in str(exc.value)


def test_model_errors():
    meta = seed000_metadata()
    text = "G0 X0\nG1 X100 F1000\n"
    with pytest.raises(PrecompError, match=r"temperature sensor\(s\) \['T_nut'\]"):
        precompensate(text, stub(sensors=("T_ambient", "T_nut")), meta)
    with pytest.raises(PrecompError, match=r"load_N"):
        precompensate(text, stub(operating=("load_N",)), meta)
    with pytest.raises(PrecompError, match="not fitted"):
        precompensate(text, PhysicsModel(), meta)
    with pytest.raises(PrecompError, match="unsupported type"):
        precompensate(text, {"k3": 1.0}, meta)
    with pytest.raises(PrecompError, match="sample_s"):
        precompensate(text, stub(), meta, sample_s=2.0)
    with pytest.raises(PrecompError, match="no G0/G1 move on axis Z"):
        precompensate(text, stub(), meta, axis="Z")
    # a model reading only the ambient it can be given is accepted
    assert precompensate(text, stub(sensors=("T_ambient",)), meta).moves["compensate"].sum() == 2


def test_file_errors(tmp_path):
    prog = tmp_path / "part.nc"
    prog.write_text("G0 X0\nG1 X100 F1000\n")
    model_path = tmp_path / "m.joblib"
    joblib.dump(oracle(), model_path)
    data = tmp_path / "data"
    data.mkdir()
    (data / "metadata.yaml").write_text(__import__("yaml").safe_dump(seed000_metadata().model_dump(mode="json")))
    out = tmp_path / "out.nc"

    with pytest.raises(PrecompError, match="missing.nc: cannot read"):
        run_precompensate(tmp_path / "missing.nc", model_path, out, dataset=data)
    with pytest.raises(PrecompError, match="nomodel.joblib: no such model file"):
        run_precompensate(prog, tmp_path / "nomodel.joblib", out, dataset=data)
    bad = tmp_path / "bad.joblib"
    joblib.dump({"not": "a model"}, bad)
    with pytest.raises(PrecompError, match="unsupported type builtins.dict"):
        run_precompensate(prog, bad, out, dataset=data)
    garbage = tmp_path / "garbage.joblib"
    garbage.write_text("not a pickle")
    with pytest.raises(PrecompError, match="garbage.joblib: not a joblib model file"):
        run_precompensate(prog, garbage, out, dataset=data)
    with pytest.raises(PrecompError, match="--dataset"):
        run_precompensate(prog, model_path, out)
    with pytest.raises(PrecompError, match="not a dataset directory nor a benchmark"):
        run_precompensate(prog, model_path, out, dataset=tmp_path / "nowhere")
    with pytest.raises(PrecompError, match="overwrite the input"):
        run_precompensate(prog, model_path, prog, dataset=data)
    with pytest.raises(PrecompError, match="was not simulated"):
        run_precompensate(prog, model_path, out, dataset=data, truth="auto")
    assert not out.exists()  # every check comes before the output is written
    binary = tmp_path / "bin.nc"
    binary.write_bytes(b"G0 X0\n\xff\xfe\n")
    with pytest.raises(PrecompError, match="bin.nc:2: not UTF-8"):
        run_precompensate(binary, model_path, out, dataset=data)


def test_building_the_models_benchmark_dataset_is_said_first(tmp_path, monkeypatch, capsys):
    """A benchmark model's metadata comes from its training dataset; when that is not built where
    the benchmark datasets are, precompensate says it will simulate it there before it starts."""
    from thermbench.bench import datasets
    from thermbench.precompensate import resolve_metadata

    monkeypatch.setenv("THERMBENCH_DATA", str(tmp_path / "bench"))
    said_before = []

    def fake_build(name, root=None, force=False):
        said_before.append(capsys.readouterr().err)
        d = tmp_path / "bench" / name
        d.mkdir(parents=True, exist_ok=True)
        (d / "metadata.yaml").write_text(yaml.safe_dump(seed000_metadata().model_dump(mode="json", exclude_none=True)))
        return d, None

    monkeypatch.setattr(datasets, "build", fake_build)
    assert resolve_metadata("seed000_x").machine.name == seed000_metadata().machine.name
    assert said_before == [f"precompensate: the model's training dataset seed000_x is not at {tmp_path / 'bench' / 'seed000_x'}; "
                           "simulating it there for its machine's metadata (--dataset DIR names one you have; "
                           "THERMBENCH_DATA moves the benchmark datasets)\n"]  # fmt: skip
    # built with its current config: nothing said
    monkeypatch.setattr(datasets, "is_built", lambda name, root=None: True)
    resolve_metadata("seed000_x")
    assert said_before[1:] == [""] and capsys.readouterr().err == ""


def test_a_move_in_machine_coordinates_is_followed_with_the_work_offset():
    """G53 G0 X0 goes to machine X0, which is program X-20 under a work offset of +20 mm: 30 mm at
    the rapid from X10 (0.18 s), then 70 mm at F600 (7 s); the G53 block is timed, not compensated,
    and its word stays as written."""
    text = "G21 G90\nG0 X10\nG53 G0 X0\nG1 X50 F600\n"
    res = precompensate(text, stub(), seed000_metadata(), work_offset_mm=20.0)
    mv = res.moves
    assert mv["kind"].tolist() == ["G0", "G53", "G1"] and mv["compensate"].tolist() == [True, False, True]
    np.testing.assert_allclose(mv["target_mm"], [10.0, -20.0, 50.0])
    np.testing.assert_allclose(mv["axis_target_mm"], [30.0, 0.0, 70.0])
    np.testing.assert_allclose(mv["t_end_s"], [0.0, 0.18, 7.18])
    assert res.text.splitlines()[2] == "G53 G0 X0"
    assert any("machine coordinates" in u.reason for u in res.unsupported)
