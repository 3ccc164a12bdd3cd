"""The C runtime on its target (thermbench.export.target): cross-compiled for the Cortex-M4F of
seed 002's STM32F407 and run on QEMU's mps2-an386 board, the model files in flash.

Marker ``target``: ``make target-test`` runs these (``make test`` does not). Without the cross
compiler or QEMU they fail, naming the packages: ``make target-test`` installs them (tools/sysdeps.sh)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from thermbench.bench.datasets import load_benchmark
from thermbench.export import ExportOptions, directory, export_model, read_manifest, target
from thermbench.export.samples import readings_queries
from thermbench.export.fileformat import Kind
from thermbench.export.native import TB_E_ALIGN
from thermbench.models.mlr import MLRSeed001, MLRSeed002

from .families import HELDOUT, TRAIN

pytestmark = pytest.mark.target

RUN = "valid1"
FLOAT_UM = 0.01  # single-precision parity for every kind
KIND_OF = {k.name: int(k) for k in Kind}  # the manifest's kind -> TB_KIND_* of tb_runtime.h (test_runtime_contract)


@pytest.fixture(scope="module")
def ds(seed001_data_root):
    return load_benchmark("seed001_vmc_x", seed001_data_root)


@pytest.fixture(scope="module")
def queries(ds):
    return readings_queries(ds, RUN)


@pytest.fixture(scope="module")
def host(seed001_exports, ds, queries):
    """The host runtime's answers (gcc on x86-64, double; parity-checked against Python at export)."""
    return {name: directory.replay_dir(seed001_exports / name, ds, RUN, queries) for name in ("mlr", "bank")}


@pytest.mark.parametrize("precision", ["double", "float"])
@pytest.mark.parametrize("name", ["mlr", "bank"])
def test_the_target_reproduces_the_host(seed001_exports, ds, queries, host, name, precision):
    """Every reading of the validation run, answered on the emulated M4: in double the same
    numbers as the host (IEEE double on both; a different compiler and instruction set), in
    float within 0.01 µm; the bank picks the same condition at every reading."""
    files, samples, temps, bank = directory.replay_inputs(seed001_exports / name, ds, RUN)
    got, rep = target.replay(files, samples, temps, queries, precision=precision)
    ref = host[name]
    assert rep["rc"] == 0 and len(got) == len(ref) == len(queries) and (got["rc"] == 0).all()
    np.testing.assert_array_equal(got[["t_s", "axis_mm"]].to_numpy(), ref[["t_s", "axis_mm"]].to_numpy())
    tol = 5e-10 if precision == "double" else FLOAT_UM
    assert np.max(np.abs(got["total_um"].to_numpy() - ref["total_um"].to_numpy())) <= tol
    assert np.max(np.abs(got["thermal_um"].to_numpy() - ref["thermal_um"].to_numpy())) <= tol
    assert got["label"].tolist() == ref["label"].tolist()
    assert (got["label"] >= 0).any() if bank else (got["label"] == -1).all()
    # what the harness measured: the arena the models took (32-bit pointers: not the host's), the
    # deepest stack (painted at reset) within the 8 KB the link script reserves
    assert 0 < rep["arena_bytes"] <= 16384 and 0 < rep["stack_bytes"] < 8192


def test_the_single_precision_runtime_reaches_no_software_double_routine(seed001_exports, ds):
    """The image's call graph (disassembly; the link map says which functions are the runtime's,
    every kind and effect linked in): in single precision (-DTB_SINGLE) nothing the runtime can
    call, down through newlib's libm, is a software double or 64-bit routine of libgcc or a double
    <math.h> function; the same walk over the double build finds them (it can see them)."""
    files, *_ = directory.replay_inputs(seed001_exports / "bank", ds, RUN)
    single = target.build(files, "float")
    assert target.soft_routines(single) == {}
    reached = target.reached_routines(single)
    assert {"powf", "sinf", "erff", "floorf"} <= set(reached)  # the walk follows the float libm
    double = target.soft_routines(target.build(files, "double"))
    assert {"__aeabi_dmul", "__aeabi_ddiv", "exp", "tanh", "pow"} <= set(double)
    assert "check_sample" in double["__aeabi_ddiv"]  # and names the runtime functions that reach each


