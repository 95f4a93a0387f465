"""The tracking store as a user meets it (fedlgr/shell/tracking/store.py): a new sqlite store
is a copy of one empty, migrated store, and still a store MLflow made."""

from __future__ import annotations

import sqlite3

import mlflow

from fedlgr.shell.tracking.store import empty_store, open_client


def _experiments(path) -> list[tuple]:
    with sqlite3.connect(path) as db:
        return db.execute(
            "SELECT experiment_id, name, artifact_location FROM experiments"
        ).fetchall()


def test_a_new_store_is_a_copy_of_the_empty_store_with_its_default_experiment_here(
    tmp_path, monkeypatch, empty_store
):
    monkeypatch.chdir(tmp_path)
    client = open_client(f"sqlite:///{tmp_path}/a.db")
    assert empty_store.is_file() and _experiments(empty_store) == []  # no cwd baked in
    # Default's artifacts under the creating process's folder, as a fresh MLflow store's
    assert _experiments(tmp_path / "a.db") == [(0, "Default", str(tmp_path / "mlruns" / "0"))]
    client.create_experiment("mine")
    with sqlite3.connect(empty_store) as db, sqlite3.connect(tmp_path / "a.db") as made:
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
