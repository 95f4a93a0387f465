"""Sweeps under faults, on real sqlite storages and real processes: a trial left unborn by a
kill, Ctrl-C and SIGTERM, bad sweep files and data, two sweeps started at once."""

from __future__ import annotations

import os
import re
import signal
import socket
import sqlite3
import subprocess
import sys
import time
from datetime import datetime, timedelta
from pathlib import Path

import pytest
from optuna.trial import TrialState

from fedlgr.shell.sweep import load_sweep, run_sweep
from fedlgr.shell.sweep.storage import open_study
from tests.support.checkout import REPO
from tests.support.processes import BIG_CHECKPOINT, partial_checkpoint
from tests.support.runs import FAST
from tests.support.sweeps import (
    child_runs,
    point,
    read_only_rows,
    sweep_command,
    trials_by_state,
    write_sweep,
)

ENV = {**os.environ, "PYTHONPATH": str(REPO)}


@pytest.mark.slow
def test_a_trial_killed_before_drawing_its_point_is_retried_on_that_point(
    tmp_path, synth_dir, cache_dir
):
    """A kill between Optuna creating a trial (GridSampler has set its ``grid_id``) and the
    trial drawing its parameters leaves a RUNNING trial with no params and no heartbeat.
    The next worker fails it and queues a copy, which gets the same grid point."""
    spec = load_sweep(write_sweep(tmp_path, synth_dir, cache_dir, name="unborn"))
    storage = f"sqlite:///{tmp_path}/optuna.db"
    study, _ = open_study(spec, storage)
    unborn = study.ask()  # what the killed worker left
    left = study._storage.get_trial(unborn._trial_id)
    assert left.state == TrialState.RUNNING and not left.params
    assert "grid_id" in left.system_attrs
    aged = datetime.now() - timedelta(hours=1)  # long past the heartbeat grace period
    with sqlite3.connect(tmp_path / "optuna.db") as db:
        db.execute(
            "UPDATE trials SET datetime_start = ? WHERE trial_id = ?", (str(aged), unborn._trial_id)
        )

    result = run_sweep(spec, storage=storage, tracking_uri=f"sqlite:///{tmp_path}/mlflow.db")
    assert result.done
    states = trials_by_state(storage, "unborn")
    complete = states["COMPLETE"]
    assert len(complete) == 4 and len({point(t.params) for t in complete}) == 4
    assert [t.number for t in states["FAIL"]] == [unborn.number]
    (copy,) = [c for c in complete if unborn.number in c.system_attrs.get("retry_history", [])]
    assert copy.system_attrs["grid_id"] == left.system_attrs["grid_id"]
    assert "PRUNED" not in states  # no point drawn twice on the way


