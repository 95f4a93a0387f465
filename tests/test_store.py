"""The tracking store as a user meets it (fedlgr/shell/tracking/store.py): a new sqlite store
is a copy of one empty, migrated store, and still a store MLflow made. A store that cannot
keep runs (in memory, a device, a pipe, a link that leads nowhere) or whose lock file is a
link is refused in one line before anything opens it."""

from __future__ import annotations

import os
import sqlite3

import mlflow
import pytest

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.stores import TrackingUnreachable, check_reachable
from fedlgr.shell.cli import main
from fedlgr.shell.sweep.storage import check_storage
from fedlgr.shell.tracking.store import StoreError, empty_store, open_client, store_lock
from tests.support.processes import Child, experiment_runs, run_args
from tests.support.runs import FAST


def _experiments(path) -> list[tuple]:
    with sqlite3.connect(path) as db:
        return db.execute(
            "SELECT experiment_id, name, artifact_location FROM experiments"
        ).fetchall()


def test_a_new_store_is_a_copy_of_the_empty_store_with_its_default_experiment_here(
    tmp_path, monkeypatch, session_empty_store
):
    monkeypatch.chdir(tmp_path)
    client = open_client(f"sqlite:///{tmp_path}/a.db")
    # the template has no experiment: no creating process's folder baked in
    assert session_empty_store.is_file() and _experiments(session_empty_store) == []
    # Default's artifacts under the creating process's folder, as a fresh MLflow store's
    assert _experiments(tmp_path / "a.db") == [(0, "Default", str(tmp_path / "mlruns" / "0"))]
    client.create_experiment("mine")
    with sqlite3.connect(session_empty_store) as db, sqlite3.connect(tmp_path / "a.db") as made:
        version = "SELECT version_num FROM alembic_version"
        assert made.execute(version).fetchall() == db.execute(version).fetchall()
    # the copy is MLflow's own schema: MLflow opens it and sees both experiments
    names = {e.name for e in mlflow.MlflowClient(f"sqlite:///{tmp_path}/a.db").search_experiments()}
    assert names == {"Default", "mine"}


def test_without_a_place_for_the_empty_store_a_new_store_is_migrated_in_place(
    tmp_path, monkeypatch
):
    blocked = tmp_path / "file"
    blocked.write_text("")
    monkeypatch.setenv("FEDLGR_EMPTY_STORE", str(blocked / "empty.db"))  # under a file
    assert empty_store() is None
    client = open_client(f"sqlite:///{tmp_path}/b.db")
    assert [e.name for e in client.search_experiments()] == ["Default"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["b.db", "b.db.lock", "file"]


def test_a_stores_lock_file_is_never_created_through_a_link(tmp_path):
    """Found by issue 20's fourth fault sweep."""
    target = tmp_path / "created-through-the-link"
    (tmp_path / "mlflow.db.lock").symlink_to(target)
    lock = store_lock(f"sqlite:///{tmp_path}/mlflow.db")
    with (
        pytest.raises(StoreError, match=r"its lock file .*mlflow\.db\.lock is a symbolic link"),
        lock,
    ):
        pass
    (tmp_path / "optuna.db.lock").symlink_to(target)
    with pytest.raises(FedlgrError, match=r"^--storage .*: its lock file .* symbolic link"):
        check_storage(f"sqlite:///{tmp_path}/optuna.db")
    assert not target.exists()


@pytest.mark.parametrize(
    "uri",
    [
        "sqlite://",
        "sqlite:///:memory:",
        "sqlite:///file::memory:?cache=shared&uri=true",
        "sqlite:///file:db?mode=memory&uri=true",
    ],
)
def test_in_memory_stores_are_refused_they_keep_nothing(uri):
    """Found by issue 20's fourth fault sweep."""
    with pytest.raises(TrackingUnreachable, match="in-memory sqlite store keeps nothing"):
        check_reachable(uri)
    with pytest.raises(FedlgrError, match="in-memory sqlite database keeps nothing"):
        check_storage(uri)


def test_a_store_path_that_is_a_dangling_link_is_refused_before_anything_is_made(
    tmp_path, synth_dir, capsys
):
    """The re-check of the seventh fault sweep (u79): the new store replaced the link with
    a file, and a checkpoints folder was made beside the link's missing target."""
    link = tmp_path / "store.db"
    link.symlink_to(tmp_path / "gone" / "x.db")
    argv = ["run", "debug/tiny", f"data.path={synth_dir}", "--tracking-uri", f"sqlite:///{link}"]
    assert main(argv) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"fedlgr: error: tracking store sqlite:///{link}: {link} is a symbolic link to "
        f"{tmp_path / 'gone' / 'x.db'}, which does not exist"
    )
    assert link.is_symlink() and not (tmp_path / "gone").exists()


