"""A sweep's own report: each trial's swept settings against the objective and the scores, read
from the study's Optuna storage (else its parent run's child runs in MLflow), and Optuna's plots."""

from __future__ import annotations

import json
import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from fedlgr.core.metrics import headline_scores
from fedlgr.shell.checks.stores import check_database
from fedlgr.shell.config import short_setting
from fedlgr.shell.report.plots import pyplot
from fedlgr.shell.report.render import csv_number, csv_text, md_row
from fedlgr.shell.report.runs import Selection, pages, swept_values
from fedlgr.shell.report.tables import Table
from fedlgr.shell.tracking.uri import mask_password, server_database, sqlite_file

PARENT_ATTR = "mlflow_parent_run_id"  # the study's user attribute naming its parent run
MLFLOW_STATES = {"FINISHED": "COMPLETE", "KILLED": "PRUNED", "FAILED": "FAIL"}
# fANOVA fits a random forest to the completed trials: on fewer points it ranks noise.
MIN_TRIALS_FOR_IMPORTANCE = 6


def headline() -> list[tuple[str, str]]:
    """The scores each row shows besides the objective, with their headings: every headline
    score (``test/rmse``, ``test RMSE ▼``)."""
    return [(f"test/{s.name}", f"test {s.label} {s.arrow}") for s in headline_scores()]


@dataclass
class TrialRow:
    number: int
    params: dict[str, Any]
    value: float | None  # the objective, as Optuna recorded it (or the run's metric)
    scores: dict[str, float]  # the headline scores of its MLflow run
    state: str  # Optuna's: COMPLETE, PRUNED, FAIL, RUNNING, WAITING


@dataclass
class Trials:
    """One study's trials, best first, and where they were read from."""

    metric: str
    direction: str  # minimize or maximize
    params: list[str]  # the swept settings, in the sweep's order
    rows: list[TrialRow]
    source: str  # "Optuna storage URL" or "MLflow"
    study: Any = None  # the optuna Study, for the plots (None when read from MLflow)
    notes: list[str] = field(default_factory=list)


def read_trials(selection: Selection, storage: str | None = None) -> Trials | None:
    """The trials of the reported study; None for trials without a parent run."""
    client, parent_id = selection.client, selection.parent_run_id
    if parent_id is None:
        return None
    parent = client.get_run(parent_id)
    tags = parent.data.tags
    direction, _, metric = (tags.get("objective") or "minimize test/rmse").partition(" ")
    runs = pages(
        client.search_runs, selection.experiment_ids, f"tags.`mlflow.parentRunId` = '{parent_id}'"
    )
    by_id = {run.info.run_id: run for run in runs}
    url = storage or tags.get("storage", "")
    study, why = _load_study(url, tags.get("study", selection.name), parent_id)
    if study is not None:  # a grid point another trial already covered is skipped
        trials = study.get_trials(deepcopy=False)
        rows = [_optuna_row(t, by_id) for t in trials if "duplicate_of" not in t.user_attrs]
        source, notes = f"Optuna storage {mask_password(url)}", []
    else:
        rows = [_mlflow_row(run, metric) for run in runs if "trial" in run.data.tags]
        source, notes = (
            "MLflow",
            [
                f"The trials are read from MLflow, not from the study's Optuna storage ({why}): "
                "only trials that started a run, and no Optuna plots."
            ],
        )
    space = json.loads(parent.data.params.get("space", "{}") or "{}")
    seen = [k for r in rows for k in r.params]
    params = [*[k for k in space if k in seen], *dict.fromkeys(k for k in seen if k not in space)]
    rows.sort(key=lambda r: _rank(r, direction))
    return Trials(metric, direction, params, rows, source, study, notes)


def _load_study(url: str, name: str, parent_id: str):
    """The study and None, or None and why it cannot be read."""
    if not url:
        return None, "its parent run records none (tag storage)"
    shown = mask_password(url)
    if "***" in url:
        return None, f"{shown}: its password is masked; give it with --storage URL"
    try:
        path = sqlite_file(url)
        if path is not None and not path.is_file():
            return None, f"{shown}: no file {path} here; report where the sweep ran, or --storage"
        if server_database(url):
            check_database(url, "--storage")
        import optuna  # lazy: optuna, only for a sweep's report

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        study = optuna.load_study(study_name=name, storage=url)
    except Exception as err:  # unreachable, no such study: the MLflow trials
        text = str(err).strip().splitlines()
        return None, f"{shown}: {text[0] if text else type(err).__name__}"
    if study.user_attrs.get(PARENT_ATTR) != parent_id:
        owner = study.user_attrs.get(PARENT_ATTR)
        return None, f"{shown}: its study {name!r} belongs to another parent run ({owner})"
    return study, None


def _optuna_row(trial, runs: dict[str, Any]) -> TrialRow:
    run = runs.get(trial.user_attrs.get("mlflow_run_id", ""))
    scores = _scores(run.data.metrics if run is not None else {})
    return TrialRow(trial.number, dict(trial.params), trial.value, scores, trial.state.name)


def _mlflow_row(run, metric: str) -> TrialRow:
    metrics, tags = run.data.metrics, run.data.tags
    state = MLFLOW_STATES.get(run.info.status, run.info.status)
    value = metrics.get(metric) if state == "COMPLETE" else None
    return TrialRow(int(tags["trial"]), swept_values(tags), value, _scores(metrics), state)


def _scores(metrics: dict[str, float]) -> dict[str, float]:
    return {m: metrics[m] for m, _ in headline() if m in metrics}


