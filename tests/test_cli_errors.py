"""Bad input on the command line: one line on stderr, exit 2, before any work starts,
and everything else keeps its traceback.

* Hydra mistakes (a typo in a key or a group option, a mandatory ``???`` value left out,
  a malformed or empty override, a value of the wrong type, a sweep without ``-m``) for
  every command that takes overrides, with a did-you-mean; in a ``-m`` sweep a mistake in
  any one combination stops the sweep before its first job and names that job.
* A bug in one job of a sweep (an unexpected exception) does not stop the other jobs: its
  traceback is printed, the summary marks it, the exit code is 1.
* A programming error (a ``KeyError``/``ValueError`` inside model or library code) keeps
  its traceback; only the validated user-input errors get the one-line form.
* ``thermbench ... | head``: the reader going away ends the command quietly (141), with no
  ``BrokenPipeError`` traceback, tried with a real pipe whose reader is gone before the
  first write (what ``| head -1`` does to the rest of the output, without the race).

Most tests call :func:`thermbench.cli.main` in-process (the checks run before Hydra starts
a job, so they take a fraction of a second); the pipe tests run ``python -m thermbench.cli``.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from thermbench.cli import main

PY = [sys.executable, "-m", "thermbench.cli"]


@pytest.fixture
def workdir(tmp_path, monkeypatch):
    """Run in a tmp dir: whatever a command would write (outputs/, mlflow.db) lands there."""
    monkeypatch.chdir(tmp_path)
    return tmp_path


def one_error_line(capsys, prefix: str = "thermbench") -> str:
    """The single stderr line of a user mistake (asserting there is exactly one)."""
    err = capsys.readouterr().err
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err
    assert lines[0].startswith(f"{prefix}: error: "), lines[0]
    return lines[0]


def run(argv: list[str]) -> int:
    """``main(argv)``'s exit code, also when argparse exits (a usage mistake)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return exc.code


def nothing_written(tmp: Path) -> bool:
    return not any(tmp.iterdir())


# ------------------------------------------------------ Hydra jobs (app.run) ---
@pytest.mark.parametrize(
    "args, expected",
    [
        (["modle=lssvm"], "unknown config key 'modle'; did you mean 'model'?"),
        (["tracking.regster=false"], "unknown config key 'tracking.regster'; did you mean 'tracking.register'?"),
        (["trackng.register=false"], "did you mean 'tracking.register'?"),
        (["register=false"], "did you mean 'tracking.register'?"),  # a key at the wrong level
        (["experimnt=seed001_m1"], "did you mean 'experiment'?"),  # an optional group, absent from the config
        (["model=lsvm"], "unknown option 'lsvm' for config group 'model'; did you mean 'lssvm'? known: ar_seed003,"),
        (["hydra/launcher=jobib"], "unknown option 'jobib' for config group 'hydra/launcher'; did you mean 'joblib'?"),
        (["dataset=path"], "config key 'dataset.source.path' needs a value (it is ??? in conf/dataset/path.yaml"),
        (["train="], "override 'train=' gives no value: write train=VALUE, or train=null for none"),
        (["model=["], "malformed override 'model=['"),
        (["model/lssvm"], "override 'model/lssvm' has no '='"),
        (["seed=abc"], "config key 'seed': expected an integer (the config has 0), got 'abc'"),
        (["model=mlr_seed001,physics"], "lists several values: add -m"),
        (["+seed=3"], "config key 'seed' already exists: set it without the '+' (seed=3)"),
        (["-m", "--cfg", "job"], "-m/--multirun and --cfg cannot be combined"),  # Hydra: a ValueError traceback
        (["--bogus"], "unrecognized arguments: --bogus (see thermbench train --help)"),
        (["model.gama=1", "model=lssvm"], "unknown config key 'model.gama'; did you mean 'model.gamma'?"),
        (["model.colour=red"], "unknown config key 'model.colour'; keys of 'model': _target_,"),
    ],
)
def test_train_override_mistake_is_one_line_before_any_work(workdir, capsys, args, expected):
    assert main(["train", *args]) == 2
    line = one_error_line(capsys, "thermbench train")
    assert expected in line, line
    assert "+modle" not in line  # not Hydra's advice to add the typo as a new key
    assert nothing_written(workdir)  # no outputs/, no mlflow.db: nothing started