def test_a_device_pipe_or_socket_as_a_store_is_refused_before_anything_opens_it(
    tmp_path, synth_dir, capsys
):
    """The ninth fault sweep: a FIFO as the tracking store hung with no word (c06); a link
    to /dev/null, /dev/null itself or a FIFO as the store or --storage made
    ``/dev/null-journal``, ``/dev/null.lock``, ``FIFO.lock`` (c07, c16, c17, c120, c135);
    a report said "does not exist" (c11-c13). Now one line each, and nothing is made."""
    import signal
    import socket

    fifo, null, sock = tmp_path / "fifo", tmp_path / "null", tmp_path / "sock"
    os.mkfifo(fifo)
    null.symlink_to("/dev/null")
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(sock))
    special = "not a regular file (a device, pipe or socket)"

    def hung(*_):
        raise TimeoutError("opened a FIFO as a store and waited on it")

    previous = signal.signal(signal.SIGALRM, hung)
    signal.alarm(60)
    try:
        for store in (fifo, null, sock):
            uri = f"sqlite:///{store}"
            run = ["run", "debug/tiny", f"data.path={synth_dir}", "--tracking-uri", uri]
            assert main(run) == 1
            said = capsys.readouterr().err.strip().splitlines()[-1]
            assert said == f"fedlgr: error: tracking store {uri}: {store} is {special}"
            report = ["report", "--tracking-uri", uri, "--no-log", "--out", str(tmp_path / "r")]
            assert main(report) == 1
            said = capsys.readouterr().err.strip().splitlines()[-1]
            assert said == f"fedlgr: error: no MLflow store at {uri}: {store} is {special}"
            with pytest.raises(FedlgrError) as err:
                check_storage(uri)
            assert str(err.value) == f"--storage {uri}: {store} is {special}"
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)
        server.close()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["fifo", "null", "sock"]


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_two_runs_opening_a_fresh_store_at_once_both_finish(synth_dir, cache_dir, tmp_path):
    for attempt in range(2):  # the race failed 2 times in 2 before the lock (5ab6af4)
        folder = tmp_path / f"race{attempt}"
        folder.mkdir()
        store = f"sqlite:///{folder}/fresh.db"
        args = run_args(synth_dir, cache_dir, store)
        children = [Child(args, folder, f"run{i}") for i in range(2)]
        try:
            codes = [c.process.wait(timeout=500) for c in children]
            failures = [c.stderr()[-2000:] for c, code in zip(children, codes, strict=True) if code]
        finally:
            for child in children:
                child.__exit__()
        assert not failures, f"attempt {attempt + 1}: {failures}"
        _, runs = experiment_runs(store)
        assert sorted(r.info.status for r in runs) == ["FINISHED", "FINISHED"], attempt


@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_new_store_appears_whole_or_not_at_all(tmp_path, monkeypatch):
    """The seventh fault sweep (g03e): SIGKILL while MLflow created a new store's schema
    left its tables without a version, and every later use of it failed ("duplicate column
    name: step"). A new store is made under a temporary name and renamed when whole: a
    creation cut short leaves no store, and its leftover is replaced by the next one."""
    from fedlgr.shell.tracking import mlflow_run

    store = tmp_path / "new.db"
    uri = f"sqlite:///{store}"
    making = tmp_path / ".new.db.creating"
    making.write_text("what a killed creation left")
    real = mlflow.MlflowClient

    def killed(uri_made):  # the creation stops in the middle (as a SIGKILL would)
        assert uri_made == f"sqlite:///{making}" and not store.exists()
        raise KeyboardInterrupt

    monkeypatch.setattr(mlflow, "MlflowClient", killed)
    with pytest.raises(KeyboardInterrupt):
        mlflow_run.open_client(uri)
    assert not store.exists()
    monkeypatch.setattr(mlflow, "MlflowClient", real)
    client = mlflow_run.open_client(uri)
    assert store.is_file() and not making.exists()
    assert [e.name for e in client.search_experiments()] == ["Default"]


@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_half_created_store_is_named_as_such(tmp_path, synth_dir, capsys):
    """A store left half-created by another tool or an earlier fedlgr (tables, no schema
    version): one line saying so, not "duplicate column name" (g03f)."""
    from fedlgr.shell.tracking import mlflow_run

    store = tmp_path / "half.db"
    mlflow_run.open_client(f"sqlite:///{store}")
    with sqlite3.connect(store) as db:
        db.execute("DELETE FROM alembic_version")
    db.close()
    argv = ["run", str(FAST), f"data.path={synth_dir}", "--tracking-uri", f"sqlite:///{store}"]
    assert main(argv) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == (
        f"fedlgr: error: tracking store sqlite:///{store}: {store} is half-created (its "
        "schema has no version: a process was killed while MLflow created it; it holds no "
        "runs: remove it)"
    )
