"""A run's life around its rounds (fedlgr/shell/run/life.py) when something goes wrong: a
run that fails after rounds with NaN scores ends FAILED with its own error, a failure
whose saving fails still ends the run, a last round of NaN scores ends FINISHED, and no
run leaves anything in the temp folder."""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from urllib.parse import urlparse

import mlflow
import pytest

from fedlgr.errors import FedlgrError
from fedlgr.shell.run.experiment import run_experiment
from tests.support.processes import experiment_runs, metric_steps, only_run
from tests.support.runs import csv_rounds, fast_config, results_csv

DIVERGES_IN_ROUND_2 = [  # round 1 trains one finite step, then predicts NaN; round 2's loss
    "train.max_batches=1",
    "train.lr_root=1e30",
    "train.lr_top=1e30",
]


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_run_failing_after_rounds_with_nan_scores_fails_with_its_own_error(
    synth_dir, cache_dir, tmp_path, monkeypatch
):
    """Round 1 is logged with NaN test scores, round 2 diverges: the run ends FAILED with
    results.csv holding round 1, and the error raised is the divergence (not one from the
    plot or the summary, which NaN scores may break on the way)."""
    monkeypatch.chdir(tmp_path)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(
        synth_dir, cache_dir, store, "federated.rounds=3", "runtime.threads=1", *DIVERGES_IN_ROUND_2
    )
    said: list[str] = []
    with pytest.raises(FedlgrError, match=r"^round 2, client \d+: the training loss is "):
        run_experiment(config, echo=said.append)
    assert any(line.startswith("round 1/3: loss -  RMSE -") for line in said), said
    client, run = only_run(store)
    assert run.info.status == "FAILED"
    rows = results_csv(client, run.info.run_id)
    assert csv_rounds(rows) == {1: ["0", "1"]}
    assert all(row["test_rmse"] == "" for row in rows)  # NaN: not a number, kept as empty
    assert metric_steps(client, run.info.run_id) == [1]
    assert "curves.png" in {a.path for a in client.list_artifacts(run.info.run_id)}  # gaps


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_failure_whose_saving_fails_still_ends_the_run_with_the_original_error(
    synth_dir, cache_dir, tmp_path, monkeypatch
):
    """``_record_failure`` goes on when a step fails: with the run's artifact folder made
    a file, results.csv and curves.png cannot be written, yet the summary is recorded,
    the run ends FAILED and the hook's own exception is what propagates."""
    monkeypatch.chdir(tmp_path)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(synth_dir, cache_dir, store, "federated.rounds=3", "runtime.threads=1")
    started: list[str] = []

    class Stop(Exception):
        pass

    def break_artifacts_and_stop(round_, metrics):
        artifacts = Path(
            urlparse(mlflow.MlflowClient(store).get_run(started[0]).info.artifact_uri).path
        )
        shutil.rmtree(artifacts)
        artifacts.write_text("a file where the artifact folder was\n")
        raise Stop(f"stopped after round {round_}")

    said: list[str] = []
    with pytest.raises(Stop, match="stopped after round 1"):
        run_experiment(
            config, echo=said.append, on_start=started.append, on_round=break_artifacts_and_stop
        )
    assert any(s.startswith("(while failing: could not record results.csv: ") for s in said), said
    client, run = only_run(store)
    assert run.info.run_id == started[0]
    assert run.info.status == "FAILED"
    note = run.data.tags["mlflow.note.content"]  # the step after the failed ones ran
    assert note.startswith("**FedAvg-2c-noaug-image: FAILED after 1 of 3 rounds (")
    assert metric_steps(client, run.info.run_id) == [1]


@pytest.mark.usefixtures("telemetry_setting_restored")
def test_a_run_whose_last_round_has_nan_scores_is_not_left_running(
    synth_dir, cache_dir, tmp_path, monkeypatch
):
    """One round, one finite training step, NaN predictions afterwards: the run completes
    its rounds and must end (FINISHED, its results kept), not crash at the plot."""
    monkeypatch.chdir(tmp_path)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(
        synth_dir, cache_dir, store, "federated.rounds=1", "runtime.threads=1", *DIVERGES_IN_ROUND_2
    )
    try:
        run_experiment(config, echo=lambda *a, **k: None)
    finally:
        client, run = only_run(store)
        assert run.info.status != "RUNNING"
    assert run.info.status == "FINISHED"
    assert csv_rounds(results_csv(client, run.info.run_id)) == {1: ["0", "1"]}
    assert "curves.png" in {a.path for a in client.list_artifacts(run.info.run_id)}


@pytest.mark.slow
@pytest.mark.usefixtures("telemetry_setting_restored")
def test_runs_leave_nothing_in_the_temp_folder(synth_dir, cache_dir, tmp_path, monkeypatch):
    """A finished run and a failed one (each writes config.yaml, results.csv, curves.png
    through temporary files) leave no entry in ``tempfile.gettempdir()``."""
    monkeypatch.chdir(tmp_path)
    store = f"sqlite:///{tmp_path}/mlflow.db"
    config = fast_config(synth_dir, cache_dir, store, "federated.rounds=2", "runtime.threads=1")
    quiet = lambda *a, **k: None  # noqa: E731
    run_experiment(config, echo=quiet)  # warm-up: imports that create caches happen now
    temp = tmp_path / "tmp"
    temp.mkdir()
    monkeypatch.setenv("TMPDIR", str(temp))
    monkeypatch.setattr(tempfile, "tempdir", str(temp))
    seen: list[str] = []

    def fail(round_, metrics):
        seen.append(tempfile.gettempdir())
        raise RuntimeError("stop")

    run_experiment(config, echo=quiet, on_round=lambda r, m: seen.append(tempfile.gettempdir()))
    with pytest.raises(RuntimeError, match="stop"):
        run_experiment(config, echo=quiet, on_round=fail)
    assert seen == [str(temp)] * 3  # the runs used this folder
    assert sorted(os.listdir(temp)) == []
    client, runs = experiment_runs(store)
    assert sorted(r.info.status for r in runs) == ["FAILED", "FINISHED", "FINISHED"]
    for run in runs:  # what went through the temp folder arrived
        names = {a.path for a in client.list_artifacts(run.info.run_id)}
        assert {"config.yaml", "results.csv", "curves.png"} <= names, names