def test_an_export_for_the_cortex_m4f_holds_the_float_build_to_the_tolerance(ds, tmp_path):
    """export.target=cortex-m4f: the single-precision runtime (-DTB_SINGLE) is verified against
    Python. A well-conditioned MLR passes and says so. An LSSVM with a large penalty and a wide
    kernel (cond(K) large: weights of thousands that cancel to micrometres) is within 0.01 µm
    in double but not in float32 (7 digits per term): that export is refused, with the reason
    and what to do, and nothing is left in its directory; for the host it is exported."""
    from thermbench.export import ExportError
    from thermbench.models.lssvm import PSOLSSVM

    mlr = MLRSeed002().fit(ds, TRAIN)
    man = export_model(mlr, tmp_path / "mlr", "mlr", ds, HELDOUT, options=ExportOptions(target="cortex-m4f"))
    assert man["target"]["name"] == "cortex-m4f" and man["parity"]["precision"] == "float"
    assert man["parity"]["model"]["float_max_abs_diff_um"] <= FLOAT_UM
    assert 0 < man["target"]["footprint"]["arena_bytes"] <= 16 * 1024
    # and measured on the emulated M4 against the budgets
    meas = man["target"]["measured"]
    got = meas["model"]
    assert 0 < got["cycle_insn_max"] <= 100_000 and 0 < got["prediction_insn_max"] <= 200_000
    assert 0 < got["arena_bytes"] <= 16 * 1024 and 0 < got["image_bytes"] <= 64 * 1024
    # over every held-out run, a query at every process sample, against the host's double build
    assert meas["runs"] == HELDOUT and got["n_samples"] == sum(len(ds.process_run(r)) for r in HELDOUT)
    assert got["cycle_worst_run"] in HELDOUT and 0 < got["finish_insn_max"] and got["parity_vs_host_double_um"] <= FLOAT_UM
    ill = PSOLSSVM(gamma=1e4, sigma2=5.0, max_samples=400).fit(ds, TRAIN)
    host = export_model(ill, tmp_path / "host", "ill", ds, HELDOUT, options=ExportOptions())
    assert host["parity"]["model"]["max_abs_diff_um"] <= FLOAT_UM < host["parity"]["model"]["float_max_abs_diff_um"]
    with pytest.raises(ExportError, match=r"ill \(model\): the C runtime in single precision \(-DTB_SINGLE\) differs .*"
                                          r"kernel weights are large and cancel.*max_samples"):  # fmt: skip
        export_model(ill, tmp_path / "m4", "ill", ds, HELDOUT, options=ExportOptions(target="cortex-m4f"))
    assert not (tmp_path / "m4").exists()


def test_an_export_whose_state_does_not_fit_the_cortex_m4f_is_refused(ds, tmp_path):
    """A GRU's state is its dT history over window_s at the sample period: 2 sensors × 3604
    samples × 4 B = 28.8 KB for a one-hour window at 1 Hz, over the target's 16 KB: refused for
    the Cortex-M4F (naming the arena and the way out), exported for the host."""
    from thermbench.export import ExportError
    from thermbench.models.neural import GRUModel

    gru = GRUModel(hidden_size=2, window_s=3600.0, step_s=600.0, max_epochs=2, min_epochs=1).fit(ds, TRAIN)
    with pytest.raises(ExportError, match=r"gru: does not fit the cortex-m4f target: \d+ B of state arena, above "
                                          r"the target's 16384 B \(its state arena\).*shorter window_s"):  # fmt: skip
        export_model(gru, tmp_path / "m4", "gru", ds, HELDOUT, options=ExportOptions(target="cortex-m4f", onnx=False))
    assert not (tmp_path / "m4").exists()
    man = export_model(gru, tmp_path / "host", "gru", ds, HELDOUT, options=ExportOptions(onnx=False, verify=False))
    assert man["footprint"]["ram_bytes"] > 2 * 3604 * 4


