"""Sweeps under faults, on real sqlite storages and real processes: a trial left unborn by a
kill, Ctrl-C and SIGTERM, bad sweep files and data, two sweeps started at once."""

from __future__ import annotations

import sqlite3
from datetime import datetime, timedelta

from optuna.trial import TrialState

from fedlgr.sweep import load_sweep, run_sweep
from fedlgr.sweep.storage import open_study

from .test_sweep import point, trials_by_state, write_sweep


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
