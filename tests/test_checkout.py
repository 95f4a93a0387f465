"""Tests write only into pytest's temp folders: a local sqlite store keeps its artifacts
next to its database (not in the working folder), and the session check that the checkout
is unchanged (``checkout_unchanged`` in conftest) tells new and changed files from a
developer's own."""

from __future__ import annotations

import subprocess
from pathlib import Path

import mlflow
import pytest

from fedlgr.shell.tracking.mlflow_run import Tracker
from tests.support.checkout import ignored, untracked_files
from tests.support.runs import fast_config


@pytest.mark.slow
def test_a_sqlite_store_keeps_its_artifacts_next_to_its_database(
    synth_dir, cache_dir, tmp_path, monkeypatch
):
    """MLflow's default artifact root is ``./mlruns`` of the folder the experiment was
    created from: runs started in the checkout wrote there whatever their store."""
    elsewhere = tmp_path / "started-here"
    elsewhere.mkdir()
    monkeypatch.chdir(elsewhere)
    store = f"sqlite:///{tmp_path}/store/mlflow.db"
    tracker = Tracker(fast_config(synth_dir, cache_dir, store))  # logs config.yaml
    tracker.finish()
    experiment = mlflow.MlflowClient(store).get_experiment(tracker.experiment_id)
    assert (
        Path(experiment.artifact_location)
        == tmp_path / "store" / "mlruns" / experiment.experiment_id
    )
    kept = tmp_path / "store" / "mlruns" / experiment.experiment_id / tracker.run_id / "artifacts"
    assert (kept / "config.yaml").is_file()
    assert list(elsewhere.iterdir()) == []


def _git(folder: Path, *args: str) -> None:
    subprocess.run(["git", "-C", str(folder), *args], check=True, capture_output=True)


def test_the_checkout_check_sees_new_and_changed_files_not_a_developers_own(tmp_path):
    repo = tmp_path / "repo"
    (repo / "mlruns" / "1").mkdir(parents=True)
    _git(repo, "init", "-q")
    (repo / "kept.py").write_text("x = 1\n")
    (repo / ".gitignore").write_text("mlruns/*\n*.db\n")
    _git(repo, "add", "kept.py", ".gitignore")
    (repo / "mlflow.db").write_bytes(b"mine")  # a developer's own store: ignored, present
    (repo / "mlruns" / "1" / "old.txt").write_text("mine")
    (repo / "__pycache__").mkdir()
    before = untracked_files(repo, tmp_path / "basetemp")
    assert before is not None and set(before) == {"mlflow.db", "mlruns/1/old.txt"}

    (repo / "mlruns" / "1" / "run" / "artifacts").mkdir(parents=True)
    (repo / "mlruns" / "1" / "run" / "artifacts" / "results.csv").write_text("a\n")
    (repo / "mlflow.db").write_bytes(b"mine, and a test's run")
    (repo / "__pycache__" / "kept.cpython-311.pyc").write_bytes(b"")  # Python's, not a test's
    (repo / "kept.py").write_text("x = 2\n")  # tracked: git shows it, a person edited it
    after = untracked_files(repo, tmp_path / "basetemp")
    assert set(after) - set(before) == {"mlruns/1/run/artifacts/results.csv"}
    (repo / "notes.md").write_text("being written")  # untracked, not ignored: a person's
    before["notes.md"] = (0, 0)
    after = untracked_files(repo, tmp_path / "basetemp")
    changed = [p for p in before if after[p] != before[p]]
    assert sorted(changed) == ["mlflow.db", "notes.md"]
    assert ignored(repo, changed) == ["mlflow.db"]  # what the session check reports


def test_the_checkout_check_is_skipped_outside_a_git_checkout(tmp_path):
    (tmp_path / "mlflow.db").write_bytes(b"")
    assert untracked_files(tmp_path) is None
