"""Dataset format 2 (docs/dataset-format.md "Format 2"), on small hand-written datasets:
what it admits that format 1 refused, each mistake as one line, and what models see."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import pytest
import yaml

from thermbench.data import DatasetError, load_dataset
from thermbench.data.reference import thermal_errors
from thermbench.data.views import channel_view, split_segments
from thermbench.models.base import ModelError

SPINDLE_META = {
    "format": "thermbench-dataset/2",
    "machine": {"name": "vmc_spindle"},
    "parts": ["spindle"],
    "sensors": {"T_front": "spindle_front_bearing", "T_amb": "ambient"},
    "channels": {
        "Z": {"kind": "fixed_point", "direction": "Z", "location": "test_mandrel"},
        "X1": {"kind": "fixed_point", "direction": "X", "location": "test_mandrel", "position_mm": 0},
        "X2": {"kind": "fixed_point", "direction": "X", "location": "test_mandrel", "position_mm": 100},
    },
    "reference": {"mode": "first_reading"},
    "runs": {"r1": {}},
}


def spindle_tables(step_s: float = 15.0, n: int = 200):
    t = np.arange(n) * step_s
    rpm = np.where((t >= 60) & (t < 1560), 3000.0, 0.0)  # 25 min on, 24 min off
    process = pd.DataFrame({"run_id": "r1", "t_s": t, "spindle_rpm": rpm, "T_front_C": 20 + 0.01 * t,
                            "T_amb_C": 20.0})  # fmt: skip
    rows = []
    for ch, k in (("Z", 0.05), ("X1", 0.01), ("X2", 0.02)):
        rows += [{"run_id": "r1", "t_s": ti, "channel": ch, "error_um": 1.0 + k * ti} for ti in t]
    return process, pd.DataFrame(rows)


def write(root: Path, meta: dict, process: pd.DataFrame, errors: pd.DataFrame | None) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    (root / "metadata.yaml").write_text(yaml.safe_dump(meta, sort_keys=False), encoding="utf-8")
    process.to_csv(root / "process.csv", index=False)
    if errors is not None:
        errors.to_csv(root / "errors.csv", index=False)
    return root


def refused(root: Path) -> str:
    with pytest.raises(DatasetError) as exc:
        load_dataset(root)
    msg = str(exc.value)
    assert "\n" not in msg
    return msg


def test_spindle_test_without_axis_feed_or_screw(tmp_path):
    p, e = spindle_tables()
    ds = load_dataset(write(tmp_path / "d", SPINDLE_META, p, e))
    assert ds.metadata.has_spindle and not ds.metadata.has_axis and ds.metadata.screw is None
    te = thermal_errors(ds)
    z = te[te["channel"] == "Z"]
    # first_reading: reading minus the first one, 0.05 µm/s by construction
    np.testing.assert_allclose(z["thermal_um"], 0.05 * z["t_s"], atol=1e-12)
    view = channel_view(ds, "Z")
    assert (view.errors["target_mm"] == 0).all() and (view.process["axis_mm"] == 0).all()
    np.testing.assert_allclose(view.errors["thermal_um"], 0.05 * view.errors["t_s"], atol=1e-12)


def test_slow_logger_gap_rule_inferred_and_declared(tmp_path):
    p, e = spindle_tables(step_s=15.0)
    load_dataset(write(tmp_path / "ok", SPINDLE_META, p, e))  # 15 s steps: no 1 Hz rule any more
    p2 = p.drop(index=range(10, 16)).reset_index(drop=True)  # a 105 s hole, 7 x the 15 s median step
    e2 = e[~e["t_s"].isin(p.loc[10:15, "t_s"])]
    msg = refused(write(tmp_path / "gap", SPINDLE_META, p2, e2))
    assert "column 't_s', row 11 (line 12): gap of 105 s in run 'r1', more than 75 s" in msg
    assert "declare sampling.max_gap_s" in msg
    meta = {**SPINDLE_META, "sampling": {"max_gap_s": 120}}
    load_dataset(write(tmp_path / "declared", meta, p2, e2))


def test_runs_without_readings_are_valid(tmp_path):
    p, _ = spindle_tables()
    ds = load_dataset(write(tmp_path / "d", SPINDLE_META, p, None))
    assert ds.errors.empty and len(ds.process) == len(p)


def test_fixed_point_reading_with_a_target_is_refused(tmp_path):
    p, e = spindle_tables()
    e["target_mm"] = np.nan
    e.loc[3, "target_mm"] = 10.0
    msg = refused(write(tmp_path / "d", SPINDLE_META, p, e))
    assert "errors.csv: column 'target_mm', row 4 (line 5): channel 'Z' is a fixed_point channel" in msg


def test_unknown_channel_and_missing_channel_column(tmp_path):
    p, e = spindle_tables()
    e.loc[5, "channel"] = "Y1"
    assert "column 'channel', row 6 (line 7): unknown channel 'Y1'" in refused(write(tmp_path / "a", SPINDLE_META, p, e))
    p, e = spindle_tables()
    msg = refused(write(tmp_path / "b", SPINDLE_META, p, e.drop(columns="channel")))
    assert "missing column 'channel'; metadata.yaml declares 3 channels" in msg


def test_v2_keys_need_format_2_and_v1_keys_stay_required(tmp_path):
    p, e = spindle_tables()
    meta = {**SPINDLE_META, "format": "thermbench-dataset/1"}
    msg = refused(write(tmp_path / "a", meta, p, e))
    assert "metadata.yaml: key 'machine.axis': missing (required)" in msg
    meta = {**SPINDLE_META}
    del meta["parts"]
    assert "key 'parts': missing; list what the dataset is a test of" in refused(write(tmp_path / "b", meta, p, e))
    meta = {**SPINDLE_META, "channels": {"Z": {"kind": "along_axis", "direction": "Z", "location": "t"}}}
    assert "key 'channels.Z': kind along_axis measures along a linear axis" in refused(write(tmp_path / "c", meta, p, e))


def test_tilt_channel_unit(tmp_path):
    p, e = spindle_tables()
    meta = {**SPINDLE_META, "channels": {**SPINDLE_META["channels"], "B": {"kind": "fixed_point", "direction": "B",
                                                                           "location": "spindle", "unit": "um"}}}  # fmt: skip
    assert "direction B is measured in urad, not um" in refused(write(tmp_path / "a", meta, p, e))


AXIS_META = {
    "format": "thermbench-dataset/2",
    "machine": {"name": "lab", "axis": "X"},
    "parts": ["axis"],
    "sensors": {"T_nut": "nut_housing"},
    "channels": {"X": {"kind": "along_axis", "direction": "X", "location": "table"}},
    "runs": {"r1": {"condition": {"feed_mm_min": 600}}},
}


def axis_tables():
    t = np.arange(0.0, 400.0, 0.5)
    x = 50.0 * (1 - np.cos(2 * np.pi * t / 200.0))  # 0..100 mm, smooth
    process = pd.DataFrame({"run_id": "r1", "t_s": t, "axis_mm": x, "T_nut_C": 20.0 + 0.01 * t})
    rows = []
    for c, t0 in enumerate((10.0, 300.0)):
        for k, (tg, d) in enumerate([(0, 1), (50, 1), (100, 1), (100, -1), (50, -1), (0, -1)]):
            # geometric 0.02 x, reversal 3 µm (+1.5 / -1.5), thermal 0.001 x t (c = 1 only)
            rows.append({"run_id": "r1", "t_s": t0 + k, "target_mm": tg, "direction": d,
                         "error_um": 0.02 * tg + 1.5 * d + (0.001 * tg * t0 if c else 0.0)})  # fmt: skip
    return process, pd.DataFrame(rows)


def test_feed_derived_from_axis_position(tmp_path):
    p, e = axis_tables()
    ds = load_dataset(write(tmp_path / "d", AXIS_META, p, e))
    t = p["t_s"].to_numpy()
    exact = np.abs(50.0 * 2 * np.pi / 200.0 * np.sin(2 * np.pi * t / 200.0)) * 60.0  # |dx/dt| * 60, by hand
    inner = slice(1, -1)  # central differences inside the run
    np.testing.assert_allclose(ds.process["feed_mm_min"].to_numpy()[inner], exact[inner], rtol=0, atol=0.2)


def test_direction_keeps_the_reversal_out_of_the_thermal_error(tmp_path):
    p, e = axis_tables()
    ds = load_dataset(write(tmp_path / "d", AXIS_META, p, e))
    te = thermal_errors(ds)
    want = np.where(te["t_s"] >= 300, 0.001 * te["target_mm"] * 300.0, 0.0)
    np.testing.assert_allclose(te["thermal_um"], want, atol=1e-12)
    bad = e.copy()
    bad.loc[2, "direction"] = 0
    msg = refused(write(tmp_path / "bad", AXIS_META, p, bad))
    assert "column 'direction', row 3 (line 4): must be 1 (approach in the positive direction) or -1" in msg


def test_along_axis_reading_needs_a_target(tmp_path):
    p, e = axis_tables()
    e.loc[1, "target_mm"] = np.nan
    msg = refused(write(tmp_path / "d", AXIS_META, p, e))
    assert "column 'target_mm', row 2 (line 3): missing value; a reading of along_axis channel 'X' needs its target" in msg


def test_segment_names_must_match_what_is_derived(tmp_path):
    p, e = spindle_tables()
    meta = {**SPINDLE_META, "runs": {"r1": {"segments": ["a", "b"]}}}
    ds = load_dataset(write(tmp_path / "d", meta, p, e))
    with pytest.raises(DatasetError, match=r"key 'runs.r1.segments': names 2 segments, but 1 were derived from spindle_rpm"):
        split_segments(ds)
    meta = {**SPINDLE_META, "runs": {"r1": {"segments": ["heat3000"]}}}
    seg = split_segments(load_dataset(write(tmp_path / "e", meta, p, e)))
    assert list(seg.metadata.runs) == ["heat3000"]
    assert seg.metadata.runs["heat3000"].condition.levels() == {"spindle_rpm": 3000.0}
    assert seg.process_run("heat3000")["t_s"].iloc[0] == 60.0  # the operation starts at 60 s


def test_screw_physics_model_on_a_spindle_test_is_one_line(tmp_path):
    from thermbench.models.physics import PhysicsModel

    p, e = spindle_tables()
    view = channel_view(load_dataset(write(tmp_path / "d", SPINDLE_META, p, e)), "Z")
    with pytest.raises(ModelError, match=r"PhysicsModel needs a screw block .* \(a test of: spindle\) has none"):
        PhysicsModel().fit(view)


def test_own_datasets_never_share_a_registered_name(tmp_path):
    from thermbench.experiment import load_split

    p, e = axis_tables()
    a = write(tmp_path / "a", AXIS_META, p, e)
    e2 = e.assign(error_um=e["error_um"] + 0.5)
    b = write(tmp_path / "b", AXIS_META, p, e2)
    src = {"_target_": "thermbench.data.io.load_dataset"}
    sa = load_split({"name": None, "source": {**src, "path": str(a)}})
    sb = load_split({"name": None, "source": {**src, "path": str(b)}})
    assert sa.name == sb.name == "lab"  # the machine's name
    assert sa.registry_name("mlr_seed002") != sb.registry_name("mlr_seed002")
    assert sa.registry_name("mlr_seed002").startswith("thermbench-lab-X-")


def test_benchmark_skips_families_a_dataset_cannot_serve(tmp_path):
    from thermbench.bench import family_lacks

    p, e = spindle_tables()
    view = channel_view(load_dataset(write(tmp_path / "d", SPINDLE_META, p, e)), "Z")
    assert "a screw block" in family_lacks("physics", view)
    assert "along a linear axis" in family_lacks("mlr_seed001", view)
    assert family_lacks("mlr_seed002", view) is None and family_lacks("bank_mlr_seed002", view) is None
    pa, ea = axis_tables()
    axis_view = channel_view(load_dataset(write(tmp_path / "a", AXIS_META, pa, ea)), "X")
    assert family_lacks("mlr_seed001", axis_view) is None
    assert family_lacks("physics", axis_view) == "needs a screw block (metadata 'screw': the ball screw's geometry)"


def test_iso230_tilt_by_position_and_drift_from_a_time_reference(tmp_path):
    from thermbench.iso230.report import compute

    p, e = spindle_tables()
    # X2 declared before X1, further out: the tilt is (X2 - X1) / 100 mm whatever the order
    meta = {**SPINDLE_META, "channels": {"X2": SPINDLE_META["channels"]["X2"], "X1": SPINDLE_META["channels"]["X1"],
                                         "Z": SPINDLE_META["channels"]["Z"]},
            "reference": {"mode": "time", "t_s": 1500.0}}  # fmt: skip
    figs = compute(load_dataset(write(tmp_path / "d", meta, p, e)))
    run = figs["runs"]["r1"]
    # by hand: X1 = 1 + 0.01 t, X2 = 1 + 0.02 t; from the reference at 1500 s, X2 - X1 = 0.01 (t - 1500) µm;
    # largest |.| at t = 0 (15 µm) vs t = 2985 (14.85 µm): 15 µm over 100 mm = 150 µrad, signed -150
    (pair, tl), = run["tilt"].items()
    assert pair == "X1-X2" and tl["signed_urad"] == pytest.approx(-150.0) and tl["t_s"] == 0.0
    z = next(r for r in run["channels"]["Z"]["drift"] if r["block"] == "all")
    # Z = 1 + 0.05 t, from its value at 1500 s: largest |.| = 0.05 * 1500 = 75 µm at t = 0
    assert z["max_from_reference_um"] == pytest.approx(75.0) and z["max_from_reference_signed_um"] == pytest.approx(-75.0)


@pytest.mark.parametrize("mode", ["first_reading", "cold_cycle"])
def test_iso230_outputs_name_the_frame(tmp_path, monkeypatch, mode):
    """report.md, figures.json and every figure's title name the frame the dataset declares
    (data.reference.frame_text): a first_reading test is never said to count from a cold cycle."""
    import json

    from thermbench import report
    from thermbench.data.reference import frame_text
    from thermbench.iso230.report import iso230_report

    titles, save = [], report.figures._save
    monkeypatch.setattr(report.figures, "_save", lambda fig, path: (titles.append(fig.axes[0].get_title()), save(fig, path))[1])
    p, e = spindle_tables()
    ds = load_dataset(write(tmp_path / "d", {**SPINDLE_META, "reference": {"mode": mode}}, p, e))
    iso230_report(ds.path, tmp_path / "iso")
    frame = frame_text(ds.metadata)
    said, other = ("first reading", "cold measuring cycle") if mode == "first_reading" else ("cold measuring cycle", "first reading")
    assert said in frame and other not in frame
    md = (tmp_path / "iso" / "report.md").read_text(encoding="utf-8")
    assert f"\nScored on: {frame} — " in md and other not in md
    assert json.loads((tmp_path / "iso" / "figures.json").read_text(encoding="utf-8"))["frame"] == frame
    assert titles == [f"vmc_spindle · run r1\nscored on {frame}"]


def test_iso230_unidirectional_run_gets_its_one_direction_figures(tmp_path):
    from thermbench.iso230.report import compute

    p, e = axis_tables()
    up = e[e["direction"] == 1].drop(columns="direction")
    figs = compute(load_dataset(write(tmp_path / "d", AXIS_META, p, up)))
    a = figs["runs"]["r1"]["channels"]["X"]["iso230_2_run"]
    # by hand, deviations 0.02 x + 1.5 (+ 0.3 x in cycle 2 at t0 = 300: 0.001 x 300): targets 0, 50, 100
    # cycle 1: 1.5, 2.5, 3.5; cycle 2: 1.5, 17.5, 33.5 -> means 1.5, 10, 18.5: E_up = 17
    assert a["E_up_um"] == pytest.approx(17.0) and a["E_um"] == pytest.approx(17.0)
    assert a["B_um"] is None and a["M_um"] is None  # undefined with one direction (NaN -> null)


def test_iso230_environmental_figure_only_over_the_machine_at_rest(tmp_path):
    from thermbench.iso230.report import compute

    p, e = spindle_tables()
    p["T_amb_C"] = 20.0 + 0.001 * p["t_s"]
    figs = compute(load_dataset(write(tmp_path / "d", SPINDLE_META, p, e)))
    ev = figs["runs"]["r1"]["channels"]["Z"]["environmental"]
    # by hand: at rest for t < 60 s and t >= 1560 s (readings every 15 s to 2985 s); Z drift = 0.05 t:
    # range 0.05 * 2985 - 0 = 149.25 µm, ambient 0.001 * 2985 - 20... range 2.985 °C
    assert ev["etve_um"] == pytest.approx(149.25) and ev["ambient_range_C"] == pytest.approx(2.985)
    assert ev["at_rest_s"] == pytest.approx(45.0 + (2985.0 - 1560.0))


def test_a_model_is_scored_on_the_channel_it_was_fitted_on(tmp_path):
    from thermbench.experiment import ExperimentError, dataset_config_for, model_from_config

    p, e = spindle_tables()
    view = channel_view(load_dataset(write(tmp_path / "d", SPINDLE_META, p, e)), "Z")
    model = model_from_config("mlr_seed002").set_params(sensors=["T_front"]).fit(view)
    assert model.channel_ == "Z"
    assert dataset_config_for(model, {"source": {}, "channel": None})["channel"] == "Z"
    with pytest.raises(ExperimentError, match=r"'dataset.channel': the model predicts error channel 'Z' .* not 'X1'"):
        dataset_config_for(model, {"source": {}, "channel": "X1"})


def test_a_declared_operating_input_is_a_checked_numeric_column(tmp_path):
    p, e = spindle_tables()
    meta = {**SPINDLE_META, "operating": ["spindle_rpm", "coolant_l_min"]}
    msg = refused(write(tmp_path / "a", meta, p, e))
    assert "process.csv: missing column(s) ['coolant_l_min']" in msg
    p["coolant_l_min"] = ["off" if i == 7 else "5.0" for i in range(len(p))]
    assert "column 'coolant_l_min', row 8 (line 9): expected a number, got 'off'" in refused(write(tmp_path / "b", meta, p, e))
    p["coolant_l_min"] = 5.0
    ds = load_dataset(write(tmp_path / "c", meta, p, e))
    assert ds.metadata.operating_inputs() == ["spindle_rpm", "coolant_l_min"]
    assert ds.process["coolant_l_min"].dtype == float


def test_a_derived_segment_is_a_run_of_its_own_for_the_models(tmp_path):
    from thermbench.experiment import dataset_view

    p, e = spindle_tables()
    meta = {**SPINDLE_META, "runs": {"r1": {"segments": ["heat3000"]}}}
    view = dataset_view(load_dataset(write(tmp_path / "d", meta, p, e)), "Z", True)
    er = view.errors_run("heat3000")
    # Z = 1 + 0.05 t; the segment starts at 60 s: its thermal error counts from its first reading there
    assert er["t_s"].iloc[0] == 60.0
    np.testing.assert_allclose(er["thermal_um"], 0.05 * (er["t_s"] - 60.0), atol=1e-12)


def test_segmentation_settings_in_the_metadata(tmp_path):
    p, e = spindle_tables()
    t = p["t_s"]
    p["spindle_rpm"] = np.where(((t >= 60) & (t < 1560)) | ((t >= 2100) & (t < 2400)), 3000.0, 0.0)  # + a 300 s run
    # by default a period must last 10 windows (10 x 5 x 15 s = 750 s): the 300 s run is no segment of its own
    assert list(split_segments(load_dataset(write(tmp_path / "a", SPINDLE_META, p, e))).metadata.runs) == ["s01_3000rpm"]
    meta = {**SPINDLE_META, "segmentation": {"min_duration_s": 200}}
    seg = split_segments(load_dataset(write(tmp_path / "b", meta, p, e)))
    assert list(seg.metadata.runs) == ["s01_3000rpm", "s02_3000rpm"]
    assert seg.process_run("s02_3000rpm")["t_s"].iloc[0] == 2100.0


@pytest.mark.parametrize("mode", ["first_reading", "cold_cycle"])
def test_channel_view_keeps_each_runs_own_reference(tmp_path, mode):
    """Two runs of one fixed-point channel whose raw readings start at 0 and at 100 µm. With
    first_reading (each run's zero is its own) the view's error_um, what models predict and scores
    compare, is each run's drift from its own first reading; with cold_cycle (the reading is not
    re-zeroed) it is each run's reading. Never one reference averaged over the runs."""
    t = np.arange(0.0, 600.0, 15.0)
    process = pd.concat([pd.DataFrame({"run_id": r, "t_s": t, "spindle_rpm": 1000.0, "T_front_C": 20.0, "T_amb_C": 20.0})
                         for r in ("r1", "r2")], ignore_index=True)  # fmt: skip
    errors = pd.concat([pd.DataFrame({"run_id": r, "t_s": t, "channel": "Z", "error_um": z0 + 0.01 * t})
                        for r, z0 in (("r1", 0.0), ("r2", 100.0))], ignore_index=True)  # fmt: skip
    meta = {**SPINDLE_META, "channels": {"Z": SPINDLE_META["channels"]["Z"]}, "reference": {"mode": mode},
            "runs": {"r1": {"condition": {"spindle_rpm": 1000}}, "r2": {"condition": {"spindle_rpm": 1000}}}}  # fmt: skip
    view = channel_view(load_dataset(write(tmp_path / "d", meta, process, errors)), "Z")
    for r, z0 in (("r1", 0.0), ("r2", 100.0)):
        er = view.errors_run(r)
        np.testing.assert_allclose(er["error_um"], (z0 if mode == "cold_cycle" else 0.0) + 0.01 * er["t_s"])
        np.testing.assert_allclose(er["thermal_um"], 0.01 * er["t_s"], atol=1e-12)
