"""``fedlgr run [CONFIG] [key=value ...] [--print-config]``: one experiment, tracked in
MLflow (or its resolved config, printed)."""

from __future__ import annotations

import argparse


def split_config_and_overrides(items: list[str]) -> tuple[str | None, list[str]]:
    """The first item without ``=`` is the config file; the rest are overrides."""
    config = next((i for i in items if "=" not in i), None)
    return config, [i for i in items if i is not config]


def resume_hint(config, run_id: str) -> str:
    """How to go on with interrupted run ``run_id``: ``--resume`` if it left a checkpoint."""
    from fedlgr.shell.run.checkpoint import checkpoint_root, checkpoints
    from fedlgr.shell.tracking.mlflow_run import tracking_uri

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
    from fedlgr.shell.config import find_config, load_config, to_yaml

    path, overrides = split_config_and_overrides(args.items)
    if args.tracking_uri:
        overrides.append(f"tracking.uri={args.tracking_uri}")
    config = load_config(None if path is None else find_config(path), overrides)
    if args.print_config:
        print(to_yaml(config), end="")
        return 0
    from fedlgr.shell.data.config import check_data_path

    check_data_path(config.data.path)  # before torch's import (~12 s), as is the next check
    if config.tracking.enabled:  # before torch's import (~12 s): an unreachable URI fails now
        from fedlgr.shell.tracking.mlflow_run import tracking_uri
        from fedlgr.shell.tracking.server import check_reachable

        check_reachable(tracking_uri(config))

    from fedlgr.shell.run.experiment import run_experiment
    from fedlgr.shell.signals import terminate_as_interrupt

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
