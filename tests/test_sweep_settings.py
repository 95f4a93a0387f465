"""A study remembers the settings its trials ran with and refuses others (issue 13)."""

from __future__ import annotations

import pytest

from fedlgr.errors import FedlgrError
from fedlgr.shell.sweep.spec import load_sweep
from fedlgr.shell.sweep.storage import SETTINGS_ATTR, open_study
from fedlgr.shell.sweep.study import run_sweep


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

    other = load_sweep("ewc", [f"data.path={synth_copy}", "seed=3"])
    with pytest.raises(FedlgrError) as refused:
        run_sweep(other, storage=storage, echo=lambda *a, **k: None)
    message = str(refused.value)
    assert f"data.path (study: {synth_dir}, now: {synth_copy})" in message
    assert "seed (study: not set, now: 3)" in message
    assert "train.epochs (study: 1, now: not set)" in message
    assert "--study NAME" in message

    # How trials run is not what they compute: other threads (--workers) go on.
    threads = load_sweep("ewc", [f"data.path={synth_dir}", "train.epochs=1", "runtime.threads=1"])
    assert open_study(threads, storage)[0].study_name == "ewc"
    # Changed on purpose (fedlgr sweep --settings-changed): goes on, the new ones recorded.
    moved, _ = open_study(other, storage, settings_changed=True)
    assert moved.user_attrs[SETTINGS_ATTR]["overrides"][-1] == "seed=3"
    assert open_study(other, storage)[0].study_name == "ewc"

    # Another study name is another study: it starts.
    study2, _ = open_study(load_sweep("ewc", [f"data.path={synth_dir}"]), storage, "ewc-2")
    assert study2.user_attrs[SETTINGS_ATTR]["overrides"][-1] == f"data.path={synth_dir}"


def test_a_changed_sweep_file_is_refused(synth_dir, tmp_path):
    source = load_sweep("ewc").path.read_text()
    path = tmp_path / "mine.yaml"
    path.write_text(source)
    storage = f"sqlite:///{tmp_path}/optuna.db"
    open_study(load_sweep(path, [f"data.path={synth_dir}"]), storage)
    path.write_text(source.replace("[100, 1000,", "[10, 1000,"))
    with pytest.raises(FedlgrError, match=r"the sweep file .*mine\.yaml changed"):
        open_study(load_sweep(path, [f"data.path={synth_dir}"]), storage)