def _rank(row: TrialRow, direction: str) -> tuple:
    """Completed trials by their value, best first; then the others by number."""
    value = row.value
    if value is None or not math.isfinite(value):
        return (1, 0.0, row.number)
    return (0, value if direction == "minimize" else -value, row.number)


def columns(trials: Trials) -> list[tuple[str, str]]:
    """(CSV header, Markdown heading) of each column."""
    arrow = "▼" if trials.direction == "minimize" else "▲"
    return [
        ("trial", "trial"),
        *[(p, short_setting(p)) for p in trials.params],
        (f"objective: {trials.metric}", f"objective: {trials.metric} {arrow}"),
        *headline(),
        ("state", "state"),
    ]


def _cells(trials: Trials, row: TrialRow, shown: bool) -> list[str]:
    def number(v: float | None) -> str:
        if not shown:
            return csv_number(v)
        return "—" if v is None else f"{v:.4f}"

    params = [str(row.params[p]) if p in row.params else "" for p in trials.params]
    scores = [number(row.scores.get(m)) for m, _ in headline()]
    return [str(row.number), *params, number(row.value), *scores, row.state]


def to_markdown(trials: Trials, sweep: str) -> str:
    """The trials as a Markdown table, best first, the best in bold."""
    heads = [h for _, h in columns(trials)]
    lines = [f"## Sweep `{sweep}`: every trial, best first by its objective", ""]
    lines += [md_row(heads), md_row(["---:"] * len(heads))]
    for k, row in enumerate(trials.rows):
        cells = _cells(trials, row, shown=True)
        if k == 0 and row.value is not None:
            cells = [f"**{c}**" for c in cells]
        lines.append(md_row(cells))
    lines += ["", f"Read from the {trials.source}; the scores are each trial's MLflow run's."]
    return "\n".join([*lines, *(f"\n{n}" for n in trials.notes), ""])


def to_csv(trials: Trials) -> str:
    """The same rows, unrounded; an empty cell where there is no value."""
    header = [key for key, _ in columns(trials)]
    return csv_text([header, *(_cells(trials, row, shown=False) for row in trials.rows)])


@dataclass
class SweepViews:
    """What a sweep's report adds to the paper's tables."""

    plots: list[str]  # Optuna's PNGs
    trials: int
    source: str
    notes: list[str]


def write_sweep_views(selection: Selection, out: Path, storage: str | None) -> SweepViews | None:
    """``trials.md``/``.csv`` and Optuna's plots of the reported study into ``out``; None
    for trials without a parent run (there is no study to read)."""
    trials = read_trials(selection, storage)
    if trials is None:
        return None
    plots: list[str] = []
    if trials.study is not None:
        plots, notes = write_study_plots(trials.study, trials.metric, trials.params, out)
        trials.notes += notes
    (out / "trials.md").write_text(to_markdown(trials, selection.name), encoding="utf-8")
    (out / "trials.csv").write_text(to_csv(trials), encoding="utf-8")
    return SweepViews(plots, len(trials.rows), trials.source, trials.notes)


def write_study_plots(study: Any, metric: str, params: list[str], out: Path) -> tuple[list, list]:
    """Draw the plots that fit the study into ``out``; returns the files written and the
    lines that say which were left out and why."""
    import optuna  # lazy: optuna and matplotlib (seconds), only for a sweep's report
    from optuna.visualization import matplotlib as views  # lazy: as optuna

    done = study.get_trials(deepcopy=False, states=(optuna.trial.TrialState.COMPLETE,))
    if not done:
        return [], ["Optuna's plots: not drawn, no trial completed."]
    varied = [p for p in params if len({repr(t.params.get(p)) for t in done}) > 1]
    plots = {
        "optuna_history.png": lambda: views.plot_optimization_history(study, target_name=metric),
        "optuna_slice.png": lambda: views.plot_slice(study, params=params, target_name=metric),
    }
    notes = []
    if len(varied) >= 2 and len(done) >= MIN_TRIALS_FOR_IMPORTANCE:
        plots["optuna_importances.png"] = lambda: views.plot_param_importances(
            study, params=varied, target_name=metric
        )
    else:
        notes.append(
            f"Parameter importances: not drawn; they need 2 or more swept settings that vary "
            f"and {MIN_TRIALS_FOR_IMPORTANCE} completed trials (this study: {len(varied)} "
            f"varying, {len(done)} completed)."
        )
    if len(varied) >= 2:
        plots["optuna_contour.png"] = lambda: views.plot_contour(
            study, params=varied, target_name=metric
        )
    else:
        notes.append("Contour plot: not drawn; it needs 2 or more swept settings that vary.")
    plt = pyplot()
    for name, draw in plots.items():
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            drawn = draw()
        figure = drawn.figure if hasattr(drawn, "figure") else drawn.flat[0].figure
        if name == "optuna_slice.png":  # long values (1000000) side by side overlap
            for ax in figure.axes[: len(params)]:
                ax.tick_params(axis="x", labelrotation=30)
        figure.savefig(out / name, dpi=110, bbox_inches="tight")
        plt.close(figure)
    return list(plots), notes


def without_empty(table: Table) -> Table:
    """A sweep's paper table with only the rows and columns that hold a value: a sweep of
    one method need not show the paper's other methods as rows of dashes."""
    rows = [row for block in table.blocks for _, row in block.rows]
    keep = [j for j in range(len(table.columns)) if any(r[j].value is not None for r in rows)]
    table.columns = [table.columns[j] for j in keep]
    for block in table.blocks:
        block.rows = [
            (label, [row[j] for j in keep])
            for label, row in block.rows
            if any(row[j].value is not None for j in keep)
        ]
    table.blocks = [block for block in table.blocks if block.rows]
    return table
