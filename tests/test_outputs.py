"""The output rules (thermbench.outputs): never delete or overwrite a file thermbench did not write."""

from __future__ import annotations

import hashlib
import json
import os

import pytest

from thermbench import outputs
from thermbench.outputs import RECORD, OutputRefused, OutputStream, output_dir, output_file


def _write(stage, files):
    for rel, text in files.items():
        p = stage / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)


def _tree(root):
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


NOTE = "my notes, do not lose\n"


def _plant(path, text=NOTE):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text)
    return path.read_bytes()


def test_new_directory_is_written_whole_with_a_record_of_each_file(tmp_path):
    target = tmp_path / "out"
    with output_dir(target, "report") as stage:
        _write(stage, {"report.md": "# r\n", "figures/a.png": "png"})
    rec = json.loads((target / RECORD).read_text())
    files = rec["sets"]["."]["files"]
    assert rec["sets"]["."]["kind"] == "report"
    assert files == {"report.md": hashlib.sha256(b"# r\n").hexdigest(), "figures/a.png": hashlib.sha256(b"png").hexdigest()}
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]  # no staging left over


def test_rewrite_replaces_own_files_and_removes_those_no_longer_made(tmp_path):
    target = tmp_path / "out"
    with output_dir(target, "report") as stage:
        _write(stage, {"report.md": "one", "figures/old.png": "old", "figures/keep.png": "k1"})
    with output_dir(target, "report") as stage:
        _write(stage, {"report.md": "two", "figures/keep.png": "k2"})
    assert _tree(target) | {RECORD: b""} == {"report.md": b"two", "figures/keep.png": b"k2", RECORD: b""}
    assert set(json.loads((target / RECORD).read_text())["sets"]["."]["files"]) == {"report.md", "figures/keep.png"}


def test_a_users_file_in_the_target_is_refused_before_the_work_and_nothing_changes(tmp_path):
    target = tmp_path / "out"
    with output_dir(target, "report") as stage:
        _write(stage, {"report.md": "one"})
    mine = _plant(target / "my_notes.txt")
    before = _tree(target)
    ran = []
    with pytest.raises(OutputRefused, match=r"out: holds 1 file\(s\) thermbench did not write there \(e\.g\. 'my_notes\.txt'\)"):
        with output_dir(target, "report") as stage:
            ran.append(True)
    assert not ran  # refused before the body ran
    assert _tree(target) == before and (target / "my_notes.txt").read_bytes() == mine
    with pytest.raises(OutputRefused, match="--force"):
        outputs.check_output_dir(target, "report")


def test_a_non_empty_directory_without_a_record_is_refused_an_empty_one_is_used(tmp_path):
    (tmp_path / "empty").mkdir()
    with output_dir(tmp_path / "empty", "replay") as stage:
        _write(stage, {"a.csv": "1"})
    assert (tmp_path / "empty" / "a.csv").read_text() == "1"
    mine = _plant(tmp_path / "full" / "thesis.tex")
    with pytest.raises(OutputRefused, match="thesis.tex"):
        with output_dir(tmp_path / "full", "replay") as stage:
            _write(stage, {"a.csv": "1"})
    assert (tmp_path / "full" / "thesis.tex").read_bytes() == mine
    assert sorted(p.name for p in (tmp_path / "full").iterdir()) == ["thesis.tex"]


def test_an_edited_output_counts_as_the_users(tmp_path):
    target = tmp_path / "out"
    with output_dir(target, "report") as stage:
        _write(stage, {"report.md": "generated"})
    (target / "report.md").write_text("generated + my comments")
    with pytest.raises(OutputRefused, match="'report.md' was changed since thermbench wrote it"):
        with output_dir(target, "report") as stage:
            _write(stage, {"report.md": "new"})
    assert (target / "report.md").read_text() == "generated + my comments"
    # even with force the edited file is never written over ...
    with pytest.raises(OutputRefused, match="report.md: exists and thermbench did not write it"):
        with output_dir(target, "report", force=True) as stage:
            _write(stage, {"report.md": "new"})
    assert (target / "report.md").read_text() == "generated + my comments"


def test_force_writes_beside_other_files_never_over_them(tmp_path):
    target = tmp_path / "shared"
    mine = _plant(target / "notes.txt")
    with output_dir(target, "diagnosis", force=True) as stage:
        _write(stage, {"diagnosis.json": "{}"})
    assert (target / "notes.txt").read_bytes() == mine and (target / "diagnosis.json").read_text() == "{}"
    with pytest.raises(OutputRefused, match="notes.txt: exists and thermbench did not write it"):
        with output_dir(target, "diagnosis", force=True) as stage:
            _write(stage, {"diagnosis.json": "{}", "notes.txt": "over"})
    assert (target / "notes.txt").read_bytes() == mine


