"""``fedlgr report [--experiment NAME | --sweep NAME [--study NAME] [--storage URL]]
[--where KEY=VALUE] [--out DIR] [--tracking-uri URI]``."""

from __future__ import annotations

import argparse
from pathlib import Path

from fedlgr.shell.cli.parser import Verbs
from fedlgr.shell.config import TrackingConfig
from fedlgr.shell.report import ReportError, make_report
from fedlgr.shell.tracking.uri import masked_text, resolve_uri


def add_parser(verbs: Verbs) -> None:
    parser = verbs.add_parser(
        "report",
        help="the paper's tables (Markdown, LaTeX, CSV) and plots from the runs in MLflow",
        description="Read the finished runs of an experiment (or the trials of a sweep) from "
        "MLflow and write Tables I-IV (tableN.md/.tex/.csv: FL and FCL results, FL and FCL "
        "costs) and PNG plots to --out, then log that folder to MLflow (a run named 'report', "
        "or the reported study's parent run) under report/. A cell averages the runs of one "
        "method and setting whose settings differ only in their seeds (seed, data.seed); a "
        "repeated seed counts once (the newest run); runs of one cell with other settings are "
        "refused: narrow them with --where.",
    )
    parser.add_argument(
        "--experiment",
        help="MLflow experiment (default: tracking.experiment's default, unless --sweep is given)",
    )
    parser.add_argument(
        "--sweep",
        help="only the trials of this sweep (tag sweep=NAME), in every experiment or in "
        "--experiment",
    )
    parser.add_argument(
        "--study",
        help="with --sweep: the study to report, by name or parent run id (default: the "
        "newest study of the sweep in this store)",
    )
    parser.add_argument(
        "--storage",
        help="with --sweep: the study's Optuna storage URL (default: the one its parent run "
        "names, tag storage; give it where that is relative to another folder or has its "
        "password masked)",
    )
    parser.add_argument(
        "--where",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="only runs with this setting, as MLflow holds it (e.g. federated.rounds=20; "
        "repeatable)",
    )
    parser.add_argument(
        "--out",
        type=Path,
        help="output folder (default: reports/EXPERIMENT or reports/sweeps/SWEEP/STUDY-RUNID, "
        "with a sub-folder for --dataset/--modality/--where)",
    )
    parser.add_argument(
        "--tracking-uri",
        help="MLflow tracking URI (default: $MLFLOW_TRACKING_URI or sqlite:///mlflow.db)",
    )
    parser.add_argument("--dataset", help="only runs on this dataset (tag dataset, e.g. synthetic)")
    parser.add_argument(
        "--modality", choices=["image", "features"], help="only runs of this modality"
    )
    parser.add_argument("--no-log", action="store_true", help="write the files but log nothing")
    parser.add_argument(
        "--paper",
        action="store_true",
        help="Tables I and II also give the paper's published values (MANNERS-DB), a row "
        "'METHOD (paper)' under each method's runs",
    )
    parser.set_defaults(run=report)


def report(args: argparse.Namespace) -> int:
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
        paper=args.paper,
        storage=args.storage,
    )
    print(masked_text(result.summary(), uri))  # a database's password is not printed
    return 0
