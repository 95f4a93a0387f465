"""Sweeps check before they train and stop when nothing is left (issue 20): bad parameter
definitions and objectives refused before trial 1, large grids checked without building
every point, a space with no new point ends the sweep, every trial's error shown and an
all-failed sweep exits 1, bad ``--storage`` paths are one line, and the parent run's best
figure is logged once however many workers finish. A bad sweep file, study name or data
folder is one error line naming it."""

from __future__ import annotations

import contextlib
import os
import signal
import sqlite3
import subprocess
import sys
import time
from pathlib import Path

import mlflow
import optuna
import pytest
from optuna.distributions import CategoricalDistribution
from optuna.trial import TrialState, create_trial

import fedlgr.shell.config
import fedlgr.shell.sweep.storage
from fedlgr.errors import ConfigError
from fedlgr.shell.cli import main
from fedlgr.shell.sweep import load_sweep, run_sweep
from fedlgr.shell.sweep.checks import run_metrics
from fedlgr.shell.sweep.space import Param
from fedlgr.shell.sweep.trials import DUPLICATES_IN_A_ROW, counts, no_new_point
from tests.support.checkout import REPO
from tests.support.runs import FAST
from tests.support.sweeps import write_sweep

BASE = f"base: {FAST}\n"


def _sweep_file(tmp_path: Path, body: str, name: str = "checks") -> Path:
    path = tmp_path / f"{name}.yaml"
    path.write_text(BASE + body)
    return path


def _fixed(synth_dir: Path, cache_dir: Path) -> str:
    return f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1]\n"


def _error_line(capsys) -> str:
    err = capsys.readouterr().err
    assert "Traceback" not in err, err
    (line,) = err.strip().splitlines()
    return line


# --------------------------------------------------------------------------- before trial 1

TPE = "sampler: tpe\ntrials: 3\nspace:\n"


@pytest.mark.parametrize(
    ("space", "message"),
    [
        ("{low: 0.1, high: 1, step: abc}", "step must be a number above 0, not 'abc'"),
        ("{low: 0.1, high: 1, step: 0}", "step must be a number above 0, not 0"),
        ("{low: 0.1, high: 1, step: 0.1, log: true}", "step and log: true cannot go together"),
        ("{low: .nan, high: 1}", "low must be a finite number, not nan"),
        ("{low: 0.1, high: .inf}", "high must be a finite number, not inf"),
        ("{low: 0.1, high: 1, log: 'yes'}", "log: expected true or false, not 'yes'"),
        ("{low: 0.1, high: 1, step: 5}", "step (5) is larger than the range"),
        ("{choices: [0.1, 0.2], log: true}", "unknown setting(s) ['log'] next to choices"),
        ("{choices: [0.1, .nan]}", "choices values cannot be .nan"),
        ("[0.1, 0.1]", "0.1 is listed twice"),
    ],
    ids=[
        "step-abc",
        "step-0",
        "log-step",
        "nan",
        "inf",
        "log-yes",
        "step-big",
        "extra",
        "choice-nan",
        "twice",
    ],
)
def test_a_bad_parameter_definition_is_one_line_before_any_trial(
    tmp_path, capsys, monkeypatch, space, message
):
    monkeypatch.chdir(tmp_path)  # the default MLflow store is ./mlflow.db
    path = _sweep_file(tmp_path, f"{TPE}  train.lr_top: {space}\n")
    storage = tmp_path / "optuna.db"
    assert main(["sweep", str(path), "--storage", f"sqlite:///{storage}"]) == 1
    line = _error_line(capsys)
    assert line.startswith(f"fedlgr: error: {path}: space.train.lr_top: ") and message in line
    assert not storage.exists()  # refused before any study existed


@pytest.mark.parametrize(
    ("objective", "space", "hint"),
    [
        ("test/rsme", "train.lr_top: [0.1]", "did you mean test/rmse?"),
        ("after_task3/test/rmse", "method: [FedAvg-EWC]", "did you mean after_task2/test/rmse?"),
    ],
    ids=["typo", "fcl-task"],
)
def test_an_objective_no_run_logs_is_refused_before_training(tmp_path, objective, space, hint):
    path = _sweep_file(tmp_path, f"objective: {{metric: {objective}}}\nspace:\n  {space}\n")
    with pytest.raises(ConfigError) as refused:
        load_sweep(path)
    message = str(refused.value)
    assert message.startswith(f"{path}: objective.metric: {objective} is not a metric")
    assert hint in message and "\n" not in message
    # What the runs end with (FL: round means and per client, FCL: after each task) passes.
    config = fedlgr.shell.config.load_config(FAST, ["method=FedAvg-EWC", "data.path=/x"])
    names = run_metrics(config)
    assert {"test/rmse", "test/client1/pcc", "after_task2/test/rmse", "mean/cost/cpu_s"} <= names
    assert "after_task2/forgetting/circle/rmse" in names and "forgetting/circle/rmse" not in names
    assert "mean/cost/paper_cpu_s" in names and "server/test/rmse" not in names
    served = fedlgr.shell.config.load_config(FAST, ["federated.server_eval=on", "data.path=/x"])
    assert {"server/test/rmse", "cost/server_cpu_s"} <= run_metrics(served)


