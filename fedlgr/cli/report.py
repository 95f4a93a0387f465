"""``fedlgr report [--experiment NAME | --sweep NAME] [--out DIR] [--tracking-uri URI]``."""

from __future__ import annotations

import argparse


def report(args: argparse.Namespace) -> int:
    from fedlgr.config import TrackingConfig
    from fedlgr.report import make_report
    from fedlgr.tracking.mlflow_run import resolve_uri

    uri = resolve_uri(args.tracking_uri)
    experiment = args.experiment
    if experiment is None and args.sweep is None:
        experiment = TrackingConfig().experiment
    result = make_report(
        uri,
        experiment=experiment,
        sweep=args.sweep,
        out=args.out,
        dataset=args.dataset,
        modality=args.modality,
        log=not args.no_log,
    )
    print(result.summary())
    return 0
