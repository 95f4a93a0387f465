"""``fedlgr report``: the paper's tables and plots from the runs (or a sweep's trials) in MLflow."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

import typer

from fedlgr.shell import config as conf  # its names load when used: pydantic
from fedlgr.shell.cli.verb import TrackingUri, Verbs
from fedlgr.shell.tracking.uri import masked_text, resolve_uri

app = Verbs()

# The options whose help takes several lines, declared here to keep report() short.
Experiment = Annotated[
    str | None,
    typer.Option(
        help="MLflow experiment (default: tracking.experiment's default, unless --sweep is given)"
    ),
]
Sweep = Annotated[
    str | None,
    typer.Option(
        help="only the trials of this sweep (tag sweep=NAME), in every experiment or in "
        "--experiment"
    ),
]
Study = Annotated[
    str | None,
    typer.Option(
        help="with --sweep: the study to report, by name or parent run id (default: the newest "
        "study of the sweep in this store)"
    ),
]
Storage = Annotated[
    str | None,
    typer.Option(
        help="with --sweep: the study's Optuna storage URL (default: the one its parent run "
        "names, tag storage; give it where that is relative to another folder or has its "
        "password masked)"
    ),
]
Where = Annotated[
    list[str],
    typer.Option(
        metavar="KEY=VALUE",
        help="only runs with this setting, as MLflow holds it (e.g. federated.rounds=20; "
        "repeatable)",
    ),
]
Out = Annotated[
    Path | None,
    typer.Option(
        help="output folder (default: reports/EXPERIMENT or reports/sweeps/SWEEP/STUDY-RUNID, "
        "with a sub-folder for --dataset/--modality/--where)"
    ),
]
Paper = Annotated[
    bool,
    typer.Option(
        help="Tables I and II also give the paper's published values (MANNERS-DB), a row "
        "'METHOD (paper)' under each method's runs",
    ),
]


@app.command(
    "report",
    short_help="the paper's tables (Markdown, LaTeX, CSV) and plots from the runs in MLflow",
)
def report(
    experiment: Experiment = None,
    sweep: Sweep = None,
    study: Study = None,
    storage: Storage = None,
    where: Where = (),
    out: Out = None,
    tracking_uri: TrackingUri = None,
    dataset: Annotated[
        str | None, typer.Option(help="only runs on this dataset (tag dataset, e.g. synthetic)")
    ] = None,
    modality: Annotated[
        Literal["image", "features"] | None, typer.Option(help="only runs of this modality")
    ] = None,
    no_log: Annotated[bool, typer.Option(help="write the files but log nothing")] = False,
    paper: Paper = False,
) -> None:
    """Read the finished runs of an experiment (or the trials of a sweep) from MLflow and
    write Tables I-IV (tableN.md/.tex/.csv: FL and FCL results, FL and FCL costs) and PNG
    plots to --out, then log that folder to MLflow (a run named 'report', or the reported
    study's parent run) under report/. A cell averages the runs of one method and setting
    whose settings differ only in their seeds (seed, data.seed); a repeated seed counts
    once (the newest run); runs of one cell with other settings are refused: narrow them
    with --where."""
    from fedlgr.shell.report import ReportError, make_report  # lazy: fedlgr --help does without

    uri = resolve_uri(tracking_uri)
    if experiment is None and sweep is None:
        experiment = conf.TrackingConfig().experiment
    settings = {}
    for item in where:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ReportError(f"--where {item}: expected KEY=VALUE, e.g. federated.rounds=20")
        settings[key.strip()] = value.strip()
    result = make_report(
        uri,
        experiment=experiment,
        sweep=sweep,
        study=study,
        out=out,
        dataset=dataset,
        modality=modality,
        where=settings,
        log=not no_log,
        paper=paper,
        storage=storage,
    )
    print(masked_text(result.summary(), uri))  # a database's password is not printed
