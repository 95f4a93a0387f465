"""What a sweep prints (issue 22, point 5): one final table with the best trial marked in
a column of its own, interrupted trials marked as such with their reason, one line for a
relaunched study that has nothing left to run, and ``tracking.experiment`` as docs/sweeps.md
says (it chooses the experiment; a relaunch does not compare ``tracking.*``)."""

from __future__ import annotations

from pathlib import Path

import optuna
import pytest
from optuna.trial import TrialState

from fedlgr.shell.cli import main
from fedlgr.shell.sweep import load_sweep, run_sweep
from fedlgr.shell.sweep.storage import fail_and_retry, open_study, retry_failed
from fedlgr.shell.sweep.trials import summary
from fedlgr.shell.sweep.worker import Worker
from tests.support.runs import FAST
from tests.support.sweeps import child_runs, trials_by_state


def write_grid(tmp_path: Path, synth_dir: Path, cache_dir: Path, name: str, lrs: str) -> Path:
    """A grid over the top learning rate on the fast-dev-run config (about 2 s a trial)."""
    path = tmp_path / f"{name}.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1]\n"
        "objective: {metric: test/rmse, direction: minimize}\n"
        f"space:\n  train.lr_top: [{lrs}]\n"
    )
    return path


def table_rows(out: str) -> tuple[str, list[str]]:
    """The final table's header line and its rows (up to the first blank line)."""
    lines = out.splitlines()
    (start,) = [k for k, line in enumerate(lines) if line.startswith("trial ")]
    end = next((k for k in range(start, len(lines)) if not lines[k].strip()), len(lines))
    return lines[start], lines[start + 2 : end]


@pytest.mark.slow
def test_one_table_with_an_aligned_best_mark_then_one_line_when_nothing_is_left(
    tmp_path, synth_dir, cache_dir, capsys
):
    path = write_grid(tmp_path, synth_dir, cache_dir, "two", "0.001, 0.01")
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    command = ["sweep", str(path), "--storage", storage, "--tracking-uri", store]
    assert main(command) == 0
    out = capsys.readouterr().out
    header, rows = table_rows(out)  # exactly one table
    assert len(rows) == 2
    best = min(trials_by_state(storage, "two")["COMPLETE"], key=lambda t: t.value)
    (marked,) = [r for r in rows if "*" in r]
    assert marked.split()[:3] == [str(best.number), "*", "COMPLETE"]
    # The mark has a column of its own: every row's columns start where the header's do.
    width = len("trial")  # trial numbers right-aligned under their header, mark or not
    assert all(r[:width] == r.split()[0].rjust(width) for r in rows), rows
    state_column = header.index("state")
    assert all(r[state_column:].startswith("COMPLETE") for r in rows), rows
    assert {r.split()[0] for r in rows} == {"0", "1"}

    # Relaunched: the header, then one line; no trial, no table; exit status 0.
    assert main(command) == 0
    again = [line for line in capsys.readouterr().out.splitlines() if line.strip()]
    assert len(again) == 2 and again[0].startswith("sweep two: grid, 2 trials"), again
    assert again[1] == (
        f"study 'two': all 2 trials are done; nothing left to run "
        f"(best: trial {best.number}, test/rmse {best.value:.4f})"
    )
    _, (parent,), children = child_runs(store, "sweep-two")
    assert parent.info.status == "FINISHED" and len(children) == 2


