"""``fedlgr run [CONFIG] [key=value ...] [--print-config]``: one experiment, tracked in
MLflow (or its resolved config, printed)."""

from __future__ import annotations

import argparse

from fedlgr.shell.checks.paths import check_data_path
from fedlgr.shell.checks.stores import check_reachable
from fedlgr.shell.cli.parser import Verbs
from fedlgr.shell.config import find_config, load_config, to_yaml
from fedlgr.shell.signals import terminate_as_interrupt
from fedlgr.shell.tracking.mlflow_run import tracking_uri

# The setting groups and where each is documented (every setting with its default:
# --print-config). Plain text: the help loads no config code.
SETTINGS_EPILOG = """settings, as key=value (each one's default: fedlgr run --print-config):

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


def add_parser(verbs: Verbs) -> None:
    parser = verbs.add_parser(
        "run",
        help="run one experiment from a config and key=value overrides",
        description="Run one federated experiment, tracked in MLflow. CONFIG is a YAML file "
        "(e.g. conf/experiment/table1/clients2_noaug.yaml); overrides are key=value, e.g. "
        "method=FedRootAvg data.path=/path/to/manners-db federated.rounds=5.",
        epilog=SETTINGS_EPILOG,
    )
    parser.add_argument(
        "items",
        nargs="*",
        metavar="CONFIG|key=value",
        help="a config file (a path, or a name in conf/ such as debug/fast.yaml), then "
        "overrides such as federated.rounds=5 (without a config: the defaults)",
    )
    parser.add_argument(
        "--print-config",
        action="store_true",
        help="print the resolved config (file, includes and overrides) as YAML and exit "
        "without running; settings resolved at start (runtime.threads, runtime.concurrency, "
        "...) show as given",
    )
    parser.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI "
        "or sqlite:///mlflow.db with artifacts in mlruns/)",
    )
    parser.add_argument(
        "--resume",
        nargs="?",
        const=True,
        metavar="RUN_ID",
        help="continue an interrupted run from its last checkpoint, in the same MLflow run: "
        "RUN_ID, or (without one) the latest unfinished run of the same config",
    )
    parser.set_defaults(run=run)


def split_config_and_overrides(items: list[str]) -> tuple[str | None, list[str]]:
    """The first item without ``=`` is the config file; the rest are overrides."""
    config = next((i for i in items if "=" not in i), None)
    return config, [i for i in items if i is not config]


def resume_hint(config, run_id: str) -> str:
    """How to go on with interrupted run ``run_id``: ``--resume`` if it left a checkpoint."""
    from fedlgr.shell.run.checkpoint import checkpoint_root, checkpoints  # lazy: torch

    if checkpoints(checkpoint_root(config, tracking_uri(config)) / run_id):
        return (
            f"MLflow run {run_id} ended KILLED; "
            f"the same command with --resume {run_id} continues it"
        )
    return (
        f"MLflow run {run_id} ended KILLED before its first checkpoint (tracking.checkpoint): "
        "nothing to resume, run the command again"
    )


def run(args: argparse.Namespace) -> int:
    path, overrides = split_config_and_overrides(args.items)
    if args.tracking_uri:
        overrides.append(f"tracking.uri={args.tracking_uri}")
    config = load_config(None if path is None else find_config(path), overrides)
    if args.print_config:
        print(to_yaml(config), end="")
        return 0
    check_data_path(config.data.path)  # before torch's import (~12 s), as is the next check
    if config.tracking.enabled:  # before torch's import (~12 s): an unreachable URI fails now
        check_reachable(tracking_uri(config))

    from fedlgr.shell.run.experiment import run_experiment  # lazy: torch and Fabric

    started: list[str] = []  # the MLflow run's id, once it exists
    with terminate_as_interrupt():  # SIGTERM (timeout, Slurm, docker stop) is a Ctrl-C
        try:
            result = run_experiment(config, resume=args.resume, on_start=started.append)
        except KeyboardInterrupt as err:
            if started:
                err.add_note(resume_hint(config, started[-1]))  # printed by fedlgr.shell.cli.main
            raise
    if result is not None and result.run_id:
        print(f"MLflow run {result.run_id} (experiment {config.tracking.experiment!r})")
    return 0
