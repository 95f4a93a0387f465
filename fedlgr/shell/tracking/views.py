"""The view of an experiment's runs that the printed MLflow link opens: the headline figures
first (docs/tracking.md).

MLflow's runs page can be shared: its "Share" button stores the page's state (columns,
sorting, charts, expanded parent runs) as the experiment tag
``mlflow.sharedViewState.<key>``, and ``?viewStateShareKey=<key>`` in the page's address
loads it. fedlgr writes such a view, :data:`VIEW`, to every experiment it logs to:

- the runs table shows the headline scores (:func:`fedlgr.core.metrics.headline_scores`:
  ``test/rmse``, ``test/pcc``, ``test/ccc``) and the costs per client per round
  (``mean/cost/cpu_s``, ``mean/cost/bytes_up``) as columns, with the method and each
  sweep's swept settings, sorted by the first score (``test/rmse``, best first); a sweep's
  trials are shown (their parent run expanded);
- the chart view opens on a "headline" section: per-round curves (line charts, step =
  round) of every headline score for every run, a scatter of the runs' final first error
  against their first correlation (``test/rmse`` against ``test/pcc``), and a
  parallel-coordinates plot of the method and swept settings against the headline scores.
  Line and scatter charts fit their axes to the values (0.810 and 0.811 are told apart);
  MLflow's bar charts start at 0 and have no range setting (its BAR card holds a metric
  key only), so there are none.

The state is the MLflow UI's own format (MLflow 3.17): ``selectedColumns`` as
``metrics.`key``` / ``params.`key```, chart cards by type, ``columnOrder`` and
``columnWidths`` (pixels by column id) - the fields its runs page persists
(``["selectedColumns", "columnOrder", "columnWidths", "runsExpanded", ...,
"compareRunCharts", "compareRunSections", ...]`` in its JavaScript bundle); a UI that no
longer reads a field ignores it, and "Exit shared view" gives MLflow's default page.
What MLflow does not take from a shared view - a run page's charts, its metrics table, the
compare page - is ordered by what a run logs (:mod:`fedlgr.shell.tracking.mlflow_run`).
"""

from __future__ import annotations

import json
from collections.abc import Iterable

from fedlgr.core.metrics import Score, headline_scores

VIEW = "fedlgr"
TAG = f"mlflow.sharedViewState.{VIEW}"
SECTION = "fedlgr-headline"
# the runs table's metric columns after the headline scores; the table sorts its columns by
# name and shows about six in a 1400-pixel window
COST_COLUMNS = ("mean/cost/cpu_s", "mean/cost/bytes_up")
# The runs table's metric columns are 100 pixels wide unless a view says otherwise: 0.8100731
# and a header such as mean/cost/bytes_up were cut ("0.81007307..."). Wide enough for 7
# significant digits and the longest header in the table's font.
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
        # ids of the columns whose width is set (MLflow applies widths in this order; a
        # column it does not list keeps MLflow's place and width)
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
    """Write (or widen) the experiment's view: ``method`` and ``params`` as columns and
    plot axes, ``parent`` (a sweep's parent run) expanded; the tag is written only when the
    view changes. A view that cannot be read (edited by hand) is replaced."""
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
