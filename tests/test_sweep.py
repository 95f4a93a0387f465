"""Sweeps: every shipped sweep builds its space; a grid runs as an Optuna study with one
MLflow child run per trial under a parent; a killed sweep resumes; two workers share one.
Under faults, on real sqlite storages and processes: a trial left unborn by a kill, a
stopped worker, Ctrl-C and SIGTERM, trials failing in a row, two sweeps started at once."""

from __future__ import annotations

import math
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

import optuna
import pytest
from optuna.distributions import CategoricalDistribution, FloatDistribution
from optuna.trial import TrialState

from fedlgr.errors import ConfigError
from fedlgr.shell.sweep import load_sweep, run_sweep
from fedlgr.shell.sweep.spec import SWEEPS_DIR
from fedlgr.shell.sweep.storage import open_study
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

SWEEPS = sorted(SWEEPS_DIR.glob("*.yaml"))
REPO = Path(__file__).resolve().parents[1]


@pytest.mark.slow
@pytest.mark.parametrize("path", SWEEPS, ids=[p.stem for p in SWEEPS])
def test_every_shipped_sweep_loads_and_builds_its_search_space(path):
    spec = load_sweep(path)  # also builds the config of every grid point
    space = spec.search_space()
    assert space and set(space) == {p.name for p in spec.params}
    if spec.sampler == "grid":
        assert spec.pruner == "none"
        assert spec.n_trials == math.prod(len(v) for v in spec.grid.values())
        assert all(isinstance(d, CategoricalDistribution) for d in space.values())
        optuna.samplers.GridSampler(spec.grid)  # Optuna accepts the grid as it is
    else:
        assert spec.pruner == "median" and spec.n_trials > 0


def test_a_grid_null_reaches_the_trial_as_an_unset_setting():
    spec = load_sweep("fedlgr_drift_image")
    assert None in spec.grid["continual.lgr.train_blocks"]
    _, overrides = spec.trial_config_args({"continual.lgr.train_blocks": None})
    assert overrides[-1] == "continual.lgr.train_blocks=null"  # not the string "None"


@pytest.mark.slow
def test_the_paper_grids_cover_every_method_and_setting():
    from fedlgr.core.methods import in_paper
    from fedlgr.shell.config import FCL_METHODS, METHODS

    fl, fcl = load_sweep("paper_fl"), load_sweep("paper_fcl")
    assert fl.n_trials == 10 * 4 and set(fl.grid["method"]) == set(filter(in_paper, METHODS))
    table2 = {m for m in FCL_METHODS if not m.endswith("-FT") and in_paper(m)}
    assert fcl.n_trials == 11 * 4 and set(fcl.grid["method"]) == table2
    assert {Path(c).name for c in fl.grid["config"]} == {
        "clients2_noaug.yaml",
        "clients2_aug.yaml",
        "clients10_noaug.yaml",
        "clients10_aug.yaml",
    }
    tpe = load_sweep("fedlgr_tpe").search_space()
    assert isinstance(tpe["continual.lgr.lr_root"], FloatDistribution)
    assert tpe["continual.lgr.lr_root"].log


@pytest.mark.parametrize(
    ("body", "message"),
    [
        ("space: {}\n", "space: needs at least one parameter"),
        ("space: {train.lr_top: {low: 1}}\n", "space.train.lr_top: a range needs low and high"),
        ("space: {train.lr_top: [0.1]}\nsampler: bayes\n", "sampler: 'bayes'"),
        ("space: {train.lr_top: {low: 0.1, high: 1}}\nsampler: grid\n", "grid needs a list"),
        ("space: {train.lr_top: {low: 0.1, high: 1}}\n", "trials: a TPE sweep needs trials"),
        ("space: {train.lr_top: [0.1]}\nobjective: {direction: up}\n", "objective.direction"),
        ("space: {train.lr_topp: [0.1]}\n", "train.lr_topp"),
        ("space: {train.lr_top: [0.1]}\nworkers: 2\n", "workers: unknown setting"),
        ("space: {train.lr_top: [0.1]}\nfailures_in_a_row: 0\n", "failures_in_a_row: 0 is below"),
    ],
)
def test_bad_sweep_files_name_the_file_and_key(tmp_path, body, message):
    path = tmp_path / "bad.yaml"
    path.write_text(f"base: {FAST}\n{body}")
    with pytest.raises(ConfigError) as err:
        load_sweep(path)
    assert str(path) in str(err.value) and message in str(err.value)


