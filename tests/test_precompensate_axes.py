"""Pre-compensation of a whole part program, every axis with its own model
(thermbench/precompensate/axes.py): one time line over all axes (timed by hand here), each axis
revised by its own model (stub models with known errors, and physics models equal to their
simulator truths), axes without a model left as written, the axes file and the CLI's messages."""

from __future__ import annotations

import math
import re
import subprocess
from pathlib import Path

import joblib
import numpy as np
import pytest
import yaml
from numpy.polynomial import Polynomial

from tests.test_precompensate import CoreParams, Stub, oracle, seed000_metadata, stub, stub_error, truth_model
from thermbench.precompensate import PrecompError, ProgramError, parse_program, plan_motion, precompensate, verify_in_simulator
from thermbench.precompensate.axes import AxisModel, plan_axes, precompensate_axes, read_axes_file, run_precompensate_axes

DIAGONAL = "G21 G90\nG0 X0 Y0\nG1 X30 Y40 F3000\nG4 P2\nG1 Y100\nG0 X0 Y0\nM30\n"


class StubY(Stub):
    """Another known error, e = 1 + 0.05·t - 0.01·y µm: the Y axis's own model."""

    def _predict_thermal(self, ds, run, t_s, axis_mm):
        return stub_y_error(t_s, axis_mm)


def stub_y_error(t_s, y_mm):
    return 1.0 + 0.05 * np.asarray(t_s) - 0.01 * np.asarray(y_mm)


def stub_y() -> StubY:
    m = StubY()
    m.train_runs_ = ["train"]
    m.geometric_ = Polynomial([0.0])
    return m


def _programs(text: str, axes: str = "XYZ"):
    return {a: parse_program(text, a) for a in axes}


def test_one_time_line_timed_by_hand():
    """A move takes its path length over every axis at F: 30/40 mm at F3000 is 50 mm, 1 s, X at
    1800 and Y at 2400 mm/min; G4 P2 2 s; Y alone 60 mm 1.2 s (X standing still); the G0 back
    √(30² + 100²) mm at the rapid 10000 mm/min."""
    plans = plan_axes(_programs(DIAGONAL))
    assert set(plans) == {"X", "Y"}  # Z is never placed: not on the time line
    back = math.hypot(30.0, 100.0) / 10000.0 * 60.0
    t_end = [0.0, 1.0, 3.0, 4.2, 4.2 + back]
    for a in "XY":
        moves, log = plans[a]
        assert moves["line"].tolist() == [2, 3, 4, 5, 6]
        np.testing.assert_allclose(moves["t_end_s"], t_end)
    mx, my = plans["X"][0], plans["Y"][0]
    assert mx["kind"].tolist() == ["G0", "G1", "G4", "hold", "G0"]
    assert mx["compensate"].tolist() == [True, True, False, False, True]
    assert mx["block"].tolist() == [0, 1, 2, -1, 3]
    np.testing.assert_allclose(mx["feed_mm_min"], [0.0, 1800.0, 0.0, 0.0, 30.0 / back * 60.0])
    np.testing.assert_allclose(my["feed_mm_min"], [0.0, 2400.0, 0.0, 3000.0, 100.0 / back * 60.0])
    np.testing.assert_allclose(mx["target_mm"], [0, 30, 30, 30, 0])
    np.testing.assert_allclose(my["target_mm"], [0, 40, 40, 100, 0])
    log_x, log_y = plans["X"][1], plans["Y"][1]
    np.testing.assert_allclose(log_x["t_s"], [0, 1, 2, 3, 4, 4.2 + back])
    np.testing.assert_allclose(log_x["axis_mm"], [0, 30, 30, 30, 30, 0])
    np.testing.assert_allclose(log_y["axis_mm"], [0, 40, 40, 40, 40 + 60 * (1.0 / 1.2), 0])
    np.testing.assert_allclose(log_x["feed_mm_min"], [1800, 0, 0, 0, 0, 0])  # at t=1: the dwell in force
    np.testing.assert_allclose(log_y["feed_mm_min"], [2400, 0, 0, 3000, 3000, 0])  # t=4: Y still on line 5
    # one axis alone plans as the one-axis planner does
    alone, _ = plan_motion(parse_program("G1 X0 F600\nX100\nG4 P1\nG0 X0\n"))
    same, _ = plan_axes(_programs("G1 X0 F600\nX100\nG4 P1\nG0 X0\n"))["X"]
    np.testing.assert_allclose(same["t_end_s"], alone["t_end_s"])
    timed = alone["duration_s"].to_numpy() > 0  # a zero-length move has no speed of its own
    np.testing.assert_allclose(same["feed_mm_min"][timed], alone["feed_mm_min"][timed])


