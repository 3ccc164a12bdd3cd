"""``thermbench validate`` against the adversarial datasets of :mod:`tests.adversarial`.

Every case ends in exit 0 (valid) or exit 2 with exactly one line on stderr naming the
file and the column / key / row; never a traceback, and the input is left byte-identical.
The resource cases (one each: alias bomb, huge file, FIFO, deep nesting, decompression
bomb) also run in a real process: peak memory below 1 GiB, CPU
time below 10 s, and an end (no hang).
"""

from __future__ import annotations

import os
import re
import resource
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tests.adversarial import CASES, build, snapshot
from thermbench.cli import main

# The budget for every case: 10 s and 1 GB. The validate process runs with its address
# space capped at 1 GiB (an allocation past it fails inside the process, which would then not end
# in its one-line error), its peak resident memory and CPU time are measured, and it must end within
# 10 s of wall time (a FIFO opened for reading would block without using CPU).
RSS_LIMIT_BYTES = 1 << 30
ADDRESS_SPACE_CAP_BYTES = 1 << 30
TIME_LIMIT_S = 10.0
HANG_LIMIT_S = 10.0
REPO = Path(__file__).resolve().parents[1]


def _check_message(name: str, code: int, err: str) -> None:
    case = CASES[name]
    assert "Traceback" not in err, err
    if case.valid:
        assert code == 0, f"{name}: expected valid, got exit {code}: {err}"
        assert err == "", err
        return
    assert code == 2, f"{name}: expected exit 2, got {code}: {err}"
    lines = err.splitlines()
    assert len(lines) == 1 and err.endswith("\n"), f"{name}: expected one line on stderr, got {err!r}"
    assert lines[0].startswith("thermbench: error: "), lines[0]
    missing = [n for n in case.needles if n not in lines[0]]
    assert not missing, f"{name}: the message does not name {missing}: {lines[0]}"


@pytest.mark.parametrize("name", list(CASES))
def test_validate(name, tmp_path, capsys):
    path = build(CASES[name], tmp_path)
    before = snapshot(tmp_path)
    code = main(["validate", str(path)])
    out, err = capsys.readouterr()
    assert snapshot(tmp_path) == before, f"{name}: validate modified its input"
    _check_message(name, code, err)
    if CASES[name].valid:
        assert "valid thermbench-dataset/1 dataset" in out


def _cap_address_space() -> None:
    resource.setrlimit(resource.RLIMIT_AS, (ADDRESS_SPACE_CAP_BYTES, ADDRESS_SPACE_CAP_BYTES))


# runs the command given as its arguments and reports that child's exit code, peak resident
# memory (KiB) and CPU time (s): RUSAGE_CHILDREN of a fresh process covers that one child only
_MEASURE = (
    "import resource, subprocess, sys\n"
    "r = subprocess.run(sys.argv[1:], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)\n"
    "sys.stderr.buffer.write(r.stderr)\n"
    "u = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
    "print(r.returncode, u.ru_maxrss, u.ru_utime + u.ru_stime)\n"
)


def _validate_in_a_process(path: Path, cwd: Path, timeout_s: float) -> tuple[int, str, int, float]:
    """``thermbench validate path`` in a real process: exit code, stderr, peak RSS (bytes), CPU seconds."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-c", _MEASURE, sys.executable, "-m", "thermbench", "validate", str(path)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=cwd, env=env,
                            preexec_fn=_cap_address_space, start_new_session=True)  # fmt: skip
    try:
        out, err = proc.communicate(timeout=timeout_s)
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)  # the wrapper and validate: its own process group
        proc.communicate()
        pytest.fail(f"validate {path} hung: no end after {timeout_s} s")
    code, maxrss_kib, cpu_s = out.split()
    return int(code), err, int(maxrss_kib) * 1024, float(cpu_s)


@pytest.mark.parametrize("name", [n for n, c in CASES.items() if c.resource])
def test_resource_case_in_a_real_process(name, tmp_path):
    path = build(CASES[name], tmp_path)
    before = snapshot(tmp_path)
    code, err, rss, cpu_s = _validate_in_a_process(path, tmp_path, HANG_LIMIT_S)
    assert snapshot(tmp_path) == before, f"{name}: validate modified its input"
    _check_message(name, code, err)
    assert rss < RSS_LIMIT_BYTES, f"{name}: peak RSS {rss / 2**20:.0f} MiB"
    assert cpu_s < TIME_LIMIT_S, f"{name}: {cpu_s:.1f} s of CPU"


def test_the_set_covers_every_class():
    kinds = {c.kind for c in CASES.values()}
    assert len(CASES) >= 70
    assert {"valid", "files", "yaml", "run ids", "metadata values", "table structure", "values: NaN/inf",
            "values: types", "values: ranges", "values: time", "values: travel", "values: duplicates"} <= kinds
    assert sum(c.valid for c in CASES.values()) >= 5
    assert {n for n, c in CASES.items() if c.resource} >= {"yaml_billion_laughs", "process_huge_sparse_300MiB",
                                                            "process_fifo", "yaml_deep_flow_nesting"}  # fmt: skip


def test_every_valid_run_id_is_a_safe_mlflow_metric_key_and_file_name(tmp_path):
    """The run-id rule implies what thermbench does with a run id: log ``runs/<id>/rmse_um``
    to MLflow and name files after it."""
    from mlflow.utils.validation import _validate_metric_name

    from thermbench.data.limits import run_id_problem

    ids = ["c1", "Run-1.a_B", "9", "a" * 64, "x.y", "a..b", "R_1-2", "NA", "null"]
    for run_id in ids:
        assert run_id_problem(run_id) is None, run_id
        _validate_metric_name(f"runs/{run_id}/rmse_um")
        (tmp_path / f"{run_id}.csv").write_text("x")
        assert (tmp_path / f"{run_id}.csv").read_text() == "x"
    for run_id in ["c2 (6000 mm/min) #2", "a/b", "..", "a.", " c1", "", "a" * 65, "CON", "nul.txt", "é", "a:b"]:
        assert run_id_problem(run_id) is not None, run_id


def test_run_ids_in_the_shipped_protocols_and_notebooks_obey_the_rule():
    import yaml

    from thermbench.data.limits import run_id_problem

    for path in sorted((REPO / "conf" / "protocol").glob("*.yaml")):
        proto = yaml.safe_load(path.read_text(encoding="utf-8"))
        for run_id in proto.get("runs") or {}:
            assert run_id_problem(run_id) is None, (path.name, run_id)
        count = int((proto.get("random_runs") or {}).get("count", 0))
        for i in range(count):  # thermbench.sim.scenario names them random_01, ...
            assert run_id_problem(f"random_{i + 1:02d}") is None
    nb = (REPO / "notebooks" / "05_your_measurements.py").read_text(encoding="utf-8")
    tests = re.search(r"TESTS = \{(.*?)\}", nb, re.S)
    assert tests is not None
    for run_id in re.findall(r'"(\w+)": \(', tests[1]):
        assert run_id_problem(run_id) is None, run_id