# --------------------------------------------------------------------------- real studies


@pytest.mark.slow
def test_a_grid_sweep_runs_every_point_once_under_one_parent_run(
    tmp_path, synth_dir, cache_dir, capsys
):
    store = f"sqlite:///{tmp_path}/mlflow.db"
    storage = f"sqlite:///{tmp_path}/optuna.db"
    spec = load_sweep(write_sweep(tmp_path, synth_dir, cache_dir))
    result = run_sweep(spec, storage=storage, tracking_uri=store, echo=print)
    assert result.done

    states = trials_by_state(storage, "grid4")
    assert list(states) == ["COMPLETE"] and len(states["COMPLETE"]) == 4
    assert len({point(t.params) for t in states["COMPLETE"]}) == 4

    client, parents, children = child_runs(store, "sweep-grid4")
    assert len(parents) == 1 and len(children) == 4
    parent = parents[0]
    assert parent.info.run_id == result.parent_run_id and parent.info.status == "FINISHED"
    assert {c.data.tags["mlflow.parentRunId"] for c in children} == {parent.info.run_id}
    assert sorted(c.data.tags["trial"] for c in children) == ["0", "1", "2", "3"]
    assert all(c.info.status == "FINISHED" for c in children)
    # Each child is a full run (params, metrics, artifacts) and the trial's value is its RMSE.
    by_trial = {int(c.data.tags["trial"]): c for c in children}
    for t in states["COMPLETE"]:
        child = by_trial[t.number]
        assert t.value == pytest.approx(child.data.metrics["test/rmse"])
        assert child.data.params["train.lr_top"] == str(t.params["train.lr_top"])
        assert child.data.tags["method"] == t.params["method"]
        assert {"config.yaml", "results.csv"} <= {
            a.path for a in client.list_artifacts(child.info.run_id)
        }
    # The parent holds the study's settings and the best trial.
    best = min(states["COMPLETE"], key=lambda t: t.value)
    assert parent.data.params["sampler"] == "grid" and parent.data.params["trials"] == "4"
    assert parent.data.tags["best.trial"] == str(best.number)
    assert parent.data.tags["best.method"] == best.params["method"]
    assert parent.data.metrics["best/test/rmse"] == pytest.approx(best.value)
    out = capsys.readouterr().out
    assert f"best (*): trial {best.number}" in out

    # Launching a finished sweep again runs nothing.
    again = run_sweep(spec, storage=storage, tracking_uri=store, echo=print)
    assert again.done and len(trials_by_state(storage, "grid4")["COMPLETE"]) == 4
    assert len(child_runs(store, "sweep-grid4")[2]) == 4


@pytest.mark.slow
def test_a_sigterm_while_optuna_records_a_trial_stops_the_sweep_as_an_interrupt(
    tmp_path, synth_dir, cache_dir, monkeypatch
):
    """The seventh fault sweep (i17): SIGTERM that arrives while Optuna records a finished
    trial (``_tell_with_warning``, here raising the Terminated the signal handler raises)
    became Optuna 4's ``UnboundLocalError: ... 'updated_state'`` and two tracebacks. It is
    the interrupt: the trial is queued again and the parent run ends KILLED."""
    import optuna.study._optimize as optimize

    from fedlgr.shell.signals import Terminated

    def interrupted(**_):
        raise Terminated("SIGTERM")

    monkeypatch.setattr(optimize, "_tell_with_warning", interrupted)
    spec = load_sweep(write_sweep(tmp_path, synth_dir, cache_dir, name="tell"))
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    with pytest.raises(Terminated):
        run_sweep(spec, storage=storage, tracking_uri=store, echo=print)
    states = trials_by_state(storage, "tell")
    assert len(states["WAITING"]) == 1  # the copy the next launch runs
    _, (parent,), _ = child_runs(store, "sweep-tell")
    assert parent.info.status == "KILLED"


