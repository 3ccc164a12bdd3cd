"""Every user mistake raised below the command line is one line on stderr, exit 2, naming
the config key: the raise sites that used to throw a plain ``ValueError`` /
``KeyError`` (now a traceback: those are reserved for bugs) throw one of
:func:`thermbench.errors.user_errors` instead.

Each case is driven as a user would, through :func:`thermbench.cli.main` in-process, and
fails before any expensive work (no simulation, no fit, nothing written): the whole file
runs in seconds. The experiment presets (``experiment=...``) override the main config,
and the command line overrides the preset.
"""

from __future__ import annotations

import shutil
from types import SimpleNamespace

import pytest
import yaml

from thermbench.cli import main
from thermbench.config import ConfigError, config_dir, load_config
from thermbench.errors import UserError, user_errors


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """Run in a tmp dir: whatever a command would write (outputs/, mlflow.db) lands there."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def run(argv: list[str]) -> int:
    try:
        return main(argv)
    except SystemExit as exc:  # argparse
        return exc.code


def user_error(capsys, argv: list[str], *needles: str, prefix: str = "thermbench") -> str:
    """Run ``thermbench argv``: exit 2 and exactly one stderr line holding every needle."""
    code = run(argv)
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith(f"{prefix}: error: "), lines[0]
    for needle in needles:
        assert needle in lines[0], lines[0]
    return lines[0]


# ------------------------------------------------------------- classify ---
def test_classify_inconsistent_stroke(workdir, capsys):
    user_error(capsys, ["classify", "--stroke", "100", "--start", "60", "--end", "100", "--feed", "1000"],
               "stroke_mm 100 must equal |end_mm - start_mm| = 40 within 1 mm")  # fmt: skip


@pytest.fixture
def own_conf(tmp_path, monkeypatch):
    """A copy of conf/ the user can add options to (THERMBENCH_CONFIG_DIR)."""
    conf = tmp_path / "conf"
    shutil.copytree(config_dir(), conf)
    monkeypatch.setenv("THERMBENCH_CONFIG_DIR", str(conf))
    return conf


@pytest.mark.parametrize(
    "change, expected",
    [
        ({"stroke_levels_mm": []}, "config key 'classifier.stroke_levels_mm': stroke_levels_mm must be a non-empty"),
        ({"feed_levels_mm_min": [800, 800, 4000]}, "config key 'classifier.feed_levels_mm_min': "),
        ({"level_tolerance": 2}, "config key 'classifier.level_tolerance': level_tolerance must be a number in [0, 1)"),
        ({"conditions": {"#1": {"stroke_mm": 50, "feed_mm_min": 800}}},
         "config key 'classifier.conditions': conditions['#1']: missing position_mm"),
        ({"conditions": {"#1": {"stroke_mm": "x", "position_mm": 0, "feed_mm_min": 800}}},
         "config key 'classifier.conditions': conditions['#1']: values must be numbers"),
        ({"conditions": {"#1": {"stroke_mm": 50, "position_mm": 0, "feed_mm_min": 800},
                         "#2": {"stroke_mm": 60, "position_mm": 0, "feed_mm_min": 800}}},
         "config key 'classifier.conditions': conditions ['#1', '#2'] map to the same levels"),
    ],
)  # fmt: skip
def test_classify_with_a_wrong_classifier_of_the_user(own_conf, workdir, capsys, change, expected):
    cfg = yaml.safe_load((own_conf / "classifier" / "seed002.yaml").read_text())
    (own_conf / "classifier" / "mine.yaml").write_text(yaml.safe_dump({**cfg, **change}))
    user_error(capsys, ["classify", "--stroke", "100", "--start", "60", "--end", "160", "--feed", "1250",
                        "--classifier", "mine"], expected)  # fmt: skip


# ------------------------------------------------------------- simulate ---
@pytest.mark.parametrize(
    "override, expected",
    [
        ("numerics.method=nope", "config key 'numerics': numerics.method must be 'macro' or 'explicit', got 'nope'"),
        ("numerics.dx_m=-1", "config key 'numerics': numerics: dx_m, dt_s and macro_dt_s must be finite and > 0"),
        ("machine.screw.length_m=-1", "config key 'machine.screw': screw.length_m must be > 0, got -1"),
        ("protocol.runs.cond1_3000.phases.0.kind=nope",
         "config key 'protocol.runs.cond1_3000.phases[0]': phase kind must be 'move' or 'stop', got 'nope'"),
        ("~protocol.runs", "config key 'protocol.runs': the protocol defines no runs"),
        ("instruments.process_rate_hz=0.5", "config key 'instruments.process_rate_hz': must be >= 1 (contract), got 0.5"),
        ("machine.sensors.T_nut=nowhere", "config key 'machine.sensors.T_nut': unknown location 'nowhere'; known: "),
        ("+effects.nope.x=1", "config key 'effects.nope': unknown effect 'nope'; the canonical effects are"),
        ("+effects.motor_heat.x=1", "config key 'effects.motor_heat.x': effect 'motor_heat' has no parameter(s) ['x']"),
        ("+effects.motor_heat.tau_s=soon", "config key 'effects.motor_heat.tau_s': expected a finite number, got 'soon'"),
    ],
)  # fmt: skip
def test_simulate_config_mistakes(workdir, capsys, override, expected):
    extra = ["protocol.random_runs.count=0"] if override == "~protocol.runs" else []
    user_error(capsys, ["simulate", override, *extra], expected)
    assert not any(workdir.iterdir())  # refused before anything was simulated or written


def test_a_negative_seed_is_refused_before_numpy(short_cfg):
    from thermbench.sim.scenario import simulate_dataset

    short_cfg.seed = -1
    with pytest.raises(ConfigError, match="config key 'seed': expected an integer >= 0, got -1"):
        simulate_dataset(short_cfg)


def test_sim_cnc_unknown_run(workdir, capsys):
    user_error(capsys, ["sim-cnc", "run=nope", "duration_s=10"],
               "config key 'run': run(s) ['nope'] are not in protocol 'seed001_states'; its runs: ['state1'")  # fmt: skip


# ------------------------------------------------------------- diagnose ---
@pytest.mark.parametrize(
    "override, expected",
    [
        ("physics.dx_m=-1", "config key 'physics.dx_m': must be > 0, got -1.0"),
        ("physics.dt_s=nan", "config key 'physics.dt_s': expected a finite number, got"),
        ("physics.dt_s=0.3", "config key 'physics.macro_dt_s': must be a whole multiple of physics.dt_s"),
        ("physics.max_iter=0", "config key 'physics.max_iter': must be >= 1, got 0"),
        ("noise.repeat_window_s=-5", "config key 'noise.repeat_window_s': expected a number >= 0, got -5"),
    ],
)
def test_diagnose_physics_numbers(workdir, capsys, override, expected):
    user_error(capsys, ["diagnose", str(workdir / "nowhere"), "--out", str(workdir / "o"), "track=false", override],
               expected)  # fmt: skip
    assert not any(workdir.iterdir())


# ---------------------------------------------------------- compensator ---
def test_compensator_period(workdir, capsys):
    user_error(capsys, ["compensator", str(workdir / "none"), "--endpoint", "opc.tcp://127.0.0.1:1", "--nodes", "n.yaml",
                        "period_s=-1"], "config key 'period_s': must be > 0, got -1.0")  # fmt: skip


@pytest.fixture
def model_and_nodes(tmp_path, monkeypatch):
    """A model directory and a nodes file for it: the compensator gets as far as its settings.

    The exported model is a stand-in with the two temperatures of a seed 001 export (the
    settings are checked whatever the model; a real export costs a fit and a compile)."""
    from thermbench.compensator.simcnc import nodes_yaml
    from thermbench.export import native

    model = SimpleNamespace(temperatures=["T_nut", "T_bed"], needs_load=False, period_s=1.0)
    monkeypatch.setattr(native, "LiveModel", lambda model_dir: model)
    nodes = tmp_path / "nodes.yaml"
    nodes.write_text(yaml.safe_dump(nodes_yaml(SimpleNamespace(samples={}, sensors=model.temperatures))))
    return tmp_path / "model", nodes


#: (override, message) of the compensator's settings: checked once the model and the nodes
#: file are read, before anything connects
COMPENSATOR_SETTINGS = [
    ("convention=nope", "config key 'convention': expected compensation or error, got 'nope'"),
    ("clock=nope", "config key 'clock': expected source or client, got 'nope'"),
    ("line.n_points=1", "config key 'line.n_points': at least 2, got 1"),
    ("ranges.axis_mm=[5,1]", "config key 'ranges.axis_mm': expected [low, high] with high > low, got [5.0, 1.0]"),
    ("rate_limit_um_s=0", "config key 'rate_limit_um_s': must be > 0, got 0.0"),
]


def test_compensator_settings(workdir, capsys, model_and_nodes):
    model_dir, nodes = model_and_nodes
    for override, expected in COMPENSATOR_SETTINGS:
        user_error(capsys, ["compensator", str(model_dir), "--endpoint", "opc.tcp://127.0.0.1:1", "--nodes", str(nodes),
                            f"log={workdir / 'c.csv'}", override], expected)  # fmt: skip
    assert not (workdir / "c.csv").exists() and not (workdir / "c.summary.json").exists()  # no log started


def test_compensator_settings_error_is_the_compensator_error():
    from thermbench.compensator import CompensatorError
    from thermbench.compensator.settings import Settings

    with pytest.raises(CompensatorError, match=r"config key 'line\.ref_mm': expected a number"):
        Settings.from_config({"line": {"ref_mm": "left"}})
    assert CompensatorError in user_errors()


# ----------------------------------------------------- train (Hydra jobs) ---
def test_tracking_uri_scheme(workdir, capsys):
    user_error(capsys, ["train", "tracking.uri=nope://x"],
               "config key 'tracking.uri': nope://x: unsupported URI scheme 'nope'; MLflow takes", "sqlite",
               prefix="thermbench train")  # fmt: skip


#: (overrides, message) of `thermbench train` mistakes found when the job loads its dataset or
#: builds its model: before anything is fitted (one test: one tracking store, one dataset)
TRAIN_MISTAKES = [
    (["dataset.source.name=nope"],
     "config key 'dataset.source.name': unknown benchmark dataset 'nope'; known: ['seed000_x'"),
    (["dataset=path", "dataset.source.path=/nowhere", "+dataset.source.paht=x"],
     "config key 'dataset.source.paht': load_dataset has no parameter 'paht' (did you mean 'path'?)"),
    (["+model.bogus=1"], "config key 'model.bogus': MLRSeed002 has no parameter 'bogus'; its parameters: sensors,"),
    (["model=bank_mlr_seed002", "+model.classifier.bogus=1"],
     "config key 'model.classifier.bogus': ProximityNaiveBayes has no parameter 'bogus'; its parameters: "),
]  # fmt: skip


def test_train_mistakes_in_the_dataset_and_model(workdir, capsys, tmp_path_factory, seed001_data_root, monkeypatch):
    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    store = f"tracking.uri=sqlite:///{tmp_path_factory.mktemp('mlflow') / 'mlflow.db'}"
    for overrides, expected in TRAIN_MISTAKES:
        user_error(capsys, ["train", store, *overrides], expected, prefix="thermbench train")


def _buggy_loader(name: str):
    return {}[name]  # a bug inside a loader: a KeyError


def test_a_bug_in_a_loader_keeps_its_traceback():
    from hydra.errors import InstantiationException

    from thermbench.experiment import ExperimentError, load_split

    with pytest.raises(InstantiationException) as info:
        load_split({"source": {"_target_": f"{__name__}._buggy_loader", "name": "x"}})
    assert isinstance(info.value.__cause__, KeyError) and not isinstance(info.value, ExperimentError)


# --------------------------------------------------------------- datasets ---
def test_yaml_input_error_is_a_dataset_error():
    from thermbench.data.errors import DatasetError
    from thermbench.data.safe_yaml import YAMLInputError, load_yaml

    assert issubclass(YAMLInputError, DatasetError)
    with pytest.raises(DatasetError, match="line 2: duplicate key 'a'"):
        load_yaml("a: 1\na: 2\n")


def test_error_classes_are_user_errors():
    import thermbench.models.classify as classify

    assert issubclass(classify.ClassifierError, UserError)
    assert all(issubclass(cls, user_errors()) for cls in (classify.ClassifierError, ConfigError))


# ------------------------------------------------------ experiment presets ---
def test_an_experiment_preset_overrides_the_main_config():
    shipped = load_config("benchmark")
    quick = load_config("benchmark", ["experiment=benchmark_quick"])
    preset = yaml.safe_load((config_dir() / "experiment" / "benchmark_quick.yaml").read_text())
    assert shipped.families is None  # as shipped: each dataset option's own benchmark_families
    assert list(quick.families) == preset["families"]
    assert list(quick.datasets) == preset["datasets"] and list(quick.bank_families) == preset["bank_families"]
    # the command line still wins over the preset, in either order
    for ov in (["experiment=benchmark_quick", "families=[physics]"], ["families=[physics]", "experiment=benchmark_quick"]):
        assert list(load_config("benchmark", ov).families) == ["physics"]
    # train: the preset's own keys win over train.yaml (seed002_bank trains on every state)
    bank = load_config("train", ["experiment=seed002_bank"])
    assert bank.train == "all" and bank.dataset.name == "seed002_vmc655h_x"
    assert load_config("train", ["experiment=seed002_bank", "train=c2"]).train == "c2"
    assert load_config("train").train == "state1"


def test_a_sweep_preset_still_composes():
    cfg = load_config("train", ["sweep=models_x_states"], return_hydra_config=True)
    assert str(cfg.hydra.mode) == "RunMode.MULTIRUN" and cfg.hydra.job.name == "train"
    assert cfg.hydra.sweeper.params.train == "state1,state3,state5"
    assert "progress" in cfg.hydra.callbacks
