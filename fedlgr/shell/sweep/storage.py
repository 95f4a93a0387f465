"""The study's Optuna storage: opening it, and re-queueing trials whose worker died or was stopped
(Optuna's retry callback, so that GridSampler hands the copy the same grid point)."""

from __future__ import annotations

import contextlib
import copy
import hashlib
import os
import sqlite3
import warnings
from pathlib import Path
from typing import Any

from fedlgr.errors import FedlgrError, exception_chain, first_line
from fedlgr.shell.checks.paths import not_a_file
from fedlgr.shell.checks.stores import CONNECT_TIMEOUT_S, check_database
from fedlgr.shell.config.export import MACHINE_CHOSEN, SAFE_KEYS
from fedlgr.shell.sweep.checks import check_space
from fedlgr.shell.sweep.space import SweepSpec
from fedlgr.shell.sweep.trials import retried
from fedlgr.shell.tracking.store import StoreError, open_lock_file, store_lock
from fedlgr.shell.tracking.uri import (
    in_memory_sqlite,
    mask_password,
    masked_text,
    server_database,
    sqlite_file,
)

DEFAULT_STORAGE = "sqlite:///optuna.db"


class RetryStaleTrial:
    """Optuna's ``RetryHeartbeatStaleTrialCallback`` that also ends the dead worker's MLflow run
    KILLED, a FINISHED one too: its worker died before the study counted it."""

    def __init__(self) -> None:
        # lazy: optuna (~1 s), not needed to check a sweep file
        from optuna.storages import RetryHeartbeatStaleTrialCallback

        # keeps the reported rounds: a retry resumed from a checkpoint reports only the later ones
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


def retry_failed(study, retry: RetryStaleTrial, trial_id: int) -> bool:
    """Queue a copy of the FAILED trial ``trial_id`` unless one exists (in any state since); True
    if queued."""
    trial = copy.deepcopy(study._storage.get_trial(trial_id))
    if trial.state.name != "FAIL" or trial.number in retried(study.get_trials(deepcopy=False)):
        return False
    retry(study, trial)
    return True


def fail_and_retry(study, retry: RetryStaleTrial, trial_id: int) -> bool:
    """Set the RUNNING trial ``trial_id`` FAILED and queue a copy, only if this call's FAIL reached
    the storage (another worker may have finished the trial first); True if queued."""
    # lazy: optuna (~1 s), not needed to check a sweep file
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
    """Create or load the study with heartbeats and retry of dead workers' trials, under
    :func:`store_lock`: two processes creating Optuna's tables at once make one fail. A storage that
    cannot hold the study is one line (:func:`check_storage`)."""
    path = check_storage(storage)
    with store_lock(storage):
        if path is not None:
            _wait_for_writes(path, storage)
        return _open_study(spec, storage, study_name, worker, settings_changed)


SQLITE_HEADER = b"SQLite format 3\x00"
LOCK_WAIT_S = 5.0  # another process's write that takes longer than this is not a sweep's


def check_storage(storage: str, make: bool = True) -> Path | None:
    """Refuse in one line (password masked) a storage that cannot hold a study, before anything
    waits on it; ``make``: create the sqlite file's folder and lock file. Its sqlite file."""
    from sqlalchemy.exc import ArgumentError  # lazy: sqlalchemy (~1 s), for a storage only

    def fail(problem: str) -> FedlgrError:
        return FedlgrError(f"--storage {mask_password(storage)}: {problem}")

    if server_database(storage):
        check_database(storage, "--storage")
        return None

    try:
        path = sqlite_file(storage)
    except ArgumentError as err:
        raise fail("not a database URL (e.g. sqlite:///optuna.db or postgresql://HOST/DB)") from err
    if in_memory_sqlite(storage):
        raise fail(
            "an in-memory sqlite database keeps nothing (the study is lost when the sweep "
            "ends, and no other worker can join it): name a file, e.g. sqlite:///optuna.db"
        )
    if path is None:
        return None
    if path.is_dir():
        raise fail(f"{path} is a folder, not an sqlite file")
    # refused at once: a dangling link would fail after a minute, a device get /dev/null.lock
    if why := not_a_file(path):
        raise fail(f"{path} is {why}")
    if not make:
        folder = next(p for p in path.absolute().parents if p.exists())
        if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
            what = "not a folder" if not folder.is_dir() else "not writable"
            raise fail(f"cannot create {path}: {folder} is {what}")
        _check_header(path, fail)
        _wait_for_writes(path, storage)
        return path
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise fail(f"cannot create the folder {path.parent}: {err.strerror or err}") from err
    try:  # the lock file store_lock keeps beside it: the folder takes new files
        os.close(open_lock_file(Path(f"{path}.lock"), f"--storage {storage}"))
    except StoreError as err:
        raise fail(str(err).partition(": ")[2]) from None
    _check_header(path, fail)
    return path


def _check_header(path: Path, fail) -> None:
    """A file that does not begin as sqlite files do is some other file."""
    try:
        if path.is_file() and path.stat().st_size:
            with path.open("rb") as f:
                head = f.read(len(SQLITE_HEADER))
            if head != SQLITE_HEADER:
                raise fail(f"{path} is not an sqlite database (another kind of file?)")
    except OSError as err:
        raise fail(f"cannot read {path}: {err.strerror or err}") from err


