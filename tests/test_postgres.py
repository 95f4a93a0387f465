"""Sweeps and runs on a real PostgreSQL server that the tests start themselves
(tests/support/postgres.py): two worker processes that share nothing but the Optuna storage's
and the MLflow server's URIs run one study, one of them killed in the middle of a trial
that the other one retries; the trial table equals the same sweep's on sqlite, and
``fedlgr report`` reads it back. A run on a ``postgresql://`` tracking store resumes.
Bad URIs, a stopped server, a wrong password and a missing driver are one line each.

Skipped, with the reason, only where PostgreSQL's ``initdb`` is not installed (.ci/run
installs Debian's ``postgresql`` package where it can)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import optuna
import pytest

from fedlgr.shell.cli import main
from fedlgr.shell.config import flatten, to_yaml
from fedlgr.shell.sweep import load_sweep, run_sweep
from fedlgr.shell.tracking.uri import mask_password, masked_text
from tests.support.data import read_rows
from tests.support.ports import free_port, wait_healthy
from tests.support.postgres import USER, PostgresServer, missing, postgres_server
from tests.support.runs import FAST, fast_config

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(missing() is not None, reason=missing() or "")


@pytest.fixture(scope="module")
def postgres():
    """One server for the module (it starts in about a second); each test makes its own
    databases."""
    with postgres_server() as server:
        yield server


@pytest.fixture(scope="module")
def stopped() -> str:
    """The URI of a database on a server that was started, then stopped."""
    server = PostgresServer().start()
    uri = server.create_database("gone")
    server.stop()
    return uri


# --------------------------------------------------------------------------- one-line errors


def test_a_password_is_masked_wherever_it_stands():
    cases = {
        "postgresql://me:s3cret@db.lab:5432/optuna": "postgresql://me:***@db.lab:5432/optuna",
        "postgresql+psycopg://me:p%40ss@h/db?sslmode=require": (
            "postgresql+psycopg://me:***@h/db?sslmode=require"
        ),
        "postgresql://me:a/b@c@h:1/db": "postgresql://me:***@h:1/db",  # unencoded / and @
        "postgresql://me:pw@[::1/db": "postgresql://me:***@[::1/db",  # no parser reads it
        "postgresql://me@h/db": "postgresql://me@h/db",
        "postgresql://h/db?user=me": "postgresql://h/db?user=me",
        "postgresql://h/db?user=me&password=s3cret&sslmode=require": (
            "postgresql://h/db?user=me&password=***&sslmode=require"
        ),
        "postgresql://me:pw@h/db?PASSWORD=x": "postgresql://me:***@h/db?PASSWORD=***",
        # libpq decodes the name (pass%77ord is password) and reads sslpassword too
        "postgresql://h/db?user=me&pass%77ord=s3cret": "postgresql://h/db?user=me&pass%77ord=***",
        "postgresql://h/db?sslpassword=k3y&sslmode=require": (
            "postgresql://h/db?sslpassword=***&sslmode=require"
        ),
        "http://alice:s3cret@127.0.0.1:1/": "http://alice:***@127.0.0.1:1/",
        "sqlite:////tmp/a:b@c/optuna.db": "sqlite:////tmp/a:b@c/optuna.db",
        "http://127.0.0.1:5000": "http://127.0.0.1:5000",
    }
    assert {uri: mask_password(uri) for uri in cases} == cases
    # elsewhere in a text: as written, decoded, and the tail a parser took for a host
    text = "could not translate host name 'ssTail@h' (p@ssTail, QueryPw, p%40ssTail)"
    uri = "postgresql://me:p@ssTail@h/db?password=QueryPw"
    assert masked_text(text, uri) == "could not translate host name '***@h' (***, ***, p%40***)"
    encoded = "postgresql://me:p%40ssTail@h/db"
    assert masked_text(text, encoded) == "could not translate host name '***@h' (***, QueryPw, ***)"


def test_the_config_a_run_shows_logs_and_sends_holds_no_password(synth_dir, tmp_path):
    """``config.yaml`` (the run's artifact, ``--print-config``, what a Flower server sends
    its robots) names the tracking URI with its password masked."""
    uri = "postgresql://me:Artifact5ecret@db.lab:5432/mlflow"
    config = fast_config(synth_dir, tmp_path, uri)
    text = to_yaml(config)
    assert "Artifact5ecret" not in text
    assert "uri: postgresql://me:***@db.lab:5432/mlflow" in text
    assert config.tracking.uri == uri  # the run itself still connects with it
    # what a checkpoint keeps of the config (and MLflow's params) neither
    assert flatten(config)["tracking.uri"] == "postgresql://me:***@db.lab:5432/mlflow"


def test_an_unreachable_tracking_server_is_named_without_its_password(capsys, synth_dir):
    uri = "http://alice:HtS3cret9@127.0.0.1:1/"
    code = main(["run", str(FAST), f"data.path={synth_dir}", "--tracking-uri", uri])
    line = _one_line(capsys, code, "HtS3cret9")
    assert line.startswith("fedlgr: error: tracking URI http://alice:***@127.0.0.1:1/: no MLflow")


def _one_line(capsys, code: int, *secrets: str) -> str:
    out, err = capsys.readouterr()
    assert code == 1, (out, err)
    (line,) = err.strip().splitlines()
    assert line.startswith("fedlgr: error: ")
    for secret in secrets:
        assert secret not in out + err
    return line


def _grid(folder: Path, name: str, rounds: int = 2) -> Path:
    """A 4-point grid on the tests' tiny config; data and image cache relative to the
    working folder (``./data``, ``./cache``): each machine has its own."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.yaml"
    path.write_text(
        f"base: {FAST}\n"
        "overrides: [data.path=data, data.cache_dir=cache, runtime.threads=1, "
        f"federated.rounds={rounds}]\n"
        "objective: {metric: test/rmse, direction: minimize}\n"
        "space:\n"
        "  method: [FedAvg, FedRootAvg]\n"
        "  train.lr_top: [0.001, 0.01]\n"
    )
    return path


