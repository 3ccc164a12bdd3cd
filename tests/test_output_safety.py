"""Every writing command against a user's files: a file planted in the target, one in its
parent, and the target being the dataset itself. Each planted file must stay byte-identical
(and a refusal comes before the work, as one line with exit 2 on the command line)."""

from __future__ import annotations

import asyncio
import hashlib
from pathlib import Path

import joblib
import pytest
import yaml

from thermbench.bench import datasets
from thermbench.cli import main
from thermbench.outputs import RECORD, OutputRefused

NOTE = "measurement campaign 2026-03, machine 4: do not lose\n"


def _plant(path: Path) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(NOTE)
    return path


def _digest(root: Path) -> dict[str, str]:
    return {p.relative_to(root).as_posix(): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}  # fmt: skip


@pytest.fixture
def campaign(tmp_path, seed001_data_root):
    """A copy of a dataset (as a user's measured one) in its own folder."""
    import shutil

    src = seed001_data_root / "seed001_vmc_x"
    dst = tmp_path / "campaign" / "vmc_x"
    dst.mkdir(parents=True)
    for f in src.iterdir():
        if not f.name.startswith("."):  # the data, not thermbench's record: a user's own dataset
            shutil.copy(f, dst / f.name)
    _plant(tmp_path / "campaign" / "README.txt")
    return dst


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


# ------------------------------------------------------------------ replay ---
def test_replay_refuses_the_dataset_its_parent_and_a_users_folder(campaign, seed001_exports, tmp_path, capsys):
    before = _digest(tmp_path / "campaign")
    model = str(seed001_exports / "mlr")
    for out, why in [(campaign, "is a dataset"), (campaign.parent, "contains the dataset"),
                     (campaign / "replay", "lies inside the dataset")]:
        assert main(["replay", model, str(campaign), "--run", "valid1", "--out", str(out)]) == 2
        assert why in _one_error_line(capsys)
        assert main(["replay", model, str(campaign), "--run", "valid1", "--out", str(out), "--force"]) == 2
        assert why in _one_error_line(capsys)
    mine = _plant(tmp_path / "replays" / "thesis.tex")
    assert main(["replay", model, str(campaign), "--run", "valid1", "--out", str(mine.parent)]) == 2
    assert "thesis.tex" in _one_error_line(capsys)
    # beside a user's file (--force), and in a new folder whose parent holds one
    assert main(["replay", model, str(campaign), "--run", "valid1", "--out", str(mine.parent), "--force"]) == 0
    assert (mine.parent / "replay.json").exists()
    parent_note = _plant(tmp_path / "out" / "notes.txt")
    assert main(["replay", model, str(campaign), "--run", "valid1", "--out", str(tmp_path / "out" / "r1")]) == 0
    assert main(["replay", model, str(campaign), "--run", "valid1", "--out", str(tmp_path / "out" / "r1")]) == 0  # its own
    assert parent_note.read_text() == NOTE and mine.read_text() == NOTE
    assert _digest(tmp_path / "campaign") == before


# ---------------------------------------------------------------- diagnose ---
def test_diagnose_refuses_before_any_work(campaign, tmp_path, capsys, monkeypatch):
    from thermbench.discrepancy import job

    before = _digest(tmp_path / "campaign")
    monkeypatch.setattr(job, "run_diagnosis", lambda *a, **k: pytest.fail("worked before refusing"))
    mine = _plant(tmp_path / "diag" / "my_notes.md")
    for out in (campaign, campaign.parent, campaign / "d", mine.parent):
        assert main(["diagnose", str(campaign), "--out", str(out), "track=false"]) == 2
        _one_error_line(capsys)
    assert main(["diagnose", str(campaign), "--out", str(campaign.parent), "track=false", "--force"]) == 2
    _one_error_line(capsys)
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before


# ------------------------------------------------------------------ export ---
@pytest.fixture
def model_dir(tmp_path, seed001_data_root, monkeypatch):
    from thermbench.experiment import save_models
    from thermbench.models.mlr import MLRSeed001, MLRSeed002

    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    ds = datasets.load_benchmark("seed001_vmc_x", seed001_data_root)
    models = {"seed001_vmc_x__mlr_seed001__global": MLRSeed001().fit(ds, ["state1", "state2"]),
              "seed001_vmc_x__mlr_seed002__global": MLRSeed002().fit(ds, ["state1", "state2"])}  # fmt: skip
    save_models(models, tmp_path / "models" / "mine")
    return tmp_path / "models" / "mine"


