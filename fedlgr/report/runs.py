"""Finished fedlgr runs read back from MLflow, and the report logged back to it.

A report covers the FINISHED runs of one experiment (``--experiment``) or the trials of
one sweep (``--sweep``: runs tagged ``sweep=NAME``, in every experiment or in the named
one). Runs that are not experiments are left out: report runs (tag ``fedlgr.kind=report``)
and sweep parent runs (``fedlgr.kind=sweep``), as are runs without the ``method`` and
``benchmark`` tags that :class:`fedlgr.tracking.mlflow_run.Tracker` sets.
"""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from fedlgr.errors import FedlgrError

KIND = "fedlgr.kind"
NOT_EXPERIMENTS = ("report", "sweep")
# Swept settings that place a trial in a table cell rather than tune it.
CELL_KEYS = frozenset({"method", "data.clients", "data.augment", "config"})


class ReportError(FedlgrError):
    """Nothing to report on: no such store, experiment or sweep, no finished runs."""


@dataclass(frozen=True)
class RunRecord:
    """One finished run: its tags and the latest value of each metric (the final round)."""

    run_id: str
    experiment_id: str
    tags: dict[str, str]
    metrics: dict[str, float]

    @property
    def method(self) -> str:
        return self.tags["method"]

    @property
    def benchmark(self) -> str:
        return self.tags["benchmark"]

    @property
    def clients(self) -> int:
        return int(self.tags["clients"])

    @property
    def augmentation(self) -> bool:
        return self.tags.get("augmentation") == "true"

    @property
    def swept(self) -> dict[str, object]:
        """A sweep trial's swept values (tag ``swept``, JSON), but those that choose the
        table cell (method, clients, augmentation, base config); {} for other runs."""
        try:
            params = json.loads(self.tags.get("swept", "{}"))
        except ValueError:
            return {}
        return {k: v for k, v in params.items() if k not in CELL_KEYS}

    def value(self, metric: str) -> float | None:
        v = self.metrics.get(metric)
        return v if v is not None and math.isfinite(v) else None


@dataclass
class Selection:
    """The runs a report covers and where they came from."""

    client: Any  # mlflow.MlflowClient
    uri: str
    name: str  # the experiment or sweep name (the default output folder)
    source: str  # for people: "experiment `fedlgr`", "sweep `ewc`"
    experiment_ids: list[str]
    sweep: str | None
    records: list[RunRecord]


def open_store(uri: str):
    """An MlflowClient for ``uri``; a sqlite file that does not exist is an error (MLflow
    would quietly create an empty store)."""
    from fedlgr.tracking.mlflow_run import open_client

    if uri.startswith("sqlite:///"):
        path = Path(uri.removeprefix("sqlite:///"))
        if not path.is_file():
            raise ReportError(f"no MLflow store at {uri}: {path} does not exist")
    return open_client(uri)


def select_runs(
    client,
    uri: str,
    *,
    experiment: str | None = None,
    sweep: str | None = None,
    dataset: str | None = None,
    modality: str | None = None,
) -> Selection:
    """The finished runs of ``experiment``, or of ``sweep`` (within ``experiment`` if given)."""
    if experiment is None and sweep is None:
        raise ReportError("name an experiment (--experiment) or a sweep (--sweep)")
    if experiment is not None:
        found = client.get_experiment_by_name(experiment)
        if found is None or found.lifecycle_stage != "active":
            known = ", ".join(repr(e.name) for e in _pages(client.search_experiments)) or "none"
            raise ReportError(
                f"no MLflow experiment named {experiment!r} at {uri} (experiments there: {known})"
            )
        ids = [found.experiment_id]
    else:
        ids = [e.experiment_id for e in _pages(client.search_experiments)]
    from fedlgr.tracking.mlflow_run import end_dead_runs

    end_dead_runs(client, ids)  # runs killed outright: KILLED, not "still running"
    where = f" (experiment `{experiment}`)" if sweep and experiment else ""
    source = f"sweep `{sweep}`{where}" if sweep else f"experiment `{experiment}`"
    base = f"tags.sweep = {_quote(sweep)}" if sweep else ""
    finished = " and ".join(f for f in (base, "attributes.status = 'FINISHED'") if f)
    runs = list(_pages(client.search_runs, ids, finished))
    _remove_leftover_checkpoints(runs)
    records = [_record(run) for run in runs if _is_experiment(run)]
    for tag, wanted in (("dataset", dataset), ("modality", modality)):
        if wanted is not None:
            records = [r for r in records if r.tags.get(tag) == wanted]
    if not records:
        raise ReportError(_no_runs_message(client, ids, base, source, dataset, modality))
    mixed = Counter(f"{r.tags.get('dataset')} ({r.tags.get('modality')})" for r in records)
    if len(mixed) > 1:
        listed = ", ".join(f"{k}: {n} runs" for k, n in mixed.most_common())
        raise ReportError(
            f"{source} mixes datasets or modalities ({listed}): "
            "pick one with --dataset and/or --modality"
        )
    if sweep:
        records = _best_per_cell(client, ids, sweep, records)
    return Selection(client, uri, sweep or experiment, source, ids, sweep, records)