@pytest.mark.slow
def test_a_wrong_password_a_stopped_server_and_bad_uris_are_one_line_each(
    postgres, stopped, tmp_path, synth_dir, capsys, monkeypatch
):
    """``fedlgr sweep``, ``run``, ``run --resume`` and ``report``: exit 1 with one line that
    names the URI, its password masked, and says what is wrong; nothing is created."""
    monkeypatch.chdir(tmp_path)
    sweep = str(_grid(tmp_path, "errors"))
    good = postgres.create_database("errors")
    wrong = postgres.uri("errors", password="Wr0ngPassw0rd")
    store = f"sqlite:///{tmp_path}/mlflow.db"
    hidden = f"postgresql://fedlgr:***@127.0.0.1:{postgres.port}"
    gone = mask_password(stopped)
    run = [str(FAST), f"data.path={synth_dir}", "--tracking-uri"]
    cases = [
        (
            ["sweep", sweep, "--storage", wrong, "--tracking-uri", store],
            f"--storage {hidden}/errors",
        ),
        (["sweep", sweep, "--storage", stopped, "--tracking-uri", store], f"--storage {gone}"),
        (["sweep", sweep, "--tracking-uri", wrong], f"tracking URI {hidden}/errors"),
        (["run", *run, wrong], f"tracking URI {hidden}/errors"),
        (["run", *run, stopped, "--resume"], f"tracking URI {gone}"),
        (["report", "--sweep", "errors", "--tracking-uri", wrong], f"tracking URI {hidden}/errors"),
        (["report", "--tracking-uri", stopped], f"tracking URI {gone}"),
    ]
    for argv, named in cases:
        line = _one_line(capsys, main(argv), postgres.password, "Wr0ngPassw0rd")
        assert line.startswith(f"fedlgr: error: {named}: "), line
        if "Wr0ng" in " ".join(argv):
            assert 'password authentication failed for user "fedlgr"' in line, line
        else:
            assert "no database server answers at 127.0.0.1:" in line, line
            assert "(connection refused)" in line, line

    bad = {
        good.replace("postgresql:", "postgres:"): "unknown database kind 'postgres': "
        "PostgreSQL's URLs begin postgresql://",
        good.replace("postgresql:", "postgresql+psycopg2:"): "its driver psycopg2 is not installed",
        good.replace(f":{postgres.port}/", ":port/"): "not a database URL (",
        postgres.uri("nosuchdb"): 'database "nosuchdb" does not exist',
        # libpq splits at the first @, SQLAlchemy at the last: the tail is no host name
        postgres.uri("errors", password="p@ssTail9"): "its user or password holds an '@': "
        "write it percent-encoded, %40",
        # libpq reads a password in the query too
        f"postgresql://127.0.0.1:{postgres.port}/errors?user=fedlgr&password=QueryWr0ng77": (
            'password authentication failed for user "fedlgr"'
        ),
        good + "?connect_timeout=abc": "connect_timeout",  # at once, not after 2 min
    }
    secrets = (postgres.password, "ssTail9", "QueryWr0ng77")
    for uri, problem in bad.items():
        code = main(["sweep", sweep, "--storage", uri, "--tracking-uri", store])
        line = _one_line(capsys, code, *secrets)
        assert line.startswith(f"fedlgr: error: --storage {mask_password(uri)}: "), line
        assert problem in line, line
        code = main(["run", *run, uri])
        line = _one_line(capsys, code, *secrets)
        assert line.startswith(f"fedlgr: error: tracking URI {mask_password(uri)}: "), line
        assert problem in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["errors.yaml"]  # nothing created
    with postgres.connect("errors") as connection:  # no table either
        tables = "SELECT tablename FROM pg_tables WHERE schemaname = 'public'"
        assert connection.execute(tables).fetchall() == []