@pytest.mark.slow
def test_a_stopped_workers_trial_is_left_to_it_while_it_lives(tmp_path, synth_dir, cache_dir):
    """The seventh fault sweep (g04): a worker stopped with ``kill -STOP`` mid-trial went
    silent, a second launch declared it dead by its heartbeat and took its trial over, and
    the first died on ``kill -CONT`` with "Cannot tell a FAIL trial". A trial whose worker
    is alive on this machine is left to it; once that worker is dead, it is retried."""
    import threading

    from fedlgr.shell.sweep.ownership import OWNER
    from fedlgr.shell.tracking.mlflow_run import process_started

    path = write_sweep(tmp_path, synth_dir, cache_dir, name="stopped")
    path.write_text(path.read_text() + "heartbeat_s: 1\n")
    spec = load_sweep(path)
    storage = f"sqlite:///{tmp_path}/optuna.db"
    study, _ = open_study(spec, storage)
    taken = study.ask()  # the stopped worker's trial: its point drawn, its heartbeat stale
    for p in spec.params:
        p.suggest(taken)
    stopped = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(600)"])
    try:
        stopped.send_signal(signal.SIGSTOP)
        owner = [socket.gethostname(), stopped.pid, process_started(stopped.pid)]
        study._storage.set_trial_system_attr(taken._trial_id, OWNER, owner)
        study._storage.record_heartbeat(taken._trial_id)
        time.sleep(3)  # past the grace period of 2 heartbeats
        said: list[tuple[float, str]] = []
        died: list[float] = []

        def end_it() -> None:  # once the sweep has run the other three points
            deadline = time.monotonic() + 300  # in any case: the sweep waits for it
            while time.monotonic() < deadline:
                try:
                    if len(trials_by_state(storage, "stopped").get("COMPLETE", [])) >= 3:
                        break
                except Exception:  # the sweep holds the database for a moment
                    pass
                time.sleep(0.5)
            time.sleep(3)
            stopped.kill()
            stopped.wait()
            died.append(time.monotonic())

        ender = threading.Thread(target=end_it, daemon=True)
        ender.start()
        result = run_sweep(
            spec,
            storage=storage,
            tracking_uri=f"sqlite:///{tmp_path}/mlflow.db",
            echo=lambda line: said.append((time.monotonic(), line)),
        )
        ender.join(timeout=60)
    finally:
        stopped.kill()
        stopped.wait()
    assert result.done
    assert "(0 done, 1 running, 0 queued)" in said[0][1]  # it said 1 done (u80)
    left = f"trial {taken.number} belongs to process {stopped.pid} on this machine, which is alive"
    assert [line for _, line in said if left in line]
    states = trials_by_state(storage, "stopped")
    assert [t.number for t in states["FAIL"]] == [taken.number]  # only after its worker died
    (copy,) = [
        c for c in states["COMPLETE"] if taken.number in c.system_attrs.get("retry_history", [])
    ]
    started = [at for at, line in said if f"trial {copy.number} (worker" in line]
    assert started and started[0] > died[0]
    assert len({point(t.params) for t in states["COMPLETE"]}) == 4


def _reporting_trial(db: Path) -> int | None:
    """The number of a RUNNING trial that has reported a round."""
    rows = read_only_rows(
        db,
        "SELECT t.number FROM trials t JOIN trial_intermediate_values v"
        " ON v.trial_id = t.trial_id WHERE t.state = 'RUNNING' LIMIT 1",
    )
    return rows[0][0] if rows else None


@pytest.mark.slow
@pytest.mark.parametrize("signum", [signal.SIGINT, signal.SIGTERM], ids=["ctrl-c", "sigterm"])
def test_a_stopped_sweep_requeues_its_trial_and_ends_its_parent_run_killed(
    tmp_path, synth_dir, cache_dir, signum
):
    """SIGINT (Ctrl-C) or SIGTERM (timeout, Slurm, docker stop) in the middle of a trial:
    the trial is queued again, the parent run ends KILLED, and the next launch runs every
    point of the grid."""
    path = write_sweep(tmp_path, synth_dir, cache_dir, name="stopped")
    storage = f"sqlite:///{tmp_path}/optuna.db"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    log = (tmp_path / "first.log").open("w")
    # Long trials at first, so that the signal surely lands in the middle of one.
    process = subprocess.Popen(
        sweep_command(path, storage, store, "federated.rounds=100"),
        env=ENV,
        stdout=log,
        stderr=subprocess.STDOUT,
    )
    deadline = time.monotonic() + 120
    while (number := _reporting_trial(tmp_path / "optuna.db")) is None:
        assert process.poll() is None and time.monotonic() < deadline, (
            tmp_path / "first.log"
        ).read_text()[-3000:]
        time.sleep(0.1)
    os.kill(process.pid, signum)
    code = 130 if signum == signal.SIGINT else 128 + signal.SIGTERM  # the shell's convention
    assert process.wait(timeout=60) == code, (tmp_path / "first.log").read_text()[-3000:]

    states = trials_by_state(storage, "stopped")
    (stopped,) = states["FAIL"]
    assert stopped.number == number and stopped.params
    why = "stopped by Ctrl-C" if signum == signal.SIGINT else "stopped by SIGTERM"
    assert stopped.user_attrs["interrupted"] == why  # the final table shows it
    (queued,) = states["WAITING"]
    assert queued.params == stopped.params and queued.system_attrs["retry_history"] == [number]
    _, (parent,), (child,) = child_runs(store, "sweep-stopped")
    assert parent.info.status == "KILLED" and child.info.status == "KILLED"

    # The relaunch drops federated.rounds=100 (short trials now): a study refuses other
    # settings unless told that they changed on purpose (--settings-changed).
    relaunch = load_sweep(path)
    assert run_sweep(relaunch, storage=storage, tracking_uri=store, settings_changed=True).done
    states = trials_by_state(storage, "stopped")
    complete = states["COMPLETE"]
    assert len(complete) == 4 and len({point(t.params) for t in complete}) == 4
    assert [t.number for t in states["FAIL"]] == [number]
    assert any(number in t.system_attrs.get("retry_history", []) for t in complete)
    _, (parent,), children = child_runs(store, "sweep-stopped")
    assert parent.info.status == "FINISHED"
    assert sorted(c.info.status for c in children) == ["FINISHED"] * 4 + ["KILLED"]


