"""Finished fedlgr runs of an experiment, or of one study of a sweep (told apart by its parent
run), read back from MLflow, and the report logged back to it (report runs are left out)."""

from __future__ import annotations

import json
import math
from collections import Counter
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from typing import Any

from fedlgr.errors import FedlgrError
from fedlgr.shell.checks.paths import not_a_file
from fedlgr.shell.tracking.liveness import end_dead_runs
from fedlgr.shell.tracking.store import open_client

KIND = "fedlgr.kind"
NOT_EXPERIMENTS = ("report", "sweep")
# Swept settings that place a trial in a table cell rather than tune it, and the seeds.
CELL_KEYS = frozenset({"method", "data.clients", "data.augment", "config", "seed", "data.seed"})


class ReportError(FedlgrError):
    """Nothing to report on: no such store, experiment or sweep, no finished runs."""


@dataclass(frozen=True)
class RunRecord:
    """One finished run: its tags, the latest value of each metric (the final round), its
    settings (the flattened config, as MLflow params) and start time (ms since the epoch)."""

    run_id: str
    experiment_id: str
    tags: dict[str, str]
    metrics: dict[str, float]
    params: dict[str, str] = field(default_factory=dict)
    start_time: int = 0

    @property
    def method(self) -> str:
        """The method's name with what makes the run no plain one, a row of its own in the
        tables: client-level DP with the epsilon it spent, its noise and clip norm (``FedAvg,
        DP ε=2.31 (z=1, C=0.5)``), simulated faults, partial participation and refused
        uploads (``FedRootMedian, 4/10 byzantine (labels)``)."""
        p, said = self.params, [self.tags["method"]]
        spent = self.metrics.get("privacy/epsilon")
        if spent is not None:
            z = p.get("federated.dp.noise_multiplier", "?")
            adaptive = " adaptive" if p.get("federated.dp.clipping") == "adaptive" else ""
            said.append(f"DP ε={spent:.2f} (z={z}, C={p.get('federated.dp.clip', '?')}{adaptive})")
        if byzantine := int(self._number("federated.faults.byzantine", 0)):
            attack = p.get("federated.faults.attack", "?")
            said.append(f"{byzantine}/{p.get('data.clients', '?')} byzantine ({attack})")
        for key, word in (("dropout", "dropout"), ("straggler", "stragglers")):
            if self._number(f"federated.faults.{key}", 0) > 0:
                said.append(f"{word} {p[f'federated.faults.{key}']}")
        if self._number("federated.fraction", 1) < 1:
            said.append(f"fraction {p['federated.fraction']}")
        if self.tags.get("fedlgr.not_taken"):
            said.append("uploads refused")
        return ", ".join(said)

    def _number(self, key: str, default: float) -> float:
        try:
            return float(self.params.get(key, default))
        except ValueError:  # as logged by hand: not a condition fedlgr can read
            return default

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
        """A sweep trial's swept values (tag ``swept``) but those that choose its table cell
        and the seeds; {} for other runs."""
        return {k: v for k, v in swept_values(self.tags).items() if k not in CELL_KEYS}

    def value(self, metric: str) -> float | None:
        v = self.metrics.get(metric)
        return v if v is not None and math.isfinite(v) else None


@dataclass
class Selection:
    """The runs a report covers and where they came from."""

    client: Any  # mlflow.MlflowClient
    uri: str
    name: str  # the experiment or sweep name
    source: str  # for people: "experiment `fedlgr`", "sweep `ewc` (study `ewc`)"
    experiment_ids: list[str]
    sweep: str | None
    records: list[RunRecord]
    folder: Path | None = None  # the default report folder (None: reports/NAME)
    parent_run_id: str | None = None  # the reported study's parent run
    objective: str = ""  # its objective, e.g. "minimize test/rmse"
    notes: list[str] = field(default_factory=list)  # what the report says once


@dataclass(frozen=True)
class Study:
    """The trials of one study of a sweep, and its parent run."""

    name: str
    parent: Any  # mlflow Run, or None for trials without one
    records: list[RunRecord]

    @property
    def started(self) -> int:
        if self.parent is not None:
            return self.parent.info.start_time or 0
        return max(r.start_time for r in self.records)

    def label(self) -> str:
        when = datetime.fromtimestamp(self.started / 1000).strftime("%Y-%m-%d %H:%M")
        parent = f"parent run {self.parent.info.run_id}" if self.parent else "no parent run"
        return f"study `{self.name}` ({parent}, started {when}, {len(self.records)} trials)"

    def matches(self, wanted: str) -> bool:
        """``--study`` names a study or its parent run (the run id or its first 8 or
        more characters)."""
        run_id = self.parent.info.run_id if self.parent is not None else ""
        return wanted == self.name or (len(wanted) >= 8 and run_id.startswith(wanted))


