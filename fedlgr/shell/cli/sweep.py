"""``fedlgr sweep SWEEP [key=value ...]``: run or resume an Optuna sweep."""

from __future__ import annotations

import argparse
import os
from dataclasses import replace
from pathlib import Path

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.stores import check_tracking
from fedlgr.shell.cli.parser import Verbs
from fedlgr.shell.config import SWEEPS_DIR
from fedlgr.shell.machine import available_cores
from fedlgr.shell.signals import terminate_as_interrupt
from fedlgr.shell.sweep import load_sweep, run_sweep
from fedlgr.shell.sweep.spec import MAX_HEARTBEAT_S
from fedlgr.shell.sweep.storage import check_storage
from fedlgr.shell.tracking.uri import given_uri, masked_echo, sqlite_file

MAX_STUDY_NAME = 512  # optuna.storages._rdb.models.MAX_INDEXED_STRING_LENGTH


def add_parser(verbs: Verbs) -> None:
    parser = verbs.add_parser(
        "sweep",
        epilog=_sweep_epilog(),
        help="run or resume an Optuna sweep (grid or TPE) of experiments",
        description="Run the trials of SWEEP (a file in sweeps/, e.g. sweeps/ewc.yaml or just "
        "ewc) as an Optuna study, each trial an experiment tracked in MLflow under one parent "
        "run. Launching it again resumes the study; --workers N (or launches elsewhere on the "
        "same --storage) work on it in parallel. Overrides apply to every trial, e.g. "
        "data.path=/path/to/manners-db.",
    )
    parser.add_argument("sweep", help="sweep file or name (the shipped ones are listed below)")
    parser.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides")
    parser.add_argument(
        "--storage",
        default="sqlite:///optuna.db",
        help="Optuna RDB storage URL (default: %(default)s; a PostgreSQL/MySQL URL for several "
        "machines)",
    )
    parser.add_argument("--study", help="study name (default: the sweep's name)")
    parser.add_argument(
        "--settings-changed",
        action="store_true",
        help="go on with a study started with other settings (the sweep file or overrides, "
        "e.g. a dataset that moved); its finished trials count as they are. A space whose "
        "values changed needs a new study (--study)",
    )
    parser.add_argument("--workers", type=int, default=1, help="processes on this machine")
    parser.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)",
    )
    parser.add_argument(
        "--heartbeat",
        type=int,
        default=None,
        help="seconds between a worker's heartbeats; a trial silent for two is retried "
        "(default: the sweep file's heartbeat_s)",
    )
    parser.add_argument("--worker-id", type=int, default=0, help=argparse.SUPPRESS)
    parser.set_defaults(run=sweep)


def shipped_sweeps() -> list[tuple[str, str]]:
    """``(name, what it sweeps)`` for each YAML file in ``sweeps/`` (the checkout's or the
    installed package's): its ``description:``, else its header comment's first line if
    short. Plain text reading, no YAML parser: ``fedlgr --help`` builds this too."""
    listing = []
    for path in sorted(SWEEPS_DIR.glob("*.yaml")):
        lines = path.read_text(encoding="utf-8").splitlines()
        described = [ln.split(":", 1)[1].strip() for ln in lines if ln.startswith("description:")]
        header = lines[0].lstrip("# ").strip() if lines and lines[0].startswith("#") else ""
        text = (described or [""])[0].strip("\"'") or (header if len(header) <= 72 else "")
        listing.append((path.stem, text))
    return listing


def _sweep_epilog() -> str:
    listing = shipped_sweeps()
    if not listing:
        return ""
    width = max(len(name) for name, _ in listing)
    lines = [f"  {name.ljust(width)}  {text}".rstrip() for name, text in listing]
    return f"shipped sweeps (in {SWEEPS_DIR}):\n" + "\n".join(lines)


def sweep(args: argparse.Namespace) -> int:
    with terminate_as_interrupt():  # SIGTERM (timeout, Slurm, docker stop) is a Ctrl-C
        return _sweep(args)


def _sweep(args: argparse.Namespace) -> int:
    overrides = list(args.overrides)
    _check_workers_and_study(args)
    check_tracking(args.tracking_uri, overrides)  # before loading Optuna and MLflow
    optuna_file = check_storage(args.storage, make=False)  # before the configs load torch
    _not_the_tracking_store(optuna_file, args, overrides)

    if args.workers > 1 and not any(o.startswith("runtime.threads=") for o in overrides):
        # Share this machine's cores between the workers instead of oversubscribing them.
        overrides.append(f"runtime.threads={max(1, available_cores() // args.workers)}")
    spec = load_sweep(args.sweep, overrides)
    if args.heartbeat is not None:
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


def _check_workers_and_study(args: argparse.Namespace) -> None:
    """``--workers`` within this machine's reach, and ``--study`` a name Optuna can keep."""
    cores = os.cpu_count() or 1
    if not 1 <= args.workers <= 4 * cores:
        raise FedlgrError(
            f"--workers {args.workers}: from 1 to {4 * cores} (4 x this machine's {cores} "
            "cores); each worker is a process that trains one trial at a time"
        )
    if args.study is None:
        return
    if not args.study.strip():  # '' would fall back to the sweep's name
        raise FedlgrError(f"--study {args.study!r}: empty; give a name, or leave it out")
    if not args.study.isprintable():  # a newline would be kept in the study's name
        raise FedlgrError(f"--study {args.study!r}: holds a control character")
    if len(args.study) > MAX_STUDY_NAME:
        raise FedlgrError(f"--study: {len(args.study)} characters, at most {MAX_STUDY_NAME}")


def _tracking_uris(overrides: list[str]) -> list[str]:
    given = [o.split("=", 1)[1] for o in overrides if o.startswith("tracking.uri=")]
    return [*given, os.environ.get("MLFLOW_TRACKING_URI", "")]


def _not_the_tracking_store(optuna_file: Path | None, args, overrides: list[str]) -> None:
    """One sqlite file for the study and the MLflow runs fails after 11 s with Alembic's
    "No such revision or branch" and leaves both sets of tables in it: refused first."""
    uri = given_uri(args.tracking_uri, overrides)
    if optuna_file is None or not uri.startswith("sqlite:///"):
        return
    tracking = sqlite_file(uri)
    if tracking and tracking.resolve() == optuna_file.resolve():  # by a link, or .., the same
        raise FedlgrError(
            f"--storage {args.storage}: the tracking store's file too; Optuna's study and "
            "MLflow's runs each need a database of their own (e.g. --storage "
            f"sqlite:///{optuna_file.with_name('optuna.db')})"
        )