def _wait_for_writes(path: Path, storage: str) -> None:
    """Wait up to :data:`LOCK_WAIT_S` for another process's write to the sqlite file: one that holds
    it longer is named, instead of the minute Optuna's connections wait."""
    if not (path.is_file() and path.stat().st_size):
        return
    try:
        with contextlib.closing(sqlite3.connect(path, timeout=LOCK_WAIT_S)) as db:
            db.isolation_level = None
            db.execute("BEGIN IMMEDIATE")
            db.execute("ROLLBACK")
    except sqlite3.Error as err:
        raise storage_error(storage, err) from err


def storage_error(storage: str, err: BaseException) -> FedlgrError | None:
    """One line for an error of the study's storage (Optuna's ``StorageInternalError``,
    SQLAlchemy's and sqlite's errors); None for any other error."""
    # lazy: optuna and sqlalchemy (~1 s), not needed to check a sweep file
    import optuna
    from sqlalchemy.exc import SQLAlchemyError

    internal = optuna.exceptions.StorageInternalError
    storage_kinds = internal | SQLAlchemyError | sqlite3.Error
    # Optuna 4's _optimize raises an UnboundLocalError over a lost server's error: that one counts
    err = next((e for e in exception_chain(err) if isinstance(e, storage_kinds)), None)
    if err is None:
        return None
    cause = err.__cause__ if isinstance(err, internal) else err
    cause = getattr(cause, "orig", None) or cause  # SQLAlchemy wraps the driver's error
    text = masked_text(first_line(cause), storage)
    known = {
        "database is locked": "the sqlite file is locked by another process (one that "
        "holds it for long: another program, or a sweep stopped with Ctrl-Z?)",
        "file is not a database": "not an sqlite database (another kind of file, or damaged)",
        "database disk image is malformed": "the sqlite file is damaged (malformed); "
        "move it away to start a new study",
        "unable to open database file": "cannot open the sqlite file (a folder, or a folder "
        "that cannot be written in?)",
        "attempt to write a readonly database": "the sqlite file is read-only",
        "database or disk is full": "the disk is full",
    }
    problem = next((v for k, v in known.items() if k in text), None)
    if problem is None:  # a database server gone, a lost connection, ...
        problem = (
            f"{text} - run the same command again once the storage answers: finished "
            "trials are kept, and a trial that was running is retried"
        )
    return FedlgrError(f"--storage {mask_password(storage)}: {problem}")


def _open_study(
    spec: SweepSpec, storage: str, study_name: str | None, worker: int, settings_changed: bool
):
    # lazy: optuna (~1 s), not needed to check a sweep file
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
                engine_kwargs=_engine_kwargs(storage),
            )
    except Exception as err:
        problem = storage_error(storage, err)
        if problem is None:
            text = masked_text(first_line(err), storage)
            problem = FedlgrError(
                f"--storage {mask_password(storage)}: cannot open the study storage: {text}"
            )
        raise problem from err
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
    try:
        study = optuna.create_study(
            study_name=study_name or spec.name,
            storage=rdb,
            sampler=sampler,
            pruner=pruner,
            direction=spec.direction,
            load_if_exists=True,
        )
        # the space first: changed values cannot go on even with --settings-changed
        check_space(study, spec, mask_password(storage))
        check_settings(study, spec, storage, settings_changed)
    except Exception as err:
        problem = storage_error(storage, err)
        if problem is None:
            raise
        raise problem from err
    return study, retry


def _engine_kwargs(storage: str) -> dict[str, Any]:
    """SQLAlchemy's engine settings for the storage: sqlite waits a minute for another worker's
    write; a silent database server is given up on, not left to the network's timeout."""
    if storage.startswith("sqlite"):
        return {"connect_args": {"timeout": 60}}
    if storage.lower().startswith(("postgresql:", "postgresql+")):
        return {"connect_args": {"connect_timeout": CONNECT_TIMEOUT_S}}
    return {}


SETTINGS_ATTR = "fedlgr.settings"


def check_settings(study, spec: SweepSpec, storage: str, changed_ok: bool = False) -> None:
    """Record the settings with a new study - the sweep file (its SHA-256) and every ``key=value``
    override, the file's and the command line's, in order; refuse one started with other settings,
    as its trials would count for these. ``changed_ok`` (``--settings-changed``): record the new."""
    digest = hashlib.sha256(spec.path.read_bytes()).hexdigest() if spec.path else ""
    now = {"file": str(spec.path or ""), "sha256": digest, "overrides": list(spec.overrides)}
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
            f"study {study.study_name!r} in {mask_password(storage)} was run with other settings: "
            f"{'; '.join(differences)}. Its trials would count as trials of these settings: "
            "start a new study with --study NAME, or relaunch with the study's own settings"
        )


def _as_dict(overrides: list[str]) -> dict[str, str]:
    """``key=value`` overrides as {key: value}, the last of a key winning, without the settings that
    change no number (``tracking.*``, ``data.cache_dir``) or how trials run (threads, workers)."""
    pairs = dict(o.split("=", 1) for o in overrides)
    return {
        k: v
        for k, v in pairs.items()
        if k not in SAFE_KEYS and k not in MACHINE_CHOSEN and not k.startswith("tracking.")
    }
