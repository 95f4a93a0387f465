"""``fedlgr report``: the paper's Tables I-IV (``tableN.md``/``.tex``/``.csv``) and plots from
what MLflow holds, the folder logged back to MLflow under ``report/``."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from fedlgr.core.metrics import headline_scores
from fedlgr.shell.checks.paths import broken_link
from fedlgr.shell.report import runs as mlflow_runs
from fedlgr.shell.report.cells import best_per_cell, check_cells, newest_per_seed
from fedlgr.shell.report.paper import with_paper
from fedlgr.shell.report.plots import write_plots
from fedlgr.shell.report.render import to_csv, to_latex, to_markdown
from fedlgr.shell.report.runs import ReportError, RunRecord, safe_name
from fedlgr.shell.report.sweep import SweepViews, without_empty, write_sweep_views
from fedlgr.shell.report.tables import build_tables
from fedlgr.shell.tracking.uri import mask_password

__all__ = ["ReportError", "ReportResult", "RunRecord", "make_report"]

TITLES = {
    "table1": "FL results",
    "table2": "FCL results",
    "table3": "FL costs",
    "table4": "FCL costs",
}
BENCHMARK = {"table1": "FL", "table2": "FCL", "table3": "FL", "table4": "FCL"}


@dataclass
class ReportResult:
    out: Path
    source: str
    uri: str
    runs: int
    tables: list[tuple[str, int]] = field(default_factory=list)  # (name, runs)
    plots: list[str] = field(default_factory=list)
    logged_to: str | None = None  # the MLflow run holding the report
    notes: list[str] = field(default_factory=list)  # said once: the study, repeats left out
    sweep: SweepViews | None = None  # a sweep's trials table and Optuna's plots

    def summary(self) -> str:
        s = "s" if self.runs != 1 else ""
        lines = [*self.notes]
        uri = mask_password(self.uri)
        lines.append(f"Report on {self.runs} finished run{s} of {self.source} ({uri}):")
        for name, runs in self.tables:
            s = "s" if runs != 1 else ""
            title = f"{name} ({TITLES[name]})"
            lines.append(f"  {title:<22} {name}.md/.tex/.csv from {runs} run{s}")
        written = {BENCHMARK[name] for name, _ in self.tables}
        for benchmark in sorted({"FL", "FCL"} - written):
            names = [n for n, b in BENCHMARK.items() if b == benchmark]
            lines.append(f"  {' and '.join(names)}: not written, no finished {benchmark} runs")
        if self.sweep is not None:
            views = self.sweep
            lines.append(
                f"  {'trials (the sweep)':<22} trials.md/.csv: {views.trials} trials, best "
                f"first, from the {views.source}"
            )
            lines += [f"  {note}" for note in views.notes]
        lines.append(f"  plots: {', '.join(self.plots) or 'none (no data)'}")
        where = f"written to {self.out}"
        if self.logged_to:
            where += f"; logged to MLflow run {self.logged_to} under report/"
        lines.append(where)
        return "\n".join(lines)


def _check_folder(out: Path) -> None:
    """Refuse a report folder (``--out``) that is empty, a file or lies under one."""
    if str(out) in ("", "."):
        raise ReportError(
            "--out names the current folder ('' or .): name a folder of its own for the "
            "report's tables and plots (default: reports/NAME)"
        )
    # a link that loops or leads nowhere is named as such (mkdir would say "File exists")
    if why := broken_link(out):
        raise ReportError(f"{out}: {why}; the report (--out) is a folder")
    existing = next((p for p in (out, *out.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        # a device or a FIFO (/dev/null) is named as such: it is not a file either
        kind = "a file" if existing.is_file() else "a device, pipe or socket"
        where = f"is {kind}" if existing == out else f"lies under {existing}, {kind}"
        raise ReportError(
            f"{out}: {where}; the report (--out) is a folder of tables and plots: "
            "name a new or existing folder"
        )


def make_report(
    uri: str,
    *,
    experiment: str | None = None,
    sweep: str | None = None,
    study: str | None = None,
    out: Path | None = None,
    dataset: str | None = None,
    modality: str | None = None,
    where: dict[str, str] | None = None,
    log: bool = True,
    paper: bool = False,
    storage: str | None = None,
) -> ReportResult:
    """Write the tables and plots of ``experiment`` or one study of ``sweep`` to ``out`` and,
    with ``log``, log them to MLflow. A cell averages replicates only: runs of other settings
    are refused (narrow them with ``where``); ``paper`` adds the paper's published values."""
    if out is not None:  # before reading the store: a wrong --out fails at once
        _check_folder(Path(out))
    client = mlflow_runs.open_store(uri)
    selection = mlflow_runs.select_runs(
        client,
        uri,
        experiment=experiment,
        sweep=sweep,
        study=study,
        dataset=dataset,
        modality=modality,
        where=where,
    )
    records, repeats = newest_per_seed(selection.records)
    if selection.objective:  # a sweep's best setting per cell
        records = best_per_cell(records, selection.objective)
    check_cells(records, selection.source)
    notes = [*selection.notes, *([repeats] if repeats else [])]
    out = Path(out or selection.folder or Path("reports", safe_name(selection.name)))
    _check_folder(out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise ReportError(f"{out}: cannot create the report folder ({err.strerror})") from err
    result = ReportResult(out, selection.source, uri, len(records), notes=notes)
    for table in build_tables(records, selection.source, notes):
        if selection.sweep:  # only the rows and columns its trials filled
            table = without_empty(table)
            if not table.columns:
                result.notes.append(f"{table.name}: not written, no run logged its values")
                continue
        table = with_paper(table) if paper else table
        for suffix, render in ((".md", to_markdown), (".tex", to_latex), (".csv", to_csv)):
            (out / f"{table.name}{suffix}").write_text(render(table), encoding="utf-8")
        result.tables.append((table.name, table.runs))
    curves = [f"test/{s.name}" for s in headline_scores()]
    histories = {m: mlflow_runs.metric_histories(client, records, m) for m in curves}
    result.plots = write_plots(records, histories, out)
    if selection.sweep:
        result.sweep = write_sweep_views(selection, out, storage)
        result.plots += result.sweep.plots if result.sweep else []
    if log:
        result.logged_to = mlflow_runs.log_report(selection, out, len(records))
    return result
