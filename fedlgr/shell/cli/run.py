"""``fedlgr run [CONFIG] [key=value ...] [--print-config]``: one experiment, tracked in
MLflow (or its resolved config, printed)."""

from __future__ import annotations

from typing import Annotated

import typer

from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.checks.paths import check_data_path
from fedlgr.shell.checks.stores import check_reachable
from fedlgr.shell.cli.verb import TrackingUri, Verbs
from fedlgr.shell.signals import terminate_as_interrupt

app = Verbs()

# Plain text, as the help loads no config code; \b keeps click from re-wrapping the listing.
SETTINGS_EPILOG = """settings, as key=value (each one's default: fedlgr run --print-config):

\b
method, seed         the paper's method name (FedRootAvg, FedLGR, ...); the seed
                     docs/methods.md
data.*               the scenes (MANNERS-DB or synthetic), clients, split, tasks
                     docs/data.md
model.*              the scholar: root, width, weights          docs/methods.md
train.*              local epochs, batches, learning rates      docs/methods.md
federated.*          strategy (+ federated.<strategy>.*), scope, rounds, fraction,
                     server evaluation, norm checks, simulated faults
                     docs/methods.md
federated.dp.*       client-level differential privacy          docs/privacy.md
continual.*          the task schedule, the CL method (+ continual.<method>.*)
                     docs/fedlgr.md
runtime.*            processes, threads, devices, precision     docs/runtimes.md
tracking.*           the MLflow store, checkpoints, system metrics
                     docs/tracking.md, docs/resume.md
deploy.*             robots behind Flower                       docs/deployment.md"""


def split_config_and_overrides(items: list[str]) -> tuple[str | None, list[str]]:
    """The first item without ``=`` is the config file; the rest are overrides."""
    config = next((i for i in items if "=" not in i), None)
    return config, [i for i in items if i is not config]


def resume_hint(config, run_id: str) -> str:
    """How to go on with interrupted run ``run_id``: ``--resume`` if it left a checkpoint."""
    from fedlgr.shell.run.checkpoint import checkpoint_root, checkpoints  # lazy: torch
    from fedlgr.shell.tracking.mlflow_run import tracking_uri as uri  # lazy: filelock

    if checkpoints(checkpoint_root(config, uri(config)) / run_id):
        return (
            f"MLflow run {run_id} ended KILLED; "
            f"the same command with --resume {run_id} continues it"
        )
    return (
        f"MLflow run {run_id} ended KILLED before its first checkpoint (tracking.checkpoint): "
        "nothing to resume, run the command again"
    )


@app.command(
    "run",
    short_help="run one experiment from a config and key=value overrides",
    epilog=SETTINGS_EPILOG,
)
def run(
    items: Annotated[list[str], typer.Argument(metavar="[CONFIG|key=value]...")] = (),
    print_config: Annotated[
        bool,
        typer.Option(
            help="print the resolved config (file, includes and overrides) as YAML and exit "
            "without running; settings resolved at start (runtime.threads, "
            "runtime.concurrency, ...) show as given",
        ),
    ] = False,
    tracking_uri: TrackingUri = None,
    resume: Annotated[
        str | None,
        typer.Option(
            metavar="[RUN_ID]",
            help="continue an interrupted run from its last checkpoint, in the same MLflow "
            "run: RUN_ID, or (without one) the latest unfinished run of the same config",
        ),
    ] = None,
) -> None:
    """Run one federated experiment, tracked in MLflow. CONFIG is a YAML file, a path or a
    name in conf/ (e.g. conf/experiment/table1/clients2_noaug.yaml, debug/fast.yaml;
    without one: the defaults); overrides are key=value, e.g. method=FedRootAvg
    data.path=/path/to/manners-db federated.rounds=5."""
    from fedlgr.shell.tracking.mlflow_run import tracking_uri as uri  # lazy: filelock

    path, overrides = split_config_and_overrides(items)
    if tracking_uri:
        overrides.append(f"tracking.uri={tracking_uri}")
    config = conf.load_config(None if path is None else conf.find_config(path), overrides)
    if print_config:
        print(conf.to_yaml(config), end="")
        return
    check_data_path(config.data.path)  # before torch's import (seconds), as is the next check
    if config.tracking.enabled:  # before torch's import: an unreachable URI fails now
        check_reachable(uri(config))

    from fedlgr.shell.run.experiment import run_experiment  # lazy: torch and Fabric

    started: list[str] = []  # the MLflow run's id, once it exists
    with terminate_as_interrupt():  # SIGTERM (timeout, Slurm, docker stop) is a Ctrl-C
        try:
            result = run_experiment(config, resume=resume, on_start=started.append)
        except KeyboardInterrupt as err:
            if started:
                err.add_note(resume_hint(config, started[-1]))  # printed by fedlgr.shell.cli.main
            raise
    if result is not None and result.run_id:
        print(f"MLflow run {result.run_id} (experiment {config.tracking.experiment!r})")