@pytest.mark.slow
def test_a_database_server_that_stops_mid_sweep_is_one_line(tmp_path, synth_dir):
    """The study's server stopped (pg_ctl -m fast) while a trial trains: the sweep exits 1
    with one line naming the storage and what to do, not Optuna's chain of seven
    tracebacks (its UnboundLocalError raised while it handled the lost connection)."""
    server = PostgresServer().start()
    try:
        storage = server.create_database("optuna")
        machine, env, path = _machine(tmp_path, "m", synth_dir, "stops")
        path.write_text(path.read_text().replace("federated.rounds=2", "federated.rounds=40"))
        command = [sys.executable, "-m", "fedlgr", "sweep", str(path), "--storage", storage]
        command += ["--tracking-uri", f"sqlite:///{machine}/mlflow.db"]
        proc = subprocess.Popen(
            command, cwd=machine, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
            text=True,
        )  # fmt: skip
        deadline = time.monotonic() + 300
        while _running_trial(storage) is None:
            assert proc.poll() is None and time.monotonic() < deadline, proc.stdout.read()
            time.sleep(0.1)
    finally:
        server.stop()
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 1, out
    assert "Traceback" not in out, out[-3000:]
    last = out.strip().splitlines()[-1]
    assert last.startswith(f"fedlgr: error: --storage {mask_password(storage)}: "), last
    assert "run the same command again once the storage answers" in last, last
    assert server.password not in out