@pytest.mark.slow
def test_a_large_grid_is_checked_one_value_at_a_time(tmp_path, monkeypatch, capsys):
    """10,000 points: every value of each parameter is loaded once (37 configs), not every
    point (10,000 loads of ~25 ms); a bad value in the middle of a list is still found."""
    loads = []
    real = fedlgr.shell.config.load_config

    def counted(*args, **kwargs):
        loads.append(args)
        assert len(loads) < 200, "the grid's points are being loaded one by one"
        return real(*args, **kwargs)

    monkeypatch.setattr(fedlgr.shell.config, "load_config", counted)
    ten = list(range(1, 11))
    space = f"  seed: {ten}\n  train.epochs: {ten}\n  federated.rounds: {ten}\n"
    spec = load_sweep(_sweep_file(tmp_path, f"space:\n{space}  data.seed: {ten}\n"))
    assert spec.n_trials == 10_000 and len(loads) == 1 + 4 * 9
    assert capsys.readouterr().out.splitlines() == [  # said before the slow part
        "sweep checks: checking its 10,000-point grid one parameter at a time (37 configs); "
        "the points are built as trials take them"
    ]
    study = optuna.create_study(sampler=optuna.samplers.GridSampler(spec.grid))
    assert counts(study, spec) == (10_000, 0, 0)

    loads.clear()
    bad = _sweep_file(tmp_path, f"space:\n{space}  train.lr_top: [0.1, -1, 0.2]\n", "bad")
    with pytest.raises(ConfigError, match=r"trial \{.*'train.lr_top': -1\}: .*train.lr_top"):
        load_sweep(bad)


def test_a_sweep_file_nested_too_deep_is_one_line(tmp_path):
    path = _sweep_file(tmp_path, "space: " + "[" * 50_000 + "]" * 50_000 + "\n")
    with pytest.raises(ConfigError) as caught:
        load_sweep(path)
    assert str(caught.value) == f"{path}: nested too deeply to be a sweep file"


def test_a_grid_optuna_cannot_hold_is_refused_in_one_line(tmp_path, monkeypatch):
    """8 parameters of 30 values: 656,100,000,000 points, which Optuna's GridSampler lists
    up front (it filled 20 GB of memory in 80 s and ignored SIGTERM). Refused before any
    config is loaded; 1,000,000 points still pass."""
    monkeypatch.setattr(fedlgr.shell.config, "load_config", lambda *a, **k: pytest.fail("loaded"))
    values = list(range(30))
    keys = ["seed", "data.seed", "train.epochs", "federated.rounds", "train.batch_size"]
    keys += ["continual.rounds_per_task", "model.top_hidden", "train.lr_top"]
    space = "".join(f"  {k}: {values}\n" for k in keys)
    with pytest.raises(ConfigError) as caught:
        load_sweep(_sweep_file(tmp_path, f"space:\n{space}"))
    assert str(caught.value) == (
        f"{tmp_path / 'checks.yaml'}: space: a 656,100,000,000-point grid; at most 1,000,000 "
        "(Optuna's GridSampler holds every point in memory, ~78,732 GB here, and each point "
        "is a trial): fewer values, or sampler: tpe with trials: N"
    )


# --------------------------------------------------------------------------- no new point


def _frozen(spec, params: dict, state=TrialState.COMPLETE, **attrs):
    """A finished trial of ``spec`` at ``params``, as a worker leaves it."""
    return create_trial(
        state=state,
        value=1.0 if state == TrialState.COMPLETE else None,
        params=params,
        distributions=spec.search_space(),
        user_attrs=attrs,
    )