def test_each_axis_is_revised_by_its_own_model_and_the_others_stay_as_written():
    """X by e = 2 + 0.01·t + 0.02·x, Y by e = 1 + 0.05·t - 0.01·y, each at its move's end on the
    hand-timed line above; Z has words but no model: every Z number as written. Both words of one
    block are rewritten (spans held), incremental blocks included."""
    text = ("%\nG21 G90 (start)\nG0 X0 Y0 Z5.\nG1 X30 Y40 Z-1. F3000\nG4 P2\nG91 G1 Y60 Z1.\nG90 G0 X0 Y0 Z5.\nM30\n%\n")
    meta = seed000_metadata()
    res = precompensate_axes(text, {"X": AxisModel(stub(), meta, "x.joblib"), "Y": AxisModel(stub_y(), meta, "y.joblib")})
    assert set(res.axes) == {"X", "Y"} and res.as_written == {"Z": "no model"}
    # the time line by hand: Z moves too (path lengths over X, Y and Z)
    l1 = math.sqrt(30**2 + 40**2 + 6**2) / 3000 * 60
    l2 = math.sqrt(60**2 + 1**2) / 3000 * 60
    l3 = math.sqrt(30**2 + 100**2 + 5**2) / 10000 * 60
    t = np.cumsum([0.0, l1, 2.0, l2, l3])  # the ends of lines 3 .. 7
    out = res.text.splitlines()
    assert out[0] == "%" and out[1].startswith("(thermbench precompensate")
    head = "\n".join(out[1:5])
    assert "(axis X: x.joblib, Stub" in head and "(axis Y: y.joblib, Stub" in head and "(axis Z: as written, no model)" in head
    body = out[5:]
    assert body[0] == "G21 G90 (start)" and body[-1] == "%" and body[-2] == "M30" and body[3] == "G4 P2"
    x = [0.0, 30.0, 0.0]
    y = [0.0, 40.0, 100.0, 0.0]
    ex = x - stub_error(t[[0, 1, 4]], x) / 1000.0
    ey = y - stub_y_error(t[[0, 1, 3, 4]], y) / 1000.0
    assert body[1] == f"G0 X{ex[0]:.4f} Y{ey[0]:.4f} Z5."
    assert body[2] == f"G1 X{ex[1]:.4f} Y{ey[1]:.4f} Z-1. F3000"
    assert body[4] == f"G91 G1 Y{round(ey[2], 4) - round(ey[1], 4):.4f} Z1."
    assert body[5] == f"G90 G0 X{ex[2]:.4f} Y{ey[3]:.4f} Z5."
    # the output re-read: every axis where it was meant to be, Z exactly as written
    for a, want in (("X", ex), ("Y", ey)):
        got = [b.target_mm for b in parse_program(res.text, a).blocks if b.kind != "G4"]
        np.testing.assert_allclose(got, want, atol=0.6e-4)
    assert [b.target_mm for b in parse_program(res.text, "Z").blocks if b.kind != "G4"] == [5.0, -1.0, 0.0, 5.0]


def test_with_each_axis_truth_as_its_model_every_axis_residual_vanishes():
    """Long diagonal strokes heat both screws; X and Y have different truths (Y's nut twice as
    warm). Replayed in each axis's simulator, a model equal to its truth leaves < 0.1 µm where
    the program as written is several µm off on both axes; one axis's model on both leaves Y off."""
    lines = ["G21 G90", "G0 X0 Y0", "F6000"]
    for k in range(60):
        lines += [f"G1 X{400 - (k % 3) * 50} Y{300 - (k % 4) * 40}", "G1 X10 Y5"]
    lines += ["G4 P60", "G1 X200 Y150", "M2"]
    text = "\n".join(lines) + "\n"
    warm = CoreParams(k3_W_per_mm_min=2 * CoreParams().k3_W_per_mm_min, k4_W_per_mm_min=2 * CoreParams().k4_W_per_mm_min)
    meta = seed000_metadata()
    res = precompensate_axes(text, {"X": AxisModel(oracle(), meta, "x"), "Y": AxisModel(oracle(warm), meta, "y")},
                             sample_s=0.5, decimals=5)  # fmt: skip
    vx = verify_in_simulator(res.axes["X"], truth_model())
    vy = verify_in_simulator(res.axes["Y"], truth_model(warm))
    for v in (vx, vy):
        assert v["moves"] == 122  # the first G0, 120 strokes, the last G1
        assert v["max_abs_before_um"] > 5.0
        assert v["max_abs_after_um"] < 0.1
    assert vy["max_abs_before_um"] > vx["max_abs_before_um"]  # the warmer nut
    wrong = precompensate_axes(text, {"X": AxisModel(oracle(), meta, "x"), "Y": AxisModel(oracle(), meta, "x")},
                               sample_s=0.5, decimals=5)  # fmt: skip
    assert verify_in_simulator(wrong.axes["Y"], truth_model(warm))["max_abs_after_um"] > 0.3 * vy["max_abs_before_um"]


