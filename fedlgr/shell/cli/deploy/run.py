"""``fedlgr deploy run CONFIG [key=value ...]``: submit fedlgr's app to the SuperLink with
``flwr run``, stream its log, and exit 0 only if the Flower run completed."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import time
from pathlib import Path
from typing import Annotated

import typer

from fedlgr.errors import FedlgrError
from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.cli.deploy import launch
from fedlgr.shell.cli.verb import Overrides, Verbs
from fedlgr.shell.deploy.flower import APP_DIR
from fedlgr.shell.tracking.uri import masked_uris

STATUS_WAIT_S = 60  # the log ends as the run does; its status may lag


app = Verbs()


@app.command(
    "run", short_help="submit a run with flwr run, stream its log and exit 0 only if it completed"
)
def run(
    config: Annotated[str, typer.Argument(metavar="CONFIG")],
    overrides: Overrides = (),
    federation: Annotated[
        str | None,
        typer.Option(
            metavar="NAME",
            help="the SuperLink connection (fedlgr deploy connect NAME; default: flwr's default)",
        ),
    ] = None,
    resume: Annotated[
        str | None,
        typer.Option(
            metavar="[RUN_ID]",
            help="continue an interrupted Flower run (its MLflow id; default: the latest "
            "unfinished run of this config) from its newest checkpoint, in the same MLflow run",
        ),
    ] = None,
    print_command: launch.PrintCommand = False,
) -> None:
    """Run fedlgr's app on the SuperLink: CONFIG (the config file, as in fedlgr run; made
    absolute) must exist at that path on the SuperLink's machine; key=value overrides as
    in fedlgr run."""
    _refuse_passwords(overrides)  # before anything is printed or submitted
    flwr = launch.flower_command("flwr")
    path = launch.absolute(config)
    run_config = (
        f"config={launch.toml_string(str(path))} "
        f"overrides={launch.toml_string(shlex.join(overrides))}"
    )
    if resume:  # bare: True, the latest unfinished run
        run_config += f" resume={launch.toml_string('latest' if resume is True else resume)}"
    link = [federation] if federation else []
    cmd = [str(flwr), "run", str(APP_DIR), *link, "--stream", "--run-config", run_config]
    _check_connection(federation)  # with --print-command too: the command must work
    if not print_command:
        _check_config(path, overrides, resume)  # a run refused here prints no flwr command
    print(shlex.join(cmd), flush=True)
    if print_command:
        return
    env = {**launch.flower_env(flwr), "PYTHONUNBUFFERED": "1"}
    run_id = _stream(cmd, env, link)
    row = _final_status(flwr, link, run_id, env)
    if row["status"] != "finished:completed":
        # Flower's own words may quote a URI with its password (a ServerApp's error)
        details = masked_uris(" ".join(str(row.get("status-details") or "no details").split()))
        raise FedlgrError(f"Flower run {run_id} ended {row['status']}: {details}")
    print(f"fedlgr: Flower run {run_id} finished:completed")


def _refuse_passwords(overrides: list[str]) -> None:
    """Refuse an override that holds a secret (``user:password@``, ``password=``, a token): it
    would be printed, kept in the SuperLink's database and sent to every robot. The ServerApp
    finds it on the SuperLink's machine instead (docs/deployment.md)."""
    for override in overrides:
        key, _, value = override.partition("=")
        # also libpq's keyword form, "host=db user=me password=..."
        masked = masked_uris(value)
        if masked != value:
            raise FedlgrError(
                f"{key}={masked}: a password or token on the command line would be "
                "printed, kept in the SuperLink's database and sent to every robot with the "
                "run's config: leave it out of the URI and keep it on the SuperLink's machine "
                "(~/.pgpass or $PGPASSWORD of the user who runs fedlgr deploy superlink, "
                "$MLFLOW_TRACKING_TOKEN for an MLflow server's token, or tracking.uri in "
                "CONFIG there; docs/deployment.md)"
            )