def test_a_space_with_no_new_point_stops_the_sweep(tmp_path):
    """The rule that ends a TPE sweep: every distinct point of a finite space has run, or
    the sampler's last DUPLICATES_IN_A_ROW draws were all points already run."""
    sizes = {
        "choices": Param("x", values=("a", "b", "c"), categorical=True),
        "int": Param("x", low=1, high=10, step=3),  # 1, 4, 7, 10
        "float": Param("x", low=0.0, high=1.0, step=0.25),
        "log-int": Param("x", low=1, high=8, log=True),
        "continuous": Param("x", low=0.0, high=1.0),
    }
    assert {k: p.size() for k, p in sizes.items()} == {
        "choices": 3,
        "int": 4,
        "float": 5,
        "log-int": 8,
        "continuous": None,
    }
    spec = load_sweep(_sweep_file(tmp_path, TPE + "  method: {choices: [FedAvg, FedRootAvg]}\n"))
    study = optuna.create_study()
    study.add_trial(_frozen(spec, {"method": "FedAvg"}))
    assert no_new_point(study, spec) is None and counts(study, spec) == (2, 0, 0)
    study.add_trial(_frozen(spec, {"method": "FedAvg"}, TrialState.PRUNED, duplicate_of=0))
    study.add_trial(_frozen(spec, {"method": "FedRootAvg"}, TrialState.FAIL, error="x"))
    reason = "its space has 2 distinct points and every one has run"
    assert no_new_point(study, spec) == reason and counts(study, spec) == (0, 0, 0)

    wide = load_sweep(_sweep_file(tmp_path, TPE + "  train.lr_top: {low: 0.1, high: 1}\n", "wide"))
    study = optuna.create_study()
    study.add_trial(_frozen(wide, {"train.lr_top": 0.5}))
    again = _frozen(wide, {"train.lr_top": 0.5}, TrialState.PRUNED, duplicate_of=0)
    for _ in range(DUPLICATES_IN_A_ROW - 1):
        study.add_trial(again)
    assert no_new_point(study, wide) is None and counts(study, wide) == (2, 0, 0)
    study.add_trial(again)
    assert counts(study, wide) == (0, 0, 0)
    assert no_new_point(study, wide) == (
        f"the sampler's last {DUPLICATES_IN_A_ROW} draws were all points already run "
        "(a continuous space)"
    )


class Hung(BaseException):
    """Raised by the alarm: the sweep did not end."""


@contextlib.contextmanager
def deadline(seconds: int):
    def ring(signum, frame):
        raise Hung(f"still running after {seconds} s")

    previous = signal.signal(signal.SIGALRM, ring)
    signal.alarm(seconds)
    try:
        yield
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def test_a_tpe_sweep_over_a_one_point_space_runs_it_once_and_stops(
    tmp_path, synth_dir, cache_dir, store, capsys
):
    body = (
        _fixed(synth_dir, cache_dir)
        + "sampler: tpe\ntrials: 3\nspace:\n  method: {choices: [FedAvg]}\n"
    )
    path = _sweep_file(tmp_path, body, "onepoint")
    storage = f"sqlite:///{tmp_path}/optuna.db"
    argv = ["sweep", str(path), "--storage", storage, "--tracking-uri", store]
    with deadline(150):  # it used to draw the same point for ever
        assert main(argv) == 0
    out = capsys.readouterr().out
    stopped = "stopped after 1 of 3 trials: its space has 1 distinct point and every one has run"
    assert f"sweep onepoint: {stopped}" in out
    trials = optuna.load_study(study_name="onepoint", storage=storage).get_trials()
    assert [t.state for t in trials if "duplicate_of" not in t.user_attrs] == [TrialState.COMPLETE]
    assert len(trials) <= 2  # at most one draw of the old point before the rule ends it


# --------------------------------------------------------------------------- errors shown