def test_interrupted_trials_show_as_interrupted_with_their_reason(tmp_path, synth_dir, cache_dir):
    """A trial stopped by SIGTERM (its worker records why), one whose worker died (no
    heartbeat: it records nothing) and one that failed on its own, on a real study."""
    spec = load_sweep(write_grid(tmp_path, synth_dir, cache_dir, "cut", "0.001, 0.01, 0.1"))
    study, retry = open_study(spec, f"sqlite:///{tmp_path}/optuna.db")

    failed = study.ask()
    failed.suggest_categorical("train.lr_top", [0.001, 0.01, 0.1])
    failed.set_user_attr("error", "ValueError: bad")
    study.tell(failed, state=TrialState.FAIL)
    stopped = study.ask()
    stopped.suggest_categorical("train.lr_top", [0.001, 0.01, 0.1])
    stopped.set_user_attr("interrupted", "stopped by SIGTERM")
    study.tell(stopped, state=TrialState.FAIL)
    assert retry_failed(study, retry, stopped._trial_id)
    died = study.ask()  # the queued copy of ``stopped``, which a worker takes up ...
    died.set_user_attr("interrupted", False)  # ... as Worker.objective does with a copy
    died.suggest_categorical("train.lr_top", [0.001, 0.01, 0.1])
    assert fail_and_retry(study, retry, died._trial_id)  # what a stale heartbeat leads to

    copies = {  # a copy's retry_history ends with the trial it re-runs
        t.system_attrs["retry_history"][-1]: t.number
        for t in study.get_trials()
        if "retry_history" in t.system_attrs
    }
    header, rows = table_rows(summary(study, spec, None))
    by_trial = {int(r.split()[0]): r for r in rows}
    error_column = header.index("error")
    assert by_trial[stopped.number].split()[1] == "INTERRUPTED"
    assert by_trial[stopped.number][error_column:] == (
        f"stopped by SIGTERM; retried as trial {copies[stopped.number]}"
    )
    assert by_trial[died.number].split()[1] == "INTERRUPTED"
    assert by_trial[died.number][error_column:] == (
        f"its worker died (no heartbeat); retried as trial {copies[died.number]}"
    )
    assert by_trial[failed.number].split()[1] == "FAIL"
    assert by_trial[failed.number][error_column:] == "ValueError: bad"
    assert by_trial[copies[died.number]].split()[1] == "WAITING"  # the point's next try


@pytest.mark.slow
def test_tracking_experiment_chooses_the_experiment_and_is_not_compared_on_relaunch(
    tmp_path, synth_dir, cache_dir
):
    """docs/sweeps.md: ``tracking.*`` is not compared. ``tracking.experiment=NAME`` puts the
    parent and its trials in NAME; a relaunch without it (or with another) goes on, in the
    experiment of the study's parent run, and says so."""
    path = write_grid(tmp_path, synth_dir, cache_dir, "exp", "0.001")
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    named = load_sweep(path, ["tracking.experiment=mine"])
    assert named.experiment == "mine"
    first = Worker(named, storage, tracking_uri=store, echo=lambda *a, **k: None)
    assert first.experiment == "mine"  # the study and its parent run, before any trial
    study = optuna.load_study(study_name="exp", storage=storage)
    assert study.user_attrs["fedlgr.settings"]["overrides"][-1] == "tracking.experiment=mine"

    lines = []
    relaunch = load_sweep(path)  # without the override: not refused
    assert relaunch.experiment == "sweep-exp"
    result = run_sweep(relaunch, storage=storage, tracking_uri=store, echo=lines.append)
    assert result.done and result.parent_run_id == first.parent_run_id
    assert "MLflow experiment 'mine'" in lines[0]  # the header
    assert lines[1] == (
        "study 'exp': its parent run is in MLflow experiment 'mine', so its trials go there "
        "too (not 'sweep-exp'); --study NAME starts a new study elsewhere"
    )
    _, (parent,), (child,) = child_runs(store, "mine")
    assert parent.info.run_id == first.parent_run_id and parent.info.status == "FINISHED"
    assert child.data.tags["mlflow.parentRunId"] == parent.info.run_id
    mlflow_client = child_runs(store, "mine")[0]
    assert mlflow_client.get_experiment_by_name("sweep-exp") is None  # nothing went there

    # Another experiment named on a relaunch is not a changed setting either.
    other = load_sweep(path, ["tracking.experiment=other"])
    assert run_sweep(other, storage=storage, tracking_uri=store, echo=lines.append).done