def open_store(uri: str):
    """An MlflowClient for ``uri``; a sqlite file that does not exist is an error (MLflow
    would quietly create an empty store)."""
    if uri.startswith("sqlite:///"):
        path = Path(uri.removeprefix("sqlite:///"))
        if not path.is_file():
            why = not_a_file(path)  # a link loop or a FIFO is named, not called missing
            what = f"is {why}" if why else "does not exist"
            raise ReportError(f"no MLflow store at {uri}: {path} {what}")
        if path.stat().st_size == 0:  # MLflow would write its schema into it
            raise ReportError(f"no MLflow store at {uri}: {path} is an empty file")
    return open_client(uri)


def select_runs(
    client,
    uri: str,
    *,
    experiment: str | None = None,
    sweep: str | None = None,
    study: str | None = None,
    dataset: str | None = None,
    modality: str | None = None,
    where: dict[str, str] | None = None,
) -> Selection:
    """The finished runs of ``experiment``, or of one study of ``sweep`` (within
    ``experiment`` if given): ``study`` (a name or parent run id), else the newest. Runs
    can be narrowed to a ``dataset``, a ``modality`` and settings (``where``: params)."""
    if experiment is None and sweep is None:
        raise ReportError("name an experiment (--experiment) or a sweep (--sweep)")
    if study is not None and sweep is None:
        raise ReportError("--study picks one study of a sweep: name the sweep too (--sweep)")
    if experiment is not None:
        found = client.get_experiment_by_name(experiment)
        if found is None or found.lifecycle_stage != "active":
            known = ", ".join(repr(e.name) for e in pages(client.search_experiments)) or "none"
            raise ReportError(
                f"no MLflow experiment named {experiment!r} at {uri} (experiments there: {known})"
            )
        ids = [found.experiment_id]
    else:
        ids = [e.experiment_id for e in pages(client.search_experiments)]
    end_dead_runs(client, ids)  # runs killed outright: KILLED, not "still running"
    where = dict(where or {})
    filters = {**{k: v for k, v in (("dataset", dataset), ("modality", modality)) if v}, **where}
    shown = ", ".join(f"{k}={v}" for k, v in filters.items())
    within = f" (experiment `{experiment}`)" if sweep and experiment else ""
    source = f"sweep `{sweep}`{within}" if sweep else f"experiment `{experiment}`"
    base = f"tags.sweep = {_quote(sweep)}" if sweep else ""
    finished = " and ".join(f for f in (base, "attributes.status = 'FINISHED'") if f)
    runs = list(pages(client.search_runs, ids, finished))
    _remove_leftover_checkpoints(runs)
    records = [_record(run) for run in runs if _is_experiment(run)]
    for tag, wanted in (("dataset", dataset), ("modality", modality)):
        if wanted is not None:
            records = [r for r in records if r.tags.get(tag) == wanted]
    records = [r for r in records if all(r.params.get(k) == v for k, v in where.items())]
    if not records:
        raise ReportError(_no_runs_message(client, ids, base, source, shown))
    mixed = Counter(f"{r.tags.get('dataset')} ({r.tags.get('modality')})" for r in records)
    if len(mixed) > 1:
        listed = ", ".join(f"{k}: {n} runs" for k, n in mixed.most_common())
        raise ReportError(
            f"{source} mixes datasets or modalities ({listed}): "
            "pick one with --dataset and/or --modality"
        )
    # The default folder is the selection's own: filters and the study are part of it.
    suffix = [safe_name(",".join(f"{k}={v}" for k, v in filters.items()))] if filters else []
    if not sweep:
        source += f" ({shown})" if shown else ""
        folder = Path("reports", safe_name(experiment), *suffix)
        return Selection(client, uri, experiment, source, ids, None, records, folder)
    chosen, notes = _one_study(client, ids, sweep, records, study)
    parent = chosen.parent.info.run_id if chosen.parent is not None else None
    source = f"sweep `{sweep}`, study `{chosen.name}`{within}" + (f" ({shown})" if shown else "")
    study_folder = f"{chosen.name}-{parent[:8]}" if parent else chosen.name
    folder = Path("reports", "sweeps", safe_name(sweep), safe_name(study_folder), *suffix)
    objective = chosen.parent.data.tags.get("objective", "") if chosen.parent else ""
    return Selection(
        client, uri, sweep, source, ids, sweep, chosen.records, folder, parent, objective, notes
    )