def _best_per_cell(client, ids, sweep: str, records: list[RunRecord]) -> list[RunRecord]:
    """A sweep over coefficients has several trials per table cell (method, clients,
    augmentation): the table shows the best of them by the sweep's own objective (tag
    ``objective`` of its parent run, e.g. ``minimize test/rmse``), as the paper reports
    grid-searched coefficients. Without a parent run the trials are averaged."""
    found = client.search_runs(
        ids, f"tags.`{KIND}` = 'sweep' and tags.sweep = {_quote(sweep)}", max_results=1
    )
    objective = found[0].data.tags.get("objective", "") if found else ""
    direction, _, metric = objective.partition(" ")
    if direction not in ("minimize", "maximize") or not metric:
        return records
    cells: dict[tuple, list[RunRecord]] = {}
    for r in records:
        cells.setdefault((r.benchmark, r.method, r.clients, r.augmentation), []).append(r)
    sign = 1.0 if direction == "minimize" else -1.0
    best = []
    for runs in cells.values():
        scored = [r for r in runs if r.value(metric) is not None]
        best.append(min(scored, key=lambda r: sign * r.value(metric)) if scored else runs[0])
    return best


def metric_histories(client, records: list[RunRecord], metric: str) -> dict[str, list]:
    """``{run_id: [(round, value), ...]}`` of ``metric`` for each run that logged it."""
    out = {}
    for r in records:
        points = sorted((m.step, m.value) for m in client.get_metric_history(r.run_id, metric))
        if points:
            out[r.run_id] = points
    return out


def log_report(selection: Selection, folder: Path, runs: int) -> str:
    """Log ``folder`` under ``report/``: into the sweep's parent run if there is one, else
    into a new run named ``report`` (tag ``fedlgr.kind=report``). Returns the run id."""
    client = selection.client
    parent = _sweep_parent(selection) if selection.sweep else None
    if parent is not None:
        client.set_tag(parent, "report.runs", str(runs))
        client.log_artifacts(parent, str(folder), artifact_path="report")
        return parent
    experiment_id = Counter(r.experiment_id for r in selection.records).most_common(1)[0][0]
    tags = {KIND: "report", "report.source": selection.source, "report.runs": str(runs)}
    run_id = client.create_run(experiment_id, run_name="report", tags=tags).info.run_id
    try:
        client.log_artifacts(run_id, str(folder), artifact_path="report")
    except BaseException:
        client.set_terminated(run_id, "FAILED")
        raise
    client.set_terminated(run_id, "FINISHED")
    return run_id


def _sweep_parent(selection: Selection) -> str | None:
    found = selection.client.search_runs(
        selection.experiment_ids,
        f"tags.`{KIND}` = 'sweep' and tags.sweep = {_quote(selection.sweep)}",
        order_by=["attributes.start_time DESC"],
        max_results=1,
    )
    return found[0].info.run_id if found else None


def _is_experiment(run) -> bool:
    tags = run.data.tags
    if tags.get(KIND) in NOT_EXPERIMENTS or "method" not in tags or "benchmark" not in tags:
        return False
    return tags.get("clients", "").isdigit()


def _record(run) -> RunRecord:
    return RunRecord(
        run.info.run_id, run.info.experiment_id, dict(run.data.tags), dict(run.data.metrics)
    )


def _no_runs_message(client, ids, base, source, dataset, modality) -> str:
    every = [r for r in _pages(client.search_runs, ids, base) if _is_experiment(r)]
    states = Counter(r.info.status for r in every if r.info.status != "FINISHED")
    unfinished = ", ".join(f"{n} {s}" for s, n in states.most_common())
    filters = " and ".join(
        f"{k}={v}" for k, v in (("dataset", dataset), ("modality", modality)) if v
    )
    message = f"{source} has no finished fedlgr runs" + (f" with {filters}" if filters else "")
    if unfinished:
        message += f" (other runs: {unfinished})"
    if source.startswith("sweep"):
        message += "; is the sweep name right? (runs carry it as tag sweep=NAME)"
    return message


def _pages(search, *args) -> list:
    """Every result of an MLflow search, page after page."""
    out, token = [], None
    while True:
        page = search(*args, page_token=token) if token else search(*args)
        out += list(page)
        token = page.token
        if not token:
            return out


def _remove_leftover_checkpoints(runs) -> None:
    """A finished run killed before it removed its checkpoint folder left it behind:
    removed, with a line (nothing resumes a finished run)."""
    from fedlgr.federated.resume import remove_leftover

    for run in runs:
        folder = run.data.tags.get("fedlgr.checkpoints")
        done = remove_leftover(Path(folder), run.info.run_id) if folder else ""
        if done:
            print(f"finished run {run.info.run_id}: {done.strip(' ()')}", flush=True)


def _quote(text: str) -> str:
    return f'"{text}"' if "'" in text else f"'{text}'"