@pytest.mark.parametrize("force", [False, True])
def test_datasets_are_never_written_into_over_or_around(tmp_path, force):
    ds = tmp_path / "campaign" / "run7"
    meta = _plant(ds / "metadata.yaml", "format: x\n")
    proc = _plant(ds / "process.csv", "t_s\n0\n")
    for target, why in [(ds, "is a dataset"), (ds / "out", "lies inside the dataset"),
                        (tmp_path / "campaign", "contains the dataset")]:
        with pytest.raises(OutputRefused, match=why):
            with output_dir(target, "replay", force=force) as stage:
                _write(stage, {"metadata.yaml": "mine"})
    with pytest.raises(OutputRefused, match="lies inside the dataset"):
        with output_file(ds / "prog.nc", "part-program") as tmp:
            tmp.write_text("G1")
    assert (ds / "metadata.yaml").read_bytes() == meta and (ds / "process.csv").read_bytes() == proc
    assert sorted(p.name for p in ds.iterdir()) == ["metadata.yaml", "process.csv"]


def test_a_dataset_thermbench_wrote_is_replaced_as_its_own_output(tmp_path):
    target = tmp_path / "sim"
    with output_dir(target, "dataset") as stage:
        _write(stage, {"metadata.yaml": "a", "process.csv": "1", "errors.csv": "2"})
    with output_dir(target, "dataset") as stage:
        _write(stage, {"metadata.yaml": "b", "process.parquet": "1", "errors.parquet": "2"})
    assert sorted(_tree(target)) == sorted([RECORD, "metadata.yaml", "process.parquet", "errors.parquet"])
    with pytest.raises(OutputRefused, match="holds dataset output, not report"):
        outputs.check_output_dir(target, "report", force=True)


def test_failure_while_writing_leaves_the_previous_output(tmp_path):
    target = tmp_path / "out"
    with output_dir(target, "models") as stage:
        _write(stage, {"a.joblib": "A"})
    before = _tree(target)
    with pytest.raises(RuntimeError, match="boom"):
        with output_dir(target, "models") as stage:
            _write(stage, {"b.joblib": "B"})
            raise RuntimeError("boom")
    assert _tree(target) == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]


def test_interrupted_replacement_is_still_recognised_as_ours(tmp_path, monkeypatch):
    """A crash between two renames leaves old and new files mixed; the record lists both
    contents, so the next run replaces them instead of calling them the user's."""
    target = tmp_path / "out"
    with output_dir(target, "models") as stage:
        _write(stage, {"a": "1", "b": "1"})
    real, calls = os.replace, []

    def die_on_second_file(src, dst):
        calls.append(dst)
        if sum(not str(d).endswith(RECORD) for d in calls) == 2:
            raise KeyboardInterrupt
        return real(src, dst)

    monkeypatch.setattr(outputs.os, "replace", die_on_second_file)
    with pytest.raises(KeyboardInterrupt):
        with output_dir(target, "models") as stage:
            _write(stage, {"a": "2", "b": "2"})
    monkeypatch.setattr(outputs.os, "replace", real)
    assert sorted(((target / "a").read_text(), (target / "b").read_text())) == ["1", "2"]  # mixed
    with output_dir(target, "models") as stage:
        _write(stage, {"a": "3", "b": "3"})
    assert (target / "a").read_text() == "3" and (target / "b").read_text() == "3"


def test_single_file_outputs_among_other_files(tmp_path):
    prog = _plant(tmp_path / "part.nc", "G1 X10\n")
    with output_file(tmp_path / "part_comp.nc", "part-program") as tmp:
        tmp.write_text("G1 X10.001\n")
    with output_file(tmp_path / "part_comp.nc", "part-program") as tmp:  # its own earlier output: replaced
        tmp.write_text("G1 X10.002\n")
    assert (tmp_path / "part_comp.nc").read_text() == "G1 X10.002\n"
    with pytest.raises(OutputRefused, match="part.nc: exists and thermbench did not write it"):
        with output_file(tmp_path / "part.nc", "part-program") as tmp:
            tmp.write_text("over")
    assert (tmp_path / "part.nc").read_bytes() == prog
    assert sorted(p.name for p in tmp_path.iterdir()) == [RECORD, "part.nc", "part_comp.nc"]
    with pytest.raises(OutputRefused, match="holds part-program output, not nodes"):
        outputs.check_output_file(tmp_path / "part_comp.nc", "nodes")


def test_a_stream_replaces_only_its_own_log_and_survives_a_crash(tmp_path):
    mine = _plant(tmp_path / "log.csv", "a user's log\n")
    with pytest.raises(OutputRefused, match="log.csv: exists and thermbench did not write it"):
        OutputStream(tmp_path / "log.csv", "compensator-log")
    assert (tmp_path / "log.csv").read_bytes() == mine
    s = OutputStream(tmp_path / "ours.csv", "compensator-log")
    s.fh.write("cycle\n1\n")  # the process dies here: no close()
    s.fh.flush()
    s2 = OutputStream(tmp_path / "ours.csv", "compensator-log")  # a crashed log is still thermbench's
    s2.fh.write("cycle\n")
    s2.close()
    rec = json.loads((tmp_path / RECORD).read_text())
    assert rec["sets"]["ours.csv"]["files"]["ours.csv"] == hashlib.sha256(b"cycle\n").hexdigest()