def test_one_model_on_x_through_the_axes_path_sees_every_axis_take_time():
    """The one-axis path times the program on X alone (Y-only blocks take no time, as before);
    the axes path puts the Y moves on the time line: the same X model then predicts for later
    times."""
    text = "G21 G90\nG1 X0 Y0 F1000\nG1 X100\nG1 Y100\nG1 X0\nM2\n"
    meta = seed000_metadata()
    one = precompensate(text, stub(), meta)
    axes = precompensate_axes(text, {"X": AxisModel(stub(), meta, "x")})
    t_one = one.moves.loc[one.moves["compensate"], "t_end_s"].to_numpy()
    t_axes = axes.axes["X"].moves.loc[axes.axes["X"].moves["compensate"], "t_end_s"].to_numpy()
    np.testing.assert_allclose(t_one, [0, 6, 12])
    np.testing.assert_allclose(t_axes, [0, 6, 18])
    assert axes.as_written == {"Y": "no model"}


def test_axes_file(tmp_path):
    """Relative model paths are the file's directory's; every mistake names the file and the key."""
    sim = {"core": CoreParams().as_dict(), "effects": {}, "numerics": {"dx_m": 0.02, "dt_s": 0.5, "macro_dt_s": 10.0}}
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "metadata.yaml").write_text(yaml.safe_dump(seed000_metadata(sim).model_dump(mode="json", exclude_none=True)))
    joblib.dump(oracle(), tmp_path / "x.joblib")
    f = tmp_path / "axes.yaml"
    f.write_text("X: {model: x.joblib, dataset: data}\ny: {model: x.joblib, dataset: data, start_mm: 5, work_offset_mm: -2}\n")
    axes = read_axes_file(f)
    assert set(axes) == {"X", "Y"} and axes["Y"].start_mm == 5.0 and axes["Y"].work_offset_mm == -2.0
    assert axes["X"].metadata.machine.name == "seed000_test"
    for body, expected in [
        ("A: x.joblib\n", "key 'A': expected a linear axis"),
        ("X: {dataset: data}\n", "key 'X': expected a model file or a mapping with 'model'"),
        ("X: {model: x.joblib, dataset: data, offset: 1}\n", "key 'X': unknown key(s) ['offset']"),
        ("X: {model: x.joblib, dataset: data, start_mm: abc}\n", "key 'X': start_mm: expected a number in mm"),
        ("X: nothere.joblib\n", "nothere.joblib: no such model file"),
        ("X: x.joblib\n", "key 'X': cannot tell which dataset"),
        ("- X\n", "expected a mapping of axes to models"),
        ("Y: x.joblib\nX: [\n", "axes.yaml:3: not YAML"),  # the line of the problem
        ("X: {model: x.joblib, dataset: data}\nX: {model: x.joblib, dataset: data}\n", "axes.yaml:2: not YAML (key 'X' given twice)"),
        ("X: {model: x.joblib, dataset: nosuch}\n", "key 'X': dataset 'nosuch'"),
        ("X: {model: ., dataset: data}\n", "key 'X': " + str(tmp_path) + ": a directory"),
    ]:
        f.write_text(body)
        with pytest.raises(PrecompError, match=re.escape(expected)) as exc:
            read_axes_file(f)
        assert str(f) in str(exc.value) and "\n" not in str(exc.value)


def test_lathe_diameter_mode_is_refused_in_one_line_by_the_reader():
    """G7: X words are diameters. The reader refuses them (for X; Z is unaffected); --flatten auto
    has rs274 give radii (tests/test_rs274_flatten.py)."""
    text = "G18 G7 G21 G90\nG0 X20 Z5\nG1 X10 Z0 F100\nM2\n"
    with pytest.raises(ProgramError, match=r"lathe.nc:1: G7 \(lathe diameter mode\)"):
        parse_program(text, "X", source="lathe.nc")
    assert [b.target_mm for b in parse_program(text, "Z").blocks] == [5.0, 0.0]
    radius = "G18 G8 G21 G90\nG0 X10 Z5\nG1 X5 Z0 F100\nM2\n"
    res = precompensate_axes(radius, {"X": AxisModel(stub(), seed000_metadata(), "x"),
                                      "Z": AxisModel(stub_y(), seed000_metadata(), "z")})  # fmt: skip
    assert set(res.axes) == {"X", "Z"} and not any("G8" in u.reason for u in res.unsupported)