@pytest.mark.slow
def test_ctrl_c_while_a_trial_writes_its_checkpoint_stops_the_sweep_and_keeps_the_point(
    tmp_path, synth_dir, cache_dir
):
    """Issue 37, Deliver 7: Ctrl-C while a trial's checkpoint was written became "cannot
    write checkpoint" (torch.save wraps the KeyboardInterrupt in a RuntimeError): the trial
    was recorded FAILED, the sweep went on and exited 0, and a relaunch said "all 2 trials
    are done" - a grid point lost. It stops the sweep as Ctrl-C elsewhere does, and the
    relaunch runs that point."""
    path = tmp_path / "ckpt.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1, "
        f"federated.rounds=1, {', '.join(BIG_CHECKPOINT)}]\n"
        "space:\n  train.lr_top: [0.001, 0.01]\n"
    )
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    log = tmp_path / "first.log"
    with log.open("w") as out:
        process = subprocess.Popen(
            sweep_command(path, storage, store), env=ENV, stdout=out, stderr=subprocess.STDOUT
        )
        try:
            partial = partial_checkpoint(tmp_path / "checkpoints", process)
            os.kill(process.pid, signal.SIGINT)
            code = process.wait(timeout=60)
        finally:
            process.kill()
            process.wait()
    said = log.read_text()
    assert code == 130, said[-3000:]
    assert "cannot write checkpoint" not in said and "fedlgr: interrupted" in said, said[-3000:]
    assert not list(partial.parent.glob(".*.tmp"))
    states = trials_by_state(storage, "ckpt")
    (stopped,) = states["FAIL"]
    assert stopped.user_attrs["interrupted"] == "stopped by Ctrl-C"
    assert "error" not in stopped.user_attrs
    (queued,) = states["WAITING"]
    assert queued.params == stopped.params
    _, (parent,), (child,) = child_runs(store, "sweep-ckpt")
    assert parent.info.status == "KILLED" and child.info.status == "KILLED"

    assert run_sweep(load_sweep(path), storage=storage, tracking_uri=store).done
    complete = trials_by_state(storage, "ckpt")["COMPLETE"]
    assert sorted(t.params["train.lr_top"] for t in complete) == [0.001, 0.01]
    assert any(stopped.number in t.system_attrs.get("retry_history", []) for t in complete)


@pytest.mark.slow
def test_a_sweep_whose_trials_keep_failing_stops_after_three_in_a_row(
    tmp_path, synth_dir, cache_dir
):
    """Issue 37, Deliver 7: with --workers 2, trials that all failed at once (here each
    point asks for more clients than there are training scenes) were run for ever, over
    7,000 in minutes, when they covered no grid point. A sweep stops once
    failures_in_a_row (default 3) trials in a row have failed: one line naming the last
    one's error, exit 1, its parent run FAILED, and both workers gone."""
    path = tmp_path / "failing.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1]\n"
        f"space:\n  data.clients: {list(range(100, 120))}\n"
    )
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    command = sweep_command(path, storage, store, "--workers", "2")
    done = subprocess.run(command, env=ENV, capture_output=True, text=True, timeout=240)
    assert done.returncode == 1, done.stdout[-3000:] + done.stderr[-3000:]
    line = done.stderr.strip().splitlines()[-1]
    stopped = re.fullmatch(
        r"fedlgr: error: sweep failing: stopped after 3 trials in a row failed "
        r"\(failures_in_a_row: 3\); the last, trial (\d+): (ConfigError: .*)",
        line,
    )
    assert stopped, line
    states = trials_by_state(storage, "failing")
    assert list(states) == ["FAIL"]
    # Each worker stops after its own trial that made the third failure in a row.
    assert 3 <= len(states["FAIL"]) <= 6, [t.number for t in states["FAIL"]]
    last = next(t for t in states["FAIL"] if t.number == int(stopped.group(1)))
    assert last.user_attrs["error"] == stopped.group(2)
    clients = last.params["data.clients"]
    assert f"data.clients={clients}: more clients than the 36 training scenes" in line
    _, (parent,), _ = child_runs(store, "sweep-failing")
    assert parent.info.status == "FAILED"