def test_a_copied_record_does_not_make_the_copy_thermbenchs(tmp_path):
    """cp -r of an output carries its record; in the copy the files are the user's."""
    import shutil

    with output_dir(tmp_path / "sim", "dataset") as stage:
        _write(stage, {"metadata.yaml": "m", "process.csv": "p"})
    with output_dir(tmp_path / "rep", "report") as stage:
        _write(stage, {"report.md": "r"})
    for src, dst, kind, why in [("sim", "myrun", "dataset", "is a dataset"),
                                ("rep", "myreport", "report", "its thermbench record was copied from another directory")]:
        shutil.copytree(tmp_path / src, tmp_path / dst)
        before = _tree(tmp_path / dst)
        with pytest.raises(OutputRefused, match=why):
            with output_dir(tmp_path / dst, kind) as stage:
                _write(stage, {"metadata.yaml": "other machine"})
        assert _tree(tmp_path / dst) == before
    (tmp_path / "sim").rename(tmp_path / "moved")  # a rename keeps the directory: still thermbench's
    with output_dir(tmp_path / "moved", "dataset") as stage:
        _write(stage, {"metadata.yaml": "again"})
    assert (tmp_path / "moved" / "metadata.yaml").read_text() == "again"


def test_a_path_through_a_file_or_a_link_is_judged_where_it_really_goes(tmp_path):
    note = _plant(tmp_path / "notes.txt")
    with pytest.raises(OutputRefused, match="notes.txt is a file, not a directory"):
        outputs.check_output_dir(tmp_path / "notes.txt" / "x", "replay")
    ds = tmp_path / "lab" / "run7"
    _plant(ds / "metadata.yaml", "format: x\n")
    (ds / "photos").mkdir()
    (tmp_path / "photolink").symlink_to(ds / "photos")
    with pytest.raises(OutputRefused, match="lies inside the dataset"):  # photolink/.. is run7 itself
        with output_dir(tmp_path / "photolink" / ".." / "evil", "dataset") as stage:
            _write(stage, {"metadata.yaml": "x"})
    assert sorted(p.name for p in ds.iterdir()) == ["metadata.yaml", "photos"] and (tmp_path / "notes.txt").read_bytes() == note


def test_hydra_directories_must_prove_they_are_hydras(tmp_path):
    users = tmp_path / "mine"
    _plant(users / "result.json", "{my results}")
    with pytest.raises(OutputRefused, match="is not an earlier Hydra job's directory"):
        outputs.check_hydra_dir(users)
    run = tmp_path / "run"
    for rel in (".hydra/hydra.yaml", ".hydra/config.yaml", "train.log", "result.json"):
        _plant(run / rel, "x")
    outputs.check_hydra_dir(run)  # an earlier run: fine
    _plant(run / "analysis.ipynb", "{}")
    with pytest.raises(OutputRefused, match="analysis.ipynb"):
        outputs.check_hydra_dir(run)


def test_a_submitit_sweep_directory_is_a_hydra_sweeps(tmp_path):
    """What hydra-submitit-launcher leaves in a sweep directory (``.submitit/%j``), with the local
    executor (a pid per job) and with SLURM (array job ids, the submission script, and in
    ``.submitit/`` itself the link to each submission script and pickles of jobs being
    submitted: submitit 1.5 core.py Executor._submit_command), is accepted for a resume; a file
    of the user's in there is not."""
    sweep = tmp_path / "sweep"
    hexa = "0123456789abcdef0123456789abcdef"
    for rel in ("multirun.yaml", "sweep_size.txt", "0/.hydra/hydra.yaml", "0/result.json", "0/train.log",
                ".submitit/27375/27375_submitted.pkl", ".submitit/27375/27375_0_log.out",
                ".submitit/27375/27375_0_log.err", ".submitit/27375/27375_0_result.pkl.save_tmp",
                ".submitit/4242_1/4242_1_submitted.pkl", ".submitit/4242_1/4242_1_0_result.pkl",
                ".submitit/4242_1/4242_submission.sh", f".submitit/.submission_file_{hexa}.sh",
                f".submitit/{hexa}.pkl"):  # fmt: skip
        _plant(sweep / rel, "x")
    outputs.check_hydra_dir(sweep, "hydra.sweep.dir")
    for mine in (".submitit/notes.txt", ".submitit/27375/analysis.pkl", f".submitit/{hexa}.csv"):
        _plant(sweep / mine, "x")
        with pytest.raises(OutputRefused, match="not an earlier Hydra job's"):
            outputs.check_hydra_dir(sweep, "hydra.sweep.dir")
        (sweep / mine).unlink()
