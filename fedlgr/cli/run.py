"""``fedlgr run [CONFIG] [key=value ...] [--print-config]``: one experiment, tracked in
MLflow (or its resolved config, printed)."""

from __future__ import annotations

import argparse


def split_config_and_overrides(items: list[str]) -> tuple[str | None, list[str]]:
    """The first item without ``=`` is the config file; the rest are overrides."""
    config = next((i for i in items if "=" not in i), None)
    return config, [i for i in items if i is not config]


def run(args: argparse.Namespace) -> int:
    from fedlgr.config import find_config, load_config, to_yaml

    path, overrides = split_config_and_overrides(args.items)
    if args.tracking_uri:
        overrides.append(f"tracking.uri={args.tracking_uri}")
    config = load_config(None if path is None else find_config(path), overrides)
    if args.print_config:
        print(to_yaml(config), end="")
        return 0
    if config.tracking.enabled:  # before torch's import (~12 s): an unreachable URI fails now
        from fedlgr.tracking.mlflow_run import tracking_uri
        from fedlgr.tracking.server import check_reachable

        check_reachable(tracking_uri(config))

    from fedlgr.federated.experiment import run_experiment
    from fedlgr.signals import terminate_as_interrupt

    with terminate_as_interrupt():  # SIGTERM (timeout, Slurm, docker stop) is a Ctrl-C
        result = run_experiment(config, resume=args.resume)
    if result is not None and result.run_id:
        print(f"MLflow run {result.run_id} (experiment {config.tracking.experiment!r})")
    return 0