def _one_study(
    client, ids, sweep: str, records: list[RunRecord], wanted: str | None
) -> tuple[Study, list[str]]:
    """The study to report (``wanted``, else the newest) and, where the sweep has several
    in this store, a line naming the one reported and the others."""
    parents = {
        run.info.run_id: run
        for run in pages(
            client.search_runs, ids, f"tags.`{KIND}` = 'sweep' and tags.sweep = {_quote(sweep)}"
        )
    }
    groups: dict[tuple[str, str | None], list[RunRecord]] = {}  # by study and parent run id
    for r in records:
        parent = parents.get(r.tags.get("mlflow.parentRunId", ""))
        name = (parent.data.tags if parent else r.tags).get("study", sweep)
        groups.setdefault((name, parent and parent.info.run_id), []).append(r)
    studies = [Study(name, parents.get(run_id), runs) for (name, run_id), runs in groups.items()]
    studies.sort(key=lambda s: s.started, reverse=True)
    candidates = studies if wanted is None else [s for s in studies if s.matches(wanted)]
    if not candidates:
        listed = "; ".join(s.label() for s in studies)
        raise ReportError(
            f"sweep `{sweep}` has no study {wanted!r} (--study: a study name or its parent "
            f"run id); its studies: {listed}"
        )
    chosen = candidates[0]
    if len(studies) == 1:
        return chosen, []
    others = "; ".join(s.label() for s in studies if s is not chosen)
    how = "the newest" if wanted is None else f"the newest matching --study {wanted}"
    return chosen, [
        f"sweep `{sweep}` has {len(studies)} studies in this store: reported {how}, "
        f"{chosen.label()}; not reported: {others}. Choose one with --study NAME or "
        "--study PARENT_RUN_ID"
    ]


def swept_values(tags: dict[str, str]) -> dict[str, Any]:
    """A sweep trial's swept values (tag ``swept``); {} for other runs."""
    try:
        return json.loads(tags.get("swept", "{}"))
    except ValueError:
        return {}


def safe_name(name: str) -> str:
    """A name as one folder name."""
    return name.replace("/", "_").replace("\\", "_")


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
    client, parent = selection.client, selection.parent_run_id
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


def _is_experiment(run) -> bool:
    tags = run.data.tags
    if tags.get(KIND) in NOT_EXPERIMENTS or "method" not in tags or "benchmark" not in tags:
        return False
    return tags.get("clients", "").isdigit()


def _record(run) -> RunRecord:
    return RunRecord(
        run.info.run_id,
        run.info.experiment_id,
        dict(run.data.tags),
        dict(run.data.metrics),
        dict(run.data.params),
        run.info.start_time or 0,
    )


def _no_runs_message(client, ids, base, source, filters: str) -> str:
    every = [r for r in pages(client.search_runs, ids, base) if _is_experiment(r)]
    states = Counter(r.info.status for r in every if r.info.status != "FINISHED")
    unfinished = ", ".join(f"{n} {s}" for s, n in states.most_common())
    message = f"{source} has no finished fedlgr runs" + (f" with {filters}" if filters else "")
    if unfinished:
        message += f" (other runs: {unfinished})"
    if source.startswith("sweep"):
        message += "; is the sweep name right? (runs carry it as tag sweep=NAME)"
    return message


def pages(search, *args) -> list:
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
    from fedlgr.shell.run.resume import remove_leftover  # lazy: torch, via its checkpoints

    for run in runs:
        folder = run.data.tags.get("fedlgr.checkpoints")
        done = remove_leftover(Path(folder), run.info.run_id) if folder else ""
        if done:
            print(f"finished run {run.info.run_id}: {done.strip(' ()')}", flush=True)


def _quote(text: str) -> str:
    return f'"{text}"' if "'" in text else f"'{text}'"
