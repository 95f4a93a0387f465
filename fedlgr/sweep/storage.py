"""The study's Optuna storage: opening it and re-queueing trials whose worker died or was stopped.

A trial whose worker cannot finish it is set FAILED and a WAITING copy of it is queued by
Optuna's ``RetryHeartbeatStaleTrialCallback``, which keeps the trial's system attributes -
so GridSampler hands the copy the same grid point (``grid_id``) - and lists the trials it
retries in ``retry_history``. Only the worker whose FAIL reached the storage queues the
copy, so two workers that notice the same dead trial queue it once.
"""

from __future__ import annotations

import copy
import hashlib
import warnings
from typing import Any

from fedlgr.errors import FedlgrError
from fedlgr.sweep.spec import SweepSpec


class RetryStaleTrial:
    """Optuna's ``RetryHeartbeatStaleTrialCallback`` for a trial whose worker died, which
    also ends that trial's MLflow run KILLED (its process can no longer do it) - a FINISHED
    one too: a worker killed between ending the run and telling the study leaves a run the
    study never counted, and the retry makes the point's result."""

    def __init__(self) -> None:
        from optuna.storages import RetryHeartbeatStaleTrialCallback

        # The copy keeps the rounds the trial reported: a retry that resumes its run from
        # a checkpoint reports the later rounds only, and the pruner sees them all.
        self.retry = RetryHeartbeatStaleTrialCallback(max_retry=3, inherit_intermediate_values=True)
        self.client = None  # set by the Worker once MLflow is open
        self.experiment_id: str | None = None

    def __call__(self, study, trial) -> None:
        self.retry(study, trial)
        if self.client is None:
            return
        runs = self.client.search_runs(
            [self.experiment_id],
            f"tags.study = '{study.study_name}' and tags.trial = '{trial.number}'",
        )
        for run in runs:
            if run.info.status in ("RUNNING", "FINISHED"):
                self.client.set_terminated(run.info.run_id, "KILLED")


def retried(study, number: int) -> bool:
    """Whether a copy of trial ``number`` has been queued (in any state since)."""
    return any(number in t.system_attrs.get("retry_history", []) for t in study.get_trials(False))


def retry_failed(study, retry: RetryStaleTrial, trial_id: int) -> bool:
    """Queue a copy of the FAILED trial ``trial_id`` unless one exists; True if queued."""
    trial = copy.deepcopy(study._storage.get_trial(trial_id))
    if trial.state.name != "FAIL" or retried(study, trial.number):
        return False
    retry(study, trial)
    return True


def fail_and_retry(study, retry: RetryStaleTrial, trial_id: int) -> bool:
    """Set the RUNNING trial ``trial_id`` FAILED and queue a copy of it - only when this
    call's FAIL reached the storage (another worker, or Optuna itself, may have finished
    the trial first). True if a copy was queued."""
    import optuna
    from optuna.trial import TrialState

    try:
        if not study._storage.set_trial_state_values(trial_id, TrialState.FAIL):
            return False
    except optuna.exceptions.UpdateFinishedTrialError:
        return False
    return retry_failed(study, retry, trial_id)


def open_study(
    spec: SweepSpec,
    storage: str,
    study_name: str | None = None,
    worker: int = 0,
    settings_changed: bool = False,
) -> tuple[Any, RetryStaleTrial]:
    """Create or load the study (``load_if_exists``) with heartbeats and retry of dead
    workers' trials; returns the study and its :class:`RetryStaleTrial`.

    The first use of a fresh sqlite file creates Optuna's tables, its schema version and
    the study; two processes doing that at once make one fail (``table ... already
    exists``, a UNIQUE constraint on the version or the study name), so it happens under
    the file lock MLflow's sqlite stores are opened under (``<file>.lock``). A server
    database (PostgreSQL, MySQL) is not locked."""
    from fedlgr.tracking.mlflow_run import store_lock

    with store_lock(storage):
        return _open_study(spec, storage, study_name, worker, settings_changed)