def test_exporting_a_model_directory_for_the_cortex_m4f_skips_what_does_not_fit(seed001_data_root, tmp_path, monkeypatch,
                                                                               capsys):  # fmt: skip
    """thermbench export export.target=cortex-m4f over a model directory (select all): the model that
    fits is exported for the target, the one whose state is over 16 KB is skipped with one line
    naming it and why; with only that one, the export says nothing meets the target. A bad target
    value is a config error naming the key and the choices."""
    from thermbench.config import ConfigError, load_config
    from thermbench.experiment import save_models
    from thermbench.export import ExportError
    from thermbench.export.job import run_export
    from thermbench.models.neural import GRUModel

    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    ds = load_benchmark("seed001_vmc_x", seed001_data_root)
    gru = GRUModel(hidden_size=2, window_s=3600.0, step_s=600.0, max_epochs=2, min_epochs=1).fit(ds, TRAIN)
    models = {"seed001_vmc_x__mlr_seed001__global": MLRSeed001().fit(ds, TRAIN), "seed001_vmc_x__gru__global": gru}
    save_models(models, tmp_path / "models", extra={k: {"dataset": "seed001_vmc_x"} for k in models})
    cfg = load_config("export", [f"export.source={tmp_path / 'models'}", f"export.out_dir={tmp_path / 'out'}",
                                 "export.target=cortex-m4f", "export.onnx=false", "export.n_jobs=1"])  # fmt: skip
    table, _ = run_export(cfg)
    assert table["model"].tolist() == ["seed001_vmc_x__mlr_seed001__global"]
    assert read_manifest(tmp_path / "out" / table["model"].iloc[0])["target"]["name"] == "cortex-m4f"
    assert not (tmp_path / "out" / "seed001_vmc_x__gru__global").exists()
    err = capsys.readouterr().err
    assert "skipped seed001_vmc_x__gru__global: seed001_vmc_x__gru__global: does not fit the cortex-m4f target" in err
    save_models({"seed001_vmc_x__gru__global": gru}, tmp_path / "only_gru", extra={"seed001_vmc_x__gru__global": {"dataset": "seed001_vmc_x"}})
    cfg = load_config("export", [f"export.source={tmp_path / 'only_gru'}", f"export.out_dir={tmp_path / 'o2'}",
                                 "export.target=cortex-m4f", "export.onnx=false"])  # fmt: skip
    with pytest.raises(ExportError, match="does not fit the cortex-m4f target"):
        run_export(cfg)
    with pytest.raises(ConfigError, match=r"export.target.*'cortex-m4f', 'host'.*'m4'"):
        run_export(load_config("export", [f"export.source={tmp_path / 'models'}", "export.target=m4"]))


def test_a_gru_over_the_prediction_budget_is_refused_with_its_measured_cost(ds, tmp_path):
    """export.target=cortex-m4f measures every model on the emulated M4 in float: a GRU of 32 hidden
    units over 31 lags (twice the benchmark's width) fits the arena but costs more than 200 000
    instructions per prediction; the export is refused with the count and what to change."""
    from thermbench.export import ExportError
    from thermbench.models.neural import GRUModel

    gru = GRUModel(hidden_size=32, window_s=1800.0, step_s=60.0, max_epochs=1, min_epochs=1).fit(ds, TRAIN)
    with pytest.raises(ExportError, match=r"gru: over the cortex-m4f budget, measured on the emulated M4 in float over "
                                          r"every sample of \['valid1', 'valid3'\]: model: prediction \d{6} instructions "
                                          r"> 200000.*fewer lags or hidden units"):  # fmt: skip
        export_model(gru, tmp_path / "m4", "gru", ds, HELDOUT, options=ExportOptions(target="cortex-m4f", onnx=False))
    assert not (tmp_path / "m4").exists()