def _export(tmp_path, *extra):
    from thermbench.config import load_config
    from thermbench.export.job import run_export

    return run_export(load_config("export", ["export.verify=false", "export.onnx=false",
                                             f"tracking.uri=sqlite:///{tmp_path}/mlflow.db", *extra]))  # fmt: skip


def test_export_replaces_its_own_set_and_leaves_no_stale_folder(model_dir, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    note = _plant(tmp_path / "exports" / "README.txt")  # in the parent of the export set
    _, out = _export(tmp_path, f"export.source={model_dir}")
    root = Path(out["dir"])
    assert root == Path("exports/mine")
    keys = sorted(p.name for p in root.iterdir() if p.is_dir())
    assert keys == ["seed001_vmc_x__mlr_seed001__global", "seed001_vmc_x__mlr_seed002__global"]
    _export(tmp_path, f"export.source={model_dir}", "export.select=[seed001_vmc_x__mlr_seed002__global]")
    assert sorted(p.name for p in root.iterdir()) == [RECORD, "seed001_vmc_x__mlr_seed002__global"]  # no stale one
    assert note.read_text() == NOTE


def test_export_refuses_a_users_folder_and_a_dataset(model_dir, campaign, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    before = _digest(tmp_path / "campaign")
    mine = _plant(tmp_path / "exports" / "mine" / "calibration.pdf")
    with pytest.raises(OutputRefused, match="calibration.pdf"):
        _export(tmp_path, f"export.source={model_dir}")
    for out in (campaign, campaign.parent, campaign / "exp"):
        for force in ("false", "true"):
            with pytest.raises(OutputRefused, match="dataset"):
                _export(tmp_path, f"export.source={model_dir}", f"export.out_dir={out}", f"export.force={force}")
    _export(tmp_path, f"export.source={model_dir}", "export.force=true")  # beside the user's file
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before


# ----------------------------------------------------------- precompensate ---
def test_precompensate_never_writes_over_a_program(tmp_path):
    from tests.test_precompensate import SAMPLE, oracle, seed000_metadata
    from thermbench.precompensate import run_precompensate

    data = tmp_path / "data"
    data.mkdir()
    (data / "metadata.yaml").write_text(yaml.safe_dump(seed000_metadata().model_dump(mode="json", exclude_none=True)))
    model = tmp_path / "physics.joblib"
    joblib.dump(oracle(), model)
    prog = tmp_path / "nc" / "part.nc"
    prog.parent.mkdir()
    prog.write_text(SAMPLE.read_text())
    other = _plant(tmp_path / "nc" / "part_v2.nc")
    with pytest.raises(OutputRefused, match="part_v2.nc: exists and thermbench did not write it"):
        run_precompensate(prog, model, other, dataset=data)
    with pytest.raises(OutputRefused, match="lies inside the dataset"):
        run_precompensate(prog, model, data / "comp.nc", dataset=data)
    out = tmp_path / "nc" / "part_comp.nc"  # beside the user's programs
    run_precompensate(prog, model, out, dataset=data)
    run_precompensate(prog, model, out, dataset=data)  # its own earlier output: replaced
    assert other.read_text() == NOTE and prog.read_text() == SAMPLE.read_text()
    assert sorted(p.name for p in prog.parent.iterdir()) == [RECORD, "part.nc", "part_comp.nc", "part_v2.nc"]


# ------------------------------------------------------- sim-cnc, compensator ---
def test_sim_cnc_and_compensator_refuse_before_serving(campaign, tmp_path, seed001_exports):
    from thermbench.compensator.client import Compensator
    from thermbench.compensator.errors import CompensatorError
    from thermbench.compensator.simcnc import build_machine, nodes_yaml, serve

    before = _digest(tmp_path / "campaign")
    machine = build_machine({"benchmark": "seed001_vmc_x", "run": "valid1", "duration_s": 60})
    mine = _plant(tmp_path / "sim" / "notes.txt")
    base = {"endpoint": "opc.tcp://127.0.0.1:1/never", "run": "valid1", "speed": 100.0}
    for cfg in ({"out_dir": str(mine.parent)}, {"out_dir": str(campaign)}, {"out_dir": str(campaign.parent), "force": True},
                {"out_dir": str(tmp_path / "new"), "write_nodes": str(mine)}):  # fmt: skip
        with pytest.raises(OutputRefused):
            asyncio.run(serve({**base, **cfg}, machine))
    nodes = tmp_path / "nodes.yaml"
    nodes.write_text(yaml.safe_dump(nodes_yaml(machine)))
    for log in (mine, campaign / "log.csv"):
        with pytest.raises((OutputRefused, CompensatorError)):
            Compensator(seed001_exports / "mlr", "opc.tcp://127.0.0.1:1", nodes, {"log": str(log)})
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before


# --------------------------------------------------------- notebooks, certs ---
def test_notebook_runner_refuses_a_users_notebook_before_running(campaign, tmp_path, capsys):
    from tools import nbrun

    before = _digest(tmp_path / "campaign")
    (tmp_path / "nb").mkdir()
    (tmp_path / "nb" / "01_x.py").write_text('# %% tags=["parameters"]\nQUICK = False\n\n# %%\nraise SystemExit("ran")\n')
    mine = _plant(tmp_path / "out" / "01_x.ipynb")
    assert nbrun.main(["--notebooks", str(tmp_path / "nb"), "--out", str(mine.parent)]) == 2
    assert "01_x.ipynb: exists and thermbench did not write it" in _one_error_line(capsys)
    assert nbrun.main(["--notebooks", str(tmp_path / "nb"), "--out", str(campaign)]) == 2
    assert "lies inside the dataset" in _one_error_line(capsys)
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before


def test_benchmark_refuses_a_dataset_as_its_report_or_model_directory_before_any_fit(campaign, tmp_path, monkeypatch):
    from thermbench import bench as bm
    from thermbench.config import load_config

    before = _digest(tmp_path / "campaign")
    monkeypatch.setattr(bm.job, "tasks",  # where the job looks it up
                         lambda *a, **k: pytest.fail("worked before refusing"))
    for key in ("report_dir", "export_dir"):
        for d in (campaign, campaign.parent, campaign / "sub"):
            cfg = load_config("benchmark", [f"{key}={d}", "force=true", f"tracking.uri=sqlite:///{tmp_path}/m.db"])
            with pytest.raises(OutputRefused, match="dataset"):
                bm.benchmark(cfg)
    assert _digest(tmp_path / "campaign") == before


def test_certs_refuse_a_dataset_and_keep_other_files(campaign, tmp_path, capsys):
    before = _digest(tmp_path / "campaign")
    assert main(["certs", str(campaign)]) == 2
    assert "lies inside the dataset" in _one_error_line(capsys)
    mine = _plant(tmp_path / "pki" / "ca_notes.txt")
    assert main(["certs", str(mine.parent)]) == 0
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before


# ---------------------------------------------------------------- datasets ---
def test_save_dataset_refuses_a_users_dataset_and_replaces_its_own(campaign, tmp_path):
    from thermbench.data.io import load_dataset, save_dataset

    ds = load_dataset(campaign)
    before = _digest(tmp_path / "campaign")
    for target in (campaign, campaign / "copy", campaign.parent):
        with pytest.raises(OutputRefused, match="dataset"):
            save_dataset(ds, target)
    mine = _plant(tmp_path / "sim" / "notes.txt")
    with pytest.raises(OutputRefused, match="notes.txt"):
        save_dataset(ds, mine.parent)
    save_dataset(ds, tmp_path / "sim2")
    save_dataset(ds, tmp_path / "sim2", file_format="parquet")  # its own: replaced, CSVs gone
    assert sorted(p.name for p in (tmp_path / "sim2").iterdir()) == [RECORD, "errors.parquet", "metadata.yaml",
                                                                      "process.parquet"]  # fmt: skip
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before


# ---------------------------------------------------------------- simulate ---
def test_simulate_refuses_before_simulating(campaign, tmp_path, capsys, monkeypatch):
    from thermbench.sim import scenario

    before = _digest(tmp_path / "campaign")
    monkeypatch.setattr(scenario, "simulate_dataset", lambda *a, **k: pytest.fail("simulated before refusing"))
    mine = _plant(tmp_path / "sims" / "plan.txt")
    for ov in (f"out_dir={campaign}", f"out_dir={campaign.parent}", f"out_dir={campaign}/sim", f"out_dir={mine.parent}",
               f"out_dir={campaign.parent}", "force=true"):  # fmt: skip
        assert main(["simulate", ov] if ov != "force=true" else ["simulate", f"out_dir={campaign}", ov]) == 2
        line = _one_error_line(capsys)
        assert "dataset" in line or "plan.txt" in line
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before


# ------------------------------------------------------------- Hydra jobs ---
@pytest.mark.parametrize("job", ["train", "evaluate", "benchmark", "export"])
def test_hydra_jobs_refuse_a_dataset_or_a_users_folder_as_their_run_dir(job, campaign, tmp_path, capsys):
    before = _digest(tmp_path / "campaign")
    mine = _plant(tmp_path / "runs" / "draft.docx")
    for d in (campaign, campaign / "out", campaign.parent, mine.parent):
        assert main([job, f"hydra.run.dir={d}"]) == 2
        line = _one_error_line(capsys)
        assert "hydra.run.dir" in line or "draft.docx" in line
    assert mine.read_text() == NOTE and _digest(tmp_path / "campaign") == before
    assert not (campaign / ".hydra").exists()


def test_hydra_subdirectories_cannot_escape_the_run_directory(campaign, tmp_path, capsys):
    before = _digest(tmp_path / "campaign")
    for ov in (f"hydra.output_subdir={campaign}", "hydra.output_subdir=../x"):
        assert main(["train", f"hydra.run.dir={tmp_path}/r", ov]) == 2
        assert "config key 'hydra.output_subdir'" in _one_error_line(capsys)
    assert main(["train", "-m", f"hydra.sweep.dir={tmp_path}/s", "hydra.sweep.subdir=../../campaign", "train=state1,state2"]) == 2
    assert "config key 'hydra.sweep.subdir'" in _one_error_line(capsys)
    assert main(["train", r"hydra.run.dir=${oc.env:THERMBENCH_NO_SUCH_VARIABLE}"]) == 2
    assert "config key 'hydra.run.dir'" in _one_error_line(capsys)
    assert _digest(tmp_path / "campaign") == before


def test_sigterm_while_writing_leaves_no_staging_directory(tmp_path, seed001_exports, campaign):
    """kill -TERM during a write: the command unwinds, the staging directory is removed."""
    import os
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "rp"
    code = ("import os, signal, time, thermbench.export.replay as r\n"
            "def slow(*a, **k):\n"
            "    open(os.environ['MARK'], 'w').close(); time.sleep(60)\n"
            "r.draw_errors = slow\n"
            "from thermbench.cli import main\n"
            f"raise SystemExit(main(['replay', {str(seed001_exports / 'mlr')!r}, {str(campaign)!r}, '--run', 'valid1', '--out', {str(out)!r}]))\n")  # fmt: skip
    mark = tmp_path / "writing"
    p = subprocess.Popen([sys.executable, "-c", code], env={**os.environ, "MARK": str(mark)})
    t0 = time.monotonic()
    while not mark.exists() and time.monotonic() - t0 < 60 and p.poll() is None:
        time.sleep(0.1)
    assert mark.exists(), "the replay never reached its figures"
    p.send_signal(signal.SIGTERM)
    assert p.wait(timeout=30) == 128 + signal.SIGTERM
    assert not out.exists() and [q.name for q in tmp_path.iterdir() if q.name.startswith(".")] == []


def test_precompensate_with_models_never_writes_over_a_program(tmp_path):
    from tests.test_precompensate import SAMPLE, oracle, seed000_metadata
    from thermbench.precompensate.axes import run_precompensate_axes

    data = tmp_path / "data"
    data.mkdir()
    (data / "metadata.yaml").write_text(yaml.safe_dump(seed000_metadata().model_dump(mode="json", exclude_none=True)))
    joblib.dump(oracle(), tmp_path / "physics.joblib")
    axes = tmp_path / "axes.yaml"
    axes.write_text("X: {model: physics.joblib, dataset: data}\nY: {model: physics.joblib, dataset: data}\n")
    prog = tmp_path / "nc" / "part.nc"
    prog.parent.mkdir()
    prog.write_text(SAMPLE.read_text())
    other = _plant(tmp_path / "nc" / "part_v2.nc")
    with pytest.raises(OutputRefused, match="part_v2.nc: exists and thermbench did not write it"):
        run_precompensate_axes(prog, axes, other)
    with pytest.raises(OutputRefused, match="lies inside the dataset"):
        run_precompensate_axes(prog, axes, data / "comp.nc")
    with pytest.raises(ValueError, match="would overwrite the input program"):
        run_precompensate_axes(prog, axes, prog)
    out = tmp_path / "nc" / "part_comp.nc"
    run_precompensate_axes(prog, axes, out)
    run_precompensate_axes(prog, axes, out)  # its own earlier output: replaced
    assert other.read_text() == NOTE and prog.read_text() == SAMPLE.read_text()
    assert sorted(p.name for p in prog.parent.iterdir()) == [RECORD, "part.nc", "part_comp.nc", "part_v2.nc"]