@pytest.mark.parametrize(
    "argv, prefix, expected",
    [
        (["evaluate", "dataset=seed001_vmc", "alias=champion"], "thermbench evaluate", "did you mean 'seed001_vmc_x'?"),
        (["benchmark", "famlies=[physics]"], "thermbench benchmark", "did you mean 'families'?"),
        (["benchmark", "progress=0"], "thermbench benchmark", "config key 'progress': expected true or false"),
        (["benchmark", "sweep=models_x_states"], "thermbench benchmark", "config 'benchmark' has no config group 'sweep'"),
        (["export", "export.sourc=x"], "thermbench export", "did you mean 'export.source'?"),
        (["simulate", "machine=seed000"], "thermbench", "did you mean 'seed000_x'?"),
        (["simulate", "seed=1,2"], "thermbench", "lists several values, but this command runs one configuration"),
        (["simulate", "suite=foo"], "thermbench", "config key 'suite': expected null or 'benchmark'"),
        (["simulate", "file_format=xls"], "thermbench", "config key 'file_format': expected csv or parquet"),
        (["diagnose", "/nonexistent", "--out", "o", "trak=false"], "thermbench", "did you mean 'track'?"),
        (["diagnose", "/nonexistent", "--out", "o", "max_effects=abc"], "thermbench", "config key 'max_effects': expected an integer"),
        (["compensator", "/nonexistent", "--endpoint", "opc.tcp://127.0.0.1:1", "--nodes", "n.yaml", "perod_s=1"],
         "thermbench", "unknown config key 'perod_s'; did you mean 'period_s'?"),
        (["compensator", "/nonexistent", "--endpoint", "opc.tcp://127.0.0.1:1", "--nodes", "n.yaml", "period_s=fast"],
         "thermbench", "config key 'period_s': expected a number"),
        (["sim-cnc", "sped=100"], "thermbench", "unknown config key 'sped'; did you mean 'speed'?"),
        (["trian"], "thermbench", "unknown command 'trian'; did you mean 'train'?"),
        (["classify", "--stroke", "100", "--start", "60", "--end", "160", "--feed", "-5"], "thermbench classify",
         "argument --feed: expected a finite number >= 0"),
    ],
)  # fmt: skip
def test_every_command_with_overrides_reports_one_line(workdir, capsys, argv, prefix, expected):
    assert run(argv) == 2
    line = one_error_line(capsys, prefix)
    assert expected in line, line
    assert nothing_written(workdir)


def test_a_config_mistake_in_one_combination_stops_the_sweep_before_any_job(workdir, capsys):
    sweep = workdir / "sweep"
    assert main(["train", "model=mlr_seed001,lsvm", "-m", "train=state1,state2", f"hydra.sweep.dir={sweep}"]) == 2
    line = one_error_line(capsys, "thermbench train")
    assert "sweep job (model=lsvm train=state1): unknown option 'lsvm' for config group 'model'" in line, line
    assert "did you mean 'lssvm'?" in line
    assert not sweep.exists() and nothing_written(workdir)
    # a value that only one point of a sweep gets wrong
    assert main(["train", "-m", "dataset=simulated", "dataset.source.seed=1,x", f"hydra.sweep.dir={sweep}"]) == 2
    line = one_error_line(capsys, "thermbench train")
    assert "sweep job (dataset=simulated dataset.source.seed=x): config key 'dataset.source.seed': expected an integer" in line
    assert not sweep.exists()


def test_config_inspection_and_help_still_work(workdir, capsys):
    # --cfg shows a config with its ??? values (nothing runs, nothing is required yet)
    assert main(["train", "--cfg", "job", "dataset=path"]) == 0
    out = capsys.readouterr().out
    assert "path: ???" in out
    # ... but a typo is still one line
    assert main(["train", "--cfg", "job", "modle=lssvm"]) == 2
    assert "did you mean 'model'?" in one_error_line(capsys, "thermbench train")
    assert main(["train", "--help"]) == 0
    assert "powered by Hydra" in capsys.readouterr().out
    assert nothing_written(workdir)