@pytest.mark.parametrize("offset", [0, 1, 2, 3])
def test_a_model_file_off_a_4_byte_boundary_is_refused_not_faulted(seed001_exports, ds, queries, offset):
    """Under unaligned-access trapping (CCR.UNALIGN_TRP, set around every runtime call), the file
    linked into flash at offset 0, 1, 2, 3 past an 8-byte boundary: on the boundary it runs; off it
    the loader returns TB_E_ALIGN, where the runtime without the check faulted in tb_model_open."""
    files, samples, temps, _ = directory.replay_inputs(seed001_exports / "mlr", ds, RUN)
    got, rep = target.replay(files, samples, temps, queries, offset=offset, trap_unaligned=True)
    if offset == 0:
        assert rep["rc"] == 0 and len(got) == len(queries)
    else:
        assert rep["rc"] == TB_E_ALIGN and "not 4-byte aligned" in rep["end"] and got.empty


def test_an_arena_beyond_the_image_s_is_named(seed001_exports, ds, queries):
    """The static arena is sized at build time: a model that needs more is refused on the END line."""
    files, samples, temps, _ = directory.replay_inputs(seed001_exports / "bank", ds, RUN)
    got, rep = target.replay(files, samples, temps, queries, arena_bytes=1024)
    assert rep["rc"] == -9 and "TB_ARENA_BYTES" in rep["end"] and got.empty


def test_instruction_counts_are_exact_and_repeatable(seed001_exports, ds, queries):
    """Under -icount shift=0 the SysTick counts instructions in 40s: a loop of 50 000 × (subs, bne)
    measures 100 000 instructions (± a tick and the marker calls); a second run counts every
    runtime call the same (emulated instruction counts are deterministic, unlike host timings)."""
    files, samples, temps, _ = directory.replay_inputs(seed001_exports / "bank", ds, RUN)
    _, a = target.replay(files, samples, temps, queries)
    _, b = target.replay(files, samples, temps, queries)
    assert a["calibrate_calls"] == 1 and abs(a["calibrate_insn_max"] - 100_000) <= 80
    # one control cycle per sample; the end-of-stream finish is counted on its own
    assert a["step_calls"] == len(samples) and a["finish_calls"] == 1 and a["predict_calls"] == len(queries)
    assert 0 < a["finish_insn_max"]
    assert 0 < a["predict_insn_mean"] <= a["predict_insn_max"] and 0 < a["step_insn_mean"] <= a["step_insn_max"]
    assert {k: v for k, v in a.items() if "insn" in k} == {k: v for k, v in b.items() if "insn" in k}


@pytest.fixture(scope="module")
def family_exports(ds, tmp_path_factory):
    """Every family of the host parity tests (tests/families.py), fitted and exported."""
    from thermbench.export import ExportOptions, export_model

    from .families import families

    from thermbench.models.bank import ConditionBank
    from thermbench.models.lssvm import PSOLSSVM
    from thermbench.models.neural import GRUModel

    root = tmp_path_factory.mktemp("target_exports")
    banks = {"gru_bank": ConditionBank(GRUModel(hidden_size=4, window_s=90.0, step_s=30.0, max_epochs=10, min_epochs=3,
                                                patience=5)),
             "lssvm_bank": ConditionBank(PSOLSSVM(gamma=100.0, sigma2=2.0, max_samples=200))}  # fmt: skip
    for name, model in {**families(), **banks}.items():
        export_model(model.fit(ds, TRAIN), root / name, name, ds, HELDOUT, options=ExportOptions(lssvm_reduced_size=40))
    return root