def _check_connection(name: str | None) -> None:
    """The SuperLink ``flwr run`` submits to must be one ``fedlgr deploy connect`` named: without
    one, flwr's own default ``local`` starts a simulation SuperLink in the background, left
    running after the run fails."""
    path, config = launch.flower_config()
    links = config.get("superlink", {})
    chosen = name or links.get("default")
    entry = links.get(chosen) if isinstance(chosen, str) else None
    if not isinstance(entry, dict) or entry.get("address", ":local:") == ":local:":
        which = f"--federation {name}" if name else "the default connection"
        raise FedlgrError(
            f"{which}: no SuperLink connection of that name in {path} (flwr would start a "
            "local simulation of its own); add one with fedlgr deploy connect NAME "
            "--superlink HOST:PORT --ca ca.pem"
        )


def _check_config(config: Path, overrides: list[str], resume: str | bool | None) -> None:
    """The config and its roster, loaded here rather than on the server once the run's ServerApp
    started: a typo is the commonest mistake. With ``resume``, the run to resume is looked for in
    the sqlite file the config names when that is on this machine too (the ServerApp's refusal
    would come as its traceback; a default store is the SuperLink machine's own)."""
    if not config.is_file():
        print(f"fedlgr: {config} is not on this machine: it must be on the SuperLink's", flush=True)
        return
    from fedlgr.shell.checks.experiment import check_robots_are_real  # lazy: pydantic
    from fedlgr.shell.deploy.roster import roster_of  # lazy: cryptography and yaml
    from fedlgr.shell.tracking.uri import sqlite_file  # lazy: sqlalchemy

    loaded = conf.load_config(config, overrides)
    check_robots_are_real(loaded)
    roster_of(loaded)
    uri = loaded.tracking.uri
    store = sqlite_file(uri) if uri else None
    here = store is not None and store.is_absolute() and store.is_file()
    if resume and (here or not loaded.tracking.enabled):
        from fedlgr.shell.run.resume import check_resumable  # lazy: MLflow and torch

        check_resumable(loaded, resume)


def _stream(cmd: list[str], env: dict[str, str], link: list[str]) -> str:
    """Run ``flwr run``, its output passed on line by line; the id of the run it started."""
    run_id = None
    with subprocess.Popen(
        cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
    ) as proc:
        try:
            for line in proc.stdout:
                print(line, end="", flush=True)
                found = re.search(r"Successfully started run (\d+)", line)
                run_id = run_id or (found and found.group(1))
        except KeyboardInterrupt:
            if run_id:
                stop = shlex.join(["flwr", "stop", run_id, *link])
                print(f"fedlgr: run {run_id} goes on on the SuperLink; {stop} stops it")
            raise
    if proc.returncode != 0 or run_id is None:
        raise FedlgrError(f"flwr run failed (exit {proc.returncode}); its output is above")
    return run_id


def _final_status(flwr: Path, link: list[str], run_id: str, env: dict[str, str]) -> dict:
    """Run ``run_id``'s row from ``flwr ls`` once its status is ``finished:...``, or as it
    stands after :data:`STATUS_WAIT_S`."""
    deadline = time.monotonic() + STATUS_WAIT_S
    while True:
        ls = subprocess.run(
            [str(flwr), "ls", *link, "--run-id", run_id, "--format", "json"],
            capture_output=True,
            text=True,
            env=env,
        )
        try:
            listed = json.loads(ls.stdout[ls.stdout.index("{") :])
            [row] = listed["runs"]
        except (ValueError, KeyError) as err:
            detail = " ".join((ls.stdout + ls.stderr).split())[-300:]
            raise FedlgrError(f"flwr ls --run-id {run_id}: no status ({err}): {detail}") from None
        if row["status"].startswith("finished") or time.monotonic() > deadline:
            return row
        time.sleep(1)