def _fedlgr(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "fedlgr", *args]
    return subprocess.run(command, cwd=cwd, env=ENV, capture_output=True, text=True)


def _one_error_line(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("fedlgr: error: ")
    return line


BASE = f"base: {FAST}\n"


@pytest.mark.parametrize(
    ("body", "message"),
    [
        (BASE + "space: {train.lr_top: [0.1, 1]\n", "line 3, column 1: not valid YAML: expected"),
        (BASE + "space:\n  train.lr_top: [0.1]\n\tseed: 1\n", "line 4, column 1: not valid YAML"),
        (BASE + "space: {seed: [1]}\nspace: {seed: [2]}\n", "line 3, column 1: not valid YAML"),
        ("- train.lr_top\n- seed\n", "a sweep file is a mapping of settings"),
        ("just words\n", "a sweep file is a mapping of settings"),
        (BASE + "space: {seed: [1]}\nworkers: 2\n", "workers: unknown setting"),
        (BASE + "space: {seed: [1]}\nobjective: {metrc: x}\n", "objective.metrc: unknown"),
        (BASE + "space: {seed: [1]}\nheartbeat_s: often\n", "heartbeat_s: expected a whole"),
        (
            BASE + f"space: {{seed: {list(range(12_000))}}}\n",
            ": too large: over 10,000 YAML nodes (keys, values and list items), more than "
            "OmegaConf reads from one file (a config holds a few hundred); give a long list "
            "as low/high/step",
        ),
        (
            BASE + "space: {tracking.uri: [sqlite:///evil.db]}\n",
            "space.tracking.uri: set by the sweep for every trial (--tracking-uri), not swept",
        ),
    ],
    ids=[
        "yaml",
        "tab",
        "twice",
        "list",
        "scalar",
        "key",
        "objective-key",
        "integer",
        "nodes",
        "set",
    ],
)
def test_a_bad_sweep_file_is_one_error_line_naming_the_file(tmp_path, body, message):
    path = tmp_path / "bad.yaml"
    path.write_text(body)
    line = _one_error_line(_fedlgr("sweep", str(path), cwd=tmp_path))
    assert line.startswith(f"fedlgr: error: {path}") and message in line
    assert not (tmp_path / "optuna.db").exists()  # refused before opening any study


@pytest.mark.parametrize("study", ["", " ", "x" * 513, "a\nb"])
def test_an_empty_or_overlong_study_name_is_refused(tmp_path, study):
    """The seventh fault sweep (w19): ``--study ''`` quietly became the sweep's name."""
    path = tmp_path / "ok.yaml"
    path.write_text(BASE + "space: {seed: [1]}\n")
    line = _one_error_line(_fedlgr("sweep", str(path), "--study", study, cwd=tmp_path))
    said = "513 characters, at most 512" if study.strip() else f"{study!r}: empty"
    said = f"{study!r}: holds a control character" if "\n" in study else said
    assert line.startswith("fedlgr: error: --study") and said in line
    assert not (tmp_path / "optuna.db").exists()


@pytest.mark.parametrize("missing", ["folder", "file"])
@pytest.mark.slow
def test_a_sweep_whose_data_path_is_not_a_folder_refuses_to_start(
    tmp_path, synth_dir, cache_dir, missing
):
    path = write_sweep(tmp_path, synth_dir, cache_dir, name="nodata")
    data = tmp_path / "no-such-data"
    if missing == "file":
        data = synth_dir / "synth.json"
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    command = ["sweep", str(path), f"data.path={data}", "--storage", storage, "--tracking-uri"]
    line = _one_error_line(_fedlgr(*command, store, cwd=tmp_path))
    assert f"data.path={data}: " in line and str(path) in line
    assert ("no such folder" if missing == "folder" else "not the dataset folder") in line
    assert not (tmp_path / "optuna.db").exists() and not (tmp_path / "mlflow.db").exists()


@pytest.mark.slow
def test_two_sweeps_started_at_once_on_a_fresh_storage_share_it(tmp_path, synth_dir, cache_dir):
    """The first use of fresh sqlite files creates Optuna's and MLflow's tables, the study
    and the parent run: two sweeps doing it at the same moment both run, on one study."""
    path = tmp_path / "twice.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1]\n"
        "space:\n  train.lr_top: [0.001, 0.01]\n"
    )
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    command = [sys.executable, "-m", "fedlgr", "sweep", str(path), "--storage", storage]
    command += ["--tracking-uri", store, "--heartbeat", "5"]
    logs = [(tmp_path / f"sweep{k}.log").open("w") for k in range(2)]
    processes = [
        subprocess.Popen(command, env=ENV, stdout=log, stderr=subprocess.STDOUT) for log in logs
    ]
    for k, process in enumerate(processes):
        code = process.wait(timeout=240)
        assert code == 0, (tmp_path / f"sweep{k}.log").read_text()[-3000:]

    states = trials_by_state(storage, "twice")
    complete = states["COMPLETE"]
    assert sorted(t.params["train.lr_top"] for t in complete) == [0.001, 0.01]
    assert set(states) <= {"COMPLETE", "PRUNED"}  # a PRUNED trial is a skipped duplicate
    assert all("duplicate_of" in t.user_attrs for t in states.get("PRUNED", []))
    _, parents, children = child_runs(store, "sweep-twice")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    assert sorted(c.info.status for c in children) == ["FINISHED", "FINISHED"]