# every family, the reduced-set LSSVM and the banks of the two families with state of their own
VARIANTS = [("mlr_seed002", "model"), ("mlr_seed004", "model"), ("mlr_seed001", "model"), ("lssvm", "model"),
            ("lssvm", "reduced"), ("mlp", "model"), ("gru", "model"), ("physics", "model"), ("ar_seed003", "model"),
            ("gru_bank", "model"), ("lssvm_bank", "model")]  # fmt: skip


@pytest.mark.parametrize("precision", ["double", "float"])
@pytest.mark.parametrize("family,variant", VARIANTS)
def test_every_family_runs_on_the_target(family_exports, ds, queries, family, variant, precision):
    """Each exported kind (and the reduced LSSVM, and GRU and LSSVM banks), from flash on the
    emulated M4 over the validation run: in double the host's numbers (to 5e-10 µm: IEEE double
    on both, another compiler and libm); in float (-DTB_SINGLE) within 0.01 µm of them. In float
    a bank's state (every member's) fits the 16 KB arena; the banks pick the host's condition."""
    files, samples, temps, bank = directory.replay_inputs(family_exports / family, ds, RUN, variant)
    ref = directory.replay_dir(family_exports / family, ds, RUN, queries, variant)
    arena = 16384 if precision == "float" else 32768  # the budget is the float build's (double arrays are twice)
    got, rep = target.replay(files, samples, temps, queries, precision=precision, arena_bytes=arena)
    assert rep["rc"] == 0 and len(got) == len(ref) and (got["rc"] == 0).all()
    assert 0 < rep["arena_bytes"] <= arena
    tol = 5e-10 if precision == "double" else FLOAT_UM
    assert np.max(np.abs(got["total_um"].to_numpy() - ref["total_um"].to_numpy())) <= tol
    assert got["label"].tolist() == ref["label"].tolist() and ((got["label"] >= 0).any() if bank else True)


def test_the_runtime_s_stack_depth_is_measured_per_model(family_exports, ds, queries):
    """The harness paints the stack before each runtime call and reads how deep it went: for the
    MLP at least its evaluation's own frame as gcc -fstack-usage reports it for the target (an
    independent source), for MLR less than that frame (it never calls the MLP)."""
    frames = target.stack_frames("double")
    eval_frame = frames["tb_kind_mlp.c:eval"]
    depth = {}
    for family in ("mlp", "mlr_seed002"):
        files, samples, temps, _ = directory.replay_inputs(family_exports / family, ds, RUN)
        _, rep = target.replay(files, samples, temps, queries)
        depth[family] = rep["stack_bytes"]
    assert eval_frame < depth["mlp"] < 8192
    assert 0 < depth["mlr_seed002"] < eval_frame


@pytest.fixture(scope="module")
def lumped_export(tmp_path_factory):
    """The spindle's lumped thermal network (LUMPED kind: ambient and sensor inputs, the limit
    filter) on the synthetic spindle runs of the host lumped tests; run "h" held out."""
    from thermbench.models.lumped import LumpedThermalNetwork

    from .test_export_lumped import HISTORY_S, SPINDLE_META, _run, channel_view, export, load_dataset, write

    rng = np.random.default_rng(0)
    pa, ea = _run("a", [0, 3000, 6000, 1500, 0, 4500, 2000], rng)
    ph, eh = _run("h", [4000, 0, 6000, 3000, 5000], rng, first_read_s=HISTORY_S)
    root = write(tmp_path_factory.mktemp("spindle") / "ds", {**SPINDLE_META, "runs": {"a": {}, "h": {}}},
                 pd.concat([pa, ph]), pd.concat([ea, eh]))  # fmt: skip
    ds = channel_view(load_dataset(root), "Z")
    model = LumpedThermalNetwork(n_starts=1, n_nodes=2, ambient_sensor="T_amb", sensors=["T_front", "T_amb"]).fit(ds, ["a"])
    out = tmp_path_factory.mktemp("lumped") / "ambient_and_sensors"
    export(model, out, ds, ["h"])
    return ds, out