def test_every_trial_error_is_shown_and_an_all_failed_sweep_exits_1(
    tmp_path, synth_dir, cache_dir, store, capsys
):
    """Trial 0 trains and then misses its objective (a metric runs may log: robots that
    dropped out); trial 1 fails before its run starts (more clients than scenes). Both
    errors reach the table and MLflow, the parent run ends FAILED, the exit status is 1."""
    body = _fixed(synth_dir, cache_dir) + "objective: {metric: round/missing_clients}\n"
    path = _sweep_file(tmp_path, body + "space:\n  data.clients: [2, 100]\n", "failing")
    argv = ["sweep", str(path), "--storage", f"sqlite:///{tmp_path}/optuna.db", "--tracking-uri"]
    assert main([*argv, store]) == 1
    captured = capsys.readouterr()
    assert "see the log above" not in captured.out
    table = captured.out[captured.out.index("\ntrial ") :]
    assert "objective.metric=round/missing_clients: this run did not log it" in table
    assert "data.clients=100: more clients than the" in table
    (line,) = captured.err.strip().splitlines()
    assert line.startswith("fedlgr: error: sweep failing: all 2 trials failed; trial 0: ")

    trials = optuna.load_study(study_name="failing", storage=argv[3]).get_trials()
    assert [t.state for t in trials] == [TrialState.FAIL] * 2
    (early,) = [t.number for t in trials if t.params == {"data.clients": 100}]
    client = mlflow.MlflowClient(store)
    runs = client.search_runs([client.get_experiment_by_name("sweep-failing").experiment_id])
    (parent,) = [r for r in runs if r.data.tags["fedlgr.kind"] == "sweep"]
    (child,) = [r for r in runs if r.data.tags["fedlgr.kind"] == "trial"]
    assert parent.info.status == "FAILED"
    assert child.info.status == "FINISHED"  # the run is whole; the trial had no value from it
    assert "this run did not log it" in child.data.tags["fedlgr.error"]
    assert "more clients than the" in parent.data.tags[f"trial.{early}.error"]
    # What the trained run logged is what the objective's check expects runs to log.
    config = fedlgr.shell.config.load_config(FAST, [f"data.path={synth_dir}", "data.clients=2"])
    logged = {m for m in child.data.metrics if not m.startswith(("forgetting/", "system/"))}
    assert logged <= run_metrics(config)


# --------------------------------------------------------------------------- the storage


@pytest.fixture
def tiny_sweep(tmp_path, synth_dir, cache_dir) -> Path:
    return _sweep_file(tmp_path, _fixed(synth_dir, cache_dir) + "space:\n  train.lr_top: [0.1]\n")


def _damaged_study(tmp_path: Path, tiny_sweep: Path) -> Path:
    """A real study's sqlite file with pages in the middle overwritten."""
    path = tmp_path / "damaged.db"
    optuna.create_study(study_name="x", storage=f"sqlite:///{path}").optimize(
        lambda t: t.suggest_float("x", 0, 1), n_trials=30
    )
    with path.open("r+b") as f:
        f.seek(4096 * 2)
        f.write(b"\xa5" * 4096 * 4)
    return path


@pytest.mark.parametrize("kind", ["folder", "text", "damaged", "under-a-file"])
def test_a_storage_that_cannot_hold_the_study_is_one_line(tmp_path, tiny_sweep, capsys, kind):
    if kind == "folder":
        (path := tmp_path / "optuna.db").mkdir()
    elif kind == "text":
        (path := tmp_path / "notes.db").write_text("my notes\n")
    elif kind == "damaged":
        path = _damaged_study(tmp_path, tiny_sweep)
    elif kind == "under-a-file":
        (tmp_path / "file").write_text("x")
        path = tmp_path / "file" / "sub" / "optuna.db"
    storage = f"sqlite:///{path}"
    store = f"sqlite:///{tmp_path}/mlflow.db"
    start = time.monotonic()
    code = main(["sweep", str(tiny_sweep), "--storage", storage, "--tracking-uri", store])
    assert code == 1 and time.monotonic() - start < 30
    line = _error_line(capsys)
    assert line.startswith(f"fedlgr: error: --storage {storage}: ")
    expected = {
        "folder": "is a folder, not an sqlite file",
        "text": "is not an sqlite database",
        "damaged": "the sqlite file is damaged",
        "under-a-file": "a file, not a folder",
    }[kind]
    assert expected in line


