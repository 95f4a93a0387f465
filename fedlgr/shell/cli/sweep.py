"""``fedlgr sweep SWEEP [key=value ...]``: run or resume an Optuna sweep."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from fedlgr.errors import FedlgrError
from fedlgr.shell.machine import available_cores

MAX_STUDY_NAME = 512  # optuna.storages._rdb.models.MAX_INDEXED_STRING_LENGTH


def sweep(args: argparse.Namespace) -> int:
    from fedlgr.shell.signals import terminate_as_interrupt

    with terminate_as_interrupt():  # SIGTERM (timeout, Slurm, docker stop) is a Ctrl-C
        return _sweep(args)


def _sweep(args: argparse.Namespace) -> int:
    from fedlgr.shell.tracking.server import check_tracking, masked_echo

    overrides = list(args.overrides)
    cores = os.cpu_count() or 1
    if not 1 <= args.workers <= 4 * cores:
        raise FedlgrError(
            f"--workers {args.workers}: from 1 to {4 * cores} (4 x this machine's {cores} "
            "cores); each worker is a process that trains one trial at a time"
        )
    if args.study is not None and not args.study.strip():  # '' fell back to the sweep's name
        raise FedlgrError(f"--study {args.study!r}: empty; give a name, or leave it out")
    if args.study is not None and not args.study.isprintable():  # a newline was kept (u56)
        raise FedlgrError(f"--study {args.study!r}: holds a control character")
    if args.study is not None and len(args.study) > MAX_STUDY_NAME:
        raise FedlgrError(f"--study: {len(args.study)} characters, at most {MAX_STUDY_NAME}")
    check_tracking(args.tracking_uri, overrides)  # before loading Optuna and MLflow
    from fedlgr.shell.sweep import load_sweep, run_sweep
    from fedlgr.shell.sweep.storage import check_storage

    optuna_file = check_storage(args.storage, make=False)  # before the configs load torch
    _not_the_tracking_store(optuna_file, args, overrides)

    if args.workers > 1 and not any(o.startswith("runtime.threads=") for o in overrides):
        # Share this machine's cores between the workers instead of oversubscribing them.
        overrides.append(f"runtime.threads={max(1, available_cores() // args.workers)}")
    spec = load_sweep(args.sweep, overrides)
    if args.heartbeat is not None:
        from dataclasses import replace

        from fedlgr.shell.sweep.spec import MAX_HEARTBEAT_S

        if not 1 <= args.heartbeat <= MAX_HEARTBEAT_S:
            raise FedlgrError(f"--heartbeat {args.heartbeat}: from 1 to {MAX_HEARTBEAT_S} s")

        spec = replace(spec, heartbeat_s=args.heartbeat)
    result = run_sweep(
        spec,
        storage=args.storage,
        study_name=args.study,
        workers=args.workers,
        tracking_uri=args.tracking_uri,
        cli_overrides=overrides,
        worker_id=args.worker_id,
        settings_changed=args.settings_changed,
        # A database's password is not printed (a helper worker's lines come through here).
        echo=masked_echo(print, args.storage, args.tracking_uri, *_tracking_uris(overrides)),
    )
    if result.failure:  # the table above shows each trial's error
        raise FedlgrError(f"sweep {spec.name}: {result.failure}")
    return 0 if result.done else 1


def _tracking_uris(overrides: list[str]) -> list[str]:
    given = [o.split("=", 1)[1] for o in overrides if o.startswith("tracking.uri=")]
    return [*given, os.environ.get("MLFLOW_TRACKING_URI", "")]


def _not_the_tracking_store(optuna_file: Path | None, args, overrides: list[str]) -> None:
    """One sqlite file for the study and the MLflow runs failed after 11 s with Alembic's
    "No such revision or branch" and left both sets of tables in it (the tenth fault
    sweep, d167): refused first."""
    from fedlgr.shell.tracking.server import given_uri, sqlite_path

    uri = given_uri(args.tracking_uri, overrides)
    if optuna_file is None or not uri.startswith("sqlite:///"):
        return
    if sqlite_path(uri).resolve() == optuna_file.resolve():  # by a link, or .. (e81, e84)
        raise FedlgrError(
            f"--storage {args.storage}: the tracking store's file too; Optuna's study and "
            "MLflow's runs each need a database of their own (e.g. --storage "
            f"sqlite:///{optuna_file.with_name('optuna.db')})"
        )
