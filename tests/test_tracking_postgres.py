"""A team's MLflow tracking server on PostgreSQL (docs/experiments.md, "A team's tracking server").

The test starts a real PostgreSQL server (Debian's ``postgresql``: ``initdb`` + ``pg_ctl``) in a
temporary directory, as a non-root user, listening on 127.0.0.1 only, and ``mlflow server`` on
it with a file artifact root; thermbench jobs run against the server with ``tracking=server``.
What they record is then read back **from PostgreSQL's own tables** with psycopg, not only
through MLflow's client: runs, params, metrics, the logged model, the registered versions and
the ``champion`` alias. Two sweeps writing at once must not lose a run.

PostgreSQL missing is a failure, not a skip: ``make test`` installs it (tools/sysdeps.sh: ``apt-get install
postgresql``); on another machine install it the same way.
"""

from __future__ import annotations

import glob
import json
import os
import pwd
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path
from types import SimpleNamespace

import pytest

from tests.test_tracking import free_port, mlflow_server_on

DATASET = "seed001_vmc_x"
REGISTERED = f"thermbench-{DATASET}-mlr_seed001"
DB_USER = "thermbench"
DB_NAME = "mlflow"


def _pg_bin(name: str) -> str:
    """A PostgreSQL server program: on PATH, else Debian's /usr/lib/postgresql/<version>/bin."""
    found = shutil.which(name) or next(iter(sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"), reverse=True)), None)
    if found is None:
        pytest.fail(f"PostgreSQL's {name} is not installed: apt-get install postgresql (make test installs it: tools/sysdeps.sh)")
    return found


def _as_server_user(cmd: list[str]) -> list[str]:
    """PostgreSQL refuses to run as root: as root, run ``cmd`` as the ``postgres`` user that the
    Debian package creates (``runuser``); as anyone else, as oneself."""
    if os.geteuid() != 0:
        return cmd
    try:
        pwd.getpwnam("postgres")
    except KeyError:
        pytest.fail("running as root and there is no 'postgres' user: apt-get install postgresql (make test installs it: tools/sysdeps.sh)")
    return ["runuser", "-u", "postgres", "--", *cmd]


@pytest.fixture(scope="module")
def postgres():
    """A PostgreSQL cluster of its own in a temporary directory, on 127.0.0.1 and a free port,
    with a database for MLflow; stopped and removed after the module."""
    import psycopg

    initdb, pg_ctl = _pg_bin("initdb"), _pg_bin("pg_ctl")
    root = Path(tempfile.mkdtemp(prefix="tb-pg-"))  # not under pytest's 0700 tmp: the server user reads it
    data, sock = root / "data", root / "sock"
    sock.mkdir()
    if os.geteuid() == 0:
        shutil.chown(root, "postgres")
        shutil.chown(sock, "postgres")
    port = free_port()
    init = subprocess.run(_as_server_user([initdb, "-D", str(data), "-U", DB_USER, "--auth=trust", "-E", "UTF8",
                                           "--no-sync"]), capture_output=True, text=True)  # fmt: skip
    assert init.returncode == 0, init.stdout + init.stderr
    log = root / "postgres.log"
    start = subprocess.run(_as_server_user([pg_ctl, "-D", str(data), "-l", str(log), "-w", "-t", "60", "-o",
                                            f"-h 127.0.0.1 -p {port} -k {sock} -c fsync=off", "start"]),
                           capture_output=True, text=True)  # fmt: skip
    try:
        assert start.returncode == 0, start.stdout + start.stderr + (log.read_text() if log.exists() else "")
        with psycopg.connect(host="127.0.0.1", port=port, user=DB_USER, dbname="postgres", autocommit=True) as admin, \
                admin.cursor() as cur:
            cur.execute(f"CREATE DATABASE {DB_NAME}")
            cur.execute("SELECT current_setting('listen_addresses'), current_setting('server_version')")
            listen, version = cur.fetchone()
        owner = pwd.getpwuid(data.stat().st_uid).pw_name
        yield SimpleNamespace(port=port, uri=f"postgresql+psycopg://{DB_USER}@127.0.0.1:{port}/{DB_NAME}", listen=listen,
                              version=version, owner=owner)  # fmt: skip
    finally:
        subprocess.run(_as_server_user([pg_ctl, "-D", str(data), "-m", "fast", "-w", "stop"]), capture_output=True)
        shutil.rmtree(root, ignore_errors=True)


@pytest.fixture(scope="module")
def pg_mlflow(postgres, tmp_path_factory):
    """``mlflow server`` with the PostgreSQL backend store and a file artifact root (proxied)."""
    with mlflow_server_on(postgres.uri, tmp_path_factory.mktemp("pg_mlflow"), workers=2) as server:
        yield SimpleNamespace(uri=server.uri, dir=server.dir, pg=postgres)


def sql(pg, query: str, *args) -> list[tuple]:
    """``query`` run on the MLflow database, straight from PostgreSQL."""
    import psycopg

    with psycopg.connect(host="127.0.0.1", port=pg.port, user=DB_USER, dbname=DB_NAME) as conn, conn.cursor() as cur:
        cur.execute(query, args)
        return cur.fetchall()


def thermbench(args: list[str], cwd: Path, env: dict, timeout: float = 600) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "thermbench.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)  # fmt: skip


@pytest.fixture
def env(seed001_data_root):
    e = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR" and not k.startswith("MLFLOW_")}
    e["THERMBENCH_DATA"] = str(seed001_data_root)
    return e


def test_the_server_is_a_private_postgresql_on_loopback(postgres):
    assert postgres.listen == "127.0.0.1"
    assert postgres.owner != "root"  # the cluster's files belong to the non-root server user
    assert int(postgres.version.split(".")[0]) >= 13


def test_a_train_job_lands_in_postgresql_and_the_champion_alias_exports(pg_mlflow, env, tmp_path):
    pg = pg_mlflow.pg
    server = ["tracking=server", f"tracking.uri={pg_mlflow.uri}", f"hydra.run.dir={tmp_path}/run"]
    proc = thermbench(["train", "model=mlr_seed001", "train=state1", "eval=valid1+valid2", *server], tmp_path, env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    run_id = proc.stdout.split("mlflow run: ", 1)[1].split()[0]

    # the run, its params and metrics, in PostgreSQL's tables
    (status, name), = sql(pg, "SELECT status, name FROM runs WHERE run_uuid = %s", run_id)
    assert status == "FINISHED"
    params = dict(sql(pg, "SELECT key, value FROM params WHERE run_uuid = %s", run_id))
    assert params["model._target_"] == "thermbench.models.mlr.MLRSeed001" and params["train"] == "state1"
    assert params["tracking.uri"] == pg_mlflow.uri
    metrics = dict(sql(pg, "SELECT key, value FROM latest_metrics WHERE run_uuid = %s", run_id))
    printed = float(proc.stdout.split("unseen_max_abs_residual_um: ", 1)[1].split()[0])
    assert metrics["unseen_max_abs_residual_um"] == pytest.approx(printed, abs=5e-4)  # printed with 3 decimals
    # the logged model (MLflow 3) and its registered version 1
    logged = sql(pg, "SELECT model_id, status FROM logged_models WHERE source_run_id = %s", run_id)
    assert len(logged) == 1 and logged[0][1] in ("READY", 2)  # MLflow stores the status name or its enum value
    versions = sql(pg, "SELECT version, run_id FROM model_versions WHERE name = %s", REGISTERED)
    assert versions == [(1, run_id)]
    # its artifacts went to the server's file artifact root, not to the client's directory
    assert list((pg_mlflow.dir / "artifacts").rglob("model.joblib"))
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "mlartifacts").exists()

    # the alias a team exports from: set as the benchmark sets it (thermbench.tracking.set_alias), read
    # back from PostgreSQL, then resolved by thermbench export through the server
    import mlflow

    from thermbench import tracking

    mlflow.set_registry_uri(pg_mlflow.uri)
    try:
        tracking.set_alias(REGISTERED, "champion", 1)
    finally:
        mlflow.set_registry_uri("")
    assert sql(pg, "SELECT name, alias, version FROM registered_model_aliases") == [(REGISTERED, "champion", 1)]
    out = thermbench(["export", f"export.name={REGISTERED}", "export.alias=champion", f"export.out_dir={tmp_path}/exp",
                      "export.verify=false", *server], tmp_path, env)  # fmt: skip
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "exp" / REGISTERED / "model.tbm").is_file()
    manifest = json.loads((tmp_path / "exp" / REGISTERED / "manifest.json").read_text())
    assert manifest["mlflow_run_id"] == run_id and manifest["source"]["uri"] == f"models:/{REGISTERED}@champion"


def test_two_sweeps_writing_at_once_lose_no_run(pg_mlflow, env, tmp_path):
    """Two multiruns (2 jobs each, both at once with the joblib launcher) against the same server,
    started together, so four jobs write at the same time: every job's run is in PostgreSQL,
    FINISHED, once, and every registered version is there with no gap."""
    pg = pg_mlflow.pg
    before = {r for (r,) in sql(pg, "SELECT run_uuid FROM runs")}
    procs = []
    for k, state in enumerate(["state2", "state3"]):
        models = "mlr_seed001,mlr_seed002"
        args = [sys.executable, "-m", "thermbench.cli", "train", "-m", f"model={models}", f"train={state}",
                "eval=valid1", "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "tracking=server",
                f"tracking.uri={pg_mlflow.uri}", f"hydra.sweep.dir={tmp_path}/sweep{k}"]  # fmt: skip
        procs.append(subprocess.Popen(args, cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                                      text=True))  # fmt: skip
    outs = [p.communicate(timeout=600) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    new = sql(pg, "SELECT r.run_uuid, r.status, p.value, q.value FROM runs r "
                  "JOIN params p ON p.run_uuid = r.run_uuid AND p.key = 'model._target_' "
                  "JOIN params q ON q.run_uuid = r.run_uuid AND q.key = 'train'")  # fmt: skip
    new = [row for row in new if row[0] not in before]
    assert len(new) == 4 and {row[1] for row in new} == {"FINISHED"}
    assert len({(row[2], row[3]) for row in new}) == 4  # 2 models x 2 states, each once
    # every job registered its model: one more version per run, none lost to a concurrent write
    registered = sql(pg, "SELECT name, version, run_id FROM model_versions")
    assert {run for *_, run in registered} >= {row[0] for row in new}
    for name in {n for n, *_ in registered}:
        numbers = sorted(v for n, v, _ in registered if n == name)
        assert numbers == list(range(1, len(numbers) + 1)), (name, numbers)  # no gap, no duplicate
    counts = {t: sql(pg, f"SELECT count(*) FROM {t}")[0][0] for t in ("runs", "params", "latest_metrics",
                                                                        "logged_models", "model_versions")}  # fmt: skip
    print(f"PostgreSQL {pg.version} holds: {counts}; this test's sweeps added {len(new)} FINISHED runs")  # pytest -s