@pytest.mark.slow
def test_a_missing_driver_is_one_line_naming_the_extra(postgres, tmp_path):
    """Without psycopg (here: its import blocked, as in an environment synced without the
    ``postgres`` extra) the storage and the tracking URI each say how to install it."""
    uri = postgres.create_database("nodriver")
    store = f"sqlite:///{tmp_path}/mlflow.db"
    sweep = str(_grid(tmp_path, "nodriver"))
    code = (
        "import sys; sys.modules['psycopg'] = None\n"  # `import psycopg` raises ImportError
        "from fedlgr.shell.cli import main; sys.exit(main(sys.argv[1:]))"
    )
    for argv, named in [
        (["sweep", sweep, "--storage", uri, "--tracking-uri", store], "--storage"),
        (["report", "--tracking-uri", uri], "tracking URI"),
    ]:
        done = subprocess.run(
            [sys.executable, "-c", code, *argv],
            cwd=tmp_path,
            env={**os.environ, "PYTHONPATH": str(REPO)},
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
        (line,) = done.stderr.strip().splitlines()
        assert line == (
            f"fedlgr: error: {named} {mask_password(uri)}: the PostgreSQL driver psycopg is "
            "not installed: `uv sync --extra postgres` (pip: fedlgr[postgres])"
        )
        assert postgres.password not in done.stdout + done.stderr


# --------------------------------------------------------------------------- two machines


def _rows(db_uri: str, sql: str) -> list[tuple]:
    """Rows of ``sql`` on the study's database, [] while its tables are not there yet (the
    test must not create them: opening the study with Optuna would, racing the workers)."""
    import psycopg

    try:
        with psycopg.connect(db_uri) as connection:
            return connection.execute(sql).fetchall()
    except psycopg.errors.UndefinedTable:
        return []


def _running_trial(storage: str) -> tuple[int, str] | None:
    """A RUNNING trial that has reported a round, and its MLflow run."""
    rows = _rows(
        storage,
        "SELECT t.number, a.value_json FROM trials t "
        "JOIN trial_intermediate_values v ON v.trial_id = t.trial_id "
        "JOIN trial_user_attributes a ON a.trial_id = t.trial_id AND a.key = 'mlflow_run_id' "
        "WHERE t.state = 'RUNNING' LIMIT 1",
    )
    return (rows[0][0], json.loads(rows[0][1])) if rows else None


def _trial_table(storage: str, name: str) -> list[tuple]:
    """(method, lr_top, state, value, rounds reported) of the study's finished points."""
    study = optuna.load_study(study_name=name, storage=storage)
    return sorted(
        (t.params["method"], t.params["train.lr_top"], t.state.name, t.value,
         sorted(t.intermediate_values.items()))
        for t in study.get_trials() if t.state.name == "COMPLETE"
    )  # fmt: skip


def _mlflow_server(folder: Path, backend: str) -> tuple[subprocess.Popen, str]:
    """``mlflow server`` on a free port, its runs in ``backend``, artifacts proxied into
    ``folder/artifacts``; not waited for (see :func:`_wait_for`)."""
    port = free_port()
    command = [sys.executable, "-m", "mlflow", "server", "--backend-store-uri", backend]
    command += ["--artifacts-destination", str(folder / "artifacts"), "--host", "127.0.0.1"]
    command += ["--port", str(port), "--workers", "1"]
    log = (folder / "mlflow-server.log").open("w")
    process = subprocess.Popen(command, cwd=folder, stdout=log, stderr=subprocess.STDOUT)
    return process, f"http://127.0.0.1:{port}"


def _wait_for(process: subprocess.Popen, url: str, log: Path) -> None:
    wait_healthy(url, process, lambda: log.read_text()[-3000:], timeout=180)


def _machine(
    root: Path, name: str, synth_dir: Path, sweep: str, postgres: PostgresServer | None = None
) -> tuple[Path, dict, Path]:
    """A working folder with its own HOME, its own copy of the data and of the sweep file;
    with ``postgres``, the database password in its ``~/.pgpass`` (the URIs hold none)."""
    folder = root / name
    home = folder / "home"
    home.mkdir(parents=True)
    shutil.copytree(synth_dir, folder / "data")
    path = _grid(folder, sweep)
    if postgres is not None:
        line = f"127.0.0.1:{postgres.port}:*:{USER}:{postgres.password}\n"
        descriptor = os.open(home / ".pgpass", os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(descriptor, "w") as pgpass:
            pgpass.write(line)
    env = {
        k: v
        for k, v in os.environ.items()
        if not k.startswith(("MLFLOW_", "FEDLGR_", "PG")) and k != "XDG_CACHE_HOME"
    }
    env.update(HOME=str(home), PYTHONPATH=str(REPO), PYTHONUNBUFFERED="1")
    return folder, env, path


MEASURED = ("CPU usage", "GPU usage", "Wall time")  # table3's rows that are timed


def _reported(out: Path) -> dict[str, list[list[str]]]:
    """The CSV tables of the report in ``out``, less the rows of measured times and a
    sweep's trials.csv (a study whose worker was killed has one more, failed, trial and
    numbers its trials otherwise)."""
    tables = {p.name: read_rows(p) for p in sorted(out.glob("*.csv")) if p.name != "trials.csv"}
    return {
        name: [row for row in rows if not (len(row) > 1 and row[1].startswith(MEASURED))]
        for name, rows in tables.items()
    }


@pytest.mark.slow
def test_two_machines_share_a_study_on_postgresql_and_match_sqlite(
    postgres, tmp_path, synth_dir, capsys, monkeypatch
):
    """Two workers on fresh databases, started at once: the study's storage is
    ``postgresql://`` (its password in the URI on one machine, in ``~/.pgpass`` on the
    other) and MLflow
    is an ``mlflow server`` whose ``--backend-store-uri`` is on the same PostgreSQL server,
    with proxied artifacts. One worker is SIGKILLed in the middle of a trial and its
    folder removed (a lost machine); the other fails and retries that trial."""
    name = "machines"
    with_password = postgres.create_database("optuna")
    storage = with_password.replace(f":{postgres.password}@", "@")
    backend = postgres.create_database("mlflow")
    server, url = _mlflow_server(tmp_path, backend)
    try:
        # While the MLflow server starts: the same sweep on sqlite, one process.
        reference, _, path = _machine(tmp_path, "reference", synth_dir, name)
        monkeypatch.chdir(reference)
        ref_storage = f"sqlite:///{reference}/optuna.db"
        ref_store = f"sqlite:///{reference}/mlflow.db"
        assert run_sweep(load_sweep(path), storage=ref_storage, tracking_uri=ref_store).done
        expected = _trial_table(ref_storage, name)
        capsys.readouterr()
        _wait_for(server, url, tmp_path / "mlflow-server.log")

        # Two "machines": each its own folder, HOME, data and sweep file; the URIs alone
        # are shared. Both start at once on the fresh databases.
        workers = {}
        # Machine a has the password in its URI, b in its ~/.pgpass.
        for machine, uri in (("a", with_password), ("b", storage)):
            keys = postgres if machine == "b" else None
            folder, env, path = _machine(tmp_path, machine, synth_dir, name, keys)
            command = [sys.executable, "-m", "fedlgr", "sweep", str(path), "--storage"]
            command += [uri, "--tracking-uri", url, "--heartbeat", "1"]
            log = (folder / "sweep.log").open("w")
            workers[machine] = subprocess.Popen(
                command, cwd=folder, env=env, stdout=log, stderr=subprocess.STDOUT,
                start_new_session=True,
            )  # fmt: skip
        logs = {m: tmp_path / m / "sweep.log" for m in workers}

        def tails() -> str:
            return "\n".join(
                f"--- {m}:\n{log.read_text()[-2000:]}" for m, log in logs.items() if log.exists()
            )

        # Kill the worker that runs a trial, once that trial has reported round 1 of 2.
        client = mlflow.MlflowClient(url)
        deadline = time.monotonic() + 300
        while (running := _running_trial(with_password)) is None:
            assert all(w.poll() is None for w in workers.values()), tails()
            assert time.monotonic() < deadline, tails()
            time.sleep(0.05)
        killed_trial, killed_run = running
        pid = int(client.get_run(killed_run).data.tags["fedlgr.pid"])
        (victim,) = [m for m, w in workers.items() if w.pid == pid]
        os.killpg(pid, signal.SIGKILL)  # no clean-up of any kind
        workers[victim].wait()
        printed = {victim: logs[victim].read_text()}
        shutil.rmtree(tmp_path / victim)  # its machine is gone, checkpoints and all
        (survivor,) = set(workers) - {victim}
        assert workers[survivor].wait(timeout=300) == 0, tails()
        log = printed[survivor] = logs[survivor].read_text()

        # The killed trial failed and the survivor ran it again, from round 1.
        study = optuna.load_study(study_name=name, storage=with_password)
        states = {}
        for t in study.get_trials():
            states.setdefault(t.state.name, []).append(t)
        assert [t.number for t in states["FAIL"]] == [killed_trial], tails()
        (retry,) = [t for t in states["COMPLETE"] if t.system_attrs.get("retry_history")]
        assert retry.system_attrs["retry_history"] == [killed_trial]
        assert retry.user_attrs["mlflow_run_id"] != killed_run
        assert f"continues run {killed_run}" not in log
        assert set(states) <= {"COMPLETE", "FAIL", "PRUNED"}  # PRUNED: a skipped duplicate
        assert all("duplicate_of" in t.user_attrs for t in states.get("PRUNED", []))

        # The same trial table as on sqlite: every point once, the same values, bit for bit.
        found = _trial_table(with_password, name)
        with capsys.disabled():  # shown with pytest -s
            print("\nsqlite trial table:", *expected, sep="\n  ")
            print("PostgreSQL trial table:", *found, sep="\n  ")
        assert found == expected

        # One parent run; the killed trial's run ended KILLED by the survivor.
        experiment = client.get_experiment_by_name(f"sweep-{name}")
        runs = client.search_runs([experiment.experiment_id])
        parents = [r for r in runs if r.data.tags.get("fedlgr.kind") == "sweep"]
        children = {r.info.run_id: r for r in runs if r.data.tags.get("fedlgr.kind") == "trial"}
        assert len(parents) == 1 and parents[0].info.status == "FINISHED"
        tag = parents[0].data.tags["storage"]  # the study's URI, never its password
        assert tag.startswith("postgresql://") and postgres.password not in tag
        assert children[killed_run].info.status == "KILLED"
        assert sorted(r.info.status for r in children.values()) == ["FINISHED"] * 4 + ["KILLED"]

        # fedlgr report reads both back: the same tables.
        tables = {}
        for which, uri in [("sqlite", ref_store), ("postgresql", url)]:
            out = tmp_path / f"report-{which}"
            assert main(["report", "--sweep", name, "--tracking-uri", uri, "--out", str(out)]) == 0
            tables[which] = _reported(out)
        assert tables["postgresql"] == tables["sqlite"] and tables["sqlite"]["table1.csv"]
        assert "table1 (FL results)" in capsys.readouterr().out
        # Machine a's lines name its storage with the password masked.
        assert f"in postgresql://fedlgr:***@127.0.0.1:{postgres.port}/optuna" in printed["a"]
        assert postgres.password not in printed["a"] + printed["b"]
    finally:
        for process in [server, *locals().get("workers", {}).values()]:
            if process.poll() is None:
                process.terminate()
                process.wait(timeout=30)


class Interrupt(KeyboardInterrupt):
    """Ctrl-C after a given round (the run ends KILLED, its checkpoints stay)."""


@pytest.mark.slow
def test_a_run_on_a_postgresql_store_resumes_and_reports(
    postgres, tmp_path, synth_dir, cache_dir, capsys, monkeypatch
):
    """``fedlgr run`` with ``--tracking-uri postgresql://``: stopped after round 2 of 3,
    ``--resume`` finishes it in the same MLflow run with the values of an uninterrupted
    run on sqlite; ``fedlgr report`` reads it back."""
    from fedlgr.shell.run.experiment import run_experiment

    monkeypatch.chdir(tmp_path)  # checkpoints/ and mlruns/ (artifacts) go here
    store = postgres.create_database("runs")
    args = ["federated.rounds=3", "tracking.experiment=pg-resume"]
    config = fast_config(synth_dir, cache_dir, store, *args)

    def stop(round_, metrics):
        if round_ == 2:
            raise Interrupt()

    with pytest.raises(Interrupt):
        run_experiment(config, on_round=stop)
    client = mlflow.MlflowClient(store)
    (run,) = client.search_runs([client.get_experiment_by_name("pg-resume").experiment_id])
    assert run.info.status == "KILLED"
    argv = ["run", str(FAST), f"data.path={synth_dir}", f"data.cache_dir={cache_dir}", *args]
    assert main([*argv, "--tracking-uri", store, "--resume", run.info.run_id]) == 0
    assert f"MLflow run {run.info.run_id}" in capsys.readouterr().out

    reference = f"sqlite:///{tmp_path}/reference/mlflow.db"
    assert main([*argv, "--tracking-uri", reference]) == 0
    ref_client = mlflow.MlflowClient(reference)
    (ref,) = ref_client.search_runs([ref_client.get_experiment_by_name("pg-resume").experiment_id])
    resumed = client.get_run(run.info.run_id)
    assert resumed.info.status == "FINISHED"
    for key in ("test/rmse", "test/pcc", "test/loss"):
        history = [(m.step, m.value) for m in client.get_metric_history(run.info.run_id, key)]
        assert sorted(history) == sorted(
            (m.step, m.value) for m in ref_client.get_metric_history(ref.info.run_id, key)
        )
        assert [s for s, _ in sorted(history)] == [1, 2, 3]

    tables = {}
    for which, uri in [("postgresql", store), ("sqlite", reference)]:
        out = tmp_path / f"report-{which}"
        code = main(
            ["report", "--experiment", "pg-resume", "--tracking-uri", uri, "--out", str(out)]
        )
        assert code == 0
        tables[which] = _reported(out)
    assert tables["postgresql"] == tables["sqlite"] and tables["sqlite"]["table1.csv"]
    assert postgres.password not in capsys.readouterr().out
