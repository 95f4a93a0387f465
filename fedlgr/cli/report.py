"""``fedlgr report [--experiment NAME | --sweep NAME] [--out DIR] [--tracking-uri URI]``."""

from __future__ import annotations

import argparse
import os


def report(args: argparse.Namespace) -> int:
    from fedlgr.config import TrackingConfig
    from fedlgr.report import make_report
    from fedlgr.tracking.mlflow_run import DEFAULT_URI

    uri = args.tracking_uri or os.environ.get("MLFLOW_TRACKING_URI") or DEFAULT_URI
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