@pytest.mark.parametrize("precision", ["double", "float"])
def test_the_lumped_kind_runs_on_the_target(lumped_export, precision):
    """The LUMPED kind (a spindle's thermal network with ambient and sensor inputs) from flash on
    the emulated M4 over the held-out run: the host's numbers in double, within 0.01 µm in float."""
    ds, model_dir = lumped_export
    q = readings_queries(ds, "h")
    files, samples, temps, _ = directory.replay_inputs(model_dir, ds, "h")
    ref = directory.replay_dir(model_dir, ds, "h", q)
    got, rep = target.replay(files, samples, temps, q, precision=precision)
    assert rep["rc"] == 0 and len(got) == len(ref) == len(q) > 10 and (got["rc"] == 0).all()
    tol = 5e-10 if precision == "double" else FLOAT_UM
    assert np.max(np.abs(got["total_um"].to_numpy() - ref["total_um"].to_numpy())) <= tol


def test_a_one_kind_image_fits_64_kb_and_holds_only_its_kind(family_exports):
    """The smallest firmware per family (runtime with the file's kind only, start-up, model in
    flash, no stdio) in float: it boots on QEMU and opens its model (image() checks the exit
    status), takes <= 64 KB of flash (the M4F budget), and its symbol table has its own kind's
    table and no other's (TB_REGISTRY restricts the kind table, --gc-sections drops the rest)."""
    import subprocess

    for family in ("mlr_seed002", "mlr_seed001", "lssvm", "mlp", "gru", "physics", "ar_seed003"):
        man = read_manifest(family_exports / family)
        fw = target.image(family_exports / family / man["files"]["model"]["file"], "float")
        assert fw.flash_bytes <= 64 * 1024, (family, fw.flash_bytes)
        syms = subprocess.run(["arm-none-eabi-nm", str(fw.elf)], capture_output=True, text=True, check=True).stdout
        kinds = {ln.split()[-1] for ln in syms.splitlines() if " tbi_kind_" in ln}
        assert kinds == {f"tbi_kind_{target.KIND_CODES[KIND_OF[man['kind']]]}"}, (family, kinds)


@pytest.fixture(scope="module")
def thermal_lag_export(tmp_path_factory):
    """The thermal-lag family (THERMAL_LAG kind: three sensors' lags and the spindle speed's) on the
    planted runs of tests/test_thermal_lag.py; run "r4" held out."""
    from thermbench.models.thermal_lag import ThermalLag

    from .test_lumped import spindle_dataset
    from .test_thermal_lag import SENSORS, SPECS, _runs

    ds = spindle_dataset(_runs(SPECS), sensors=SENSORS, operating=["spindle_rpm"])
    model = ThermalLag(max_inputs=4, min_gain=0.0).fit(ds, ["r0", "r1", "r2", "r3"])
    out = tmp_path_factory.mktemp("thermal_lag") / "tl"
    export_model(model, out, "tl", ds=ds, heldout=["r4"])
    return ds, out


@pytest.mark.parametrize("precision", ["double", "float"])
def test_the_thermal_lag_kind_runs_on_the_target(thermal_lag_export, precision):
    """THERMAL_LAG from flash on the emulated Cortex-M4F over the held-out run: the host's numbers
    in double, within 0.01 µm in float."""
    ds, model_dir = thermal_lag_export
    _host_and_target_agree(ds, model_dir, "r4", precision, min_readings=300)


