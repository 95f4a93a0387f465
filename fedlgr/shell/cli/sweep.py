"""``fedlgr sweep SWEEP [key=value ...]``: run or resume an Optuna sweep."""

from __future__ import annotations

import os
from dataclasses import replace
from pathlib import Path
from typing import Annotated

import typer

from fedlgr.errors import FedlgrError
from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.checks.stores import check_reachable
from fedlgr.shell.cli.verb import Overrides, TrackingUri, Verbs
from fedlgr.shell.machine import available_cores
from fedlgr.shell.signals import terminate_as_interrupt
from fedlgr.shell.tracking.uri import given_uri, masked_echo, sqlite_file

MAX_STUDY_NAME = 512  # optuna.storages._rdb.models.MAX_INDEXED_STRING_LENGTH

app = Verbs()


def shipped_sweeps() -> list[tuple[str, str]]:
    """``(name, what it sweeps)`` for each YAML file in ``sweeps/`` (the checkout's or the
    installed package's): its ``description:``, else its header comment's first line if
    short. Plain text reading, no YAML parser: ``fedlgr --help`` builds this too."""
    listing = []
    for path in sorted(conf.SWEEPS_DIR.glob("*.yaml")):
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
    lines = [f"{name.ljust(width)}  {text}".rstrip() for name, text in listing]
    return f"\b\nshipped sweeps (in {conf.SWEEPS_DIR}):\n" + "\n".join(lines)  # \b: as written


@app.command(
    "sweep",
    short_help="run or resume an Optuna sweep (grid or TPE) of experiments",
    epilog=_sweep_epilog(),
)
def run_or_resume(
    sweep: Annotated[str, typer.Argument(metavar="SWEEP")],
    overrides: Overrides = (),
    storage: Annotated[
        str,
        typer.Option(help="Optuna RDB storage URL (a PostgreSQL/MySQL URL for several machines)"),
    ] = "sqlite:///optuna.db",
    study: Annotated[
        str | None, typer.Option(help="study name (default: the sweep's name)")
    ] = None,
    settings_changed: Annotated[
        bool,
        typer.Option(
            help="go on with a study started with other settings (the sweep file or "
            "overrides, e.g. a dataset that moved); its finished trials count as they are. A "
            "space whose values changed needs a new study (--study)",
        ),
    ] = False,
    workers: Annotated[int, typer.Option(help="processes on this machine")] = 1,
    tracking_uri: TrackingUri = None,
    heartbeat: Annotated[
        int | None,
        typer.Option(
            help="seconds between a worker's heartbeats; a trial silent for two is retried "
            "(default: the sweep file's heartbeat_s)"
        ),
    ] = None,
    worker_id: Annotated[int, typer.Option(hidden=True)] = 0,
) -> int:
    """Run the trials of SWEEP (a file in sweeps/, e.g. sweeps/ewc.yaml or just ewc; the
    shipped ones are listed below) as an Optuna study, each trial an experiment tracked in
    MLflow under one parent run. Launching it again resumes the study; --workers N (or
    launches elsewhere on the same --storage) work on it in parallel. Overrides (key=value)
    apply to every trial, e.g. data.path=/path/to/manners-db."""
    # lazy: the sweep's modules and filelock, which fedlgr --help does without
    from fedlgr.shell.sweep import load_sweep, run_sweep
    from fedlgr.shell.sweep.spec import MAX_HEARTBEAT_S
    from fedlgr.shell.sweep.storage import check_storage

    with terminate_as_interrupt():  # SIGTERM (timeout, Slurm, docker stop) is a Ctrl-C
        overrides = list(overrides)
        _check_workers_and_study(workers, study)
        check_reachable(given_uri(tracking_uri, overrides))  # before loading Optuna and MLflow
        optuna_file = check_storage(storage, make=False)  # before the configs load torch
        _not_the_tracking_store(optuna_file, storage, tracking_uri, overrides)
        if workers > 1 and not any(o.startswith("runtime.threads=") for o in overrides):
            # Share this machine's cores between the workers instead of oversubscribing them.
            overrides.append(f"runtime.threads={max(1, available_cores() // workers)}")
        spec = load_sweep(sweep, overrides)
        uris = [o.split("=", 1)[1] for o in overrides if o.startswith("tracking.uri=")]
        if heartbeat is not None:
            if not 1 <= heartbeat <= MAX_HEARTBEAT_S:
                raise FedlgrError(f"--heartbeat {heartbeat}: from 1 to {MAX_HEARTBEAT_S} s")
            spec = replace(spec, heartbeat_s=heartbeat)
        result = run_sweep(
            spec,
            storage=storage,
            study_name=study,
            workers=workers,
            tracking_uri=tracking_uri,
            cli_overrides=overrides,
            worker_id=worker_id,
            settings_changed=settings_changed,
            # A database's password is not printed (a helper worker's lines come through here).
            echo=masked_echo(
                print, storage, tracking_uri, *uris, os.environ.get("MLFLOW_TRACKING_URI")
            ),
        )
    if result.failure:  # the table above shows each trial's error
        raise FedlgrError(f"sweep {spec.name}: {result.failure}")
    return 0 if result.done else 1


def _check_workers_and_study(workers: int, study: str | None) -> None:
    """``--workers`` within this machine's reach, and ``--study`` a name Optuna can keep."""
    cores = os.cpu_count() or 1
    if not 1 <= workers <= 4 * cores:
        raise FedlgrError(
            f"--workers {workers}: from 1 to {4 * cores} (4 x this machine's {cores} "
            "cores); each worker is a process that trains one trial at a time"
        )
    if study is None:
        return
    if not study.strip():  # '' would fall back to the sweep's name
        raise FedlgrError(f"--study {study!r}: empty; give a name, or leave it out")
    if not study.isprintable():  # a newline would be kept in the study's name
        raise FedlgrError(f"--study {study!r}: holds a control character")
    if len(study) > MAX_STUDY_NAME:
        raise FedlgrError(f"--study: {len(study)} characters, at most {MAX_STUDY_NAME}")


def _not_the_tracking_store(
    optuna_file: Path | None, storage: str, tracking_uri: str | None, overrides: list[str]
) -> None:
    """One sqlite file for the study and the MLflow runs fails late with Alembic's "No such
    revision or branch" and leaves both sets of tables in it: refused first."""
    uri = given_uri(tracking_uri, overrides)
    if optuna_file is None or not uri.startswith("sqlite:///"):
        return
    tracking = sqlite_file(uri)
    if tracking and tracking.resolve() == optuna_file.resolve():  # by a link, or .., the same
        raise FedlgrError(
            f"--storage {storage}: the tracking store's file too; Optuna's study and "
            "MLflow's runs each need a database of their own (e.g. --storage "
            f"sqlite:///{optuna_file.with_name('optuna.db')})"
        )
