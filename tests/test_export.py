"""Export for the embedded compensator: the model file format, the C runtime's parity with
the Python models on held-out runs (seed 002 §2.5: the compensator loads models at run
time), bad files, ONNX, reduced-set LSSVM, the export job and ``thermbench replay``.

The C runtime is compiled here with gcc (-std=c99 -Wall -Wextra -Werror -pedantic), once
more under -fsanitize=address,undefined. The tolerance 0.01 um is the requirement;
the Python models are the reference.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from thermbench.bench.datasets import load_benchmark
from thermbench.export import ExportOptions, Kind, ModelFileError, export_model, pack, read_manifest, replay_dir, unpack
from thermbench.export import runtime
from thermbench.export.samples import readings_queries
from thermbench.models.autoregressive import AutoRegressiveSeed003
from thermbench.models.bank import ConditionBank
from thermbench.models.mlr import MLRSeed002, MLRSeed004
from thermbench.models.physics import PhysicsModel

from .families import FAST_PHYSICS, HELDOUT, TRAIN, families as _families  # noqa: F401

TOL_UM = 0.01  # required: the C runtime reproduces the Python models within 0.01 um


@pytest.fixture(scope="module")
def ds(seed001_data_root):
    return load_benchmark("seed001_vmc_x", seed001_data_root)


@pytest.fixture(scope="module")
def loaded_ds(ds):
    """seed001 with an axial load column (for the load-dependent heat effect and the AR load term)."""
    from thermbench.data.dataset import Dataset

    pr = ds.process.copy()
    pr["load_N"] = 800.0 + 0.05 * pr["feed_mm_min"] + 100.0 * np.sin(pr["t_s"] / 900.0)
    return Dataset(ds.metadata, pr, ds.errors.copy(), path=ds.path)


@pytest.fixture(scope="module")
def exported(ds, tmp_path_factory):
    """Every family fitted on the five loading states and exported (with the parity check)."""
    root = tmp_path_factory.mktemp("exports")
    out = {}
    for name, model in _families().items():
        m = model.fit(ds, TRAIN)
        man = export_model(m, root / name, name, ds, HELDOUT, options=ExportOptions(lssvm_reduced_size=40))
        out[name] = (m, root / name, man)
    return out


def _c_vs_python(model, model_dir, ds, runs, sanitize=False):
    worst, n = 0.0, 0
    for run in runs:
        q = readings_queries(ds, run)
        c = replay_dir(model_dir, ds, run, q, sanitize=sanitize)
        py = model.predict_at(ds, run, q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
        worst = max(worst, float(np.max(np.abs(c["total_um"].to_numpy() - py))))
        n += len(q)
    return worst, n


@pytest.mark.parametrize("name", ["mlr_seed001", "mlr_seed002", "mlr_seed004", "gru", "mlp", "lssvm", "physics", "ar_seed003"])
def test_float_and_double_agree_at_every_sample_also_at_t_2_22(exported, ds, name):
    """Every process sample of a held-out run (grid and macro-step times, the stream's end)
    in the single- and the double-precision build, the run as recorded and moved to t = 2^22 s,
    where floats are 0.5 s apart: the same answers to rounding (measured: at most 4e-4 um)."""
    from .families import double_and_float_at_every_sample

    _, model_dir, man = exported[name]
    assert man["parity"]["model"]["float_vs_double_every_sample_max_abs_um"] < 1e-3  # the export's own check
    for shift_s in (0.0, 2.0**22):
        double, single = double_and_float_at_every_sample(
            ds, "valid1", shift_s, lambda data, q, exe: replay_dir(model_dir, data, "valid1", q, exe=exe))
        assert len(double) == len(ds.process_run("valid1")) and np.max(np.abs(single - double)) < 1e-3, shift_s


# ------------------------------------------------------------ format ---
def test_pack_unpack_round_trip_and_header_fields():
    data = pack(Kind.MLR_CURVE, [2, 1], [0.0, 1.5, -2.25])
    assert data[:4] == b"TBMF"
    assert struct.unpack_from("<HHH", data, 4) == (1, Kind.MLR_CURVE, 2)
    assert struct.unpack_from("<I", data, 44)[0] == 3
    assert len(data) == 48 + 3 * 4 + 4
    assert struct.unpack_from("<I", data, len(data) - 4)[0] == zlib.crc32(data[:-4])
    mf = unpack(data)
    assert mf.kind == Kind.MLR_CURVE and mf.dims == (2, 1)
    assert mf.payload.tolist() == [0.0, 1.5, -2.25]


@pytest.mark.parametrize(
    "mutate, message",
    [
        (lambda d: d[:40], "shorter"),
        (lambda d: b"XXXX" + d[4:], "magic"),
        (lambda d: d[:4] + struct.pack("<H", 7) + d[6:], "version 7"),
        (lambda d: d[:-5] + bytes([d[-5] ^ 1]) + d[-4:], "CRC"),
        (lambda d: d + b"\0\0\0\0", "announces"),
    ],
)
def test_python_reader_names_what_is_wrong(mutate, message):
    data = pack(Kind.MLR_CURVE, [2, 1], [0.0, 1.5, -2.25])
    with pytest.raises(ModelFileError, match=message):
        unpack(mutate(data), "m.tbm")


def test_pack_refuses_values_float32_cannot_hold():
    with pytest.raises(ModelFileError, match="not a finite float32"):
        pack(Kind.MLR_CURVE, [0, 0], [1.0, 1e39])
    with pytest.raises(ModelFileError, match="not a finite float32"):
        pack(Kind.MLR_CURVE, [0, 0], [np.nan])


# ------------------------------------------------------------ parity ---
@pytest.mark.parametrize("family", list(_families()))
def test_c_runtime_reproduces_every_family_on_heldout_runs(exported, ds, family):
    """Every family: the C runtime, fed the held-out runs' process logs sample by sample,
    predicts the positioning error at every reading within 0.01 um of the Python model."""
    model, model_dir, man = exported[family]
    worst, n = _c_vs_python(model, model_dir, ds, HELDOUT)
    assert n > 300
    assert worst < TOL_UM, f"{family}: max |C - Python| = {worst} um"
    # the export recorded the same check, and the single-precision build's (-DTB_SINGLE, the
    # Cortex-M4F's; gcc on the host) over the whole held-out runs: within 0.01 um too
    assert man["parity"]["model"]["max_abs_diff_um"] < TOL_UM
    assert man["parity"]["model"]["float_max_abs_diff_um"] < TOL_UM, (family, man["parity"]["model"])
    assert man["parity"]["runs"] == HELDOUT


def test_physics_with_every_effect_and_an_ar_load_term(loaded_ds, tmp_path):
    """The effects the C physics implements (motor heat lag, free-end bearing, viscous and
    load-dependent nut heat, origin drift through the fixed-bearing housing, fixed-fixed
    suppression, a simulated ambient drift) and an AR model with a load input."""
    effects = {
        "motor_heat": {"tau_s": 1200.0}, "free_end_bearing_heat": {}, "quadratic_friction_heat": {},
        "load_dependent_heat": {}, "origin_drift": {"beta_um_per_K": 1.5}, "fixed_fixed_constraint": {"kappa": 0.3},
        "ambient_drift": {"amplitude_C": 0.8, "period_s": 20000.0, "rate_C_per_h": 0.1},
    }  # fmt: skip
    phys = PhysicsModel(effects=effects, ambient_sensor=None, **FAST_PHYSICS).fit(loaded_ds, TRAIN[:2])
    assert phys.effects_["motor_heat"]["k_motor_W_per_mm_min"] >= 0
    ar = AutoRegressiveSeed003(operating=["feed_mm_min", "load_N"], na=1, nb=2).fit(loaded_ds, TRAIN)
    for name, m in (("phys", phys), ("ar", ar)):
        man = export_model(m, tmp_path / name, name, loaded_ds, ["valid2"])
        assert man["needs_load"]
        assert any(i["name"] == "load_N" and i["unit"] == "N" for i in man["inputs"])
        worst, _ = _c_vs_python(m, tmp_path / name, loaded_ds, ["valid2"])
        assert worst < TOL_UM, f"{name}: {worst}"


def test_bank_switches_models_online_like_python(ds, tmp_path):
    """seed 002 §2.4-2.5: the classifier runs in C on the motion window and picks the same
    condition model as the Python bank at every reading; the predictions agree."""
    bank = ConditionBank(MLRSeed002(sensors=["T_nut", "T_bed"])).fit(ds, TRAIN)
    man = export_model(bank, tmp_path / "bank", "bank", ds, HELDOUT)
    assert man["kind"] == "bank" and len(man["bank"]["members"]) == len(bank.labels_)
    assert [m["label"] for m in man["bank"]["members"]] == [str(c) for c in bank.classifier_.classes_]
    for run in HELDOUT:
        q = readings_queries(ds, run)
        c = replay_dir(tmp_path / "bank", ds, run, q)
        labels = [str(bank.classifier_.classes_[i]) if i >= 0 else None for i in c["label"]]
        assert labels == list(bank.conditions_at(ds, run, q["t_s"].to_numpy()))
        assert len({lab for lab in labels if lab}) >= 1
        py = bank.predict_at(ds, run, q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
        assert np.max(np.abs(c["total_um"].to_numpy() - py)) < TOL_UM


def test_sanitizers_find_nothing_on_a_bank_and_the_physics_model(exported, ds, tmp_path):
    """The runtime under -fsanitize=address,undefined: same numbers, no report (a report
    makes the tool exit non-zero, which raises)."""
    model, model_dir, _ = exported["physics"]
    worst, _ = _c_vs_python(model, model_dir, ds, ["valid2"], sanitize=True)
    assert worst < TOL_UM
    model, model_dir, _ = exported["gru"]
    worst, _ = _c_vs_python(model, model_dir, ds, ["valid2"], sanitize=True)
    assert worst < TOL_UM


# ------------------------------------------------------------ bad files ---
def _info(path: Path) -> tuple[int, str]:
    import subprocess

    exe = runtime.build("tb_replay", sanitize=True)
    res = subprocess.run([str(exe), "--info", str(path)], capture_output=True, text=True)
    return res.returncode, res.stderr


def _refresh_crc(d: bytes) -> bytes:
    return d[:-4] + struct.pack("<I", zlib.crc32(d[:-4]) & 0xFFFFFFFF)


@pytest.mark.parametrize(
    "mutate, code",
    [
        (lambda d: d[: len(d) // 2], -1),  # truncated
        (lambda d: b"TBMX" + d[4:], -2),  # magic
        (lambda d: _refresh_crc(d[:4] + struct.pack("<H", 2) + d[6:]), -3),  # version
        (lambda d: _refresh_crc(d[:6] + struct.pack("<H", 99) + d[8:]), -4),  # kind
        (lambda d: d[:60] + bytes([d[60] ^ 0x10]) + d[61:], -5),  # one flipped bit: CRC
        (lambda d: _refresh_crc(d[:16] + struct.pack("<I", 10**9) + d[20:]), -6),  # absurd dims
        (lambda d: _refresh_crc(d[:48 + 4 * 9] + struct.pack("<f", float("nan")) + d[48 + 4 * 10 :]), -7),  # NaN
        (lambda d: _refresh_crc(d[:48 + 4 * 9] + struct.pack("<f", float("inf")) + d[48 + 4 * 10 :]), -7),
    ],
)
def test_bad_model_files_give_an_error_code_not_an_overread(exported, tmp_path, mutate, code):
    """Each corruption is refused with its own code by the loader built with ASan+UBSan
    (an out-of-bounds read would abort with a sanitizer report instead)."""
    good = (exported["gru"][1] / "model.tbm").read_bytes()
    bad = tmp_path / "bad.tbm"
    bad.write_bytes(mutate(good))
    rc, err = _info(bad)
    assert rc == 3, err
    assert f"error {code}:" in err, err
    assert "Sanitizer" not in err


# ------------------------------------------------------------ extras ---
def test_onnx_matches_the_nets(exported, ds):
    """ONNX (float32) of the thermal part, checked by onnxruntime at export and here again."""
    import onnxruntime as ort

    for fam in ("mlp", "gru"):
        model, model_dir, man = exported[fam]
        assert man["onnx"]["onnxruntime_max_abs_diff_um"] < 1e-3
        sess = ort.InferenceSession(str(model_dir / "model.onnx"), providers=["CPUExecutionProvider"])
        q = readings_queries(ds, "valid2").iloc[::7]
        inputs = model._inputs(ds, "valid2", q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
        feed = {i.name: np.asarray(a, dtype=np.float32) for i, a in zip(sess.get_inputs(), inputs)}
        got = sess.run(None, feed)[0]
        ref = model.predict_thermal_at(ds, "valid2", q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
        assert np.max(np.abs(got - ref)) < 1e-3


def test_reduced_set_lssvm_is_smaller_and_reports_its_cost(exported, ds):
    model, model_dir, man = exported["lssvm"]
    full, red = man["files"]["model"], man["files"]["reduced"]
    assert red["support_vectors"] == 40 and red["from_support_vectors"] == model.n_support_
    assert red["bytes"] < full["bytes"] / 5
    par = man["parity"]
    assert par["reduced"]["max_abs_diff_um"] < TOL_UM  # the C reduced file = the Python reduced model
    # the reported cost is the held-out RMSE difference, recomputed here from the C predictions
    res = []
    for variant in ("model", "reduced"):
        errs = []
        for run in HELDOUT:
            q = readings_queries(ds, run)
            c = replay_dir(model_dir, ds, run, q, variant)
            errs.append(q["error_um"].to_numpy() - c["total_um"].to_numpy())
        res.append(float(np.sqrt(np.mean(np.concatenate(errs) ** 2))))
    assert abs((res[1] - res[0]) - par["reduced_cost_um"]) < 1e-3


def test_manifest_lists_inputs_units_preprocessing_and_training(exported, ds):
    _, model_dir, man = exported["mlr_seed002"]
    disk = read_manifest(model_dir)
    assert disk == json.loads((model_dir / "manifest.json").read_text())
    names = [i["name"] for i in disk["inputs"]]
    assert names[:3] == ["t_s", "axis_mm", "feed_mm_min"]
    temps = [i for i in disk["inputs"] if i["unit"] == "°C"]
    assert [t["sensor"] for t in temps] == disk["temperatures"] == list(exported["mlr_seed002"][0].sensors_)
    for s in disk["temperatures"]:
        assert [f["filter"] for f in disk["preprocessing"][s]] == ["limit", "kalman"]
        assert disk["preprocessing"][s][1]["R"] == pytest.approx(8.8706, rel=1e-6)  # seed 002 §2.3.1
    assert disk["training"]["dataset_hash"] == ds.content_hash()
    assert disk["training"]["runs"] == TRAIN
    f = disk["files"]["model"]
    data = (model_dir / f["file"]).read_bytes()
    assert f["bytes"] == len(data) <= 1024  # MLR within the 1 KB budget
    assert f["crc32"] == f"{zlib.crc32(data[:-4]):08x}"


def test_export_job_and_replay_command(exported, ds, seed001_data_root, tmp_path, monkeypatch, capsys):
    """thermbench export from a benchmark-style model directory, then thermbench replay: the
    before/after figures equal those computed from the Python model's predictions."""
    from omegaconf import OmegaConf

    from thermbench.cli import main
    from thermbench.config import load_config
    from thermbench.experiment import save_models
    from thermbench.export.job import run_export
    from thermbench.bench.metrics import residual_metrics
    from thermbench.data.reference import thermal_errors

    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    model = exported["mlr_seed001"][0]
    save_models({"seed001_vmc_x__mlr_seed001__global": model}, tmp_path / "models",
                extra={"seed001_vmc_x__mlr_seed001__global": {"dataset": "seed001_vmc_x", "metrics": {"x_um": 1.0},
                                                              "mlflow_run_id": "abc"}})  # fmt: skip
    cfg = load_config("export", [f"export.source={tmp_path / 'models'}", f"export.out_dir={tmp_path / 'out'}"])
    table, _ = run_export(cfg)
    out = tmp_path / "out" / "seed001_vmc_x__mlr_seed001__global"
    man = read_manifest(out)
    assert man["metrics"] == {"x_um": 1.0} and man["mlflow_run_id"] == "abc"
    assert set(man["parity"]["runs"]) == {"valid1", "valid2", "valid3", "valid4"}
    assert table["parity_max_abs_diff_nm"].iloc[0] < 1000 * TOL_UM
    # one fitted model file, its dataset named
    one = tmp_path / "models" / "seed001_vmc_x__mlr_seed001__global.joblib"
    cfg = load_config("export", [f"export.source={one}", "export.dataset=seed001_vmc_x", f"export.out_dir={tmp_path / 'o2'}"])
    t2, _ = run_export(cfg)
    assert t2["model"].tolist() == [one.stem] and t2["parity_max_abs_diff_nm"].iloc[0] < 1000 * TOL_UM
    assert read_manifest(tmp_path / "o2" / one.stem)["source"]["file"] == str(one)
    # a key nobody knows is named
    bad = load_config("export", [f"export.source={tmp_path / 'models'}", "+export.colour=red"])
    with pytest.raises(Exception, match="export.colour"):
        run_export(bad)

    rep = tmp_path / "rep"
    import matplotlib

    before = matplotlib.get_backend()
    matplotlib.use("svg")  # as a notebook has its own backend: the replay's figures must leave it alone
    try:
        assert main(["replay", str(out), str(ds.path), "--run", "valid3", "--out", str(rep)]) == 0
        assert matplotlib.get_backend() == "svg"
    finally:
        matplotlib.use(before)
    fig = json.loads((rep / "replay.json").read_text())
    te = thermal_errors(ds)
    te = te[te["run_id"] == "valid3"]
    m = residual_metrics(te["error_um"], model.predict(ds, "valid3"), te["thermal_um"])
    assert fig["before_max_abs_um"] == pytest.approx(m["max_abs_error_um"], abs=1e-9)
    assert fig["after_max_abs_um"] == pytest.approx(m["max_abs_residual_um"], abs=TOL_UM)
    assert fig["after_max_abs_um"] < 0.5 * fig["before_max_abs_um"]
    comp = pd.read_csv(rep / "compensation.csv")
    assert len(comp) == len(ds.process_run("valid3"))
    assert (rep / "errors_before_after.png").stat().st_size > 10_000
    # a user mistake: one line, exit 2
    assert main(["replay", str(out), str(ds.path), "--run", "nope", "--out", str(rep)]) == 2
    assert "nope" in capsys.readouterr().err


def test_export_in_two_processes_writes_what_one_process_writes(exported, seed001_data_root, tmp_path, monkeypatch):
    """export.n_jobs=2 exports the models of a directory in two processes: the same files,
    byte for byte, and the same rows in the same order as in one process."""
    from thermbench.config import ConfigError, load_config
    from thermbench.experiment import save_models
    from thermbench.export.job import run_export

    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    fams = ["mlr_seed001", "physics", "lssvm"]
    keys = {f"seed001_vmc_x__{f}__global": exported[f][0] for f in fams}
    save_models(keys, tmp_path / "models", extra={k: {"dataset": "seed001_vmc_x"} for k in keys})
    tables = {}
    for n in (1, 2):
        cfg = load_config("export", [f"export.source={tmp_path / 'models'}", f"export.out_dir={tmp_path / f'out{n}'}",
                                     f"export.n_jobs={n}", "export.lssvm_reduced_size=40"])  # fmt: skip
        tables[n] = run_export(cfg)[0]
    assert tables[2]["model"].tolist() == tables[1]["model"].tolist() == list(keys)
    for k in keys:
        files = sorted(p.name for p in (tmp_path / "out1" / k).glob("*.tbm"))
        assert files and files == sorted(p.name for p in (tmp_path / "out2" / k).glob("*.tbm"))
        for f in files:
            assert (tmp_path / "out1" / k / f).read_bytes() == (tmp_path / "out2" / k / f).read_bytes()
    assert (tables[2]["parity_max_abs_diff_nm"] < 1000 * TOL_UM).all()
    bad = load_config("export", [f"export.source={tmp_path / 'models'}", f"export.out_dir={tmp_path / 'o3'}",
                                 "export.n_jobs=0"])  # fmt: skip
    with pytest.raises(ConfigError, match="export.n_jobs"):
        run_export(bad)


# ------------------------------------------------------- hostile streams ---
def _without_row(ds, run: str, t_s: float):
    """``ds`` with the process sample of ``run`` at ``t_s`` removed (what a compensator that
    skipped that sample has seen)."""
    from thermbench.data.dataset import Dataset

    pr = ds.process
    keep = ~((pr["run_id"] == run) & (pr["t_s"] == t_s))
    assert (~keep).sum() == 1
    return Dataset(ds.metadata, pr[keep].reset_index(drop=True), ds.errors, path=ds.path)


def test_a_refused_sample_is_skipped_and_the_models_go_on(exported, ds, tmp_path):
    """A NaN temperature (and an impossible feed) at one sample: the runtime refuses that sample
    with an error code; a compensator skips it, and the GRU (uniform history: the gap is filled
    as numpy.interp fills it) and a bank (all models refuse it together) then agree with the
    Python models on the log without that sample."""
    from thermbench.export.samples import process_samples

    run = "valid2"
    pr = process_samples(ds, run)
    t_bad = float(pr["t_s"].iloc[3000])
    bad = pr.copy()
    bad.loc[3000, ds.metadata.sensor_column("T_nut")] = np.nan
    bad.loc[4000, "feed_mm_min"] = 1e200
    ds_skip = _without_row(_without_row(ds, run, t_bad), run, float(pr["t_s"].iloc[4000]))
    bank = ConditionBank(MLRSeed002(sensors=["T_nut", "T_bed"])).fit(ds, TRAIN)
    export_model(bank, tmp_path / "bank", "bank", ds, [run], options=ExportOptions(verify=False))
    q = readings_queries(ds, run)
    for model, d in ((exported["gru"][0], exported["gru"][1]), (bank, tmp_path / "bank")):
        with pytest.raises(runtime.RuntimeFailed, match="error -11"):
            replay_dir(d, ds, run, q, samples=bad)
        c = replay_dir(d, ds, run, q, samples=bad, lenient=True)
        py = model.predict_at(ds_skip, run, q["t_s"].to_numpy(), q["axis_mm"].to_numpy())
        assert np.max(np.abs(c["total_um"].to_numpy() - py)) < TOL_UM


def test_a_log_off_the_sampling_grid_is_refused_not_mispredicted(exported, ds):
    """The GRU history assumes the log's period; a clock running 0.09 % fast (each step within
    1e-3 of the period) is refused once it leaves the grid, instead of predicting 0.1 um off."""
    from thermbench.export.samples import process_samples

    pr = process_samples(ds, "valid2")
    drift = pr.assign(t_s=pr["t_s"] * 1.0009)
    q = readings_queries(ds, "valid2").assign(t_s=lambda d: d["t_s"] * 1.0009)
    with pytest.raises(runtime.RuntimeFailed, match="error -12"):
        replay_dir(exported["gru"][1], ds, "valid2", q, samples=drift)


def test_a_family_of_its_own_is_asked_for_its_encoding_first():
    """encode() asks a class with export_encoding before the built-in chain, and checks the answer
    (the positive path, with parity in the C runtime, is docs/extending.md's worked example)."""
    from thermbench.export import ExportError, encode
    from thermbench.export.encoding import Encoded
    from thermbench.export.fileformat import Kind

    class Own:
        train_runs_ = ["a"]

        def __init__(self, answer):
            self.answer = answer

        def export_encoding(self, channels, period_s, where):
            self.asked = (channels, period_s, where)
            return self.answer

    with pytest.raises(ExportError, match=r"m1: Own.export_encoding returned str, not Encoded"):
        encode(Own("nope"), where="m1")
    enc = Encoded(Kind.MLR_CURVE, [1, 1], [1.0] * 8, ["T_nut"])
    own = Own(enc)
    assert encode(own, {"T_nut": 0}, 2.0, "m2") is enc
    assert own.asked == ({"T_nut": 0}, 2.0, "m2")


def test_built_in_families_are_found_by_their_registered_class(monkeypatch):
    """encode() finds a built-in family's encoder by the class it is registered for (by name, along
    the MRO: a subclass uses its base's), a new family needs one @family line, and a class that
    is neither registered nor has export_encoding is refused in one line."""
    from thermbench.export import ExportError, encode, encoding
    from thermbench.export.encoding import Encoded

    for name, cls in _families().items():
        assert encoding.family_encoder(type(cls)) is not None, name
    assert encoding.family_encoder(MLRSeed002) is encoding.family_encoder(MLRSeed004) is encoding._encode_curve_regression

    class Tuned(PhysicsModel):
        pass

    assert encoding.family_encoder(Tuned) is encoding._encode_physics

    class Tiny:
        train_runs_ = ["a"]

    with pytest.raises(ExportError, match=r"^m: no file encoding for Tiny$"):
        encode(Tiny(), where="m")
    enc = Encoded(Kind.MLR_CURVE, [1, 1], [1.0] * 8, ["T_nut"])
    key = f"{Tiny.__module__}:{Tiny.__qualname__}"
    monkeypatch.setitem(encoding.FAMILIES, key, None)  # the registration below lasts this test only
    seen = {}

    @encoding.family(key)
    def _encode_tiny(m, channels, period_s, where, **options):
        seen.update(channels=channels, period_s=period_s, where=where, options=options)
        return enc

    assert encode(Tiny(), {"T_nut": 0}, 2.0, "m4") is enc
    assert seen == {"channels": {"T_nut": 0}, "period_s": 2.0, "where": "m4", "options": {"lssvm_reduced": None}}
    too_big = Encoded(Kind.MLR_CURVE, [33, 1], [], ["T_nut"])  # check_limits still runs on a family's answer
    encoding.FAMILIES[key] = lambda *a, **k: too_big
    with pytest.raises(ExportError, match=r"^m5: sensors = 33 exceeds the C runtime's limit 32"):
        encode(Tiny(), where="m5")