def _host_and_target_agree(ds, model_dir, run: str, precision: str, min_readings: int) -> None:
    """The model in model_dir replayed over run on the emulated target answers every reading, as the
    host's runtime does: to 5e-10 µm in double, within FLOAT_UM in float."""
    q = readings_queries(ds, run)
    files, samples, temps, _ = directory.replay_inputs(model_dir, ds, run)
    ref = directory.replay_dir(model_dir, ds, run, q)
    got, rep = target.replay(files, samples, temps, q, precision=precision)
    assert rep["rc"] == 0 and len(got) == len(ref) == len(q) > min_readings and (got["rc"] == 0).all()
    tol = 5e-10 if precision == "double" else FLOAT_UM
    assert np.max(np.abs(got["total_um"].to_numpy() - ref["total_um"].to_numpy())) <= tol


def test_a_thermal_lag_export_for_the_cortex_m4f_is_within_its_budget(thermal_lag_export, tmp_path):
    """export.target=cortex-m4f measures the THERMAL_LAG model on the emulated M4 in float over every
    sample of the held-out run and holds it to the budget (RAM, file, cycle and prediction instructions)."""
    from thermbench.models.thermal_lag import ThermalLag

    ds, _ = thermal_lag_export
    model = ThermalLag(max_inputs=4, min_gain=0.0).fit(ds, ["r0", "r1", "r2", "r3"])
    man = export_model(model, tmp_path / "m4", "tl", ds=ds, heldout=["r4"],
                       options=ExportOptions(target="cortex-m4f", onnx=False))  # fmt: skip
    assert man["footprint"]["within_budget"] and man["parity"]["model"]["max_abs_diff_um"] <= FLOAT_UM


@pytest.fixture(scope="module")
def lag_bank_export(tmp_path_factory):
    """The lag bank with the start state (THERMAL_LAG layout 2, conf/model/lag_bank.yaml's settings) on
    twenty sensors that start warm by different amounts (tests/test_start_state.py's runs), no ambient
    sensor: forty inputs, six lags each; run "r4" held out."""
    from omegaconf import OmegaConf

    from thermbench.config import config_dir
    from thermbench.models.thermal_lag import ThermalLag

    from .test_start_state import twenty_sensors

    ds = twenty_sensors()
    cfg = OmegaConf.to_container(OmegaConf.load(f"{config_dir()}/model/lag_bank.yaml"))
    params = {k: v for k, v in cfg.items() if not k.startswith("_")}
    model = ThermalLag(**params).fit(ds, ["r0", "r1", "r2", "r3"])
    assert len(model.inputs_) == 40 and len(model.taus_s_) == 6
    out = tmp_path_factory.mktemp("lag_bank") / "lb"
    export_model(model, out, "lb", ds=ds, heldout=["r4"])
    return ds, out, model


@pytest.mark.parametrize("precision", ["double", "float"])
def test_the_lag_bank_with_its_start_state_runs_on_the_target(lag_bank_export, precision):
    """THERMAL_LAG layout 2 from flash on the emulated Cortex-M4F: the start state captured at the
    first sample as on the host, every reading to 5e-10 µm in double, within 0.01 µm in float."""
    ds, model_dir, _ = lag_bank_export
    _host_and_target_agree(ds, model_dir, "r4", precision, min_readings=300)


def test_a_lag_bank_export_for_the_cortex_m4f_is_within_its_budget(lag_bank_export, tmp_path):
    """Forty inputs through six lags each on the M4 in float: within the budget (RAM, file, cycle and
    prediction instructions), at parity."""
    ds, _, model = lag_bank_export
    man = export_model(model, tmp_path / "m4", "lb", ds=ds, heldout=["r4"],
                       options=ExportOptions(target="cortex-m4f", onnx=False))  # fmt: skip
    assert man["footprint"]["within_budget"] and man["parity"]["model"]["max_abs_diff_um"] <= FLOAT_UM


