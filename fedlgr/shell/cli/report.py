"""``fedlgr report [--experiment NAME | --sweep NAME [--study NAME]] [--where KEY=VALUE]
[--out DIR] [--tracking-uri URI]``."""

from __future__ import annotations

import argparse


def report(args: argparse.Namespace) -> int:
    from fedlgr.shell.config import TrackingConfig
    from fedlgr.shell.report import ReportError, make_report
    from fedlgr.shell.tracking.mlflow_run import resolve_uri

    uri = resolve_uri(args.tracking_uri)
    experiment = args.experiment
    if experiment is None and args.sweep is None:
        experiment = TrackingConfig().experiment
    where = {}
    for item in args.where:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ReportError(f"--where {item}: expected KEY=VALUE, e.g. federated.rounds=20")
        where[key.strip()] = value.strip()
    result = make_report(
        uri,
        experiment=experiment,
        sweep=args.sweep,
        study=args.study,
        out=args.out,
        dataset=args.dataset,
        modality=args.modality,
        where=where,
        log=not args.no_log,
    )
    from fedlgr.shell.tracking.server import masked_text

    print(masked_text(result.summary(), uri))  # a database's password is not printed
    return 0