def test_top_level_help_names_spindles_too(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--help"])
    assert exc.value.code == 0
    text = " ".join(capsys.readouterr().out.split())
    assert "ball-screw feed axes and spindles" in text and "Ball-screw thermal error modelling" not in text


# ------------------------------------------------------- which errors are ours ---
def test_one_definition_of_user_errors_and_no_plain_valueerror_in_it():
    from thermbench import app
    from thermbench.config import ConfigError
    from thermbench.errors import UserError, user_errors

    assert app.user_errors is user_errors
    errors = user_errors()
    assert issubclass(ConfigError, UserError) and issubclass(UserError, ValueError)
    assert ValueError not in errors and KeyError not in errors and Exception not in errors
    assert not issubclass(ValueError, errors) and not issubclass(KeyError, errors)
    assert issubclass(ConfigError, errors) and issubclass(FileNotFoundError, errors)


def test_a_keyerror_in_library_code_keeps_its_traceback(workdir, monkeypatch, capsys):
    import thermbench.models.classify_one

    def broken(*args, **kwargs):
        raise KeyError("a bug, not a user mistake")

    monkeypatch.setattr(thermbench.models.classify_one, "classify_motion", broken)
    with pytest.raises(KeyError, match="a bug"):
        main(["classify", "--stroke", "100", "--start", "60", "--end", "160", "--feed", "1250"])
    assert "error:" not in capsys.readouterr().err


def _train_args(tmp: Path, *extra: str) -> list[str]:
    return ["train", f"tracking.uri=sqlite:///{tmp}/mlflow.db", f"tracking.artifact_root={tmp}/art",
            "tracking.register=false", f"hydra.run.dir={tmp}/run", f"hydra.sweep.dir={tmp}/sweep", "eval=valid1", *extra]  # fmt: skip


def test_a_valueerror_in_a_job_keeps_its_traceback(workdir, monkeypatch, capsys):
    """A Hydra job (no sweep): a ValueError from library code is Hydra's report of a failed
    job, with the traceback, exit code 1 (not the one-line form of a user mistake)."""
    import thermbench.export.job

    def run_export(cfg):
        raise ValueError("a bug inside the export")

    monkeypatch.setattr(thermbench.export.job, "run_export", run_export)
    rc = main(["export", f"hydra.run.dir={workdir}/run"])
    err = capsys.readouterr().err
    assert rc == 1, err
    assert "Traceback" in err and "ValueError: a bug inside the export" in err
    assert "thermbench export: error:" not in err


def test_a_bug_in_one_job_of_a_sweep_lets_the_others_finish(workdir, monkeypatch, capsys, seed001_data_root):
    """Basic launcher: job 0 raises an unexpected KeyError; job 1 still runs, the summary
    marks job 0 failed with the exception, its traceback is printed, the exit code is 1."""
    from thermbench.models.mlr import MLRSeed001

    def fit(self, *args, **kwargs):
        raise KeyError("a bug inside fit")

    monkeypatch.setenv("THERMBENCH_DATA", str(seed001_data_root))
    monkeypatch.setattr(MLRSeed001, "fit", fit)
    rc = main(_train_args(workdir, "-m", "model=mlr_seed001,mlr_seed002"))  # -m among the overrides: fine
    out, err = capsys.readouterr()
    assert rc == 1, err[-2000:]
    assert "Traceback" in err and "KeyError: 'a bug inside fit'" in err
    results = {p.parent.name: json.loads(p.read_text()) for p in (workdir / "sweep").glob("*/result.json")}
    assert set(results) == {"0", "1"}
    assert results["0"]["unexpected"] and results["0"]["error"].startswith("unexpected KeyError")
    assert "error" not in results["1"] and results["1"]["metrics"]["fit_s"] >= 0  # the other job finished
    summary = out.split("[sweep] summary", 1)[1]
    assert "unexpected KeyError" in summary and "1 job(s) failed: 0" in summary


# ---------------------------------------------------------------- | head ---
def _closed_pipe(args: list[str], env: dict) -> tuple[int, str]:
    """Run with stdout a pipe whose reader has gone (closed before the first write)."""
    proc = subprocess.Popen([*PY, *args], stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    proc.stdout.close()
    err = proc.stderr.read().decode()
    return proc.wait(timeout=120), err


@pytest.fixture
def pipe_env(seed001_data_root):
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["THERMBENCH_DATA"] = str(seed001_data_root)
    return env


@pytest.mark.parametrize(
    "args",
    [
        ["validate", "DATA"],  # an argparse command
        ["train", "--cfg", "job"],  # a Hydra job: Hydra prints the config
    ],
    ids=["validate", "train-cfg"],
)
def test_a_closed_pipe_ends_quietly(args, pipe_env, seed001_data_root):
    args = [str(seed001_data_root / "seed001_vmc_x") if a == "DATA" else a for a in args]
    rc, err = _closed_pipe(args, pipe_env)
    assert "Traceback" not in err and "BrokenPipe" not in err and "Exception ignored" not in err, err
    assert err == "" and rc == 141