@pytest.fixture(scope="module")
def lag_bank_mean_export(tmp_path_factory):
    """The lag bank (conf/model/lag_bank.yaml's settings) where the machine's one start level is chosen
    (tests/test_start_state.py's machine runs: six sensors and an ambient one, seven training runs):
    the mean exported as each sensor's start state at a sixth of its weights; run "m7" held out."""
    from omegaconf import OmegaConf

    from thermbench.config import config_dir
    from thermbench.models.thermal_lag import START_MEAN, ThermalLag

    from .test_lumped import spindle_dataset
    from .test_start_state import machine_runs

    runs, _ = machine_runs()
    ds = spindle_dataset(runs, sensors={**{f"S{i}": "structure" for i in range(6)}, "T_amb": "ambient"}, operating=[])
    cfg = OmegaConf.to_container(OmegaConf.load(f"{config_dir()}/model/lag_bank.yaml"))
    model = ThermalLag(**{k: v for k, v in cfg.items() if not k.startswith("_")}).fit(ds, [f"m{k}" for k in range(7)])
    assert START_MEAN in model.inputs_
    out = tmp_path_factory.mktemp("lag_bank_mean") / "lb"
    export_model(model, out, "lb", ds=ds, heldout=["m7"])
    return ds, out, model


@pytest.mark.parametrize("precision", ["double", "float"])
def test_the_lag_bank_with_the_machines_start_level_runs_on_the_target(lag_bank_mean_export, precision):
    """The machine's mean start level, carried as its sensors' start states, on the emulated
    Cortex-M4F: every reading to 5e-10 µm in double, within 0.01 µm in float."""
    ds, model_dir, _ = lag_bank_mean_export
    _host_and_target_agree(ds, model_dir, "m7", precision, min_readings=300)


def test_a_lag_bank_with_the_machines_start_level_is_within_the_cortex_m4f_budget(lag_bank_mean_export, tmp_path):
    ds, _, model = lag_bank_mean_export
    man = export_model(model, tmp_path / "m4", "lb", ds=ds, heldout=["m7"],
                       options=ExportOptions(target="cortex-m4f", onnx=False))  # fmt: skip
    assert man["footprint"]["within_budget"] and man["parity"]["model"]["max_abs_diff_um"] <= FLOAT_UM


@pytest.fixture(scope="module")
def linear_history_export(tmp_path_factory):
    """The linear-with-history family (LINEAR_HISTORY kind: three sensors' delay lines and the spindle
    speed's) on the planted irregular runs of tests/test_linear_history.py; run "r4" held out."""
    from thermbench.models.linear_history import LinearHistory

    from .test_linear_history import SENSORS, SPECS, _runs
    from .test_lumped import spindle_dataset

    ds = spindle_dataset(_runs(SPECS), sensors=SENSORS, operating=["spindle_rpm"])
    model = LinearHistory(operating=["spindle_rpm"]).fit(ds, ["r0", "r1", "r2", "r3"])
    out = tmp_path_factory.mktemp("linear_history") / "lh"
    export_model(model, out, "lh", ds=ds, heldout=["r4"])
    return ds, model, out


@pytest.mark.parametrize("precision", ["double", "float"])
def test_the_linear_history_kind_runs_on_the_target(linear_history_export, precision):
    """LINEAR_HISTORY from flash on the emulated Cortex-M4F over the held-out run: the host's numbers
    in double, within 0.01 µm in float, at every reading."""
    ds, _, model_dir = linear_history_export
    _host_and_target_agree(ds, model_dir, "r4", precision, min_readings=1000)


def test_a_linear_history_export_for_the_cortex_m4f_is_within_its_budget(linear_history_export, tmp_path):
    """export.target=cortex-m4f measures the LINEAR_HISTORY model (delay lines of an hour at 60 s) on
    the emulated M4 in float over every sample of the held-out run and holds it to the budget."""
    ds, model, _ = linear_history_export
    man = export_model(model, tmp_path / "m4", "lh", ds=ds, heldout=["r4"],
                       options=ExportOptions(target="cortex-m4f", onnx=False))  # fmt: skip
    assert man["footprint"]["within_budget"] and man["parity"]["model"]["max_abs_diff_um"] <= FLOAT_UM