def test_cli_models(tmp_path, monkeypatch, capsys):
    sim = {"core": CoreParams().as_dict(), "effects": {}, "numerics": {"dx_m": 0.02, "dt_s": 0.5, "macro_dt_s": 10.0}}
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "metadata.yaml").write_text(yaml.safe_dump(seed000_metadata(sim).model_dump(mode="json", exclude_none=True)))
    joblib.dump(oracle(), tmp_path / "x.joblib")
    (tmp_path / "axes.yaml").write_text("X: {model: x.joblib, dataset: data}\nY: {model: x.joblib, dataset: data}\n")
    prog = tmp_path / "p.nc"
    prog.write_text(DIAGONAL)

    from thermbench.cli import main

    monkeypatch.chdir(tmp_path)

    def run(*args):  # the CLI in this process: its exit code, stdout and stderr
        code = main(["precompensate", *args])
        out = capsys.readouterr()
        return subprocess.CompletedProcess(args, code, out.out, out.err)

    ok = run("p.nc", "--models", "axes.yaml", "--out", "o.nc", "--verify")
    assert ok.returncode == 0, ok.stderr
    assert "axis X" in ok.stdout and "axis Y" in ok.stdout and ok.stdout.count("verification") == 2
    assert (tmp_path / "o.nc").read_text().startswith("(thermbench precompensate")
    for args, expected in [
        (("p.nc", "--out", "o2.nc"), "no model; expected one of --model"),
        (("p.nc", "--models", "axes.yaml", "--model", "x.joblib", "--out", "o2.nc"), "--model and --models together"),
        (("p.nc", "--models", "axes.yaml", "--work-offset", "3", "--out", "o2.nc"), "--work-offset with --models"),
        (("o.nc", "--models", "axes.yaml", "--out", "o2.nc"), "o.nc:1: already revised by thermbench precompensate"),
        (("p.nc", "--models", "axes.yaml", "--axis", "Y", "--out", "o2.nc"), "--axis with --models"),
        (("p.nc", "--models", "nothere.yaml", "--out", "o2.nc"), "nothere.yaml: cannot read the axes file"),
    ]:
        r = run(*args)
        assert r.returncode == 2 and expected in r.stderr and r.stderr.count("\n") == 1, (args, r.stderr)
        assert not (tmp_path / "o2.nc").exists()
    res = run_precompensate_axes(prog, tmp_path / "axes.yaml", tmp_path / "o3.nc")
    assert Path(res.settings["out_path"]).read_text() == res.text


def test_an_axis_without_a_model_that_the_reader_cannot_follow_is_left_out_of_the_time_line():
    """G28 Z0 puts Z somewhere the program does not say: with no Z model, Z is left out of the time
    line (and the header says so); with one, the program is refused in one line naming the line."""
    text = "G21 G90\nG0 X0 Z5\nG1 X100 Z0 F1000\nG91 G28 Z0\nG90 G1 X0\nM2\n"
    meta = seed000_metadata()
    res = precompensate_axes(text, {"X": AxisModel(stub(), meta, "x")}, source="p.nc")
    assert "not timed" in res.as_written["Z"] and "p.nc:4: G28 with a Z word" in res.as_written["Z"]
    moves = res.axes["X"].moves
    np.testing.assert_allclose(moves.loc[moves["compensate"], "t_end_s"], [0.0, 6.0, 12.0])  # X alone: 100 mm at F1000
    assert "(axis Z: as written, no model; its motion is not timed" in res.text
    with pytest.raises(ProgramError, match="p.nc:4: G28 with a Z word"):
        precompensate_axes(text, {"X": AxisModel(stub(), meta, "x"), "Z": AxisModel(stub(), meta, "z")}, source="p.nc")


def test_arcs_and_other_axes_notes_are_said_once_for_the_time_line():
    text = "G21 G90 G17\nG0 X0 Y0\nG2 X10 Y0 I5 J0 F600\nG91 G28 Z0\nG90 G1 X20 Y5\nM2\n"
    res = precompensate_axes(text, {"X": AxisModel(stub(), seed000_metadata(), "x"),
                                    "Y": AxisModel(stub_y(), seed000_metadata(), "y")})  # fmt: skip
    listed = {u.line: u.reason for u in res.unsupported}
    assert listed[3] == "G2 with X, Y: end point followed, timed on its chord over the axes, not compensated"
    assert "G28 not interpreted (X, Y not involved)" in listed[4] and listed[4].count("G28") == 1
