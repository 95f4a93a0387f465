"""The view of an experiment's runs that the printed MLflow link opens (MLflow's shared view, an
experiment tag in the MLflow UI's own format): the headline scores first (docs/tracking.md)."""

from __future__ import annotations

import json
from collections.abc import Iterable

from fedlgr.core.metrics import Score, headline_scores

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
