"""A study remembers the settings its trials ran with and refuses others (issue 13), and
a space its trials cannot take (issue 37)."""

from __future__ import annotations

import subprocess

import pytest

from fedlgr.errors import ConfigError, FedlgrError
from fedlgr.shell.sweep.spec import load_sweep
from fedlgr.shell.sweep.storage import SETTINGS_ATTR, open_study
from fedlgr.shell.sweep.study import run_sweep
from tests.support.processes import child_env
from tests.support.runs import FAST
from tests.support.sweeps import child_runs, sweep_command, trials_by_state


@pytest.mark.slow
def test_a_sweep_relaunched_with_other_overrides_is_refused(synth_dir, synth_copy, tmp_path):
    storage = f"sqlite:///{tmp_path}/optuna.db"
    first = load_sweep("ewc", [f"data.path={synth_dir}", "train.epochs=1"])
    study, _ = open_study(first, storage)
    recorded = study.user_attrs[SETTINGS_ATTR]
    assert recorded["overrides"][-2:] == [f"data.path={synth_dir}", "train.epochs=1"]
    assert len(recorded["sha256"]) == 64 and recorded["file"].endswith("ewc.yaml")

    again, _ = open_study(load_sweep("ewc", [f"data.path={synth_dir}", "train.epochs=1"]), storage)
    assert again.study_name == study.study_name  # the same settings: resumed

    other = load_sweep("ewc", [f"data.path={synth_copy}", "train.lr_top=0.002"])
    with pytest.raises(FedlgrError) as refused:
        run_sweep(other, storage=storage, echo=lambda *a, **k: None)
    message = str(refused.value)
    assert f"data.path (study: {synth_dir}, now: {synth_copy})" in message
    assert "train.lr_top (study: not set, now: 0.002)" in message
    assert "train.epochs (study: 1, now: not set)" in message
    assert "--study NAME" in message

    # How trials run is not what they compute: other threads (--workers) go on.
    threads = load_sweep("ewc", [f"data.path={synth_dir}", "train.epochs=1", "runtime.threads=1"])
    assert open_study(threads, storage)[0].study_name == "ewc"
    # Changed on purpose (fedlgr sweep --settings-changed): goes on, the new ones recorded.
    moved, _ = open_study(other, storage, settings_changed=True)
    assert moved.user_attrs[SETTINGS_ATTR]["overrides"][-1] == "train.lr_top=0.002"
    assert open_study(other, storage)[0].study_name == "ewc"

    # Another study name is another study: it starts.
    study2, _ = open_study(load_sweep("ewc", [f"data.path={synth_dir}"]), storage, "ewc-2")
    assert study2.user_attrs[SETTINGS_ATTR]["overrides"][-1] == f"data.path={synth_dir}"


@pytest.mark.slow
def test_a_changed_sweep_file_is_refused(synth_dir, tmp_path):
    source = load_sweep("ewc").path.read_text()
    path = tmp_path / "mine.yaml"
    path.write_text(source)
    storage = f"sqlite:///{tmp_path}/optuna.db"
    open_study(load_sweep(path, [f"data.path={synth_dir}"]), storage)
    changed = source.replace("continual.ewc.lambda_: [", "continual.ewc.lambda_: [0.5, ")
    assert changed != source  # the grid line is where the test expects it
    path.write_text(changed)
    with pytest.raises(FedlgrError, match=r"the sweep file .*mine\.yaml changed"):
        open_study(load_sweep(path, [f"data.path={synth_dir}"]), storage)


def _quiet(*args, **kwargs) -> None:
    """A sweep's echo that prints nothing."""


@pytest.mark.slow
def test_a_grid_given_another_value_is_refused_before_any_trial_runs(
    tmp_path, synth_dir, cache_dir
):
    """Issue 37, Deliver 7: a finished 3-value grid whose sweep file gained a 4th value,
    relaunched with --workers 2 (and --settings-changed), failed every trial at once with
    Optuna's "CategoricalDistribution does not support dynamic value space" and asked for
    new ones for ever (7,000 FAILED trials in minutes). Optuna cannot change a
    parameter's values inside a study: the relaunch is one line naming the study, the
    setting and both lists, before any trial; a new study (--study) takes the new grid."""
    path = tmp_path / "grow.yaml"
    path.write_text(
        f"base: {FAST}\n"
        f"overrides: [data.path={synth_dir}, data.cache_dir={cache_dir}, runtime.threads=1]\n"
        "space:\n  train.lr_top: [0.001, 0.01, 0.1]\n"
    )
    storage, store = f"sqlite:///{tmp_path}/optuna.db", f"sqlite:///{tmp_path}/mlflow.db"
    assert run_sweep(load_sweep(path), storage=storage, tracking_uri=store, echo=_quiet).done
    path.write_text(path.read_text().replace("0.1]", "0.1, 1.0]"))

    command = sweep_command(path, storage, store, "--workers", "2", "--settings-changed")
    done = subprocess.run(command, env=child_env(), capture_output=True, text=True, timeout=240)
    assert done.returncode == 1 and "Traceback" not in done.stderr, done.stderr[-3000:]
    (line,) = done.stderr.strip().splitlines()
    assert line.startswith(
        f"fedlgr: error: study 'grow' in {storage}: space.train.lr_top changed since its "
        "trials ran: [0.001, 0.01, 0.1] -> [0.001, 0.01, 0.1, 1.0]; "
    )
    assert "start a new study with --study NAME" in line
    assert list(trials_by_state(storage, "grow")) == ["COMPLETE"]
    assert len(trials_by_state(storage, "grow")["COMPLETE"]) == 3  # no trial ran
    _, (parent,), children = child_runs(store, "sweep-grow")
    assert parent.info.status == "FINISHED" and len(children) == 3
    # Without --settings-changed the space is what the line names too.
    with pytest.raises(ConfigError, match=r"space\.train\.lr_top changed since its trials ran"):
        open_study(load_sweep(path), storage)

    # A new study of the new grid opens (running it is any sweep's business)
    study, _ = open_study(load_sweep(path), storage, "grow-2")
    assert study.study_name == "grow-2" and not study.trials


def test_a_range_may_move_but_not_change_kind(tmp_path, synth_dir):
    """Optuna lets a range's ends move inside a study (on purpose: --settings-changed) but
    not its kind: log to linear is refused in one line naming both."""
    path = tmp_path / "range.yaml"
    space = "space:\n  train.lr_top: {low: 0.001, high: %s, log: %s}\ntrials: 4\n"
    path.write_text(f"base: {FAST}\n" + space % (0.1, "true"))
    storage = f"sqlite:///{tmp_path}/optuna.db"
    spec = load_sweep(path, [f"data.path={synth_dir}"])
    study, _ = open_study(spec, storage)
    trial = study.ask()
    spec.params[0].suggest(trial)
    study.tell(trial, 1.0)

    path.write_text(f"base: {FAST}\n" + space % (0.5, "true"))
    moved = load_sweep(path, [f"data.path={synth_dir}"])
    assert open_study(moved, storage, settings_changed=True)[0].study_name == "range"
    path.write_text(f"base: {FAST}\n" + space % (0.5, "false"))
    linear = load_sweep(path, [f"data.path={synth_dir}"])
    with pytest.raises(ConfigError) as refused:
        open_study(linear, storage, settings_changed=True)
    assert (
        "space.train.lr_top changed since its trials ran: {low: 0.001, high: 0.1, log: true} "
        "-> {low: 0.001, high: 0.5}; "
    ) in str(refused.value)