@pytest.mark.slow
def test_a_trial_killed_in_its_third_round_is_retried_from_its_checkpoint(
    tmp_path, synth_dir, cache_dir
):
    """The retried trial continues its MLflow run from the round-2 checkpoint: rounds 1-2
    are logged once, and Optuna sees every round's report."""
    import mlflow

    path = tmp_path / "one.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, federated.rounds=4]\n"
        "objective: {metric: test/rmse, direction: minimize}\n"
        "heartbeat_s: 1\n"  # the relaunch finds the dead worker's trial within 2 s
        "space:\n"
        "  method: [FedRootOpt]\n"
    )
    storage = f"sqlite:///{tmp_path}/optuna.db"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    log = (tmp_path / "first.log").open("w")
    process = subprocess.Popen(
        sweep_command(path, storage, store),
        env=ENV,
        stdout=log,
        stderr=subprocess.STDOUT,
        start_new_session=True,
    )
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob("checkpoints/*/round-0002.ckpt")):
        assert process.poll() is None and time.monotonic() < deadline, (
            tmp_path / "first.log"
        ).read_text()[-3000:]
        time.sleep(0.05)
    os.killpg(process.pid, signal.SIGKILL)  # in round 3: no clean-up of any kind
    process.wait()
    (folder,) = tmp_path.glob("checkpoints/*")
    killed_run = folder.name

    lines = []
    assert run_sweep(load_sweep(path), storage=storage, tracking_uri=store, echo=lines.append).done
    states = trials_by_state(storage, "one")
    (retry,) = states["COMPLETE"]
    assert retry.system_attrs["retry_history"] == [0]
    assert retry.user_attrs["mlflow_run_id"] == killed_run
    assert sorted(retry.intermediate_values) == [1, 2, 3, 4]
    assert f"=== trial {retry.number} continues run {killed_run} of trial 0" in lines
    client = mlflow.MlflowClient(store)
    _, _, (child,) = child_runs(store, "sweep-one")  # one run for the point, the same one
    assert child.info.run_id == killed_run and child.info.status == "FINISHED"
    assert child.data.tags["trial"] == str(retry.number)
    steps = [m.step for m in client.get_metric_history(killed_run, "round/seconds")]
    assert sorted(steps) == [1, 2, 3, 4]  # each round logged once
    history = client.get_metric_history(killed_run, "test/rmse")
    assert sorted(m.step for m in history) == [1, 2, 3, 4]
    assert retry.value == pytest.approx(history[-1].value if history[-1].step == 4 else None)