def test_a_sighup_just_as_a_trial_begins_queues_that_trial_again(
    tmp_path, synth_dir, cache_dir, monkeypatch
):
    """The ninth fault sweep (i17d, i17g): SIGTERM or SIGHUP the moment a trial began -
    after Optuna's ask() had made it, before the objective ran - left it RUNNING and
    queued nothing (only a relaunch's dead-worker check recovered it). The signal now waits
    for the objective: the trial ends FAIL, interrupted, and a copy waits for the next
    launch."""
    import os
    import signal

    import optuna

    from fedlgr.shell.signals import Terminated, terminate_as_interrupt

    ask = optuna.Study.ask

    def ask_then_signal(study, *args, **kwargs):
        trial = ask(study, *args, **kwargs)
        os.kill(os.getpid(), signal.SIGHUP)  # its handler runs here, in ask()
        return trial

    monkeypatch.setattr(optuna.Study, "ask", ask_then_signal)
    spec = load_sweep(write_sweep(tmp_path, synth_dir, cache_dir, name="ask"))
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    with pytest.raises(Terminated), terminate_as_interrupt():
        run_sweep(spec, storage=storage, tracking_uri=store, echo=print)
    states = trials_by_state(storage, "ask")
    assert "RUNNING" not in states, states
    (failed,) = states["FAIL"]
    # the signal named (a SIGHUP was "stopped by SIGTERM": the tenth fault sweep, d03)
    assert failed.user_attrs["interrupted"] == "stopped by SIGHUP"
    assert len(states["WAITING"]) == 1  # the copy the next launch runs
    _, (parent,), _ = child_runs(store, "sweep-ask")
    assert parent.info.status == "KILLED"


@pytest.mark.slow
def test_a_failing_trial_is_recorded_failed_and_the_sweep_goes_on(tmp_path, synth_dir, cache_dir):
    path = tmp_path / "fails.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1]\n"
        "space:\n"
        "  data.clients: [2, 100]\n"  # 100 clients > training scenes: a clear error
    )
    storage = f"sqlite:///{tmp_path}/optuna.db"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    result = run_sweep(load_sweep(path), storage=storage, tracking_uri=store, echo=print)
    assert result.done
    states = trials_by_state(storage, "fails")
    assert len(states["COMPLETE"]) == 1 and states["COMPLETE"][0].params == {"data.clients": 2}
    (failed,) = states["FAIL"]
    assert failed.params == {"data.clients": 100}
    assert "100" in failed.user_attrs["error"] and "client" in failed.user_attrs["error"]


@pytest.mark.slow
def test_pruned_trials_end_killed_in_mlflow(tmp_path, synth_dir, cache_dir):
    """A TPE sweep with the median pruner and a prune-everything warm-up of 0: trials after
    the startup ones that are worse than the median at a round stop there."""
    path = tmp_path / "tpe.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1, "
        "federated.rounds=3]\n"
        "sampler: tpe\ntrials: 6\npruner: median\nprune_warmup_rounds: 0\n"
        "space:\n"
        "  train.lr_top: {low: 0.00001, high: 0.1, log: true}\n"
    )
    storage = f"sqlite:///{tmp_path}/optuna.db"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    run_sweep(load_sweep(path), storage=storage, tracking_uri=store, echo=print)
    study = optuna.load_study(study_name="tpe", storage=storage)
    trials = study.get_trials()
    assert len(trials) == 6
    for t in trials:  # every trial reported its per-round RMSE as intermediate values
        assert t.intermediate_values and set(t.intermediate_values) <= {1, 2, 3}
    pruned = [t for t in trials if t.state.name == "PRUNED"]
    assert pruned, [(t.state.name, t.intermediate_values) for t in trials]
    _, _, children = child_runs(store, "sweep-tpe")
    status = {int(c.data.tags["trial"]): c.info.status for c in children}
    for t in pruned:
        assert status[t.number] == "KILLED"
        assert max(t.intermediate_values) == t.user_attrs["pruned_at_round"] < 3
    for t in trials:
        if t.state.name == "COMPLETE":
            assert status[t.number] == "FINISHED"