def test_a_storage_locked_by_another_process_is_one_line_within_seconds(
    tmp_path, tiny_sweep, capsys, monkeypatch
):
    monkeypatch.setattr(fedlgr.shell.sweep.storage, "LOCK_WAIT_S", 1.0)  # 5 s in real use
    path = tmp_path / "optuna.db"
    optuna.create_study(study_name="other", storage=f"sqlite:///{path}")
    holder = subprocess.Popen(
        [
            sys.executable,
            "-c",
            "import sqlite3, sys, time\n"
            f"db = sqlite3.connect({str(path)!r}, isolation_level=None)\n"
            "db.execute('BEGIN EXCLUSIVE'); print('locked', flush=True); time.sleep(120)",
        ],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        assert holder.stdout.readline().strip() == "locked"
        start = time.monotonic()
        store = f"sqlite:///{tmp_path}/mlflow.db"
        argv = ["sweep", str(tiny_sweep), "--storage", f"sqlite:///{path}", "--tracking-uri"]
        assert main([*argv, store]) == 1
        assert time.monotonic() - start < 20  # Optuna's own connections wait 60 s
    finally:
        holder.kill()
        holder.wait()
    line = _error_line(capsys)
    assert line.startswith(f"fedlgr: error: --storage sqlite:///{path}: the sqlite file is locked")
    with contextlib.closing(sqlite3.connect(path)) as db:  # nothing was written meanwhile
        assert db.execute("SELECT COUNT(*) FROM studies").fetchone() == (1,)


# --------------------------------------------------------------------------- the parent run


def test_the_best_figure_is_logged_once_however_many_workers_finish(
    tmp_path, synth_dir, cache_dir, store
):
    """A ``--workers 2`` helper that finds the study done leaves the parent run to the
    process that started it; that one, and a relaunch of the finished sweep, log the
    best figure once (the helper used to log it too: two points at step 0)."""
    body = _fixed(synth_dir, cache_dir) + "space:\n  train.lr_top: [0.1]\n"
    spec = load_sweep(_sweep_file(tmp_path, body, "best"))
    storage = f"sqlite:///{tmp_path}/optuna.db"
    study = optuna.create_study(study_name="best", storage=storage)
    dist = {"train.lr_top": CategoricalDistribution([0.1])}
    study.add_trial(create_trial(params={"train.lr_top": 0.1}, distributions=dist, value=0.7))

    quiet = lambda *a, **k: None  # noqa: E731
    helper = run_sweep(spec, storage=storage, tracking_uri=store, worker_id=1, echo=quiet)
    client = mlflow.MlflowClient(store)
    assert helper.done and client.get_run(helper.parent_run_id).info.status == "RUNNING"
    assert client.get_metric_history(helper.parent_run_id, "best/test/rmse") == []
    for _ in range(2):  # the launching worker, then the finished sweep launched again
        result = run_sweep(spec, storage=storage, tracking_uri=store, echo=quiet)
        assert result.parent_run_id == helper.parent_run_id and result.failure is None
    parent = client.get_run(result.parent_run_id)
    assert parent.info.status == "FINISHED" and parent.data.tags["best.trial"] == "0"
    history = client.get_metric_history(result.parent_run_id, "best/test/rmse")
    assert [(m.step, m.value) for m in history] == [(0, 0.7)]


def test_a_sweep_file_resolves_no_environment_variable(tmp_path, monkeypatch):
    """The config files' rule holds in sweep files: ``${oc.env:...}`` of a variable that
    is not FEDLGR_* is refused, its value never shown."""
    from fedlgr.errors import ConfigError
    from fedlgr.shell.sweep.spec import load_sweep

    monkeypatch.setenv("SWEEP_SECRET", "s3cr3t-value")
    path = tmp_path / "leak.yaml"
    path.write_text(
        "name: leak\nbase: conf/debug/tiny.yaml\ntrials: 1\n"
        "objective: {metric: test/rmse, direction: minimize}\n"
        "space:\n  train.lr_top: {choices: [0.1]}\n"
        "overrides: ['tracking.run_name=${oc.env:SWEEP_SECRET}']\n"
    )
    with pytest.raises(ConfigError) as refused:
        load_sweep(path)
    assert "s3cr3t-value" not in str(refused.value)
    assert str(path) in str(refused.value) and "oc.env" in str(refused.value)


ENV = {**os.environ, "PYTHONPATH": str(REPO)}


def _fedlgr(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    command = [sys.executable, "-m", "fedlgr", *args]
    return subprocess.run(command, cwd=cwd, env=ENV, capture_output=True, text=True)


def _one_error_line(done: subprocess.CompletedProcess) -> str:
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith("fedlgr: error: ")
    return line


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


def test_a_text_file_named_as_a_sweep_is_refused_without_its_text(tmp_path, capsys):
    """Found by issue 20's fourth fault sweep."""
    for text in ("API_KEY=sk-live-SECRET123\nDB_PASSWORD=hunter2\n", "_apt:*:20228:0:99999:7:::\n"):
        sweep = tmp_path / "sweep.yaml"
        sweep.write_text(text)
        assert main(["sweep", str(sweep), "--storage", f"sqlite:///{tmp_path}/o.db"]) == 1
        err = capsys.readouterr().err
        assert "SECRET" not in err and "hunter2" not in err and "20228" not in err
        assert f"fedlgr: error: {sweep}: " in err