def _open_study(
    spec: SweepSpec, storage: str, study_name: str | None, worker: int, settings_changed: bool
):
    import optuna
    from optuna.storages import RDBStorage

    optuna.logging.set_verbosity(optuna.logging.WARNING)  # no INFO line per study/trial
    try:
        with warnings.catch_warnings():
            # Heartbeats and their retry callback are "experimental" since Optuna 2.8/2.9.
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            retry = RetryStaleTrial()
            rdb = RDBStorage(
                storage,
                heartbeat_interval=spec.heartbeat_s,
                grace_period=2 * spec.heartbeat_s,
                heartbeat_stale_trial_callback=retry,
                engine_kwargs=(
                    {"connect_args": {"timeout": 60}} if storage.startswith("sqlite") else {}
                ),
            )
    except Exception as err:
        raise FedlgrError(f"--storage {storage}: cannot open the study storage: {err}") from err
    if spec.sampler == "grid":
        sampler = optuna.samplers.GridSampler(spec.grid, seed=spec.seed)
    else:
        # Parallel workers with one seed would propose the same first points.
        sampler = optuna.samplers.TPESampler(seed=spec.seed * 1000 + worker)
    pruner = (
        optuna.pruners.MedianPruner(n_startup_trials=2, n_warmup_steps=spec.prune_warmup_rounds)
        if spec.pruner == "median"
        else optuna.pruners.NopPruner()
    )
    study = optuna.create_study(
        study_name=study_name or spec.name,
        storage=rdb,
        sampler=sampler,
        pruner=pruner,
        direction=spec.direction,
        load_if_exists=True,
    )
    check_settings(study, spec, storage, settings_changed)
    return study, retry


SETTINGS_ATTR = "fedlgr.settings"


def sweep_settings(spec: SweepSpec) -> dict[str, Any]:
    """What a study's trials were run with: the sweep file (its SHA-256) and every
    ``key=value`` override (the file's and the command line's, in order)."""
    digest = hashlib.sha256(spec.path.read_bytes()).hexdigest() if spec.path else ""
    return {"file": str(spec.path or ""), "sha256": digest, "overrides": list(spec.overrides)}


def check_settings(study, spec: SweepSpec, storage: str, changed_ok: bool = False) -> None:
    """Record the settings with a new study; refuse to go on with a study that was started
    with other ones: its finished trials would be taken for trials of these settings (a
    relaunch with another ``data.path`` would train nothing and report the old table).
    Settings that change no number (``tracking.*``, ``data.cache_dir``: those a resumed run
    may change) and how trials run (threads, workers) are not compared. ``changed_ok``
    (``fedlgr sweep --settings-changed``): go on, e.g. with a dataset that moved, and
    record the new settings."""
    now = sweep_settings(spec)
    then = study.user_attrs.get(SETTINGS_ATTR)
    if then is None or changed_ok:  # new (or from before studies recorded settings)
        study.set_user_attr(SETTINGS_ATTR, now)
        return
    differences = []
    if then.get("sha256") != now["sha256"]:
        differences.append(f"the sweep file {now['file']} changed since the study began")
    before, after = _as_dict(then.get("overrides", [])), _as_dict(now["overrides"])
    for key in sorted(set(before) | set(after)):
        if before.get(key) != after.get(key):
            differences.append(
                f"{key} (study: {before.get(key, 'not set')}, now: {after.get(key, 'not set')})"
            )
    if differences:
        raise FedlgrError(
            f"study {study.study_name!r} in {storage} was run with other settings: "
            f"{'; '.join(differences)}. Its trials would count as trials of these settings: "
            "start a new study with --study NAME, or relaunch with the study's own settings"
        )


def _as_dict(overrides: list[str]) -> dict[str, str]:
    """``key=value`` overrides as {key: value}, the last one of a key winning; settings
    that change no number left out, and how trials run (``--workers`` sets the threads per
    trial: a relaunch with other workers or on another machine goes on with the study)."""
    from fedlgr.tracking.checkpoint import MACHINE_CHOSEN, SAFE_KEYS

    pairs = dict(o.split("=", 1) for o in overrides)
    return {k: v for k, v in pairs.items() if k not in SAFE_KEYS and k not in MACHINE_CHOSEN}