@pytest.mark.slow
def test_a_killed_sweep_resumes_without_redoing_finished_trials(tmp_path, synth_dir, cache_dir):
    path = write_sweep(tmp_path, synth_dir, cache_dir, name="resume")
    storage = f"sqlite:///{tmp_path}/optuna.db"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    process = subprocess.Popen(
        sweep_command(path, storage, store),
        env=env,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        start_new_session=True,
    )
    deadline = time.monotonic() + 240
    complete = "SELECT number FROM trials WHERE state = 'COMPLETE'"
    first = []
    while time.monotonic() < deadline and not first:
        time.sleep(0.5)
        first = read_only_rows(tmp_path / "optuna.db", complete)
    os.killpg(process.pid, signal.SIGKILL)  # a real kill: no clean-up runs
    process.wait()
    assert first, "the first trial never finished"
    done_before = {
        t.number: point(t.params) for t in trials_by_state(storage, "resume")["COMPLETE"]
    }
    assert 1 <= len(done_before) < 4

    finished = subprocess.run(
        sweep_command(path, storage, store), env=env, capture_output=True, text=True
    )
    assert finished.returncode == 0, finished.stderr[-2000:]
    states = trials_by_state(storage, "resume")
    complete = states["COMPLETE"]
    assert len(complete) == 4 and len({point(t.params) for t in complete}) == 4
    for number, params in done_before.items():  # finished trials are not redone
        assert [t.number for t in complete if point(t.params) == params] == [number]
    # The trial the kill interrupted (if any) is FAILED and was retried.
    for t in states.get("FAIL", []):
        assert any(t.number in c.system_attrs.get("retry_history", []) for c in complete)
    _, parents, children = child_runs(store, "sweep-resume")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    assert sum(c.info.status == "FINISHED" for c in children) == 4
    assert all(c.info.status in ("FINISHED", "KILLED") for c in children)


@pytest.mark.slow
def test_two_workers_share_one_study_and_run_no_point_twice(
    tmp_path, synth_dir, cache_dir, monkeypatch
):
    path = write_sweep(tmp_path, synth_dir, cache_dir, name="parallel")
    storage = f"sqlite:///{tmp_path}/optuna.db"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    monkeypatch.setenv("PYTHONPATH", str(REPO))
    lines = []
    spec = load_sweep(path)
    result = run_sweep(spec, storage=storage, tracking_uri=store, workers=2, echo=lines.append)
    assert result.done
    # Each worker's lines carry its label (the helper's come through this process); the
    # sweep's own header and final table do not.
    text = "\n".join(lines).splitlines()
    start = text.index(next(t for t in text if t.startswith("trial ")))
    worker_lines = [t for t in text[1:start] if t.strip()]
    assert worker_lines and all(t.startswith(("[w0] ", "[w1] ")) for t in worker_lines), text
    assert any(t.startswith("[w1] sweep parallel: grid, 4 trials") for t in worker_lines)
    assert any(t.startswith("[w0] === parallel trial ") for t in worker_lines)
    assert sum(t.startswith("trial ") for t in text) == 1  # one final table
    states = trials_by_state(storage, "parallel")
    complete = states["COMPLETE"]
    assert len(complete) == 4 and len({point(t.params) for t in complete}) == 4
    # Any extra trial is a skipped duplicate that never trained.
    for t in states.get("PRUNED", []):
        assert "duplicate_of" in t.user_attrs
    _, parents, children = child_runs(store, "sweep-parallel")
    assert len(parents) == 1 and len(children) == 4
    assert len({(c.data.tags["method"], c.data.params["train.lr_top"]) for c in children}) == 4
    assert {t.user_attrs["worker"] for t in complete} <= {0, 1}


ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _reporting_trial(db: Path) -> int | None:
    """The number of a RUNNING trial that has reported a round."""
    rows = read_only_rows(
        db,
        "SELECT t.number FROM trials t JOIN trial_intermediate_values v"
        " ON v.trial_id = t.trial_id WHERE t.state = 'RUNNING' LIMIT 1",
    )
    return rows[0][0] if rows else None


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
    from fedlgr.shell.tracking.liveness import process_started

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
