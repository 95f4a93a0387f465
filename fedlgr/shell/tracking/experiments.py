"""The MLflow experiment a run goes into, found or made (perhaps by two processes at once), and the
shared view of its runs that the printed link opens (headline scores first: docs/tracking.md)."""

from __future__ import annotations

import json
from collections.abc import Iterable
from pathlib import Path

from fedlgr.core.metrics import Score, headline_scores

# MLflow 3's UI shows an experiment of this kind on its runs table, not on its GenAI traces.
KIND = {"mlflow.experimentKind": "custom_model_development"}


def experiment_id(client, name: str) -> str:
    """The id of MLflow experiment ``name``, created if it does not exist yet (by this
    process or, at the same moment, by another one)."""
    experiment = client.get_experiment_by_name(name)
    if experiment is None:
        try:
            made = _create_experiment(client, name)
        except Exception:
            experiment = client.get_experiment_by_name(name)  # another process created it
            if experiment is None:
                raise
        else:
            _share_view(client, made)  # what the printed link opens
            return made
    for key, value in KIND.items():
        if key not in experiment.tags:  # made by an older fedlgr or by hand
            client.set_experiment_tag(experiment.experiment_id, key, value)
    if TAG not in experiment.tags:
        _share_view(client, experiment.experiment_id)
    return experiment.experiment_id


def _share_view(client, experiment_id: str) -> None:
    """:func:`share_view`, again if it fails: another process may have written the tag in
    between, and MLflow's SQL store then inserts a duplicate key."""
    try:
        share_view(client, experiment_id)
    except Exception:
        share_view(client, experiment_id)


def artifact_root(uri: str) -> Path | None:
    """Where a local sqlite store's experiments keep their artifacts: ``mlruns/`` beside its
    database, not MLflow's ``./mlruns`` of whatever folder a run starts in; else None."""
    if not uri.startswith("sqlite:///"):
        return None
    database = uri.removeprefix("sqlite:///").split("?", 1)[0]
    if not database or database == ":memory:":
        return None
    return Path(database).expanduser().resolve().parent / "mlruns"


def _create_experiment(client, name: str) -> str:
    """A new experiment; in a local sqlite store with its artifacts under :func:`artifact_root`."""
    root = artifact_root(client.tracking_uri)
    if root is None:
        return client.create_experiment(name, tags=KIND)
    # lazy: mlflow (seconds), only when an experiment is made
    from mlflow.entities import ExperimentTag
    from mlflow.tracking._tracking_service.utils import _get_store

    # root as the store's default artifact root: the location derives from the id made here
    store = _get_store(client.tracking_uri, str(root))
    return store.create_experiment(name, tags=[ExperimentTag(k, v) for k, v in KIND.items()])


# --------------------------------------------------------------------------- the shared view

VIEW = "fedlgr"
TAG = f"mlflow.sharedViewState.{VIEW}"
SECTION = "fedlgr-headline"
# the runs table's metric columns after the headline scores
COST_COLUMNS = ("mean/cost/cpu_s", "mean/cost/bytes_up")
# MLflow's 100-pixel metric columns cut 0.8100731 and mean/cost/bytes_up; 150 fits both
METRIC_WIDTH = 150
MAX_PARAMS = 6  # in the parallel-coordinates plot, the runs table's columns too
MAX_EXPANDED = 40  # the newest sweeps' parent runs (an experiment tag holds 5000 characters)

LINE = {  # MLflow's LINE card: x the step, linear axes, no fixed range (fitted)
    "xAxisKey": "step",
    "scaleType": "linear",
    "xAxisScaleType": "linear",
    "lineSmoothness": 0,
    "useGlobalXaxisKey": False,
    "useGlobalLineSmoothing": False,
    "range": {"xMin": None, "xMax": None, "yMin": None, "yMax": None},
}


def _key(score: Score) -> str:
    return f"test/{score.name}"


def _card(uuid: str, kind: str, **fields) -> dict:
    base = {"uuid": uuid, "type": kind, "metricSectionId": SECTION, "runsCountToCompare": 10}
    return {**base, "deleted": False, "isGenerated": False, **fields}


def view_state(params: Iterable[str], expanded: Iterable[str]) -> dict:
    """The shared state: ``params`` as columns and plot axes, the runs ``expanded`` (sweep
    parent runs) open."""
    params = list(dict.fromkeys(params))[:MAX_PARAMS]
    scores = headline_scores()
    keys = [_key(s) for s in scores]
    lines = [  # the chart view's first row: x the round (step), y fitted to the values
        _card(f"fedlgr-{s.name}", "LINE", metricKey=k, displayName=k, **LINE)
        for s, k in zip(scores, keys, strict=True)
    ]
    error = next(s for s in scores if not s.higher_is_better)
    correlation = next(s for s in scores if s.higher_is_better)
    scatter = _card(  # an error against a correlation: how the two rankings agree
        "fedlgr-scatter",
        "SCATTER",
        xaxis={"key": _key(error), "type": "METRIC"},
        yaxis={"key": _key(correlation), "type": "METRIC"},
        runsCountToCompare=100,
    )
    parallel = _card(
        "fedlgr-parallel",
        "PARALLEL",
        selectedParams=params,
        selectedMetrics=keys,
        showAllRuns=False,
    )
    charts = [*lines, scatter, parallel]
    section = {"uuid": SECTION, "name": "headline", "display": True, "isReordered": True}
    metrics = [f"metrics.`{m}`" for m in (*keys, *COST_COLUMNS)]
    return {
        "selectedColumns": metrics + [f"params.`{p}`" for p in params],
        # the columns whose width is set (MLflow applies widths in this order)
        "columnOrder": metrics,
        "columnWidths": dict.fromkeys(metrics, METRIC_WIDTH),
        "orderByKey": f"metrics.`{keys[0]}`",  # best first
        "orderByAsc": not scores[0].higher_is_better,
        "runsExpanded": {run_id: True for run_id in expanded},
        "compareRunCharts": charts,
        "compareRunSections": [{**section, "deleted": False, "isGenerated": False}],
        "isAccordionReordered": True,
    }


def share_view(client, experiment_id: str, params: Iterable[str] = (), parent: str = "") -> None:
    """Write (or widen) the experiment's view: ``method`` and ``params`` as columns and plot axes,
    ``parent`` (a sweep's parent run) expanded; a view that cannot be read is replaced."""
    experiment = client.get_experiment(experiment_id)
    try:
        old = json.loads(experiment.tags.get(TAG, "{}"))
        charts = old.get("compareRunCharts", ())
        old_params = [c["selectedParams"] for c in charts if "selectedParams" in c]
        old_expanded = list(old.get("runsExpanded", {}))
    except (ValueError, TypeError, AttributeError):  # written by hand or by another version
        old_params, old_expanded = [], []
    wanted = ["method", *(old_params[0] if old_params else []), *params]
    expanded = [*old_expanded, *([parent] if parent else [])][-MAX_EXPANDED:]
    state = view_state(wanted, expanded)
    text = json.dumps(state)
    if experiment.tags.get(TAG) != text:
        client.set_experiment_tag(experiment_id, TAG, text)
